//! Wiring: builds the source, processing loop, LED driver and network services from a
//! [`Config`], and stops them again.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use irtrack_core::params::RigParams;
use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::stream::PositionRecord;
use tokio::net::TcpListener;
use tokio::sync::{oneshot, watch};

use crate::config::{Config, Leds, ListenConfig, RealtimeConfig, Resolved, Source};
use crate::engine::{Engine, ParamsHandle};
use crate::error::{FirmwareError, Result};
use crate::leds::StatusLeds;
use crate::leds::driver::LedDriver;
use crate::leds::indication::RobotIndication;
use crate::leds::sim::{LedRecord, SimLeds};
use crate::net::stream::{StreamFormat, StreamHub};
use crate::params::{ParamService, RigShape};
use crate::source::FrameSource;
use crate::source::replay::ReplaySource;
use crate::source::sim::SimSource;
use crate::status::SharedStatus;
use crate::storage::ParamStore;
use crate::tuning::TuningHandle;
use irtrack_robot::deadman::{DeadmanConfig, FlagDeadman};
use irtrack_robot::{LinkHandle, MonotonicClock, RobotConfig};

/// Actual addresses of the bound listeners.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoundAddrs {
    /// Parameter push listener.
    pub params: SocketAddr,
    /// Position stream, JSON lines.
    pub stream_ndjson: SocketAddr,
    /// Position stream, binary records.
    pub stream_binary: SocketAddr,
    /// Status port (`/status`, `/metrics`, set-up view).
    pub status: SocketAddr,
    /// NatNet command socket, when `[outputs.natnet]` is enabled.
    pub natnet: Option<SocketAddr>,
}

impl BoundAddrs {
    /// The line printed on stdout once every listener is bound (parsed by tests and the QEMU
    /// system test).
    pub fn ready_line(&self) -> String {
        let mut line = format!(
            "irtrackd ready params={} stream={} binary={} status={}",
            self.params, self.stream_ndjson, self.stream_binary, self.status
        );
        if let Some(a) = self.natnet {
            line.push_str(&format!(" natnet={a}"));
        }
        line
    }
}

/// Things tests (or other front ends) may supply instead of what the config describes.
#[derive(Default)]
pub struct Overrides {
    /// A frame source to use instead of opening the configured one.
    pub source: Option<Box<dyn FrameSource>>,
    /// An LED driver to use instead of the configured one.
    pub leds: Option<Box<dyn StatusLeds>>,
}

