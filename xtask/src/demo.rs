//! `cargo xtask demo`: the whole system on simulated cameras, as a list of steps.
//!
//! Every step says what it does before running it. A step whose subcommand is not
//! implemented yet stops the demo with that message: the demo never pretends.
//! Extend it by adding entries to [`steps`]; `{out}` in arguments is the demo's output
//! directory (`out/demo` under the repository root).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

use crate::util::{self, Ctx, RunOpts};

/// What a step runs.
enum Action {
    /// `host-tools <args...>`.
    HostTools(&'static [&'static str]),
    /// Checkerboard views -> `host-tools calibrate` -> `push-params` into a running irtrackd
    /// ([`crate::demo_live::calibrate_and_push`]).
    CalibrateAndPush,
    /// Capture a wand wave from irtrackd and calibrate with it ([`crate::demo_live`]).
    WandCalibration,
    /// irtrackd on simulated cameras driving `host-tools robot-sim` ([`crate::demo_live`]).
    RobotFollows,
    /// The cell survey: robot-sim carries the LED, `host-tools survey` ([`crate::demo_live::survey`]).
    Survey,
    /// irtrackd on simulated cameras; headless Chromium saves a picture of its set-up page
    /// ([`crate::demo_view`]).
    SetupView,
    /// irtrackd's NatNet and ROS 2 outputs read by independent clients
    /// ([`crate::demo_outputs`]).
    StandardOutputs,
    /// Two camera boards and a solver (irtrackd with the `cluster` feature), positions against
    /// the simulator's truth ([`run_cluster`]).
    Cluster,
}

struct Step {
    title: &'static str,
    /// One or two sentences for the person watching.
    explain: &'static str,
    action: Action,
    /// Files (relative to `{out}`) the step must leave behind, non-empty.
    produces: &'static [&'static str],
}

fn steps() -> Vec<Step> {
    vec![
        Step {
            title: "simulate",
            explain: "Render a simulated two-camera rig watching an IR LED move along a trajectory: \
                      frames per camera, the rig's calibration and the ground truth.",
            action: Action::HostTools(&["simulate", "--out", "{out}/scenario"]),
            produces: &["scenario/truth.csv", "scenario/rig.irp"],
        },
        Step {
            title: "track",
            explain: "Run the board's pipeline offline on those frames: blob centroids, undistortion, \
                      triangulation; one 3-D position (or 'missing') per frame.",
            action: Action::HostTools(&[
                "track",
                "--frames",
                "{out}/scenario",
                "--params",
                "{out}/scenario/rig.irp",
                "--out",
                "{out}/positions.csv",
            ]),
            produces: &["positions.csv"],
        },
        Step {
            title: "plan",
            explain: "Analytic resolution of the parallel and the 90-degree convergent rig over the \
                      workspace (the paper's Table I).",
            action: Action::HostTools(&["plan"]),
            produces: &[],
        },
        Step {
            title: "calibrate and push",
            explain: "Calibrate the simulated 90-degree rig from rendered checkerboard images with \
                      OpenCV, push the result (signed) into irtrackd running on that rig without \
                      parameters, and watch the positions appear, compared with the simulator.",
            action: Action::CalibrateAndPush,
            produces: &["calib/rig.irp", "calib/report.md"],
        },
        Step {
            title: "wand calibration (capture, then wand)",
            explain: "Wave a simulated LED wand in front of the same 90-degree rig served by irtrackd, \
                      save the frame sets with `host-tools capture --wand`, calibrate the rig with \
                      `host-tools wand-calibrate` and compare both calibrations with the truth.",
            action: Action::WandCalibration,
            produces: &["wand/rig.irp", "wand/report.md", "wand/coverage_cam0.png"],
        },
        Step {
            title: "robot follows the marker",
            explain: "Start the board service irtrackd on simulated cameras and a simulated robot \
                      controller; enable motion over irtrackd's control endpoint and watch the robot \
                      follow the marker within the safety limits.",
            action: Action::RobotFollows,
            produces: &["robot/robot-sim.csv"],
        },
        Step {
            title: "cell survey",
            explain: "Fix the LED to the simulated robot's flange (a robot with 0.02 mm repeatability \
                      and a 0.3 mm absolute error field), drive it through a grid with \
                      `host-tools survey`, register tracker to robot base, solve the LED's offset \
                      from turned visits and report FRE/TRE with pass/fail.",
            action: Action::Survey,
            produces: &["survey/report/survey.md", "survey/report/error-vs-distance.png"],
        },
        Step {
            title: "standard outputs (NatNet, ROS 2)",
            explain: "Start irtrackd on simulated cameras with its NatNet and ROS 2 outputs; PyPI's \
                      NatNet client and a Cyclone DDS subscriber (PyPI cyclonedds + rosbags), each a \
                      separate process, print the tool's live poses beside irtrackd's own stream.",
            action: Action::StandardOutputs,
            produces: &["outputs/poses.md"],
        },
        Step {
            title: "set-up view",
            explain: "Start irtrackd on simulated cameras and open its set-up page (http://BOARD:7704/ \
                      on a board) in headless Chromium: live previews with the blob overlay, \
                      controls, health and the 3-D view; save a screenshot.",
            action: Action::SetupView,
            produces: &["setup-view.png"],
        },
        Step {
            title: "more cameras than one board",
            explain: "Build irtrackd with the `cluster` feature (Zenoh) and start two simulated camera \
                      boards (cameras 0-1, and camera 2 alone) and a solver that owns camera 3 of \
                      a four-camera ring: the boards publish their blobs, the solver pairs them \
                      with its own camera's and triangulates all four; its positions are printed \
                      against the simulator's truth, then the one-camera board is stopped.",
            action: Action::Cluster,
            produces: &["cluster/solver.log", "cluster/b0.log", "cluster/b1.log"],
        },
    ]
}

