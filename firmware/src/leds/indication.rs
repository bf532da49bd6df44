//! What the LEDs should show, and the blink patterns that show it.
//!
//! Patterns (`t` = ms since the driver started; all periods are exact multiples of the tick):
//!
//! | LED   | state                         | pattern                                            |
//! |-------|-------------------------------|----------------------------------------------------|
//! | Run   | loop making progress          | heartbeat: 100 ms on at the start of every second  |
//! | Run   | loop stalled (> 1 s)          | off                                                |
//! | Track | marker seen in all cameras    | steady on                                          |
//! | Track | marker seen in some cameras   | fast blink, 4 Hz (125 ms on / 125 ms off)          |
//! | Track | marker not seen / no params   | off                                                |
//! | Robot | connected and streaming       | steady on                                          |
//! | Robot | connected, holding            | slow blink, 1 Hz (500 ms on / 500 ms off)          |
//! | Robot | not connected                 | off                                                |
//! | Fault | camera lost                   | 2 flashes (200 ms on/200 ms off), 2 s cycle        |
//! | Fault | no valid parameters           | 1 flash every 2 s                                  |
//! | Fault | deadline misses               | 3 flashes every 2 s                                |
//! | Fault | none                          | off                                                |
//!
//! Only the most important fault blinks (camera lost > no params > deadline misses); the status
//! endpoint lists all active faults.

use serde::Serialize;

use super::Led;

/// How well the marker is seen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackIndication {
    /// Not seen, or nothing can be tracked (no parameters, failure): track LED off.
    None,
    /// Seen by some cameras only: fast blink.
    Partial,
    /// Seen by every camera and tracked: steady on.
    All,
}

/// Robot link state, set by the robot client.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RobotIndication {
    /// No robot link (or still connecting): robot LED off.
    Disconnected,
    /// Connected and sending targets: steady on.
    Connected,
    /// Connected, robot held still (the link says why): slow blink.
    Holding,
}

impl From<irtrack_robot::LinkState> for RobotIndication {
    /// What the robot status LED shows for a link state.
    fn from(state: irtrack_robot::LinkState) -> Self {
        use irtrack_robot::LinkState;
        match state {
            LinkState::Disconnected | LinkState::Connecting => RobotIndication::Disconnected,
            LinkState::Holding(_) => RobotIndication::Holding,
            LinkState::Moving => RobotIndication::Connected,
        }
    }
}

/// Faults shown on the fault LED, most important first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Fault {
    /// A camera stopped delivering frames: two flashes.
    CameraLost,
    /// No valid parameter set is active: one flash.
    NoParams,
    /// The loop misses its per-set deadline too often: three flashes.
    DeadlineMisses,
}

impl Fault {
    /// Number of flashes per cycle on the fault LED.
    pub fn flashes(self) -> u64 {
        match self {
            Fault::NoParams => 1,
            Fault::CameraLost => 2,
            Fault::DeadlineMisses => 3,
        }
    }
}

/// The logical state the LEDs show.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Indication {
    /// The loop is making progress (run LED heartbeat).
    pub alive: bool,
    /// What the track LED shows.
    pub track: TrackIndication,
    /// What the robot LED shows.
    pub robot: RobotIndication,
    /// The fault being shown (highest priority active fault).
    pub fault: Option<Fault>,
}

impl Indication {
    /// The state before the loop's first pass: nothing alive, tracked or linked, no fault.
    pub const STARTING: Indication = Indication {
        alive: false,
        track: TrackIndication::None,
        robot: RobotIndication::Disconnected,
        fault: None,
    };
}

/// LED levels for an indication at time `t_ms`, in [`Led::ALL`] order.
pub fn led_levels(ind: &Indication, t_ms: u64) -> [bool; 4] {
    let run = ind.alive && t_ms % 1000 < 100;
    let track = match ind.track {
        TrackIndication::All => true,
        TrackIndication::Partial => t_ms % 250 < 125,
        TrackIndication::None => false,
    };
    let robot = match ind.robot {
        RobotIndication::Connected => true,
        RobotIndication::Holding => t_ms % 1000 < 500,
        RobotIndication::Disconnected => false,
    };
    let fault = ind.fault.is_some_and(|f| {
        let phase = t_ms % 2000;
        phase < f.flashes() * 400 && phase % 400 < 200
    });
    [run, track, robot, fault]
}

/// Index of `led` in [`Led::ALL`] / [`led_levels`].
pub fn led_index(led: Led) -> usize {
    match led {
        Led::Run => 0,
        Led::Track => 1,
        Led::Robot => 2,
        Led::Fault => 3,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn count_rising_edges(ind: &Indication, led: usize, from_ms: u64, to_ms: u64) -> usize {
        let mut prev = false;
        let mut edges = 0;
        for t in (from_ms..to_ms).step_by(25) {
            let on = led_levels(ind, t)[led];
            if on && !prev {
                edges += 1;
            }
            prev = on;
        }
        edges
    }

    #[test]
    fn fault_codes_flash_their_count_per_cycle() {
        for (fault, n) in [
            (Fault::NoParams, 1),
            (Fault::CameraLost, 2),
            (Fault::DeadlineMisses, 3),
        ] {
            let ind = Indication {
                fault: Some(fault),
                ..Indication::STARTING
            };
            assert_eq!(count_rising_edges(&ind, 3, 0, 2000), n, "{fault:?}");
            assert_eq!(count_rising_edges(&ind, 3, 0, 6000), 3 * n, "{fault:?}");
        }
        assert_eq!(count_rising_edges(&Indication::STARTING, 3, 0, 6000), 0);
    }

    #[test]
    fn heartbeat_track_and_robot_patterns() {
        let alive = Indication {
            alive: true,
            track: TrackIndication::Partial,
            robot: RobotIndication::Holding,
            fault: None,
        };
        assert_eq!(count_rising_edges(&alive, 0, 0, 3000), 3);
        assert_eq!(count_rising_edges(&alive, 1, 0, 1000), 4);
        assert_eq!(count_rising_edges(&alive, 2, 0, 3000), 3);
        let all = Indication {
            track: TrackIndication::All,
            robot: RobotIndication::Connected,
            ..alive
        };
        assert!(
            (0..2000)
                .step_by(25)
                .all(|t| led_levels(&all, t)[1] && led_levels(&all, t)[2])
        );
        let dead = Indication {
            alive: false,
            ..alive
        };
        assert_eq!(count_rising_edges(&dead, 0, 0, 3000), 0);
    }
}
