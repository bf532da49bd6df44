//! The layout of a RAUC "plain" bundle, checked before any tool runs: a squashfs image, the
//! CMS signature over it (DER), and the signature's size as 8 bytes big-endian at the very end.
//! A truncated copy loses that trailer or part of the image, which this names plainly instead
//! of RAUC's "Signature size (…) exceeds bundle size".

use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use super::{Refusal, RefusalKind};

/// Where the parts of a bundle are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BundleLayout {
    /// The squashfs image: bytes `0..payload_len`.
    pub payload_len: u64,
    /// The CMS signature follows the image.
    pub signature_len: u64,
}

/// Largest signature RAUC accepts.
const MAX_SIGNATURE_BYTES: u64 = 64 * 1024;
/// squashfs's magic, little-endian "hsqs".
const SQUASHFS_MAGIC: &[u8; 4] = b"hsqs";

/// Checks the layout of the bundle at `path`.
pub fn inspect(path: &Path) -> Result<BundleLayout, Refusal> {
    let io = |e: std::io::Error| Refusal::new(RefusalKind::Failed, format!("reading the bundle failed: {e}"));
    let mut f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    let truncated = |what: String| {
        Refusal::new(
            RefusalKind::Truncated,
            format!("the bundle is truncated or corrupted ({what}); copy or download it again"),
        )
    };
    if len < 4096 + 8 {
        return Err(truncated(format!("only {len} bytes")));
    }
    let mut head = [0u8; 48];
    f.read_exact(&mut head).map_err(io)?;
    if &head[..4] != SQUASHFS_MAGIC {
        return Err(Refusal::new(
            RefusalKind::NotABundle,
            "this file is not an update bundle (no squashfs image at its start); \
             make one with `cargo xtask image bundle`",
        ));
    }
    let mut tail = [0u8; 8];
    f.seek(SeekFrom::End(-8)).map_err(io)?;
    f.read_exact(&mut tail).map_err(io)?;
    let signature_len = u64::from_be_bytes(tail);
    if signature_len == 0 || signature_len > MAX_SIGNATURE_BYTES || signature_len > len - 8 - 4096 {
        return Err(truncated("its end holds no signature".into()));
    }
    let payload_len = len - 8 - signature_len;
    let mut used = [0u8; 8];
    used.copy_from_slice(&head[40..48]);
    let bytes_used = u64::from_le_bytes(used);
    if bytes_used > payload_len {
        return Err(truncated(format!(
            "the image needs {bytes_used} bytes, {payload_len} are there"
        )));
    }
    if payload_len % 4096 != 0 {
        return Err(truncated(format!(
            "image size {payload_len} is not whole 4 KiB blocks"
        )));
    }
    Ok(BundleLayout {
        payload_len,
        signature_len,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bundle(payload_len: usize, bytes_used: u64, sig: &[u8]) -> Vec<u8> {
        let mut b = vec![0u8; payload_len];
        b[..4].copy_from_slice(SQUASHFS_MAGIC);
        b[40..48].copy_from_slice(&bytes_used.to_le_bytes());
        b.extend_from_slice(sig);
        b.extend_from_slice(&(sig.len() as u64).to_be_bytes());
        b
    }

    fn check(bytes: &[u8]) -> Result<BundleLayout, Refusal> {
        let p = std::env::temp_dir().join(format!(
            "irtrack-bundle-layout-{}-{}",
            std::process::id(),
            bytes.len()
        ));
        std::fs::write(&p, bytes).unwrap();
        let r = inspect(&p);
        std::fs::remove_file(&p).unwrap();
        r
    }

    #[test]
    fn layout_and_truncation() {
        let good = bundle(8192, 5000, &[0x30; 700]);
        assert_eq!(
            check(&good).unwrap(),
            BundleLayout {
                payload_len: 8192,
                signature_len: 700
            }
        );
        // Cut anywhere: the trailer is gone.
        let cut = &good[..good.len() - 100];
        assert_eq!(check(cut).unwrap_err().kind, RefusalKind::Truncated);
        // An image that claims more than is there.
        let short = bundle(8192, 9000, &[0x30; 700]);
        assert_eq!(check(&short).unwrap_err().kind, RefusalKind::Truncated);
        let mut text = b"hello".repeat(1000);
        text.extend_from_slice(&8u64.to_be_bytes());
        assert_eq!(check(&text).unwrap_err().kind, RefusalKind::NotABundle);
    }
}
