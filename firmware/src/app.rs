//! Wiring: builds the source, processing loop, LED driver and network services from a
//! [`Config`], and stops them again.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use irtrack_core::params::RigParams;
use irtrack_core::stream::PositionRecord;
use tokio::net::TcpListener;
use tokio::sync::{oneshot, watch};

use crate::config::{Config, LedBackend, SourceKind};
use crate::engine::{Engine, ParamsHandle};
use crate::error::{FirmwareError, Result};
use crate::leds::StatusLeds;
use crate::leds::driver::LedDriver;
use crate::leds::sim::{LedRecord, SimLeds};
use crate::net::stream::{StreamFormat, StreamHub};
use crate::params::{ParamService, RigShape};
use crate::robot::TcpRobotLink;
use crate::robot::client::MonotonicClock;
use crate::robot::deadman::FlagDeadman;
use crate::source::FrameSource;
use crate::source::replay::ReplaySource;
use crate::source::sim::SimSource;
use crate::status::SharedStatus;
use crate::storage::ParamStore;

/// Actual addresses of the bound listeners.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoundAddrs {
    pub params: SocketAddr,
    pub stream_ndjson: SocketAddr,
    pub stream_binary: SocketAddr,
    pub status: SocketAddr,
}

impl BoundAddrs {
    /// The line printed on stdout once every listener is bound (parsed by tests and the QEMU
    /// system test).
    pub fn ready_line(&self) -> String {
        format!(
            "irtrackd ready params={} stream={} binary={} status={}",
            self.params, self.stream_ndjson, self.stream_binary, self.status
        )
    }
}

/// Things tests (or other front ends) may supply instead of what the config describes.
#[derive(Default)]
pub struct Overrides {
    pub source: Option<Box<dyn FrameSource>>,
    pub leds: Option<Box<dyn StatusLeds>>,
}

