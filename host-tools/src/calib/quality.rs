//! Quality gates of the calibration commands (`calibrate`, `wand-calibrate`, `pivot`): every
//! result is judged against stated limits (docs/calibration.md, "Quality gates"); a failed
//! limit stops the command with a plain-words verdict and the most likely cause, computed from
//! the data, unless `--accept-poor` asks for the files anyway, marked poor in the parameter
//! blob's calibration record (docs/param-blob.md, version 3).

use std::fmt::Write as _;

use anyhow::{Result, bail};
use irtrack_core::params::{CalibrationInfo, Figure, MAX_CALIBRATION_SUMMARY_LEN, Verdict};

/// One judged figure.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    /// What was measured, e.g. `cam1 reprojection RMS`.
    pub what: String,
    /// The measured value, in `unit`.
    pub value: f64,
    /// The limit it is judged against, in `unit`.
    pub limit: f64,
    /// Unit as printed after the numbers (`px`, `mm`, `%`, `°`, or empty).
    pub unit: &'static str,
    /// `true`: the value must not exceed the limit; `false`: it must reach it.
    pub at_most: bool,
}

impl Check {
    /// A figure that must stay at or below `limit`.
    pub fn at_most(what: impl Into<String>, value: f64, limit: f64, unit: &'static str) -> Check {
        Check {
            what: what.into(),
            value,
            limit,
            unit,
            at_most: true,
        }
    }

    /// A figure that must reach at least `limit`.
    pub fn at_least(what: impl Into<String>, value: f64, limit: f64, unit: &'static str) -> Check {
        Check {
            what: what.into(),
            value,
            limit,
            unit,
            at_most: false,
        }
    }

    /// Whether the figure is within its limit (a NaN figure never is).
    pub fn passed(&self) -> bool {
        if self.at_most {
            self.value <= self.limit
        } else {
            self.value >= self.limit
        }
    }

    /// `cam1 reprojection RMS 3.712 px (limit ≤ 1 px)`.
    pub fn line(&self) -> String {
        let unit = |v: f64| {
            if self.unit.is_empty() || self.unit == "°" {
                format!("{}{}", fmt_num(v), self.unit)
            } else {
                format!("{} {}", fmt_num(v), self.unit)
            }
        };
        format!(
            "{} {} (limit {} {})",
            self.what,
            unit(self.value),
            if self.at_most { "≤" } else { "≥" },
            unit(self.limit)
        )
    }
}

/// Numbers as people read them: 3 significant digits, integers as integers.
fn fmt_num(v: f64) -> String {
    if v.is_finite() && v == v.round() && v.abs() < 1e9 {
        format!("{v:.0}")
    } else if v.abs() >= 100.0 {
        format!("{v:.1}")
    } else if v.abs() >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

/// The judgement of one calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct Gate {
    /// `wand`, `checkerboard`, `wand+checkerboard`, `pivot`.
    pub method: String,
    /// Every limit judged, passed or not, in the order checked.
    pub checks: Vec<Check>,
    /// Likely causes of the failed limits, computed from the data, most likely first.
    pub causes: Vec<String>,
    /// Reprojection RMS per camera (px) for the record; empty if the method has none.
    pub rms_px: Vec<f64>,
    /// Figures for the record (names carry their unit).
    pub figures: Vec<Figure>,
}

impl Gate {
    /// An empty gate for `method` (see [`Gate::method`]); checks and figures are added after.
    pub fn new(method: &str) -> Gate {
        Gate {
            method: method.into(),
            checks: Vec::new(),
            causes: Vec::new(),
            rms_px: Vec::new(),
            figures: Vec::new(),
        }
    }

    /// Adds a figure to the record (non-finite values are left out: the record refuses them).
    pub fn figure(&mut self, name: &str, value: f64) {
        if value.is_finite() {
            self.figures.push(Figure {
                name: name.into(),
                value,
            });
        }
    }

    /// The checks whose limit was not met.
    pub fn failed(&self) -> Vec<&Check> {
        self.checks.iter().filter(|c| !c.passed()).collect()
    }

    /// `Good` when every check passed, else `Poor` (the record's verdict).
    pub fn verdict(&self) -> Verdict {
        if self.failed().is_empty() {
            Verdict::Good
        } else {
            Verdict::Poor
        }
    }

