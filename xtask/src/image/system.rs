//! The system test: boots the SD image in `qemu-system-aarch64 -M virt,acpi=off` through U-Boot
//! and checks irtrackd on the real kernel (vivid cameras, PL061 GPIO, network, restart, reboot).
//!
//! QEMU runs with its serial console on a pipe: the test reads the boot log from it and types
//! shell commands into the guest's console shell. Host ports are chosen free per run and
//! forwarded to irtrackd's ports. QEMU is killed on every path (the guard's `Drop`), and QEMU
//! exiting before a step completes fails the test.

use std::fmt;
use std::fs;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use super::{Image, UBOOT_QEMU, work_dir};
use crate::util::{self, Ctx};

/// irtrackd's ports in the guest: parameters, NDJSON stream, binary stream, status.
const GUEST_PORTS: [u16; 4] = [7701, 7702, 7703, 7704];
/// What the image's irtrackd.toml configures (checked against what the service reports).
const LED_LINES: [(&str, u32); 4] = [("run", 4), ("track", 5), ("robot", 6), ("fault", 7)];
const CAMERA_FPS: f64 = 15.0;
const CONFIG_GAIN: i64 = 16;
const BOOT_TIMEOUT: Duration = Duration::from_secs(120);
/// Empty lines sent after each console command (see [`Qemu::console`]).
const PUSH: &str = "\n\n\n\n\n\n\n\n\n\n\n\n\n\n\n\n";

/// Free host ports, all bound at once so they differ, then released for QEMU.
fn free_ports<const N: usize>() -> Result<[u16; N]> {
    let listeners: Vec<TcpListener> = (0..N)
        .map(|_| TcpListener::bind((Ipv4Addr::LOCALHOST, 0)))
        .collect::<std::io::Result<_>>()?;
    let mut ports = [0; N];
    for (p, l) in ports.iter_mut().zip(&listeners) {
        *p = l.local_addr()?.port();
    }
    Ok(ports)
}

fn qemu_command(disk: &Path, host_ports: &[u16; 4]) -> Command {
    let fwd: Vec<String> = host_ports
        .iter()
        .zip(GUEST_PORTS)
        .map(|(h, g)| format!("hostfwd=tcp:127.0.0.1:{h}-:{g}"))
        .collect();
    let mut cmd = Command::new("qemu-system-aarch64");
    // acpi=off keeps the PL061 GPIO in the device tree when booting through U-Boot.
    cmd.args([
        "-M",
        "virt,acpi=off",
        "-cpu",
        "cortex-a53",
        "-smp",
        "2",
        "-m",
        "512",
    ])
    .args(["-display", "none", "-monitor", "none", "-serial", "stdio"])
    .args(["-bios", UBOOT_QEMU])
    .arg("-drive")
    .arg(format!("if=none,file={},format=raw,id=sd", disk.display()))
    .args(["-device", "virtio-blk-device,drive=sd"])
    .arg("-netdev")
    .arg(format!("user,id=net0,{}", fwd.join(",")))
    .args(["-device", "virtio-net-device,netdev=net0"]);
    cmd
}

/// A running QEMU whose serial console is collected into a log; killed when dropped.
struct Qemu {
    child: Child,
    stdin: ChildStdin,
    log: Arc<Mutex<String>>,
    log_path: PathBuf,
    started: Instant,
    commands: u32,
}

impl Qemu {
    fn spawn(mut cmd: Command, log_path: &Path) -> Result<Self> {
        println!("$ {}", util::display_cmd(&cmd));
        cmd.stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        let started = Instant::now();
        let mut child = cmd
            .spawn()
            .context("starting qemu-system-aarch64 (run `cargo xtask setup`)")?;
        let stdin = child.stdin.take().context("qemu stdin")?;
        let mut stdout = child.stdout.take().context("qemu stdout")?;
        let log = Arc::new(Mutex::new(String::new()));
        let mut file = fs::File::create(log_path)?;
        let sink = Arc::clone(&log);
        thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = stdout.read(&mut buf) {
                if n == 0 {
                    break;
                }
                let _ = file.write_all(&buf[..n]);
                let text = String::from_utf8_lossy(&buf[..n]).replace('\r', "");
                if let Ok(mut log) = sink.lock() {
                    log.push_str(&text);
                }
            }
        });
        Ok(Self {
            child,
            stdin,
            log,
            log_path: log_path.to_path_buf(),
            started,
            commands: 0,
        })
    }

    fn log_len(&self) -> usize {
        self.log.lock().map(|l| l.len()).unwrap_or(0)
    }

    fn ensure_running(&mut self, waiting_for: &str) -> Result<()> {
        if let Some(status) = self.child.try_wait()? {
            bail!(
                "QEMU exited ({status}) while waiting for {waiting_for}; serial log in {}",
                self.log_path.display()
            );
        }
        Ok(())
    }

    /// Waits until `needle` appears in the log after byte offset `from`; returns the offset
    /// just past it.
    fn wait_for(&mut self, needle: &str, from: usize, timeout: Duration) -> Result<usize> {
        let start = Instant::now();
        loop {
            if let Ok(log) = self.log.lock()
                && let Some(i) = log.get(from..).and_then(|rest| rest.find(needle))
            {
                return Ok(from + i + needle.len());
            }
            self.ensure_running(&format!("{needle:?}"))?;
            if start.elapsed() > timeout {
                bail!(
                    "no {needle:?} on the serial console within {}; log in {}",
                    util::fmt_duration(timeout),
                    self.log_path.display()
                );
            }
            thread::sleep(Duration::from_millis(50));
        }
    }

    /// Runs a shell command on the guest console and returns its output. Markers printed by
    /// `printf` bracket the output; the terminal's echo of the typed line cannot match them.
    fn console(&mut self, command: &str, timeout: Duration) -> Result<String> {
        self.commands += 1;
        let n = self.commands;
        let begin = format!("@@B{n}@@\n");
        let end = format!("@@E{n}@@");
        let from = self.log_len();
        // Trailing newlines: QEMU's PL011 raises the receive interrupt only at the FIFO trigger
        // level, so the last few bytes written can sit in the FIFO until more arrive. Empty
        // lines push the command's own newline through and are ignored by the shell.
        let line = format!("printf '@@%s@@\\n' B{n}; {command}; printf '@@%s@@\\n' E{n}\n{PUSH}");
        self.stdin.write_all(line.as_bytes())?;
        self.stdin.flush()?;
        let after_begin = self.wait_for(&begin, from, timeout)?;
        let after_end = self.wait_for(&end, after_begin, timeout)?;
        let log = self
            .log
            .lock()
            .map_err(|_| anyhow::anyhow!("serial log lock poisoned"))?;
        Ok(log[after_begin..after_end - end.len()].to_owned())
    }
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One named check of the system test.
pub struct Check {
    pub name: &'static str,
    pub ok: bool,
    pub detail: String,
}

