//! Parameter push protocol between `host-tools push-params` (client) and irtrackd (server).
//! Spec: docs/param-protocol.md.
//!
//! One exchange per TCP connection: the client sends `b"IRPP"`, the blob length as u32 LE and
//! the blob (or `b"IRPF"`, the length, u32 LE request flags and the blob, when it asks for
//! something, e.g. to allow a rollback); the server answers with exactly one ASCII line,
//! `OK <rig_id>\n` or `ERR <CODE> <message>\n`, and closes.

use alloc::format;
use alloc::string::{String, ToString};
use alloc::vec::Vec;

use crate::{Error, Result};

/// Default TCP port of irtrackd's parameter endpoint.
pub const DEFAULT_PORT: u16 = 7701;
/// Magic of a push request.
pub const PUSH_MAGIC: [u8; 4] = *b"IRPP";
/// Size of the push header (magic + u32 LE length).
pub const PUSH_HEADER_LEN: usize = 8;
/// Magic of a push request with flags: the [`PUSH_HEADER_LEN`] header as for `IRPP`, then
/// [`PUSH_FLAGS_LEN`] bytes of u32 LE flags, then the blob. Clients send it only when a flag is
/// set, so a plain push stays what every server knows.
pub const PUSH_FLAGS_MAGIC: [u8; 4] = *b"IRPF";
/// Size of the flags word that follows an `IRPF` header.
pub const PUSH_FLAGS_LEN: usize = 4;
/// Request flag: the operator allows this push to replace the active set with an older one
/// (`host-tools push-params --allow-rollback`).
pub const PUSH_FLAG_ALLOW_ROLLBACK: u32 = 0x0000_0001;
/// Every request flag this build knows; a server refuses others (`PROTOCOL`).
pub const PUSH_KNOWN_FLAGS: u32 = PUSH_FLAG_ALLOW_ROLLBACK;
/// Largest blob a server accepts (1 MiB; real rigs are well under 4 KiB).
pub const MAX_BLOB_BYTES: usize = 1 << 20;
/// Longest verdict line, newline included; longer messages are cut by [`Verdict::to_line`].
pub const MAX_VERDICT_LINE: usize = 1024;

const PROTOCOL: &str = "param-push";

/// What a push asks of the server besides taking the blob (the request flags).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PushOptions {
    /// Accept a set older than the active one ([`PUSH_FLAG_ALLOW_ROLLBACK`]).
    pub allow_rollback: bool,
}

impl PushOptions {
    /// The flags word for these options.
    pub fn flags(self) -> u32 {
        if self.allow_rollback {
            PUSH_FLAG_ALLOW_ROLLBACK
        } else {
            0
        }
    }

    /// Options from a flags word; unknown bits are an [`Error::Protocol`] naming them (a
    /// server must not ignore a request it does not understand).
    pub fn from_flags(flags: u32) -> Result<PushOptions> {
        let unknown = flags & !PUSH_KNOWN_FLAGS;
        if unknown != 0 {
            return Err(Error::Protocol {
                protocol: PROTOCOL,
                reason: format!("unknown request flags {unknown:#010x} (known {PUSH_KNOWN_FLAGS:#010x})"),
            });
        }
        Ok(PushOptions {
            allow_rollback: flags & PUSH_FLAG_ALLOW_ROLLBACK != 0,
        })
    }
}

/// Builds a complete push request for `blob` (`IRPP`, no flags).
pub fn encode_push(blob: &[u8]) -> Vec<u8> {
    encode_push_with(blob, PushOptions::default())
}

/// Builds a complete push request for `blob` with `options`: `IRPP` when no flag is set (every
/// server takes it), else `IRPF` with the flags word.
pub fn encode_push_with(blob: &[u8], options: PushOptions) -> Vec<u8> {
    let flags = options.flags();
    let mut out = Vec::with_capacity(PUSH_HEADER_LEN + PUSH_FLAGS_LEN + blob.len());
    out.extend_from_slice(if flags == 0 {
        &PUSH_MAGIC
    } else {
        &PUSH_FLAGS_MAGIC
    });
    // Blobs over MAX_BLOB_BYTES are refused by servers anyway; saturate instead of wrapping.
    let len = u32::try_from(blob.len()).unwrap_or(u32::MAX);
    out.extend_from_slice(&len.to_le_bytes());
    if flags != 0 {
        out.extend_from_slice(&flags.to_le_bytes());
    }
    out.extend_from_slice(blob);
    out
}

