//! Parameter sets: validation against the running rig, durable storage, swap into the loop.

use std::sync::Arc;

use irtrack_core::param_wire::{PushOptions, RejectCode, Verdict};
use irtrack_core::params::{BlobHeader, RigParams};
use irtrack_core::pipeline::{Tracker, TrackerConfig};
use irtrack_core::pose6d::{MultiTracker, PoseConfig};
use irtrack_core::signing::{self, KeyId, SignaturePolicy, SignatureStatus, VerifyingKey};

use crate::engine::{ActiveParams, ParamsHandle};
use crate::error::{FirmwareError, Result};
use crate::source::FrameSet;
use crate::status::SharedStatus;
use crate::storage::{ParamStore, StoredSlot};

/// What the running source looks like; parameter sets must match it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RigShape {
    /// (width, height) per camera.
    pub image_sizes_px: Vec<(u32, u32)>,
}

impl RigShape {
    /// The shape of the frames in `set` (the running source's).
    pub fn of_set(set: &FrameSet) -> Self {
        Self {
            image_sizes_px: set.frames.iter().map(|f| (f.width_px, f.height_px)).collect(),
        }
    }

    /// Checks camera count and image sizes; the error says exactly what differs.
    pub fn check(&self, rig: &RigParams) -> std::result::Result<(), String> {
        if rig.cameras.len() != self.image_sizes_px.len() {
            return Err(format!(
                "parameter set {:?} has {} cameras, this rig has {}",
                rig.rig_id,
                rig.cameras.len(),
                self.image_sizes_px.len()
            ));
        }
        for (i, (c, &(w, h))) in rig.cameras.iter().zip(&self.image_sizes_px).enumerate() {
            let s = c.model.image_size;
            if (s.width_px, s.height_px) != (w, h) {
                return Err(format!(
                    "camera {i}: parameters are for {}x{} px images, the camera delivers {w}x{h}",
                    s.width_px, s.height_px
                ));
            }
        }
        Ok(())
    }
}

/// Validates, stores and activates parameter sets.
#[derive(Debug)]
pub struct ParamService {
    store: ParamStore,
    shape: RigShape,
    tracker_cfg: TrackerConfig,
    handle: Arc<ParamsHandle>,
    status: Arc<SharedStatus>,
    /// Pushes are handled one at a time (storage order must match activation order).
    busy: std::sync::Mutex<()>,
    /// Keys whose signatures are accepted, and whether unsigned blobs pass (development mode).
    trusted_keys: Vec<VerifyingKey>,
    policy: SignaturePolicy,
    /// Settings the loop's 6-DOF tracker uses; a set whose tool they refuse is rejected.
    pose_cfg: PoseConfig,
    /// `[robot] tool`: a set without a tool of this name is rejected.
    robot_tool: Option<String>,
    /// Where pushed credential envelopes go (cluster roles); none: they are refused.
    credentials: Option<Arc<dyn CredentialInbox>>,
}

/// The policy's name in status and logs.
pub fn policy_name(policy: SignaturePolicy) -> &'static str {
    match policy {
        SignaturePolicy::RequireSigned => "require_signed",
        SignaturePolicy::AllowUnsigned => "allow_unsigned",
    }
}

/// First bytes of a sealed credential envelope (`irtrack_cluster::envelope`,
/// docs/cluster-envelope.md), pushed on the parameter port like a parameter blob.
pub const CREDENTIAL_ENVELOPE_MAGIC: [u8; 4] = *b"IRCK";

/// Takes sealed credential envelopes pushed on the parameter port (cluster camera boards and
/// solvers): they are signed by the same trusted keys as parameter sets.
pub trait CredentialInbox: Send + Sync + std::fmt::Debug {
    /// Verifies, opens and stores one envelope; the verdict as for a parameter set.
    fn accept(&self, envelope: &[u8], trusted: &[VerifyingKey]) -> Verdict;
}

fn reject(code: RejectCode, message: String) -> Verdict {
    Verdict::Rejected { code, message }
}

impl ParamService {
    /// The service's shared status (counters of the parameter listener live there).
    pub fn status(&self) -> &Arc<SharedStatus> {
        &self.status
    }

