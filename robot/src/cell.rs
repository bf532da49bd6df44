//! The simulated robot cell: a robot whose flange carries the LED, with a real robot's errors.
//! (It lives with the other simulated controllers; the simulator crate gives it its noise.)
//!
//! The robot controller believes its TCP is where it was commanded (that is what RAPID's
//! `CRobT` and robot-sim's `A` answer report). The flange is really somewhere slightly
//! different: a smooth, position-dependent absolute error (kinematic model errors, elasticity)
//! plus a small random repeatability error drawn anew every time the robot comes to rest. The
//! cameras see the LED where the robot *really* put it.
//!
//! [`RobotErrorModel`] is that error; [`CellFeed`] is the simulator-only channel over which
//! `host-tools robot-sim` tells irtrackd's simulated cameras (`[source.sim.cell]`) where the LED
//! really is: one UDP request (`LED?`), one answer (`LED x y z`, robot base frame, mm). Nothing
//! of it exists on a real cell, and the tracker never learns the base-from-camera transform the
//! simulated cameras use.

use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;

use nalgebra::{UnitQuaternion, Vector3};

use irtrack_sim::noise::{hash_words, normal_quantile, unit_from_hash};

use crate::RobotError;

/// Terms of the smooth error field per axis.
const FIELD_TERMS: usize = 3;

/// Errors of the simulated robot (robot base frame, mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotErrorModel {
    /// Repeatability: RMS of the 3-D deviation between visits of the same point (each axis
    /// `repeatability_mm / √3`), drawn anew at every standstill.
    pub repeatability_mm: f64,
    /// Absolute-position error field: RMS of its 3-D magnitude over space.
    pub field_rms_mm: f64,
    /// Wavelength of the field's sinusoids: the field changes by about its full amplitude over
    /// half this distance (a few hundred mm: a smooth error, as from joint offsets).
    pub field_wavelength_mm: f64,
    /// Absolute-orientation error field: RMS of the flange's rotation error over space (deg),
    /// a smooth rotation-vector field of the same wavelength (joint offsets turn the flange
    /// too). 0 leaves the flange's orientation as commanded.
    pub orientation_rms_deg: f64,
    /// Seed of the field's directions and phases and of the repeatability draws.
    pub seed: u64,
}

impl Default for RobotErrorModel {
    /// A typical small industrial robot: 0.02 mm repeatability, 0.3 mm absolute error.
    fn default() -> Self {
        Self {
            repeatability_mm: 0.02,
            field_rms_mm: 0.3,
            field_wavelength_mm: 800.0,
            orientation_rms_deg: 0.0,
            seed: 1,
        }
    }
}

impl RobotErrorModel {
    /// No error at all (an ideal robot).
    pub fn ideal() -> Self {
        Self {
            repeatability_mm: 0.0,
            field_rms_mm: 0.0,
            orientation_rms_deg: 0.0,
            ..Self::default()
        }
    }

    /// Checks the values are usable; the message names the field.
    pub fn validate(&self) -> Result<(), RobotError> {
        let bad = |field, reason: String| Err(RobotError::Simulator { field, reason });
        if !(self.repeatability_mm.is_finite() && self.repeatability_mm >= 0.0) {
            return bad(
                "repeatability_mm",
                format!("{} must be >= 0", self.repeatability_mm),
            );
        }
        if !(self.field_rms_mm.is_finite() && self.field_rms_mm >= 0.0) {
            return bad("field_rms_mm", format!("{} must be >= 0", self.field_rms_mm));
        }
        if !(self.orientation_rms_deg.is_finite() && (0.0..=10.0).contains(&self.orientation_rms_deg)) {
            return bad(
                "orientation_rms_deg",
                format!("{} must be in 0..=10", self.orientation_rms_deg),
            );
        }
        if !(self.field_wavelength_mm.is_finite() && self.field_wavelength_mm > 0.0) {
            return bad(
                "field_wavelength_mm",
                format!("{} must be > 0", self.field_wavelength_mm),
            );
        }
        Ok(())
    }

