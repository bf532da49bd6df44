//! Static checks of non-Rust files: systemd units (`systemd-analyze verify`, and
//! `systemd-analyze security --offline=true` against each service's exposure limit) and the
//! Yocto layer's BitBake recipes (`oelint-adv`). Each skips, saying so, while there is nothing to
//! check, and fails when its tool is missing.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::report::Outcome;
use crate::util::{self, Ctx, RunOpts};

const UNIT_SUFFIXES: &[&str] = &["service", "socket", "timer", "path", "target", "mount"];
const RECIPE_SUFFIXES: &[&str] = &["bb", "bbappend", "bbclass"];

/// Binaries this workspace builds; a unit may name them although they are not installed here.
const PROJECT_BINARIES: &[&str] = &["irtrackd", "host-tools"];

/// The highest `systemd-analyze security` exposure (0.0 safe .. 10.0 unsafe, in tenths) a
/// service unit of `systemd/` may reach; a unit not listed gets [`DEFAULT_EXPOSURE_LIMIT`].
/// Each limit and what the remaining exposure is for: docs/security.md, "systemd units".
const EXPOSURE_LIMITS: &[(&str, u32)] = &[
    // DynamicUser, no capabilities; what is left is the network and the camera/GPIO devices.
    ("irtrackd.service", 15),
    // Root with CAP_NET_BIND_SERVICE/NET_ADMIN/SYS_TIME, @clock, /dev/ptp*, writable /run.
    ("irtrack-ptp4l.service", 30),
    // Root with CAP_SYS_TIME, @clock, /dev/ptp*, writable /run; no IP traffic.
    ("irtrack-phc2sys.service", 30),
];
/// The limit for a service unit not in [`EXPOSURE_LIMITS`] (systemd's "OK" band ends at 3.9;
/// the project holds new units to the PTP units' level).
const DEFAULT_EXPOSURE_LIMIT: u32 = 30;

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
        exposure_check(&units)
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

/// `systemd-analyze security --offline=true` on every service unit: each unit's exposure is
/// printed, and the phase fails naming every unit above its limit.
fn exposure_check(units: &[PathBuf]) -> Outcome {
    let services = units
        .iter()
        .filter(|u| u.extension().is_some_and(|x| x == "service"));
    let mut over = Vec::new();
    for unit in services {
        let name = unit.file_name().and_then(|n| n.to_str()).unwrap_or("?");
        let mut cmd = Command::new("systemd-analyze");
        cmd.args(["security", "--offline=true", "--no-pager"]).arg(unit);
        let opts = RunOpts {
            capture_stdout: true,
            capture_stderr: true,
            ..RunOpts::default()
        };
        let out = match util::run(&mut cmd, opts) {
            Ok(o) if o.success() => o,
            Ok(o) => {
                return Outcome::failed(format!("systemd-analyze security {name} {}", o.describe()));
            }
            Err(e) => return Outcome::failed(format!("{e:#}")),
        };
        let exposure = match parse_exposure(&out.stdout, name) {
            Ok(x) => x,
            Err(e) => return Outcome::failed(e),
        };
        let limit = exposure_limit(name);
        let verdict = if exposure > limit { "ABOVE" } else { "within" };
        println!(
            "systemd: {name} exposure {} ({verdict} its limit {})",
            tenths(exposure),
            tenths(limit)
        );
        if exposure > limit {
            over.push(format!(
                "{name}: exposure {} is above its limit {} (docs/security.md, \"systemd units\")",
                tenths(exposure),
                tenths(limit)
            ));
        }
    }
    if over.is_empty() {
        Outcome::passed()
    } else {
        Outcome::failed(over.join("\n"))
    }
}

fn exposure_limit(unit: &str) -> u32 {
    EXPOSURE_LIMITS
        .iter()
        .find(|(n, _)| *n == unit)
        .map_or(DEFAULT_EXPOSURE_LIMIT, |(_, l)| *l)
}

fn tenths(x: u32) -> String {
    format!("{}.{}", x / 10, x % 10)
}