/// A running irtrackd.
pub struct Running {
    /// Where the listeners are bound.
    pub addrs: BoundAddrs,
    /// The shared counters and health state.
    pub status: Arc<SharedStatus>,
    /// The parameter store and its active set.
    pub params: Arc<ParamService>,
    /// Present when the simulated LED back end is in use.
    pub led_record: Option<LedRecord>,
    /// Counters of the standard outputs (docs/outputs.md).
    pub outputs: crate::outputs::OutputsStats,
    positions: watch::Receiver<Option<PositionRecord>>,
    stop_loop: Arc<AtomicBool>,
    loop_thread: Option<std::thread::JoinHandle<()>>,
    loop_result: Option<oneshot::Receiver<Result<()>>>,
    leds: Option<LedDriver>,
    /// Shared only weakly with the status endpoint's control requests.
    robot: Option<Arc<LinkHandle>>,
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
pub fn open_source(source: &Source) -> Result<(Box<dyn FrameSource>, Option<RigParams>)> {
    Ok(match source {
        Source::Sim(sim_cfg) => {
            let s = SimSource::new(sim_cfg)?;
            let mut rig = sim_cfg.rendered_rig(s.scenario().rig());
            // The simulator's truth includes the tool it renders (6-DOF demo and tests).
            rig.tools.extend(sim_cfg.tool_definitions());
            (Box::new(s), Some(rig))
        }
        Source::Replay(r) => (Box::new(ReplaySource::open(r)?), None),
        Source::V4l2(v) => (crate::source::v4l2::open(v)?, None),
    })
}

/// The loop's deadline: configured, else the source's nominal frame period.
pub fn deadline(realtime: &RealtimeConfig, source: &Source) -> Duration {
    deadline_at(realtime, source.nominal_fps())
}

/// The loop's deadline: configured, else the period of `nominal_fps` (a replay's recorded
/// rate, else the config's).
pub fn deadline_at(realtime: &RealtimeConfig, nominal_fps: Option<f64>) -> Duration {
    match (realtime.deadline_ms, nominal_fps) {
        (Some(ms), _) => Duration::from_secs_f64(ms / 1e3),
        (None, Some(fps)) if fps > 0.0 => Duration::from_secs_f64(1.0 / fps),
        // Replay without a rate: assume 30 fps, a common recording rate.
        _ => Duration::from_secs_f64(1.0 / 30.0),
    }
}

/// An LED back end (if any) and, for the simulated one, its change record.
type OpenedLeds = (Option<Box<dyn StatusLeds>>, Option<LedRecord>);

fn open_leds(leds: &Leds) -> Result<OpenedLeds> {
    Ok(match leds {
        Leds::Sim => {
            let (leds, record) = SimLeds::new();
            (Some(Box::new(leds)), Some(record))
        }
        Leds::None => (None, None),
        Leds::Gpio(g) => (Some(crate::leds::gpio::open(g)?), None),
        #[cfg(feature = "rpi")]
        Leds::Rppal(r) => (Some(crate::leds::rppal::open(r)?), None),
    })
}

/// The four bound listeners and their actual addresses.
struct Listeners {
    params: TcpListener,
    ndjson: TcpListener,
    binary: TcpListener,
    status: TcpListener,
    addrs: BoundAddrs,
}

/// Step 1: binds every listener, so a port clash fails before anything starts.
async fn bind_listeners(listen: &ListenConfig) -> Result<Listeners> {
    let params = bind("parameters", &listen.params).await?;
    let ndjson = bind("NDJSON stream", &listen.stream_ndjson).await?;
    let binary = bind("binary stream", &listen.stream_binary).await?;
    let status = bind("status", &listen.status).await?;
    // The connection caps only hold if the descriptors they allow exist.
    crate::net::limit::check_fd_limit(crate::net::limit::fds_needed(listen.max_stream_clients));
    let addrs = BoundAddrs {
        params: local("parameters", &params)?,
        stream_ndjson: local("NDJSON stream", &ndjson)?,
        stream_binary: local("binary stream", &binary)?,
        status: local("status", &status)?,
        natnet: None,
    };
    Ok(Listeners {
        params,
        ndjson,
        binary,
        status,
        addrs,
    })
}

/// Frame source and LEDs, from the overrides or else the config.
struct Devices {
    source: Box<dyn FrameSource>,
    /// The simulator's ground-truth rig (simulated source only).
    sim_rig: Option<RigParams>,
    leds: Option<Box<dyn StatusLeds>>,
    led_record: Option<LedRecord>,
}

/// Step 2: opens the source (a cluster solver's: the camera boards) and the LED back end.
fn open_devices(
    cfg: &Config,
    resolved: &Resolved,
    overrides: Overrides,
    handle: &Arc<ParamsHandle>,
    cluster: &Option<crate::cluster::SharedReport>,
    tracking: TrackerConfig,
) -> Result<Devices> {
    let (source, sim_rig) = match overrides.source {
        Some(s) => (s, None),
        None if cfg.cluster.role == crate::cluster::Role::Solver => {
            // Its own cameras, if any, feed the pairing beside the camera boards'.
            let own = if cfg.cluster.own_cameras {
                Some((open_source(&resolved.source)?.0, tracking))
            } else {
                None
            };
            (
                crate::cluster::solver_source(
                    &cfg.cluster,
                    handle.clone(),
                    cluster.clone().unwrap_or_default(),
                    own,
                )?,
                None,
            )
        }
        None => open_source(&resolved.source)?,
    };
    let (leds, led_record) = match overrides.leds {
        Some(l) => (Some(l), None),
        None => open_leds(&resolved.leds)?,
    };
    Ok(Devices {
        source,
        sim_rig,
        leds,
        led_record,
    })
}

/// Step 3: the parameter service with its stored (or simulator) parameter set. Keys are read
/// before anything starts: a broken key file must stop the service, not leave it unable to
/// accept parameters.
fn start_params(
    cfg: &Config,
    source: &dyn FrameSource,
    sim_rig: Option<RigParams>,
    handle: Arc<ParamsHandle>,
    status: Arc<SharedStatus>,
    credentials: Option<Arc<dyn crate::params::CredentialInbox>>,
) -> Result<Arc<ParamService>> {
    let trusted_keys = cfg.params.load_keys()?;
    let store = ParamStore::open(&cfg.service.state_dir)?;
    let shape = RigShape::of_set(&source.allocate_set());
    status.update_params_info(|p| p.calibration_max_age_days = cfg.params.calibration_max_age_days);
    let params = Arc::new(
        ParamService::new(store, shape, cfg.tracking, handle, status)
            .with_signature_policy(trusted_keys, cfg.params.policy())
            .with_pose_config(cfg.pose)
            .with_robot_tool(cfg.robot.as_ref().and_then(|r| r.tool.clone()))
            .with_credential_inbox(credentials),
    );
    let loaded = params.load_stored();
    if !loaded
        && cfg.service.params_from_simulator
        && let Some(rig) = sim_rig
    {
        if rig.cameras.len() >= 2 {
            params.install_unstored(rig, "simulator")?;
        } else {
            // A camera board's single camera: a parameter set needs two, the board none.
            tracing::info!("simulated camera board with one camera: no parameter set of its own");
        }
    }
    Ok(params)
}

/// Step 4: saved tuning (set-up view "Save") overrides [tracking]'s detector values and the
/// cameras' exposure/gain. Returns the detector settings the loop starts with.
fn load_tuning(cfg: &Config) -> Result<(TrackerConfig, Arc<TuningHandle>)> {
    let state_dir = &cfg.service.state_dir;
    let saved_tuning = crate::tuning::TuningFile::load(state_dir)?;
    let tracking = match &saved_tuning {
        Some(t) => {
            let path = state_dir.join(crate::tuning::TUNING_FILE);
            let tracking = t
                .apply_to(&cfg.tracking)
                .map_err(|reason| FirmwareError::Config {
                    reason: format!("{}: {reason}", path.display()),
                })?;
            tracing::info!(
                path = %path.display(),
                threshold_dn = tracking.threshold_dn,
                "saved tuning applied"
            );
            tracking
        }
        None => cfg.tracking,
    };
    let tuning = Arc::new(TuningHandle::new(
        tracking,
        saved_tuning.as_ref().map_or(&[][..], |t| &t.camera[..]),
        state_dir,
        saved_tuning.is_some(),
    ));
    Ok((tracking, tuning))
}

/// The processing loop's thread and how to stop it.
struct LoopThread {
    stop: Arc<AtomicBool>,
    thread: std::thread::JoinHandle<()>,
    result: oneshot::Receiver<Result<()>>,
}

/// Step 5: runs the engine on its own (possibly real-time) thread.
fn spawn_loop(engine: Engine, rt_cfg: RealtimeConfig, status: Arc<SharedStatus>) -> Result<LoopThread> {
    let stop = Arc::new(AtomicBool::new(false));
    let (result_tx, result) = oneshot::channel();
    let stop2 = stop.clone();
    let thread = std::thread::Builder::new()
        .name("irtrackd-loop".into())
        .spawn(move || {
            let lines = crate::rt::apply(&rt_cfg);
            if let Ok(mut g) = status.realtime.lock() {
                *g = lines;
            }
            let _ = result_tx.send(engine.run(&stop2));
        })
        .map_err(|e| FirmwareError::Thread {
            what: "processing loop",
            reason: e.to_string(),
        })?;
    Ok(LoopThread { stop, thread, result })
}

/// A shutdown future factory for the services (each gets its own future).
fn shutdown_future(rx: &watch::Receiver<bool>) -> impl std::future::Future<Output = ()> + Send + 'static {
    let mut rx = rx.clone();
    async move {
        let _ = rx.wait_for(|v| *v).await;
    }
}

