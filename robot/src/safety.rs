//! Safety supervisor: pure logic deciding, for the newest tracker sample, whether a target may go
//! to the robot or the robot must hold. No I/O and no clock of its own, so every rule is testable.
//!
//! Rules, checked in this order: operator enable, deadman, marker present, quality (status and
//! ray gap), sample age, frame (world coordinates), workspace box, step from the previous target
//! (or from the robot's reported position after an enable), implied speed, and for 6-DOF samples
//! the orientation (a unit quaternion) and the rotation step from the previous oriented target.
//!
//! The robot reports only its TCP position, not its orientation, so the first oriented target
//! after an enable or a reconnect has no rotation reference; the operator enables with the tool
//! held at the robot's TCP, and from then on every target is checked against the previous one.
//!
//! Transient conditions (deadman, marker lost, poor quality, stale) hold only while they last;
//! resuming still has to pass the step check against the last target, so the robot never jumps.
//! Violations that indicate a wrong target (workspace, step, speed) latch: motion stays held until
//! the operator enables again.
//!
//! Reacquisition after a tracking gap (marker lost, poor quality, stale samples since the last
//! target): the tool moved on while it was not seen, so the first target after the gap may lie
//! up to `max_speed_mm_s × gap` from the last one (the gap counted up to
//! [`REACQUIRE_MAX_GAP_S`]) instead of `max_step_mm`; the implied speed and the rotation step
//! are checked as always. Within that, motion resumes without a new enable; beyond it the
//! jump latches as before.

use irtrack_core::robot_proto::HoldReason;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use serde::Deserialize;

fn default_true() -> bool {
    true
}

fn default_max_rotation_step_deg() -> f64 {
    10.0
}

/// `[robot.safety]`: limits of one installation.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SafetyConfig {
    /// Workspace box in the robot base frame (min corner).
    pub workspace_min_mm: [f64; 3],
    /// Workspace box (max corner).
    pub workspace_max_mm: [f64; 3],
    /// Largest distance between consecutive targets.
    pub max_step_mm: f64,
    /// Largest speed implied by consecutive targets and their capture times.
    pub max_speed_mm_s: f64,
    /// Largest ray gap accepted as good quality.
    pub max_gap_mm: f64,
    /// Oldest sample (capture to send) that may become a target.
    pub max_age_ms: u64,
    /// Only send positions the tracker reports in the registered world (robot) frame.
    #[serde(default = "default_true")]
    pub require_world_frame: bool,
    /// Largest rotation between consecutive oriented targets (degrees, 6-DOF `Q` targets).
    #[serde(default = "default_max_rotation_step_deg")]
    pub max_rotation_step_deg: f64,
}

impl SafetyConfig {
    /// Checks the limits are usable; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        for i in 0..3 {
            let (lo, hi) = (self.workspace_min_mm[i], self.workspace_max_mm[i]);
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(format!(
                    "robot.safety workspace axis {i}: min {lo} must be < max {hi}"
                ));
            }
        }
        let pos = |v: f64, k: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!("robot.safety.{k} = {v} must be > 0"))
            }
        };
        pos(self.max_step_mm, "max_step_mm")?;
        pos(self.max_speed_mm_s, "max_speed_mm_s")?;
        pos(self.max_gap_mm, "max_gap_mm")?;
        if !(self.max_rotation_step_deg > 0.0 && self.max_rotation_step_deg <= 180.0) {
            return Err(format!(
                "robot.safety.max_rotation_step_deg = {} must be in (0, 180]",
                self.max_rotation_step_deg
            ));
        }
        if self.max_age_ms == 0 {
            return Err("robot.safety.max_age_ms must be > 0".into());
        }
        Ok(())
    }
}

/// Longest tracking gap (s) that widens the step allowance on reacquisition: after a longer gap
/// the first target may still lie `max_speed_mm_s × REACQUIRE_MAX_GAP_S` away, no further.
pub const REACQUIRE_MAX_GAP_S: f64 = 0.5;

