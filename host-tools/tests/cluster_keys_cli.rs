//! `host-tools cluster-keys`: per-board passwords and the solver's dictionary, mode 0600,
//! readable by the same parsers irtrackd uses (irtrack_cluster::credentials).

mod common;

use std::os::unix::fs::PermissionsExt;
use std::path::Path;

use common::*;
use irtrack_cluster::credentials::{parse_dictionary, parse_password};

fn mode(path: &Path) -> u32 {
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

#[test]
fn cluster_keys_writes_private_files_that_irtrackd_reads() {
    let dir = std::env::temp_dir().join(format!("irtrack-cluster-keys-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.join("cell1");
    let o = host_tools(&["cluster-keys", "--boards", "b0,b1,b2", "--out", p(&out)]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("password_file") && stdout.contains("credentials_file"),
        "{stdout}"
    );

    let dict_path = out.join("solver.credentials");
    assert_eq!(mode(&dict_path), 0o600);
    let dict = parse_dictionary(&dict_path, &std::fs::read_to_string(&dict_path).unwrap()).unwrap();
    let boards: Vec<&str> = dict.iter().map(|c| c.board.as_str()).collect();
    assert_eq!(boards, ["b0", "b1", "b2"]);
    for c in &dict {
        let pw_path = out.join(format!("{}.password", c.board));
        assert_eq!(mode(&pw_path), 0o600, "{}", pw_path.display());
        let pw = parse_password(&pw_path, &std::fs::read_to_string(&pw_path).unwrap()).unwrap();
        assert_eq!(
            pw, c.password,
            "board {}'s file and the dictionary agree",
            c.board
        );
        // The password is not printed.
        assert!(!stdout.contains(&pw));
    }
    assert_ne!(dict[0].password, dict[1].password);

    // Refuses to overwrite; --force makes new passwords.
    let o = host_tools(&["cluster-keys", "--boards", "b0", "--out", p(&out)]);
    assert!(!o.status.success());
    assert!(text(&o).1.contains("--force"), "{:?}", text(&o));
    let o = host_tools(&[
        "cluster-keys",
        "--boards",
        "b0,b1,b2",
        "--out",
        p(&out),
        "--force",
    ]);
    assert!(o.status.success(), "{:?}", text(&o));
    let again = parse_dictionary(&dict_path, &std::fs::read_to_string(&dict_path).unwrap()).unwrap();
    assert_ne!(again[0].password, dict[0].password);

    // Bad names are named.
    let o = host_tools(&["cluster-keys", "--boards", "b0,b/1", "--out", p(&dir.join("x"))]);
    assert!(!o.status.success());
    assert!(text(&o).1.contains("b/1"), "{:?}", text(&o));
    let o = host_tools(&["cluster-keys", "--boards", "b0,b0", "--out", p(&dir.join("y"))]);
    assert!(text(&o).1.contains("twice"), "{:?}", text(&o));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn cluster_keys_tls_makes_the_certificate_the_boards_pin_and_a_private_key() {
    use irtrack_cluster::credentials::{parse_pinned_certificate, parse_tls_identity};
    let dir = std::env::temp_dir().join(format!("irtrack-cluster-tls-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.join("cell1");
    let o = host_tools(&["cluster-keys", "--boards", "b0,b1", "--out", p(&out), "--tls"]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("tls_key_file") && stdout.contains("tls_solver_certificate_file"),
        "{stdout}"
    );
    let (crt, key) = (out.join("solver.tls.crt"), out.join("solver.tls.key"));
    assert_eq!(mode(&key), 0o600);
    let crt_text = std::fs::read_to_string(&crt).unwrap();
    let key_text = std::fs::read_to_string(&key).unwrap();
    parse_pinned_certificate(&crt, &crt_text).unwrap();
    parse_tls_identity(&key, &format!("{crt_text}{key_text}")).unwrap();
    // The key is not printed; the certificate names the solver's role.
    assert!(!stdout.contains(key_text.lines().nth(1).unwrap()));
    // Refuses to overwrite them; --force makes a new pair.
    let o = host_tools(&["cluster-keys", "--boards", "b0,b1", "--out", p(&out), "--tls"]);
    assert!(!o.status.success());
    assert!(
        text(&o).1.contains("solver.tls") || text(&o).1.contains("--force"),
        "{:?}",
        text(&o)
    );
    let o = host_tools(&[
        "cluster-keys",
        "--boards",
        "b0,b1",
        "--out",
        p(&out),
        "--tls",
        "--force",
    ]);
    assert!(o.status.success(), "{:?}", text(&o));
    assert_ne!(std::fs::read_to_string(&crt).unwrap(), crt_text);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A stand-in board for `cluster-keys push` over real sockets: `/status` on one port (its
/// name and public key), the parameter port on another, which opens each envelope with the
/// board's key exactly as irtrackd does (`envelope::open`) and answers a verdict line.
/// Returns the two addresses and what it received.
fn stand_in_board(
    key: irtrack_cluster::envelope::BoxKey,
    trusted: irtrack_core::signing::VerifyingKey,
) -> (String, String, std::sync::mpsc::Receiver<String>) {
    use std::io::{Read, Write};
    let status = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let params = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addrs = (
        status.local_addr().unwrap().to_string(),
        params.local_addr().unwrap().to_string(),
    );
    let public = irtrack_cluster::envelope::hex(&key.public());
    std::thread::spawn(move || {
        for s in status.incoming().flatten() {
            let mut s = s;
            let mut buf = [0u8; 2048];
            let _ = s.read(&mut buf);
            let body = format!("{{\"cluster\":{{\"board\":\"b0\",\"box_public_key\":\"{public}\"}}}}");
            let _ = write!(
                s,
                "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
        }
    });
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut last = None;
        for s in params.incoming().flatten() {
            let mut s = s;
            let mut hdr = [0u8; 8];
            s.read_exact(&mut hdr).unwrap();
            assert_eq!(&hdr[..4], b"IRPP", "pushed as a parameter blob");
            let mut env = vec![0u8; u32::from_le_bytes(hdr[4..].try_into().unwrap()) as usize];
            s.read_exact(&mut env).unwrap();
            let trusted = [trusted];
            let to = irtrack_cluster::envelope::Recipient {
                board: "b0",
                key: &key,
                trusted: &trusted,
                last_serial: last,
            };
            let line = match irtrack_cluster::envelope::open(&env, &to) {
                Ok(o) => {
                    last = Some(o.header.serial);
                    tx.send(o.secret).unwrap();
                    format!("OK credentials-b0-{}\n", o.header.serial)
                }
                Err(irtrack_cluster::ClusterError::Envelope { why, reason }) => {
                    format!("ERR {} {reason}\n", why.code())
                }
                Err(e) => format!("ERR BAD_BLOB {e}\n"),
            };
            let _ = s.write_all(line.as_bytes());
        }
    });
    (addrs.0, addrs.1, rx)
}

#[test]
fn cluster_keys_push_pins_the_board_key_and_sends_the_password_sealed() {
    let dir = std::env::temp_dir().join(format!("irtrack-cluster-push-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.join("cell1");
    assert!(
        host_tools(&["cluster-keys", "--boards", "b0", "--out", p(&out), "--tls"])
            .status
            .success()
    );
    let o = host_tools(&["keygen", "--out", p(&dir.join("pc"))]);
    assert!(o.status.success(), "{:?}", text(&o));
    let pc_pub =
        irtrack_core::signing::parse_public_key_file(&std::fs::read_to_string(dir.join("pc.pub")).unwrap())
            .unwrap();
    let key = irtrack_cluster::envelope::BoxKey::from_secret_bytes([0x22; 32]);
    let (status, params, received) = stand_in_board(key.clone(), pc_pub);
    let sign_key = dir.join("pc.key");
    let push = |extra: &[&str]| {
        let mut args = vec![
            "cluster-keys",
            "push",
            "--board",
            "b0",
            "--dir",
            p(&out),
            "--to",
            &params,
            "--status",
            &status,
            "--sign-key",
            p(&sign_key),
            "--retries",
            "0",
        ];
        args.extend_from_slice(extra);
        host_tools(&args)
    };
    // First contact: the key is shown, not pinned, nothing sent.
    let o = push(&[]);
    let (stdout, stderr) = text(&o);
    assert!(!o.status.success());
    let shown = irtrack_cluster::envelope::hex(&key.public());
    assert!(
        stderr.contains(&shown) && stderr.contains("--accept-new-key"),
        "{stdout}\n{stderr}"
    );
    assert!(received.try_recv().is_err());
    // Pinned, sealed, accepted; the board got the password file's text.
    let o = push(&["--accept-new-key", "--serial", "10"]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("pinned board b0's key") && stdout.contains("accepted (serial 10)"),
        "{stdout}"
    );
    let secret = received.recv_timeout(std::time::Duration::from_secs(5)).unwrap();
    assert_eq!(secret, std::fs::read_to_string(out.join("b0.password")).unwrap());
    let pinned = std::fs::read_to_string(out.join("known_boards")).unwrap();
    assert_eq!(pinned.trim(), format!("b0 {shown}"));
    // The solver's certificate for the board to pin: the certificate alone, never the key.
    let o = push(&["--tls", "--serial", "12"]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("the solver's TLS certificate (to pin)"),
        "{stdout}"
    );
    let secret = received.recv_timeout(std::time::Duration::from_secs(5)).unwrap();
    assert_eq!(
        secret,
        std::fs::read_to_string(out.join("solver.tls.crt")).unwrap()
    );
    assert!(!secret.contains("PRIVATE KEY"));
    // An older serial: the board's refusal is printed and the exit status is 1.
    let o = push(&["--serial", "9"]);
    let (_, stderr) = text(&o);
    assert!(!o.status.success());
    assert!(
        stderr.contains("ROLLBACK") && stderr.contains("not newer"),
        "{stderr}"
    );
    // A pinned key the board no longer has (reinstalled): refused by the board, naming it.
    std::fs::write(out.join("known_boards"), format!("b0 {}\n", "ab".repeat(32))).unwrap();
    let o = push(&["--serial", "11"]);
    let (_, stderr) = text(&o);
    assert!(!o.status.success());
    assert!(
        stderr.contains("RIG_MISMATCH") && stderr.contains("sealed to key abababab"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
