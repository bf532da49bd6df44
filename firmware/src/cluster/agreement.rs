//! The solver's check that its boards agree (docs/cluster.md, "Do the boards agree?").
//!
//! A set's cameras come from several boards, each with its own clock and its own frames. A
//! board whose timestamps do not say when its frames were exposed (a wrong clock, a replay
//! started at another moment, a frame paired with its neighbour) or whose cameras moved since
//! the calibration gives rays that miss the other boards' point. The tracker already leaves
//! out a camera whose ray misses the point by more than `max_gap_mm`; what it cannot know is
//! which cameras belong together. So after every solve:
//!
//! - a camera with usable blobs that the point does not use, whose nearest ray misses it by
//!   more than `max_gap_mm` (the tracker's own gate), *disagrees*; a board disagrees when its
//!   cameras saw the marker and none of them supports the point;
//! - a point supported by two or more boards is published, a disagreeing board's cameras
//!   being left out (the majority decides); a point supported by one board while another
//!   board disagrees is refused: nothing says which of the two is right;
//! - a set whose boards give no common point at all is diagnosed board by board (each board
//!   with two cameras solves its own point) and counts against the boards involved;
//! - a board that disagrees in a quarter of its recent sets is *suspect*: its cameras are left
//!   out of every set until it agrees again (checked on the full solve each set), and a fault
//!   names it. With two boards disagreeing and no third to decide, both are suspect (no
//!   position from them) unless one of them has a measured clock offset and the other not.
//!
//! The cause is told from the disagreeing camera's reprojection error against the others'
//! point and its image velocity along its track: a miss along the motion, explained by a
//! time shift Δ (miss ≈ velocity · Δ), is a clock or pairing fault; a miss while the marker
//! stands still is calibration.

use irtrack_core::pipeline::{CameraResidual, MAX_CAMERAS, Measurement, TrackStatus, Tracker};
use nalgebra::Vector3;

/// Weight of one set in a pair of boards' disagreement share (about the last 16 sets count).
const EWMA_ALPHA: f64 = 1.0 / 16.0;
/// Two boards disagree from this share of the sets that compared them ...
const PAIR_ON: f64 = 0.25;
/// ... after at least this many comparisons ...
const MIN_EVIDENCE: u64 = 4;
/// ... and agree again below this share.
const PAIR_OFF: f64 = 0.05;
/// Below this image speed (px/s) the marker counts as standing still: a miss then is no time
/// shift (at 120 fps, 0.17 px per frame: the centroid noise of a still marker).
const STILL_PX_S: f64 = 20.0;
/// Weight kept by the past misses at each new one in the time-shift estimate.
const SHIFT_DECAY: f64 = 0.95;
/// Below this speed of the point (mm/s) the marker stands still.
const STILL_MM_S: f64 = 5.0;

/// Why a board's rays miss the others', as far as the misses tell.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    /// The misses follow the marker's motion (a time shift explains them): its clock, its
    /// timestamps or the pairing of its frames.
    Clock,
    /// The misses stay while the marker stands still: the calibration (a camera moved, or the
    /// parameter set is not this rig's).
    Calibration,
    /// Not enough moving or still misses to tell.
    Unknown,
}