#[derive(Default)]
pub struct Report {
    pub checks: Vec<Check>,
    pub figures: Vec<String>,
}

impl Report {
    pub fn passed(&self) -> u64 {
        self.checks.iter().filter(|c| c.ok).count() as u64
    }
    pub fn failed(&self) -> u64 {
        self.checks.iter().filter(|c| !c.ok).count() as u64
    }
    fn check(&mut self, name: &'static str, result: Result<String>) {
        let (ok, detail) = match result {
            Ok(d) => (true, d),
            Err(e) => (false, format!("{e:#}")),
        };
        println!(
            "system-test: {} {name}: {detail}",
            if ok { "PASS" } else { "FAIL" }
        );
        self.checks.push(Check { name, ok, detail });
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "system test:")?;
        for c in &self.checks {
            writeln!(
                f,
                "  {} {}: {}",
                if c.ok { "PASS" } else { "FAIL" },
                c.name,
                c.detail
            )?;
        }
        for fig in &self.figures {
            writeln!(f, "  {fig}")?;
        }
        write!(
            f,
            "system-test: {} passed, {} failed",
            self.passed(),
            self.failed()
        )
    }
}

/// GET /status over the forwarded port, parsed; retried while the guest is not listening yet
/// (QEMU's forwarder accepts and then closes in that case).
fn get_status(port: u16) -> Result<Json> {
    let mut last = anyhow::anyhow!("no attempt");
    for _ in 0..20 {
        match try_get_status(port) {
            Ok(j) => return Ok(j),
            Err(e) => last = e,
        }
        thread::sleep(Duration::from_millis(500));
    }
    Err(last.context(format!("GET /status on 127.0.0.1:{port}")))
}

fn try_get_status(port: u16) -> Result<Json> {
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    s.write_all(b"GET /status HTTP/1.0\r\nHost: irtrack\r\n\r\n")?;
    let mut resp = String::new();
    s.read_to_string(&mut resp)?;
    let (head, body) = resp.split_once("\r\n\r\n").context("no HTTP header end")?;
    if !head.starts_with("HTTP/1.") || !head.lines().next().is_some_and(|l| l.contains(" 200")) {
        bail!("unexpected reply: {}", head.lines().next().unwrap_or(""));
    }
    Json::parse(body)
}

/// `GET /` (the embedded set-up page) and one message of the live WebSocket (`/api/live`),
/// over raw sockets: the handshake and one unmasked server frame are simple enough to read
/// by hand, and xtask stays free of HTTP/WebSocket client crates.
fn check_web(port: u16) -> Result<String> {
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let mut s = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    s.set_read_timeout(Some(Duration::from_secs(20)))?;
    s.write_all(b"GET / HTTP/1.0\r\nHost: irtrack\r\n\r\n")?;
    let mut page = String::new();
    s.read_to_string(&mut page)?;
    let (head, body) = page.split_once("\r\n\r\n").context("no HTTP header end for /")?;
    if !head.lines().next().is_some_and(|l| l.contains(" 200")) || !body.contains("<html") {
        bail!(
            "GET / answered {:?} with {} bytes",
            head.lines().next(),
            body.len()
        );
    }
    let mut ws = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    ws.set_read_timeout(Some(Duration::from_secs(20)))?;
    ws.write_all(
        b"GET /api/live HTTP/1.1\r\nHost: irtrack\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
          Sec-WebSocket-Key: aXJ0cmFjay1zeXN0ZW0tdA==\r\nSec-WebSocket-Version: 13\r\n\r\n",
    )?;
    // Answer head, byte by byte up to the blank line (the first frame follows directly).
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        ws.read_exact(&mut byte)
            .context("reading the WebSocket handshake answer")?;
        head.push(byte[0]);
        if head.len() > 8192 {
            bail!("WebSocket handshake answer too long");
        }
    }
    let head = String::from_utf8_lossy(&head);
    if !head.starts_with("HTTP/1.1 101") {
        bail!("no WebSocket upgrade: {}", head.lines().next().unwrap_or(""));
    }
    let mut hdr = [0u8; 2];
    ws.read_exact(&mut hdr)?;
    let len = match hdr[1] & 0x7f {
        126 => {
            let mut b = [0u8; 2];
            ws.read_exact(&mut b)?;
            u64::from(u16::from_be_bytes(b))
        }
        127 => {
            let mut b = [0u8; 8];
            ws.read_exact(&mut b)?;
            u64::from_be_bytes(b)
        }
        n => u64::from(n),
    };
    if hdr[0] & 0x0f != 1 || len > 1 << 20 {
        bail!(
            "first live frame is not a text message (opcode {}, {len} bytes)",
            hdr[0] & 0x0f
        );
    }
    let mut payload = vec![0u8; len as usize];
    ws.read_exact(&mut payload)?;
    let msg = Json::parse(&String::from_utf8_lossy(&payload))?;
    let kind = text(&msg, "type")?.to_string();
    Ok(format!(
        "GET / {} bytes of HTML; first live message: {kind} ({len} bytes)",
        body.len()
    ))
}

fn num(j: &Json, path: &str) -> Result<f64> {
    j.get(path)
        .and_then(Json::as_f64)
        .with_context(|| format!("status has no number at {path}"))
}

fn text<'a>(j: &'a Json, path: &str) -> Result<&'a str> {
    j.get(path)
        .and_then(Json::as_str)
        .with_context(|| format!("status has no string at {path}"))
}

