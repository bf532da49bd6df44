//! What phases report to the CI runner (`ci.rs`): test counts and a phase's outcome, plus the
//! reader of cargo's `test result:` lines. Phases depend on this module, never on `ci.rs`, so
//! the runner and its phases do not import each other.

/// Test counts from cargo's `test result:` lines (or from a phase module).
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Counts {
    pub passed: u64,
    pub failed: u64,
    pub ignored: u64,
}

impl Counts {
    pub fn add(&mut self, other: Counts) {
        self.passed += other.passed;
        self.failed += other.failed;
        self.ignored += other.ignored;
    }
}

/// What a phase reports.
#[derive(Debug, Default)]
pub struct Outcome {
    /// Tests run by the phase, if it runs tests.
    pub counts: Option<Counts>,
    /// Why the phase failed.
    pub failure: Option<String>,
    /// Why the phase did not run (not a failure).
    pub skipped: Option<String>,
}

impl Outcome {
    pub fn passed() -> Self {
        Self::default()
    }

    pub fn failed(msg: impl Into<String>) -> Self {
        Self {
            failure: Some(msg.into()),
            ..Self::default()
        }
    }

    pub fn skipped(msg: impl Into<String>) -> Self {
        Self {
            skipped: Some(msg.into()),
            ..Self::default()
        }
    }

    /// An error becomes a failure with its message chain.
    pub fn from_result(r: anyhow::Result<Outcome>) -> Self {
        r.unwrap_or_else(|e| Outcome::failed(format!("{e:#}")))
    }

    /// A phase module's `ci_phase` result: Ok(counts) passed, Err failed.
    pub fn from_counts(r: anyhow::Result<Counts>) -> Self {
        match r {
            Ok(c) => Outcome {
                counts: Some(c),
                ..Outcome::default()
            },
            Err(e) => Outcome::failed(format!("{e:#}")),
        }
    }
}

/// Sums `test result: ok. 12 passed; 0 failed; 1 ignored; ...` lines; also returns how many
/// such lines (test binaries and doctest runs) there were.
pub fn parse_test_results(stdout: &str) -> (Counts, usize) {
    let mut total = Counts::default();
    let mut n = 0;
    for line in stdout.lines() {
        let Some(rest) = line.trim().strip_prefix("test result: ") else {
            continue;
        };
        let mut c = Counts::default();
        let mut seen = false;
        for part in rest.split(';') {
            let mut words = part.split_whitespace().rev();
            let (Some(key), Some(num)) = (words.next(), words.next()) else {
                continue;
            };
            let Ok(num) = num.parse::<u64>() else { continue };
            match key {
                "passed" => (c.passed, seen) = (num, true),
                "failed" => c.failed = num,
                "ignored" => c.ignored = num,
                _ => {}
            }
        }
        if seen {
            total.add(c);
            n += 1;
        }
    }
    (total, n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_cargo_test_result_lines() {
        let out = "\
running 3 tests
test a ... ok
test result: ok. 3 passed; 0 failed; 1 ignored; 0 measured; 0 filtered out; finished in 0.01s

test result: FAILED. 5 passed; 2 failed; 0 ignored; 0 measured; 0 filtered out; finished in 1.20s
   Doc-tests irtrack_core
test result: ok. 0 passed; 0 failed; 0 ignored; 0 measured; 0 filtered out; finished in 0.00s
test something_named_test result: is not a summary
";
        let (c, n) = parse_test_results(out);
        assert_eq!(n, 3);
        assert_eq!(
            c,
            Counts {
                passed: 8,
                failed: 2,
                ignored: 1
            }
        );
    }

    #[test]
    fn no_result_lines_means_no_binaries() {
        let (c, n) = parse_test_results("error[E0425]: cannot find value `x`\n");
        assert_eq!((c, n), (Counts::default(), 0));
    }
}
