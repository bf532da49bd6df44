//! Authenticated parameter blobs: Ed25519 signatures (docs/param-blob.md, docs/security.md).
//!
//! A signed blob is an ordinary blob with flag bit 0 set and a 72-byte trailer after the body:
//! an 8-byte [`KeyId`] and a 64-byte Ed25519 signature over header + body. Services read blobs
//! with [`verify_blob`]; [`crate::params::RigParams::from_blob`] refuses signed blobs so that a
//! signature is never silently ignored.
//!
//! Key files are two-line text files (`irtrack-ed25519-public v1` / `irtrack-ed25519-secret v1`
//! followed by 64 hex digits); see [`parse_public_key_file`].

use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;
use core::fmt;

use ed25519_dalek::{Digest, SIGNATURE_LENGTH, Sha512, Signature, Signer};
pub use ed25519_dalek::{PUBLIC_KEY_LENGTH, SECRET_KEY_LENGTH, SigningKey, VerifyingKey};

use crate::param_wire::{RejectCode, Verdict};
use crate::params::{BLOB_FLAG_SIGNED, BLOB_SIGNATURE_TRAILER_LEN, BlobHeader, RigParams, decode_body};
use crate::{Error, Result};

/// Length of a key id in bytes.
pub const KEY_ID_LEN: usize = 8;
/// First line of a public key file.
pub const PUBLIC_KEY_FILE_HEADER: &str = "irtrack-ed25519-public v1";
/// First line of a secret key file.
pub const SECRET_KEY_FILE_HEADER: &str = "irtrack-ed25519-secret v1";

// The trailer layout is fixed by the format; keep the constants in step.
const _: () = assert!(BLOB_SIGNATURE_TRAILER_LEN == KEY_ID_LEN + SIGNATURE_LENGTH);

/// Short id of a public key: the first 8 bytes of SHA-512 over its 32 bytes. It lets a
/// verifier pick the key without trying all of them and names the key in errors and status.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyId(pub [u8; KEY_ID_LEN]);

impl KeyId {
    /// The id of `key`.
    pub fn of(key: &VerifyingKey) -> KeyId {
        let digest = Sha512::digest(key.as_bytes());
        let mut id = [0u8; KEY_ID_LEN];
        id.copy_from_slice(&digest[..KEY_ID_LEN]);
        KeyId(id)
    }
}

impl fmt::Display for KeyId {
    /// 16 lower-case hex digits.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for b in self.0 {
            write!(f, "{b:02x}")?;
        }
        Ok(())
    }
}

/// Whether unsigned blobs are acceptable.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SignaturePolicy {
    /// Production: only blobs signed by a trusted key.
    RequireSigned,
    /// Development mode: unsigned blobs pass too. Signed blobs must still verify.
    AllowUnsigned,
}

/// How a blob accepted by [`verify_blob`] was authenticated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SignatureStatus {
    /// Signed by the trusted key with this id.
    Signed {
        /// Id of the key that signed it.
        key_id: KeyId,
    },
    /// Unsigned, accepted only because the policy is [`SignaturePolicy::AllowUnsigned`].
    UnsignedAccepted,
}

impl RigParams {
    /// Encodes a signed blob: header with flag bit 0, body, key id and Ed25519 signature over
    /// header + body. Does not validate; call [`RigParams::validate`] first.
    pub fn to_signed_blob(&self, key: &SigningKey) -> Result<Vec<u8>> {
        let mut blob = self.encode_blob(BLOB_FLAG_SIGNED, BLOB_SIGNATURE_TRAILER_LEN)?;
        // Ed25519 is deterministic: the same key and parameters give the same bytes.
        let signature = key.sign(&blob);
        blob.extend_from_slice(&KeyId::of(&key.verifying_key()).0);
        blob.extend_from_slice(&signature.to_bytes());
        Ok(blob)
    }
}

/// Header, framing and CRC checks shared by the readers; returns the header and the body.
fn open_blob(bytes: &[u8]) -> Result<(BlobHeader, &[u8])> {
    let header = BlobHeader::parse_allow_signed(bytes)?;
    let body = header.check_frame(bytes)?;
    Ok((header, body))
}

/// Key id and signature of a signed blob whose frame has been checked.
fn trailer(bytes: &[u8], header: &BlobHeader) -> (KeyId, Signature) {
    let t = &bytes[header.signed_part_len()..];
    let mut id = [0u8; KEY_ID_LEN];
    id.copy_from_slice(&t[..KEY_ID_LEN]);
    let mut sig = [0u8; SIGNATURE_LENGTH];
    sig.copy_from_slice(&t[KEY_ID_LEN..]);
    (KeyId(id), Signature::from_bytes(&sig))
}