/// Boots a copy of the image and runs every check. Errors only for setup failures; failed
/// checks are in the report.
pub fn run(ctx: &Ctx, image: &Image) -> Result<Report> {
    let dir = work_dir(ctx).join("system-test");
    fs::create_dir_all(&dir)?;
    // A parameter set for the vivid rig; if host-tools cannot make one, the checks that need
    // it fail and the others still run.
    let params = make_params(ctx, &dir).and_then(|f| Ok((rig_id_of(ctx, &f)?, f)));
    // A fresh copy per run: the test's parameter pushes must not leak into the next run.
    let disk = dir.join("sd.img");
    let _ = fs::remove_file(&disk);
    let cp = Command::new("cp")
        .arg("--sparse=always")
        .arg(&image.sd_img)
        .arg(&disk)
        .status()?;
    if !cp.success() {
        bail!("copying the image to {}", disk.display());
    }
    let ports = free_ports::<4>()?;
    let [params_port, stream_port, _binary_port, status_port] = ports;
    let mut report = Report::default();
    report.figures.push(format!(
        "image size: {:.1} MiB ({} bytes; boot {:.0} MiB + root {:.0} MiB)",
        super::mib(image.size_bytes),
        image.size_bytes,
        super::mib(image.boot_bytes),
        super::mib(image.root_bytes)
    ));
    let mut q = Qemu::spawn(qemu_command(&disk, &ports), &dir.join("serial-boot1.log"))?;

    // 1. Boot to ready.
    let ready = q.wait_for("irtrackd ready", 0, BOOT_TIMEOUT);
    let boot_s = q.started.elapsed().as_secs_f64();
    match ready {
        Ok(_) => {
            report.check(
                "boot to irtrackd ready (U-Boot, kernel, initramfs, busybox init)",
                Ok(format!("{boot_s:.1} s")),
            );
            report.figures.push(format!(
                "boot time to ready: {boot_s:.1} s (QEMU start to irtrackd's ready line)"
            ));
        }
        Err(e) => {
            report.check(
                "boot to irtrackd ready (U-Boot, kernel, initramfs, busybox init)",
                Err(e),
            );
            return Ok(report);
        }
    };
    // The console shell starts with irtrackd; make sure it answers before typing commands.
    let shell = q.console("uname -r", Duration::from_secs(20));
    report.check(
        "guest console shell",
        shell.map(|s| format!("kernel {}", s.trim())),
    );
    report.check(OPERATOR, set_operator_password(&mut q, status_port));

    report.check(
        "v4l2 capture from vivid (format, streaming, kernel timestamps)",
        check_capture(status_port),
    );
    report.check(
        "set-up page and one live WebSocket message through the forwarded status port",
        check_web(status_port),
    );
    if focus_camera_loss()? {
        // Focused run for work on the V4L2 reconnect path: no parameters, no reboot.
        camera_loss(&mut report, &mut q, status_port);
        report.check(RESTART, check_restart(&mut q, status_port, None));
        report.figures.push(qemu_time(&q));
        return Ok(report);
    }
    report.check(
        "status LEDs on the PL061 through gpiocdev, read back via gpiolib",
        check_gpio(&mut q, status_port, true),
    );
    report.check(
        "unsigned parameter push refused (only the image's trusted keys may push)",
        match &params {
            Ok((_, file)) => check_unsigned_refused(ctx, params_port, file),
            Err(e) => Err(anyhow::anyhow!("no parameter set to push: {e:#}")),
        },
    );
    let pushed = match &params {
        Ok((rig_id, file)) => {
            push_params(ctx, params_port, file, Some(&image.signing_key)).map(|d| (rig_id.clone(), d))
        }
        Err(e) => Err(anyhow::anyhow!("no parameter set to push: {e:#}")),
    };
    let rig_id = pushed.as_ref().ok().map(|(id, _)| id.clone());
    report.check(
        "host-tools push-params over the forwarded port",
        pushed.map(|(_, d)| d),
    );
    report.check(
        "pushed parameters in use",
        match &rig_id {
            Some(id) => check_params_used(status_port, id),
            None => Err(anyhow::anyhow!("nothing was pushed")),
        },
    );
    report.check(
        "position stream reaches a host client",
        check_stream(stream_port, rig_id.is_some()),
    );
    if rig_id.is_some() {
        report.check(
            "fault LED off once parameters are in use",
            check_gpio(&mut q, status_port, false),
        );
    }
    // Before the restart check, so that a restart after the cameras came back is tested too.
    camera_loss(&mut report, &mut q, status_port);
    report.check(RESTART, check_restart(&mut q, status_port, rig_id.as_deref()));
    match check_reboot(&mut q, status_port, rig_id.as_deref()) {
        Ok((detail, second_boot_s)) => {
            report
                .figures
                .push(format!("reboot to ready: {second_boot_s:.1} s"));
            report.check("parameters survive a reboot", Ok(detail));
        }
        Err(e) => report.check("parameters survive a reboot", Err(e)),
    }
    report.figures.push(qemu_time(&q));
    drop(q);
    Ok(report)
}

fn qemu_time(q: &Qemu) -> String {
    format!(
        "system test in QEMU: {:.0} s (QEMU start to the last check)",
        q.started.elapsed().as_secs_f64()
    )
}

fn camera_loss(report: &mut Report, q: &mut Qemu, status_port: u16) {
    let t0 = Instant::now();
    report.check(CAMERA_LOSS, check_camera_loss(q, status_port));
    report.figures.push(format!(
        "camera-loss check: {:.1} s (unbind, hold, bind, reopen, frames flowing)",
        t0.elapsed().as_secs_f64()
    ));
}

const CAMERA_LOSS: &str =
    "cameras lost (vivid unbound) are reported and reopened with the operator's live gain";
const OPERATOR: &str = "operator password set on the console (irtrackd --hash-password), tuning needs it";
/// Gain the operator sets live on camera 1 before the cameras are lost: neither vivid's
/// default (100) nor the config's ([`CONFIG_GAIN`]), so only the re-applied live value can show it.
const LIVE_GAIN: i64 = 57;
const RESTART: &str = "irtrackd restarts after being killed";

/// `IRTRACK_SYSTEM_TEST_ONLY=camera-loss` runs only boot, capture, camera loss and restart.
fn focus_camera_loss() -> Result<bool> {
    match std::env::var("IRTRACK_SYSTEM_TEST_ONLY") {
        Err(_) => Ok(false),
        Ok(v) if v == "camera-loss" => Ok(true),
        Ok(v) => bail!("IRTRACK_SYSTEM_TEST_ONLY={v:?}: the only focused run is `camera-loss`"),
    }
}

