//! Disk space during `cargo xtask test`.
//!
//! A cold run compiles the workspace for several profiles and targets (host debug and release,
//! aarch64 debug and static release, fuzz) and unpacks BitBake's trees; together that is more
//! than some CI machines have free. Each phase names the build directories under `target/` it
//! uses; when free space falls below a floor, directories that no remaining phase needs are
//! removed before the next phase starts, and the run says what it removed and why. With space
//! to spare nothing is removed, so a developer's warm `target/` survives a local run.

use std::fs;
use std::path::Path;
use std::process::Command;

/// Below this much free space (bytes), finished phases' build directories are removed.
/// `IRTRACK_CI_MIN_FREE_GB` overrides it (0 never removes anything).
pub const DEFAULT_MIN_FREE: u64 = 20 * GIB;

pub const GIB: u64 = 1 << 30;

/// The floor in bytes: `IRTRACK_CI_MIN_FREE_GB` or [`DEFAULT_MIN_FREE`].
pub fn min_free() -> Result<u64, String> {
    match std::env::var("IRTRACK_CI_MIN_FREE_GB") {
        Err(_) => Ok(DEFAULT_MIN_FREE),
        Ok(v) => v
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|g| g.is_finite() && *g >= 0.0)
            .map(|g| (g * GIB as f64) as u64)
            .ok_or_else(|| format!("IRTRACK_CI_MIN_FREE_GB must be a number of GiB >= 0, not `{v}`")),
    }
}

/// Free space for unprivileged users on the file system holding `path`, from `df -Pk`
/// (xtask depends on std only). `None` when df is missing or its output is not understood.
pub fn free_bytes(path: &Path) -> Option<u64> {
    // df needs an existing path; walk up to the nearest one (target/ may not exist yet).
    let mut p = path;
    while !p.exists() {
        p = p.parent()?;
    }
    let out = Command::new("df").arg("-Pk").arg(p).output().ok()?;
    if !out.status.success() {
        return None;
    }
    parse_df_available_kib(&String::from_utf8_lossy(&out.stdout)).map(|k| k * 1024)
}

/// The "Available" column (KiB) of `df -P` output's data line.
fn parse_df_available_kib(text: &str) -> Option<u64> {
    let line = text.lines().nth(1)?;
    // Filesystem, 1024-blocks, Used, Available, Capacity, Mounted on (POSIX format; the file
    // system name has no spaces in -P output, the mount point may).
    line.split_whitespace().nth(3)?.parse().ok()
}

/// Bytes used by the files under `path` (symbolic links are not followed). Unreadable
/// entries count as zero: the figure is for reports only.
pub fn dir_bytes(path: &Path) -> u64 {
    let Ok(meta) = fs::symlink_metadata(path) else {
        return 0;
    };
    if !meta.is_dir() {
        return meta.len();
    }
    let Ok(entries) = fs::read_dir(path) else {
        return 0;
    };
    entries.filter_map(|e| e.ok()).map(|e| dir_bytes(&e.path())).sum()
}

/// `12.3 GiB`.
pub fn fmt_gib(bytes: u64) -> String {
    format!("{:.1} GiB", bytes as f64 / GIB as f64)
}

/// Build directories (names under `target/`) that were used by phases already run and are
/// used by none of the phases still to come, in a stable order.
pub fn finished_builds<'a>(done: &[&'a [&'a str]], remaining: &[&'a [&'a str]]) -> Vec<&'a str> {
    let mut out: Vec<&str> = Vec::new();
    for dirs in done {
        for d in *dirs {
            let still_needed = remaining.iter().any(|r| r.contains(d));
            if !still_needed && !out.contains(d) {
                out.push(d);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn df_available_column() {
        let text = "Filesystem     1024-blocks      Used Available Capacity Mounted on\n\
                    /dev/vda         263174212  12582912  83886080      14% /\n";
        assert_eq!(parse_df_available_kib(text), Some(83_886_080));
        assert_eq!(parse_df_available_kib("Filesystem\n"), None);
        assert_eq!(parse_df_available_kib(""), None);
    }

    #[test]
    fn finished_builds_are_those_no_later_phase_uses() {
        let clippy: &[&str] = &["debug"];
        let aarch64: &[&str] = &["aarch64"];
        let image: &[&str] = &["image", "aarch64-static", "debug"];
        let fuzz: &[&str] = &["fuzz"];
        // Before the image phase: aarch64 is finished, debug is still needed by the image.
        assert_eq!(
            finished_builds(&[clippy, aarch64], &[image, fuzz]),
            vec!["aarch64"]
        );
        // Before fuzz: everything the image used is finished too.
        assert_eq!(
            finished_builds(&[clippy, aarch64, image], &[fuzz]),
            vec!["debug", "aarch64", "image", "aarch64-static"]
        );
        assert!(finished_builds(&[], &[fuzz]).is_empty());
    }

    #[test]
    fn dir_bytes_sums_files() {
        let dir = std::env::temp_dir().join(format!("xtask-disk-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(dir.join("a/b")).unwrap();
        fs::write(dir.join("a/one"), [0u8; 1000]).unwrap();
        fs::write(dir.join("a/b/two"), [0u8; 24]).unwrap();
        assert_eq!(dir_bytes(&dir), 1024);
        assert_eq!(dir_bytes(&dir.join("missing")), 0);
        fs::remove_dir_all(&dir).unwrap();
    }
}
