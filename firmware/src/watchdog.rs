//! systemd integration: READY/STOPPING notifications and watchdog pings that are sent only
//! while the processing loop makes progress (so a hung loop gets the service restarted).

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use sd_notify::NotifyState;

use crate::status::SharedStatus;

/// Tells systemd the service is ready (listeners bound). No-op outside systemd.
pub fn notify_ready(status_line: &str) {
    if let Err(e) = sd_notify::notify(false, &[NotifyState::Ready, NotifyState::Status(status_line)]) {
        tracing::debug!(error = %e, "sd_notify READY failed");
    }
}

/// Tells systemd the service is shutting down, so a slow stop is not taken for a hang. No-op
/// outside systemd.
pub fn notify_stopping() {
    let _ = sd_notify::notify(false, &[NotifyState::Stopping]);
}

/// Whether the loop progressed since `last` (updated). A source that ended on purpose
/// (replay finished) counts as healthy: the service still answers status requests.
pub fn loop_progressed(status: &SharedStatus, last: &mut u64) -> bool {
    let now = status.loop_iterations.load(Ordering::Relaxed);
    let progressed = now != *last || status.source_ended.load(Ordering::Relaxed);
    *last = now;
    progressed
}

/// Spawns the watchdog task when systemd asked for one (WatchdogSec=); pings at half the
/// interval, only after progress.
pub fn spawn(status: Arc<SharedStatus>) -> Option<tokio::task::JoinHandle<()>> {
    let mut usec = 0u64;
    if !sd_notify::watchdog_enabled(false, &mut usec) || usec == 0 {
        return None;
    }
    let period = Duration::from_micros(usec / 2);
    tracing::info!(period_ms = period.as_millis() as u64, "systemd watchdog enabled");
    Some(tokio::spawn(async move {
        let mut last = 0u64;
        let mut warned = false;
        let mut tick = tokio::time::interval(period);
        loop {
            tick.tick().await;
            if loop_progressed(&status, &mut last) {
                let _ = sd_notify::notify(false, &[NotifyState::Watchdog]);
                warned = false;
            } else if !warned {
                tracing::error!("processing loop made no progress; withholding watchdog ping");
                warned = true;
            }
        }
    }))
}
