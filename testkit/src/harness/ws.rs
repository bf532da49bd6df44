//! The set-up view's live WebSocket (`/api/live`, docs/http-api.md) as a blocking client
//! (tungstenite).

use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

use tungstenite::{Message, WebSocket};

use super::error::{Error, Result};

/// An open WebSocket.
#[derive(Debug)]
pub struct LiveSocket {
    ws: WebSocket<TcpStream>,
    url: String,
}

impl LiveSocket {
    /// Connects to `ws://addr{path}`; connecting and each later read wait at most `timeout`.
    pub fn connect(addr: SocketAddr, path: &str, timeout: Duration) -> Result<LiveSocket> {
        let url = format!("ws://{addr}{path}");
        let fail = |reason: String| Error::WebSocket {
            url: url.clone(),
            reason,
        };
        let stream =
            TcpStream::connect_timeout(&addr, timeout).map_err(|e| fail(format!("connecting: {e}")))?;
        stream
            .set_read_timeout(Some(timeout))
            .and_then(|()| stream.set_write_timeout(Some(timeout)))
            .map_err(|e| fail(e.to_string()))?;
        let (ws, _answer) =
            tungstenite::client(url.as_str(), stream).map_err(|e| fail(format!("handshake: {e}")))?;
        Ok(LiveSocket { ws, url })
    }

    /// The next text message; pings, pongs and binary messages are skipped.
    pub fn next_text(&mut self) -> Result<String> {
        loop {
            let msg = self.ws.read().map_err(|e| Error::WebSocket {
                url: self.url.clone(),
                reason: format!("reading: {e}"),
            })?;
            match msg {
                Message::Text(t) => return Ok(t.to_string()),
                Message::Close(c) => {
                    return Err(Error::WebSocket {
                        url: self.url.clone(),
                        reason: format!("closed by the server: {c:?}"),
                    });
                }
                _ => {}
            }
        }
    }

    /// Sends a text message (e.g. a subscription change).
    pub fn send_text(&mut self, text: &str) -> Result<()> {
        self.ws.send(Message::text(text)).map_err(|e| Error::WebSocket {
            url: self.url.clone(),
            reason: format!("sending: {e}"),
        })
    }

    /// Closes the connection politely.
    pub fn close(mut self) {
        let _ = self.ws.close(None);
        let _ = self.ws.flush();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::TcpListener;

    #[test]
    fn reads_text_after_skipping_binary_and_names_a_refused_upgrade() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap();
        let server = std::thread::spawn(move || {
            let (s, _) = l.accept().unwrap();
            let mut ws = tungstenite::accept(s).unwrap();
            ws.send(Message::binary(vec![1u8, 2, 3])).unwrap();
            ws.send(Message::text("{\"type\":\"status\"}")).unwrap();
            let got = ws.read().unwrap();
            assert_eq!(got, Message::text("hello"));
        });
        let mut c = LiveSocket::connect(addr, "/api/live", Duration::from_secs(5)).unwrap();
        assert_eq!(c.next_text().unwrap(), "{\"type\":\"status\"}");
        c.send_text("hello").unwrap();
        server.join().unwrap();

        // A plain HTTP answer instead of the upgrade.
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap();
        let server = std::thread::spawn(move || {
            use std::io::{Read, Write};
            let (mut s, _) = l.accept().unwrap();
            let mut buf = [0u8; 1024];
            let _ = s.read(&mut buf);
            s.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n")
                .unwrap();
        });
        let e = LiveSocket::connect(addr, "/api/live", Duration::from_secs(5))
            .unwrap_err()
            .to_string();
        assert!(e.contains("handshake"), "{e}");
        server.join().unwrap();
    }
}
