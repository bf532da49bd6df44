//! The checks of the image's system test, each against the booted guest: irtrackd over the
//! forwarded ports (HTTP, WebSocket and NDJSON through the shared harness), the guest's kernel
//! through the console shell ([`Qemu::console`]). Each returns a detail line or an error.

use std::io::BufRead;
use std::io::BufReader;
use std::net::{Ipv4Addr, SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde_json::Value as Json;

use super::qemu::Qemu;
use crate::util::{self, Ctx, Http, LiveSocket, json};

/// What the image's irtrackd.toml configures (checked against what the service reports).
const LED_LINES: [(&str, u32); 4] = [("run", 4), ("track", 5), ("robot", 6), ("fault", 7)];
const CAMERA_FPS: f64 = 15.0;
const CONFIG_GAIN: i64 = 16;
/// Gain the operator sets live on camera 1 before the cameras are lost: neither vivid's
/// default (100) nor the config's ([`CONFIG_GAIN`]), so only the re-applied live value can show it.
const LIVE_GAIN: i64 = 57;

/// GET /status over the forwarded port, parsed; retried while the guest is not listening yet
/// (QEMU's forwarder accepts and then closes in that case).
pub(super) fn get_status(port: u16) -> Result<Json> {
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

pub(super) fn try_get_status(port: u16) -> Result<Json> {
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let (code, body) = Http::new(Duration::from_secs(10)).get(addr, "/status")?;
    if code != 200 {
        bail!("unexpected reply: {code} {}", body.lines().next().unwrap_or(""));
    }
    Ok(json::parse(&body)?)
}

/// `GET /` (the embedded set-up page) and one message of the live WebSocket (`/api/live`).
pub(super) fn check_web(port: u16) -> Result<String> {
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let (code, body) = Http::new(Duration::from_secs(20)).get(addr, "/")?;
    if code != 200 || !body.contains("<html") {
        bail!("GET / answered {code} with {} bytes", body.len());
    }
    let mut ws = LiveSocket::connect(addr, "/api/live", Duration::from_secs(20))?;
    let text = ws.next_text()?;
    ws.close();
    let msg = json::parse(&text)?;
    let kind = self::text(&msg, "type")?.to_string();
    Ok(format!(
        "GET / {} bytes of HTML; first live message: {kind} ({} bytes)",
        body.len(),
        text.len()
    ))
}

pub(super) fn num(j: &Json, path: &str) -> Result<f64> {
    json::f64_at(j, path).with_context(|| format!("status has no number at {path}"))
}

pub(super) fn text<'a>(j: &'a Json, path: &str) -> Result<&'a str> {
    json::str_at(j, path).with_context(|| format!("status has no string at {path}"))
}

