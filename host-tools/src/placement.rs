//! Where each camera of a parameter set sits when the cameras are on several boards (the
//! blob's `placement`, docs/param-blob.md and docs/cluster.md): from a capture folder's
//! `cameras.csv` or a `--placement b0:0,b0:1,b1:0` option, checked against the set's cameras.

use std::path::Path;

use anyhow::{Context, Result, anyhow, bail};
use irtrack_core::params::{CameraPlace, RigParams};

/// The capture folder's file naming each camera's board: `camera,board,board_camera,from`
/// (written by `host-tools capture` across boards).
pub const CAMERAS_FILE: &str = "cameras.csv";

/// Parses `BOARD:INDEX,BOARD:INDEX,…` (camera 0 first). Each entry is checked for its form
/// here; names and duplicates against the set in [`apply`].
pub fn parse(spec: &str) -> Result<Vec<CameraPlace>> {
    let mut out = Vec::new();
    for (i, entry) in spec.split(',').enumerate() {
        let entry = entry.trim();
        let (board, index) = entry.rsplit_once(':').ok_or_else(|| {
            anyhow!("--placement entry {i} ({entry:?}) is not BOARD:INDEX (e.g. b0:1, the camera's board and its index there)")
        })?;
        let local_index: u8 = index.trim().parse().map_err(|_| {
            anyhow!("--placement entry {i} ({entry:?}): camera index {index:?} is not a number 0..=255")
        })?;
        let board = board.trim();
        if board.is_empty() {
            bail!("--placement entry {i} ({entry:?}) has no board name");
        }
        out.push(CameraPlace {
            board: board.to_string(),
            local_index,
        });
    }
    Ok(out)
}

/// `cam0 = b0/0, cam1 = b0/1, …`
pub fn describe(placement: &[CameraPlace]) -> String {
    placement
        .iter()
        .enumerate()
        .map(|(i, p)| format!("cam{i} = {}/{}", p.board, p.local_index))
        .collect::<Vec<_>>()
        .join(", ")
}

/// What a capture folder's `cameras.csv` says about board names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CamerasFile {
    /// No `cameras.csv` (one board's capture, or no capture folder).
    Absent,
    /// Every board reported its name: the placement, camera 0 first.
    Named(Vec<CameraPlace>),
    /// The board column holds addresses (a board reported no name, or the file was written
    /// before capture recorded names); why, for one line of output.
    Unnamed(String),
}

/// Reads `DIR/cameras.csv`. Rows must be cameras 0, 1, … in order; a malformed file is an
/// error naming the line.
pub fn read_cameras_file(dir: &Path) -> Result<CamerasFile> {
    let path = dir.join(CAMERAS_FILE);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(CamerasFile::Absent),
        Err(e) => return Err(e).with_context(|| format!("{}: cannot read", path.display())),
    };
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').map(str::trim).collect();
    if header.get(..3) != Some(&["camera", "board", "board_camera"][..]) {
        bail!(
            "{}: header {:?} is not camera,board,board_camera[,from]",
            path.display(),
            header.join(",")
        );
    }
    let has_from = header.get(3) == Some(&"from");
    let mut placement = Vec::new();
    let mut unnamed = Vec::new();
    for (n, line) in lines.enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        let bad = |what: &str| anyhow!("{} line {}: {what} ({line:?})", path.display(), n + 2);
        if f.len() < 3 {
            return Err(bad("expected camera,board,board_camera"));
        }
        let camera: usize = f[0].parse().map_err(|_| bad("camera is not a number"))?;
        if camera != placement.len() {
            return Err(bad(&format!(
                "camera {camera} where camera {} belongs",
                placement.len()
            )));
        }
        let local_index: u8 = f[2]
            .parse()
            .map_err(|_| bad("board_camera is not a number 0..=255"))?;
        // `from` is empty when the board reported no name: `board` is then its address.
        if !has_from || f.get(3).is_none_or(|s| s.is_empty()) {
            unnamed.push(f[1].to_string());
        }
        placement.push(CameraPlace {
            board: f[1].to_string(),
            local_index,
        });
    }
    if !has_from {
        return Ok(CamerasFile::Unnamed(
            "written before capture recorded board names (its board column holds the --from addresses)"
                .into(),
        ));
    }
    if !unnamed.is_empty() {
        unnamed.dedup();
        return Ok(CamerasFile::Unnamed(format!(
            "board {} reported no name (/status has no cluster.board)",
            unnamed.join(", ")
        )));
    }
    Ok(CamerasFile::Named(placement))
}

