//! Soak run: the real processing loop ([`Engine`]) fed by the simulated source for many frame
//! sets, measuring frame-set-ready → position-published latency, deadline misses, resident
//! memory and counter consistency. Used by `examples/soak.rs` and `tests/soak.rs`.
//!
//! "Ready" is the instant the source hands the filled set back to the loop (a thin source
//! wrapper takes it); "published" is the instant `Engine::step` returns, right after the record
//! went into the latest-value slot.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::stream::TrackStatus;
use tokio::sync::watch;

use crate::clock;
use crate::engine::{ActiveParams, Engine, ParamsHandle, StepOutcome};
use crate::error::{FirmwareError, Result};
use crate::source::sim::{SimSource, SimSourceConfig};
use crate::source::{FrameSet, FrameSource, SourceError, SourceStats};
use crate::status::SharedStatus;

/// What to run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SoakConfig {
    /// Frame sets to run.
    pub frames: u64,
    /// Frame rate of the simulated cameras, Hz (also the latency budget: one period).
    pub fps: f64,
    /// `false`: the source delivers as fast as the loop takes sets.
    pub paced: bool,
}

/// Resident set size in bytes from `/proc/self/statm` (Linux); `None` elsewhere.
pub fn rss_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = text.split_whitespace().nth(1)?.parse().ok()?;
    // SAFETY: sysconf has no preconditions.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    Some(pages * u64::try_from(page).ok()?)
}

/// Measured results.
#[derive(Debug, Clone, PartialEq)]
pub struct SoakReport {
    /// Records the loop returned, as counted by the soak run itself.
    pub sets_published: u64,
    /// Of those, records with a position.
    pub tracked: u64,
    /// Of those, records without a position (no marker, fault).
    pub lost: u64,
    /// Of those, records the quality gate refused.
    pub gated: u64,
    /// Sets the source delivered ([`SourceStats`]).
    pub sets_delivered: u64,
    /// Sets the source skipped.
    pub sets_dropped: u64,
    /// Engine counters: sets processed, records published, deadline misses.
    pub engine_sets_processed: u64,
    /// The loop's own count of published records.
    pub engine_published: u64,
    /// The loop's own count of sets over its deadline.
    pub engine_deadline_misses: u64,
    /// Sets whose ready → published latency exceeded the frame period.
    pub latency_over_period: u64,
    /// Published frame indices strictly increasing (no duplicates, no reordering).
    pub frames_monotonic: bool,
    /// Latency percentiles in µs: p50, p99, p99.9, max.
    pub latency_us: [f64; 4],
    /// RSS in bytes at start (after warm-up), middle and end.
    pub rss_bytes: [u64; 3],
    /// Duration of the run, wall-clock seconds.
    pub wall_s: f64,
}

impl SoakReport {
    /// Counter cross-checks; each mismatch is described.
    pub fn consistency_errors(&self) -> Vec<String> {
        let mut errs = Vec::new();
        let mut check = |ok: bool, what: String| {
            if !ok {
                errs.push(what);
            }
        };
        check(
            self.engine_sets_processed == self.sets_published,
            format!(
                "engine sets_processed {} != sets seen published {}",
                self.engine_sets_processed, self.sets_published
            ),
        );
        check(
            self.engine_published == self.sets_published,
            format!(
                "engine published {} != sets seen published {}",
                self.engine_published, self.sets_published
            ),
        );
        check(
            self.tracked + self.lost + self.gated == self.sets_published,
            format!(
                "tracked {} + lost {} + gated {} != published {}",
                self.tracked, self.lost, self.gated, self.sets_published
            ),
        );
        check(
            self.sets_delivered == self.sets_published,
            format!(
                "source delivered {} != published {}",
                self.sets_delivered, self.sets_published
            ),
        );
        check(
            self.frames_monotonic,
            "published frame indices not strictly increasing".into(),
        );
        errs
    }
}

/// Records the instant each set became ready (CLOCK_MONOTONIC ns).
struct ReadyStamp<S> {
    inner: S,
    ready_ns: Arc<AtomicU64>,
}

impl<S: FrameSource> FrameSource for ReadyStamp<S> {
    fn camera_count(&self) -> usize {
        self.inner.camera_count()
    }
    fn allocate_set(&self) -> FrameSet {
        self.inner.allocate_set()
    }
    fn next_set(&mut self, out: &mut FrameSet) -> std::result::Result<(), SourceError> {
        let r = self.inner.next_set(out);
        self.ready_ns.store(clock::monotonic_ns(), Ordering::Relaxed);
        r
    }
    fn stats(&self) -> SourceStats {
        self.inner.stats()
    }
    fn describe(&self) -> String {
        self.inner.describe()
    }
}

