//! `yocto-bitbake` CI phase and `cargo xtask yocto ...`: the Yocto layer under real BitBake.
//!
//! The Yocto servers cannot be reached from CI, so unchanged snapshots of BitBake 2.8,
//! openembedded-core and meta-oe (scarthgap) are provided next to the checkout
//! (`../shared/yocto/`, see docs/image.md). The phase unpacks them once into
//! `target/yocto/src/`, copies `yocto-layer/meta-irtrack` into `target/yocto/layers/`, and with
//! `BB_NO_NETWORK = "1"` and `MACHINE = "qemuarm64"`:
//!
//! 1. parses every recipe (`bitbake -p`) of openembedded-core and the layer, and of meta-oe the
//!    ones the images use ([`META_OE_USED`]; the others are masked);
//! 2. lists the layer's recipes (`bitbake-layers show-recipes -l meta-irtrack`): every `.bb` file
//!    of the layer must be there and none skipped;
//! 3. resolves the image's whole task graph (`bitbake -g irtrack-image`);
//! 4. proves that a broken recipe fails step 1 with BitBake's own message (a syntax error is
//!    added to the copy, parsed, then removed), so the phase cannot pass vacuously;
//! 5. checks that the recipe's pinned `SRCREV` is a commit of this repository;
//! 6. checks that irtrackd is built with the cluster roles;
//! 7. for the layer's Pandaboard machine (`MACHINE = "pandaboard"`, a second build directory):
//!    resolves the image's task graph with the board's kernel and boot loader, and checks its
//!    Cortex-A9/NEON tune and the kernel's defconfig as BitBake expands them;
//! 8. the A/B update layout: the SD card's partitions (wic), RAUC's slots (system.conf) and the
//!    boot counters' file (fw_env.config) agree, and BitBake expands the image and
//!    irtrack-update for each machine as that layout needs (boot files, slot disk, board part of
//!    the boot script). Check 5 also proves that SRCREV holds the files irtrack-update installs.
//!
//! BitBake refuses to run as root; as root the phase runs it as [`BITBAKE_USER`] (made by
//! `cargo xtask setup`) through `runuser`.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use anyhow::{Context, Result, bail};

use crate::report::Counts;
use crate::util::{self, Ctx, RunOpts};

/// The unprivileged system user that runs BitBake when CI runs as root.
pub const BITBAKE_USER: &str = "irtrack-yocto";
/// Directory of the snapshots when not `../shared/yocto` (or a `shared/yocto` further up).
pub const SNAPSHOTS_ENV: &str = "IRTRACK_YOCTO_SNAPSHOTS";
/// The snapshot archives and the directory each unpacks to.
const TARBALLS: &[(&str, &str)] = &[
    ("bitbake-2.8.tar.xz", "bitbake"),
    ("openembedded-core-scarthgap.tar.xz", "openembedded-core"),
    ("meta-oe-scarthgap.tar.xz", "meta-openembedded"),
];
const LAYER: &str = "meta-irtrack";
/// meta-oe's recipe directories the images use (found in `bitbake -g`'s graph for both
/// machines). The checks mask meta-oe's other ~960 recipes: parsing them took half of each
/// build directory's parse, and the layer neither appends to them nor needs them.
/// openembedded-core and the layer itself are parsed whole.
const META_OE_USED: &[&str] = &[
    "recipes-connectivity/linuxptp/",
    "recipes-multimedia/v4l2apps/",
    "recipes-support/libgpiod/",
];
/// The layer's machine file for the Pandaboard (conf/machine/pandaboard.conf).
const PANDABOARD: &str = "pandaboard";
/// The machine of the main checks: the snapshots have no board layer.
const QEMU_MACHINE: &str = "qemuarm64";
const IMAGE: &str = "irtrack-image";
/// The include with the pinned source revision (shared by irtrackd and irtrack-update).
const SRC_RECIPE: &str = "recipes-irtrack/irtrack-source.inc";
/// The recipe of the A/B update pieces, which installs files of the repository at SRCREV.
const UPDATE_RECIPE: &str = "recipes-irtrack/irtrack-update/irtrack-update_git.bb";
/// The A/B SD card layout and the slot configuration it must agree with.
const AB_WKS: &str = "wic/irtrack-sdcard-ab.wks";
const AB_SYSTEM_CONF: &str = "recipes-irtrack/irtrack-update/files/system.conf.in";
/// The recipe the negative control adds to the layer's copy: line 3 is not BitBake syntax.
const BROKEN_RECIPE: &str = "recipes-irtrack/ci-broken/ci-broken_1.0.bb";
const BROKEN_TEXT: &str = "SUMMARY = \"deliberately broken (yocto-bitbake negative control)\"\n\
                           LICENSE = \"MIT\"\n\
                           this line is not bitbake syntax\n";
/// Marks the blocks of conf files this module writes (rewritten on every run).
const BEGIN: &str = "# >>> irtrack: written by `cargo xtask` (yocto-bitbake); do not edit";
const END: &str = "# <<< irtrack";

/// `cargo xtask yocto <command>`.
#[derive(Debug, clap::Subcommand)]
pub enum YoctoCmd {
    /// What CI's yocto-bitbake phase runs: parse, list recipes, resolve irtrack-image.
    Check,
    /// Run openembedded-core's yocto-check-layer on meta-irtrack (about 25 min; not in CI).
    CheckLayer,
    /// Print the commands to work in the BitBake build directory by hand.
    Shell,
}

/// CI entry point.
/// Why the snapshots cannot be used, when they are absent or incomplete (the CI phase reports
/// this as "skipped" with the message, not as a pass).
pub fn snapshots_missing(ctx: &Ctx) -> Option<String> {
    find_snapshots(&ctx.root, std::env::var_os(SNAPSHOTS_ENV).map(PathBuf::from))
        .err()
        .map(|e| format!("{e:#}"))
}

pub fn ci_phase(ctx: &Ctx) -> Result<Counts> {
    let report = check(ctx)?;
    Ok(Counts {
        passed: report,
        failed: 0,
        ignored: 0,
    })
}

