//! Reading an MCAP recording back with an independent reader: PyPI's `mcap` and
//! `mcap-ros2-support` in a separate Python process (`testkit/py/check_mcap.py`), for every
//! test of irtrack's MCAP writer (irtrackd's `[outputs.mcap]`, `host-tools record --mcap`).

use std::path::{Path, PathBuf};
use std::process::Command;

/// The reader script: decodes every message with its ROS 2 schema and prints JSON with
/// `profile`, `monotonic`, `counts` and `schemas` per topic, and the decoded `positions`,
/// `poses`, `tf` and `status` messages.
pub const CHECK_MCAP_PY: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/py/check_mcap.py");

/// Why a recording did not read back.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum McapCheckError {
    /// python3 could not be started.
    #[error("starting python3 {script}: {source}")]
    Spawn {
        /// The script.
        script: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The reader failed (a message that does not decode, a truncated file, missing modules).
    #[error(
        "check_mcap.py on {file} failed (are PyPI's mcap and mcap-ros2-support installed? cargo xtask setup): {stderr}"
    )]
    Reader {
        /// The recording.
        file: PathBuf,
        /// The reader's error output.
        stderr: String,
    },
    /// The reader's output is not the JSON it prints.
    #[error("check_mcap.py output is not JSON: {reason}")]
    Output {
        /// Parser message.
        reason: String,
    },
    /// A property every irtrack recording has does not hold.
    #[error("{file}: {what}")]
    Property {
        /// The recording.
        file: PathBuf,
        /// Which property, e.g. `log times not monotonic`.
        what: String,
    },
}

/// Reads `file` with the Python reader and returns its JSON, after checking what every
/// recording must satisfy: profile `ros2` and log times monotonic in file order.
pub fn read_mcap_with_python(file: &Path) -> Result<serde_json::Value, McapCheckError> {
    let out = Command::new("python3")
        .arg(CHECK_MCAP_PY)
        .arg(file)
        .output()
        .map_err(|source| McapCheckError::Spawn {
            script: PathBuf::from(CHECK_MCAP_PY),
            source,
        })?;
    if !out.status.success() {
        return Err(McapCheckError::Reader {
            file: file.to_path_buf(),
            stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        });
    }
    let got: serde_json::Value = serde_json::from_slice(&out.stdout).map_err(|e| McapCheckError::Output {
        reason: e.to_string(),
    })?;
    let property = |what: &str| McapCheckError::Property {
        file: file.to_path_buf(),
        what: what.to_string(),
    };
    if got["profile"] != "ros2" {
        return Err(property(&format!("profile {} is not ros2", got["profile"])));
    }
    if got["monotonic"] != true {
        return Err(property("log times not monotonic in file order"));
    }
    Ok(got)
}
