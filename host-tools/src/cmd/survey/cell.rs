//! Cell I/O: the robot link (the survey is the protocol's client) and irtrackd's position
//! stream, and the drive through the plan that measures every point.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::time::{Duration, Instant};

use anyhow::{Context, bail, ensure};
use irtrack_core::robot_proto::{HoldReason, PROTOCOL_VERSION, RobotMsg, TrackerMsg, seq_next};
use irtrack_core::stream::{PositionRecord, ToolRecord, TrackStatus};
use irtrack_robot::safety::SafetyConfig;
use nalgebra::Vector3;

use super::Args;
use super::plan::{Planned, Role, split_move};
use super::safety::SafetyGate;

/// One visited point.
#[derive(Debug, Clone, PartialEq)]
pub struct Measured {
    /// Position in the plan (0-based).
    pub index: usize,
    /// What the point is for: fit, held out, or turned.
    pub role: Role,
    /// The flange position as the robot's controller reports it (`A` line), robot frame (mm).
    pub flange_mm: [f64; 3],
    /// The flange orientation (w, x, y, z) from the same report.
    pub flange_wxyz: [f64; 4],
    /// Mean tracked position (stream frame, mm).
    pub tracker_mm: [f64; 3],
    /// Per-axis standard deviation of the samples averaged into `tracker_mm` (mm).
    pub tracker_sd_mm: [f64; 3],
    /// With `--tool`: the tool's mean tracked orientation (w, x, y, z; tool → stream frame).
    pub tracker_wxyz: Option<[f64; 4]>,
    /// Tracker samples averaged into `tracker_mm`.
    pub frames: usize,
}

enum Ev {
    Robot(RobotMsg),
    Record(PositionRecord),
    End(String),
}

fn reader<T: Send + 'static>(
    stream: TcpStream,
    tx: Sender<Ev>,
    what: &'static str,
    parse: impl Fn(&str) -> Result<T, String> + Send + 'static,
    wrap: fn(T) -> Ev,
) {
    std::thread::spawn(move || {
        for line in BufReader::new(stream).lines() {
            let ev = match line {
                Ok(l) => match parse(&l) {
                    Ok(v) => wrap(v),
                    Err(e) => Ev::End(format!("{what}: {e} in {l:?}")),
                },
                Err(e) => Ev::End(format!("{what}: {e}")),
            };
            let end = matches!(ev, Ev::End(_));
            if tx.send(ev).is_err() || end {
                return;
            }
        }
        let _ = tx.send(Ev::End(format!("{what} closed the connection")));
    });
}

/// Reads per-tool records (the client asked with `tools`) and passes on those of `tool`; when a
/// whole set's tools went by without it, the connection ends naming the set's tools.
fn tool_reader(stream: TcpStream, tx: Sender<Ev>, tool: String) {
    std::thread::spawn(move || {
        let mut seen: Vec<String> = Vec::new();
        for line in BufReader::new(stream).lines() {
            let line = match line {
                Ok(l) => l,
                Err(e) => {
                    let _ = tx.send(Ev::End(format!("stream: {e}")));
                    return;
                }
            };
            // The main record comes too; only the per-tool ones carry `tool_id`.
            if !line.contains("\"tool_id\"") {
                continue;
            }
            let r = match ToolRecord::from_ndjson_line(&line) {
                Ok(r) => r,
                Err(e) => {
                    let _ = tx.send(Ev::End(format!("stream: {e} in {line:?}")));
                    return;
                }
            };
            if r.name() == tool {
                if tx.send(Ev::Record(r.record)).is_err() {
                    return;
                }
                continue;
            }
            if !seen.iter().any(|n| n == r.name()) {
                seen.push(r.name().to_string());
            }
            if seen.len() >= usize::from(r.tool_count) {
                let _ = tx.send(Ev::End(format!(
                    "irtrackd's parameter set has no tool {tool:?} (its tools: {})",
                    seen.join(", ")
                )));
                return;
            }
        }
        let _ = tx.send(Ev::End("stream closed the connection".to_string()));
    });
}

/// The robot link as its client plus the position stream.
struct Cell {
    robot: TcpStream,
    rx: Receiver<Ev>,
    seq: u32,
    beat: u32,
    last_sent: Instant,
    pose_counter: u32,
    robot_name: String,
}

