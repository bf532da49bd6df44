//! The RAPID module implements the same protocol as the Rust codec: structure, constants, and
//! an emulation of its string parsing/formatting on every message kind at extreme values.

use std::collections::HashMap;

use irtrack_core::robot_proto::{self as rp, HoldReason, RobotMsg, TrackerMsg};

fn module() -> String {
    let p = concat!(env!("CARGO_MANIFEST_DIR"), "/../rapid/IrTrack.mod");
    std::fs::read_to_string(p).unwrap()
}

/// Code lines without comments and string literals (so keywords inside strings do not count).
fn code_lines(src: &str) -> Vec<String> {
    src.lines()
        .map(|l| {
            let mut out = String::new();
            let mut in_str = false;
            for c in l.chars() {
                match c {
                    '"' => in_str = !in_str,
                    '!' if !in_str => break,
                    _ if in_str => {}
                    _ => out.push(c),
                }
            }
            out.trim().to_string()
        })
        .filter(|l| !l.is_empty())
        .collect()
}

fn consts(src: &str) -> HashMap<String, f64> {
    let mut m = HashMap::new();
    for l in src.lines() {
        let l = l.trim();
        if let Some(rest) = l.strip_prefix("CONST num ") {
            let (name, val) = rest.split_once(":=").unwrap();
            m.insert(
                name.trim().to_string(),
                val.trim().trim_end_matches(';').trim().parse().unwrap(),
            );
        }
    }
    m
}

#[test]
fn rapid_module_structure_is_balanced() {
    check_structure(
        &module(),
        "IrTrack",
        &[
            "SocketCreate",
            "SocketBind",
            "SocketListen",
            "SocketAccept",
            "SocketReceive",
            "SocketSend",
            "SocketClose",
            "StrPart",
            "StrToVal",
            "MoveL",
            "ERR_SOCK_TIMEOUT",
            "ERR_SOCK_CLOSED",
            "StopMove",
            "ClearPath",
            "CRobT",
            "\\Tool:=irtTool",
            "\\WObj:=irtWobj",
            "irtSpeed",
            "irtZone",
            "irtSurvey",
            "irtSurveySpeed, fine, irtSurveyTool",
            "CRobT(\\Tool:=irtSurveyTool",
            "IrtSendPose",
        ],
    );
}

/// The EGM module (docs/robot-streaming.md) passes the same structure checks.
#[test]
fn rapid_egm_module_structure_is_balanced() {
    let p = concat!(env!("CARGO_MANIFEST_DIR"), "/../rapid/IrTrackEgm.mod");
    let src = std::fs::read_to_string(p).unwrap();
    check_structure(
        &src,
        "IrTrackEgm",
        &[
            "EGMGetId",
            "EGMGetState",
            "EGMSetupUC",
            "\\Pose",
            "\\CommTimeout:=",
            "EGMActPose",
            "\\MaxSpeedDeviation:=",
            "\\MaxPosDeviation:=",
            "EGMRunPose",
            "EGM_STOP_HOLD",
            "ERR_UDPUC_COMM",
            "EGMReset",
            "\\Tool:=egmTool",
            "\\WObj:=egmWobj",
        ],
    );
    // The cycle the module documents is the one the simulated controller runs by default.
    let sim = irtrack_robot::ctrl_sim::CtrlConfig::new(
        irtrack_robot::ctrl_sim::CtrlKind::Egm,
        "127.0.0.1:6510".parse().unwrap(),
    );
    assert_eq!(consts(&src).get("EGM_CYCLE_MS"), Some(&sim.cycle_ms));
}

