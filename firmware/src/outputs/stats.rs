//! Counters of the standard outputs, read by tests, `/status` (`outputs`) and `/metrics`
//! (`irtrackd_output_*{output="natnet"|"mcap"|"ros2"}`). A leaf module: the status service
//! reads it without importing the outputs themselves.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use crate::metrics::LatencyHistogram;

const R: Ordering = Ordering::Relaxed;

/// Counters of one output.
#[derive(Debug, Default)]
pub struct OutputStats {
    /// The output is configured on (set when it is bound).
    pub enabled: AtomicBool,
    /// Datagrams (or messages, or records written) handed on.
    pub frames_sent: AtomicU64,
    /// Sends that failed or would have blocked; the packet was dropped, not queued.
    pub send_drops: AtomicU64,
    /// Records the loop published that this output never saw (the slot was overwritten first).
    pub slot_skips: AtomicU64,
    /// Clients currently served (NatNet unicast clients, matched DDS subscriptions).
    pub clients: AtomicU64,
    /// Clients refused by the client limit.
    pub refused: AtomicU64,
    /// Requests received from clients (NatNet commands).
    pub requests: AtomicU64,
    /// Malformed or unknown requests.
    pub bad_requests: AtomicU64,
    /// Clients refused by the per-address client limit (NatNet `max_clients_per_address`).
    pub refused_per_address: AtomicU64,
    /// Replies larger than their request, and client slots, not given to an address outside
    /// NatNet's `client_networks` (it has not shown it receives what is sent to it).
    pub withheld: AtomicU64,
    /// Replies not sent because of a reply rate limit.
    pub rate_limited: AtomicU64,
    /// Capture (mid-exposure stamp) → handed to the kernel / DDS stack / writer queue, per
    /// record (lock-free, no allocation).
    pub latency: LatencyHistogram,
    /// Writes that failed (MCAP: a write that stopped a file, or a new file that could not be
    /// started).
    pub write_errors: AtomicU64,
    /// Files started (MCAP recordings).
    pub files: AtomicU64,
    /// The file being written (MCAP); `None` while none is.
    pub file: Mutex<Option<String>>,
    /// What is wrong with this output now, in plain words; `None`: nothing.
    pub fault: Mutex<Option<String>>,
}

impl OutputStats {
    /// Records one record's capture → sent latency.
    pub fn record_latency(&self, capture_ts_ns: u64) {
        let now = crate::clock::monotonic_ns();
        self.latency.record_ns(now.saturating_sub(capture_ts_ns));
    }

    /// The `/status` view of this output.
    pub fn report_json(&self) -> serde_json::Value {
        serde_json::json!({
            "enabled": self.enabled.load(R),
            "sent": self.frames_sent.load(R),
            "dropped": self.send_drops.load(R),
            "skipped": self.slot_skips.load(R),
            "clients": self.clients.load(R),
            "refused": self.refused.load(R),
            "refused_per_address": self.refused_per_address.load(R),
            "withheld": self.withheld.load(R),
            "rate_limited": self.rate_limited.load(R),
            "requests": self.requests.load(R),
            "bad_requests": self.bad_requests.load(R),
            "capture_to_sent": self.latency.snapshot().summary(),
            "write_errors": self.write_errors.load(R),
            "files": self.files.load(R),
            "file": self.file_now(),
            "fault": self.fault_now(),
        })
    }

    /// The file being written, if any.
    pub fn file_now(&self) -> Option<String> {
        self.file.lock().ok().and_then(|g| g.clone())
    }

    /// The output's fault in plain words, if it has one.
    pub fn fault_now(&self) -> Option<String> {
        self.fault.lock().ok().and_then(|g| g.clone())
    }
}

/// Counters of every output.
#[derive(Debug, Clone, Default)]
pub struct OutputsStats {
    /// The NatNet output's counters.
    pub natnet: Arc<OutputStats>,
    /// `frames_sent`: records written; `send_drops`: records the full queue refused.
    pub mcap: Arc<OutputStats>,
    /// `frames_sent`: messages published; `send_drops`: publishes refused (send window full);
    /// `clients`: matched subscriptions.
    pub ros2: Arc<OutputStats>,
}

