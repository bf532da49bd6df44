//! Deadman (enabling) input: motion is allowed only while it is pressed.
//!
//! Back ends: a GPIO input line (gpiocdev), a flag set by software (e.g. a button on the hand-held
//! unit relayed over the network, or tests), and an explicit "none" for bench setups without a
//! robot that can hurt anyone — it must be chosen in the config, never a default.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use gpiocdev::line::{Offset, Value};
use gpiocdev::request::Request;
use serde::Deserialize;

use crate::RobotError;

/// `[robot.deadman]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum DeadmanConfig {
    /// A GPIO input line; `active_low` for a switch that pulls the line to ground when pressed.
    Gpio {
        /// Chip path (`/dev/gpiochip0`) or name (`gpiochip0`).
        chip: String,
        /// Line offset on that chip.
        line: Offset,
        /// Pressed reads as low (a switch to ground).
        #[serde(default)]
        active_low: bool,
    },
    /// A software flag (hand-held unit, operator console); starts released.
    Flag,
    /// No deadman: always pressed. Only for simulation and bench tests.
    None,
}

/// Reads the deadman state; must be quick and non-blocking (called on every sample).
pub trait Deadman: Send + Sync {
    /// True while motion is allowed.
    fn pressed(&self) -> bool;
}

/// Software deadman flag.
#[derive(Debug, Clone, Default)]
pub struct FlagDeadman(Arc<AtomicBool>);

impl FlagDeadman {
    /// A released flag.
    pub fn new() -> Self {
        Self::default()
    }
    /// Presses or releases it.
    pub fn set(&self, pressed: bool) {
        self.0.store(pressed, Ordering::SeqCst);
    }
}

impl Deadman for FlagDeadman {
    fn pressed(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

/// Always pressed (`kind = "none"`).
#[derive(Debug, Clone, Copy, Default)]
pub struct NoDeadman;

impl Deadman for NoDeadman {
    fn pressed(&self) -> bool {
        true
    }
}

/// GPIO input line through the character device.
pub struct GpioDeadman {
    request: Request,
    offset: Offset,
}

impl GpioDeadman {
    /// Requests the line as an input.
    pub fn open(chip: &str, line: Offset, active_low: bool) -> Result<Self, RobotError> {
        let path = if chip.contains('/') {
            PathBuf::from(chip)
        } else {
            PathBuf::from("/dev").join(chip)
        };
        let mut b = Request::builder();
        b.on_chip(&path)
            .with_consumer("irtrackd-deadman")
            .with_line(line)
            .as_input();
        if active_low {
            b.as_active_low();
        }
        let request = b.request().map_err(|e| RobotError::Deadman {
            what: format!("{} line {line}", path.display()),
            reason: e.to_string(),
        })?;
        Ok(Self {
            request,
            offset: line,
        })
    }
}

impl Deadman for GpioDeadman {
    fn pressed(&self) -> bool {
        // A read error counts as released: fail safe.
        matches!(self.request.value(self.offset), Ok(Value::Active))
    }
}

impl DeadmanConfig {
    /// Opens the configured input. `flag` is the software flag to use for `kind = "flag"`.
    pub fn open(&self, flag: &FlagDeadman) -> Result<Arc<dyn Deadman>, RobotError> {
        Ok(match self {
            DeadmanConfig::Gpio {
                chip,
                line,
                active_low,
            } => Arc::new(GpioDeadman::open(chip, *line, *active_low)?),
            DeadmanConfig::Flag => Arc::new(flag.clone()),
            DeadmanConfig::None => {
                tracing::warn!("robot deadman input disabled by config (kind = \"none\"): bench use only");
                Arc::new(NoDeadman)
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flag_starts_released_and_follows_set() {
        let f = FlagDeadman::new();
        let d = DeadmanConfig::Flag.open(&f).unwrap();
        assert!(!d.pressed());
        f.set(true);
        assert!(d.pressed());
        f.set(false);
        assert!(!d.pressed());
    }

    #[test]
    fn missing_gpio_chip_is_a_clear_error() {
        let cfg = DeadmanConfig::Gpio {
            chip: "/dev/gpiochip-does-not-exist".into(),
            line: 3,
            active_low: false,
        };
        let e = cfg.open(&FlagDeadman::new()).err().unwrap().to_string();
        assert!(
            e.contains("gpiochip-does-not-exist") && e.contains("line 3"),
            "{e}"
        );
    }
}
