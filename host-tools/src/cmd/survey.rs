//! `host-tools survey`: the cell survey with the robot (docs/teach-in.md, step 0).
//!
//! With the LED fixed to the robot's flange, the robot is driven through a grid of points
//! inside a box the user gives, over the robot protocol (`host-tools` is the link's client, as
//! irtrackd is in live following). Every target is checked before it is sent (inside the box,
//! steps no longer than `--max-step-mm`, rotation steps no larger than
//! `--max-rotation-step-deg`; longer moves are split) and every point is a standstill: after the
//! robot acknowledges it and `--settle-ms` passed, `--frames` tracked positions from irtrackd's
//! stream are averaged and the robot is asked for its pose (`POSE` → `A`, RAPID `CRobT`).
//!
//! The survey runs under the installation's safety limits: `--safety` names the board's
//! `irtrackd.toml`, whose `[robot.safety]` section governs it as it governs live following. The
//! survey box must lie inside the configured workspace (refused before anything moves), moves are
//! split to no more than the configured `max_step_mm` / `max_rotation_step_deg` (the smaller of
//! those and the CLI values), and every target passes irtrackd's own safety `Supervisor` before it
//! is sent; a `Hold` stops the survey at once, the robot stays where it is and the report says why.
//!
//! Then: a rigid registration (Kabsch) of the tracker positions onto the robot's on the fit
//! points, the Umeyama scale reported and checked against `--max-scale-error-ppm` (never
//! fitted), the target registration error (TRE) on the held-out points, per axis, the error
//! against the distance from the cameras (the paper's Fig. 11) and, when some points were
//! visited with the flange turned and the LED's offset on the flange is not given, that offset
//! solved jointly with the registration. The report (Markdown, CSV, PNG) ends in PASS or FAIL
//! against `--tolerance-mm`; with `--params`/`--out` the registration is written into the
//! parameter set (`world_from_cam0`) so that irtrackd streams robot-base coordinates.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::time::{Duration, Instant};

use anyhow::{Context, bail, ensure};
use irtrack_core::camera::RigidTransform;
use irtrack_core::registration;
use irtrack_core::robot_proto::{HoldReason, PROTOCOL_VERSION, RobotMsg, TrackerMsg, seq_next};
use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_firmware::robot::safety::{SafetyConfig, Sample, Supervisor, Verdict};
use nalgebra::{Matrix3, Matrix6, Quaternion, UnitQuaternion, Vector3, Vector6};

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// irtrackd's position stream (NDJSON), `host:port` (port 7702 on the board).
    #[arg(long)]
    pub stream: String,
    /// The robot controller's link (RAPID `IrTrack` in survey mode, or robot-sim), `host:port`.
    #[arg(long)]
    pub robot: String,
    /// Survey box, robot base frame: min corner `x,y,z` mm.
    #[arg(long, value_parser = parse_v3)]
    pub box_min: [f64; 3],
    /// Survey box: max corner `x,y,z` mm.
    #[arg(long, value_parser = parse_v3)]
    pub box_max: [f64; 3],
    /// The board's irtrackd config (`irtrackd.toml`, the same file the board uses): its
    /// `[robot.safety]` limits govern the survey. The box must lie inside the workspace, steps and
    /// turns are split to the configured limits, and every target passes the safety supervisor
    /// before it is sent (a hold stops the survey). Required: a survey never drives a robot
    /// without the installation's limits.
    #[arg(long)]
    pub safety: PathBuf,
    /// Grid points per axis `nx,ny,nz` (N = nx·ny·nz).
    #[arg(long, default_value = "3,3,3", value_parser = parse_grid)]
    pub grid: [usize; 3],
    /// Tracked frames averaged per point.
    #[arg(long, default_value_t = 20)]
    pub frames: usize,
    /// Wait after the robot reports a point reached before averaging (vibrations, stream lag).
    #[arg(long, default_value_t = 300)]
    pub settle_ms: u64,
    /// Every K-th grid point is held out of the fit and measures the TRE.
    #[arg(long, default_value_t = 3)]
    pub holdout_every: usize,
    /// Flange orientation at the grid points, quaternion `w,x,y,z` (robot base frame).
    #[arg(long, default_value = "0,0,1,0", value_parser = parse_quat)]
    pub orient: [f64; 4],
    /// Extra visits with the flange turned (about its x, y, z axes in turn), for the LED offset.
    #[arg(long, default_value_t = 0)]
    pub rotations: usize,
    /// Turn of those visits.
    #[arg(long, default_value_t = 25.0)]
    pub rotation_deg: f64,
    /// The LED's position in the flange (TCP) frame, `x,y,z` mm, when known; otherwise it is
    /// solved from the turned visits (or taken as 0 — LED at the TCP — without them).
    #[arg(long, value_parser = parse_v3)]
    pub led_offset_mm: Option<[f64; 3]>,
    /// Longest step between consecutive targets; longer moves are split (never longer than
    /// `[robot.safety] max_step_mm`).
    #[arg(long, default_value_t = 50.0)]
    pub max_step_mm: f64,
    /// Largest rotation between consecutive targets; larger turns are split (never larger than
    /// `[robot.safety] max_rotation_step_deg`).
    #[arg(long, default_value_t = 10.0)]
    pub max_rotation_step_deg: f64,
    /// Pass when the largest held-out error (TRE max) is at most this.
    #[arg(long, default_value_t = 1.0)]
    pub tolerance_mm: f64,
    /// Fail when the Umeyama scale differs from 1 by more than this (a calibration/units check).
    #[arg(long, default_value_t = 2000.0)]
    pub max_scale_error_ppm: f64,
    /// Time allowed per point (move, settle, frames).
    #[arg(long, default_value_t = 30.0)]
    pub point_timeout_s: f64,
    /// Parameter set (blob or YAML) the positions were tracked with; needed for `--out` and
    /// when the stream is already in a (previous) world frame.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Write the parameter set with the new registration here (then sign and push it).
    #[arg(long, requires = "params")]
    pub out: Option<PathBuf>,
    /// Report directory: survey.md, survey.csv, error-vs-distance.png.
    #[arg(long)]
    pub report: PathBuf,
}

fn parse_v3(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let a = <[f64; 3]>::try_from(v).map_err(|v| format!("need x,y,z, got {} values", v.len()))?;
    if a.iter().all(|x| x.is_finite()) {
        Ok(a)
    } else {
        Err("values must be finite".into())
    }
}

