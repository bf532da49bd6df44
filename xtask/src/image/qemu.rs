//! The QEMU driver of the image's system and update tests: `qemu-system-aarch64 -M
//! virt,acpi=off` (or `qemu-system-arm -M virt` for the armv7 image) booting the SD image
//! through U-Boot, irtrackd's ports forwarded to free host ports, the serial
//! console collected into a log and used as a shell (commands typed, output read back between
//! markers). QEMU is killed on every path (`Drop`).

use std::fs;
use std::io::{Read, Write};
use std::net::{Ipv4Addr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use super::{Image, UBOOT_QEMU};
use crate::cross::Arch;
use crate::util::{self, Ctx};

/// irtrackd's ports in the guest: parameters, NDJSON stream, binary stream, status.
const GUEST_PORTS: [u16; 4] = [7701, 7702, 7703, 7704];
/// From QEMU start (or a reboot) to irtrackd's ready line.
pub const BOOT_TIMEOUT: Duration = Duration::from_secs(120);
/// Empty lines sent after each console command (see [`Qemu::console`]).
const PUSH: &str = "\n\n\n\n\n\n\n\n\n\n\n\n\n\n\n\n";

/// Free host ports, all bound at once so they differ, then released for QEMU.
pub fn free_ports<const N: usize>() -> Result<[u16; N]> {
    let listeners: Vec<TcpListener> = (0..N)
        .map(|_| TcpListener::bind((Ipv4Addr::LOCALHOST, 0)))
        .collect::<std::io::Result<_>>()?;
    let mut ports = [0; N];
    for (p, l) in ports.iter_mut().zip(&listeners) {
        *p = l.local_addr()?.port();
    }
    Ok(ports)
}

/// The system emulator of `arch`.
fn qemu_system(arch: Arch) -> &'static str {
    match arch {
        Arch::Aarch64 => "qemu-system-aarch64",
        Arch::Armv7 => "qemu-system-arm",
    }
}

/// QEMU booting `disk` through U-Boot for the image of `arch`, irtrackd's ports forwarded to
/// `host_ports`: aarch64 on `virt` with a Cortex-A53; armv7 on the same `virt` machine with a
/// Cortex-A15 and U-Boot's 32-bit build (see [`super::armv7::QEMU_CPU`]).
pub fn qemu_command_for(arch: Arch, disk: &Path, host_ports: &[u16; 4]) -> Command {
    let fwd: Vec<String> = host_ports
        .iter()
        .zip(GUEST_PORTS)
        .map(|(h, g)| format!("hostfwd=tcp:127.0.0.1:{h}-:{g}"))
        .collect();
    let mut cmd = Command::new(qemu_system(arch));
    let (machine, cpu, uboot) = match arch {
        // acpi=off keeps the PL061 GPIO in the device tree when booting through U-Boot.
        Arch::Aarch64 => ("virt,acpi=off", "cortex-a53", UBOOT_QEMU),
        // The 32-bit virt machine has no ACPI.
        Arch::Armv7 => ("virt", super::armv7::QEMU_CPU, super::armv7::UBOOT_QEMU_ARM),
    };
    cmd.args(["-M", machine, "-cpu", cpu, "-smp", "2", "-m", "512"])
        .args(["-display", "none", "-monitor", "none", "-serial", "stdio"])
        .args(["-bios", uboot])
        .arg("-drive")
        .arg(format!("if=none,file={},format=raw,id=sd", disk.display()))
        .args(["-device", "virtio-blk-device,drive=sd"])
        .arg("-netdev")
        .arg(format!("user,id=net0,{}", fwd.join(",")))
        .args(["-device", "virtio-net-device,netdev=net0"]);
    cmd
}

/// A running QEMU whose serial console is collected into a log; killed when dropped.
pub struct Qemu {
    child: Child,
    stdin: ChildStdin,
    log: Arc<Mutex<String>>,
    log_path: PathBuf,
    pub started: Instant,
    commands: u32,
}

impl Qemu {
    pub fn spawn(mut cmd: Command, log_path: &Path) -> Result<Self> {
        println!("$ {}", util::display_cmd(&cmd));
        cmd.stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        let started = Instant::now();
        let mut child = cmd.spawn().with_context(|| {
            format!(
                "starting {} (run `cargo xtask setup`)",
                cmd.get_program().to_string_lossy()
            )
        })?;
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

    /// The serial log from byte offset `from` on.
    pub fn log_since(&self, from: usize) -> String {
        self.log
            .lock()
            .map(|l| l.get(from..).unwrap_or("").to_owned())
            .unwrap_or_default()
    }

    /// Cuts the power: QEMU is killed without any shutdown in the guest.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    pub fn log_len(&self) -> usize {
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
    pub fn wait_for(&mut self, needle: &str, from: usize, timeout: Duration) -> Result<usize> {
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

    /// Types `line` on the console without waiting for anything (e.g. `reboot`).
    pub fn type_line(&mut self, line: &str) -> Result<()> {
        self.stdin.write_all(format!("{line}\n{PUSH}").as_bytes())?;
        self.stdin.flush()?;
        Ok(())
    }

    /// Runs a shell command on the guest console and returns its output. Markers printed by
    /// `printf` bracket the output; the terminal's echo of the typed line cannot match them.
    pub fn console(&mut self, command: &str, timeout: Duration) -> Result<String> {
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

/// `cargo xtask image run`: boots the image with the console on this terminal.
pub fn interactive(ctx: &Ctx, image: &Image) -> Result<()> {
    let ports = free_ports::<4>()?;
    let disk = super::image_dir(ctx, image).join("interactive-sd.img");
    fs::copy(&image.sd_img, &disk)?;
    let mut cmd = qemu_command_for(image.arch, &disk, &ports);
    // The terminal becomes the serial console; Ctrl-A X quits QEMU.
    let args: Vec<String> = cmd.get_args().map(|a| a.to_string_lossy().into_owned()).collect();
    let mut fixed = Command::new(qemu_system(image.arch));
    for a in &args {
        fixed.arg(if a == "stdio" { "mon:stdio" } else { a.as_str() });
    }
    cmd = fixed;
    println!(
        "irtrackd ports on this host: params 127.0.0.1:{}, stream 127.0.0.1:{}, binary 127.0.0.1:{}, status http://127.0.0.1:{}/status",
        ports[0], ports[1], ports[2], ports[3]
    );
    println!("$ {}", util::display_cmd(&cmd));
    let status = cmd
        .status()
        .with_context(|| format!("starting {}", qemu_system(image.arch)))?;
    println!("QEMU exited: {status}");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
