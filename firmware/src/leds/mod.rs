//! Status LEDs: the hardware seam for indicator lights.
//!
//! The processing loop never touches GPIO: it publishes an [`indication::Indication`]; a small driver
//! thread turns it into blink patterns and calls a [`StatusLeds`] back end.

/// Physical indicator lights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Led {
    /// Heartbeat: service alive and the loop making progress.
    Run,
    /// Marker tracked in all cameras.
    Track,
    /// Robot connected (and streaming).
    Robot,
    /// Fault (no parameters, camera lost, deadline misses, ...).
    Fault,
}

impl Led {
    /// Every LED, in the order the driver updates them.
    pub const ALL: [Led; 4] = [Led::Run, Led::Track, Led::Robot, Led::Fault];
}

/// A back end that can switch LEDs. Implementations must be quick (no sleeping).
pub trait StatusLeds: Send {
    /// Switches `led` on or off.
    fn set(&mut self, led: Led, on: bool) -> Result<(), LedError>;
    /// The back end in a few words, for the log and `/status`.
    fn describe(&self) -> String;
}

/// No LEDs on the board (`[leds] kind = "none"`). The driver still runs on it, so `/status`
/// and the set-up page show what the LEDs would show (the indication) on boards without them.
pub struct NoLeds;

impl StatusLeds for NoLeds {
    fn set(&mut self, _led: Led, _on: bool) -> Result<(), LedError> {
        Ok(())
    }
    fn describe(&self) -> String {
        "none".to_string()
    }
}

/// Errors of the LED back ends.
#[derive(Debug, thiserror::Error)]
pub enum LedError {
    /// A GPIO line could not be opened or driven.
    #[error("GPIO {what}: {reason}")]
    Gpio {
        /// The chip, line or operation that failed.
        what: String,
        /// The system's reason.
        reason: String,
    },
}

pub mod driver;
pub mod gpio;
pub mod indication;
#[cfg(feature = "rpi")]
pub mod rppal;
pub mod sim;
