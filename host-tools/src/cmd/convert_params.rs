//! `host-tools convert-params IN OUT`: parameter blob ↔ OpenCV YAML. The output format follows
//! OUT's extension: `.yaml`/`.yml` is YAML, anything else a blob.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::opencv_yaml::{is_yaml_path, load_params_any, write_rig_yaml};

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Input: parameter blob or OpenCV YAML (detected from the content).
    pub input: PathBuf,
    /// Output: `.yaml`/`.yml` for OpenCV YAML, anything else for a parameter blob.
    pub output: PathBuf,
    /// Convert even if the parameters do not validate.
    #[arg(long)]
    pub force: bool,
}

/// Writes `bytes` to `path` through a temporary file and a rename, so readers never see half.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp-write");
    std::fs::write(&tmp, bytes).with_context(|| format!("{}: cannot write", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("{}: cannot rename into place", path.display()))
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let rig = load_params_any(&args.input)?;
    if let Err(e) = rig.validate() {
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
    if is_yaml_path(&args.output) {
        write_rig_yaml(&args.output, &rig)?;
        println!(
            "wrote {} (OpenCV YAML, rig {}, {} cameras)",
            args.output.display(),
            rig.rig_id,
            rig.cameras.len()
        );
    } else {
        let blob = rig.to_blob()?;
        write_atomically(&args.output, &blob)?;
        println!(
            "wrote {} (parameter blob, {} bytes, rig {})",
            args.output.display(),
            blob.len(),
            rig.rig_id
        );
    }
    Ok(())
}
