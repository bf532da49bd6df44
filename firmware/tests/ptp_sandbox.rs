//! The PTP units' confinement (`systemd/irtrack-ptp4l.service`, `irtrack-phc2sys.service`;
//! docs/security.md, "systemd units") does not stop linuxptp from working. The build machine
//! has no systemd as PID 1, so `systemd-run -p ...` cannot apply the units; the test rebuilds
//! the sandbox from the units' own settings with `unshare`, read-only remounts and `setpriv`, and
//! checks under `strace` what it cannot enforce without systemd's seccomp filters:
//!
//! - reproduced: `CapabilityBoundingSet=` (setpriv `--bounding-set`, asserted from
//!   /proc/self/status; a control run without CAP_NET_BIND_SERVICE must fail to bind PTP's
//!   ports), `AmbientCapabilities=` empty, `NoNewPrivileges=`, `UMask=`, `ProtectSystem=strict`
//!   (`/` remounted read-only; a write to /etc is refused), `ReadWritePaths=/run` (a private
//!   tmpfs, so the machine's own /run is not touched), `PrivateTmp=`, `ProtectHome=`,
//!   `ProtectKernelTunables=` (/proc/sys and /sys read-only);
//! - checked on the trace: every system call ptp4l and phc2sys make is in the unit's
//!   `SystemCallFilter=` (groups expanded by `systemd-analyze syscall-filter`), every socket
//!   family in `RestrictAddressFamilies=`, no W+X mapping and no `mprotect(PROT_EXEC)`
//!   (`MemoryDenyWriteExecute=`), no namespace creation (`RestrictNamespaces=`);
//! - not reproduced: `DeviceAllow=char-ptp` (no PTP hardware clock here: a veth pair has none,
//!   so ptp4l runs with software time stamping and phc2sys finds no port to synchronise), and
//!   CAP_SYS_TIME is kept but only inside a user namespace, where it cannot steer the machine's
//!   clock (on purpose: a test must not).

mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::process::Command;

use common::TempDir;
use irtrack_firmware::config::Config;

/// `[Service]` settings of a unit file, in order; keys may repeat (SystemCallFilter=).
struct Unit {
    name: String,
    service: Vec<(String, String)>,
}

impl Unit {
    fn load(name: &str) -> Unit {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../systemd")
            .join(name);
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let mut section = String::new();
        let mut service = Vec::new();
        for line in text.lines().map(str::trim) {
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            if line.starts_with('[') {
                section = line.to_string();
            } else if section == "[Service]"
                && let Some((k, v)) = line.split_once('=')
            {
                service.push((k.trim().to_string(), v.trim().to_string()));
            }
        }
        Unit {
            name: name.to_string(),
            service,
        }
    }

