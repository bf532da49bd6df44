//! `host-tools capture`: takes synchronised frame sets from a running irtrackd for calibration.
//!
//! Each set comes from irtrackd's `GET /api/frameset` (docs/http-api.md): one JSON line, then
//! each camera's full-resolution frame as binary PGM. A set is saved as `DIR/cam0/NNNNNN.pgm`,
//! `DIR/cam1/NNNNNN.pgm`, … (one file name per set, the layout `calibrate`, `wand-calibrate` and
//! `track` read), on Enter or every `--every` seconds. Each checkerboard set is searched for the
//! board as it arrives, and the terminal shows per camera whether it was found and how much of
//! the image the board has covered so far, so the person holding it knows where views are
//! still missing. `--wand` saves sets as fast as irtrackd serves them (no board search).
//!
//! Across camera boards (`--from A --from B …`, docs/cluster.md "Calibration across boards"):
//! every board is asked at once, their sets are paired on CLOCK_REALTIME (each board's
//! monotonic timestamps plus the clock difference it serves, the clock the cluster pairs by)
//! within a tolerance (default half a frame period), and saved as one set. With `--params`
//! (the rig's parameter set, its placement) the cameras are numbered in the rig's order: each
//! board is known by the name it reports (`/status` → `cluster.board`), and each rig camera is
//! taken from the board and index its placement names, whatever the `--from` order. Without
//! it they are numbered board by board in `--from` order (and capture says so). A set whose
//! boards do not pair is refused, named, and never saved. The folder's `cameras.csv` names each
//! camera's board as the board reports itself, so `calibrate`/`wand-calibrate` write it as the
//! set's placement.

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail, ensure};
use opencv::core::{Mat, Point2f, Vector};
use opencv::imgcodecs;
use opencv::prelude::*;

use irtrack_core::params::CameraPlace;

use crate::calib::detect::{Board, find_corners};
use crate::cmd::keygen::load_params_file;

/// Default port of irtrackd's HTTP listener.
pub const DEFAULT_HTTP_PORT: u16 = 7704;
/// Coverage grid columns and rows per camera.
const GRID_COLS: usize = 8;
const GRID_ROWS: usize = 6;

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// The board running irtrackd: HOST or HOST:PORT (port 7704 if left out). Give it once per
    /// camera board to capture across boards. Without --params the cameras are numbered board
    /// by board in this order (so give the board of the rig's cameras 0, 1 first). Across
    /// boards, cameras.csv records each board by the name its /status reports (the placement
    /// calibrate and wand-calibrate then write).
    #[arg(long, value_name = "BOARD[:PORT]", required = true)]
    pub from: Vec<String>,
    /// The rig's parameter blob with its camera placement (the set pushed to the solver with
    /// push-params): cameras are numbered as the rig's, each taken from the board whose
    /// reported name (`[cluster] board`, its /status) and camera index the placement gives, in
    /// whatever order --from lists the boards.
    #[arg(long, value_name = "FILE")]
    pub params: Option<PathBuf>,
    /// Across boards: largest capture-time offset between boards' frames in one set, ms
    /// (default: half the frame period the boards show).
    #[arg(long, value_name = "MS")]
    pub tolerance_ms: Option<f64>,
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

/// `http://HOST:PORT` for `BOARD` or `BOARD:PORT`.
fn base_url(from: &str) -> String {
    let from = from.trim_start_matches("http://").trim_end_matches('/');
    let has_port = from
        .rsplit_once(':')
        .is_some_and(|(h, p)| !h.is_empty() && !h.ends_with(':') && p.parse::<u16>().is_ok());
    if has_port {
        format!("http://{from}")
    } else {
        format!("http://{from}:{DEFAULT_HTTP_PORT}")
    }
}

/// `http://HOST:PORT/api/frameset` for `BOARD` or `BOARD:PORT`.
pub fn frameset_url(from: &str) -> String {
    format!("{}/api/frameset", base_url(from))
}

/// `http://HOST:PORT/status` for `BOARD` or `BOARD:PORT`.
pub fn status_url(from: &str) -> String {
    format!("{}/status", base_url(from))
}

/// irtrackd's `/status` on `board` as JSON, or the HTTP status code it answered instead.
fn status_json(agent: &ureq::Agent, board: &str) -> anyhow::Result<Result<serde_json::Value, u16>> {
    let url = status_url(board);
    let body = match agent.get(&url).call() {
        Ok(r) => r
            .into_string()
            .with_context(|| format!("reading /status of irtrackd on {board}"))?,
        Err(ureq::Error::Status(code, _)) => return Ok(Err(code)),
        Err(ureq::Error::Transport(t)) => {
            bail!("cannot reach irtrackd on {board} ({url}): {t}; is the board on and irtrackd running?")
        }
    };
    let status =
        serde_json::from_str(&body).with_context(|| format!("/status of irtrackd on {board} is not JSON"))?;
    Ok(Ok(status))
}

/// `cluster.board` of a `/status` answer, if it names one.
fn cluster_board(status: &serde_json::Value) -> Option<String> {
    status
        .get("cluster")
        .and_then(|c| c.get("board"))
        .and_then(serde_json::Value::as_str)
        .filter(|n| !n.is_empty())
        .map(str::to_owned)
}