    /// A unit direction and a phase for term `j` of axis `axis` of the field tagged `tag`.
    fn term(&self, tag: u64, axis: usize, j: usize) -> (Vector3<f64>, f64) {
        let h = |k: u64| unit_from_hash(hash_words(&[self.seed, tag, axis as u64, j as u64, k]));
        // Uniform direction on the sphere.
        let z = 2.0 * h(0) - 1.0;
        let phi = std::f64::consts::TAU * h(1);
        let r = (1.0 - z * z).max(0.0).sqrt();
        (
            Vector3::new(r * phi.cos(), r * phi.sin(), z),
            std::f64::consts::TAU * h(2),
        )
    }

    /// The smooth absolute error at `p_mm` (robot base frame): where the flange really is minus
    /// where the controller believes it is.
    pub fn field_mm(&self, p_mm: [f64; 3]) -> [f64; 3] {
        self.smooth_field(0x4649_454c, self.field_rms_mm, p_mm)
    }

    /// A smooth vector field of 3-D RMS `rms` over space, its terms seeded by `tag`.
    fn smooth_field(&self, tag: u64, rms: f64, p_mm: [f64; 3]) -> [f64; 3] {
        if rms == 0.0 {
            return [0.0; 3];
        }
        // Per axis: FIELD_TERMS sinusoids of amplitude a, so the mean square of the 3-D
        // magnitude is 3 · FIELD_TERMS · a² / 2.
        let a = rms * (2.0 / (3.0 * FIELD_TERMS as f64)).sqrt();
        let p = Vector3::from(p_mm);
        let k = std::f64::consts::TAU / self.field_wavelength_mm;
        let mut out = [0.0; 3];
        for (axis, o) in out.iter_mut().enumerate() {
            for j in 0..FIELD_TERMS {
                let (dir, phase) = self.term(tag, axis, j);
                *o += a * (k * dir.dot(&p) + phase).sin();
            }
        }
        out
    }

    /// The flange's orientation error at `p_mm` (robot base frame): the rotation that takes
    /// the commanded orientation to the real one, `q_real = error · q_commanded`.
    pub fn orientation_error(&self, p_mm: [f64; 3]) -> UnitQuaternion<f64> {
        let v = self.smooth_field(0x4f52_4945, self.orientation_rms_deg.to_radians(), p_mm);
        UnitQuaternion::from_scaled_axis(Vector3::from(v))
    }

    /// Where the flange really is and how it is really turned, when the controller believes it
    /// is at `nominal_mm`, turned `nominal_wxyz`, after standstill number `visit` (while moving,
    /// `visit = None`: the error fields only).
    pub fn actual_pose(
        &self,
        nominal_mm: [f64; 3],
        nominal_wxyz: [f64; 4],
        visit: Option<u64>,
    ) -> ([f64; 3], [f64; 4]) {
        let p = match visit {
            Some(v) => self.actual_mm(nominal_mm, v),
            None => {
                let f = self.field_mm(nominal_mm);
                [nominal_mm[0] + f[0], nominal_mm[1] + f[1], nominal_mm[2] + f[2]]
            }
        };
        let q = self.orientation_error(nominal_mm) * quat(nominal_wxyz);
        let q = q.into_inner();
        (p, [q.w, q.i, q.j, q.k])
    }

    /// The repeatability error of the `visit`-th standstill.
    pub fn repeat_mm(&self, visit: u64) -> [f64; 3] {
        let sigma = self.repeatability_mm / 3f64.sqrt();
        let mut out = [0.0; 3];
        for (axis, o) in out.iter_mut().enumerate() {
            let u = unit_from_hash(hash_words(&[self.seed, 0x5245_5054, visit, axis as u64]));
            *o = sigma * normal_quantile(u.clamp(1e-12, 1.0 - 1e-12));
        }
        out
    }

    /// Where the flange really is when the controller believes it is at `nominal_mm` after
    /// standstill number `visit`.
    pub fn actual_mm(&self, nominal_mm: [f64; 3], visit: u64) -> [f64; 3] {
        let f = self.field_mm(nominal_mm);
        let r = self.repeat_mm(visit);
        [
            nominal_mm[0] + f[0] + r[0],
            nominal_mm[1] + f[1] + r[1],
            nominal_mm[2] + f[2] + r[2],
        ]
    }
}