    fn all(&self, key: &str) -> Vec<&str> {
        self.service
            .iter()
            .filter(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
            .collect()
    }

    /// The effective value of a single-valued setting (the last assignment).
    fn one(&self, key: &str) -> &str {
        self.all(key)
            .last()
            .copied()
            .unwrap_or_else(|| panic!("{}: no {key}=", self.name))
    }

    /// The settings the sandbox below reproduces must be the unit's; a change to the unit that
    /// the sandbox does not follow fails here instead of testing something else.
    fn assert_reproducible(&self) {
        for (key, want) in [
            ("NoNewPrivileges", "yes"),
            ("ProtectSystem", "strict"),
            ("ReadWritePaths", "/run"),
            ("PrivateTmp", "yes"),
            ("ProtectHome", "yes"),
            ("ProtectKernelTunables", "yes"),
            ("MemoryDenyWriteExecute", "yes"),
            ("RestrictNamespaces", "yes"),
            ("UMask", "0077"),
        ] {
            assert_eq!(
                self.one(key),
                want,
                "{}: {key}= is not what the test reproduces",
                self.name
            );
        }
        assert_eq!(self.one("AmbientCapabilities"), "", "{}", self.name);
    }

    /// CapabilityBoundingSet= as capability names without `CAP_`, lower case.
    fn capabilities(&self) -> Vec<String> {
        self.one("CapabilityBoundingSet")
            .split_whitespace()
            .map(|c| c.trim_start_matches("CAP_").to_ascii_lowercase())
            .collect()
    }

    fn address_families(&self) -> BTreeSet<String> {
        self.one("RestrictAddressFamilies")
            .split_whitespace()
            .map(str::to_string)
            .collect()
    }

    /// The system calls SystemCallFilter= allows: the first assignment is an allow list, the
    /// `~` ones remove from it (systemd.exec(5)).
    fn allowed_syscalls(&self) -> BTreeSet<String> {
        let mut cache = BTreeMap::new();
        let mut allowed = BTreeSet::new();
        for (i, v) in self.all("SystemCallFilter").into_iter().enumerate() {
            let (deny, list) = match v.strip_prefix('~') {
                Some(rest) => (true, rest),
                None => (false, v),
            };
            assert!(
                i > 0 || !deny,
                "{}: the filter must start with an allow list",
                self.name
            );
            for item in list.split_whitespace() {
                let names = expand_syscalls(item, &mut cache);
                if deny {
                    allowed.retain(|s| !names.contains(s));
                } else {
                    allowed.extend(names);
                }
            }
        }
        allowed
    }
}

/// A system call name, or a `@group` expanded (recursively) by `systemd-analyze syscall-filter`.
fn expand_syscalls(item: &str, cache: &mut BTreeMap<String, BTreeSet<String>>) -> BTreeSet<String> {
    if !item.starts_with('@') {
        return BTreeSet::from([item.to_string()]);
    }
    if let Some(s) = cache.get(item) {
        return s.clone();
    }
    let o = Command::new("systemd-analyze")
        .args(["syscall-filter", "--no-pager", item])
        .output()
        .unwrap();
    assert!(o.status.success(), "systemd-analyze syscall-filter {item}: {o:?}");
    let mut out = BTreeSet::new();
    for line in String::from_utf8_lossy(&o.stdout).lines().skip(1) {
        let entry = line.trim();
        if entry.is_empty() || entry.starts_with('#') {
            continue;
        }
        out.extend(expand_syscalls(entry, cache));
    }
    assert!(!out.is_empty(), "{item}: empty system call group");
    cache.insert(item.to_string(), out.clone());
    out
}

fn have(cmd: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {cmd}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// The capability mask /proc/self/status shows for these capability names.
fn capability_mask(names: &[String]) -> u64 {
    names.iter().fold(0, |mask, n| {
        let bit = match n.as_str() {
            "net_bind_service" => 10,
            "net_broadcast" => 11,
            "net_admin" => 12,
            "net_raw" => 13,
            "sys_time" => 25,
            other => panic!("capability {other}: add its number to capability_mask"),
        };
        mask | 1 << bit
    })
}

/// One traced process's system calls (names) and the rest of each call line.
struct Trace {
    calls: Vec<(String, String)>,
}

impl Trace {
    /// strace -f output, only the process that executed `program` and only after its execve
    /// (not `timeout`, which starts it).
    fn of_program(strace_out: &str, program: &str) -> Trace {
        let mut pid = None;
        let mut calls = Vec::new();
        for line in strace_out.lines() {
            let Some((p, rest)) = line.split_once(char::is_whitespace) else {
                continue;
            };
            let rest = rest.trim_start();
            if pid.is_none() {
                // A successful execve (it may be split into `<unfinished ...>` and `resumed`).
                if rest.starts_with(&format!("execve(\"{program}\"")) && !rest.contains(" = -1 ") {
                    pid = Some(p.to_string());
                }
                continue;
            }
            if pid.as_deref() != Some(p) {
                continue;
            }
            // `<... x resumed>`, `+++ exited`, `--- SIGTERM` are not calls.
            let Some((name, args)) = rest.split_once('(') else {
                continue;
            };
            if !name.is_empty() && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                calls.push((name.to_string(), args.to_string()));
            }
        }
        assert!(
            pid.is_some(),
            "no execve of {program} in the trace:\n{strace_out}"
        );
        assert!(calls.len() > 20, "{program}: too few calls traced:\n{strace_out}");
        Trace { calls }
    }

    /// Every restriction of `unit` that is a property of the calls made.
    fn assert_within(&self, unit: &Unit, program: &str) {
        let allowed = unit.allowed_syscalls();
        let names: BTreeSet<&str> = self.calls.iter().map(|(n, _)| n.as_str()).collect();
        let outside: Vec<&&str> = names.iter().filter(|n| !allowed.contains(**n)).collect();
        assert!(
            outside.is_empty(),
            "{program} calls {outside:?}, outside {}'s SystemCallFilter=",
            unit.name
        );
        let families = unit.address_families();
        for (name, args) in &self.calls {
            if name == "socket" {
                let family = args.split(',').next().unwrap_or("");
                assert!(
                    families.contains(family),
                    "{program}: socket({args} — {family} not in {}'s RestrictAddressFamilies=",
                    unit.name
                );
            }
            let prot = args.split(", ").nth(2).unwrap_or("");
            let wx = name == "mmap" && prot.contains("PROT_WRITE") && prot.contains("PROT_EXEC");
            let x = (name == "mprotect" || name == "pkey_mprotect") && prot.contains("PROT_EXEC");
            assert!(!wx && !x, "{program}: {name}({args} (MemoryDenyWriteExecute=)");
            assert!(
                !(matches!(name.as_str(), "unshare" | "setns" | "clone" | "clone3")
                    && args.contains("CLONE_NEW")),
                "{program}: {name}({args} (RestrictNamespaces=)"
            );
        }
        eprintln!(
            "{program}: {} calls, {} distinct, all within {}",
            self.calls.len(),
            names.len(),
            unit.name
        );
    }
}

/// `setpriv` with a unit's confinement of the process (capabilities, no ambient ones,
/// no_new_privs); `caps_file` gets the capabilities the process runs with.
fn confined(caps: &[String], caps_file: &str, command: &str) -> String {
    let bounding: String = std::iter::once("-all".to_string())
        .chain(caps.iter().map(|c| format!("+{c}")))
        .collect::<Vec<_>>()
        .join(",");
    format!(
        "setpriv --no-new-privs --inh-caps=-all --ambient-caps=-all --bounding-set={bounding} -- \\\n  \
         sh -c 'grep -E \"^(CapEff|CapBnd|CapAmb|NoNewPrivs)\" /proc/self/status > {caps_file}; exec {command}'"
    )
}

/// The sandbox, as a shell script run by `unshare -r --net --mount`: a veth pair and the
/// mounts; `body` runs in it (as root of the namespace, processes started through
/// [`confined`]) with the generated config in /run/irtrack-ptp.
fn sandbox_script(unit: &Unit, conf: &Path, body: &str) -> String {
    unit.assert_reproducible();
    format!(
        r#"set -e
ip link add veth0 type veth peer name veth1
ip link set veth0 up; ip link set veth1 up; ip link set lo up
# ReadWritePaths=/run: a private /run, holding the generated config like RuntimeDirectory=.
mount -t tmpfs -o mode=0755 tmpfs /run
mkdir /run/irtrack-ptp
cp {conf} /run/irtrack-ptp/ptp4l.conf
# ProtectSystem=strict, PrivateTmp=, ProtectHome=, ProtectKernelTunables=.
mount -o remount,bind,ro /
mount -t tmpfs -o mode=1777 tmpfs /tmp
mount -t tmpfs -o mode=1777 tmpfs /var/tmp
for d in /home /root; do [ -d $d ] && mount -t tmpfs -o ro,mode=000 tmpfs $d; done
mount --bind /proc/sys /proc/sys && mount -o remount,bind,ro /proc/sys
mount -o remount,bind,ro /sys
umask {umask}
if touch /etc/irtrack-sandbox-probe 2>/dev/null; then echo "PROBE /etc writable"; else echo "PROBE /etc read-only"; fi
# The programs are stopped by `timeout` (exit 124); their output is judged, not their status.
set +e
{body}
"#,
        conf = conf.display(),
        umask = unit.one("UMask"),
    )
}

/// `==== name` sections the script prints (files it wrote in its private /run).
fn sections(out: &str) -> BTreeMap<String, String> {
    let mut map = BTreeMap::new();
    let mut current = String::from("head");
    for line in out.lines() {
        if let Some(name) = line.strip_prefix("==== ") {
            current = name.to_string();
            continue;
        }
        let s: &mut String = map.entry(current.clone()).or_default();
        s.push_str(line);
        s.push('\n');
    }
    map
}

fn run_sandbox(script: &str) -> Option<String> {
    let o = Command::new("unshare")
        .args([
            "-r",
            "--net",
            "--mount",
            "--propagation",
            "private",
            "sh",
            "-c",
            script,
        ])
        .output()
        .unwrap();
    let out = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    if out.contains("unshare failed") || (out.contains("Operation not permitted") && !out.contains("PROBE")) {
        if std::env::var_os("IRTRACK_REQUIRE_NETNS").is_some() {
            panic!("IRTRACK_REQUIRE_NETNS is set but the sandbox's namespaces do not work here: {out}");
        }
        eprintln!("SKIPPED: no user, network or mount namespace here: {out}");
        return None;
    }
    Some(out)
}

fn tools_present() -> bool {
    let tools = [
        "ptp4l",
        "phc2sys",
        "unshare",
        "setpriv",
        "strace",
        "ip",
        "systemd-analyze",
    ];
    let missing: Vec<&str> = tools.into_iter().filter(|t| !have(t)).collect();
    if missing.is_empty() {
        return true;
    }
    assert!(
        std::env::var_os("IRTRACK_REQUIRE_NETNS").is_none(),
        "IRTRACK_REQUIRE_NETNS is set but {missing:?} are missing (`cargo xtask setup`)"
    );
    eprintln!("SKIPPED: {missing:?} not found (`cargo xtask setup` installs linuxptp, strace)");
    false
}

fn which(cmd: &str) -> String {
    let o = Command::new("sh")
        .args(["-c", &format!("command -v {cmd}")])
        .output()
        .unwrap();
    String::from_utf8_lossy(&o.stdout).trim().to_string()
}

/// The config irtrackd generates for a master with software time stamping on the veth end.
fn ptp4l_conf(dir: &TempDir) -> std::path::PathBuf {
    let c = Config::from_toml(
        "[clock]\nptp = true\ninterface = \"veth0\"\nrole = \"master\"\ntime_stamping = \"software\"\n",
        "test",
    )
    .unwrap();
    let conf = dir.path().join("ptp4l.conf");
    std::fs::write(&conf, c.clock.ptp4l_conf()).unwrap();
    conf
}

/// ptp4l under irtrack-ptp4l.service's confinement reaches LISTENING, and phc2sys under
/// irtrack-phc2sys.service's talks to it over its management socket; both stay within the
/// units' system call filters and address families.
#[test]
fn ptp4l_and_phc2sys_work_inside_the_units_sandbox() {
    if !tools_present() {
        return;
    }
    let ptp4l_unit = Unit::load("irtrack-ptp4l.service");
    let phc2sys_unit = Unit::load("irtrack-phc2sys.service");
    let dir = TempDir::new("ptp-sandbox");
    let conf = ptp4l_conf(&dir);
    let (ptp4l, phc2sys) = (which("ptp4l"), which("phc2sys"));
    let phc2sys_caps = phc2sys_unit.capabilities();
    // Each with its own unit's capabilities; both units have the same file-system settings
    // (assert_reproducible), so they share the mounts.
    let run_ptp4l = confined(
        &ptp4l_unit.capabilities(),
        "/run/ptp4l-caps",
        &format!("strace -f -qq -o /run/strace-ptp4l timeout 4 {ptp4l} -f /run/irtrack-ptp/ptp4l.conf -m -q"),
    );
    let run_phc2sys = confined(
        &phc2sys_caps,
        "/run/phc2sys-caps",
        &format!("strace -f -qq -o /run/strace-phc2sys timeout 2 {phc2sys} -a -rr -m -q"),
    );
    phc2sys_unit.assert_reproducible();
    let body = format!(
        r#"{run_ptp4l} > /run/ptp4l.log 2>&1 &
sleep 1.5
{run_phc2sys} > /run/phc2sys.log 2>&1 || true
wait
for f in ptp4l-caps ptp4l.log strace-ptp4l phc2sys-caps phc2sys.log strace-phc2sys; do echo "==== $f"; cat /run/$f; done"#
    );
    let script = sandbox_script(&ptp4l_unit, &conf, &body);
    let Some(out) = run_sandbox(&script) else {
        return;
    };
    let s = sections(&out);
    // The sandbox is in force: / is read-only, capabilities are the units', no_new_privs.
    assert!(s["head"].contains("PROBE /etc read-only"), "{out}");
    for (unit, file) in [(&ptp4l_unit, "ptp4l-caps"), (&phc2sys_unit, "phc2sys-caps")] {
        let caps = &s[file];
        let mask = format!("{:016x}", capability_mask(&unit.capabilities()));
        assert!(
            caps.contains(&format!("CapBnd:\t{mask}")),
            "{file}: bounding set {mask}: {caps}"
        );
        assert!(
            caps.contains(&format!("CapEff:\t{mask}")),
            "{file}: effective {mask}: {caps}"
        );
        assert!(caps.contains("CapAmb:\t0000000000000000"), "{file}: {caps}");
        assert!(caps.contains("NoNewPrivs:\t1"), "{file}: {caps}");
    }

    // Port 1 is the PTP port on veth0 (port 0 is ptp4l's management socket).
    let log = &s["ptp4l.log"];
    assert!(
        log.contains("port 1: INITIALIZING to LISTENING"),
        "ptp4l did not reach LISTENING:\n{out}"
    );
    for bad in [
        "unknown option",
        "failed to parse",
        "failed to create a clock",
        "Permission denied",
    ] {
        assert!(!log.contains(bad), "{bad}: {log}");
    }
    Trace::of_program(&s["strace-ptp4l"], &ptp4l).assert_within(&ptp4l_unit, "ptp4l");

    // phc2sys -a asked ptp4l (its management socket in /run) for the ports and got answers;
    // with no PHC on a veth it then finds nothing to synchronise and exits.
    let phc = Trace::of_program(&s["strace-phc2sys"], &phc2sys);
    let answered = phc.calls.iter().any(|(n, a)| {
        n == "recvfrom"
            && a.contains("/var/run/ptp4l")
            && a.rsplit("= ")
                .next()
                .is_some_and(|r| r.trim().parse::<i64>().is_ok_and(|n| n > 0))
    });
    assert!(
        answered,
        "phc2sys got no answer from ptp4l:\n{}\n{}",
        s["phc2sys.log"], s["strace-phc2sys"]
    );
    phc.assert_within(&phc2sys_unit, "phc2sys");
}

/// The control: the same sandbox without CAP_NET_BIND_SERVICE, and ptp4l cannot bind PTP's
/// ports 319/320 — the capability the unit keeps is needed, and the sandbox does take the
/// others away.
#[test]
fn ptp4l_without_the_units_bind_capability_fails() {
    if !tools_present() {
        return;
    }
    let unit = Unit::load("irtrack-ptp4l.service");
    assert!(unit.capabilities().contains(&"net_bind_service".to_string()));
    let caps: Vec<String> = unit
        .capabilities()
        .into_iter()
        .filter(|c| c != "net_bind_service")
        .collect();
    let dir = TempDir::new("ptp-sandbox-nocap");
    let conf = ptp4l_conf(&dir);
    let run = confined(
        &caps,
        "/run/caps",
        "timeout 3 ptp4l -f /run/irtrack-ptp/ptp4l.conf -m -q 2>&1",
    );
    let body = format!("{run}; echo ptp4l exit $?; echo '==== caps'; cat /run/caps");
    let Some(out) = run_sandbox(&sandbox_script(&unit, &conf, &body)) else {
        return;
    };
    let mask = format!("{:016x}", capability_mask(&caps));
    assert!(out.contains(&format!("CapBnd:\t{mask}")), "{out}");
    assert!(out.contains("PROBE /etc read-only"), "{out}");
    assert!(
        out.contains("bind failed: Permission denied"),
        "ptp4l bound 319/320 without the capability:\n{out}"
    );
    assert!(out.contains("port 1: INITIALIZING to FAULTY"), "{out}");
    assert!(!out.contains("port 1: INITIALIZING to LISTENING"), "{out}");
}
