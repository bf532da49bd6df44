//! `host-tools update push` against a real irtrackd process with the simulated system
//! (`[update] backend = "simulated"`, docs/updates.md): a good bundle installs with progress
//! shown; a bundle from a foreign CA, a truncated one and a wrong password end non-zero with
//! the board's reason. `--reboot`: the test plays the board's reboot (restarts irtrackd on the
//! same port when the simulated system records the request) and checks the exit codes of a
//! good reboot (0), a rollback (3) and a board that never comes back (4). Build irtrackd first (`cargo build -p irtrack-firmware --bin
//! irtrackd`); bundles are made with the host's `rauc` and `openssl` (`cargo xtask setup`).

mod common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use common::{host_tools, p, text};
use irtrack_testkit::harness::http::Http;
use irtrack_testkit::harness::irtrackd::{Irtrackd, IrtrackdConfig, operator_hash};
use irtrack_testkit::harness::process::{TempDir, workspace_bin};
use irtrack_testkit::update_bundles;

const PASSWORD: &str = "update-cli operator";

/// A CA and a signer it issued (as `cargo xtask image update-keys` makes them).
fn make_keys(dir: &Path) {
    update_bundles::make_update_keys(dir, "cli").unwrap();
}

/// A signed bundle of `version` with a 2 MiB image of noise (so the upload has some length).
fn make_bundle(keys: &Path, work: &Path, name: &str, version: &str) -> PathBuf {
    let mut x = 0x9e37_79b9_u32;
    let image: Vec<u8> = (0..2 << 20)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as u8
        })
        .collect();
    update_bundles::make_bundle(keys, work, name, "irtrack-qemu-arm64", version, &image).unwrap()
}

fn push(board: SocketAddr, password_file: &Path, bundle: &Path) -> (bool, String, String) {
    let o = host_tools(&[
        "update",
        "push",
        "--board",
        &board.to_string(),
        "--password-file",
        p(password_file),
        p(bundle),
    ]);
    let (out, err) = text(&o);
    (o.status.success(), out, err)
}

#[test]
fn update_push_installs_and_reports_refusals() {
    let dir = TempDir::new("update-cli").unwrap();
    let keys = dir.path().join("keys");
    let foreign = dir.path().join("foreign");
    make_keys(&keys);
    make_keys(&foreign);
    let good = make_bundle(&keys, dir.path(), "good", "1.2.0");
    let bad_sig = make_bundle(&foreign, dir.path(), "foreign", "1.3.0");
    let bytes = std::fs::read(&good).unwrap();
    let truncated = dir.path().join("truncated.raucb");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();

    let irtrackd = workspace_bin("irtrackd").unwrap();
    let config = dir.path().join("irtrackd.toml");
    IrtrackdConfig::simulated()
        .operator_hash(&operator_hash(&irtrackd, PASSWORD).unwrap())
        .set("update.backend", "simulated")
        .set("update.ca_cert", p(&keys.join("ca.cert.pem")))
        .set("update.sim_dir", p(&dir.path().join("system")))
        .set("update.running_version", "1.1.0")
        .write(&config)
        .unwrap();
    let board = Irtrackd::start(
        &irtrackd,
        &config,
        &dir.path().join("state"),
        Duration::from_secs(30),
    )
    .unwrap();
    let status = board.ready().status;
    let pw = dir.path().join("password");
    std::fs::write(&pw, format!("{PASSWORD}\n")).unwrap();
    let wrong = dir.path().join("wrong");
    std::fs::write(&wrong, "not the password\n").unwrap();

    let (ok, _, err) = push(status, &wrong, &good);
    assert!(!ok);
    assert!(
        err.contains("refused the sign-in (401)") && err.contains("wrong operator password"),
        "{err}"
    );

    let (ok, _, err) = push(status, &pw, &bad_sig);
    assert!(!ok);
    assert!(
        err.contains("the board refused the bundle: wrong signature"),
        "{err}"
    );

    let (ok, _, err) = push(status, &pw, &truncated);
    assert!(!ok);
    assert!(
        err.contains("the board refused the bundle (422)") && err.contains("truncated"),
        "{err}"
    );

    let (ok, out, err) = push(status, &pw, &good);
    assert!(ok, "{out}\n{err}");
    assert!(err.contains("upload: 100%"), "{err}");
    assert!(
        err.contains("upload done in") && err.contains("installing"),
        "{err}"
    );
    assert!(out.contains("installed 1.2.0 into slot B"), "{out}");

    let (code, body) = Http::new(Duration::from_secs(10)).get(status, "/status").unwrap();
    assert_eq!(code, 200);
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(v["system"]["other"]["version"], "1.2.0", "{}", v["system"]);
    assert_eq!(v["system"]["boot_next"], "B");
    assert_eq!(v["system"]["last_update"]["outcome"], "installed");
}