/// The name irtrackd on `board` reports for itself: `/status` → `cluster.board` (its
/// `[cluster] board`, the name a placement uses).
pub fn board_name(agent: &ureq::Agent, board: &str) -> anyhow::Result<String> {
    let status = status_json(agent, board)?.map_err(|code| {
        anyhow!("irtrackd on {board} answered {code} to GET /status; cannot tell its board name")
    })?;
    cluster_board(&status).ok_or_else(|| {
        anyhow!(
            "irtrackd on {board} reports no board name (/status has no cluster.board): --params needs camera boards \
             ([cluster] role = \"camera\" and board = \"…\", docs/cluster.md) or a solver with cameras of its own"
        )
    })
}

/// The board's name if it reports one (a camera board or solver); `None` for a standalone
/// board or firmware without `/status`, whose cameras.csv rows then carry the address.
pub fn reported_name(agent: &ureq::Agent, board: &str) -> anyhow::Result<Option<String>> {
    Ok(status_json(agent, board)?.ok().as_ref().and_then(cluster_board))
}

/// Why the boards given do not match the rig's placement. Every message names the board (as
/// reported, and as given to `--from`) and the camera.
#[derive(Debug, Clone, PartialEq)]
pub enum PlacementError {
    /// Two boards given report one name.
    SameName {
        /// The name both report.
        name: String,
        /// The first board as given to `--from`.
        first: String,
        /// The second board as given to `--from`.
        second: String,
    },
    /// A rig camera is placed on a board no `--from` reports.
    BoardNotGiven {
        /// The rig's camera.
        camera: usize,
        /// The board name its placement gives.
        board: String,
        /// Its index on that board.
        local_index: u8,
        /// The names of the boards given.
        given: Vec<String>,
    },
    /// A rig camera is placed on a camera the board does not serve.
    NoSuchCamera {
        /// The rig's camera.
        camera: usize,
        /// The board's name.
        board: String,
        /// The board as given to `--from`.
        from: String,
        /// Its index on that board.
        local_index: u8,
        /// Cameras the board serves.
        served: usize,
    },
    /// A camera of a board given is no rig camera.
    NotPlaced {
        /// The board's name.
        board: String,
        /// The board as given to `--from`.
        from: String,
        /// The camera's index on that board.
        local_index: usize,
    },
}

impl std::fmt::Display for PlacementError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlacementError::SameName { name, first, second } => write!(
                f,
                "boards {first} and {second} both report the name {name} ([cluster] board); each camera board needs its own name"
            ),
            PlacementError::BoardNotGiven {
                camera,
                board,
                local_index,
                given,
            } => write!(
                f,
                "rig camera {camera} is placed on board {board} (its camera {local_index}), but no --from board reports that name (they report: {}); give that board too",
                given.join(", ")
            ),
            PlacementError::NoSuchCamera {
                camera,
                board,
                from,
                local_index,
                served,
            } => write!(
                f,
                "rig camera {camera} is placed on board {board} ({from}) as its camera {local_index}, but that board serves {served} camera{}",
                if *served == 1 { "" } else { "s" }
            ),
            PlacementError::NotPlaced {
                board,
                from,
                local_index,
            } => write!(
                f,
                "camera {local_index} of board {board} ({from}) is not placed: no rig camera of the parameter set is on it; check the board's [source] cameras or the set's placement"
            ),
        }
    }
}

/// One board of a capture: as given to `--from`, its reported name, and its cameras.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardCameras {
    /// As given to `--from`.
    pub from: String,
    /// Its name (`/status` → `cluster.board`).
    pub name: String,
    /// Cameras it serves in a frame set.
    pub cameras: usize,
}

/// Two boards of one name, if any.
pub fn check_names(from: &[String], names: &[String]) -> Result<(), PlacementError> {
    for (i, n) in names.iter().enumerate() {
        if let Some(j) = names[..i].iter().position(|m| m == n) {
            return Err(PlacementError::SameName {
                name: n.clone(),
                first: from[j].clone(),
                second: from[i].clone(),
            });
        }
    }
    Ok(())
}

/// Where each rig camera comes from, in the rig's order: (board, in `boards`' order; camera on
/// that board), as the placement says. Every camera of every board must be placed, and every
/// placed camera served by a board given.
pub fn placement_order(
    placement: &[CameraPlace],
    boards: &[BoardCameras],
) -> Result<Vec<(usize, usize)>, PlacementError> {
    let from: Vec<String> = boards.iter().map(|b| b.from.clone()).collect();
    let names: Vec<String> = boards.iter().map(|b| b.name.clone()).collect();
    check_names(&from, &names)?;
    let mut order = Vec::with_capacity(placement.len());
    for (camera, pl) in placement.iter().enumerate() {
        let b = names
            .iter()
            .position(|n| *n == pl.board)
            .ok_or_else(|| PlacementError::BoardNotGiven {
                camera,
                board: pl.board.clone(),
                local_index: pl.local_index,
                given: names.clone(),
            })?;
        let c = usize::from(pl.local_index);
        if c >= boards[b].cameras {
            return Err(PlacementError::NoSuchCamera {
                camera,
                board: pl.board.clone(),
                from: boards[b].from.clone(),
                local_index: pl.local_index,
                served: boards[b].cameras,
            });
        }
        order.push((b, c));
    }
    for (b, board) in boards.iter().enumerate() {
        for c in 0..board.cameras {
            if !order.contains(&(b, c)) {
                return Err(PlacementError::NotPlaced {
                    board: board.name.clone(),
                    from: board.from.clone(),
                    local_index: c,
                });
            }
        }
    }
    Ok(order)
}

