//! Configuration errors and the `irtrackd` binary's command line (`--check-config`, ready line).

mod common;

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};

use common::*;
use irtrack_firmware::config::{Config, SourceKind};

fn err(toml: &str) -> String {
    Config::from_toml(toml, "test.toml").unwrap_err().to_string()
}

#[test]
fn defaults_are_a_simulated_pc_run() {
    let c = Config::from_toml("", "empty").unwrap();
    assert_eq!(c.source.kind, SourceKind::Sim);
    assert_eq!(c.listen.params, "0.0.0.0:7701");
    assert_eq!(c.listen.stream_ndjson, "0.0.0.0:7702");
    assert_eq!(c.listen.stream_binary, "0.0.0.0:7703");
    assert_eq!(c.listen.status, "0.0.0.0:7704");
    assert!(!c.service.params_from_simulator);
    // Secure by default: nothing trusted, unsigned blobs refused.
    assert!(c.params.trusted_keys.is_empty() && !c.params.allow_unsigned);
    assert_eq!(
        c.params.policy(),
        irtrack_core::signing::SignaturePolicy::RequireSigned
    );
    let full = r#"
[service]
state_dir = "/tmp/x"
[listen]
params = "127.0.0.1:9701"
[source]
kind = "sim"
[source.sim]
rig = "parallel"
fps = 30.0
[tracking]
threshold_dn = 40
max_gap_mm = 2.0
[leds]
backend = "none"
[realtime]
fifo_priority = 50
cpu_affinity = [1]
lock_memory = true
deadline_ms = 20.0
"#;
    let c = Config::from_toml(full, "full").unwrap();
    assert_eq!(c.tracking.threshold_dn, 40);
    assert_eq!(c.realtime.cpu_affinity, Some(vec![1]));
}

#[test]
fn shipped_example_config_is_valid() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../systemd/irtrackd.example.toml");
    let c = Config::load(&path).unwrap();
    assert_eq!(c.service.state_dir, std::path::PathBuf::from("/var/lib/irtrackd"));
    assert_eq!(c.source.sim.unwrap().fps, 60.0);
    assert_eq!(
        c.params.trusted_keys,
        vec![std::path::PathBuf::from("/etc/irtrack/trusted-keys")]
    );
    assert!(!c.params.allow_unsigned);
}

#[test]
fn params_table_is_strict() {
    let c = Config::from_toml(
        "[params]\nallow_unsigned = true\ntrusted_keys = [\"/k/a.pub\"]\n",
        "t",
    )
    .unwrap();
    assert!(c.params.allow_unsigned);
    assert_eq!(
        c.params.policy(),
        irtrack_core::signing::SignaturePolicy::AllowUnsigned
    );
    let e = err("[params]\ntrusted_key = \"/k/a.pub\"\n");
    assert!(
        e.contains("unknown field `trusted_key`") && e.contains("trusted_keys"),
        "{e}"
    );
    let e = err("[params]\nallow_unsigned = \"yes\"\n");
    assert!(e.contains("invalid type") && e.contains("allow_unsigned"), "{e}");
}