impl OutputsStats {
    /// (name, counters) of every output.
    pub fn each(&self) -> [(&'static str, &OutputStats); 3] {
        [
            ("natnet", &self.natnet),
            ("mcap", &self.mcap),
            ("ros2", &self.ros2),
        ]
    }

    /// The outputs' faults for `/status`'s `fault_texts`: (code, what is wrong and what to do).
    pub fn fault_texts(&self) -> Vec<(&'static str, String)> {
        self.each()
            .into_iter()
            .filter_map(|(name, s)| {
                let code = match name {
                    "mcap" => "recording_failed",
                    "natnet" => "natnet_failed",
                    _ => "ros2_failed",
                };
                s.fault_now().map(|text| (code, text))
            })
            .collect()
    }

    /// `/status`'s `outputs` object.
    pub fn report_json(&self) -> serde_json::Value {
        serde_json::Value::Object(
            self.each()
                .into_iter()
                .map(|(name, s)| (name.to_string(), s.report_json()))
                .collect(),
        )
    }

    /// The `/metrics` families of the enabled outputs, from a snapshot of the counters.
    pub fn metrics(&self) -> OutputsMetrics {
        OutputsMetrics {
            rows: self
                .each()
                .into_iter()
                .filter(|(_, s)| s.enabled.load(R))
                .map(|(name, s)| OutputRow {
                    name,
                    sent: s.frames_sent.load(R),
                    dropped: s.send_drops.load(R),
                    skipped: s.slot_skips.load(R),
                    clients: s.clients.load(R),
                    refused: s.refused.load(R),
                    refused_per_address: s.refused_per_address.load(R),
                    withheld: s.withheld.load(R),
                    rate_limited: s.rate_limited.load(R),
                    requests: s.requests.load(R),
                    bad_requests: s.bad_requests.load(R),
                    write_errors: s.write_errors.load(R),
                    fault: s.fault_now().is_some(),
                    p50_s: s.latency.snapshot().quantile_ns(0.5).map(|ns| ns / 1e9),
                    p99_s: s.latency.snapshot().quantile_ns(0.99).map(|ns| ns / 1e9),
                })
                .collect(),
        }
    }
}

#[derive(Debug)]
struct OutputRow {
    name: &'static str,
    sent: u64,
    dropped: u64,
    skipped: u64,
    clients: u64,
    refused: u64,
    refused_per_address: u64,
    withheld: u64,
    rate_limited: u64,
    requests: u64,
    bad_requests: u64,
    write_errors: u64,
    fault: bool,
    p50_s: Option<f64>,
    p99_s: Option<f64>,
}

/// A scrape's output counters (a `prometheus-client` collector).
#[derive(Debug)]
pub struct OutputsMetrics {
    rows: Vec<OutputRow>,
}

impl prometheus_client::collector::Collector for OutputsMetrics {
    fn encode(
        &self,
        mut enc: prometheus_client::encoding::DescriptorEncoder,
    ) -> std::result::Result<(), std::fmt::Error> {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::MetricType;
        use prometheus_client::metrics::counter::ConstCounter;
        use prometheus_client::metrics::gauge::ConstGauge;
        type Get = fn(&OutputRow) -> u64;
        // Counter names without `_total`: the encoder appends it.
        let counters: [(&str, &str, Get); 10] = [
            (
                "irtrackd_output_sent",
                "messages or datagrams sent per output",
                |r| r.sent,
            ),
            (
                "irtrackd_output_dropped",
                "sends dropped (not queued) per output",
                |r| r.dropped,
            ),
            (
                "irtrackd_output_skipped",
                "published records an output never saw (slot overwritten)",
                |r| r.skipped,
            ),
            (
                "irtrackd_output_refused",
                "clients refused by the client limit per output",
                |r| r.refused,
            ),
            (
                "irtrackd_output_refused_per_address",
                "clients refused by the per-address client limit per output",
                |r| r.refused_per_address,
            ),
            (
                "irtrackd_output_withheld",
                "replies larger than their request and client slots not given to an address outside client_networks",
                |r| r.withheld,
            ),
            (
                "irtrackd_output_rate_limited",
                "replies not sent because of a reply rate limit",
                |r| r.rate_limited,
            ),
            (
                "irtrackd_output_requests",
                "requests received per output (NatNet commands)",
                |r| r.requests,
            ),
            (
                "irtrackd_output_bad_requests",
                "malformed or unknown requests per output",
                |r| r.bad_requests,
            ),
            (
                "irtrackd_output_write_errors",
                "failed writes per output (MCAP: a full disk stopping a file)",
                |r| r.write_errors,
            ),
        ];
        for (name, help, get) in counters {
            let mut m = enc.encode_descriptor(name, help, None, MetricType::Counter)?;
            for r in &self.rows {
                ConstCounter::new(get(r)).encode(m.encode_family(&[("output", r.name)])?)?;
            }
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_output_clients",
            "clients served per output (NatNet unicast clients, matched DDS subscriptions)",
            None,
            MetricType::Gauge,
        )?;
        for r in &self.rows {
            ConstGauge::new(r.clients as i64).encode(m.encode_family(&[("output", r.name)])?)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_output_fault",
            "1 while an output has a fault (its text is in /status fault_texts)",
            None,
            MetricType::Gauge,
        )?;
        for r in &self.rows {
            ConstGauge::new(i64::from(r.fault)).encode(m.encode_family(&[("output", r.name)])?)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_output_latency_seconds",
            "capture to sent per output (quantile 0.5 and 0.99)",
            None,
            MetricType::Gauge,
        )?;
        for r in &self.rows {
            for (q, v) in [("0.5", r.p50_s), ("0.99", r.p99_s)] {
                if let Some(v) = v {
                    ConstGauge::new(v).encode(m.encode_family(&[("output", r.name), ("quantile", q)])?)?;
                }
            }
        }
        Ok(())
    }
}