/// Board by board in the order given, each board's cameras in its own order.
pub fn from_order(counts: &[usize]) -> Vec<(usize, usize)> {
    counts
        .iter()
        .enumerate()
        .flat_map(|(b, n)| (0..*n).map(move |c| (b, c)))
        .collect()
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

/// Refused sets in a row after which a capture across boards gives up.
const MAX_REFUSED_IN_A_ROW: u32 = 10;

/// Why the boards' sets were not paired into one.
#[derive(Debug, Clone, PartialEq)]
pub enum PairError {
    /// This board's set has no realtime clock difference (irtrackd older than the field).
    NoClock {
        /// The board as given to `--from`.
        board: String,
    },
    /// This board's frames are `offset_ns` from the first board's (CLOCK_REALTIME), beyond
    /// the tolerance.
    Offset {
        /// The board as given to `--from`.
        board: String,
        /// The first board, whose first camera the others are measured from.
        reference: String,
        /// This board's first camera minus the reference's, CLOCK_REALTIME.
        offset_ns: i128,
        /// The largest offset allowed.
        tolerance_ns: i128,
    },
}

impl std::fmt::Display for PairError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PairError::NoClock { board } => write!(
                f,
                "irtrackd on {board} does not serve its realtime clock difference \
                 (realtime_minus_monotonic_ns, docs/frameset.md); update its firmware to capture across boards"
            ),
            PairError::Offset {
                board,
                reference,
                offset_ns,
                tolerance_ns,
            } => write!(
                f,
                "board {board}'s frames are {:+.3} ms from board {reference}'s (tolerance {:.3} ms, CLOCK_REALTIME)",
                *offset_ns as f64 / 1e6,
                *tolerance_ns as f64 / 1e6
            ),
        }
    }
}

/// Pairs one set per board into one set: camera `i` is `order[i]` (board, camera on that
/// board; [`from_order`] or [`placement_order`]), timestamps on CLOCK_REALTIME,
/// `pairing_error_ns` the spread over all cameras. Refused when a board has no clock difference
/// or its first camera is more than `tolerance_ns` from the first board's first camera.
/// `set_index` is the first board's.
pub fn pair_sets(
    boards: &[String],
    sets: Vec<FrameSet>,
    order: &[(usize, usize)],
    tolerance_ns: i128,
) -> Result<FrameSet, PairError> {
    let mut reference_ns: Option<i128> = None;
    let mut worst: Option<PairError> = None;
    for (board, set) in boards.iter().zip(&sets) {
        let t = set
            .header
            .realtime_ns(0)
            .ok_or_else(|| PairError::NoClock { board: board.clone() })?;
        let t0 = *reference_ns.get_or_insert(t);
        let offset_ns = t - t0;
        let beyond = offset_ns.abs() > tolerance_ns;
        let worse = match &worst {
            Some(PairError::Offset { offset_ns: w, .. }) => offset_ns.abs() > w.abs(),
            _ => true,
        };
        if beyond && worse {
            worst = Some(PairError::Offset {
                board: board.clone(),
                reference: boards[0].clone(),
                offset_ns,
                tolerance_ns,
            });
        }
    }
    if let Some(e) = worst {
        return Err(e);
    }
    Ok(arrange(sets, order, true))
}

/// One set of the cameras `order` names ((board, camera on that board) per camera), numbered
/// in that order. `realtime`: timestamps moved to CLOCK_REALTIME (every set has its clock
/// difference) and the pairing error taken over all cameras; otherwise they stay as served and
/// the first set's header fields are kept.
pub fn arrange(sets: Vec<FrameSet>, order: &[(usize, usize)], realtime: bool) -> FrameSet {
    let set_index = sets.first().map_or(0, |s| s.header.set_index);
    let first_error_ns = sets.first().map_or(0, |s| s.header.pairing_error_ns);
    let first_clock = sets.first().and_then(|s| s.header.realtime_minus_monotonic_ns);
    let headers: Vec<FrameSetHeader> = sets.iter().map(|s| s.header.clone()).collect();
    // Each frame is moved, not copied: taken out of its board's set once.
    let mut frames: Vec<Vec<Option<Vec<u8>>>> = sets
        .into_iter()
        .map(|s| s.pgms.into_iter().map(Some).collect())
        .collect();
    let mut cameras = Vec::with_capacity(order.len());
    let mut pgms = Vec::with_capacity(order.len());
    let (mut lo, mut hi) = (i128::MAX, i128::MIN);
    for &(b, c) in order {
        let header = &headers[b];
        let cam = &header.cameras[c];
        let timestamp_ns = if realtime {
            let t = header.realtime_ns(c).unwrap_or(0).max(0);
            lo = lo.min(t);
            hi = hi.max(t);
            u64::try_from(t).unwrap_or(u64::MAX)
        } else {
            cam.timestamp_ns
        };
        cameras.push(CameraHeader {
            camera: cameras.len() as u32,
            timestamp_ns,
            ..cam.clone()
        });
        pgms.push(frames[b][c].take().unwrap_or_default());
    }
    let (pairing_error_ns, realtime_minus_monotonic_ns) = if realtime {
        (u64::try_from(hi - lo).unwrap_or(0), Some(0))
    } else {
        (first_error_ns, first_clock)
    };
    FrameSet {
        header: FrameSetHeader {
            set_index,
            pairing_error_ns,
            cameras,
            realtime_minus_monotonic_ns,
        },
        pgms,
    }
}

