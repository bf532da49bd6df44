//! `host-tools capture`: takes synchronised frame sets from a running irtrackd for calibration.
//!
//! Each set comes from irtrackd's `GET /api/frameset` (docs/http-api.md): one JSON line, then
//! each camera's full-resolution frame as binary PGM. A set is saved as `DIR/cam0/NNNNNN.pgm`,
//! `DIR/cam1/NNNNNN.pgm`, … (one file name per set, the layout `calibrate`, `wand-calibrate` and
//! `track` read), on Enter or every `--every` seconds. Each checkerboard set is searched for the
//! board as it arrives, and the terminal shows per camera whether it was found and how much of
//! the image the board has covered so far, so the person holding it knows where views are
//! still missing. `--wand` saves sets as fast as irtrackd serves them (no board search).

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail, ensure};
use opencv::core::{Mat, Point2f, Vector};
use opencv::imgcodecs;
use opencv::prelude::*;

use crate::calib::detect::{Board, find_corners};

/// Default port of irtrackd's HTTP listener.
pub const DEFAULT_HTTP_PORT: u16 = 7704;
/// Coverage grid columns and rows per camera.
const GRID_COLS: usize = 8;
const GRID_ROWS: usize = 6;

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// The board running irtrackd: HOST or HOST:PORT (port 7704 if left out).
    #[arg(long, value_name = "BOARD[:PORT]")]
    pub from: String,
    /// Output directory (cam0/, cam1/, … are created; numbering continues after existing sets).
    #[arg(long)]
    pub out: PathBuf,
    /// Save a set every this many seconds instead of on Enter.
    #[arg(long, value_name = "SECONDS")]
    pub every: Option<f64>,
    /// Stop after this many saved sets.
    #[arg(long)]
    pub count: Option<u64>,
    /// Checkerboard inner corners per row.
    #[arg(long, default_value_t = 9)]
    pub board_cols: u32,
    /// Checkerboard inner corners per column.
    #[arg(long, default_value_t = 6)]
    pub board_rows: u32,
    /// Wand wave: save sets as fast as irtrackd serves them, without a board search
    /// (stop with --count, or `q` + Enter).
    #[arg(long)]
    pub wand: bool,
    /// Per-request timeout, seconds (irtrackd waits up to 2 s for a set).
    #[arg(long, default_value_t = 10.0)]
    pub timeout_s: f64,
}

/// The frame-set format (header line + one PGM per camera) lives in `irtrack_core::frameset`
/// beside irtrackd's writer of it (docs/frameset.md).
pub use irtrack_core::frameset::{CameraHeader, FrameSet, FrameSetHeader};

/// `http://HOST:PORT/api/frameset` for `BOARD` or `BOARD:PORT`.
pub fn frameset_url(from: &str) -> String {
    let from = from.trim_start_matches("http://").trim_end_matches('/');
    let has_port = from
        .rsplit_once(':')
        .is_some_and(|(h, p)| !h.is_empty() && !h.ends_with(':') && p.parse::<u16>().is_ok());
    if has_port {
        format!("http://{from}/api/frameset")
    } else {
        format!("http://{from}:{DEFAULT_HTTP_PORT}/api/frameset")
    }
}

/// Why a fetch gave no set.
#[derive(Debug)]
pub enum FetchError {
    /// Busy (503) or no set in time (504): worth another try.
    Retry(String),
    /// Anything else: give up with this message.
    Fatal(anyhow::Error),
}

/// Fetches and parses one frame set.
pub fn fetch(agent: &ureq::Agent, url: &str, board: &str) -> Result<FrameSet, FetchError> {
    let resp = match agent.get(url).call() {
        Ok(r) => r,
        Err(ureq::Error::Status(404, r)) => {
            // Old firmware has no route; newer firmware without a frame tap says why.
            let said = r.into_string().unwrap_or_default();
            let said = said.trim();
            let detail = if said.is_empty() {
                String::new()
            } else {
                format!(" (it answered: {said})")
            };
            return Err(FetchError::Fatal(anyhow!(
                "irtrackd on {board} has no /api/frameset; update the firmware{detail}"
            )));
        }
        Err(ureq::Error::Status(code @ (503 | 504), r)) => {
            let why = r.into_string().unwrap_or_default();
            return Err(FetchError::Retry(format!("{code}: {}", why.trim())));
        }
        Err(ureq::Error::Status(code, r)) => {
            let why = r.into_string().unwrap_or_default();
            return Err(FetchError::Fatal(anyhow!(
                "irtrackd on {board} answered {code} to GET /api/frameset: {}",
                why.trim()
            )));
        }
        Err(ureq::Error::Transport(t)) => {
            return Err(FetchError::Fatal(anyhow!(
                "cannot reach irtrackd on {board} ({url}): {t}; is the board on and irtrackd running?"
            )));
        }
    };
    let mut body = Vec::new();
    // 16 cameras of 16-bit 4K frames stay below this; anything larger is not a frame set.
    const MAX_BODY: u64 = 512 << 20;
    let mut reader = std::io::Read::take(resp.into_reader(), MAX_BODY);
    std::io::Read::read_to_end(&mut reader, &mut body)
        .map_err(|e| FetchError::Fatal(anyhow!("reading the frame set from {board}: {e}")))?;
    FrameSet::parse(&body).map_err(|e| FetchError::Fatal(anyhow!("frame set from {board}: {e}")))
}