/// A parsed push header: the announced blob length, and whether a flags word follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PushHead {
    /// Announced blob length (1 ..= [`MAX_BLOB_BYTES`]).
    pub blob_len: usize,
    /// `IRPF`: [`PUSH_FLAGS_LEN`] bytes of flags come before the blob
    /// ([`PushOptions::from_flags`]).
    pub has_flags: bool,
}

/// Parses the 8-byte header of either request form (`IRPP` or `IRPF`).
///
/// Errors as [`parse_push_header`].
pub fn parse_push_head(hdr: &[u8; PUSH_HEADER_LEN]) -> Result<PushHead> {
    let has_flags = hdr[..4] == PUSH_FLAGS_MAGIC;
    let blob_len = parse_len(hdr, has_flags)?;
    Ok(PushHead { blob_len, has_flags })
}

/// Parses a plain (`IRPP`) push header and returns the announced blob length. A server that
/// also takes flags uses [`parse_push_head`].
///
/// Errors: [`Error::Protocol`] for a wrong magic or a zero length, [`Error::MessageTooLarge`]
/// for a length over [`MAX_BLOB_BYTES`] (answer it with [`RejectCode::TooLarge`]).
pub fn parse_push_header(hdr: &[u8; PUSH_HEADER_LEN]) -> Result<usize> {
    parse_len(hdr, false)
}

fn parse_len(hdr: &[u8; PUSH_HEADER_LEN], flags_form: bool) -> Result<usize> {
    if !flags_form && hdr[..4] != PUSH_MAGIC {
        return Err(Error::Protocol {
            protocol: PROTOCOL,
            reason: format!("bad magic {:02x?}, expected \"IRPP\"", &hdr[..4]),
        });
    }
    let len = u32::from_le_bytes([hdr[4], hdr[5], hdr[6], hdr[7]]) as usize;
    if len == 0 {
        return Err(Error::Protocol {
            protocol: PROTOCOL,
            reason: "empty blob".to_string(),
        });
    }
    if len > MAX_BLOB_BYTES {
        return Err(Error::MessageTooLarge {
            protocol: PROTOCOL,
            size: len,
            max: MAX_BLOB_BYTES,
        });
    }
    Ok(len)
}

/// Why a server refused a parameter set. On the wire as the upper-case code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum RejectCode {
    /// Blob did not decode: magic, version, flags, CRC, truncation, body (`BAD_BLOB`).
    BadBlob,
    /// Blob decoded but [`crate::params::RigParams::validate`] refused it (`INVALID_PARAMS`).
    InvalidParams,
    /// Valid, but does not fit this rig: camera count, image sizes (`RIG_MISMATCH`).
    RigMismatch,
    /// Announced length over [`MAX_BLOB_BYTES`] (`TOO_LARGE`).
    TooLarge,
    /// Could not be stored durably; the previous set stays active (`STORAGE`).
    Storage,
    /// Signature missing or not trusted (`UNAUTHORIZED`).
    Unauthorized,
    /// Request framing wrong: magic, empty, connection closed early (`PROTOCOL`).
    Protocol,
    /// Another push is in progress (`BUSY`).
    Busy,
    /// The set is older than the active one and the push did not allow a rollback
    /// (`ROLLBACK`; [`PUSH_FLAG_ALLOW_ROLLBACK`]).
    Rollback,
    /// Anything else on the server side (`INTERNAL`).
    Internal,
    /// A code this build does not know (forward compatibility; the raw code starts the message).
    Unknown,
}

