//! Network services. Each takes its bound listener and a shutdown future, so tests can bind
//! `127.0.0.1:0` and stop them deterministically.

pub mod advice;
pub mod auth;
pub mod live;
pub mod params;
pub mod status;
pub mod stream;
