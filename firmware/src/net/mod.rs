//! Network services. Each takes its bound listener and a shutdown future, so tests can bind
//! `127.0.0.1:0` and stop them deterministically.
//!
//! The status listener's modules form layers without cycles: `http` (shared text helpers and
//! the Host/Origin rules) ← `auth` ← `status` (state and its own answers) ← `live` (set-up
//! view endpoints, `advice`) ← `server` (routes, limits, accept loop). `limit` holds the connection caps
//! of every listener.

pub mod advice;
pub mod auth;
pub mod http;
pub mod limit;
pub mod live;
pub mod params;
mod previews;
pub mod server;
pub mod status;
pub mod stream;
pub mod update;
