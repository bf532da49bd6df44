//! Sealed credential envelopes (docs/cluster-envelope.md): the golden bytes (fixed keys and
//! nonce, built independently by tests/python/envelope_vector.py with Python's
//! `cryptography`), and every refusal with its verdict code.

use ed25519_dalek::SigningKey;
use irtrack_cluster::ClusterError;
use irtrack_cluster::envelope::{self, BoxKey, Recipient, Refusal, Sealing, SecretKind, hex, parse_key_hex};

const PASSWORD: &str = "b0-pw-7Tq2Lm9Xz4Kc8Vn1Rb5W\n";

/// The envelope of the fixed inputs below, from envelope_vector.py.
const GOLDEN: &str = "4952434b01010262300700000000000000c086fd6a000000000faa684ed28867b97f4a6a2dee5df8ce974e76b7018e3f22a1c4cf2678570f207b0d47d93427f8311160781c7c733fd89f88970aef490d8aa0ee19a4cb8a1b144444444444444444444444442b000000117e3207a5e8c3100c1da9e3892b1235aacb6d93a620913ee460c3ef4ff97d0b0c3cfb97eae20a9a7ff8c8e3490f57fdd0736417f4471eb5478a7e07c45489e1435d7b9eca37cdc6e767e32b246d43845a471d60ba458cade3c451319abc7bfa0e51878ad606a24bdde1f304cd703a048b9704";

fn signer() -> SigningKey {
    SigningKey::from_bytes(&[0x11; 32])
}

fn board_key() -> BoxKey {
    BoxKey::from_secret_bytes([0x22; 32])
}

fn sealing(
    recipient: [u8; 32],
    board: &'static str,
    serial: u64,
    plaintext: &'static [u8],
) -> Sealing<'static> {
    Sealing {
        kind: SecretKind::BoardPassword,
        board,
        serial,
        created_unix_s: 1_795_000_000,
        recipient,
        plaintext,
    }
}

fn golden() -> Vec<u8> {
    envelope::seal_with(
        &sealing(board_key().public(), "b0", 7, PASSWORD.as_bytes()),
        &signer(),
        [0x33; 32],
        [0x44; 12],
    )
    .unwrap()
}

fn refusal(e: ClusterError) -> (Refusal, String) {
    match e {
        ClusterError::Envelope { why, reason } => (why, reason),
        other => panic!("not an envelope refusal: {other}"),
    }
}

#[test]
fn golden_envelope_bytes() {
    let bytes = golden();
    assert_eq!(hex(&bytes), GOLDEN, "the envelope differs from Python's");
    // The layout's offsets (docs/cluster-envelope.md) for board "b0": 7 + 2 + 8 + 8 + 32 + 32
    // + 12 = 101 header bytes + 4 length, 27 + 16 ciphertext, 8 key id, 64 signature.
    assert_eq!(bytes.len(), 105 + 43 + 8 + 64);
    assert_eq!(&bytes[..7], b"IRCK\x01\x01\x02");
    assert_eq!(&bytes[101..105], &43u32.to_le_bytes());
    let h = envelope::peek(&bytes).unwrap();
    assert_eq!(
        (h.board.as_str(), h.serial, h.kind),
        ("b0", 7, SecretKind::BoardPassword)
    );
    assert_eq!(h.key_id.to_string(), hex(&bytes[148..156]));
    let key = board_key();
    let trusted = [signer().verifying_key()];
    let opened = envelope::open(
        &bytes,
        &Recipient {
            board: "b0",
            key: &key,
            trusted: &trusted,
            last_serial: Some(6),
        },
    )
    .unwrap();
    assert_eq!(opened.secret, PASSWORD);
    assert!(
        !format!("{opened:?}").contains("7Tq2"),
        "Debug must not show the secret"
    );
}

