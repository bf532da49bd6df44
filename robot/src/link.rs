//! A running robot link of any kind: its state, counters and the handle irtrackd holds
//! ([`LinkHandle`], the one implementation of [`RobotLink`] for the socket, EGM and RSI links;
//! what differs between them is the task behind the handle).

use std::future::Future;
use std::time::Duration;

use irtrack_core::robot_proto::HoldReason;
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tokio::time::timeout;

use crate::gate::Control;
use crate::{LinkKind, RobotLink};

/// Connection and motion state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkState {
    /// Not connected (between attempts).
    Disconnected,
    /// Connecting or waiting for the robot's ready.
    Connecting,
    /// Connected, robot held for this reason.
    Holding(HoldReason),
    /// Connected and sending targets.
    Moving,
}

/// State and counters, published on every change.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkStatus {
    /// Which interface this link speaks.
    pub kind: LinkKind,
    /// Where the link is (disconnected, connecting, holding, moving).
    pub state: LinkState,
    /// Name the robot gave in HELLO.
    pub robot_name: Option<String>,
    /// Robot TCP from its last credit line.
    pub robot_pos_mm: Option<[f64; 3]>,
    /// Connections (or streaming sessions) made.
    pub connects: u64,
    /// Targets sent to the robot.
    pub targets_sent: u64,
    /// Hold commands sent.
    pub holds_sent: u64,
    /// Targets the robot rejected.
    pub rejects: u64,
    /// Streaming kinds: controller packets answered.
    pub packets_answered: u64,
    /// Streaming kinds: packets that could not be decoded (not answered).
    pub bad_packets: u64,
    /// Streaming kinds: duplicated or reordered packets (older sequence number; not answered).
    pub out_of_order: u64,
    /// Streaming kinds: the UDP address irtrackd listens on.
    pub local_addr: Option<std::net::SocketAddr>,
    /// The newest error, in words.
    pub last_error: Option<String>,
    /// Targets sent so far: the sample's age when it left and the protocol wait (published →
    /// on the wire), refreshed about twice a second.
    pub latency: Option<crate::gate::LatencySummary>,
}

impl Default for LinkStatus {
    fn default() -> Self {
        Self {
            kind: LinkKind::Socket,
            state: LinkState::Disconnected,
            robot_name: None,
            robot_pos_mm: None,
            connects: 0,
            targets_sent: 0,
            holds_sent: 0,
            rejects: 0,
            packets_answered: 0,
            bad_packets: 0,
            out_of_order: 0,
            local_addr: None,
            last_error: None,
            latency: None,
        }
    }
}

/// A running link of any kind (a tokio task) and its control handle.
pub struct LinkHandle {
    ctl: watch::Sender<Control>,
    status: watch::Receiver<LinkStatus>,
    task: Option<JoinHandle<()>>,
}

impl LinkHandle {
    /// Starts `task` with a fresh control channel and status.
    pub(crate) fn start<T, Fut>(task: T) -> Self
    where
        T: FnOnce(watch::Receiver<Control>, watch::Sender<LinkStatus>) -> Fut,
        Fut: Future<Output = ()> + Send + 'static,
    {
        let (ctl, ctl_rx) = watch::channel(Control::default());
        let (status_tx, status) = watch::channel(LinkStatus::default());
        let task = tokio::spawn(task(ctl_rx, status_tx));
        Self {
            ctl,
            status,
            task: Some(task),
        }
    }

    /// A receiver that sees every status change (for LEDs and the status endpoint).
    pub fn subscribe(&self) -> watch::Receiver<LinkStatus> {
        self.status.clone()
    }

    /// Holds the robot, says BYE and ends the task.
    pub async fn shutdown(mut self) {
        self.ctl.send_modify(|c| c.stop = true);
        if let Some(task) = self.task.take() {
            let _ = timeout(Duration::from_secs(2), task).await;
        }
    }
}

impl Drop for LinkHandle {
    fn drop(&mut self) {
        if let Some(task) = &self.task {
            task.abort();
        }
    }
}

impl RobotLink for LinkHandle {
    fn enable(&self) {
        self.ctl.send_modify(|c| {
            c.generation += 1;
            c.enabled = true;
        });
    }
    fn disable(&self) {
        self.ctl.send_modify(|c| {
            c.generation += 1;
            c.enabled = false;
        });
    }
    fn status(&self) -> LinkStatus {
        self.status.borrow().clone()
    }
}
