//! A clock model per camera: its frame period and phase estimated from its timestamp stream
//! (docs/timing.md, "Camera clocks").
//!
//! Free-running cameras each expose on their own crystal: a period of their own (tens of ppm
//! from nominal), a phase of their own within it, and driver timestamps that jitter by
//! 100–500 µs (USB scheduling, driver clock recovery). Frames are dropped, sometimes delivered
//! twice, and the timestamps can jump (a driver clock reset, a camera restart).
//!
//! [`ClockModel`] fits a straight line `timestamp = a + period × index` over a window of recent
//! frames, where `index` counts elapsed frame periods (a dropped frame leaves its index out).
//! The line's value at a frame's index is the *smoothed instant* of that frame: the jitter
//! averages out, the drift is followed because the window slides. Timestamps farther from the
//! line than a few times the jitter are not used to update it (outliers); a step the line cannot
//! explain re-initialises the model (a jump). [`relative_clock`] compares two models: the phase
//! of one camera against another and how fast it drifts.
//!
//! The window is allocated once, at construction; [`ClockModel::observe`] does not allocate and
//! costs O(1) (running sums, rebased once per window length); [`ClockModel::report`] scans the
//! window (O(window)) for the largest residual.

use alloc::format;
use alloc::vec;
use alloc::vec::Vec;

use crate::error::{Error, Result};

/// Frames collected before the first period estimate (their median interval).
const WARM_FRAMES: usize = 8;

/// Settings of a [`ClockModel`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockConfig {
    /// Frames in the fitting window (the line is fitted to at most this many recent frames).
    /// Longer: smoother instants and a steadier rate; shorter: follows rate changes sooner.
    pub window_frames: usize,
    /// Frames in the fit before the model is locked and its instants are used.
    pub lock_frames: usize,
    /// The configured frame period (ns), if any: only for the rate error in ppm; the period
    /// itself is always measured.
    pub nominal_period_ns: Option<f64>,
    /// A timestamp farther from the line than this many RMS residuals is an outlier.
    pub gate_sigmas: f64,
    /// The outlier gate is never narrower than this (ns): a clean stream has no residual to
    /// scale from.
    pub min_gate_ns: f64,
    /// Consecutive outliers that make a jump (the camera's phase changed).
    pub outliers_to_jump: u32,
    /// A gap longer than this (ns) whose frame is off the line re-initialises at once (a
    /// camera that restarted after a stall); a shorter one counts as dropped frames.
    pub max_gap_ns: u64,
}

impl Default for ClockConfig {
    fn default() -> Self {
        Self {
            window_frames: 1024,
            lock_frames: 16,
            nominal_period_ns: None,
            gate_sigmas: 4.0,
            min_gate_ns: 100_000.0,
            outliers_to_jump: 4,
            max_gap_ns: 1_000_000_000,
        }
    }
}

impl ClockConfig {
    /// The defaults with a nominal frame rate (for the rate error); `None` or a rate that is
    /// not positive leaves the rate error out.
    pub fn with_nominal_fps(fps: Option<f64>) -> Self {
        Self {
            nominal_period_ns: fps.filter(|f| f.is_finite() && *f > 0.0).map(|f| 1e9 / f),
            ..Self::default()
        }
    }

    /// Checks the settings, naming the first one out of range.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str| {
            Err(Error::InvalidParams {
                reason: format!("clock model: {what}"),
            })
        };
        if self.window_frames < 2 * WARM_FRAMES {
            return bad(&format!(
                "window_frames = {} is below {}",
                self.window_frames,
                2 * WARM_FRAMES
            ));
        }
        if self.lock_frames < WARM_FRAMES || self.lock_frames > self.window_frames {
            return bad(&format!(
                "lock_frames = {} must lie in {WARM_FRAMES}..={}",
                self.lock_frames, self.window_frames
            ));
        }
        if self
            .nominal_period_ns
            .is_some_and(|p| !(p.is_finite() && p > 0.0))
        {
            return bad("nominal_period_ns must be a positive number");
        }
        if !(self.gate_sigmas.is_finite() && self.gate_sigmas >= 1.0) {
            return bad("gate_sigmas must be at least 1");
        }
        if !(self.min_gate_ns.is_finite() && self.min_gate_ns >= 0.0) {
            return bad("min_gate_ns must be a non-negative number");
        }
        if self.outliers_to_jump == 0 {
            return bad("outliers_to_jump must be at least 1");
        }
        Ok(())
    }
}

/// Where a model stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ClockState {
    /// Not enough frames yet since start: instants are the raw timestamps.
    #[default]
    WarmingUp,
    /// The line is fitted: instants are smoothed.
    Locked,
    /// A jump re-initialised the model; raw timestamps until it is locked again.
    Relocking,
}

impl ClockState {
    /// The name used on `/status` and `/metrics`.
    pub fn as_str(self) -> &'static str {
        match self {
            ClockState::WarmingUp => "warming_up",
            ClockState::Locked => "locked",
            ClockState::Relocking => "relocking",
        }
    }
}