fn parse_quat(s: &str) -> Result<[f64; 4], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let q = <[f64; 4]>::try_from(v).map_err(|v| format!("need w,x,y,z, got {} values", v.len()))?;
    let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    if !(n > 0.99 && n < 1.01) {
        return Err(format!("quaternion norm {n} is not 1"));
    }
    Ok(q)
}

fn parse_grid(s: &str) -> Result<[usize; 3], String> {
    let v: Vec<usize> = s
        .split(',')
        .map(|p| p.trim().parse::<usize>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let g = <[usize; 3]>::try_from(v).map_err(|v| format!("need nx,ny,nz, got {} values", v.len()))?;
    if g.iter().any(|&n| n == 0 || n > 20) {
        return Err("each of nx,ny,nz must be 1..=20".into());
    }
    Ok(g)
}

fn quat(q: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
}

fn wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    // w ≥ 0: one sign for the same rotation on the wire.
    let q = if q.w < 0.0 {
        -q.into_inner()
    } else {
        q.into_inner()
    };
    [q.w, q.i, q.j, q.k]
}

/// Role of a survey point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Used in the registration fit.
    Fit,
    /// Held out: measures the target registration error.
    Holdout,
    /// Fit point visited with the flange turned (carries the LED offset).
    Turned,
}

impl Role {
    fn name(self) -> &'static str {
        match self {
            Role::Fit => "fit",
            Role::Holdout => "holdout",
            Role::Turned => "turned",
        }
    }
}

/// A planned survey pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Planned {
    pub role: Role,
    pub pos_mm: [f64; 3],
    pub quat_wxyz: [f64; 4],
}

/// The survey poses: a serpentine grid in the box (every `holdout_every`-th held out), then
/// `rotations` turned visits spread over the grid.
pub fn plan(args: &Args) -> anyhow::Result<Vec<Planned>> {
    for i in 0..3 {
        ensure!(
            args.box_min[i] < args.box_max[i],
            "--box-min must be below --box-max on every axis (axis {i}: {} >= {})",
            args.box_min[i],
            args.box_max[i]
        );
    }
    ensure!(args.holdout_every >= 2, "--holdout-every must be at least 2");
    let coord = |axis: usize, k: usize| {
        let n = args.grid[axis];
        if n == 1 {
            0.5 * (args.box_min[axis] + args.box_max[axis])
        } else {
            args.box_min[axis] + (args.box_max[axis] - args.box_min[axis]) * k as f64 / (n - 1) as f64
        }
    };
    let [nx, ny, nz] = args.grid;
    let mut grid = Vec::with_capacity(nx * ny * nz);
    for iz in 0..nz {
        for jy in 0..ny {
            let iy = if iz % 2 == 0 { jy } else { ny - 1 - jy };
            for jx in 0..nx {
                let ix = if (iz * ny + jy) % 2 == 0 { jx } else { nx - 1 - jx };
                grid.push([coord(0, ix), coord(1, iy), coord(2, iz)]);
            }
        }
    }
    let mut out: Vec<Planned> = grid
        .iter()
        .enumerate()
        .map(|(i, p)| Planned {
            role: if i % args.holdout_every == args.holdout_every / 2 {
                Role::Holdout
            } else {
                Role::Fit
            },
            pos_mm: *p,
            quat_wxyz: args.orient,
        })
        .collect();
    let fit = out.iter().filter(|p| p.role == Role::Fit).count();
    ensure!(
        fit >= 4 && out.len() > fit,
        "a grid of {} points with --holdout-every {} leaves {fit} fit and {} held-out points; need at least 4 and 1",
        out.len(),
        args.holdout_every,
        out.len() - fit
    );
    let base = quat(args.orient);
    for k in 0..args.rotations {
        let axis = [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()][k % 3];
        let sign = if (k / 3) % 2 == 0 { 1.0 } else { -1.0 };
        let turn = UnitQuaternion::from_axis_angle(&axis, sign * args.rotation_deg.to_radians());
        // Spread over the grid, in the same serpentine order.
        let at = grid[(k * grid.len()) / args.rotations.max(1) % grid.len()];
        out.push(Planned {
            role: Role::Turned,
            pos_mm: at,
            quat_wxyz: wxyz(&(base * turn)),
        });
    }
    Ok(out)
}

/// Intermediate targets from `from` to `to` so that no step exceeds the limits (the last is `to`).
pub fn split_move(
    from: ([f64; 3], [f64; 4]),
    to: ([f64; 3], [f64; 4]),
    max_step_mm: f64,
    max_rot_deg: f64,
) -> Vec<([f64; 3], [f64; 4])> {
    let (p0, p1) = (Vector3::from(from.0), Vector3::from(to.0));
    let (q0, q1) = (quat(from.1), quat(to.1));
    let dist = (p1 - p0).norm();
    let angle = q0.angle_to(&q1).to_degrees();
    let n = ((dist / max_step_mm).ceil().max((angle / max_rot_deg).ceil()) as usize).max(1);
    (1..=n)
        .map(|k| {
            let f = k as f64 / n as f64;
            let p = p0 + (p1 - p0) * f;
            let q = q0.try_slerp(&q1, f, 1e-9).unwrap_or(q1);
            ([p.x, p.y, p.z], if k == n { to.1 } else { wxyz(&q) })
        })
        .collect()
}

