//! Sealed credential envelopes: a board's Zenoh password (or the solver's dictionary) pushed
//! from the PC over the unencrypted parameter port, readable only by that board and accepted
//! only from a trusted signer (docs/cluster-envelope.md has the byte layout).
//!
//! - **Confidential**: the secret is encrypted to the board's own X25519 key (made at its first
//!   start, kept in its state directory, its public key shown in `/status` and pinned by the
//!   PC): an ephemeral X25519 key per envelope, HKDF-SHA256 of the shared secret, and
//!   ChaCha20-Poly1305 with the envelope's header as associated data.
//! - **Authentic**: the whole envelope is signed with Ed25519 by a key the board already trusts
//!   for parameter sets (`[params] trusted_keys`); the signature is checked before anything is
//!   decrypted.
//! - **For this board, not replayed**: it names the board and its public key, and carries a
//!   serial that must be greater than that of the last envelope the board accepted.

use chacha20poly1305::aead::{Aead, KeyInit, Payload};
use chacha20poly1305::{ChaCha20Poly1305, Nonce};
use ed25519_dalek::{Signature, Signer, SigningKey, VerifyingKey};
use irtrack_core::signing::{KEY_ID_LEN, KeyId};
use x25519_dalek::{PublicKey, StaticSecret};

use crate::error::{ClusterError, Result};

/// First bytes of an envelope.
pub const MAGIC: [u8; 4] = *b"IRCK";
/// The format's version.
pub const VERSION: u8 = 1;
/// Longest plaintext (a dictionary of many boards fits easily).
pub const MAX_PLAINTEXT: usize = 64 * 1024;
/// ChaCha20-Poly1305's tag.
pub const TAG_LEN: usize = 16;
/// The AEAD nonce's length.
pub const NONCE_LEN: usize = 12;
/// HKDF's salt: names the format, so a key derived here is used for nothing else.
pub const KDF_SALT: &[u8] = b"irtrack-cluster-credentials-v1";
/// First line of a board's X25519 secret key file.
pub const BOX_SECRET_FILE_HEADER: &str = "irtrack-x25519-secret v1";
/// Longest envelope (header, largest ciphertext, signature).
pub const MAX_ENVELOPE: usize = 200 + MAX_PLAINTEXT + TAG_LEN;

/// What an envelope holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SecretKind {
    /// A camera board's password file (one line).
    BoardPassword = 1,
    /// The solver's dictionary (`board:password` lines).
    SolverDictionary = 2,
    /// The solver's TLS identity: its certificate and private key (PEM).
    SolverTls = 3,
    /// The solver's TLS certificate a camera board pins (PEM, no key).
    PinnedSolverCertificate = 4,
}

impl SecretKind {
    fn from_byte(b: u8) -> Option<SecretKind> {
        match b {
            1 => Some(SecretKind::BoardPassword),
            2 => Some(SecretKind::SolverDictionary),
            3 => Some(SecretKind::SolverTls),
            4 => Some(SecretKind::PinnedSolverCertificate),
            _ => None,
        }
    }

    /// In words.
    pub fn words(self) -> &'static str {
        match self {
            SecretKind::BoardPassword => "board password",
            SecretKind::SolverDictionary => "solver credentials",
            SecretKind::SolverTls => "the solver's TLS certificate and key",
            SecretKind::PinnedSolverCertificate => "the solver's TLS certificate (to pin)",
        }
    }
}

/// Why an envelope is refused; each maps to a verdict code of the parameter port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// Not an envelope, truncated, or a field out of range (`BAD_BLOB`).
    Malformed,
    /// Signed by a key this board does not trust, or the signature does not verify
    /// (`UNAUTHORIZED`).
    Unauthorized,
    /// Sealed to another board's key or naming another board (`RIG_MISMATCH`).
    OtherBoard,
    /// Its serial is not newer than the last accepted envelope's (`ROLLBACK`).
    Replayed,
    /// Signed and for this board, but the ciphertext does not open (`BAD_BLOB`).
    Undecryptable,
    /// Opens, but the secret is not a valid password file / dictionary (`INVALID_PARAMS`).
    Invalid,
}