/// One board's agreement with the others.
#[derive(Debug, Clone, Default)]
pub struct BoardAgreement {
    /// The largest disagreement share (EWMA over the sets that compared them) between it and
    /// another board.
    pub share: f64,
    /// Sets in which it could be compared with another board.
    pub compared: u64,
    /// Sets in which it disagreed.
    pub disagreed: u64,
    /// Sets published without its cameras because they disagreed or it is suspect.
    pub dropped: u64,
    /// Its cameras are left out of every set.
    pub suspect: bool,
    /// Its measured clock offset says its clock runs ahead of the solver's by more than a
    /// healthy board's ever does while another board's does not: its timestamps are late,
    /// by at least that much, whether or not its rays miss by more than the gate. Its cameras
    /// are left out of every set.
    pub clock_ahead: bool,
    /// How far its rays missed the others' point when it disagreed (EWMA, mm).
    pub miss_mm: Option<f64>,
    /// Its reprojection error against the others' point when it disagreed (EWMA, px).
    pub miss_px: Option<f64>,
    /// The time shift that explains its misses (EWMA, ms; positive: its frames show later
    /// instants than their timestamps say, relative to the other boards).
    pub shift_ms: Option<f64>,
    /// Misses a time shift along the motion explains.
    pub time_like: u64,
    /// Σ residual·velocity and Σ |velocity|² of those misses (decaying): their least-squares
    /// time shift, which weights the fast misses most (slow ones say little about time).
    rv_sum: f64,
    vv_sum: f64,
    /// Misses while the marker stood still.
    pub still: u64,
    /// The board it last disagreed with when no majority could decide (`None`: outvoted by
    /// two or more boards, or never).
    pub peer: Option<usize>,
}

impl BoardAgreement {
    /// The likely cause of its disagreement.
    pub fn cause(&self) -> Cause {
        if self.time_like > 0 && self.time_like >= self.still {
            Cause::Clock
        } else if self.still > 0 {
            Cause::Calibration
        } else {
            Cause::Unknown
        }
    }
}

/// How two boards compare (they saw the marker in the same sets).
#[derive(Debug, Clone, Copy, Default)]
struct PairState {
    share: f64,
    compared: u64,
    /// Comparisons with a third ray to decide (see [`Comparison::redundant`]).
    redundant: u64,
    /// Their disagreement share crossed [`PAIR_ON`] (and not yet back under [`PAIR_OFF`]).
    disagree: bool,
}

/// The solver's agreement check over the boards of the active placement.
#[derive(Debug, Clone)]
pub struct Agreement {
    /// Board of each rig camera.
    camera_board: Vec<usize>,
    /// Cameras of each board (bit per camera).
    board_mask: Vec<u32>,
    /// Per pair of boards `a < b`, at `a * boards + b`.
    pairs: Vec<PairState>,
    /// Per board.
    pub boards: Vec<BoardAgreement>,
    /// The last reference point and its instant (is the marker standing still?).
    last_point: Option<(Vector3<f64>, f64)>,
    /// Sets in which two or more boards saw the marker.
    pub sets_compared: u64,
    /// Sets given no position because the boards disagreed.
    pub sets_refused: u64,
    /// Sets published with a board's cameras left out.
    pub sets_board_dropped: u64,
}

/// What one set says about two boards: they agree, or `b` misses `a`'s point.
#[derive(Debug, Clone, Copy)]
struct Comparison {
    a: usize,
    b: usize,
    disagree: bool,
    /// Decided with three or more rays (a point of two cameras and another's ray). Two rays
    /// of two one-camera boards that meet are no test of their timing: such an agreement
    /// counts only while the pair has no redundant comparisons.
    redundant: bool,
}

/// At most one comparison per pair of boards per set.
const MAX_PAIRS: usize = MAX_CAMERAS * (MAX_CAMERAS - 1) / 2;

fn bits(mask: u32) -> impl Iterator<Item = usize> {
    (0..32).filter(move |i| mask & (1u32 << i) != 0)
}

fn point_of(m: &Measurement) -> Option<Vector3<f64>> {
    (m.status == TrackStatus::Tracked)
        .then_some(m.point_cam0_mm)
        .flatten()
}

fn support_of(m: &Measurement) -> u32 {
    m.cameras()
        .iter()
        .enumerate()
        .filter(|(_, c)| c.marker.is_some())
        .fold(0, |acc, (i, _)| acc | (1u32 << i))
}

/// A set's comparisons (fixed capacity: no allocation per set).
struct Comparisons {
    list: [Option<Comparison>; MAX_PAIRS],
    len: usize,
}

impl Comparisons {
    fn new() -> Self {
        Comparisons {
            list: [None; MAX_PAIRS],
            len: 0,
        }
    }
    fn push(&mut self, a: usize, b: usize, disagree: bool, redundant: bool) {
        if let Some(slot) = self.list.get_mut(self.len) {
            *slot = Some(Comparison {
                a,
                b,
                disagree,
                redundant,
            });
            self.len += 1;
        }
    }
}

