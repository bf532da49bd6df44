//! `yocto-layer/meta-irtrack/recipes-irtrack/irtrackd/irtrackd-crates.inc`: the crate list
//! the OE-core `cargo` class fetches (crate:// URIs with sha256 sums), generated from
//! Cargo.lock so do_compile needs no network. CI regenerates it and fails on a difference.

use std::fs;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};

use crate::util::Ctx;

const INC: &str = "yocto-layer/meta-irtrack/recipes-irtrack/irtrackd/irtrackd-crates.inc";
const CRATES_IO: &str = "registry+https://github.com/rust-lang/crates.io-index";

#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct LockedCrate {
    name: String,
    version: String,
    checksum: String,
}

/// The parts of Cargo.lock read here.
#[derive(serde::Deserialize)]
struct Lock {
    #[serde(default)]
    package: Vec<LockPackage>,
}

#[derive(serde::Deserialize)]
struct LockPackage {
    name: String,
    version: String,
    source: Option<String>,
    checksum: Option<String>,
}

/// Registry packages of a Cargo.lock (workspace members have no source and are skipped).
/// Anything not from crates.io cannot be fetched by `crate://` and is an error.
fn parse_lock(text: &str) -> Result<Vec<LockedCrate>> {
    let lock: Lock = toml::from_str(text).context("Cargo.lock is not the TOML cargo writes")?;
    let mut crates = Vec::new();
    for p in lock.package {
        let (name, version) = (p.name, p.version);
        match p.source {
            None => continue,
            Some(s) if s == CRATES_IO => {}
            Some(s) => bail!("Cargo.lock: {name} {version} comes from {s}; only crates.io can be listed"),
        }
        let checksum = p
            .checksum
            .with_context(|| format!("Cargo.lock: {name} {version} has no checksum"))?;
        if checksum.len() != 64 || !checksum.bytes().all(|b| b.is_ascii_hexdigit()) {
            bail!("Cargo.lock: {name} {version} has a malformed checksum {checksum:?}");
        }
        crates.push(LockedCrate {
            name,
            version,
            checksum,
        });
    }
    crates.sort();
    Ok(crates)
}

/// The .inc text in the layout of OE-core's `cargo-update-recipe-crates`.
fn render(crates: &[LockedCrate]) -> String {
    let mut out = String::from(
        "# Generated from Cargo.lock by `cargo xtask image crates`; do not edit.\n\
         # CI regenerates this file and fails if it differs.\n\n\
         # from Cargo.lock\nSRC_URI += \"",
    );
    let uris: Vec<String> = crates
        .iter()
        .map(|c| format!("crate://crates.io/{}/{}", c.name, c.version))
        .collect();
    out.push_str(&uris.join(" \\\n    "));
    out.push_str("\"\n\n");
    for c in crates {
        out.push_str(&format!(
            "SRC_URI[{}-{}.sha256sum] = \"{}\"\n",
            c.name, c.version, c.checksum
        ));
    }
    out
}

fn generate(ctx: &Ctx) -> Result<(PathBuf, String, usize)> {
    let lock = ctx.root.join("Cargo.lock");
    let text = fs::read_to_string(&lock).with_context(|| format!("reading {}", lock.display()))?;
    let crates = parse_lock(&text)?;
    Ok((ctx.root.join(INC), render(&crates), crates.len()))
}

/// Fails when the committed .inc differs from what Cargo.lock gives.
pub fn check(ctx: &Ctx) -> Result<()> {
    let (path, want, n) = generate(ctx)?;
    let have = fs::read_to_string(&path).unwrap_or_default();
    if have != want {
        bail!(
            "{} is out of date with Cargo.lock ({n} crates); run `cargo xtask image crates`",
            path.display()
        );
    }
    println!("image: {} matches Cargo.lock ({n} crates)", path.display());
    Ok(())
}

pub fn cli(ctx: &Ctx, check_only: bool) -> Result<()> {
    if check_only {
        return check(ctx);
    }
    let (path, text, n) = generate(ctx)?;
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir)?;
    }
    fs::write(&path, text)?;
    println!("wrote {} ({n} crates)", path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const SUM: &str = "320119579fcad9c21884f5c4861d16174d0e06250625266f50fe6898340abefa";

    #[test]
    fn registry_crates_listed_sorted_members_skipped() {
        let lock = format!(
            "version = 4\n\n[[package]]\nname = \"zed\"\nversion = \"1.0.0\"\nsource = \"{CRATES_IO}\"\n\
             checksum = \"{SUM}\"\n\n[[package]]\nname = \"irtrack-core\"\nversion = \"0.1.0\"\n\
             dependencies = [\n \"zed\",\n]\n\n[[package]]\nname = \"adler2\"\nversion = \"2.0.1\"\n\
             source = \"{CRATES_IO}\"\nchecksum = \"{SUM}\"\n"
        );
        let crates = parse_lock(&lock).unwrap();
        assert_eq!(
            crates.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(),
            ["adler2", "zed"]
        );
        let inc = render(&crates);
        assert!(
            inc.contains(
                "SRC_URI += \"crate://crates.io/adler2/2.0.1 \\\n    crate://crates.io/zed/1.0.0\"\n"
            )
        );
        assert!(inc.contains(&format!("SRC_URI[zed-1.0.0.sha256sum] = \"{SUM}\"\n")));
        assert!(!inc.contains("irtrack-core"));
    }

    #[test]
    fn git_sources_and_bad_checksums_are_rejected() {
        let git =
            "[[package]]\nname = \"x\"\nversion = \"1.0.0\"\nsource = \"git+https://example.invalid/x\"\n";
        assert!(
            parse_lock(git)
                .unwrap_err()
                .to_string()
                .contains("only crates.io")
        );
        let bad = format!(
            "[[package]]\nname = \"x\"\nversion = \"1.0.0\"\nsource = \"{CRATES_IO}\"\nchecksum = \"abc\"\n"
        );
        assert!(
            parse_lock(&bad)
                .unwrap_err()
                .to_string()
                .contains("malformed checksum")
        );
    }
}
