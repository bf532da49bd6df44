//! The A/B image's boot counters as files (docs/updates.md, "Boot counters"): a redundant U-Boot
//! environment in libubootenv's layout, two copies of [`ENV_BYTES`] bytes in two files on the
//! boot partition, which `boot.scr` and `fw_setenv` both read and write.
//!
//! Each copy: CRC32 (IEEE, little-endian) of the data, one flags byte, then the data —
//! `name=value` strings each ended by a NUL, an empty string after the last, zeros to the end.
//! A copy is valid when it is whole and its CRC matches; of two valid copies the higher flags
//! byte wins, except that 0 wins over 255 (the counter wrapped); equal flags: copy 0. A writer
//! writes the copy that did not win, with the winner's flags + 1.
//!
//! The image build writes the first copies with this; the update test reads and corrupts them
//! between boots to check that U-Boot and libubootenv agree.

use std::collections::BTreeMap;

use anyhow::{Result, bail};

/// Size of each copy (fw_env.config, boot.cmd).
pub const ENV_BYTES: usize = 0x4000;
/// The two copies' files on the boot partition: copy 0, copy 1.
pub const COPY_FILES: [&str; 2] = ["uboot.env", "uboot-redund.env"];
/// CRC (4 bytes) and flags (1 byte) before the data.
const HEADER: usize = 5;

/// CRC-32 as zlib and U-Boot compute it (reflected, polynomial 0xEDB88320).
pub fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// One copy with `vars` (in this order) and `flags`.
pub fn encode(vars: &[(&str, &str)], flags: u8) -> Result<Vec<u8>> {
    let mut data = Vec::with_capacity(ENV_BYTES - HEADER);
    for (name, value) in vars {
        if name.is_empty() || name.contains(['=', '\0']) || value.contains('\0') {
            bail!("boot environment entry {name:?}={value:?}: names need no '=' or NUL, values no NUL");
        }
        data.extend_from_slice(name.as_bytes());
        data.push(b'=');
        data.extend_from_slice(value.as_bytes());
        data.push(0);
    }
    // The empty string that ends the list, and room for it within the copy.
    if data.len() + 1 > ENV_BYTES - HEADER {
        bail!(
            "boot environment of {} bytes does not fit a {ENV_BYTES}-byte copy",
            data.len()
        );
    }
    data.resize(ENV_BYTES - HEADER, 0);
    let mut out = Vec::with_capacity(ENV_BYTES);
    out.extend_from_slice(&crc32(&data).to_le_bytes());
    out.push(flags);
    out.extend_from_slice(&data);
    Ok(out)
}

/// One copy as read back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EnvCopy {
    /// Whole, with a matching CRC.
    pub valid: bool,
    /// Its flags byte (0 when the file is too short to have one).
    pub flags: u8,
    /// Its variables (empty unless valid).
    pub vars: BTreeMap<String, String>,
    /// Why it is not valid.
    pub problem: Option<String>,
}

impl EnvCopy {
    /// A variable's value.
    pub fn get(&self, name: &str) -> Option<&str> {
        self.vars.get(name).map(String::as_str)
    }
}

/// Reads one copy (any length: a truncated file is simply not valid).
pub fn decode(bytes: &[u8]) -> EnvCopy {
    let flags = bytes.get(4).copied().unwrap_or(0);
    let invalid = |problem: String| EnvCopy {
        valid: false,
        flags,
        vars: BTreeMap::new(),
        problem: Some(problem),
    };
    if bytes.len() != ENV_BYTES {
        return invalid(format!("{} bytes, not {ENV_BYTES}", bytes.len()));
    }
    let stored = u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
    let data = &bytes[HEADER..];
    let actual = crc32(data);
    if stored != actual {
        return invalid(format!("CRC {stored:08x} stored, {actual:08x} computed"));
    }
    let mut vars = BTreeMap::new();
    for entry in data.split(|&b| b == 0).take_while(|e| !e.is_empty()) {
        let text = String::from_utf8_lossy(entry);
        if let Some((k, v)) = text.split_once('=') {
            vars.insert(k.to_owned(), v.to_owned());
        }
    }
    EnvCopy {
        valid: true,
        flags,
        vars,
        problem: None,
    }
}

/// Which copy counts (0 or 1), by libubootenv's rule; `None` when neither is valid.
pub fn winner(c0: &EnvCopy, c1: &EnvCopy) -> Option<usize> {
    match (c0.valid, c1.valid) {
        (false, false) => None,
        (true, false) => Some(0),
        (false, true) => Some(1),
        (true, true) => Some(match (c0.flags, c1.flags) {
            (0xFF, 0) => 1,
            (0, 0xFF) => 0,
            (f0, f1) if f1 > f0 => 1,
            _ => 0,
        }),
    }
}

