//! The one safety path every robot link goes through: operator enable/disable, the deadman and
//! the [`Supervisor`] judging the newest sample. The socket client, EGM and RSI all hold a
//! [`Gate`] and ask it for a [`Verdict`]; only what they do with a hold differs (a `HOLD` line, or
//! the robot's own position commanded again every cycle).

use std::sync::Arc;

use irtrack_core::robot_proto::HoldReason;
use tokio::sync::watch;

use crate::deadman::Deadman;
use crate::safety::{Sample, Supervisor, Verdict};
use crate::{Clock, PositionFeed, RobotConfig};

/// Operator commands, shared by every link kind through a watch channel.
#[derive(Debug, Clone, Copy, Default)]
pub struct Control {
    /// Bumped on every enable/disable so each command is seen once.
    pub generation: u64,
    /// The operator enabled the link.
    pub enabled: bool,
    /// The link must hold the robot, say goodbye and end (`LinkHandle::shutdown`).
    pub stop: bool,
}

/// Per target leaving irtrackd (µs): the sample's age (capture → on the wire) and the
/// protocol wait (published → on the wire: the time the sample waited for the robot's request
/// or the controller's cycle).
pub struct Latency {
    /// `None` only if the fixed bounds were refused (they are valid; no panic path either way).
    age: Option<hdrhistogram::Histogram<u64>>,
    wait: Option<hdrhistogram::Histogram<u64>>,
}

/// Percentiles of [`Latency`] (µs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct LatencySummary {
    /// Targets recorded.
    pub count: u64,
    /// Sample age (capture → on the wire), median.
    pub p50_us: u64,
    /// Sample age, 99th percentile.
    pub p99_us: u64,
    /// Sample age, 99.9th percentile.
    pub p999_us: u64,
    /// Sample age, largest.
    pub max_us: u64,
    /// Protocol wait, published → on the wire.
    pub wait_p50_us: u64,
    /// Protocol wait, 99th percentile.
    pub wait_p99_us: u64,
    /// Protocol wait, largest.
    pub wait_max_us: u64,
}

impl Latency {
    fn new() -> Self {
        // 1 µs .. 60 s at 3 significant digits (0.1 %), allocated once: recording never
        // allocates. The links record from their own task with `&mut`, so no lock is needed.
        let h = || hdrhistogram::Histogram::new_with_bounds(1, 60_000_000, 3).ok();
        Self { age: h(), wait: h() }
    }

    fn record(&mut self, age_us: u64, wait_us: Option<u64>) {
        if let Some(h) = &mut self.age {
            h.saturating_record(age_us.max(1));
        }
        if let (Some(h), Some(w)) = (&mut self.wait, wait_us) {
            h.saturating_record(w.max(1));
        }
    }

    /// Percentiles so far.
    pub fn summary(&self) -> LatencySummary {
        let mut s = LatencySummary::default();
        if let Some(h) = &self.age {
            s.count = h.len();
            s.p50_us = h.value_at_quantile(0.5);
            s.p99_us = h.value_at_quantile(0.99);
            s.p999_us = h.value_at_quantile(0.999);
            s.max_us = h.max();
        }
        if let Some(h) = &self.wait {
            s.wait_p50_us = h.value_at_quantile(0.5);
            s.wait_p99_us = h.value_at_quantile(0.99);
            s.wait_max_us = h.max();
        }
        s
    }
}

/// Safety state shared by every link kind. Fields are visible to the links so that their
/// `select!` loops can borrow the feed and the control channel at the same time.
pub struct Gate<F, C> {
    pub(crate) sup: Supervisor,
    pub(crate) feed: F,
    pub(crate) clock: C,
    pub(crate) deadman: Arc<dyn Deadman>,
    pub(crate) ctl: watch::Receiver<Control>,
    /// Newest sample (orientation removed when orientation is not sent).
    pub(crate) cur: Option<Sample>,
    /// When `cur` was published, if the feed knows.
    cur_published_ns: Option<u64>,
    pub(crate) feed_open: bool,
    send_orientation: bool,
    pub(crate) latency: Latency,
    /// When [`Gate::latency_summary_due`] last gave a summary (clock ns).
    summary_at_ns: u64,
}

/// How often the links copy their latency percentiles into their status (for `/status` and
/// the set-up page; reading percentiles costs a pass over the histogram).
pub const LATENCY_SUMMARY_PERIOD_NS: u64 = 500_000_000;

