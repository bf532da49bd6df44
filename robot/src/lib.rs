//! irtrack's robot side, shared by irtrackd (the board) and the PC tools: the tracker end of the
//! three robot interfaces (`[robot] kind`): the socket protocol (docs/robot-protocol.md), ABB EGM
//! and KUKA RSI (docs/robot-streaming.md); the safety supervisor that decides what may be sent
//! and the deadman input; and the simulated controllers the tests and `host-tools robot-sim` run
//! (socket, EGM, RSI, and the cell robot with its error model, [`cell`]).
//! The wire codecs themselves are no_std and live in `irtrack_core::robot_proto`.
//!
//! [`LinkHandle`] is the running link of any kind and implements [`RobotLink`], the seam irtrackd
//! uses; [`spawn_link`] is the one place a link is built from the config. All kinds judge samples
//! through the same [`gate::Gate`] (operator enable, deadman, supervisor), fed by a
//! [`PositionFeed`] and timed by a [`Clock`].

// Every public item says what it is for (issue 24).
#![deny(missing_docs)]

pub mod cell;
pub mod client;
pub mod ctrl_sim;
pub mod deadman;
pub mod egm;
pub mod gate;
pub mod link;
pub mod rsi;
pub mod safety;
pub mod sim;
pub mod sim_robot;
pub mod udp;

#[cfg(test)]
mod link_tests;

use std::future::Future;
use std::sync::Arc;

use irtrack_core::stream::PositionRecord;
use serde::Deserialize;
use tokio::sync::watch;

pub use deadman::{Deadman, DeadmanConfig};
pub use link::{LinkHandle, LinkState, LinkStatus, Refusal, RefusedPacket};
pub use safety::{SafetyConfig, Sample, Supervisor, Verdict};
pub use udp::{RsiMode, StreamConfig};

/// Current CLOCK_MONOTONIC time in ns: the clock V4L2 stamps frames with, so simulated,
/// replayed and real frames, the robot links and the simulated controllers share one time base.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid out-pointer; CLOCK_MONOTONIC always exists on Linux.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    if rc != 0 {
        return 0;
    }
    (ts.tv_sec as u64)
        .saturating_mul(1_000_000_000)
        .saturating_add(ts.tv_nsec as u64)
}

/// Time base of the samples' `capture_ts_ns` (CLOCK_MONOTONIC for irtrackd).
pub trait Clock: Send + Sync + 'static {
    /// Now, ns on the clock the samples' capture times are read on.
    fn now_ns(&self) -> u64;
}

/// CLOCK_MONOTONIC, the clock frames are stamped with.
#[derive(Debug, Clone, Copy, Default)]
pub struct MonotonicClock;

impl Clock for MonotonicClock {
    fn now_ns(&self) -> u64 {
        monotonic_ns()
    }
}

/// Source of the newest tracker sample.
pub trait PositionFeed: Send + Sync + 'static {
    /// The newest sample, marking it seen.
    fn latest(&mut self) -> Option<Sample>;
    /// Resolves when a newer sample may be available; `false` once the feed is closed.
    fn changed(&mut self) -> impl Future<Output = bool> + Send;
    /// When the newest sample was published (same clock as its capture time), if known: the
    /// start of the link's protocol wait.
    fn published_ns(&self) -> Option<u64> {
        None
    }
}

/// irtrackd's latest-value slot of position records.
impl PositionFeed for watch::Receiver<Option<PositionRecord>> {
    fn latest(&mut self) -> Option<Sample> {
        self.borrow_and_update().as_ref().map(Sample::from)
    }
    fn published_ns(&self) -> Option<u64> {
        // The record carries capture → published (µs) in `latency_us`.
        self.borrow()
            .as_ref()
            .map(|r| r.capture_ts_ns + u64::from(r.latency_us) * 1000)
    }
    async fn changed(&mut self) -> bool {
        watch::Receiver::changed(self).await.is_ok()
    }
}

