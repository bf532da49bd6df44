//! `host-tools keygen --out NAME`: create an Ed25519 key pair for signing parameter blobs
//! (NAME.key secret, mode 0600; NAME.pub public, for irtrackd's `trusted_keys`). Also the key
//! and signed-file reading shared by `push-params`, `convert-params` and `show-params`.

use std::ffi::OsString;
use std::io::Write;
use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use irtrack_core::params::{BlobHeader, RigParams, looks_like_blob};
use irtrack_core::signing::{self, KeyId, SigningKey, VerifyingKey};
use rand::rngs::OsRng;

use crate::opencv_yaml::load_params_any;

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Path prefix of the key pair: writes NAME.key (secret) and NAME.pub (public).
    #[arg(long, value_name = "NAME")]
    pub out: PathBuf,
    /// Replace existing key files (the old secret key is lost).
    #[arg(long)]
    pub force: bool,
}

fn with_suffix(prefix: &Path, suffix: &str) -> PathBuf {
    let mut s: OsString = prefix.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

/// The secret and public key paths for `--out NAME`.
pub fn key_paths(prefix: &Path) -> (PathBuf, PathBuf) {
    (with_suffix(prefix, ".key"), with_suffix(prefix, ".pub"))
}

/// Writes `text` to `path` through a new temporary file created with `mode` and a rename, so
/// the secret is never readable by others, not even for a moment.
fn write_file_mode(path: &Path, text: &str, mode: u32) -> Result<()> {
    let tmp = with_suffix(path, ".tmp-keygen");
    let _ = std::fs::remove_file(&tmp);
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(mode)
        .open(&tmp)
        .with_context(|| format!("{}: cannot create", tmp.display()))?;
    // The umask may have removed bits; it cannot have added any, but set exactly.
    f.set_permissions(std::fs::Permissions::from_mode(mode))?;
    f.write_all(text.as_bytes())
        .and_then(|()| f.sync_all())
        .with_context(|| format!("{}: cannot write", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("{}: cannot rename into place", path.display()))
}

/// Reads a secret key file. Warns on stderr when group or others may read it.
pub fn read_secret_key(path: &Path) -> Result<SigningKey> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read secret key", path.display()))?;
    if let Ok(meta) = std::fs::metadata(path)
        && meta.permissions().mode() & 0o077 != 0
    {
        eprintln!(
            "warning: {}: secret key is accessible by other users (mode {:o}); chmod 600 it",
            path.display(),
            meta.permissions().mode() & 0o777
        );
    }
    signing::parse_secret_key_file(&text).with_context(|| format!("{}", path.display()))
}

/// Reads a public key file.
pub fn read_public_key(path: &Path) -> Result<VerifyingKey> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read public key", path.display()))?;
    signing::parse_public_key_file(&text).with_context(|| format!("{}", path.display()))
}

/// A parameter file as loaded by the tools.
#[derive(Debug, Clone)]
pub struct LoadedParams {
    /// The rig parameters the file holds.
    pub rig: RigParams,
    /// For a signed blob file: its key id and exact bytes (the signature is NOT verified).
    pub signed: Option<(KeyId, Vec<u8>)>,
}

/// Loads a parameter blob (signed or not) or an OpenCV YAML file. Signatures are reported,
/// not verified: that is the device's job (or `show-params --trusted-key`).
pub fn load_params_file(path: &Path) -> Result<LoadedParams> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    if looks_like_blob(&bytes) && BlobHeader::parse_allow_signed(&bytes).is_ok_and(|h| h.is_signed()) {
        let (rig, key_id) = signing::decode_without_verifying(&bytes)
            .with_context(|| format!("{}: bad signed parameter blob", path.display()))?;
        return Ok(LoadedParams {
            rig,
            signed: key_id.map(|id| (id, bytes)),
        });
    }
    Ok(LoadedParams {
        rig: load_params_any(path)?,
        signed: None,
    })
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let (secret_path, public_path) = key_paths(&args.out);
    if !args.force {
        for p in [&secret_path, &public_path] {
            if p.exists() {
                bail!(
                    "{}: already exists; refusing to overwrite a key (use --force to replace it)",
                    p.display()
                );
            }
        }
    }
    if let Some(dir) = secret_path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create directory", dir.display()))?;
    }
    let key = SigningKey::generate(&mut OsRng);
    let public = key.verifying_key();
    write_file_mode(&secret_path, &signing::secret_key_file(&key), 0o600)?;
    write_file_mode(&public_path, &signing::public_key_file(&public), 0o644)?;
    println!("key id {}", KeyId::of(&public));
    println!(
        "secret key: {} (mode 600; keep it off the device)",
        secret_path.display()
    );
    println!(
        "public key: {} (list it in irtrackd's [params] trusted_keys)",
        public_path.display()
    );
    Ok(())
}
