//! irtrackd's config parser (`Config::from_toml`: TOML, then validation) never panics, and an
//! accepted config passes its own validation again.
#![no_main]

use irtrack_firmware::config::Config;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(cfg) = Config::from_toml(text, "fuzz") {
        cfg.validate().expect("an accepted config must stay valid");
    }
});