/// Errors of the robot link (logged by the client, which keeps reconnecting).
#[derive(Debug, thiserror::Error)]
pub enum RobotError {
    /// Connecting, reading or writing failed.
    #[error("robot link {addr}: {what}: {source}")]
    Io {
        /// The robot's (or listening) address.
        addr: String,
        /// What was being done.
        what: &'static str,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// The robot sent something the protocol does not allow.
    #[error("robot link {addr}: {source}")]
    Protocol {
        /// The robot's address.
        addr: String,
        /// The codec's error, naming the line's problem.
        source: irtrack_core::Error,
    },
    /// The robot speaks another protocol version.
    #[error("robot link {addr}: robot speaks protocol version {found}, this build speaks {supported}")]
    Version {
        /// The robot's address.
        addr: String,
        /// The version the robot sent in HELLO.
        found: u8,
        /// The version this build speaks.
        supported: u8,
    },
    /// Nothing heard from the robot within the timeout.
    #[error("robot link {addr}: no message from the robot for {ms} ms")]
    Timeout {
        /// The robot's address.
        addr: String,
        /// The silence limit, ms.
        ms: u64,
    },
    /// The robot closed the connection.
    #[error("robot link {addr}: connection closed by the robot")]
    Closed {
        /// The robot's address.
        addr: String,
    },
    /// The deadman GPIO line could not be opened or read.
    #[error("deadman input {what}: {reason}")]
    Deadman {
        /// The chip and line.
        what: String,
        /// Why it failed.
        reason: String,
    },
    /// Invalid configuration.
    #[error("robot config: {reason}")]
    Config {
        /// What is wrong, naming the key.
        reason: String,
    },
    /// A simulated controller's setting (the cell robot's error model) or simulator-only
    /// message (the cell feed) is unusable; the message names the field.
    #[error("invalid simulator configuration: {field}: {reason}")]
    Simulator {
        /// The key or channel.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A streaming-interface packet (EGM or RSI) that cannot be decoded.
    #[error("{protocol} packet ({len} bytes): {reason}")]
    Packet {
        /// `EGM` or `RSI`.
        protocol: &'static str,
        /// The datagram's length in bytes.
        len: usize,
        /// What does not decode.
        reason: String,
    },
}

/// `[robot] kind`: which interface irtrackd speaks to the robot controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LinkKind {
    /// irtrack's own line protocol over TCP; irtrackd connects to `address`.
    #[default]
    Socket,
    /// ABB Externally Guided Motion: irtrackd is the EGM sensor, bound to UDP `address`.
    Egm,
    /// KUKA RobotSensorInterface: irtrackd answers `<Rob>` packets on UDP `address`.
    Rsi,
}

impl LinkKind {
    /// Name as written in the config.
    pub fn name(self) -> &'static str {
        match self {
            LinkKind::Socket => "socket",
            LinkKind::Egm => "egm",
            LinkKind::Rsi => "rsi",
        }
    }
}

/// What irtrackd needs from a robot link.
pub trait RobotLink: Send + Sync {
    /// Operator enable: motion may start (again). Required after start, after every reconnect
    /// and after every latched safety stop.
    fn enable(&self);
    /// Operator disable: hold now.
    fn disable(&self);
    /// Current state and counters.
    fn status(&self) -> LinkStatus;
}

fn default_name() -> String {
    "irtrackd".into()
}
fn default_connect_timeout_ms() -> u64 {
    2000
}
fn default_heartbeat_ms() -> u64 {
    200
}
fn default_peer_timeout_ms() -> u64 {
    1000
}
fn default_backoff_min_ms() -> u64 {
    100
}
fn default_backoff_max_ms() -> u64 {
    5000
}