/// Frame period a board shows between two of its sets (camera 0's timestamps over its frame
/// counter), if the sets are different frames.
fn frame_period_ns(a: &FrameSet, b: &FrameSet) -> Option<u64> {
    let (x, y) = (a.header.cameras.first()?, b.header.cameras.first()?);
    let frames = y.sequence.checked_sub(x.sequence).filter(|n| *n > 0)?;
    let dt_ns = y.timestamp_ns.checked_sub(x.timestamp_ns).filter(|d| *d > 0)?;
    Some(dt_ns / frames)
}

/// The boards of one capture and how their sets are fetched and paired.
struct Boards {
    agent: ureq::Agent,
    /// (name as given, URL) per board, in `--from` order.
    boards: Vec<(String, String)>,
    /// Pairing tolerance across boards; unused with one board.
    tolerance_ns: i128,
}

impl Boards {
    fn names(&self) -> Vec<String> {
        self.boards.iter().map(|(b, _)| b.clone()).collect()
    }

    /// One set from every board, asked at the same time (so the frames are close in time);
    /// the first failing board's error (it names the board).
    fn fetch_each(&self) -> anyhow::Result<Vec<FrameSet>> {
        std::thread::scope(|s| {
            let handles: Vec<_> = self
                .boards
                .iter()
                .map(|(board, url)| {
                    let agent = &self.agent;
                    s.spawn(move || fetch_with_retries(agent, url, board))
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .unwrap_or_else(|_| Err(anyhow!("a fetch thread panicked")))
                })
                .collect()
        })
    }
}

// `DIR/cameras.csv` for a capture across boards (its one home, reader included, is
// `placement`): the folder says where each `camN/` came from, and `calibrate`/`wand-calibrate`
// write it as the set's placement. A folder holding sets of other boards (or of boards in
// another order) is refused instead of mixed.
use crate::placement::CAMERAS_FILE;

/// `camera,board,board_camera,from` per camera of `order`. Per board: `names` its reported
/// name (`None`: it reports none), `from` as given to `--from`. `board` is the name, else the
/// address (as files before the `from` column); `from` is the address when `board` is a name
/// and empty when it is not, so a reader tells names from addresses.
fn cameras_csv(names: &[Option<String>], from: &[String], order: &[(usize, usize)]) -> String {
    let mut s = String::from("camera,board,board_camera,from\n");
    for (g, (b, c)) in order.iter().enumerate() {
        match &names[*b] {
            Some(name) => s.push_str(&format!("{g},{name},{c},{}\n", from[*b])),
            None => s.push_str(&format!("{g},{},{c},\n", from[*b])),
        }
    }
    s
}

