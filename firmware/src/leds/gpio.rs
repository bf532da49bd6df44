//! Status LEDs on any Linux GPIO controller through the character device (`gpiocdev`).
//!
//! All four lines are requested once, as outputs, in one request; switching an LED is then a
//! single `GPIO_V2_LINE_SET_VALUES` ioctl, quick enough for the LED driver thread.

use std::path::{Path, PathBuf};

use gpiocdev::line::{Offset, Value, Values};
use gpiocdev::request::Request;
use serde::Deserialize;

use super::{Led, LedError, StatusLeds};

/// One LED line: by offset on the chip or by line name.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum LineRef {
    /// Line offset on the chip (a TOML integer).
    Offset(u32),
    /// Line name as the device tree gives it (a TOML string).
    Name(String),
}

/// `[leds.gpio]` section of the irtrackd config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GpioLedConfig {
    /// Chip path, device name or label, e.g. `/dev/gpiochip0`, `gpiochip0` or `9030000.pl061`.
    pub chip: String,
    /// Line of the run LED.
    pub run: LineRef,
    /// Line of the track LED.
    pub track: LineRef,
    /// Line of the robot LED.
    pub robot: LineRef,
    /// Line of the fault LED.
    pub fault: LineRef,
    /// LEDs wired to light when the line is low.
    #[serde(default)]
    pub active_low: bool,
    /// Consumer label shown by the kernel (`gpioinfo`, debugfs) for the requested lines.
    #[serde(default = "default_consumer")]
    pub consumer: String,
}

fn default_consumer() -> String {
    "irtrackd".to_owned()
}

/// Opens the chip, resolves the four lines and requests them as outputs, all LEDs off.
pub fn open(config: &GpioLedConfig) -> Result<Box<dyn StatusLeds>, LedError> {
    Ok(Box::new(GpioLeds::open(config)?))
}

/// The gpiocdev back end; also usable directly to read the line levels back.
pub struct GpioLeds {
    request: Request,
    chip_path: PathBuf,
    chip_label: String,
    /// Line offset per LED, in [`Led::ALL`] order.
    offsets: [Offset; 4],
}

fn gpio_err(what: impl Into<String>, reason: impl ToString) -> LedError {
    LedError::Gpio {
        what: what.into(),
        reason: reason.to_string(),
    }
}

fn led_index(led: Led) -> usize {
    match led {
        Led::Run => 0,
        Led::Track => 1,
        Led::Robot => 2,
        Led::Fault => 3,
    }
}

/// Finds the chip by path, by `/dev` name, or by label among all chips.
fn resolve_chip(spec: &str) -> Result<gpiocdev::Chip, LedError> {
    if spec.contains('/') {
        return gpiocdev::Chip::from_path(spec).map_err(|e| gpio_err(format!("chip {spec}"), e));
    }
    if let Ok(chip) = gpiocdev::Chip::from_name(spec) {
        return Ok(chip);
    }
    let paths = gpiocdev::chip::chips().map_err(|e| gpio_err(format!("chip {spec}"), e))?;
    let mut labels = Vec::new();
    for path in paths {
        let Ok(chip) = gpiocdev::Chip::from_path(&path) else {
            continue;
        };
        let Ok(info) = chip.info() else { continue };
        if info.label == spec {
            return Ok(chip);
        }
        labels.push(format!("{} ({})", info.name, info.label));
    }
    Err(gpio_err(
        format!("chip {spec}"),
        format!(
            "no chip with that path, name or label; present: [{}]",
            labels.join(", ")
        ),
    ))
}

fn resolve_line(chip: &gpiocdev::Chip, num_lines: u32, led: Led, line: &LineRef) -> Result<Offset, LedError> {
    let what = || format!("{led:?} LED line {line:?} on {}", chip.path().display());
    match line {
        LineRef::Offset(offset) if *offset < num_lines => Ok(*offset),
        LineRef::Offset(_) => Err(gpio_err(what(), format!("chip has only {num_lines} lines"))),
        LineRef::Name(name) => chip
            .find_line_info(name)
            .map(|info| info.offset)
            .ok_or_else(|| gpio_err(what(), "no line with that name")),
    }
}

