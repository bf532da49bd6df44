//! `host-tools robot-sim`: a simulated robot controller, the robot (server) side of the robot
//! protocol (docs/robot-protocol.md). The TCP point moves toward each target at a limited speed;
//! replies are those of the RAPID module; faults can be injected; everything received and the
//! TCP position are logged to CSV for comparison with the marker's truth.
//!
//! `--egm` / `--rsi` simulate a streaming controller instead (ABB EGM, KUKA RSI;
//! docs/robot-streaming.md): a packet to irtrackd's UDP `--sensor` address every cycle, a servo
//! with lag and speed/acceleration limits, late/missing answers counted, the session stopped
//! after `--max-missed` missed cycles in a row, and one CSV row per cycle in `--log`.

use std::io::{BufWriter, ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use std::net::UdpSocket;
use std::sync::{Arc, Mutex};

use anyhow::{Context, bail};
use irtrack_core::robot_proto::{MAX_LINE_BYTES, RobotMsg};
use irtrack_robot::RsiMode;
use irtrack_robot::cell::{self, RobotErrorModel};
use irtrack_robot::ctrl_sim::{CtrlConfig, CtrlKind, SimController, wait_readable};
use irtrack_robot::sim_robot::{SimEvent, SimRobot, SimRobotConfig};

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Address to listen on (port 0 picks a free port; the chosen address is printed).
    #[arg(long, default_value = "127.0.0.1:1025")]
    pub listen: String,
    /// TCP speed limit.
    #[arg(long, default_value_t = 250.0)]
    pub speed_mm_s: f64,
    /// Credit window granted (1 = step-by-step).
    #[arg(long, default_value_t = 1)]
    pub credits: u8,
    /// Start position `x,y,z` in mm.
    #[arg(long, default_value = "0,0,0", value_parser = parse_xyz)]
    pub home: [f64; 3],
    /// CSV log of received targets, events and the TCP position.
    #[arg(long)]
    pub log: Option<PathBuf>,
    /// Delay before every credit reply (a slow controller).
    #[arg(long, default_value_t = 0)]
    pub inject_delay_ms: u64,
    /// Drop each connection after this many targets (0 = never).
    #[arg(long, default_value_t = 0)]
    pub disconnect_after: u32,
    /// Reject every N-th target (0 = never).
    #[arg(long, default_value_t = 0)]
    pub reject_every: u32,
    /// Motion update period.
    #[arg(long, default_value_t = 5)]
    pub tick_ms: u64,
    /// Position rows in the log every this many ms.
    #[arg(long, default_value_t = 20)]
    pub log_every_ms: u64,
    /// Exit after serving this many connections (0 = serve forever).
    #[arg(long, default_value_t = 0)]
    pub max_connections: u32,
    /// Name sent in HELLO.
    #[arg(long, default_value = "robot-sim")]
    pub name: String,
    /// Simulate an ABB EGM controller (UDP, protobuf) instead of the socket protocol.
    #[arg(long, conflicts_with = "rsi")]
    pub egm: bool,
    /// Simulate a KUKA RSI controller (UDP, XML) instead of the socket protocol.
    #[arg(long)]
    pub rsi: bool,
    /// RSI correction mode: `absolute` or `relative` (must match irtrackd's `rsi_mode`).
    #[arg(long, default_value = "absolute", value_parser = parse_rsi_mode)]
    pub rsi_mode: RsiMode,
    /// EGM/RSI: irtrackd's UDP address (its `[robot] address`).
    #[arg(long)]
    pub sensor: Option<String>,
    /// EGM/RSI: interpolation cycle (4 = 250 Hz; KR C2's RSI: 12 ≈ 83 Hz).
    #[arg(long, default_value_t = 4.0)]
    pub cycle_ms: f64,
    /// EGM/RSI: servo lag time constant.
    #[arg(long, default_value_t = 12.0)]
    pub servo_lag_ms: f64,
    /// EGM/RSI: acceleration limit (the speed limit is `--speed-mm-s`).
    #[arg(long, default_value_t = 5000.0)]
    pub max_accel_mm_s2: f64,
    /// EGM/RSI: missed cycles in a row that stop the session (0 = never).
    #[arg(long, default_value_t = 25)]
    pub max_missed: u32,
    /// EGM/RSI: stop after this many seconds (default: run until killed).
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// Simulated cell: answer irtrackd's simulated cameras (`[source.sim.cell] robot`) on this
    /// UDP address with where the LED on the flange really is (port 0 picks one; printed).
    #[arg(long)]
    pub cell_feed: Option<String>,
    /// Simulated cell: the LED's position in the flange (TCP) frame, `x,y,z` mm; for a tool
    /// (`TOOL?` on the cell feed, `[source.sim.cell]` with `[source.sim] tool`) the tool
    /// frame's origin in the flange frame.
    #[arg(long, default_value = "0,0,0", value_parser = parse_xyz)]
    pub led_offset_mm: [f64; 3],
    /// Simulated cell: the tool's rotation on the flange (flange ← tool), a rotation vector
    /// (axis × angle) `x,y,z` in degrees.
    #[arg(long, default_value = "0,0,0", value_parser = parse_xyz)]
    pub tool_mount_rotation_deg: [f64; 3],
    /// Simulated cell: smooth absolute-orientation error of the flange, RMS of its angle (deg).
    #[arg(long, default_value_t = 0.0)]
    pub abs_orientation_error_rms_deg: f64,
    /// Simulated cell: repeatability, RMS of the 3-D deviation between visits (mm).
    #[arg(long, default_value_t = 0.02)]
    pub repeatability_mm: f64,
    /// Simulated cell: smooth absolute-position error field, RMS of its 3-D magnitude (mm).
    #[arg(long, default_value_t = 0.3)]
    pub abs_error_rms_mm: f64,
    /// Simulated cell: wavelength of the error field (mm).
    #[arg(long, default_value_t = 800.0)]
    pub abs_error_wavelength_mm: f64,
    /// Simulated cell: seed of the error field and of the repeatability draws.
    #[arg(long, default_value_t = 1)]
    pub error_seed: u64,
}