/// What the model made of one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameClock {
    /// The frame's instant (ns, the timestamps' clock): the line's value at the frame's index
    /// when [`Self::smoothed`], else the raw timestamp.
    pub instant_ns: u64,
    /// The timestamp as given.
    pub raw_ns: u64,
    /// `instant_ns` comes from the fitted line (the model is locked).
    pub smoothed: bool,
    /// The frame repeats the one before (same sequence, or within a fraction of a period):
    /// skip it. Its instant is the earlier frame's.
    pub duplicate: bool,
    /// Frames missing just before this one (its index minus the previous one's, minus 1).
    pub dropped_before: u64,
    /// The timestamp was too far from the line to update it (its instant is still the line's).
    pub outlier: bool,
    /// A jump was detected at this frame: the model started again from it.
    pub jump: bool,
}

/// A model's figures (`/status`, `/metrics`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ClockReport {
    /// Warming up, locked or re-locking.
    pub state: ClockState,
    /// Measured frame period (ns), once fitted.
    pub period_ns: Option<f64>,
    /// Measured rate against the nominal one (ppm; positive = the camera runs fast), when a
    /// nominal period is configured and the period is measured.
    pub rate_error_ppm: Option<f64>,
    /// RMS distance of the used timestamps from the line (ns): the timestamp jitter.
    pub jitter_rms_ns: Option<f64>,
    /// Largest distance of a timestamp in the window from the line as it was when it arrived
    /// (ns), outliers included.
    pub jitter_max_ns: Option<f64>,
    /// Frames observed.
    pub frames: u64,
    /// Frames missing from the index sequence (dropped by camera, driver or source).
    pub drops: u64,
    /// Frames delivered twice.
    pub duplicates: u64,
    /// Steps the line could not explain (model re-initialised).
    pub jumps: u64,
    /// Timestamps left out of the fit as too far from the line.
    pub outliers: u64,
    /// The camera's sequence numbers count its frames (else indices come from the timestamps).
    pub sequence_used: bool,
}

/// One frame of the window.
#[derive(Debug, Clone, Copy, Default)]
struct Point {
    /// Frame index since the epoch's first frame.
    k: i64,
    /// Timestamp minus the epoch's origin (ns).
    t_rel: i64,
    /// Distance from the line when it arrived (ns).
    innov_ns: f32,
    /// Part of the fit (not an outlier).
    used: bool,
}

/// Running sums of the fit over the used points, in coordinates relative to a base point and
/// a reference period (so that they stay small and the sums keep their precision).
#[derive(Debug, Clone, Copy, Default)]
struct Sums {
    n: f64,
    k: f64,
    u: f64,
    kk: f64,
    ku: f64,
    uu: f64,
}

/// The clock model of one camera; feed it every frame with [`Self::observe`].
#[derive(Debug, Clone)]
pub struct ClockModel {
    cfg: ClockConfig,
    ring: Vec<Point>,
    /// Next slot to write.
    head: usize,
    len: usize,
    warm: [(u64, Option<u64>); WARM_FRAMES],
    warm_len: usize,
    state: ClockState,
    /// The line exists (the warm-up frames gave a period).
    fitted: bool,
    /// Absolute time (ns) of `t_rel = 0` in this epoch.
    epoch_t0: u64,
    /// Base point and reference period of the sums.
    k_base: i64,
    t_base: i64,
    p_ref: f64,
    sums: Sums,
    /// Fit `u = a + c (k - k_base)` where `u = t_rel - t_base - (k - k_base) p_ref`.
    a: f64,
    c: f64,
    rms_ns: f64,
    have_last: bool,
    last_k: i64,
    last_t: u64,
    last_seq: Option<u64>,
    last_instant: u64,
    /// Sequences count frames (sticky: once found not to, timestamps alone decide).
    seq_trusted: bool,
    outlier_run: u32,
    frames: u64,
    drops: u64,
    duplicates: u64,
    jumps: u64,
    outliers: u64,
}

impl ClockModel {
    /// A model with its window allocated; the settings are checked.
    pub fn new(cfg: ClockConfig) -> Result<Self> {
        cfg.validate()?;
        Ok(Self {
            cfg,
            ring: vec![Point::default(); cfg.window_frames],
            head: 0,
            len: 0,
            warm: [(0, None); WARM_FRAMES],
            warm_len: 0,
            state: ClockState::WarmingUp,
            fitted: false,
            epoch_t0: 0,
            k_base: 0,
            t_base: 0,
            p_ref: 0.0,
            sums: Sums::default(),
            a: 0.0,
            c: 0.0,
            rms_ns: 0.0,
            have_last: false,
            last_k: 0,
            last_t: 0,
            last_seq: None,
            last_instant: 0,
            seq_trusted: true,
            outlier_run: 0,
            frames: 0,
            drops: 0,
            duplicates: 0,
            jumps: 0,
            outliers: 0,
        })
    }

    /// The settings.
    pub fn config(&self) -> &ClockConfig {
        &self.cfg
    }

    /// Warming up, locked or re-locking.
    pub fn state(&self) -> ClockState {
        self.state
    }

    /// Whether instants are smoothed.
    pub fn is_locked(&self) -> bool {
        self.state == ClockState::Locked
    }

    /// The measured period (ns), once fitted.
    pub fn period_ns(&self) -> Option<f64> {
        self.fitted.then_some(self.p_ref + self.c)
    }

    /// Jumps detected since construction.
    pub fn jumps(&self) -> u64 {
        self.jumps
    }

    /// The instant of the newest (non-duplicate) frame: smoothed when locked, else raw.
    pub fn last_instant_ns(&self) -> Option<u64> {
        self.have_last.then_some(self.last_instant)
    }

