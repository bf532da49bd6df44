//! The survey under the installation's safety limits: the board's `[robot.safety]` section,
//! the survey box checked against its workspace, and every target judged by irtrack-robot's
//! `Supervisor` before it is sent.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, bail, ensure};
use irtrack_core::robot_proto::HoldReason;
use irtrack_core::stream::TrackStatus;
use irtrack_robot::safety::{SafetyConfig, Sample, Supervisor, Verdict};
use nalgebra::Vector3;

use super::Args;

/// Reads the `[robot.safety]` limits from the board's irtrackd config (its `[robot]` section,
/// parsed and validated by irtrack-robot with irtrackd's keys).
pub fn load_safety(path: &Path) -> anyhow::Result<SafetyConfig> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--safety {}: cannot read the irtrackd config", path.display()))?;
    let robot = irtrack_robot::robot_section(&text, &path.display().to_string())
        .with_context(|| format!("--safety {}: cannot load the irtrackd config", path.display()))?;
    let robot = robot.with_context(|| {
        format!(
            "--safety {}: the file has no [robot.safety] section (the survey runs only under the \
             installation's safety limits: give the board's irtrackd.toml)",
            path.display()
        )
    })?;
    Ok(robot.safety)
}

/// Applies the safety limits to the arguments before anything moves: the survey box must lie
/// inside the workspace, and the step and rotation limits become the smaller of the CLI's and the
/// configured ones. Returns what was tightened, for the log.
pub fn apply_safety(args: &mut Args, cfg: &SafetyConfig) -> anyhow::Result<Vec<String>> {
    const AXES: [&str; 3] = ["x", "y", "z"];
    for (i, axis) in AXES.iter().enumerate() {
        ensure!(
            args.box_min[i] >= cfg.workspace_min_mm[i] && args.box_max[i] <= cfg.workspace_max_mm[i],
            "the survey box leaves the [robot.safety] workspace on axis {}: box {}..{} mm, \
             workspace {}..{} mm; nothing was moved",
            axis,
            args.box_min[i],
            args.box_max[i],
            cfg.workspace_min_mm[i],
            cfg.workspace_max_mm[i]
        );
    }
    let mut notes = Vec::new();
    if cfg.max_step_mm < args.max_step_mm {
        notes.push(format!(
            "step limit {} mm ([robot.safety] max_step_mm) instead of --max-step-mm {}",
            cfg.max_step_mm, args.max_step_mm
        ));
        args.max_step_mm = cfg.max_step_mm;
    }
    if cfg.max_rotation_step_deg < args.max_rotation_step_deg {
        notes.push(format!(
            "rotation step limit {}° ([robot.safety] max_rotation_step_deg) instead of \
             --max-rotation-step-deg {}",
            cfg.max_rotation_step_deg, args.max_rotation_step_deg
        ));
        args.max_rotation_step_deg = cfg.max_rotation_step_deg;
    }
    Ok(notes)
}

/// irtrackd's safety supervisor in front of the survey's robot link: every target is judged as a
/// tracker sample would be in live following before it goes out.
///
/// Timestamps: a survey target is not a tracked position, so its "capture time" is the monotonic
/// time at which the survey commits to sending it (age 0, hence never stale). The supervisor's
/// speed rule then measures the distance between consecutive targets over the time between
/// their sends. Every target is a fine point (the next one is sent only after the robot reported
/// the previous one reached), so this is the rate at which the survey commands motion, and it is
/// bounded by how fast the robot actually travelled the previous, equally long, segment of a
/// split move; the robot's own travel speed is set by its controller (RAPID survey mode,
/// robot-sim `--speed-mm-s`), which this check cannot see ahead of time.
pub struct SafetyGate {
    sup: Supervisor,
    t0: Instant,
    /// The step reference, for the message: the last target sent, else the robot's TCP.
    last_mm: [f64; 3],
}

impl SafetyGate {
    /// Connected: the step reference is the robot's reported TCP; then armed (the survey is the
    /// operator's explicit start).
    pub fn new(cfg: SafetyConfig, robot_pos_mm: [f64; 3]) -> Self {
        let mut sup = Supervisor::new(cfg);
        sup.on_connect(robot_pos_mm);
        sup.enable();
        SafetyGate {
            sup,
            t0: Instant::now(),
            last_mm: robot_pos_mm,
        }
    }

    /// The robot reported its TCP (after a point was reached).
    pub fn on_robot_position(&mut self, pos_mm: [f64; 3]) {
        self.sup.on_robot_position(pos_mm);
    }