impl Agreement {
    /// For a rig whose camera `c` is on board `camera_board[c]` (boards numbered from 0).
    pub fn new(camera_board: &[usize]) -> Self {
        let count = camera_board.iter().map(|b| b + 1).max().unwrap_or(0);
        let mut board_mask = vec![0u32; count];
        for (c, &b) in camera_board.iter().enumerate().take(MAX_CAMERAS) {
            board_mask[b] |= 1u32 << c;
        }
        Agreement {
            camera_board: camera_board.to_vec(),
            board_mask,
            pairs: vec![PairState::default(); count * count],
            boards: vec![BoardAgreement::default(); count],
            last_point: None,
            sets_compared: 0,
            sets_refused: 0,
            sets_board_dropped: 0,
        }
    }

    fn boards_of(&self, cameras: u32) -> u32 {
        bits(cameras)
            .filter_map(|c| self.camera_board.get(c))
            .fold(0, |acc, &b| acc | (1u32 << b))
    }

    fn cameras_of(&self, boards: u32) -> u32 {
        bits(boards)
            .filter_map(|b| self.board_mask.get(b))
            .fold(0, |acc, m| acc | m)
    }

    fn pair_index(&self, a: usize, b: usize) -> usize {
        let (lo, hi) = if a < b { (a, b) } else { (b, a) };
        lo * self.boards.len() + hi
    }

    /// Cameras with usable blobs that miss `p` by more than `gate_mm`, among `among`.
    fn dissenters(tracker: &Tracker, p: &Vector3<f64>, among: u32, gate_mm: f64) -> u32 {
        bits(among)
            .filter(|&c| tracker.camera_residual(c, p).is_none_or(|r| r.ray_mm > gate_mm))
            .fold(0, |acc, c| acc | (1u32 << c))
    }

    /// The residual of board `b`'s camera that misses `p` most (it speaks for the board).
    fn residual(&self, tracker: &Tracker, b: usize, p: &Vector3<f64>) -> Option<CameraResidual> {
        bits(self.board_mask.get(b).copied().unwrap_or(0))
            .filter_map(|c| tracker.camera_residual(c, p))
            .max_by(|x, y| x.ray_mm.total_cmp(&y.ray_mm))
    }

    /// Whether the marker stands still, from the reference point `p` at `instant_ns` and the
    /// last one (`None`: cannot tell).
    fn still(&mut self, p: &Vector3<f64>, instant_ns: Option<f64>) -> Option<bool> {
        let t = instant_ns?;
        let last = self.last_point.replace((*p, t));
        let (q, tq) = last?;
        let dt_s = (t - tq) / 1e9;
        (dt_s > 0.0 && dt_s <= 0.5).then(|| (p - q).norm() / dt_s < STILL_MM_S)
    }

    /// Solves with `excluded` left out; the point and its supporting cameras when every other
    /// camera that saw the marker agrees with it.
    fn consistent(
        tracker: &mut Tracker,
        seen: u32,
        excluded: u32,
        gate_mm: f64,
    ) -> Option<(Vector3<f64>, u32, Option<f64>)> {
        let m = *tracker.solve_excluding(excluded);
        let p = point_of(&m)?;
        let support = support_of(&m);
        let dissent = Self::dissenters(tracker, &p, seen & !support & !excluded, gate_mm);
        (dissent == 0).then_some((p, support, m.instant_ns))
    }