/// `[robot]` section of the irtrackd config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    /// Interface to the controller; `socket` when absent, so older configs keep working.
    #[serde(default)]
    pub kind: LinkKind,
    /// `socket`: the robot controller's `host:port` (the tracker is the TCP client).
    /// `egm` / `rsi`: the local UDP `host:port` irtrackd listens on (the controller sends first).
    pub address: String,
    /// Name sent in HELLO (1..=24 of `[A-Za-z0-9._-]`).
    #[serde(default = "default_name")]
    pub name: String,
    /// A connection attempt (socket link) fails after this long.
    #[serde(default = "default_connect_timeout_ms")]
    pub connect_timeout_ms: u64,
    /// Heartbeat period towards the robot.
    #[serde(default = "default_heartbeat_ms")]
    pub heartbeat_ms: u64,
    /// The connection is dropped when the robot is silent this long.
    #[serde(default = "default_peer_timeout_ms")]
    pub peer_timeout_ms: u64,
    /// Reconnect backoff: first delay, doubled up to the maximum.
    #[serde(default = "default_backoff_min_ms")]
    pub backoff_min_ms: u64,
    /// Reconnect backoff: the longest delay.
    #[serde(default = "default_backoff_max_ms")]
    pub backoff_max_ms: u64,
    /// The tool of the parameter set whose pose the link follows (`[robot] tool = "name"`);
    /// absent: the set's first tool. irtrackd refuses parameter sets without this tool.
    #[serde(default)]
    pub tool: Option<String>,
    /// Send 6-DOF `Q` lines when the record has an orientation.
    #[serde(default)]
    pub send_orientation: bool,
    /// Safety limits of this installation (required: there are no safe defaults for a workspace).
    pub safety: SafetyConfig,
    /// Deadman / enabling input.
    pub deadman: DeadmanConfig,
    /// `[robot.stream]`: options of the streaming interfaces (EGM, RSI).
    #[serde(default)]
    pub stream: udp::StreamConfig,
}

impl RobotConfig {
    /// Checks values a TOML parser cannot.
    pub fn validate(&self) -> Result<(), RobotError> {
        let bad = |reason: String| Err(RobotError::Config { reason });
        if let Some(t) = &self.tool
            && (t.is_empty()
                || t.len() > 32
                || !t
                    .bytes()
                    .all(|b| (0x20..0x7f).contains(&b) && b != b'"' && b != b'\\'))
        {
            return bad(format!(
                "robot.tool {t:?} must be 1..=32 printable ASCII characters without \" or \\ (a tool name of the parameter set)"
            ));
        }
        if self.address.is_empty() {
            return bad("robot.address is empty".into());
        }
        if self.kind != LinkKind::Socket {
            if self.address.parse::<std::net::SocketAddr>().is_err() {
                return bad(format!(
                    "robot.address = {:?}: kind = \"{}\" needs a local ip:port to listen on",
                    self.address,
                    self.kind.name()
                ));
            }
            self.stream
                .validate()
                .map_err(|reason| RobotError::Config { reason })?;
        }
        let hello = irtrack_core::robot_proto::TrackerMsg::Hello {
            version: 1,
            name: self.name.clone(),
        };
        if let Err(e) = hello.encode() {
            return bad(format!("robot.name: {e}"));
        }
        if self.heartbeat_ms == 0 || self.peer_timeout_ms <= self.heartbeat_ms {
            return bad(format!(
                "robot.peer_timeout_ms ({}) must exceed robot.heartbeat_ms ({}) > 0",
                self.peer_timeout_ms, self.heartbeat_ms
            ));
        }
        if self.backoff_min_ms == 0 || self.backoff_max_ms < self.backoff_min_ms {
            return bad("robot.backoff_min_ms must be > 0 and <= robot.backoff_max_ms".into());
        }
        self.safety
            .validate()
            .map_err(|reason| RobotError::Config { reason })
    }
}

/// The `[robot]` section of an irtrackd config file (TOML; same keys as irtrackd reads), parsed
/// and validated; `None` when the file has no `[robot]` section. Other sections are not looked
/// at, so the PC tools can read the board's file without knowing irtrackd's whole config.
pub fn robot_section(text: &str, origin: &str) -> Result<Option<RobotConfig>, RobotError> {
    #[derive(Deserialize)]
    struct File {
        robot: Option<RobotConfig>,
    }
    let file: File = toml::from_str(text).map_err(|e| RobotError::Config {
        reason: format!("{origin}: {e}"),
    })?;
    if let Some(robot) = &file.robot {
        robot.validate()?;
    }
    Ok(file.robot)
}

