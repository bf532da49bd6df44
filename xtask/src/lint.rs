//! Static checks of non-Rust files: systemd units (`systemd-analyze verify`) and the Yocto
//! layer's BitBake recipes (`oelint-adv`). Each skips, saying so, while there is nothing to
//! check, and fails when its tool is missing.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::report::Outcome;
use crate::util::{self, Ctx, RunOpts};

const UNIT_SUFFIXES: &[&str] = &["service", "socket", "timer", "path", "target", "mount"];
const RECIPE_SUFFIXES: &[&str] = &["bb", "bbappend", "bbclass"];

/// Binaries this workspace builds; a unit may name them although they are not installed here.
const PROJECT_BINARIES: &[&str] = &["irtrackd", "host-tools"];

/// Files under `dir` (recursively) whose extension is one of `suffixes`, sorted.
fn files_with(dir: &Path, suffixes: &[&str]) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p
                .extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| suffixes.contains(&x))
            {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

pub fn systemd_phase(ctx: &Ctx) -> Outcome {
    let units = files_with(&ctx.root.join("systemd"), UNIT_SUFFIXES);
    if units.is_empty() {
        return Outcome {
            skipped: Some("not present (no unit files in systemd/)".into()),
            ..Outcome::default()
        };
    }
    if !util::on_path("systemd-analyze") {
        return Outcome {
            failure: Some("systemd-analyze not found".into()),
            ..Outcome::default()
        };
    }
    let mut cmd = Command::new("systemd-analyze");
    cmd.args(["verify", "--man=no"])
        .args(&units)
        .current_dir(&ctx.root);
    let opts = RunOpts {
        capture_stdout: true,
        capture_stderr: true,
        ..RunOpts::default()
    };
    let out = match util::run(&mut cmd, opts) {
        Ok(o) => o,
        Err(e) => {
            return Outcome {
                failure: Some(format!("{e:#}")),
                ..Outcome::default()
            };
        }
    };
    // verify exits 0 on mere warnings (unknown keys, bad values), so every message counts,
    // except that the project's own binaries are not installed on the build machine.
    let problems: Vec<&str> = out
        .stdout
        .lines()
        .chain(out.stderr.lines())
        .map(str::trim)
        .filter(|l| !l.is_empty() && !is_missing_project_binary(l))
        .collect();
    if problems.is_empty() && (out.success() || !out.stderr.is_empty()) {
        println!("systemd: {} unit file(s) verified", units.len());
        Outcome::default()
    } else if problems.is_empty() {
        Outcome {
            failure: Some(format!("systemd-analyze verify {}", out.describe())),
            ..Outcome::default()
        }
    } else {
        Outcome {
            failure: Some(problems.join("\n")),
            ..Outcome::default()
        }
    }
}

/// `irtrackd.service: Command /usr/bin/irtrackd is not executable: No such file or directory`
fn is_missing_project_binary(line: &str) -> bool {
    let Some(rest) = line.split_once("Command ").map(|(_, r)| r) else {
        return false;
    };
    let Some((path, why)) = rest.split_once(" is not executable: ") else {
        return false;
    };
    let name = Path::new(path).file_name().and_then(|n| n.to_str()).unwrap_or("");
    why.starts_with("No such file or directory") && PROJECT_BINARIES.contains(&name)
}

pub fn yocto_phase(ctx: &Ctx) -> Outcome {
    let layer = ctx.root.join("yocto-layer");
    let recipes = files_with(&layer, RECIPE_SUFFIXES);
    if recipes.is_empty() {
        return Outcome {
            skipped: Some("not present (no recipes in yocto-layer/)".into()),
            ..Outcome::default()
        };
    }
    let Some(oelint) = crate::setup::oelint_adv() else {
        return Outcome {
            failure: Some("oelint-adv not found (run `cargo xtask setup`)".into()),
            ..Outcome::default()
        };
    };
    let mut cmd = Command::new(oelint);
    // Rules of the release the layer is written for (else oelint-adv applies the newest
    // release's, e.g. UNPACKDIR, which scarthgap does not have).
    if let Some(release) = layer_release(&layer) {
        cmd.args(["--release", &release]);
    }
    // Infos are suggestions, not findings. The HOMEPAGE reachability rule needs the network,
    // which would make CI flaky. Run inside the layer so a layer-local .oelint.cfg applies.
    cmd.args([
        "--quiet",
        "--relpaths",
        "--hide",
        "info",
        "--suppress",
        "oelint.vars.homepageping",
    ])
    .args(&recipes)
    .current_dir(&layer);
    match util::run(&mut cmd, RunOpts::default()) {
        Ok(out) if out.success() => {
            println!("yocto-lint: {} recipe file(s) clean", recipes.len());
            Outcome::default()
        }
        Ok(out) => Outcome {
            failure: Some(format!("oelint-adv {}", out.describe())),
            ..Outcome::default()
        },
        Err(e) => Outcome {
            failure: Some(format!("{e:#}")),
            ..Outcome::default()
        },
    }
}

/// The first release named by `LAYERSERIES_COMPAT_*` in a `conf/layer.conf` under `dir`.
fn layer_release(dir: &Path) -> Option<String> {
    files_with(dir, &["conf"])
        .iter()
        .filter(|p| p.ends_with("conf/layer.conf"))
        .find_map(|p| release_of(&std::fs::read_to_string(p).ok()?))
}

fn release_of(layer_conf: &str) -> Option<String> {
    layer_conf.lines().find_map(|l| {
        let rest = l.trim().strip_prefix("LAYERSERIES_COMPAT_")?;
        let value = rest.split_once('=')?.1.trim().trim_matches('"');
        value.split_whitespace().next().map(str::to_string)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_project_binaries_may_be_missing() {
        let ok = "irtrackd.service: Command /usr/bin/irtrackd is not executable: No such file or directory";
        assert!(is_missing_project_binary(ok));
        let other = "x.service: Command /usr/bin/nosuch is not executable: No such file or directory";
        assert!(!is_missing_project_binary(other));
        let warn = "/w/systemd/irtrackd.service:4: Failed to parse service type, ignoring: notifyy";
        assert!(!is_missing_project_binary(warn));
    }

    fn temp_root(tag: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("xtask-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn ctx_at(root: &Path) -> Ctx {
        Ctx {
            root: root.to_path_buf(),
            cargo: "cargo".into(),
        }
    }

    #[test]
    fn systemd_phase_accepts_good_units_and_rejects_bad_ones() {
        let root = temp_root("systemd");
        let ctx = ctx_at(&root);
        assert!(systemd_phase(&ctx).skipped.is_some(), "no systemd/ dir: skipped");
        std::fs::create_dir_all(root.join("systemd")).unwrap();
        let good = "[Unit]\nDescription=t\n[Service]\nExecStart=/usr/bin/irtrackd\n\
                    [Install]\nWantedBy=multi-user.target\n";
        std::fs::write(root.join("systemd/t.service"), good).unwrap();
        let o = systemd_phase(&ctx);
        assert!(o.failure.is_none() && o.skipped.is_none(), "{o:?}");
        // An unknown key only warns (exit 0) in systemd-analyze; the phase must still fail.
        std::fs::write(
            root.join("systemd/t.service"),
            good.replace("Description", "Descripshun"),
        )
        .unwrap();
        let o = systemd_phase(&ctx);
        std::fs::remove_dir_all(&root).unwrap();
        assert!(
            o.failure.as_deref().is_some_and(|f| f.contains("Descripshun")),
            "{o:?}"
        );
    }

    #[test]
    fn yocto_phase_flags_a_recipe_missing_mandatory_variables() {
        let root = temp_root("yocto");
        let ctx = ctx_at(&root);
        assert!(yocto_phase(&ctx).skipped.is_some(), "no recipes: skipped");
        let dir = root.join("yocto-layer/recipes-t/t");
        std::fs::create_dir_all(&dir).unwrap();
        let good = "SUMMARY = \"t\"\nDESCRIPTION = \"t tool\"\nHOMEPAGE = \"https://example.invalid/t\"\n\
                    LICENSE = \"MIT\"\n\
                    LIC_FILES_CHKSUM = \"file://LICENSE;md5=0835ade698e0bcf8506ecda2f7b4f302\"\n\
                    SRC_URI = \"file://t.c\"\n";
        std::fs::write(dir.join("t_1.0.bb"), good).unwrap();
        let clean = yocto_phase(&ctx);
        std::fs::write(dir.join("t_1.0.bb"), good.replace("DESCRIPTION", "# DESCRIPTION")).unwrap();
        let flagged = yocto_phase(&ctx);
        std::fs::remove_dir_all(&root).unwrap();
        assert!(clean.failure.is_none() && clean.skipped.is_none(), "{clean:?}");
        assert!(flagged.failure.is_some(), "{flagged:?}");
    }

    #[test]
    fn layer_release_comes_from_layerseries_compat() {
        let conf = "BBFILE_PRIORITY_x = \"10\"\nLAYERSERIES_COMPAT_x = \"scarthgap styhead\"\n";
        assert_eq!(release_of(conf).as_deref(), Some("scarthgap"));
        assert_eq!(release_of("LAYERVERSION_x = \"1\"\n"), None);
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        assert_eq!(
            layer_release(&root.join("yocto-layer")).as_deref(),
            Some("scarthgap")
        );
    }

    #[test]
    fn finds_files_by_suffix_recursively() {
        let dir = std::env::temp_dir().join(format!("xtask-lint-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("recipes-irtrack/irtrackd")).unwrap();
        std::fs::write(dir.join("recipes-irtrack/irtrackd/irtrackd_0.1.bb"), "").unwrap();
        std::fs::write(dir.join("README.md"), "").unwrap();
        let found = files_with(&dir, RECIPE_SUFFIXES);
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(found.len(), 1);
        assert!(found[0].ends_with("irtrackd_0.1.bb"));
    }
}
