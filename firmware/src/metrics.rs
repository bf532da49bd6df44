//! Allocation-free, lock-free latency histograms shared between the processing loop (and the
//! robot link tasks: any number of writers) and the status endpoint (readers).
//!
//! Log-linear buckets over nanoseconds, in the manner of HdrHistogram: values below
//! 2 × [`SUB_BUCKETS`] ns have a bucket each; above, every power of two is split into
//! [`SUB_BUCKETS`] equal buckets. A bucket is then at most 1/32 of its lower bound wide, and a
//! percentile reported at its bucket's midpoint is within 1/64 (1.6 %) of the exact sample —
//! from 1 ns up to [`MAX_TRACKABLE_NS`] (137 s; larger values count in the last bucket, the
//! maximum is kept exactly). The `hdrhistogram` crate is not used here because its `record`
//! takes `&mut self` (a writer would need a lock) and may resize.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use serde::Serialize;

const R: Ordering = Ordering::Relaxed;

/// log2 of the buckets per power of two.
const SUB_BITS: u32 = 5;
/// Buckets per power of two (linear inside it).
pub const SUB_BUCKETS: usize = 1 << SUB_BITS;
/// Largest value with its own bucket: 2^37 - 1 ns (137 s).
pub const MAX_TRACKABLE_NS: u64 = (1 << 37) - 1;
/// Bucket count: index of `MAX_TRACKABLE_NS` + 1.
pub const BUCKETS: usize = bucket_of(MAX_TRACKABLE_NS) + 1;

/// Bucket index of a value (ns).
const fn bucket_of(value_ns: u64) -> usize {
    let v = if value_ns > MAX_TRACKABLE_NS {
        MAX_TRACKABLE_NS
    } else {
        value_ns
    };
    if v < (2 * SUB_BUCKETS) as u64 {
        return v as usize;
    }
    let msb = 63 - v.leading_zeros();
    let shift = msb - SUB_BITS;
    (shift as usize) * SUB_BUCKETS + (v >> shift) as usize
}

/// Smallest value (ns) of bucket `index` and the bucket's width (ns).
const fn bucket_bounds(index: usize) -> (u64, u64) {
    if index < 2 * SUB_BUCKETS {
        return (index as u64, 1);
    }
    let shift = (index / SUB_BUCKETS - 1) as u32;
    let sub = (index % SUB_BUCKETS + SUB_BUCKETS) as u64;
    (sub << shift, 1 << shift)
}