    /// Feeds one frame: its sequence number (the camera's frame counter, if it has one) and
    /// its timestamp (ns). Returns the frame's instant and what the model saw.
    pub fn observe(&mut self, sequence: Option<u64>, timestamp_ns: u64) -> FrameClock {
        self.frames += 1;
        let mut out = FrameClock {
            instant_ns: timestamp_ns,
            raw_ns: timestamp_ns,
            smoothed: false,
            duplicate: false,
            dropped_before: 0,
            outlier: false,
            jump: false,
        };
        if sequence.is_none() {
            self.seq_trusted = false;
        }
        if !self.have_last {
            self.restart(sequence, timestamp_ns, ClockState::WarmingUp);
            return out;
        }
        if !self.fitted {
            self.warm_step(sequence, timestamp_ns, &mut out);
        } else {
            self.line_step(sequence, timestamp_ns, &mut out);
        }
        if !out.duplicate {
            self.last_instant = out.instant_ns;
        }
        out
    }

    /// Starts a new epoch from one frame (start or after a jump).
    fn restart(&mut self, sequence: Option<u64>, t: u64, state: ClockState) {
        self.state = state;
        self.fitted = false;
        self.len = 0;
        self.head = 0;
        self.sums = Sums::default();
        self.a = 0.0;
        self.c = 0.0;
        self.rms_ns = 0.0;
        self.outlier_run = 0;
        self.warm[0] = (t, sequence);
        self.warm_len = 1;
        self.have_last = true;
        self.last_k = 0;
        self.last_t = t;
        self.last_seq = sequence;
        self.last_instant = t;
    }

    fn jump(&mut self, sequence: Option<u64>, t: u64, out: &mut FrameClock) {
        self.jumps += 1;
        out.jump = true;
        out.instant_ns = t;
        out.smoothed = false;
        self.restart(sequence, t, ClockState::Relocking);
    }

    /// Before the first period estimate: collect frames (raw instants out).
    fn warm_step(&mut self, sequence: Option<u64>, t: u64, out: &mut FrameClock) {
        let seq_back = matches!((sequence, self.last_seq), (Some(s), Some(l)) if s < l);
        if t < self.last_t || (self.seq_trusted && seq_back) {
            self.jump(sequence, t, out);
            return;
        }
        if t == self.last_t {
            self.duplicates += 1;
            out.duplicate = true;
            out.instant_ns = self.last_instant;
            return;
        }
        self.warm[self.warm_len] = (t, sequence);
        self.warm_len += 1;
        self.last_t = t;
        self.last_seq = sequence;
        if self.warm_len == WARM_FRAMES {
            self.fit_from_warm();
        }
    }

    /// The first line: the period is the median interval of the warm-up frames; each frame's
    /// index follows from its sequence (when sequences count frames) or its interval.
    fn fit_from_warm(&mut self) {
        let w = self.warm;
        let gaps = WARM_FRAMES - 1;
        let seq_step = |i: usize| match (w[i].1, w[i - 1].1) {
            (Some(s), Some(l)) if s > l => Some(s - l),
            _ => None,
        };
        let unit_steps = (1..WARM_FRAMES).filter(|&i| seq_step(i) == Some(1)).count();
        if 2 * unit_steps < gaps {
            // Sequences that stand still or leap do not count this camera's frames.
            self.seq_trusted = false;
        }
        let mut est = [0.0f64; WARM_FRAMES - 1];
        for (i, e) in est.iter_mut().enumerate() {
            let g = (w[i + 1].0 - w[i].0) as f64;
            let dk = if self.seq_trusted {
                seq_step(i + 1).unwrap_or(1)
            } else {
                1
            };
            *e = g / dk as f64;
        }
        est.sort_unstable_by(|a, b| a.total_cmp(b));
        let p0 = est[gaps / 2];
        self.epoch_t0 = w[0].0;
        // The sums' coordinates: base at the first frame, reference period p0.
        self.p_ref = p0;
        self.k_base = 0;
        self.t_base = 0;
        let mut k = 0i64;
        self.push(0, 0, 0.0, true);
        for i in 1..WARM_FRAMES {
            let g = (w[i].0 - w[i - 1].0) as f64;
            let by_time = libm::round(g / p0) as i64;
            let dk = match (self.seq_trusted, seq_step(i)) {
                (true, Some(d)) => i64::try_from(d).unwrap_or(i64::MAX / 4),
                _ => by_time,
            };
            if dk <= 0 {
                // Much closer than a period to the frame before: the same frame again.
                self.duplicates += 1;
                continue;
            }
            self.drops += (dk - 1) as u64;
            k += dk;
            self.push(k, (w[i].0 - self.epoch_t0) as i64, 0.0, true);
        }
        self.fitted = true;
        self.last_k = k;
        self.rebase();
        self.promote();
    }

