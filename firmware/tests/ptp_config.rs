//! `[clock]` → linuxptp's `ptp4l.conf` (docs/cluster.md, "Clocks"): golden text for a camera
//! board (slave, hardware time stamping) and a solver (master, software fallback), bad values
//! refused with the key named, and `irtrackd --write-ptp-config` as the image's unit runs it.

mod common;

use std::process::Command;

use common::TempDir;
use irtrack_firmware::config::Config;

fn config(clock: &str) -> Config {
    Config::from_toml(&format!("[clock]\n{clock}"), "test").unwrap()
}

fn golden(name: &str) -> String {
    let p = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/");
    std::fs::read_to_string(format!("{p}{name}")).unwrap()
}

#[test]
fn ptp4l_config_is_generated_from_the_clock_section() {
    // Defaults: a camera board on eth0 with hardware time stamping.
    let c = config("ptp = true\n");
    assert_eq!(c.clock.ptp4l_conf(), golden("ptp4l-slave-hardware.conf"));
    let c = config(
        "ptp = true\ninterface = \"end0\"\ndomain = 3\nrole = \"master\"\ntime_stamping = \"software\"\n",
    );
    assert_eq!(c.clock.ptp4l_conf(), golden("ptp4l-master-software.conf"));
    let auto = config("ptp = true\nrole = \"auto\"\n").clock.ptp4l_conf();
    assert!(auto.contains("slaveOnly\t\t0\npriority1\t\t128\n"), "{auto}");
    // Off by default.
    assert!(!Config::from_toml("", "test").unwrap().clock.ptp);
}

#[test]
fn bad_clock_values_are_refused_by_name() {
    for (text, named) in [
        ("interface = \"eth0; rm -rf /\"\n", "clock.interface"),
        ("interface = \"\"\n", "clock.interface"),
        ("domain = 200\n", "clock.domain"),
        ("ptp4l_socket = \"\"\n", "clock.ptp4l_socket"),
    ] {
        let e = Config::from_toml(&format!("[clock]\n{text}"), "test")
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(e.contains(named), "{text}: {e}");
    }
    let e = Config::from_toml("[clock]\nrole = \"boss\"\n", "test")
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(e.contains("role") || e.contains("boss"), "{e}");
}

#[test]
fn irtrackd_writes_the_ptp_config_only_when_ptp_is_on() {
    let dir = TempDir::new("ptp-config");
    let run = |toml: &str| {
        let cfg = dir.path().join("irtrackd.toml");
        std::fs::write(&cfg, toml).unwrap();
        irtrackd()
            .arg("--config")
            .arg(&cfg)
            .arg("--write-ptp-config")
            .arg(dir.path().join("run"))
            .output()
            .unwrap()
    };
    // Off: exit 1 (the unit's ExecCondition skips ptp4l), nothing written.
    let o = run("");
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    assert!(!dir.path().join("run/ptp4l.conf").exists());
    // On, hardware: the config and the marker that starts phc2sys.
    let o = run("[clock]\nptp = true\n");
    assert!(o.status.success(), "{o:?}");
    assert_eq!(
        std::fs::read_to_string(dir.path().join("run/ptp4l.conf")).unwrap(),
        golden("ptp4l-slave-hardware.conf")
    );
    assert!(dir.path().join("run/hardware-timestamps").exists());
    // Software: no phc2sys (ptp4l steers CLOCK_REALTIME itself), the marker goes.
    let o = run("[clock]\nptp = true\ntime_stamping = \"software\"\n");
    assert!(o.status.success(), "{o:?}");
    assert!(!dir.path().join("run/hardware-timestamps").exists());
    assert!(
        std::fs::read_to_string(dir.path().join("run/ptp4l.conf"))
            .unwrap()
            .contains("time_stamping\t\tsoftware\n")
    );
    // A bad value: refused at load, exit 2, named.
    let o = run("[clock]\nptp = true\ndomain = 300\n");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("domain"), "{err}");
}

/// Debian's linuxptp (`cargo xtask setup`) reads the generated config: ptp4l in a network
/// namespace of its own (`unshare -rn`, where it cannot steer any clock) on a veth link, as a
/// master with software time stamping, reaches LISTENING with no configuration error.
#[test]
fn ptp4l_reads_the_generated_config() {
    let have = |cmd: &str| {
        Command::new("sh")
            .args(["-c", &format!("command -v {cmd}")])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !(have("ptp4l") && have("unshare") && have("ip")) {
        eprintln!("SKIPPED: ptp4l, unshare or ip not found (`cargo xtask setup` installs linuxptp)");
        return;
    }
    let dir = TempDir::new("ptp4l-run");
    let conf = dir.path().join("ptp4l.conf");
    let c = config("ptp = true\ninterface = \"veth0\"\nrole = \"master\"\ntime_stamping = \"software\"\n");
    std::fs::write(&conf, c.clock.ptp4l_conf()).unwrap();
    let script = format!(
        "ip link add veth0 type veth peer name veth1 && ip link set veth0 up && ip link set veth1 up \
         && timeout 3 ptp4l -f {} -m -q; true",
        conf.display()
    );
    let o = Command::new("unshare")
        .args(["-rn", "sh", "-c", &script])
        .output()
        .unwrap();
    let out = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    if out.contains("unshare failed") || out.contains("Operation not permitted") && !out.contains("ptp4l[") {
        eprintln!("SKIPPED: no user/network namespace here: {out}");
        return;
    }
    assert!(out.contains("INITIALIZING to LISTENING"), "{out}");
    for bad in ["unknown option", "failed to parse", "failed to create a clock"] {
        assert!(!out.contains(bad), "{bad}: {out}");
    }
}

/// The binary under test; cross-built test runs set `IRTRACK_TEST_RUNNER` (e.g.
/// `qemu-aarch64 -L /`) because a foreign binary cannot be executed directly.
fn irtrackd() -> Command {
    let exe = env!("CARGO_BIN_EXE_irtrackd");
    match std::env::var("IRTRACK_TEST_RUNNER") {
        Ok(runner) if !runner.trim().is_empty() => {
            let mut parts = runner.split_whitespace();
            let mut cmd = Command::new(parts.next().unwrap_or("qemu-aarch64"));
            cmd.args(parts).arg(exe);
            cmd
        }
        _ => Command::new(exe),
    }
}
