//! gpiocdev status LEDs (owned by the hardware/image work; config seam defined here first).

use serde::Deserialize;

/// One LED line: by offset on the chip or by line name.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum LineRef {
    Offset(u32),
    Name(String),
}

/// `[leds.gpio]` section of the irtrackd config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GpioLedConfig {
    /// Chip path or name, e.g. `/dev/gpiochip0` or `gpiochip0`.
    pub chip: String,
    pub run: LineRef,
    pub track: LineRef,
    pub robot: LineRef,
    pub fault: LineRef,
}