/// One visited point.
#[derive(Debug, Clone, PartialEq)]
pub struct Measured {
    pub index: usize,
    pub role: Role,
    /// The robot's pose as its controller reports it (`A` line).
    pub flange_mm: [f64; 3],
    pub flange_wxyz: [f64; 4],
    /// Mean tracked position (stream frame) and the per-axis standard deviation of the mean's samples.
    pub tracker_mm: [f64; 3],
    pub tracker_sd_mm: [f64; 3],
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
    fn connect(robot: &str, stream: &str) -> anyhow::Result<Self> {
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
        reader(
            s,
            tx,
            "stream",
            |l| PositionRecord::from_ndjson_line(l).map_err(|e| e.to_string()),
            Ev::Record,
        );
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

    /// Drops everything until `until`, then averages `frames` tracked positions.
    fn average(
        &mut self,
        until: Instant,
        frames: usize,
        deadline: Instant,
    ) -> anyhow::Result<(Vec<[f64; 3]>, bool)> {
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
                        got.push(p);
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

/// Results of the analysis.
#[derive(Debug, Clone)]
pub struct Analysis {
    /// `robot_from_tracker` fitted on the fit (and turned) points.
    pub fit: RigidTransform,
    /// The same fitted on every point (what gets written).
    pub all: RigidTransform,
    /// Umeyama scale on the fit points.
    pub scale: f64,
    /// LED offset in the flange frame, and whether it was solved.
    pub led_offset_mm: [f64; 3],
    pub offset_solved: bool,
    /// Residual vectors (robot frame: registered tracker − robot) per point, in `points` order.
    pub residual_mm: Vec<[f64; 3]>,
}

/// Error statistics of a set of residual vectors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stats {
    pub n: usize,
    pub rms_mm: f64,
    pub max_mm: f64,
    pub axis_rms_mm: [f64; 3],
    pub axis_max_mm: [f64; 3],
}

/// RMS and max of the 3-D errors and per axis.
pub fn stats(res: &[[f64; 3]]) -> Stats {
    let n = res.len();
    let nf = n.max(1) as f64;
    let mut s = Stats {
        n,
        rms_mm: 0.0,
        max_mm: 0.0,
        axis_rms_mm: [0.0; 3],
        axis_max_mm: [0.0; 3],
    };
    for r in res {
        let e = Vector3::from(*r).norm();
        s.rms_mm += e * e / nf;
        s.max_mm = s.max_mm.max(e);
        for (k, v) in r.iter().enumerate() {
            s.axis_rms_mm[k] += v * v / nf;
            s.axis_max_mm[k] = s.axis_max_mm[k].max(v.abs());
        }
    }
    s.rms_mm = s.rms_mm.sqrt();
    s.axis_rms_mm = s.axis_rms_mm.map(f64::sqrt);
    s
}

fn robot_points(points: &[Measured], offset: &Vector3<f64>) -> Vec<[f64; 3]> {
    points
        .iter()
        .map(|m| {
            let p = Vector3::from(m.flange_mm) + quat(m.flange_wxyz) * offset;
            [p.x, p.y, p.z]
        })
        .collect()
}

/// The LED offset given the registration: least squares of `R p + t = f + F o` in `(o, t)`.
fn solve_offset(points: &[Measured], r: &Matrix3<f64>) -> anyhow::Result<(Vector3<f64>, f64)> {
    let mut ata = Matrix6::<f64>::zeros();
    let mut atb = Vector6::<f64>::zeros();
    for m in points {
        // Row block: [F  -I] [o; t] = R p − f
        let f = quat(m.flange_wxyz).to_rotation_matrix().into_inner();
        let mut a = nalgebra::Matrix3x6::<f64>::zeros();
        a.fixed_view_mut::<3, 3>(0, 0).copy_from(&f);
        a.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-Matrix3::identity()));
        let b = r * Vector3::from(m.tracker_mm) - Vector3::from(m.flange_mm);
        ata += a.transpose() * a;
        atb += a.transpose() * b;
    }
    let eig = ata.symmetric_eigen();
    let (lo, hi) = eig
        .eigenvalues
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
    let x = ata
        .cholesky()
        .map(|c| c.solve(&atb))
        .context("LED offset: normal equations singular")?;
    Ok((Vector3::new(x[0], x[1], x[2]), lo / hi.max(1e-300)))
}

/// Registration (and LED offset) from the fit and turned points; residuals of every point.
pub fn analyse(points: &[Measured], led_offset_mm: Option<[f64; 3]>) -> anyhow::Result<Analysis> {
    let fit_pts: Vec<Measured> = points
        .iter()
        .filter(|m| m.role != Role::Holdout)
        .cloned()
        .collect();
    ensure!(
        fit_pts.len() >= 4,
        "only {} fit points measured; need 4",
        fit_pts.len()
    );
    let turned = fit_pts.iter().filter(|m| m.role == Role::Turned).count();
    let tracker_fit: Vec<[f64; 3]> = fit_pts.iter().map(|m| m.tracker_mm).collect();
    let (offset, solved) = match led_offset_mm {
        Some(o) => (Vector3::from(o), false),
        None if turned >= 2 => {
            // Alternate: rigid fit for a given offset, offset (and translation) for a given fit.
            let mut o = Vector3::zeros();
            let mut converged = false;
            for _ in 0..200 {
                let reg = registration::fit(&tracker_fit, &robot_points(&fit_pts, &o), false)
                    .context("registration (LED offset solve)")?;
                let (o_new, cond) = solve_offset(&fit_pts, &reg.transform.rotation())?;
                ensure!(
                    cond > 1e-6,
                    "the LED offset is not observable from these turns (condition {cond:.1e}): turn the flange about at least two axes (--rotations 3 or more)"
                );
                let step = (o_new - o).norm();
                o = o_new;
                if step < 1e-5 {
                    converged = true;
                    break;
                }
            }
            ensure!(converged, "the LED offset solve did not converge");
            (o, true)
        }
        None => (Vector3::zeros(), false),
    };
    let robot_fit = robot_points(&fit_pts, &offset);
    let fit = registration::fit(&tracker_fit, &robot_fit, false).context("registration on the fit points")?;
    let scaled = registration::fit(&tracker_fit, &robot_fit, true).context("scale check")?;
    let tracker_all: Vec<[f64; 3]> = points.iter().map(|m| m.tracker_mm).collect();
    let robot_all = robot_points(points, &offset);
    let all = registration::fit(&tracker_all, &robot_all, false).context("registration on all points")?;
    let residual_mm = tracker_all
        .iter()
        .zip(&robot_all)
        .map(|(p, q)| {
            let e = fit.transform.apply(&Vector3::from(*p)) - Vector3::from(*q);
            [e.x, e.y, e.z]
        })
        .collect();
    Ok(Analysis {
        fit: fit.transform,
        all: all.transform,
        scale: scaled.scale,
        led_offset_mm: [offset.x, offset.y, offset.z],
        offset_solved: solved,
        residual_mm,
    })
}