/// `cargo xtask demo`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Leave out the setup step.
    #[arg(long)]
    pub skip_setup: bool,
    /// Only irtrackd and its set-up page, until Ctrl-C.
    #[arg(long)]
    pub view: bool,
    /// Internal: the standard-outputs step's live part inside its network namespace
    /// (`unshare -rn`), with the directory holding irtrackd.
    #[arg(long, hide = true, value_name = "BIN_DIR")]
    pub outputs_in_netns: Option<PathBuf>,
}

pub fn run(ctx: &Ctx, args: &Args) -> Result<()> {
    let (skip_setup, view) = (args.skip_setup, args.view);
    if let Some(bin_dir) = &args.outputs_in_netns {
        return crate::demo_outputs::inside_netns(bin_dir, &ctx.root.join("out/demo"));
    }
    if view {
        return run_view(ctx, skip_setup);
    }
    let out_dir = ctx.root.join("out/demo");
    let steps = steps();
    let total = steps.len() + 2;

    banner(
        1,
        total,
        "setup",
        "Install missing system packages (skipped when all are present).",
    );
    if skip_setup {
        println!("skipped (--skip-setup)");
    } else {
        crate::setup::run(ctx)?;
    }

    banner(
        2,
        total,
        "build",
        "Build the PC tools (host-tools), the board service (irtrackd) and the checkerboard \
         renderer (an example of irtrack-tests).",
    );
    let host_tools = build_host_tools(ctx)?;
    let views_bin = views_tool(ctx)?;
    std::fs::create_dir_all(&out_dir).with_context(|| format!("creating {}", out_dir.display()))?;

    for (i, step) in steps.iter().enumerate() {
        banner(i + 3, total, step.title, step.explain);
        match &step.action {
            Action::HostTools(argv) => {
                let argv: Vec<String> = argv.iter().map(|a| expand(a, &out_dir)).collect();
                let mut cmd = Command::new(&host_tools);
                cmd.args(&argv).current_dir(&ctx.root);
                let out = util::run(
                    &mut cmd,
                    RunOpts {
                        capture_stderr: true,
                        ..RunOpts::default()
                    },
                )?;
                if !out.success() {
                    bail!(
                        "{}",
                        explain_failure(&format!("host-tools {}", argv[0]), &out.stderr, &out.describe())
                    );
                }
            }
            Action::CalibrateAndPush => crate::demo_live::calibrate_and_push(
                &crate::demo_live::bin_dir(&host_tools),
                &views_bin,
                &out_dir,
            )?,
            Action::RobotFollows => {
                crate::demo_live::robot_follows(&crate::demo_live::bin_dir(&host_tools), &out_dir)?
            }
            Action::Survey => crate::demo_live::survey(&crate::demo_live::bin_dir(&host_tools), &out_dir)?,
            Action::WandCalibration => {
                crate::demo_live::wand_calibration(&crate::demo_live::bin_dir(&host_tools), &out_dir)?
            }
            Action::SetupView => {
                crate::demo_view::screenshot(&crate::demo_live::bin_dir(&host_tools), &out_dir)?
            }
            Action::StandardOutputs => {
                crate::demo_outputs::standard_outputs(&crate::demo_live::bin_dir(&host_tools), &out_dir)?
            }
            Action::Cluster => run_cluster(ctx, &out_dir)?,
        }
        for rel in step.produces {
            let p = out_dir.join(rel);
            let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
            if len == 0 {
                bail!(
                    "step `{}` finished but did not produce {}",
                    step.title,
                    p.display()
                );
            }
            println!("produced {} ({len} bytes)", p.display());
        }
    }
    println!("\ndemo: all {total} steps done; outputs in {}", out_dir.display());
    Ok(())
}

