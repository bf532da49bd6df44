//! Parameter push protocol between `host-tools push-params` (client) and irtrackd (server).
//! Spec: docs/param-protocol.md.
//!
//! One exchange per TCP connection: the client sends `b"IRPP"`, the blob length as u32 LE and
//! the blob; the server answers with exactly one ASCII line, `OK <rig_id>\n` or
//! `ERR <CODE> <message>\n`, and closes.

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
/// Largest blob a server accepts (1 MiB; real rigs are well under 4 KiB).
pub const MAX_BLOB_BYTES: usize = 1 << 20;
/// Longest verdict line, newline included; longer messages are cut by [`Verdict::to_line`].
pub const MAX_VERDICT_LINE: usize = 1024;

const PROTOCOL: &str = "param-push";

/// Builds a complete push request for `blob`.
pub fn encode_push(blob: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(PUSH_HEADER_LEN + blob.len());
    out.extend_from_slice(&PUSH_MAGIC);
    // Blobs over MAX_BLOB_BYTES are refused by servers anyway; saturate instead of wrapping.
    let len = u32::try_from(blob.len()).unwrap_or(u32::MAX);
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(blob);
    out
}

/// Parses a push header and returns the announced blob length.
///
/// Errors: [`Error::Protocol`] for a wrong magic or a zero length, [`Error::MessageTooLarge`]
/// for a length over [`MAX_BLOB_BYTES`] (answer it with [`RejectCode::TooLarge`]).
pub fn parse_push_header(hdr: &[u8; PUSH_HEADER_LEN]) -> Result<usize> {
    if hdr[..4] != PUSH_MAGIC {
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
    /// Anything else on the server side (`INTERNAL`).
    Internal,
    /// A code this build does not know (forward compatibility; the raw code starts the message).
    Unknown,
}

impl RejectCode {
    const ALL: [RejectCode; 9] = [
        RejectCode::BadBlob,
        RejectCode::InvalidParams,
        RejectCode::RigMismatch,
        RejectCode::TooLarge,
        RejectCode::Storage,
        RejectCode::Unauthorized,
        RejectCode::Protocol,
        RejectCode::Busy,
        RejectCode::Internal,
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
