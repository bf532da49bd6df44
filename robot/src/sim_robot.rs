//! The robot (server) side of the socket protocol as a sans-IO state machine: a TCP point that
//! moves toward each target at a bounded speed and answers as the RAPID module does.
//! `host-tools robot-sim` and the in-process [`crate::sim::SimRobotServer`] wrap it with
//! sockets, so both speak exactly the same protocol (docs/robot-protocol.md).

use std::collections::VecDeque;

use irtrack_core::robot_proto::{
    HoldReason, PROTOCOL_VERSION, RobotMsg, TrackerMsg, reject, seq_distance, seq_next,
};

/// Configuration of the simulated robot.
#[derive(Debug, Clone, PartialEq)]
pub struct SimRobotConfig {
    /// Name sent in `HELLO`.
    pub name: String,
    /// TCP speed limit.
    pub speed_mm_s: f64,
    /// Credit window granted (1 = step-by-step).
    pub window: u8,
    /// Start position of the TCP point.
    pub home_mm: [f64; 3],
    /// Reject every N-th received target (fault injection); 0 = never.
    pub reject_every: u32,
    /// Heartbeat period of the robot side.
    pub beat_period_s: f64,
}

impl Default for SimRobotConfig {
    fn default() -> Self {
        Self {
            name: "robot-sim".into(),
            speed_mm_s: 250.0,
            window: 1,
            home_mm: [0.0; 3],
            reject_every: 0,
            beat_period_s: 0.2,
        }
    }
}

/// Something the simulated robot did, for logs and tests.
#[derive(Debug, Clone, PartialEq)]
pub enum SimEvent {
    /// Target accepted into the queue.
    Target {
        /// The target's sequence number.
        seq: u32,
        /// The target position (mm).
        target_mm: [f64; 3],
    },
    /// Target reached and acknowledged.
    Reached {
        /// The target's sequence number.
        seq: u32,
    },
    /// Target rejected (code from [`reject`]).
    Rejected {
        /// The target's sequence number.
        seq: u32,
        /// The reject code sent.
        code: u8,
    },
    /// `HOLD` received: motion stopped, queue cleared.
    Hold {
        /// The tracker's reason.
        reason: HoldReason,
    },
    /// Malformed or unexpected line.
    Malformed {
        /// What was wrong with it.
        reason: String,
    },
}

/// The robot side of the protocol with a point that moves at a bounded speed.
#[derive(Debug, Clone)]
pub struct SimRobot {
    cfg: SimRobotConfig,
    pos_mm: [f64; 3],
    /// TCP orientation w, x, y, z: the last `Q` target's once reached (identity at start).
    quat_wxyz: [f64; 4],
    queue: VecDeque<(u32, [f64; 3], Option<[f64; 4]>)>,
    /// Last sequence the robot consumed (reached, rejected or flushed by HOLD).
    ack_seq: u32,
    /// Last sequence received.
    last_rx_seq: u32,
    received: u32,
    beat_counter: u32,
    since_beat_s: f64,
    last_rx_s: f64,
    events: Vec<SimEvent>,
}

impl SimRobot {
    /// A robot at its home position, waiting for a connection.
    pub fn new(cfg: SimRobotConfig) -> Self {
        let pos_mm = cfg.home_mm;
        Self {
            cfg,
            pos_mm,
            quat_wxyz: [1.0, 0.0, 0.0, 0.0],
            queue: VecDeque::new(),
            ack_seq: 0,
            last_rx_seq: 0,
            received: 0,
            beat_counter: 0,
            since_beat_s: 0.0,
            last_rx_s: 0.0,
            events: Vec::new(),
        }
    }

    /// Current TCP position.
    pub fn pos_mm(&self) -> [f64; 3] {
        self.pos_mm
    }

    /// Current TCP orientation (w, x, y, z).
    pub fn quat_wxyz(&self) -> [f64; 4] {
        self.quat_wxyz
    }

    /// True while the robot has a target to move to.
    pub fn is_moving(&self) -> bool {
        !self.queue.is_empty()
    }

    /// Seconds since the last line from the tracker (for the robot-side timeout).
    pub fn since_rx_s(&self) -> f64 {
        self.last_rx_s
    }

    /// Drains the event log.
    pub fn take_events(&mut self) -> Vec<SimEvent> {
        core::mem::take(&mut self.events)
    }

    fn credit(&self) -> RobotMsg {
        RobotMsg::Credit {
            ack_seq: self.ack_seq,
            window: self.cfg.window,
            pos_mm: self.pos_mm,
        }
    }

    /// New connection: sequence state resets, motion stops; returns `HELLO` and the ready credit.
    pub fn connect(&mut self) -> Vec<RobotMsg> {
        self.queue.clear();
        self.ack_seq = 0;
        self.last_rx_seq = 0;
        self.last_rx_s = 0.0;
        let name = self.cfg.name.clone();
        vec![
            RobotMsg::Hello {
                version: PROTOCOL_VERSION,
                name,
            },
            self.credit(),
        ]
    }