/// `--view`: setup, build, then irtrackd on simulated cameras with its page until Ctrl-C.
fn run_view(ctx: &Ctx, skip_setup: bool) -> Result<()> {
    banner(
        1,
        3,
        "setup",
        "Install missing system packages (skipped when all are present).",
    );
    if skip_setup {
        println!("skipped (--skip-setup)");
    } else {
        crate::setup::run(ctx)?;
    }
    banner(
        2,
        3,
        "build",
        "Build the board service (irtrackd) and the PC tools.",
    );
    let host_tools = build_host_tools(ctx)?;
    let out_dir = ctx.root.join("out/demo");
    banner(
        3,
        3,
        "set-up view",
        "Run irtrackd on simulated cameras and keep it running: open the printed address in \
         a browser.",
    );
    crate::demo_view::view(&crate::demo_live::bin_dir(&host_tools), &out_dir)
}

fn banner(i: usize, n: usize, title: &str, explain: &str) {
    println!("\n==> demo step {i}/{n}: {title}\n    {explain}");
}

fn expand(arg: &str, out_dir: &Path) -> String {
    arg.replace("{out}", &out_dir.to_string_lossy())
}

/// Turns a failed step into a message that says plainly whether the feature is missing.
fn explain_failure(what: &str, stderr: &str, how: &str) -> String {
    if stderr.contains("not implemented") {
        format!("DEMO INCOMPLETE: `{what}` is not implemented yet ({how})")
    } else if stderr.contains("unexpected argument") || stderr.contains("unrecognized subcommand") {
        format!(
            "DEMO INCOMPLETE: `{what}` does not accept the demo's arguments yet ({how}); \
             either it is not implemented or its interface changed (update xtask/src/demo.rs)"
        )
    } else {
        format!("`{what}` failed ({how}); see its output above")
    }
}

/// Everything the demo runs, in one cargo invocation with one feature set and one profile:
/// `host-tools`, `irtrackd` (ROS 2 output for the standard-outputs step, `cluster` for the
/// camera-board and solver roles), the checkerboard renderer and the cluster demo (examples of
/// irtrack-tests; xtask itself may not depend on the simulator). Two invocations that differ
/// only in features compile the shared dependency graph twice (Zenoh alone is ~200 crates):
/// the first demo took over an hour that way (issue 42).
pub fn demo_build(ctx: &Ctx) -> Command {
    let mut cmd = ctx.cargo();
    cmd.args([
        "build",
        "-p",
        "irtrack-host-tools",
        "--bin",
        "host-tools",
        "-p",
        "irtrack-firmware",
        "--bin",
        "irtrackd",
        "-p",
        "irtrack-tests",
        "--example",
        "checkerboard_views",
        "--example",
        "cluster_demo",
        "--features",
        DEMO_FEATURES,
    ]);
    cmd
}

