//! irtrackd: capture, processing loop, status LEDs, parameters and outputs.

pub mod clock;
pub mod config;
pub mod error;
pub mod leds;
pub mod metrics;
pub mod robot;
pub mod source;
pub mod status;
pub mod storage;

pub use error::{FirmwareError, Result};
