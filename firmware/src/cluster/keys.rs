//! Credentials pushed like parameter sets (docs/cluster.md, "Pushing credentials"): the
//! board's own X25519 key pair (made at its first start, kept in the state directory, its
//! public key in `/status` → `cluster.box_public_key`), and the parameter port's handler for
//! sealed credential envelopes (`irtrack_cluster::envelope`, docs/cluster-envelope.md).
//!
//! An accepted envelope's secret is stored (mode 0600) in `<state>/cluster-credentials/` with
//! its serial and **takes effect at the next start**: the solver's dictionary and a board's
//! password must change together (a board with a new password is refused by a solver with the
//! old dictionary), so the operator picks the moment, pushes to all of them, then restarts
//! them; a live switch would also re-open the Zenoh session under the running loop.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use irtrack_cluster::envelope::{self, BoxKey, Recipient, SecretKind};
use irtrack_core::param_wire::{RejectCode, Verdict};
use irtrack_core::signing::VerifyingKey;

use super::{ClusterConfig, Role, SharedReport};
use crate::error::{FirmwareError, Result};

/// The board's X25519 secret key file in the state directory.
pub const BOX_KEY_FILE: &str = "cluster-box.key";
/// Where pushed credentials are kept in the state directory.
pub const PUSHED_DIR: &str = "cluster-credentials";
/// The serial of the last accepted envelope, in [`PUSHED_DIR`].
const SERIAL_FILE: &str = "serial";

/// The pushed secret's file for `role` under `state_dir`.
pub fn pushed_file(state_dir: &Path, role: Role) -> PathBuf {
    let name = match role {
        Role::Solver => "solver.credentials",
        _ => "board.password",
    };
    state_dir.join(PUSHED_DIR).join(name)
}

/// The pushed TLS file for `role` under `state_dir`: the solver's certificate and key in one
/// PEM file, or the solver certificate a camera board pins.
pub fn pushed_tls_file(state_dir: &Path, role: Role) -> PathBuf {
    let name = match role {
        Role::Solver => "solver.tls.pem",
        _ => "solver.tls.crt",
    };
    state_dir.join(PUSHED_DIR).join(name)
}

/// The kinds of secret `role` takes: its credentials, and its TLS file.
fn kinds_for(role: Role) -> [SecretKind; 2] {
    match role {
        Role::Solver => [SecretKind::SolverDictionary, SecretKind::SolverTls],
        _ => [SecretKind::BoardPassword, SecretKind::PinnedSolverCertificate],
    }
}

fn is_tls(kind: SecretKind) -> bool {
    matches!(kind, SecretKind::SolverTls | SecretKind::PinnedSolverCertificate)
}

fn read_serial(dir: &Path) -> Option<u64> {
    std::fs::read_to_string(dir.join(SERIAL_FILE))
        .ok()?
        .trim()
        .parse()
        .ok()
}

impl ClusterConfig {
    /// Without `password_file` (camera) / `credentials_file` (solver) in the config, takes the
    /// pushed credentials in `state_dir` when there are any; returns the file taken (also when
    /// it was taken before).
    pub fn adopt_pushed_credentials(&mut self, state_dir: &Path) -> Option<PathBuf> {
        let slot = match self.role {
            Role::Camera => &mut self.password_file,
            Role::Solver => &mut self.credentials_file,
            Role::Standalone => return None,
        };
        let file = pushed_file(state_dir, self.role);
        let taken = if slot.as_ref() == Some(&file) {
            Some(file)
        } else if slot.is_some() || !file.exists() {
            None
        } else {
            *slot = Some(file.clone());
            Some(file)
        };
        self.adopt_pushed_tls(state_dir);
        taken
    }

    /// Without TLS files in the config, takes the pushed one when there is one (the solver's
    /// certificate and key are in one file).
    fn adopt_pushed_tls(&mut self, state_dir: &Path) {
        let file = pushed_tls_file(state_dir, self.role);
        if !file.exists() {
            return;
        }
        match self.role {
            Role::Solver if self.tls_certificate_file.is_none() && self.tls_key_file.is_none() => {
                self.tls_certificate_file = Some(file.clone());
                self.tls_key_file = Some(file.clone());
            }
            Role::Camera if self.tls_solver_certificate_file.is_none() => {
                self.tls_solver_certificate_file = Some(file.clone());
            }
            _ => return,
        }
        tracing::info!(file = %file.display(), "cluster transport: using the pushed TLS file");
    }
}

/// Takes credential envelopes for this board (camera board or solver).
pub struct Inbox {
    role: Role,
    board: String,
    dir: PathBuf,
    key: BoxKey,
    /// The config names its own credentials file: pushes are refused (it would be ignored).
    configured: Option<PathBuf>,
    /// Likewise its own TLS file.
    configured_tls: Option<PathBuf>,
    report: SharedReport,
    last_serial: Mutex<Option<u64>>,
}

impl std::fmt::Debug for Inbox {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Inbox({}, {:?})", self.board, self.key)
    }
}