/// The features of [`demo_build`]. The examples bring in irtrack-tests' dev-dependencies
/// (irtrack-firmware with `mcap` and `ros2`), and its `cluster` feature turns on irtrackd's.
pub const DEMO_FEATURES: &str = "irtrack-tests/cluster,irtrack-firmware/ros2,irtrack-firmware/cluster";

fn build_host_tools(ctx: &Ctx) -> Result<PathBuf> {
    let mut cmd = demo_build(ctx);
    let out = util::run(&mut cmd, RunOpts::default())?;
    if !out.success() {
        bail!("building the demo's programs {}", out.describe());
    }
    let bin = ctx.target_dir().join("debug").join("host-tools");
    if !bin.is_file() {
        bail!("{} missing after a successful build", bin.display());
    }
    Ok(bin)
}

/// The checkerboard renderer [`demo_build`] built (dev profile, opt-level 1: fast enough to
/// render the views).
fn views_tool(ctx: &Ctx) -> Result<PathBuf> {
    let bin = ctx.target_dir().join("debug/examples/checkerboard_views");
    if !bin.is_file() {
        bail!("{} missing after a successful build", bin.display());
    }
    Ok(bin)
}

/// The host build of irtrackd with the `cluster` feature and the `cluster_demo` example, in
/// target/debug (the demo's step and the `cluster-qemu-user` phase's solver): the demo's one
/// build, so that after the demo's step 2 it compiles nothing.
pub fn cluster_host_build(ctx: &Ctx) -> Command {
    demo_build(ctx)
}

/// Runs the cluster demo (built with everything else in step 2; the build here is a no-op
/// check that nothing changed since).
fn run_cluster(ctx: &Ctx, out_dir: &Path) -> Result<()> {
    let mut cmd = cluster_host_build(ctx);
    let out = util::run(&mut cmd, RunOpts::default())?;
    if !out.success() {
        bail!("building irtrackd with the cluster feature {}", out.describe());
    }
    let bin = ctx.target_dir().join("debug/examples/cluster_demo");
    let mut cmd = Command::new(&bin);
    cmd.arg(out_dir.join("cluster")).current_dir(&ctx.root);
    let opts = RunOpts {
        timeout: Some(std::time::Duration::from_secs(120)),
        ..RunOpts::default()
    };
    let out = util::run(&mut cmd, opts)?;
    if !out.success() {
        bail!("the cluster demo {}; see its output above", out.describe());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failures_are_named_honestly() {
        let m = explain_failure(
            "host-tools plan",
            "Error: this subcommand is not implemented yet\n",
            "exit 1",
        );
        assert!(m.starts_with("DEMO INCOMPLETE"), "{m}");
        let m = explain_failure(
            "host-tools plan",
            "error: unexpected argument '--out' found\n",
            "exit 2",
        );
        assert!(m.contains("does not accept"), "{m}");
        let m = explain_failure("host-tools plan", "Error: file not found\n", "exit 1");
        assert!(!m.contains("INCOMPLETE"), "{m}");
    }

    #[test]
    fn out_placeholder_expands() {
        assert_eq!(
            expand("{out}/positions.csv", Path::new("/r/out/demo")),
            "/r/out/demo/positions.csv"
        );
        assert_eq!(expand("plan", Path::new("/x")), "plan");
    }

    #[test]
    fn every_step_has_a_title_and_explanation() {
        for s in steps() {
            assert!(!s.title.is_empty() && s.explain.len() > 20, "{}", s.title);
        }
    }
}
