//! `host-tools cluster-keys --boards b0,b1 --out DIR`: the credentials of a cluster's Zenoh
//! transport (docs/cluster.md, "Credentials"). One random password per camera board
//! (`DIR/<board>.password`, for that board's `[cluster] password_file`) and the solver's
//! dictionary of all of them (`DIR/solver.credentials`, its `credentials_file`), every file
//! mode 0600; the passwords come from the operating system's CSPRNG
//! (`irtrack_cluster::credentials`, the same code irtrackd reads them with).
//!
//! `host-tools cluster-keys push --board b0 --dir DIR --to HOST --sign-key pc.key`: sends one
//! of them to its irtrackd through the parameter port, sealed (docs/cluster.md, "Pushing
//! credentials"; format: docs/cluster-envelope.md). That port does not encrypt, so the secret
//! is encrypted to the board's own X25519 key (read from its `/status` once and pinned in
//! `DIR/known_boards`, as SSH pins host keys) and signed with the key the board trusts for
//! parameter sets. The board stores it (mode 0600) and uses it from its next start.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use irtrack_cluster::credentials::{dictionary_path, password_path, write_new_credentials, write_private};
use irtrack_cluster::envelope::{self, Sealing, SecretKind};
use irtrack_cluster::names::SOLVER_TLS_NAME;
use irtrack_core::param_wire::Verdict;

/// Arguments.
#[derive(clap::Args, Debug)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct Args {
    /// `push`: send one board's credentials to it (without: make new credentials).
    #[command(subcommand)]
    pub action: Option<Action>,
    /// The camera boards' names (their `[cluster] board`), comma separated.
    #[arg(long, value_delimiter = ',', required = true)]
    pub boards: Vec<String>,
    /// Directory to write `<board>.password` and `solver.credentials` into (created).
    #[arg(long, value_name = "DIR", required = true)]
    pub out: Option<PathBuf>,
    /// Replace existing files (the old passwords stop working once the solver has the new
    /// dictionary).
    #[arg(long)]
    pub force: bool,
    /// Also make the solver's TLS certificate and key (`solver.tls.crt`, which every board
    /// pins, and `solver.tls.key`, mode 0600): the solver proves itself, links are encrypted.
    #[arg(long)]
    pub tls: bool,
}

/// What else `cluster-keys` does.
#[derive(clap::Subcommand, Debug)]
pub enum Action {
    /// Push a camera board's password (or, with --solver, the solver's dictionary) to its
    /// irtrackd through the parameter port, encrypted to the board's key and signed.
    Push(PushArgs),
}

/// Arguments of `cluster-keys push`.
#[derive(clap::Args, Debug)]
pub struct PushArgs {
    /// The receiving irtrackd's `[cluster] board` name.
    #[arg(long)]
    pub board: String,
    /// Push the solver's dictionary (`DIR/solver.credentials`) instead of `DIR/<board>.password`.
    #[arg(long)]
    pub solver: bool,
    /// Push the TLS file instead (`cluster-keys --tls`): to a camera board the solver's
    /// certificate it pins (`DIR/solver.tls.crt`), with --solver its certificate and key.
    #[arg(long)]
    pub tls: bool,
    /// The directory `cluster-keys --out` wrote.
    #[arg(long, value_name = "DIR")]
    pub dir: PathBuf,
    /// irtrackd's parameter endpoint, HOST:PORT (HOST alone means port 7701).
    #[arg(long, value_name = "HOST:PORT")]
    pub to: String,
    /// Its status endpoint, HOST:PORT, to read its public key from on first use (default: the
    /// host of --to, port 7704).
    #[arg(long, value_name = "HOST:PORT")]
    pub status: Option<String>,
    /// Secret key (from `host-tools keygen`) that signs the envelope: one the board trusts for
    /// parameter sets.
    #[arg(long, value_name = "FILE")]
    pub sign_key: PathBuf,
    /// Pinned board keys, one `board key` line each (default `DIR/known_boards`).
    #[arg(long, value_name = "FILE")]
    pub known_boards: Option<PathBuf>,
    /// Pin the key the board reports when none is pinned yet (compare it with the board's
    /// `/status` or log first, as with a new SSH host key).
    #[arg(long)]
    pub accept_new_key: bool,
    /// Serial of the envelope (default: now, ms since 1970); the board refuses one not newer
    /// than the last it accepted.
    #[arg(long)]
    pub serial: Option<u64>,
    /// Connection attempts after the first one, with exponential backoff.
    #[arg(long, default_value_t = 5)]
    pub retries: u32,
    /// Timeout for connecting and for each read/write, seconds.
    #[arg(long, default_value_t = 5.0)]
    pub timeout_s: f64,
}

