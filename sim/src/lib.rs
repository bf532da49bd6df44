//! irtrack-sim: simulated multi-camera IR-LED tracking rigs.
//!
//! [`Scenario`] renders 8- or 10-bit frames of IR LEDs moving along a [`Trajectory`] as seen by a
//! virtual rig (presets for the paper's parallel and 90° convergent set-ups), with sensor noise,
//! saturation, lens distortion, motion blur, ambient clutter and dropped frames, and gives the
//! ground truth for every frame. [`resolution`] is the analytic planner behind `host-tools plan`.

// Every public item says what it is for (issue 24).
#![deny(missing_docs)]

pub mod backdrop;
pub mod checkerboard;
pub mod error;
pub mod multibody;
pub mod noise;
pub mod resolution;
pub mod rig;
pub mod scenario;
pub mod timing;
pub mod tools;
pub mod trajectory;
pub mod wand;

pub use backdrop::Backdrop;
pub use error::SimError;
pub use rig::{CameraSpec, RigPreset};
pub use scenario::{
    BitDepth, Body, Clutter, FrameInfo, FrameTruth, MarkerSpec, MarkerTruth, Scenario, SensorSpec, SimConfig,
};
pub use timing::{FrameTime, SimCameraTiming, TimingLists};
pub use trajectory::{Orientation, Trajectory};
