//! Signed parameter blobs through irtrackd's parameter service: only trusted signatures pass
//! unless development mode allows unsigned blobs; stored blobs keep their signature and verify
//! again at start-up.

use std::sync::Arc;

use irtrack_core::param_wire::{RejectCode, Verdict};
use irtrack_core::params::RigParams;
use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::signing::{SignaturePolicy, SigningKey};
use irtrack_firmware::engine::ParamsHandle;
use irtrack_firmware::params::{ParamService, RigShape};
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::status::SharedStatus;
use irtrack_firmware::storage::{ParamStore, StoredSlot};

fn rig_and_shape() -> (RigParams, RigShape) {
    let sim = SimSource::new(&SimSourceConfig::default()).unwrap();
    (
        sim.scenario().rig().clone(),
        RigShape::of_set(&sim.allocate_set()),
    )
}

fn service(
    dir: &std::path::Path,
    shape: &RigShape,
    keys: &[&SigningKey],
    policy: SignaturePolicy,
) -> (ParamService, Arc<SharedStatus>) {
    let status = Arc::new(SharedStatus::new(2, "test".into(), "none".into()));
    let s = ParamService::new(
        ParamStore::open(dir).unwrap(),
        shape.clone(),
        TrackerConfig::default(),
        Arc::new(ParamsHandle::new()),
        Arc::clone(&status),
    )
    .with_signature_policy(keys.iter().map(|k| k.verifying_key()).collect(), policy);
    (s, status)
}

fn rejected(v: Verdict) -> (RejectCode, String) {
    match v {
        Verdict::Rejected { code, message } => (code, message),
        other => panic!("expected a rejection, got {other:?}"),
    }
}