    /// Checks the set the tracker just solved (see the module documentation) and leaves in the
    /// tracker the measurement to publish. `clock_off[b]`: board `b`'s measured clock offset
    /// is noticeably off (decides between two disagreeing boards); `clock_ahead[b]`: it is
    /// ahead, which transit cannot explain (its cameras are left out); `clock_settling[b]`: its
    /// clock just stepped and is not yet measured again (its cameras are left out). Returns
    /// false when the set must not give a position.
    pub fn vet(
        &mut self,
        tracker: &mut Tracker,
        clock_off: &[bool],
        clock_ahead: &[bool],
        clock_settling: &[bool],
    ) -> bool {
        let n = tracker.camera_count();
        if n != self.camera_board.len() || n > MAX_CAMERAS {
            return true;
        }
        let gate_mm = tracker.config().max_gap_mm;
        let full = *tracker.measurement();
        let seen = full
            .cameras()
            .iter()
            .enumerate()
            .filter(|(_, c)| c.candidate_count > 0)
            .fold(0u32, |acc, (i, _)| acc | (1u32 << i));
        let seen_boards = self.boards_of(seen);
        let mut changed = false;
        if seen_boards.count_ones() >= 2 {
            self.sets_compared += 1;
            let mut cmp = Comparisons::new();
            if let Some(p) = point_of(&full) {
                let support = support_of(&full);
                let dissent = Self::dissenters(tracker, &p, seen & !support, gate_mm);
                if dissent == 0 {
                    self.still(&p, full.instant_ns);
                    let boards = self.boards_of(support);
                    let redundant = support.count_ones() >= 3;
                    for a in bits(boards) {
                        for b in bits(boards).filter(|&b| b > a) {
                            cmp.push(a, b, false, redundant);
                        }
                    }
                } else {
                    // Which board's cameras, left out, leave a point every other camera agrees
                    // with? That board disagrees with the point's boards.
                    changed = true;
                    for d in bits(self.boards_of(dissent)) {
                        let mask = self.cameras_of(1u32 << d);
                        let Some((pd, sd, instant)) = Self::consistent(tracker, seen, mask, gate_mm) else {
                            continue;
                        };
                        tracker.solve_excluding(0);
                        let still = self.still(&pd, instant);
                        let res = self.residual(tracker, d, &pd);
                        self.note_miss(d, res, still);
                        let boards = self.boards_of(sd);
                        for s in bits(boards) {
                            cmp.push(s, d, true, true);
                            for b in bits(boards).filter(|&b| b > s) {
                                cmp.push(s, b, false, sd.count_ones() >= 3);
                            }
                        }
                    }
                }
            } else if full.status == TrackStatus::NoConsistentPair {
                changed = self.diagnose(tracker, seen, seen_boards, gate_mm, &full, &mut cmp);
            }
            self.record(&cmp, clock_off);
        }
        // What may be published: a point without the disagreeing boards' cameras that every
        // other camera that saw the marker agrees with — or, leaving out one more board whose
        // cameras miss it, a point two or more boards still agree on. Never a point one board
        // gives while another contradicts it.
        for (b, &ahead) in self.boards.iter_mut().zip(clock_ahead) {
            b.clock_ahead = ahead;
        }
        let suspect_boards = self
            .boards
            .iter()
            .enumerate()
            .filter(|(i, b)| b.suspect || b.clock_ahead || clock_settling.get(*i).copied().unwrap_or(false))
            .fold(0u32, |acc, (i, _)| acc | (1u32 << i));
        let excluded = self.cameras_of(suspect_boards);
        let m = if excluded != 0 || changed {
            *tracker.solve_excluding(excluded)
        } else {
            full
        };
        let Some(p) = point_of(&m) else {
            if excluded != 0 && point_of(&full).is_some() {
                // The point needed a disagreeing board's cameras.
                self.sets_refused += 1;
                return false;
            }
            return true;
        };
        let support = support_of(&m);
        let dissent = Self::dissenters(tracker, &p, seen & !support & !excluded, gate_mm);
        let mut dropped = self.boards_of(seen & excluded) & !self.boards_of(support);
        if dissent != 0 {
            let mut rescued = false;
            for d in bits(self.boards_of(dissent)) {
                let without = excluded | self.cameras_of(1u32 << d);
                if let Some((_, sd, _)) = Self::consistent(tracker, seen, without, gate_mm)
                    && self.boards_of(sd).count_ones() >= 2
                {
                    dropped |= 1u32 << d;
                    rescued = true;
                    break;
                }
            }
            if !rescued {
                self.sets_refused += 1;
                return false;
            }
        }
        if dropped != 0 {
            self.sets_board_dropped += 1;
            for b in bits(dropped) {
                if let Some(st) = self.boards.get_mut(b) {
                    st.dropped += 1;
                }
            }
        }
        true
    }