/// Builds and starts the link `cfg.kind` names: the one place irtrackd creates a robot link.
pub fn spawn_link<F: PositionFeed, C: Clock>(
    cfg: RobotConfig,
    feed: F,
    clock: C,
    deadman: Arc<dyn Deadman>,
) -> Result<LinkHandle, RobotError> {
    match cfg.kind {
        LinkKind::Socket => LinkHandle::spawn_socket(cfg, feed, clock, deadman),
        LinkKind::Egm => udp::spawn::<egm::Egm, F, C>(cfg, feed, clock, deadman),
        LinkKind::Rsi => udp::spawn::<rsi::Rsi, F, C>(cfg, feed, clock, deadman),
    }
}

#[cfg(test)]
mod config_tests {
    use super::*;

    const GOOD: &str = r#"
address = "192.168.125.1:1025"
[safety]
workspace_min_mm = [-500.0, -500.0, 0.0]
workspace_max_mm = [500.0, 500.0, 800.0]
max_step_mm = 20.0
max_speed_mm_s = 250.0
max_gap_mm = 2.0
max_age_ms = 100
[deadman]
kind = "gpio"
chip = "gpiochip0"
line = 17
active_low = true
"#;

    #[test]
    fn parses_and_validates() {
        let c: RobotConfig = toml::from_str(GOOD).unwrap();
        c.validate().unwrap();
        assert_eq!(c.heartbeat_ms, 200);
        assert_eq!(c.kind, LinkKind::Socket);
        assert!(matches!(
            c.deadman,
            DeadmanConfig::Gpio {
                line: 17,
                active_low: true,
                ..
            }
        ));
    }

    #[test]
    fn kind_selects_the_link_and_checks_its_address() {
        let egm = format!(
            "kind = \"egm\"\n{}",
            GOOD.replace("192.168.125.1:1025", "0.0.0.0:6510")
        );
        let c: RobotConfig = toml::from_str(&egm).unwrap();
        c.validate().unwrap();
        assert_eq!((c.kind, c.stream.session_timeout_ms), (LinkKind::Egm, 500));
        let rsi = format!(
            "kind = \"rsi\"\n{}\n[stream]\nrsi_mode = \"relative\"\n",
            GOOD.replace("192.168.125.1:1025", "0.0.0.0:49152")
        );
        let c: RobotConfig = toml::from_str(&rsi).unwrap();
        c.validate().unwrap();
        assert_eq!(c.stream.rsi_mode, udp::RsiMode::Relative);
        // A host name is fine for the socket client, not for a UDP listener.
        let named = format!(
            "kind = \"rsi\"\n{}",
            GOOD.replace("192.168.125.1:1025", "robot:1025")
        );
        let e = toml::from_str::<RobotConfig>(&named)
            .unwrap()
            .validate()
            .unwrap_err()
            .to_string();
        assert!(e.contains("kind = \"rsi\"") && e.contains("robot:1025"), "{e}");
        let e = toml::from_str::<RobotConfig>(&format!("kind = \"profinet\"\n{GOOD}"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("profinet"), "{e}");
        let bad_type = format!(
            "kind = \"rsi\"\n{}\n[stream]\nrsi_sen_type = \"Im Free\"\n",
            GOOD.replace("192.168.125.1:1025", "0.0.0.0:49152")
        );
        let e = toml::from_str::<RobotConfig>(&bad_type)
            .unwrap()
            .validate()
            .unwrap_err()
            .to_string();
        assert!(e.contains("rsi_sen_type"), "{e}");
    }

    #[test]
    fn stream_controller_is_an_address_with_or_without_port() {
        let base = format!(
            "kind = \"egm\"\n{}",
            GOOD.replace("192.168.125.1:1025", "0.0.0.0:6510")
        );
        for (v, ok) in [
            ("192.168.125.1", true),
            ("192.168.125.1:6511", true),
            ("[fe80::1]:6511", true),
            ("robot:6511", false),
            ("192.168.125.1:0", false),
            ("", false),
        ] {
            let c: RobotConfig =
                toml::from_str(&format!("{base}\n[stream]\ncontroller = \"{v}\"\n")).unwrap();
            match c.validate() {
                Ok(()) => assert!(ok, "{v:?} accepted"),
                Err(e) => {
                    assert!(!ok, "{v:?}: {e}");
                    assert!(e.to_string().contains("robot.stream.controller"), "{e}");
                }
            }
        }
        let c: RobotConfig =
            toml::from_str(&format!("{base}\n[stream]\nmax_robot_speed_mm_s = 0.0\n")).unwrap();
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("max_robot_speed_mm_s"), "{e}");
        let any_port = udp::ControllerAddr::parse("127.0.0.1").unwrap();
        assert!(any_port.matches("127.0.0.1:9".parse().unwrap()));
        assert!(any_port.matches("[::ffff:127.0.0.1]:9".parse().unwrap()));
        assert!(!any_port.matches("127.0.0.2:9".parse().unwrap()));
        let exact = udp::ControllerAddr::parse("127.0.0.1:9").unwrap();
        assert!(exact.matches("127.0.0.1:9".parse().unwrap()));
        assert!(!exact.matches("127.0.0.1:10".parse().unwrap()));
    }

