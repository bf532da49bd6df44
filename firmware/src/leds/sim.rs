//! Simulated LEDs: log every change and keep a record for tests and the status page.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use super::{Led, LedError, StatusLeds};

/// One recorded LED change.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LedChange {
    /// Which LED changed.
    pub led: Led,
    /// Its new state (`true`: lit).
    pub on: bool,
    /// Seconds since the back end was created.
    pub at_s: f64,
}

/// Shared, growing record of LED changes (bounded: the oldest half is discarded when full so a
/// long-running PC instance does not grow without limit).
#[derive(Debug, Clone, Default)]
pub struct LedRecord(Arc<Mutex<Vec<LedChange>>>);

const RECORD_LIMIT: usize = 100_000;

impl LedRecord {
    /// A copy of the changes recorded so far, oldest first.
    pub fn changes(&self) -> Vec<LedChange> {
        self.0.lock().map(|g| g.clone()).unwrap_or_default()
    }

    fn push(&self, c: LedChange) {
        if let Ok(mut g) = self.0.lock() {
            if g.len() >= RECORD_LIMIT {
                g.drain(..RECORD_LIMIT / 2);
            }
            g.push(c);
        }
    }
}

/// LED back end without hardware.
#[derive(Debug)]
pub struct SimLeds {
    state: [bool; 4],
    record: LedRecord,
    started: Instant,
}

impl SimLeds {
    /// Simulated LEDs, all off, and the record they write their changes to.
    pub fn new() -> (Self, LedRecord) {
        let record = LedRecord::default();
        (
            Self {
                state: [false; 4],
                record: record.clone(),
                started: Instant::now(),
            },
            record,
        )
    }
}

impl StatusLeds for SimLeds {
    fn set(&mut self, led: Led, on: bool) -> Result<(), LedError> {
        let i = super::indication::led_index(led);
        if self.state[i] != on {
            self.state[i] = on;
            // Blinks are frequent: trace level; indication changes are logged by the driver.
            tracing::trace!(?led, on, "sim LED");
            self.record.push(LedChange {
                led,
                on,
                at_s: self.started.elapsed().as_secs_f64(),
            });
        }
        Ok(())
    }

    fn describe(&self) -> String {
        "simulated LEDs (logged)".to_string()
    }
}