/// `host-tools update push --reboot ...` started in the background.
fn push_reboot(
    board: SocketAddr,
    password_file: &Path,
    bundle: &Path,
    timeout_s: &str,
) -> std::process::Child {
    std::process::Command::new(env!("CARGO_BIN_EXE_host-tools"))
        .args([
            "update",
            "push",
            "--board",
            &board.to_string(),
            "--password-file",
            p(password_file),
            "--reboot",
            "--reboot-timeout-s",
            timeout_s,
            p(bundle),
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// Plays the board's part of a reboot: once the simulated system records the request, wait
/// 2 s as the image's root agent does, stop irtrackd, stay down a moment, start it again on the
/// same status port.
fn reboot_when_asked(board: Irtrackd, sim_dir: &Path, restart: impl FnOnce() -> Irtrackd) -> Irtrackd {
    let t0 = std::time::Instant::now();
    while !sim_dir.join("reboot-requested").exists() {
        assert!(t0.elapsed() < Duration::from_secs(60), "no reboot asked for");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_secs(2));
    board.shutdown(Duration::from_secs(10)).unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    restart()
}

#[test]
fn update_push_reboot_waits_for_the_board_and_says_how_it_came_back() {
    let dir = TempDir::new("update-cli-reboot").unwrap();
    let keys = dir.path().join("keys");
    make_keys(&keys);
    let good = make_bundle(&keys, dir.path(), "good", "1.2.0");
    let next = make_bundle(&keys, dir.path(), "next", "1.3.0");
    let last = make_bundle(&keys, dir.path(), "last", "1.4.0");
    let irtrackd = workspace_bin("irtrackd").unwrap();
    let config = dir.path().join("irtrackd.toml");
    let sim_dir = dir.path().join("system");
    IrtrackdConfig::simulated()
        .operator_hash(&operator_hash(&irtrackd, PASSWORD).unwrap())
        .set("update.backend", "simulated")
        .set("update.ca_cert", p(&keys.join("ca.cert.pem")))
        .set("update.sim_dir", p(&sim_dir))
        .set("update.running_version", "1.1.0")
        .write(&config)
        .unwrap();
    let state = dir.path().join("state");
    let board = Irtrackd::start(&irtrackd, &config, &state, Duration::from_secs(30)).unwrap();
    let status = board.ready().status;
    // The "reboot": the same configuration and state, on the same status port.
    let restart = || {
        let mut cmd = Irtrackd::command(&irtrackd, &config, &state);
        cmd.args(["--listen-status", &status.to_string()]);
        Irtrackd::spawn(&mut cmd, Duration::from_secs(30)).unwrap()
    };
    let pw = dir.path().join("password");
    std::fs::write(&pw, format!("{PASSWORD}\n")).unwrap();

    // Installed into B, rebooted, back on B and marked good: exit 0.
    let child = push_reboot(status, &pw, &good, "60");
    let board = reboot_when_asked(board, &sim_dir, restart);
    let o = child.wait_with_output().unwrap();
    let (out, err) = text(&o);
    assert_eq!(o.status.code(), Some(0), "{out}\n{err}");
    assert!(
        out.contains("installed 1.2.0 into slot B")
            && out.contains("rebooted: slot B runs 1.2.0, healthy and marked good"),
        "{out}"
    );
    assert!(err.contains("the board reboots into it"), "{err}");
    assert!(err.contains("reboot: irtrackd answers again after"), "{err}");

    // A new system that never becomes healthy: back on B, exit 3 with the board's words.
    let child = push_reboot(status, &pw, &next, "60");
    std::fs::write(sim_dir.join("fail-next-boot"), b"").unwrap();
    let board = reboot_when_asked(board, &sim_dir, restart);
    let o = child.wait_with_output().unwrap();
    let (out, err) = text(&o);
    assert_eq!(o.status.code(), Some(3), "{out}\n{err}");
    assert!(
        err.contains("came back on slot B (version 1.2.0), not on slot A")
            && err.contains("rolled back")
            && err.contains("slot A (version 1.3.0) did not become healthy"),
        "{err}"
    );

    // Nobody reboots the board: exit 4 once --reboot-timeout-s has passed.
    let child = push_reboot(status, &pw, &last, "3");
    let o = child.wait_with_output().unwrap();
    let (out, err) = text(&o);
    assert_eq!(o.status.code(), Some(4), "{out}\n{err}");
    assert!(
        err.contains("the board did not come back healthy within 3 s")
            && err.contains("irtrackd of the old system still answers"),
        "{err}"
    );
    // The request is on record for whoever runs the simulated board.
    assert!(sim_dir.join("reboot-requested").exists());
    board.shutdown(Duration::from_secs(10)).unwrap();
}
