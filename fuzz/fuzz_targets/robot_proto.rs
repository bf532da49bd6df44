//! Robot link protocol (core/src/robot_proto.rs): both directions' line parsers never panic;
//! every accepted line encodes back to a line that parses to the same message. A second mode
//! drives the simulated robot's state machine (`SimRobot`, what `host-tools robot-sim`
//! runs) with a sequence of lines and time steps.
#![no_main]

use irtrack_core::robot_proto::{RobotMsg, TrackerMsg};
use irtrack_robot::sim_robot::{SimRobot, SimRobotConfig};
use libfuzzer_sys::fuzz_target;

/// Quaternions the parser reads but the encoder refuses (components beyond ±1 or a norm away
/// from 1): the fixed-width field `±d.dddddd` can carry them, the encoder checks the domain.
fn encoder_domain(m: &TrackerMsg) -> bool {
    match m {
        TrackerMsg::Pose { quat_wxyz, .. } => unit(quat_wxyz),
        _ => true,
    }
}

/// The same for the robot's pose answer `A`.
fn robot_encoder_domain(m: &RobotMsg) -> bool {
    match m {
        RobotMsg::Actual { quat_wxyz, .. } => unit(quat_wxyz),
        _ => true,
    }
}

fn unit(q: &[f64; 4]) -> bool {
    let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    q.iter().all(|c| c.abs() <= 1.0) && n > 0.99 && n < 1.01
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let Ok(text) = std::str::from_utf8(rest) else {
        return;
    };
    if mode & 1 == 0 {
        if let Ok(m) = TrackerMsg::parse(text) {
            if encoder_domain(&m) {
                let line = m.encode().expect("a parsed tracker line must encode");
                assert_eq!(TrackerMsg::parse(line.as_str()).expect("re-parse"), m);
            }
        }
        if let Ok(m) = RobotMsg::parse(text)
            && robot_encoder_domain(&m)
        {
            let line = m.encode().expect("a parsed robot line must encode");
            assert_eq!(RobotMsg::parse(line.as_str()).expect("re-parse"), m);
        }
    } else {
        let mut robot = SimRobot::new(SimRobotConfig::default());
        let mut replies = robot.connect();
        for (i, line) in text.split('\n').enumerate() {
            replies.extend(robot.on_line(line));
            // Advance time between lines by a line-dependent step (0..2.55 s).
            let dt_s = f64::from(line.bytes().next().unwrap_or(0)) / 100.0;
            replies.extend(robot.advance(dt_s));
            if i % 8 == 7 {
                let _ = robot.take_events();
            }
        }
        let _ = robot.pos_mm();
        // What the simulated robot says must itself be valid protocol.
        // (Positions are rounded to 0.01 mm on the wire, so lines are compared, not messages.)
        for r in replies {
            let line = r
                .encode()
                .expect("simulated robot produced an unencodable message");
            let back = RobotMsg::parse(line.as_str()).expect("robot reply parses");
            assert_eq!(back.encode().expect("re-encode").as_str(), line.as_str());
        }
    }
});
