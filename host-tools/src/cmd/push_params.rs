//! `host-tools push-params`: send a parameter blob (or a converted OpenCV YAML calibration)
//! to irtrackd and report its verdict (protocol: docs/param-protocol.md). With `--sign-key`
//! the blob is signed first (docs/param-blob.md); an already signed blob file is sent as is.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use irtrack_core::param_wire::{self, MAX_VERDICT_LINE, RejectCode, Verdict};
use irtrack_core::params::Verdict as CalVerdict;
use irtrack_core::signing::KeyId;

use crate::cmd::keygen::{load_params_file, read_secret_key};

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// irtrackd's parameter endpoint, HOST:PORT (HOST alone means port 7701).
    #[arg(long, value_name = "HOST:PORT", required_unless_present = "dry_run")]
    pub to: Option<String>,
    /// Parameter blob or OpenCV YAML calibration (converted before sending).
    pub file: PathBuf,
    /// Secret key file (from `host-tools keygen`) to sign the blob with. Devices that require
    /// signed parameters refuse unsigned blobs with UNAUTHORIZED.
    #[arg(long, value_name = "FILE")]
    pub sign_key: Option<PathBuf>,
    /// Only load and validate locally; send nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Connection attempts after the first one, with exponential backoff.
    #[arg(long, default_value_t = 5)]
    pub retries: u32,
    /// Timeout for connecting and for each read/write, seconds.
    #[arg(long, default_value_t = 5.0)]
    pub timeout_s: f64,
    /// Send a parameter set whose calibration is marked poor (written with `--accept-poor`);
    /// without it such a set is refused here.
    #[arg(long)]
    pub accept_poor: bool,
    /// Let this set replace a newer active one (a rollback). Without it irtrackd refuses a set
    /// older than its active one (by serial, else by creation time) with ROLLBACK, naming both.
    #[arg(long)]
    pub allow_rollback: bool,
}

/// First retry delay; doubles per attempt up to [`MAX_BACKOFF`].
pub const FIRST_BACKOFF: Duration = Duration::from_millis(250);
/// Longest delay between attempts.
pub const MAX_BACKOFF: Duration = Duration::from_secs(4);

/// How to push.
#[derive(Debug, Clone)]
pub struct PushOptions {
    /// Attempts after the first before giving up.
    pub retries: u32,
    /// Timeout of the connect and of each read and write.
    pub timeout: Duration,
    /// Delay before the first retry; doubles per attempt up to [`MAX_BACKOFF`].
    pub first_backoff: Duration,
    /// Ask the server to accept a set older than its active one (request flag,
    /// docs/param-protocol.md).
    pub allow_rollback: bool,
}

fn resolve(to: &str) -> Result<SocketAddr> {
    let with_port =
        if to.rsplit_once(':').is_some_and(|(_, p)| p.parse::<u16>().is_ok()) && !to.ends_with(']') {
            to.to_string()
        } else {
            format!("{to}:{}", param_wire::DEFAULT_PORT)
        };
    with_port
        .to_socket_addrs()
        .with_context(|| format!("cannot resolve {to:?}"))?
        .next()
        .ok_or_else(|| anyhow!("{to:?} resolves to no address"))
}

/// Connects with retries and exponential backoff; `log` receives one line per failed attempt.
pub fn connect_with_retries(to: &str, opts: &PushOptions, log: &mut dyn FnMut(&str)) -> Result<TcpStream> {
    let mut delay = opts.first_backoff;
    let mut attempt = 0u32;
    loop {
        let result = resolve(to).and_then(|addr| {
            TcpStream::connect_timeout(&addr, opts.timeout).with_context(|| format!("connect to {addr}"))
        });
        match result {
            Ok(stream) => return Ok(stream),
            Err(e) if attempt < opts.retries => {
                attempt += 1;
                log(&format!(
                    "{e:#}; retry {attempt}/{} in {:.2} s",
                    opts.retries,
                    delay.as_secs_f64()
                ));
                std::thread::sleep(delay);
                delay = (delay * 2).min(MAX_BACKOFF);
            }
            Err(e) => {
                return Err(e.context(format!("giving up on {to} after {} attempts", opts.retries + 1)));
            }
        }
    }
}