impl RejectCode {
    const ALL: [RejectCode; 10] = [
        RejectCode::BadBlob,
        RejectCode::InvalidParams,
        RejectCode::RigMismatch,
        RejectCode::TooLarge,
        RejectCode::Storage,
        RejectCode::Unauthorized,
        RejectCode::Protocol,
        RejectCode::Busy,
        RejectCode::Internal,
        RejectCode::Rollback,
    ];

    /// The code as sent on the wire.
    pub fn as_str(self) -> &'static str {
        match self {
            RejectCode::BadBlob => "BAD_BLOB",
            RejectCode::InvalidParams => "INVALID_PARAMS",
            RejectCode::RigMismatch => "RIG_MISMATCH",
            RejectCode::TooLarge => "TOO_LARGE",
            RejectCode::Storage => "STORAGE",
            RejectCode::Unauthorized => "UNAUTHORIZED",
            RejectCode::Protocol => "PROTOCOL",
            RejectCode::Busy => "BUSY",
            RejectCode::Rollback => "ROLLBACK",
            RejectCode::Internal => "INTERNAL",
            RejectCode::Unknown => "UNKNOWN",
        }
    }

    /// Parses a wire code; `None` for codes this build does not know.
    pub fn from_wire(code: &str) -> Option<RejectCode> {
        RejectCode::ALL.iter().copied().find(|c| c.as_str() == code)
    }

    /// The code a server should answer for a core error met while handling a push.
    pub fn for_error(e: &Error) -> RejectCode {
        match e {
            Error::BlobTruncated { .. }
            | Error::BlobBadMagic { .. }
            | Error::BlobUnsupportedVersion { .. }
            | Error::BlobUnsupportedFlags { .. }
            | Error::BlobBadCrc { .. }
            | Error::BlobTrailingBytes { .. }
            | Error::BlobBody { .. } => RejectCode::BadBlob,
            Error::InvalidParams { .. } | Error::NoSuchCamera { .. } => RejectCode::InvalidParams,
            Error::MessageTooLarge { .. } => RejectCode::TooLarge,
            Error::Protocol { .. } => RejectCode::Protocol,
            _ => RejectCode::Internal,
        }
    }
}

impl core::fmt::Display for RejectCode {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The server's one-line answer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// Stored and swapped in.
    Accepted {
        /// Rig id of the accepted set.
        rig_id: String,
    },
    /// Refused; the previous parameter set stays active.
    Rejected {
        /// Why, as a code.
        code: RejectCode,
        /// Why, in words.
        message: String,
    },
}

impl Verdict {
    /// Rejection for a core error, with the error's text as message.
    pub fn from_error(e: &Error) -> Verdict {
        Verdict::Rejected {
            code: RejectCode::for_error(e),
            message: e.to_string(),
        }
    }

    /// The wire line, newline-terminated. Control characters in the message become spaces and
    /// the line is cut to [`MAX_VERDICT_LINE`] bytes, so the answer is always one line.
    pub fn to_line(&self) -> String {
        let mut line = match self {
            Verdict::Accepted { rig_id } => format!("OK {}", sanitize(rig_id)),
            Verdict::Rejected { code, message } => format!("ERR {} {}", code.as_str(), sanitize(message)),
        };
        if line.len() > MAX_VERDICT_LINE - 1 {
            let mut cut = MAX_VERDICT_LINE - 1;
            while !line.is_char_boundary(cut) {
                cut -= 1;
            }
            line.truncate(cut);
        }
        line.push('\n');
        line
    }

