//! Per-camera timing in irtrackd's config (`[[camera_timing]]`, docs/timing.md "Camera timing
//! settings") and which timing the loop uses: the parameter set's when it carries timing, else
//! the config's, else the default.

use irtrack_core::params::RigParams;
use irtrack_core::timing::{CameraTiming, Shutter};
use irtrack_firmware::config::{Config, TimingOrigin, effective_timing, effective_timing_with_origin};
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};

fn rig() -> RigParams {
    SimSource::new(&SimSourceConfig::default())
        .unwrap()
        .scenario()
        .rig()
        .clone()
}

const V4L2: &str = r#"
[source]
kind = "v4l2"
[source.v4l2]
devices = ["/dev/video0", "/dev/video2"]
width_px = 640
height_px = 480
fps = 60
exposure_us = 800
"#;

fn with_timing(tables: &str) -> String {
    format!("{V4L2}\n{tables}")
}

#[test]
fn config_timing_applies_until_the_set_carries_its_own() {
    let cfg = Config::from_toml(
        &with_timing(
            r#"
[[camera_timing]]
camera = 1
shutter = "rolling"
line_time_us = 15.2
offset_us = -120.5
"#,
        ),
        "test.toml",
    )
    .unwrap();
    let rig = rig();
    assert_eq!(rig.camera_count(), 2);
    let (timing, origin) = effective_timing_with_origin(&cfg, &rig);
    assert_eq!(origin, TimingOrigin::Config);
    assert_eq!(
        timing,
        vec![
            // Not listed: the default.
            CameraTiming::default(),
            CameraTiming {
                shutter: Shutter::Rolling,
                line_time_ns: 15_200,
                // From [source.v4l2] exposure_us, as the table gives none.
                exposure_ns: 800_000,
                offset_ns: -120_500,
            },
        ]
    );

    // The set's calibrated timing wins, for every camera, over the config.
    let calibrated = CameraTiming {
        shutter: Shutter::Global,
        line_time_ns: 0,
        exposure_ns: 0,
        offset_ns: 2_300,
    };
    let set_timed = RigParams {
        timing: vec![CameraTiming::default(), calibrated],
        ..rig.clone()
    };
    let (timing, origin) = effective_timing_with_origin(&cfg, &set_timed);
    assert_eq!(origin, TimingOrigin::ParameterSet);
    assert_eq!(timing, vec![CameraTiming::default(), calibrated]);

    // Neither: every camera at the default, one per camera of the set.
    let plain = Config::from_toml(V4L2, "test.toml").unwrap();
    let (timing, origin) = effective_timing_with_origin(&plain, &rig);
    assert_eq!(origin, TimingOrigin::Default);
    assert_eq!(timing, vec![CameraTiming::default(); 2]);
    assert_eq!(effective_timing(&plain, &rig), timing);
    // A set whose timing list holds only defaults carries none: the config applies.
    let all_default = RigParams {
        timing: vec![CameraTiming::default(); 2],
        ..rig
    };
    assert_eq!(
        effective_timing_with_origin(&cfg, &all_default).1,
        TimingOrigin::Config
    );
}

#[test]
fn bad_camera_timing_tables_are_named() {
    for (table, words) in [
        (
            "camera = 2\nshutter = \"global\"",
            "camera_timing[0] (camera 2): [source] has 2 cameras",
        ),
        (
            "camera = 1\nshutter = \"rolling\"",
            "a rolling shutter needs line_time_ns > 0",
        ),
        (
            "camera = 1\nshutter = \"rolling\"\nline_time_us = 15000",
            "line_time_ns above 10 ms",
        ),
        (
            "camera = 0\noffset_us = 2e6",
            "offset_us = 2000000 must be a finite number of µs",
        ),
        (
            "camera = 0\nline_time_us = -1",
            "line_time_us = -1 must be a finite number of µs ≥ 0",
        ),
        ("camera = 0\nshutter = \"sideways\"", "sideways"),
        ("camera = 0\nline_us = 3", "line_us"),
    ] {
        let e = Config::from_toml(&with_timing(&format!("[[camera_timing]]\n{table}\n")), "t.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains(words), "{table:?}: {e}");
    }
    let twice = with_timing("[[camera_timing]]\ncamera = 0\n[[camera_timing]]\ncamera = 0\n");
    let e = Config::from_toml(&twice, "t.toml").unwrap_err().to_string();
    assert!(
        e.contains("camera_timing[1] (camera 0): the camera is listed twice"),
        "{e}"
    );
}
