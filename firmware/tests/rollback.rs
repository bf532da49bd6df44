//! No rollback by default (issue 41, item 3; docs/param-protocol.md "Rollback"): a pushed
//! set older than the active one is refused with `ROLLBACK` naming both, unless the push sets
//! the allow-rollback flag; refusals and allowed rollbacks are counted on `/status` and
//! `/metrics`, and a refused set never reaches the store, so the newer set survives a restart.
//! Pushes go through irtrackd's real parameter endpoint on 127.0.0.1.

use std::net::SocketAddr;
use std::sync::Arc;

use irtrack_core::param_wire::{PushOptions, RejectCode, Verdict, encode_push, encode_push_with};
use irtrack_core::params::RigParams;
use irtrack_core::pipeline::TrackerConfig;
use irtrack_firmware::engine::ParamsHandle;
use irtrack_firmware::params::{ParamService, RigShape};
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::status::SharedStatus;
use irtrack_firmware::storage::ParamStore;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// 2023-11-14 22:13:20 UTC and 2026-09-21 14:13 UTC (as in the issue: cell-v1 from 2023-11,
/// cell-v2 from 2026-09).
const NOV_2023: u64 = 1_700_000_000;
const SEP_2026: u64 = 1_790_000_000;

fn rig_and_shape() -> (RigParams, RigShape) {
    let sim = SimSource::new(&SimSourceConfig::default()).unwrap();
    (
        sim.scenario().rig().clone(),
        RigShape::of_set(&sim.allocate_set()),
    )
}

/// `cell-v2` (created 2026-09) and `cell-v1` (created 2023-11, camera 1 moved 10 mm).
fn cell_sets() -> (RigParams, RigParams, RigShape) {
    let (base, shape) = rig_and_shape();
    let v2 = RigParams {
        rig_id: "cell-v2".into(),
        created_unix_s: SEP_2026,
        ..base.clone()
    };
    let mut v1 = RigParams {
        rig_id: "cell-v1".into(),
        created_unix_s: NOV_2023,
        ..base
    };
    v1.cameras[1].cam_from_cam0.t_mm[0] += 10.0;
    (v2, v1, shape)
}