/// Reads the `[robot.safety]` limits from the board's irtrackd config.
pub fn load_safety(path: &Path) -> anyhow::Result<SafetyConfig> {
    let cfg = irtrack_firmware::config::Config::load(path)
        .with_context(|| format!("--safety {}: cannot load the irtrackd config", path.display()))?;
    let robot = cfg.robot.with_context(|| {
        format!(
            "--safety {}: the file has no [robot.safety] section (the survey runs only under the \
             installation's safety limits: give the board's irtrackd.toml)",
            path.display()
        )
    })?;
    robot
        .safety
        .validate()
        .map_err(|e| anyhow::anyhow!("--safety {}: {e}", path.display()))?;
    Ok(robot.safety)
}

/// Applies the safety limits to the arguments before anything moves: the survey box must lie
/// inside the workspace, and the step and rotation limits become the smaller of the CLI's and the
/// configured ones. Returns what was tightened, for the log.
pub fn apply_safety(args: &mut Args, cfg: &SafetyConfig) -> anyhow::Result<Vec<String>> {
    const AXES: [&str; 3] = ["x", "y", "z"];
    for (i, axis) in AXES.iter().enumerate() {
        ensure!(
            args.box_min[i] >= cfg.workspace_min_mm[i] && args.box_max[i] <= cfg.workspace_max_mm[i],
            "the survey box leaves the [robot.safety] workspace on axis {}: box {}..{} mm, \
             workspace {}..{} mm; nothing was moved",
            axis,
            args.box_min[i],
            args.box_max[i],
            cfg.workspace_min_mm[i],
            cfg.workspace_max_mm[i]
        );
    }
    let mut notes = Vec::new();
    if cfg.max_step_mm < args.max_step_mm {
        notes.push(format!(
            "step limit {} mm ([robot.safety] max_step_mm) instead of --max-step-mm {}",
            cfg.max_step_mm, args.max_step_mm
        ));
        args.max_step_mm = cfg.max_step_mm;
    }
    if cfg.max_rotation_step_deg < args.max_rotation_step_deg {
        notes.push(format!(
            "rotation step limit {}° ([robot.safety] max_rotation_step_deg) instead of \
             --max-rotation-step-deg {}",
            cfg.max_rotation_step_deg, args.max_rotation_step_deg
        ));
        args.max_rotation_step_deg = cfg.max_rotation_step_deg;
    }
    Ok(notes)
}

/// irtrackd's safety supervisor in front of the survey's robot link: every target is judged as a
/// tracker sample would be in live following before it goes out.
///
/// Timestamps: a survey target is not a tracked position, so its "capture time" is the monotonic
/// time at which the survey commits to sending it (age 0, hence never stale). The supervisor's
/// speed rule then measures the distance between consecutive targets over the time between
/// their sends. Every target is a fine point (the next one is sent only after the robot reported
/// the previous one reached), so this is the rate at which the survey commands motion, and it is
/// bounded by how fast the robot actually travelled the previous, equally long, segment of a
/// split move; the robot's own travel speed is set by its controller (RAPID survey mode,
/// robot-sim `--speed-mm-s`), which this check cannot see ahead of time.
pub struct SafetyGate {
    sup: Supervisor,
    t0: Instant,
    /// The step reference, for the message: the last target sent, else the robot's TCP.
    last_mm: [f64; 3],
}

impl SafetyGate {
    /// Connected: the step reference is the robot's reported TCP; then armed (the survey is the
    /// operator's explicit start).
    pub fn new(cfg: SafetyConfig, robot_pos_mm: [f64; 3]) -> Self {
        let mut sup = Supervisor::new(cfg);
        sup.on_connect(robot_pos_mm);
        sup.enable();
        SafetyGate {
            sup,
            t0: Instant::now(),
            last_mm: robot_pos_mm,
        }
    }

    /// The robot reported its TCP (after a point was reached).
    pub fn on_robot_position(&mut self, pos_mm: [f64; 3]) {
        self.sup.on_robot_position(pos_mm);
    }

    /// Judges one target now; `Ok` means it may be sent (and is recorded as sent).
    pub fn check(&mut self, pos_mm: [f64; 3], quat_wxyz: [f64; 4]) -> anyhow::Result<()> {
        // +1: a capture time of 0 would look like "before the previous target".
        let now_ns = self.t0.elapsed().as_nanos() as u64 + 1;
        let sample = Sample {
            frame: 0,
            capture_ts_ns: now_ns,
            position_mm: Some(pos_mm),
            orientation_wxyz: Some(quat_wxyz),
            gap_mm: 0.0,
            status: TrackStatus::Ok,
            world_frame: true,
        };
        match self.sup.check(&sample, now_ns, true) {
            Verdict::Send { pos_mm, quat_wxyz } => {
                self.sup.committed(pos_mm, quat_wxyz, now_ns);
                self.last_mm = pos_mm;
                Ok(())
            }
            Verdict::Hold(reason) => bail!(
                "the safety supervisor ([robot.safety]) held target [{:.2}, {:.2}, {:.2}] mm \
                 ({:.2} mm from [{:.2}, {:.2}, {:.2}]): {} ({reason:?}); the survey stopped and \
                 the robot was left where it is",
                pos_mm[0],
                pos_mm[1],
                pos_mm[2],
                Vector3::from(pos_mm).metric_distance(&Vector3::from(self.last_mm)),
                self.last_mm[0],
                self.last_mm[1],
                self.last_mm[2],
                hold_text(reason)
            ),
        }
    }
}

fn hold_text(r: HoldReason) -> &'static str {
    match r {
        HoldReason::Workspace => "outside the workspace",
        HoldReason::StepTooLarge => "step or rotation from the previous target too large",
        HoldReason::TooFast => "implied speed above max_speed_mm_s",
        HoldReason::PoorQuality => "poor quality",
        HoldReason::Stale => "stale",
        HoldReason::MarkerLost => "marker lost",
        HoldReason::NotEnabled => "not enabled",
        HoldReason::Deadman => "deadman released",
        HoldReason::Stop => "stop",
    }
}

/// Moves are split this far below the step limits (floating-point headroom for the supervisor).
const SPLIT_MARGIN: f64 = 0.999;

