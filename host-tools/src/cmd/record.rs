//! `host-tools record`: records a path from irtrackd's position stream for teach-in.
//!
//! Continuous mode writes every record (lost ones with empty positions, so gaps stay visible);
//! `--points` (point-teach) writes only the waypoints. A waypoint is marked by typing `p` + Enter
//! on stdin, or by creating the `--mark-file` (a foot switch script can `touch` it; the recorder
//! deletes it after marking). `q` + Enter stops. The newest valid position at the moment of the
//! mark becomes the waypoint.
//!
//! `--mcap FILE` also records every record into an MCAP file with ROS 2 schemas (Foxglove,
//! `ros2 bag`; docs/outputs.md). Its stamps are wall-clock times: the board's capture times
//! shifted by (this PC's clock − the first record's capture time) when it arrives, so the
//! spacing is the board's and the absolute time is this PC's, to within the stream latency.

use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use irtrack_core::stream::{BINARY_FRAME_LEN, MAX_NDJSON_LINE, PositionRecord, TrackStatus};
use irtrack_interop::mcap::McapRecorder;

/// Stream encoding to subscribe to.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// Newline-delimited JSON (irtrackd port 7702).
    Ndjson,
    /// Binary frames (irtrackd port 7703).
    Binary,
}

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// irtrackd position stream, `host:port`.
    #[arg(long, default_value = "127.0.0.1:7702")]
    pub from: String,
    /// Stream encoding; `--from` must name the port that serves it (7702 NDJSON, 7703 binary).
    #[arg(long, value_enum, default_value_t = Format::Ndjson)]
    pub format: Format,
    /// Output CSV.
    #[arg(long, required_unless_present = "mcap")]
    pub out: Option<PathBuf>,
    /// Also (or only) record into this MCAP file, ROS 2 message schemas (docs/outputs.md).
    #[arg(long)]
    pub mcap: Option<PathBuf>,
    /// Stop after this many seconds.
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// Point-teach: write only marked waypoints.
    #[arg(long)]
    pub points: bool,
    /// Stop after this many waypoints (point-teach).
    #[arg(long)]
    pub max_points: Option<usize>,
    /// Marks a waypoint whenever this file appears (it is deleted after marking).
    #[arg(long)]
    pub mark_file: Option<PathBuf>,
    /// Do not read commands from stdin.
    #[arg(long)]
    pub no_stdin: bool,
}

/// What the recording produced.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Summary {
    /// Records received from the stream.
    pub records: u64,
    /// Records with a tracked position (status ok).
    pub valid: u64,
    /// Records without a tracked position (lost, or any status but ok).
    pub lost: u64,
    /// Waypoints marked.
    pub waypoints: usize,
    /// Rows written to the CSV (every record in continuous mode, waypoints only with `--points`).
    pub written_rows: u64,
    /// Messages written to the MCAP file, per topic.
    pub mcap: Option<irtrack_interop::mcap::McapCounts>,
}

/// The orientation columns (6-DOF tools; empty for a single LED) come last so readers that
/// index the older columns keep working.
const HEADER: &str = "t_s,frame,capture_ts_ns,x_mm,y_mm,z_mm,gap_mm,status,waypoint,qw,qx,qy,qz";

enum Cmd {
    Mark,
    Quit,
}

/// Partial input kept across read timeouts (a timeout may split a line or a frame).
#[derive(Default)]
struct Partial {
    line: String,
    bin: Vec<u8>,
}