/// What the supervisor needs from a tracker record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// The tracker's frame-set number.
    pub frame: u64,
    /// CLOCK_MONOTONIC capture time (the clock the client's [`crate::Clock`] reads).
    pub capture_ts_ns: u64,
    /// The tracked position (mm); `None` when nothing was tracked.
    pub position_mm: Option<[f64; 3]>,
    /// The tool's orientation (w, x, y, z) for a 6-DOF sample.
    pub orientation_wxyz: Option<[f64; 4]>,
    /// Quality of the position: ray gap or RMS ray distance (mm); NaN when none.
    pub gap_mm: f64,
    /// The tracker's status for this set.
    pub status: TrackStatus,
    /// The position is in the robot's frame (a registration is applied).
    pub world_frame: bool,
}

impl From<&PositionRecord> for Sample {
    fn from(r: &PositionRecord) -> Self {
        Sample {
            frame: r.frame,
            capture_ts_ns: r.capture_ts_ns,
            position_mm: r.position_mm,
            orientation_wxyz: r.orientation_wxyz,
            gap_mm: r.gap_mm,
            status: r.status,
            world_frame: r.world_frame,
        }
    }
}

/// Decision for one sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Verdict {
    /// This position (and orientation, for a 6-DOF sample) may be sent as the next target.
    Send {
        /// The target position (mm).
        pos_mm: [f64; 3],
        /// The target orientation, for a 6-DOF sample.
        quat_wxyz: Option<[f64; 4]>,
    },
    /// The robot must hold.
    Hold(HoldReason),
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Angle (degrees) of the rotation between two unit quaternions; q and −q are the same rotation.
pub fn rotation_between_deg(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    (2.0 * dot.abs().min(1.0).acos()).to_degrees()
}

/// The supervisor's state: armed or not, and the last target that went out.
#[derive(Debug, Clone)]
pub struct Supervisor {
    cfg: SafetyConfig,
    armed: bool,
    /// Why motion is latched off (None while armed, NotEnabled after connect).
    latched: Option<HoldReason>,
    /// Last target sent and its capture time; steps and speed are measured from here.
    last_target: Option<([f64; 3], u64)>,
    /// Orientation of the last target when it was a 6-DOF one; the rotation step reference.
    last_orientation: Option<[f64; 4]>,
    /// Where the robot reported its TCP; the step reference right after an enable.
    robot_pos_mm: Option<[f64; 3]>,
    /// Samples were held for a tracking reason (lost, poor quality, stale) since the last
    /// target: the next target is a reacquisition.
    tracking_gap: bool,
}

impl Supervisor {
    /// A disarmed supervisor.
    pub fn new(cfg: SafetyConfig) -> Self {
        Self {
            cfg,
            armed: false,
            latched: Some(HoldReason::NotEnabled),
            last_target: None,
            last_orientation: None,
            robot_pos_mm: None,
            tracking_gap: false,
        }
    }

    /// The limits in force.
    pub fn config(&self) -> &SafetyConfig {
        &self.cfg
    }

    /// True when motion is enabled (no latched stop).
    pub fn is_armed(&self) -> bool {
        self.armed
    }

    /// Why motion is latched off, if it is.
    pub fn latched(&self) -> Option<HoldReason> {
        self.latched
    }

    /// New connection: disarmed until an explicit enable; the step reference is the robot's TCP.
    pub fn on_connect(&mut self, robot_pos_mm: [f64; 3]) {
        self.armed = false;
        self.latched = Some(HoldReason::NotEnabled);
        self.last_target = None;
        self.last_orientation = None;
        self.robot_pos_mm = Some(robot_pos_mm);
        self.tracking_gap = false;
    }

    /// The robot reported its position (credit line).
    pub fn on_robot_position(&mut self, pos_mm: [f64; 3]) {
        self.robot_pos_mm = Some(pos_mm);
    }

    /// Operator enable. The first target must then lie within `max_step_mm` of the robot's TCP:
    /// the operator brings the marker to the tool to "pick it up".
    pub fn enable(&mut self) {
        self.armed = true;
        self.latched = None;
        self.last_target = None;
        self.last_orientation = None;
        self.tracking_gap = false;
    }

