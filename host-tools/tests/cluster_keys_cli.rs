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