fn percentile(sorted: &[u32], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    f64::from(sorted[i.min(sorted.len() - 1)]) / 1000.0
}

/// Runs the soak. `progress` is called about every 10 % with (sets done, RSS bytes).
pub fn run(cfg: SoakConfig, mut progress: impl FnMut(u64, u64)) -> Result<SoakReport> {
    let sim_cfg = SimSourceConfig {
        fps: cfg.fps,
        paced: cfg.paced,
        frames: Some(cfg.frames),
        ..SimSourceConfig::default()
    };
    sim_cfg.validate()?;
    let sim = SimSource::new(&sim_cfg).map_err(|e| FirmwareError::Config {
        reason: e.to_string(),
    })?;
    let handle = Arc::new(ParamsHandle::new());
    handle.install(ActiveParams {
        rig: sim.scenario().rig().clone(),
        crc: 1,
    });
    let status = Arc::new(SharedStatus::new(
        sim.camera_count(),
        sim.describe(),
        "none".into(),
    ));
    let ready_ns = Arc::new(AtomicU64::new(0));
    let source = ReadyStamp {
        inner: sim,
        ready_ns: Arc::clone(&ready_ns),
    };
    let (tx, _rx) = watch::channel(None);
    let period = Duration::from_secs_f64(1.0 / cfg.fps);
    let mut engine = Engine::new(
        Box::new(source),
        TrackerConfig::default(),
        handle,
        tx,
        Arc::clone(&status),
        period,
    );
    let period_ns = u64::try_from(period.as_nanos()).unwrap_or(u64::MAX);
    let n = usize::try_from(cfg.frames).unwrap_or(usize::MAX);
    // Filled with a non-zero value so every page of the record is touched now, before the
    // start RSS sample: a merely reserved buffer is faulted in page by page as it fills
    // (4 bytes a set, ~0.4 MiB per 10^5 sets), which earlier showed up as an RSS "creep".
    let mut lat_ns: Vec<u32> = vec![u32::MAX; n];
    let mut done_sets = 0usize;
    let (mut tracked, mut lost, mut gated, mut over) = (0u64, 0u64, 0u64, 0u64);
    let mut last_frame: Option<u64> = None;
    let mut monotonic = true;
    let mut rss = [0u64; 3];
    let warmup = (cfg.frames / 100).clamp(1, 1000);
    let tick = (cfg.frames / 10).max(1);
    let t0 = std::time::Instant::now();
    loop {
        match engine.step()? {
            StepOutcome::EndOfStream => break,
            StepOutcome::SourceError => {
                return Err(FirmwareError::Config {
                    reason: "simulated source reported a camera fault".into(),
                });
            }
            StepOutcome::Published(rec) => {
                let done_ns = clock::monotonic_ns();
                let l = done_ns.saturating_sub(ready_ns.load(Ordering::Relaxed));
                if l > period_ns {
                    over += 1;
                }
                if let Some(slot) = lat_ns.get_mut(done_sets) {
                    *slot = u32::try_from(l).unwrap_or(u32::MAX);
                    done_sets += 1;
                }
                match rec.status {
                    TrackStatus::Ok => tracked += 1,
                    TrackStatus::Rejected => gated += 1,
                    _ => lost += 1,
                }
                if last_frame.is_some_and(|f| rec.frame <= f) {
                    monotonic = false;
                }
                last_frame = Some(rec.frame);
                let done = done_sets as u64;
                if done == warmup {
                    rss[0] = rss_bytes().unwrap_or(0);
                } else if done == cfg.frames / 2 {
                    rss[1] = rss_bytes().unwrap_or(0);
                }
                if done.is_multiple_of(tick) {
                    progress(done, rss_bytes().unwrap_or(0));
                }
            }
        }
    }
    rss[2] = rss_bytes().unwrap_or(0);
    let wall_s = t0.elapsed().as_secs_f64();
    lat_ns.truncate(done_sets);
    let published = lat_ns.len() as u64;
    lat_ns.sort_unstable();
    let stats = engine.source().stats();
    let r = Ordering::Relaxed;
    Ok(SoakReport {
        sets_published: published,
        tracked,
        lost,
        gated,
        sets_delivered: stats.sets_delivered,
        sets_dropped: stats.sets_dropped,
        engine_sets_processed: status.sets_processed.load(r),
        engine_published: status.published.load(r),
        engine_deadline_misses: status.deadline_misses.load(r),
        latency_over_period: over,
        frames_monotonic: monotonic,
        latency_us: [
            percentile(&lat_ns, 0.5),
            percentile(&lat_ns, 0.99),
            percentile(&lat_ns, 0.999),
            lat_ns.last().map_or(f64::NAN, |&v| f64::from(v) / 1000.0),
        ],
        rss_bytes: rss,
        wall_s,
    })
}