/// The flags a writer gives the copy it writes after `winner_flags`.
pub fn next_flags(winner_flags: u8) -> u8 {
    winner_flags.wrapping_add(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32_is_the_zlib_crc() {
        // The standard check value of CRC-32/ISO-HDLC.
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn a_copy_has_crc_flags_and_nul_ended_strings() {
        let copy = encode(&[("BOOT_ORDER", "B A"), ("BOOT_A_LEFT", "0")], 7).unwrap();
        assert_eq!(copy.len(), ENV_BYTES);
        // Golden bytes: the header and the start of the data.
        let mut data = b"BOOT_ORDER=B A\0BOOT_A_LEFT=0\0".to_vec();
        data.resize(ENV_BYTES - 5, 0);
        let crc = crc32(&data);
        assert_eq!(&copy[..4], &crc.to_le_bytes());
        assert_eq!(copy[4], 7);
        assert_eq!(&copy[5..34], b"BOOT_ORDER=B A\0BOOT_A_LEFT=0\0");
        assert!(copy[34..].iter().all(|&b| b == 0));
        let back = decode(&copy);
        assert!(back.valid, "{back:?}");
        assert_eq!(back.flags, 7);
        assert_eq!(back.get("BOOT_ORDER"), Some("B A"));
        assert_eq!(back.get("BOOT_A_LEFT"), Some("0"));
        assert_eq!(back.vars.len(), 2);
    }

    #[test]
    fn the_initial_copy_matches_a_fixed_vector() {
        // BOOT_ORDER=A, A 3, B 0 with flags 1: what the image starts with. The CRC was
        // cross-checked with `mkenvimage -r -p 0 -s 0x4000` (see the next test).
        let copy = encode(
            &[("BOOT_ORDER", "A"), ("BOOT_A_LEFT", "3"), ("BOOT_B_LEFT", "0")],
            1,
        )
        .unwrap();
        let mut data = b"BOOT_ORDER=A\0BOOT_A_LEFT=3\0BOOT_B_LEFT=0\0".to_vec();
        data.resize(ENV_BYTES - 5, 0);
        assert_eq!(
            u32::from_le_bytes([copy[0], copy[1], copy[2], copy[3]]),
            crc32(&data)
        );
        assert_eq!(copy[4], 1);
    }

    #[test]
    fn copies_agree_with_mkenvimage() {
        // U-Boot's own tool writes the same layout for a redundant environment (flags 1).
        let dir = std::env::temp_dir().join(format!("xtask-bootenv-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let text = dir.join("env.txt");
        std::fs::write(&text, "BOOT_ORDER=A\nBOOT_A_LEFT=3\nBOOT_B_LEFT=0\n").unwrap();
        let out = dir.join("env.bin");
        // u-boot-tools is installed by `cargo xtask setup`.
        let ok = std::process::Command::new("mkenvimage")
            .args(["-r", "-p", "0", "-s", "0x4000", "-o"])
            .arg(&out)
            .arg(&text)
            .status()
            .expect("mkenvimage (u-boot-tools; run `cargo xtask setup`)");
        assert!(ok.success());
        let theirs = std::fs::read(&out).unwrap();
        let ours = encode(
            &[("BOOT_ORDER", "A"), ("BOOT_A_LEFT", "3"), ("BOOT_B_LEFT", "0")],
            1,
        )
        .unwrap();
        assert_eq!(&theirs[..5], &ours[..5], "CRC and flags");
        assert_eq!(theirs, ours);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn broken_copies_are_not_valid() {
        let good = encode(&[("BOOT_ORDER", "A B")], 3).unwrap();
        let mut flipped = good.clone();
        flipped[100] ^= 0x40;
        let c = decode(&flipped);
        assert!(!c.valid && c.problem.as_deref().unwrap().contains("CRC"), "{c:?}");
        assert!(c.vars.is_empty());
        let short = decode(&good[..1000]);
        assert!(!short.valid);
        assert_eq!(short.problem.as_deref(), Some("1000 bytes, not 16384"));
        assert!(!decode(&[]).valid);
        // A torn write: the first half of a newer copy over an older one. (Its data must reach
        // past the tear: bytes the new copy shares with the old one tear nothing.)
        let pad = "x".repeat(ENV_BYTES * 3 / 4);
        let newer = encode(&[("BOOT_ORDER", "B A"), ("PAD", &pad)], 4).unwrap();
        let mut torn = good.clone();
        torn[..ENV_BYTES / 2].copy_from_slice(&newer[..ENV_BYTES / 2]);
        assert!(!decode(&torn).valid);
        assert!(decode(&newer).valid);
        assert!(encode(&[("A=B", "1")], 0).is_err());
        assert!(encode(&[("BIG", &"x".repeat(ENV_BYTES))], 0).is_err());
    }

    #[test]
    fn the_newest_valid_copy_wins_as_libubootenv_decides() {
        let with = |flags: u8, valid: bool| {
            let mut c = decode(&encode(&[("BOOT_ORDER", "A")], flags).unwrap());
            c.valid = valid;
            c
        };
        assert_eq!(winner(&with(1, true), &with(2, true)), Some(1));
        assert_eq!(winner(&with(9, true), &with(2, true)), Some(0));
        assert_eq!(winner(&with(5, true), &with(5, true)), Some(0));
        assert_eq!(winner(&with(0xFF, true), &with(0, true)), Some(1));
        assert_eq!(winner(&with(0, true), &with(0xFF, true)), Some(0));
        assert_eq!(winner(&with(200, true), &with(3, false)), Some(0));
        assert_eq!(winner(&with(3, false), &with(1, true)), Some(1));
        assert_eq!(winner(&with(3, false), &with(4, false)), None);
        assert_eq!(next_flags(0xFF), 0);
        assert_eq!(next_flags(6), 7);
    }
}
