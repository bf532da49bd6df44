//! Pairing observations of many boards into frame sets (no network code here).
//!
//! Each camera's observation carries a capture timestamp on a clock the boards share (PTP or
//! chrony) and, with a hardware trigger, the trigger's frame counter. The [`Pairer`] groups
//! them by trigger counter when configured, otherwise by timestamps: each frame is given a slot
//! of a frame-period grid centred on camera 0's frames ([`irtrack_core::slots`]), and a set is
//! the frames of one slot, whatever order they arrive in. Free-running cameras at any phase
//! keep their slot through timestamp jitter, so sets do not fall apart when a camera's phase
//! is half a period from camera 0's. A set closes when every camera that is not faulted contributed,
//! when a newer set completed, or at its deadline; observations arriving for a closed set are
//! counted late, cameras absent from a closed set are counted missing. Nothing is waited on
//! without bound.
//!
//! Clocks: per board, `capture + send_delay − receive` is the board's clock offset from the
//! receiver minus the one-way transit. Its maximum over a window (transit only subtracts) is
//! the measured offset. A board whose offset exceeds the tolerance could be paired with the wrong
//! frame, so it is faulted and its observations are kept out of every set until its offset is
//! back within the tolerance: never a wrong pairing.
//!
//! Every buffer is allocated in [`Pairer::new`]; pushing and closing sets does not allocate.

use irtrack_core::observation::{MAX_OBS_BLOBS, ObsBlob, Observation};
use irtrack_core::params::MAX_CAMERAS;
use irtrack_core::slots::SlotGrid;

use crate::error::{ClusterError, Result};

/// How observations of one instant are recognised.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PairingMode {
    /// By the hardware trigger's frame counter (every observation must carry one).
    Trigger,
    /// By capture timestamps: one slot of a grid of `period_ns` per set.
    Timestamp {
        /// The cameras' frame period, ns (the grid's pitch).
        period_ns: u64,
    },
}

/// Settings of a [`Pairer`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PairingConfig {
    /// `camera_board[i]` is the board index of the rig's camera `i` (boards numbered from 0).
    pub camera_board: Vec<usize>,
    /// How observations of one instant are recognised.
    pub mode: PairingMode,
    /// A set closes this long after its first observation arrived, complete or not.
    pub deadline_ns: u64,
    /// Largest clock offset of a board before it is faulted.
    pub max_clock_offset_ns: u64,
    /// Observations per board in one offset window (the maximum of two windows is used).
    pub offset_window: u32,
}

impl PairingConfig {
    /// Timestamp pairing at `fps`: slots of one frame period, clock limit half a period,
    /// deadline two periods.
    pub fn for_fps(camera_board: Vec<usize>, fps: f64) -> PairingConfig {
        let period_ns = (1e9 / fps) as u64;
        PairingConfig {
            camera_board,
            mode: PairingMode::Timestamp { period_ns },
            deadline_ns: 2 * period_ns,
            max_clock_offset_ns: period_ns / 2,
            offset_window: 64,
        }
    }
}

/// One camera's contribution to a set.
#[derive(Debug, Clone, Copy)]
pub struct CameraEntry {
    /// The camera's observation arrived for this set.
    pub present: bool,
    /// The observation's sequence number (per board and camera).
    pub sequence: u64,
    /// Capture time on the sending board's clock, ns.
    pub capture_ts_ns: u64,
    /// Exposure of the frame, µs.
    pub exposure_us: u32,
    /// How many of `blobs` are valid.
    pub blob_count: usize,
    /// The observed blobs (fixed storage: no allocation per set).
    pub blobs: [ObsBlob; MAX_OBS_BLOBS],
}

impl CameraEntry {
    const EMPTY: CameraEntry = CameraEntry {
        present: false,
        sequence: 0,
        capture_ts_ns: 0,
        exposure_us: 0,
        blob_count: 0,
        blobs: [ObsBlob {
            x_px: 0.0,
            y_px: 0.0,
            area_px: 0,
            peak_dn: 0,
            roundness: 0.0,
            touches_frame_edge: false,
            touches_roi_edge: false,
            saturated: false,
        }; MAX_OBS_BLOBS],
    };

