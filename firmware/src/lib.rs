//! irtrackd: capture, processing loop, status LEDs, parameters and outputs.

pub mod leds;
pub mod robot;
pub mod source;