/// A running parameter endpoint (as irtrackd starts it) on a state directory.
struct Device {
    addr: SocketAddr,
    status: Arc<SharedStatus>,
    handle: Arc<ParamsHandle>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl Device {
    /// Starts like irtrackd does: the stored set is loaded, then pushes are served.
    async fn start(dir: &std::path::Path, shape: &RigShape) -> Device {
        let status = Arc::new(SharedStatus::new(2, "test".into(), "none".into()));
        let handle = Arc::new(ParamsHandle::new());
        let service = ParamService::new(
            ParamStore::open(dir).unwrap(),
            shape.clone(),
            TrackerConfig::default(),
            Arc::clone(&handle),
            Arc::clone(&status),
        );
        service.load_stored();
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(irtrack_firmware::net::params::serve(
            listener,
            Arc::new(service),
            async move {
                let _ = stopped.await;
            },
        ));
        Device {
            addr,
            status,
            handle,
            stop: Some(stop),
            task,
        }
    }

    async fn push_raw(&self, request: &[u8]) -> Verdict {
        let mut s = TcpStream::connect(self.addr).await.unwrap();
        s.write_all(request).await.unwrap();
        let mut line = String::new();
        s.read_to_string(&mut line).await.unwrap();
        Verdict::parse_line(&line).unwrap()
    }

    async fn push(&self, rig: &RigParams) -> Verdict {
        self.push_raw(&encode_push(&rig.to_blob().unwrap())).await
    }

    async fn push_allowing_rollback(&self, rig: &RigParams) -> Verdict {
        let request = encode_push_with(&rig.to_blob().unwrap(), PushOptions { allow_rollback: true });
        self.push_raw(&request).await
    }

    fn active_id(&self) -> Option<String> {
        self.handle.current().map(|a| a.rig.rig_id.clone())
    }

    async fn stop(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        self.task.await.unwrap();
    }
}

fn rejected(v: Verdict) -> (RejectCode, String) {
    match v {
        Verdict::Rejected { code, message } => (code, message),
        other => panic!("expected a rejection, got {other:?}"),
    }
}

fn temp_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("irtrackd-rollback-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[tokio::test]
async fn an_older_set_is_refused_unless_the_push_allows_it_and_the_newer_survives_restart() {
    let dir = temp_dir("dates");
    let (v2, v1, shape) = cell_sets();
    let dev = Device::start(&dir, &shape).await;

    assert_eq!(
        dev.push(&v2).await,
        Verdict::Accepted {
            rig_id: "cell-v2".into()
        }
    );
    let (code, message) = rejected(dev.push(&v1).await);
    assert_eq!(code, RejectCode::Rollback, "{message}");
    println!("refusal: ERR {code} {message}");
    for words in [
        "cell-v1 (no serial, created 2023-11-14 22:13 UTC)",
        "is older than the active set",
        "cell-v2 (no serial, created 2026-09-21",
        "--allow-rollback",
    ] {
        assert!(message.contains(words), "{words:?} missing from {message:?}");
    }
    assert_eq!(dev.active_id().as_deref(), Some("cell-v2"));
    let info = dev.status.params_info();
    assert_eq!(
        (info.rollbacks_refused, info.rollbacks_allowed, info.rejected),
        (1, 0, 1)
    );
    let last = info.last_rollback.unwrap();
    assert!(
        last.starts_with("refused: cell-v1") && last.contains("cell-v2"),
        "{last}"
    );
    assert!(
        dev.status
            .prometheus()
            .contains("irtrackd_params_rollbacks_refused_total 1"),
        "{}",
        dev.status.prometheus()
    );
    // The same set pushed again is not a rollback.
    assert!(dev.push(&v2).await.is_accepted());

    // Restart: the refused set was never stored, the newer one comes back.
    dev.stop().await;
    let dev = Device::start(&dir, &shape).await;
    assert_eq!(dev.active_id().as_deref(), Some("cell-v2"));
    assert_eq!(dev.status.params_info().origin.as_deref(), Some("state_dir"));

    // The operator allows it for this push: accepted, counted, and it is what a restart loads.
    assert_eq!(
        dev.push_allowing_rollback(&v1).await,
        Verdict::Accepted {
            rig_id: "cell-v1".into()
        }
    );
    assert_eq!(dev.active_id().as_deref(), Some("cell-v1"));
    let info = dev.status.params_info();
    assert_eq!((info.rollbacks_refused, info.rollbacks_allowed), (0, 1));
    let last = info.last_rollback.unwrap();
    assert!(
        last.starts_with("allowed: cell-v1") && last.contains("replaced the newer cell-v2"),
        "{last}"
    );
    assert!(
        dev.status
            .prometheus()
            .contains("irtrackd_params_rollbacks_allowed_total 1")
    );
    // The flag allows; it does not require: a newer set with the flag is taken as usual.
    assert!(dev.push_allowing_rollback(&v2).await.is_accepted());
    assert_eq!(dev.status.params_info().rollbacks_allowed, 1);
    assert!(dev.push_allowing_rollback(&v1).await.is_accepted());
    dev.stop().await;
    let dev = Device::start(&dir, &shape).await;
    assert_eq!(dev.active_id().as_deref(), Some("cell-v1"));
    dev.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test]
async fn serials_decide_when_both_sets_have_one() {
    let dir = temp_dir("serials");
    let (v2, _, shape) = cell_sets();
    let dev = Device::start(&dir, &shape).await;
    // Serial 1790000100, then a set made "later" by a PC whose clock runs ahead but with a
    // smaller serial: the serial decides, not the creation time.
    let newer = RigParams {
        rig_id: "cell-s100".into(),
        serial: 1_790_000_100,
        ..v2.clone()
    };
    let older = RigParams {
        rig_id: "cell-s99".into(),
        serial: 1_790_000_099,
        created_unix_s: SEP_2026 + 86_400,
        ..v2.clone()
    };
    assert!(dev.push(&newer).await.is_accepted());
    assert_eq!(dev.status.params_info().serial, Some(1_790_000_100));
    let (code, message) = rejected(dev.push(&older).await);
    assert_eq!(code, RejectCode::Rollback);
    assert!(
        message.contains("cell-s99 (serial 1790000099, created 2026-09-22")
            && message.contains("cell-s100 (serial 1790000100, created 2026-09-21"),
        "{message}"
    );
    // A set modified from the active one (the tools' next serial) is newer.
    let modified = RigParams {
        rig_id: "cell-s101".into(),
        serial: RigParams::next_serial(newer.serial, 0),
        ..v2.clone()
    };
    assert!(dev.push(&modified).await.is_accepted());
    dev.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test]
async fn unknown_request_flags_are_refused_before_the_body() {
    let dir = temp_dir("flags");
    let (v2, _, shape) = cell_sets();
    let dev = Device::start(&dir, &shape).await;
    let blob = v2.to_blob().unwrap();
    let mut request = encode_push_with(&blob, PushOptions { allow_rollback: true });
    request[8..12].copy_from_slice(&0x0000_0003u32.to_le_bytes());
    let (code, message) = rejected(dev.push_raw(&request).await);
    assert_eq!(code, RejectCode::Protocol);
    assert!(message.contains("unknown request flags 0x00000002"), "{message}");
    assert_eq!(dev.active_id(), None);
    dev.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}