impl<F: PositionFeed, C: Clock> Gate<F, C> {
    /// A gate judging `feed`'s samples by `cfg`'s safety limits, timed by `clock`, with the
    /// `deadman` input and the operator's commands on `ctl`.
    pub fn new(
        cfg: &RobotConfig,
        feed: F,
        clock: C,
        deadman: Arc<dyn Deadman>,
        ctl: watch::Receiver<Control>,
    ) -> Self {
        Self {
            sup: Supervisor::new(cfg.safety.clone()),
            feed,
            clock,
            deadman,
            ctl,
            cur: None,
            cur_published_ns: None,
            feed_open: true,
            send_orientation: cfg.send_orientation,
            latency: Latency::new(),
            summary_at_ns: 0,
        }
    }

    /// Takes the newest sample from the feed.
    pub fn refresh(&mut self) {
        self.cur = if self.feed_open { self.feed.latest() } else { None };
        self.cur_published_ns = self.cur.and_then(|_| self.feed.published_ns());
        if !self.send_orientation {
            // Orientation that is never sent must not hold the robot either.
            if let Some(c) = &mut self.cur {
                c.orientation_wxyz = None;
            }
        }
    }

    /// Applies an operator command not seen yet (streaming links call this per packet); true
    /// when the link must stop.
    pub fn poll_control(&mut self) -> bool {
        match self.ctl.has_changed() {
            Ok(true) => self.apply_control(),
            Ok(false) => self.ctl.borrow().stop,
            // The handle is gone: nobody can enable or stop any more, so stop.
            Err(_) => true,
        }
    }

    /// Applies the newest operator command; true when the link must stop.
    pub fn apply_control(&mut self) -> bool {
        let c = *self.ctl.borrow_and_update();
        if c.stop {
            return true;
        }
        if c.enabled {
            self.sup.enable();
        } else {
            self.sup.disarm(HoldReason::Stop);
        }
        false
    }

    /// A new session with the controller, whose TCP is at `robot_pos_mm`: held until an enable
    /// given after this moment (an earlier enable never moves a fresh session).
    pub fn on_connect(&mut self, robot_pos_mm: [f64; 3]) {
        self.ctl.mark_unchanged();
        self.sup.on_connect(robot_pos_mm);
    }

    /// The clock the samples are stamped with.
    pub fn now_ns(&self) -> u64 {
        self.clock.now_ns()
    }

    /// Judges `sample` (normally [`Gate::cur`], possibly predicted ahead) now.
    pub fn verdict(&mut self, sample: Option<&Sample>) -> Verdict {
        match sample {
            Some(s) => self.sup.check(s, self.clock.now_ns(), self.deadman.pressed()),
            None if !self.sup.is_armed() => {
                Verdict::Hold(self.sup.latched().unwrap_or(HoldReason::NotEnabled))
            }
            None => Verdict::Hold(HoldReason::MarkerLost),
        }
    }

    /// A target captured at `capture_ts_ns` has just left irtrackd.
    pub fn record_sent(&mut self, capture_ts_ns: u64) {
        let now_ns = self.clock.now_ns();
        let age_ns = now_ns.saturating_sub(capture_ts_ns);
        // The publication time belongs to the newest sample; a predicted or older target
        // carries the same capture time when it came from it.
        let wait_ns = match (self.cur, self.cur_published_ns) {
            (Some(c), Some(p)) if c.capture_ts_ns == capture_ts_ns => Some(now_ns.saturating_sub(p)),
            _ => None,
        };
        self.latency.record(age_ns / 1000, wait_ns.map(|w| w / 1000));
    }

    /// The latency percentiles so far, at most every [`LATENCY_SUMMARY_PERIOD_NS`] (`None`
    /// in between): for the link's status.
    pub fn latency_summary_due(&mut self) -> Option<LatencySummary> {
        let now = self.clock.now_ns();
        if now.saturating_sub(self.summary_at_ns) < LATENCY_SUMMARY_PERIOD_NS {
            return None;
        }
        self.summary_at_ns = now;
        Some(self.latency.summary())
    }

    /// Logs the latency summary (read by `cargo xtask bench-links`).
    pub fn log_latency(&self, kind: &str) {
        let l = self.latency.summary();
        tracing::info!(
            "robot link latency kind={kind} n={} p50_us={} p99_us={} p999_us={} max_us={} wait_p50_us={} wait_p99_us={} wait_max_us={}",
            l.count,
            l.p50_us,
            l.p99_us,
            l.p999_us,
            l.max_us,
            l.wait_p50_us,
            l.wait_p99_us,
            l.wait_max_us
        );
    }
}
