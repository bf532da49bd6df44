//! Allocation-free latency histograms shared between the processing loop (single writer)
//! and the status endpoint (readers).

use std::sync::atomic::{AtomicU64, Ordering};

use serde::Serialize;

/// Upper bucket bounds in microseconds. Fixed so that recording never allocates and the
/// Prometheus export has stable `le` labels; the last bucket (`+Inf`) is implicit.
pub const LATENCY_BUCKETS_US: [u64; 20] = [
    25, 50, 100, 200, 300, 500, 750, 1_000, 1_500, 2_000, 3_000, 5_000, 7_500, 10_000, 15_000, 20_000,
    33_000, 50_000, 100_000, 250_000,
];

const BUCKETS: usize = LATENCY_BUCKETS_US.len() + 1;

/// Fixed-bucket latency histogram. Written by one thread, read by any.
#[derive(Debug)]
pub struct LatencyHistogram {
    counts: [AtomicU64; BUCKETS],
    sum_us: AtomicU64,
    max_us: AtomicU64,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl LatencyHistogram {
    pub const fn new() -> Self {
        Self {
            counts: [const { AtomicU64::new(0) }; BUCKETS],
            sum_us: AtomicU64::new(0),
            max_us: AtomicU64::new(0),
        }
    }

    /// Records one sample. Lock-free and allocation-free.
    pub fn record_us(&self, value_us: u64) {
        let bucket = LATENCY_BUCKETS_US
            .iter()
            .position(|&b| value_us <= b)
            .unwrap_or(BUCKETS - 1);
        self.counts[bucket].fetch_add(1, Ordering::Relaxed);
        self.sum_us.fetch_add(value_us, Ordering::Relaxed);
        self.max_us.fetch_max(value_us, Ordering::Relaxed);
    }

    /// Records a `std::time::Duration`, saturating at `u64::MAX` µs.
    pub fn record(&self, d: std::time::Duration) {
        self.record_us(u64::try_from(d.as_micros()).unwrap_or(u64::MAX));
    }

    pub fn snapshot(&self) -> HistogramSnapshot {
        let mut counts = [0u64; BUCKETS];
        for (c, a) in counts.iter_mut().zip(&self.counts) {
            *c = a.load(Ordering::Relaxed);
        }
        HistogramSnapshot {
            counts,
            sum_us: self.sum_us.load(Ordering::Relaxed),
            max_us: self.max_us.load(Ordering::Relaxed),
        }
    }
}

/// A copy of a histogram's counters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HistogramSnapshot {
    /// Per-bucket counts (not cumulative); the last entry is the overflow bucket.
    pub counts: [u64; BUCKETS],
    pub sum_us: u64,
    pub max_us: u64,
}

impl HistogramSnapshot {
    pub fn count(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// Upper bound (µs) of the bucket holding the `q`-quantile (`0 < q <= 1`); the overflow
    /// bucket reports the observed maximum. `None` when empty.
    pub fn quantile_us(&self, q: f64) -> Option<u64> {
        let total = self.count();
        if total == 0 {
            return None;
        }
        // Rank of the sample we want, 1-based; ceil keeps p100 == last sample.
        let rank = ((q.clamp(0.0, 1.0) * total as f64).ceil() as u64).max(1);
        let mut seen = 0u64;
        for (i, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return Some(
                    LATENCY_BUCKETS_US
                        .get(i)
                        .map_or(self.max_us, |&b| b.min(self.max_us)),
                );
            }
        }
        Some(self.max_us)
    }

    pub fn summary(&self) -> LatencySummary {
        let count = self.count();
        LatencySummary {
            count,
            p50_us: self.quantile_us(0.50),
            p90_us: self.quantile_us(0.90),
            p99_us: self.quantile_us(0.99),
            max_us: (count > 0).then_some(self.max_us),
            mean_us: (count > 0).then(|| self.sum_us as f64 / count as f64),
        }
    }
}

/// Percentiles for the JSON status (bucket upper bounds, µs).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LatencySummary {
    pub count: u64,
    pub p50_us: Option<u64>,
    pub p90_us: Option<u64>,
    pub p99_us: Option<u64>,
    pub max_us: Option<u64>,
    pub mean_us: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_follow_bucket_bounds() {
        let h = LatencyHistogram::new();
        for _ in 0..90 {
            h.record_us(80); // bucket <=100
        }
        for _ in 0..10 {
            h.record_us(4_000); // bucket <=5000
        }
        let s = h.snapshot();
        assert_eq!(s.count(), 100);
        assert_eq!(s.quantile_us(0.5), Some(100));
        assert_eq!(s.quantile_us(0.9), Some(100));
        assert_eq!(s.quantile_us(0.91), Some(4_000)); // capped at the observed max
        assert_eq!(s.max_us, 4_000);
    }

    #[test]
    fn overflow_bucket_reports_max() {
        let h = LatencyHistogram::new();
        h.record_us(10);
        h.record_us(1_000_000);
        let s = h.snapshot();
        assert_eq!(s.quantile_us(1.0), Some(1_000_000));
        assert_eq!(s.counts[0], 1);
        assert_eq!(s.counts[LATENCY_BUCKETS_US.len()], 1, "overflow bucket");
        assert!(LatencyHistogram::new().snapshot().quantile_us(0.5).is_none());
    }
}