    /// Connection lost: a real controller stops at once.
    pub fn disconnect(&mut self) {
        self.queue.clear();
    }

    /// Handles one received line; returns the replies.
    pub fn on_line(&mut self, line: &str) -> Vec<RobotMsg> {
        self.last_rx_s = 0.0;
        let msg = match TrackerMsg::parse(line) {
            Ok(m) => m,
            Err(e) => {
                self.events.push(SimEvent::Malformed {
                    reason: e.to_string(),
                });
                let reason = "MALFORMED".to_string();
                return vec![RobotMsg::Reject {
                    seq: 0,
                    code: reject::MALFORMED,
                    reason,
                }];
            }
        };
        match msg {
            TrackerMsg::Hello { .. } | TrackerMsg::Beat { .. } => Vec::new(),
            TrackerMsg::PoseRequest { counter } => vec![RobotMsg::Actual {
                counter,
                pos_mm: self.pos_mm,
                quat_wxyz: self.quat_wxyz,
            }],
            TrackerMsg::Bye => vec![RobotMsg::Bye],
            TrackerMsg::Hold { reason } => {
                self.queue.clear();
                self.ack_seq = self.last_rx_seq;
                self.events.push(SimEvent::Hold { reason });
                vec![self.credit()]
            }
            TrackerMsg::Target { seq, pos_mm } => self.on_target(seq, pos_mm, None),
            TrackerMsg::Pose {
                seq,
                pos_mm,
                quat_wxyz,
            } => {
                // Like RAPID's NOrient: a nearly unit quaternion is normalised, anything else
                // is refused (the `A` answer must carry a unit quaternion).
                let n = (quat_wxyz.iter().map(|q| q * q).sum::<f64>()).sqrt();
                if !(0.9..=1.1).contains(&n) {
                    self.events.push(SimEvent::Malformed {
                        reason: format!("Q target {seq} quaternion norm {n}"),
                    });
                    return vec![RobotMsg::Reject {
                        seq,
                        code: reject::MALFORMED,
                        reason: "MALFORMED".to_string(),
                    }];
                }
                self.on_target(seq, pos_mm, Some(quat_wxyz.map(|q| q / n)))
            }
        }
    }

    fn on_target(&mut self, seq: u32, target_mm: [f64; 3], quat: Option<[f64; 4]>) -> Vec<RobotMsg> {
        let outstanding = seq_distance(self.ack_seq, seq);
        if outstanding == 0 || outstanding > u32::from(self.cfg.window) {
            self.events.push(SimEvent::Rejected {
                seq,
                code: reject::NO_CREDIT,
            });
            let reason = "NO_CREDIT".to_string();
            return vec![RobotMsg::Reject {
                seq,
                code: reject::NO_CREDIT,
                reason,
            }];
        }
        self.last_rx_seq = seq;
        self.received += 1;
        if self.cfg.reject_every > 0 && self.received.is_multiple_of(self.cfg.reject_every) {
            self.events.push(SimEvent::Rejected {
                seq,
                code: reject::INJECTED,
            });
            // A rejected target counts as consumed once everything before it is done.
            if self.queue.is_empty() {
                self.ack_seq = seq;
                let reason = "INJECTED".to_string();
                return vec![
                    RobotMsg::Reject {
                        seq,
                        code: reject::INJECTED,
                        reason,
                    },
                    self.credit(),
                ];
            }
            // Keep it in the queue as a no-op at the current end so ordering of acks holds.
            let at = self.queue.back().map(|q| q.1).unwrap_or(self.pos_mm);
            self.queue.push_back((seq, at, None));
            let reason = "INJECTED".to_string();
            return vec![RobotMsg::Reject {
                seq,
                code: reject::INJECTED,
                reason,
            }];
        }
        self.events.push(SimEvent::Target { seq, target_mm });
        self.queue.push_back((seq, target_mm, quat));
        Vec::new()
    }