/// Balanced blocks, statements ending in ';', the instructions `needed`, short literals.
fn check_structure(src: &str, name: &str, needed: &[&str]) {
    let lines = code_lines(src);
    let first = format!("MODULE {name}");
    assert_eq!(lines.first().map(String::as_str), Some(first.as_str()));
    assert_eq!(lines.last().map(String::as_str), Some("ENDMODULE"));
    // Block openers and closers must nest properly.
    let mut stack: Vec<&str> = Vec::new();
    for l in &lines {
        let first = l.split([' ', '(']).next().unwrap();
        let opener = match first {
            "MODULE" => Some("ENDMODULE"),
            "PROC" => Some("ENDPROC"),
            "FUNC" => Some("ENDFUNC"),
            "TRAP" => Some("ENDTRAP"),
            "WHILE" => Some("ENDWHILE"),
            "FOR" => Some("ENDFOR"),
            "TEST" => Some("ENDTEST"),
            "IF" if l.ends_with("THEN") => Some("ENDIF"),
            _ => None,
        };
        if let Some(close) = opener {
            stack.push(close);
        } else if first.starts_with("END") && first != "ENDFUNC;" {
            assert_eq!(stack.pop(), Some(first), "unbalanced at {l:?}");
        }
    }
    assert!(stack.is_empty(), "unclosed blocks {stack:?}");
    // Statements end with ';' except block lines.
    for l in &lines {
        let first = l.split([' ', '(']).next().unwrap();
        let block = matches!(
            first,
            "MODULE"
                | "ENDMODULE"
                | "PROC"
                | "ENDPROC"
                | "FUNC"
                | "ENDFUNC"
                | "WHILE"
                | "ENDWHILE"
                | "IF"
                | "ELSEIF"
                | "ELSE"
                | "ENDIF"
                | "ERROR"
        );
        assert!(block || l.ends_with(';'), "statement without ';': {l:?}");
    }
    for needed in needed {
        assert!(src.contains(needed), "module {name} lacks {needed}");
    }
    // Every string literal fits RAPID's 80-character string limit.
    for l in src.lines() {
        for (i, s) in l.split('"').enumerate() {
            if i % 2 == 1 {
                assert!(s.len() <= 80, "literal too long: {s:?}");
            }
        }
    }
}

#[test]
fn rapid_constants_match_the_codec() {
    let c = consts(&module());
    let expect = [
        ("IRT_VERSION", rp::PROTOCOL_VERSION as usize),
        ("IRT_MAX_LINE", rp::MAX_LINE_BYTES),
        ("IRT_SEQ_COL", rp::SEQ_COL),
        ("IRT_SEQ_LEN", rp::SEQ_LEN),
        ("IRT_COORD_LEN", rp::COORD_LEN),
        ("IRT_QUAT_LEN", rp::QUAT_LEN),
        ("IRT_T_X_COL", rp::T_X_COL),
        ("IRT_T_Y_COL", rp::T_Y_COL),
        ("IRT_T_Z_COL", rp::T_Z_COL),
        ("IRT_Q_Q1_COL", rp::Q_Q1_COL),
        ("IRT_HOLD_CODE_COL", rp::HOLD_CODE_COL),
        ("IRT_POSE_COL", rp::POSE_COL),
        ("IRT_REJ_UNREACHABLE", rp::reject::UNREACHABLE as usize),
        ("IRT_REJ_MALFORMED", rp::reject::MALFORMED as usize),
    ];
    for (name, v) in expect {
        assert_eq!(c.get(name).copied(), Some(v as f64), "{name}");
    }
    // The module's HELLO says the same version.
    assert!(module().contains(&format!("\"HELLO {:02} ROBOT \"", rp::PROTOCOL_VERSION)));
}

/// RAPID's StrPart: 1-based, errors when the range leaves the string.
fn str_part(s: &str, start: usize, len: usize) -> &str {
    assert!(
        start >= 1 && start - 1 + len <= s.len(),
        "StrPart({s:?}, {start}, {len}) out of range"
    );
    &s[start - 1..start - 1 + len]
}

/// Emulates IrtField: sign character, then StrToVal of the rest.
fn irt_field(f: &str) -> Option<f64> {
    let v: f64 = f[1..].parse().ok()?;
    match &f[..1] {
        "+" => Some(v),
        "-" => Some(-v),
        _ => None,
    }
}

/// The exact line lengths IrtDispatch accepts for T and Q, read from the module.
fn dispatch_len(src: &str, tag: &str) -> usize {
    let needle = format!("AND StrPart(line, 1, 2) = \"{tag} \"");
    let l = src.lines().find(|l| l.contains(&needle)).unwrap();
    let n = l.split("n = ").nth(1).unwrap().split_whitespace().next().unwrap();
    n.parse().unwrap()
}