    /// The valid blobs.
    pub fn blobs(&self) -> &[ObsBlob] {
        &self.blobs[..self.blob_count]
    }
}

/// A closed frame set.
#[derive(Debug, Clone)]
pub struct PairedSet {
    /// Trigger counter (trigger mode) or slot number (timestamp mode).
    pub key: u64,
    /// Earliest capture timestamp in the set, ns.
    pub capture_ts_ns: u64,
    /// Receive time of the set's first observation, ns on the receiver's clock.
    pub opened_ns: u64,
    /// Cameras that contributed.
    pub present: usize,
    /// Per rig camera (only the first `Pairer::camera_count` are used).
    pub cameras: [CameraEntry; MAX_CAMERAS],
}

impl PairedSet {
    fn empty() -> PairedSet {
        PairedSet {
            key: 0,
            capture_ts_ns: 0,
            opened_ns: 0,
            present: 0,
            cameras: [CameraEntry::EMPTY; MAX_CAMERAS],
        }
    }

    fn clear(&mut self) {
        for c in &mut self.cameras {
            c.present = false;
            c.blob_count = 0;
        }
        self.present = 0;
    }
}

/// Counters of a [`Pairer`] (reported in `/status`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PairStats {
    /// Sets closed with every camera present.
    pub sets_complete: u64,
    /// Sets closed with a camera missing (at their deadline or to make room).
    pub sets_incomplete: u64,
    /// Observations for a set already closed.
    pub late: u64,
    /// Camera slots empty in closed sets (per camera).
    pub missing: [u64; MAX_CAMERAS],
    /// A second observation of a camera for the same open set.
    pub conflicting: u64,
    /// Observations of a faulted board, kept out of every set.
    pub refused_clock: u64,
    /// Trigger mode: observations without a trigger counter.
    pub no_trigger: u64,
}

/// What [`Pairer::push`] did with an observation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PushOutcome {
    /// Put into an open set (or a new one).
    Added,
    /// For a set already closed: dropped, counted in `late`.
    Late,
    /// A second observation of that camera for the same open set: dropped.
    Conflicting,
    /// From a board whose clock offset is over the limit: refused.
    ClockFault,
    /// Trigger mode, but the observation carries no trigger counter: refused.
    NoTrigger,
}

/// Clock state of one board.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BoardClock {
    /// Measured offset (board clock − receiver clock, less the smallest transit), ns; `None`
    /// before the first observation.
    pub offset_ns: Option<i64>,
    /// The offset is beyond the limit: the board's observations are refused.
    pub faulted: bool,
    /// Reported silent by the receiver ([`Pairer::set_board_down`]): sets stop waiting for
    /// its cameras, so one stopped board does not delay every position to the deadline.
    pub down: bool,
    /// Its last [`RECENT`] observations all arrived later than any of the last full window
    /// by more than that window's spread (and at least [`STEP_BACK_MIN_NS`]): its clock
    /// stepped back, or its link holds a queue. The receiver cannot tell which from here.
    pub stepped_back: bool,
    cur_max: i64,
    cur_min: i64,
    cur_count: u32,
    prev_max: Option<i64>,
    prev_min: Option<i64>,
    recent: [i64; RECENT],
    recent_n: usize,
}

/// Observations whose offsets [`BoardClock::stepped_back`] looks at.
pub const RECENT: usize = 4;
/// The smallest drop of a board's offset taken as a step back, ns.
pub const STEP_BACK_MIN_NS: i64 = 2_000_000;
/// Added to the last window's spread (its jitter) for the drop to count, ns.
const STEP_BACK_MARGIN_NS: i64 = 1_000_000;

/// The pairing state machine (see the module documentation).
#[derive(Debug, Clone)]
pub struct Pairer {
    cfg: PairingConfig,
    cameras: usize,
    sets: Vec<PairedSet>,
    open: Vec<bool>,
    boards: Vec<BoardClock>,
    /// Timestamp mode: the slot grid.
    grid: Option<SlotGrid>,
    /// Key of the newest closed set: anything at or before it is late.
    closed_key: Option<u64>,
    stats: PairStats,
}

