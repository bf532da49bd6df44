//! `host-tools capture` against a stand-in for irtrackd's `GET /api/frameset` (format of
//! docs/http-api.md) that serves checkerboard views of the simulated 90° rig: sets are saved in
//! the layout `calibrate` reads, the board is found per camera and the coverage grid is shown.
//! Across boards (`--from A --from B`): sets paired on the realtime clock, numbered board by
//! board, unpaired sets refused. With `--params` (the rig's placement) the boards are known by
//! the name their `/status` reports and the cameras come out in the rig's order, whatever the
//! `--from` order; a board's camera not placed, a placed camera on no board given and two boards
//! of one name are refused before anything is saved. Error cases: firmware without the endpoint
//! (404), nothing listening. Against real irtrackd processes: tests/tests/capture_e2e.rs (one board) and
//! tests/tests/cluster_calibration_e2e.rs (two camera boards, then `wand-calibrate`).

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::thread;

use common::*;
use irtrack_sim::checkerboard::{self, BoardSpec, PoseConfig, RenderSettings};
use irtrack_sim::rig::{CameraSpec, RigPreset, build_rig};

/// Serves `responses` to consecutive HTTP requests (status line, content type, body), then stops.
/// JSON answers are for `GET /status`, all others for `GET /api/frameset`.
fn serve(responses: Responses) -> (String, thread::JoinHandle<usize>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let handle = thread::spawn(move || {
        let mut served = 0;
        for (status, ctype, body) in responses {
            let (mut s, _) = listener.accept().unwrap();
            let mut reader = BufReader::new(s.try_clone().unwrap());
            let mut request_line = String::new();
            reader.read_line(&mut request_line).unwrap();
            let path = if ctype == "application/json" {
                "/status"
            } else {
                "/api/frameset"
            };
            assert!(
                request_line.starts_with(&format!("GET {path} ")),
                "{request_line}"
            );
            loop {
                let mut l = String::new();
                if reader.read_line(&mut l).unwrap() == 0 || l == "\r\n" {
                    break;
                }
            }
            let reason = match status {
                200 => "OK",
                404 => "Not Found",
                _ => "Error",
            };
            write!(
                s,
                "HTTP/1.1 {status} {reason}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                body.len()
            )
            .unwrap();
            s.write_all(&body).unwrap();
            served += 1;
        }
        served
    });
    (addr, handle)
}

/// A frame-set body as docs/http-api.md describes it, from one PGM file per camera.
fn frameset_body(set_index: u64, pgms: &[Vec<u8>], size: (u32, u32)) -> Vec<u8> {
    let cams: Vec<String> = pgms
        .iter()
        .enumerate()
        .map(|(c, pgm)| {
            format!(
                "{{\"camera\":{c},\"width_px\":{},\"height_px\":{},\"bit_depth\":8,\"timestamp_ns\":{},\"sequence\":{set_index},\"pgm_bytes\":{}}}",
                size.0,
                size.1,
                set_index * 1000 + c as u64,
                pgm.len()
            )
        })
        .collect();
    let mut b = format!(
        "{{\"set_index\":{set_index},\"pairing_error_ns\":500,\"cameras\":[{}]}}\n",
        cams.join(",")
    )
    .into_bytes();
    for pgm in pgms {
        b.extend_from_slice(pgm);
    }
    b
}