/// What an integrator does on a board before anyone may change settings from the set-up view:
/// hash a password with irtrackd itself, put it under `[service]`, restart the service. Then
/// a tuning change must be refused with a wrong password and accepted with the right one.
fn set_operator_password(q: &mut Qemu, status_port: u16) -> Result<String> {
    let config = "/etc/irtrack/irtrackd.toml";
    let out = q.console(
        &format!(
            "H=$(echo {} | irtrackd --hash-password 2>/dev/null) && \
             sed -i \"/^\\[service\\]/a operator_password_hash = \\\"$H\\\"\" {config} && \
             grep -c '^operator_password_hash = \"\\$argon2id' {config}",
            util::OPERATOR_PASSWORD
        ),
        Duration::from_secs(60),
    )?;
    if !out.lines().any(|l| l.trim() == "1") {
        bail!(
            "the password hash did not land in {config} once: {:?}",
            out.trim()
        );
    }
    let pid = pid_of_irtrackd(q)?;
    if pid.is_empty() {
        bail!("irtrackd not running before the restart");
    }
    let from = q.log_len();
    q.console(&format!("kill {pid}"), Duration::from_secs(10))?;
    q.wait_for("irtrackd ready", from, Duration::from_secs(60))?;
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, status_port));
    // Reading is open to everyone; a change is not.
    let body = r#"{"threshold_dn": 41}"#;
    let (wrong, _) = util::http_as(addr, "POST", "/api/tuning", "not-the-password", body)?;
    if wrong != 401 {
        bail!("a tuning change with a wrong password answered {wrong}, want 401");
    }
    let (code, answer) = util::http_as(addr, "POST", "/api/tuning", util::OPERATOR_PASSWORD, body)?;
    if code != 200 {
        bail!("a tuning change with the operator password answered {code}: {answer}");
    }
    let threshold = Json::parse(&answer)?
        .get("threshold_dn")
        .and_then(Json::as_f64)
        .context("tuning answer without threshold_dn")?;
    if threshold != 41.0 {
        bail!("tuning answer shows threshold {threshold}, want 41: {answer}");
    }
    Ok(format!(
        "hash written to {config}, irtrackd restarted; wrong password 401, operator 200 (threshold 41)"
    ))
}

/// Camera `camera`'s gain in a `/api/tuning` object.
fn tuning_gain(tuning: &Json, camera: usize) -> Option<f64> {
    tuning
        .get(&format!("cameras.{camera}.gain"))
        .and_then(Json::as_f64)
}

fn check_capture(port: u16) -> Result<String> {
    let s1 = get_status(port)?;
    let desc = text(&s1, "source.description")?.to_owned();
    for want in ["v4l2", "/dev/video0", "/dev/video1", "vivid"] {
        if !desc.contains(want) {
            bail!("source description lacks {want:?}: {desc}");
        }
    }
    let t0 = Instant::now();
    let sets0 = num(&s1, "source.sets_delivered")?;
    thread::sleep(Duration::from_secs(3));
    let s2 = get_status(port)?;
    let sets1 = num(&s2, "source.sets_delivered")?;
    let rate = (sets1 - sets0) / t0.elapsed().as_secs_f64();
    if rate < CAMERA_FPS * 0.3 {
        bail!("only {rate:.1} frame sets/s delivered (vivid runs at {CAMERA_FPS} fps): {desc}");
    }
    let mut fps = Vec::new();
    for cam in 0..2 {
        let frames = num(&s2, &format!("source.cameras.{cam}.frames"))?;
        // The service computes fps from the kernel timestamps of successive frames.
        let f = num(&s2, &format!("source.cameras.{cam}.fps"))?;
        if frames <= 0.0 || !(CAMERA_FPS * 0.5..=CAMERA_FPS * 1.5).contains(&f) {
            bail!("camera {cam}: {frames} frames at {f:.1} fps from timestamps (want about {CAMERA_FPS})");
        }
        fps.push(f);
    }
    let pairing_max_us = num(&s2, "source.pairing_error_max_us")?;
    let half_period_us = 0.5e6 / CAMERA_FPS;
    if pairing_max_us > half_period_us {
        bail!("pairing error {pairing_max_us:.0} µs exceeds half a frame period");
    }
    Ok(format!(
        "{desc}; {rate:.1} sets/s, timestamp fps {:.1}/{:.1}, pairing error ≤ {pairing_max_us:.0} µs, unpaired dropped {}",
        fps[0],
        fps[1],
        num(&s2, "source.unpaired_dropped").unwrap_or(f64::NAN)
    ))
}

/// One line of gpiolib's debugfs view, for a line requested by irtrackd.
#[derive(Debug, Clone, PartialEq)]
struct GpioLine {
    offset: u32,
    output: bool,
    high: bool,
}

/// Parses /sys/kernel/debug/gpio for the chip labelled `label`: lines whose consumer is
/// `consumer`. The header gives the chip's global base (`GPIOs 512-519`).
fn parse_debugfs_gpio(text: &str, label: &str, consumer: &str) -> Vec<GpioLine> {
    let mut out = Vec::new();
    let mut base: Option<u32> = None;
    for line in text.lines() {
        if line.starts_with("gpiochip") {
            base = if line.contains(label) {
                line.split("GPIOs ")
                    .nth(1)
                    .and_then(|r| r.split('-').next())
                    .and_then(|n| n.trim().parse().ok())
            } else {
                None
            };
            continue;
        }
        let (Some(base), Some(rest)) = (base, line.trim_start().strip_prefix("gpio-")) else {
            continue;
        };
        let Some((num, rest)) = rest.split_once(' ') else {
            continue;
        };
        let (Ok(num), Some((names, state))) = (num.parse::<u32>(), rest.split_once(')')) else {
            continue;
        };
        let used_by = names.split('|').nth(1).map(str::trim);
        if used_by != Some(consumer) || num < base {
            continue;
        }
        let mut words = state.split_whitespace();
        let output = words.next() == Some("out");
        let high = words.next() == Some("hi");
        out.push(GpioLine {
            offset: num - base,
            output,
            high,
        });
    }
    out
}

