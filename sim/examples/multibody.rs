//! Issue 29's multi-body runs from the command line (figures only):
//! `cargo run --release -p irtrack-sim --example multibody -- [pair|four] [seconds]`.

use irtrack_core::pose6d::PoseConfig;
use irtrack_sim::multibody::{FPS, four_camera_rig, missed_targets, ninety_degree_pair, report, run};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let which = args.first().map_or("pair", String::as_str);
    let seconds: f64 = args.get(1).map_or(Ok(60.0), |s| s.parse())?;
    let rig = match which {
        "four" => four_camera_rig()?,
        _ => ninety_degree_pair(),
    };
    let r = run(rig, (seconds * FPS) as u64, PoseConfig::default())?;
    print!("{}", report(which, &r));
    for m in missed_targets(which, &r) {
        println!("  MISSED: {m}");
    }
    Ok(())
}