fn read_record(
    fmt: Format,
    rd: &mut BufReader<TcpStream>,
    p: &mut Partial,
) -> anyhow::Result<Option<PositionRecord>> {
    match fmt {
        Format::Ndjson => {
            let room = MAX_NDJSON_LINE.saturating_sub(p.line.len()) as u64;
            // On a timeout the bytes read so far stay in `p.line`.
            let n = rd
                .by_ref()
                .take(room)
                .read_line(&mut p.line)
                .context("read position stream")?;
            if !p.line.ends_with('\n') {
                if p.line.len() >= MAX_NDJSON_LINE {
                    bail!("position stream line longer than {MAX_NDJSON_LINE} bytes");
                }
                if n == 0 {
                    return Ok(None); // end of stream
                }
                return Err(std::io::Error::from(std::io::ErrorKind::WouldBlock).into());
            }
            let r = PositionRecord::from_ndjson_line(p.line.trim_end());
            p.line.clear();
            Ok(Some(r.context("bad NDJSON record")?))
        }
        Format::Binary => {
            let mut buf = [0u8; BINARY_FRAME_LEN];
            let want = BINARY_FRAME_LEN - p.bin.len();
            let n = rd.read(&mut buf[..want]).context("read position stream")?;
            if n == 0 {
                return Ok(None);
            }
            p.bin.extend_from_slice(&buf[..n]);
            if p.bin.len() < BINARY_FRAME_LEN {
                return Err(std::io::Error::from(std::io::ErrorKind::WouldBlock).into());
            }
            let r = PositionRecord::decode_binary(&p.bin);
            p.bin.clear();
            Ok(Some(r.context("bad binary record")?))
        }
    }
}

fn write_row(out: &mut impl Write, t0_ns: u64, r: &PositionRecord, waypoint: bool) -> std::io::Result<()> {
    let t = r.capture_ts_ns.saturating_sub(t0_ns) as f64 * 1e-9;
    let (x, y, z) = match r.position_mm {
        Some(p) => (
            format!("{:.4}", p[0]),
            format!("{:.4}", p[1]),
            format!("{:.4}", p[2]),
        ),
        None => (String::new(), String::new(), String::new()),
    };
    let gap = if r.gap_mm.is_finite() {
        format!("{:.4}", r.gap_mm)
    } else {
        String::new()
    };
    write!(
        out,
        "{t:.6},{},{},{x},{y},{z},{gap},{},{}",
        r.frame,
        r.capture_ts_ns,
        r.status.as_str(),
        u8::from(waypoint)
    )?;
    match r.orientation_wxyz.filter(|_| r.position_mm.is_some()) {
        Some(q) => writeln!(out, ",{:.7},{:.7},{:.7},{:.7}", q[0], q[1], q[2], q[3]),
        None => writeln!(out, ",,,,"),
    }
}