/// The exposure in tenths from `systemd-analyze security`'s last line,
/// `→ Overall exposure level for irtrackd.service: 1.5 OK 🙂`.
fn parse_exposure(output: &str, unit: &str) -> Result<u32, String> {
    let marker = format!("Overall exposure level for {unit}:");
    let line = output
        .lines()
        .find(|l| l.contains(&marker))
        .ok_or_else(|| format!("systemd-analyze security printed no \"{marker}\" line"))?;
    let value = line
        .split_once(&marker)
        .map(|(_, rest)| rest.trim())
        .and_then(|rest| rest.split_whitespace().next())
        .unwrap_or("");
    let bad = || format!("{unit}: exposure {value:?} is not a number 0.0..=10.0 in \"{line}\"");
    let (whole, frac) = value.split_once('.').ok_or_else(bad)?;
    let whole: u32 = whole.parse().map_err(|_| bad())?;
    let frac: u32 = match frac.len() {
        1 => frac.parse().map_err(|_| bad())?,
        _ => return Err(bad()),
    };
    let x = whole * 10 + frac;
    if x > 100 {
        return Err(bad());
    }
    Ok(x)
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
    ]);
    // Kernel variables oelint-adv's database lacks (linux-yocto's KBUILD_DEFCONFIG, KCONFIG_MODE,
    // used by the Pandaboard bbappend): declared known in yocto-layer/oelint-known.json.
    let known = layer.join("oelint-known.json");
    if known.is_file() {
        cmd.arg(format!("--constantmods=+{}", known.display()));
    }
    cmd.args(&recipes).current_dir(&layer);
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
        // Confined enough for the default limit (exposure 1.3 with systemd 252).
        let good = "[Unit]\nDescription=t\n[Service]\nExecStart=/usr/bin/irtrackd\n\
                    DynamicUser=yes\nCapabilityBoundingSet=\nPrivateNetwork=yes\nPrivateDevices=yes\n\
                    ProtectSystem=strict\nProtectHome=yes\nProtectKernelTunables=yes\n\
                    ProtectKernelModules=yes\nProtectKernelLogs=yes\nProtectControlGroups=yes\n\
                    ProtectClock=yes\nProtectProc=invisible\nRestrictAddressFamilies=AF_UNIX\n\
                    RestrictNamespaces=yes\nSystemCallFilter=@system-service\n\
                    [Install]\nWantedBy=multi-user.target\n";
        let unit = root.join("systemd/t.service");
        std::fs::write(&unit, good).unwrap();
        let o = systemd_phase(&ctx);
        assert!(o.failure.is_none() && o.skipped.is_none(), "{o:?}");
        // An unknown key only warns (exit 0) in systemd-analyze; the phase must still fail.
        std::fs::write(&unit, good.replace("Description", "Descripshun")).unwrap();
        let unknown_key = systemd_phase(&ctx);
        // Valid but unconfined (root, every capability): 9.6, above the default limit 3.0.
        let bare = "[Unit]\nDescription=t\n[Service]\nExecStart=/usr/bin/irtrackd\n";
        std::fs::write(&unit, bare).unwrap();
        let unconfined = systemd_phase(&ctx);
        std::fs::remove_dir_all(&root).unwrap();
        assert!(
            unknown_key
                .failure
                .as_deref()
                .is_some_and(|f| f.contains("Descripshun")),
            "{unknown_key:?}"
        );
        let f = unconfined.failure.unwrap_or_default();
        assert!(
            f.contains("t.service: exposure 9.6 is above its limit 3.0"),
            "{f}"
        );
    }

    #[test]
    fn exposure_is_read_from_systemd_analyze_security() {
        let out = "  NAME   DESCRIPTION   EXPOSURE\n\
                   ✗ PrivateNetwork=   Service has access to the host's network   0.5\n\
                   \n\
                   → Overall exposure level for irtrack-ptp4l.service: 2.7 OK 🙂\n";
        assert_eq!(parse_exposure(out, "irtrack-ptp4l.service"), Ok(27));
        let worst = "→ Overall exposure level for x.service: 10.0 UNSAFE 😨";
        assert_eq!(parse_exposure(worst, "x.service"), Ok(100));
        assert_eq!(
            parse_exposure("→ Overall exposure level for x.service: 0.0 SAFE 😀", "x.service"),
            Ok(0)
        );
        // Another unit's line, no line, and values that are not an exposure are errors that say
        // what was expected.
        let e = parse_exposure(out, "irtrackd.service").unwrap_err();
        assert!(e.contains("Overall exposure level for irtrackd.service:"), "{e}");
        for bad in ["", "2", "2.75", "-1.0", "x.5", "10.5", "2,7"] {
            let line = format!("→ Overall exposure level for x.service: {bad} OK");
            let e = parse_exposure(&line, "x.service").unwrap_err();
            assert!(e.contains("is not a number 0.0..=10.0"), "{bad:?}: {e}");
        }
    }

    #[test]
    fn exposure_limits_per_unit() {
        assert_eq!(exposure_limit("irtrackd.service"), 15);
        assert_eq!(exposure_limit("irtrack-ptp4l.service"), 30);
        assert_eq!(exposure_limit("irtrack-phc2sys.service"), 30);
        assert_eq!(exposure_limit("new-thing.service"), DEFAULT_EXPOSURE_LIMIT);
        assert_eq!(tenths(15), "1.5");
        assert_eq!(tenths(100), "10.0");
    }

    /// The project's own units are within their limits (what CI's systemd phase checks).
    #[test]
    fn project_units_are_within_their_exposure_limits() {
        if !util::on_path("systemd-analyze") {
            eprintln!("SKIPPED: systemd-analyze not found (`cargo xtask setup`)");
            return;
        }
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        let units = files_with(&root.join("systemd"), &["service"]);
        assert!(units.len() >= 3, "{units:?}");
        let o = exposure_check(&units);
        assert!(o.failure.is_none(), "{o:?}");
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
