//! Power-cut-safe parameter storage: a child process stores parameter sets in a loop through
//! the real `ParamStore`; the parent SIGKILLs it at a random instant, then runs irtrackd's
//! start-up load path (`ParamService::load_stored`) on the state directory. After every kill
//! the loaded set must be the old or the new complete set, never a corrupt or missing one.
//!
//! The child is this test binary re-invoked with `--ignored --exact powercut_child_writer`
//! and `IRTRACK_POWERCUT_DIR` set. SIGKILL keeps the page cache, so this proves the ordering
//! of writes and renames (no window without a complete set), not the drive's flush behaviour.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use irtrack_core::params::RigParams;
use irtrack_core::pipeline::TrackerConfig;
use irtrack_firmware::engine::ParamsHandle;
use irtrack_firmware::params::{ParamService, RigShape};
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::status::SharedStatus;
use irtrack_firmware::storage::ParamStore;

const DIR_ENV: &str = "IRTRACK_POWERCUT_DIR";
const START_ENV: &str = "IRTRACK_POWERCUT_START";
const TRIALS: usize = 220;
/// Random kill delay after the child reported ready, µs.
const MAX_DELAY_US: u64 = 30_000;

fn sim() -> SimSource {
    SimSource::new(&SimSourceConfig::default()).unwrap()
}

/// Parameter set number `k`: the simulator's rig with a distinct id and creation time.
fn rig_set(base: &RigParams, k: u64) -> Vec<u8> {
    let mut rig = base.clone();
    rig.rig_id = format!("set-{k}");
    rig.created_unix_s = 1_700_000_000 + k;
    rig.to_blob().unwrap()
}

/// The child: stores set `start`, `start+1`, … until killed, logging each step unbuffered.
#[test]
#[ignore = "helper process for powercut_never_loses_the_parameter_set"]
fn powercut_child_writer() {
    let dir = std::env::var(DIR_ENV).expect("run by the parent test only");
    let start: u64 = std::env::var(START_ENV).unwrap().parse().unwrap();
    let base = sim().scenario().rig().clone();
    let store = ParamStore::open(&dir).unwrap();
    let mut log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(Path::new(&dir).join("progress.log"))
        .unwrap();
    let blobs: Vec<Vec<u8>> = (start..start + 10_000).map(|k| rig_set(&base, k)).collect();
    log.write_all(b"ready\n").unwrap();
    for (k, blob) in (start..).zip(&blobs) {
        writeln!(log, "storing {k}").unwrap();
        store.store(blob).unwrap();
        writeln!(log, "stored {k}").unwrap();
    }
}

/// xorshift64*: reproducible random delays without an extra dependency.
struct Rng(u64);
impl Rng {
    fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) % n
    }
}

/// irtrackd's start-up load path on `dir`: the rig id it activates and the origin.
fn load_like_irtrackd(dir: &Path, shape: &RigShape) -> Option<(String, String)> {
    let status = Arc::new(SharedStatus::new(2, "test".into(), "none".into()));
    let service = ParamService::new(
        ParamStore::open(dir).unwrap(),
        shape.clone(),
        TrackerConfig::default(),
        Arc::new(ParamsHandle::new()),
        Arc::clone(&status),
    );
    if !service.load_stored() {
        return None;
    }
    let info = status.params_info();
    Some((info.rig_id?, info.origin?))
}

#[test]
fn powercut_never_loses_the_parameter_set() {
    let dir = std::env::temp_dir().join(format!("irtrackd-powercut-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let sim = sim();
    let shape = RigShape::of_set(&sim.allocate_set());
    let base = sim.scenario().rig().clone();
    ParamStore::open(&dir).unwrap().store(&rig_set(&base, 0)).unwrap();
    let exe = std::env::current_exe().unwrap();
    let seed = Instant::now().elapsed().as_nanos() as u64 ^ u64::from(std::process::id());
    let mut rng = Rng(seed | 1);
    let (mut old, mut new, mut rollbacks, mut stores_done) = (0usize, 0usize, 0usize, 0u64);
    let mut current = 0u64;
    let t0 = Instant::now();
    for trial in 0..TRIALS {
        let progress = dir.join("progress.log");
        let _ = std::fs::remove_file(&progress);
        let mut child = Command::new(&exe)
            .args(["--ignored", "--exact", "powercut_child_writer", "--nocapture"])
            .env(DIR_ENV, &dir)
            .env(START_ENV, (current + 1).to_string())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let wait_ready = Instant::now();
        while !std::fs::read_to_string(&progress).is_ok_and(|s| s.starts_with("ready")) {
            assert!(
                wait_ready.elapsed() < Duration::from_secs(20),
                "child never became ready"
            );
            std::thread::sleep(Duration::from_micros(200));
        }
        std::thread::sleep(Duration::from_micros(rng.below(MAX_DELAY_US)));
        child.kill().unwrap(); // SIGKILL on Unix
        child.wait().unwrap();

        let log = std::fs::read_to_string(&progress).unwrap();
        let storing = log
            .lines()
            .filter_map(|l| l.strip_prefix("storing "))
            .filter_map(|k| k.parse::<u64>().ok())
            .next_back();
        stores_done += log.lines().filter(|l| l.starts_with("stored ")).count() as u64;
        // The set being written when the kill came (if any) is "new"; the one before is "old".
        let (old_k, new_k) = match storing {
            Some(k) => (k - 1, k),
            None => (current, current),
        };
        let (rig_id, origin) = load_like_irtrackd(&dir, &shape)
            .unwrap_or_else(|| panic!("trial {trial}: no parameter set loads after the kill; log:\n{log}"));
        let loaded: u64 = rig_id
            .strip_prefix("set-")
            .and_then(|k| k.parse().ok())
            .unwrap_or_else(|| panic!("trial {trial}: unexpected rig id {rig_id:?}"));
        assert!(
            loaded == old_k || loaded == new_k,
            "trial {trial}: loaded set-{loaded}, expected set-{old_k} (old) or set-{new_k} (new)"
        );
        if origin == "rollback" {
            rollbacks += 1;
        }
        if loaded == new_k && storing.is_some() {
            new += 1;
        } else {
            old += 1;
        }
        current = loaded;
    }
    let elapsed = t0.elapsed();
    println!(
        "powercut: {TRIALS} SIGKILL trials in {:.1} s, {stores_done} complete stores; loaded old set {old}×, new set {new}×, via rollback {rollbacks}×",
        elapsed.as_secs_f64()
    );
    // Both outcomes must actually occur, otherwise the kills did not land inside stores.
    assert!(
        old > 0 && new > 0,
        "kills did not hit both sides of a store: old {old}, new {new}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