/// One entry per camera of a set of `n_cameras`, no board camera twice; `source` names the
/// list in the error.
pub fn check_list(placement: &[CameraPlace], n_cameras: usize, source: &str) -> Result<()> {
    if placement.len() != n_cameras {
        bail!(
            "{source} places {} camera{}, the parameter set has {n_cameras}",
            placement.len(),
            if placement.len() == 1 { "" } else { "s" }
        );
    }
    for (i, p) in placement.iter().enumerate() {
        if let Some(j) = placement[..i].iter().position(|q| q == p) {
            bail!(
                "{source}: cameras {j} and {i} are both placed on board {} camera {}; each board camera holds one rig camera",
                p.board,
                p.local_index
            );
        }
    }
    Ok(())
}

/// A `--placement` option checked against a set of `n_cameras` before any work is done.
pub fn parse_for(spec: &str, n_cameras: usize) -> Result<Vec<CameraPlace>> {
    let placement = parse(spec)?;
    check_list(&placement, n_cameras, "--placement")?;
    Ok(placement)
}

/// Before a calibration of `dir` with `n_cameras`: a wrong `--placement` or `cameras.csv` is
/// said now, not after the work.
pub fn precheck(dir: &Path, option: Option<&str>, n_cameras: usize) -> Result<()> {
    match option {
        Some(spec) => parse_for(spec, n_cameras).map(drop),
        None => match read_cameras_file(dir)? {
            CamerasFile::Named(p) => check_list(&p, n_cameras, &dir.join(CAMERAS_FILE).display().to_string()),
            _ => Ok(()),
        },
    }
}

/// Sets `rig.placement` to `placement` after checking it ([`check_list`], then the set's own
/// rules, e.g. board names, through [`RigParams::validate`]); on an error the set keeps its
/// old placement.
pub fn apply(rig: &mut RigParams, placement: Vec<CameraPlace>, source: &str) -> Result<()> {
    check_list(&placement, rig.cameras.len(), source)?;
    let old = std::mem::replace(&mut rig.placement, placement);
    if let Err(e) = rig.validate() {
        rig.placement = old;
        return Err(anyhow!("{source}: {e}"));
    }
    Ok(())
}

