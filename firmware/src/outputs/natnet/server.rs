//! The NatNet UDP service (see the module docs of [`super`]).

use std::future::Future;
use std::net::{Ipv4Addr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use irtrack_core::stream::PositionRecord;
use tokio::net::UdpSocket;
use tokio::sync::watch;

use super::NatNetPlan;
use super::gate::{Gate, Verdict};
use super::wire::{self, FrameStamps, ServerInfo};
use crate::clock;
use crate::engine::ParamsHandle;
use crate::error::{FirmwareError, Result};
use crate::outputs::OutputStats;
use crate::outputs::scene::{Models, SceneBuilder, SceneFrame};
use crate::status::SharedStatus;

const R: Ordering = Ordering::Relaxed;

/// A bound, not yet running NatNet server.
pub struct NatNetServer {
    socket: UdpSocket,
    plan: NatNetPlan,
    local: SocketAddr,
    tools: Option<watch::Receiver<crate::engine::ToolSet>>,
}

/// Sets `IP_MULTICAST_IF` (std and tokio have no setter for it).
fn set_multicast_interface(socket: &std::net::UdpSocket, iface: Ipv4Addr) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let addr = libc::in_addr {
        s_addr: u32::from_ne_bytes(iface.octets()),
    };
    // SAFETY: valid socket fd owned by `socket`; the option value is an in_addr of that size.
    let rc = unsafe {
        libc::setsockopt(
            socket.as_raw_fd(),
            libc::IPPROTO_IP,
            libc::IP_MULTICAST_IF,
            (&addr as *const libc::in_addr).cast(),
            std::mem::size_of::<libc::in_addr>() as libc::socklen_t,
        )
    };
    if rc == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

impl NatNetServer {
    /// Binds the command socket (a port in use fails here, naming the address).
    pub fn bind(plan: NatNetPlan) -> Result<Self> {
        let bind_err = |source| FirmwareError::Bind {
            what: "NatNet command",
            addr: plan.command.to_string(),
            source,
        };
        let std_socket = std::net::UdpSocket::bind(plan.command).map_err(bind_err)?;
        if plan.multicast.is_some() {
            let setup = |s: &std::net::UdpSocket| -> std::io::Result<()> {
                // Frames stay on the local network unless a router is told otherwise.
                s.set_multicast_ttl_v4(1)?;
                // Clients on the board itself receive the frames too.
                s.set_multicast_loop_v4(true)?;
                if !plan.interface.is_unspecified() {
                    set_multicast_interface(s, plan.interface)?;
                }
                Ok(())
            };
            setup(&std_socket).map_err(|e| FirmwareError::Config {
                reason: format!(
                    "outputs.natnet.multicast_interface: {} cannot send multicast: {e}",
                    plan.interface
                ),
            })?;
        }
        std_socket.set_nonblocking(true).map_err(bind_err)?;
        let socket = UdpSocket::from_std(std_socket).map_err(bind_err)?;
        let local = socket.local_addr().map_err(bind_err)?;
        Ok(Self {
            socket,
            plan,
            local,
            tools: None,
        })
    }

    /// Sends every tool as its own rigid body, from the loop's per-tool slot.
    pub fn with_tools(mut self, tools: Option<watch::Receiver<crate::engine::ToolSet>>) -> Self {
        self.tools = tools;
        self
    }

    /// The address the command socket is bound to (the real port when 0 was asked for).
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Serves until `shutdown` resolves. Frames come from `slot` (the loop's latest-value
    /// slot); the model list follows the active parameter set in `params`.
    pub async fn serve(
        self,
        mut slot: watch::Receiver<Option<PositionRecord>>,
        params: Arc<ParamsHandle>,
        status: Arc<SharedStatus>,
        stats: Arc<OutputStats>,
        shutdown: impl Future<Output = ()>,
    ) {
        tokio::pin!(shutdown);
        let mut state = State::new(self.plan, self.local, params, status, stats);
        state.builder.tools = self.tools;
        let mut buf = vec![0u8; 2048];
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        tracing::info!(command = %self.local, multicast = ?state.plan.multicast, axes = ?state.plan.axes, "NatNet server started");
        loop {
            tokio::select! {
                _ = &mut shutdown => break,
                got = self.socket.recv_from(&mut buf) => match got {
                    Ok((n, peer)) => state.request(&self.socket, &buf[..n], peer),
                    // ICMP "port unreachable" of an earlier send shows up here on Linux.
                    Err(e) => tracing::debug!(error = %e, "NatNet receive"),
                },
                changed = slot.changed() => {
                    if changed.is_err() {
                        break;
                    }
                    let rec = *slot.borrow_and_update();
                    if let Some(rec) = rec {
                        state.frame(&self.socket, &rec);
                    }
                }
                _ = tick.tick() => state.expire(),
            }
        }
        tracing::info!("NatNet server stopped");
    }
}

struct Client {
    addr: SocketAddr,
    last_heard: Instant,
}

struct State {
    plan: NatNetPlan,
    local: SocketAddr,
    params: Arc<ParamsHandle>,
    status: Arc<SharedStatus>,
    stats: Arc<OutputStats>,
    /// Parameter generation the models were built from (`u64::MAX`: never).
    generation: u64,
    builder: SceneBuilder,
    names: Vec<String>,
    models_changed: bool,
    scene: SceneFrame,
    packet: Vec<u8>,
    /// The last frame sent, for `NAT_REQUEST_FRAMEOFDATA`.
    last_frame: Vec<u8>,
    clients: Vec<Client>,
    received: u64,
    /// Who may get how much (replies larger than a request, client slots, reply rates).
    gate: Gate,
}

impl State {
    fn new(
        plan: NatNetPlan,
        local: SocketAddr,
        params: Arc<ParamsHandle>,
        status: Arc<SharedStatus>,
        stats: Arc<OutputStats>,
    ) -> Self {
        let axes = plan.axes;
        let gate = Gate::new(
            plan.client_networks.clone(),
            plan.replies_per_s_per_address,
            plan.replies_per_s,
            Instant::now(),
        );
        let mut s = Self {
            plan,
            local,
            params,
            status,
            stats,
            generation: u64::MAX,
            builder: SceneBuilder::new(Models::default(), axes),
            names: Vec::new(),
            models_changed: false,
            scene: SceneFrame::default(),
            packet: Vec::with_capacity(1024),
            last_frame: Vec::with_capacity(1024),
            clients: Vec::new(),
            received: 0,
            gate,
        };
        s.refresh_models();
        s.models_changed = false;
        s
    }

    /// Rebuilds the models after a parameter swap (allocates; only then).
    fn refresh_models(&mut self) {
        let generation = self.params.generation();
        if generation == self.generation {
            return;
        }
        self.generation = generation;
        let current = self.params.current();
        let models = Models::of_rig(current.as_ref().map(|p| &p.rig));
        if models != self.builder.models {
            self.names = models.list.iter().map(|m| m.name.clone()).collect();
            self.builder.models = models;
            self.models_changed = true;
        }
    }

    fn send(&self, socket: &UdpSocket, bytes: &[u8], to: SocketAddr) -> bool {
        match socket.try_send_to(bytes, to) {
            Ok(_) => true,
            Err(e) => {
                let drops = self.stats.send_drops.fetch_add(1, R);
                if drops.is_multiple_of(1000) {
                    tracing::warn!(%to, error = %e, drops = drops + 1, "NatNet packet not sent; dropped");
                }
                false
            }
        }
    }

    /// Sends `self.packet` to `to` in answer to a request of `request_len` bytes, if the gate
    /// lets it (super::gate); a reply it stops is counted.
    fn reply(&mut self, socket: &UdpSocket, to: SocketAddr, request_len: usize) {
        let packet = std::mem::take(&mut self.packet);
        self.reply_bytes(socket, &packet, to, request_len);
        self.packet = packet;
    }

    fn reply_bytes(&mut self, socket: &UdpSocket, bytes: &[u8], to: SocketAddr, request_len: usize) {
        match self.gate.reply(to.ip(), request_len, bytes.len(), Instant::now()) {
            Verdict::Send => {
                self.send(socket, bytes, to);
            }
            Verdict::Withheld => self.withheld(to, "a reply larger than the request"),
            Verdict::RateLimited => {
                let n = self.stats.rate_limited.fetch_add(1, R);
                if n.is_multiple_of(1000) {
                    tracing::warn!(peer = %to, limited = n + 1, "NatNet reply rate limit reached; request not answered");
                }
            }
        }
    }

    /// Counts (and logs now and then) what an address outside `client_networks` did not get.
    fn withheld(&self, to: SocketAddr, what: &str) {
        let n = self.stats.withheld.fetch_add(1, R);
        if n.is_multiple_of(1000) {
            tracing::warn!(
                peer = %to,
                withheld = n + 1,
                "NatNet: {what} not sent to an address outside [outputs.natnet] client_networks (it has not shown it receives what is sent to it; add its network to serve it)"
            );
        }
    }

    fn request(&mut self, socket: &UdpSocket, datagram: &[u8], peer: SocketAddr) {
        let req = match wire::parse_request(datagram) {
            Ok(r) => r,
            Err(e) => {
                if self.stats.bad_requests.fetch_add(1, R) == 0 {
                    tracing::warn!(%peer, error = %e, "NatNet request refused");
                }
                return;
            }
        };
        self.stats.requests.fetch_add(1, R);
        let request_len = datagram.len();
        match req.id {
            wire::NAT_CONNECT => {
                self.heard_from(peer);
                let info = ServerInfo {
                    app_name: "irtrackd".into(),
                    app_version: app_version(),
                    data_port: self.plan.multicast.map_or(self.local.port(), |(_, p)| p),
                    multicast: self.plan.multicast.map(|(g, _)| g),
                };
                if wire::encode_server_info(&info, &mut self.packet).is_ok() {
                    self.reply(socket, peer, request_len);
                }
                // Only for addresses that are served: a spoofed flood is counted, not logged.
                if self.gate.vouched_for(peer.ip()) {
                    tracing::info!(%peer, "NatNet client connected");
                }
            }
            wire::NAT_KEEPALIVE => self.heard_from(peer),
            wire::NAT_REQUEST_MODELDEF => {
                self.heard_from(peer);
                self.refresh_models();
                match wire::encode_model_def(&self.builder.models, &mut self.packet) {
                    Ok(()) => self.reply(socket, peer, request_len),
                    Err(e) => tracing::error!(error = %e, "NatNet model definitions not sent"),
                }
            }
            wire::NAT_REQUEST_FRAMEOFDATA => {
                self.heard_from(peer);
                if !self.last_frame.is_empty() {
                    let frame = std::mem::take(&mut self.last_frame);
                    self.reply_bytes(socket, &frame, peer, request_len);
                    self.last_frame = frame;
                }
            }
            wire::NAT_DISCONNECT => {
                let before = self.clients.len();
                self.clients.retain(|c| c.addr != peer);
                self.stats.clients.store(self.clients.len() as u64, R);
                if self.clients.len() != before {
                    tracing::info!(%peer, "NatNet client disconnected");
                }
            }
            wire::NAT_REQUEST => {
                // Motive's remote-control commands (recording, playback, bitstream version)
                // have no meaning here: answered with a failure code.
                tracing::debug!(%peer, command = %wire::command_text(req.payload), "NatNet command not supported");
                if wire::encode_response_code(1, &mut self.packet).is_ok() {
                    self.reply(socket, peer, request_len);
                }
            }
            other => {
                if self.stats.bad_requests.fetch_add(1, R) == 0 {
                    tracing::warn!(%peer, message = other, "NatNet message not understood");
                }
                if wire::encode_empty(wire::NAT_UNRECOGNIZED_REQUEST, &mut self.packet).is_ok() {
                    self.reply(socket, peer, request_len);
                }
            }
        }
    }

    /// Unicast: remembers (or refreshes) a client. Any request counts, so keep-alives from a
    /// forgotten client bring it back as a connect would. Frames flow to a client without
    /// further requests, so only addresses in `client_networks` become clients, at most
    /// `max_clients_per_address` per IP address.
    fn heard_from(&mut self, peer: SocketAddr) {
        if self.plan.multicast.is_some() {
            return;
        }
        let now = Instant::now();
        if let Some(c) = self.clients.iter_mut().find(|c| c.addr == peer) {
            c.last_heard = now;
            return;
        }
        if !self.gate.vouched_for(peer.ip()) {
            self.withheld(peer, "a unicast client slot (frames)");
            return;
        }
        let ip = peer.ip().to_canonical();
        let same_ip = self
            .clients
            .iter()
            .filter(|c| c.addr.ip().to_canonical() == ip)
            .count();
        if same_ip >= self.plan.max_clients_per_address {
            if self.stats.refused_per_address.fetch_add(1, R) == 0 {
                tracing::warn!(%peer, max = self.plan.max_clients_per_address, "NatNet clients per address limit reached; client refused");
            }
            return;
        }
        if self.clients.len() >= self.plan.max_clients {
            if self.stats.refused.fetch_add(1, R) == 0 {
                tracing::warn!(%peer, max = self.plan.max_clients, "NatNet client limit reached; client refused");
            }
            return;
        }
        self.clients.push(Client {
            addr: peer,
            last_heard: now,
        });
        self.stats.clients.store(self.clients.len() as u64, R);
    }

    fn expire(&mut self) {
        self.gate.sweep(Instant::now());
        let timeout = self.plan.unicast_timeout;
        let before = self.clients.len();
        self.clients.retain(|c| {
            let keep = c.last_heard.elapsed() < timeout;
            if !keep {
                tracing::info!(peer = %c.addr, "NatNet client silent; no more frames to it");
            }
            keep
        });
        if self.clients.len() != before {
            self.stats.clients.store(self.clients.len() as u64, R);
        }
    }

    fn frame(&mut self, socket: &UdpSocket, rec: &PositionRecord) {
        self.received += 1;
        let published = self.status.published.load(R);
        self.stats
            .slot_skips
            .store(published.saturating_sub(self.received), R);
        self.refresh_models();
        self.builder.fill(rec, &mut self.scene);
        let stamps = FrameStamps {
            transmit_ns: clock::monotonic_ns(),
            models_changed: std::mem::take(&mut self.models_changed),
        };
        if let Err(e) = wire::encode_frame(&self.scene, &self.names, stamps, &mut self.last_frame) {
            if self.stats.send_drops.fetch_add(1, R) == 0 {
                tracing::error!(error = %e, "NatNet frame not encoded");
            }
            return;
        }
        let frame = std::mem::take(&mut self.last_frame);
        let mut sent = 0u64;
        match self.plan.multicast {
            Some((group, port)) => {
                sent += u64::from(self.send(socket, &frame, SocketAddr::from((group, port))));
            }
            None => {
                for c in &self.clients {
                    sent += u64::from(self.send(socket, &frame, c.addr));
                }
            }
        }
        if sent > 0 {
            self.stats.frames_sent.fetch_add(sent, R);
            // Capture → the frame's datagrams handed to the kernel.
            self.stats.record_latency(rec.capture_ts_ns);
        }
        self.last_frame = frame;
    }
}

/// irtrackd's version as NatNet's four version bytes.
fn app_version() -> [u8; 4] {
    let mut v = [0u8; 4];
    for (slot, part) in v.iter_mut().zip(env!("CARGO_PKG_VERSION").split('.')) {
        *slot = part.parse().unwrap_or(0);
    }
    v
}