pub fn cli(ctx: &Ctx, cmd: YoctoCmd) -> Result<()> {
    match cmd {
        YoctoCmd::Check => {
            let n = check(ctx)?;
            println!("yocto: all {n} checks passed");
            Ok(())
        }
        YoctoCmd::CheckLayer => check_layer(ctx),
        YoctoCmd::Shell => {
            let env = prepare(ctx, "build", true, QEMU_MACHINE)?;
            println!(
                "{}cd {} && LANG=en_US.UTF-8 BITBAKEDIR={} . ./openembedded-core/oe-init-build-env {}",
                env.runner
                    .as_ref()
                    .map(|u| format!("runuser -u {u} -- bash  # then:\n"))
                    .unwrap_or_default(),
                env.src.display(),
                env.src.join("bitbake").display(),
                env.build.display()
            );
            Ok(())
        }
    }
}

/// The uid of [`BITBAKE_USER`], if that user exists.
pub fn bitbake_user_uid() -> Option<u32> {
    let out = Command::new("id").args(["-u", BITBAKE_USER]).output().ok()?;
    if !out.status.success() {
        return None;
    }
    String::from_utf8_lossy(&out.stdout).trim().parse().ok()
}

/// Where the snapshots are: `$IRTRACK_YOCTO_SNAPSHOTS`, else the nearest `shared/yocto` beside
/// the checkout or one of its parents (`../shared/yocto` first). The error says what is missing.
fn find_snapshots(root: &Path, env: Option<PathBuf>) -> Result<PathBuf> {
    let complete = |dir: &Path| -> Vec<String> {
        std::iter::once("SHA256SUMS")
            .chain(TARBALLS.iter().map(|(f, _)| *f))
            .filter(|f| !dir.join(f).is_file())
            .map(str::to_string)
            .collect()
    };
    if let Some(dir) = env {
        let missing = complete(&dir);
        if !missing.is_empty() {
            bail!(
                "{SNAPSHOTS_ENV}={}: missing {} (the BitBake 2.8 / openembedded-core / meta-oe \
                 scarthgap snapshots, see docs/image.md)",
                dir.display(),
                missing.join(", ")
            );
        }
        return Ok(dir);
    }
    let mut looked = Vec::new();
    for parent in root.ancestors().skip(1) {
        let dir = parent.join("shared/yocto");
        if dir.is_dir() {
            let missing = complete(&dir);
            if missing.is_empty() {
                return Ok(dir);
            }
            bail!("{} is incomplete: missing {}", dir.display(), missing.join(", "));
        }
        looked.push(dir.display().to_string());
    }
    bail!(
        "the BitBake snapshots are missing: CI provides bitbake-2.8.tar.xz, \
         openembedded-core-scarthgap.tar.xz, meta-oe-scarthgap.tar.xz and SHA256SUMS in \
         ../shared/yocto beside the checkout (looked in {}); set {SNAPSHOTS_ENV} to their \
         directory if they are elsewhere (docs/image.md)",
        looked.join(", ")
    )
}

/// Everything a BitBake command needs.
struct BbEnv {
    /// Unpacked snapshots (bitbake/, openembedded-core/, meta-openembedded/).
    src: PathBuf,
    /// The copy of the layer that BitBake parses.
    layer: PathBuf,
    build: PathBuf,
    /// `Some(user)`: run through `runuser -u user` (we are root).
    runner: Option<String>,
}

impl BbEnv {
    /// `bash -c` running `script` in the initialised build directory, as the right user.
    fn command(&self, script: &str) -> Command {
        let full = format!(
            "set -e; export LANG=en_US.UTF-8 LC_ALL=en_US.UTF-8 BITBAKEDIR={bb}; \
             . {oe}/oe-init-build-env {build} >/dev/null; {script}",
            bb = util::shell_quote(&self.src.join("bitbake").to_string_lossy()),
            oe = util::shell_quote(&self.src.join("openembedded-core").to_string_lossy()),
            build = util::shell_quote(&self.build.to_string_lossy()),
        );
        let mut cmd = match &self.runner {
            Some(user) => {
                let mut c = Command::new("runuser");
                c.args(["-u", user, "--", "bash", "-c", &full]);
                c
            }
            None => {
                let mut c = Command::new("bash");
                c.args(["-c", &full]);
                c
            }
        };
        cmd.current_dir(&self.build);
        // Nothing from the caller's shell (a cargo/rustup environment) leaks into BitBake,
        // which whitelists its environment anyway; HOME must be the runner's.
        if let Some(user) = &self.runner {
            cmd.env("HOME", format!("/var/lib/{user}"));
            cmd.env("USER", user);
            cmd.env("LOGNAME", user);
        }
        cmd
    }

    /// Runs `script`, capturing its output (echoed live unless `quiet`).
    fn run(&self, script: &str, quiet: bool) -> Result<util::Output> {
        util::run(
            &mut self.command(script),
            RunOpts {
                capture_stdout: true,
                capture_stderr: true,
                quiet_stdout: quiet,
                timeout: Some(Duration::from_secs(25 * 60)),
                ..RunOpts::default()
            },
        )
    }
}