/// Drives the robot through the plan and measures every point.
fn measure(
    args: &Args,
    plan: &[Planned],
    safety: &SafetyConfig,
) -> anyhow::Result<(Vec<Measured>, bool, Vec<String>)> {
    let mut cell = Cell::connect(&args.robot, &args.stream)?;
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
            let pose = cell.pose(deadline)?;
            gate.on_robot_position(pose.0);
            at = (p.pos_mm, p.quat_wxyz);
            if samples.len() < args.frames {
                let why = format!(
                    "point {i} at [{:.1}, {:.1}, {:.1}] mm: marker tracked in {} of {} frames before the point's time ran out",
                    p.pos_mm[0],
                    p.pos_mm[1],
                    p.pos_mm[2],
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
            let (m, sd) = mean_sd(&samples);
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
                frames: samples.len(),
            });
        }
        Ok((out, world.unwrap_or(false), skipped))
    })();
    cell.close();
    result
}

/// Runs the subcommand.
pub fn run(mut args: Args) -> anyhow::Result<()> {
    ensure!(args.frames >= 1, "--frames must be at least 1");
    ensure!(
        args.max_step_mm > 0.0 && args.max_rotation_step_deg > 0.0,
        "--max-step-mm and --max-rotation-step-deg must be > 0"
    );
    ensure!(args.tolerance_mm > 0.0, "--tolerance-mm must be > 0");
    let params = match &args.params {
        Some(p) => Some(crate::opencv_yaml::load_params_any(p)?),
        None => None,
    };
    let safety = load_safety(&args.safety)?;
    let plan = plan(&args)?;
    for note in apply_safety(&mut args, &safety)? {
        println!("survey: {note}");
    }
    println!(
        "survey: under the [robot.safety] limits of {} (workspace {:?}..{:?} mm, step {} mm, \
         rotation step {}°, speed {} mm/s)",
        args.safety.display(),
        safety.workspace_min_mm,
        safety.workspace_max_mm,
        args.max_step_mm,
        args.max_rotation_step_deg,
        safety.max_speed_mm_s
    );
    std::fs::create_dir_all(&args.report)
        .with_context(|| format!("{}: cannot create the report directory", args.report.display()))?;
    let (points, world, skipped) = match measure(&args, &plan, &safety) {
        Ok(r) => r,
        Err(e) => {
            let md = format!("# Cell survey\n\n**STOPPED**: {e:#}\n");
            let _ = std::fs::write(args.report.join("survey.md"), md);
            return Err(e.context("survey STOPPED"));
        }
    };
    // Positions in camera 0's frame, for the distance to the cameras (and the registration).
    let old_world = if world {
        let w = params
            .as_ref()
            .and_then(|p| p.world_from_cam0)
            .context("the stream is in a world frame already: give --params with that registration")?;
        Some(w)
    } else {
        None
    };
    let a = analyse(&points, args.led_offset_mm)?;
    let report = Report::new(&args, &points, &a, old_world.as_ref(), &skipped);
    report.write(&args.report)?;
    print!("{}", report.summary());
    if let (Some(out), Some(mut p)) = (&args.out, params) {
        // robot_from_cam0 = robot_from_tracker ∘ tracker_from_cam0.
        let robot_from_cam0 = match &old_world {
            Some(w) => a.all.compose(w),
            None => a.all,
        };
        p.world_from_cam0 = Some(robot_from_cam0);
        p.validate().context("parameters with the registration")?;
        if crate::opencv_yaml::is_yaml_path(out) {
            crate::opencv_yaml::write_rig_yaml(out, &p)?;
        } else {
            let blob = p.to_blob().context("encode parameter blob")?;
            std::fs::write(out, blob).with_context(|| format!("{}: cannot write", out.display()))?;
        }
        println!(
            "survey: registration written to {} (sign and push it with host-tools push-params)",
            out.display()
        );
    }
    ensure!(report.pass, "survey FAILED: {}", report.verdict);
    Ok(())
}

/// The survey report.
pub struct Report {
    pub fre: Stats,
    pub tre: Stats,
    pub scale: f64,
    pub pass: bool,
    pub verdict: String,
    md: String,
    csv: String,
    /// (distance from camera 0, 3-D error, held out) per point.
    fig: Vec<(f64, f64, bool)>,
}