    /// The boards' rays gave no common point: each board with two cameras that saw the marker
    /// solves its own; boards whose points differ, a board whose rays miss another's point,
    /// or two one-camera boards whose rays do not meet disagree. Returns whether the
    /// tracker's measurement was changed.
    fn diagnose(
        &mut self,
        tracker: &mut Tracker,
        seen: u32,
        seen_boards: u32,
        gate_mm: f64,
        full: &Measurement,
        cmp: &mut Comparisons,
    ) -> bool {
        let mut own: [Option<Vector3<f64>>; MAX_CAMERAS] = [None; MAX_CAMERAS];
        let mut instant = None;
        let mut changed = false;
        for b in bits(seen_boards) {
            let mask = self.board_mask.get(b).copied().unwrap_or(0);
            if (mask & seen).count_ones() >= 2 {
                let m = tracker.solve_excluding(!mask);
                own[b] = point_of(m);
                if own[b].is_some() && instant.is_none() {
                    instant = Some(m.instant_ns);
                }
                changed = true;
            }
        }
        if changed {
            // Every camera's candidates again, for the residuals below.
            tracker.solve_excluding(0);
        }
        let reference = bits(seen_boards).find_map(|b| own[b]);
        let still = match (reference, instant) {
            (Some(p), Some(t)) => self.still(&p, t),
            _ => None,
        };
        let list = seen_boards;
        for a in bits(list) {
            for b in bits(list).filter(|&b| b > a) {
                match (own[a], own[b]) {
                    (Some(pa), Some(pb)) => {
                        let disagree = (pa - pb).norm() > gate_mm;
                        if disagree {
                            let (ra, rb) = (self.residual(tracker, a, &pb), self.residual(tracker, b, &pa));
                            self.note_miss(a, ra, still);
                            self.note_miss(b, rb, still);
                        }
                        cmp.push(a, b, disagree, true);
                    }
                    (Some(p), None) | (None, Some(p)) => {
                        let (with, without) = if own[a].is_some() { (a, b) } else { (b, a) };
                        let res = self.residual(tracker, without, &p);
                        let disagree = res.is_none_or(|r| r.ray_mm > gate_mm);
                        if disagree {
                            self.note_miss(without, res, still);
                        }
                        cmp.push(with, without, disagree, true);
                    }
                    (None, None) if list.count_ones() == 2 => {
                        // Two one-camera boards: the set failed on their one pair.
                        for x in [a, b] {
                            if let Some(st) = self.boards.get_mut(x)
                                && full.gap_mm.is_finite()
                            {
                                st.miss_mm = Some(ewma(st.miss_mm, full.gap_mm, 0.1));
                            }
                        }
                        cmp.push(a, b, true, false);
                    }
                    (None, None) => {}
                }
            }
        }
        changed
    }

    /// Board `b` missed a point by `res` (its worst camera); `still`: the marker stood still.
    fn note_miss(&mut self, b: usize, res: Option<CameraResidual>, still: Option<bool>) {
        let Some(st) = self.boards.get_mut(b) else { return };
        let Some(r) = res else { return };
        let [rx, ry] = r.residual_px;
        let miss_px = rx.hypot(ry);
        st.miss_mm = Some(ewma(st.miss_mm, r.ray_mm, 0.1));
        st.miss_px = Some(ewma(st.miss_px, miss_px, 0.1));
        let moving = r.velocity_px_s.filter(|[vx, vy]| vx.hypot(*vy) >= STILL_PX_S);
        match (moving, still) {
            (_, Some(true)) => st.still += 1,
            (Some([vx, vy]), _) => {
                // The shift Δ that best explains the miss along the motion, and what it leaves
                // unexplained across it.
                let v2 = vx * vx + vy * vy;
                let dt_s = (rx * vx + ry * vy) / v2;
                let across = (rx - vx * dt_s).hypot(ry - vy * dt_s);
                if across <= 0.5 * miss_px {
                    st.time_like += 1;
                    st.rv_sum = SHIFT_DECAY * st.rv_sum + (rx * vx + ry * vy);
                    st.vv_sum = SHIFT_DECAY * st.vv_sum + v2;
                    st.shift_ms = Some(st.rv_sum / st.vv_sum * 1e3);
                }
            }
            (None, _) if r.velocity_px_s.is_some() => st.still += 1,
            (None, _) => {}
        }
    }