/// Decodes a parameter blob and checks its signature against `trusted` keys: the one call a
/// service makes for a pushed or stored blob.
///
/// Order: header (magic, version, flags), length (a signed blob needs its 72-byte trailer),
/// CRC, then the signature — before the body is decoded, so untrusted bodies are not parsed.
/// Errors, besides the blob errors of [`RigParams::from_blob`]: [`Error::BlobUnsigned`]
/// (unsigned under [`SignaturePolicy::RequireSigned`]), [`Error::BlobUnknownKey`],
/// [`Error::BlobBadSignature`]. Does not validate the contents.
pub fn verify_blob(
    bytes: &[u8],
    trusted: &[VerifyingKey],
    policy: SignaturePolicy,
) -> Result<(RigParams, SignatureStatus)> {
    let (header, body) = open_blob(bytes)?;
    let status = if header.is_signed() {
        let (key_id, signature) = trailer(bytes, &header);
        let signed_part = &bytes[..header.signed_part_len()];
        let mut candidates = trusted.iter().filter(|k| KeyId::of(k) == key_id).peekable();
        if candidates.peek().is_none() {
            return Err(Error::BlobUnknownKey {
                key_id,
                trusted: trusted.len(),
            });
        }
        // Two trusted keys may share an id (64-bit prefix); any one verifying is enough.
        // verify_strict also refuses malleable signatures and small-order keys.
        if !candidates.any(|k| k.verify_strict(signed_part, &signature).is_ok()) {
            return Err(Error::BlobBadSignature { key_id });
        }
        SignatureStatus::Signed { key_id }
    } else {
        match policy {
            SignaturePolicy::RequireSigned => return Err(Error::BlobUnsigned),
            SignaturePolicy::AllowUnsigned => SignatureStatus::UnsignedAccepted,
        }
    };
    Ok((decode_body(header.version, body)?, status))
}

/// Decodes a signed or unsigned blob WITHOUT checking the signature, for tools that display
/// or forward a blob (`show-params`, `push-params` of an already signed file). Returns the
/// key id for a signed blob. Never use it to decide whether to trust parameters.
pub fn decode_without_verifying(bytes: &[u8]) -> Result<(RigParams, Option<KeyId>)> {
    let (header, body) = open_blob(bytes)?;
    let key_id = header.is_signed().then(|| trailer(bytes, &header).0);
    Ok((decode_body(header.version, body)?, key_id))
}

/// The reject code for an error met while handling a push: signature problems are
/// `UNAUTHORIZED`, everything else as [`RejectCode::for_error`].
pub fn reject_code(e: &Error) -> RejectCode {
    match e {
        Error::BlobUnsigned | Error::BlobUnknownKey { .. } | Error::BlobBadSignature { .. } => {
            RejectCode::Unauthorized
        }
        other => RejectCode::for_error(other),
    }
}

/// The verdict for an error met while handling a push (see [`reject_code`]).
pub fn verdict_for(e: &Error) -> Verdict {
    Verdict::Rejected {
        code: reject_code(e),
        message: format!("{e}"),
    }
}

fn hex(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        s.push_str(&format!("{b:02x}"));
    }
    s
}

fn unhex_32(what: &'static str, text: &str) -> Result<[u8; 32]> {
    let bad = |reason: String| Error::BadKey { what, reason };
    if text.len() != 64 {
        return Err(bad(format!(
            "key line has {} characters, expected 64 hex digits",
            text.len()
        )));
    }
    let mut out = [0u8; 32];
    for (i, pair) in text.as_bytes().chunks(2).enumerate() {
        let digit = |c: u8| (c as char).to_digit(16);
        match (digit(pair[0]), digit(pair[1])) {
            (Some(h), Some(l)) => out[i] = (h * 16 + l) as u8,
            _ => {
                return Err(bad(format!(
                    "key line has a non-hex character near column {}",
                    2 * i + 1
                )));
            }
        }
    }
    Ok(out)
}

/// The key line of a key file: the header must come first; blank and `#` lines are comments.
fn key_line<'a>(text: &'a str, what: &'static str, header: &str, other_header: &str) -> Result<&'a str> {
    let bad = |reason: String| Error::BadKey { what, reason };
    let mut lines = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'));
    match lines.next() {
        Some(h) if h == header => {}
        Some(h) if h == other_header => {
            return Err(bad(format!(
                "this is a \"{other_header}\" file, expected \"{header}\""
            )));
        }
        Some(h) => {
            let shown: String = h.chars().take(40).collect();
            return Err(bad(format!("first line {shown:?} is not \"{header}\"")));
        }
        None => return Err(bad("file is empty".into())),
    }
    let Some(key) = lines.next() else {
        return Err(bad("no key line after the header".into()));
    };
    if lines.next().is_some() {
        return Err(bad("more than one key line".into()));
    }
    Ok(key)
}

/// Text of a public key file: header, a comment with the key id, 64 hex digits.
pub fn public_key_file(key: &VerifyingKey) -> String {
    format!(
        "{PUBLIC_KEY_FILE_HEADER}\n# key id {}\n{}\n",
        KeyId::of(key),
        hex(key.as_bytes())
    )
}