impl Report {
    fn new(
        args: &Args,
        points: &[Measured],
        a: &Analysis,
        old_world: Option<&RigidTransform>,
        skipped: &[String],
    ) -> Self {
        let pick = |holdout: bool| -> Vec<[f64; 3]> {
            points
                .iter()
                .zip(&a.residual_mm)
                .filter(|(m, _)| (m.role == Role::Holdout) == holdout)
                .map(|(_, r)| *r)
                .collect()
        };
        let fre = stats(&pick(false));
        let tre = stats(&pick(true));
        let cam0_from_tracker = old_world.map(RigidTransform::inverse);
        let dist = |m: &Measured| {
            let p = Vector3::from(m.tracker_mm);
            cam0_from_tracker.map_or(p, |t| t.apply(&p)).norm()
        };
        let scale_ppm = (a.scale - 1.0) * 1e6;
        let mut problems = Vec::new();
        if tre.n == 0 {
            problems.push("no held-out point was measured".to_string());
        }
        if tre.max_mm > args.tolerance_mm {
            problems.push(format!(
                "TRE max {:.3} mm exceeds the tolerance {:.3} mm",
                tre.max_mm, args.tolerance_mm
            ));
        }
        if scale_ppm.abs() > args.max_scale_error_ppm {
            problems.push(format!(
                "scale {:.6} is {:.0} ppm off 1 (limit {:.0} ppm): check the calibration's units",
                a.scale, scale_ppm, args.max_scale_error_ppm
            ));
        }
        let pass = problems.is_empty();
        let verdict = if pass {
            format!(
                "TRE max {:.3} mm within {:.3} mm, scale within {:.0} ppm",
                tre.max_mm, args.tolerance_mm, args.max_scale_error_ppm
            )
        } else {
            problems.join("; ")
        };
        let fig: Vec<(f64, f64, bool)> = points
            .iter()
            .zip(&a.residual_mm)
            .map(|(m, r)| (dist(m), Vector3::from(*r).norm(), m.role == Role::Holdout))
            .collect();

        let mut md = String::new();
        let w = &mut md;
        let _ = writeln!(w, "# Cell survey\n");
        let _ = writeln!(w, "**{}** — {}\n", if pass { "PASS" } else { "FAIL" }, verdict);
        let _ = writeln!(
            w,
            "Box [{:.1}, {:.1}, {:.1}] … [{:.1}, {:.1}, {:.1}] mm, grid {}×{}×{}, {} turned visits, {} frames per point, settle {} ms. Measured {} points ({} skipped).\n",
            args.box_min[0],
            args.box_min[1],
            args.box_min[2],
            args.box_max[0],
            args.box_max[1],
            args.box_max[2],
            args.grid[0],
            args.grid[1],
            args.grid[2],
            args.rotations,
            args.frames,
            args.settle_ms,
            points.len(),
            skipped.len()
        );
        let _ = writeln!(
            w,
            "| | points | RMS (mm) | max (mm) | x RMS / max | y RMS / max | z RMS / max |"
        );
        let _ = writeln!(w, "|---|---|---|---|---|---|---|");
        for (name, s) in [("FRE (fit points)", fre), ("TRE (held out)", tre)] {
            let _ = writeln!(
                w,
                "| {name} | {} | {:.3} | {:.3} | {:.3} / {:.3} | {:.3} / {:.3} | {:.3} / {:.3} |",
                s.n,
                s.rms_mm,
                s.max_mm,
                s.axis_rms_mm[0],
                s.axis_max_mm[0],
                s.axis_rms_mm[1],
                s.axis_max_mm[1],
                s.axis_rms_mm[2],
                s.axis_max_mm[2]
            );
        }
        let _ = writeln!(
            w,
            "\nUmeyama scale {:.6} ({scale_ppm:+.0} ppm; checked, not fitted — the registration is rigid).",
            a.scale
        );
        let _ = writeln!(
            w,
            "LED offset in the flange frame: [{:.3}, {:.3}, {:.3}] mm ({}).",
            a.led_offset_mm[0],
            a.led_offset_mm[1],
            a.led_offset_mm[2],
            if a.offset_solved {
                "solved jointly with the registration from the turned visits"
            } else if args.led_offset_mm.is_some() {
                "given"
            } else {
                "taken as 0: no turned visits"
            }
        );
        let t = a.all.translation_mm();
        let _ = writeln!(
            w,
            "Registration robot_from_tracker (all points): t = [{:.3}, {:.3}, {:.3}] mm.\n",
            t.x, t.y, t.z
        );
        let _ = writeln!(w, "## Worst points\n");
        let _ = writeln!(
            w,
            "| # | role | robot x, y, z (mm) | distance to camera 0 (mm) | error (mm) | ex, ey, ez (mm) |"
        );
        let _ = writeln!(w, "|---|---|---|---|---|---|");
        let mut order: Vec<usize> = (0..points.len()).collect();
        order.sort_by(|&i, &j| fig[j].1.total_cmp(&fig[i].1));
        for &i in order.iter().take(5) {
            let (m, r) = (&points[i], a.residual_mm[i]);
            let _ = writeln!(
                w,
                "| {} | {} | {:.2}, {:.2}, {:.2} | {:.0} | {:.3} | {:+.3}, {:+.3}, {:+.3} |",
                m.index + 1,
                m.role.name(),
                m.flange_mm[0],
                m.flange_mm[1],
                m.flange_mm[2],
                fig[i].0,
                fig[i].1,
                r[0],
                r[1],
                r[2]
            );
        }
        if !skipped.is_empty() {
            let _ = writeln!(w, "\n## Skipped\n");
            for s in skipped {
                let _ = writeln!(w, "- {s}");
            }
        }
        let _ = writeln!(
            w,
            "\n![error vs distance from the cameras](error-vs-distance.png)\n\nPer point: survey.csv."
        );

        let mut csv = String::from(
            "index,role,robot_x_mm,robot_y_mm,robot_z_mm,q1,q2,q3,q4,tracker_x_mm,tracker_y_mm,tracker_z_mm,tracker_sd_mm,frames,distance_cam0_mm,err_x_mm,err_y_mm,err_z_mm,err_mm\n",
        );
        for (i, m) in points.iter().enumerate() {
            let r = a.residual_mm[i];
            let _ = writeln!(
                csv,
                "{},{},{:.3},{:.3},{:.3},{:.6},{:.6},{:.6},{:.6},{:.4},{:.4},{:.4},{:.4},{},{:.1},{:.4},{:.4},{:.4},{:.4}",
                m.index,
                m.role.name(),
                m.flange_mm[0],
                m.flange_mm[1],
                m.flange_mm[2],
                m.flange_wxyz[0],
                m.flange_wxyz[1],
                m.flange_wxyz[2],
                m.flange_wxyz[3],
                m.tracker_mm[0],
                m.tracker_mm[1],
                m.tracker_mm[2],
                Vector3::from(m.tracker_sd_mm).norm(),
                m.frames,
                fig[i].0,
                r[0],
                r[1],
                r[2],
                fig[i].1
            );
        }
        Report {
            fre,
            tre,
            scale: a.scale,
            pass,
            verdict,
            md,
            csv,
            fig,
        }
    }

    /// Lines printed at the end of a run (the test reads them).
    pub fn summary(&self) -> String {
        format!(
            "survey: FRE RMS {:.3} mm max {:.3} mm ({} points)\n\
             survey: TRE RMS {:.3} mm max {:.3} mm ({} points); per axis RMS x {:.3} y {:.3} z {:.3} mm\n\
             survey: scale {:.6}\n\
             survey: {} — {}\n",
            self.fre.rms_mm,
            self.fre.max_mm,
            self.fre.n,
            self.tre.rms_mm,
            self.tre.max_mm,
            self.tre.n,
            self.tre.axis_rms_mm[0],
            self.tre.axis_rms_mm[1],
            self.tre.axis_rms_mm[2],
            self.scale,
            if self.pass { "PASS" } else { "FAIL" },
            self.verdict
        )
    }

    fn write(&self, dir: &Path) -> anyhow::Result<()> {
        std::fs::write(dir.join("survey.md"), &self.md).context("write survey.md")?;
        std::fs::write(dir.join("survey.csv"), &self.csv).context("write survey.csv")?;
        plot::error_vs_distance(&dir.join("error-vs-distance.png"), &self.fig)
    }
}

use std::fmt::Write as _;

mod plot {
    use std::path::Path;

    use plotters::prelude::*;

    use crate::calib::plots::{FONT, draw_err, ensure_font, write_rgb_png};

    const W: u32 = 900;
    const H: u32 = 560;