/// Unpacks (or reuses) the snapshots, copies the layer, writes the configuration of the
/// build directory `target/yocto/<build_name>`, whose BBLAYERS has the layer under test only
/// when `with_layer` (yocto-check-layer wants a build without it and adds it itself), for
/// `machine`.
fn prepare(ctx: &Ctx, build_name: &str, with_layer: bool, machine: &str) -> Result<BbEnv> {
    let snapshots = find_snapshots(&ctx.root, std::env::var_os(SNAPSHOTS_ENV).map(PathBuf::from))?;
    let runner = if util::is_root() {
        if bitbake_user_uid().is_none() {
            bail!(
                "running as root, and BitBake refuses root: the user `{BITBAKE_USER}` that runs \
                 it does not exist (run `cargo xtask setup`)"
            );
        }
        Some(BITBAKE_USER.to_string())
    } else {
        None
    };
    if !has_locale() {
        bail!("BitBake needs the en_US.UTF-8 locale, which is not generated (run `cargo xtask setup`)");
    }
    let work = ctx.target_dir().join("yocto");
    let src = work.join("src");
    unpack(&snapshots, &src)?;
    let layers = work.join("layers");
    let layer = layers.join(LAYER);
    if layer.exists() {
        fs::remove_dir_all(&layer).with_context(|| format!("removing {}", layer.display()))?;
    }
    fs::create_dir_all(&layers)?;
    copy_tree(&ctx.root.join("yocto-layer").join(LAYER), &layer)?;
    let build = work.join(build_name);
    fs::create_dir_all(&build)?;
    if let Some(user) = &runner {
        // The runner owns the whole work area (it writes caches and tmp/ everywhere in it).
        let out = util::run(
            Command::new("chown").args(["-R", &format!("{user}:")]).arg(&work),
            RunOpts::default(),
        )?;
        if !out.success() {
            bail!("chown -R {user} {} {}", work.display(), out.describe());
        }
    }
    let env = BbEnv {
        src,
        layer,
        build,
        runner,
    };
    // A first run creates conf/ from openembedded-core's templates; it also proves that the
    // runner can reach and write the build directory (a parent not searchable by others,
    // e.g. a checkout under /root, would stop it here).
    let out = env.run("true", false)?;
    if !out.success() {
        bail!(
            "initialising the BitBake build directory {} {}{}",
            env.build.display(),
            out.describe(),
            env.runner
                .as_ref()
                .map(|u| format!(" (as user {u}: every parent directory must be searchable by it)"))
                .unwrap_or_default()
        );
    }
    let conf = env.build.join("conf");
    let mut layers_list = vec![env.src.join("openembedded-core/meta")];
    if with_layer {
        layers_list.push(env.src.join("meta-openembedded/meta-oe"));
        layers_list.push(env.layer.clone());
    }
    let bblayers = format!(
        "BBLAYERS = \" \\\n{} \\\n  \"",
        layers_list
            .iter()
            .map(|p| format!("  {}", p.display()))
            .collect::<Vec<_>>()
            .join(" \\\n")
    );
    set_block(&conf.join("bblayers.conf"), &bblayers)?;
    // The kas build's settings that matter for parsing (yocto-layer/kas/irtrack.yml), no
    // network, and the machine (QEMU's, as the snapshots have no board layer, or the layer's
    // own Pandaboard file).
    let mut local = format!("BB_NO_NETWORK = \"1\"\nMACHINE = \"{machine}\"\nINIT_MANAGER = \"systemd\"");
    if with_layer {
        local.push_str(&format!("\nBBMASK += \"{}\"", meta_oe_mask()));
    }
    set_block(&conf.join("local.conf"), &local)?;
    Ok(env)
}

/// A BBMASK regular expression (Python's `re.search` on each recipe's path) for every meta-oe
/// recipe and append file outside [`META_OE_USED`].
fn meta_oe_mask() -> String {
    let keep: Vec<String> = META_OE_USED
        .iter()
        .map(|d| d.strip_prefix("recipes-").unwrap_or(d).to_string())
        .collect();
    format!("/meta-openembedded/meta-oe/recipes-(?!{})", keep.join("|"))
}

/// A hint for an unresolved dependency: it may be a masked meta-oe recipe.
fn mask_hint(errors: &str) -> &'static str {
    if errors.contains("Nothing PROVIDES") || errors.contains("Nothing RPROVIDES") {
        "\n(meta-oe's recipes other than META_OE_USED in xtask/src/yocto.rs are masked in these \
         checks: if the missing recipe is meta-oe's, add its directory there)"
    } else {
        ""
    }
}

fn has_locale() -> bool {
    Command::new("locale").arg("-a").output().is_ok_and(|o| {
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .any(|l| l.eq_ignore_ascii_case("en_US.utf8") || l.eq_ignore_ascii_case("en_US.UTF-8"))
    })
}

/// Unpacks the snapshots into `src` unless exactly these (by SHA256SUMS) are there already.
fn unpack(snapshots: &Path, src: &Path) -> Result<()> {
    let sums = fs::read_to_string(snapshots.join("SHA256SUMS"))?;
    let stamp = src.join(".unpacked-from-SHA256SUMS");
    if fs::read_to_string(&stamp).is_ok_and(|s| s == sums)
        && TARBALLS.iter().all(|(_, d)| src.join(d).is_dir())
    {
        println!("yocto: snapshots already unpacked in {}", src.display());
        return Ok(());
    }
    println!(
        "yocto: verifying and unpacking the snapshots from {}",
        snapshots.display()
    );
    let out = util::run(
        Command::new("sha256sum")
            .args(["--check", "--strict", "SHA256SUMS"])
            .current_dir(snapshots),
        RunOpts::default(),
    )?;
    if !out.success() {
        bail!(
            "sha256sum --check SHA256SUMS in {} {}",
            snapshots.display(),
            out.describe()
        );
    }
    if src.exists() {
        fs::remove_dir_all(src).with_context(|| format!("removing {}", src.display()))?;
    }
    fs::create_dir_all(src)?;
    for (tarball, _) in TARBALLS {
        let out = util::run(
            Command::new("tar")
                .arg("-xJf")
                .arg(snapshots.join(tarball))
                .arg("-C")
                .arg(src),
            RunOpts::default(),
        )?;
        if !out.success() {
            bail!("unpacking {tarball} {}", out.describe());
        }
    }
    for (tarball, dir) in TARBALLS {
        if !src.join(dir).is_dir() {
            bail!("{tarball} did not unpack to {dir}/");
        }
    }
    fs::write(&stamp, sums)?;
    Ok(())
}

/// Replaces (or appends) this module's marked block in a conf file.
fn set_block(file: &Path, body: &str) -> Result<()> {
    let text = fs::read_to_string(file).with_context(|| format!("reading {}", file.display()))?;
    fs::write(file, with_block(&text, body)).with_context(|| format!("writing {}", file.display()))
}

fn with_block(text: &str, body: &str) -> String {
    let mut kept = String::new();
    let mut inside = false;
    for line in text.lines() {
        if line == BEGIN {
            inside = true;
        } else if inside && line == END {
            inside = false;
        } else if !inside {
            kept.push_str(line);
            kept.push('\n');
        }
    }
    format!("{kept}{BEGIN}\n{body}\n{END}\n")
}

fn copy_tree(src: &Path, dest: &Path) -> Result<()> {
    fs::create_dir_all(dest)?;
    for entry in fs::read_dir(src).with_context(|| format!("reading {}", src.display()))? {
        let entry = entry?;
        let to = dest.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_tree(&entry.path(), &to)?;
        } else {
            fs::copy(entry.path(), &to).with_context(|| format!("copying {}", entry.path().display()))?;
        }
    }
    Ok(())
}

/// BitBake's own error message: from its first `ERROR:` line up to its `Summary:` (the
/// detail lines of an exception follow the `ERROR:` line unprefixed), at most 40 lines; its
/// last lines when it printed no `ERROR:`.
fn bitbake_errors(out: &util::Output) -> String {
    let all = format!("{}\n{}", out.stdout, out.stderr);
    let lines: Vec<&str> = all.lines().filter(|l| !l.trim().is_empty()).collect();
    match lines.iter().position(|l| l.starts_with("ERROR:")) {
        Some(start) => lines[start..]
            .iter()
            .take_while(|l| !l.starts_with("Summary:"))
            .take(40)
            .copied()
            .collect::<Vec<_>>()
            .join("\n"),
        None => lines[lines.len().saturating_sub(10)..].join("\n"),
    }
}