/// Log-linear latency histogram (see the module documentation). Record from any thread.
#[derive(Debug)]
pub struct LatencyHistogram {
    counts: [AtomicU64; BUCKETS],
    sum_ns: AtomicU64,
    min_ns: AtomicU64,
    max_ns: AtomicU64,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl LatencyHistogram {
    /// An empty histogram (usable in a `static`).
    pub const fn new() -> Self {
        Self {
            counts: [const { AtomicU64::new(0) }; BUCKETS],
            sum_ns: AtomicU64::new(0),
            min_ns: AtomicU64::new(u64::MAX),
            max_ns: AtomicU64::new(0),
        }
    }

    /// Records one sample in nanoseconds. Lock-free (four relaxed atomic updates) and
    /// allocation-free.
    pub fn record_ns(&self, value_ns: u64) {
        self.counts[bucket_of(value_ns)].fetch_add(1, R);
        self.sum_ns.fetch_add(value_ns, R);
        self.min_ns.fetch_min(value_ns, R);
        self.max_ns.fetch_max(value_ns, R);
    }

    /// Records one sample in microseconds.
    pub fn record_us(&self, value_us: u64) {
        self.record_ns(value_us.saturating_mul(1000));
    }

    /// Records a `Duration`, saturating at `u64::MAX` ns.
    pub fn record(&self, d: Duration) {
        self.record_ns(u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    }

    /// Copies the counters (allocates; reader side only). Counters are read one by one while
    /// writers may go on, so a snapshot may be a few samples behind in some buckets.
    pub fn snapshot(&self) -> HistogramSnapshot {
        HistogramSnapshot {
            counts: self.counts.iter().map(|c| c.load(R)).collect(),
            sum_ns: self.sum_ns.load(R),
            min_ns: self.min_ns.load(R),
            max_ns: self.max_ns.load(R),
        }
    }
}

/// A copy of a histogram's counters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HistogramSnapshot {
    /// Per-bucket counts (not cumulative), [`BUCKETS`] entries.
    pub counts: Vec<u64>,
    /// Sum of all samples, ns (for the mean).
    pub sum_ns: u64,
    /// `u64::MAX` while empty.
    pub min_ns: u64,
    /// Largest sample, ns; 0 while empty.
    pub max_ns: u64,
}

impl HistogramSnapshot {
    /// Number of samples.
    pub fn count(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// The `q`-quantile in ns (`0 < q <= 1`): the sample of rank ⌈q·n⌉, reported at the middle
    /// of its bucket and clamped to the observed minimum and maximum; within 1.6 % of the exact
    /// sample. `None` when empty.
    pub fn quantile_ns(&self, q: f64) -> Option<f64> {
        let total = self.count();
        if total == 0 {
            return None;
        }
        // Rank of the sample we want, 1-based; ceil keeps p100 == last sample.
        let rank = ((q.clamp(0.0, 1.0) * total as f64).ceil() as u64).clamp(1, total);
        let mut seen = 0u64;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                if i == BUCKETS - 1 {
                    return Some(self.max_ns as f64); // beyond the trackable range
                }
                let (low, width) = bucket_bounds(i);
                let mid = low as f64 + (width - 1) as f64 / 2.0;
                return Some(mid.clamp(self.min_ns as f64, self.max_ns as f64));
            }
        }
        Some(self.max_ns as f64)
    }

    /// [`Self::quantile_ns`] in µs.
    pub fn quantile_us(&self, q: f64) -> Option<f64> {
        self.quantile_ns(q).map(|ns| ns / 1e3)
    }

    /// Samples not larger than `limit_ns`, counted by bucket midpoints (for the Prometheus
    /// histogram's fixed `le` edges; exact to the bucket resolution).
    pub fn count_at_most_ns(&self, limit_ns: f64) -> u64 {
        self.counts
            .iter()
            .enumerate()
            .filter(|&(i, _)| {
                let (low, width) = bucket_bounds(i);
                low as f64 + (width - 1) as f64 / 2.0 <= limit_ns
            })
            .map(|(_, c)| *c)
            .sum()
    }

    /// Count, percentiles, minimum, maximum and mean in µs, rounded to 0.01 µs.
    pub fn summary(&self) -> LatencySummary {
        let count = self.count();
        // Two decimals of a µs (the resolution at 1 µs is 1/64 µs); every figure is rounded
        // alike, so p99 ≤ max holds in the report too.
        let round = |us: f64| (us * 100.0).round() / 100.0;
        let us = |q: f64| self.quantile_us(q).map(round);
        LatencySummary {
            count,
            p50_us: us(0.50),
            p90_us: us(0.90),
            p99_us: us(0.99),
            p999_us: us(0.999),
            min_us: (count > 0).then(|| round(self.min_ns as f64 / 1e3)),
            max_us: (count > 0).then(|| round(self.max_ns as f64 / 1e3)),
            mean_us: (count > 0).then(|| round(self.sum_ns as f64 / count as f64 / 1e3)),
        }
    }
}

