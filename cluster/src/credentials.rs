//! Credentials of the cluster's Zenoh transport (docs/cluster.md, "Credentials"): a camera
//! board proves with a password that it is the board it claims to be, the solver checks it
//! against its dictionary. Plain text files, the formats Zenoh's user/password authentication
//! reads:
//!
//! - a board's **password file**: one line, the password;
//! - the solver's **dictionary**: one `board:password` line per camera board.
//!
//! The user name is always the board's name: the solver's access control lets user `X`
//! publish only under board `X`'s key expressions, so a separate user name would be a second
//! mapping that could disagree with the first.
//!
//! Passwords are 16..=128 printable ASCII characters without space, `"` or `\` (they travel
//! into Zenoh's JSON5 configuration); `host-tools cluster-keys` makes 32 random characters.

use std::path::Path;

use crate::error::{ClusterError, Result};
use crate::names::check_name;

/// Shortest password accepted (a guessable password would make the check decorative).
pub const MIN_PASSWORD_LEN: usize = 16;
/// Longest password accepted.
pub const MAX_PASSWORD_LEN: usize = 128;

fn bad(file: &Path, reason: String) -> ClusterError {
    ClusterError::Credentials {
        file: file.display().to_string(),
        reason,
    }
}

/// Checks one password's length and characters; the error says what is wrong, never the
/// password.
pub fn check_password(password: &str) -> std::result::Result<(), String> {
    let n = password.len();
    if !(MIN_PASSWORD_LEN..=MAX_PASSWORD_LEN).contains(&n) {
        return Err(format!(
            "a password must be {MIN_PASSWORD_LEN}..={MAX_PASSWORD_LEN} characters, this one has {n}"
        ));
    }
    if let Some(c) = password
        .chars()
        .find(|c| !c.is_ascii_graphic() || *c == '"' || *c == '\\')
    {
        return Err(format!(
            "a password may hold printable ASCII without space, '\"' or '\\', not {c:?}"
        ));
    }
    Ok(())
}

/// What a TLS PEM text holds: certificates and private keys.
fn pem_sections(file: &Path, text: &str) -> Result<(usize, usize)> {
    use rustls_pki_types::pem::{PemObject, SectionKind};
    let mut certs = 0;
    let mut keys = 0;
    for item in <(SectionKind, Vec<u8>)>::pem_slice_iter(text.as_bytes()) {
        let (kind, _) = item.map_err(|e| bad(file, format!("not PEM: {e}")))?;
        match kind {
            SectionKind::Certificate => certs += 1,
            SectionKind::PrivateKey | SectionKind::RsaPrivateKey | SectionKind::EcPrivateKey => keys += 1,
            _ => {}
        }
    }
    Ok((certs, keys))
}

/// Checks the solver's TLS identity (its certificate and private key, PEM; crate::tls).
pub fn parse_tls_identity(file: &Path, text: &str) -> Result<()> {
    match pem_sections(file, text)? {
        (0, _) => Err(bad(
            file,
            "holds no certificate (expected -----BEGIN CERTIFICATE-----)".into(),
        )),
        (_, 0) => Err(bad(
            file,
            "holds no private key: the solver needs its key with its certificate".into(),
        )),
        (_, 1) => Ok(()),
        (_, n) => Err(bad(file, format!("holds {n} private keys, one expected"))),
    }
}

/// Checks the solver certificate a board pins (PEM, without any private key: a key pushed to
/// a board by mistake would spread the solver's secret).
pub fn parse_pinned_certificate(file: &Path, text: &str) -> Result<()> {
    match pem_sections(file, text)? {
        (0, _) => Err(bad(
            file,
            "holds no certificate (expected -----BEGIN CERTIFICATE-----)".into(),
        )),
        (_, 0) => Ok(()),
        _ => Err(bad(
            file,
            "holds a private key: a board pins the solver's certificate only (solver.tls.crt, not the key)"
                .into(),
        )),
    }
}

/// Parses a board's password file: one line (a final newline is allowed).
pub fn parse_password(file: &Path, text: &str) -> Result<String> {
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let pw = lines
        .next()
        .ok_or_else(|| bad(file, "the password file is empty".into()))?
        .trim();
    if lines.next().is_some() {
        return Err(bad(
            file,
            "a password file holds one line (the board's password); is this the solver's dictionary?".into(),
        ));
    }
    check_password(pw).map_err(|r| bad(file, r))?;
    Ok(pw.to_string())
}

/// One entry of the solver's dictionary.
#[derive(Clone, PartialEq, Eq)]
pub struct BoardCredential {
    /// The camera board's name (its `[cluster] board`), also its Zenoh user name.
    pub board: String,
    /// Its password.
    pub password: String,
}

impl std::fmt::Debug for BoardCredential {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BoardCredential({}, ***)", self.board)
    }
}

