//! Plain-HTTP requests to irtrackd's status listener (ureq), optionally signed in as the
//! operator (HTTP Basic). Every answer, including 4xx and 5xx, comes back as status + body.

use std::net::SocketAddr;
use std::time::Duration;

use base64::Engine as _;

use super::error::{Error, Result};
use super::irtrackd::OPERATOR_USER;

/// Largest answer body read (a frame set of 16-bit 4K frames from several cameras is below).
const MAX_BODY_BYTES: u64 = 512 << 20;

/// A client; cheap to clone.
#[derive(Debug, Clone)]
pub struct Http {
    agent: ureq::Agent,
    authorization: Option<String>,
}

impl Http {
    /// A client waiting at most `timeout` to connect and for each read.
    pub fn new(timeout: Duration) -> Http {
        Http {
            agent: ureq::AgentBuilder::new()
                .timeout_connect(timeout)
                .timeout_read(timeout)
                .timeout_write(timeout)
                .build(),
            authorization: None,
        }
    }

    /// The same client, signed in as the operator with `password` (HTTP Basic on every
    /// request; irtrackd's change requests need it).
    pub fn signed_in(mut self, password: &str) -> Http {
        self.authorization = Some(basic_authorization(password));
        self
    }

    /// `GET path`.
    pub fn get(&self, addr: SocketAddr, path: &str) -> Result<(u16, String)> {
        self.request(addr, "GET", path, None)
    }

    /// `POST path`, with a JSON body if given.
    pub fn post(&self, addr: SocketAddr, path: &str, json: Option<&str>) -> Result<(u16, String)> {
        self.request(addr, "POST", path, json)
    }

    /// Any request; answers with the status code and the body as text.
    pub fn request(
        &self,
        addr: SocketAddr,
        method: &str,
        path: &str,
        json: Option<&str>,
    ) -> Result<(u16, String)> {
        let (code, body) = self.request_bytes(addr, method, path, json)?;
        Ok((code, String::from_utf8_lossy(&body).into_owned()))
    }

    /// Any request; answers with the status code and the raw body.
    pub fn request_bytes(
        &self,
        addr: SocketAddr,
        method: &str,
        path: &str,
        json: Option<&str>,
    ) -> Result<(u16, Vec<u8>)> {
        let url = format!("http://{addr}{path}");
        let fail = |reason: String| Error::Http {
            method: method.to_string(),
            url: url.clone(),
            reason,
        };
        let mut req = self.agent.request(method, &url);
        if let Some(a) = &self.authorization {
            req = req.set("Authorization", a);
        }
        let sent = match json {
            Some(body) => req.set("Content-Type", "application/json").send_string(body),
            None => req.call(),
        };
        let resp = match sent {
            Ok(r) => r,
            // 4xx and 5xx are answers too; tests check them.
            Err(ureq::Error::Status(_, r)) => r,
            Err(ureq::Error::Transport(t)) => return Err(fail(t.to_string())),
        };
        let code = resp.status();
        let mut body = Vec::new();
        std::io::Read::read_to_end(
            &mut std::io::Read::take(resp.into_reader(), MAX_BODY_BYTES),
            &mut body,
        )
        .map_err(|e| fail(format!("reading the answer: {e}")))?;
        Ok((code, body))
    }
}

/// `Basic <base64(operator:password)>`: the operator's HTTP Basic credentials.
pub fn basic_authorization(password: &str) -> String {
    let token = base64::engine::general_purpose::STANDARD.encode(format!("{OPERATOR_USER}:{password}"));
    format!("Basic {token}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};
    use std::net::TcpListener;

    /// A one-shot server answering `answer` and returning the request it got.
    fn serve_once(answer: &'static str) -> (SocketAddr, std::thread::JoinHandle<String>) {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap();
        let h = std::thread::spawn(move || {
            let (mut s, _) = l.accept().unwrap();
            s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
            let mut req = Vec::new();
            let mut buf = [0u8; 4096];
            // Head, then the body announced by Content-Length.
            loop {
                let n = s.read(&mut buf).unwrap();
                req.extend_from_slice(&buf[..n]);
                let text = String::from_utf8_lossy(&req).to_string();
                if let Some((head, body)) = text.split_once("\r\n\r\n") {
                    let len = head
                        .lines()
                        .find_map(|l| {
                            l.to_ascii_lowercase()
                                .strip_prefix("content-length: ")
                                .map(str::to_string)
                        })
                        .and_then(|v| v.trim().parse::<usize>().ok())
                        .unwrap_or(0);
                    if body.len() >= len {
                        break;
                    }
                }
                if n == 0 {
                    break;
                }
            }
            s.write_all(answer.as_bytes()).unwrap();
            String::from_utf8_lossy(&req).into_owned()
        });
        (addr, h)
    }

    #[test]
    fn signed_in_post_sends_basic_credentials_and_reads_error_answers() {
        let (addr, h) =
            serve_once("HTTP/1.1 401 Unauthorized\r\nContent-Length: 5\r\nConnection: close\r\n\r\nnope\n");
        let http = Http::new(Duration::from_secs(5)).signed_in("pw");
        let (code, body) = http.post(addr, "/api/tuning", Some("{\"a\":1}")).unwrap();
        assert_eq!((code, body.as_str()), (401, "nope\n"));
        let req = h.join().unwrap();
        assert!(req.starts_with("POST /api/tuning HTTP/1.1\r\n"), "{req}");
        // base64("operator:pw")
        assert!(req.contains("Authorization: Basic b3BlcmF0b3I6cHc=\r\n"), "{req}");
        assert!(req.ends_with("{\"a\":1}"), "{req}");
    }

    #[test]
    fn no_listener_is_a_named_error() {
        let addr = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap();
        let e = Http::new(Duration::from_secs(2))
            .get(addr, "/status")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with(&format!("GET http://{addr}/status: ")), "{e}");
    }
}