impl Inbox {
    /// Loads (or at first start makes) the board's key pair and shows its public key in the
    /// report. `in_use`: the credentials in use came from an earlier push.
    pub fn open(cfg: &ClusterConfig, state_dir: &Path, report: SharedReport, in_use: bool) -> Result<Inbox> {
        let key_file = state_dir.join(BOX_KEY_FILE);
        let (key, made) = BoxKey::load_or_create(&key_file).map_err(|e| FirmwareError::Config {
            reason: e.to_string(),
        })?;
        let public = envelope::hex(&key.public());
        if made {
            tracing::info!(file = %key_file.display(), public_key = %public, "made this board's key pair for pushed cluster credentials");
        }
        let dir = state_dir.join(PUSHED_DIR);
        let last_serial = read_serial(&dir);
        let configured = match cfg.role {
            Role::Camera => cfg.password_file.clone(),
            Role::Solver => cfg.credentials_file.clone(),
            Role::Standalone => None,
        }
        .filter(|f| *f != pushed_file(state_dir, cfg.role));
        let configured_tls = match cfg.role {
            Role::Camera => cfg.tls_solver_certificate_file.clone(),
            Role::Solver => cfg.tls_certificate_file.clone(),
            Role::Standalone => None,
        }
        .filter(|f| *f != pushed_tls_file(state_dir, cfg.role));
        if let Ok(mut r) = report.lock() {
            r.box_public_key = Some(public);
            r.pushed_credentials = last_serial.map(|serial| super::report::PushedCredentialsReport {
                serial,
                signed_by: None,
                in_use,
                words: if in_use {
                    format!("in use: pushed credentials, serial {serial}")
                } else {
                    format!("stored (serial {serial}) but not in use: the config names its own file")
                },
            });
        }
        Ok(Inbox {
            role: cfg.role,
            board: cfg.board.clone(),
            dir,
            key,
            configured,
            configured_tls,
            report,
            last_serial: Mutex::new(last_serial),
        })
    }

    /// This board's public key.
    pub fn public_key(&self) -> [u8; 32] {
        self.key.public()
    }

    fn store(&self, secret: &str, serial: u64, kind: SecretKind) -> std::result::Result<PathBuf, String> {
        std::fs::create_dir_all(&self.dir)
            .map_err(|e| format!("cannot create {}: {e}", self.dir.display()))?;
        let name = if is_tls(kind) {
            pushed_tls_file(Path::new(""), self.role)
        } else {
            pushed_file(Path::new(""), self.role)
        };
        let file = self.dir.join(name.file_name().unwrap_or_default());
        irtrack_cluster::credentials::write_private(&file, secret).map_err(|e| e.to_string())?;
        // The serial after the secret: a crash between them leaves an older serial, which
        // accepts a replay of the stored envelope only (the same secret again).
        irtrack_cluster::credentials::write_private(&self.dir.join(SERIAL_FILE), &format!("{serial}\n"))
            .map_err(|e| e.to_string())?;
        Ok(file)
    }
}

fn reject(code: RejectCode, message: String) -> Verdict {
    Verdict::Rejected { code, message }
}

impl crate::params::CredentialInbox for Inbox {
    fn accept(&self, bytes: &[u8], trusted: &[VerifyingKey]) -> Verdict {
        let Ok(mut last) = self.last_serial.lock() else {
            return reject(RejectCode::Internal, "credential state poisoned".into());
        };
        let opened = match envelope::open(
            bytes,
            &Recipient {
                board: &self.board,
                key: &self.key,
                trusted,
                last_serial: *last,
            },
        ) {
            Ok(o) => o,
            Err(irtrack_cluster::ClusterError::Envelope { why, reason }) => {
                let code = RejectCode::from_wire(why.code()).unwrap_or(RejectCode::BadBlob);
                return reject(code, reason);
            }
            Err(e) => return reject(RejectCode::BadBlob, e.to_string()),
        };
        let want = kinds_for(self.role);
        let kind = opened.header.kind;
        if !want.contains(&kind) {
            return reject(
                RejectCode::RigMismatch,
                format!(
                    "the envelope holds {}, this board ({}) takes {} or {}",
                    kind.words(),
                    if self.role == Role::Solver {
                        "the solver"
                    } else {
                        "a camera board"
                    },
                    want[0].words(),
                    want[1].words()
                ),
            );
        }
        let configured = if is_tls(kind) {
            self.configured_tls.as_ref().map(|f| {
                (
                    f,
                    if self.role == Role::Solver {
                        "tls_certificate_file"
                    } else {
                        "tls_solver_certificate_file"
                    },
                )
            })
        } else {
            self.configured.as_ref().map(|f| {
                (
                    f,
                    if self.role == Role::Solver {
                        "credentials_file"
                    } else {
                        "password_file"
                    },
                )
            })
        };
        if let Some((f, key)) = configured {
            return reject(
                RejectCode::InvalidParams,
                format!(
                    "this board's {} comes from {} ([cluster] {key}); remove that key to take a pushed one",
                    kind.words(),
                    f.display()
                ),
            );
        }
        let serial = opened.header.serial;
        match self.store(&opened.secret, serial, kind) {
            Err(e) => reject(RejectCode::Storage, format!("{e}; the credentials in use stay")),
            Ok(file) => {
                *last = Some(serial);
                let signer = opened.header.key_id.to_string();
                tracing::warn!(
                    file = %file.display(),
                    serial,
                    signed_by = %signer,
                    "pushed cluster credentials stored; they take effect at the next start of irtrackd"
                );
                if let Ok(mut r) = self.report.lock() {
                    r.pushed_credentials = Some(super::report::PushedCredentialsReport {
                        serial,
                        signed_by: Some(signer),
                        in_use: false,
                        words: format!(
                            "stored (serial {serial}); takes effect at the next start of irtrackd"
                        ),
                    });
                }
                Verdict::Accepted {
                    rig_id: format!("credentials-{}-{serial}", self.board),
                }
            }
        }
    }
}
