//! `host-tools convert-params IN OUT`: parameter blob ↔ OpenCV YAML. The output format follows
//! OUT's extension: `.yaml`/`.yml` is YAML, anything else a blob (signed with `--sign-key`).
//! `--placement` adds or replaces the cameras' placement on boards (docs/cluster.md), so a set
//! calibrated without one can be pushed to a cluster solver without recalibrating.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use irtrack_core::signing::KeyId;

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