/// The solver's TLS certificate in DIR.
pub fn tls_certificate_path(dir: &Path) -> PathBuf {
    dir.join("solver.tls.crt")
}

/// The solver's TLS private key in DIR.
pub fn tls_key_path(dir: &Path) -> PathBuf {
    dir.join("solver.tls.key")
}

/// Makes the solver's TLS identity: an ECDSA P-256 key and a self-signed certificate for
/// [`SOLVER_TLS_NAME`], which the boards pin. Valid from 1970: a board without a real-time
/// clock starts in 1970 until its time service sets it, and must not refuse the solver
/// then; it does not expire (it is pinned, not trusted through a CA; replace it with
/// `--tls --force`).
fn write_tls_identity(dir: &Path) -> Result<(PathBuf, PathBuf)> {
    let key = rcgen::KeyPair::generate().context("making the solver's TLS key")?;
    let mut params = rcgen::CertificateParams::new(vec![SOLVER_TLS_NAME.to_string()])
        .context("the solver's TLS certificate")?;
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "irtrack solver");
    params.not_before = rcgen::date_time_ymd(1970, 1, 1);
    params.not_after = rcgen::date_time_ymd(4000, 1, 1);
    let cert = params
        .self_signed(&key)
        .context("signing the solver's TLS certificate")?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let (crt, key_path) = (tls_certificate_path(dir), tls_key_path(dir));
    write_private(&key_path, &key.serialize_pem())?;
    std::fs::write(&crt, cert.pem()).with_context(|| format!("writing {}", crt.display()))?;
    Ok((crt, key_path))
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    if let Some(Action::Push(p)) = args.action {
        return push(p);
    }
    let out = args.out.ok_or_else(|| anyhow!("--out DIR is required"))?;
    let boards: Vec<&str> = args.boards.iter().map(|b| b.trim()).collect();
    if args.tls && !args.force {
        for p in [tls_certificate_path(&out), tls_key_path(&out)] {
            if p.exists() {
                bail!(
                    "{}: already exists; refusing to overwrite (--force makes new ones)",
                    p.display()
                );
            }
        }
    }
    let written = write_new_credentials(&out, &boards, args.force)?;
    for c in &written {
        println!(
            "board {}: {} (mode 600) -> its [cluster] password_file",
            c.board,
            password_path(&out, &c.board).display()
        );
    }
    println!(
        "solver: {} (mode 600) -> its [cluster] credentials_file",
        dictionary_path(&out).display()
    );
    if args.tls {
        let (crt, key) = write_tls_identity(&out)?;
        println!(
            "solver: {} (mode 600) -> its [cluster] tls_key_file; {} -> its tls_certificate_file",
            key.display(),
            crt.display()
        );
        println!(
            "every camera board: {} -> its [cluster] tls_solver_certificate_file (public, but it must be this file: the board trusts nothing else)",
            crt.display()
        );
    }
    println!(
        "push each to its board sealed (host-tools cluster-keys push --board NAME --dir {} --to HOST --sign-key KEY), or copy it by hand (scp, then chmod 600); docs/cluster.md \"Credentials\"",
        out.display()
    );
    Ok(())
}

/// A pinned key of `board` in the known-boards file, if any.
pub fn pinned_key(file: &Path, board: &str) -> Result<Option<[u8; 32]>> {
    let text = match std::fs::read_to_string(file) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("reading {}", file.display())),
    };
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let (name, key) = line
            .split_once(char::is_whitespace)
            .ok_or_else(|| anyhow!("{} line {}: expected `board key`", file.display(), i + 1))?;
        if name == board {
            let key = envelope::parse_key_hex(key)
                .ok_or_else(|| anyhow!("{} line {}: the key must be 64 hex digits", file.display(), i + 1))?;
            return Ok(Some(key));
        }
    }
    Ok(None)
}

fn pin_key(file: &Path, board: &str, key: &[u8; 32]) -> Result<()> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(file)
        .with_context(|| format!("writing {}", file.display()))?;
    writeln!(f, "{board} {}", envelope::hex(key)).with_context(|| format!("writing {}", file.display()))
}

/// The board's name and public key from its `/status` (`cluster.board`, `cluster.box_public_key`).
pub fn reported_key(status: &str, timeout: std::time::Duration) -> Result<(String, [u8; 32])> {
    let url = format!("http://{status}/status");
    let agent = ureq::AgentBuilder::new().timeout(timeout).build();
    let body = agent
        .get(&url)
        .call()
        .map_err(|e| anyhow!("cannot read {url}: {e}"))?
        .into_string()
        .with_context(|| format!("reading {url}"))?;
    let v: serde_json::Value = serde_json::from_str(&body).with_context(|| format!("{url} is not JSON"))?;
    // A solver without cameras of its own shows no board name (""): the board checks the
    // envelope's name itself.
    let board = v["cluster"]["board"]
        .as_str()
        .ok_or_else(|| anyhow!("{url}: no cluster.board (is it a camera board or solver?)"))?;
    let key = v["cluster"]["box_public_key"]
        .as_str()
        .and_then(envelope::parse_key_hex)
        .ok_or_else(|| {
            anyhow!("{url}: no cluster.box_public_key (irtrackd too old for pushed credentials?)")
        })?;
    Ok((board.to_string(), key))
}