    /// Parses a verdict line (with or without its trailing newline).
    pub fn parse_line(line: &str) -> Result<Verdict> {
        let bad = |reason: String| Error::Protocol {
            protocol: PROTOCOL,
            reason,
        };
        let line = line.strip_suffix('\n').unwrap_or(line);
        let line = line.strip_suffix('\r').unwrap_or(line);
        if line.len() >= MAX_VERDICT_LINE {
            return Err(bad(format!("verdict line of {} bytes is too long", line.len())));
        }
        if let Some(rest) = line.strip_prefix("OK ") {
            let rig_id = rest.trim();
            // Control characters too: `to_line` turns them into spaces, so such an id could
            // not be written back as one word (found by fuzzing).
            if rig_id.is_empty() || rig_id.contains(|c: char| c.is_whitespace() || c.is_control()) {
                return Err(bad(format!("bad rig id in verdict {line:?}")));
            }
            return Ok(Verdict::Accepted {
                rig_id: rig_id.to_string(),
            });
        }
        if let Some(rest) = line.strip_prefix("ERR ") {
            let (code, message) = rest.split_once(' ').unwrap_or((rest, ""));
            if code.is_empty() {
                return Err(bad(format!("verdict {line:?} has no error code")));
            }
            // `UNKNOWN` is what `to_line` writes for an unknown code (raw code first in the
            // message): read it back as such, or relaying a verdict would stack `UNKNOWN`s.
            let known = match code {
                "UNKNOWN" => Some(RejectCode::Unknown),
                _ => RejectCode::from_wire(code),
            };
            return Ok(match known {
                Some(code) => Verdict::Rejected {
                    code,
                    message: message.to_string(),
                },
                None => Verdict::Rejected {
                    code: RejectCode::Unknown,
                    message: format!("{code} {message}"),
                },
            });
        }
        Err(bad(format!(
            "verdict {line:?} starts with neither \"OK \" nor \"ERR \""
        )))
    }

    /// Whether the parameters were accepted.
    pub fn is_accepted(&self) -> bool {
        matches!(self, Verdict::Accepted { .. })
    }
}

