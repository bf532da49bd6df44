//! The credentials files (docs/cluster.md, "Credentials"): the formats irtrackd reads, the
//! files `host-tools cluster-keys` writes (mode 0600, random passwords), and errors that name
//! the problem without quoting a password.

use std::path::Path;

use irtrack_cluster::credentials::*;

const PW: &str = "Zq8-xT_3kLmN0pQr7sUvWy2A";

#[test]
fn dictionary_round_trips_and_names_bad_lines() {
    let f = Path::new("dict");
    let entries = vec![
        BoardCredential {
            board: "b0".into(),
            password: PW.into(),
        },
        BoardCredential {
            board: "b1".into(),
            password: format!("{PW}:x"),
        },
    ];
    let text = dictionary_text(&entries);
    assert_eq!(text, format!("b0:{PW}\nb1:{PW}:x\n"));
    assert_eq!(parse_dictionary(f, &text).unwrap(), entries);
    let e = parse_dictionary(f, &format!("b0:{PW}\n\nb 1:{PW}\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("line 3") && e.contains("board name"), "{e}");
    let e = parse_dictionary(f, "b0:short\n").unwrap_err().to_string();
    assert!(
        e.contains("line 1") && e.contains("16..=128") && !e.contains("short"),
        "{e}"
    );
    let e = parse_dictionary(f, &format!("b0:{PW}\nb0:{PW}\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("listed twice"), "{e}");
    let e = parse_dictionary(f, "\n\n").unwrap_err().to_string();
    assert!(e.contains("no board"), "{e}");
    let e = parse_dictionary(f, "no colon here at all\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("board:password"), "{e}");
}

#[test]
fn generated_credentials_are_private_random_and_read_back() {
    use std::os::unix::fs::PermissionsExt;
    let dir = std::env::temp_dir().join(format!("irtrack-cluster-cred-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let written = write_new_credentials(&dir, &["b0", "b1"], false).unwrap();
    let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    let (dict, loose) = read_dictionary_file(&dictionary_path(&dir)).unwrap();
    assert!(!loose);
    assert_eq!(mode(&dictionary_path(&dir)), 0o600);
    assert_eq!(dict, written);
    for c in &written {
        let p = password_path(&dir, &c.board);
        assert_eq!(mode(&p), 0o600);
        assert_eq!(read_password_file(&p).unwrap(), (c.password.clone(), false));
        assert_eq!(c.password.len(), GENERATED_PASSWORD_LEN);
    }
    assert_ne!(written[0].password, written[1].password);
    let e = write_new_credentials(&dir, &["b0"], false)
        .unwrap_err()
        .to_string();
    assert!(e.contains("already exists"), "{e}");
    let again = write_new_credentials(&dir, &["b0", "b1"], true).unwrap();
    assert_ne!(again[0].password, written[0].password);
    let e = write_new_credentials(&dir, &["b0", "b0"], true)
        .unwrap_err()
        .to_string();
    assert!(e.contains("twice"), "{e}");
    let e = write_new_credentials(&dir, &["b/0"], true)
        .unwrap_err()
        .to_string();
    assert!(e.contains("b/0"), "{e}");
    // A looser mode is noticed.
    std::fs::set_permissions(dictionary_path(&dir), std::fs::Permissions::from_mode(0o644)).unwrap();
    assert!(read_dictionary_file(&dictionary_path(&dir)).unwrap().1);
    let _ = std::fs::remove_dir_all(&dir);
    // Over many passwords every one of the 64 characters appears (the mapping is onto).
    let all: String = (0..200).map(|_| random_password()).collect();
    for &c in PASSWORD_ALPHABET {
        assert!(all.contains(char::from(c)), "{} never drawn", char::from(c));
    }
}

#[test]
fn password_file_is_one_clean_line() {
    let f = Path::new("pw");
    assert_eq!(parse_password(f, &format!("{PW}\n")).unwrap(), PW);
    assert!(parse_password(f, "").is_err());
    let e = parse_password(f, &format!("{PW}\n{PW}\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("one line"), "{e}");
    let e = parse_password(f, "abc\"defghijklmnopq").unwrap_err().to_string();
    assert!(e.contains("printable ASCII"), "{e}");
    let e = parse_password(f, "abcdefgh ijklmnopq").unwrap_err().to_string();
    assert!(e.contains("' '"), "{e}");
}