impl Refusal {
    /// The parameter port's verdict code (docs/param-protocol.md).
    pub fn code(self) -> &'static str {
        match self {
            Refusal::Malformed | Refusal::Undecryptable => "BAD_BLOB",
            Refusal::Unauthorized => "UNAUTHORIZED",
            Refusal::OtherBoard => "RIG_MISMATCH",
            Refusal::Replayed => "ROLLBACK",
            Refusal::Invalid => "INVALID_PARAMS",
        }
    }
}

fn refuse(why: Refusal, reason: String) -> ClusterError {
    ClusterError::Envelope { why, reason }
}

/// A board's X25519 key pair for receiving credentials.
#[derive(Clone)]
pub struct BoxKey {
    secret: StaticSecret,
}

impl std::fmt::Debug for BoxKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BoxKey(public {})", hex(&self.public()))
    }
}

/// Lower-case hex.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Parses exactly 32 bytes of hex (a public key as `/status` shows it).
pub fn parse_key_hex(text: &str) -> Option<[u8; 32]> {
    let t = text.trim();
    if t.len() != 64 || !t.is_ascii() {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(&t[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(out)
}

impl BoxKey {
    /// A new key from the OS's CSPRNG.
    pub fn generate() -> BoxKey {
        let mut b = [0u8; 32];
        rand::RngCore::fill_bytes(&mut rand::rngs::OsRng, &mut b);
        BoxKey::from_secret_bytes(b)
    }

    /// The key of these 32 secret bytes.
    pub fn from_secret_bytes(b: [u8; 32]) -> BoxKey {
        BoxKey {
            secret: StaticSecret::from(b),
        }
    }

    /// Its public key.
    pub fn public(&self) -> [u8; 32] {
        PublicKey::from(&self.secret).to_bytes()
    }

    /// The key file's text (header line, 64 hex digits).
    pub fn file_text(&self) -> String {
        format!("{BOX_SECRET_FILE_HEADER}\n{}\n", hex(self.secret.as_bytes()))
    }

    /// Parses a key file.
    pub fn parse_file(file: &std::path::Path, text: &str) -> Result<BoxKey> {
        let mut lines = text.lines();
        let bad = |reason: &str| ClusterError::Credentials {
            file: file.display().to_string(),
            reason: reason.to_string(),
        };
        if lines.next().map(str::trim) != Some(BOX_SECRET_FILE_HEADER) {
            return Err(bad("not an irtrack X25519 secret key file (first line)"));
        }
        let key = lines
            .next()
            .and_then(parse_key_hex)
            .ok_or_else(|| bad("the second line must be 64 hex digits"))?;
        Ok(BoxKey::from_secret_bytes(key))
    }

    /// Loads the key file at `path`, or makes a new key and writes it there (mode 0600) when
    /// there is none; `true` besides when it was made now.
    pub fn load_or_create(path: &std::path::Path) -> Result<(BoxKey, bool)> {
        match std::fs::read_to_string(path) {
            Ok(text) => Ok((BoxKey::parse_file(path, &text)?, false)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                let key = BoxKey::generate();
                crate::credentials::write_private(path, &key.file_text())?;
                Ok((key, true))
            }
            Err(e) => Err(ClusterError::Credentials {
                file: path.display().to_string(),
                reason: format!("cannot read: {e}"),
            }),
        }
    }
}

/// What [`seal`] puts into an envelope.
#[derive(Debug, Clone)]
pub struct Sealing<'a> {
    /// What the secret is.
    pub kind: SecretKind,
    /// The board it is for (its `[cluster] board`).
    pub board: &'a str,
    /// Greater than every earlier envelope's for this board.
    pub serial: u64,
    /// When it was made, Unix seconds.
    pub created_unix_s: u64,
    /// The board's public key (pinned on the PC).
    pub recipient: [u8; 32],
    /// The secret file's text.
    pub plaintext: &'a [u8],
}

fn derive_key(shared: &[u8; 32], ephemeral: &[u8; 32], recipient: &[u8; 32]) -> [u8; 32] {
    let hk = hkdf::Hkdf::<sha2::Sha256>::new(Some(KDF_SALT), shared);
    let mut info = [0u8; 64];
    info[..32].copy_from_slice(ephemeral);
    info[32..].copy_from_slice(recipient);
    let mut key = [0u8; 32];
    // 32 bytes are always within HKDF-SHA256's limit (8160 bytes).
    let _ = hk.expand(&info, &mut key);
    key
}

fn header_bytes(s: &Sealing<'_>, ephemeral: &[u8; 32], nonce: &[u8; NONCE_LEN], ct_len: u32) -> Vec<u8> {
    let mut h = Vec::with_capacity(128);
    h.extend_from_slice(&MAGIC);
    h.push(VERSION);
    h.push(s.kind as u8);
    h.push(s.board.len() as u8);
    h.extend_from_slice(s.board.as_bytes());
    h.extend_from_slice(&s.serial.to_le_bytes());
    h.extend_from_slice(&s.created_unix_s.to_le_bytes());
    h.extend_from_slice(&s.recipient);
    h.extend_from_slice(ephemeral);
    h.extend_from_slice(nonce);
    h.extend_from_slice(&ct_len.to_le_bytes());
    h
}

/// Seals with a given ephemeral secret and nonce (tests' golden vectors; [`seal`] draws them
/// from the OS's CSPRNG).
pub fn seal_with(
    s: &Sealing<'_>,
    signer: &SigningKey,
    ephemeral_secret: [u8; 32],
    nonce: [u8; NONCE_LEN],
) -> Result<Vec<u8>> {
    crate::names::check_name("board", s.board)?;
    if s.plaintext.is_empty() || s.plaintext.len() > MAX_PLAINTEXT {
        return Err(ClusterError::Config {
            reason: format!(
                "a sealed secret must be 1..={MAX_PLAINTEXT} bytes, this one is {}",
                s.plaintext.len()
            ),
        });
    }
    let eph = StaticSecret::from(ephemeral_secret);
    let eph_pub = PublicKey::from(&eph).to_bytes();
    let shared = eph.diffie_hellman(&PublicKey::from(s.recipient));
    if !shared.was_contributory() {
        return Err(ClusterError::Config {
            reason: "the board's public key is a low-order point, not a real key".into(),
        });
    }
    let key = derive_key(shared.as_bytes(), &eph_pub, &s.recipient);
    let ct_len = (s.plaintext.len() + TAG_LEN) as u32;
    let mut out = header_bytes(s, &eph_pub, &nonce, ct_len);
    let cipher = ChaCha20Poly1305::new(chacha20poly1305::Key::from_slice(&key));
    let ct = cipher
        .encrypt(
            Nonce::from_slice(&nonce),
            Payload {
                msg: s.plaintext,
                aad: &out,
            },
        )
        .map_err(|_| ClusterError::Config {
            reason: "encryption failed".into(),
        })?;
    out.extend_from_slice(&ct);
    out.extend_from_slice(&KeyId::of(&signer.verifying_key()).0);
    let signature = signer.sign(&out);
    out.extend_from_slice(&signature.to_bytes());
    Ok(out)
}

/// Seals `s` for its board and signs it with `signer`.
pub fn seal(s: &Sealing<'_>, signer: &SigningKey) -> Result<Vec<u8>> {
    let mut eph = [0u8; 32];
    let mut nonce = [0u8; NONCE_LEN];
    rand::RngCore::fill_bytes(&mut rand::rngs::OsRng, &mut eph);
    rand::RngCore::fill_bytes(&mut rand::rngs::OsRng, &mut nonce);
    seal_with(s, signer, eph, nonce)
}

/// An envelope's fields, before anything is trusted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EnvelopeHeader {
    /// What it holds.
    pub kind: SecretKind,
    /// The board it names.
    pub board: String,
    /// Its serial.
    pub serial: u64,
    /// When it was made, Unix seconds.
    pub created_unix_s: u64,
    /// The public key it was sealed to.
    pub recipient: [u8; 32],
    /// The signer's key id.
    pub key_id: KeyId,
}

struct Parsed<'a> {
    header: EnvelopeHeader,
    ephemeral: [u8; 32],
    nonce: [u8; NONCE_LEN],
    aad: &'a [u8],
    ciphertext: &'a [u8],
    signed: &'a [u8],
    signature: Signature,
}