const BEAT_EVERY: Duration = Duration::from_millis(200);

impl Cell {
    fn connect(robot: &str, stream: &str, tool: Option<&str>) -> anyhow::Result<Self> {
        let (tx, rx) = channel();
        let r =
            TcpStream::connect(robot).with_context(|| format!("cannot connect to the robot at {robot}"))?;
        r.set_nodelay(true)?;
        let s = TcpStream::connect(stream)
            .with_context(|| format!("cannot connect to irtrackd's stream at {stream}"))?;
        reader(
            r.try_clone()?,
            tx.clone(),
            "robot",
            |l| RobotMsg::parse(l).map_err(|e| e.to_string()),
            Ev::Robot,
        );
        match tool {
            Some(name) => {
                // Ask for a record per tool (docs/stream-protocol.md).
                (&s).write_all(b"tools\n")
                    .context("ask irtrackd's stream for per-tool records")?;
                tool_reader(s, tx, name.to_string());
            }
            None => reader(
                s,
                tx,
                "stream",
                |l| PositionRecord::from_ndjson_line(l).map_err(|e| e.to_string()),
                Ev::Record,
            ),
        }
        let mut cell = Cell {
            robot: r,
            rx,
            seq: 0,
            beat: 0,
            last_sent: Instant::now(),
            pose_counter: 0,
            robot_name: String::new(),
        };
        cell.send(&TrackerMsg::Hello {
            version: PROTOCOL_VERSION,
            name: "host-tools-survey".into(),
        })?;
        let deadline = Instant::now() + Duration::from_secs(10);
        let what = "the robot's HELLO (the controller serves one client: is irtrackd's [robot] link connected to it?)";
        let name = cell.wait(deadline, what, |m| match m {
            RobotMsg::Hello { version, name } => Some(Ok((*version, name.clone()))),
            _ => None,
        })?;
        ensure!(
            name.0 == PROTOCOL_VERSION,
            "robot speaks protocol version {}, this tool {PROTOCOL_VERSION}",
            name.0
        );
        cell.robot_name = name.1;
        cell.wait(deadline, "the robot's ready credit", |m| match m {
            RobotMsg::Credit { ack_seq: 0, .. } => Some(Ok(())),
            _ => None,
        })?;
        Ok(cell)
    }

    fn send(&mut self, m: &TrackerMsg) -> anyhow::Result<()> {
        let line = m.encode().context("encode a robot line")?;
        self.robot
            .write_all(line.as_bytes())
            .context("write to the robot")?;
        self.last_sent = Instant::now();
        Ok(())
    }

    fn beat_if_idle(&mut self) -> anyhow::Result<()> {
        if self.last_sent.elapsed() >= BEAT_EVERY {
            self.beat = seq_next(self.beat);
            self.send(&TrackerMsg::Beat { counter: self.beat })?;
        }
        Ok(())
    }

    /// Waits for a robot line `f` accepts; stream records are dropped meanwhile.
    fn wait<T>(
        &mut self,
        deadline: Instant,
        what: &str,
        mut f: impl FnMut(&RobotMsg) -> Option<anyhow::Result<T>>,
    ) -> anyhow::Result<T> {
        loop {
            self.beat_if_idle()?;
            let left = deadline.saturating_duration_since(Instant::now());
            ensure!(!left.is_zero(), "timed out waiting for {what}");
            match self.rx.recv_timeout(left.min(Duration::from_millis(50))) {
                Ok(Ev::Robot(m)) => {
                    if let Some(r) = f(&m) {
                        return r;
                    }
                }
                Ok(Ev::Record(_)) => {}
                Ok(Ev::End(why)) => bail!("{why} while waiting for {what}"),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => bail!("links closed while waiting for {what}"),
            }
        }
    }

    /// Sends one target and waits until the robot reports it reached (fine point).
    fn move_to(&mut self, pos_mm: [f64; 3], quat_wxyz: [f64; 4], deadline: Instant) -> anyhow::Result<()> {
        self.seq = seq_next(self.seq);
        let seq = self.seq;
        self.send(&TrackerMsg::Pose {
            seq,
            pos_mm,
            quat_wxyz,
        })?;
        self.wait(
            deadline,
            &format!("the robot to reach target {seq}"),
            |m| match m {
                RobotMsg::Credit { ack_seq, .. } if *ack_seq == seq => Some(Ok(())),
                RobotMsg::Reject { seq: s, code, reason } if *s == seq => Some(Err(anyhow::anyhow!(
                    "the robot rejected target {seq} at [{:.2}, {:.2}, {:.2}] mm: {code:02} {reason}",
                    pos_mm[0],
                    pos_mm[1],
                    pos_mm[2]
                ))),
                _ => None,
            },
        )
    }

