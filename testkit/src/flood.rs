//! A connection flood against a TCP port (issue 40): a thread keeps a number of idle
//! connections open to the port and replaces each one the listener closes, as an attacker who
//! wants to fill a server's handshake slots would.

use std::io::Read;
use std::net::TcpStream;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// A running flood; stopped when dropped (also when a test's assertion fails, which would
/// otherwise leave the thread keeping the test process alive).
pub struct Flood {
    stop: Arc<AtomicBool>,
    closed: Arc<AtomicU64>,
    open: Arc<AtomicU64>,
    thread: Option<JoinHandle<()>>,
}

impl Flood {
    /// Starts holding `connections` idle connections to `127.0.0.1:port`, for at most
    /// `limit` (a bound for the thread, whatever the test does).
    pub fn start(port: u16, connections: usize, limit: Duration) -> Flood {
        let stop = Arc::new(AtomicBool::new(false));
        let (closed, open) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
        let thread = {
            let (stop, closed, open) = (stop.clone(), closed.clone(), open.clone());
            std::thread::spawn(move || {
                let mut conns: Vec<TcpStream> = Vec::with_capacity(connections);
                let mut buf = [0u8; 64];
                let start = Instant::now();
                while !stop.load(Ordering::Relaxed) && start.elapsed() < limit {
                    conns.retain_mut(|c| match c.read(&mut buf) {
                        Ok(0) => {
                            closed.fetch_add(1, Ordering::Relaxed);
                            false
                        }
                        Ok(_) => true,
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => true,
                        Err(_) => {
                            closed.fetch_add(1, Ordering::Relaxed);
                            false
                        }
                    });
                    while conns.len() < connections {
                        match TcpStream::connect(("127.0.0.1", port)) {
                            Ok(c) if c.set_nonblocking(true).is_ok() => conns.push(c),
                            _ => break,
                        }
                    }
                    open.store(conns.len() as u64, Ordering::Relaxed);
                    std::thread::sleep(Duration::from_millis(20));
                }
            })
        };
        Flood {
            stop,
            closed,
            open,
            thread: Some(thread),
        }
    }

    /// Connections the listener closed so far (each was replaced).
    pub fn closed(&self) -> u64 {
        self.closed.load(Ordering::Relaxed)
    }

    /// Connections held open at the last round.
    pub fn open(&self) -> u64 {
        self.open.load(Ordering::Relaxed)
    }

    /// Stops the flood and waits for its thread; returns the connections closed in all.
    pub fn stop(mut self) -> u64 {
        self.halt();
        self.closed()
    }

    fn halt(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Flood {
    fn drop(&mut self) {
        self.halt();
    }
}