fn read_verdict(stream: &mut TcpStream) -> Result<Verdict> {
    let mut line = Vec::with_capacity(128);
    let mut byte = [0u8; 1];
    loop {
        match stream.read(&mut byte) {
            Ok(0) => break,
            Ok(_) => {
                line.push(byte[0]);
                if byte[0] == b'\n' {
                    break;
                }
                if line.len() >= MAX_VERDICT_LINE {
                    bail!("server reply exceeds {MAX_VERDICT_LINE} bytes without a newline");
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e).context("reading the verdict"),
        }
    }
    if line.is_empty() {
        bail!("server closed the connection without a verdict");
    }
    let text = String::from_utf8(line).map_err(|_| anyhow!("server reply is not UTF-8"))?;
    Ok(Verdict::parse_line(&text)?)
}

/// Sends `blob` to `to` and returns the server's verdict. Only connecting is retried: once the
/// request is out, the server may have applied it.
pub fn push_blob(to: &str, blob: &[u8], opts: &PushOptions, log: &mut dyn FnMut(&str)) -> Result<Verdict> {
    let mut stream = connect_with_retries(to, opts, log)?;
    stream.set_read_timeout(Some(opts.timeout))?;
    stream.set_write_timeout(Some(opts.timeout))?;
    let request = param_wire::encode_push_with(
        blob,
        param_wire::PushOptions {
            allow_rollback: opts.allow_rollback,
        },
    );
    let sent = stream.write_all(&request).and_then(|()| stream.flush());
    // A server may answer (e.g. TOO_LARGE) and close before reading everything: prefer its verdict.
    match (sent, read_verdict(&mut stream)) {
        (_, Ok(v)) => Ok(v),
        (Err(w), Err(_)) => Err(w).context("sending the blob"),
        (Ok(()), Err(r)) => Err(r),
    }
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let path = &args.file;
    let loaded = load_params_file(path)?;
    let rig = loaded.rig;
    rig.validate()
        .with_context(|| format!("{}: parameters are not usable", path.display()))?;
    if let Some(c) = &rig.calibration {
        println!(
            "{}: calibration {} of {} by {}: {}",
            path.display(),
            c.method,
            crate::opencv_yaml::iso_utc(c.calibrated_unix_s),
            c.tool_version,
            c.verdict.as_str()
        );
        if c.verdict == CalVerdict::Poor {
            if !args.accept_poor {
                bail!(
                    "{}: this calibration is marked poor, so it is not sent: {}. Calibrate again, or add \
                     --accept-poor to push it anyway",
                    path.display(),
                    c.summary
                );
            }
            eprintln!(
                "warning: pushing a calibration marked poor (--accept-poor): {}",
                c.summary
            );
        }
    }
    let (blob, signature) = match (&args.sign_key, loaded.signed) {
        (Some(key_path), previous) => {
            let key = read_secret_key(key_path)?;
            if let Some((old_id, _)) = previous {
                println!("{}: replacing the signature by key {old_id}", path.display());
            }
            let id = KeyId::of(&key.verifying_key());
            (rig.to_signed_blob(&key)?, format!("signed by key {id}"))
        }
        (None, Some((id, bytes))) => (bytes, format!("signed by key {id} (as in the file)")),
        (None, None) => (rig.to_blob()?, "unsigned".to_string()),
    };
    println!(
        "{}: rig {} with {} cameras, blob {} bytes, params CRC-32 {:08x}, {signature}: valid",
        path.display(),
        rig.rig_id,
        rig.cameras.len(),
        blob.len(),
        rig.params_crc()?
    );
    if blob.len() > param_wire::MAX_BLOB_BYTES {
        bail!(
            "{}: blob of {} bytes exceeds the protocol limit of {} bytes",
            path.display(),
            blob.len(),
            param_wire::MAX_BLOB_BYTES
        );
    }
    if args.dry_run {
        println!("dry run: nothing sent");
        return Ok(());
    }
    let to = args
        .to
        .as_deref()
        .ok_or_else(|| anyhow!("--to HOST:PORT is required"))?;
    if !(args.timeout_s.is_finite() && args.timeout_s > 0.0) {
        bail!("--timeout-s must be a positive number of seconds");
    }
    let opts = PushOptions {
        retries: args.retries,
        timeout: Duration::from_secs_f64(args.timeout_s),
        first_backoff: FIRST_BACKOFF,
        allow_rollback: args.allow_rollback,
    };
    if args.allow_rollback {
        println!("--allow-rollback: the device may go back to this set even if its active set is newer");
    }
    let mut log = |msg: &str| eprintln!("push-params: {msg}");
    match push_blob(to, &blob, &opts, &mut log)? {
        Verdict::Accepted { rig_id } => {
            println!("accepted by {to}: rig {rig_id} is active");
            Ok(())
        }
        Verdict::Rejected {
            code: RejectCode::Protocol,
            message,
        } if args.allow_rollback && message.contains("bad magic") => bail!(
            "rejected by {to}: PROTOCOL: {message}. This irtrackd predates --allow-rollback (and does \
             not refuse rollbacks either): push again without the option"
        ),
        Verdict::Rejected { code, message } => bail!("rejected by {to}: {code}: {message}"),
    }
}