/// One stand-in board's answers, in order: status, content type, body.
type Responses = Vec<(u16, &'static str, Vec<u8>)>;

/// Checkerboard views of the simulated 90° rig (one camera per rig camera), rendered into
/// `dir/views`: the files per camera and view, and the image size.
fn rig_views(dir: &Path, count: usize) -> (Vec<Vec<PathBuf>>, (u32, u32)) {
    let rig = build_rig(
        &RigPreset::Convergent {
            distance_mm: 659.84,
            angle_deg: 90.0,
        },
        &CameraSpec::default(),
    )
    .unwrap();
    let board = BoardSpec::new(9, 6, 25.0).unwrap();
    let poses = checkerboard::generate_poses(
        &rig,
        &board,
        &PoseConfig {
            count,
            seed: 4,
            ..Default::default()
        },
    )
    .unwrap();
    let set = checkerboard::write_set(
        &dir.join("views"),
        &rig,
        &board,
        &poses,
        &RenderSettings {
            seed: 4,
            ..Default::default()
        },
    )
    .unwrap();
    let size = rig.cameras[0].model.image_size;
    (set.files, (size.width_px, size.height_px))
}

/// A capture session against stand-in boards.
struct Session {
    /// The boards' addresses, in `--from` order.
    addrs: Vec<String>,
    output: std::process::Output,
    servers: Vec<thread::JoinHandle<usize>>,
}

impl Session {
    /// Requests each board answered (waits for every board's server to finish its list).
    fn served(self) -> Vec<usize> {
        self.servers.into_iter().map(|h| h.join().unwrap()).collect()
    }
}

/// Serves each board's responses and runs `host-tools capture` with a `--from` per board, in
/// the order given, `--out out` and `args`.
fn capture(boards: Vec<Responses>, out: &Path, args: &[&str]) -> Session {
    let (addrs, servers): (Vec<String>, Vec<_>) = boards.into_iter().map(serve).unzip();
    let mut argv = vec!["capture"];
    for a in &addrs {
        argv.extend(["--from", a.as_str()]);
    }
    argv.extend(["--out", p(out)]);
    argv.extend_from_slice(args);
    let output = host_tools(&argv);
    Session {
        addrs,
        output,
        servers,
    }
}

#[test]
fn capture_saves_sets_finds_the_board_and_shows_coverage() {
    let dir = scratch("board");
    let (files, size) = rig_views(&dir, 3);
    let expected: Vec<Vec<Vec<u8>>> = (0..3)
        .map(|v| (0..2).map(|c| std::fs::read(&files[c][v]).unwrap()).collect())
        .collect();
    let bodies = expected.iter().enumerate().map(|(v, pgms)| {
        (
            200,
            "application/x-irtrack-frameset",
            frameset_body(10 + v as u64, pgms, size),
        )
    });
    // capture asks the board once before the session (to fail early and name the cameras);
    // that set is not saved.
    let probe = (
        200,
        "application/x-irtrack-frameset",
        frameset_body(9, &expected[0], size),
    );
    let out = dir.join("shots");
    let run = capture(
        vec![std::iter::once(probe.clone()).chain(bodies).collect()],
        &out,
        &["--every", "0.05", "--count", "3"],
    );
    let (stdout, stderr) = text(&run.output);
    assert!(run.output.status.success(), "{stdout}\n{stderr}");
    print!("{stdout}");
    let addr = run.addrs[0].clone();
    assert_eq!(run.served(), [4]);
    assert!(
        stdout.starts_with(&format!("board {addr}: 2 cameras, {}x{} 8-bit\n", size.0, size.1)),
        "{stdout}"
    );
    for (v, cams) in expected.iter().enumerate() {
        for (c, pgm) in cams.iter().enumerate() {
            let saved = std::fs::read(out.join(format!("cam{c}/{v:06}.pgm"))).unwrap();
            assert!(saved == *pgm, "cam{c} set {v} differs from what was served");
        }
    }
    assert_eq!(
        stdout.matches("cam0 board found (54 corners)").count(),
        3,
        "{stdout}"
    );
    assert_eq!(
        stdout.matches("cam1 board found (54 corners)").count(),
        3,
        "{stdout}"
    );
    assert!(
        stdout.contains("views with the board in every camera: 3"),
        "{stdout}"
    );
    // The coverage grid: some cells reached, and not the whole image from three views.
    assert!(stdout.contains('#') || stdout.contains('+'), "{stdout}");
    assert!(stdout.contains("saved 3 sets"), "{stdout}");

    // A second session continues the numbering instead of overwriting.
    let again = (
        200,
        "application/x-irtrack-frameset",
        frameset_body(99, &expected[0], size),
    );
    let run = capture(
        vec![vec![probe, again]],
        &out,
        &["--every", "0.05", "--count", "1"],
    );
    assert!(run.output.status.success(), "{}", text(&run.output).1);
    run.served();
    assert!(out.join("cam1/000003.pgm").is_file());
}

#[test]
fn capture_names_old_firmware_and_unreachable_boards() {
    let dir = scratch("errors");
    let (addr, server) = serve(vec![(404, "text/plain", b"not found".to_vec())]);
    let o = host_tools(&[
        "capture",
        "--from",
        &addr,
        "--out",
        p(&dir),
        "--wand",
        "--count",
        "2",
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success());
    assert!(
        err.contains(&format!(
            "irtrackd on {addr} has no /api/frameset; update the firmware"
        )),
        "{err}"
    );
    server.join().unwrap();

    // Nothing listens on a port that was just free.
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let board = format!("127.0.0.1:{port}");
    let o = host_tools(&[
        "capture",
        "--from",
        &board,
        "--out",
        p(&dir),
        "--wand",
        "--count",
        "2",
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success());
    assert!(
        err.contains(&format!("cannot reach irtrackd on {board}")),
        "{err}"
    );
    // In the Enter-driven mode too: said before any prompt, with what to check, and no
    // output folder made for nothing.
    let out = dir.join("never");
    let o = host_tools(&["capture", "--from", &board, "--out", p(&out)]);
    let (stdout, err) = text(&o);
    assert!(!o.status.success(), "{stdout}");
    assert!(
        err.contains(&format!("cannot reach irtrackd on {board}"))
            && err.contains("is the board on and irtrackd running?"),
        "{err}"
    );
    assert!(
        !stdout.contains("Enter"),
        "prompted before checking the board: {stdout}"
    );
    assert!(!out.exists(), "{} created for nothing", out.display());
}

/// A busy board (503) is asked again, before the session and during it; 21 busy answers in a
/// row end the capture with the board's reason.
#[test]
fn capture_retries_a_busy_board_and_gives_up_after_twenty() {
    let dir = scratch("busy");
    let pgm = |v: u8| {
        let mut b = b"P5\n4 2\n255\n".to_vec();
        b.extend_from_slice(&[v; 8]);
        b
    };
    let set = |i: u64| {
        (
            200,
            "application/x-irtrack-frameset",
            frameset_body(i, &[pgm(i as u8), pgm(i as u8 + 1)], (4, 2)),
        )
    };
    let busy = || {
        (
            503,
            "text/plain",
            b"another frame-set request is in progress".to_vec(),
        )
    };
    let (addr, server) = serve(vec![busy(), set(1), busy(), busy(), set(2)]);
    let out = dir.join("wave");
    let o = host_tools(&[
        "capture",
        "--from",
        &addr,
        "--out",
        p(&out),
        "--wand",
        "--count",
        "1",
    ]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert_eq!(server.join().unwrap(), 5);
    assert_eq!(
        stderr
            .matches("no set this time (503: another frame-set request")
            .count(),
        3,
        "{stderr}"
    );
    assert_eq!(std::fs::read(out.join("cam1/000000.pgm")).unwrap(), pgm(3));

    let (addr, server) = serve((0..21).map(|_| busy()).collect());
    let o = host_tools(&[
        "capture",
        "--from",
        &addr,
        "--out",
        p(&out),
        "--wand",
        "--count",
        "1",
    ]);
    let (_, stderr) = text(&o);
    assert!(!o.status.success());
    assert!(
        stderr.contains(&format!(
            "irtrackd on {addr} gave no frame set 20 times in a row: 503"
        )),
        "{stderr}"
    );
    assert_eq!(server.join().unwrap(), 21);
}

/// A frame-set body of one board with a realtime clock difference (docs/frameset.md): every
/// camera at monotonic `t_ns`, frame counter `seq`.
fn clocked_body(seq: u64, pgms: &[Vec<u8>], size: (u32, u32), t_ns: u64, rt_minus_mono_ns: i64) -> Vec<u8> {
    let cams: Vec<String> = pgms
        .iter()
        .enumerate()
        .map(|(c, pgm)| {
            format!(
                "{{\"camera\":{c},\"width_px\":{},\"height_px\":{},\"bit_depth\":8,\"timestamp_ns\":{t_ns},\"sequence\":{seq},\"pgm_bytes\":{}}}",
                size.0,
                size.1,
                pgm.len()
            )
        })
        .collect();
    let mut b = format!(
        "{{\"set_index\":{seq},\"pairing_error_ns\":0,\"cameras\":[{}],\"realtime_minus_monotonic_ns\":{rt_minus_mono_ns}}}\n",
        cams.join(",")
    )
    .into_bytes();
    for pgm in pgms {
        b.extend_from_slice(pgm);
    }
    b
}

/// 120 fps.
const PERIOD_NS: u64 = 8_333_333;
/// Realtime of frame 0 on both boards.
const EPOCH_NS: u64 = 1_700_000_000_000_000_000;
/// Two boards booted at different times: their monotonic clocks differ by 49 s.
const MONO_A_NS: u64 = 1_000_000_000;
const MONO_B_NS: u64 = 50_000_000_000;

/// Board A's frame `k` and board B's frame `k` `phase_ns` later (realtime).
fn board_set(
    board_b: bool,
    k: u64,
    phase_ns: u64,
    pgms: &[Vec<u8>],
    size: (u32, u32),
) -> (u16, &'static str, Vec<u8>) {
    let mono0 = if board_b { MONO_B_NS } else { MONO_A_NS };
    let body = clocked_body(
        k,
        pgms,
        size,
        mono0 + k * PERIOD_NS + phase_ns,
        (EPOCH_NS - mono0) as i64,
    );
    (200, "application/x-irtrack-frameset", body)
}

/// Two boards of one camera each (the simulated 90° rig's cameras): sets are paired on the
/// realtime clock, numbered board by board, a set whose boards are 6 ms apart (tolerance: half
/// of 8.33 ms) is refused and not saved, and `calibrate` runs on the folder.
#[test]
fn capture_across_boards_pairs_numbers_and_refuses_offsets() {
    let dir = scratch("boards");
    let (files, size) = rig_views(&dir, 4);
    let view = |c: usize, v: usize| std::fs::read(&files[c][v]).unwrap();
    // Per board: two probe sets (frames 0, 1: the frame period), a set where B's frame is 6 ms
    // after A's (refused), then four sets 1 ms apart.
    let responses = |b: bool| -> Responses {
        let c = usize::from(b);
        // Board A reports the name b0; board B (standalone) none: its rows keep its address.
        let status = if b { unnamed_status() } else { status_of("b0") };
        let mut r = vec![
            status,
            board_set(b, 0, 0, &[view(c, 0)], size),
            board_set(b, 1, 0, &[view(c, 0)], size),
            board_set(b, 5, if b { 6_000_000 } else { 0 }, &[view(c, 0)], size),
        ];
        for v in 0..4 {
            r.push(board_set(
                b,
                6 + v as u64,
                if b { 1_000_000 } else { 0 },
                &[view(c, v)],
                size,
            ));
        }
        r
    };
    let out = dir.join("shots");
    let run = capture(
        vec![responses(false), responses(true)],
        &out,
        &["--every", "0.05", "--count", "4"],
    );
    let (stdout, stderr) = text(&run.output);
    print!("{stdout}{stderr}");
    assert!(run.output.status.success(), "{stdout}\n{stderr}");
    let (addr_a, addr_b) = (run.addrs[0].clone(), run.addrs[1].clone());
    assert_eq!(run.served(), [8, 8]);
    assert!(
        stdout.contains(&format!(
            "board {addr_a}: 1 camera, {}x{} 8-bit → cam0..cam0",
            size.0, size.1
        )) && stdout.contains(&format!(
            "board {addr_b}: 1 camera, {}x{} 8-bit → cam1..cam1",
            size.0, size.1
        )),
        "{stdout}"
    );
    assert!(stdout.contains("on CLOCK_REALTIME within ±4.167 ms"), "{stdout}");
    assert_eq!(
        stderr
            .matches(&format!(
                "capture: set refused, not saved: board {addr_b}'s frames are +6.000 ms from board {addr_a}'s (tolerance 4.167 ms"
            ))
            .count(),
        1,
        "{stderr}"
    );
    for v in 0..4 {
        for c in 0..2 {
            let saved = std::fs::read(out.join(format!("cam{c}/{v:06}.pgm"))).unwrap();
            assert!(saved == view(c, v), "cam{c} set {v} is not board {c}'s view {v}");
        }
    }
    assert!(!out.join("cam0/000004.pgm").exists());
    assert_eq!(
        stdout.matches("cam1 board found (54 corners)").count(),
        4,
        "{stdout}"
    );
    assert_eq!(
        stdout.matches("boards paired within 1000 µs").count(),
        4,
        "{stdout}"
    );
    assert!(
        stdout.contains("saved 4 sets into") && stdout.contains("(1 refused"),
        "{stdout}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("cameras.csv")).unwrap(),
        format!("camera,board,board_camera,from\n0,b0,0,{addr_a}\n1,{addr_b},0,\n")
    );
    assert!(
        stdout.contains(&format!(
            "board {addr_b} reports no name ([cluster] board): cameras.csv holds its address and calibrate writes no placement"
        )),
        "{stdout}"
    );
    // Timestamps on the shared realtime clock, not the boards' monotonic ones.
    let ts = std::fs::read_to_string(out.join("timestamps.csv")).unwrap();
    assert!(
        ts.contains(&format!("0,0,{},0\n", EPOCH_NS + 6 * PERIOD_NS))
            && ts.contains(&format!("0,1,{},0\n", EPOCH_NS + 6 * PERIOD_NS + 1_000_000)),
        "{ts}"
    );

    // calibrate takes the folder as it is: two cameras, four views each (too few for a good
    // calibration, so --accept-poor; what is checked is that it reads and solves the folder).
    let images = irtrack_host_tools::calib::input::discover(&out, None).unwrap();
    assert_eq!(images.cameras.len(), 2);
    assert_eq!(images.complete_views, ["000000", "000001", "000002", "000003"]);
    assert!(images.incomplete_views.is_empty());
    let calib = dir.join("calib");
    let o = host_tools(&[
        "calibrate",
        "--images",
        p(&out),
        "--board-cols",
        "9",
        "--board-rows",
        "6",
        "--square-mm",
        "25",
        "--out-dir",
        p(&calib),
        "--accept-poor",
    ]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    let said = format!("{stdout}{stderr}");
    assert!(
        said.contains("2 cameras, 4 complete views")
            && said.contains("cam1 (cam1/): board found in 4 of 4 images"),
        "{said}"
    );
    assert!(calib.join("rig.irp").is_file() && calib.join("rig.yaml").is_file());
}

/// Boards that do not pair are never saved: ten refused sets in a row end the capture naming the
/// board and its offset. A board without the clock field, or one that does not answer, is named.
#[test]
fn capture_across_boards_refuses_unpaired_sets_and_names_silent_boards() {
    let dir = scratch("boards_refused");
    let size = (4, 2);
    let pgm = {
        let mut b = b"P5\n4 2\n255\n".to_vec();
        b.extend_from_slice(&[9; 8]);
        b
    };
    let responses = |b: bool| -> Responses {
        std::iter::once(status_of(if b { "b1" } else { "b0" }))
            .chain((0..12u64).map(|k| {
                let phase = if b && k >= 2 { 20_000_000 } else { 0 };
                board_set(b, k, phase, std::slice::from_ref(&pgm), size)
            }))
            .collect()
    };
    let out = dir.join("never");
    let run = capture(
        vec![responses(false), responses(true)],
        &out,
        &["--wand", "--count", "5"],
    );
    let (stdout, stderr) = text(&run.output);
    assert!(!run.output.status.success(), "{stdout}\n{stderr}");
    let (addr_a, addr_b) = (run.addrs[0].clone(), run.addrs[1].clone());
    assert_eq!(run.served(), [13, 13]);
    let offset = format!("board {addr_b}'s frames are +20.000 ms from board {addr_a}'s (tolerance 4.167 ms");
    assert_eq!(stderr.matches("set refused, not saved").count(), 9, "{stderr}");
    assert!(
        stderr.contains(&format!("10 sets in a row refused, the last: {offset}")),
        "{stderr}"
    );
    assert!(!out.join("cam0").exists(), "a mismatched set was saved");

    // irtrackd without the clock field.
    let run = capture(
        vec![
            vec![
                status_of("b0"),
                board_set(false, 0, 0, std::slice::from_ref(&pgm), size),
            ],
            vec![
                status_of("b1"),
                (
                    200,
                    "application/x-irtrack-frameset",
                    frameset_body(1, std::slice::from_ref(&pgm), size),
                ),
            ],
        ],
        &out,
        &["--wand"],
    );
    let (_, stderr) = text(&run.output);
    assert!(!run.output.status.success());
    assert!(
        stderr.contains(&format!(
            "irtrackd on {} does not serve its realtime clock difference",
            run.addrs[1]
        )),
        "{stderr}"
    );
    run.served();

    // Nothing listens on B. A port just freed may be handed out again, so B's is taken after
    // A's server holds its own (once both came out equal and capture refused `--from` twice).
    let (addr_a, _) = serve(vec![status_of("b0")]);
    let silent = (0..20)
        .map(|_| {
            let port = TcpListener::bind("127.0.0.1:0")
                .unwrap()
                .local_addr()
                .unwrap()
                .port();
            format!("127.0.0.1:{port}")
        })
        .find(|a| *a != addr_a)
        .expect("a free port other than A's");
    let out = dir.join("silent");
    let o = host_tools(&[
        "capture",
        "--from",
        &addr_a,
        "--from",
        &silent,
        "--out",
        p(&out),
        "--wand",
    ]);
    let (_, stderr) = text(&o);
    assert!(!o.status.success());
    assert!(
        stderr.contains(&format!("cannot reach irtrackd on {silent}")),
        "{stderr}"
    );
    assert!(!out.exists(), "{} created for nothing", out.display());
}

/// A standalone board's `/status` answer: no cluster section, so no name.
fn unnamed_status() -> (u16, &'static str, Vec<u8>) {
    (
        200,
        "application/json",
        b"{\"uptime_s\":1.0,\"cluster\":null}".to_vec(),
    )
}

/// A camera board's `/status` answer: the parts capture reads (`cluster.board`).
fn status_of(board: &str) -> (u16, &'static str, Vec<u8>) {
    (
        200,
        "application/json",
        format!("{{\"uptime_s\":3.5,\"cluster\":{{\"role\":\"camera\",\"rig\":\"cell1\",\"board\":\"{board}\",\"published\":7}}}}")
            .into_bytes(),
    )
}

/// The simulated 90° rig's parameter set with its two cameras placed on `placement`, written
/// to `path` as a blob the way push-params takes it.
fn placed_params(path: &Path, placement: &[(&str, u8)]) -> PathBuf {
    let mut rig = build_rig(
        &RigPreset::Convergent {
            distance_mm: 659.84,
            angle_deg: 90.0,
        },
        &CameraSpec::default(),
    )
    .unwrap();
    rig.rig_id = "cell1".into();
    rig.placement = placement
        .iter()
        .map(|(b, i)| irtrack_core::params::CameraPlace {
            board: (*b).into(),
            local_index: *i,
        })
        .collect();
    rig.validate().unwrap();
    std::fs::write(path, rig.to_blob().unwrap()).unwrap();
    path.to_path_buf()
}

/// The integrator gives the boards the other way round: board "b1" (the rig's camera 1) first.
/// With the placement the folder still has the rig's camera 0 in cam0/, and cameras.csv says
/// so by the boards' names; without it the --from order decides and capture says how to fix it.
#[test]
fn capture_across_boards_follows_the_rig_placement_not_the_from_order() {
    let dir = scratch("placement");
    let (files, size) = rig_views(&dir, 2);
    let view = |c: usize, v: usize| std::fs::read(&files[c][v]).unwrap();
    let params = placed_params(&dir.join("rig.irp"), &[("b0", 0), ("b1", 0)]);
    // Board b0 renders rig camera 0, b1 rig camera 1: status, two probe sets, two sets.
    let responses = |rig_camera: usize, name: &str| -> Responses {
        let b = rig_camera == 1;
        let mut r = vec![status_of(name)];
        r.push(board_set(b, 0, 0, &[view(rig_camera, 0)], size));
        r.push(board_set(b, 1, 0, &[view(rig_camera, 0)], size));
        for v in 0..2 {
            r.push(board_set(b, 2 + v as u64, 0, &[view(rig_camera, v)], size));
        }
        r
    };
    let out = dir.join("shots");
    let run = capture(
        vec![responses(1, "b1"), responses(0, "b0")],
        &out,
        &["--params", p(&params), "--wand", "--count", "2"],
    );
    let (stdout, stderr) = text(&run.output);
    print!("{stdout}{stderr}");
    assert!(run.output.status.success(), "{stdout}\n{stderr}");
    let (addr_b1, addr_b0) = (run.addrs[0].clone(), run.addrs[1].clone());
    assert_eq!(run.served(), [5, 5]);
    assert!(
        stdout.contains(&format!(
            "board b1 at {addr_b1}: 1 camera, {}x{} 8-bit → cam1..cam1",
            size.0, size.1
        )) && stdout.contains(&format!(
            "board b0 at {addr_b0}: 1 camera, {}x{} 8-bit → cam0..cam0",
            size.0, size.1
        )),
        "{stdout}"
    );
    assert!(
        stdout.contains("cameras numbered in the rig's order, as the placement in"),
        "{stdout}"
    );
    for v in 0..2 {
        for c in 0..2 {
            let saved = std::fs::read(out.join(format!("cam{c}/{v:06}.pgm"))).unwrap();
            assert!(
                saved == view(c, v),
                "cam{c} set {v} is not rig camera {c}'s view {v}"
            );
        }
    }
    assert_eq!(
        std::fs::read_to_string(out.join("cameras.csv")).unwrap(),
        format!("camera,board,board_camera,from\n0,b0,0,{addr_b0}\n1,b1,0,{addr_b1}\n")
    );
    // Timestamps follow their cameras: cam0's row is board b0's realtime (phase 0 on both).
    let ts = std::fs::read_to_string(out.join("timestamps.csv")).unwrap();
    assert!(
        ts.contains(&format!("0,0,{},0\n", EPOCH_NS + 2 * PERIOD_NS)),
        "{ts}"
    );

    // The same boards without --params: --from order (b1's camera is cam0), said in one line.
    let plain = dir.join("plain");
    let run = capture(
        vec![responses(1, "b1"), responses(0, "b0")],
        &plain,
        &["--wand", "--count", "2"],
    );
    let (stdout, stderr) = text(&run.output);
    assert!(run.output.status.success(), "{stdout}\n{stderr}");
    let run_addrs = run.addrs.clone();
    run.served();
    assert!(
        stdout.contains(
            "cameras numbered board by board in --from order, not by the rig's placement; give --params <the rig's parameter set>"
        ),
        "{stdout}"
    );
    assert!(std::fs::read(plain.join("cam0/000000.pgm")).unwrap() == view(1, 0));
    // The boards' reported names, in the --from order, so calibrate places the cameras.
    let (a1, a0) = (run_addrs[0].clone(), run_addrs[1].clone());
    assert!(
        stdout.contains(&format!("boards by the names they report: b1 ({a1}), b0 ({a0})")),
        "{stdout}"
    );
    assert_eq!(
        std::fs::read_to_string(plain.join("cameras.csv")).unwrap(),
        format!("camera,board,board_camera,from\n0,b1,0,{a1}\n1,b0,0,{a0}\n")
    );
    // A folder an older capture wrote (no from column) is not continued, and says why.
    let old = dir.join("old");
    std::fs::create_dir_all(old.join("cam0")).unwrap();
    std::fs::write(old.join("cam0/000000.pgm"), view(0, 0)).unwrap();
    std::fs::write(
        old.join("cameras.csv"),
        format!("camera,board,board_camera\n0,{a1},0\n1,{a0},0\n"),
    )
    .unwrap();
    let run = capture(
        vec![responses(1, "b1"), responses(0, "b0")],
        &old,
        &["--wand", "--count", "2"],
    );
    let (stdout, stderr) = text(&run.output);
    assert!(!run.output.status.success(), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("was written by an older capture (its cameras.csv has no from column"),
        "{stderr}"
    );
    assert!(!old.join("cam1").exists(), "saved into the old folder");
}

/// Runs capture with `--params` against boards that answer only their `/status` and then
/// `frames` probe sets; returns (stderr, addresses) after checking it failed and saved nothing.
fn refused_placement(
    dir: &Path,
    name: &str,
    params: &Path,
    boards: &[(&str, usize, usize)],
) -> (String, Vec<String>) {
    let pgm = {
        let mut b = b"P5\n4 2\n255\n".to_vec();
        b.extend_from_slice(&[9; 8]);
        b
    };
    let responses = boards
        .iter()
        .enumerate()
        .map(|(i, (board, cameras, probes))| {
            let mut r = vec![status_of(board)];
            for k in 0..*probes as u64 {
                r.push(board_set(i == 1, k, 0, &vec![pgm.clone(); *cameras], (4, 2)));
            }
            r
        })
        .collect();
    let out = dir.join(name);
    let run = capture(
        responses,
        &out,
        &["--params", p(params), "--wand", "--count", "2"],
    );
    let (stdout, stderr) = text(&run.output);
    assert!(!run.output.status.success(), "{stdout}\n{stderr}");
    assert!(
        !out.exists(),
        "{} created before the placement was checked",
        out.display()
    );
    let addrs = run.addrs.clone();
    run.served();
    (stderr, addrs)
}

#[test]
fn capture_with_a_placement_names_each_mismatch_before_saving() {
    let dir = scratch("placement_errors");
    let rig = placed_params(&dir.join("rig.irp"), &[("b0", 0), ("b1", 0)]);
    let rig_path = p(&rig);

    // Board b0 serves two cameras; the rig places only its camera 0.
    let (err, a) = refused_placement(&dir, "extra", &rig, &[("b0", 2, 1), ("b1", 1, 1)]);
    assert!(
        err.contains(&format!(
            "camera 1 of board b0 ({}) is not placed: no rig camera of the parameter set is on it",
            a[0]
        )) && err.contains(&format!("(placement of {rig_path})")),
        "{err}"
    );

    // The rig's camera 1 is on b1, but the boards given are b0 and b2.
    let (err, _) = refused_placement(&dir, "missing", &rig, &[("b0", 1, 1), ("b2", 1, 1)]);
    assert!(
        err.contains(
            "rig camera 1 is placed on board b1 (its camera 0), but no --from board reports that name (they report: b0, b2)"
        ),
        "{err}"
    );

    // Two boards report one name: said after their /status, before any frame is asked for.
    let (err, a) = refused_placement(&dir, "twice", &rig, &[("b0", 1, 0), ("b0", 1, 0)]);
    assert!(
        err.contains(&format!(
            "boards {} and {} both report the name b0 ([cluster] board)",
            a[0], a[1]
        )),
        "{err}"
    );

    // A placed camera index the board does not serve.
    let beyond = placed_params(&dir.join("beyond.irp"), &[("b0", 0), ("b1", 1)]);
    let (err, a) = refused_placement(&dir, "beyond", &beyond, &[("b0", 1, 1), ("b1", 1, 1)]);
    assert!(
        err.contains(&format!(
            "rig camera 1 is placed on board b1 ({}) as its camera 1, but that board serves 1 camera",
            a[1]
        )),
        "{err}"
    );
    // A single board's set (no placement) is refused by name, before any board is asked.
    let single = dir.join("single.irp");
    let mut one = irtrack_core::params::RigParams::from_blob(&std::fs::read(&beyond).unwrap()).unwrap();
    one.placement.clear();
    std::fs::write(&single, one.to_blob().unwrap()).unwrap();
    let (addr, server) = serve(Vec::new());
    let o = host_tools(&[
        "capture",
        "--from",
        &addr,
        "--params",
        p(&single),
        "--out",
        p(&dir.join("unplaced")),
        "--wand",
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success());
    assert!(
        err.contains(&format!(
            "{}: this parameter set places no camera on a board",
            p(&single)
        )),
        "{err}"
    );
    assert_eq!(server.join().unwrap(), 0);

    // A standalone board (no cluster section in its /status) has no name to place by.
    let (addr, server) = serve(vec![(
        200,
        "application/json",
        b"{\"uptime_s\":1.0,\"cluster\":null}".to_vec(),
    )]);
    let o = host_tools(&[
        "capture",
        "--from",
        &addr,
        "--params",
        p(&rig),
        "--out",
        p(&dir.join("standalone")),
        "--wand",
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success());
    assert!(
        err.contains(&format!(
            "irtrackd on {addr} reports no board name (/status has no cluster.board)"
        )),
        "{err}"
    );
    server.join().unwrap();
}
