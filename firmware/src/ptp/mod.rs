//! `[clock]`: PTP (linuxptp) for the boards of a multi-board rig (docs/cluster.md, "Clocks").
//!
//! irtrackd does not set the clock itself (its sandbox forbids it, `ProtectClock=yes`): a
//! root unit of the image (`systemd/irtrack-ptp4l.service`) runs `irtrackd
//! --write-ptp-config /run/irtrack-ptp` before `ptp4l`, which writes `ptp4l.conf` generated
//! from this section, so the one file a user edits stays irtrackd.toml. With hardware time
//! stamping `phc2sys -a -rr` (`systemd/irtrack-phc2sys.service`) then carries the NIC's clock
//! to CLOCK_REALTIME (or, on the grandmaster, the other way).

pub mod mgmt;
pub mod monitor;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::error::{FirmwareError, Result};

/// This board's part in PTP's best-master-clock choice.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum PtpRole {
    /// Never a master: follows the grandmaster (camera boards).
    #[default]
    Slave,
    /// Preferred grandmaster (priority1 = 10): the solver, or one board of the rig.
    Master,
    /// Left to the best-master-clock algorithm (default priorities).
    Auto,
}

/// Where packets are time-stamped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum TimeStamping {
    /// By the NIC (sub-µs; needs PTP support in the Ethernet driver, `ethtool -T`).
    #[default]
    Hardware,
    /// By the kernel: the documented fallback for NICs without it (tens of µs on a LAN).
    Software,
}

/// `[clock]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClockConfig {
    /// Run ptp4l with a config generated from this section (off by default).
    #[serde(default)]
    pub ptp: bool,
    /// The Ethernet interface PTP runs on.
    #[serde(default = "d_interface")]
    pub interface: String,
    /// PTP domain number (0..=127); every board of a rig uses the same.
    #[serde(default)]
    pub domain: u8,
    /// `"slave"` (default), `"master"` or `"auto"`.
    #[serde(default)]
    pub role: PtpRole,
    /// `"hardware"` (default) or `"software"`.
    #[serde(default)]
    pub time_stamping: TimeStamping,
    /// ptp4l's management socket irtrackd reads `clock.ptp` on `/status` from (when `ptp` is
    /// on). Default: `/var/run/ptp4lro` (linuxptp ≥ 4.0's read-only socket) when it exists,
    /// else `/var/run/ptp4l`. Set it when ptp4l runs with another `uds_address`.
    #[serde(default)]
    pub ptp4l_socket: Option<PathBuf>,
}

fn d_interface() -> String {
    "eth0".into()
}

impl Default for ClockConfig {
    fn default() -> Self {
        ClockConfig {
            ptp: false,
            interface: d_interface(),
            domain: 0,
            role: PtpRole::default(),
            time_stamping: TimeStamping::default(),
            ptp4l_socket: None,
        }
    }
}

/// Name of the marker file that tells `irtrack-phc2sys.service` to run (hardware stamping).
pub const HARDWARE_MARKER: &str = "hardware-timestamps";

impl ClockConfig {
    /// Checks the values ptp4l would otherwise refuse at boot.
    pub fn validate(&self) -> Result<()> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        let ok_if = !self.interface.is_empty()
            && self.interface.len() <= 15
            && self
                .interface
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"._-@".contains(&b));
        if !ok_if {
            return bad(format!(
                "clock.interface {:?} is not a network interface name (1..=15 characters)",
                self.interface
            ));
        }
        if self.domain > 127 {
            return bad(format!("clock.domain must be 0..=127, got {}", self.domain));
        }
        if let Some(p) = &self.ptp4l_socket
            && (p.as_os_str().is_empty() || p.as_os_str().len() > 107)
        {
            return bad(format!(
                "clock.ptp4l_socket {:?} is not a Unix socket path (1..=107 bytes)",
                p.display()
            ));
        }
        Ok(())
    }

    /// ptp4l's configuration (linuxptp 3.1 and 4.x keys).
    pub fn ptp4l_conf(&self) -> String {
        let mut s = String::new();
        s.push_str("# Written by irtrackd from [clock] in irtrackd.toml; edit that, not this file.\n");
        s.push_str("[global]\n");
        let _ = writeln!(s, "domainNumber\t\t{}", self.domain);
        let (slave_only, priority1) = match self.role {
            PtpRole::Slave => (1, 128),
            PtpRole::Master => (0, 10),
            PtpRole::Auto => (0, 128),
        };
        let _ = writeln!(s, "slaveOnly\t\t{slave_only}");
        let _ = writeln!(s, "priority1\t\t{priority1}");
        let stamping = match self.time_stamping {
            TimeStamping::Hardware => "hardware",
            TimeStamping::Software => "software",
        };
        let _ = writeln!(s, "time_stamping\t\t{stamping}");
        s.push_str("network_transport\tUDPv4\n");
        s.push_str("delay_mechanism\t\tE2E\n");
        // One summary line a minute in the journal instead of one per second.
        s.push_str("summary_interval\t6\n");
        let _ = writeln!(s, "[{}]", self.interface);
        s
    }

    /// Writes `ptp4l.conf` into `dir` and the hardware marker when phc2sys is needed.
    pub fn write_files(&self, dir: &Path) -> Result<()> {
        self.validate()?;
        let io = |e: std::io::Error| FirmwareError::Config {
            reason: format!("writing the PTP config into {}: {e}", dir.display()),
        };
        std::fs::create_dir_all(dir).map_err(io)?;
        std::fs::write(dir.join("ptp4l.conf"), self.ptp4l_conf()).map_err(io)?;
        let marker = dir.join(HARDWARE_MARKER);
        match self.time_stamping {
            TimeStamping::Hardware => std::fs::write(&marker, b"").map_err(io)?,
            TimeStamping::Software => {
                if marker.exists() {
                    std::fs::remove_file(&marker).map_err(io)?;
                }
            }
        }
        Ok(())
    }
}