impl Pairer {
    /// Up to 8 sets are open at once (older ones are closed to make room).
    pub const OPEN_SETS: usize = 8;

    /// A pairer for `cfg`; refuses a camera count outside 1..=`MAX_CAMERAS` and a zero
    /// deadline or offset window.
    pub fn new(cfg: PairingConfig) -> Result<Pairer> {
        let n = cfg.camera_board.len();
        if !(1..=MAX_CAMERAS).contains(&n) {
            return Err(ClusterError::Config {
                reason: format!("{n} cameras; the solver pairs 1..={MAX_CAMERAS}"),
            });
        }
        if cfg.deadline_ns == 0 || cfg.offset_window == 0 {
            return Err(ClusterError::Config {
                reason: "pairing deadline and offset window must be > 0".into(),
            });
        }
        let boards = cfg.camera_board.iter().copied().max().unwrap_or(0) + 1;
        let grid = match cfg.mode {
            PairingMode::Trigger => None,
            PairingMode::Timestamp { period_ns } => Some(
                SlotGrid::new(n, period_ns, 0, SlotGrid::DEFAULT_HYSTERESIS).map_err(|e| {
                    ClusterError::Config {
                        reason: e.to_string(),
                    }
                })?,
            ),
        };
        Ok(Pairer {
            grid,
            cameras: n,
            sets: (0..Self::OPEN_SETS).map(|_| PairedSet::empty()).collect(),
            open: vec![false; Self::OPEN_SETS],
            boards: vec![BoardClock::default(); boards],
            closed_key: None,
            stats: PairStats::default(),
            cfg,
        })
    }

    /// Counters so far.
    pub fn stats(&self) -> &PairStats {
        &self.stats
    }

    /// Clock state per board.
    pub fn boards(&self) -> &[BoardClock] {
        &self.boards
    }

    /// Cameras in the rig (`camera_board.len()`).
    pub fn camera_count(&self) -> usize {
        self.cameras
    }

    fn board_of(&self, camera: usize) -> usize {
        self.cfg.camera_board[camera]
    }

    /// Updates the board's offset estimate; returns whether it is faulted.
    fn track_clock(&mut self, board: usize, offset_sample_ns: i64) -> bool {
        let window = self.cfg.offset_window;
        let limit = self.cfg.max_clock_offset_ns;
        let b = &mut self.boards[board];
        (b.cur_max, b.cur_min) = if b.cur_count == 0 {
            (offset_sample_ns, offset_sample_ns)
        } else {
            (b.cur_max.max(offset_sample_ns), b.cur_min.min(offset_sample_ns))
        };
        b.cur_count += 1;
        b.recent[b.recent_n % RECENT] = offset_sample_ns;
        b.recent_n += 1;
        // A clock stepped back makes every observation after it look that much later: the
        // window's maximum shows it only after two windows, the last few at once.
        b.stepped_back = match (b.prev_max, b.prev_min) {
            (Some(mx), Some(mn)) if b.recent_n >= RECENT => {
                let recent_max = b.recent.iter().copied().max().unwrap_or(i64::MAX);
                recent_max < mx - STEP_BACK_MIN_NS.max(mx - mn + STEP_BACK_MARGIN_NS)
            }
            _ => false,
        };
        // The estimate: the larger of this window's and the last full window's maximum, so a
        // change shows within two windows and one slow packet never counts.
        let est = b.prev_max.map_or(b.cur_max, |p| p.max(b.cur_max));
        if b.cur_count >= window {
            b.prev_max = Some(b.cur_max);
            b.prev_min = Some(b.cur_min);
            b.cur_count = 0;
        }
        b.offset_ns = Some(est);
        b.faulted = est.unsigned_abs() > limit;
        b.faulted
    }