/// Percentiles for the JSON status (µs, within 1.6 % of the exact samples).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LatencySummary {
    /// Number of samples.
    pub count: u64,
    /// Median, µs; `None` while empty (as every figure below).
    pub p50_us: Option<f64>,
    /// 90th percentile, µs.
    pub p90_us: Option<f64>,
    /// 99th percentile, µs.
    pub p99_us: Option<f64>,
    /// 99.9th percentile, µs.
    pub p999_us: Option<f64>,
    /// Smallest sample, µs.
    pub min_us: Option<f64>,
    /// Largest sample, µs.
    pub max_us: Option<f64>,
    /// Mean, µs.
    pub mean_us: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The exact q-quantile of sorted samples, with the histogram's rank definition.
    fn exact(sorted: &[u64], q: f64) -> u64 {
        let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
        sorted[rank - 1]
    }

    #[test]
    fn buckets_are_contiguous_and_narrow() {
        let mut expected_low = 0u64;
        for i in 0..BUCKETS {
            let (low, width) = bucket_bounds(i);
            assert_eq!(
                low,
                expected_low,
                "bucket {i} starts where {} ended",
                i.wrapping_sub(1)
            );
            assert_eq!(bucket_of(low), i);
            assert_eq!(bucket_of(low + width - 1), i);
            // Width relative to the bucket's smallest value: ≤ 1/32 above the exact range.
            assert!(low < 64 || width as f64 / low as f64 <= 1.0 / 32.0, "bucket {i}");
            expected_low = low + width;
        }
        assert_eq!(expected_low, MAX_TRACKABLE_NS + 1);
        assert_eq!(bucket_of(u64::MAX), BUCKETS - 1);
    }

    #[test]
    fn percentiles_of_random_samples_are_within_three_percent() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(30);
        let qs = [0.001, 0.01, 0.1, 0.25, 0.5, 0.75, 0.9, 0.99, 0.999, 1.0];
        let mut worst = 0.0f64;
        for trial in 0..12 {
            let n = rng.gen_range(1..20_000usize);
            // Log-uniform over 1 µs .. 1 s, or clustered like a real stage (a narrow body
            // with a far tail), to hit both dense and sparse bucket regions.
            let samples: Vec<u64> = (0..n)
                .map(|_| {
                    if trial % 2 == 0 {
                        let e = rng.gen_range(3.0f64..9.0);
                        10f64.powf(e) as u64
                    } else if rng.gen_bool(0.98) {
                        rng.gen_range(14_000..19_000u64)
                    } else {
                        rng.gen_range(1_000..1_000_000_000u64)
                    }
                })
                .collect();
            let h = LatencyHistogram::new();
            for &s in &samples {
                h.record_ns(s);
            }
            let mut sorted = samples.clone();
            sorted.sort_unstable();
            let snap = h.snapshot();
            assert_eq!(snap.count(), n as u64);
            for q in qs {
                let want = exact(&sorted, q) as f64;
                let got = snap.quantile_ns(q).unwrap();
                let err = (got - want).abs() / want;
                worst = worst.max(err);
                assert!(
                    err <= 0.03,
                    "trial {trial} n {n} q {q}: got {got} ns, exact {want} ns"
                );
                // The construction promises half a bucket: 1/64.
                assert!(err <= 1.0 / 64.0 + 1e-12, "trial {trial} q {q}: {err}");
            }
            assert_eq!(snap.max_ns, sorted[n - 1]);
            assert_eq!(snap.min_ns, sorted[0]);
            assert_eq!(snap.sum_ns, samples.iter().sum::<u64>());
        }
        assert!(worst > 0.0, "the test exercised no rounding at all");
    }

    #[test]
    fn old_bucket_edge_is_not_reported() {
        // The fixed buckets reported 1,500 µs for anything in 1,000..=1,500 µs.
        let h = LatencyHistogram::new();
        for v in [1_010u64, 1_020, 1_030, 1_040, 1_050] {
            h.record_us(v);
        }
        let p50 = h.snapshot().quantile_us(0.5).unwrap();
        assert!((p50 - 1_030.0).abs() <= 1_030.0 / 64.0, "{p50}");
    }

    #[test]
    fn concurrent_writers_lose_no_sample() {
        let h = std::sync::Arc::new(LatencyHistogram::new());
        let threads: Vec<_> = (0..4)
            .map(|t| {
                let h = h.clone();
                std::thread::spawn(move || {
                    for i in 0..10_000u64 {
                        h.record_ns(1_000 + i * 7 + t);
                    }
                })
            })
            .collect();
        for t in threads {
            t.join().unwrap();
        }
        let s = h.snapshot();
        assert_eq!(s.count(), 40_000);
        assert_eq!(s.min_ns, 1_000);
        assert_eq!(s.max_ns, 1_000 + 9_999 * 7 + 3);
    }

    #[test]
    fn empty_and_overflow() {
        let s = LatencyHistogram::new().snapshot();
        assert!(s.quantile_us(0.5).is_none());
        assert_eq!(s.summary().count, 0);
        assert!(s.summary().max_us.is_none());
        let h = LatencyHistogram::new();
        h.record_ns(10);
        h.record(Duration::from_secs(500)); // beyond the trackable range
        let s = h.snapshot();
        assert_eq!(s.counts[BUCKETS - 1], 1, "overflow bucket");
        assert_eq!(s.quantile_ns(1.0), Some(500e9), "the maximum is kept exactly");
        assert_eq!(s.quantile_ns(0.5), Some(10.0));
        assert_eq!(s.count_at_most_ns(1e3), 1);
    }

    #[test]
    fn summary_keeps_percentiles_below_the_maximum() {
        let h = LatencyHistogram::new();
        for v in [12_001u64, 12_345, 12_346] {
            h.record_ns(v);
        }
        let s = h.snapshot().summary();
        assert!(s.p99_us.unwrap() <= s.max_us.unwrap(), "{s:?}");
        assert!(s.p50_us.unwrap() >= s.min_us.unwrap(), "{s:?}");
    }
}

