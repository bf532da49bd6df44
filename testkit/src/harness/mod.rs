//! Running irtrackd (and other workspace binaries) for system tests, the demo, the soak and the
//! image system test, and talking to it.
//!
//! - [`process`]: child processes killed on every path out, stdout lines, temporary
//!   directories kept after a failure, workspace binaries next to a test.
//! - [`irtrackd`]: a config builder, start with ephemeral ports up to the ready line, the ready
//!   line's addresses, graceful shutdown, the operator's password hash.
//! - [`http`]: plain-HTTP requests (ureq) with optional operator sign-in (HTTP Basic).
//! - [`ws`]: the live WebSocket (`/api/live`, tungstenite).
//! - [`json`]: reading fields of status documents by dotted path (serde_json).
//!
//! Everything returns [`Error`]; callers that are tests unwrap, xtask adds context.

pub mod http;
pub mod irtrackd;
pub mod json;
pub mod process;
pub mod ws;

mod error;

pub use error::{Error, Result};
pub use http::Http;
pub use irtrackd::{Irtrackd, IrtrackdConfig, OPERATOR_USER, Ready, operator_hash};
pub use process::{Proc, TempDir, workspace_bin};
pub use ws::LiveSocket;