    /// The paper's Fig. 11: 3-D error of every point against its distance from the cameras.
    pub fn error_vs_distance(path: &Path, pts: &[(f64, f64, bool)]) -> anyhow::Result<()> {
        ensure_font()?;
        anyhow::ensure!(!pts.is_empty(), "no survey points to plot");
        let (dmin, dmax) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.0), b.max(p.0))
        });
        let emax = pts.iter().map(|p| p.1).fold(0.0, f64::max).max(1e-3);
        let pad = ((dmax - dmin) * 0.1).max(10.0);
        let mut rgb = vec![255u8; (W * H * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut rgb, (W, H)).into_drawing_area();
            let mut chart = ChartBuilder::on(&root)
                .caption("survey: error vs distance from camera 0", (FONT, 20))
                .margin(14)
                .x_label_area_size(44)
                .y_label_area_size(70)
                .build_cartesian_2d((dmin - pad)..(dmax + pad), 0.0..emax * 1.15)
                .map_err(draw_err)?;
            chart
                .configure_mesh()
                .x_desc("distance from camera 0 (mm)")
                .y_desc("3-D error after registration (mm)")
                .x_label_formatter(&|d| format!("{d:.0}"))
                .y_label_formatter(&|v| format!("{v:.2}"))
                .label_style((FONT, 14))
                .draw()
                .map_err(draw_err)?;
            for (held, colour, label) in [
                (false, RGBColor(20, 80, 220), "fit points (FRE)"),
                (true, RGBColor(210, 30, 30), "held-out points (TRE)"),
            ] {
                chart
                    .draw_series(
                        pts.iter()
                            .filter(|p| p.2 == held)
                            .map(|p| Circle::new((p.0, p.1), 5, colour.filled())),
                    )
                    .map_err(draw_err)?
                    .label(label)
                    .legend(move |(x, y)| Circle::new((x + 10, y), 5, colour.filled()));
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.9))
                .border_style(BLACK.mix(0.3))
                .label_font((FONT, 14))
                .draw()
                .map_err(draw_err)?;
            root.present().map_err(draw_err)?;
        }
        write_rgb_png(path, W, H, &rgb)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn measured(
        pts: &[([f64; 3], [f64; 4], Role)],
        robot_from_tracker: &RigidTransform,
        offset: [f64; 3],
        noise: impl Fn(usize) -> [f64; 3],
    ) -> Vec<Measured> {
        let tracker_from_robot = robot_from_tracker.inverse();
        pts.iter()
            .enumerate()
            .map(|(i, (p, q, role))| {
                let led = Vector3::from(*p) + quat(*q) * Vector3::from(offset);
                let n = Vector3::from(noise(i));
                let t = tracker_from_robot.apply(&(led + n));
                Measured {
                    index: i,
                    role: *role,
                    flange_mm: *p,
                    flange_wxyz: *q,
                    tracker_mm: [t.x, t.y, t.z],
                    tracker_sd_mm: [0.0; 3],
                    frames: 1,
                }
            })
            .collect()
    }

    fn safety_cfg() -> SafetyConfig {
        SafetyConfig {
            workspace_min_mm: [300.0, -200.0, 100.0],
            workspace_max_mm: [700.0, 200.0, 500.0],
            max_step_mm: 20.0,
            max_speed_mm_s: 250.0,
            max_gap_mm: 1.0,
            max_age_ms: 100,
            require_world_frame: true,
            max_rotation_step_deg: 5.0,
        }
    }

    #[test]
    fn safety_refuses_a_box_outside_the_workspace_and_tightens_steps() {
        let mut a = args();
        let notes = apply_safety(&mut a, &safety_cfg()).unwrap();
        assert_eq!((a.max_step_mm, a.max_rotation_step_deg), (20.0, 5.0));
        assert_eq!(notes.len(), 2, "{notes:?}");
        assert!(notes[0].contains("max_step_mm"), "{notes:?}");
        let mut a = args();
        a.box_max[2] = 550.0;
        let e = apply_safety(&mut a, &safety_cfg()).unwrap_err().to_string();
        assert!(
            e.contains("axis z") && e.contains("550") && e.contains("500"),
            "{e}"
        );
        // The CLI's smaller limits stay.
        let mut a = args();
        a.max_step_mm = 5.0;
        assert!(apply_safety(&mut a, &safety_cfg()).unwrap().len() == 1);
        assert_eq!(a.max_step_mm, 5.0);
    }

    #[test]
    fn safety_file_without_a_robot_section_is_refused() {
        let p = std::env::temp_dir().join(format!("survey-safety-{}.toml", std::process::id()));
        std::fs::write(&p, "[leds]\nbackend = \"none\"\n").unwrap();
        let e = format!("{:#}", load_safety(&p).unwrap_err());
        let _ = std::fs::remove_file(&p);
        assert!(e.contains("no [robot.safety] section"), "{e}");
    }

    #[test]
    fn safety_gate_passes_split_moves_and_holds_what_the_supervisor_holds() {
        let q = [0.0, 0.0, 1.0, 0.0];
        let start = [500.0, 0.0, 300.0];
        // Split to the limits, a move inside the workspace passes target by target.
        let mut gate = SafetyGate::new(safety_cfg(), start);
        for (p, q) in split_move((start, q), ([520.0, 30.0, 320.0], q), 20.0, 5.0) {
            gate.check(p, q).unwrap();
            std::thread::sleep(Duration::from_millis(100));
        }
        // A step the supervisor's limit forbids (e.g. a split with a larger CLI step) is held.
        let mut gate = SafetyGate::new(safety_cfg(), start);
        let moves = split_move((start, q), ([560.0, 0.0, 300.0], q), 30.0, 5.0);
        let e = gate.check(moves[0].0, moves[0].1).unwrap_err().to_string();
        assert!(e.contains("StepTooLarge") && e.contains("stopped"), "{e}");
        // And a target outside the workspace (the robot may start outside the box).
        let mut gate = SafetyGate::new(safety_cfg(), [690.0, 0.0, 300.0]);
        let e = gate.check([710.0, 0.0, 300.0], q).unwrap_err().to_string();
        assert!(e.contains("Workspace"), "{e}");
        // And targets commanded faster than max_speed_mm_s.
        let mut gate = SafetyGate::new(safety_cfg(), start);
        gate.check([510.0, 0.0, 300.0], q).unwrap();
        let e = gate.check([520.0, 0.0, 300.0], q).unwrap_err().to_string();
        assert!(e.contains("TooFast"), "{e}");
    }

    fn args() -> Args {
        Args {
            stream: String::new(),
            robot: String::new(),
            safety: PathBuf::new(),
            box_min: [400.0, -100.0, 200.0],
            box_max: [600.0, 100.0, 400.0],
            grid: [3, 3, 3],
            frames: 10,
            settle_ms: 0,
            holdout_every: 3,
            orient: [0.0, 0.0, 1.0, 0.0],
            rotations: 6,
            rotation_deg: 25.0,
            led_offset_mm: None,
            max_step_mm: 50.0,
            max_rotation_step_deg: 10.0,
            tolerance_mm: 1.0,
            max_scale_error_ppm: 2000.0,
            point_timeout_s: 10.0,
            params: None,
            out: None,
            report: PathBuf::new(),
        }
    }

    #[test]
    fn plan_holds_out_a_third_and_splits_long_moves() {
        let p = plan(&args()).unwrap();
        assert_eq!(p.len(), 27 + 6);
        assert_eq!(p.iter().filter(|x| x.role == Role::Holdout).count(), 9);
        // Serpentine: consecutive grid points are one grid step apart.
        for w in p[..27].windows(2) {
            let d = (Vector3::from(w[1].pos_mm) - Vector3::from(w[0].pos_mm)).norm();
            assert!((d - 100.0).abs() < 1e-9, "{d}");
        }
        let steps = split_move(
            ([0.0; 3], [1.0, 0.0, 0.0, 0.0]),
            (
                [120.0, 0.0, 0.0],
                wxyz(&UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6)),
            ),
            50.0,
            10.0,
        );
        // 0.6 rad = 34.4° needs 4 steps; 120 mm needs 3.
        assert_eq!(steps.len(), 4);
        assert_eq!(steps[3].0, [120.0, 0.0, 0.0]);
        let mut bad = args();
        bad.box_max[1] = -200.0;
        assert!(plan(&bad).unwrap_err().to_string().contains("axis 1"));
    }

    #[test]
    fn registration_and_led_offset_are_recovered_and_tre_sees_errors() {
        let a = args();
        let planned = plan(&a).unwrap();
        let pts: Vec<_> = planned.iter().map(|p| (p.pos_mm, p.quat_wxyz, p.role)).collect();
        let r = UnitQuaternion::from_euler_angles(0.3, -2.0, 0.7)
            .to_rotation_matrix()
            .into_inner();
        let truth = RigidTransform::from_parts(&r, &Vector3::new(450.0, -30.0, 900.0));
        let offset = [12.0, -8.0, 95.0];
        let exact = measured(&pts, &truth, offset, |_| [0.0; 3]);
        let an = analyse(&exact, None).unwrap();
        assert!(an.offset_solved);
        for (got, want) in an.led_offset_mm.iter().zip(offset) {
            assert!((got - want).abs() < 1e-6, "{:?}", an.led_offset_mm);
        }
        assert!(stats(&an.residual_mm).max_mm < 1e-6);
        assert!((an.scale - 1.0).abs() < 1e-9);
        // Known offset, no turns: same registration.
        let grid_only: Vec<Measured> = exact.iter().filter(|m| m.role != Role::Turned).cloned().collect();
        let an2 = analyse(&grid_only, Some(offset)).unwrap();
        assert!((an2.fit.translation_mm() - truth.translation_mm()).norm() < 1e-6);
        // Errors on the held-out points only show up in the TRE.
        let noisy = measured(&pts, &truth, offset, |i| {
            if pts[i].2 == Role::Holdout {
                [0.5, 0.0, 0.0]
            } else {
                [0.0; 3]
            }
        });
        let an3 = analyse(&noisy, None).unwrap();
        let held: Vec<[f64; 3]> = noisy
            .iter()
            .zip(&an3.residual_mm)
            .filter(|(m, _)| m.role == Role::Holdout)
            .map(|(_, r)| *r)
            .collect();
        let s = stats(&held);
        assert!(
            (s.rms_mm - 0.5).abs() < 1e-6 && (s.axis_rms_mm[0] - 0.5).abs() < 1e-6,
            "{s:?}"
        );
        // A turn about one axis only leaves the offset along it unobservable.
        let mut one_axis = a.clone();
        one_axis.rotations = 1;
        let planned = plan(&one_axis).unwrap();
        let pts: Vec<_> = planned.iter().map(|p| (p.pos_mm, p.quat_wxyz, p.role)).collect();
        let m = measured(&pts, &truth, offset, |_| [0.0; 3]);
        assert!(
            analyse(&m, None).is_err() || {
                // One turned visit is below the two the solve needs: the offset is taken as 0.
                !analyse(&m, None).unwrap().offset_solved
            }
        );
    }

    #[test]
    fn report_fails_on_tolerance_and_scale() {
        let mut a = args();
        a.rotations = 0;
        let planned = plan(&a).unwrap();
        let pts: Vec<_> = planned.iter().map(|p| (p.pos_mm, p.quat_wxyz, p.role)).collect();
        let m = measured(&pts, &RigidTransform::IDENTITY, [0.0; 3], |i| {
            if i % 3 == 1 { [0.0, 0.0, 0.4] } else { [0.0; 3] }
        });
        let an = analyse(&m, None).unwrap();
        let r = Report::new(&a, &m, &an, None, &[]);
        assert!(r.pass, "{}", r.verdict);
        a.tolerance_mm = 0.2;
        let r = Report::new(&a, &m, &an, None, &[]);
        assert!(!r.pass && r.verdict.contains("TRE max"), "{}", r.verdict);
        // Tracker 1 % too large: the scale check fails even with a generous tolerance.
        let big: Vec<Measured> = m
            .iter()
            .map(|x| Measured {
                tracker_mm: x.tracker_mm.map(|v| v * 1.01),
                ..x.clone()
            })
            .collect();
        a.tolerance_mm = 50.0;
        let an = analyse(&big, None).unwrap();
        let r = Report::new(&a, &big, &an, None, &[]);
        assert!(!r.pass && r.verdict.contains("ppm"), "{}", r.verdict);
        let dir = std::env::temp_dir().join(format!("survey-report-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        r.write(&dir).unwrap();
        assert!(
            std::fs::metadata(dir.join("error-vs-distance.png"))
                .unwrap()
                .len()
                > 1000
        );
        assert!(
            std::fs::read_to_string(dir.join("survey.md"))
                .unwrap()
                .contains("FAIL")
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