/// A running irtrackd.
pub struct Running {
    pub addrs: BoundAddrs,
    pub status: Arc<SharedStatus>,
    pub params: Arc<ParamService>,
    /// Present when the simulated LED back end is in use.
    pub led_record: Option<LedRecord>,
    positions: watch::Receiver<Option<PositionRecord>>,
    stop_loop: Arc<AtomicBool>,
    loop_thread: Option<std::thread::JoinHandle<()>>,
    loop_result: Option<oneshot::Receiver<Result<()>>>,
    leds: Option<LedDriver>,
    /// Shared only weakly with the status endpoint's control requests.
    robot: Option<Arc<TcpRobotLink>>,
    /// Software deadman for `[robot.deadman] kind = "flag"` (set by a control front end).
    pub robot_deadman_flag: FlagDeadman,
    shutdown_tx: watch::Sender<bool>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

async fn bind(what: &'static str, addr: &str) -> Result<TcpListener> {
    TcpListener::bind(addr)
        .await
        .map_err(|source| FirmwareError::Bind {
            what,
            addr: addr.to_string(),
            source,
        })
}

fn local(what: &'static str, l: &TcpListener) -> Result<SocketAddr> {
    l.local_addr().map_err(|source| FirmwareError::Bind {
        what,
        addr: "?".into(),
        source,
    })
}

/// Opens the configured source; for the simulator also returns its ground-truth rig.
pub fn open_source(cfg: &Config) -> Result<(Box<dyn FrameSource>, Option<RigParams>)> {
    Ok(match cfg.source.kind {
        SourceKind::Sim => {
            let sim_cfg = cfg.source.sim.clone().unwrap_or_default();
            let s = SimSource::new(&sim_cfg)?;
            let mut rig = s.scenario().rig().clone();
            // The simulator's truth includes the tool it renders (6-DOF demo and tests).
            rig.tools.extend(sim_cfg.tool_definition());
            (Box::new(s), Some(rig))
        }
        SourceKind::Replay => {
            let r = cfg.source.replay.as_ref().ok_or_else(|| FirmwareError::Config {
                reason: "source.kind = \"replay\" needs [source.replay]".into(),
            })?;
            (Box::new(ReplaySource::open(r)?), None)
        }
        SourceKind::V4l2 => {
            let v = cfg.source.v4l2.as_ref().ok_or_else(|| FirmwareError::Config {
                reason: "source.kind = \"v4l2\" needs [source.v4l2]".into(),
            })?;
            (crate::source::v4l2::open(v)?, None)
        }
    })
}

/// The loop's deadline: configured, else the source's nominal frame period.
pub fn deadline(cfg: &Config) -> Duration {
    let fps = match cfg.source.kind {
        SourceKind::Sim => Some(cfg.source.sim.clone().unwrap_or_default().fps),
        SourceKind::Replay => cfg.source.replay.as_ref().and_then(|r| r.fps),
        SourceKind::V4l2 => cfg.source.v4l2.as_ref().map(|v| f64::from(v.fps)),
    };
    match (cfg.realtime.deadline_ms, fps) {
        (Some(ms), _) => Duration::from_secs_f64(ms / 1e3),
        (None, Some(fps)) if fps > 0.0 => Duration::from_secs_f64(1.0 / fps),
        // Replay without a rate: assume 30 fps, a common recording rate.
        _ => Duration::from_secs_f64(1.0 / 30.0),
    }
}

/// An LED back end (if any) and, for the simulated one, its change record.
type OpenedLeds = (Option<Box<dyn StatusLeds>>, Option<LedRecord>);

fn open_leds(cfg: &Config) -> Result<OpenedLeds> {
    Ok(match cfg.leds.backend {
        LedBackend::Sim => {
            let (leds, record) = SimLeds::new();
            (Some(Box::new(leds)), Some(record))
        }
        LedBackend::None => (None, None),
        LedBackend::Gpio => {
            let g = cfg.leds.gpio.as_ref().ok_or_else(|| FirmwareError::Config {
                reason: "leds.backend = \"gpio\" needs [leds.gpio]".into(),
            })?;
            (Some(crate::leds::gpio::open(g)?), None)
        }
        #[cfg(feature = "rpi")]
        LedBackend::Rppal => {
            let r = cfg.leds.rppal.as_ref().ok_or_else(|| FirmwareError::Config {
                reason: "leds.backend = \"rppal\" needs [leds.rppal]".into(),
            })?;
            (Some(crate::leds::rppal::open(r)?), None)
        }
        #[cfg(not(feature = "rpi"))]
        LedBackend::Rppal => {
            return Err(FirmwareError::Config {
                reason: "irtrackd was built without the `rpi` feature".into(),
            });
        }
    })
}

/// Starts everything. Must be called inside a tokio runtime. Listeners are bound before
/// anything else starts, so a port clash fails fast.
pub async fn start(cfg: Config, overrides: Overrides) -> Result<Running> {
    let l_params = bind("parameters", &cfg.listen.params).await?;
    let l_ndjson = bind("NDJSON stream", &cfg.listen.stream_ndjson).await?;
    let l_binary = bind("binary stream", &cfg.listen.stream_binary).await?;
    let l_status = bind("status", &cfg.listen.status).await?;
    let addrs = BoundAddrs {
        params: local("parameters", &l_params)?,
        stream_ndjson: local("NDJSON stream", &l_ndjson)?,
        stream_binary: local("binary stream", &l_binary)?,
        status: local("status", &l_status)?,
    };

    let (source, sim_rig) = match overrides.source {
        Some(s) => (s, None),
        None => open_source(&cfg)?,
    };
    let (leds, led_record) = match overrides.leds {
        Some(l) => (Some(l), None),
        None => open_leds(&cfg)?,
    };
    let led_desc = leds.as_ref().map_or_else(|| "none".to_string(), |l| l.describe());
    let status = Arc::new(SharedStatus::new(
        source.camera_count(),
        source.describe(),
        led_desc,
    ));
    tracing::info!(source = %source.describe(), leds = %status.led_backend, "starting");

    // Keys are read before anything starts: a broken key file must stop the service, not
    // leave it unable to accept parameters.
    let trusted_keys = cfg.params.load_keys()?;
    let handle = Arc::new(ParamsHandle::new());
    let store = ParamStore::open(&cfg.service.state_dir)?;
    let shape = RigShape::of_set(&source.allocate_set());
    let params = Arc::new(
        ParamService::new(store, shape, cfg.tracking, handle.clone(), status.clone())
            .with_signature_policy(trusted_keys, cfg.params.policy())
            .with_pose_config(cfg.pose),
    );
    let loaded = params.load_stored();
    if !loaded
        && cfg.service.params_from_simulator
        && let Some(rig) = sim_rig
    {
        params.install_unstored(rig, "simulator")?;
    }

    // Saved tuning (set-up view "Save") overrides [tracking]'s detector values and the
    // cameras' exposure/gain.
    let saved_tuning = crate::tuning::TuningFile::load(&cfg.service.state_dir)?;
    let tracking = match &saved_tuning {
        Some(t) => {
            let tracking = t
                .apply_to(&cfg.tracking)
                .map_err(|reason| FirmwareError::Config {
                    reason: format!(
                        "{}: {reason}",
                        cfg.service.state_dir.join(crate::tuning::TUNING_FILE).display()
                    ),
                })?;
            tracing::info!(
                path = %cfg.service.state_dir.join(crate::tuning::TUNING_FILE).display(),
                threshold_dn = tracking.threshold_dn,
                "saved tuning applied"
            );
            tracking
        }
        None => cfg.tracking,
    };
    let tuning = Arc::new(crate::tuning::TuningHandle::new(
        tracking,
        saved_tuning.as_ref().map_or(&[][..], |t| &t.camera[..]),
        &cfg.service.state_dir,
        saved_tuning.is_some(),
    ));
    let tap = Arc::new(crate::viewer::ViewerTap::new());
    let auth = crate::net::auth::OperatorAuth::new(cfg.service.operator_password_hash.clone())?;

    let (slot_tx, slot_rx) = watch::channel(None);
    let engine = Engine::new(
        source,
        tracking,
        handle.clone(),
        slot_tx,
        status.clone(),
        deadline(&cfg),
    )
    .with_pose_config(cfg.pose)
    .with_viewer_tap(tap.clone())
    .with_tuning(tuning.clone());
    let engine = match cfg.source.max_pairing_error_us {
        Some(us) => engine.with_max_pairing_error(Duration::from_micros(us)),
        None => engine,
    };
    let stop_loop = Arc::new(AtomicBool::new(false));
    let (result_tx, result_rx) = oneshot::channel();
    let rt_cfg = cfg.realtime.clone();
    let (stop2, status2) = (stop_loop.clone(), status.clone());
    let loop_thread = std::thread::Builder::new()
        .name("irtrackd-loop".into())
        .spawn(move || {
            let lines = crate::rt::apply(&rt_cfg);
            if let Ok(mut g) = status2.realtime.lock() {
                *g = lines;
            }
            let _ = result_tx.send(engine.run(&stop2));
        })
        .map_err(|e| FirmwareError::Thread {
            what: "processing loop",
            reason: e.to_string(),
        })?;

    let leds = leds.map(|l| LedDriver::start(l, status.clone())).transpose()?;

    let (shutdown_tx, shutdown_rx) = watch::channel(false);
    let shutdown = move || {
        let mut rx = shutdown_rx.clone();
        async move {
            let _ = rx.wait_for(|v| *v).await;
        }
    };
    let hub = StreamHub::start(slot_rx.clone(), cfg.listen.client_queue_records, status.clone())
        .with_max_clients(cfg.listen.max_stream_clients);
    let mut tasks = vec![
        tokio::spawn(crate::net::params::serve(l_params, params.clone(), shutdown())),
        tokio::spawn(crate::net::stream::serve(
            l_ndjson,
            StreamFormat::Ndjson,
            hub.clone(),
            shutdown(),
        )),
        tokio::spawn(crate::net::stream::serve(
            l_binary,
            StreamFormat::Binary,
            hub,
            shutdown(),
        )),
    ];

    // Robot link: consumes the same latest-value slot; its state drives the Robot LED.
    let robot_deadman_flag = FlagDeadman::new();
    let robot = match &cfg.robot {
        None => None,
        Some(rc) => {
            let deadman = rc.deadman.open(&robot_deadman_flag)?;
            let link = crate::robot::spawn_link(rc.clone(), slot_rx.clone(), MonotonicClock, deadman)?;
            let mut link_status = link.subscribe();
            let st = status.clone();
            tasks.push(tokio::spawn(async move {
                loop {
                    let state = link_status.borrow_and_update().state;
                    st.set_robot(state.indication());
                    if link_status.changed().await.is_err() {
                        break;
                    }
                }
            }));
            tracing::info!(
                kind = rc.kind.name(),
                address = %rc.address,
                "robot link started (motion needs an explicit enable)"
            );
            Some(Arc::new(link))
        }
    };
    let control = crate::net::status::RobotControl {
        allowed: cfg.service.control,
        link: robot.as_ref().map(Arc::downgrade),
        deadman_flag: cfg
            .robot
            .as_ref()
            .filter(|rc| rc.deadman == crate::robot::deadman::DeadmanConfig::Flag)
            .map(|_| robot_deadman_flag.clone()),
    };
    let service = crate::net::status::StatusService::new(status.clone())
        .with_control(control)
        .with_auth(auth)
        .with_live(tap, tuning, slot_rx.clone(), handle)
        .with_workspace(
            cfg.robot
                .as_ref()
                .map(|r| (r.safety.workspace_min_mm, r.safety.workspace_max_mm)),
        );
    tasks.push(tokio::spawn(service.serve(l_status, shutdown())));

    Ok(Running {
        addrs,
        status,
        params,
        led_record,
        positions: slot_rx,
        stop_loop,
        loop_thread: Some(loop_thread),
        loop_result: Some(result_rx),
        leds,
        robot,
        robot_deadman_flag,
        shutdown_tx,
        tasks,
    })
}

impl Running {
    /// The latest-value slot of position records (for the robot link and other in-process
    /// consumers). `None` until the loop publishes its first record.
    pub fn positions(&self) -> watch::Receiver<Option<PositionRecord>> {
        self.positions.clone()
    }