/// The robot link, when `[robot]` is configured.
struct RobotParts {
    link: Option<Arc<LinkHandle>>,
    /// Software deadman for `[robot.deadman] kind = "flag"` (set by a control front end).
    deadman_flag: FlagDeadman,
}

/// Step 7: starts the robot link on the latest-value slot; its state drives the Robot LED.
fn start_robot(
    robot: Option<&RobotConfig>,
    positions: &watch::Receiver<Option<PositionRecord>>,
    status: &Arc<SharedStatus>,
    tasks: &mut Vec<tokio::task::JoinHandle<()>>,
) -> Result<RobotParts> {
    let deadman_flag = FlagDeadman::new();
    let Some(rc) = robot else {
        return Ok(RobotParts {
            link: None,
            deadman_flag,
        });
    };
    let deadman = rc.deadman.open(&deadman_flag)?;
    let link = irtrack_robot::spawn_link(rc.clone(), positions.clone(), MonotonicClock, deadman)?;
    let mut link_status = link.subscribe();
    // /metrics and the fault texts read the link's counters.
    let _ = status.robot_link.set(link.subscribe());
    let st = status.clone();
    tasks.push(tokio::spawn(async move {
        loop {
            let state = link_status.borrow_and_update().state;
            st.set_robot(RobotIndication::from(state));
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
    Ok(RobotParts {
        link: Some(Arc::new(link)),
        deadman_flag,
    })
}

/// Starts everything. Must be called inside a tokio runtime. The config is validated first;
/// listeners are bound before anything else starts, so a port clash fails fast.
pub async fn start(mut cfg: Config, overrides: Overrides) -> Result<Running> {
    // Credentials pushed to this board earlier (docs/cluster.md, "Pushing credentials").
    let pushed = cfg.cluster.adopt_pushed_credentials(&cfg.service.state_dir);
    if let Some(f) = &pushed {
        tracing::info!(file = %f.display(), "cluster transport: using the pushed credentials");
    }
    let resolved = cfg.validate()?;
    let listeners = bind_listeners(&cfg.listen).await?;
    let outputs = crate::outputs::Outputs::bind(&cfg.outputs, &cfg.service.state_dir)?;
    let addrs = BoundAddrs {
        natnet: outputs.natnet_addr(),
        ..listeners.addrs
    };

    let handle = Arc::new(ParamsHandle::new());
    let cluster = crate::cluster::new_report(&cfg.cluster);
    let (tracking, tuning) = load_tuning(&cfg)?;
    let devices = open_devices(&cfg, &resolved, overrides, &handle, &cluster, tracking)?;
    let led_desc = devices
        .leds
        .as_ref()
        .map_or_else(|| "none".to_string(), |l| l.describe());
    let status = Arc::new(SharedStatus::new(
        devices.source.camera_count(),
        devices.source.describe(),
        led_desc,
    ));
    crate::cluster::register(&status, &cluster);
    tracing::info!(source = %devices.source.describe(), leds = %status.led_backend, "starting");
    // /status and /metrics show the outputs' counters.
    let _ = status.outputs.set(outputs.stats.clone());

    let inbox =
        crate::cluster::credential_inbox(&cfg.cluster, &cfg.service.state_dir, &cluster, pushed.is_some())?;
    let params = start_params(
        &cfg,
        devices.source.as_ref(),
        devices.sim_rig,
        handle.clone(),
        status.clone(),
        inbox,
    )?;
    // Tools named by outputs exist in the set irtrackd starts with.
    outputs.check_params(&handle)?;
    let tap = Arc::new(crate::viewer::ViewerTap::new());
    // /metrics shows the viewers' copies and drops.
    let _ = status.viewer_tap.set(tap.clone());
    let auth = crate::net::auth::OperatorAuth::new(cfg.service.operator_password_hash.clone())?;

    let (slot_tx, slot_rx) = watch::channel(None);
    let (tools_tx, tools_rx) = watch::channel(crate::engine::ToolSet::EMPTY);
    // A replay knows its recording's rate (timestamps.csv) better than the config.
    let nominal_fps = devices
        .source
        .nominal_fps()
        .or_else(|| resolved.source.nominal_fps());
    let engine = Engine::new(
        devices.source,
        tracking,
        handle.clone(),
        slot_tx,
        status.clone(),
        deadline_at(&cfg.realtime, nominal_fps),
    )
    .with_nominal_fps(nominal_fps)
    .with_camera_timing(config_timing(&cfg, &resolved.source))
    .with_pose_config(cfg.pose)
    .with_robot_tool(cfg.robot.as_ref().and_then(|r| r.tool.clone()))
    .with_tool_slot(tools_tx)
    .with_viewer_tap(tap.clone())
    .with_tuning(tuning.clone());
    let engine = match cfg.source.max_pairing_error_us {
        Some(us) => engine.with_max_pairing_error(Duration::from_micros(us)),
        None => engine,
    };
    let engine = crate::cluster::with_role(engine, &cfg.cluster, &cluster)?;
    // The session is open (camera board: its publishers; solver: its subscriber): raise
    // Zenoh's threads that carry observations, now and when they appear later.
    if let Some(prio) = cfg.cluster.transport_fifo_priority {
        if let Some(advice) = crate::rt::transport_priority_advice(prio, cfg.realtime.fifo_priority) {
            tracing::warn!("{advice}");
        }
        crate::rt::watch_transport_threads(cfg.cluster.role, prio, Arc::downgrade(&status)).map_err(|e| {
            FirmwareError::Thread {
                what: "transport priority watcher",
                reason: e.to_string(),
            }
        })?;
    }
    let processing = spawn_loop(engine, cfg.realtime.clone(), status.clone())?;
    // Whole-frame analysis for /status and its faults, off the loop; suggests a threshold at
    // first start (no saved tuning).
    {
        let (tap, stop) = (tap.clone(), processing.stop.clone());
        let first_start = !tuning.loaded_from_file;
        std::thread::Builder::new()
            .name("irtrackd-frames".into())
            .spawn(move || crate::viewer::run_sampler(tap, first_start, stop))
            .map_err(|e| FirmwareError::Thread {
                what: "frame analysis",
                reason: e.to_string(),
            })?;
    }

    // Without LEDs the driver runs on `NoLeds`: its indication still reaches /status and the page.
    let leds = Some(LedDriver::start(
        devices.leds.unwrap_or_else(|| Box::new(crate::leds::NoLeds)),
        status.clone(),
    )?);

    // Step 6: the parameter and stream services.
    let (shutdown_tx, shutdown_rx) = watch::channel(false);
    let hub = StreamHub::start_with_tools(
        slot_rx.clone(),
        Some(tools_rx.clone()),
        cfg.listen.client_queue_records,
        status.clone(),
    )
    .with_max_clients(cfg.listen.max_stream_clients);
    let mut tasks = vec![
        tokio::spawn(crate::net::params::serve(
            listeners.params,
            params.clone(),
            shutdown_future(&shutdown_rx),
        )),
        tokio::spawn(crate::net::stream::serve(
            listeners.ndjson,
            StreamFormat::Ndjson,
            hub.clone(),
            shutdown_future(&shutdown_rx),
        )),
        tokio::spawn(crate::net::stream::serve(
            listeners.binary,
            StreamFormat::Binary,
            hub,
            shutdown_future(&shutdown_rx),
        )),
    ];

    // ptp4l's own offset and port state for /status, polled off the frame path.
    if cfg.clock.ptp {
        let state = crate::ptp::monitor::SharedPtp::default();
        let _ = status.ptp.set(state.clone());
        tasks.push(tokio::spawn(crate::ptp::monitor::run(
            state,
            cfg.clock.ptp4l_socket.clone(),
            cfg.clock.domain,
            shutdown_future(&shutdown_rx),
        )));
    }

    let robot = start_robot(cfg.robot.as_ref(), &slot_rx, &status, &mut tasks)?;

    // Step 7b: the standard outputs (docs/outputs.md), on the same latest-value slot.
    let output_stats = outputs.stats.clone();
    let feed = crate::outputs::Feed {
        slot: slot_rx.clone(),
        params: handle.clone(),
        status: status.clone(),
        tools: Some(tools_rx.clone()),
    };
    tasks.extend(outputs.spawn(&feed, || shutdown_future(&shutdown_rx)));

    // Step 8: the status service (set-up page, live view, robot control).
    let control = crate::net::status::RobotControl {
        allowed: cfg.service.control,
        link: robot.link.as_ref().map(Arc::downgrade),
        deadman_flag: cfg
            .robot
            .as_ref()
            .filter(|rc| rc.deadman == DeadmanConfig::Flag)
            .map(|_| robot.deadman_flag.clone()),
    };
    // The system updater (docs/updates.md); one that cannot start leaves tracking running.
    let updates =
        crate::update::Updates::from_config(&cfg.update, &cfg.service.state_dir).unwrap_or_else(|e| {
            tracing::warn!(error = %e, "system updates are off");
            None
        });
    let service = crate::net::status::StatusService::new(status.clone())
        .with_updates(updates)
        .with_control(control)
        .with_auth(auth)
        .with_view_policy(&cfg.status.allowed_hosts, cfg.status.public_view)
        .with_live(tap, tuning, slot_rx.clone(), handle)
        .with_tools(tools_rx.clone())
        .with_workspace(
            cfg.robot
                .as_ref()
                .map(|r| (r.safety.workspace_min_mm, r.safety.workspace_max_mm)),
        );
    tasks.push(tokio::spawn(
        service.serve(listeners.status, shutdown_future(&shutdown_rx)),
    ));

    Ok(Running {
        addrs,
        status,
        params,
        led_record: devices.led_record,
        outputs: output_stats,
        positions: slot_rx,
        stop_loop: processing.stop,
        loop_thread: Some(processing.thread),
        loop_result: Some(processing.result),
        leds,
        robot: robot.link,
        robot_deadman_flag: robot.deadman_flag,
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
    pub fn robot(&self) -> Option<&LinkHandle> {
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

/// Each camera's timing from the config: the simulated source's own cameras (`[source.sim.timing]`)
/// or the `[[camera_timing]]` tables (V4L2 and replayed cameras); a parameter set carrying
/// timing overrides these in the loop.
fn config_timing(cfg: &Config, source: &crate::config::Source) -> Vec<irtrack_core::timing::CameraTiming> {
    if let crate::config::Source::Sim(sim) = source
        && sim.timing.is_some()
    {
        return sim.camera_timings();
    }
    let n = cfg.camera_timing.iter().map(|t| t.camera + 1).max().unwrap_or(0);
    let exposure = cfg.source.v4l2.as_ref().and_then(|v| v.exposure_us);
    (0..n)
        .map(|i| {
            cfg.camera_timing
                .iter()
                .find(|t| t.camera == i)
                // `Config::validate` refused what does not convert.
                .and_then(|t| t.to_timing(exposure).ok())
                .unwrap_or_default()
        })
        .collect()
}
