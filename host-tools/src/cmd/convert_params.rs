//! `host-tools convert-params IN OUT`: parameter blob ↔ OpenCV YAML. The output format follows
//! OUT's extension: `.yaml`/`.yml` is YAML, anything else a blob (signed with `--sign-key`).
//! `--placement` adds or replaces the cameras' placement on boards (docs/cluster.md), so a set
//! calibrated without one can be pushed to a cluster solver without recalibrating.
//! `--timing` sets a camera's timing (shutter, line time, exposure, offset; docs/timing.md) and
//! `--serial` the set's serial (docs/param-blob.md). A set that is changed (placement, timing)
//! gets the next serial (`RigParams::next_serial`: previous + 1, at least the current Unix
//! time) unless `--serial` gives one; a plain conversion keeps the set, serial included.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use irtrack_core::signing::KeyId;
use irtrack_core::timing::{CameraTiming, Shutter};

use crate::cmd::keygen::{load_params_file, read_secret_key};
use crate::opencv_yaml::{is_yaml_path, write_rig_yaml};

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Input: parameter blob or OpenCV YAML (detected from the content).
    pub input: PathBuf,
    /// Output: `.yaml`/`.yml` for OpenCV YAML, anything else for a parameter blob.
    pub output: PathBuf,
    /// Convert even if the parameters do not validate (never together with --sign-key).
    #[arg(long)]
    pub force: bool,
    /// Secret key file (from `host-tools keygen`): write a signed blob.
    #[arg(long, value_name = "FILE")]
    pub sign_key: Option<PathBuf>,
    /// Place the cameras on boards (adds or replaces the set's placement), camera 0 first:
    /// BOARD:INDEX,… with each board's `[cluster] board` name, e.g. b0:0,b0:1,b1:0,b1:1.
    /// Blob output only (OpenCV YAML carries no placement).
    #[arg(long, value_name = "BOARD:INDEX,…")]
    pub placement: Option<String>,
    /// Set a camera's timing (repeatable): CAMERA:SHUTTER[:KEY=VALUE]…, SHUTTER `global` or
    /// `rolling`, keys `line_time_us`, `exposure_us`, `offset_us` (unset keys are 0), e.g.
    /// `1:rolling:line_time_us=15.2:offset_us=-120`. Cameras not named keep their timing.
    #[arg(long, value_name = "CAM:SHUTTER[:KEY=VALUE]…")]
    pub timing: Vec<String>,
    /// The set's serial (the rollback counter irtrackd compares; docs/param-blob.md). Default:
    /// kept on a plain conversion, the next serial when the set is changed.
    #[arg(long, value_name = "N")]
    pub serial: Option<u64>,
}

/// Parses one `--timing` value for a rig of `n_cameras`: the camera and its timing.
pub fn parse_timing(spec: &str, n_cameras: usize) -> Result<(usize, CameraTiming)> {
    let mut parts = spec.split(':');
    let cam_text = parts.next().unwrap_or_default();
    let camera: usize = cam_text
        .trim()
        .parse()
        .with_context(|| format!("--timing {spec:?}: camera {cam_text:?} is not a number"))?;
    if camera >= n_cameras {
        bail!(
            "--timing {spec:?}: camera {camera} does not exist (the set has cameras 0..={})",
            n_cameras.saturating_sub(1)
        );
    }
    let shutter = match parts.next().map(str::trim) {
        Some("global") => Shutter::Global,
        Some("rolling") => Shutter::Rolling,
        other => bail!("--timing {spec:?}: shutter {other:?} must be `global` or `rolling`"),
    };
    let mut timing = CameraTiming {
        shutter,
        ..CameraTiming::default()
    };
    for kv in parts {
        let Some((key, value)) = kv.split_once('=') else {
            bail!("--timing {spec:?}: {kv:?} is not KEY=VALUE");
        };
        let us: f64 = value
            .trim()
            .parse()
            .with_context(|| format!("--timing {spec:?}: {key} = {value:?} is not a number"))?;
        // Within ±1 s: larger values are unit mistakes, and the conversions cannot overflow.
        if !us.is_finite() || us.abs() > 1.0e6 {
            bail!("--timing {spec:?}: {key} = {us} µs must be finite and within one second");
        }
        let ns = (us * 1000.0).round();
        match key.trim() {
            "line_time_us" | "exposure_us" if ns < 0.0 => {
                bail!("--timing {spec:?}: {key} = {us} µs must be ≥ 0")
            }
            "line_time_us" => timing.line_time_ns = ns as u32,
            "exposure_us" => timing.exposure_ns = ns as u32,
            "offset_us" => timing.offset_ns = ns as i64,
            other => bail!(
                "--timing {spec:?}: unknown key {other:?} (known: line_time_us, exposure_us, offset_us)"
            ),
        }
    }
    timing
        .validate()
        .map_err(|e| anyhow::anyhow!("--timing {spec:?}: {e} (values are in µs)"))?;
    Ok((camera, timing))
}

/// Now, Unix seconds (0 if the clock is before 1970).
pub fn now_unix_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// Gives a set that a tool has changed the next serial (`RigParams::next_serial`: its serial
/// + 1, at least the current Unix time), so irtrackd takes it as newer than the set it came
/// from (docs/param-blob.md, "Serial").
pub fn bump_serial(rig: &mut irtrack_core::params::RigParams) {
    rig.serial = irtrack_core::params::RigParams::next_serial(rig.serial, now_unix_s());
}

