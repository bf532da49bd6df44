//! Standard outputs that existing tools read (docs/outputs.md): NatNet for OptiTrack clients,
//! ROS 2 over DDS, MCAP recordings.
//!
//! Every output is fed from the processing loop's latest-value slot on the async side, never
//! from the loop itself: a slow or absent consumer can only make an output skip records
//! (counted in [`OutputStats`]), never slow the loop.

pub mod natnet;
pub mod recording;
pub mod ros2;
pub mod scene;
pub mod stats;

pub use stats::{OutputStats, OutputsStats};

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use irtrack_core::stream::PositionRecord;
use serde::Deserialize;
use tokio::sync::watch;

use crate::engine::ParamsHandle;
use crate::error::Result;
use crate::status::SharedStatus;

/// `[outputs]`: every output is off unless its table enables it.
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct OutputsConfig {
    /// `[outputs.natnet]`: NatNet for Motive clients.
    #[serde(default)]
    pub natnet: natnet::NatNetConfig,
    /// `[outputs.mcap]`: MCAP recording of positions and poses.
    #[serde(default)]
    pub mcap: recording::McapConfig,
    /// `[outputs.ros2]`: ROS 2 topics over DDS.
    #[serde(default)]
    pub ros2: ros2::Ros2Config,
}

impl OutputsConfig {
    /// Checks every enabled output's settings (errors name the key).
    pub fn validate(&self) -> Result<()> {
        if self.natnet.enabled {
            self.natnet.plan()?;
        }
        self.mcap.validate()?;
        self.ros2.validate()
    }
}

/// What outputs read: the latest-value slot, the active parameter set (for the models) and
/// the loop's publication counter (for skipped records).
pub struct Feed {
    /// The loop's latest record.
    pub slot: watch::Receiver<Option<PositionRecord>>,
    /// The active parameter set (tool models for NatNet's model definitions).
    pub params: Arc<ParamsHandle>,
    /// The loop's counters (publication count, to count skipped records).
    pub status: Arc<SharedStatus>,
    /// The loop's per-tool records (every tool as its own body); `None`: main record only.
    pub tools: Option<watch::Receiver<crate::engine::ToolSet>>,
}

/// The enabled outputs, bound (so a port in use fails at start) but not yet running.
pub struct Outputs {
    natnet: Option<natnet::server::NatNetServer>,
    #[cfg(feature = "mcap")]
    mcap: Option<recording::Recorder>,
    #[cfg(feature = "ros2")]
    ros2: Option<ros2::Ros2Output>,
    ros2_cfg: ros2::Ros2Config,
    /// Per-output counters, shared with `/status`.
    pub stats: OutputsStats,
}

impl Outputs {
    /// Checks the configuration, binds every enabled output's sockets and creates its files
    /// (relative paths under `state_dir`).
    pub fn bind(cfg: &OutputsConfig, state_dir: &std::path::Path) -> Result<Self> {
        cfg.validate()?;
        #[cfg(not(feature = "mcap"))]
        let _ = state_dir;
        let natnet = if cfg.natnet.enabled {
            Some(natnet::server::NatNetServer::bind(cfg.natnet.plan()?)?)
        } else {
            None
        };
        Ok(Self {
            natnet,
            #[cfg(feature = "mcap")]
            mcap: match cfg.mcap.enabled {
                true => Some(recording::Recorder::create(
                    cfg.mcap.resolved_path(state_dir),
                    cfg.mcap.queue_records,
                )?),
                false => None,
            },
            #[cfg(feature = "ros2")]
            ros2: match cfg.ros2.enabled {
                true => Some(ros2::Ros2Output::start(&cfg.ros2)?),
                false => None,
            },
            ros2_cfg: cfg.ros2.clone(),
            stats: {
                let stats = OutputsStats::default();
                stats.natnet.enabled.store(cfg.natnet.enabled, Ordering::Relaxed);
                stats.mcap.enabled.store(cfg.mcap.enabled, Ordering::Relaxed);
                stats.ros2.enabled.store(cfg.ros2.enabled, Ordering::Relaxed);
                stats
            },
        })
    }

    /// Checks the outputs' tool names against the parameter set irtrackd starts with (an
    /// unknown tool fails the start, naming the tools the set has). Without a set nothing is
    /// checked; a later set without a named tool is logged and that tool not published.
    pub fn check_params(&self, params: &ParamsHandle) -> Result<()> {
        if !self.ros2_cfg.enabled {
            return Ok(());
        }
        match params.current() {
            Some(p) => self
                .ros2_cfg
                .check_tools(p.rig.tools.iter().map(|t| t.name.as_str())),
            None => Ok(()),
        }
    }

    /// The NatNet command socket's address, when enabled.
    pub fn natnet_addr(&self) -> Option<SocketAddr> {
        self.natnet.as_ref().map(|n| n.local_addr())
    }

    /// Starts the outputs' tasks; each ends when its `shutdown()` future resolves.
    pub fn spawn<S, F>(self, feed: &Feed, shutdown: S) -> Vec<tokio::task::JoinHandle<()>>
    where
        S: Fn() -> F,
        F: Future<Output = ()> + Send + 'static,
    {
        let mut tasks = Vec::new();
        if let Some(server) = self.natnet {
            tasks.push(tokio::spawn(server.with_tools(feed.tools.clone()).serve(
                feed.slot.clone(),
                feed.params.clone(),
                feed.status.clone(),
                self.stats.natnet.clone(),
                shutdown(),
            )));
        }
        #[cfg(feature = "mcap")]
        if let Some(rec) = self.mcap {
            let rec = rec.with_models(feed.params.clone(), feed.tools.clone());
            tasks.push(tokio::spawn(rec.run(
                feed.slot.clone(),
                feed.status.clone(),
                self.stats.mcap.clone(),
                shutdown(),
            )));
        }
        #[cfg(feature = "ros2")]
        if let Some(out) = self.ros2 {
            let started = out.with_tools(feed.tools.clone()).spawn(
                tokio::runtime::Handle::current(),
                feed.slot.clone(),
                feed.params.clone(),
                feed.status.clone(),
                self.stats.ros2.clone(),
                shutdown(),
            );
            match started {
                // The thread ends with the shutdown future; a task waits for it.
                Ok(thread) => tasks.push(tokio::task::spawn_blocking(move || {
                    if thread.join().is_err() {
                        tracing::error!("ROS 2 output thread panicked");
                    }
                })),
                Err(e) => tracing::error!(error = %e, "ROS 2 output not started"),
            }
        }
        tasks
    }
}
