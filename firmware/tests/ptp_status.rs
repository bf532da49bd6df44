//! ptp4l's own clock state on `/status` (`clock.ptp`; docs/cluster.md, "What `/status`
//! shows"): irtrackd's management client against real ptp4l processes (Debian's linuxptp,
//! `cargo xtask setup`), a master and a slave in two network namespaces joined by a veth
//! pair; and the cases where nothing (or something broken) answers.

mod common;

use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{TempDir, runtime, scrape_metrics, start_with, status_json};
use irtrack_firmware::config::Config;
use irtrack_firmware::ptp::mgmt::{PortState, clock_identity_text};
use irtrack_firmware::ptp::monitor;

const SIM: &str = "fps = 30.0\n";

fn have(cmd: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {cmd}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

fn ip(args: &[&str]) -> bool {
    Command::new("ip")
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Two namespaces (master, slave) joined by a veth pair with a private /30; deleted on drop,
/// with the ptp4l processes started in them.
struct PtpPair {
    ns: [String; 2],
    ifs: [String; 2],
    children: Vec<Child>,
}

impl PtpPair {
    fn try_new() -> Option<Self> {
        let tag = std::process::id() % 100_000;
        let ns = [format!("irtk-ptpm-{tag}"), format!("irtk-ptps-{tag}")];
        let ifs = [format!("ptpm{tag}"), format!("ptps{tag}")];
        let pair = PtpPair {
            ns: ns.clone(),
            ifs: ifs.clone(),
            children: Vec::new(),
        };
        let ok = ip(&["netns", "add", &ns[0]])
            && ip(&["netns", "add", &ns[1]])
            && ip(&["link", "add", &ifs[0], "type", "veth", "peer", "name", &ifs[1]])
            && (0..2).all(|i| {
                let addr = format!("10.232.7.{}/30", i + 1);
                ip(&["link", "set", &ifs[i], "netns", &ns[i]])
                    && ip(&["-n", &ns[i], "addr", "add", &addr, "dev", &ifs[i]])
                    && ip(&["-n", &ns[i], "link", "set", &ifs[i], "up"])
                    && ip(&["-n", &ns[i], "link", "set", "lo", "up"])
            });
        ok.then_some(pair)
    }

    /// ptp4l in namespace `i` on its veth end, with the config irtrackd generates for `role`
    /// plus test settings: its own management socket, `free_running 1` (it measures but never
    /// steers the host's clock) and short announce/sync intervals (state reached in seconds).
    fn start_ptp4l(&mut self, i: usize, role: &str, dir: &Path) -> PathBuf {
        let c = Config::from_toml(
            &format!(
                "[clock]\nptp = true\ninterface = \"{}\"\nrole = \"{role}\"\ntime_stamping = \"software\"\n",
                self.ifs[i]
            ),
            "test",
        )
        .unwrap();
        let sock = dir.join(format!("ptp4l-{role}.sock"));
        let conf = c.clock.ptp4l_conf().replacen(
            "[global]\n",
            &format!(
                "[global]\nuds_address\t\t{}\nfree_running\t\t1\nlogAnnounceInterval\t-2\nlogSyncInterval\t\t-3\nlogMinDelayReqInterval\t-3\n",
                sock.display()
            ),
            1,
        );
        let path = dir.join(format!("ptp4l-{role}.conf"));
        std::fs::write(&path, conf).unwrap();
        let log = std::fs::File::create(dir.join(format!("ptp4l-{role}.log"))).unwrap();
        let child = Command::new("ip")
            .args(["netns", "exec", &self.ns[i], "ptp4l", "-f"])
            .arg(&path)
            .arg("-m")
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap();
        self.children.push(child);
        sock
    }
}

impl Drop for PtpPair {
    fn drop(&mut self) {
        for c in &mut self.children {
            let _ = c.kill();
            let _ = c.wait();
        }
        for n in &self.ns {
            ip(&["netns", "del", n]);
        }
    }
}

fn ptp(status: &serde_json::Value) -> &serde_json::Value {
    &status["clock"]["ptp"]
}

/// A master and a slave ptp4l (software time stamping, `free_running`) on a veth link:
/// irtrackd's `/status` shows the slave's port state, a measured offset and path delay, one
/// step to the grandmaster, which is the master; the library client reads the master's port
/// as MASTER. linuxptp's own `pmc` reads the same port states and grandmaster.
#[test]
fn status_shows_ptp4l_slave_and_master_over_veth() {
    if !(have("ptp4l") && have("ip")) {
        eprintln!("SKIPPED: ptp4l or ip not found (`cargo xtask setup` installs linuxptp and iproute2)");
        return;
    }
    let Some(mut pair) = PtpPair::try_new() else {
        if std::env::var_os("IRTRACK_REQUIRE_NETNS").is_some() {
            panic!("IRTRACK_REQUIRE_NETNS is set but `ip netns` with a veth pair does not work here");
        }
        eprintln!("SKIPPED: network namespaces are not available here (root and iproute2 needed)");
        return;
    };
    let dir = TempDir::new("ptp-status");
    let master_sock = pair.start_ptp4l(0, "master", dir.path());
    let slave_sock = pair.start_ptp4l(1, "slave", dir.path());
    let rt = runtime();
    rt.block_on(async {
        let extra = format!(
            "[clock]\nptp = true\ninterface = \"{}\"\nptp4l_socket = \"{}\"\n",
            pair.ifs[1],
            slave_sock.display()
        );
        let running = start_with(&dir, SIM, &extra).await;
        let t0 = Instant::now();
        let mut last = serde_json::Value::Null;
        let synced = loop {
            let st = status_json(running.addrs.status).await;
            let p = ptp(&st).clone();
            let state_ok = matches!(p["port_state"].as_str(), Some("SLAVE" | "UNCALIBRATED"));
            if state_ok && p["error"].is_null() && p["mean_path_delay_ns"].as_f64().is_some_and(|d| d > 0.0) {
                break Some(p);
            }
            last = p;
            if t0.elapsed() > Duration::from_secs(20) {
                break None;
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        };
        let logs = || {
            ["master", "slave"]
                .map(|r| {
                    std::fs::read_to_string(dir.path().join(format!("ptp4l-{r}.log"))).unwrap_or_default()
                })
                .join("\n---\n")
        };
        let p = synced
            .unwrap_or_else(|| panic!("no synchronised slave in 20 s; last clock.ptp {last}\n{}", logs()));
        let offset_ns = p["offset_ns"].as_f64().unwrap();
        let delay_ns = p["mean_path_delay_ns"].as_f64().unwrap();
        println!(
            "slave after {:.1} s: {} offset {offset_ns:.0} ns, mean path delay {delay_ns:.0} ns",
            t0.elapsed().as_secs_f64(),
            p["port_state"]
        );
        assert!(offset_ns.is_finite() && offset_ns.abs() < 1e6, "{p}");
        assert!(delay_ns < 1e6, "{p}");
        assert_eq!(p["steps_removed"], 1, "{p}");
        assert_eq!(p["gm_present"], true, "{p}");
        assert!(p["age_ms"].as_u64().is_some_and(|a| a < 3000), "{p}");
        assert_eq!(p["socket"].as_str(), Some(slave_sock.to_str().unwrap()));
        // The same in /metrics, read by an independent OpenMetrics parser.
        let m = scrape_metrics(running.addrs.status).await;
        let state = m.0["samples"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == "irtrackd_ptp_port_state")
            .map(|s| (s["labels"]["state"].clone(), s["value"].clone()));
        let state = state.unwrap_or_else(|| panic!("no irtrackd_ptp_port_state in {}", m.0));
        assert!(
            matches!(state.0.as_str(), Some("SLAVE" | "UNCALIBRATED")),
            "{state:?}"
        );
        assert_eq!(state.1.as_f64(), Some(1.0));
        let offset_s = m.value("irtrackd_ptp_offset_seconds", &[]).expect("offset");
        assert!(offset_s.abs() < 1e-3, "ptp offset {offset_s} s");
        let delay_s = m
            .value("irtrackd_ptp_mean_path_delay_seconds", &[])
            .expect("delay");
        assert!(delay_s > 0.0 && delay_s < 1e-3, "path delay {delay_s} s");
        assert_eq!(m.value("irtrackd_ptp_steps_removed", &[]), Some(1.0));
        assert_eq!(m.value("irtrackd_ptp_grandmaster_present", &[]), Some(1.0));
        assert!(m.value("irtrackd_ptp_polls_total", &[]).is_some_and(|n| n >= 1.0));

        // The master, through the library client.
        let m = monitor::query(dir.path(), &master_sock, 0).await.unwrap();
        assert_eq!(m.port.state, PortState::Master, "{m:?}");
        assert_eq!(m.current.steps_removed, 0);
        // The slave's grandmaster is this master.
        assert_eq!(
            p["gm_identity"].as_str(),
            Some(clock_identity_text(&m.port.port.clock).as_str())
        );

        // linuxptp's own client agrees on the states and the grandmaster.
        if have("pmc") {
            let pmc = |sock: &Path, what: &str| {
                let o = Command::new("pmc")
                    .args(["-u", "-b", "0", "-s"])
                    .arg(sock)
                    .arg(what)
                    .output()
                    .unwrap();
                String::from_utf8_lossy(&o.stdout).into_owned()
            };
            let out = pmc(&master_sock, "GET PORT_DATA_SET");
            assert!(out.contains("portState               MASTER"), "{out}");
            let out = pmc(&slave_sock, "GET TIME_STATUS_NP");
            assert!(out.contains(p["gm_identity"].as_str().unwrap()), "{out}");
            let s = monitor::query(dir.path(), &slave_sock, 0).await.unwrap();
            let out = pmc(&slave_sock, "GET PORT_DATA_SET");
            assert!(
                out.contains(&format!("portState               {}", s.port.state)),
                "{out}"
            );
        }
        running.shutdown().await;
    });
}

/// No ptp4l: `/status` names the problem and irtrackd goes on; a socket nobody answers on
/// gives a timeout; a broken answer is named as such.
#[test]
fn status_names_a_missing_silent_or_broken_ptp4l_and_keeps_running() {
    let dir = TempDir::new("ptp-missing");
    let rt = runtime();
    rt.block_on(async {
        let absent = dir.path().join("absent.sock");
        let extra = format!("[clock]\nptp = true\nptp4l_socket = \"{}\"\n", absent.display());
        let running = start_with(&dir, SIM, &extra).await;
        let mut st = status_json(running.addrs.status).await;
        let t0 = Instant::now();
        while ptp(&st)["polls"].as_u64().unwrap_or(0) < 2 && t0.elapsed() < Duration::from_secs(10) {
            tokio::time::sleep(Duration::from_millis(200)).await;
            st = status_json(running.addrs.status).await;
        }
        let p = ptp(&st);
        let err = p["error"].as_str().unwrap_or_default();
        assert!(
            err.contains("absent.sock") && err.contains("is ptp4l running"),
            "{p}"
        );
        assert!(p["port_state"].is_null() && p["offset_ns"].is_null(), "{p}");
        assert_eq!(p["failures"], p["polls"], "{p}");
        // /metrics: failures counted, no made-up offset or state.
        let m = scrape_metrics(running.addrs.status).await;
        let polls = m.value("irtrackd_ptp_polls_total", &[]).expect("polls");
        assert!(polls >= 1.0);
        assert_eq!(m.value("irtrackd_ptp_poll_failures_total", &[]), Some(polls));
        assert_eq!(m.value("irtrackd_ptp_offset_seconds", &[]), None);
        assert!(!m.0.to_string().contains("irtrackd_ptp_port_state"));
        // Still processing frames, still serving.
        let it0 = st["processing"]["iterations"].as_u64().unwrap();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let st = status_json(running.addrs.status).await;
        assert!(st["processing"]["iterations"].as_u64().unwrap() > it0);
        running.shutdown().await;

        // A socket that never answers, then one that answers garbage (via the library client).
        let silent_path = dir.path().join("silent.sock");
        let silent = UnixDatagram::bind(&silent_path).unwrap();
        let e = monitor::query(dir.path(), &silent_path, 0)
            .await
            .unwrap_err()
            .to_string();
        assert!(e.contains("did not answer GET CURRENT_DATA_SET"), "{e}");
        // Answer every request (the unanswered one above included) with its first 40 bytes.
        let echo = std::thread::spawn(move || {
            let mut buf = [0u8; 1500];
            silent.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
            while let Ok((n, from)) = silent.recv_from(&mut buf) {
                if let Some(p) = from.as_pathname() {
                    let _ = silent.send_to(&buf[..n.min(40)], p);
                }
            }
        });
        let e = monitor::query(dir.path(), &silent_path, 0)
            .await
            .unwrap_err()
            .to_string();
        assert!(e.contains("management reply: 40 bytes, need at least 52"), "{e}");
        echo.join().unwrap();
    });
}