/// The LED's position (robot base frame) for a flange at `flange_mm` turned by `flange_wxyz`,
/// with the LED at `led_offset_mm` in the flange frame.
pub fn led_position_mm(flange_mm: [f64; 3], flange_wxyz: [f64; 4], led_offset_mm: [f64; 3]) -> [f64; 3] {
    let p = Vector3::from(flange_mm) + quat(flange_wxyz) * Vector3::from(led_offset_mm);
    [p.x, p.y, p.z]
}

fn quat(wxyz: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(wxyz[0], wxyz[1], wxyz[2], wxyz[3]))
}

/// The pose (robot base frame) of a tool mounted on a flange at `flange_mm` turned
/// `flange_wxyz`: the tool frame's origin at `mount_mm` and turned `mount_wxyz` in the flange
/// frame (`base_from_tool = base_from_flange · flange_from_tool`).
pub fn tool_pose(
    flange_mm: [f64; 3],
    flange_wxyz: [f64; 4],
    mount_mm: [f64; 3],
    mount_wxyz: [f64; 4],
) -> PoseWxyz {
    let q = (quat(flange_wxyz) * quat(mount_wxyz)).into_inner();
    (
        led_position_mm(flange_mm, flange_wxyz, mount_mm),
        [q.w, q.i, q.j, q.k],
    )
}

/// Request datagram of the cell feed: where is the LED?
pub const FEED_REQUEST: &[u8] = b"LED?";

/// A pose in the robot base frame: position (mm) and unit quaternion (w, x, y, z).
pub type PoseWxyz = ([f64; 3], [f64; 4]);

/// Request datagram of the cell feed: where is the tool (its frame's pose)?
pub const FEED_TOOL_REQUEST: &[u8] = b"TOOL?";

/// Encodes the feed's answer to `TOOL?`: the tool frame's actual pose (robot base frame, mm and
/// unit quaternion w, x, y, z), or `TOOL off`.
pub fn encode_tool_answer(pose: Option<PoseWxyz>) -> String {
    match pose {
        Some((p, q)) => format!(
            "TOOL {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
            p[0], p[1], p[2], q[0], q[1], q[2], q[3]
        ),
        None => "TOOL off".to_string(),
    }
}

/// An error of the cell feed's text answers.
fn feed_error(reason: String) -> RobotError {
    RobotError::Simulator {
        field: "cell feed",
        reason,
    }
}

/// The numbers after `prefix` in a feed answer, or `None` for `<prefix>off`.
fn feed_numbers(text: &str, prefix: &str) -> Result<Option<Vec<f64>>, RobotError> {
    let rest = text
        .trim()
        .strip_prefix(prefix)
        .ok_or_else(|| feed_error(format!("answer {text:?} does not start with {prefix:?}")))?;
    if rest == "off" {
        return Ok(None);
    }
    rest.split_whitespace()
        .map(|w| w.parse::<f64>().map_err(|e| feed_error(format!("{w:?}: {e}"))))
        .collect::<Result<_, _>>()
        .map(Some)
}

/// Decodes an answer of [`encode_tool_answer`]: `Ok(None)` for `TOOL off`.
pub fn decode_tool_answer(text: &str) -> Result<Option<PoseWxyz>, RobotError> {
    let Some(v) = feed_numbers(text, "TOOL ")? else {
        return Ok(None);
    };
    let norm = v
        .get(3..7)
        .map_or(0.0, |q| q.iter().map(|c| c * c).sum::<f64>().sqrt());
    match <[f64; 7]>::try_from(v) {
        Ok(a) if a.iter().all(|x| x.is_finite()) && (norm - 1.0).abs() < 1e-6 => {
            Ok(Some(([a[0], a[1], a[2]], [a[3], a[4], a[5], a[6]])))
        }
        _ => Err(feed_error(format!(
            "answer {text:?} needs a position and a unit quaternion (seven finite numbers)"
        ))),
    }
}

/// Encodes the feed's answer: the LED's actual position (robot base frame), or `LED off` when
/// the robot has no LED to show (e.g. before it is placed).
pub fn encode_feed_answer(led_mm: Option<[f64; 3]>) -> String {
    match led_mm {
        Some(p) => format!("LED {:.6} {:.6} {:.6}", p[0], p[1], p[2]),
        None => "LED off".to_string(),
    }
}