/// What the cell feed needs from the simulated robot, shared with the feed's thread.
#[derive(Debug, Clone, Copy)]
struct CellState {
    nominal_mm: [f64; 3],
    quat_wxyz: [f64; 4],
    moving: bool,
    /// Standstills so far: each draws a new repeatability error.
    visit: u64,
}

type SharedCell = Arc<Mutex<CellState>>;

impl Args {
    fn error_model(&self) -> RobotErrorModel {
        RobotErrorModel {
            repeatability_mm: self.repeatability_mm,
            field_rms_mm: self.abs_error_rms_mm,
            field_wavelength_mm: self.abs_error_wavelength_mm,
            orientation_rms_deg: self.abs_orientation_error_rms_deg,
            seed: self.error_seed,
        }
    }
}

/// Binds the cell feed and answers every `LED?` with the LED's actual position and every
/// `TOOL?` with the tool frame's actual pose (base frame).
fn spawn_cell_feed(args: &Args, listen: &str, cell: SharedCell) -> anyhow::Result<SocketAddr> {
    let model = args.error_model();
    model.validate().context("robot-sim error model")?;
    let offset = args.led_offset_mm;
    let mount = nalgebra::UnitQuaternion::from_scaled_axis(
        nalgebra::Vector3::from(args.tool_mount_rotation_deg).map(f64::to_radians),
    )
    .into_inner();
    let mount_wxyz = [mount.w, mount.i, mount.j, mount.k];
    let socket = UdpSocket::bind(listen).with_context(|| format!("--cell-feed {listen}: cannot bind"))?;
    let addr = socket.local_addr()?;
    std::thread::Builder::new()
        .name("cell-feed".into())
        .spawn(move || {
            let mut buf = [0u8; 64];
            loop {
                let Ok((n, from)) = socket.recv_from(&mut buf) else {
                    continue;
                };
                let tool = &buf[..n] == cell::FEED_TOOL_REQUEST;
                if !tool && &buf[..n] != cell::FEED_REQUEST {
                    continue;
                }
                let st = match cell.lock() {
                    Ok(g) => *g,
                    Err(p) => *p.into_inner(),
                };
                // While moving the robot follows its error fields; at rest it also has the
                // repeatability error of this standstill.
                let (flange, flange_wxyz) =
                    model.actual_pose(st.nominal_mm, st.quat_wxyz, (!st.moving).then_some(st.visit));
                let answer = if tool {
                    cell::encode_tool_answer(Some(cell::tool_pose(flange, flange_wxyz, offset, mount_wxyz)))
                } else {
                    cell::encode_feed_answer(Some(cell::led_position_mm(flange, flange_wxyz, offset)))
                };
                let _ = socket.send_to(answer.as_bytes(), from);
            }
        })
        .context("start the cell feed thread")?;
    Ok(addr)
}

fn parse_rsi_mode(s: &str) -> Result<RsiMode, String> {
    match s {
        "absolute" => Ok(RsiMode::Absolute),
        "relative" => Ok(RsiMode::Relative),
        _ => Err(format!("{s:?}: expected absolute or relative")),
    }
}