/// A scrape's robot link packet counters (EGM/RSI; the socket link reports zeros): answered,
/// and refused by reason (a `prometheus-client` collector, registered by
/// `SharedStatus::prometheus` when `[robot]` is configured).
#[derive(Debug)]
pub struct RobotLinkMetrics {
    answered: u64,
    sessions: u64,
    refused: [(&'static str, u64); 5],
}

impl From<&irtrack_robot::LinkStatus> for RobotLinkMetrics {
    fn from(st: &irtrack_robot::LinkStatus) -> Self {
        Self {
            answered: st.packets_answered,
            sessions: st.connects,
            refused: st.refused_by_reason(),
        }
    }
}

impl prometheus_client::collector::Collector for RobotLinkMetrics {
    fn encode(&self, mut enc: prometheus_client::encoding::DescriptorEncoder) -> Result<(), std::fmt::Error> {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::MetricType;
        use prometheus_client::metrics::counter::ConstCounter;
        for (name, help, v) in [
            (
                "irtrackd_robot_packets_answered",
                "robot controller packets answered",
                self.answered,
            ),
            (
                "irtrackd_robot_sessions",
                "robot link connections or streaming sessions started",
                self.sessions,
            ),
        ] {
            let m = enc.encode_descriptor(name, help, None, MetricType::Counter)?;
            ConstCounter::new(v).encode(m)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_robot_packets_refused",
            "robot controller packets refused and not answered, by reason",
            None,
            MetricType::Counter,
        )?;
        for (reason, v) in self.refused {
            ConstCounter::new(v).encode(m.encode_family(&[("reason", reason)])?)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod robot_link_tests {
    use crate::status::{SharedStatus, fault_texts};

    /// The link's refusal counters reach `/metrics` by reason, and a recent refusal is a fault
    /// in plain words (issue 41).
    #[test]
    fn robot_link_refusals_in_metrics_and_fault_texts() {
        let st = SharedStatus::new(2, "sim".into(), "none".into());
        assert!(!st.prometheus().contains("irtrackd_robot_packets_refused"));
        let link = irtrack_robot::LinkStatus {
            kind: irtrack_robot::LinkKind::Rsi,
            packets_answered: 250,
            refused_source: 7,
            refused_sequence: 1,
            refused_implausible: 2,
            bad_packets: 3,
            out_of_order: 4,
            last_refused: Some(irtrack_robot::RefusedPacket {
                reason: irtrack_robot::Refusal::Sequence,
                from: "10.0.0.9:6000".parse().unwrap(),
                words: "a packet from 10.0.0.9:6000: sequence number 100005 is 100000 ahead".into(),
                at: std::time::Instant::now(),
            }),
            ..Default::default()
        };
        let (_tx, rx) = tokio::sync::watch::channel(link);
        assert!(st.robot_link.set(rx).is_ok());
        let m = st.prometheus();
        for line in [
            "irtrackd_robot_packets_answered_total 250",
            "irtrackd_robot_packets_refused_total{reason=\"wrong_source\"} 7",
            "irtrackd_robot_packets_refused_total{reason=\"sequence_window\"} 1",
            "irtrackd_robot_packets_refused_total{reason=\"implausible_position\"} 2",
            "irtrackd_robot_packets_refused_total{reason=\"malformed\"} 3",
            "irtrackd_robot_packets_refused_total{reason=\"out_of_order\"} 4",
        ] {
            assert!(m.lines().any(|l| l == line), "{line:?} missing in:\n{m}");
        }
        let f = fault_texts(&st, None, None);
        let refused = f
            .iter()
            .find(|t| t.code == "robot_packets_refused")
            .expect("the refusal fault");
        assert!(
            refused.message.contains("10.0.0.9:6000") && refused.message.contains("7 from another address"),
            "{}",
            refused.message
        );
    }
}

#[cfg(test)]
mod timing_tests {
    use std::sync::atomic::Ordering::Relaxed;

    use irtrack_core::retime::TimeMode;

    use crate::status::{SharedStatus, TimingReport, fault_texts};

    /// Time-true tracking reaches `/status`, `/metrics` and the faults (issue 39): the mode,
    /// each camera's bridge and unbridged blobs, and a recent set beyond the bridge as a fault
    /// that names the spread and the limit; an old one is no fault any more.
    #[test]
    fn time_mode_bridges_and_skew_fault() {
        let st = SharedStatus::new(2, "sim".into(), "none".into());
        *st.timing.lock().unwrap() = Some(TimingReport::new(TimeMode::Accurate, 25.0));
        st.cameras[1].record_bridge(-2.5e6, 0);
        st.cameras[1].record_bridge(1.0e6, 3);
        let r = st.report();
        let t = r.processing.timing.as_ref().expect("timing on /status");
        assert_eq!((t.mode, t.max_bridge_ms), ("accurate", 25.0));
        let cam = &r.source.cameras[1];
        assert_eq!(cam.bridge_ms_last, Some(1.0));
        assert_eq!(cam.bridge_ms_max, Some(2.5));
        assert_eq!(cam.unbridged, 3);
        let m = st.prometheus();
        for line in [
            "irtrackd_camera_bridge_seconds{camera=\"1\"} 0.001",
            "irtrackd_camera_unbridged_blobs_total{camera=\"1\"} 3",
        ] {
            assert!(m.lines().any(|l| l == line), "{line:?} missing in:\n{m}");
        }
        assert!(
            !fault_texts(&st, None, None)
                .iter()
                .any(|f| f.code == "skewed_sets")
        );
        let now = crate::clock::monotonic_ns();
        st.skewed_sets.store(4, Relaxed);
        st.skewed_last_spread_ns.store(31_200_000, Relaxed);
        st.skewed_last_ns.store(now, Relaxed);
        let f = fault_texts(&st, None, None);
        let skew = f
            .iter()
            .find(|f| f.code == "skewed_sets")
            .expect("the skew fault");
        assert!(
            skew.message.contains("31.2 ms apart")
                && skew.message.contains("25.0 ms")
                && skew.message.contains("4 so far"),
            "{}",
            skew.message
        );
        st.skewed_last_ns.store(
            now.saturating_sub(crate::status::SKEW_FAULT_HOLD_NS + 1_000_000_000),
            Relaxed,
        );
        assert!(
            !fault_texts(&st, None, None)
                .iter()
                .any(|f| f.code == "skewed_sets")
        );
    }
}