/// Parses the solver's dictionary: `board:password` per line, blank lines ignored, every board
/// once, at least one.
pub fn parse_dictionary(file: &Path, text: &str) -> Result<Vec<BoardCredential>> {
    let mut out: Vec<BoardCredential> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let at = |r: String| bad(file, format!("line {}: {r}", i + 1));
        let (board, password) = line
            .split_once(':')
            .ok_or_else(|| at("expected board:password".into()))?;
        let (board, password) = (board.trim(), password.trim());
        check_name("board", board).map_err(|e| at(e.to_string()))?;
        check_password(password).map_err(at)?;
        if out.iter().any(|c| c.board == board) {
            return Err(at(format!("board {board:?} is listed twice")));
        }
        out.push(BoardCredential {
            board: board.to_string(),
            password: password.to_string(),
        });
    }
    if out.is_empty() {
        return Err(bad(file, "the dictionary lists no board".into()));
    }
    Ok(out)
}

/// The dictionary file's text for `entries` (what [`parse_dictionary`] reads).
pub fn dictionary_text(entries: &[BoardCredential]) -> String {
    entries
        .iter()
        .map(|c| format!("{}:{}\n", c.board, c.password))
        .collect()
}

/// Characters of a generated password: 64 of them, so one random byte's low 6 bits pick one
/// uniformly.
pub const PASSWORD_ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_";
/// Length of a generated password: 32 characters of 6 bits, 192 random bits.
pub const GENERATED_PASSWORD_LEN: usize = 32;

/// A new random password from the operating system's CSPRNG (`OsRng`).
pub fn random_password() -> String {
    use rand::RngCore;
    let mut bytes = [0u8; GENERATED_PASSWORD_LEN];
    rand::rngs::OsRng.fill_bytes(&mut bytes);
    bytes
        .iter()
        .map(|b| char::from(PASSWORD_ALPHABET[usize::from(b & 63)]))
        .collect()
}

/// The solver's dictionary file in `dir` (as [`write_new_credentials`] names it).
pub fn dictionary_path(dir: &Path) -> std::path::PathBuf {
    dir.join("solver.credentials")
}

/// A board's password file in `dir` (as [`write_new_credentials`] names it).
pub fn password_path(dir: &Path, board: &str) -> std::path::PathBuf {
    dir.join(format!("{board}.password"))
}

/// Writes `text` to `path` through a new temporary file created with mode 0600 and a rename,
/// so the secret is never readable by others, not even for a moment.
pub fn write_private(path: &Path, text: &str) -> Result<()> {
    use std::io::Write;
    use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
    let io = |e: std::io::Error| bad(path, format!("cannot write: {e}"));
    let mut tmp_name = path.as_os_str().to_owned();
    tmp_name.push(".tmp-cluster-keys");
    let tmp = std::path::PathBuf::from(tmp_name);
    let _ = std::fs::remove_file(&tmp);
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(&tmp)
        .map_err(io)?;
    f.set_permissions(std::fs::Permissions::from_mode(0o600))
        .map_err(io)?;
    f.write_all(text.as_bytes())
        .and_then(|()| f.sync_all())
        .map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// Makes a random password for each of `boards` and writes `dir/<board>.password` (one line)
/// and the solver's `dir/solver.credentials`, all mode 0600. Refuses to replace existing
/// files unless `force`. Returns the entries written (the caller prints no password).
pub fn write_new_credentials(dir: &Path, boards: &[&str], force: bool) -> Result<Vec<BoardCredential>> {
    let mut seen: Vec<&str> = Vec::new();
    for b in boards {
        check_name("board", b)?;
        if seen.contains(b) {
            return Err(ClusterError::Config {
                reason: format!("board {b:?} is listed twice"),
            });
        }
        seen.push(b);
    }
    if boards.is_empty() {
        return Err(ClusterError::Config {
            reason: "no board given".into(),
        });
    }
    let dict = dictionary_path(dir);
    if !force {
        for p in boards.iter().map(|b| password_path(dir, b)).chain([dict.clone()]) {
            if p.exists() {
                return Err(bad(
                    &p,
                    "already exists; refusing to overwrite credentials (--force makes new ones)".into(),
                ));
            }
        }
    }
    std::fs::create_dir_all(dir).map_err(|e| bad(dir, format!("cannot create directory: {e}")))?;
    let entries: Vec<BoardCredential> = boards
        .iter()
        .map(|b| BoardCredential {
            board: (*b).to_string(),
            password: random_password(),
        })
        .collect();
    for c in &entries {
        write_private(&password_path(dir, &c.board), &format!("{}\n", c.password))?;
    }
    write_private(&dict, &dictionary_text(&entries))?;
    Ok(entries)
}

/// Reads a secret file; also says whether group or others may read it (the caller warns).
pub fn read_secret(file: &Path) -> Result<(String, bool)> {
    use std::os::unix::fs::PermissionsExt;
    let text = std::fs::read_to_string(file).map_err(|e| bad(file, format!("cannot read: {e}")))?;
    let loose = std::fs::metadata(file).is_ok_and(|m| m.permissions().mode() & 0o077 != 0);
    Ok((text, loose))
}

/// Reads and parses a board's password file.
pub fn read_password_file(file: &Path) -> Result<(String, bool)> {
    let (text, loose) = read_secret(file)?;
    Ok((parse_password(file, &text)?, loose))
}

/// Reads and parses the solver's dictionary file.
pub fn read_dictionary_file(file: &Path) -> Result<(Vec<BoardCredential>, bool)> {
    let (text, loose) = read_secret(file)?;
    Ok((parse_dictionary(file, &text)?, loose))
}