fn parse_xyz(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    <[f64; 3]>::try_from(v).map_err(|v| format!("need x,y,z, got {} values", v.len()))
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    if args.egm || args.rsi {
        return run_streaming(&args);
    }
    let listener =
        TcpListener::bind(&args.listen).with_context(|| format!("cannot listen on {}", args.listen))?;
    let addr = listener.local_addr()?;
    println!("robot-sim listening on {addr}");
    std::io::stdout().flush()?;
    serve(&args, listener)
}

struct Log {
    out: Option<BufWriter<std::fs::File>>,
    t0: Instant,
}

impl Log {
    fn row(
        &mut self,
        conn: u32,
        event: &str,
        seq: Option<u32>,
        target: Option<[f64; 3]>,
        pos: [f64; 3],
        detail: &str,
    ) {
        let Some(out) = self.out.as_mut() else { return };
        let seq = seq.map(|s| s.to_string()).unwrap_or_default();
        let t = target
            .map(|t| format!("{:.3},{:.3},{:.3}", t[0], t[1], t[2]))
            .unwrap_or_else(|| ",,".into());
        // A failing log write must not stop the simulated robot; it is reported once at exit.
        let _ = writeln!(
            out,
            "{:.4},{conn},{event},{seq},{t},{:.3},{:.3},{:.3},{detail}",
            self.t0.elapsed().as_secs_f64(),
            pos[0],
            pos[1],
            pos[2]
        );
    }
}

/// Serves connections one at a time on `listener`.
pub fn serve(args: &Args, listener: TcpListener) -> anyhow::Result<()> {
    if !(args.speed_mm_s.is_finite() && args.speed_mm_s > 0.0) {
        bail!("--speed-mm-s must be > 0");
    }
    if args.credits == 0 || args.credits > irtrack_core::robot_proto::MAX_WINDOW {
        bail!("--credits must be 1..=99");
    }
    let cfg = SimRobotConfig {
        name: args.name.clone(),
        speed_mm_s: args.speed_mm_s,
        window: args.credits,
        home_mm: args.home,
        reject_every: args.reject_every,
        beat_period_s: 0.2,
    };
    let out = match &args.log {
        Some(p) => {
            let mut w =
                BufWriter::new(std::fs::File::create(p).with_context(|| format!("create {}", p.display()))?);
            writeln!(
                w,
                "t_s,conn,event,seq,target_x_mm,target_y_mm,target_z_mm,robot_x_mm,robot_y_mm,robot_z_mm,detail"
            )?;
            Some(w)
        }
        None => None,
    };
    let mut log = Log {
        out,
        t0: Instant::now(),
    };
    // The log's t_s counts from here; CLOCK_MONOTONIC of that instant lets a benchmark line the
    // robot's path up with irtrackd's capture timestamps.
    // Not `println!`: a reader that stopped after the "listening" line must not end the robot.
    let mut stdout = std::io::stdout();
    let _ = writeln!(
        stdout,
        "robot-sim clock t0_mono_ns={}",
        irtrack_robot::monotonic_ns()
    );
    let _ = stdout.flush();
    let mut robot = SimRobot::new(cfg);
    let cell_state = Arc::new(Mutex::new(CellState {
        nominal_mm: robot.pos_mm(),
        quat_wxyz: robot.quat_wxyz(),
        moving: false,
        visit: 0,
    }));
    if let Some(listen) = &args.cell_feed {
        let addr = spawn_cell_feed(args, listen, cell_state.clone())?;
        let _ = writeln!(stdout, "robot-sim cell feed on {addr}");
        let _ = stdout.flush();
    }
    let mut conn = 0;
    loop {
        let (stream, peer) = listener.accept().context("accept")?;
        conn += 1;
        eprintln!("robot-sim: connection {conn} from {peer}");
        log.row(conn, "connected", None, None, robot.pos_mm(), &peer.to_string());
        let why = connection(args, &mut robot, stream, &mut log, conn, &cell_state);
        publish(&cell_state, &robot);
        robot.disconnect();
        eprintln!("robot-sim: connection {conn} ended: {why}");
        log.row(conn, "disconnected", None, None, robot.pos_mm(), &why);
        if let Some(out) = log.out.as_mut() {
            out.flush().context("write log")?;
        }
        if args.max_connections > 0 && conn >= args.max_connections {
            return Ok(());
        }
    }
}