    /// With a line: index the frame, sort it into duplicate / outlier / jump / used.
    fn line_step(&mut self, sequence: Option<u64>, t: u64, out: &mut FrameClock) {
        let period = self.p_ref + self.c;
        let t_rel = i128::from(t) - i128::from(self.epoch_t0);
        let t_rel_f = t_rel as f64;
        let gap_ns = t.saturating_sub(self.last_t);
        let since_last = t_rel_f - self.line(self.last_k);
        let mut by_seq = None;
        if let (true, Some(s), Some(l)) = (self.seq_trusted, sequence, self.last_seq) {
            if s == l {
                if (t as f64 - self.last_t as f64).abs() < 0.5 * period {
                    return self.duplicate(out);
                }
                // The counter stood still while time went on: it does not count frames.
                self.seq_trusted = false;
            } else if s < l {
                return self.jump(sequence, t, out);
            } else {
                by_seq = Some(s - l);
            }
        }
        let dk = match by_seq {
            // A counter that leapt while the time did not shows as a residual beyond half a
            // period below.
            Some(d) => i64::try_from(d).unwrap_or(i64::MAX / 4),
            None => {
                let dk = libm::round(since_last / period);
                if dk < 0.0 {
                    // Back in time by more than half a period.
                    return self.jump(sequence, t, out);
                }
                if dk == 0.0 {
                    return self.duplicate(out);
                }
                dk as i64
            }
        };
        let k = self.last_k.saturating_add(dk);
        let r = t_rel_f - self.line(k);
        let gate = self.gate(period);
        let off_line = r.abs() > gate;
        // Sequence and time disagree on which frame this is, or a frame after a long stall
        // sits off the line: the clock stepped.
        if off_line && ((by_seq.is_some() && r.abs() > 0.5 * period) || gap_ns > self.cfg.max_gap_ns) {
            return self.jump(sequence, t, out);
        }
        if off_line {
            self.outlier_run += 1;
            if self.outlier_run >= self.cfg.outliers_to_jump {
                return self.jump(sequence, t, out);
            }
            self.outliers += 1;
            out.outlier = true;
        } else {
            self.outlier_run = 0;
        }
        let t_rel_i = i64::try_from(t_rel).unwrap_or(i64::MAX);
        self.push(k, t_rel_i, r as f32, !off_line);
        if k - self.k_base >= self.ring.len() as i64 {
            self.rebase();
        } else {
            self.fit();
        }
        self.drops += (dk - 1) as u64;
        out.dropped_before = (dk - 1) as u64;
        self.last_k = k;
        self.last_t = t;
        self.last_seq = sequence;
        self.promote();
        if self.state == ClockState::Locked {
            out.instant_ns = self.instant_at(k);
            out.smoothed = true;
        }
    }

    fn duplicate(&mut self, out: &mut FrameClock) {
        self.duplicates += 1;
        out.duplicate = true;
        out.instant_ns = self.last_instant;
        out.smoothed = self.state == ClockState::Locked;
    }

    /// Locked once the fit has enough frames.
    fn promote(&mut self) {
        if self.fitted && self.state != ClockState::Locked && self.sums.n >= self.cfg.lock_frames as f64 {
            self.state = ClockState::Locked;
        }
    }

    fn gate(&self, period: f64) -> f64 {
        (self.cfg.gate_sigmas * self.rms_ns)
            .max(self.cfg.min_gate_ns)
            .min(0.25 * period)
    }

    /// The line at index `k`, relative to the epoch's origin (ns).
    fn line(&self, k: i64) -> f64 {
        let dk = (k - self.k_base) as f64;
        self.t_base as f64 + dk * self.p_ref + self.a + self.c * dk
    }

    fn instant_at(&self, k: i64) -> u64 {
        let v = i128::from(self.epoch_t0) + libm::round(self.line(k)) as i128;
        u64::try_from(v.max(0)).unwrap_or(u64::MAX)
    }

    fn coords(&self, p: &Point) -> (f64, f64) {
        let dk = (p.k - self.k_base) as f64;
        (dk, (p.t_rel - self.t_base) as f64 - dk * self.p_ref)
    }

    fn add(&mut self, p: &Point, sign: f64) {
        let (k, u) = self.coords(p);
        let s = &mut self.sums;
        s.n += sign;
        s.k += sign * k;
        s.u += sign * u;
        s.kk += sign * k * k;
        s.ku += sign * k * u;
        s.uu += sign * u * u;
    }

    /// Appends a frame to the window, evicting the oldest when full.
    fn push(&mut self, k: i64, t_rel: i64, innov_ns: f32, used: bool) {
        let cap = self.ring.len();
        if self.len == cap {
            let old = self.ring[self.head];
            if old.used {
                self.add(&old, -1.0);
            }
        } else {
            self.len += 1;
        }
        let p = Point {
            k,
            t_rel,
            innov_ns,
            used,
        };
        self.ring[self.head] = p;
        self.head = (self.head + 1) % cap;
        if used {
            self.add(&p, 1.0);
        }
    }

    /// Moves the base to the newest frame and the reference period to the fitted one, and
    /// recomputes the sums (once per window length: keeps them small and exact).
    fn rebase(&mut self) {
        if self.fitted && self.sums.n >= 2.0 {
            self.fit();
            self.p_ref += self.c;
        }
        let newest = self.ring[(self.head + self.ring.len() - 1) % self.ring.len()];
        self.k_base = newest.k;
        self.t_base = newest.t_rel;
        self.sums = Sums::default();
        for i in 0..self.len {
            let p = self.ring[i];
            if p.used {
                self.add(&p, 1.0);
            }
        }
        self.fit();
    }