/// Samples the LED lines through the kernel for about 3 s. Always: the four configured lines
/// are outputs held by irtrackd and the heartbeat toggles. `expect_no_params_fault`: the fault
/// LED flashes (no parameters yet); otherwise, with no fault reported, it stays off.
fn check_gpio(q: &mut Qemu, status_port: u16, expect_no_params_fault: bool) -> Result<String> {
    let before = get_status(status_port)?;
    let samples = 30;
    // A script on the image loops over gpiolib's debugfs view (a loop typed into the piped
    // console shell would only run once the next line arrives).
    let out = q.console(
        &format!("irtrack-gpio-sample 9030000.pl061 {samples}"),
        Duration::from_secs(40),
    )?;
    let after = get_status(status_port)?;
    let mut seen = [[false; 2]; 4];
    let mut n = 0;
    for sample in out.split("SAMPLE\n").skip(1) {
        let lines = parse_debugfs_gpio(sample, "9030000.pl061", "irtrackd");
        for (i, (name, offset)) in LED_LINES.iter().enumerate() {
            let line = lines
                .iter()
                .find(|l| l.offset == *offset)
                .with_context(|| format!("{name} LED line {offset} not held by irtrackd:\n{sample}"))?;
            if !line.output {
                bail!("{name} LED line {offset} is not an output:\n{sample}");
            }
            seen[i][usize::from(line.high)] = true;
        }
        n += 1;
    }
    if n < samples / 2 {
        bail!("only {n} of {samples} gpio samples parsed:\n{out}");
    }
    if !(seen[0][0] && seen[0][1]) {
        bail!("run LED (heartbeat) did not toggle in {n} samples");
    }
    let (f0, f1) = (faults_of(&before), faults_of(&after));
    let fault_detail = if expect_no_params_fault {
        if !f0.iter().chain(&f1).any(|f| f == "no_params") {
            bail!("status does not report the no-parameters fault: {f0:?} {f1:?}");
        }
        if !seen[3][1] {
            bail!("fault LED never lit in {n} samples although status reports {f0:?}");
        }
        format!("fault LED flashing for {f0:?}")
    } else if f0.is_empty() && f1.is_empty() {
        if seen[3][1] {
            bail!("fault LED lit although status reports no fault");
        }
        "fault LED off, no faults reported".to_owned()
    } else {
        format!("fault LED not checked: status reports faults {f0:?} {f1:?}")
    };
    Ok(format!(
        "lines 4-7 outputs held by irtrackd, heartbeat toggling over {n} samples; {fault_detail}"
    ))
}

/// Samples the fault LED through gpiolib; returns (samples with it lit, samples parsed).
fn sample_fault_led(q: &mut Qemu, samples: usize) -> Result<(usize, usize)> {
    let (name, offset) = LED_LINES[3];
    let out = q.console(
        &format!("irtrack-gpio-sample 9030000.pl061 {samples}"),
        Duration::from_secs(40),
    )?;
    let mut lit = 0;
    let mut n = 0;
    for sample in out.split("SAMPLE\n").skip(1) {
        let lines = parse_debugfs_gpio(sample, "9030000.pl061", "irtrackd");
        let line = lines
            .iter()
            .find(|l| l.offset == offset)
            .with_context(|| format!("{name} LED line {offset} not held by irtrackd:\n{sample}"))?;
        lit += usize::from(line.high);
        n += 1;
    }
    if n < samples / 2 {
        bail!("only {n} of {samples} gpio samples parsed:\n{out}");
    }
    Ok((lit, n))
}

