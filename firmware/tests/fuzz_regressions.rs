//! Regression tests for the config fuzz target (fuzz/fuzz_targets/config.rs, docs/fuzzing.md):
//! the committed seeds are replayed, and inputs of the kinds the fuzzer produces (numbers out
//! of range, wrong types, deep nesting, odd bytes) must give an error naming the problem,
//! never a panic. No config crash has been found so far; crashes found later go here.

use std::path::Path;

use irtrack_firmware::config::Config;

/// Every committed seed (the image's and the Yocto layer's config and the test suite's full
/// example) is a valid config, and stays valid when validated again.
#[test]
fn config_seeds_replay() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/seeds/config");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let text = std::fs::read_to_string(&path).unwrap();
        let cfg = Config::from_toml(&text, &path.display().to_string())
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        cfg.validate().unwrap();
        n += 1;
    }
    assert!(n >= 3, "only {n} config seeds");
}

/// Mutations of the kinds libFuzzer applies; each must be refused with a message.
#[test]
fn hostile_configs_are_refused_without_panicking() {
    let deep = format!("x = {}{}", "[".repeat(5000), "]".repeat(5000));
    let cases: Vec<(String, &str)> = vec![
        ("[realtime]\ndeadline_ms = nan\n".into(), "deadline_ms"),
        ("[realtime]\ndeadline_ms = -inf\n".into(), "deadline_ms"),
        (
            "[realtime]\nfifo_priority = 99999999999999999999\n".into(),
            "fifo_priority",
        ),
        ("[realtime]\ncpu_affinity = [-1]\n".into(), "cpu_affinity"),
        ("[listen]\nparams = \"127.0.0.1:99999\"\n".into(), "listen.params"),
        (
            "[listen]\nclient_queue_records = 0\n".into(),
            "client_queue_records",
        ),
        ("[source]\nkind = \"replay\"\n".into(), "replay"),
        ("[source]\nkind = \"\\u0000\"\n".into(), "kind"),
        ("[tracking]\nthreshold_dn = 1e400\n".into(), "threshold_dn"),
        ("[service\n".into(), "service"),
        (deep, ""),
    ];
    for (text, needle) in cases {
        let err = match Config::from_toml(&text, "fuzz.toml") {
            Ok(cfg) => panic!("accepted {text:?}: {cfg:?}"),
            Err(e) => e.to_string(),
        };
        assert!(
            err.contains(needle),
            "{text:.60?}: message {err:?} does not name {needle:?}"
        );
    }
}
