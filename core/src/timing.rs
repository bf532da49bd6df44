//! When a camera's pixels were exposed (docs/timing.md).
//!
//! A frame's timestamp is one instant per frame, taken by the driver (often at the start or end
//! of readout, on the board's clock). What the tracker needs is the instant each *blob* was
//! exposed: the middle of the exposure of the rows it covers. For a global shutter that is the
//! timestamp plus a per-camera offset; for a rolling shutter row `r` is exposed `r × line time`
//! after row 0. [`CameraTiming`] holds the per-camera constants; [`CameraTiming::blob_instant_ns`]
//! turns a frame timestamp and a blob's row into its exposure instant.

use serde::{Deserialize, Serialize};

/// How a sensor exposes its rows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Shutter {
    /// Every row is exposed over the same interval (global shutter).
    #[default]
    Global,
    /// Row `r` is exposed `r × line_time_ns` after row 0 (rolling shutter).
    Rolling,
}

impl Shutter {
    /// The name used in configs, `/status` and reports.
    pub fn as_str(self) -> &'static str {
        match self {
            Shutter::Global => "global",
            Shutter::Rolling => "rolling",
        }
    }
}

/// A camera's timing constants (per camera, in the config and the parameter set).
///
/// Defaults: global shutter, no offset, i.e. the frame timestamp *is* the exposure instant —
/// what every set made before timing existed assumed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraTiming {
    /// Global or rolling shutter.
    pub shutter: Shutter,
    /// Rolling shutter: time from the start of one row's exposure to the next row's (ns).
    /// Ignored for a global shutter.
    pub line_time_ns: u32,
    /// Exposure (integration) time (ns); informative (motion blur, the simulator). The instant
    /// used is the middle of the exposure, which `offset_ns` already includes.
    pub exposure_ns: u32,
    /// Middle of row 0's exposure minus the frame timestamp (ns, signed): the camera's known
    /// (calibrated or measured) time offset against its own timestamps.
    pub offset_ns: i64,
}

impl CameraTiming {
    /// A global-shutter camera whose timestamps are its exposure instants.
    pub const SYNCHRONOUS: CameraTiming = CameraTiming {
        shutter: Shutter::Global,
        line_time_ns: 0,
        exposure_ns: 0,
        offset_ns: 0,
    };

    /// Time (ns) from row 0's exposure instant to that of (sub-pixel) row `row_px`: 0 for a
    /// global shutter.
    pub fn row_delay_ns(&self, row_px: f64) -> f64 {
        match self.shutter {
            Shutter::Global => 0.0,
            Shutter::Rolling => row_px.max(0.0) * f64::from(self.line_time_ns),
        }
    }

    /// Exposure instant (ns, on the timestamp's clock) of a blob centred on row `row_px` of a
    /// frame stamped `frame_ts_ns`. `f64` keeps sub-nanosecond row delays; it represents every
    /// whole nanosecond up to 2^53 ns (104 days of monotonic clock).
    pub fn blob_instant_ns(&self, frame_ts_ns: u64, row_px: f64) -> f64 {
        frame_ts_ns as f64 + self.offset_ns as f64 + self.row_delay_ns(row_px)
    }

    /// Checks that the constants describe a real sensor: a rolling shutter needs a line time,
    /// and no value may exceed a second (a unit mistake: µs typed as ns or the other way).
    pub fn validate(&self) -> Result<(), &'static str> {
        const SECOND_NS: i64 = 1_000_000_000;
        if self.shutter == Shutter::Rolling && self.line_time_ns == 0 {
            return Err("a rolling shutter needs line_time_ns > 0");
        }
        if i64::from(self.line_time_ns) > SECOND_NS / 100 {
            return Err("line_time_ns above 10 ms (a row takes µs: check the unit)");
        }
        if i64::from(self.exposure_ns) > SECOND_NS || self.offset_ns.abs() > SECOND_NS {
            return Err("exposure_ns or offset_ns beyond one second (check the unit)");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn global_shutter_ignores_the_row() {
        let t = CameraTiming {
            offset_ns: -1500,
            line_time_ns: 15_000,
            ..CameraTiming::SYNCHRONOUS
        };
        assert_eq!(t.blob_instant_ns(1_000_000, 0.0), 998_500.0);
        assert_eq!(t.blob_instant_ns(1_000_000, 479.0), 998_500.0);
    }

    #[test]
    fn rolling_shutter_delays_each_row() {
        let t = CameraTiming {
            shutter: Shutter::Rolling,
            line_time_ns: 15_000,
            exposure_ns: 1_000_000,
            offset_ns: 500_000,
        };
        // Row 240.5 of a VGA frame: 3.6075 ms after row 0.
        assert_eq!(
            t.blob_instant_ns(10_000_000, 240.5),
            10_000_000.0 + 500_000.0 + 3_607_500.0
        );
        assert!(t.validate().is_ok());
    }

    #[test]
    fn validation_names_unit_mistakes() {
        let no_line = CameraTiming {
            shutter: Shutter::Rolling,
            ..CameraTiming::SYNCHRONOUS
        };
        assert!(no_line.validate().unwrap_err().contains("line_time_ns"));
        let huge = CameraTiming {
            offset_ns: 2_000_000_000,
            ..CameraTiming::SYNCHRONOUS
        };
        assert!(huge.validate().unwrap_err().contains("unit"));
        assert!(CameraTiming::default().validate().is_ok());
    }
}