fn take<'a>(b: &'a [u8], at: &mut usize, n: usize, what: &str) -> Result<&'a [u8]> {
    let end = at.checked_add(n).filter(|e| *e <= b.len()).ok_or_else(|| {
        refuse(
            Refusal::Malformed,
            format!("envelope ends inside its {what} ({} bytes)", b.len()),
        )
    })?;
    let s = &b[*at..end];
    *at = end;
    Ok(s)
}

fn arr<const N: usize>(s: &[u8]) -> [u8; N] {
    let mut a = [0u8; N];
    a.copy_from_slice(s);
    a
}

fn parse(b: &[u8]) -> Result<Parsed<'_>> {
    let bad = |reason: String| refuse(Refusal::Malformed, reason);
    if b.len() > MAX_ENVELOPE {
        return Err(bad(format!(
            "envelope of {} bytes, at most {MAX_ENVELOPE}",
            b.len()
        )));
    }
    let mut at = 0;
    let magic = take(b, &mut at, 4, "magic")?;
    if magic != MAGIC {
        return Err(bad(format!("not a credential envelope (magic {})", hex(magic))));
    }
    let version = take(b, &mut at, 1, "version")?[0];
    if version != VERSION {
        return Err(bad(format!(
            "envelope version {version}, this irtrackd reads {VERSION}"
        )));
    }
    let kind_byte = take(b, &mut at, 1, "kind")?[0];
    let kind =
        SecretKind::from_byte(kind_byte).ok_or_else(|| bad(format!("unknown secret kind {kind_byte}")))?;
    let n = usize::from(take(b, &mut at, 1, "board name length")?[0]);
    let name = take(b, &mut at, n, "board name")?;
    let board = std::str::from_utf8(name)
        .ok()
        .filter(|s| crate::names::check_name("board", s).is_ok())
        .ok_or_else(|| bad("the board name is not 1..=32 characters of A-Z a-z 0-9 _ -".into()))?
        .to_string();
    let serial = u64::from_le_bytes(arr(take(b, &mut at, 8, "serial")?));
    let created_unix_s = u64::from_le_bytes(arr(take(b, &mut at, 8, "creation time")?));
    let recipient = arr(take(b, &mut at, 32, "recipient key")?);
    let ephemeral = arr(take(b, &mut at, 32, "ephemeral key")?);
    let nonce = arr(take(b, &mut at, NONCE_LEN, "nonce")?);
    let ct_len = u32::from_le_bytes(arr(take(b, &mut at, 4, "ciphertext length")?)) as usize;
    if !(TAG_LEN + 1..=MAX_PLAINTEXT + TAG_LEN).contains(&ct_len) {
        return Err(bad(format!("ciphertext length {ct_len} out of range")));
    }
    let aad_end = at;
    let ciphertext = take(b, &mut at, ct_len, "ciphertext")?;
    let key_id = KeyId(arr(take(b, &mut at, KEY_ID_LEN, "signer key id")?));
    let signed_end = at;
    let signature = Signature::from_bytes(&arr(take(b, &mut at, 64, "signature")?));
    if at != b.len() {
        return Err(bad(format!("{} bytes after the signature", b.len() - at)));
    }
    Ok(Parsed {
        header: EnvelopeHeader {
            kind,
            board,
            serial,
            created_unix_s,
            recipient,
            key_id,
        },
        ephemeral,
        nonce,
        aad: &b[..aad_end],
        ciphertext,
        signed: &b[..signed_end],
        signature,
    })
}