    /// Operator disable or any latched stop.
    pub fn disarm(&mut self, reason: HoldReason) {
        self.armed = false;
        self.latched = Some(reason);
    }

    /// Judges the newest sample at `now_ns`. Latching rules disarm the supervisor.
    pub fn check(&mut self, s: &Sample, now_ns: u64, deadman_pressed: bool) -> Verdict {
        let v = self.judge(s, now_ns, deadman_pressed);
        if let Verdict::Hold(HoldReason::MarkerLost | HoldReason::PoorQuality | HoldReason::Stale) = v
            && self.armed
            && self.last_target.is_some()
        {
            self.tracking_gap = true;
        }
        v
    }

    /// Step allowance (mm) for a target captured at `capture_ts_ns`: `max_step_mm`, widened
    /// to `max_speed_mm_s × gap` on reacquisition after a tracking gap.
    fn step_allowance_mm(&self, capture_ts_ns: u64) -> f64 {
        match self.last_target {
            Some((_, t_ns)) if self.tracking_gap && capture_ts_ns > t_ns => {
                let gap_s = ((capture_ts_ns - t_ns) as f64 * 1e-9).min(REACQUIRE_MAX_GAP_S);
                self.cfg.max_step_mm.max(self.cfg.max_speed_mm_s * gap_s)
            }
            _ => self.cfg.max_step_mm,
        }
    }

    fn judge(&mut self, s: &Sample, now_ns: u64, deadman_pressed: bool) -> Verdict {
        if !self.armed {
            return Verdict::Hold(self.latched.unwrap_or(HoldReason::NotEnabled));
        }
        if !deadman_pressed {
            return Verdict::Hold(HoldReason::Deadman);
        }
        match s.status {
            TrackStatus::Ok => {}
            TrackStatus::Rejected => return Verdict::Hold(HoldReason::PoorQuality),
            TrackStatus::Lost | TrackStatus::NoParams | TrackStatus::Fault => {
                return Verdict::Hold(HoldReason::MarkerLost);
            }
        }
        let Some(p) = s.position_mm else {
            return Verdict::Hold(HoldReason::MarkerLost);
        };
        // NaN gap fails this comparison too: unknown quality is poor quality.
        if s.gap_mm.is_nan() || s.gap_mm > self.cfg.max_gap_mm || !p.iter().all(|v| v.is_finite()) {
            return Verdict::Hold(HoldReason::PoorQuality);
        }
        // A sample from the future (clock mix-up) is as untrustworthy as an old one.
        let age_ns = now_ns.checked_sub(s.capture_ts_ns);
        if age_ns.is_none_or(|a| a > self.cfg.max_age_ms * 1_000_000) {
            return Verdict::Hold(HoldReason::Stale);
        }
        if self.cfg.require_world_frame && !s.world_frame {
            // Camera-frame coordinates would send the robot somewhere meaningless.
            self.disarm(HoldReason::Workspace);
            return Verdict::Hold(HoldReason::Workspace);
        }
        let inside =
            (0..3).all(|i| p[i] >= self.cfg.workspace_min_mm[i] && p[i] <= self.cfg.workspace_max_mm[i]);
        if !inside {
            self.disarm(HoldReason::Workspace);
            return Verdict::Hold(HoldReason::Workspace);
        }
        let reference = self.last_target.map(|(q, _)| q).or(self.robot_pos_mm);
        let Some(reference) = reference else {
            return Verdict::Hold(HoldReason::NotEnabled);
        };
        let step = dist(p, reference);
        if step > self.step_allowance_mm(s.capture_ts_ns) {
            self.disarm(HoldReason::StepTooLarge);
            return Verdict::Hold(HoldReason::StepTooLarge);
        }
        if let Some((q, t_ns)) = self.last_target
            && s.capture_ts_ns > t_ns
        {
            let speed = dist(p, q) / ((s.capture_ts_ns - t_ns) as f64 * 1e-9);
            if speed > self.cfg.max_speed_mm_s {
                self.disarm(HoldReason::TooFast);
                return Verdict::Hold(HoldReason::TooFast);
            }
        }
        if let Some(q) = s.orientation_wxyz {
            let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            // The tracker emits unit quaternions; anything else is a corrupt sample.
            if !(q.iter().all(|v| v.is_finite()) && (norm - 1.0).abs() <= 1e-3) {
                return Verdict::Hold(HoldReason::PoorQuality);
            }
            if let Some(prev) = self.last_orientation
                && rotation_between_deg(&prev, &q) > self.cfg.max_rotation_step_deg
            {
                self.disarm(HoldReason::StepTooLarge);
                return Verdict::Hold(HoldReason::StepTooLarge);
            }
        }
        Verdict::Send {
            pos_mm: p,
            quat_wxyz: s.orientation_wxyz,
        }
    }

