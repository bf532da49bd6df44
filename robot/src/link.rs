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

/// Why a streaming link refused a controller packet.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// From an address or port other than the controller's.
    Source,
    /// Sequence number beyond the window.
    Sequence,
    /// Reported robot position the robot cannot have reached.
    Implausible,
    /// Not a packet of the protocol (does not decode).
    Malformed,
}

impl Refusal {
    /// Stable name (metrics label, JSON key).
    pub fn name(self) -> &'static str {
        match self {
            Refusal::Source => "wrong_source",
            Refusal::Sequence => "sequence_window",
            Refusal::Implausible => "implausible_position",
            Refusal::Malformed => "malformed",
        }
    }
}

/// The newest packet a streaming link refused.
#[derive(Debug, Clone, PartialEq)]
pub struct RefusedPacket {
    /// Why.
    pub reason: Refusal,
    /// Where it came from.
    pub from: std::net::SocketAddr,
    /// What was wrong, in words (names the address and the check).
    pub words: String,
    /// When (to tell a refusal going on now from an old one).
    pub at: std::time::Instant,
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
    /// Streaming kinds: packets refused because they came from another address (or port) than
    /// the controller's: the configured one, or the one whose session is running. Not answered.
    pub refused_source: u64,
    /// Streaming kinds: packets refused because their sequence number jumped further ahead than
    /// the window allows (not answered, and the number is not adopted).
    pub refused_sequence: u64,
    /// Streaming kinds: packets refused because the robot position they report is further from
    /// the last accepted one than the robot can move in the time between (not answered).
    pub refused_implausible: u64,
    /// Streaming kinds: the controller whose packets the running session accepts.
    pub controller: Option<std::net::SocketAddr>,
    /// Streaming kinds: the newest refused packet, in words.
    pub last_refused: Option<RefusedPacket>,
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
            refused_source: 0,
            refused_sequence: 0,
            refused_implausible: 0,
            controller: None,
            last_refused: None,
            local_addr: None,
            last_error: None,
            latency: None,
        }
    }
}

/// A refusal at most this old is an active fault ([`LinkStatus::refusal_fault`]).
pub const REFUSAL_FAULT_S: u64 = 10;

impl LinkStatus {
    /// The refusal counters by [`Refusal::name`], then `out_of_order` (duplicated or
    /// reordered packets, also not answered): for `/metrics` and `/status`.
    pub fn refused_by_reason(&self) -> [(&'static str, u64); 5] {
        [
            (Refusal::Source.name(), self.refused_source),
            (Refusal::Sequence.name(), self.refused_sequence),
            (Refusal::Implausible.name(), self.refused_implausible),
            (Refusal::Malformed.name(), self.bad_packets),
            ("out_of_order", self.out_of_order),
        ]
    }

    /// While the link has refused a packet within the last [`REFUSAL_FAULT_S`] seconds (at
    /// `now`): that fault in plain words with what to check; `None` otherwise. Duplicated or
    /// reordered packets are normal on a network and no fault.
    pub fn refusal_fault(&self, now: std::time::Instant) -> Option<String> {
        let r = self.last_refused.as_ref()?;
        let age = now.saturating_duration_since(r.at);
        if age > Duration::from_secs(REFUSAL_FAULT_S) {
            return None;
        }
        Some(format!(
            "the robot link ({}) refuses packets that fail its checks and never answers them; the newest, {:.0} s ago: {}. Refused so far: {} from another address, {} out of the sequence window, {} reporting a robot position the robot cannot have reached, {} malformed — another device is sending to the robot port (or the controller restarted): check the cell network and [robot.stream] controller",
            self.kind.name(),
            age.as_secs_f64(),
            r.words,
            self.refused_source,
            self.refused_sequence,
            self.refused_implausible,
            self.bad_packets
        ))
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusal_fault_names_the_check_and_lasts_ten_seconds() {
        let at = std::time::Instant::now();
        let mut st = LinkStatus {
            kind: LinkKind::Egm,
            refused_source: 3,
            refused_sequence: 1,
            out_of_order: 9,
            ..LinkStatus::default()
        };
        assert_eq!(st.refusal_fault(at), None, "no refusal, no fault");
        st.last_refused = Some(RefusedPacket {
            reason: Refusal::Source,
            from: "127.0.0.2:5000".parse().unwrap(),
            words: "a packet from 127.0.0.2:5000: the configured controller is 10.0.0.1".into(),
            at,
        });
        let f = st.refusal_fault(at + Duration::from_secs(2)).unwrap();
        for part in [
            "robot link (egm)",
            "2 s ago",
            "127.0.0.2:5000",
            "3 from another address",
            "1 out of the sequence window",
            "[robot.stream] controller",
        ] {
            assert!(f.contains(part), "{part:?} missing: {f}");
        }
        assert_eq!(
            st.refusal_fault(at + Duration::from_secs(REFUSAL_FAULT_S + 1)),
            None
        );
        assert_eq!(
            st.refused_by_reason(),
            [
                ("wrong_source", 3),
                ("sequence_window", 1),
                ("implausible_position", 0),
                ("malformed", 0),
                ("out_of_order", 9)
            ]
        );
    }
}