    /// Advances the simulated motion by `dt_s`; returns credits for reached targets and heartbeats.
    pub fn advance(&mut self, dt_s: f64) -> Vec<RobotMsg> {
        let mut out = Vec::new();
        self.last_rx_s += dt_s;
        let mut budget_mm = self.cfg.speed_mm_s * dt_s;
        while let Some(&(seq, target, quat)) = self.queue.front() {
            let d = [
                target[0] - self.pos_mm[0],
                target[1] - self.pos_mm[1],
                target[2] - self.pos_mm[2],
            ];
            let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if dist <= budget_mm {
                self.pos_mm = target;
                if let Some(q) = quat {
                    self.quat_wxyz = q;
                }
                budget_mm -= dist;
                self.queue.pop_front();
                self.ack_seq = seq;
                self.events.push(SimEvent::Reached { seq });
                out.push(self.credit());
            } else {
                let f = budget_mm / dist;
                for (p, di) in self.pos_mm.iter_mut().zip(d) {
                    *p += di * f;
                }
                break;
            }
        }
        self.since_beat_s += dt_s;
        if self.since_beat_s >= self.cfg.beat_period_s {
            self.since_beat_s = 0.0;
            self.beat_counter = seq_next(self.beat_counter);
            out.push(RobotMsg::Beat {
                counter: self.beat_counter,
            });
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn answers_pose_requests_and_normalises_q_targets() {
        // The simulated robot normalises a nearly unit Q target and refuses a far one.
        let mut r0 = SimRobot::new(SimRobotConfig::default());
        r0.connect();
        let far = "Q 000001 +0000.00 +0000.00 +0000.00 +0.500000 +0.000000 +0.000000 +0.000000";
        assert!(matches!(
            r0.on_line(far).as_slice(),
            [RobotMsg::Reject {
                code: reject::MALFORMED,
                ..
            }]
        ));
        let near = "Q 000001 +0000.00 +0000.00 +0000.00 +0.950000 +0.000000 +0.000000 +0.000000";
        assert!(r0.on_line(near).is_empty());
        r0.advance(0.1);
        assert_eq!(r0.quat_wxyz(), [1.0, 0.0, 0.0, 0.0]);
        // The simulated robot answers with its pose; a Q target sets the orientation.
        let mut r = SimRobot::new(SimRobotConfig {
            home_mm: [500.0, 0.0, 400.0],
            ..SimRobotConfig::default()
        });
        r.connect();
        let q = [0.0, 0.6, 0.8, 0.0];
        feed(
            &mut r,
            TrackerMsg::Pose {
                seq: 1,
                pos_mm: [510.0, 0.0, 400.0],
                quat_wxyz: q,
            },
        );
        r.advance(1.0);
        let got = feed(&mut r, TrackerMsg::PoseRequest { counter: 3 });
        assert_eq!(
            got,
            vec![RobotMsg::Actual {
                counter: 3,
                pos_mm: [510.0, 0.0, 400.0],
                quat_wxyz: q
            }]
        );
    }

    fn feed(r: &mut SimRobot, m: TrackerMsg) -> Vec<RobotMsg> {
        r.on_line(m.encode().unwrap().as_str())
    }

    #[test]
    fn sim_robot_step_by_step_moves_at_speed_and_acks() {
        let mut r = SimRobot::new(SimRobotConfig {
            speed_mm_s: 100.0,
            ..Default::default()
        });
        let hello = r.connect();
        assert!(matches!(
            hello[1],
            RobotMsg::Credit {
                ack_seq: 0,
                window: 1,
                ..
            }
        ));
        assert!(
            feed(
                &mut r,
                TrackerMsg::Target {
                    seq: 1,
                    pos_mm: [10.0, 0.0, 0.0]
                }
            )
            .is_empty()
        );
        // Without credit the second target is refused.
        let no = feed(
            &mut r,
            TrackerMsg::Target {
                seq: 2,
                pos_mm: [20.0, 0.0, 0.0],
            },
        );
        assert!(matches!(
            no[0],
            RobotMsg::Reject {
                seq: 2,
                code: reject::NO_CREDIT,
                ..
            }
        ));
        let mid = r.advance(0.05);
        assert!(mid.iter().all(|m| !matches!(m, RobotMsg::Credit { .. })));
        assert!(
            (r.pos_mm()[0] - 5.0).abs() < 1e-9,
            "speed limit: {:?}",
            r.pos_mm()
        );
        let done = r.advance(0.06);
        assert!(
            done.iter()
                .any(|m| matches!(m, RobotMsg::Credit { ack_seq: 1, .. }))
        );
        assert_eq!(r.pos_mm(), [10.0, 0.0, 0.0]);
    }

    #[test]
    fn sim_robot_hold_flushes_and_rejects_inject() {
        let cfg = SimRobotConfig {
            window: 3,
            reject_every: 2,
            ..Default::default()
        };
        let mut r = SimRobot::new(cfg);
        r.connect();
        feed(
            &mut r,
            TrackerMsg::Target {
                seq: 1,
                pos_mm: [100.0, 0.0, 0.0],
            },
        );
        let x = feed(
            &mut r,
            TrackerMsg::Target {
                seq: 2,
                pos_mm: [200.0, 0.0, 0.0],
            },
        );
        assert!(matches!(
            x[0],
            RobotMsg::Reject {
                seq: 2,
                code: reject::INJECTED,
                ..
            }
        ));
        let c = feed(
            &mut r,
            TrackerMsg::Hold {
                reason: HoldReason::Deadman,
            },
        );
        assert!(matches!(c[0], RobotMsg::Credit { ack_seq: 2, .. }));
        assert!(!r.is_moving());
        let garbage = r.on_line("T 1 2 3");
        assert!(matches!(
            garbage[0],
            RobotMsg::Reject {
                code: reject::MALFORMED,
                ..
            }
        ));
    }
}