#[test]
fn every_client_message_fits_the_rapid_parser() {
    let src = module();
    let c = consts(&src);
    let col = |k: &str| c[k] as usize;
    let (t_len, q_len) = (dispatch_len(&src, "T"), dispatch_len(&src, "Q"));
    let mut msgs = vec![
        TrackerMsg::Hello {
            version: rp::PROTOCOL_VERSION,
            name: "N".repeat(rp::MAX_NAME_CHARS),
        },
        TrackerMsg::Beat {
            counter: rp::SEQ_MODULUS - 1,
        },
        TrackerMsg::Bye,
        TrackerMsg::PoseRequest { counter: 0 },
        TrackerMsg::PoseRequest {
            counter: rp::SEQ_MODULUS - 1,
        },
    ];
    msgs.extend(HoldReason::ALL.iter().map(|&reason| TrackerMsg::Hold { reason }));
    for v in [-rp::MAX_COORD_MM, rp::MAX_COORD_MM, 0.0, 0.004, -1234.565] {
        for seq in [0, 1, rp::SEQ_MODULUS - 1] {
            msgs.push(TrackerMsg::Target {
                seq,
                pos_mm: [v, -v, v],
            });
            msgs.push(TrackerMsg::Pose {
                seq,
                pos_mm: [v, v, -v],
                quat_wxyz: [0.5, -0.5, 0.5, -0.5],
            });
            msgs.push(TrackerMsg::Pose {
                seq,
                pos_mm: [v; 3],
                quat_wxyz: [-1.0, 0.0, 0.0, 0.0],
            });
        }
    }
    for m in &msgs {
        let line = m.encode().unwrap();
        assert!(line.len() <= c["IRT_MAX_LINE"] as usize);
        // What IrtReadLine hands to IrtDispatch: the line without its newline.
        let s = line.as_str().strip_suffix('\n').unwrap();
        let n = s.len();
        match m {
            TrackerMsg::Target { seq, pos_mm } | TrackerMsg::Pose { seq, pos_mm, .. } => {
                let is_q = matches!(m, TrackerMsg::Pose { .. });
                assert_eq!(n, if is_q { q_len } else { t_len }, "{s:?}");
                let got_seq: f64 = str_part(s, col("IRT_SEQ_COL"), col("IRT_SEQ_LEN"))
                    .parse()
                    .unwrap();
                assert_eq!(got_seq as u32, *seq);
                for (k, name) in ["IRT_T_X_COL", "IRT_T_Y_COL", "IRT_T_Z_COL"].iter().enumerate() {
                    let v = irt_field(str_part(s, col(name), col("IRT_COORD_LEN"))).unwrap();
                    assert!((v - pos_mm[k]).abs() <= 0.005 + 1e-9, "{s:?} axis {k}: {v}");
                }
                if let TrackerMsg::Pose { quat_wxyz, .. } = m {
                    for (k, q) in quat_wxyz.iter().enumerate() {
                        let f = str_part(s, col("IRT_Q_Q1_COL") + 10 * k, col("IRT_QUAT_LEN"));
                        assert!((irt_field(f).unwrap() - q).abs() < 1e-6, "{s:?}");
                    }
                }
            }
            TrackerMsg::Hold { reason } => {
                assert!(n >= 8 && &s[..5] == "HOLD ");
                let code: u8 = str_part(s, col("IRT_HOLD_CODE_COL"), 2).parse().unwrap();
                assert_eq!(code, reason.code());
            }
            TrackerMsg::Beat { .. } => assert!(n == 11 && &s[..5] == "BEAT "),
            TrackerMsg::PoseRequest { counter } => {
                assert!(n == 11 && &s[..5] == "POSE ", "{s:?}");
                let got: u32 = str_part(s, col("IRT_POSE_COL"), col("IRT_SEQ_LEN"))
                    .parse()
                    .unwrap();
                assert_eq!(got, *counter);
            }
            TrackerMsg::Hello { .. } => assert!(n >= 17 && &s[..6] == "HELLO " && &s[6..8] == "01"),
            TrackerMsg::Bye => assert_eq!(s, "BYE"),
        }
    }
}

