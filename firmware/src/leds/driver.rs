//! The LED driver thread: derives the indication from the shared status and blinks the LEDs.
//! It only reads atomics written by the processing loop, so the loop never waits for GPIO.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::indication::{Indication, led_levels};
use super::{Led, StatusLeds};
use crate::error::{FirmwareError, Result};
use crate::status::SharedStatus;

/// Driver tick; every pattern edge is a multiple of it.
pub const TICK: Duration = Duration::from_millis(25);
/// The loop counts as stalled when it made no progress for this long.
pub const STALL_AFTER: Duration = Duration::from_secs(1);
/// Deadline-miss fault: more than this fraction of sets missed within one window.
pub const DEADLINE_FAULT_FRACTION: f64 = 0.05;
/// Window over which deadline misses are counted for the fault.
pub const DEADLINE_WINDOW: Duration = Duration::from_secs(2);

/// Derives liveness and the deadline fault from counter deltas.
#[derive(Debug)]
pub struct HealthMonitor {
    last_iterations: u64,
    last_progress: Instant,
    window_start: Instant,
    window_sets: u64,
    window_misses: u64,
}

impl HealthMonitor {
    /// A monitor whose first window starts at `now` from the counters' current values.
    pub fn new(status: &SharedStatus, now: Instant) -> Self {
        Self {
            last_iterations: status.loop_iterations.load(Ordering::Relaxed),
            last_progress: now,
            window_start: now,
            window_sets: status.sets_processed.load(Ordering::Relaxed),
            window_misses: status.deadline_misses.load(Ordering::Relaxed),
        }
    }

    /// Updates `alive` and `deadline_fault` in `status` and returns the current indication.
    pub fn update(&mut self, status: &SharedStatus, now: Instant) -> Indication {
        let it = status.loop_iterations.load(Ordering::Relaxed);
        if it != self.last_iterations {
            self.last_iterations = it;
            self.last_progress = now;
        }
        let alive = now.duration_since(self.last_progress) < STALL_AFTER && it > 0;
        status.alive.store(alive, Ordering::Relaxed);
        if now.duration_since(self.window_start) >= DEADLINE_WINDOW {
            let sets = status.sets_processed.load(Ordering::Relaxed);
            let misses = status.deadline_misses.load(Ordering::Relaxed);
            let (ds, dm) = (sets - self.window_sets, misses - self.window_misses);
            let fault = dm >= 2 && dm as f64 > DEADLINE_FAULT_FRACTION * ds.max(1) as f64;
            status.deadline_fault.store(fault, Ordering::Relaxed);
            (self.window_start, self.window_sets, self.window_misses) = (now, sets, misses);
        }
        Indication {
            alive,
            track: status.track(),
            robot: status.robot(),
            fault: status.top_fault(),
        }
    }
}

/// Running LED driver; stops and switches all LEDs off when dropped or stopped.
pub struct LedDriver {
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
}

impl LedDriver {
    /// Starts the driver thread for `leds`, showing what `status` says.
    pub fn start(mut leds: Box<dyn StatusLeds>, status: Arc<SharedStatus>) -> Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = stop.clone();
        let handle = std::thread::Builder::new()
            .name("irtrackd-leds".into())
            .spawn(move || run(leds.as_mut(), &status, &stop2))
            .map_err(|e| FirmwareError::Thread {
                what: "LED driver",
                reason: e.to_string(),
            })?;
        Ok(Self {
            stop,
            handle: Some(handle),
        })
    }

    /// Stops the thread and waits for it; the LEDs are switched off.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

impl Drop for LedDriver {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn run(leds: &mut dyn StatusLeds, status: &SharedStatus, stop: &AtomicBool) {
    let start = Instant::now();
    let mut monitor = HealthMonitor::new(status, start);
    let mut current: Option<[bool; 4]> = None;
    let mut last_ind: Option<Indication> = None;
    let mut error_logged = false;
    let mut next = start;
    while !stop.load(Ordering::Relaxed) {
        let now = Instant::now();
        let ind = monitor.update(status, now);
        if last_ind != Some(ind) {
            tracing::info!(
                alive = ind.alive,
                track = ?ind.track,
                robot = ?ind.robot,
                fault = ?ind.fault,
                "LED indication changed"
            );
            last_ind = Some(ind);
        }
        let t_ms = u64::try_from(now.duration_since(start).as_millis()).unwrap_or(u64::MAX);
        let levels = led_levels(&ind, t_ms);
        for (i, led) in Led::ALL.into_iter().enumerate() {
            if current.is_none_or(|c| c[i] != levels[i])
                && let Err(e) = leds.set(led, levels[i])
                // A broken LED line must not spam the journal 40 times per second.
                && !error_logged
            {
                tracing::warn!(error = %e, "LED back end failed; continuing without it");
                error_logged = true;
            }
        }
        current = Some(levels);
        status.set_led_output(ind, levels);
        next += TICK;
        let now = Instant::now();
        if next > now {
            std::thread::sleep(next - now);
        } else {
            next = now;
        }
    }
    for led in Led::ALL {
        let _ = leds.set(led, false);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::leds::indication::{Fault, TrackIndication};

    fn step(status: &SharedStatus, sets: u64, misses: u64) {
        status.loop_iterations.fetch_add(sets, Ordering::Relaxed);
        status.sets_processed.fetch_add(sets, Ordering::Relaxed);
        status.deadline_misses.fetch_add(misses, Ordering::Relaxed);
    }

    #[test]
    fn health_monitor_derives_liveness_and_faults() {
        let status = SharedStatus::new(2, "test".into(), "none".into());
        let t0 = Instant::now();
        let mut m = HealthMonitor::new(&status, t0);
        // Nothing processed yet: not alive, no params.
        let ind = m.update(&status, t0);
        assert!(!ind.alive);
        assert_eq!(ind.fault, Some(Fault::NoParams));

        status.params_loaded.store(true, Ordering::Relaxed);
        status.set_track(TrackIndication::All);
        step(&status, 100, 1);
        let ind = m.update(&status, t0 + Duration::from_millis(100));
        assert!(ind.alive);
        assert_eq!((ind.fault, ind.track), (None, TrackIndication::All));

        // 1 % misses over a window: no fault; 20 % in the next window: deadline fault.
        step(&status, 100, 0);
        assert_eq!(m.update(&status, t0 + DEADLINE_WINDOW).fault, None);
        step(&status, 100, 20);
        let t = t0 + 2 * DEADLINE_WINDOW;
        assert_eq!(m.update(&status, t).fault, Some(Fault::DeadlineMisses));
        // A clean window clears it.
        step(&status, 100, 0);
        assert_eq!(m.update(&status, t + DEADLINE_WINDOW).fault, None);

        // Camera lost outranks everything; a stalled loop is not alive.
        status.camera_lost.store(true, Ordering::Relaxed);
        let ind = m.update(
            &status,
            t + DEADLINE_WINDOW + STALL_AFTER + Duration::from_millis(1),
        );
        assert_eq!(ind.fault, Some(Fault::CameraLost));
        assert!(!ind.alive);
        assert_eq!(status.active_faults(), vec![Fault::CameraLost]);
    }
}