    /// Records that `pos_mm` (and `quat_wxyz` for a 6-DOF target), captured at `capture_ts_ns`,
    /// went out as a target.
    pub fn committed(&mut self, pos_mm: [f64; 3], quat_wxyz: Option<[f64; 4]>, capture_ts_ns: u64) {
        self.last_target = Some((pos_mm, capture_ts_ns));
        self.last_orientation = quat_wxyz;
        self.tracking_gap = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn cfg() -> SafetyConfig {
        SafetyConfig {
            workspace_min_mm: [-200.0, -200.0, 0.0],
            workspace_max_mm: [200.0, 200.0, 300.0],
            max_step_mm: 10.0,
            max_speed_mm_s: 200.0,
            max_gap_mm: 1.0,
            max_age_ms: 50,
            require_world_frame: true,
            max_rotation_step_deg: 5.0,
        }
    }

    fn sample(ts_ms: u64, p: [f64; 3]) -> Sample {
        Sample {
            frame: ts_ms,
            capture_ts_ns: ts_ms * 1_000_000,
            position_mm: Some(p),
            orientation_wxyz: None,
            gap_mm: 0.2,
            status: TrackStatus::Ok,
            world_frame: true,
        }
    }

    fn armed() -> Supervisor {
        let mut s = Supervisor::new(cfg());
        s.on_connect([0.0, 0.0, 100.0]);
        s.enable();
        s
    }

    const MS: u64 = 1_000_000;

    #[test]
    fn disarmed_until_enable_even_after_reconnect() {
        let mut s = Supervisor::new(cfg());
        s.on_connect([0.0, 0.0, 100.0]);
        let x = sample(100, [1.0, 0.0, 100.0]);
        assert_eq!(s.check(&x, 100 * MS, true), Verdict::Hold(HoldReason::NotEnabled));
        s.enable();
        assert_eq!(
            s.check(&x, 100 * MS, true),
            Verdict::Send {
                pos_mm: [1.0, 0.0, 100.0],
                quat_wxyz: None
            }
        );
        s.on_connect([0.0, 0.0, 100.0]);
        assert_eq!(s.check(&x, 100 * MS, true), Verdict::Hold(HoldReason::NotEnabled));
    }

    #[test]
    fn transient_holds_clear_by_themselves() {
        let mut s = armed();
        let good = sample(100, [1.0, 0.0, 100.0]);
        assert_eq!(
            s.check(&good, 110 * MS, false),
            Verdict::Hold(HoldReason::Deadman)
        );
        let lost = Sample {
            position_mm: None,
            status: TrackStatus::Lost,
            gap_mm: f64::NAN,
            ..good
        };
        assert_eq!(
            s.check(&lost, 110 * MS, true),
            Verdict::Hold(HoldReason::MarkerLost)
        );
        let gap = Sample { gap_mm: 1.5, ..good };
        assert_eq!(
            s.check(&gap, 110 * MS, true),
            Verdict::Hold(HoldReason::PoorQuality)
        );
        let rejected = Sample {
            position_mm: None,
            status: TrackStatus::Rejected,
            ..good
        };
        assert_eq!(
            s.check(&rejected, 110 * MS, true),
            Verdict::Hold(HoldReason::PoorQuality)
        );
        assert_eq!(s.check(&good, 151 * MS, true), Verdict::Hold(HoldReason::Stale));
        assert_eq!(s.check(&good, 99 * MS, true), Verdict::Hold(HoldReason::Stale));
        assert!(s.is_armed());
        assert!(matches!(s.check(&good, 150 * MS, true), Verdict::Send { .. }));
    }

    #[test]
    fn workspace_step_speed_and_frame_latch() {
        let mut s = armed();
        let out = sample(100, [0.0, 0.0, -1.0]);
        assert_eq!(
            s.check(&out, 100 * MS, true),
            Verdict::Hold(HoldReason::Workspace)
        );
        assert!(!s.is_armed());
        assert_eq!(
            s.check(&sample(101, [0.0, 0.0, 100.0]), 101 * MS, true),
            Verdict::Hold(HoldReason::Workspace)
        );

        // First target after enable is measured from the robot's position.
        let mut s = armed();
        assert_eq!(
            s.check(&sample(100, [11.0, 0.0, 100.0]), 100 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
        let mut s = armed();
        let Verdict::Send { pos_mm, .. } = s.check(&sample(100, [9.0, 0.0, 100.0]), 100 * MS, true) else {
            panic!()
        };
        s.committed(pos_mm, None, 100 * MS);
        // 9 mm in 30 ms = 300 mm/s > 200.
        assert_eq!(
            s.check(&sample(130, [18.0, 0.0, 100.0]), 130 * MS, true),
            Verdict::Hold(HoldReason::TooFast)
        );
        assert_eq!(s.latched(), Some(HoldReason::TooFast));

        let mut s = armed();
        let cam = Sample {
            world_frame: false,
            ..sample(100, [1.0, 0.0, 100.0])
        };
        assert_eq!(
            s.check(&cam, 100 * MS, true),
            Verdict::Hold(HoldReason::Workspace)
        );
        let mut s = Supervisor::new(SafetyConfig {
            require_world_frame: false,
            ..cfg()
        });
        s.on_connect([0.0, 0.0, 100.0]);
        s.enable();
        assert!(matches!(s.check(&cam, 100 * MS, true), Verdict::Send { .. }));
    }

    #[test]
    fn resume_after_loss_checks_step_from_last_target() {
        let mut s = armed();
        s.committed([5.0, 0.0, 100.0], None, 100 * MS);
        // Marker reappears 30 mm away: would be a jump.
        assert_eq!(
            s.check(&sample(500, [35.0, 0.0, 100.0]), 500 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
        s.enable();
        // After enable the reference is the robot position (0,0,100), still far.
        s.on_robot_position([5.0, 0.0, 100.0]);
        assert_eq!(
            s.check(&sample(600, [35.0, 0.0, 100.0]), 600 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
        s.enable();
        assert!(matches!(
            s.check(&sample(700, [8.0, 0.0, 100.0]), 700 * MS, true),
            Verdict::Send { .. }
        ));
    }

    #[test]
    fn reacquisition_after_a_gap_resumes_within_speed_times_gap() {
        // max_step 10 mm, max_speed 200 mm/s.
        let mut s = armed();
        s.committed([0.0, 0.0, 100.0], None, 100 * MS);
        let mut lost = sample(110, [0.0, 0.0, 100.0]);
        lost.status = TrackStatus::Lost;
        lost.position_mm = None;
        assert_eq!(
            s.check(&lost, 110 * MS, true),
            Verdict::Hold(HoldReason::MarkerLost)
        );
        // Back 150 ms after the last target, 25 mm away: more than a step, less than
        // 200 mm/s × 0.15 s = 30 mm. Resumes without a new enable.
        assert!(matches!(
            s.check(&sample(250, [25.0, 0.0, 100.0]), 250 * MS, true),
            Verdict::Send { .. }
        ));
        s.committed([25.0, 0.0, 100.0], None, 250 * MS);
        // The allowance ends with the gap: the next frame is held to the step limit again.
        assert_eq!(
            s.check(&sample(260, [37.0, 0.0, 100.0]), 260 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
        // Beyond max_speed × gap after a gap: held and latched as before.
        s.enable();
        s.committed([0.0, 0.0, 100.0], None, 300 * MS);
        assert_eq!(
            s.check(&lost, 310 * MS, true),
            Verdict::Hold(HoldReason::MarkerLost)
        );
        assert_eq!(
            s.check(&sample(400, [25.0, 0.0, 100.0]), 400 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
        assert_eq!(s.latched(), Some(HoldReason::StepTooLarge));
        // A gap of minutes widens the allowance only up to REACQUIRE_MAX_GAP_S (100 mm here).
        s.enable();
        s.committed([0.0, 0.0, 100.0], None, 1000 * MS);
        assert_eq!(
            s.check(&lost, 1010 * MS, true),
            Verdict::Hold(HoldReason::MarkerLost)
        );
        assert_eq!(
            s.check(&sample(100_000, [0.0, 0.0, 210.0]), 100_000 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
    }

    #[test]
    fn rotation_step_latches_and_bad_quaternions_hold() {
        let mut s = armed();
        let turn = |deg: f64| {
            let h = (deg.to_radians() / 2.0).sin_cos();
            Some([h.1, 0.0, 0.0, h.0])
        };
        let oriented = |ts_ms: u64, q: Option<[f64; 4]>| Sample {
            orientation_wxyz: q,
            ..sample(ts_ms, [1.0, 0.0, 100.0])
        };
        // First oriented target after enable: no rotation reference, sent as a pose.
        let x = oriented(100, turn(40.0));
        let Verdict::Send { pos_mm, quat_wxyz } = s.check(&x, 100 * MS, true) else {
            panic!("first pose not sent")
        };
        assert_eq!(quat_wxyz, turn(40.0));
        s.committed(pos_mm, quat_wxyz, 100 * MS);
        // 4.5° further: within the 5° limit; the sign of q does not matter.
        let q = turn(44.5).map(|q| q.map(|v| -v));
        assert!(matches!(
            s.check(&oriented(110, q), 110 * MS, true),
            Verdict::Send { .. }
        ));
        s.committed(pos_mm, q, 110 * MS);
        assert!((rotation_between_deg(&q.unwrap(), &turn(40.0).unwrap()) - 4.5).abs() < 1e-9);
        // A non-unit or NaN quaternion is poor quality (transient, not latched).
        assert_eq!(
            s.check(&oriented(120, Some([0.9, 0.0, 0.0, 0.0])), 120 * MS, true),
            Verdict::Hold(HoldReason::PoorQuality)
        );
        assert_eq!(
            s.check(&oriented(120, Some([f64::NAN, 0.0, 0.0, 1.0])), 120 * MS, true),
            Verdict::Hold(HoldReason::PoorQuality)
        );
        // 6° from the last target: a rotation jump latches like a position jump.
        assert_eq!(
            s.check(&oriented(130, turn(50.5)), 130 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
        assert!(!s.is_armed());
        assert_eq!(
            s.check(&oriented(140, turn(44.5)), 140 * MS, true),
            Verdict::Hold(HoldReason::StepTooLarge)
        );
        let e = SafetyConfig {
            max_rotation_step_deg: 0.0,
            ..cfg()
        }
        .validate()
        .unwrap_err();
        assert!(e.contains("max_rotation_step_deg"), "{e}");
    }

    #[test]
    fn config_validation_names_keys() {
        assert!(cfg().validate().is_ok());
        let e = SafetyConfig {
            max_gap_mm: f64::NAN,
            ..cfg()
        }
        .validate()
        .unwrap_err();
        assert!(e.contains("max_gap_mm"));
        let e = SafetyConfig {
            max_age_ms: 0,
            ..cfg()
        }
        .validate()
        .unwrap_err();
        assert!(e.contains("max_age_ms"));
    }
}