    /// Judges one target now; `Ok` means it may be sent (and is recorded as sent).
    pub fn check(&mut self, pos_mm: [f64; 3], quat_wxyz: [f64; 4]) -> anyhow::Result<()> {
        // +1: a capture time of 0 would look like "before the previous target".
        let now_ns = self.t0.elapsed().as_nanos() as u64 + 1;
        let sample = Sample {
            frame: 0,
            capture_ts_ns: now_ns,
            position_mm: Some(pos_mm),
            orientation_wxyz: Some(quat_wxyz),
            gap_mm: 0.0,
            status: TrackStatus::Ok,
            world_frame: true,
        };
        match self.sup.check(&sample, now_ns, true) {
            Verdict::Send { pos_mm, quat_wxyz } => {
                self.sup.committed(pos_mm, quat_wxyz, now_ns);
                self.last_mm = pos_mm;
                Ok(())
            }
            Verdict::Hold(reason) => bail!(
                "the safety supervisor ([robot.safety]) held target [{:.2}, {:.2}, {:.2}] mm \
                 ({:.2} mm from [{:.2}, {:.2}, {:.2}]): {} ({reason:?}); the survey stopped and \
                 the robot was left where it is",
                pos_mm[0],
                pos_mm[1],
                pos_mm[2],
                Vector3::from(pos_mm).metric_distance(&Vector3::from(self.last_mm)),
                self.last_mm[0],
                self.last_mm[1],
                self.last_mm[2],
                hold_text(reason)
            ),
        }
    }
}

fn hold_text(r: HoldReason) -> &'static str {
    match r {
        HoldReason::Workspace => "outside the workspace",
        HoldReason::StepTooLarge => "step or rotation from the previous target too large",
        HoldReason::TooFast => "implied speed above max_speed_mm_s",
        HoldReason::PoorQuality => "poor quality",
        HoldReason::Stale => "stale",
        HoldReason::MarkerLost => "marker lost",
        HoldReason::NotEnabled => "not enabled",
        HoldReason::Deadman => "deadman released",
        HoldReason::Stop => "stop",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    use crate::cmd::survey::plan::split_move;
    use crate::cmd::survey::test_support::{args, safety_cfg};

    #[test]
    fn safety_refuses_a_box_outside_the_workspace_and_tightens_steps() {
        let mut a = args();
        let notes = apply_safety(&mut a, &safety_cfg()).unwrap();
        assert_eq!((a.max_step_mm, a.max_rotation_step_deg), (20.0, 5.0));
        assert_eq!(notes.len(), 2, "{notes:?}");
        assert!(notes[0].contains("max_step_mm"), "{notes:?}");
        let mut a = args();
        a.box_max[2] = 550.0;
        let e = apply_safety(&mut a, &safety_cfg()).unwrap_err().to_string();
        assert!(
            e.contains("axis z") && e.contains("550") && e.contains("500"),
            "{e}"
        );
        // The CLI's smaller limits stay.
        let mut a = args();
        a.max_step_mm = 5.0;
        assert!(apply_safety(&mut a, &safety_cfg()).unwrap().len() == 1);
        assert_eq!(a.max_step_mm, 5.0);
    }

    #[test]
    fn safety_file_without_a_robot_section_is_refused() {
        let p = std::env::temp_dir().join(format!("survey-safety-{}.toml", std::process::id()));
        std::fs::write(&p, "[leds]\nbackend = \"none\"\n").unwrap();
        let e = format!("{:#}", load_safety(&p).unwrap_err());
        let _ = std::fs::remove_file(&p);
        assert!(e.contains("no [robot.safety] section"), "{e}");
    }

    #[test]
    fn safety_gate_passes_split_moves_and_holds_what_the_supervisor_holds() {
        let q = [0.0, 0.0, 1.0, 0.0];
        let start = [500.0, 0.0, 300.0];
        // Split to the limits, a move inside the workspace passes target by target.
        let mut gate = SafetyGate::new(safety_cfg(), start);
        for (p, q) in split_move((start, q), ([520.0, 30.0, 320.0], q), 20.0, 5.0) {
            gate.check(p, q).unwrap();
            std::thread::sleep(Duration::from_millis(100));
        }
        // A step the supervisor's limit forbids (e.g. a split with a larger CLI step) is held.
        let mut gate = SafetyGate::new(safety_cfg(), start);
        let moves = split_move((start, q), ([560.0, 0.0, 300.0], q), 30.0, 5.0);
        let e = gate.check(moves[0].0, moves[0].1).unwrap_err().to_string();
        assert!(e.contains("StepTooLarge") && e.contains("stopped"), "{e}");
        // And a target outside the workspace (the robot may start outside the box).
        let mut gate = SafetyGate::new(safety_cfg(), [690.0, 0.0, 300.0]);
        let e = gate.check([710.0, 0.0, 300.0], q).unwrap_err().to_string();
        assert!(e.contains("Workspace"), "{e}");
        // And targets commanded faster than max_speed_mm_s.
        let mut gate = SafetyGate::new(safety_cfg(), start);
        gate.check([510.0, 0.0, 300.0], q).unwrap();
        let e = gate.check([520.0, 0.0, 300.0], q).unwrap_err().to_string();
        assert!(e.contains("TooFast"), "{e}");
    }
}
