//! Signing keys and RAUC bundles for the update tests (firmware's `system_update`, host-tools'
//! `update_cli`): a CA and a signer it issued, made with the host's `openssl` as the image's
//! keys are (EC P-256, no extendedKeyUsage, which RAUC refuses), and plain bundles made with the
//! host's `rauc bundle`. Both programs are installed by `cargo xtask setup`.

use std::io;
use std::path::{Path, PathBuf};
use std::process::Command;

/// `program args…` in `dir`; its stderr in the error when it fails.
fn run(program: &str, args: &[&str], dir: &Path) -> io::Result<()> {
    let out = Command::new(program)
        .args(args)
        .current_dir(dir)
        .output()
        .map_err(|e| io::Error::other(format!("{program} (cargo xtask setup installs it): {e}")))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(io::Error::other(format!(
            "{program} {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        )))
    }
}

/// In `dir`: `ca.key.pem`, `ca.cert.pem` (subject `/CN=<name> CA`) and `signer.key.pem`,
/// `signer.cert.pem` issued by it, valid 30 days. Returns the CA certificate's path.
pub fn make_update_keys(dir: &Path, name: &str) -> io::Result<PathBuf> {
    std::fs::create_dir_all(dir)?;
    std::fs::write(
        dir.join("openssl.cnf"),
        "[req]\ndistinguished_name=dn\n[dn]\n[ca]\nbasicConstraints=critical,CA:TRUE\n\
         keyUsage=critical,keyCertSign,cRLSign\nsubjectKeyIdentifier=hash\n[signer]\n\
         basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n",
    )?;
    for key in ["ca.key.pem", "signer.key.pem"] {
        let args = [
            "genpkey",
            "-algorithm",
            "EC",
            "-pkeyopt",
            "ec_paramgen_curve:P-256",
            "-out",
            key,
        ];
        run("openssl", &args, dir)?;
    }
    let (ca_subject, signer_subject) = (format!("/CN={name} CA"), format!("/CN={name} signer"));
    run(
        "openssl",
        &[
            "req",
            "-new",
            "-x509",
            "-key",
            "ca.key.pem",
            "-out",
            "ca.cert.pem",
            "-days",
            "30",
            "-subj",
            &ca_subject,
            "-config",
            "openssl.cnf",
            "-extensions",
            "ca",
        ],
        dir,
    )?;
    run(
        "openssl",
        &[
            "req",
            "-new",
            "-key",
            "signer.key.pem",
            "-out",
            "signer.csr",
            "-subj",
            &signer_subject,
            "-config",
            "openssl.cnf",
        ],
        dir,
    )?;
    run(
        "openssl",
        &[
            "x509",
            "-req",
            "-in",
            "signer.csr",
            "-CA",
            "ca.cert.pem",
            "-CAkey",
            "ca.key.pem",
            "-CAcreateserial",
            "-out",
            "signer.cert.pem",
            "-days",
            "30",
            "-extfile",
            "openssl.cnf",
            "-extensions",
            "signer",
        ],
        dir,
    )?;
    Ok(dir.join("ca.cert.pem"))
}

/// `work/<name>.raucb`: a plain bundle of `version` (build `test.<name>`) for `compatible`,
/// its slot image `image`, signed with the signer of `keys` ([`make_update_keys`]).
pub fn make_bundle(
    keys: &Path,
    work: &Path,
    name: &str,
    compatible: &str,
    version: &str,
    image: &[u8],
) -> io::Result<PathBuf> {
    let content = work.join(format!("content-{name}"));
    std::fs::create_dir_all(&content)?;
    std::fs::write(content.join("rootfs.ext4"), image)?;
    std::fs::write(
        content.join("manifest.raucm"),
        format!(
            "[update]\ncompatible={compatible}\nversion={version}\nbuild=test.{name}\n\n[bundle]\nformat=plain\n\n\
             [image.rootfs]\nfilename=rootfs.ext4\n"
        ),
    )?;
    let out = work.join(format!("{name}.raucb"));
    // `rauc bundle` refuses to overwrite.
    let _ = std::fs::remove_file(&out);
    let (cert, key) = (keys.join("signer.cert.pem"), keys.join("signer.key.pem"));
    let path = |p: &Path| {
        p.to_str()
            .map(str::to_owned)
            .ok_or_else(|| io::Error::other(format!("{} is not UTF-8", p.display())))
    };
    run(
        "rauc",
        &[
            "bundle",
            "--cert",
            &path(&cert)?,
            "--key",
            &path(&key)?,
            &path(&content)?,
            &path(&out)?,
        ],
        work,
    )?;
    Ok(out)
}