#[test]
fn sealing_draws_fresh_randomness_and_hides_the_secret() {
    let key = board_key();
    let s = sealing(key.public(), "b0", 1, PASSWORD.as_bytes());
    let (a, b) = (
        envelope::seal(&s, &signer()).unwrap(),
        envelope::seal(&s, &signer()).unwrap(),
    );
    assert_ne!(a, b, "ephemeral key and nonce are random");
    for env in [&a, &b] {
        assert!(
            !env.windows(10).any(|w| w == &PASSWORD.as_bytes()[..10]),
            "the password is in clear"
        );
    }
    // A public key as /status shows it parses back.
    assert_eq!(parse_key_hex(&hex(&key.public())), Some(key.public()));
    assert_eq!(parse_key_hex("00"), None);
    // The key file round-trips.
    let p = std::path::Path::new("k");
    assert_eq!(
        BoxKey::parse_file(p, &key.file_text()).unwrap().public(),
        key.public()
    );
    assert!(BoxKey::parse_file(p, "irtrack-ed25519-secret v1\n00\n").is_err());
}

#[test]
fn refusals_name_the_problem() {
    let key = board_key();
    let trusted = [signer().verifying_key()];
    let to = |last: Option<u64>| Recipient {
        board: "b0",
        key: &key,
        trusted: &trusted,
        last_serial: last,
    };
    let good = golden();

    // Wrong signer: a key the board does not trust.
    let stranger = SigningKey::from_bytes(&[0x55; 32]);
    let s = sealing(key.public(), "b0", 8, PASSWORD.as_bytes());
    let e = envelope::seal_with(&s, &stranger, [0x33; 32], [0x44; 12]).unwrap();
    let (why, words) = refusal(envelope::open(&e, &to(None)).unwrap_err());
    assert_eq!((why, why.code()), (Refusal::Unauthorized, "UNAUTHORIZED"));
    assert!(words.contains("does not trust"), "{words}");

    // Tampered: every single byte flipped is refused (framing or signature), never opened.
    for i in 0..good.len() {
        let mut t = good.clone();
        t[i] ^= 0x01;
        let (why, words) = refusal(envelope::open(&t, &to(None)).unwrap_err());
        assert!(
            matches!(why, Refusal::Unauthorized | Refusal::Malformed),
            "byte {i}: {why:?} {words}"
        );
    }

    // For another board: sealed to b1's key (the PC pinned the wrong key) ...
    let other = BoxKey::from_secret_bytes([0x66; 32]);
    let s = sealing(other.public(), "b0", 8, PASSWORD.as_bytes());
    let e = envelope::seal_with(&s, &signer(), [0x33; 32], [0x44; 12]).unwrap();
    let (why, words) = refusal(envelope::open(&e, &to(None)).unwrap_err());
    assert_eq!((why, why.code()), (Refusal::OtherBoard, "RIG_MISMATCH"));
    assert!(words.contains("sealed to key"), "{words}");
    // ... or naming another board.
    let s = sealing(key.public(), "b1", 8, PASSWORD.as_bytes());
    let e = envelope::seal_with(&s, &signer(), [0x33; 32], [0x44; 12]).unwrap();
    let (why, words) = refusal(envelope::open(&e, &to(None)).unwrap_err());
    assert_eq!(why, Refusal::OtherBoard);
    assert!(
        words.contains("for board \"b1\", this is board \"b0\""),
        "{words}"
    );

    // Replayed or older: serial not above the last accepted.
    for last in [7, 8] {
        let (why, words) = refusal(envelope::open(&good, &to(Some(last))).unwrap_err());
        assert_eq!((why, why.code()), (Refusal::Replayed, "ROLLBACK"));
        assert!(
            words.contains(&format!(
                "serial 7 is not newer than the last accepted envelope's ({last})"
            )),
            "{words}"
        );
    }

    // A secret that is no password file.
    let s = sealing(key.public(), "b0", 9, b"short\n");
    let e = envelope::seal_with(&s, &signer(), [0x33; 32], [0x44; 12]).unwrap();
    let (why, words) = refusal(envelope::open(&e, &to(None)).unwrap_err());
    assert_eq!((why, why.code()), (Refusal::Invalid, "INVALID_PARAMS"));
    assert!(words.contains("16..=128") && !words.contains("short"), "{words}");

    // Truncated, extended, not an envelope.
    let extended = [good.as_slice(), &[0u8][..]].concat();
    let bads: [&[u8]; 3] = [&good[..good.len() - 1], &extended, &b"IRPP\x01\x00\x00\x00x"[..]];
    for bad in bads {
        let (why, _) = refusal(envelope::open(bad, &to(None)).unwrap_err());
        assert_eq!((why, why.code()), (Refusal::Malformed, "BAD_BLOB"));
    }
}