/// The placement a calibration of `dir` writes: `--placement` when given, else the folder's
/// `cameras.csv` when every board there has a name; prints one line saying which. Empty (one
/// board) when neither.
pub fn for_calibration(rig: &mut RigParams, dir: &Path, option: Option<&str>) -> Result<()> {
    if let Some(spec) = option {
        apply(rig, parse(spec)?, "--placement")?;
        println!("placement from --placement: {}", describe(&rig.placement));
        return Ok(());
    }
    match read_cameras_file(dir)? {
        CamerasFile::Absent => {}
        CamerasFile::Named(p) => {
            let source = dir.join(CAMERAS_FILE).display().to_string();
            apply(rig, p, &source)?;
            println!("placement from {source}: {}", describe(&rig.placement));
        }
        CamerasFile::Unnamed(why) => println!(
            "no placement: {} {why}; give --placement BOARD:INDEX,… for a set pushed to a cluster solver",
            dir.join(CAMERAS_FILE).display()
        ),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn place(b: &str, i: u8) -> CameraPlace {
        CameraPlace {
            board: b.into(),
            local_index: i,
        }
    }

    #[test]
    fn parses_entries_and_names_malformed_ones() {
        assert_eq!(
            parse("b0:0, b0:1,b1:0").unwrap(),
            vec![place("b0", 0), place("b0", 1), place("b1", 0)]
        );
        assert_eq!(
            parse("b0:0,b0").unwrap_err().to_string(),
            "--placement entry 1 (\"b0\") is not BOARD:INDEX (e.g. b0:1, the camera's board and its index there)"
        );
        assert_eq!(
            parse("b0:x").unwrap_err().to_string(),
            "--placement entry 0 (\"b0:x\"): camera index \"x\" is not a number 0..=255"
        );
        assert_eq!(
            parse("b0:256").unwrap_err().to_string(),
            "--placement entry 0 (\"b0:256\"): camera index \"256\" is not a number 0..=255"
        );
        assert_eq!(
            parse(":1").unwrap_err().to_string(),
            "--placement entry 0 (\":1\") has no board name"
        );
    }

    /// The simulated two-camera rig.
    fn rig() -> RigParams {
        use irtrack_sim::rig::{CameraSpec, RigPreset, build_rig};
        build_rig(
            &RigPreset::Convergent {
                distance_mm: 1000.0,
                angle_deg: 90.0,
            },
            &CameraSpec::default(),
        )
        .unwrap()
    }

    #[test]
    fn apply_checks_count_duplicates_and_names_and_keeps_the_old_placement() {
        let mut r = rig();
        assert_eq!(
            apply(&mut r, vec![place("b0", 0)], "--placement")
                .unwrap_err()
                .to_string(),
            "--placement places 1 camera, the parameter set has 2"
        );
        assert_eq!(
            apply(&mut r, vec![place("b0", 1), place("b0", 1)], "--placement")
                .unwrap_err()
                .to_string(),
            "--placement: cameras 0 and 1 are both placed on board b0 camera 1; each board camera holds one rig camera"
        );
        let err = apply(&mut r, vec![place("b0", 0), place("10.0.0.5:7704", 0)], "x.csv")
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("x.csv: ") && err.contains("camera 1: board name \"10.0.0.5:7704\""),
            "{err}"
        );
        assert!(r.placement.is_empty());
        apply(&mut r, vec![place("b1", 0), place("b0", 0)], "--placement").unwrap();
        assert_eq!(describe(&r.placement), "cam0 = b1/0, cam1 = b0/0");
        // The placed set round-trips through the blob (format v4).
        let back = RigParams::from_blob(&r.to_blob().unwrap()).unwrap();
        assert_eq!(back.placement, r.placement);
    }

    #[test]
    fn cameras_file_named_unnamed_old_and_malformed() {
        let dir = std::env::temp_dir().join(format!("irtrack-placement-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let write = |s: &str| std::fs::write(dir.join(CAMERAS_FILE), s).unwrap();
        std::fs::remove_file(dir.join(CAMERAS_FILE)).ok();
        assert_eq!(read_cameras_file(&dir).unwrap(), CamerasFile::Absent);
        write("camera,board,board_camera,from\n0,b0,0,h0:7704\n1,b1,0,h1:7704\n");
        assert_eq!(
            read_cameras_file(&dir).unwrap(),
            CamerasFile::Named(vec![place("b0", 0), place("b1", 0)])
        );
        write("camera,board,board_camera\n0,h0:7704,0\n1,h1:7704,0\n");
        assert!(
            matches!(read_cameras_file(&dir).unwrap(), CamerasFile::Unnamed(w) if w.starts_with("written before"))
        );
        write("camera,board,board_camera,from\n0,b0,0,h0\n1,h1:7704,0,\n");
        assert_eq!(
            read_cameras_file(&dir).unwrap(),
            CamerasFile::Unnamed("board h1:7704 reported no name (/status has no cluster.board)".into())
        );
        write("camera,board,board_camera,from\n1,b0,0,h0\n");
        let err = read_cameras_file(&dir).unwrap_err().to_string();
        assert!(
            err.ends_with("line 2: camera 1 where camera 0 belongs (\"1,b0,0,h0\")"),
            "{err}"
        );
        write("cam,board\n");
        assert!(
            read_cameras_file(&dir)
                .unwrap_err()
                .to_string()
                .contains("is not camera,board,board_camera[,from]")
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
