//! Status LEDs on Raspberry Pi boards through `rppal` (feature `rpi`).
//!
//! rppal drives the BCM GPIO registers through `/dev/gpiomem`, which works on Pi kernels where
//! the character device is not wanted. Built in CI for x86-64 and aarch64, but it cannot be run
//! here: it needs a Raspberry Pi SoC (rppal identifies the board from the device tree).

use rppal::gpio::{Gpio, OutputPin};
use serde::Deserialize;

use super::{Led, LedError, StatusLeds};

/// `[leds.rppal]` section of the irtrackd config: BCM pin numbers.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RppalLedConfig {
    /// BCM number of the run LED's pin.
    pub run_bcm: u8,
    /// BCM number of the track LED's pin.
    pub track_bcm: u8,
    /// BCM number of the robot LED's pin.
    pub robot_bcm: u8,
    /// BCM number of the fault LED's pin.
    pub fault_bcm: u8,
    /// LEDs wired to light when the pin is low.
    #[serde(default)]
    pub active_low: bool,
}

/// The four status LEDs on Raspberry Pi pins (rppal).
pub struct RppalLeds {
    /// One pin per LED, in [`Led::ALL`] order.
    pins: [OutputPin; 4],
    active_low: bool,
}

fn rppal_err(what: String, err: rppal::gpio::Error) -> LedError {
    LedError::Gpio {
        what,
        reason: err.to_string(),
    }
}

/// Claims the four BCM pins as outputs with all LEDs off.
pub fn open(config: &RppalLedConfig) -> Result<Box<dyn StatusLeds>, LedError> {
    let gpio = Gpio::new().map_err(|e| rppal_err("open Raspberry Pi GPIO".to_owned(), e))?;
    let numbers = [
        config.run_bcm,
        config.track_bcm,
        config.robot_bcm,
        config.fault_bcm,
    ];
    for (i, n) in numbers.iter().enumerate() {
        if numbers[..i].contains(n) {
            return Err(LedError::Gpio {
                what: format!("{:?} LED BCM pin {n}", Led::ALL[i]),
                reason: "pin is already used by another LED".to_owned(),
            });
        }
    }
    let claim = |led: Led, bcm: u8| -> Result<OutputPin, LedError> {
        let pin = gpio
            .get(bcm)
            .map_err(|e| rppal_err(format!("{led:?} LED BCM pin {bcm}"), e))?;
        // Off means high for active-low wiring.
        let mut out = if config.active_low {
            pin.into_output_high()
        } else {
            pin.into_output_low()
        };
        // Keep the LED off after the service exits instead of restoring the previous mode.
        out.set_reset_on_drop(false);
        Ok(out)
    };
    let pins = [
        claim(Led::Run, numbers[0])?,
        claim(Led::Track, numbers[1])?,
        claim(Led::Robot, numbers[2])?,
        claim(Led::Fault, numbers[3])?,
    ];
    Ok(Box::new(RppalLeds {
        pins,
        active_low: config.active_low,
    }))
}

impl StatusLeds for RppalLeds {
    fn set(&mut self, led: Led, on: bool) -> Result<(), LedError> {
        let index = match led {
            Led::Run => 0,
            Led::Track => 1,
            Led::Robot => 2,
            Led::Fault => 3,
        };
        let pin = &mut self.pins[index];
        if on != self.active_low {
            pin.set_high();
        } else {
            pin.set_low();
        }
        Ok(())
    }

    fn describe(&self) -> String {
        let pins: Vec<String> = self.pins.iter().map(|p| p.pin().to_string()).collect();
        format!("rppal BCM pins run/track/robot/fault = {}", pins.join("/"))
    }
}
