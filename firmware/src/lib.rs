//! irtrackd: capture, processing loop, status LEDs, parameters and outputs.
//!
//! Data flow: a [`source::FrameSource`] feeds the [`engine::Engine`] on its own thread; results
//! go into a latest-value slot (`tokio::sync::watch`) that the stream server and the robot link
//! read; [`status::SharedStatus`] holds atomics that the LED driver, the status endpoint and the
//! systemd watchdog read. See docs/irtrackd.md.

#![deny(missing_docs)]

pub mod advice;
pub mod app;
pub mod blob_view;
pub mod calibration;
pub mod clock;
pub mod cluster;
pub mod config;
pub mod engine;
pub mod error;
pub mod frame_clocks;
pub mod leds;
pub mod metrics;
pub mod net;
pub mod outputs;
pub mod params;
pub mod ptp;
pub mod rt;
pub mod soak;
pub mod source;
pub mod status;
pub mod storage;
pub mod tuning;
pub mod update;
pub mod viewer;
pub mod watchdog;

pub use error::{FirmwareError, Result};