    /// Takes one set's comparisons into the pairs' shares, then decides which boards disagree:
    /// a board is left out when it disagrees with more boards than agree with it (two boards
    /// that disagree with no third: both), a pair's disagreement counting only against the
    /// board with a measured clock offset when exactly one of the two has one.
    fn record(&mut self, cmp: &Comparisons, clock_off: &[bool]) {
        let nb = self.boards.len();
        let mut involved = 0u32;
        let mut disagreed = 0u32;
        for c in cmp.list.iter().take(cmp.len).flatten() {
            let i = self.pair_index(c.a, c.b);
            let Some(p) = self.pairs.get_mut(i) else { continue };
            if !c.redundant && !c.disagree && p.redundant >= MIN_EVIDENCE {
                continue;
            }
            p.redundant += u64::from(c.redundant);
            p.compared += 1;
            p.share += EWMA_ALPHA * (f64::from(u8::from(c.disagree)) - p.share);
            if !p.disagree && p.compared >= MIN_EVIDENCE && p.share >= PAIR_ON {
                p.disagree = true;
            } else if p.disagree && p.share < PAIR_OFF {
                p.disagree = false;
            }
            involved |= (1u32 << c.a) | (1u32 << c.b);
            if c.disagree {
                disagreed |= (1u32 << c.a) | (1u32 << c.b);
            }
        }
        let off = |x: usize| clock_off.get(x).copied().unwrap_or(false);
        for b in 0..nb {
            let (mut against, mut with, mut peer, mut share) = (0u32, 0u32, None, 0.0f64);
            for x in (0..nb).filter(|&x| x != b) {
                let p = self.pairs[self.pair_index(b, x)];
                if p.compared < MIN_EVIDENCE {
                    continue;
                }
                share = share.max(p.share);
                if !p.disagree {
                    with += 1;
                } else if !off(x) || off(b) {
                    against += 1;
                    peer = Some(x);
                }
            }
            let st = &mut self.boards[b];
            st.share = share;
            if involved & (1u32 << b) != 0 {
                st.compared += 1;
            }
            if disagreed & (1u32 << b) != 0 {
                st.disagreed += 1;
            }
            let suspect = against >= 1 && against > with;
            // A pair is named when the two disagree with each other and nothing decides.
            let decided = off(b) && peer.is_some_and(|x| !off(x));
            st.peer = if suspect && against == 1 && with == 0 && !decided {
                peer
            } else {
                None
            };
            if suspect != st.suspect {
                st.suspect = suspect;
                if suspect {
                    tracing::warn!(
                        board = b,
                        share = st.share,
                        miss_mm = st.miss_mm,
                        shift_ms = st.shift_ms,
                        "camera board disagrees with the others; its cameras are left out"
                    );
                } else {
                    tracing::info!(board = b, "camera board agrees again; its cameras are used");
                }
            }
        }
        // Only a mutual disagreement is a pair's: a board outvoted by one that others trust
        // disagrees "with the other boards".
        for b in 0..nb {
            if let Some(x) = self.boards[b].peer
                && self.boards.get(x).is_none_or(|o| !o.suspect)
            {
                self.boards[b].peer = None;
            }
        }
    }
}

fn ewma(old: Option<f64>, x: f64, alpha: f64) -> f64 {
    match old {
        Some(o) if o.is_finite() => o + alpha * (x - o),
        _ => x,
    }
}