#[test]
fn bad_configs_name_the_problem() {
    let e = err("[servic]\nstate_dir = \"/x\"\n");
    assert!(
        e.contains("test.toml") && e.contains("unknown field `servic`"),
        "{e}"
    );
    let e = err("[source.sim]\nfpz = 30.0\n");
    assert!(e.contains("unknown field `fpz`") && e.contains("fps"), "{e}");
    let e = err("[source.sim]\nfps = \"fast\"\n");
    assert!(e.contains("invalid type") && e.contains("fps"), "{e}");
    let e = err("[tracking]\nthreshold = 3\n");
    assert!(e.contains("unknown field `threshold`"), "{e}");
    let e = err("[tracking]\nmin_area_px = 0\n");
    assert!(e.contains("[tracking]") && e.contains("area"), "{e}");
    let e = err("[source]\nkind = \"replay\"\n");
    assert!(e.contains("needs a [source.replay] table"), "{e}");
    let e = err("[source]\nkind = \"usb\"\n");
    assert!(e.contains("unknown variant `usb`"), "{e}");
    let e = err("[listen]\nstatus = \"localhost\"\n");
    assert!(e.contains("listen.status"), "{e}");
    let e = err("[source.sim]\nbit_depth = 12\n");
    assert!(e.contains("source.sim.bit_depth must be 8 or 10"), "{e}");
    let e = err("[leds]\nbackend = \"gpio\"\n");
    assert!(e.contains("[leds.gpio]"), "{e}");
    let e = err("[realtime]\nfifo_priority = 100\n");
    assert!(e.contains("1..=99"), "{e}");
    let e = err("[cluster]\ntransport_fifo_priority = 0\n");
    assert!(
        e.contains("cluster.transport_fifo_priority must be 1..=99, got 0"),
        "{e}"
    );
    let e = Config::load(std::path::Path::new("/nonexistent/irtrackd.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("/nonexistent/irtrackd.toml") && e.contains("cannot read"),
        "{e}"
    );
}

/// The binary under test; cross-built test runs set `IRTRACK_TEST_RUNNER` (e.g.
/// `qemu-aarch64 -L /`) because a foreign binary cannot be executed directly.
fn irtrackd() -> Command {
    let exe = env!("CARGO_BIN_EXE_irtrackd");
    match std::env::var("IRTRACK_TEST_RUNNER") {
        Ok(runner) if !runner.trim().is_empty() => {
            let mut parts = runner.split_whitespace();
            let mut cmd = Command::new(parts.next().unwrap());
            cmd.args(parts).arg(exe);
            cmd
        }
        _ => Command::new(exe),
    }
}

#[test]
fn check_config_flag_reports_and_exits() {
    let dir = TempDir::new("cli-check");
    let good = dir.path().join("good.toml");
    std::fs::write(&good, "[source.sim]\nfps = 50.0\n").unwrap();
    let out = irtrackd()
        .arg("--check-config")
        .arg("-c")
        .arg(&good)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).contains("config OK"));

    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[source.sim]\nfps = 50.0\ncolour = 1\n").unwrap();
    let out = irtrackd()
        .arg("--check-config")
        .arg("-c")
        .arg(&bad)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("unknown field `colour`") && stderr.contains("bad.toml"),
        "{stderr}"
    );

    let out = irtrackd()
        .arg("--check-config")
        .arg("-c")
        .arg(dir.path().join("missing.toml"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot read"));

    // An override can make a good file invalid, and says so.
    let out = irtrackd()
        .args(["--check-config", "--sim-fps", "0", "-c"])
        .arg(&good)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("command-line overrides"));
}

#[test]
fn check_config_names_the_cluster_role_board_and_feature() {
    let dir = TempDir::new("cli-check-cluster");
    let good = dir.path().join("standalone.toml");
    std::fs::write(&good, "[source.sim]\nfps = 50.0\n").unwrap();
    let out = irtrackd()
        .arg("--check-config")
        .arg("-c")
        .arg(&good)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let feature = if cfg!(feature = "cluster") {
        "this binary is built with the cluster feature"
    } else {
        "this binary is built without the cluster feature"
    };
    assert!(
        stdout.contains("cluster role standalone") && stdout.contains(feature),
        "{stdout}"
    );
    let solver = dir.path().join("solver.toml");
    std::fs::write(
        &solver,
        "[cluster]\nrole = \"solver\"\nrig = \"cell1\"\nboard = \"s0\"\nlisten = [\"tcp/127.0.0.1:7447\"]\nimage_sizes_px = [[640, 480], [640, 480]]\n",
    )
    .unwrap();
    let out = irtrackd()
        .arg("--check-config")
        .arg("-c")
        .arg(&solver)
        .output()
        .unwrap();
    if cfg!(feature = "cluster") {
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            stdout.contains("source the camera boards' observations (cluster solver)")
                && stdout.contains("cluster role solver (board \"s0\", rig \"cell1\"")
                && stdout.contains("2 cameras in all, pairing by timestamps")
                && stdout.contains(feature),
            "{stdout}"
        );
    } else {
        assert_eq!(out.status.code(), Some(2));
        assert!(String::from_utf8_lossy(&out.stderr).contains("`cluster` feature"));
    }
}