fn send(stream: &mut TcpStream, msgs: &[RobotMsg]) -> std::io::Result<()> {
    for m in msgs {
        let line = m
            .encode()
            .map_err(|e| std::io::Error::new(ErrorKind::InvalidData, e.to_string()))?;
        stream.write_all(line.as_bytes())?;
    }
    Ok(())
}

/// One connection; returns why it ended.
/// Hands the robot's nominal pose to the cell feed; a new standstill draws a new repeatability error.
fn publish(cell: &SharedCell, robot: &SimRobot) {
    let mut st = match cell.lock() {
        Ok(g) => g,
        Err(p) => p.into_inner(),
    };
    let moving = robot.is_moving();
    if st.moving && !moving {
        st.visit += 1;
    }
    st.moving = moving;
    st.nominal_mm = robot.pos_mm();
    st.quat_wxyz = robot.quat_wxyz();
}

fn connection(
    args: &Args,
    robot: &mut SimRobot,
    stream: TcpStream,
    log: &mut Log,
    conn: u32,
    cell: &SharedCell,
) -> String {
    // How late the loop woke for its ticks (µs): the robot's own timing, printed for the
    // benchmark (docs/performance.md: the socket link's wait). A late tick delays the credit.
    let mut late_us: Vec<u64> = Vec::with_capacity(1 << 14);
    let why = connection_loop(args, robot, stream, log, conn, cell, &mut late_us);
    late_us.sort_unstable();
    let q = |f: f64| {
        late_us
            .get(((late_us.len() as f64 * f) as usize).min(late_us.len().saturating_sub(1)))
            .copied()
            .unwrap_or(0)
    };
    let mut out = std::io::stdout().lock();
    let _ = writeln!(
        out,
        "robot-sim summary socket conn={conn} ticks={} tick_late_p50_us={} tick_late_p99_us={} tick_late_max_us={} over_1ms={}",
        late_us.len(),
        q(0.5),
        q(0.99),
        late_us.last().copied().unwrap_or(0),
        late_us.iter().filter(|&&l| l > 1000).count()
    );
    let _ = out.flush();
    why
}

fn connection_loop(
    args: &Args,
    robot: &mut SimRobot,
    mut stream: TcpStream,
    log: &mut Log,
    conn: u32,
    cell: &SharedCell,
    late_us: &mut Vec<u64>,
) -> String {
    let _ = stream.set_nodelay(true);
    // Motion is advanced on a fixed tick (and on every line). The wait for the next line or tick
    // is poll(2) on a high-resolution timer: a socket read timeout (SO_RCVTIMEO) counts in kernel
    // ticks (4 ms at HZ=250) and woke this loop every 8-12 ms for a 4 ms tick, so the robot
    // answered up to three ticks late (docs/performance.md: the socket link's protocol wait).
    let tick = Duration::from_millis(args.tick_ms.max(1));
    let mut next_tick = Instant::now() + tick;
    if let Err(e) = send(&mut stream, &robot.connect()) {
        return format!("write: {e}");
    }
    let mut pending: Vec<u8> = Vec::with_capacity(4 * MAX_LINE_BYTES);
    let mut buf = [0u8; 512];
    let mut targets = 0u32;
    let mut last = Instant::now();
    let mut last_pos_log = Instant::now();
    let peer_timeout = Duration::from_secs(5);
    let mut last_rx = Instant::now();
    loop {
        let mut replies = Vec::new();
        let now = Instant::now();
        if now >= next_tick {
            late_us.push(now.duration_since(next_tick).as_micros() as u64);
            next_tick += tick;
            if next_tick <= now {
                // Fell behind by more than a tick (a stalled machine): start afresh from now.
                next_tick = now + tick;
            }
        }
        let got = if wait_readable(&stream, next_tick.saturating_duration_since(now)) {
            stream.read(&mut buf)
        } else {
            Err(ErrorKind::WouldBlock.into())
        };
        match got {
            Ok(0) => return "closed by the tracker".into(),
            Ok(n) => {
                last_rx = Instant::now();
                pending.extend_from_slice(&buf[..n]);
                while let Some(i) = pending.iter().position(|&b| b == b'\n') {
                    let line: Vec<u8> = pending.drain(..=i).collect();
                    let text = String::from_utf8_lossy(&line);
                    replies.extend(robot.on_line(&text));
                }
                if pending.len() > MAX_LINE_BYTES {
                    pending.clear();
                    replies.extend(robot.on_line("line too long"));
                }
            }
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(e) => return format!("read: {e}"),
        }
        if last_rx.elapsed() > peer_timeout {
            return "tracker silent for 5 s".into();
        }
        let dt = last.elapsed().as_secs_f64();
        last = Instant::now();
        replies.extend(robot.advance(dt));
        publish(cell, robot);
        for e in robot.take_events() {
            let pos = robot.pos_mm();
            match e {
                SimEvent::Target { seq, target_mm } => {
                    targets += 1;
                    log.row(conn, "target", Some(seq), Some(target_mm), pos, "");
                }
                SimEvent::Reached { seq } => log.row(conn, "reached", Some(seq), None, pos, ""),
                SimEvent::Rejected { seq, code } => {
                    log.row(conn, "rejected", Some(seq), None, pos, &format!("{code:02}"))
                }
                SimEvent::Hold { reason } => log.row(conn, "hold", None, None, pos, reason.text()),
                SimEvent::Malformed { reason } => {
                    log.row(conn, "malformed", None, None, pos, &reason.replace(',', ";"))
                }
            }
        }
        if last_pos_log.elapsed() >= Duration::from_millis(args.log_every_ms) {
            last_pos_log = Instant::now();
            log.row(conn, "pos", None, None, robot.pos_mm(), "");
        }
        if args.inject_delay_ms > 0 && replies.iter().any(|m| matches!(m, RobotMsg::Credit { .. })) {
            std::thread::sleep(Duration::from_millis(args.inject_delay_ms));
        }
        if let Err(e) = send(&mut stream, &replies) {
            return format!("write: {e}");
        }
        if replies.contains(&RobotMsg::Bye) {
            return "BYE".into();
        }
        if args.disconnect_after > 0 && targets >= args.disconnect_after {
            return format!("injected disconnect after {targets} targets");
        }
    }
}