/// Text of a secret key file: header, a comment with the key id, the 32-byte seed in hex.
pub fn secret_key_file(key: &SigningKey) -> String {
    format!(
        "{SECRET_KEY_FILE_HEADER}\n# key id {}; keep this file private\n{}\n",
        KeyId::of(&key.verifying_key()),
        hex(&key.to_bytes())
    )
}

/// Parses a public key file (`irtrack-ed25519-public v1`, then 64 hex digits; blank lines and
/// lines starting with `#` are ignored). Refuses keys that are not valid curve points.
pub fn parse_public_key_file(text: &str) -> Result<VerifyingKey> {
    const WHAT: &str = "public key file";
    let line = key_line(text, WHAT, PUBLIC_KEY_FILE_HEADER, SECRET_KEY_FILE_HEADER)?;
    let bytes = unhex_32(WHAT, line)?;
    let key = VerifyingKey::from_bytes(&bytes).map_err(|_| Error::BadKey {
        what: WHAT,
        reason: "the 32 bytes are not a valid Ed25519 public key".into(),
    })?;
    if key.is_weak() {
        return Err(Error::BadKey {
            what: WHAT,
            reason: "weak (small-order) Ed25519 public key".into(),
        });
    }
    Ok(key)
}

/// Parses a secret key file (`irtrack-ed25519-secret v1`, then the 32-byte seed in hex).
pub fn parse_secret_key_file(text: &str) -> Result<SigningKey> {
    const WHAT: &str = "secret key file";
    let line = key_line(text, WHAT, SECRET_KEY_FILE_HEADER, PUBLIC_KEY_FILE_HEADER)?;
    Ok(SigningKey::from_bytes(&unhex_32(WHAT, line)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_files_round_trip_and_name_problems() {
        let key = SigningKey::from_bytes(&[7u8; 32]);
        let public = key.verifying_key();
        let pub_text = public_key_file(&public);
        let sec_text = secret_key_file(&key);
        assert_eq!(parse_public_key_file(&pub_text).unwrap(), public);
        assert_eq!(
            parse_secret_key_file(&sec_text).unwrap().to_bytes(),
            key.to_bytes()
        );
        assert!(pub_text.contains(&format!("# key id {}", KeyId::of(&public))));

        let reason = |r: Result<VerifyingKey>| match r {
            Err(Error::BadKey { reason, .. }) => reason,
            other => panic!("expected BadKey, got {other:?}"),
        };
        assert!(reason(parse_public_key_file(&sec_text)).contains("irtrack-ed25519-secret v1"));
        assert!(reason(parse_public_key_file("")).contains("empty"));
        assert!(reason(parse_public_key_file("hello\n")).contains("is not"));
        assert!(reason(parse_public_key_file(PUBLIC_KEY_FILE_HEADER)).contains("no key line"));
        let short = format!("{PUBLIC_KEY_FILE_HEADER}\nabcd\n");
        assert!(reason(parse_public_key_file(&short)).contains("4 characters"));
        let nonhex = format!("{PUBLIC_KEY_FILE_HEADER}\n{}zz\n", "0".repeat(62));
        assert!(reason(parse_public_key_file(&nonhex)).contains("non-hex"));
        let two = format!("{pub_text}{}\n", hex(public.as_bytes()));
        assert!(reason(parse_public_key_file(&two)).contains("more than one"));
        // The identity point has small order: a forger's key, never trusted.
        let mut identity = [0u8; 32];
        identity[0] = 1;
        let weak = format!("{PUBLIC_KEY_FILE_HEADER}\n{}\n", hex(&identity));
        assert!(reason(parse_public_key_file(&weak)).contains("weak"));
        assert!(matches!(
            parse_secret_key_file(&pub_text),
            Err(Error::BadKey {
                what: "secret key file",
                ..
            })
        ));
    }

    #[test]
    fn key_id_display_is_hex() {
        assert_eq!(
            format!("{}", KeyId([0, 1, 0xab, 0xff, 2, 3, 4, 5])),
            "0001abff02030405"
        );
    }

    #[test]
    fn signature_errors_map_to_unauthorized() {
        let id = KeyId([0; 8]);
        assert_eq!(reject_code(&Error::BlobUnsigned), RejectCode::Unauthorized);
        assert_eq!(
            reject_code(&Error::BlobUnknownKey {
                key_id: id,
                trusted: 1
            }),
            RejectCode::Unauthorized
        );
        assert_eq!(
            reject_code(&Error::BlobBadSignature { key_id: id }),
            RejectCode::Unauthorized
        );
        assert_eq!(
            reject_code(&Error::BlobBadCrc {
                found: 1,
                computed: 2
            }),
            RejectCode::BadBlob
        );
        let v = verdict_for(&Error::BlobUnsigned);
        assert!(
            matches!(v, Verdict::Rejected { code: RejectCode::Unauthorized, ref message } if message.contains("not signed"))
        );
    }
}