    /// A service that stores accepted sets in `store`, checks them against the source's
    /// `shape` and installs them into `handle`; unsigned sets are accepted until
    /// [`ParamService::with_signature_policy`] says otherwise.
    pub fn new(
        store: ParamStore,
        shape: RigShape,
        tracker_cfg: TrackerConfig,
        handle: Arc<ParamsHandle>,
        status: Arc<SharedStatus>,
    ) -> Self {
        status.update_params_info(|p| p.signature_policy = policy_name(SignaturePolicy::AllowUnsigned));
        Self {
            store,
            shape,
            tracker_cfg,
            handle,
            status,
            busy: std::sync::Mutex::new(()),
            trusted_keys: Vec::new(),
            policy: SignaturePolicy::AllowUnsigned,
            pose_cfg: PoseConfig::default(),
            robot_tool: None,
            credentials: None,
        }
    }

    /// Takes credential envelopes pushed on this port (cluster roles).
    pub fn with_credential_inbox(mut self, inbox: Option<Arc<dyn CredentialInbox>>) -> Self {
        self.credentials = inbox;
        self
    }

    /// The 6-DOF settings of the processing loop (`[pose]`), so that tools are checked with
    /// the same limits the loop applies.
    pub fn with_pose_config(mut self, cfg: PoseConfig) -> Self {
        self.pose_cfg = cfg;
        self
    }

    /// The robot link's tool (`[robot] tool`): sets that lack it are refused, naming it and
    /// the set's tools.
    pub fn with_robot_tool(mut self, name: Option<String>) -> Self {
        self.robot_tool = name;
        self
    }

    /// Sets the signature policy for pushed and stored blobs. Without this call the service
    /// accepts unsigned blobs and no signed ones (no trusted keys).
    pub fn with_signature_policy(mut self, trusted_keys: Vec<VerifyingKey>, policy: SignaturePolicy) -> Self {
        let ids: Vec<String> = trusted_keys.iter().map(|k| KeyId::of(k).to_string()).collect();
        match policy {
            SignaturePolicy::AllowUnsigned => {
                tracing::warn!("development mode: unsigned parameter blobs are accepted")
            }
            SignaturePolicy::RequireSigned if trusted_keys.is_empty() => tracing::warn!(
                "no trusted keys configured ([params] trusted_keys): every parameter push will be rejected"
            ),
            SignaturePolicy::RequireSigned => {
                tracing::info!(keys = ?ids, "parameter blobs must be signed by a trusted key")
            }
        }
        self.status.update_params_info(|p| {
            p.signature_policy = policy_name(policy);
            p.trusted_keys = ids;
        });
        self.trusted_keys = trusted_keys;
        self.policy = policy;
        self
    }

    /// Which signatures a pushed set needs.
    pub fn signature_policy(&self) -> SignaturePolicy {
        self.policy
    }

    /// Where accepted sets are handed to the loop.
    pub fn handle(&self) -> &Arc<ParamsHandle> {
        &self.handle
    }

    /// Decodes and checks a blob without storing it. The signature is checked first (before
    /// the body is decoded); signature problems give `UNAUTHORIZED`. Returns the set, its CRC
    /// and the id of the key that signed it (`None`: unsigned, development mode).
    pub fn check_blob(&self, blob: &[u8]) -> std::result::Result<(RigParams, u32, Option<KeyId>), Verdict> {
        if self.policy == SignaturePolicy::RequireSigned && self.trusted_keys.is_empty() {
            // Say what to fix on the device rather than blaming the blob.
            return Err(reject(
                RejectCode::Unauthorized,
                "this irtrackd trusts no signing key yet: list the public key from `host-tools keygen` in \
                 [params] trusted_keys of irtrackd.toml (or set allow_unsigned = true for development)"
                    .into(),
            ));
        }
        let (rig, auth) = signing::verify_blob(blob, &self.trusted_keys, self.policy)
            .map_err(|e| signing::verdict_for(&e))?;
        let signed_by = match auth {
            SignatureStatus::Signed { key_id } => {
                tracing::debug!(%key_id, rig_id = %rig.rig_id, "parameter blob signature verified");
                Some(key_id)
            }
            SignatureStatus::UnsignedAccepted => None,
        };
        self.check_rig(&rig)?;
        // The set's id does not depend on signing (docs/param-blob.md): the same parameters
        // carry the same `params_crc` whether pushed signed or not.
        let crc = rig.params_crc().map_err(|e| Verdict::from_error(&e))?;
        Ok((rig, crc, signed_by))
    }