#[test]
fn binary_prints_ready_line_streams_and_stops_on_sigterm() {
    let dir = TempDir::new("cli-run");
    let mut child = irtrackd()
        .args([
            "--ephemeral-ports",
            "127.0.0.1",
            "--params-from-simulator",
            "--sim-fps",
            "100",
            "--state-dir",
        ])
        .arg(dir.path())
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    assert!(line.starts_with("irtrackd ready params=127.0.0.1:"), "{line}");
    let field = |k: &str| -> std::net::SocketAddr {
        line.split_whitespace()
            .find_map(|f| f.strip_prefix(&format!("{k}=")))
            .unwrap()
            .parse()
            .unwrap()
    };
    let stream = field("stream");
    let status = field("status");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let mut c = NdjsonClient::connect(stream).await;
        let r = c
            .until(100, |r| r.status == irtrack_core::stream::TrackStatus::Ok)
            .await;
        assert!(r.position_mm.is_some());
        let st = status_json(status).await;
        assert_eq!(st["params"]["origin"], "simulator");
    });
    // SAFETY: plain kill(2) on our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    let code = child.wait().unwrap();
    assert!(code.success(), "{code:?}");
    let _ = std::io::stdout().flush();
}

/// Triangulation needs two cameras: a standalone board with one is refused with a pointer to
/// the camera role; a camera board with one camera is fine (the solver has the others).
#[test]
fn one_camera_runs_as_a_camera_board_only() {
    let one_sim = "[source.sim]\nrig = \"ring\"\nring_cameras = 4\ncameras = [2]\n";
    let e = err(one_sim);
    assert!(
        e.contains("standalone board needs at least 2") && e.contains("role = \"camera\""),
        "{e}"
    );
    let v4l2 = "[source]\nkind = \"v4l2\"\n[source.v4l2]\nwidth_px = 640\nheight_px = 480\nfps = 120\n";
    let one_v4l2 = &format!("{v4l2}devices = [\"/dev/video0\"]\n");
    let e = err(one_v4l2);
    assert!(e.contains("[source] gives 1 camera"), "{e}");
    let e = err(&format!("{v4l2}devices = []\n"));
    assert!(e.contains("lists no camera"), "{e}");
    let camera = "[cluster]\nrole = \"camera\"\nboard = \"b2\"\nconnect = [\"tcp/127.0.0.1:7447\"]\n";
    for source in [one_sim, one_v4l2.as_str()] {
        let toml = format!("{source}{camera}");
        let r = Config::from_toml(&toml, "test.toml");
        if cfg!(feature = "cluster") {
            r.unwrap_or_else(|e| panic!("{toml}: {e}"));
        } else {
            let e = r.unwrap_err().to_string();
            assert!(e.contains("`cluster` feature"), "{e}");
        }
    }
    if cfg!(feature = "cluster") {
        let e = err(&format!("{one_sim}{camera}own_cameras = true\n"));
        assert!(e.contains("own_cameras is for role = \"solver\""), "{e}");
        // The solver's own cameras are part of image_sizes_px (every camera of the rig).
        let solver = "[cluster]\nrole = \"solver\"\nboard = \"s0\"\nown_cameras = true\n\
                      listen = [\"tcp/127.0.0.1:7447\"]\nimage_sizes_px = [[640, 480], [640, 480]]\n";
        let e = err(&format!(
            "[source.sim]\nrig = \"ring\"\nring_cameras = 4\ncameras = [0, 1, 2]\n{solver}"
        ));
        assert!(
            e.contains("image_sizes_px lists 2 cameras but the solver's own [source] has 3"),
            "{e}"
        );
        Config::from_toml(&format!("{one_sim}{solver}"), "test.toml").unwrap();
        let e = err(
            "[cluster]\nrole = \"solver\"\nlisten = [\"tcp/127.0.0.1:7447\"]\nimage_sizes_px = [[640, 480]]\n",
        );
        assert!(e.contains("a solver needs 2..=8 cameras in all"), "{e}");
    }
}