/// Reads an envelope's header without trusting it (tools that show what a file holds).
pub fn peek(bytes: &[u8]) -> Result<EnvelopeHeader> {
    Ok(parse(bytes)?.header)
}

/// An accepted envelope.
#[derive(Clone, PartialEq, Eq)]
pub struct Opened {
    /// Its header (signer, serial, ...).
    pub header: EnvelopeHeader,
    /// The secret file's text, checked to parse as its kind.
    pub secret: String,
}

impl std::fmt::Debug for Opened {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Opened({:?}, ***)", self.header)
    }
}

/// What the receiving board is.
#[derive(Debug)]
pub struct Recipient<'a> {
    /// Its `[cluster] board`.
    pub board: &'a str,
    /// Its key pair.
    pub key: &'a BoxKey,
    /// The keys it trusts for parameter sets.
    pub trusted: &'a [VerifyingKey],
    /// The serial of the last envelope it accepted (none yet: any serial).
    pub last_serial: Option<u64>,
}

/// Checks and opens an envelope, in this order: framing, signature (before anything is
/// decrypted), recipient key and board name, serial, decryption, the secret's format.
pub fn open(bytes: &[u8], to: &Recipient<'_>) -> Result<Opened> {
    let p = parse(bytes)?;
    let h = &p.header;
    let mut candidates = to.trusted.iter().filter(|k| KeyId::of(k) == h.key_id).peekable();
    if candidates.peek().is_none() {
        return Err(refuse(
            Refusal::Unauthorized,
            format!(
                "signed by key {}, which this board does not trust ({} trusted keys in [params] trusted_keys)",
                h.key_id,
                to.trusted.len()
            ),
        ));
    }
    if !candidates.any(|k| k.verify_strict(p.signed, &p.signature).is_ok()) {
        return Err(refuse(
            Refusal::Unauthorized,
            format!(
                "the signature of key {} does not verify: the envelope was altered",
                h.key_id
            ),
        ));
    }
    let own = to.key.public();
    if h.recipient != own {
        return Err(refuse(
            Refusal::OtherBoard,
            format!(
                "sealed to key {}, this board's key is {}: the PC pinned another board's key for {:?}",
                &hex(&h.recipient)[..16],
                &hex(&own)[..16],
                h.board
            ),
        ));
    }
    if h.board != to.board {
        return Err(refuse(
            Refusal::OtherBoard,
            format!("for board {:?}, this is board {:?}", h.board, to.board),
        ));
    }
    if let Some(last) = to.last_serial
        && h.serial <= last
    {
        return Err(refuse(
            Refusal::Replayed,
            format!(
                "serial {} is not newer than the last accepted envelope's ({last}): replayed or older",
                h.serial
            ),
        ));
    }
    let shared = to.key.secret.diffie_hellman(&PublicKey::from(p.ephemeral));
    let key = derive_key(shared.as_bytes(), &p.ephemeral, &own);
    let plain = ChaCha20Poly1305::new(chacha20poly1305::Key::from_slice(&key))
        .decrypt(
            Nonce::from_slice(&p.nonce),
            Payload {
                msg: p.ciphertext,
                aad: p.aad,
            },
        )
        .map_err(|_| {
            refuse(
                Refusal::Undecryptable,
                "the ciphertext does not open with this board's key".into(),
            )
        })?;
    let secret =
        String::from_utf8(plain).map_err(|_| refuse(Refusal::Invalid, "the secret is not text".into()))?;
    let file = std::path::Path::new("(pushed envelope)");
    let check = match h.kind {
        SecretKind::BoardPassword => crate::credentials::parse_password(file, &secret).map(|_| ()),
        SecretKind::SolverDictionary => crate::credentials::parse_dictionary(file, &secret).map(|_| ()),
        SecretKind::SolverTls => crate::credentials::parse_tls_identity(file, &secret),
        SecretKind::PinnedSolverCertificate => crate::credentials::parse_pinned_certificate(file, &secret),
    };
    check.map_err(|e| refuse(Refusal::Invalid, e.to_string()))?;
    Ok(Opened {
        header: p.header,
        secret,
    })
}