/// [`fetch`], trying again while irtrackd is busy or has no set yet (up to 20 times in a row).
fn fetch_with_retries(agent: &ureq::Agent, url: &str, board: &str) -> anyhow::Result<FrameSet> {
    let mut retries = 0;
    loop {
        match fetch(agent, url, board) {
            Ok(set) => return Ok(set),
            Err(FetchError::Retry(why)) => {
                retries += 1;
                ensure!(
                    retries <= 20,
                    "irtrackd on {board} gave no frame set 20 times in a row: {why}"
                );
                eprintln!("capture: no set this time ({why}); trying again");
                std::thread::sleep(Duration::from_millis(100));
            }
            Err(FetchError::Fatal(e)) => return Err(e),
        }
    }
}

/// One line naming what the board serves, e.g. `board 10.0.0.5: 2 cameras, 752x480 8-bit`.
pub fn describe_cameras(board: &str, header: &FrameSetHeader) -> String {
    let mut kinds: Vec<String> = Vec::new();
    for c in &header.cameras {
        let k = format!("{}x{} {}-bit", c.width_px, c.height_px, c.bit_depth);
        if !kinds.contains(&k) {
            kinds.push(k);
        }
    }
    let n = header.cameras.len();
    format!(
        "board {board}: {n} camera{}, {}",
        if n == 1 { "" } else { "s" },
        kinds.join(" / ")
    )
}

/// Where the board's corners have landed so far in one camera: corners per grid cell.
#[derive(Debug, Clone, PartialEq)]
pub struct Coverage {
    /// Image width (px) the grid divides.
    pub width_px: u32,
    /// Image height (px) the grid divides.
    pub height_px: u32,
    /// Corners counted per cell, `cells[row][column]`.
    pub cells: [[u32; GRID_COLS]; GRID_ROWS],
    /// Views added so far.
    pub views: u32,
}

impl Coverage {
    /// An empty grid for an image of this size.
    pub fn new(width_px: u32, height_px: u32) -> Self {
        Coverage {
            width_px,
            height_px,
            cells: [[0; GRID_COLS]; GRID_ROWS],
            views: 0,
        }
    }

    /// Counts one view's corners.
    pub fn add(&mut self, corners: &[Point2f]) {
        self.views += 1;
        for p in corners {
            let cx = (f64::from(p.x) / f64::from(self.width_px) * GRID_COLS as f64).floor();
            let cy = (f64::from(p.y) / f64::from(self.height_px) * GRID_ROWS as f64).floor();
            if (0.0..GRID_COLS as f64).contains(&cx) && (0.0..GRID_ROWS as f64).contains(&cy) {
                self.cells[cy as usize][cx as usize] += 1;
            }
        }
    }

    /// Share of grid cells with at least one corner.
    pub fn fraction(&self) -> f64 {
        let hit = self.cells.iter().flatten().filter(|c| **c > 0).count();
        hit as f64 / (GRID_COLS * GRID_ROWS) as f64
    }

    /// The grid as text rows: `.` no corner yet, `+` a few, `#` well covered.
    pub fn rows(&self) -> Vec<String> {
        self.cells
            .iter()
            .map(|row| {
                row.iter()
                    .map(|c| match c {
                        0 => '.',
                        1..=5 => '+',
                        _ => '#',
                    })
                    .collect()
            })
            .collect()
    }
}

/// Decodes a PGM into an 8-bit grey `Mat` for the board search.
fn grey_mat(pgm: &[u8]) -> anyhow::Result<Mat> {
    let buf: Vector<u8> = Vector::from_slice(pgm);
    let m = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_GRAYSCALE).context("OpenCV cannot decode the PGM")?;
    ensure!(!m.empty(), "OpenCV cannot decode the PGM");
    Ok(m)
}

