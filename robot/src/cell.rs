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
        if !(self.field_wavelength_mm.is_finite() && self.field_wavelength_mm > 0.0) {
            return bad(
                "field_wavelength_mm",
                format!("{} must be > 0", self.field_wavelength_mm),
            );
        }
        Ok(())
    }

    /// A unit direction and a phase for term `j` of axis `axis`.
    fn term(&self, axis: usize, j: usize) -> (Vector3<f64>, f64) {
        let h = |k: u64| unit_from_hash(hash_words(&[self.seed, 0x4649_454c, axis as u64, j as u64, k]));
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
        if self.field_rms_mm == 0.0 {
            return [0.0; 3];
        }
        // Per axis: FIELD_TERMS sinusoids of amplitude a, so the mean square of the 3-D
        // magnitude is 3 · FIELD_TERMS · a² / 2.
        let a = self.field_rms_mm * (2.0 / (3.0 * FIELD_TERMS as f64)).sqrt();
        let p = Vector3::from(p_mm);
        let k = std::f64::consts::TAU / self.field_wavelength_mm;
        let mut out = [0.0; 3];
        for (axis, o) in out.iter_mut().enumerate() {
            for j in 0..FIELD_TERMS {
                let (dir, phase) = self.term(axis, j);
                *o += a * (k * dir.dot(&p) + phase).sin();
            }
        }
        out
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
    let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        flange_wxyz[0],
        flange_wxyz[1],
        flange_wxyz[2],
        flange_wxyz[3],
    ));
    let p = Vector3::from(flange_mm) + q * Vector3::from(led_offset_mm);
    [p.x, p.y, p.z]
}

/// Request datagram of the cell feed.
pub const FEED_REQUEST: &[u8] = b"LED?";

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
    let bad = |reason: String| RobotError::Simulator {
        field: "cell feed",
        reason,
    };
    let rest = text
        .trim()
        .strip_prefix("LED ")
        .ok_or_else(|| bad(format!("answer {text:?} does not start with \"LED \"")))?;
    if rest == "off" {
        return Ok(None);
    }
    let v: Vec<f64> = rest
        .split_whitespace()
        .map(|w| w.parse::<f64>().map_err(|e| bad(format!("{w:?}: {e}"))))
        .collect::<Result<_, _>>()?;
    match <[f64; 3]>::try_from(v) {
        Ok(p) if p.iter().all(|x| x.is_finite()) => Ok(Some(p)),
        _ => Err(bad(format!("answer {text:?} needs three finite numbers"))),
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
    fn led_follows_the_flange_rotation() {
        // Flange turned 180° about x: the offset's y and z flip.
        let p = led_position_mm([100.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 2.0, 3.0]);
        assert!((p[0] - 101.0).abs() < 1e-12 && (p[1] + 2.0).abs() < 1e-12 && (p[2] + 3.0).abs() < 1e-12);
    }
}
