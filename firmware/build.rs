//! The status listener embeds every file under `web/` (rust-embed); rebuild when any changes,
//! including files added or removed (rust-embed alone only tracks the files it saw).
fn main() {
    println!("cargo:rerun-if-changed=web");
}