/// Highest `NNNNNN.pgm` index in `DIR/cam0/`, so a new session continues the numbering.
fn next_index(out: &Path) -> u64 {
    std::fs::read_dir(out.join("cam0"))
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    e.file_name()
                        .to_string_lossy()
                        .strip_suffix(".pgm")
                        .and_then(|s| s.parse::<u64>().ok())
                })
                .max()
                .map_or(0, |m| m + 1)
        })
        .unwrap_or(0)
}

/// Writes one set as `DIR/camN/NNNNNN.pgm`; cam0 last is not needed: each file goes through a
/// temporary name and a rename, so a reader never sees half a frame.
fn save_set(out: &Path, index: u64, set: &FrameSet) -> anyhow::Result<()> {
    for (c, pgm) in set.pgms.iter().enumerate() {
        let dir = out.join(format!("cam{c}"));
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        crate::cmd::convert_params::write_atomically(&dir.join(format!("{index:06}.pgm")), pgm)?;
    }
    Ok(())
}

/// File beside cam0/, cam1/, … with each saved frame's capture time (the board's clock), the
/// format irtrackd's replay source reads: `frame,camera,timestamp_ns,dropped`.
pub const TIMESTAMPS_FILE: &str = "timestamps.csv";

/// Appends one set's rows to `DIR/timestamps.csv` (header written when the file is new), so a
/// replay of the directory keeps the recorded frame intervals.
pub fn append_timestamps(out: &Path, index: u64, set: &FrameSet) -> anyhow::Result<()> {
    let path = out.join(TIMESTAMPS_FILE);
    let new = !path.exists();
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .with_context(|| format!("opening {}", path.display()))?;
    let mut rows = String::new();
    if new {
        rows.push_str("frame,camera,timestamp_ns,dropped\n");
    }
    for (c, cam) in set.header.cameras.iter().enumerate() {
        rows.push_str(&format!("{index},{c},{},0\n", cam.timestamp_ns));
    }
    f.write_all(rows.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// What happened to one saved set in checkerboard mode, per camera: corners found or not.
pub fn detect_set(
    set: &FrameSet,
    board: &Board,
    coverage: &mut Vec<Coverage>,
) -> anyhow::Result<Vec<Option<usize>>> {
    let mut out = Vec::with_capacity(set.pgms.len());
    for (c, pgm) in set.pgms.iter().enumerate() {
        let h = &set.header.cameras[c];
        if coverage.len() <= c {
            coverage.push(Coverage::new(h.width_px, h.height_px));
        }
        let img = grey_mat(pgm).with_context(|| format!("camera {c}"))?;
        match find_corners(&img, board)? {
            Some(corners) => {
                coverage[c].add(&corners);
                out.push(Some(corners.len()));
            }
            None => out.push(None),
        }
    }
    Ok(out)
}

/// The terminal report after one set: found/not found per camera, then the coverage grids side
/// by side.
pub fn report(saved: u64, name: &str, found: &[Option<usize>], coverage: &[Coverage], both: u64) -> String {
    let mut s = format!("set {saved} ({name}.pgm):");
    for (c, f) in found.iter().enumerate() {
        match f {
            Some(n) => s.push_str(&format!("  cam{c} board found ({n} corners)")),
            None => s.push_str(&format!("  cam{c} no board")),
        }
    }
    s.push('\n');
    let width = GRID_COLS + 4;
    for (c, cov) in coverage.iter().enumerate() {
        let label = format!("cam{c} {:>3.0}%", cov.fraction() * 100.0);
        s.push_str(&format!("{label:<w$}  ", w = width.max(label.len())));
    }
    s.push('\n');
    for r in 0..GRID_ROWS {
        for cov in coverage {
            s.push_str(&format!("[{}]{:w$}", cov.rows()[r], "", w = width - GRID_COLS));
        }
        s.push('\n');
    }
    s.push_str(&format!(
        "views with the board in every camera: {both} (calibrate wants 15–20 or more, spread over the grid)\n"
    ));
    s
}

/// Commands from the terminal.
enum Key {
    /// Enter.
    Capture,
    /// `q` + Enter.
    Quit,
    /// Standard input closed (no terminal): ends an Enter-driven session only.
    Eof,
}

fn stdin_keys() -> mpsc::Receiver<Key> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            let key = if line.trim().eq_ignore_ascii_case("q") {
                Key::Quit
            } else {
                Key::Capture
            };
            if tx.send(key).is_err() {
                return;
            }
        }
        let _ = tx.send(Key::Eof);
    });
    rx
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    if let Some(e) = args.every {
        ensure!(
            e.is_finite() && e > 0.0,
            "--every {e} must be a positive number of seconds"
        );
    }
    ensure!(args.count != Some(0), "--count must be at least 1");
    ensure!(
        args.board_cols >= 2 && args.board_rows >= 2,
        "--board-cols/--board-rows must be at least 2 inner corners"
    );
    ensure!(args.timeout_s > 0.0, "--timeout-s must be positive");
    let url = frameset_url(&args.from);
    let agent = ureq::AgentBuilder::new()
        .timeout(Duration::from_secs_f64(args.timeout_s))
        .build();
    // Ask once before the session: an unreachable board or old firmware is said now, not
    // after the person has positioned the board and pressed Enter.
    let first = fetch_with_retries(&agent, &url, &args.from)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let board = Board {
        cols: args.board_cols,
        rows: args.board_rows,
        square_mm: 1.0,
    };
    let keys = stdin_keys();
    let mode = if args.wand {
        "wand wave: saving sets as fast as irtrackd serves them; `q` + Enter stops".to_string()
    } else if let Some(e) = args.every {
        format!("saving a set every {e} s; `q` + Enter stops")
    } else {
        "Enter saves a set, `q` + Enter stops".to_string()
    };
    let limit = args.count.map_or(String::new(), |n| format!(", up to {n} sets"));
    println!("{}", describe_cameras(&args.from, &first.header));
    println!("capturing from {url} into {}: {mode}{limit}", args.out.display());
    let mut index = next_index(&args.out);
    // Sets saved earlier without a timestamps file: rows for the new ones only would make a
    // replay skip the old ones, so the directory stays without (replay paces it at a set rate).
    let write_timestamps = index == 0 || args.out.join(TIMESTAMPS_FILE).exists();
    if !write_timestamps {
        eprintln!(
            "capture: {} holds sets without {TIMESTAMPS_FILE}; continuing without it (a replay paces these sets at [source.replay] fps)",
            args.out.display()
        );
    }
    let mut saved = 0u64;
    let mut both = 0u64;
    let mut last_set: Option<u64> = None;
    let mut coverage: Vec<Coverage> = Vec::new();
    let mut camera_count: Option<usize> = None;
    let started = Instant::now();
    let mut next_due = Instant::now();
    while args.count.is_none_or(|n| saved < n) {
        // Wait for the trigger of this mode; `q` ends the session in every mode.
        if args.wand || args.every.is_some() {
            if let Ok(Key::Quit) = keys.try_recv() {
                break;
            }
            if let Some(e) = args.every {
                let now = Instant::now();
                if now < next_due {
                    std::thread::sleep((next_due - now).min(Duration::from_millis(100)));
                    continue;
                }
                next_due += Duration::from_secs_f64(e);
            }
        } else {
            print!("Enter: save a set ({saved} so far) > ");
            std::io::stdout().flush().ok();
            match keys.recv() {
                Ok(Key::Capture) => {}
                Ok(Key::Quit | Key::Eof) | Err(_) => break,
            }
        }
        let set = fetch_with_retries(&agent, &url, &args.from)?;
        // The endpoint serves the newest set: asking faster than the cameras run repeats it.
        if last_set == Some(set.header.set_index) {
            if !args.wand {
                eprintln!(
                    "capture: set {} again (cameras slower than requests); skipped",
                    set.header.set_index
                );
            }
            continue;
        }
        last_set = Some(set.header.set_index);
        match camera_count {
            None => camera_count = Some(set.pgms.len()),
            Some(n) if n != set.pgms.len() => bail!(
                "irtrackd on {} now sends {} cameras, earlier {n}",
                args.from,
                set.pgms.len()
            ),
            Some(_) => {}
        }
        save_set(&args.out, index, &set)?;
        if write_timestamps {
            append_timestamps(&args.out, index, &set)?;
        }
        saved += 1;
        let name = format!("{index:06}");
        index += 1;
        if args.wand {
            if saved.is_multiple_of(50) || args.count == Some(saved) {
                println!(
                    "{saved} sets ({:.1} sets/s), last pairing error {} µs",
                    saved as f64 / started.elapsed().as_secs_f64().max(1e-9),
                    set.header.pairing_error_ns / 1000
                );
            }
            continue;
        }
        let found = detect_set(&set, &board, &mut coverage)?;
        if found.iter().all(Option::is_some) {
            both += 1;
        }
        print!("{}", report(saved, &name, &found, &coverage, both));
        std::io::stdout().flush().ok();
    }
    match camera_count {
        Some(n) => println!(
            "saved {saved} sets into {}/cam0..cam{}",
            args.out.display(),
            n.saturating_sub(1)
        ),
        None => println!("saved no sets into {}", args.out.display()),
    }
    if !args.wand && saved > 0 {
        println!(
            "next: host-tools calibrate --images {} --board-cols {} --board-rows {} --square-mm <SIZE> --out-dir <OUT>",
            args.out.display(),
            args.board_cols,
            args.board_rows
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A body as docs/http-api.md describes it, with `n` cameras of `w`×`h` 8-bit frames.
    pub(crate) fn body(n: usize, w: u32, h: u32) -> Vec<u8> {
        let pgm = |c: usize| {
            let mut v = format!("P5\n{w} {h}\n255\n").into_bytes();
            v.extend((0..w * h).map(|i| ((i as usize + c * 7) % 256) as u8));
            v
        };
        let cams: Vec<String> = (0..n)
            .map(|c| {
                format!(
                    "{{\"camera\":{c},\"width_px\":{w},\"height_px\":{h},\"bit_depth\":8,\"timestamp_ns\":{},\"sequence\":{},\"pgm_bytes\":{}}}",
                    1000 + c,
                    5 + c,
                    pgm(c).len()
                )
            })
            .collect();
        let mut b = format!(
            "{{\"set_index\":123,\"pairing_error_ns\":800,\"cameras\":[{}]}}\n",
            cams.join(",")
        )
        .into_bytes();
        for c in 0..n {
            b.extend(pgm(c));
        }
        b
    }

    #[test]
    fn parses_the_documented_format() {
        let set = FrameSet::parse(&body(3, 8, 4)).unwrap();
        assert_eq!(set.header.set_index, 123);
        assert_eq!(set.header.pairing_error_ns, 800);
        assert_eq!(set.header.cameras.len(), 3);
        assert_eq!(set.header.cameras[2].timestamp_ns, 1002);
        assert_eq!(set.pgms.len(), 3);
        assert!(set.pgms[1].starts_with(b"P5\n8 4\n255\n"));
        assert_eq!(set.pgms[1].len(), 11 + 32);
        assert_eq!(set.pgms[1][11], 7);
    }

    #[test]
    fn refuses_bodies_that_do_not_match_their_header() {
        let good = body(2, 8, 4);
        let e = |b: &[u8]| FrameSet::parse(b).unwrap_err().to_string();
        assert!(e(&good[..good.len() - 1]).contains("left in the body"));
        let mut extra = good.clone();
        extra.push(0);
        assert!(e(&extra).contains("after the last camera"));
        assert!(e(b"{\"set_index\":1}").contains("no header line"));
        assert!(e(b"<html>404</html>\n").contains("not the documented JSON"));
        let text = String::from_utf8_lossy(&good).into_owned();
        let wrong = text.replacen("\"width_px\":8", "\"width_px\":9", 1);
        assert!(e(wrong.as_bytes()).contains("PGM is 8x4, header says 9x4"));
        let swapped = text.replacen("\"camera\":0", "\"camera\":1", 1);
        assert!(e(swapped.as_bytes()).contains("in order"));
    }

    #[test]
    fn urls_get_the_default_port() {
        assert_eq!(
            frameset_url("board.local"),
            "http://board.local:7704/api/frameset"
        );
        assert_eq!(frameset_url("10.0.0.5:8080"), "http://10.0.0.5:8080/api/frameset");
        assert_eq!(frameset_url("http://b:7704/"), "http://b:7704/api/frameset");
    }

    #[test]
    fn coverage_grid_counts_cells() {
        let mut c = Coverage::new(800, 600);
        assert_eq!(c.fraction(), 0.0);
        c.add(&[
            Point2f::new(10.0, 10.0),
            Point2f::new(790.0, 590.0),
            Point2f::new(-5.0, 3.0),
        ]);
        assert_eq!(c.views, 1);
        assert!((c.fraction() - 2.0 / 48.0).abs() < 1e-12);
        let rows = c.rows();
        assert_eq!(rows[0], "+.......");
        assert_eq!(rows[5], ".......+");
        let text = report(
            1,
            "000000",
            &[Some(54), None],
            &[c.clone(), Coverage::new(800, 600)],
            0,
        );
        assert!(
            text.contains("cam0 board found (54 corners)") && text.contains("cam1 no board"),
            "{text}"
        );
        assert!(text.contains("[+.......]"), "{text}");
    }
}
