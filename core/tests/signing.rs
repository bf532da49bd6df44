//! Signed parameter blobs: golden vector, round trip, tampering, unknown keys, policy.

use irtrack_core::Error;
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::crc::Crc32;
use irtrack_core::params::{
    BLOB_FLAG_SIGNED, BLOB_HEADER_LEN, BLOB_SIGNATURE_TRAILER_LEN, BlobHeader, CameraParams, RigParams,
};
use irtrack_core::signing::{
    self, KeyId, SignaturePolicy, SignatureStatus, SigningKey, VerifyingKey, decode_without_verifying,
    verify_blob,
};

/// RFC 8032 section 7.1, TEST 1: secret seed and public key.
const RFC_SEED: &str = "9d61b19deffd5a60ba844af492ec2cc44449c5697b326919703bac031cae7f60";
const RFC_PUBLIC: &str = "d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a";
/// RFC 8032 TEST 1 signature of the empty message.
const RFC_EMPTY_SIG: &str = "e5564300c360ac729086e2cc806e828a84877f1eb8e5d974d873e06522490155\
                             5fb8821590a33bacc61e39701cf9b46bd25bf5f0595bbe24655141438e7a100b";

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
        .collect()
}

fn rfc_key() -> SigningKey {
    SigningKey::from_bytes(&unhex(RFC_SEED).try_into().unwrap())
}

fn other_key() -> SigningKey {
    SigningKey::from_bytes(&[0x5a; 32])
}