#[test]
fn only_trusted_signatures_are_accepted_and_survive_restart() {
    let dir = std::env::temp_dir().join(format!("irtrackd-signing-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (mut rig, shape) = rig_and_shape();
    let trusted = SigningKey::from_bytes(&[7; 32]);
    let stranger = SigningKey::from_bytes(&[9; 32]);
    let (svc, status) = service(&dir, &shape, &[&trusted], SignaturePolicy::RequireSigned);

    let (code, msg) = rejected(svc.push(&rig.to_blob().unwrap()));
    assert_eq!(code, RejectCode::Unauthorized, "{msg}");
    assert!(msg.contains("unsigned") || msg.contains("not signed"), "{msg}");

    let (code, msg) = rejected(svc.push(&rig.to_signed_blob(&stranger).unwrap()));
    assert_eq!(code, RejectCode::Unauthorized, "{msg}");

    let mut forged = rig.to_signed_blob(&trusted).unwrap();
    *forged.last_mut().unwrap() ^= 0x01;
    let (code, msg) = rejected(svc.push(&forged));
    assert_eq!(code, RejectCode::Unauthorized, "{msg}");
    assert!(
        !status.params_info().loaded,
        "nothing may be active after rejected pushes"
    );
    assert_eq!(status.params_info().rejected, 3);
    assert_eq!(
        ParamStore::open(&dir).unwrap().read(StoredSlot::Active).unwrap(),
        None
    );

    rig.rig_id = "signed-rig".into();
    let signed = rig.to_signed_blob(&trusted).unwrap();
    assert_eq!(
        svc.push(&signed),
        Verdict::Accepted {
            rig_id: "signed-rig".into()
        }
    );
    // Stored byte for byte, signature included.
    let stored = ParamStore::open(&dir).unwrap().read(StoredSlot::Active).unwrap();
    assert_eq!(stored.as_deref(), Some(&signed[..]));

    // Restart with the same key: the stored set verifies and loads.
    let (svc2, status2) = service(&dir, &shape, &[&trusted], SignaturePolicy::RequireSigned);
    assert!(svc2.load_stored());
    assert_eq!(status2.params_info().rig_id.as_deref(), Some("signed-rig"));
    // Restart after the key was removed from the trusted list: the set no longer loads.
    let (svc3, status3) = service(&dir, &shape, &[&stranger], SignaturePolicy::RequireSigned);
    assert!(!svc3.load_stored());
    assert!(!status3.params_info().loaded);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn development_mode_accepts_unsigned_but_still_checks_signatures() {
    let dir = std::env::temp_dir().join(format!("irtrackd-signing-dev-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (rig, shape) = rig_and_shape();
    let trusted = SigningKey::from_bytes(&[7; 32]);
    let stranger = SigningKey::from_bytes(&[9; 32]);
    let (svc, _status) = service(&dir, &shape, &[&trusted], SignaturePolicy::AllowUnsigned);
    assert_eq!(svc.signature_policy(), SignaturePolicy::AllowUnsigned);
    assert!(matches!(
        svc.push(&rig.to_blob().unwrap()),
        Verdict::Accepted { .. }
    ));
    assert!(matches!(
        svc.push(&rig.to_signed_blob(&trusted).unwrap()),
        Verdict::Accepted { .. }
    ));
    let (code, _) = rejected(svc.push(&rig.to_signed_blob(&stranger).unwrap()));
    assert_eq!(code, RejectCode::Unauthorized);
    std::fs::remove_dir_all(&dir).unwrap();
}

mod common;

/// The whole service as configured by `[params]`: the default trusts nobody, a key directory
/// makes its `*.pub` keys trusted, the status shows the policy and key ids, and a broken key
/// file stops the start with an error naming the file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn config_params_table_decides_who_may_push() {
    use irtrack_core::signing::{KeyId, public_key_file};
    use irtrack_firmware::app::{self, Overrides};

    let dir = common::TempDir::new("signing-config");
    let (rig, _) = rig_and_shape();
    let trusted = SigningKey::from_bytes(&[21; 32]);
    let stranger = SigningKey::from_bytes(&[22; 32]);
    let keys_dir = dir.path().join("trusted-keys");
    std::fs::create_dir_all(&keys_dir).unwrap();
    std::fs::write(
        keys_dir.join("shop.pub"),
        public_key_file(&trusted.verifying_key()),
    )
    .unwrap();
    // Not a *.pub file: ignored, even though it holds a key.
    std::fs::write(
        keys_dir.join("notes.txt"),
        public_key_file(&stranger.verifying_key()),
    )
    .unwrap();

    // 1. Out of the box: nothing trusted, every push rejected, status says so.
    let mut cfg = common::test_config(&dir.path().join("state-default"));
    cfg.params = Default::default();
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let st = common::status_json(running.addrs.status).await;
    assert_eq!(st["params"]["signature_policy"], "require_signed", "{st}");
    assert_eq!(st["params"]["trusted_keys"].as_array().unwrap().len(), 0);
    for blob in [rig.to_blob().unwrap(), rig.to_signed_blob(&trusted).unwrap()] {
        match common::push_verdict(running.addrs.params, &blob).await {
            Verdict::Rejected { code, message } => {
                assert_eq!(code, RejectCode::Unauthorized);
                assert!(message.contains("trusts no signing key"), "{message}");
            }
            v => panic!("accepted without trusted keys: {v:?}"),
        }
    }
    running.shutdown().await;

    // 2. A key directory: only its key signs; unsigned and foreign signatures are refused.
    let mut cfg = common::test_config(&dir.path().join("state-keys"));
    cfg.params.allow_unsigned = false;
    cfg.params.trusted_keys = vec![keys_dir.clone()];
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let st = common::status_json(running.addrs.status).await;
    assert_eq!(st["params"]["signature_policy"], "require_signed");
    let id = KeyId::of(&trusted.verifying_key()).to_string();
    assert_eq!(st["params"]["trusted_keys"], serde_json::json!([id]), "{st}");
    let Verdict::Rejected { code, message } =
        common::push_verdict(running.addrs.params, &rig.to_blob().unwrap()).await
    else {
        panic!("unsigned blob accepted in production mode")
    };
    assert_eq!(code, RejectCode::Unauthorized);
    assert!(message.contains("not signed"), "{message}");
    let v = common::push_verdict(running.addrs.params, &rig.to_signed_blob(&stranger).unwrap()).await;
    assert!(
        matches!(
            v,
            Verdict::Rejected {
                code: RejectCode::Unauthorized,
                ..
            }
        ),
        "{v:?}"
    );
    let v = common::push_verdict(running.addrs.params, &rig.to_signed_blob(&trusted).unwrap()).await;
    assert!(matches!(v, Verdict::Accepted { .. }), "{v:?}");
    let st = common::status_json(running.addrs.status).await;
    assert_eq!(st["params"]["loaded"], true);
    assert_eq!(st["params"]["signature"], format!("key {id}"), "{st}");
    assert_eq!(st["params"]["rejected"], 2);
    running.shutdown().await;

    // 3. Development mode is visible.
    let mut cfg = common::test_config(&dir.path().join("state-dev"));
    cfg.params.allow_unsigned = true;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let st = common::status_json(running.addrs.status).await;
    assert_eq!(st["params"]["signature_policy"], "allow_unsigned");
    assert!(matches!(
        common::push_verdict(running.addrs.params, &rig.to_blob().unwrap()).await,
        Verdict::Accepted { .. }
    ));
    let st = common::status_json(running.addrs.status).await;
    assert_eq!(st["params"]["signature"], "unsigned", "{st}");
    running.shutdown().await;

    // 4. A broken or missing key file stops the start and names the file.
    let bad = dir.path().join("broken.pub");
    std::fs::write(&bad, "not a key\n").unwrap();
    for path in [bad, dir.path().join("missing.pub")] {
        let mut cfg = common::test_config(&dir.path().join("state-bad"));
        cfg.params.trusted_keys = vec![path.clone()];
        let err = match app::start(cfg, Overrides::default()).await {
            Ok(_) => panic!("started with key file {}", path.display()),
            Err(e) => e.to_string(),
        };
        assert!(
            err.contains("trusted_keys") && err.contains(&*path.to_string_lossy()),
            "{err}"
        );
    }
}
