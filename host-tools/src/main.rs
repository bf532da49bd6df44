//! `host-tools`: the PC side of irtrack. Thin dispatch over `irtrack_host_tools::cmd`.

use clap::{Parser, Subcommand};
use irtrack_host_tools::cmd;

#[derive(Parser)]
#[command(name = "host-tools", version, about = "irtrack PC tools")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a simulated scenario (frames, calibration, truth) to a directory.
    Simulate(cmd::simulate::Args),
    /// Run the tracking pipeline offline on recorded frames.
    Track(cmd::track::Args),
    /// Analytic resolution planner for a rig.
    Plan(cmd::plan::Args),
    /// Accuracy study: simulated rigs vs the paper's Table I.
    Accuracy(cmd::accuracy::Args),
    /// Calibrate cameras from checkerboard images (OpenCV).
    Calibrate(cmd::calibrate::Args),
    /// Send a parameter blob to irtrackd.
    PushParams(cmd::push_params::Args),
    /// Print a parameter blob or calibration YAML in readable form.
    ShowParams(cmd::show_params::Args),
    /// Convert between parameter blobs and OpenCV YAML; --placement places the cameras on boards.
    ConvertParams(cmd::convert_params::Args),
    /// Simulated robot controller (robot side of the robot protocol).
    RobotSim(cmd::robot_sim::Args),
    /// Record a path from irtrackd's position stream.
    Record(cmd::record::Args),
    /// Filter, simplify and export a recorded path.
    Path(cmd::path::Args),
    /// Tracker-to-robot registration from corresponding points.
    Register(cmd::register::Args),
    /// Cell survey with the robot: grid, registration, TRE and a pass/fail report.
    Survey(cmd::survey::Args),
    /// Create a signing key pair for parameter blobs.
    Keygen(cmd::keygen::Args),
    /// Passwords for the camera boards and the solver's dictionary (cluster transport).
    ClusterKeys(cmd::cluster_keys::Args),
    /// Measure a multi-LED tool's layout from frames of it held still; adds it to the parameters.
    MeasureTool(cmd::measure_tool::Args),
    /// Pivot calibration: the tip of a 6-DOF tool from poses of it turned about its tip.
    Pivot(cmd::pivot::Args),
    /// Save synchronised frame sets from irtrackd for calibration (checkerboard or wand).
    Capture(cmd::capture::Args),
    /// Camera poses (and optionally intrinsics) from a wave of a collinear LED wand.
    WandCalibrate(cmd::wand_calibrate::Args),
    /// Field updates of a board: `update push` uploads a signed bundle and installs it.
    Update(cmd::update::Args),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Simulate(a) => cmd::simulate::run(a),
        Command::Track(a) => cmd::track::run(a),
        Command::Plan(a) => cmd::plan::run(a),
        Command::Accuracy(a) => cmd::accuracy::run(a),
        Command::Calibrate(a) => cmd::calibrate::run(a),
        Command::PushParams(a) => cmd::push_params::run(a),
        Command::ShowParams(a) => cmd::show_params::run(a),
        Command::ConvertParams(a) => cmd::convert_params::run(a),
        Command::RobotSim(a) => cmd::robot_sim::run(a),
        Command::Record(a) => cmd::record::run(a),
        Command::Path(a) => cmd::path::run(a),
        Command::Register(a) => cmd::register::run(a),
        Command::Survey(a) => cmd::survey::run(a),
        Command::Keygen(a) => cmd::keygen::run(a),
        Command::ClusterKeys(a) => cmd::cluster_keys::run(a),
        Command::MeasureTool(a) => cmd::measure_tool::run(a),
        Command::Pivot(a) => cmd::pivot::run(a),
        Command::Capture(a) => cmd::capture::run(a),
        Command::WandCalibrate(a) => cmd::wand_calibrate::run(a),
        Command::Update(a) => cmd::update::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            // As anyhow's own report from main, with a command's own exit code where it has one
            // (`update push --reboot`: 3 rolled back, 4 not back in time).
            eprintln!("Error: {e:?}");
            let code = e.downcast_ref::<cmd::update::PushExit>().map_or(1, |x| x.code);
            std::process::ExitCode::from(code)
        }
    }
}