/// `bitbake -p`: Ok, or Err with BitBake's own error lines.
fn parse_all(env: &BbEnv) -> Result<()> {
    let out = env.run("bitbake -p", false)?;
    if !out.success() {
        bail!("bitbake -p {}:\n{}", out.describe(), bitbake_errors(&out));
    }
    Ok(())
}

/// Recipe names of the layer from `bitbake-layers show-recipes -l <layer>` output, with the
/// skip reason of any skipped one.
fn layer_recipes(show: &str, layer: &str) -> Vec<(String, Option<String>)> {
    let mut out = Vec::new();
    let mut current: Option<String> = None;
    for line in show.lines() {
        if !line.starts_with(' ') {
            current = line.strip_suffix(':').map(str::to_string);
            continue;
        }
        let mut words = line.split_whitespace();
        if words.next() != Some(layer) {
            continue;
        }
        if let Some(pn) = &current {
            let skipped = line
                .split_once("(skipped")
                .map(|(_, r)| r.trim_start_matches(':').trim_end_matches(')').trim().to_string());
            out.push((pn.clone(), skipped));
        }
    }
    out
}

/// PNs of the layer's `.bb` files (file name up to the first `_`).
fn expected_recipes(layer: &Path) -> Result<Vec<String>> {
    let mut out = Vec::new();
    let mut stack = vec![layer.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in fs::read_dir(&dir)?.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "bb") {
                let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("");
                out.push(stem.split('_').next().unwrap_or(stem).to_string());
            }
        }
    }
    out.sort();
    out.dedup();
    Ok(out)
}

/// The `SRCREV = "..."` of a recipe.
fn pinned_srcrev(recipe: &str) -> Option<String> {
    recipe.lines().find_map(|l| {
        let rest = l.trim().strip_prefix("SRCREV")?.trim_start();
        let value = rest.strip_prefix('=')?.trim().trim_matches('"');
        Some(value.to_string())
    })
}