/// `host-tools simulate` writes a rig (two VGA cameras, like the vivid ones) as `rig.irp`.
fn make_params(ctx: &Ctx, dir: &Path) -> Result<PathBuf> {
    let out_dir = dir.join("sim");
    let out = ctx
        .cargo()
        .args([
            "run",
            "-q",
            "-p",
            "irtrack-host-tools",
            "--",
            "simulate",
            "--frames",
            "1",
            "--out",
        ])
        .arg(&out_dir)
        .output()
        .context("running host-tools simulate")?;
    if !out.status.success() {
        bail!(
            "host-tools simulate failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let file = out_dir.join("rig.irp");
    if !file.is_file() {
        bail!("host-tools simulate wrote no {}", file.display());
    }
    Ok(file)
}

fn rig_id_of(ctx: &Ctx, file: &Path) -> Result<String> {
    let out = ctx
        .cargo()
        .args(["run", "-q", "-p", "irtrack-host-tools", "--", "show-params"])
        .arg(file)
        .output()
        .context("running host-tools show-params")?;
    let text = String::from_utf8_lossy(&out.stdout);
    text.lines()
        .find_map(|l| l.trim().strip_prefix("rig id:").map(|r| r.trim().to_owned()))
        .filter(|id| !id.is_empty())
        .with_context(|| format!("no `rig id:` in host-tools show-params output:\n{text}"))
}

/// An unsigned push must be refused by the image's irtrackd with `UNAUTHORIZED`.
fn check_unsigned_refused(ctx: &Ctx, port: u16, file: &Path) -> Result<String> {
    match push_params(ctx, port, file, None) {
        Ok(reply) => bail!("an unsigned blob was accepted: {reply}"),
        Err(e) => {
            let text = format!("{e:#}");
            match text.lines().find(|l| l.contains("UNAUTHORIZED")) {
                Some(line) => Ok(line.trim().to_owned()),
                None => bail!("refused, but not as UNAUTHORIZED: {text}"),
            }
        }
    }
}

fn push_params(ctx: &Ctx, port: u16, file: &Path, sign_key: Option<&Path>) -> Result<String> {
    let mut cmd = ctx.cargo();
    cmd.args([
        "run",
        "-q",
        "-p",
        "irtrack-host-tools",
        "--",
        "push-params",
        "--to",
    ])
    .arg(format!("127.0.0.1:{port}"));
    if let Some(key) = sign_key {
        cmd.arg("--sign-key").arg(key);
    }
    let out = cmd.arg(file).output().context("running host-tools push-params")?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    if !out.status.success() {
        bail!("push-params {}: {}", out.status, text.trim());
    }
    Ok(text.trim().lines().last().unwrap_or("").to_owned())
}

fn check_params_used(port: u16, rig_id: &str) -> Result<String> {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let s = get_status(port)?;
        let id = s.get("params.rig_id").and_then(Json::as_str).unwrap_or("");
        let published = num(&s, "processing.published").unwrap_or(0.0);
        if id == rig_id {
            return Ok(format!("status shows rig {id}; {published} records published"));
        }
        if Instant::now() > deadline {
            bail!("status shows rig {id:?}, want {rig_id:?}");
        }
        thread::sleep(Duration::from_millis(300));
    }
}

/// Reads NDJSON records from the forwarded stream port for a few seconds.
fn check_stream(port: u16, params_pushed: bool) -> Result<String> {
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let s = TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    let mut reader = BufReader::new(s);
    let start = Instant::now();
    let mut records = Vec::new();
    let mut line = String::new();
    while start.elapsed() < Duration::from_secs(3) {
        line.clear();
        if reader.read_line(&mut line)? == 0 {
            bail!("stream closed after {} records", records.len());
        }
        records.push(Json::parse(line.trim()).with_context(|| format!("bad NDJSON record {line:?}"))?);
    }
    if records.len() < 5 {
        bail!("only {} records in 3 s", records.len());
    }
    let field = |r: &Json, k: &str| {
        r.get(k)
            .and_then(Json::as_f64)
            .with_context(|| format!("record without {k}"))
    };
    let (first, last) = (&records[0], &records[records.len() - 1]);
    let frames = field(last, "frame")? - field(first, "frame")?;
    let span_s = (field(last, "capture_ts_ns")? - field(first, "capture_ts_ns")?) / 1e9;
    if frames <= 0.0 || span_s <= 0.0 {
        bail!("frame numbers or capture timestamps do not advance");
    }
    let crc = field(last, "params_crc")?;
    if params_pushed && crc == 0.0 {
        bail!("records carry no parameter CRC although parameters were pushed");
    }
    let status = last.get("status").and_then(Json::as_str).unwrap_or("?");
    Ok(format!(
        "{} records in 3 s, frames advanced by {frames}, capture timestamps span {span_s:.2} s, last status {status}",
        records.len()
    ))
}

fn faults_of(j: &Json) -> Vec<String> {
    j.get("faults")
        .and_then(Json::as_array)
        .map(|a| a.iter().filter_map(|f| f.as_str().map(str::to_owned)).collect())
        .unwrap_or_default()
}

/// Polls the status until `pred` holds (or the time is up); returns the last document.
fn wait_status(port: u16, timeout: Duration, pred: impl Fn(&Json) -> bool) -> Result<(Json, bool)> {
    let deadline = Instant::now() + timeout;
    loop {
        let s = get_status(port)?;
        if pred(&s) {
            return Ok((s, true));
        }
        if Instant::now() > deadline {
            return Ok((s, false));
        }
        thread::sleep(Duration::from_millis(250));
    }
}

/// Unbinds the vivid driver (one platform device that owns both instances, so /dev/video0 and
/// /dev/video1 disappear under the running streams), then binds it again: the source must
/// report the loss while the driver is gone and reopen both cameras by itself, on the same
/// device paths (a restart afterwards, the next check, opens them again).
fn check_camera_loss(q: &mut Qemu, port: u16) -> Result<String> {
    let result = camera_loss_steps(q, port);
    match result {
        Ok(detail) => Ok(detail),
        // The guest's view of the video nodes says most about a failed reopen.
        Err(e) => Err(e.context(format!("video nodes in the guest: {}", video_nodes(q)))),
    }
}

fn video_nodes(q: &mut Qemu) -> String {
    q.console(
        "ls -l /dev/video* 2>&1; ls /sys/class/video4linux 2>&1",
        Duration::from_secs(10),
    )
    .map(|s| s.split_whitespace().collect::<Vec<_>>().join(" "))
    .unwrap_or_else(|e| format!("(not read: {e:#})"))
}

fn camera_loss_steps(q: &mut Qemu, port: u16) -> Result<String> {
    let has_lost = |s: &Json| faults_of(s).iter().any(|f| f == "camera_lost");
    // The operator tunes camera 1's gain live; a camera coming back must come back with it.
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let (code, answer) = util::http_as(
        addr,
        "POST",
        "/api/tuning",
        util::OPERATOR_PASSWORD,
        &format!(r#"{{"cameras": [{{"camera": 1, "gain": {LIVE_GAIN}}}]}}"#),
    )?;
    if code != 200 {
        bail!("setting camera 1's gain to {LIVE_GAIN} answered {code}: {answer}");
    }
    // The loop applies it before its next set, which under emulation can be after the answer.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (_, answer) = util::http(addr, "GET", "/api/tuning")?;
        let gain = Json::parse(&answer).ok().and_then(|t| tuning_gain(&t, 1));
        if gain == Some(LIVE_GAIN as f64) {
            break;
        }
        if Instant::now() > deadline {
            bail!("camera 1's gain still reads {gain:?} 10 s after setting {LIVE_GAIN}: {answer}");
        }
        thread::sleep(Duration::from_millis(200));
    }
    let s0 = get_status(port)?;
    let reconnects0 = num(&s0, "source.reconnects")?;
    let faults0 = faults_of(&s0);
    let t0 = Instant::now();
    q.console(
        "cd /sys/bus/platform/drivers/vivid && V=$(ls -d vivid*) && echo $V > unbind; cd /",
        Duration::from_secs(10),
    )?;
    let (s, lost) = wait_status(port, Duration::from_secs(10), has_lost)?;
    if !lost {
        bail!(
            "no camera_lost fault after unbinding vivid; faults {:?}",
            faults_of(&s)
        );
    }
    let lost_s = t0.elapsed().as_secs_f64();
    // Still reported, shown on the fault LED, and no frame set delivered, while the driver
    // stays unbound.
    let sets_lost = num(&s, "source.sets_delivered")?;
    let (lit, samples) = sample_fault_led(q, 25)?;
    if lit == 0 {
        bail!("fault LED never lit in {samples} samples while the cameras were lost");
    }
    let s = get_status(port)?;
    if !has_lost(&s) || num(&s, "source.sets_delivered")? != sets_lost {
        bail!(
            "with vivid unbound the status shows faults {:?} and {} frame sets (was {sets_lost})",
            faults_of(&s),
            num(&s, "source.sets_delivered")?
        );
    }
    let t1 = Instant::now();
    q.console(
        "echo $V > /sys/bus/platform/drivers/vivid/bind",
        Duration::from_secs(10),
    )?;
    // Both cameras reopened (the counter is published with the first set after the reopen).
    let (s, back) = wait_status(port, Duration::from_secs(20), |s| {
        num(s, "source.reconnects").is_ok_and(|r| r >= reconnects0 + 2.0) && !has_lost(s)
    })?;
    if !back {
        bail!(
            "cameras not reopened within 20 s of binding: reconnects {:?} (was {reconnects0}), faults {:?}",
            num(&s, "source.reconnects").ok(),
            faults_of(&s)
        );
    }
    let reopen_s = t1.elapsed().as_secs_f64();
    let sets0 = num(&s, "source.sets_delivered")?;
    let (s2, flowing) = wait_status(port, Duration::from_secs(8), |s| {
        num(s, "source.sets_delivered").is_ok_and(|n| n >= sets0 + 15.0)
    })?;
    if !flowing {
        bail!(
            "frame sets stopped after reconnecting: {:?} (was {sets0}), faults {:?}",
            num(&s2, "source.sets_delivered").ok(),
            faults_of(&s2)
        );
    }
    let new_faults: Vec<String> = faults_of(&s2)
        .into_iter()
        .filter(|f| !faults0.contains(f))
        .collect();
    if !new_faults.is_empty() {
        bail!("after the reopen the status reports {new_faults:?}, not there before the unbind");
    }
    // The cameras' values as read back from the devices after the reopen (irtrackd reads them
    // again when a camera reconnects): camera 1 has the live gain, camera 0 the config's.
    let (_, answer) = util::http(addr, "GET", "/api/tuning")?;
    let tuning = Json::parse(&answer)?;
    let gains = (tuning_gain(&tuning, 0), tuning_gain(&tuning, 1));
    if gains.1 != Some(LIVE_GAIN as f64) || gains.0 != Some(CONFIG_GAIN as f64) {
        bail!(
            "after the reopen the cameras' gains are {:?} / {:?}, want {CONFIG_GAIN} (config) / {LIVE_GAIN} (set live before the loss)",
            gains.0,
            gains.1
        );
    }
    Ok(format!(
        "camera_lost reported {lost_s:.1} s after unbind and held while unbound (fault LED lit \
         in {lit} of {samples} samples); both cameras reopened {reopen_s:.1} s after bind (reconnects {reconnects0} -> {}), {} frame sets since, \
         gains {CONFIG_GAIN} / {LIVE_GAIN} kept, faults now {:?}",
        num(&s2, "source.reconnects")?,
        num(&s2, "source.sets_delivered")? - sets0,
        faults_of(&s2)
    ))
}

/// The rig id in the status document must be the pushed one (or none when nothing was pushed).
fn check_rig(port: u16, want: Option<&str>, when: &str) -> Result<String> {
    let s = get_status(port)?;
    let id = s.get("params.rig_id").and_then(Json::as_str);
    if id != want {
        bail!("{when} the status shows rig {id:?}, want {want:?} (from the state dir)");
    }
    Ok(match id {
        Some(id) => format!("rig {id} loaded from disk"),
        None => "no parameters (none were pushed)".to_owned(),
    })
}

fn check_restart(q: &mut Qemu, status_port: u16, rig_id: Option<&str>) -> Result<String> {
    let pid_before = pid_of_irtrackd(q)?;
    if pid_before.is_empty() {
        bail!("irtrackd not running before the kill");
    }
    let from = q.log_len();
    let t0 = Instant::now();
    q.console(&format!("kill -9 {pid_before}"), Duration::from_secs(10))?;
    q.wait_for("irtrackd exited", from, Duration::from_secs(10))?;
    q.wait_for("irtrackd ready", from, Duration::from_secs(60))?;
    let restart_s = t0.elapsed().as_secs_f64();
    let pid_after = pid_of_irtrackd(q)?;
    if pid_after.is_empty() || pid_after == pid_before {
        bail!("pid before {pid_before}, after {pid_after:?}");
    }
    let rig = check_rig(status_port, rig_id, "after the restart")?;
    Ok(format!(
        "pid {pid_before} killed, pid {pid_after} ready in {restart_s:.1} s; {rig}"
    ))
}

/// `pidof irtrackd` on the console: the line of digits in its output. irtrackd logs to the
/// same serial console, so a log line can land between the command's markers.
fn pid_of_irtrackd(q: &mut Qemu) -> Result<String> {
    let out = q.console("pidof irtrackd", Duration::from_secs(10))?;
    Ok(pid_line(&out).unwrap_or_default())
}

fn pid_line(out: &str) -> Option<String> {
    out.lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && l.chars().all(|c| c.is_ascii_digit() || c == ' '))
        .map(str::to_owned)
}