/// `→ cam2..cam3` (one board's cameras, in its own order, numbered consecutively) or
/// `→ cam3, cam0` (placed elsewhere in the rig).
fn camera_names(board: usize, order: &[(usize, usize)]) -> String {
    let mut mine: Vec<(usize, usize)> = order
        .iter()
        .enumerate()
        .filter(|(_, (b, _))| *b == board)
        .map(|(g, (_, c))| (*c, g))
        .collect();
    mine.sort_unstable();
    let globals: Vec<usize> = mine.iter().map(|(_, g)| *g).collect();
    match (globals.first(), globals.last()) {
        (Some(a), Some(z)) if globals.windows(2).all(|w| w[1] == w[0] + 1) => {
            format!("cam{a}..cam{z}")
        }
        _ => globals
            .iter()
            .map(|g| format!("cam{g}"))
            .collect::<Vec<_>>()
            .join(", "),
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

/// One set's board search from its thread: set number, name, image sizes, corners per camera.
type SearchResult = (
    u64,
    String,
    Vec<(u32, u32)>,
    anyhow::Result<Vec<Option<Vec<Point2f>>>>,
);

/// The board search of one set's images (run on a thread of its own).
/// Live board searches allowed to run at once: one per core. Each holds a copy of its set's
/// frames, so without a bound a run of slow views would pile up threads and memory.
fn max_live_searches() -> usize {
    std::thread::available_parallelism().map_or(2, |n| n.get()).max(1)
}

fn search_set(pgms: &[Vec<u8>], board: &Board) -> anyhow::Result<Vec<Option<Vec<Point2f>>>> {
    pgms.iter()
        .enumerate()
        .map(|(c, pgm)| {
            let img = grey_mat(pgm).with_context(|| format!("camera {c}"))?;
            find_corners(&img, board)
        })
        .collect()
}

/// Adds a search's corners to the coverage grids; corners found per camera.
fn apply_search(
    dims: &[(u32, u32)],
    found: Vec<Option<Vec<Point2f>>>,
    coverage: &mut Vec<Coverage>,
) -> Vec<Option<usize>> {
    found
        .into_iter()
        .enumerate()
        .map(|(c, corners)| {
            while coverage.len() <= c {
                let (w, h) = dims.get(coverage.len()).copied().unwrap_or((1, 1));
                coverage.push(Coverage::new(w, h));
            }
            corners.map(|k| {
                coverage[c].add(&k);
                k.len()
            })
        })
        .collect()
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
    if let Some(t) = args.tolerance_ms {
        ensure!(
            t.is_finite() && t > 0.0,
            "--tolerance-ms {t} must be a positive number of milliseconds"
        );
    }
    for (i, b) in args.from.iter().enumerate() {
        ensure!(
            !args.from[..i].contains(b),
            "--from {b} is given twice; give each board once"
        );
    }
    let agent = ureq::AgentBuilder::new()
        .timeout(Duration::from_secs_f64(args.timeout_s))
        .build();
    let mut boards = Boards {
        agent,
        boards: args.from.iter().map(|b| (b.clone(), frameset_url(b))).collect(),
        tolerance_ns: 0,
    };
    let multi = boards.boards.len() > 1;
    // With the rig's placement: the set is read and every board's name asked first, so a
    // wrong file, a board that is no camera board or two boards of one name are said now.
    let placed = match &args.params {
        Some(path) => {
            let rig = load_params_file(path)?.rig;
            ensure!(
                !rig.placement.is_empty(),
                "{}: this parameter set places no camera on a board (a single board's set); give the rig's set, the one pushed to the solver, whose placement names each camera's board (docs/cluster.md, \"Roles\")",
                path.display()
            );
            let names = args
                .from
                .iter()
                .map(|b| board_name(&boards.agent, b))
                .collect::<anyhow::Result<Vec<String>>>()?;
            check_names(&args.from, &names).map_err(|e| anyhow!("{e}"))?;
            Some((path, rig.placement, names))
        }
        None => None,
    };
    // Without the placement, across boards: each board's name if it reports one, for
    // cameras.csv (calibrate writes it as the set's placement).
    let reported = if placed.is_none() && multi {
        let names = args
            .from
            .iter()
            .map(|b| reported_name(&boards.agent, b))
            .collect::<anyhow::Result<Vec<Option<String>>>>()?;
        // Two boards of one name would place two cameras on one board camera. A board
        // without a name is keyed by its address (never equal: --from is given once each).
        let keys: Vec<String> = names
            .iter()
            .zip(&args.from)
            .map(|(n, f)| n.clone().unwrap_or_else(|| format!("\0{f}")))
            .collect();
        check_names(&args.from, &keys).map_err(|e| anyhow!("{e}"))?;
        names
    } else {
        vec![None; args.from.len()]
    };
    // Ask once before the session: an unreachable board or old firmware is said now, not
    // after the person has positioned the board and pressed Enter.
    let firsts = boards.fetch_each()?;
    let counts: Vec<usize> = firsts.iter().map(|s| s.pgms.len()).collect();
    // Which board and camera each saved camera is, and how cameras.csv names the boards (by
    // the names they report, so calibrate can write the placement).
    let (order, labels) = match &placed {
        Some((path, placement, names)) => {
            let cams: Vec<BoardCameras> = args
                .from
                .iter()
                .zip(names)
                .zip(&counts)
                .map(|((from, name), n)| BoardCameras {
                    from: from.clone(),
                    name: name.clone(),
                    cameras: *n,
                })
                .collect();
            let order = placement_order(placement, &cams)
                .map_err(|e| anyhow!("{e} (placement of {})", path.display()))?;
            (order, names.iter().cloned().map(Some).collect::<Vec<_>>())
        }
        None => (from_order(&counts), reported.clone()),
    };
    if multi {
        for (board, set) in args.from.iter().zip(&firsts) {
            if set.header.realtime_minus_monotonic_ns.is_none() {
                bail!("{}", PairError::NoClock { board: board.clone() });
            }
        }
        // A second set per board shows the frame period: the default tolerance is half of it,
        // as in the cluster's pairing.
        boards.tolerance_ns = match args.tolerance_ms {
            Some(t) => (t * 1e6) as i128,
            None => {
                let seconds = boards.fetch_each()?;
                let period = firsts
                    .iter()
                    .zip(&seconds)
                    .filter_map(|(a, b)| frame_period_ns(a, b))
                    .min()
                    .ok_or_else(|| {
                        anyhow!(
                            "cannot tell the cameras' frame period from two sets of each board (no newer frame came); give --tolerance-ms"
                        )
                    })?;
                i128::from(period / 2)
            }
        };
    }
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
    for (b, ((board, _), set)) in boards.boards.iter().zip(&firsts).enumerate() {
        let label = match &placed {
            Some((_, _, names)) => format!("{} at {board}", names[b]),
            None => board.clone(),
        };
        if multi || placed.is_some() {
            println!(
                "{} → {}",
                describe_cameras(&label, &set.header),
                camera_names(b, &order)
            );
        } else {
            println!("{}", describe_cameras(board, &set.header));
        }
    }
    match &placed {
        Some((path, _, _)) => println!(
            "cameras numbered in the rig's order, as the placement in {} puts them on the boards",
            path.display()
        ),
        None if multi => println!(
            "cameras numbered board by board in --from order, not by the rig's placement; give --params <the rig's parameter set> to number them as the rig's cameras"
        ),
        None => {}
    }
    if placed.is_none() && multi {
        let unnamed: Vec<&str> = args
            .from
            .iter()
            .zip(&reported)
            .filter(|(_, n)| n.is_none())
            .map(|(f, _)| f.as_str())
            .collect();
        if unnamed.is_empty() {
            let named: Vec<String> = args
                .from
                .iter()
                .zip(reported.iter().flatten())
                .map(|(f, n)| format!("{n} ({f})"))
                .collect();
            println!(
                "boards by the names they report: {}; {CAMERAS_FILE} records them, and calibrate/wand-calibrate write them as the set's placement (so a set calibrated from this folder is placed as captured, whatever the --from order)",
                named.join(", ")
            );
        } else {
            println!(
                "board {} reports no name ([cluster] board): {CAMERAS_FILE} holds its address and calibrate writes no placement (give it --placement for a cluster solver)",
                unnamed.join(", ")
            );
        }
    }
    if multi {
        println!(
            "pairing the boards' frames on CLOCK_REALTIME within ±{:.3} ms",
            boards.tolerance_ns as f64 / 1e6
        );
    }
    if multi || placed.is_some() {
        println!("capturing into {}: {mode}{limit}", args.out.display());
        let csv = cameras_csv(&labels, &args.from, &order);
        let path = args.out.join(CAMERAS_FILE);
        match std::fs::read_to_string(&path) {
            Ok(old) if old.starts_with("camera,board,board_camera\n") => bail!(
                "{} was written by an older capture (its {CAMERAS_FILE} has no from column, so no board names for the placement); use another --out",
                args.out.display()
            ),
            Ok(old) if old != csv => bail!(
                "{} holds sets of other boards or another camera order ({}); use another --out",
                args.out.display(),
                path.display()
            ),
            Ok(_) => {}
            Err(_) if next_index(&args.out) > 0 => bail!(
                "{} holds sets without {CAMERAS_FILE} (from one board); use another --out",
                args.out.display()
            ),
            Err(_) => crate::cmd::convert_params::write_atomically(&path, csv.as_bytes())?,
        }
    } else {
        println!(
            "capturing from {} into {}: {mode}{limit}",
            boards.boards[0].1,
            args.out.display()
        );
    }
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
    let mut last_sets: Option<Vec<u64>> = None;
    let mut refused = 0u64;
    let mut refused_in_a_row = 0u32;
    let mut coverage: Vec<Coverage> = Vec::new();
    let mut camera_count: Option<usize> = None;
    let started = Instant::now();
    let mut next_due = Instant::now();
    let (search_tx, search_rx) = mpsc::channel::<SearchResult>();
    let mut searching = 0usize;
    // Sets saved without a live board search (see max_live_searches).
    let mut skipped_searches = 0usize;
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
        let sets = boards.fetch_each()?;
        // The endpoint serves the newest set: asking faster than the cameras run repeats it.
        let set_indices: Vec<u64> = sets.iter().map(|s| s.header.set_index).collect();
        if last_sets.as_ref() == Some(&set_indices) {
            if !args.wand {
                eprintln!(
                    "capture: set {} again (cameras slower than requests); skipped",
                    set_indices
                        .iter()
                        .map(u64::to_string)
                        .collect::<Vec<_>>()
                        .join("/")
                );
            }
            continue;
        }
        last_sets = Some(set_indices);
        for ((board, _), (set, n)) in boards.boards.iter().zip(sets.iter().zip(&counts)) {
            ensure!(
                set.pgms.len() == *n,
                "irtrackd on {board} now sends {} cameras, earlier {n}",
                set.pgms.len()
            );
        }
        let set = if multi {
            match pair_sets(&boards.names(), sets, &order, boards.tolerance_ns) {
                Ok(set) => {
                    refused_in_a_row = 0;
                    set
                }
                Err(e) => {
                    // Never saved mismatched: said, counted, and asked again.
                    refused += 1;
                    refused_in_a_row += 1;
                    ensure!(
                        refused_in_a_row < MAX_REFUSED_IN_A_ROW,
                        "{MAX_REFUSED_IN_A_ROW} sets in a row refused, the last: {e}; are the boards' clocks synchronised (docs/cluster.md, \"Clocks\")?"
                    );
                    eprintln!("capture: set refused, not saved: {e}");
                    continue;
                }
            }
        } else {
            arrange(sets, &order, false)
        };
        camera_count = Some(set.pgms.len());
        save_set(&args.out, index, &set)?;
        if write_timestamps {
            append_timestamps(&args.out, index, &set)?;
        }
        saved += 1;
        let name = format!("{index:06}");
        index += 1;
        if args.wand {
            if saved.is_multiple_of(50) || args.count == Some(saved) {
                let refusals = if multi {
                    format!(", {refused} refused")
                } else {
                    String::new()
                };
                println!(
                    "{saved} sets ({:.1} sets/s), last pairing error {} µs{refusals}",
                    saved as f64 / started.elapsed().as_secs_f64().max(1e-9),
                    set.header.pairing_error_ns / 1000
                );
            }
            continue;
        }
        // The board search runs on its own thread: OpenCV's corner search takes seconds on
        // some views (measured: 4.4 s for one set of four VGA frames, 0.2 s for most), and
        // with --every a stalled loop would skip the poses shown meanwhile.
        // The pairing is known now; it is reported whether or not the board search keeps up.
        if multi {
            println!(
                "set {saved}: boards paired within {} µs ({refused} sets refused so far)",
                set.header.pairing_error_ns / 1000
            );
        }
        let dims: Vec<(u32, u32)> = set
            .header
            .cameras
            .iter()
            .map(|c| (c.width_px, c.height_px))
            .collect();
        if searching >= max_live_searches() {
            // Slow views piled up: searching this set too would only add to the backlog and
            // slow the capture loop. The set is saved; calibrate searches it like every other.
            println!(
                "set {saved}: saved; live board search skipped ({searching} still running), calibrate will search it"
            );
            skipped_searches += 1;
            std::io::stdout().flush().ok();
            continue;
        }
        let (pgms, tx) = (set.pgms.clone(), search_tx.clone());
        std::thread::spawn(move || {
            let _ = tx.send((saved, name, dims, search_set(&pgms, &board)));
        });
        searching += 1;
        let budget = args.every.map(|e| Duration::from_secs_f64(e * 0.75));
        let mut mine = false;
        while !mine {
            let got = match budget {
                Some(b) => search_rx.recv_timeout(b).ok(),
                None => search_rx.recv().ok(),
            };
            let Some((n, nm, dims, found)) = got else {
                println!("set {saved}: board search still running (slow view); its result follows when done");
                break;
            };
            searching -= 1;
            mine = n == saved;
            let found = apply_search(&dims, found?, &mut coverage);
            if found.iter().all(Option::is_some) {
                both += 1;
            }
            print!("{}", report(n, &nm, &found, &coverage, both));
        }
        std::io::stdout().flush().ok();
    }
    // Searches still running: their results count too (nothing saved goes unreported).
    while searching > 0 {
        let Ok((n, nm, dims, found)) = search_rx.recv_timeout(Duration::from_secs(120)) else {
            eprintln!(
                "capture: {searching} board search(es) did not finish within 2 min; calibrate searches the saved images again"
            );
            break;
        };
        searching -= 1;
        let found = apply_search(&dims, found?, &mut coverage);
        if found.iter().all(Option::is_some) {
            both += 1;
        }
        print!("{}", report(n, &nm, &found, &coverage, both));
    }
    let refusals = if multi {
        format!(" ({refused} refused: boards not paired)")
    } else {
        String::new()
    };
    if skipped_searches > 0 {
        println!(
            "{skipped_searches} saved set(s) had no live board search (slow views kept the searches busy); calibrate searches them"
        );
    }
    match camera_count {
        Some(n) => println!(
            "saved {saved} sets into {}/cam0..cam{}{refusals}",
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

    /// Board b's monotonic clock started at another time; its realtime difference puts its
    /// frame 2 ms after board a's. Cameras are numbered a's first, then b's.
    #[test]
    fn pairs_boards_on_the_realtime_clock_and_refuses_offsets() {
        let mut a = FrameSet::parse(&body(2, 8, 4)).unwrap(); // timestamps 1000, 1001
        let mut b = FrameSet::parse(&body(1, 8, 4)).unwrap();
        a.header.realtime_minus_monotonic_ns = Some(10_000_000_000);
        b.header.cameras[0].timestamp_ns = 6_002_001_000;
        b.header.realtime_minus_monotonic_ns = Some(4_000_000_000);
        let names = ["a".to_string(), "b".to_string()];
        let order = from_order(&[2, 1]);
        assert_eq!(order, [(0, 0), (0, 1), (1, 0)]);
        let paired = pair_sets(&names, vec![a.clone(), b.clone()], &order, 4_166_666).unwrap();
        let cams = &paired.header.cameras;
        assert_eq!(cams.iter().map(|c| c.camera).collect::<Vec<_>>(), [0, 1, 2]);
        assert_eq!(
            cams.iter().map(|c| c.timestamp_ns).collect::<Vec<_>>(),
            [10_000_001_000, 10_000_001_001, 10_002_001_000]
        );
        assert_eq!(paired.header.pairing_error_ns, 2_000_000);
        assert_eq!(paired.pgms[2], b.pgms[0]);
        assert_eq!(paired.pgms[1], a.pgms[1]);

        let e = pair_sets(&names, vec![a.clone(), b.clone()], &order, 1_000_000).unwrap_err();
        assert_eq!(
            e.to_string(),
            "board b's frames are +2.000 ms from board a's (tolerance 1.000 ms, CLOCK_REALTIME)"
        );
        // The other way round the offset is negative.
        let e = pair_sets(
            &["b".into(), "a".into()],
            vec![b.clone(), a.clone()],
            &from_order(&[1, 2]),
            1_000_000,
        )
        .unwrap_err();
        assert!(e.to_string().starts_with("board a's frames are -2.000 ms"), "{e}");
        // The rig's order: b's camera first, then a's cameras the other way round.
        let placed = [(1, 0), (0, 1), (0, 0)];
        let paired = pair_sets(&names, vec![a.clone(), b.clone()], &placed, 4_166_666).unwrap();
        let cams = &paired.header.cameras;
        assert_eq!(cams.iter().map(|c| c.camera).collect::<Vec<_>>(), [0, 1, 2]);
        assert_eq!(
            cams.iter().map(|c| c.timestamp_ns).collect::<Vec<_>>(),
            [10_002_001_000, 10_000_001_001, 10_000_001_000]
        );
        assert_eq!(
            paired.pgms,
            [b.pgms[0].clone(), a.pgms[1].clone(), a.pgms[0].clone()]
        );
        assert_eq!(
            cameras_csv(
                &[Some("a".into()), Some("b".into())],
                &["h0".into(), "h1:7704".into()],
                &placed
            ),
            "camera,board,board_camera,from\n0,b,0,h1:7704\n1,a,1,h0\n2,a,0,h0\n"
        );
        assert_eq!(camera_names(0, &placed), "cam2, cam1");
        assert_eq!(camera_names(1, &placed), "cam0..cam0");
        b.header.realtime_minus_monotonic_ns = None;
        assert_eq!(
            pair_sets(&names, vec![a, b], &order, 4_166_666).unwrap_err(),
            PairError::NoClock { board: "b".into() }
        );
        assert_eq!(
            cameras_csv(&[None, Some("b".into())], &names, &order),
            "camera,board,board_camera,from\n0,a,0,\n1,a,1,\n2,b,0,b\n"
        );
    }

    fn place(p: &[(&str, u8)]) -> Vec<CameraPlace> {
        p.iter()
            .map(|(b, i)| CameraPlace {
                board: (*b).into(),
                local_index: *i,
            })
            .collect()
    }

    fn boards(b: &[(&str, &str, usize)]) -> Vec<BoardCameras> {
        b.iter()
            .map(|(from, name, n)| BoardCameras {
                from: (*from).into(),
                name: (*name).into(),
                cameras: *n,
            })
            .collect()
    }

    /// Boards given in any order: the cameras come out in the rig's order; every mismatch
    /// is named with board and camera.
    #[test]
    fn placement_orders_the_cameras_and_names_each_mismatch() {
        let rig = place(&[("b0", 0), ("b0", 1), ("b1", 0), ("b1", 1)]);
        let order = placement_order(&rig, &boards(&[("h1", "b1", 2), ("h0", "b0", 2)])).unwrap();
        assert_eq!(order, [(1, 0), (1, 1), (0, 0), (0, 1)]);
        let e = |p: &[CameraPlace], b: &[(&str, &str, usize)]| {
            placement_order(p, &boards(b)).unwrap_err().to_string()
        };
        assert_eq!(
            e(&rig, &[("h0", "b0", 2), ("h1", "b0", 2)]),
            "boards h0 and h1 both report the name b0 ([cluster] board); each camera board needs its own name"
        );
        assert_eq!(
            e(&rig, &[("h0", "b0", 2), ("h2", "b2", 2)]),
            "rig camera 2 is placed on board b1 (its camera 0), but no --from board reports that name (they report: b0, b2); give that board too"
        );
        assert_eq!(
            e(&rig, &[("h0", "b0", 2), ("h1", "b1", 1)]),
            "rig camera 3 is placed on board b1 (h1) as its camera 1, but that board serves 1 camera"
        );
        assert_eq!(
            e(&rig, &[("h0", "b0", 3), ("h1", "b1", 2)]),
            "camera 2 of board b0 (h0) is not placed: no rig camera of the parameter set is on it; check the board's [source] cameras or the set's placement"
        );
        // A board the rig does not use at all.
        assert!(
            e(&rig, &[("h0", "b0", 2), ("h1", "b1", 2), ("h9", "b9", 1)])
                .starts_with("camera 0 of board b9 (h9) is not placed"),
        );
    }

    #[test]
    fn urls_get_the_default_port() {
        assert_eq!(
            frameset_url("board.local"),
            "http://board.local:7704/api/frameset"
        );
        assert_eq!(frameset_url("10.0.0.5:8080"), "http://10.0.0.5:8080/api/frameset");
        assert_eq!(frameset_url("http://b:7704/"), "http://b:7704/api/frameset");
        assert_eq!(status_url("board.local"), "http://board.local:7704/status");
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