/// Emulates IrtDigits / IrtCoord from the module.
fn irt_digits(v: f64, width: usize) -> String {
    format!("{:0width$}", v.round() as i64)
}
fn irt_coord(v: f64) -> String {
    let sign = if v < 0.0 { "-" } else { "+" };
    let cents = ((v.abs() * 100.0).round()).min(999_999.0);
    format!(
        "{sign}{}.{}",
        irt_digits((cents / 100.0).floor(), 4),
        irt_digits(cents % 100.0, 2)
    )
}

/// Emulates IrtQuat from the module.
fn irt_quat(v: f64) -> String {
    let sign = if v < 0.0 { "-" } else { "+" };
    let u = (v.abs() * 1e6).round().min(1e6);
    format!(
        "{sign}{}.{}",
        irt_digits((u / 1e6).floor(), 1),
        irt_digits(u % 1e6, 6)
    )
}

#[test]
fn lines_the_rapid_module_builds_parse_in_rust() {
    let src = module();
    // The credit line layout as the module concatenates it.
    assert!(src.contains(
        "\"C \" + IrtDigits(irtAckSeq, 6) + \" \" + IrtDigits(IRT_WINDOW, 2) + \" \" + IrtCoord(now.trans.x)"
    ));
    for (seq, x) in [
        (0.0, 0.0),
        (999_999.0, -9999.994),
        (17.0, 123.456),
        (1.0, 20000.0),
        (5.0, -0.001),
    ] {
        let line = format!(
            "C {} {} {} {} {}",
            irt_digits(seq, 6),
            irt_digits(1.0, 2),
            irt_coord(x),
            irt_coord(-x),
            irt_coord(400.0)
        );
        let m = RobotMsg::parse(&line).unwrap_or_else(|e| panic!("{line:?}: {e}"));
        let RobotMsg::Credit {
            ack_seq,
            window,
            pos_mm,
        } = m
        else {
            panic!()
        };
        assert_eq!((ack_seq, window), (seq as u32, 1));
        assert!((pos_mm[0] - x.clamp(-9999.99, 9999.99)).abs() < 0.006, "{line}");
    }
    for reason in ["MALFORMED", "UNREACHABLE", "OUTSIDE_BOX"] {
        assert!(src.contains(&format!("\"{reason}\"")));
        let line = format!("X {} {} {reason}", irt_digits(42.0, 6), irt_digits(1.0, 2));
        assert!(matches!(
            RobotMsg::parse(&line).unwrap(),
            RobotMsg::Reject { seq: 42, .. }
        ));
    }
    // The survey's pose answer as the module concatenates it (Q layout, IrtQuat components).
    assert!(src.contains(
        "\"A \" + IrtDigits(c, 6) + \" \" + IrtCoord(now.trans.x) + \" \" + IrtCoord(now.trans.y) + \" \" + IrtCoord(now.trans.z) + \" \" + IrtQuat(now.rot.q1)"
    ));
    for (x, q) in [
        (612.5, [0.0, 0.0, 1.0, 0.0]),
        (-9999.994, [0.5, -0.5, 0.5, -0.5]),
        (0.004, [0.6, 0.0, -0.8, 0.0]),
    ] {
        let line = format!(
            "A {} {} {} {} {} {} {} {}",
            irt_digits(17.0, 6),
            irt_coord(x),
            irt_coord(-x),
            irt_coord(220.0),
            irt_quat(q[0]),
            irt_quat(q[1]),
            irt_quat(q[2]),
            irt_quat(q[3])
        );
        let m = RobotMsg::parse(&line).unwrap_or_else(|e| panic!("{line:?}: {e}"));
        let RobotMsg::Actual {
            counter,
            pos_mm,
            quat_wxyz,
        } = m
        else {
            panic!("{line}")
        };
        assert_eq!(counter, 17);
        assert!((pos_mm[0] - x).abs() < 0.006, "{line}");
        for k in 0..4 {
            assert!((quat_wxyz[k] - q[k]).abs() < 1e-6, "{line}");
        }
    }
    let beat = format!("BEAT {}", irt_digits(999_999.0, 6));
    assert_eq!(
        RobotMsg::parse(&beat).unwrap(),
        RobotMsg::Beat { counter: 999_999 }
    );
}