fn host_of(to: &str) -> &str {
    match to.rsplit_once(':') {
        Some((h, p)) if p.parse::<u16>().is_ok() && !to.ends_with(']') => h,
        _ => to,
    }
}

fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// `cluster-keys push`.
pub fn push(args: PushArgs) -> Result<()> {
    let timeout = std::time::Duration::from_secs_f64(args.timeout_s);
    let (kind, file) = match (args.solver, args.tls) {
        (true, false) => (SecretKind::SolverDictionary, dictionary_path(&args.dir)),
        (false, false) => (SecretKind::BoardPassword, password_path(&args.dir, &args.board)),
        (true, true) => (SecretKind::SolverTls, tls_key_path(&args.dir)),
        (false, true) => (
            SecretKind::PinnedSolverCertificate,
            tls_certificate_path(&args.dir),
        ),
    };
    // Checked here as the board will check it: a bad file is not sent.
    let secret = match kind {
        SecretKind::SolverTls => {
            // The solver's key and certificate travel as one PEM text (its one file).
            let key = irtrack_cluster::credentials::read_secret(&file)?.0;
            let crt_file = tls_certificate_path(&args.dir);
            let crt = std::fs::read_to_string(&crt_file)
                .with_context(|| format!("reading {}", crt_file.display()))?;
            let text = format!("{crt}{key}");
            irtrack_cluster::credentials::parse_tls_identity(&file, &text)?;
            text
        }
        SecretKind::PinnedSolverCertificate => {
            let text =
                std::fs::read_to_string(&file).with_context(|| format!("reading {}", file.display()))?;
            irtrack_cluster::credentials::parse_pinned_certificate(&file, &text)?;
            text
        }
        SecretKind::BoardPassword => {
            irtrack_cluster::credentials::read_password_file(&file)?;
            irtrack_cluster::credentials::read_secret(&file)?.0
        }
        SecretKind::SolverDictionary => {
            irtrack_cluster::credentials::read_dictionary_file(&file)?;
            irtrack_cluster::credentials::read_secret(&file)?.0
        }
    };
    let signer = crate::cmd::keygen::read_secret_key(&args.sign_key)?;
    let known = args
        .known_boards
        .clone()
        .unwrap_or_else(|| args.dir.join("known_boards"));
    let recipient = match pinned_key(&known, &args.board)? {
        Some(k) => k,
        None => {
            let status = args
                .status
                .clone()
                .unwrap_or_else(|| format!("{}:7704", host_of(&args.to)));
            let (name, key) = reported_key(&status, timeout)?;
            if !name.is_empty() && name != args.board {
                bail!("irtrackd at {status} is board {name:?}, not {:?}", args.board);
            }
            if !args.accept_new_key {
                bail!(
                    "no key of board {:?} is pinned in {}; it reports {} — compare with its /status (cluster.box_public_key) or log, then run again with --accept-new-key to pin it",
                    args.board,
                    known.display(),
                    envelope::hex(&key)
                );
            }
            pin_key(&known, &args.board, &key)?;
            println!(
                "pinned board {}'s key {} in {}",
                args.board,
                envelope::hex(&key),
                known.display()
            );
            key
        }
    };
    let serial = args.serial.unwrap_or_else(unix_ms);
    let sealed = envelope::seal(
        &Sealing {
            kind,
            board: &args.board,
            serial,
            created_unix_s: unix_ms() / 1000,
            recipient,
            plaintext: secret.as_bytes(),
        },
        &signer,
    )?;
    let opts = crate::cmd::push_params::PushOptions {
        retries: args.retries,
        timeout,
        first_backoff: crate::cmd::push_params::FIRST_BACKOFF,
        allow_rollback: false,
    };
    let verdict = crate::cmd::push_params::push_blob(&args.to, &sealed, &opts, &mut |l| eprintln!("{l}"))?;
    match verdict {
        Verdict::Accepted { .. } => {
            println!(
                "{} of board {} accepted (serial {serial}); it takes effect when irtrackd on {} restarts",
                kind.words(),
                args.board,
                args.to
            );
            Ok(())
        }
        Verdict::Rejected { code, message } => bail!("{} refused: {code} {message}", args.to),
    }
}