fn rig() -> RigParams {
    let cam = |t_mm: [f64; 3]| CameraParams {
        model: CameraModel {
            intrinsics: Intrinsics {
                fx_px: 800.0,
                fy_px: 800.0,
                cx_px: 319.5,
                cy_px: 239.5,
            },
            distortion: Distortion {
                k1: -0.25,
                k2: 0.0,
                p1: 0.0,
                p2: 0.0,
                k3: 0.0,
            },
            image_size: ImageSize {
                width_px: 640,
                height_px: 480,
            },
        },
        cam_from_cam0: RigidTransform {
            t_mm,
            ..RigidTransform::IDENTITY
        },
    };
    RigParams {
        rig_id: "signed-rig".into(),
        created_unix_s: 1_700_000_000,
        cameras: vec![cam([0.0; 3]), cam([-150.0, 0.0, 0.0])],
        world_from_cam0: None,
        tools: vec![],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

/// Recomputes the header CRC the way an attacker who edits the body would.
fn fix_crc(blob: &mut [u8]) {
    let h = BlobHeader::parse_allow_signed(blob).unwrap();
    let mut c = Crc32::new();
    c.update(&blob[..12]);
    c.update(&blob[BLOB_HEADER_LEN..h.signed_part_len()]);
    blob[12..16].copy_from_slice(&c.finish().to_le_bytes());
}

const REQUIRE: SignaturePolicy = SignaturePolicy::RequireSigned;
const ALLOW: SignaturePolicy = SignaturePolicy::AllowUnsigned;

#[test]
fn rfc8032_test1_key_and_signature() {
    // Checks the library and our use of it against the RFC, independently of our format.
    let key = rfc_key();
    assert_eq!(key.verifying_key().to_bytes().to_vec(), unhex(RFC_PUBLIC));
    use ed25519_dalek::Signer as _;
    assert_eq!(key.sign(b"").to_bytes().to_vec(), unhex(RFC_EMPTY_SIG));
}

/// Golden signed blob, cross-checked outside Rust (docs/param-blob.md, "Golden signed vector"):
/// key id = first 8 bytes of `hashlib.sha512(public).digest()` (Python), signature =
/// `openssl pkeyutl -sign -rawin` (OpenSSL 3.0) over header + body with the RFC seed.
/// CRC-32 cross-checked with Python's `zlib.crc32` over bytes 0..12 + body.
const GOLDEN_KEY_ID: &str = "0e02a50225b4baaa";
const GOLDEN_SIG: &str = "00abddb5df036a0f5e91200028365b9cb6ef234adbc33df83fbf4e4ca8c03565\
                          d8bde40410cb7a4a7658161e3a3313461c6e937f11121cfd74141629cfb50c07";
const GOLDEN_LEN: usize = 451;
const GOLDEN_CRC: u32 = 0x2afe_3050;

#[test]
fn golden_signed_blob() {
    let rig = rig();
    let blob = rig.to_signed_blob(&rfc_key()).unwrap();
    let unsigned = rig.to_blob().unwrap();
    let n = unsigned.len();
    assert_eq!(blob.len(), GOLDEN_LEN);
    // Header: magic, version 1, flags = signed, same body length, CRC over the flagged header.
    assert_eq!(&blob[..6], b"IRPB\x01\x00");
    assert_eq!(u16::from_le_bytes([blob[6], blob[7]]), BLOB_FLAG_SIGNED);
    assert_eq!(&blob[8..12], &unsigned[8..12]);
    assert_eq!(u32::from_le_bytes(blob[12..16].try_into().unwrap()), GOLDEN_CRC);
    // Body identical to the unsigned encoding.
    assert_eq!(&blob[16..n], &unsigned[16..]);
    assert_eq!(blob.len(), n + BLOB_SIGNATURE_TRAILER_LEN);
    assert_eq!(blob[n..n + 8].to_vec(), unhex(GOLDEN_KEY_ID));
    assert_eq!(blob[n + 8..].to_vec(), unhex(GOLDEN_SIG));
    // Deterministic: signing again gives the same bytes.
    assert_eq!(rig.to_signed_blob(&rfc_key()).unwrap(), blob);
}

#[test]
fn round_trip_signed() {
    let rig = rig();
    let key = rfc_key();
    let blob = rig.to_signed_blob(&key).unwrap();
    let trusted = [other_key().verifying_key(), key.verifying_key()];
    for policy in [REQUIRE, ALLOW] {
        let (got, status) = verify_blob(&blob, &trusted, policy).unwrap();
        assert_eq!(got, rig);
        assert_eq!(
            status,
            SignatureStatus::Signed {
                key_id: KeyId::of(&key.verifying_key())
            }
        );
    }
    // The parameter-set id does not depend on signing.
    assert_eq!(got_crc(&blob), rig.params_crc().unwrap());
    let (decoded, key_id) = decode_without_verifying(&blob).unwrap();
    assert_eq!(decoded, rig);
    assert_eq!(key_id, Some(KeyId::of(&key.verifying_key())));
}

fn got_crc(blob: &[u8]) -> u32 {
    verify_blob(blob, &[rfc_key().verifying_key()], REQUIRE)
        .unwrap()
        .0
        .params_crc()
        .unwrap()
}

#[test]
fn tampered_body_with_fixed_crc_is_bad_signature() {
    let key = rfc_key();
    let trusted = [key.verifying_key()];
    let key_id = KeyId::of(&key.verifying_key());
    let blob = rig().to_signed_blob(&key).unwrap();
    let body_end = blob.len() - BLOB_SIGNATURE_TRAILER_LEN;
    // Every body byte, changed with the CRC fixed up: the signature must catch all of them.
    let mut caught = 0;
    for i in BLOB_HEADER_LEN..body_end {
        let mut b = blob.clone();
        b[i] ^= 0x01;
        fix_crc(&mut b);
        assert_eq!(
            verify_blob(&b, &trusted, ALLOW),
            Err(Error::BlobBadSignature { key_id }),
            "byte {i}"
        );
        caught += 1;
    }
    assert!(caught > 100);
    // Without fixing the CRC the cheaper check answers first.
    let mut b = blob.clone();
    b[20] ^= 0x80;
    assert!(matches!(
        verify_blob(&b, &trusted, REQUIRE),
        Err(Error::BlobBadCrc { .. })
    ));
    // A changed signature byte.
    let mut b = blob.clone();
    *b.last_mut().unwrap() ^= 0x40;
    assert_eq!(
        verify_blob(&b, &trusted, REQUIRE),
        Err(Error::BlobBadSignature { key_id })
    );
}

#[test]
fn stripping_the_signature_does_not_help() {
    // An attacker removes the trailer, clears the flag and fixes the CRC: a valid unsigned
    // blob, refused when signatures are required.
    let key = rfc_key();
    let mut b = rig().to_signed_blob(&key).unwrap();
    b.truncate(b.len() - BLOB_SIGNATURE_TRAILER_LEN);
    b[6] = 0;
    fix_crc(&mut b);
    assert_eq!(b, rig().to_blob().unwrap());
    assert_eq!(
        verify_blob(&b, &[key.verifying_key()], REQUIRE),
        Err(Error::BlobUnsigned)
    );
}

#[test]
fn unknown_key_rejected_even_in_development_mode() {
    let blob = rig().to_signed_blob(&other_key()).unwrap();
    let key_id = KeyId::of(&other_key().verifying_key());
    for policy in [REQUIRE, ALLOW] {
        assert_eq!(
            verify_blob(&blob, &[rfc_key().verifying_key()], policy),
            Err(Error::BlobUnknownKey { key_id, trusted: 1 })
        );
    }
    assert_eq!(
        verify_blob(&blob, &[], REQUIRE),
        Err(Error::BlobUnknownKey { key_id, trusted: 0 })
    );
    // The message names the key, so an operator can tell which key file is missing.
    let msg = verify_blob(&blob, &[], REQUIRE).unwrap_err().to_string();
    assert!(msg.contains(&key_id.to_string()), "{msg}");
}

#[test]
fn key_id_of_a_trusted_key_on_a_foreign_signature() {
    // A forger copies a trusted key id into the trailer of his own signature.
    let trusted_key = rfc_key();
    let key_id = KeyId::of(&trusted_key.verifying_key());
    let mut b = rig().to_signed_blob(&other_key()).unwrap();
    let n = b.len() - BLOB_SIGNATURE_TRAILER_LEN;
    b[n..n + 8].copy_from_slice(&key_id.0);
    assert_eq!(
        verify_blob(&b, &[trusted_key.verifying_key()], REQUIRE),
        Err(Error::BlobBadSignature { key_id })
    );
}

#[test]
fn unsigned_policy() {
    let rig = rig();
    let blob = rig.to_blob().unwrap();
    let trusted = [rfc_key().verifying_key()];
    assert_eq!(verify_blob(&blob, &trusted, REQUIRE), Err(Error::BlobUnsigned));
    assert_eq!(
        verify_blob(&blob, &trusted, ALLOW),
        Ok((rig.clone(), SignatureStatus::UnsignedAccepted))
    );
    assert_eq!(verify_blob(&blob, &[], ALLOW).unwrap().0, rig);
    assert_eq!(decode_without_verifying(&blob), Ok((rig, None)));
}

#[test]
fn truncated_or_extended_trailer() {
    let key = rfc_key();
    let trusted = [key.verifying_key()];
    let blob = rig().to_signed_blob(&key).unwrap();
    for cut in [1, 8, 40, 71, 72] {
        let b = &blob[..blob.len() - cut];
        assert_eq!(
            verify_blob(b, &trusted, ALLOW),
            Err(Error::BlobTruncated {
                needed: blob.len(),
                got: blob.len() - cut
            }),
            "cut {cut}"
        );
        assert!(decode_without_verifying(b).is_err());
    }
    let mut longer = blob.clone();
    longer.push(0);
    assert_eq!(
        verify_blob(&longer, &trusted, ALLOW),
        Err(Error::BlobTrailingBytes { extra: 1 })
    );
}

#[test]
fn plain_decoder_refuses_signed_blobs() {
    // RigParams::from_blob cannot check signatures, so it must not look past them.
    let blob = rig().to_signed_blob(&rfc_key()).unwrap();
    assert!(matches!(
        RigParams::from_blob(&blob),
        Err(Error::BlobUnsupportedFlags { flags: 1, .. })
    ));
    assert!(BlobHeader::parse(&blob).is_err());
    assert!(BlobHeader::parse_allow_signed(&blob).unwrap().is_signed());
}

#[test]
fn public_key_file_round_trip_through_verification() {
    let key = rfc_key();
    let text = signing::public_key_file(&key.verifying_key());
    let parsed: VerifyingKey = signing::parse_public_key_file(&text).unwrap();
    let secret = signing::parse_secret_key_file(&signing::secret_key_file(&key)).unwrap();
    let blob = rig().to_signed_blob(&secret).unwrap();
    assert!(verify_blob(&blob, &[parsed], REQUIRE).is_ok());
    assert!(text.starts_with("irtrack-ed25519-public v1\n"));
    assert!(text.ends_with(&format!("{RFC_PUBLIC}\n")));
}