    fn pose(&mut self, deadline: Instant) -> anyhow::Result<([f64; 3], [f64; 4])> {
        self.pose_counter = seq_next(self.pose_counter);
        let counter = self.pose_counter;
        self.send(&TrackerMsg::PoseRequest { counter })?;
        self.wait(deadline, "the robot's pose (A line)", |m| match m {
            RobotMsg::Actual {
                counter: c,
                pos_mm,
                quat_wxyz,
            } if *c == counter => Some(Ok((*pos_mm, *quat_wxyz))),
            _ => None,
        })
    }

    /// Drops everything until `until`, then collects `frames` tracked positions (with the
    /// orientation when the record has one).
    fn average(
        &mut self,
        until: Instant,
        frames: usize,
        deadline: Instant,
    ) -> anyhow::Result<(Vec<Sample>, bool)> {
        let mut got = Vec::with_capacity(frames);
        let mut world = false;
        loop {
            self.beat_if_idle()?;
            let now = Instant::now();
            if now >= deadline {
                return Ok((got, world));
            }
            match self
                .rx
                .recv_timeout((deadline - now).min(Duration::from_millis(50)))
            {
                Ok(Ev::Record(r)) if Instant::now() >= until => {
                    if r.status == TrackStatus::Ok
                        && let Some(p) = r.position_mm
                    {
                        world = r.world_frame;
                        got.push((p, r.orientation_wxyz));
                        if got.len() >= frames {
                            return Ok((got, world));
                        }
                    }
                }
                Ok(Ev::Record(_)) | Ok(Ev::Robot(RobotMsg::Beat { .. })) => {}
                Ok(Ev::Robot(m)) => bail!("unexpected robot line while averaging: {m:?}"),
                Ok(Ev::End(why)) => bail!("{why} while averaging"),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => bail!("links closed while averaging"),
            }
        }
    }

    fn close(&mut self) {
        let _ = self.send(&TrackerMsg::Hold {
            reason: HoldReason::Stop,
        });
        let _ = self.send(&TrackerMsg::Bye);
    }
}

/// One tracked sample: position and, for a tool, orientation (w, x, y, z).
type Sample = ([f64; 3], Option<[f64; 4]>);

/// Mean of nearby unit quaternions: each turned to the first one's hemisphere, summed and
/// normalised (the samples of a standstill differ by hundredths of a degree).
fn mean_quat(v: &[[f64; 4]]) -> Option<[f64; 4]> {
    let first = nalgebra::Vector4::from(*v.first()?);
    let sum = v.iter().fold(nalgebra::Vector4::zeros(), |acc, q| {
        let q = nalgebra::Vector4::from(*q);
        if q.dot(&first) < 0.0 { acc - q } else { acc + q }
    });
    let n = sum.norm();
    (n > 0.0).then(|| [sum[0] / n, sum[1] / n, sum[2] / n, sum[3] / n])
}

fn mean_sd(v: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let n = v.len().max(1) as f64;
    let mut m = [0.0; 3];
    for p in v {
        for k in 0..3 {
            m[k] += p[k] / n;
        }
    }
    let mut sd = [0.0; 3];
    for p in v {
        for k in 0..3 {
            sd[k] += (p[k] - m[k]).powi(2) / (n - 1.0).max(1.0);
        }
    }
    (m, sd.map(f64::sqrt))
}

/// Moves are split this far below the step limits (floating-point headroom for the supervisor).
const SPLIT_MARGIN: f64 = 0.999;