/// Writes `bytes` to `path` through a temporary file and a rename, so readers never see half.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp-write");
    std::fs::write(&tmp, bytes).with_context(|| format!("{}: cannot write", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("{}: cannot rename into place", path.display()))
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let loaded = load_params_file(&args.input)?;
    let mut rig = loaded.rig;
    if let Some(spec) = &args.placement {
        if is_yaml_path(&args.output) {
            bail!(
                "{}: OpenCV YAML carries no camera placement; write a parameter blob to place the cameras",
                args.output.display()
            );
        }
        let placement = crate::placement::parse_for(spec, rig.cameras.len())?;
        let was = crate::placement::describe(&rig.placement);
        crate::placement::apply(&mut rig, placement, "--placement")?;
        println!(
            "placement: {}{}",
            crate::placement::describe(&rig.placement),
            if was.is_empty() {
                String::new()
            } else {
                format!(" (was: {was})")
            }
        );
    }
    let changed = args.placement.is_some() || !args.timing.is_empty();
    if !args.timing.is_empty() {
        let n = rig.cameras.len();
        if rig.timing.len() != n {
            rig.timing = (0..n).map(|i| rig.camera_timing(i)).collect();
        }
        for spec in &args.timing {
            let (camera, timing) = parse_timing(spec, n)?;
            rig.timing[camera] = timing;
            println!(
                "timing: camera {camera}: {}",
                crate::cmd::show_params::timing_words(&rig, camera)
            );
        }
    }
    let before = rig.serial;
    if let Some(serial) = args.serial {
        rig.serial = serial;
    } else if changed {
        bump_serial(&mut rig);
    }
    if rig.serial != before {
        println!("serial: {} (was {before})", rig.serial);
    }
    if args.sign_key.is_some() && is_yaml_path(&args.output) {
        bail!(
            "{}: OpenCV YAML cannot carry a signature; sign a blob output instead",
            args.output.display()
        );
    }
    if let Err(e) = rig.validate() {
        if args.sign_key.is_some() {
            // A signature vouches for the parameters: never for ones known to be unusable.
            return Err(e).with_context(|| {
                format!(
                    "{}: refusing to sign parameters that are not usable",
                    args.input.display()
                )
            });
        }
        if args.force {
            eprintln!("convert-params: warning: {}: {e}", args.input.display());
        } else {
            return Err(e).with_context(|| {
                format!(
                    "{}: parameters are not usable (use --force to convert anyway)",
                    args.input.display()
                )
            });
        }
    }
    if let Some((id, _)) = &loaded.signed {
        // The output is re-encoded; only --sign-key produces a new signature.
        eprintln!(
            "convert-params: note: {} is signed by key {id}; the output carries {}",
            args.input.display(),
            if args.sign_key.is_some() {
                "the new signature"
            } else {
                "no signature"
            }
        );
    }
    if is_yaml_path(&args.output) {
        write_rig_yaml(&args.output, &rig)?;
        println!(
            "wrote {} (OpenCV YAML, rig {}, {} cameras)",
            args.output.display(),
            rig.rig_id,
            rig.cameras.len()
        );
    } else {
        let (blob, signature) = match &args.sign_key {
            Some(key_path) => {
                let key = read_secret_key(key_path)?;
                let id = KeyId::of(&key.verifying_key());
                (rig.to_signed_blob(&key)?, format!("signed by key {id}"))
            }
            None => (rig.to_blob()?, "unsigned".to_string()),
        };
        write_atomically(&args.output, &blob)?;
        println!(
            "wrote {} (parameter blob, {} bytes, rig {}, {signature})",
            args.output.display(),
            blob.len(),
            rig.rig_id
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timing_specs_parse_in_microseconds() {
        let (cam, t) = parse_timing("1:rolling:line_time_us=15.2:offset_us=-120", 2).unwrap();
        assert_eq!(cam, 1);
        assert_eq!(
            t,
            CameraTiming {
                shutter: Shutter::Rolling,
                line_time_ns: 15_200,
                exposure_ns: 0,
                offset_ns: -120_000,
            }
        );
        let (cam, t) = parse_timing("0:global:exposure_us=500:offset_us=2.5", 2).unwrap();
        assert_eq!((cam, t.exposure_ns, t.offset_ns), (0, 500_000, 2_500));
        assert_eq!(parse_timing("0:global", 2).unwrap().1, CameraTiming::default());
    }

    #[test]
    fn bad_timing_specs_name_the_problem() {
        for (spec, words) in [
            ("2:global", "camera 2 does not exist"),
            ("x:global", "is not a number"),
            ("0:fast", "must be `global` or `rolling`"),
            ("1:rolling", "line_time_ns > 0"),
            ("1:rolling:line_time_us", "is not KEY=VALUE"),
            ("1:rolling:line_us=3", "unknown key"),
            ("1:rolling:line_time_us=-3", "must be ≥ 0"),
            ("1:global:offset_us=5e9", "within one second"),
            ("1:rolling:line_time_us=15000000", "within one second"),
            ("1:rolling:line_time_us=15000", "10 ms"),
        ] {
            let e = format!("{:#}", parse_timing(spec, 2).unwrap_err());
            assert!(e.contains(words), "{spec}: {e}");
        }
    }
}
