//! Detects optional phase modules (`src/image.rs`, `src/bench.rs`, `src/fuzz.rs`) that other
//! parts of the project add. A module that exists is compiled in and its CI phase runs; a
//! missing one is reported as "skipped: not present". No registration edit is needed.

use std::path::Path;

/// Optional modules: file stem == module name == cfg name suffix.
const OPTIONAL_MODULES: &[&str] = &["image", "bench", "fuzz"];

fn main() {
    // A directory here makes cargo rescan it, so a newly created module is picked up.
    println!("cargo::rerun-if-changed=src");
    for name in OPTIONAL_MODULES {
        println!("cargo::rustc-check-cfg=cfg(xtask_has_{name})");
        if Path::new("src").join(format!("{name}.rs")).is_file() {
            println!("cargo::rustc-cfg=xtask_has_{name}");
        }
    }
}
