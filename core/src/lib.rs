//! irtrack-core: everything the board and the PC share.
//!
//! `no_std` + `alloc` without the default `std` feature; nalgebra then uses `libm`.
//! Per-frame code (blob detection, undistortion, triangulation) never allocates:
//! callers own every buffer.
#![cfg_attr(not(feature = "std"), no_std)]
#![forbid(unsafe_code)]
#![deny(missing_docs)]

extern crate alloc;

pub mod blob;
pub mod camera;
pub mod clock_model;
pub mod crc;
pub mod error;
pub mod filter;
pub mod frameset;
pub mod image;
pub mod observation;
pub mod param_wire;
pub mod params;
pub mod pgm;
pub mod pipeline;
pub mod pose6d;
pub mod registration;
pub mod retime;
pub mod robot_proto;
pub mod signing;
pub mod simd;
pub mod slots;
pub mod stream;
pub mod timing;
pub mod triangulate;

pub use error::{Error, Result};