fn sanitize(s: &str) -> String {
    s.chars().map(|c| if c.is_control() { ' ' } else { c }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn push_header_round_trips() {
        let blob = [7u8; 300];
        let msg = encode_push(&blob);
        assert_eq!(msg.len(), PUSH_HEADER_LEN + 300);
        let hdr: [u8; 8] = msg[..8].try_into().unwrap();
        assert_eq!(&hdr, b"IRPP\x2c\x01\x00\x00");
        assert_eq!(parse_push_header(&hdr).unwrap(), 300);
        assert_eq!(&msg[8..], &blob[..]);
    }

    #[test]
    fn flagged_push_golden_bytes() {
        let blob = [7u8; 300];
        // Without a flag the request is the plain form older servers know.
        assert_eq!(
            encode_push_with(&blob, PushOptions::default()),
            encode_push(&blob)
        );
        let msg = encode_push_with(&blob, PushOptions { allow_rollback: true });
        assert_eq!(msg.len(), PUSH_HEADER_LEN + PUSH_FLAGS_LEN + 300);
        // "IRPF", length 300, flags 0x00000001 (allow rollback), then the blob.
        assert_eq!(&msg[..12], b"IRPF\x2c\x01\x00\x00\x01\x00\x00\x00");
        assert_eq!(&msg[12..], &blob[..]);
        let hdr: [u8; 8] = msg[..8].try_into().unwrap();
        assert_eq!(
            parse_push_head(&hdr).unwrap(),
            PushHead {
                blob_len: 300,
                has_flags: true
            }
        );
        // The plain parser does not take the flagged form (it would read flags as blob).
        assert!(matches!(parse_push_header(&hdr), Err(Error::Protocol { .. })));
        let plain: [u8; 8] = *b"IRPP\x2c\x01\x00\x00";
        assert_eq!(
            parse_push_head(&plain).unwrap(),
            PushHead {
                blob_len: 300,
                has_flags: false
            }
        );
        assert_eq!(
            PushOptions::from_flags(u32::from_le_bytes([1, 0, 0, 0])).unwrap(),
            PushOptions { allow_rollback: true }
        );
        assert_eq!(PushOptions::from_flags(0).unwrap(), PushOptions::default());
        let e = PushOptions::from_flags(0x8000_0001).unwrap_err().to_string();
        assert!(e.contains("unknown request flags 0x80000000"), "{e}");
        // The flagged form keeps the length checks.
        assert!(matches!(
            parse_push_head(b"IRPF\0\0\0\0"),
            Err(Error::Protocol { .. })
        ));
        assert_eq!(RejectCode::from_wire("ROLLBACK"), Some(RejectCode::Rollback));
    }

    #[test]
    fn push_header_errors() {
        assert!(matches!(
            parse_push_header(b"IRPX\x01\0\0\0"),
            Err(Error::Protocol { .. })
        ));
        assert!(matches!(
            parse_push_header(b"IRPP\0\0\0\0"),
            Err(Error::Protocol { .. })
        ));
        let too_big = ((MAX_BLOB_BYTES + 1) as u32).to_le_bytes();
        let hdr = [
            b'I', b'R', b'P', b'P', too_big[0], too_big[1], too_big[2], too_big[3],
        ];
        let e = parse_push_header(&hdr).unwrap_err();
        assert_eq!(
            e,
            Error::MessageTooLarge {
                protocol: PROTOCOL,
                size: MAX_BLOB_BYTES + 1,
                max: MAX_BLOB_BYTES
            }
        );
        assert_eq!(RejectCode::for_error(&e), RejectCode::TooLarge);
        let max = (MAX_BLOB_BYTES as u32).to_le_bytes();
        let hdr = [b'I', b'R', b'P', b'P', max[0], max[1], max[2], max[3]];
        assert_eq!(parse_push_header(&hdr).unwrap(), MAX_BLOB_BYTES);
    }

    #[test]
    fn verdict_lines_round_trip() {
        let ok = Verdict::Accepted {
            rig_id: "lab-rig-7".into(),
        };
        assert_eq!(ok.to_line(), "OK lab-rig-7\n");
        assert_eq!(Verdict::parse_line(&ok.to_line()).unwrap(), ok);
        for code in RejectCode::ALL {
            let v = Verdict::Rejected {
                code,
                message: format!("because {code}"),
            };
            let line = v.to_line();
            assert_eq!(line, format!("ERR {} because {}\n", code.as_str(), code.as_str()));
            assert_eq!(Verdict::parse_line(&line).unwrap(), v);
        }
    }

    #[test]
    fn verdict_message_stays_one_line() {
        let v = Verdict::Rejected {
            code: RejectCode::Storage,
            message: "disk\nfull\r".into(),
        };
        let line = v.to_line();
        assert_eq!(line.matches('\n').count(), 1);
        assert_eq!(line, "ERR STORAGE disk full \n");
        let long = Verdict::Rejected {
            code: RejectCode::Internal,
            message: "é".repeat(2000),
        };
        let line = long.to_line();
        assert!(line.len() <= MAX_VERDICT_LINE && line.ends_with('\n'));
        assert!(Verdict::parse_line(&line).is_ok());
    }

    #[test]
    fn unknown_code_and_garbage() {
        assert_eq!(
            Verdict::parse_line("ERR QUOTA over quota\n").unwrap(),
            Verdict::Rejected {
                code: RejectCode::Unknown,
                message: "QUOTA over quota".into()
            }
        );
        assert_eq!(
            Verdict::parse_line("ERR BUSY\n").unwrap(),
            Verdict::Rejected {
                code: RejectCode::Busy,
                message: String::new()
            }
        );
        for bad in ["", "OK\n", "OK \n", "OK a b\n", "HELLO\n", "ERR \n", "ok rig\n"] {
            assert!(
                matches!(Verdict::parse_line(bad), Err(Error::Protocol { .. })),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn blob_errors_map_to_bad_blob() {
        assert_eq!(
            RejectCode::for_error(&Error::BlobBadCrc {
                found: 1,
                computed: 2
            }),
            RejectCode::BadBlob
        );
        assert_eq!(
            RejectCode::for_error(&Error::InvalidParams { reason: "x".into() }),
            RejectCode::InvalidParams
        );
        let v = Verdict::from_error(&Error::BlobBadMagic { found: *b"abcd" });
        assert!(matches!(
            v,
            Verdict::Rejected {
                code: RejectCode::BadBlob,
                ..
            }
        ));
        assert!(!v.is_accepted());
    }
}