    /// The verdict in plain words: empty when good, else the failed limits and the likely
    /// causes.
    pub fn summary(&self) -> String {
        let failed = self.failed();
        if failed.is_empty() {
            return String::new();
        }
        let mut s = format!(
            "POOR {} calibration: {}",
            self.method,
            failed.iter().map(|c| c.line()).collect::<Vec<_>>().join("; ")
        );
        if self.causes.is_empty() {
            s.push_str(
                ". Likely cause: not determined from the data (see docs/calibration.md, \"Quality gates\")",
            );
        } else {
            let _ = write!(s, ". Likely cause: {}", self.causes.join(". Also: "));
        }
        s
    }

    /// The record that goes into the parameter blob.
    pub fn record(&self, calibrated_unix_s: u64) -> CalibrationInfo {
        let mut summary = self.summary();
        if summary.len() > MAX_CALIBRATION_SUMMARY_LEN {
            let mut cut = MAX_CALIBRATION_SUMMARY_LEN - 3;
            while !summary.is_char_boundary(cut) {
                cut -= 1;
            }
            summary.truncate(cut);
            summary.push_str("...");
        }
        CalibrationInfo {
            method: self.method.clone(),
            calibrated_unix_s,
            tool_version: tool_version(),
            verdict: self.verdict(),
            summary,
            rms_px: self
                .rms_px
                .iter()
                .map(|v| if v.is_finite() { *v } else { 0.0 })
                .collect(),
            figures: self.figures.clone(),
        }
    }

    /// Prints every check (stdout) as `quality: ok|FAIL <line>`.
    pub fn print(&self) {
        for c in &self.checks {
            println!(
                "quality: {} {}",
                if c.passed() { "ok  " } else { "FAIL" },
                c.line()
            );
        }
    }

    /// Stops the command (non-zero exit, nothing written) when a limit failed and poor results
    /// are not accepted; otherwise prints the verdict.
    pub fn enforce(&self, accept_poor: bool) -> Result<()> {
        self.print();
        if self.verdict() == Verdict::Good {
            println!("verdict: good (every limit of docs/calibration.md held)");
            return Ok(());
        }
        if accept_poor {
            eprintln!("warning: {}", self.summary());
            println!("verdict: POOR, written anyway (--accept-poor) and marked poor in the parameters");
            return Ok(());
        }
        bail!(
            "{}. Nothing was written; fix the cause and calibrate again, or add --accept-poor to write \
             the result marked as poor",
            self.summary()
        )
    }
}

/// `host-tools <version>`, the tool named in calibration records.
pub fn tool_version() -> String {
    format!("host-tools {}", env!("CARGO_PKG_VERSION"))
}

/// Seconds since the Unix epoch (0 if the clock is before it).
pub fn now_unix_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

/// Median of `v` (NaN when empty); sorts `v`.
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn verdict_summary_and_record() {
        let mut g = Gate::new("wand");
        g.checks
            .push(Check::at_most("cam0 reprojection RMS", 0.02, 1.0, "px"));
        g.checks.push(Check::at_least("frames used", 150.0, 60.0, ""));
        g.rms_px = vec![0.02, 0.03];
        g.figure("wand_length_rms_mm", 0.04);
        g.figure("nan", f64::NAN);
        assert_eq!(g.verdict(), Verdict::Good);
        assert_eq!(g.summary(), "");
        assert!(g.enforce(false).is_ok());
        let r = g.record(5);
        assert_eq!(
            (r.verdict, r.figures.len(), r.calibrated_unix_s),
            (Verdict::Good, 1, 5)
        );
        assert!(r.tool_version.starts_with("host-tools "));

        g.checks
            .push(Check::at_most("cam1 reprojection RMS", 3.712, 1.0, "px"));
        g.checks.push(Check::at_most("nan figure", f64::NAN, 1.0, "px"));
        g.causes.push("the wand's spacing".into());
        assert_eq!(g.verdict(), Verdict::Poor);
        let s = g.summary();
        assert!(
            s.starts_with("POOR wand calibration: cam1 reprojection RMS 3.71 px (limit ≤ 1 px)")
                && s.contains("Likely cause: the wand's spacing"),
            "{s}"
        );
        let e = g.enforce(false).unwrap_err().to_string();
        assert!(
            e.contains("--accept-poor") && e.contains("Nothing was written"),
            "{e}"
        );
        assert!(g.enforce(true).is_ok());
        g.causes = vec!["x".repeat(2000)];
        let r = g.record(5);
        assert_eq!(r.verdict, Verdict::Poor);
        assert!(r.summary.len() <= MAX_CALIBRATION_SUMMARY_LEN && r.summary.ends_with("..."));
    }
}