    fn fit(&mut self) {
        let s = self.sums;
        if s.n < 2.0 {
            self.a = if s.n > 0.0 { s.u / s.n } else { 0.0 };
            self.c = 0.0;
            return;
        }
        let kbar = s.k / s.n;
        let ubar = s.u / s.n;
        let skk = s.kk - s.n * kbar * kbar;
        let sku = s.ku - s.n * kbar * ubar;
        let suu = s.uu - s.n * ubar * ubar;
        if skk.is_nan() || skk <= 0.0 {
            // All used frames at one index: no slope to fit.
            return;
        }
        self.c = sku / skk;
        self.a = ubar - self.c * kbar;
        let ssr = (suu - self.c * sku).max(0.0);
        self.rms_ns = libm::sqrt(ssr / (s.n - 2.0).max(1.0));
    }

    /// The model's figures.
    pub fn report(&self) -> ClockReport {
        let period = self.period_ns();
        let max = self.ring[..self.len]
            .iter()
            .map(|p| f64::from(p.innov_ns).abs())
            .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))));
        ClockReport {
            state: self.state,
            period_ns: period,
            rate_error_ppm: match (period, self.cfg.nominal_period_ns) {
                (Some(p), Some(n)) => Some((n / p - 1.0) * 1e6),
                _ => None,
            },
            jitter_rms_ns: self.fitted.then_some(self.rms_ns),
            jitter_max_ns: if self.fitted { max } else { None },
            frames: self.frames,
            drops: self.drops,
            duplicates: self.duplicates,
            jumps: self.jumps,
            outliers: self.outliers,
            sequence_used: self.seq_trusted,
        }
    }
}

/// One camera's clock against another's (the reference, usually camera 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativeClock {
    /// How long after the reference camera's nearest frame this camera's newest frame was
    /// exposed (ns), in −½…+½ of the reference's period.
    pub phase_ns: f64,
    /// How fast that phase changes (ppm of elapsed time; positive = later and later, i.e. this
    /// camera's frames come slower than the reference's).
    pub drift_ppm: f64,
    /// The same as phase change per minute (µs/min).
    pub drift_us_per_min: f64,
}

/// The phase of `other` against `reference` and its drift; `None` unless both are locked.
///
/// For cameras at different rates (one at a whole multiple of the other's period), the drift
/// is that of the slower camera's frames against every `m`-th frame of the faster.
pub fn relative_clock(reference: &ClockModel, other: &ClockModel) -> Option<RelativeClock> {
    if !(reference.is_locked() && other.is_locked()) {
        return None;
    }
    let b_r = reference.period_ns()?;
    let b_o = other.period_ns()?;
    let d = (i128::from(other.epoch_t0) - i128::from(reference.epoch_t0)) as f64 + other.line(other.last_k)
        - reference.line(reference.last_k);
    let x = d / b_r;
    let phase_ns = (x - libm::round(x)) * b_r;
    let m = libm::round(b_o / b_r).max(1.0);
    let rate = (b_o - m * b_r) / b_o;
    Some(RelativeClock {
        phase_ns,
        drift_ppm: rate * 1e6,
        drift_us_per_min: rate * 60e6,
    })
}

/// The clock models of a board's cameras, allocated together.
#[derive(Debug, Clone)]
pub struct CameraClocks {
    models: Vec<ClockModel>,
}

impl CameraClocks {
    /// `cameras` models with the same settings (checked).
    pub fn new(cameras: usize, cfg: ClockConfig) -> Result<Self> {
        let model = ClockModel::new(cfg)?;
        Ok(Self {
            models: vec![model; cameras],
        })
    }

    /// Number of cameras.
    pub fn len(&self) -> usize {
        self.models.len()
    }

    /// Whether there are no cameras.
    pub fn is_empty(&self) -> bool {
        self.models.is_empty()
    }

    /// Camera `camera`'s model.
    pub fn model(&self, camera: usize) -> Option<&ClockModel> {
        self.models.get(camera)
    }

    /// Feeds camera `camera`'s frame to its model (see [`ClockModel::observe`]).
    pub fn observe(&mut self, camera: usize, sequence: Option<u64>, timestamp_ns: u64) -> Result<FrameClock> {
        let count = self.models.len();
        self.models
            .get_mut(camera)
            .map(|m| m.observe(sequence, timestamp_ns))
            .ok_or(Error::NoSuchCamera { index: camera, count })
    }