fn check_reboot(q: &mut Qemu, status_port: u16, rig_id: Option<&str>) -> Result<(String, f64)> {
    let from = q.log_len();
    let t0 = Instant::now();
    // `reboot` runs the shutdown actions (stop irtrackd, sync, remount read-only) and resets
    // the machine; U-Boot boots the same disk again.
    q.stdin.write_all(format!("reboot\n{PUSH}").as_bytes())?;
    q.stdin.flush()?;
    q.wait_for("U-Boot", from, Duration::from_secs(60))?;
    q.wait_for("irtrackd ready", from, BOOT_TIMEOUT)?;
    let boot_s = t0.elapsed().as_secs_f64();
    let rig = check_rig(status_port, rig_id, "after the reboot")?;
    if rig_id.is_none() {
        bail!("rebooted in {boot_s:.1} s, but no parameters were pushed, so persistence is untested");
    }
    Ok((format!("rebooted, ready again in {boot_s:.1} s; {rig}"), boot_s))
}

/// `cargo xtask image run`: boots the image with the console on this terminal.
pub fn interactive(ctx: &Ctx, image: &Image) -> Result<()> {
    let ports = free_ports::<4>()?;
    let disk = work_dir(ctx).join("interactive-sd.img");
    fs::copy(&image.sd_img, &disk)?;
    let mut cmd = qemu_command(&disk, &ports);
    // The terminal becomes the serial console; Ctrl-A X quits QEMU.
    let args: Vec<String> = cmd.get_args().map(|a| a.to_string_lossy().into_owned()).collect();
    let mut fixed = Command::new("qemu-system-aarch64");
    for a in &args {
        fixed.arg(if a == "stdio" { "mon:stdio" } else { a.as_str() });
    }
    cmd = fixed;
    println!(
        "irtrackd ports on this host: params 127.0.0.1:{}, stream 127.0.0.1:{}, binary 127.0.0.1:{}, status http://127.0.0.1:{}/status",
        ports[0], ports[1], ports[2], ports[3]
    );
    println!("$ {}", util::display_cmd(&cmd));
    let status = cmd.status().context("starting qemu-system-aarch64")?;
    println!("QEMU exited: {status}");
    Ok(())
}

/// A small JSON reader for the status document (xtask has no serde).
#[derive(Debug, Clone, PartialEq)]
pub enum Json {
    Null,
    Bool(bool),
    Num(f64),
    Str(String),
    Arr(Vec<Json>),
    Obj(Vec<(String, Json)>),
}

impl Json {
    pub fn parse(text: &str) -> Result<Json> {
        let mut p = Parser {
            s: text.as_bytes(),
            i: 0,
        };
        let v = p.value()?;
        p.ws();
        if p.i != p.s.len() {
            bail!("trailing characters at byte {}", p.i);
        }
        Ok(v)
    }

    /// Looks up a dotted path; numeric parts index arrays (`source.cameras.0.fps`).
    pub fn get(&self, path: &str) -> Option<&Json> {
        let mut cur = self;
        for part in path.split('.') {
            cur = match cur {
                Json::Obj(fields) => fields.iter().find(|(k, _)| k == part).map(|(_, v)| v)?,
                Json::Arr(items) => items.get(part.parse::<usize>().ok()?)?,
                _ => return None,
            };
        }
        Some(cur)
    }

    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Json::Num(n) => Some(*n),
            _ => None,
        }
    }

    pub fn as_str(&self) -> Option<&str> {
        match self {
            Json::Str(s) => Some(s),
            _ => None,
        }
    }

    pub fn as_array(&self) -> Option<&[Json]> {
        match self {
            Json::Arr(a) => Some(a),
            _ => None,
        }
    }
}