/// Runs every check; returns how many passed (all, or an error naming the failure).
fn check(ctx: &Ctx) -> Result<u64> {
    let mut passed = 0;
    let env = prepare(ctx, "build", true, QEMU_MACHINE)?;

    println!(
        "yocto: 1. parsing the recipes (meta-oe: only those the images use; BB_NO_NETWORK=1, MACHINE={QEMU_MACHINE})"
    );
    parse_all(&env)?;
    passed += 1;

    println!("yocto: 2. the layer's recipes");
    let out = env.run(&format!("bitbake-layers show-recipes -l {LAYER}"), false)?;
    if !out.success() {
        bail!(
            "bitbake-layers show-recipes {}:\n{}",
            out.describe(),
            bitbake_errors(&out)
        );
    }
    let listed = layer_recipes(&out.stdout, LAYER);
    let want = expected_recipes(&env.layer)?;
    for pn in &want {
        match listed.iter().find(|(n, _)| n == pn) {
            None => bail!("recipe {pn} of {LAYER} is not listed by bitbake-layers show-recipes"),
            Some((_, Some(why))) => bail!("BitBake skips recipe {pn}: {why}"),
            Some(_) => {}
        }
    }
    println!("yocto: {LAYER} provides {} (none skipped)", want.join(", "));
    passed += 1;

    println!("yocto: 3. resolving the task graph of {IMAGE}");
    let graph = resolve_image(&env)?;
    for pn in [IMAGE, "irtrackd", "rauc", "irtrack-update"] {
        if !graph.recipes.iter().any(|r| r == pn) {
            bail!("{pn} is not in the task graph of {IMAGE} (pn-buildlist)");
        }
    }
    let (pns, tasks) = (&graph.recipes, graph.tasks);
    println!("yocto: {IMAGE} resolves to {} recipes, {tasks} tasks", pns.len());
    passed += 1;

    println!("yocto: 4. negative control: a broken recipe must fail the parse with BitBake's message");
    let broken = env.layer.join(BROKEN_RECIPE);
    fs::create_dir_all(broken.parent().context("broken recipe path has no parent")?)?;
    fs::write(&broken, BROKEN_TEXT)?;
    if let Some(user) = &env.runner {
        let _ = Command::new("chown")
            .args(["-R", &format!("{user}:")])
            .arg(&env.layer)
            .status();
    }
    let control = parse_all(&env);
    if let Some(dir) = broken.parent() {
        fs::remove_dir_all(dir)?;
    }
    match control {
        Ok(()) => bail!(
            "bitbake -p accepted {} (a recipe with a syntax error)",
            broken.display()
        ),
        Err(e) => {
            let msg = format!("{e:#}");
            if !(msg.contains("ParseError") && msg.contains("ci-broken_1.0.bb")) {
                bail!("bitbake -p failed on the broken recipe, but not with its ParseError:\n{msg}");
            }
            println!("yocto: refused as expected:\n{msg}");
        }
    }
    passed += 1;

    println!("yocto: 5. the pinned SRCREV is a commit of this repository");
    let recipe = fs::read_to_string(ctx.root.join("yocto-layer").join(LAYER).join(SRC_RECIPE))?;
    let rev = pinned_srcrev(&recipe).with_context(|| format!("{SRC_RECIPE} has no SRCREV = \"...\""))?;
    if rev.len() != 40 || !rev.bytes().all(|b| b.is_ascii_hexdigit()) {
        bail!("{SRC_RECIPE}: SRCREV {rev:?} is not a full commit hash (parsing would need the network)");
    }
    let out = Command::new("git")
        .args(["cat-file", "-e", &format!("{rev}^{{commit}}")])
        .current_dir(&ctx.root)
        .output()
        .context("running git cat-file")?;
    if !out.status.success() {
        bail!(
            "{SRC_RECIPE}: SRCREV {rev} is not a commit of this repository (a shallow clone? \
             {})",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    println!("yocto: SRCREV {rev} is a commit of this repository");
    let update = fs::read_to_string(ctx.root.join("yocto-layer").join(LAYER).join(UPDATE_RECIPE))?;
    let files = files_from_source(&update);
    if files.is_empty() {
        bail!("{UPDATE_RECIPE} installs no ${{S}}/... file: the check below would prove nothing");
    }
    for f in &files {
        let out = Command::new("git")
            .args(["cat-file", "-e", &format!("{rev}:{f}")])
            .current_dir(&ctx.root)
            .output()
            .context("running git cat-file")?;
        if !out.status.success() {
            bail!(
                "{UPDATE_RECIPE} installs {f}, which commit {rev} (SRCREV) does not have: pin a newer commit"
            );
        }
    }
    println!(
        "yocto: SRCREV holds the {} files irtrack-update installs from the repository",
        files.len()
    );
    passed += 1;

    println!("yocto: 6. irtrackd is built with the cluster roles (PACKAGECONFIG cluster)");
    let out = env.run("bitbake -e irtrackd", true)?;
    if !out.success() {
        bail!(
            "bitbake -e irtrackd {}:\n{}",
            out.describe(),
            bitbake_errors(&out)
        );
    }
    let flags = exported_value(&out.stdout, "CARGO_BUILD_FLAGS")
        .context("bitbake -e irtrackd shows no CARGO_BUILD_FLAGS")?;
    for want in ["-p irtrack-firmware", "--bin irtrackd", "--features cluster"] {
        if !flags.contains(want) {
            bail!("irtrackd's CARGO_BUILD_FLAGS lack {want:?}: {flags}");
        }
    }
    println!("yocto: CARGO_BUILD_FLAGS = {flags}");
    passed += 1;

    println!(
        "yocto: 7. MACHINE={PANDABOARD} (the layer's machine file): {IMAGE} resolves with the \
         board's kernel and boot loader, Cortex-A9/NEON tune"
    );
    check_pandaboard(ctx)?;
    passed += 1;

    println!("yocto: 8. A/B updates: the SD card layout, RAUC's slots and the boot counters' file agree");
    check_ab(ctx, &env)?;
    passed += 1;
    Ok(passed)
}

/// Check 8: the layer's A/B layout (wic) matches RAUC's slot configuration and fw_env.config,
/// and BitBake expands the image and irtrack-update as that layout needs for both machines.
fn check_ab(ctx: &Ctx, env: &BbEnv) -> Result<()> {
    let layer = ctx.root.join("yocto-layer").join(LAYER);
    let wks = fs::read_to_string(layer.join(AB_WKS))?;
    let conf = fs::read_to_string(layer.join(AB_SYSTEM_CONF))?;
    let fw_env = fs::read_to_string(ctx.root.join("image/update/rootfs/etc/fw_env.config"))?;
    ab_layout_agrees(&wks, &conf, &fw_env)?;
    println!(
        "yocto: {AB_WKS}: boot on /uboot (fw_env.config's counters), slots A and B on partitions 2 and 3 as system.conf says, data on 4"
    );
    let image = bitbake_env(env, IMAGE)?;
    let wks_file =
        exported_value(&image, "WKS_FILE").context("bitbake -e irtrack-image shows no WKS_FILE")?;
    if wks_file != "irtrack-sdcard-ab.wks" {
        bail!("{IMAGE} uses WKS_FILE {wks_file:?}, not the A/B layout");
    }
    let boot_files = exported_value(&image, "IMAGE_BOOT_FILES").unwrap_or_default();
    for want in ["boot.scr", "uboot.env", "uboot-redund.env"] {
        if !boot_files.split_whitespace().any(|f| f == want) {
            bail!("{IMAGE}'s IMAGE_BOOT_FILES for {QEMU_MACHINE} lack {want}: {boot_files:?}");
        }
    }
    let update = bitbake_env(env, "irtrack-update")?;
    let disk = exported_value(&update, "IRTRACK_DISK").unwrap_or_default();
    if disk != "/dev/vda" {
        bail!("irtrack-update's IRTRACK_DISK for {QEMU_MACHINE} is {disk:?}, not /dev/vda");
    }
    let pandaboard = prepare(ctx, "build-pandaboard", true, PANDABOARD)?;
    let image = bitbake_env(&pandaboard, IMAGE)?;
    let boot_files = exported_value(&image, "IMAGE_BOOT_FILES").unwrap_or_default();
    for want in ["MLO", "u-boot.img", "boot.scr", "uboot.env", "uboot-redund.env"] {
        if !boot_files.split_whitespace().any(|f| f == want) {
            bail!("{IMAGE}'s IMAGE_BOOT_FILES for {PANDABOARD} lack {want}: {boot_files:?}");
        }
    }
    let update = bitbake_env(&pandaboard, "irtrack-update")?;
    let disk = exported_value(&update, "IRTRACK_DISK").unwrap_or_default();
    let compatible = exported_value(&update, "IRTRACK_COMPATIBLE").unwrap_or_default();
    if disk != "/dev/mmcblk0p" || compatible != "irtrack-pandaboard" {
        bail!(
            "irtrack-update for {PANDABOARD}: IRTRACK_DISK {disk:?} (want /dev/mmcblk0p), IRTRACK_COMPATIBLE {compatible:?}"
        );
    }
    // The board's half of the boot script must be the Pandaboard's (files/pandaboard/ first).
    let filespath = exported_value(&update, "FILESPATH").unwrap_or_default();
    let dirs: Vec<&str> = filespath.split(':').map(|p| p.trim_end_matches('/')).collect();
    let board_dir = dirs
        .iter()
        .position(|p| p.ends_with("irtrack-update/files/pandaboard"));
    let common_dir = dirs.iter().position(|p| p.ends_with("irtrack-update/files"));
    match (board_dir, common_dir) {
        (Some(b), Some(c)) if b < c => {}
        _ => bail!(
            "irtrack-update for {PANDABOARD} does not take files/pandaboard/ before files/: FILESPATH {filespath}"
        ),
    }
    println!(
        "yocto: {PANDABOARD}: boot partition {boot_files}; slots {disk}2/{disk}3, bundles for {compatible}; boot script half from files/pandaboard/"
    );
    Ok(())
}

/// One `part` line of a wic kickstart file.
#[derive(Debug, PartialEq)]
struct WksPart {
    mount: Option<String>,
    fstype: Option<String>,
    label: Option<String>,
}

/// The `part` lines of a .wks file, in partition order.
fn wks_partitions(text: &str) -> Vec<WksPart> {
    text.lines()
        .map(str::trim)
        .filter_map(|l| l.strip_prefix("part "))
        .map(|rest| {
            let words: Vec<&str> = rest.split_whitespace().collect();
            let value = |flag: &str| {
                words.iter().enumerate().find_map(|(i, w)| {
                    w.strip_prefix(&format!("{flag}="))
                        .map(str::to_string)
                        .or_else(|| {
                            (*w == flag)
                                .then(|| words.get(i + 1).map(|v| v.to_string()))
                                .flatten()
                        })
                })
            };
            WksPart {
                mount: words
                    .first()
                    .filter(|w| w.starts_with('/'))
                    .map(|w| w.to_string()),
                fstype: value("--fstype"),
                label: value("--label"),
            }
        })
        .collect()
}

/// `[slot.rootfs.N]` device and bootname pairs of a RAUC system.conf.
fn rauc_slots(conf: &str) -> Vec<(String, String)> {
    let mut slots = Vec::new();
    let mut cur: Option<(Option<String>, Option<String>)> = None;
    let mut flush = |cur: &mut Option<(Option<String>, Option<String>)>| {
        if let Some((Some(dev), Some(name))) = cur.take() {
            slots.push((dev, name));
        }
    };
    for line in conf.lines().map(str::trim) {
        if line.starts_with('[') {
            flush(&mut cur);
            if line.starts_with("[slot.rootfs.") {
                cur = Some((None, None));
            }
        } else if let Some((dev, name)) = cur.as_mut() {
            if let Some(v) = line.strip_prefix("device=") {
                *dev = Some(v.to_string());
            } else if let Some(v) = line.strip_prefix("bootname=") {
                *name = Some(v.to_string());
            }
        }
    }
    flush(&mut cur);
    slots
}

/// The A/B layout's three descriptions agree: the wks partitions, RAUC's slots and the path of
/// the boot counters in fw_env.config.
fn ab_layout_agrees(wks: &str, system_conf: &str, fw_env: &str) -> Result<()> {
    let parts = wks_partitions(wks);
    let part = |n: usize| parts.get(n - 1);
    let boot = part(1).filter(|p| p.fstype.as_deref() == Some("vfat"));
    let Some(boot_mount) = boot.and_then(|p| p.mount.clone()) else {
        bail!(
            "{AB_WKS}: partition 1 is not a mounted vfat boot partition: {:?}",
            part(1)
        );
    };
    let env_file = fw_env
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .and_then(|l| l.split_whitespace().next())
        .context("fw_env.config names no environment file")?;
    if !env_file.starts_with(&format!("{boot_mount}/")) {
        bail!(
            "fw_env.config keeps the boot counters in {env_file}, but the boot partition is mounted on {boot_mount}"
        );
    }
    for (n, label) in [(2, "root-a"), (3, "root-b")] {
        if part(n).and_then(|p| p.label.as_deref()) != Some(label) {
            bail!("{AB_WKS}: partition {n} is not the slot {label}: {:?}", part(n));
        }
    }
    if part(4).and_then(|p| p.mount.as_deref()) != Some("/data") {
        bail!(
            "{AB_WKS}: partition 4 is not the data partition on /data: {:?}",
            part(4)
        );
    }
    let slots = rauc_slots(system_conf);
    let want = [
        ("@DISK@2".to_string(), "A".to_string()),
        ("@DISK@3".to_string(), "B".to_string()),
    ];
    if slots != want {
        bail!("{AB_SYSTEM_CONF}: slots {slots:?}, but the layout has A on partition 2 and B on 3");
    }
    if !system_conf
        .lines()
        .any(|l| l.trim().starts_with("data-directory=/data/"))
    {
        bail!("{AB_SYSTEM_CONF}: RAUC's data-directory is not on the data partition (/data)");
    }
    Ok(())
}

/// Repository paths a recipe installs from its source tree (`${S}/path`).
fn files_from_source(recipe: &str) -> Vec<String> {
    let mut out: Vec<String> = recipe
        .split(|c: char| c.is_whitespace())
        .filter_map(|w| w.strip_prefix("${S}/"))
        .map(|p| p.trim_end_matches([';', '"']).to_string())
        .filter(|p| !p.is_empty())
        .collect();
    out.sort();
    out.dedup();
    out
}

/// Check 7: the Pandaboard machine in its own build directory (a second MACHINE means a second
/// parse; its cache is kept there for the next run).
fn check_pandaboard(ctx: &Ctx) -> Result<()> {
    let env = prepare(ctx, "build-pandaboard", true, PANDABOARD)?;
    let graph = resolve_image(&env)?;
    // The kernel and boot loader the machine file selects: a machine they refuse
    // (COMPATIBLE_MACHINE) would leave virtual/kernel unprovided and fail `bitbake -g`; a
    // missing one would not be in the graph.
    for pn in [IMAGE, "irtrackd", "linux-yocto", "u-boot"] {
        if !graph.recipes.iter().any(|r| r == pn) {
            bail!("{pn} is not in the task graph of {IMAGE} for MACHINE={PANDABOARD}");
        }
    }
    println!(
        "yocto: {PANDABOARD}: {IMAGE} resolves to {} recipes, {} tasks (linux-yocto, u-boot, irtrackd among them)",
        graph.recipes.len(),
        graph.tasks
    );
    let irtrackd = bitbake_env(&env, "irtrackd")?;
    let tune =
        exported_value(&irtrackd, "TUNE_FEATURES").context("bitbake -e irtrackd shows no TUNE_FEATURES")?;
    for want in ["cortexa9", "neon", "callconvention-hard"] {
        if !tune.split_whitespace().any(|f| f == want) {
            bail!("irtrackd's TUNE_FEATURES for {PANDABOARD} lack {want:?}: {tune}");
        }
    }
    let kernel = bitbake_env(&env, "linux-yocto")?;
    let defconfig = exported_value(&kernel, "KBUILD_DEFCONFIG")
        .context("bitbake -e linux-yocto shows no KBUILD_DEFCONFIG")?;
    if defconfig != "omap2plus_defconfig" {
        bail!("linux-yocto for {PANDABOARD} is configured from {defconfig:?}, not omap2plus_defconfig");
    }
    println!("yocto: {PANDABOARD}: TUNE_FEATURES = {tune}; linux-yocto from {defconfig}");
    Ok(())
}

/// `bitbake -e <recipe>`'s output.
fn bitbake_env(env: &BbEnv, recipe: &str) -> Result<String> {
    let out = env.run(&format!("bitbake -e {recipe}"), true)?;
    if !out.success() {
        bail!(
            "bitbake -e {recipe} {}:\n{}",
            out.describe(),
            bitbake_errors(&out)
        );
    }
    Ok(out.stdout)
}

/// What `bitbake -g` found for the image.
struct Graph {
    /// Recipe names (pn-buildlist).
    recipes: Vec<String>,
    /// Tasks in task-depends.dot.
    tasks: usize,
}

/// `bitbake -g` of the image in `env`'s build directory.
fn resolve_image(env: &BbEnv) -> Result<Graph> {
    for f in ["pn-buildlist", "task-depends.dot"] {
        let _ = fs::remove_file(env.build.join(f));
    }
    let out = env.run(&format!("bitbake -g {IMAGE}"), false)?;
    if !out.success() {
        let errors = bitbake_errors(&out);
        bail!(
            "bitbake -g {IMAGE} {}:\n{errors}{}",
            out.describe(),
            mask_hint(&errors)
        );
    }
    let buildlist =
        fs::read_to_string(env.build.join("pn-buildlist")).context("bitbake -g wrote no pn-buildlist")?;
    let recipes = buildlist
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(str::to_string)
        .collect();
    let tasks = fs::read_to_string(env.build.join("task-depends.dot"))
        .map(|t| t.lines().filter(|l| l.contains("[label=")).count())
        .unwrap_or(0);
    Ok(Graph { recipes, tasks })
}

/// The value of `NAME="..."` in `bitbake -e` output (the final, expanded assignment).
fn exported_value(env_dump: &str, name: &str) -> Option<String> {
    let prefix = format!("{name}=\"");
    env_dump.lines().rev().find_map(|l| {
        let v = l.strip_prefix(&prefix)?;
        Some(v.strip_suffix('"').unwrap_or(v).to_string())
    })
}

/// `yocto-check-layer` on the layer (not in CI: about 25 minutes on 2 cores).
fn check_layer(ctx: &Ctx) -> Result<()> {
    let env = prepare(ctx, "build-check-layer", false, QEMU_MACHINE)?;
    let script = format!(
        "yocto-check-layer --dependency {} -- {}",
        util::shell_quote(&env.src.join("meta-openembedded/meta-oe").to_string_lossy()),
        util::shell_quote(&env.layer.to_string_lossy())
    );
    // It parses every recipe several times over: allow far more than one parse.
    let out = util::run(
        &mut env.command(&script),
        RunOpts {
            timeout: Some(Duration::from_secs(3 * 3600)),
            ..RunOpts::default()
        },
    )?;
    if !out.success() {
        bail!("yocto-check-layer {}", out.describe());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// BBMASK is a Python regular expression (BitBake applies `re.search` to each path), so
    /// the mask is checked with Python's `re`: meta-oe's other recipes masked, the ones the
    /// images use and every openembedded-core recipe kept.
    #[test]
    fn meta_oe_mask_keeps_the_images_recipes_and_masks_the_rest() {
        let src = "/w/target/yocto/src";
        let cases = [
            (
                "meta-openembedded/meta-oe/recipes-support/libgpiod/libgpiod_2.1.3.bb",
                false,
            ),
            (
                "meta-openembedded/meta-oe/recipes-connectivity/linuxptp/linuxptp_4.1.bb",
                false,
            ),
            (
                "meta-openembedded/meta-oe/recipes-multimedia/v4l2apps/v4l-utils_1.26.1.bb",
                false,
            ),
            (
                "meta-openembedded/meta-oe/recipes-support/htop/htop_3.3.0.bb",
                true,
            ),
            (
                "meta-openembedded/meta-oe/recipes-connectivity/gammu/gammu_1.42.0.bb",
                true,
            ),
            (
                "meta-openembedded/meta-oe/recipes-core/glib-2.0/glib-2.0_%.bbappend",
                true,
            ),
            (
                "openembedded-core/meta/recipes-support/libgpg-error/libgpg-error_1.48.bb",
                false,
            ),
            (
                "openembedded-core/meta/recipes-connectivity/openssh/openssh_9.6p1.bb",
                false,
            ),
        ];
        let script = format!(
            "import re, sys\nm = re.compile(r'{}')\nfor line in sys.stdin.read().splitlines():\n    print(bool(m.search(line)))\n",
            meta_oe_mask()
        );
        let mut child = Command::new("python3")
            .args(["-c", &script])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("python3");
        let input: Vec<String> = cases.iter().map(|(p, _)| format!("{src}/{p}")).collect();
        std::io::Write::write_all(child.stdin.as_mut().unwrap(), input.join("\n").as_bytes()).unwrap();
        drop(child.stdin.take());
        let out = child.wait_with_output().unwrap();
        assert!(out.status.success());
        let got: Vec<bool> = String::from_utf8_lossy(&out.stdout)
            .lines()
            .map(|l| l == "True")
            .collect();
        let want: Vec<bool> = cases.iter().map(|(_, m)| *m).collect();
        assert_eq!(got, want, "{cases:?}");
    }

    #[test]
    fn an_unprovided_dependency_points_at_the_mask() {
        assert!(mask_hint("ERROR: Nothing PROVIDES 'htop'").contains("META_OE_USED"));
        assert!(mask_hint("ERROR: Nothing RPROVIDES 'htop'").contains("META_OE_USED"));
        assert_eq!(mask_hint("ERROR: ParseError at x.bb:3"), "");
    }

    #[test]
    fn conf_block_is_replaced_not_duplicated() {
        let base = "CONF_VERSION = \"2\"\n";
        let once = with_block(base, "MACHINE = \"a\"");
        assert_eq!(once, format!("{base}{BEGIN}\nMACHINE = \"a\"\n{END}\n"));
        let twice = with_block(&once, "MACHINE = \"b\"");
        assert_eq!(twice, format!("{base}{BEGIN}\nMACHINE = \"b\"\n{END}\n"));
    }

    #[test]
    fn layer_recipes_and_skip_reasons_are_read() {
        let show = "NOTE: Starting bitbake server...\nLoading cache...done.\n\
                    === Matching recipes: ===\n\
                    irtrack-image:\n  meta-irtrack         1.0\n\
                    irtrackd:\n  meta-irtrack         0.1.0+git (skipped: missing required distro feature 'systemd')\n\
                    zlib:\n  core                 1.3.1\n";
        let r = layer_recipes(show, "meta-irtrack");
        assert_eq!(
            r,
            vec![
                ("irtrack-image".to_string(), None),
                (
                    "irtrackd".to_string(),
                    Some("missing required distro feature 'systemd'".to_string())
                )
            ]
        );
    }

    #[test]
    fn bitbake_error_lines_are_extracted() {
        let out = util::Output {
            status: None,
            timed_out: false,
            stdout: "Parsing recipes...\nERROR: ParseError at /l/ci-broken_1.0.bb:3: unparsed line: 'x'\n"
                .into(),
            stderr: "Summary: There was 1 ERROR message, returning a non-zero exit code.\n".into(),
        };
        assert_eq!(
            bitbake_errors(&out),
            "ERROR: ParseError at /l/ci-broken_1.0.bb:3: unparsed line: 'x'"
        );
    }

    #[test]
    fn bitbake_exception_details_are_kept() {
        let out = util::Output {
            status: None,
            timed_out: false,
            stdout: "Parsing recipes...WARNING: x.bb: Exception during build_dependencies\n\
                     ERROR: ExpansionError during parsing /l/irtrackd_git.bb\n\
                     bb.data_smart.ExpansionError: ... NetworkAccess: Network access disabled\n\
                     \n\
                     ERROR: Parsing halted due to errors, see error messages above\n\
                     \n\
                     Summary: There were 2 ERROR messages, returning a non-zero exit code.\n"
                .into(),
            stderr: String::new(),
        };
        assert_eq!(
            bitbake_errors(&out),
            "ERROR: ExpansionError during parsing /l/irtrackd_git.bb\n\
             bb.data_smart.ExpansionError: ... NetworkAccess: Network access disabled\n\
             ERROR: Parsing halted due to errors, see error messages above"
        );
    }

    #[test]
    fn exported_values_are_read_from_bitbake_e() {
        let dump = "# comment\nexport CARGO_HOME=\"/x\"\nCARGO_BUILD_FLAGS=\"-v --frozen -p irtrack-firmware --features cluster\"\nOTHER=\"1\"\n";
        assert_eq!(
            exported_value(dump, "CARGO_BUILD_FLAGS").as_deref(),
            Some("-v --frozen -p irtrack-firmware --features cluster")
        );
        assert_eq!(exported_value(dump, "MISSING"), None);
    }

    #[test]
    fn srcrev_is_read_from_the_recipe() {
        let r = "PV = \"0.1.0+git\"\n# SRCREV in a comment\nSRCREV = \"0123456789abcdef0123456789abcdef01234567\"\n";
        assert_eq!(
            pinned_srcrev(r).as_deref(),
            Some("0123456789abcdef0123456789abcdef01234567")
        );
        assert_eq!(pinned_srcrev("SRCREV_FORMAT = \"x\"\n"), None);
    }

    #[test]
    fn the_layers_ab_layout_agrees_and_disagreements_are_named() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        let layer = root.join("yocto-layer").join(LAYER);
        let wks = fs::read_to_string(layer.join(AB_WKS)).unwrap();
        let conf = fs::read_to_string(layer.join(AB_SYSTEM_CONF)).unwrap();
        let fw_env = fs::read_to_string(root.join("image/update/rootfs/etc/fw_env.config")).unwrap();
        ab_layout_agrees(&wks, &conf, &fw_env).unwrap();
        let parts = wks_partitions(&wks);
        assert_eq!(parts.len(), 4);
        assert_eq!(
            parts[0],
            WksPart {
                mount: Some("/uboot".into()),
                fstype: Some("vfat".into()),
                label: Some("boot".into())
            }
        );
        assert_eq!(parts[2].mount, None);
        // Slots swapped in system.conf, the boot partition mounted elsewhere, the data
        // partition missing: each is refused, naming what disagrees.
        let swapped = conf
            .replace("bootname=A", "bootname=X")
            .replace("bootname=B", "bootname=A");
        let e = ab_layout_agrees(&wks, &swapped, &fw_env).unwrap_err().to_string();
        assert!(e.contains("slots"), "{e}");
        let e = ab_layout_agrees(&wks.replace("part /uboot", "part /boot"), &conf, &fw_env)
            .unwrap_err()
            .to_string();
        assert!(e.contains("mounted on /boot"), "{e}");
        let no_data: String = wks
            .lines()
            .filter(|l| !l.contains("/data"))
            .map(|l| format!("{l}\n"))
            .collect();
        let e = ab_layout_agrees(&no_data, &conf, &fw_env)
            .unwrap_err()
            .to_string();
        assert!(e.contains("partition 4"), "{e}");
    }

    #[test]
    fn files_installed_from_the_source_tree_are_listed() {
        let recipe = "do_install() {\n    install -m 0644 ${S}/image/a.conf ${D}${sysconfdir}/a.conf\n    \
                      cat ${WORKDIR}/x ${S}/image/b.cmd > ${B}/b\n    install ${S}/image/a.conf ${D}/y\n}\n";
        assert_eq!(files_from_source(recipe), vec!["image/a.conf", "image/b.cmd"]);
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        let update = fs::read_to_string(root.join("yocto-layer").join(LAYER).join(UPDATE_RECIPE)).unwrap();
        let files = files_from_source(&update);
        assert!(files.iter().any(|f| f == "image/update/boot.cmd"), "{files:?}");
        for f in &files {
            assert!(
                root.join(f).is_file(),
                "{f} is installed by irtrack-update but not in the tree"
            );
        }
    }

    #[test]
    fn snapshots_are_found_beside_the_checkout_or_reported_missing() {
        let base = std::env::temp_dir().join(format!("xtask-yocto-snapshots-{}", std::process::id()));
        let root = base.join("work/checkout");
        fs::create_dir_all(&root).unwrap();
        let err = find_snapshots(&root, None).unwrap_err().to_string();
        assert!(err.contains("snapshots are missing"), "{err}");
        assert!(
            err.contains(&base.join("work/shared/yocto").display().to_string()),
            "{err}"
        );
        let shared = base.join("work/shared/yocto");
        fs::create_dir_all(&shared).unwrap();
        fs::write(shared.join("SHA256SUMS"), "").unwrap();
        let err = find_snapshots(&root, None).unwrap_err().to_string();
        assert!(err.contains("missing bitbake-2.8.tar.xz"), "{err}");
        for (f, _) in TARBALLS {
            fs::write(shared.join(f), "").unwrap();
        }
        assert_eq!(find_snapshots(&root, None).unwrap(), shared);
        let err = find_snapshots(&root, Some(base.join("nowhere")))
            .unwrap_err()
            .to_string();
        fs::remove_dir_all(&base).unwrap();
        assert!(err.contains(SNAPSHOTS_ENV) && err.contains("SHA256SUMS"), "{err}");
    }
}