    /// Resolves when the processing loop ends (source ended or fatal error), with its result.
    pub fn take_loop_result(&mut self) -> Option<oneshot::Receiver<Result<()>>> {
        self.loop_result.take()
    }

    /// A future resolving when [`Running::shutdown`] starts (for extra tasks like the robot link).
    pub fn shutdown_signal(&self) -> impl std::future::Future<Output = ()> + Send + 'static {
        let mut rx = self.shutdown_tx.subscribe();
        async move {
            let _ = rx.wait_for(|v| *v).await;
        }
    }

    /// The robot link, when `[robot]` is configured (enable/disable/status via `RobotLink`).
    pub fn robot(&self) -> Option<&TcpRobotLink> {
        self.robot.as_deref()
    }

    /// Stops the robot link (hold + BYE first), services, loop and LEDs (LEDs end off).
    pub async fn shutdown(mut self) {
        if let Some(mut link) = self.robot.take() {
            // A control request may hold the link for a moment; wait for it to finish.
            for _ in 0..100 {
                match Arc::try_unwrap(link) {
                    Ok(owned) => {
                        owned.shutdown().await;
                        break;
                    }
                    Err(shared) => {
                        link = shared;
                        tokio::time::sleep(Duration::from_millis(10)).await;
                    }
                }
            }
        }
        let _ = self.shutdown_tx.send(true);
        for t in self.tasks.drain(..) {
            let _ = t.await;
        }
        self.stop_loop.store(true, Ordering::Relaxed);
        if let Some(h) = self.loop_thread.take() {
            let _ = tokio::task::spawn_blocking(move || h.join()).await;
        }
        if let Some(l) = self.leds.take() {
            let _ = tokio::task::spawn_blocking(move || l.stop()).await;
        }
    }
}