struct Parser<'a> {
    s: &'a [u8],
    i: usize,
}

impl Parser<'_> {
    fn ws(&mut self) {
        while self.s.get(self.i).is_some_and(|c| c.is_ascii_whitespace()) {
            self.i += 1;
        }
    }

    fn eat(&mut self, lit: &str) -> Result<()> {
        if self.s[self.i..].starts_with(lit.as_bytes()) {
            self.i += lit.len();
            Ok(())
        } else {
            bail!("expected {lit:?} at byte {}", self.i)
        }
    }

    fn value(&mut self) -> Result<Json> {
        self.ws();
        match self.s.get(self.i) {
            None => bail!("unexpected end of JSON"),
            Some(b'n') => self.eat("null").map(|_| Json::Null),
            Some(b't') => self.eat("true").map(|_| Json::Bool(true)),
            Some(b'f') => self.eat("false").map(|_| Json::Bool(false)),
            Some(b'"') => self.string().map(Json::Str),
            Some(b'[') => {
                self.i += 1;
                let mut items = Vec::new();
                self.ws();
                if self.s.get(self.i) == Some(&b']') {
                    self.i += 1;
                    return Ok(Json::Arr(items));
                }
                loop {
                    items.push(self.value()?);
                    self.ws();
                    match self.s.get(self.i) {
                        Some(b',') => self.i += 1,
                        Some(b']') => {
                            self.i += 1;
                            return Ok(Json::Arr(items));
                        }
                        _ => bail!("expected , or ] at byte {}", self.i),
                    }
                }
            }
            Some(b'{') => {
                self.i += 1;
                let mut fields = Vec::new();
                self.ws();
                if self.s.get(self.i) == Some(&b'}') {
                    self.i += 1;
                    return Ok(Json::Obj(fields));
                }
                loop {
                    self.ws();
                    let key = self.string()?;
                    self.ws();
                    self.eat(":")?;
                    fields.push((key, self.value()?));
                    self.ws();
                    match self.s.get(self.i) {
                        Some(b',') => self.i += 1,
                        Some(b'}') => {
                            self.i += 1;
                            return Ok(Json::Obj(fields));
                        }
                        _ => bail!("expected , or }} at byte {}", self.i),
                    }
                }
            }
            Some(_) => {
                let start = self.i;
                while self.s.get(self.i).is_some_and(|c| b"+-.eE0123456789".contains(c)) {
                    self.i += 1;
                }
                let t = std::str::from_utf8(&self.s[start..self.i])?;
                t.parse()
                    .map(Json::Num)
                    .with_context(|| format!("bad number {t:?} at byte {start}"))
            }
        }
    }

    fn string(&mut self) -> Result<String> {
        self.eat("\"")?;
        let mut out = Vec::new();
        loop {
            let c = *self.s.get(self.i).context("unterminated string")?;
            self.i += 1;
            match c {
                b'"' => return Ok(String::from_utf8(out)?),
                b'\\' => {
                    let e = *self.s.get(self.i).context("unterminated escape")?;
                    self.i += 1;
                    match e {
                        b'n' => out.push(b'\n'),
                        b't' => out.push(b'\t'),
                        b'r' => out.push(b'\r'),
                        b'b' => out.push(8),
                        b'f' => out.push(12),
                        b'u' => {
                            let hex = self.s.get(self.i..self.i + 4).context("short \\u escape")?;
                            let code = u32::from_str_radix(std::str::from_utf8(hex)?, 16)?;
                            self.i += 4;
                            let ch = char::from_u32(code).unwrap_or('\u{fffd}');
                            out.extend_from_slice(ch.to_string().as_bytes());
                        }
                        other => out.push(other),
                    }
                }
                c => out.push(c),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pid_is_found_between_interleaved_log_lines() {
        let out = "\n\x1b[2m2026-11-23T14:13:48Z\x1b[0m INFO irtrack_firmware::engine: tuning applied threshold_dn=30\n146\n";
        assert_eq!(pid_line(out).as_deref(), Some("146"));
        assert_eq!(pid_line("  212 \n").as_deref(), Some("212"));
        assert_eq!(pid_line("INFO ready\n\n"), None);
    }

    #[test]
    fn json_paths_and_types() {
        let j = Json::parse(
            r#"{"params":{"rig_id":"rig-7","loaded":true},"source":{"cameras":[{"fps":14.9},{"fps":null}]},
               "faults":["no_params"],"s":"a\"b\u00e9","n":-1.5e3}"#,
        )
        .unwrap();
        assert_eq!(j.get("params.rig_id").and_then(Json::as_str), Some("rig-7"));
        assert_eq!(j.get("source.cameras.0.fps").and_then(Json::as_f64), Some(14.9));
        assert_eq!(j.get("source.cameras.1.fps"), Some(&Json::Null));
        assert_eq!(j.get("source.cameras.2"), None);
        assert_eq!(j.get("s").and_then(Json::as_str), Some("a\"bé"));
        assert_eq!(j.get("n").and_then(Json::as_f64), Some(-1500.0));
        assert_eq!(
            j.get("faults").and_then(Json::as_array).map(<[Json]>::len),
            Some(1)
        );
        assert!(Json::parse("{\"a\":1,}").is_err());
        assert!(Json::parse("[1 2]").is_err());
        assert!(Json::parse("{} x").is_err());
    }

    #[test]
    fn debugfs_gpio_lines_of_one_chip() {
        let text = "gpiochip1: GPIOs 500-503, parent: platform/other, other:\n \
                    gpio-501 (                    |irtrackd            ) out hi \n\n\
                    gpiochip0: GPIOs 512-519, parent: platform/9030000.pl061, 9030000.pl061:\n \
                    gpio-515 (                    |GPIO Key Poweroff   ) in  lo IRQ \n \
                    gpio-516 (                    |irtrackd            ) out hi \n \
                    gpio-517 (                    |irtrackd            ) out lo \n";
        let lines = parse_debugfs_gpio(text, "9030000.pl061", "irtrackd");
        assert_eq!(
            lines,
            vec![
                GpioLine {
                    offset: 4,
                    output: true,
                    high: true
                },
                GpioLine {
                    offset: 5,
                    output: true,
                    high: false
                },
            ]
        );
    }

    #[test]
    fn free_ports_are_distinct() {
        let p = free_ports::<4>().unwrap();
        let mut sorted = p.to_vec();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), 4);
        assert!(p.iter().all(|&port| port != 0));
    }
}