/// Address helper for tests: binds `listen` and returns the listener and its address.
pub fn bind(listen: &str) -> anyhow::Result<(TcpListener, SocketAddr)> {
    let l = TcpListener::bind(listen).with_context(|| format!("cannot listen on {listen}"))?;
    let a = l.local_addr()?;
    Ok((l, a))
}

/// `--egm` / `--rsi`: one streaming session against irtrackd; prints a summary line at the end.
fn run_streaming(args: &Args) -> anyhow::Result<()> {
    let sensor = args
        .sensor
        .as_deref()
        .context("--egm/--rsi need --sensor HOST:PORT (irtrackd's [robot] address)")?;
    let sensor: SocketAddr = sensor
        .parse()
        .with_context(|| format!("--sensor {sensor:?} is not an ip:port"))?;
    if !(args.speed_mm_s.is_finite() && args.speed_mm_s > 0.0) {
        bail!("--speed-mm-s must be > 0");
    }
    if !(args.max_accel_mm_s2.is_finite() && args.max_accel_mm_s2 > 0.0) {
        bail!("--max-accel-mm-s2 must be > 0");
    }
    let kind = if args.egm {
        CtrlKind::Egm
    } else {
        CtrlKind::Rsi(args.rsi_mode)
    };
    let bind: SocketAddr = args
        .listen
        .parse()
        .with_context(|| format!("--listen {:?} is not an ip:port", args.listen))?;
    let log: Option<Box<dyn Write + Send>> = match &args.log {
        Some(p) => Some(Box::new(BufWriter::new(
            std::fs::File::create(p).with_context(|| format!("create {}", p.display()))?,
        ))),
        None => None,
    };
    let cfg = CtrlConfig {
        bind,
        cycle_ms: args.cycle_ms,
        home_mm: args.home,
        servo_lag_ms: args.servo_lag_ms,
        max_speed_mm_s: args.speed_mm_s,
        max_accel_mm_s2: args.max_accel_mm_s2,
        max_missed: args.max_missed,
        duration_s: args.duration_s,
        ..CtrlConfig::new(kind, sensor)
    };
    let ctrl = SimController::spawn(cfg, log)?;
    println!(
        "robot-sim {} controller on {} sending to {sensor} every {} ms",
        if args.egm { "EGM" } else { "RSI" },
        ctrl.local,
        args.cycle_ms
    );
    std::io::stdout().flush()?;
    while !ctrl.finished() {
        std::thread::sleep(Duration::from_millis(20));
    }
    let r = ctrl.stop();
    println!(
        "robot-sim summary cycles={} answered={} missed={} late={} malformed={} max_missed_run={} stopped={}",
        r.cycles,
        r.answered,
        r.missed,
        r.late,
        r.malformed,
        r.max_missed_run,
        r.stopped.as_deref().unwrap_or("no")
    );
    Ok(())
}