/// Decodes an answer of [`encode_feed_answer`]: `Ok(None)` for `LED off`.
pub fn decode_feed_answer(text: &str) -> Result<Option<[f64; 3]>, RobotError> {
    let Some(v) = feed_numbers(text, "LED ")? else {
        return Ok(None);
    };
    match <[f64; 3]>::try_from(v) {
        Ok(p) if p.iter().all(|x| x.is_finite()) => Ok(Some(p)),
        _ => Err(feed_error(format!("answer {text:?} needs three finite numbers"))),
    }
}

/// The simulated cameras' side of the cell feed: asks robot-sim where the LED is.
#[derive(Debug)]
pub struct CellFeed {
    socket: UdpSocket,
    robot: SocketAddr,
}

impl CellFeed {
    /// A feed asking `robot` (robot-sim's `--cell-feed` address), answers awaited `timeout`.
    pub fn connect(robot: SocketAddr, timeout: Duration) -> std::io::Result<Self> {
        let local: SocketAddr = if robot.is_ipv4() {
            "0.0.0.0:0".parse().map_err(std::io::Error::other)?
        } else {
            "[::]:0".parse().map_err(std::io::Error::other)?
        };
        let socket = UdpSocket::bind(local)?;
        socket.set_read_timeout(Some(timeout))?;
        Ok(Self { socket, robot })
    }

    /// The LED's actual position in the robot base frame; `Ok(None)` when robot-sim says it has
    /// none, an error when it does not answer in time (the caller shows no LED then).
    pub fn led_mm(&mut self) -> std::io::Result<Option<[f64; 3]>> {
        // Answers to earlier, timed-out requests may still be queued: drop them.
        self.socket.set_nonblocking(true)?;
        let mut buf = [0u8; 128];
        while self.socket.recv_from(&mut buf).is_ok() {}
        self.socket.set_nonblocking(false)?;
        self.socket.send_to(FEED_REQUEST, self.robot)?;
        loop {
            let (n, from) = self.socket.recv_from(&mut buf)?;
            if from != self.robot {
                continue;
            }
            let text = std::str::from_utf8(&buf[..n]).map_err(std::io::Error::other)?;
            return decode_feed_answer(text).map_err(std::io::Error::other);
        }
    }