impl GpioLeds {
    /// Finds the chip and requests the four lines as outputs, all LEDs off; the error names the
    /// chip or line that is missing.
    pub fn open(config: &GpioLedConfig) -> Result<Self, LedError> {
        let chip = resolve_chip(&config.chip)?;
        let info = chip
            .info()
            .map_err(|e| gpio_err(format!("chip info of {}", chip.path().display()), e))?;
        let mut offsets = [0; 4];
        let refs = [&config.run, &config.track, &config.robot, &config.fault];
        for (i, (led, line)) in Led::ALL.iter().zip(refs).enumerate() {
            offsets[i] = resolve_line(&chip, info.num_lines, *led, line)?;
            if offsets[..i].contains(&offsets[i]) {
                return Err(gpio_err(
                    format!("{led:?} LED line {line:?}"),
                    format!("offset {} is already used by another LED", offsets[i]),
                ));
            }
        }
        let mut builder = Request::builder();
        builder
            .on_chip(chip.path())
            .with_consumer(config.consumer.as_str())
            .with_lines(&offsets);
        if config.active_low {
            builder.as_active_low();
        }
        // Request as outputs with the LEDs off, so nothing flashes before the first state.
        let request = builder.as_output(Value::Inactive).request().map_err(|e| {
            gpio_err(
                format!("request lines {offsets:?} on {}", chip.path().display()),
                e,
            )
        })?;
        Ok(Self {
            request,
            chip_path: chip.path().to_path_buf(),
            chip_label: info.label,
            offsets,
        })
    }

    /// Line offset of an LED on the chip.
    pub fn offset(&self, led: Led) -> Offset {
        self.offsets[led_index(led)]
    }

    /// Device path of the chip in use.
    pub fn chip_path(&self) -> &Path {
        &self.chip_path
    }

    /// Reads the logical level of an LED line back from the kernel (GPIO_V2_LINE_GET_VALUES).
    pub fn read_back(&self, led: Led) -> Result<bool, LedError> {
        let offset = self.offset(led);
        let value = self
            .request
            .value(offset)
            .map_err(|e| gpio_err(format!("read {led:?} LED line {offset}"), e))?;
        Ok(value == Value::Active)
    }

    /// Sets all four LEDs in one ioctl, in [`Led::ALL`] order.
    pub fn set_all(&mut self, on: [bool; 4]) -> Result<(), LedError> {
        let mut values = Values::default();
        for (offset, on) in self.offsets.iter().zip(on) {
            values.set(*offset, Value::from(on));
        }
        self.request
            .set_values(&values)
            .map_err(|e| gpio_err("set LED lines", e))
    }
}

impl StatusLeds for GpioLeds {
    fn set(&mut self, led: Led, on: bool) -> Result<(), LedError> {
        let offset = self.offset(led);
        self.request
            .set_value(offset, Value::from(on))
            .map_err(|e| gpio_err(format!("set {led:?} LED line {offset}"), e))
    }

    fn describe(&self) -> String {
        format!(
            "gpiocdev {} ({}) lines run={} track={} robot={} fault={}",
            self.chip_path.display(),
            self.chip_label,
            self.offsets[0],
            self.offsets[1],
            self.offsets[2],
            self.offsets[3]
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Deserialize)]
    struct Wrap {
        gpio: GpioLedConfig,
    }

    #[test]
    fn config_accepts_offsets_and_names() {
        let cfg: Wrap = toml::from_str(
            "[gpio]\nchip = \"9030000.pl061\"\nrun = 0\ntrack = \"LED_TRACK\"\nrobot = 2\nfault = 3\n",
        )
        .unwrap();
        assert_eq!(cfg.gpio.run, LineRef::Offset(0));
        assert_eq!(cfg.gpio.track, LineRef::Name("LED_TRACK".into()));
        assert!(!cfg.gpio.active_low);
        assert_eq!(cfg.gpio.consumer, "irtrackd");
    }

    #[test]
    fn config_rejects_unknown_keys() {
        let err = toml::from_str::<Wrap>(
            "[gpio]\nchip = \"gpiochip0\"\nrun = 0\ntrack = 1\nrobot = 2\nfault = 3\nblink = true\n",
        )
        .err()
        .unwrap();
        assert!(err.to_string().contains("blink"), "{err}");
    }

    #[test]
    fn missing_chip_is_a_clear_error() {
        let cfg = GpioLedConfig {
            chip: "/nonexistent/gpiochip9".into(),
            run: LineRef::Offset(0),
            track: LineRef::Offset(1),
            robot: LineRef::Offset(2),
            fault: LineRef::Offset(3),
            active_low: false,
            consumer: default_consumer(),
        };
        let err = open(&cfg).err().unwrap().to_string();
        assert!(err.contains("/nonexistent/gpiochip9"), "{err}");
    }

    #[test]
    fn unknown_chip_label_is_a_clear_error() {
        let cfg = GpioLedConfig {
            chip: "no-such-label".into(),
            run: LineRef::Offset(0),
            track: LineRef::Offset(1),
            robot: LineRef::Offset(2),
            fault: LineRef::Offset(3),
            active_low: false,
            consumer: default_consumer(),
        };
        let err = open(&cfg).err().unwrap().to_string();
        assert!(err.contains("no-such-label"), "{err}");
    }
}