    /// Adds the observation `obs` of the rig's camera `camera` (already checked by the
    /// [`irtrack_core::observation::ObservationGate`]) received at `now_ns`.
    pub fn push(&mut self, camera: usize, obs: &Observation<'_>, now_ns: u64) -> PushOutcome {
        let h = &obs.header;
        let board = self.board_of(camera);
        let sample = i128::from(h.capture_ts_ns) + i128::from(h.send_delay_us) * 1000 - i128::from(now_ns);
        let sample = sample.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
        if self.track_clock(board, sample) {
            self.stats.refused_clock += 1;
            return PushOutcome::ClockFault;
        }
        let key = match self.cfg.mode {
            PairingMode::Trigger => match h.trigger_count {
                Some(t) => t,
                None => {
                    self.stats.no_trigger += 1;
                    return PushOutcome::NoTrigger;
                }
            },
            PairingMode::Timestamp { .. } => {
                match self.grid.as_mut().and_then(|g| g.assign(camera, h.capture_ts_ns)) {
                    Some(slot) => slot.index,
                    None => return PushOutcome::Late,
                }
            }
        };
        if let Some(closed) = self.closed_key
            && !self.after_closed(key, closed)
        {
            self.stats.late += 1;
            return PushOutcome::Late;
        }
        let slot = match self.find_open(key) {
            Some(s) => s,
            None => self.open_set(key, now_ns),
        };
        let set = &mut self.sets[slot];
        let entry = &mut set.cameras[camera];
        if entry.present {
            self.stats.conflicting += 1;
            return PushOutcome::Conflicting;
        }
        entry.present = true;
        entry.sequence = h.sequence;
        entry.capture_ts_ns = h.capture_ts_ns;
        entry.exposure_us = h.exposure_us;
        entry.blob_count = 0;
        for b in obs.blobs().take(MAX_OBS_BLOBS) {
            entry.blobs[entry.blob_count] = b;
            entry.blob_count += 1;
        }
        set.present += 1;
        set.capture_ts_ns = set.capture_ts_ns.min(h.capture_ts_ns);
        PushOutcome::Added
    }

    /// Whether `key` belongs after the newest closed set's key.
    fn after_closed(&self, key: u64, closed: u64) -> bool {
        key > closed
    }

    fn find_open(&self, key: u64) -> Option<usize> {
        (0..self.sets.len()).find(|&i| self.open[i] && self.sets[i].key == key)
    }

    /// Timestamp mode: how often a camera's frame went to another slot than its previous
    /// frame's plus the frames between (drift across a slot boundary, a restart).
    pub fn slot_moves(&self) -> u64 {
        self.grid.as_ref().map_or(0, SlotGrid::moves)
    }

    fn open_set(&mut self, key: u64, now_ns: u64) -> usize {
        let slot = match self.open.iter().position(|o| !o) {
            Some(s) => s,
            None => {
                // Full: the oldest set is closed as it is (counted; its content is lost since
                // nobody polled it in time).
                let oldest = self.oldest_open().unwrap_or(0);
                self.close(oldest);
                oldest
            }
        };
        let set = &mut self.sets[slot];
        set.clear();
        set.key = key;
        set.capture_ts_ns = u64::MAX;
        set.opened_ns = now_ns;
        self.open[slot] = true;
        slot
    }

    fn oldest_open(&self) -> Option<usize> {
        (0..self.sets.len())
            .filter(|&i| self.open[i])
            .min_by_key(|&i| self.sets[i].key)
    }

    /// Cameras a set waits for: those whose board is neither faulted nor down.
    fn expected(&self) -> usize {
        (0..self.cameras)
            .filter(|&c| {
                let b = &self.boards[self.board_of(c)];
                !b.faulted && !b.down
            })
            .count()
    }

    fn close(&mut self, slot: usize) {
        self.open[slot] = false;
        let set = &self.sets[slot];
        self.closed_key = Some(self.closed_key.map_or(set.key, |k| k.max(set.key)));
        if set.present >= self.cameras {
            self.stats.sets_complete += 1;
        } else {
            self.stats.sets_incomplete += 1;
            for (c, e) in set.cameras[..self.cameras].iter().enumerate() {
                if !e.present {
                    self.stats.missing[c] += 1;
                }
            }
        }
    }

    /// Closes the oldest open set if it is complete, a newer set is complete, or its
    /// deadline has passed, and returns it; `None` if no set is ready.
    pub fn poll(&mut self, now_ns: u64) -> Option<&PairedSet> {
        let oldest = self.oldest_open()?;
        let expected = self.expected();
        let ready = |s: &PairedSet| s.present >= expected.max(1);
        let set = &self.sets[oldest];
        let newer_complete =
            (0..self.sets.len()).any(|i| self.open[i] && i != oldest && ready(&self.sets[i]));
        if ready(set) || newer_complete || now_ns >= set.opened_ns.saturating_add(self.cfg.deadline_ns) {
            self.close(oldest);
            return Some(&self.sets[oldest]);
        }
        None
    }