    #[test]
    fn rejects_unknown_keys_and_bad_values() {
        let unknown = GOOD.replace("max_age_ms = 100", "max_age_ms = 100\nmax_agee = 3");
        let e = toml::from_str::<RobotConfig>(&unknown).unwrap_err().to_string();
        assert!(e.contains("max_agee"), "{e}");
        let inverted = GOOD.replace("[500.0, 500.0, 800.0]", "[500.0, -600.0, 800.0]");
        let c: RobotConfig = toml::from_str(&inverted).unwrap();
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("workspace"), "{e}");
        let c: RobotConfig =
            toml::from_str(&GOOD.replace("max_step_mm = 20.0", "max_step_mm = 0.0")).unwrap();
        assert!(c.validate().unwrap_err().to_string().contains("max_step_mm"));
        let missing = GOOD.replace(
            "[deadman]\nkind = \"gpio\"\nchip = \"gpiochip0\"\nline = 17\nactive_low = true\n",
            "",
        );
        assert!(
            toml::from_str::<RobotConfig>(&missing)
                .unwrap_err()
                .to_string()
                .contains("deadman")
        );
    }

    #[test]
    fn robot_section_of_a_whole_irtrackd_file() {
        let file = format!(
            "[service]\ncontrol = true\n[source.sim]\nfps = 30.0\n{}",
            GOOD.replace("address =", "[robot]\naddress =")
                .replace("[safety]", "[robot.safety]")
                .replace("[deadman]", "[robot.deadman]")
        );
        let r = robot_section(&file, "irtrackd.toml").unwrap().unwrap();
        assert_eq!(r.address, "192.168.125.1:1025");
        assert_eq!(r.safety.max_step_mm, 20.0);
        assert_eq!(r.safety.workspace_max_mm, [500.0, 500.0, 800.0]);
        assert!(
            robot_section("[leds]\nbackend = \"none\"\n", "x.toml")
                .unwrap()
                .is_none()
        );
        // A typo inside [robot] is an error naming the key; values are validated too.
        let typo = file.replace("max_age_ms = 100", "max_age_ms = 100\nmax_agee = 1");
        let e = robot_section(&typo, "irtrackd.toml").unwrap_err().to_string();
        assert!(e.contains("irtrackd.toml") && e.contains("max_agee"), "{e}");
        let inverted = file.replace("[500.0, 500.0, 800.0]", "[500.0, -600.0, 800.0]");
        let e = robot_section(&inverted, "irtrackd.toml").unwrap_err().to_string();
        assert!(e.contains("workspace"), "{e}");
    }
}