/// Drives the robot through the plan and measures every point.
pub(super) fn measure(
    args: &Args,
    plan: &[Planned],
    safety: &SafetyConfig,
) -> anyhow::Result<(Vec<Measured>, bool, Vec<String>)> {
    let mut cell = Cell::connect(&args.robot, &args.stream, args.tool.as_deref())?;
    println!(
        "survey: robot {:?} connected; {} points",
        cell.robot_name,
        plan.len()
    );
    let result = (|| {
        // Start from where the robot stands.
        let t0 = Instant::now() + Duration::from_secs(10);
        let mut at = cell.pose(t0)?;
        let mut gate = SafetyGate::new(safety.clone(), at.0);
        let (lo, hi) = (args.box_min, args.box_max);
        let mut out = Vec::new();
        let mut skipped = Vec::new();
        let mut world = None;
        for (i, p) in plan.iter().enumerate() {
            let deadline = Instant::now() + Duration::from_secs_f64(args.point_timeout_s);
            let start_inside = (0..3).all(|k| at.0[k] >= lo[k] - 1e-6 && at.0[k] <= hi[k] + 1e-6);
            // A hair below the limits: a move that is an exact multiple of them (a half turn in
            // 10° steps) would otherwise exceed the supervisor's limit by rounding.
            for (pos, q) in split_move(
                at,
                (p.pos_mm, p.quat_wxyz),
                args.max_step_mm * SPLIT_MARGIN,
                args.max_rotation_step_deg * SPLIT_MARGIN,
            ) {
                // The robot may start outside the box; from its first target on it stays inside.
                let inside = (0..3).all(|k| pos[k] >= lo[k] - 1e-6 && pos[k] <= hi[k] + 1e-6);
                ensure!(
                    inside || !start_inside,
                    "target [{:.2}, {:.2}, {:.2}] mm leaves the survey box",
                    pos[0],
                    pos[1],
                    pos[2]
                );
                gate.check(pos, q)?;
                cell.move_to(pos, q, deadline)?;
            }
            let settle = Instant::now() + Duration::from_millis(args.settle_ms);
            let (samples, w) = cell.average(settle, args.frames, deadline)?;
            // The point's time may be used up by a marker that was not seen: the robot's pose
            // still gets its own few seconds, and the point is skipped below, naming why.
            let pose = cell.pose(deadline.max(Instant::now() + Duration::from_secs(5)))?;
            gate.on_robot_position(pose.0);
            at = (p.pos_mm, p.quat_wxyz);
            if samples.len() < args.frames {
                let why = format!(
                    "point {i} at [{:.1}, {:.1}, {:.1}] mm: {} tracked in {} of {} frames before the point's time ran out",
                    p.pos_mm[0],
                    p.pos_mm[1],
                    p.pos_mm[2],
                    args.tool
                        .as_deref()
                        .map_or("marker".to_string(), |t| format!("tool {t:?}")),
                    samples.len(),
                    args.frames
                );
                println!("survey: skipped {why}");
                skipped.push(why);
                continue;
            }
            ensure!(
                world.is_none_or(|x| x == w),
                "the stream switched between camera and world frame during the survey (a parameter push?)"
            );
            world = Some(w);
            let positions: Vec<[f64; 3]> = samples.iter().map(|s| s.0).collect();
            let (m, sd) = mean_sd(&positions);
            let tracker_wxyz = if args.tool.is_some() {
                let quats: Vec<[f64; 4]> = samples.iter().filter_map(|s| s.1).collect();
                ensure!(
                    quats.len() == samples.len(),
                    "point {i}: tool {:?} tracked without an orientation in {} of {} frames",
                    args.tool.as_deref().unwrap_or(""),
                    samples.len() - quats.len(),
                    samples.len()
                );
                mean_quat(&quats)
            } else {
                None
            };
            println!(
                "survey: point {:>3}/{} {:<7} robot [{:8.2} {:8.2} {:8.2}] tracker [{:8.2} {:8.2} {:8.2}] sd {:.3} mm",
                i + 1,
                plan.len(),
                p.role.name(),
                pose.0[0],
                pose.0[1],
                pose.0[2],
                m[0],
                m[1],
                m[2],
                Vector3::from(sd).norm()
            );
            out.push(Measured {
                index: i,
                role: p.role,
                flange_mm: pose.0,
                flange_wxyz: pose.1,
                tracker_mm: m,
                tracker_sd_mm: sd,
                tracker_wxyz,
                frames: samples.len(),
            });
        }
        Ok((out, world.unwrap_or(false), skipped))
    })();
    cell.close();
    result
}