    /// Marks `board` silent (`down`) or heard again. Its cameras' slots stay open (an
    /// observation that still arrives is paired), but sets no longer wait for them.
    pub fn set_board_down(&mut self, board: usize, down: bool) {
        if let Some(b) = self.boards.get_mut(board) {
            b.down = down;
        }
    }

    /// Forgets the clock state of `board` (restarted).
    pub fn reset_board(&mut self, board: usize) {
        if let Some(b) = self.boards.get_mut(board) {
            *b = BoardClock::default();
        }
        if let Some(grid) = self.grid.as_mut() {
            for (c, _) in self
                .cfg
                .camera_board
                .iter()
                .enumerate()
                .filter(|(_, b)| **b == board)
            {
                grid.reset_camera(c);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use irtrack_core::observation::{MAX_OBS_LEN, ObsClock, ObsHeader, decode, encode};

    const PERIOD: u64 = 10_000_000; // 100 fps

    struct Msg {
        buf: [u8; MAX_OBS_LEN],
        len: usize,
    }

    fn msg(camera: u8, seq: u64, ts: u64, trigger: Option<u64>, x: f32) -> Msg {
        let h = ObsHeader {
            rig: "r",
            board: "b",
            camera,
            sequence: seq,
            trigger_count: trigger,
            capture_ts_ns: ts,
            clock: ObsClock::Realtime,
            exposure_us: 100,
            dropped: 0,
            send_delay_us: 1000,
        };
        let blob = ObsBlob {
            x_px: x,
            y_px: 1.0,
            area_px: 4,
            peak_dn: 200,
            roundness: 1.0,
            ..ObsBlob::default()
        };
        let mut buf = [0u8; MAX_OBS_LEN];
        let len = encode(&h, &[blob], &mut buf).unwrap();
        Msg { buf, len }
    }

    fn push(p: &mut Pairer, camera: usize, m: &Msg, now: u64) -> PushOutcome {
        p.push(camera, &decode(&m.buf[..m.len]).unwrap(), now)
    }

    fn cfg() -> PairingConfig {
        PairingConfig::for_fps(vec![0, 0, 1, 1], 100.0)
    }

    /// Four cameras on two boards; frame k at k·PERIOD; received 2 ms after capture.
    #[test]
    fn pairs_by_timestamp_and_closes_complete_sets() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 1_000 * PERIOD;
        for k in 0..5u64 {
            let t = t0 + k * PERIOD;
            // Board 1 stamps 2 ms later (free-running cameras, phase offset): same instant.
            for c in [2usize, 0, 3, 1] {
                let ts = if c >= 2 { t + 2_000_000 } else { t };
                let m = msg(c as u8 % 2, k, ts, None, (k * 10 + c as u64) as f32);
                assert_eq!(push(&mut p, c, &m, ts + 2_000_000), PushOutcome::Added);
            }
            let set = p.poll(t + 4_000_000).expect("complete set");
            assert_eq!(set.present, 4);
            for c in 0..4 {
                assert_eq!(set.cameras[c].sequence, k);
                assert_eq!(set.cameras[c].blobs()[0].x_px, (k * 10 + c as u64) as f32);
            }
            assert!(p.poll(t + 4_000_000).is_none());
        }
        assert_eq!(p.stats().sets_complete, 5);
        assert_eq!(p.stats().late, 0);
    }

    /// A clock that steps back is seen from the last few observations' arrival, within
    /// [`RECENT`] of them; a link's jitter (here up to 3 ms) and a small step are not.
    #[test]
    fn a_step_back_shows_in_the_last_few_arrivals_and_jitter_does_not() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 1_000 * PERIOD;
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut jitter_ns = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng % 3_000_000
        };
        let mut flagged = Vec::new();
        // Board 1's camera 2: 300 frames in line (transit 0.2–3.2 ms), then its clock steps
        // back by 8 ms (every stamp 8 ms early), then by 1.5 ms only (another run below).
        for k in 0..400u64 {
            let t = t0 + k * PERIOD;
            let stamp = if k >= 300 { t - 8_000_000 } else { t };
            let m = msg(0, k, stamp, None, 1.0);
            let _ = push(&mut p, 2, &m, t + 200_000 + jitter_ns());
            if p.boards()[1].stepped_back {
                flagged.push(k);
            }
            let _ = p.poll(t + 5_000_000);
        }
        assert!(
            flagged
                .first()
                .is_some_and(|k| (300..300 + RECENT as u64).contains(k)),
            "flagged at {flagged:?}"
        );
        assert!(!p.boards()[0].stepped_back);
        let mut p = Pairer::new(cfg()).unwrap();
        for k in 0..400u64 {
            let t = t0 + k * PERIOD;
            let stamp = if k >= 300 { t - 1_500_000 } else { t };
            let _ = push(&mut p, 2, &msg(0, k, stamp, None, 1.0), t + 200_000 + jitter_ns());
            assert!(
                !p.boards()[1].stepped_back,
                "a 1.5 ms step within 3 ms of jitter, at {k}"
            );
            let _ = p.poll(t + 5_000_000);
        }
    }

