//! NatNet server (`[outputs.natnet]`): OptiTrack's streaming protocol, so NatNet clients
//! (game-engine plugins, MotionBuilder, ROS NatNet drivers, drone-swarm software) read
//! irtrackd's poses as rigid bodies and markers. Spec: docs/outputs.md.
//!
//! One UDP socket on the command port answers connect, model-definition, frame and keep-alive
//! requests. Frames go to the multicast group's data port (transport "multicast"), or to the
//! address each client's requests came from (transport "unicast"; clients that stop sending
//! keep-alives are forgotten after `unicast_timeout_s`). The server reads only the latest-value
//! slot; a frame it cannot send at once is dropped and counted, never waited for.
//!
//! Requests are unauthenticated UDP: [`gate`] keeps the socket from reflecting or amplifying
//! traffic onto spoofed addresses (replies larger than a request only to `client_networks`,
//! a per-address client cap, reply rate limits).

pub mod gate;
pub mod server;
pub mod wire;

use std::net::{Ipv4Addr, SocketAddr};

use serde::Deserialize;

use crate::error::{FirmwareError, Result};
use crate::outputs::scene::Axes;

/// How frames reach the clients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Transport {
    /// To `multicast_group:data_port` (Motive's default; every client on the network).
    #[default]
    Multicast,
    /// To each client that sent a connect or keep-alive, at the address it sent from.
    Unicast,
}

/// `[outputs.natnet]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NatNetConfig {
    /// Off by default.
    #[serde(default)]
    pub enabled: bool,
    /// Command socket (`host:port`); NatNet's port is 1510.
    #[serde(default = "default_command")]
    pub command: String,
    /// How frames reach clients: multicast (default) or unicast.
    #[serde(default)]
    pub transport: Transport,
    /// Multicast group for frames (transport "multicast").
    #[serde(default = "default_group")]
    pub multicast_group: String,
    /// Address of the interface multicast frames leave by (`0.0.0.0`: the routing table's
    /// choice).
    #[serde(default = "default_interface")]
    pub multicast_interface: String,
    /// Destination port of multicast frames; NatNet's is 1511.
    #[serde(default = "default_data_port")]
    pub data_port: u16,
    /// Output axes: "tracker" (unchanged) or "y_up" (docs/outputs.md).
    #[serde(default)]
    pub axes: Axes,
    /// A unicast client not heard from for this long gets no more frames.
    #[serde(default = "default_unicast_timeout")]
    pub unicast_timeout_s: f64,
    /// Unicast clients served at once; further ones are refused (counted).
    #[serde(default = "default_max_clients")]
    pub max_clients: usize,
    /// Unicast clients with the same IP address served at once (several programs on one PC);
    /// further ones are refused (counted), so one host cannot take every slot.
    #[serde(default = "default_max_clients_per_address")]
    pub max_clients_per_address: usize,
    /// Networks (`address/prefix`) whose addresses may get replies larger than their request
    /// and become unicast clients; elsewhere a reply is at most the request's size
    /// (docs/outputs.md, "Spoofed requests and floods"). Default: this host only.
    #[serde(default = "default_client_networks")]
    pub client_networks: Vec<String>,
    /// Replies (server info, model definitions, frames on request, responses) per second to
    /// one address, and the burst; further requests get no reply (counted).
    #[serde(default = "default_replies_per_s_per_address")]
    pub replies_per_s_per_address: f64,
    /// Replies per second to all addresses together, and the burst.
    #[serde(default = "default_replies_per_s")]
    pub replies_per_s: f64,
}

fn default_command() -> String {
    "0.0.0.0:1510".into()
}
fn default_group() -> String {
    "239.255.42.99".into()
}
fn default_interface() -> String {
    "0.0.0.0".into()
}
fn default_data_port() -> u16 {
    1511
}
fn default_unicast_timeout() -> f64 {
    10.0
}
fn default_max_clients() -> usize {
    16
}
fn default_max_clients_per_address() -> usize {
    4
}
fn default_client_networks() -> Vec<String> {
    vec!["127.0.0.0/8".into(), "::1/128".into()]
}
fn default_replies_per_s_per_address() -> f64 {
    20.0
}
fn default_replies_per_s() -> f64 {
    200.0
}

impl Default for NatNetConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            command: default_command(),
            transport: Transport::default(),
            multicast_group: default_group(),
            multicast_interface: default_interface(),
            data_port: default_data_port(),
            axes: Axes::default(),
            unicast_timeout_s: default_unicast_timeout(),
            max_clients: default_max_clients(),
            max_clients_per_address: default_max_clients_per_address(),
            client_networks: default_client_networks(),
            replies_per_s_per_address: default_replies_per_s_per_address(),
            replies_per_s: default_replies_per_s(),
        }
    }
}