/// Records until the stream ends, the duration elapses, `q` is typed or enough points exist.
pub fn record(args: &Args) -> anyhow::Result<Summary> {
    let stream =
        TcpStream::connect(&args.from).with_context(|| format!("cannot connect to {}", args.from))?;
    // A short timeout lets the loop check the clock and commands while the stream is quiet.
    stream.set_read_timeout(Some(Duration::from_millis(200)))?;
    let mut rd = BufReader::new(stream);
    let mut out: Box<dyn Write> = match &args.out {
        Some(path) => {
            let file =
                std::fs::File::create(path).with_context(|| format!("{}: cannot create", path.display()))?;
            Box::new(BufWriter::new(file))
        }
        None => Box::new(std::io::sink()),
    };
    writeln!(out, "{HEADER}")?;
    let mcap_file = match &args.mcap {
        Some(path) => {
            Some(std::fs::File::create(path).with_context(|| format!("{}: cannot create", path.display()))?)
        }
        None => None,
    };
    let mut mcap: Option<McapRecorder<std::fs::File>> = None;
    let (tx, cmds) = mpsc::channel();
    if !args.no_stdin {
        std::thread::spawn(move || {
            for line in std::io::stdin().lock().lines() {
                let Ok(line) = line else { break };
                let cmd = match line.trim() {
                    "p" | "P" => Cmd::Mark,
                    "q" | "Q" => Cmd::Quit,
                    _ => continue,
                };
                if tx.send(cmd).is_err() {
                    break;
                }
            }
        });
    }
    let started = Instant::now();
    let mut s = Summary::default();
    let mut t0_ns = None;
    let mut last_valid: Option<PositionRecord> = None;
    let mut pending_marks = 0usize;
    let mut last_progress = Instant::now();
    let mut partial = Partial::default();
    let interactive = !args.no_stdin;
    loop {
        if args
            .duration_s
            .is_some_and(|d| started.elapsed().as_secs_f64() >= d)
        {
            break;
        }
        if args.max_points.is_some_and(|m| s.waypoints >= m) {
            break;
        }
        let mut quit = false;
        while let Ok(c) = cmds.try_recv() {
            match c {
                Cmd::Mark => pending_marks += 1,
                Cmd::Quit => quit = true,
            }
        }
        if quit {
            break;
        }
        if let Some(f) = &args.mark_file
            && f.exists()
        {
            std::fs::remove_file(f).with_context(|| format!("{}: cannot remove mark file", f.display()))?;
            pending_marks += 1;
        }
        let rec = match read_record(args.format, &mut rd, &mut partial) {
            Ok(Some(r)) => Some(r),
            Ok(None) => break,
            Err(e)
                if e.chain().any(|c| {
                    c.downcast_ref::<std::io::Error>().is_some_and(|io| {
                        matches!(
                            io.kind(),
                            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                        )
                    })
                }) =>
            {
                None
            }
            Err(e) => return Err(e),
        };
        if let Some(r) = rec {
            s.records += 1;
            let t0 = *t0_ns.get_or_insert(r.capture_ts_ns);
            if let Some(file) = mcap_file.as_ref().filter(|_| mcap.is_none()) {
                let wall_ns = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos() as i128);
                let file = file.try_clone().context("MCAP file")?;
                mcap = Some(McapRecorder::new(file, wall_ns - i128::from(t0))?);
            }
            if let Some(m) = mcap.as_mut() {
                m.write(&r)?;
            }
            let valid = r.status == TrackStatus::Ok && r.position_mm.is_some();
            if valid {
                s.valid += 1;
                last_valid = Some(r);
            } else {
                s.lost += 1;
            }
            if !args.points {
                // A mark applies to the next valid record in continuous mode.
                let mark = valid && pending_marks > 0;
                if mark {
                    pending_marks -= 1;
                    s.waypoints += 1;
                }
                write_row(&mut out, t0, &r, mark)?;
                s.written_rows += 1;
            }
        }
        if args.points {
            while pending_marks > 0 {
                let Some(r) = last_valid else { break };
                pending_marks -= 1;
                s.waypoints += 1;
                write_row(&mut out, t0_ns.unwrap_or(r.capture_ts_ns), &r, true)?;
                s.written_rows += 1;
                if interactive {
                    let p = r.position_mm.unwrap_or_default();
                    eprintln!(
                        "\nwaypoint {}: {:.2} {:.2} {:.2} mm",
                        s.waypoints, p[0], p[1], p[2]
                    );
                }
            }
        }
        if last_progress.elapsed() >= Duration::from_millis(250) {
            last_progress = Instant::now();
            let pos = last_valid
                .and_then(|r| r.position_mm)
                .map(|p| format!("{:8.2} {:8.2} {:8.2}", p[0], p[1], p[2]))
                .unwrap_or_else(|| "     --       --       --".into());
            eprint!(
                "\r{:6.1} s  {} records  {} lost  {} waypoints  at {pos} mm ",
                started.elapsed().as_secs_f64(),
                s.records,
                s.lost,
                s.waypoints
            );
        }
    }
    out.flush()?;
    if mcap.is_none()
        && let Some(file) = &mcap_file
    {
        // No record arrived: still leave a valid (empty) MCAP file with its channels.
        mcap = Some(McapRecorder::new(file.try_clone()?, 0)?);
    }
    if let Some(m) = mcap {
        s.mcap = Some(m.finish()?);
    }
    eprintln!();
    Ok(s)
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    if args.points && args.mark_file.is_none() && args.no_stdin {
        bail!("--points needs a way to mark waypoints: stdin or --mark-file");
    }
    if !args.no_stdin {
        eprintln!(
            "recording from {}; type p + Enter to mark a waypoint, q + Enter to stop",
            args.from
        );
    }
    let s = record(&args)?;
    if let Some(out) = &args.out {
        println!(
            "{} records ({} valid, {} lost), {} waypoints, {} rows written to {}",
            s.records,
            s.valid,
            s.lost,
            s.waypoints,
            s.written_rows,
            display(out)
        );
    }
    if let (Some(path), Some(c)) = (&args.mcap, s.mcap) {
        println!(
            "{} records into {}: {} positions, {} poses, {} tf, {} status messages",
            s.records,
            display(path),
            c.position,
            c.pose,
            c.tf,
            c.status
        );
    }
    Ok(())
}

fn display(p: &Path) -> String {
    p.display().to_string()
}