    /// The tool frame's actual pose in the robot base frame (`TOOL?`); `Ok(None)` when
    /// robot-sim says it has none, an error when it does not answer in time.
    pub fn tool_pose(&mut self) -> std::io::Result<Option<PoseWxyz>> {
        self.socket.set_nonblocking(true)?;
        let mut buf = [0u8; 160];
        while self.socket.recv_from(&mut buf).is_ok() {}
        self.socket.set_nonblocking(false)?;
        self.socket.send_to(FEED_TOOL_REQUEST, self.robot)?;
        loop {
            let (n, from) = self.socket.recv_from(&mut buf)?;
            if from != self.robot {
                continue;
            }
            let text = std::str::from_utf8(&buf[..n]).map_err(std::io::Error::other)?;
            return decode_tool_answer(text).map_err(std::io::Error::other);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_has_the_configured_rms_and_is_smooth() {
        let m = RobotErrorModel::default();
        let mut sum2 = 0.0;
        let mut n = 0.0;
        let mut max_grad: f64 = 0.0;
        for i in 0..20 {
            for j in 0..20 {
                for k in 0..20 {
                    let p = [i as f64 * 97.0, j as f64 * 101.0 - 1000.0, k as f64 * 89.0];
                    let f = m.field_mm(p);
                    sum2 += f.iter().map(|v| v * v).sum::<f64>();
                    n += 1.0;
                    let g = m.field_mm([p[0] + 1.0, p[1], p[2]]);
                    max_grad = max_grad.max((g[0] - f[0]).abs().max((g[1] - f[1]).abs()));
                }
            }
        }
        let rms = (sum2 / n).sqrt();
        assert!((rms - 0.3).abs() < 0.06, "field RMS {rms}");
        // Smooth: at most ~ amplitude · 2π / wavelength per mm.
        assert!(max_grad < 0.01, "gradient {max_grad} mm/mm");
    }

    #[test]
    fn repeatability_draws_have_the_configured_rms() {
        let m = RobotErrorModel::default();
        let n = 4000;
        let s2: f64 = (0..n)
            .map(|v| m.repeat_mm(v).iter().map(|x| x * x).sum::<f64>())
            .sum();
        let rms = (s2 / n as f64).sqrt();
        assert!((rms - 0.02).abs() < 0.002, "repeatability RMS {rms}");
        assert_ne!(m.repeat_mm(1), m.repeat_mm(2));
        assert_eq!(
            RobotErrorModel::ideal().actual_mm([1.0, 2.0, 3.0], 5),
            [1.0, 2.0, 3.0]
        );
    }

    #[test]
    fn feed_answers_round_trip_and_bad_ones_are_named() {
        let p = [512.25, -3.5, 300.125];
        assert_eq!(decode_feed_answer(&encode_feed_answer(Some(p))).unwrap(), Some(p));
        assert_eq!(decode_feed_answer("LED off").unwrap(), None);
        assert!(decode_feed_answer("LED 1 2").is_err());
        assert!(decode_feed_answer("POS 1 2 3").is_err());
        assert!(decode_feed_answer("LED 1 2 nan").is_err());
    }

    #[test]
    fn orientation_field_has_the_configured_rms_and_tool_answers_round_trip() {
        let m = RobotErrorModel {
            orientation_rms_deg: 0.1,
            ..RobotErrorModel::default()
        };
        let mut sum2 = 0.0;
        let n = 2000;
        for i in 0..n {
            let p = [
                (i % 13) as f64 * 71.0,
                (i % 7) as f64 * 113.0,
                (i / 91) as f64 * 53.0,
            ];
            sum2 += m.orientation_error(p).angle().to_degrees().powi(2);
        }
        let rms = (sum2 / n as f64).sqrt();
        assert!((rms - 0.1).abs() < 0.03, "orientation field RMS {rms}°");
        // Without it the flange turns as commanded; the position error is unchanged.
        let q = [0.0, 0.0, 1.0, 0.0];
        let (p, q0) = RobotErrorModel::default().actual_pose([500.0, 0.0, 300.0], q, Some(3));
        assert_eq!(q0, q);
        assert_eq!(p, RobotErrorModel::default().actual_mm([500.0, 0.0, 300.0], 3));
        let (_, q1) = m.actual_pose([500.0, 0.0, 300.0], q, None);
        assert!(quat(q1).angle_to(&quat(q)) > 1e-6);
        assert!(m.validate().is_ok());
        let too_much = RobotErrorModel {
            orientation_rms_deg: 20.0,
            ..m
        };
        assert!(
            too_much
                .validate()
                .unwrap_err()
                .to_string()
                .contains("orientation_rms_deg")
        );

        let pose = ([512.25, -3.5, 300.125], [0.5, 0.5, -0.5, 0.5]);
        assert_eq!(
            decode_tool_answer(&encode_tool_answer(Some(pose))).unwrap(),
            Some(pose)
        );
        assert_eq!(decode_tool_answer("TOOL off").unwrap(), None);
        assert!(decode_tool_answer("TOOL 1 2 3 1 0 0").is_err());
        assert!(decode_tool_answer("TOOL 1 2 3 2 0 0 0").is_err());
        assert!(decode_tool_answer("LED 1 2 3").is_err());
        // The tool frame follows flange and mount: a half turn about x flips the mount's y, z.
        let (p, q) = tool_pose(
            [100.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [1.0, 2.0, 3.0],
            [1.0, 0.0, 0.0, 0.0],
        );
        assert!((p[1] + 2.0).abs() < 1e-12 && (p[2] + 3.0).abs() < 1e-12);
        assert!((q[1].abs() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn led_follows_the_flange_rotation() {
        // Flange turned 180° about x: the offset's y and z flip.
        let p = led_position_mm([100.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 2.0, 3.0]);
        assert!((p[0] - 101.0).abs() < 1e-12 && (p[1] + 2.0).abs() < 1e-12 && (p[2] + 3.0).abs() < 1e-12);
    }
}