/// A checked [`NatNetConfig`].
#[derive(Debug, Clone, PartialEq)]
pub struct NatNetPlan {
    /// Address the command socket binds.
    pub command: SocketAddr,
    /// Group and data port, for transport "multicast".
    pub multicast: Option<(Ipv4Addr, u16)>,
    /// Interface multicast frames leave by (`0.0.0.0`: the routing table's choice).
    pub interface: Ipv4Addr,
    /// Output axes.
    pub axes: Axes,
    /// A unicast client not heard from for this long gets no more frames.
    pub unicast_timeout: std::time::Duration,
    /// Unicast clients served at once.
    pub max_clients: usize,
    /// Unicast clients with the same IP address served at once.
    pub max_clients_per_address: usize,
    /// `client_networks`, parsed.
    pub client_networks: Vec<gate::Network>,
    /// Replies per second (also the burst) to one address.
    pub replies_per_s_per_address: f64,
    /// Replies per second (also the burst) to all addresses together.
    pub replies_per_s: f64,
}

impl NatNetConfig {
    /// `irtrackd --ephemeral-ports IP`: the command socket on `IP` with a port the OS chooses,
    /// and with multicast a data port that is free on this host now (asked of the OS by
    /// binding a socket to port 0 and letting it go), so that instances started side by side
    /// (tests, several rigs on one host) never contend for NatNet's fixed 1510/1511. Clients
    /// learn both from the ready line (`natnet=`) and the server info (data port).
    pub fn use_ephemeral_ports(&mut self, ip: std::net::IpAddr) -> Result<()> {
        self.command = SocketAddr::new(ip, 0).to_string();
        if self.transport == Transport::Multicast {
            let free = std::net::UdpSocket::bind((Ipv4Addr::UNSPECIFIED, 0))
                .and_then(|s| s.local_addr())
                .map_err(|source| FirmwareError::Bind {
                    what: "NatNet data port (--ephemeral-ports)",
                    addr: "0.0.0.0:0".into(),
                    source,
                })?;
            self.data_port = free.port();
        }
        Ok(())
    }

    /// Validates the settings; errors name the key.
    pub fn plan(&self) -> Result<NatNetPlan> {
        let bad = |reason: String| FirmwareError::Config {
            reason: format!("outputs.natnet.{reason}"),
        };
        let command: SocketAddr = self.command.parse().map_err(|_| {
            bad(format!(
                "command: {:?} is not an address `host:port`",
                self.command
            ))
        })?;
        let interface: Ipv4Addr = self.multicast_interface.parse().map_err(|_| {
            bad(format!(
                "multicast_interface: {:?} is not an IPv4 address",
                self.multicast_interface
            ))
        })?;
        let multicast = match self.transport {
            Transport::Unicast => None,
            Transport::Multicast => {
                let group: Ipv4Addr = self.multicast_group.parse().map_err(|_| {
                    bad(format!(
                        "multicast_group: {:?} is not an IPv4 address",
                        self.multicast_group
                    ))
                })?;
                if !group.is_multicast() {
                    return Err(bad(format!(
                        "multicast_group: {group} is not a multicast address (224.0.0.0/4)"
                    )));
                }
                if self.data_port == 0 {
                    return Err(bad("data_port: 0 is not a port clients can listen on".into()));
                }
                Some((group, self.data_port))
            }
        };
        if !(self.unicast_timeout_s.is_finite() && self.unicast_timeout_s > 0.0) {
            return Err(bad(format!(
                "unicast_timeout_s: {} must be a positive number of seconds",
                self.unicast_timeout_s
            )));
        }
        if self.max_clients == 0 {
            return Err(bad("max_clients: must be at least 1".into()));
        }
        if self.max_clients_per_address == 0 {
            return Err(bad("max_clients_per_address: must be at least 1".into()));
        }
        let client_networks = self
            .client_networks
            .iter()
            .map(|n| gate::Network::parse(n).map_err(|e| bad(format!("client_networks: {e}"))))
            .collect::<Result<Vec<_>>>()?;
        for (key, rate) in [
            ("replies_per_s_per_address", self.replies_per_s_per_address),
            ("replies_per_s", self.replies_per_s),
        ] {
            // At least one reply must fit in a bucket, else nothing is ever answered.
            if !(rate.is_finite() && rate >= 1.0) {
                return Err(bad(format!(
                    "{key}: {rate} must be a number of replies per second >= 1"
                )));
            }
        }
        Ok(NatNetPlan {
            command,
            multicast,
            interface,
            axes: self.axes,
            unicast_timeout: std::time::Duration::from_secs_f64(self.unicast_timeout_s),
            max_clients: self.max_clients,
            max_clients_per_address: self.max_clients_per_address,
            client_networks,
            replies_per_s_per_address: self.replies_per_s_per_address,
            replies_per_s: self.replies_per_s,
        })
    }
}