    /// Camera `camera`'s clock against camera 0's (`None` until both are locked).
    pub fn relative_to_first(&self, camera: usize) -> Option<RelativeClock> {
        relative_clock(self.models.first()?, self.models.get(camera)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SplitMix64: deterministic noise without a rand dependency.
    struct Rng(u64);

    impl Rng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        /// Uniform in [0, 1).
        fn unit(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        fn uniform(&mut self, half_width: f64) -> f64 {
            (2.0 * self.unit() - 1.0) * half_width
        }
        /// Box–Muller.
        fn gauss(&mut self, sigma: f64) -> f64 {
            let u1 = self.unit().max(1e-300);
            let u2 = self.unit();
            sigma * libm::sqrt(-2.0 * libm::log(u1)) * libm::cos(2.0 * core::f64::consts::PI * u2)
        }
    }

    const P120: f64 = 1e9 / 120.0;

    /// A free-running camera: exposure instant of frame `k` and its jittered timestamp.
    struct Cam {
        start_ns: f64,
        period_ns: f64,
    }

    impl Cam {
        fn true_ns(&self, k: u64) -> f64 {
            self.start_ns + k as f64 * self.period_ns
        }
    }

    fn model() -> ClockModel {
        ClockModel::new(ClockConfig::with_nominal_fps(Some(120.0))).unwrap()
    }

    fn rms(v: &[f64]) -> f64 {
        libm::sqrt(v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64)
    }

    #[test]
    fn clean_stream_is_recovered_exactly() {
        let mut m = model();
        let cam = Cam {
            start_ns: 5e9,
            period_ns: 8_333_000.0,
        };
        for k in 0..3000u64 {
            let t = libm::round(cam.true_ns(k)) as u64;
            let f = m.observe(Some(k + 17), t);
            assert!(
                !f.duplicate && !f.outlier && !f.jump && f.dropped_before == 0,
                "{k}: {f:?}"
            );
            if k >= 16 {
                assert!(f.smoothed, "locked after 16 frames");
            }
            assert!(f.instant_ns.abs_diff(t) <= 1, "{k}: {} vs {t}", f.instant_ns);
        }
        let r = m.report();
        assert_eq!(r.state, ClockState::Locked);
        assert!((r.period_ns.unwrap() - 8_333_000.0).abs() < 1e-3, "{r:?}");
        // 8.333 ms against 1/120 s: the camera runs 40 ppm fast.
        assert!((r.rate_error_ppm.unwrap() - 40.0).abs() < 0.01, "{r:?}");
        assert!(
            r.jitter_rms_ns.unwrap() < 1.0 && r.jitter_max_ns.unwrap() <= 1.0,
            "{r:?}"
        );
        assert_eq!((r.drops, r.duplicates, r.jumps, r.outliers), (0, 0, 0, 0));
        assert!(r.sequence_used);
    }

    /// Smoothed instants against the truth compared with raw ones, after warm-up.
    fn smoothing_ratio(noise: impl Fn(&mut Rng) -> f64, with_seq: bool) -> (f64, f64, ClockReport) {
        let mut rng = Rng(0x5EED_0001);
        let mut m = model();
        let cam = Cam {
            start_ns: 1e9 + 1_234_567.0,
            period_ns: P120 * (1.0 + 20e-6),
        };
        let (mut raw_err, mut smooth_err) = (Vec::new(), Vec::new());
        for k in 0..4000u64 {
            let truth = cam.true_ns(k);
            let t = libm::round(truth + noise(&mut rng)) as u64;
            let f = m.observe(with_seq.then_some(k), t);
            if k >= 200 {
                assert!(f.smoothed, "{k}: {f:?}");
                raw_err.push(t as f64 - truth);
                smooth_err.push(f.instant_ns as f64 - truth);
            }
        }
        (rms(&raw_err), rms(&smooth_err), m.report())
    }

    #[test]
    fn uniform_jitter_is_smoothed() {
        let (raw, smooth, r) = smoothing_ratio(|g| g.uniform(200_000.0), true);
        eprintln!("uniform ±200 µs: raw RMS {raw:.0} ns, smoothed {smooth:.0} ns; {r:?}");
        assert!(smooth <= 0.3 * raw, "raw {raw} ns, smoothed {smooth} ns");
        // Uniform ±200 µs has an RMS of 115 µs.
        let j = r.jitter_rms_ns.unwrap();
        assert!((j - 115_470.0).abs() < 10_000.0, "{r:?}");
        assert!(
            r.jitter_max_ns.unwrap() > 150_000.0 && r.jitter_max_ns.unwrap() < 260_000.0,
            "{r:?}"
        );
        assert!((r.rate_error_ppm.unwrap() + 20.0).abs() < 8.0, "{r:?}");
        assert_eq!((r.drops, r.duplicates, r.jumps), (0, 0, 0));
    }

    #[test]
    fn gaussian_jitter_is_smoothed_without_sequences() {
        let (raw, smooth, r) = smoothing_ratio(|g| g.gauss(200_000.0), false);
        eprintln!("Gaussian σ 200 µs: raw RMS {raw:.0} ns, smoothed {smooth:.0} ns; {r:?}");
        assert!(smooth <= 0.3 * raw, "raw {raw} ns, smoothed {smooth} ns");
        assert!(!r.sequence_used);
        // 4 σ gate: a few Gaussian tails are left out, no jump.
        assert!(r.outliers < 10, "{r:?}");
        assert_eq!((r.drops, r.duplicates, r.jumps), (0, 0, 0), "{r:?}");
    }

    #[test]
    fn drift_of_plus_minus_50_ppm_is_tracked() {
        for ppm in [50.0, -50.0] {
            let mut rng = Rng(7);
            let mut m = model();
            let cam = Cam {
                start_ns: 3e9,
                // A camera fast by `ppm` has a period shorter by that much.
                period_ns: P120 / (1.0 + ppm * 1e-6),
            };
            let mut worst_late = 0.0f64;
            for k in 0..20_000u64 {
                let truth = cam.true_ns(k);
                let f = m.observe(Some(k), libm::round(truth + rng.uniform(200_000.0)) as u64);
                if k > 1000 {
                    worst_late = worst_late.max((f.instant_ns as f64 - truth).abs());
                }
            }
            let r = m.report();
            assert!((r.rate_error_ppm.unwrap() - ppm).abs() < 5.0, "{ppm}: {r:?}");
            // After 2.8 min the drift has moved the phase by 8.3 ms: the line still follows.
            assert!(worst_late < 60_000.0, "{ppm}: worst {worst_late} ns");
        }
    }

    #[test]
    fn drops_single_and_bursts_are_counted_and_bridged() {
        for with_seq in [true, false] {
            let mut rng = Rng(11);
            let mut m = model();
            let cam = Cam {
                start_ns: 2e9,
                period_ns: P120,
            };
            // Frames 100 (single), 300..305 (burst of 5) and 600..620 (burst of 20) are lost.
            let lost = |k: u64| k == 100 || (300..305).contains(&k) || (600..620).contains(&k);
            for k in (0..1000u64).filter(|&k| !lost(k)) {
                let truth = cam.true_ns(k);
                let f = m.observe(
                    with_seq.then_some(k),
                    libm::round(truth + rng.uniform(150_000.0)) as u64,
                );
                let expect = match k {
                    101 => 1,
                    305 => 5,
                    620 => 20,
                    _ => 0,
                };
                assert_eq!(f.dropped_before, expect, "{with_seq} {k}");
                if k > 300 {
                    assert!(
                        (f.instant_ns as f64 - truth).abs() < 60_000.0,
                        "{with_seq} {k}: {f:?}"
                    );
                }
            }
            let r = m.report();
            assert_eq!((r.drops, r.duplicates, r.jumps), (26, 0, 0), "{with_seq}: {r:?}");
        }
    }

    #[test]
    fn duplicates_are_flagged_with_the_first_frames_instant() {
        for with_seq in [true, false] {
            let mut m = model();
            let cam = Cam {
                start_ns: 2e9,
                period_ns: P120,
            };
            let mut dups = 0;
            for k in 0..500u64 {
                let t = cam.true_ns(k) as u64;
                let first = m.observe(with_seq.then_some(k), t);
                assert!(!first.duplicate);
                if k % 50 == 49 {
                    // The same frame again (same sequence and stamp), or a stamp 0.3 ms later.
                    let again = m.observe(with_seq.then_some(k), t + if with_seq { 0 } else { 300_000 });
                    assert!(again.duplicate, "{with_seq} {k}: {again:?}");
                    assert_eq!(again.instant_ns, first.instant_ns);
                    dups += 1;
                }
            }
            let r = m.report();
            assert_eq!(
                (r.duplicates, r.drops, r.jumps),
                (dups, 0, 0),
                "{with_seq}: {r:?}"
            );
            assert_eq!(r.state, ClockState::Locked);
        }
    }

    /// Feeds `frames` frames of `cam` from index `from`, with sequence `seq0 + i` (or none).
    fn feed(
        m: &mut ClockModel,
        cam: &Cam,
        from: u64,
        frames: u64,
        seq0: Option<u64>,
        rng: &mut Rng,
    ) -> Vec<FrameClock> {
        (0..frames)
            .map(|i| {
                let k = from + i;
                let t = libm::round(cam.true_ns(k) + rng.uniform(100_000.0)) as u64;
                m.observe(seq0.map(|s| s + i), t)
            })
            .collect()
    }

    #[test]
    fn a_sequence_reset_is_a_jump() {
        let mut rng = Rng(3);
        let mut m = model();
        let cam = Cam {
            start_ns: 1e9,
            period_ns: P120,
        };
        feed(&mut m, &cam, 0, 500, Some(1000), &mut rng);
        // The camera restarted: its counter begins at 0 again, the phase moved by 3.1 ms.
        let after = Cam {
            start_ns: cam.true_ns(520) + 3_100_000.0,
            period_ns: P120,
        };
        let out = feed(&mut m, &after, 0, 500, Some(0), &mut rng);
        assert!(out[0].jump && !out[0].smoothed, "{:?}", out[0]);
        assert!(out[1..].iter().all(|f| !f.jump));
        assert_eq!(m.report().jumps, 1);
        assert_eq!(m.report().state, ClockState::Locked);
        let last = out.last().unwrap();
        assert!(
            (last.instant_ns as f64 - after.true_ns(499)).abs() < 40_000.0,
            "{last:?}"
        );
    }

    #[test]
    fn a_timestamp_step_is_a_jump_with_and_without_sequences() {
        for with_seq in [true, false] {
            let mut rng = Rng(5);
            let mut m = model();
            let cam = Cam {
                start_ns: 1e9,
                period_ns: P120,
            };
            feed(&mut m, &cam, 0, 500, with_seq.then_some(0), &mut rng);
            // The driver's clock steps by +3.7 ms; the frame counter goes on.
            let stepped = Cam {
                start_ns: cam.start_ns + 3_700_000.0,
                period_ns: P120,
            };
            let out = feed(&mut m, &stepped, 500, 500, with_seq.then_some(500), &mut rng);
            let at = out.iter().position(|f| f.jump).expect("a jump");
            // Less than half a period: a late stamp or a step? A run of outliers decides.
            assert_eq!(at, 3, "{with_seq}: jump at {at}");
            assert!(out[..3].iter().all(|f| f.outlier));
            let r = m.report();
            assert_eq!(r.jumps, 1, "{with_seq}: {r:?}");
            assert_eq!(r.state, ClockState::Locked);
            let last = out.last().unwrap();
            assert!(
                (last.instant_ns as f64 - stepped.true_ns(999)).abs() < 40_000.0,
                "{last:?}"
            );
            // A step back in time.
            let back = Cam {
                start_ns: stepped.start_ns - 500_000_000.0,
                period_ns: P120,
            };
            let out = feed(&mut m, &back, 1000, 100, with_seq.then_some(1000), &mut rng);
            assert!(out[0].jump, "{with_seq}: {:?}", out[0]);
            assert_eq!(m.report().jumps, 2);
        }
    }

    #[test]
    fn single_late_stamps_are_outliers_corrected_by_the_line() {
        let mut rng = Rng(9);
        let mut m = model();
        let cam = Cam {
            start_ns: 1e9,
            period_ns: P120,
        };
        for k in 0..800u64 {
            let truth = cam.true_ns(k);
            // Every 97th stamp is 2 ms late (a USB transfer held back).
            let late = if k % 97 == 96 { 2_000_000.0 } else { 0.0 };
            let f = m.observe(None, libm::round(truth + late + rng.uniform(100_000.0)) as u64);
            if k > 100 {
                assert_eq!(f.outlier, late > 0.0, "{k}: {f:?}");
                assert!((f.instant_ns as f64 - truth).abs() < 40_000.0, "{k}: {f:?}");
            }
        }
        let r = m.report();
        assert_eq!((r.jumps, r.drops), (0, 0), "{r:?}");
        assert!(
            r.jitter_max_ns.unwrap() > 1_800_000.0 && r.jitter_rms_ns.unwrap() < 80_000.0,
            "{r:?}"
        );
    }

    #[test]
    fn phase_and_drift_between_two_cameras_are_recovered() {
        let mut rng = Rng(21);
        let mut clocks = CameraClocks::new(2, ClockConfig::with_nominal_fps(Some(120.0))).unwrap();
        let cam0 = Cam {
            start_ns: 1e9,
            period_ns: P120,
        };
        // Camera 1 exposes 3.1 ms after camera 0, and its crystal is 30 ppm slow.
        let cam1 = Cam {
            start_ns: 1e9 + 3_100_000.0,
            period_ns: P120 * (1.0 + 30e-6),
        };
        assert!(clocks.relative_to_first(1).is_none());
        for k in 0..3000u64 {
            for (c, cam) in [&cam0, &cam1].into_iter().enumerate() {
                let t = libm::round(cam.true_ns(k) + rng.uniform(200_000.0)) as u64;
                clocks.observe(c, Some(k), t).unwrap();
            }
        }
        let rel = clocks.relative_to_first(1).unwrap();
        let truth = cam1.true_ns(2999) - cam0.true_ns(2999);
        assert!((rel.phase_ns - truth).abs() < 30_000.0, "{rel:?} vs {truth}");
        assert!((rel.drift_ppm - 30.0).abs() < 6.0, "{rel:?}");
        // 30 ppm: 1.8 ms of phase per minute.
        assert!((rel.drift_us_per_min - 1800.0).abs() < 360.0, "{rel:?}");
        let self_rel = clocks.relative_to_first(0).unwrap();
        assert!(self_rel.phase_ns.abs() < 1.0 && self_rel.drift_ppm.abs() < 1e-9);
        assert!(matches!(
            clocks.observe(2, None, 0),
            Err(Error::NoSuchCamera { index: 2, count: 2 })
        ));
    }

    #[test]
    fn a_phase_near_half_a_period_wraps_consistently() {
        let mut clocks = CameraClocks::new(2, ClockConfig::default()).unwrap();
        let cam0 = Cam {
            start_ns: 1e9,
            period_ns: P120,
        };
        // 6 ms after camera 0 is 2.33 ms before its next frame.
        let cam1 = Cam {
            start_ns: 1e9 + 6_000_000.0,
            period_ns: P120,
        };
        for k in 0..100u64 {
            clocks.observe(0, Some(k), cam0.true_ns(k) as u64).unwrap();
            clocks.observe(1, Some(k), cam1.true_ns(k) as u64).unwrap();
        }
        let rel = clocks.relative_to_first(1).unwrap();
        assert!((rel.phase_ns - (6_000_000.0 - P120)).abs() < 10.0, "{rel:?}");
    }

    #[test]
    fn a_counter_that_stands_still_is_ignored() {
        let mut m = model();
        let cam = Cam {
            start_ns: 1e9,
            period_ns: P120,
        };
        for k in 0..200u64 {
            let f = m.observe(Some(0), cam.true_ns(k) as u64);
            assert!(!f.duplicate && !f.jump, "{k}: {f:?}");
        }
        let r = m.report();
        assert!(!r.sequence_used && r.state == ClockState::Locked, "{r:?}");
    }

    #[test]
    fn bad_settings_are_named() {
        let e = ClockModel::new(ClockConfig {
            window_frames: 4,
            ..ClockConfig::default()
        })
        .unwrap_err();
        assert!(e.to_string().contains("window_frames"), "{e}");
        let e = ClockConfig {
            gate_sigmas: f64::NAN,
            ..ClockConfig::default()
        }
        .validate()
        .unwrap_err();
        assert!(e.to_string().contains("gate_sigmas"), "{e}");
        assert_eq!(ClockConfig::with_nominal_fps(Some(0.0)).nominal_period_ns, None);
    }
}
