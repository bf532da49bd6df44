//! Signed parameters from the command line: keygen, convert-params/show-params with keys, and
//! push-params --sign-key against a fake irtrackd endpoint that verifies with core's
//! `signing::verify_blob`, as the device does.

mod common;

use std::io::{Read, Write};
use std::net::TcpListener;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::thread;

use common::*;
use irtrack_core::Error;
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::param_wire::{self, Verdict};
use irtrack_core::params::{CameraParams, RigParams};
use irtrack_core::signing::{self, KeyId, SignaturePolicy, SignatureStatus, VerifyingKey, verify_blob};

fn tmp_dir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("irtrack-signing-cli-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn rig() -> RigParams {
    let cam = |t_mm: [f64; 3]| CameraParams {
        model: CameraModel {
            intrinsics: Intrinsics {
                fx_px: 900.0,
                fy_px: 900.5,
                cx_px: 640.0,
                cy_px: 360.0,
            },
            distortion: Distortion {
                k1: -0.1,
                k2: 0.01,
                p1: 0.0,
                p2: 0.0,
                k3: 0.0,
            },
            image_size: ImageSize {
                width_px: 1280,
                height_px: 720,
            },
        },
        cam_from_cam0: RigidTransform {
            t_mm,
            ..RigidTransform::IDENTITY
        },
    };
    RigParams {
        rig_id: "signed-pair".into(),
        created_unix_s: 1_720_000_000,
        cameras: vec![cam([0.0; 3]), cam([-200.0, 0.0, 0.0])],
        world_from_cam0: None,
        tools: vec![],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

/// Runs keygen for `dir/name`; returns the (secret, public) paths.
fn keygen(dir: &Path, name: &str) -> (PathBuf, PathBuf) {
    let o = host_tools(&["keygen", "--out", p(&dir.join(name))]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    (dir.join(format!("{name}.key")), dir.join(format!("{name}.pub")))
}

fn public(path: &Path) -> VerifyingKey {
    signing::parse_public_key_file(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn keygen_writes_private_pair_and_refuses_overwrite() {
    let dir = tmp_dir("keygen");
    let (sec, publ) = keygen(&dir, "lab");
    let mode = std::fs::metadata(&sec).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "secret key mode {mode:o}");
    let secret = signing::parse_secret_key_file(&std::fs::read_to_string(&sec).unwrap()).unwrap();
    let pk = public(&publ);
    assert_eq!(secret.verifying_key(), pk);

    // Refuses to overwrite; both files unchanged.
    let o = host_tools(&["keygen", "--out", p(&dir.join("lab"))]);
    let (_, err) = text(&o);
    assert!(!o.status.success());
    assert!(err.contains("already exists") && err.contains("--force"), "{err}");
    assert_eq!(public(&publ), pk);

    // --force makes a fresh, different pair (keys come from the OS RNG).
    let o = host_tools(&["keygen", "--out", p(&dir.join("lab")), "--force"]);
    assert!(o.status.success(), "{:?}", text(&o));
    let pk2 = public(&publ);
    assert_ne!(pk2, pk);
    let (out, _) = text(&o);
    assert!(out.contains(&format!("key id {}", KeyId::of(&pk2))), "{out}");
    assert_eq!(
        std::fs::metadata(&sec).unwrap().permissions().mode() & 0o777,
        0o600
    );
}

#[test]
fn convert_signs_and_show_reports_verification() {
    let dir = tmp_dir("convert");
    let (sec, publ) = keygen(&dir, "k1");
    let (_, other_pub) = keygen(&dir, "k2");
    let unsigned = dir.join("rig.irp");
    std::fs::write(&unsigned, rig().to_blob().unwrap()).unwrap();
    let signed = dir.join("rig-signed.irp");
    let o = host_tools(&["convert-params", p(&unsigned), p(&signed), "--sign-key", p(&sec)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    let id = KeyId::of(&public(&publ));
    assert!(out.contains(&format!("signed by key {id}")), "{out}");

    let bytes = std::fs::read(&signed).unwrap();
    let (got, status) = verify_blob(&bytes, &[public(&publ)], SignaturePolicy::RequireSigned).unwrap();
    assert_eq!(got, rig());
    assert_eq!(status, SignatureStatus::Signed { key_id: id });

    // show-params: unverified without keys, verified with the right key, INVALID with another.
    let show = |extra: &[&str]| {
        let mut args = vec!["show-params", p(&signed)];
        args.extend_from_slice(extra);
        let o = host_tools(&args);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{out}\n{err}");
        out
    };
    assert!(show(&[]).contains(&format!("signature:    key {id}, not verified")));
    assert!(show(&["--trusted-key", p(&publ)]).contains(&format!("signature:    key {id}, verified")));
    let wrong = show(&["--trusted-key", p(&other_pub)]);
    assert!(
        wrong.contains("signature:    INVALID") && wrong.contains("not one of the 1 trusted keys"),
        "{wrong}"
    );
    let plain = host_tools(&["show-params", p(&unsigned)]);
    assert!(text(&plain).0.contains("signature:    none (unsigned blob)"));
    // The parameter-set id is the same signed or not.
    let crc_line = format!("params CRC:   {:08x}", rig().params_crc().unwrap());
    assert!(show(&[]).contains(&crc_line));
    assert!(text(&plain).0.contains(&crc_line));

    // YAML cannot carry a signature; the public key is not a secret key.
    let o = host_tools(&[
        "convert-params",
        p(&unsigned),
        p(&dir.join("x.yaml")),
        "--sign-key",
        p(&sec),
    ]);
    assert!(!o.status.success() && text(&o).1.contains("cannot carry a signature"));
    let o = host_tools(&[
        "convert-params",
        p(&unsigned),
        p(&dir.join("x.irp")),
        "--sign-key",
        p(&publ),
    ]);
    let (_, err) = text(&o);
    assert!(
        !o.status.success() && err.contains("irtrack-ed25519-public v1"),
        "{err}"
    );

    // Invalid parameters are never signed, even with --force.
    let mut bad = rig();
    bad.cameras.truncate(1);
    let bad_path = dir.join("bad.irp");
    std::fs::write(&bad_path, bad.to_blob().unwrap()).unwrap();
    let o = host_tools(&[
        "convert-params",
        p(&bad_path),
        p(&dir.join("bad-signed.irp")),
        "--force",
        "--sign-key",
        p(&sec),
    ]);
    assert!(!o.status.success() && text(&o).1.contains("refusing to sign"));
    assert!(!dir.join("bad-signed.irp").exists());
}

#[test]
fn tampered_signed_file_is_reported_invalid() {
    let dir = tmp_dir("tamper");
    let (sec, publ) = keygen(&dir, "k");
    let key = signing::parse_secret_key_file(&std::fs::read_to_string(&sec).unwrap()).unwrap();
    let mut rig2 = rig();
    let blob = rig2.to_signed_blob(&key).unwrap();
    // Same length, other content: splice a different body under the old signature.
    rig2.created_unix_s += 1;
    let other = rig2.to_signed_blob(&key).unwrap();
    let mut forged = other[..other.len() - 72].to_vec();
    forged.extend_from_slice(&blob[blob.len() - 72..]);
    let path = dir.join("forged.irp");
    std::fs::write(&path, &forged).unwrap();
    let o = host_tools(&["show-params", p(&path), "--trusted-key", p(&publ)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{err}");
    assert!(
        out.contains("signature:    INVALID") && out.contains("does not verify"),
        "{out}"
    );
}

/// irtrackd's parameter endpoint for one connection, checking signatures like the device:
/// `verify_blob` under `policy`, then `validate`; signature problems answer UNAUTHORIZED.
fn serve_one(
    listener: TcpListener,
    trusted: Vec<VerifyingKey>,
    policy: SignaturePolicy,
) -> thread::JoinHandle<Result<(RigParams, SignatureStatus), Error>> {
    serve_push_once(
        listener,
        move |blob| {
            let result =
                verify_blob(blob, &trusted, policy).and_then(|(r, st)| r.validate().map(|()| (r, st)));
            let verdict = match &result {
                Ok((r, _)) => Verdict::Accepted {
                    rig_id: r.rig_id.clone(),
                },
                Err(e) => signing::verdict_for(e),
            };
            (verdict, result)
        },
        Err(Error::Protocol {
            protocol: "param",
            reason: "bad push header".into(),
        }),
    )
}

fn push(args: &[&str]) -> (bool, String, String) {
    let mut all = vec!["push-params", "--retries", "0", "--timeout-s", "10"];
    all.extend_from_slice(args);
    let o = host_tools(&all);
    let (out, err) = text(&o);
    (o.status.success(), out, err)
}

#[test]
fn push_signed_accepted_unsigned_unauthorized() {
    let dir = tmp_dir("push");
    let (sec, publ) = keygen(&dir, "ops");
    let (stranger_sec, _) = keygen(&dir, "stranger");
    let file = dir.join("rig.irp");
    std::fs::write(&file, rig().to_blob().unwrap()).unwrap();
    let trusted = vec![public(&publ)];
    let id = KeyId::of(&trusted[0]);

    // Signed with a trusted key: accepted, and the server saw a verified signature.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = serve_one(listener, trusted.clone(), SignaturePolicy::RequireSigned);
    let (ok, out, err) = push(&["--to", &addr, "--sign-key", p(&sec), p(&file)]);
    assert!(ok, "{out}\n{err}");
    assert!(out.contains(&format!("signed by key {id}")), "{out}");
    assert!(out.contains("rig signed-pair is active"), "{out}");
    assert_eq!(
        server.join().unwrap(),
        Ok((rig(), SignatureStatus::Signed { key_id: id }))
    );

    // Unsigned: refused with UNAUTHORIZED and a reason; the command fails.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = serve_one(listener, trusted.clone(), SignaturePolicy::RequireSigned);
    let (ok, out, err) = push(&["--to", &addr, p(&file)]);
    assert!(!ok, "{out}");
    assert!(
        err.contains("UNAUTHORIZED") && err.contains("not signed"),
        "{err}"
    );
    assert_eq!(server.join().unwrap(), Err(Error::BlobUnsigned));

    // Signed by a key the device does not trust.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = serve_one(listener, trusted.clone(), SignaturePolicy::RequireSigned);
    let (ok, _, err) = push(&["--to", &addr, "--sign-key", p(&stranger_sec), p(&file)]);
    assert!(!ok);
    assert!(
        err.contains("UNAUTHORIZED") && err.contains("not one of the 1 trusted keys"),
        "{err}"
    );
    assert!(matches!(
        server.join().unwrap(),
        Err(Error::BlobUnknownKey { .. })
    ));

    // Development mode accepts the unsigned blob.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = serve_one(listener, trusted, SignaturePolicy::AllowUnsigned);
    let (ok, out, err) = push(&["--to", &addr, p(&file)]);
    assert!(ok, "{out}\n{err}");
    assert!(out.contains("unsigned"), "{out}");
    assert_eq!(
        server.join().unwrap(),
        Ok((rig(), SignatureStatus::UnsignedAccepted))
    );
}

#[test]
fn push_forwards_a_presigned_file_unchanged() {
    let dir = tmp_dir("presigned");
    let (sec, publ) = keygen(&dir, "ops");
    let key = signing::parse_secret_key_file(&std::fs::read_to_string(&sec).unwrap()).unwrap();
    let file = dir.join("signed.irp");
    let blob = rig().to_signed_blob(&key).unwrap();
    std::fs::write(&file, &blob).unwrap();

    // A raw server that records the exact bytes.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = thread::spawn(move || {
        let (mut s, _) = listener.accept().unwrap();
        let mut hdr = [0u8; param_wire::PUSH_HEADER_LEN];
        s.read_exact(&mut hdr).unwrap();
        let mut got = vec![0u8; param_wire::parse_push_header(&hdr).unwrap()];
        s.read_exact(&mut got).unwrap();
        s.write_all(b"OK signed-pair\n").unwrap();
        got
    });
    let (ok, out, err) = push(&["--to", &addr, p(&file)]);
    assert!(ok, "{out}\n{err}");
    assert!(out.contains("(as in the file)"), "{out}");
    let got = server.join().unwrap();
    assert_eq!(got, blob);
    assert!(verify_blob(&got, &[public(&publ)], SignaturePolicy::RequireSigned).is_ok());
}