/// What an integrator does on a board before anyone may change settings from the set-up view:
/// hash a password with irtrackd itself, put it under `[service]`, restart the service. Then
/// a tuning change must be refused with a wrong password and accepted with the right one.
pub(super) fn set_operator_password(q: &mut Qemu, status_port: u16) -> Result<String> {
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
    let threshold = json::parse(&answer)?
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
pub(super) fn tuning_gain(tuning: &Json, camera: usize) -> Option<f64> {
    json::f64_at(tuning, &format!("cameras.{camera}.gain"))
}

pub(super) fn check_capture(port: u16) -> Result<String> {
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
    // The two vivid instances run free against each other, at any phase. The source pairs one
    // frame per camera and slot of a frame-period grid centred on camera 0's frames (a frame
    // keeps its slot up to ⅝ of a period from the centre, so timestamp jitter on a slot edge
    // does not make it hop): a set's frames lie within that, never a whole period apart.
    let pairing_max_us = num(&s2, "source.pairing_error_max_us")?;
    let period_us = 1e6 / CAMERA_FPS;
    if pairing_max_us >= period_us {
        bail!(
            "pairing error {pairing_max_us:.0} µs: frames a whole frame period ({period_us:.0} µs) apart were paired"
        );
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
pub(super) struct GpioLine {
    offset: u32,
    output: bool,
    high: bool,
}

/// Parses /sys/kernel/debug/gpio for the chip labelled `label`: lines whose consumer is
/// `consumer`. The header gives the chip's global base (`GPIOs 512-519`).
pub(super) fn parse_debugfs_gpio(text: &str, label: &str, consumer: &str) -> Vec<GpioLine> {
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

/// Samples the LED lines through the kernel, 30 samples at a time (about 3 s; up to three
/// rounds while the heartbeat has not shown both levels: under a loaded emulator a round can
/// fall between pulses). Always: the four configured lines are outputs held by irtrackd and the
/// heartbeat toggles. `expect_no_params_fault`: the fault LED flashes (no parameters yet);
/// otherwise, with no fault reported, it stays off.
pub(super) fn check_gpio(q: &mut Qemu, status_port: u16, expect_no_params_fault: bool) -> Result<String> {
    let before = get_status(status_port)?;
    let samples = 30;
    let rounds = 3;
    let mut seen = [[false; 2]; 4];
    let mut n = 0;
    let mut span_s = 0.0;
    let mut alive_after = Vec::new();
    for _ in 0..rounds {
        // A script on the image loops over gpiolib's debugfs view (a loop typed into the piped
        // console shell would only run once the next line arrives).
        let started = Instant::now();
        let out = q.console(
            &format!("irtrack-gpio-sample 9030000.pl061 {samples}"),
            Duration::from_secs(40),
        )?;
        span_s += started.elapsed().as_secs_f64();
        let mut parsed = 0;
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
            parsed += 1;
        }
        if parsed < samples / 2 {
            bail!("only {parsed} of {samples} gpio samples parsed:\n{out}");
        }
        n += parsed;
        // The service's own view of its loop, to tell a stalled loop from a missed pulse.
        let st = get_status(status_port)?;
        alive_after.push(json::at(&st, "leds.indication.alive").and_then(Json::as_bool));
        if seen[0][0] && seen[0][1] {
            break;
        }
    }
    if !(seen[0][0] && seen[0][1]) {
        bail!(
            "run LED (heartbeat) did not toggle in {n} samples over {span_s:.1} s (levels seen: \
             low {}, high {}); the service's leds.indication.alive after each round: {alive_after:?}",
            seen[0][0],
            seen[0][1]
        );
    }
    let after = get_status(status_port)?;
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
        "lines 4-7 outputs held by irtrackd, heartbeat toggling over {n} samples ({span_s:.1} s); {fault_detail}"
    ))
}

/// Samples the fault LED through gpiolib; returns (samples with it lit, samples parsed).
pub(super) fn sample_fault_led(q: &mut Qemu, samples: usize) -> Result<(usize, usize)> {
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
pub(super) fn make_params(ctx: &Ctx, dir: &Path) -> Result<PathBuf> {
    let out_dir = dir.join("sim");
    let out = ctx
        .host_tools()
        .args(["simulate", "--frames", "1", "--out"])
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

pub(super) fn rig_id_of(ctx: &Ctx, file: &Path) -> Result<String> {
    let out = ctx
        .host_tools()
        .args(["show-params"])
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
pub(super) fn check_unsigned_refused(ctx: &Ctx, port: u16, file: &Path) -> Result<String> {
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

pub(super) fn push_params(ctx: &Ctx, port: u16, file: &Path, sign_key: Option<&Path>) -> Result<String> {
    let mut cmd = ctx.host_tools();
    cmd.args(["push-params", "--to"]).arg(format!("127.0.0.1:{port}"));
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

pub(super) fn check_params_used(port: u16, rig_id: &str) -> Result<String> {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let s = get_status(port)?;
        let id = json::str_at(&s, "params.rig_id").unwrap_or("");
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
pub(super) fn check_stream(port: u16, params_pushed: bool) -> Result<String> {
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
        records.push(json::parse(line.trim()).with_context(|| format!("bad NDJSON record {line:?}"))?);
    }
    if records.len() < 5 {
        bail!("only {} records in 3 s", records.len());
    }
    let field = |r: &Json, k: &str| json::f64_at(r, k).with_context(|| format!("record without {k}"));
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
    let status = json::str_at(last, "status").unwrap_or("?");
    Ok(format!(
        "{} records in 3 s, frames advanced by {frames}, capture timestamps span {span_s:.2} s, last status {status}",
        records.len()
    ))
}

pub(super) fn faults_of(j: &Json) -> Vec<String> {
    json::at(j, "faults")
        .and_then(Json::as_array)
        .map(|a| a.iter().filter_map(|f| f.as_str().map(str::to_owned)).collect())
        .unwrap_or_default()
}

/// Polls the status until `pred` holds (or the time is up); returns the last document.
pub(super) fn wait_status(
    port: u16,
    timeout: Duration,
    pred: impl Fn(&Json) -> bool,
) -> Result<(Json, bool)> {
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
pub(super) fn check_camera_loss(q: &mut Qemu, port: u16) -> Result<String> {
    let result = camera_loss_steps(q, port);
    match result {
        Ok(detail) => Ok(detail),
        // The guest's view of the video nodes says most about a failed reopen.
        Err(e) => Err(e.context(format!("video nodes in the guest: {}", video_nodes(q)))),
    }
}

pub(super) fn video_nodes(q: &mut Qemu) -> String {
    q.console(
        "ls -l /dev/video* 2>&1; ls /sys/class/video4linux 2>&1",
        Duration::from_secs(10),
    )
    .map(|s| s.split_whitespace().collect::<Vec<_>>().join(" "))
    .unwrap_or_else(|e| format!("(not read: {e:#})"))
}

pub(super) fn camera_loss_steps(q: &mut Qemu, port: u16) -> Result<String> {
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
        let gain = json::parse(&answer).ok().and_then(|t| tuning_gain(&t, 1));
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
    let tuning = json::parse(&answer)?;
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
pub(super) fn check_rig(port: u16, want: Option<&str>, when: &str) -> Result<String> {
    let s = get_status(port)?;
    let id = json::str_at(&s, "params.rig_id");
    if id != want {
        bail!("{when} the status shows rig {id:?}, want {want:?} (from the state dir)");
    }
    Ok(match id {
        Some(id) => format!("rig {id} loaded from disk"),
        None => "no parameters (none were pushed)".to_owned(),
    })
}

pub(super) fn check_restart(q: &mut Qemu, status_port: u16, rig_id: Option<&str>) -> Result<String> {
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
pub(super) fn pid_of_irtrackd(q: &mut Qemu) -> Result<String> {
    let out = q.console("pidof irtrackd", Duration::from_secs(10))?;
    Ok(pid_line(&out).unwrap_or_default())
}

pub(super) fn pid_line(out: &str) -> Option<String> {
    out.lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && l.chars().all(|c| c.is_ascii_digit() || c == ' '))
        .map(str::to_owned)
}

pub(super) fn check_reboot(q: &mut Qemu, status_port: u16, rig_id: Option<&str>) -> Result<(String, f64)> {
    let from = q.log_len();
    let t0 = Instant::now();
    // `reboot` runs the shutdown actions (stop irtrackd, sync, remount read-only) and resets
    // the machine; U-Boot boots the same disk again.
    q.type_line("reboot")?;
    q.wait_for("U-Boot", from, Duration::from_secs(60))?;
    q.wait_for("irtrackd ready", from, super::qemu::BOOT_TIMEOUT)?;
    let boot_s = t0.elapsed().as_secs_f64();
    let rig = check_rig(status_port, rig_id, "after the reboot")?;
    if rig_id.is_none() {
        bail!("rebooted in {boot_s:.1} s, but no parameters were pushed, so persistence is untested");
    }
    Ok((format!("rebooted, ready again in {boot_s:.1} s; {rig}"), boot_s))
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
}