    #[test]
    fn deadline_closes_incomplete_sets_and_late_ones_are_counted() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t = 500 * PERIOD;
        for c in 0..3usize {
            push(&mut p, c, &msg(c as u8, 1, t, None, 1.0), t + 1_000_000);
        }
        assert!(
            p.poll(t + 1_500_000).is_none(),
            "waits for camera 3 until the deadline"
        );
        let set = p.poll(t + 1_000_000 + 2 * PERIOD).expect("deadline");
        assert_eq!(set.present, 3);
        assert!(!set.cameras[3].present);
        assert_eq!(p.stats().missing[3], 1);
        // Camera 3's observation of that instant arrives after the close.
        assert_eq!(
            push(&mut p, 3, &msg(1, 1, t + 500_000, None, 1.0), t + 3 * PERIOD),
            PushOutcome::Late
        );
        assert_eq!(p.stats().late, 1);
    }

    #[test]
    fn newer_complete_set_closes_an_older_one() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t = 700 * PERIOD;
        push(&mut p, 0, &msg(0, 1, t, None, 1.0), t + 1_000_000);
        for c in 0..4usize {
            push(
                &mut p,
                c,
                &msg(c as u8, 2, t + PERIOD, None, 2.0),
                t + PERIOD + 1_000_000,
            );
        }
        let first = p.poll(t + PERIOD + 1_000_000).unwrap();
        let (first_key, first_present) = (first.key, first.present);
        assert_eq!((first.capture_ts_ns, first_present), (t, 1));
        let second = p.poll(t + PERIOD + 1_000_000).unwrap();
        assert_eq!((second.key, second.present), (first_key + 1, 4));
    }

    #[test]
    fn trigger_mode_pairs_by_counter_whatever_the_timestamps() {
        let mut c = cfg();
        c.mode = PairingMode::Trigger;
        let mut p = Pairer::new(c).unwrap();
        let t = 900 * PERIOD;
        for cam in 0..4usize {
            // Timestamps spread over 4 ms: the counter decides.
            let ts = t + cam as u64 * 1_000_000;
            push(&mut p, cam, &msg(cam as u8, 5, ts, Some(77), 0.0), ts + 1_000_000);
        }
        let set = p.poll(t + 5_000_000).unwrap();
        assert_eq!((set.key, set.present), (77, 4));
        assert_eq!(
            push(&mut p, 0, &msg(0, 6, t, None, 0.0), t + 1_000_000),
            PushOutcome::NoTrigger
        );
    }

    /// Board 1's clock runs one frame period ahead: its frame k looks like frame k+1. It must
    /// be faulted, and no set may ever hold its observations together with board 0's.
    #[test]
    fn clock_offset_beyond_tolerance_faults_and_never_pairs_wrongly() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 2_000 * PERIOD;
        let mut mixed = 0;
        for k in 0..200u64 {
            let t = t0 + k * PERIOD;
            let recv = t + 2_000_000;
            for c in 0..4usize {
                let ts = if c >= 2 { t + PERIOD } else { t };
                push(&mut p, c, &msg(c as u8 % 2, k, ts, None, k as f32), recv);
            }
            while let Some(set) = p.poll(recv + 3 * PERIOD) {
                let board0 = set.cameras[0].present || set.cameras[1].present;
                let board1 = set.cameras[2].present || set.cameras[3].present;
                if board0 && board1 {
                    mixed += 1;
                }
            }
        }
        assert_eq!(mixed, 0, "sets mixing board 0 and the offset board 1");
        assert!(p.boards()[1].faulted);
        assert!(!p.boards()[0].faulted);
        let off = p.boards()[1].offset_ns.unwrap();
        assert!((off - PERIOD as i64).abs() < 2_000_000, "offset {off}");
        assert!(p.stats().refused_clock >= 390);
    }

    /// An offset within the tolerance (3 ms of 5) with 3 ms receive jitter still pairs.
    #[test]
    fn offset_within_tolerance_pairs_with_jitter() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 3_000 * PERIOD;
        let mut complete = 0;
        let mut jitter = 12345u64;
        for k in 0..100u64 {
            let t = t0 + k * PERIOD;
            for c in 0..4usize {
                jitter = jitter
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                // Board 1 stamps 3 ms ahead of the true capture time t.
                let ts = if c >= 2 { t + 3_000_000 } else { t };
                let recv = t + 1_000_000 + (jitter >> 33) % 3_000_000;
                push(&mut p, c, &msg(c as u8 % 2, k, ts, None, k as f32), recv);
            }
            while let Some(set) = p.poll(t + 8_000_000) {
                let first = set.cameras[0].blobs()[0].x_px;
                assert!(
                    set.cameras[..4]
                        .iter()
                        .all(|e| !e.present || e.blobs()[0].x_px == first)
                );
                if set.present == 4 {
                    complete += 1;
                }
            }
        }
        assert!(complete >= 95, "{complete} complete sets of 100");
        assert!(!p.boards()[1].faulted);
    }

    /// Board 1's clock drifts 2000 ppm (2 ms/s, a board whose PTP daemon stopped): while its
    /// offset is inside the 5 ms tolerance its frames pair with board 0's same frames; beyond
    /// it the board is faulted. At no point does a set hold two different frames.
    #[test]
    fn drifting_clock_pairs_while_inside_tolerance_then_faults_never_wrongly() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 5_000 * PERIOD;
        let (mut complete_early, mut mixed_frames) = (0, 0);
        for k in 0..600u64 {
            let t = t0 + k * PERIOD;
            let drift_ns = k * PERIOD * 2_000 / 1_000_000;
            for c in 0..4usize {
                let ts = if c >= 2 { t + drift_ns } else { t };
                push(&mut p, c, &msg(c as u8 % 2, k, ts, None, k as f32), t + 2_000_000);
            }
            while let Some(set) = p.poll(t + 2_000_000 + 3 * PERIOD) {
                let frames: Vec<f32> = set.cameras[..4]
                    .iter()
                    .filter(|e| e.present)
                    .map(|e| e.blobs()[0].x_px)
                    .collect();
                if frames.iter().any(|&x| x != frames[0]) {
                    mixed_frames += 1;
                }
                // Frames 0..200: drift below 4 ms.
                if set.present == 4 && frames[0] < 200.0 {
                    complete_early += 1;
                }
            }
        }
        assert_eq!(mixed_frames, 0, "sets holding two different frames");
        assert!(
            complete_early >= 190,
            "{complete_early} complete sets of the first 200"
        );
        assert!(p.boards()[1].faulted, "12 ms off at the end, not faulted");
        assert!(!p.boards()[0].faulted);
        assert!(p.stats().refused_clock > 0);
    }

    #[test]
    fn faulted_board_leaves_the_others_complete() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 4_000 * PERIOD;
        for k in 0..100u64 {
            let t = t0 + k * PERIOD;
            for c in 0..4usize {
                let ts = if c >= 2 { t + 30 * PERIOD } else { t };
                push(&mut p, c, &msg(c as u8 % 2, k, ts, None, 0.0), t + 1_000_000);
            }
        }
        // Board 0's sets complete on their own once board 1 is faulted.
        let set = p.poll(t0 + 100 * PERIOD).unwrap();
        assert_eq!(set.present, 2);
    }

    #[test]
    fn a_board_marked_down_is_not_waited_for() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 4_000 * PERIOD;
        // Board 1 (cameras 2 and 3) is silent: without the mark a set waits to its deadline.
        for c in 0..2usize {
            push(&mut p, c, &msg(c as u8 % 2, 0, t0, None, 0.0), t0 + 1_000_000);
        }
        assert!(
            p.poll(t0 + 1_000_000).is_none(),
            "waits for board 1 before it is down"
        );
        p.set_board_down(1, true);
        let set = p.poll(t0 + 1_000_000).expect("closes at once with board 1 down");
        assert_eq!(set.present, 2);
        // Heard again: sets wait for all four cameras once more.
        p.set_board_down(1, false);
        for c in 0..2usize {
            push(
                &mut p,
                c,
                &msg(c as u8 % 2, 1, t0 + PERIOD, None, 0.0),
                t0 + PERIOD + 1_000_000,
            );
        }
        assert!(p.poll(t0 + PERIOD + 1_000_000).is_none());
        for c in 2..4usize {
            push(
                &mut p,
                c,
                &msg(c as u8 % 2, 1, t0 + PERIOD, None, 0.0),
                t0 + PERIOD + 1_000_000,
            );
        }
        assert_eq!(p.poll(t0 + PERIOD + 1_000_000).expect("complete").present, 4);
    }

    /// Free-running cameras on two boards, phases spread over the whole period (camera 2 half a
    /// period from camera 0, on a slot boundary), ±300 µs timestamp jitter, observations
    /// arriving in a different order every frame. Every set holds each camera's frame of the
    /// same slot: complete, and never two frames of one camera further apart than the grid.
    /// (Grouping around the first observation to arrive split such sets, issue 39's cell.)
    #[test]
    fn free_running_cameras_at_any_phase_pair_into_complete_sets_whatever_the_arrival_order() {
        let mut p = Pairer::new(cfg()).unwrap();
        let t0 = 9_000 * PERIOD;
        let phase = [0, PERIOD / 4, PERIOD / 2, PERIOD - PERIOD / 4];
        let mut rng = 99u64;
        let mut next = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            rng >> 33
        };
        let (mut sets, mut complete, mut frames_of_one_instant) = (0, 0, 0);
        for k in 0..500u64 {
            let mut order = [0usize, 1, 2, 3];
            for i in (1..4).rev() {
                order.swap(i, (next() % (i as u64 + 1)) as usize);
            }
            for c in order {
                let jitter = (next() % 600_000) as i64 - 300_000;
                let ts = (t0 + k * PERIOD + phase[c]) as i64 + jitter;
                // 1–3 ms in transit (board 1's later, with its later phases).
                let recv = ts as u64 + 1_000_000 + next() % 2_000_000;
                push(&mut p, c, &msg(c as u8 % 2, k, ts as u64, None, k as f32), recv);
            }
            while let Some(set) = p.poll(t0 + k * PERIOD + PERIOD + 3_000_000) {
                sets += 1;
                if set.present == 4 {
                    complete += 1;
                }
                let frames: Vec<f32> = set.cameras[..4]
                    .iter()
                    .filter(|e| e.present)
                    .map(|e| e.blobs()[0].x_px)
                    .collect();
                // Camera 3 (phase −T/4) exposes frame k+1 a quarter period before camera 0's
                // k+1: its frame k+1 belongs to camera 0's slot k+1, so a set holds frames of
                // one number or, for camera 3, the one before camera 0's slot's.
                if frames.iter().all(|&x| (x - frames[0]).abs() <= 1.0) {
                    frames_of_one_instant += 1;
                }
            }
        }
        assert!(complete >= 495, "{complete} complete sets of {sets}");
        assert_eq!(frames_of_one_instant, sets);
        assert_eq!(p.stats().conflicting, 0);
        assert_eq!(p.slot_moves(), 0);
    }
}
