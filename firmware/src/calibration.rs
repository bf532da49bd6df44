//! The active parameter set's calibration record as `/status` and the set-up page show it:
//! method, when and by what it was calibrated, its age and quality, and a warning in plain
//! words when it is marked poor or older than `[params] calibration_max_age_days`
//! (docs/calibration.md, "Quality gates"; the record itself: docs/param-blob.md, version 3).

use irtrack_core::params::{CalibrationInfo, Verdict};
use serde::Serialize;

/// Default of `[params] calibration_max_age_days`: after this many days the page suggests
/// checking the calibration (cameras get knocked, mounts creep).
pub const DEFAULT_MAX_AGE_DAYS: f64 = 180.0;

/// One named figure of the record.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FigureReport {
    /// The figure's name; it carries the unit (e.g. `pivot_rms_mm`).
    pub name: String,
    /// Its value, in the unit the name gives.
    pub value: f64,
}

/// The calibration part of `/status` `params`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CalibrationStatus {
    /// `wand`, `checkerboard`, `wand+checkerboard`, `pivot`.
    pub method: String,
    /// When the calibration was computed, Unix seconds.
    pub calibrated_unix_s: u64,
    /// The tool that computed it, e.g. `host-tools 0.1.0`.
    pub tool_version: String,
    /// `good` or `poor`.
    pub verdict: &'static str,
    /// The tool's verdict in plain words (empty when good).
    pub summary: String,
    /// Reprojection RMS per camera (px), in camera order (empty if the method has none).
    pub rms_px: Vec<f64>,
    /// The record's other figures (length errors, coverage, ...).
    pub figures: Vec<FigureReport>,
    /// Days since `calibrated_unix_s` when the status was built (negative clock skew reads 0).
    pub age_days: f64,
    /// Age beyond which `warning` asks for a check (`[params] calibration_max_age_days`).
    pub max_age_days: f64,
    /// Why the operator should look at the calibration, if they should.
    pub warning: Option<String>,
}

impl CalibrationStatus {
    /// The status of `record` at `now_unix_s`, warning when poor or older than `max_age_days`.
    pub fn of(record: &CalibrationInfo, now_unix_s: u64, max_age_days: f64) -> CalibrationStatus {
        let age_days = now_unix_s.saturating_sub(record.calibrated_unix_s) as f64 / 86_400.0;
        let mut warnings = Vec::new();
        if record.verdict == Verdict::Poor {
            warnings.push(format!(
                "this calibration is marked POOR (written with --accept-poor): {}",
                if record.summary.is_empty() {
                    "see the calibration report"
                } else {
                    record.summary.as_str()
                }
            ));
        }
        if age_days > max_age_days {
            warnings.push(format!(
                "the calibration is {age_days:.0} days old (older than {max_age_days:.0} days): check it, e.g. \
                 with a verify path, and calibrate again if the cameras moved"
            ));
        }
        CalibrationStatus {
            method: record.method.clone(),
            calibrated_unix_s: record.calibrated_unix_s,
            tool_version: record.tool_version.clone(),
            verdict: record.verdict.as_str(),
            summary: record.summary.clone(),
            rms_px: record.rms_px.clone(),
            figures: record
                .figures
                .iter()
                .map(|f| FigureReport {
                    name: f.name.clone(),
                    value: f.value,
                })
                .collect(),
            age_days,
            max_age_days,
            warning: (!warnings.is_empty()).then(|| warnings.join("; ")),
        }
    }
}

/// Seconds since the Unix epoch (0 if the clock is before it).
pub fn now_unix_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use irtrack_core::params::Figure;

    fn record(verdict: Verdict) -> CalibrationInfo {
        CalibrationInfo {
            method: "wand".into(),
            calibrated_unix_s: 1_000_000,
            tool_version: "host-tools 0.1.0".into(),
            verdict,
            summary: if verdict == Verdict::Poor {
                "POOR wand calibration: cam1 reprojection RMS 3.71 px (limit ≤ 1 px)".into()
            } else {
                String::new()
            },
            rms_px: vec![0.02, 3.71],
            figures: vec![Figure {
                name: "frames_used".into(),
                value: 150.0,
            }],
        }
    }

    #[test]
    fn warns_when_poor_or_old() {
        let day = 86_400;
        let good = CalibrationStatus::of(&record(Verdict::Good), 1_000_000 + 10 * day, 180.0);
        assert_eq!((good.verdict, good.warning.as_deref()), ("good", None));
        assert!((good.age_days - 10.0).abs() < 1e-9);
        let old = CalibrationStatus::of(&record(Verdict::Good), 1_000_000 + 200 * day, 180.0);
        assert!(
            old.warning.as_deref().unwrap().contains("200 days old"),
            "{old:?}"
        );
        let poor = CalibrationStatus::of(&record(Verdict::Poor), 1_000_000, 180.0);
        let w = poor.warning.unwrap();
        assert!(w.contains("POOR") && w.contains("cam1 reprojection RMS"), "{w}");
        // A clock behind the calibration reads as age 0, not as a huge age.
        assert_eq!(
            CalibrationStatus::of(&record(Verdict::Good), 5, 180.0).age_days,
            0.0
        );
    }
}