    /// Contents checks: validation, fit to the running rig, a tracker accepts the set.
    fn check_rig(&self, rig: &RigParams) -> std::result::Result<(), Verdict> {
        rig.validate().map_err(|e| Verdict::from_error(&e))?;
        self.shape
            .check(rig)
            .map_err(|m| reject(RejectCode::RigMismatch, m))?;
        // Building a tracker here means the loop's swap cannot fail later.
        Tracker::new(rig, self.tracker_cfg)
            .map_err(|e| reject(RejectCode::InvalidParams, format!("tracker refuses the set: {e}")))?;
        // The loop tracks every tool in 6-DOF; a tool it cannot identify (symmetric layout,
        // LEDs too close) or two tools it could confuse must not be accepted only to fall back
        // to single-marker output.
        crate::engine::robot_tool_index(
            self.robot_tool.as_deref(),
            rig.tools.iter().map(|t| t.name.as_str()),
        )
        .map_err(|m| reject(RejectCode::InvalidParams, m))?;
        // The same tracker the loop builds (every tool at once; a single tool is named).
        if !rig.tools.is_empty() {
            MultiTracker::new(rig, &rig.tools, self.pose_cfg).map_err(|e| {
                let message = match rig.tools.as_slice() {
                    [one] => format!("6-DOF tracker refuses tool `{}`: {e}", one.name),
                    _ => format!("6-DOF tracker refuses the tools: {e}"),
                };
                reject(RejectCode::InvalidParams, message)
            })?;
        }
        Ok(())
    }

    /// Handles one pushed blob: check, store durably, activate. Blocking (fsync). A set older
    /// than the active one is refused ([`Self::push_with`] can allow it).
    pub fn push(&self, blob: &[u8]) -> Verdict {
        self.push_with(blob, PushOptions::default())
    }

    /// [`Self::push`] with the request's options: `allow_rollback` lets an older set replace
    /// the active one (logged and counted as an allowed rollback).
    pub fn push_with(&self, blob: &[u8], options: PushOptions) -> Verdict {
        let Ok(_guard) = self.busy.try_lock() else {
            return reject(RejectCode::Busy, "another parameter push is being stored".into());
        };
        if blob.starts_with(&CREDENTIAL_ENVELOPE_MAGIC) {
            // Always signed: development mode's unsigned sets do not extend to secrets.
            let verdict = match &self.credentials {
                Some(inbox) => inbox.accept(blob, &self.trusted_keys),
                None => reject(
                    RejectCode::BadBlob,
                    "a cluster credential envelope, but this irtrackd takes none (not a camera board or solver of an irtrackd built with the cluster feature)".into(),
                ),
            };
            self.note_rejection(&verdict);
            return verdict;
        }
        let verdict = match self.check_blob(blob).and_then(|(rig, crc, signed_by)| {
            let rollback = self.check_rollback(&rig, options)?;
            Ok((rig, crc, signed_by, rollback))
        }) {
            Err(v) => v,
            Ok((rig, crc, signed_by, rollback)) => match self.store.store(blob) {
                Err(e) => reject(RejectCode::Storage, format!("{e}; the previous set stays active")),
                Ok(()) => {
                    let rig_id = rig.rig_id.clone();
                    if let Some(text) = rollback {
                        // Counted once it happened: a storage failure above is no rollback.
                        tracing::warn!(event = %text, "rollback allowed by the push: an older parameter set replaces the active one");
                        self.status.update_params_info(|p| {
                            p.rollbacks_allowed += 1;
                            p.last_rollback = Some(text);
                        });
                    }
                    self.activate(rig, crc, "pushed", signed_by);
                    Verdict::Accepted { rig_id }
                }
            },
        };
        self.note_rejection(&verdict);
        verdict
    }

    /// Refuses a set older than the active one (serials when both have one, creation times
    /// otherwise; `RigParams::is_older_than`) unless the push allows a rollback; then it returns
    /// the allowed rollback in words (logged and counted once the set is active). A refusal is
    /// counted here and logged with the rejection.
    fn check_rollback(
        &self,
        rig: &RigParams,
        options: PushOptions,
    ) -> std::result::Result<Option<String>, Verdict> {
        let Some(active) = self.handle.current() else {
            return Ok(None);
        };
        if !rig.is_older_than(&active.rig) {
            return Ok(None);
        }
        let (pushed, current) = (rig.age_label(), active.rig.age_label());
        if options.allow_rollback {
            return Ok(Some(format!("allowed: {pushed} replaced the newer {current}")));
        }
        let message = format!(
            "parameter set {pushed} is older than the active set {current}; refused so that an old \
             set cannot replace a newer one (push it with --allow-rollback if you mean to go back)"
        );
        let text = format!("refused: {pushed} is older than the active {current}");
        self.status.update_params_info(|p| {
            p.rollbacks_refused += 1;
            p.last_rollback = Some(text);
        });
        Err(reject(RejectCode::Rollback, message))
    }

    /// Counts and logs a rejection (also for framing errors caught by the endpoint).
    pub fn note_rejection(&self, verdict: &Verdict) {
        if let Verdict::Rejected { code, message } = verdict {
            tracing::warn!(%code, %message, "parameter push rejected");
            let text = format!("{code} {message}");
            self.status.update_params_info(|p| {
                p.rejected += 1;
                p.last_rejection = Some(text);
            });
        }
    }

    fn activate(&self, rig: RigParams, crc: u32, origin: &str, signed_by: Option<KeyId>) {
        let signature = signed_by.map_or_else(|| "unsigned".to_string(), |id| format!("key {id}"));
        tracing::info!(rig_id = %rig.rig_id, crc = format_args!("{crc:08x}"), origin, %signature, "parameter set active");
        self.status.update_params_info(|p| {
            p.signature = Some(signature);
            p.loaded = true;
            p.rig_id = Some(rig.rig_id.clone());
            p.created_unix_s = Some(rig.created_unix_s);
            p.serial = (rig.serial != 0).then_some(rig.serial);
            p.set_calibration(rig.calibration.as_deref());
            p.origin = Some(origin.to_string());
            p.swaps += 1;
        });
        self.handle.install(ActiveParams { rig, crc });
    }

    /// Loads the stored set at start: the active file, else the previous one (rollback).
    /// Returns whether a set is active; a missing or unusable store is logged, not fatal.
    pub fn load_stored(&self) -> bool {
        for (slot, origin) in [
            (StoredSlot::Active, "state_dir"),
            (StoredSlot::Previous, "rollback"),
        ] {
            let path = self.store.path(slot);
            match self.store.read(slot) {
                Ok(None) => {}
                Ok(Some(blob)) => match self.check_blob(&blob) {
                    Ok((rig, crc, signed_by)) => {
                        if slot == StoredSlot::Previous {
                            tracing::warn!(path = %path.display(), "active parameter file unusable; rolled back to the previous set");
                        }
                        self.activate(rig, crc, origin, signed_by);
                        return true;
                    }
                    Err(v) => {
                        tracing::error!(path = %path.display(), verdict = %v.to_line().trim_end(), "stored parameter set unusable")
                    }
                },
                Err(e) => tracing::error!(error = %e, "cannot read stored parameters"),
            }
        }
        tracing::warn!(dir = %self.store.dir().display(), "no valid parameter set: running without positions until one is pushed");
        false
    }

    /// Activates a set that did not come through the wire (simulator ground truth).
    pub fn install_unstored(&self, rig: RigParams, origin: &str) -> Result<()> {
        // Not from the network, so no signature to check; the CRC names the set in records.
        let blob = rig.to_blob()?;
        self.check_rig(&rig)
            .map_err(|v| FirmwareError::RigMismatch { reason: v.to_line() })?;
        let crc = BlobHeader::parse(&blob)?.crc32;
        self.activate(rig, crc, origin, None);
        Ok(())
    }
}
