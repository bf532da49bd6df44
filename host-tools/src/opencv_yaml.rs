//! Rig parameters as OpenCV FileStorage YAML, written and read through OpenCV itself so
//! that OpenCV tools certainly accept the files.
//!
//! Names follow OpenCV's calibration samples; cameras are numbered from 1 as there
//! (`K1` is camera 0 of [`RigParams`]):
//!
//! | key                               | content                                                 |
//! |-----------------------------------|---------------------------------------------------------|
//! | `rig_id`                          | string (optional on read: default from the file name)   |
//! | `created_unix_s`                  | real (integral seconds)                                 |
//! | `calibration_time`                | string, ISO 8601 UTC (informational, ignored on read)   |
//! | `camera_count`                    | int N (optional on read: counts `K1`, `K2`, ...)        |
//! | `image_width`, `image_height`     | int, camera 1's image size (OpenCV samples' names)      |
//! | `image_width_<n>`, `image_height_<n>` | int, camera n's size (on read falls back to the above) |
//! | `K<n>` (read also `M<n>`)         | 3×3 camera matrix, no skew                             |
//! | `D<n>`                            | 1×5 distortion k1 k2 p1 p2 k3 (4..14 entries read, extras must be 0) |
//! | `R`, `T`                          | camera 2 from camera 1: `x2 = R x1 + T`, T in mm (as stereoCalibrate) |
//! | `R<n>`, `T<n>` (n ≥ 3)            | camera n from camera 1, same convention                 |
//! | `R_world`, `T_world`              | optional registration world-from-camera-1               |
//! | `tool_count`, `tool<j>_name`, `tool<j>_leds_mm` | optional tools (j from 1), LEDs as M×3 mm  |
//! | `tool<j>_tip_mm`                  | optional 1×3 tool tip in the tool frame, mm (pivot)     |
//! | `serial`                          | string, decimal (the set's serial, version 5; absent = 0) |
//! | `timing_<n>`                      | optional 1×4 shutter (0 global, 1 rolling), line_time_ns, exposure_ns, offset_ns of camera n (version 5) |
//! | `calibration_method`, `calibration_unix_s`, `calibration_tool`, `calibration_verdict` (`good`/`poor`), `calibration_summary`, `calibration_rms_px` (1×N), `calibration_figure_count`, `calibration_figure<j>_name`, `calibration_figure<j>` | optional calibration record (docs/param-blob.md, version 3) |

use std::path::Path;

use anyhow::{Context, Result, anyhow, bail, ensure};
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::params::{
    CalibrationInfo, CameraParams, Figure, MAX_RIG_ID_LEN, RigParams, ToolDefinition, Verdict,
    looks_like_blob,
};
use irtrack_core::timing::{CameraTiming, Shutter};
use opencv::core::{
    CV_64F, FileNode, FileNode_MAP, FileNode_TYPE_MASK, FileNodeTraitConst, FileStorage, FileStorage_Mode,
    FileStorageTrait, FileStorageTraitConst, Mat, MatTraitConst,
};

fn path_str(path: &Path) -> Result<&str> {
    path.to_str()
        .ok_or_else(|| anyhow!("{}: path is not UTF-8 (OpenCV needs UTF-8 paths)", path.display()))
}

fn mat(rows: &[&[f64]]) -> Result<Mat> {
    Ok(Mat::from_slice_2d(rows)?)
}

/// ISO 8601 UTC from Unix seconds (civil-from-days, proleptic Gregorian).
pub fn iso_utc(unix_s: u64) -> String {
    let days = (unix_s / 86_400) as i64;
    let secs = unix_s % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        secs / 3600,
        (secs / 60) % 60,
        secs % 60
    )
}

fn write_transform(fs: &mut FileStorage, r_key: &str, t_key: &str, t: &RigidTransform) -> Result<()> {
    let r = &t.r_row_major;
    fs.write_mat(r_key, &mat(&[&r[0..3], &r[3..6], &r[6..9]])?)?;
    fs.write_mat(t_key, &mat(&[&[t.t_mm[0]], &[t.t_mm[1]], &[t.t_mm[2]]])?)?;
    Ok(())
}

/// Writes `rig` as OpenCV YAML (names in the module documentation).
pub fn write_rig_yaml(path: &Path, rig: &RigParams) -> Result<()> {
    ensure!(
        !rig.cameras.is_empty(),
        "{}: rig has no cameras to write",
        path.display()
    );
    let flags = FileStorage_Mode::WRITE as i32 | FileStorage_Mode::FORMAT_YAML as i32;
    let mut fs = FileStorage::new(path_str(path)?, flags, "")
        .with_context(|| format!("{}: OpenCV cannot open for writing", path.display()))?;
    ensure!(
        fs.is_opened()?,
        "{}: OpenCV cannot open for writing",
        path.display()
    );
    let write = |fs: &mut FileStorage| -> Result<()> {
        fs.write_str("rig_id", &rig.rig_id)?;
        // Real, not int: OpenCV ints are 32-bit; f64 is exact for any plausible time.
        fs.write_f64("created_unix_s", rig.created_unix_s as f64)?;
        fs.write_str("calibration_time", &iso_utc(rig.created_unix_s))?;
        let n = i32::try_from(rig.cameras.len())?;
        fs.write_i32("camera_count", n)?;
        let size0 = rig.cameras[0].model.image_size;
        fs.write_i32("image_width", i32::try_from(size0.width_px)?)?;
        fs.write_i32("image_height", i32::try_from(size0.height_px)?)?;
        for (i, cam) in rig.cameras.iter().enumerate() {
            let n = i + 1;
            let k = &cam.model.intrinsics;
            fs.write_i32(
                &format!("image_width_{n}"),
                i32::try_from(cam.model.image_size.width_px)?,
            )?;
            fs.write_i32(
                &format!("image_height_{n}"),
                i32::try_from(cam.model.image_size.height_px)?,
            )?;
            fs.write_mat(
                &format!("K{n}"),
                &mat(&[
                    &[k.fx_px, 0.0, k.cx_px],
                    &[0.0, k.fy_px, k.cy_px],
                    &[0.0, 0.0, 1.0],
                ])?,
            )?;
            fs.write_mat(&format!("D{n}"), &mat(&[&cam.model.distortion.as_array()])?)?;
        }
        for (i, cam) in rig.cameras.iter().enumerate().skip(1) {
            let (r_key, t_key) = if i == 1 {
                ("R".to_string(), "T".to_string())
            } else {
                pose_keys(i + 1)
            };
            write_transform(fs, &r_key, &t_key, &cam.cam_from_cam0)?;
        }
        if let Some(w) = &rig.world_from_cam0 {
            write_transform(fs, "R_world", "T_world", w)?;
        }
        if !rig.tools.is_empty() {
            fs.write_i32("tool_count", i32::try_from(rig.tools.len())?)?;
            for (j, tool) in rig.tools.iter().enumerate() {
                fs.write_str(&format!("tool{}_name", j + 1), &tool.name)?;
                if !tool.leds_mm.is_empty() {
                    let rows: Vec<&[f64]> = tool.leds_mm.iter().map(|p| &p[..]).collect();
                    fs.write_mat(&format!("tool{}_leds_mm", j + 1), &mat(&rows)?)?;
                }
                if let Some(tip) = &tool.tip_mm {
                    fs.write_mat(&format!("tool{}_tip_mm", j + 1), &mat(&[&tip[..]])?)?;
                }
            }
        }
        if let Some(c) = &rig.calibration {
            write_calibration(fs, c)?;
        }
        if rig.serial != 0 {
            // A string: OpenCV ints are 32-bit and reals exact only to 2^53.
            fs.write_str("serial", &rig.serial.to_string())?;
        }
        if rig.has_timing() {
            for i in 0..rig.cameras.len() {
                let t = rig.camera_timing(i);
                let shutter = match t.shutter {
                    Shutter::Global => 0.0,
                    Shutter::Rolling => 1.0,
                };
                let row = [
                    shutter,
                    f64::from(t.line_time_ns),
                    f64::from(t.exposure_ns),
                    t.offset_ns as f64,
                ];
                fs.write_mat(&format!("timing_{}", i + 1), &mat(&[&row])?)?;
            }
        }
        fs.release()?;
        Ok(())
    };
    write(&mut fs).with_context(|| format!("{}: writing OpenCV YAML failed", path.display()))
}

fn pose_keys(n: usize) -> (String, String) {
    (format!("R{n}"), format!("T{n}"))
}

fn node(fs: &FileStorage, key: &str) -> Result<Option<FileNode>> {
    let n = fs.get(key)?;
    Ok(if n.empty()? || n.is_none()? { None } else { Some(n) })
}

fn required(fs: &FileStorage, key: &str, what: &str) -> Result<FileNode> {
    node(fs, key)?.ok_or_else(|| anyhow!("missing `{key}` ({what})"))
}

fn read_mat(n: &FileNode, key: &str) -> Result<(usize, usize, Vec<f64>)> {
    let m = n
        .mat()
        .with_context(|| format!("`{key}` is not an !!opencv-matrix"))?;
    ensure!(!m.empty(), "`{key}` is not an !!opencv-matrix (or is empty)");
    let mut m64 = Mat::default();
    m.convert_to(&mut m64, CV_64F, 1.0, 0.0)?;
    let (rows, cols) = (m64.rows(), m64.cols());
    let mut out = Vec::with_capacity((rows * cols) as usize);
    for r in 0..rows {
        for c in 0..cols {
            out.push(*m64.at_2d::<f64>(r, c)?);
        }
    }
    Ok((rows as usize, cols as usize, out))
}

fn read_fixed(fs: &FileStorage, key: &str, what: &str, rows: usize, cols: usize) -> Result<Vec<f64>> {
    let (r, c, v) = read_mat(&required(fs, key, what)?, key)?;
    // A 1×3 or 3×1 vector is the same thing; accept either orientation for vectors.
    let ok = (r, c) == (rows, cols) || (rows.min(cols) == 1 && r * c == rows * cols && r.min(c) == 1);
    ensure!(ok, "`{key}` ({what}) is {r}×{c}, expected {rows}×{cols}");
    Ok(v)
}

fn read_int(fs: &FileStorage, key: &str) -> Result<Option<i64>> {
    let Some(n) = node(fs, key)? else { return Ok(None) };
    ensure!(n.is_int()? || n.is_real()?, "`{key}` must be a number");
    let v = n.real()?;
    ensure!(
        v.fract() == 0.0 && v.is_finite(),
        "`{key}` = {v} must be an integer"
    );
    Ok(Some(v as i64))
}

fn read_size(fs: &FileStorage, n: usize) -> Result<ImageSize> {
    let dim = |specific: String, general: &str| -> Result<u32> {
        let v = match read_int(fs, &specific)? {
            Some(v) => v,
            None => read_int(fs, general)?
                .ok_or_else(|| anyhow!("missing `{specific}` and `{general}` (camera {n} image size)"))?,
        };
        u32::try_from(v).map_err(|_| anyhow!("`{specific}`/`{general}` = {v} is not a valid size"))
    };
    Ok(ImageSize {
        width_px: dim(format!("image_width_{n}"), "image_width")?,
        height_px: dim(format!("image_height_{n}"), "image_height")?,
    })
}

fn read_camera_matrix(fs: &FileStorage, n: usize) -> Result<Intrinsics> {
    let key = if node(fs, &format!("K{n}"))?.is_some() {
        format!("K{n}")
    } else {
        format!("M{n}")
    };
    let k = read_fixed(fs, &key, &format!("camera {n} matrix"), 3, 3)?;
    ensure!(
        k[1].abs() < 1e-9,
        "`{key}`: skew {} is not supported (must be 0)",
        k[1]
    );
    ensure!(
        k[3] == 0.0 && k[6] == 0.0 && k[7] == 0.0 && (k[8] - 1.0).abs() < 1e-12,
        "`{key}` is not a camera matrix (last row must be 0 0 1, K[1][0] = 0)"
    );
    Ok(Intrinsics {
        fx_px: k[0],
        fy_px: k[4],
        cx_px: k[2],
        cy_px: k[5],
    })
}

fn read_transform(fs: &FileStorage, r_key: &str, t_key: &str, what: &str) -> Result<RigidTransform> {
    let r = read_fixed(fs, r_key, what, 3, 3)?;
    let t = read_fixed(fs, t_key, what, 3, 1)?;
    let mut r_row_major = [0.0; 9];
    r_row_major.copy_from_slice(&r);
    Ok(RigidTransform {
        r_row_major,
        t_mm: [t[0], t[1], t[2]],
    })
}

/// A rig id made from a file name: the stem, with anything that is not printable ASCII (or
/// is a space) replaced by `-`, cut to [`MAX_RIG_ID_LEN`] bytes, so that it validates.
pub fn rig_id_from_path(path: &Path) -> String {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let id: String = stem
        .chars()
        .map(|c| if c.is_ascii_graphic() { c } else { '-' })
        .take(MAX_RIG_ID_LEN)
        .collect();
    if id.is_empty() {
        "opencv-calibration".into()
    } else {
        id
    }
}

fn write_calibration(fs: &mut FileStorage, c: &CalibrationInfo) -> Result<()> {
    fs.write_str("calibration_method", &c.method)?;
    fs.write_f64("calibration_unix_s", c.calibrated_unix_s as f64)?;
    fs.write_str("calibration_tool", &c.tool_version)?;
    fs.write_str("calibration_verdict", c.verdict.as_str())?;
    if !c.summary.is_empty() {
        fs.write_str("calibration_summary", &c.summary)?;
    }
    if !c.rms_px.is_empty() {
        fs.write_mat("calibration_rms_px", &mat(&[&c.rms_px])?)?;
    }
    fs.write_i32("calibration_figure_count", i32::try_from(c.figures.len())?)?;
    for (j, f) in c.figures.iter().enumerate() {
        fs.write_str(&format!("calibration_figure{}_name", j + 1), &f.name)?;
        fs.write_f64(&format!("calibration_figure{}", j + 1), f.value)?;
    }
    Ok(())
}

fn read_string(fs: &FileStorage, key: &str) -> Result<Option<String>> {
    match node(fs, key)? {
        None => Ok(None),
        Some(n) => Ok(Some(
            n.to_string()
                .with_context(|| format!("`{key}` must be a string"))?,
        )),
    }
}

fn read_calibration(fs: &FileStorage) -> Result<Option<CalibrationInfo>> {
    let Some(method) = read_string(fs, "calibration_method")? else {
        return Ok(None);
    };
    let when = required(fs, "calibration_unix_s", "calibration time")?.real()?;
    ensure!(
        when >= 0.0 && when.fract() == 0.0 && when < 2f64.powi(53),
        "`calibration_unix_s` = {when} is not a time"
    );
    let verdict = match read_string(fs, "calibration_verdict")?.as_deref() {
        Some("good") => Verdict::Good,
        Some("poor") => Verdict::Poor,
        other => bail!("`calibration_verdict` must be \"good\" or \"poor\", got {other:?}"),
    };
    let rms_px = match node(fs, "calibration_rms_px")? {
        None => Vec::new(),
        Some(n) => read_mat(&n, "calibration_rms_px")?.2,
    };
    let mut figures = Vec::new();
    for j in 1..=read_int(fs, "calibration_figure_count")?.unwrap_or(0) {
        let name = read_string(fs, &format!("calibration_figure{j}_name"))?
            .ok_or_else(|| anyhow!("missing `calibration_figure{j}_name`"))?;
        let value = required(fs, &format!("calibration_figure{j}"), "calibration figure")?.real()?;
        figures.push(Figure { name, value });
    }
    Ok(Some(CalibrationInfo {
        method,
        calibrated_unix_s: when as u64,
        tool_version: read_string(fs, "calibration_tool")?.unwrap_or_default(),
        verdict,
        summary: read_string(fs, "calibration_summary")?.unwrap_or_default(),
        rms_px,
        figures,
    }))
}

/// `serial` (a decimal string; a real is taken too if integral), 0 when absent.
fn read_serial(fs: &FileStorage) -> Result<u64> {
    let Some(n) = node(fs, "serial")? else {
        return Ok(0);
    };
    if let Ok(text) = n.to_string()
        && !text.is_empty()
    {
        return text
            .trim()
            .parse::<u64>()
            .map_err(|_| anyhow!("`serial` = {text:?} is not a whole number ≥ 0"));
    }
    let v = n.real()?;
    ensure!(
        v >= 0.0 && v.fract() == 0.0 && v < 2f64.powi(53),
        "`serial` = {v} is not a whole number ≥ 0"
    );
    Ok(v as u64)
}

/// `timing_<n>` of each camera: empty when no camera has one (a missing one is the default).
fn read_timing(fs: &FileStorage, count: usize) -> Result<Vec<CameraTiming>> {
    let keys: Vec<String> = (1..=count).map(|n| format!("timing_{n}")).collect();
    let mut any = false;
    let mut timing = Vec::with_capacity(count);
    for key in &keys {
        if node(fs, key)?.is_none() {
            timing.push(CameraTiming::default());
            continue;
        }
        any = true;
        let v = read_fixed(fs, key, "camera timing", 1, 4)?;
        let whole = |x: f64, what: &str, lo: f64, hi: f64| -> Result<f64> {
            ensure!(
                x.fract() == 0.0 && (lo..=hi).contains(&x),
                "`{key}`: {what} = {x} must be a whole number in {lo}..={hi}"
            );
            Ok(x)
        };
        let shutter = if v[0] == 0.0 {
            Shutter::Global
        } else if v[0] == 1.0 {
            Shutter::Rolling
        } else {
            bail!("`{key}`: shutter = {} must be 0 (global) or 1 (rolling)", v[0])
        };
        let u32_max = f64::from(u32::MAX);
        timing.push(CameraTiming {
            shutter,
            line_time_ns: whole(v[1], "line_time_ns", 0.0, u32_max)? as u32,
            exposure_ns: whole(v[2], "exposure_ns", 0.0, u32_max)? as u32,
            offset_ns: whole(v[3], "offset_ns", -9.0e15, 9.0e15)? as i64,
        });
    }
    if !any {
        timing.clear();
    }
    Ok(timing)
}

/// Reads the rig; a file without `rig_id` (a plain OpenCV stereo calibration) gets
/// `fallback_rig_id`, and the second value says that this happened.
fn read_all(fs: &FileStorage, fallback_rig_id: &str) -> Result<(RigParams, bool)> {
    let (rig_id, id_from_name) = match node(fs, "rig_id")? {
        Some(n) => (n.to_string().context("`rig_id` must be a string")?, false),
        None => (fallback_rig_id.to_string(), true),
    };
    let created_unix_s = match node(fs, "created_unix_s")? {
        None => 0,
        Some(n) => {
            let v = n.real()?;
            ensure!(
                v >= 0.0 && v.fract() == 0.0 && v < 2f64.powi(53),
                "`created_unix_s` = {v} is not a time"
            );
            v as u64
        }
    };
    let count = match read_int(fs, "camera_count")? {
        Some(c) => usize::try_from(c).map_err(|_| anyhow!("`camera_count` = {c} is negative"))?,
        None => (1..)
            .take_while(|n| {
                matches!(node(fs, &format!("K{n}")), Ok(Some(_)))
                    || matches!(node(fs, &format!("M{n}")), Ok(Some(_)))
            })
            .count(),
    };
    ensure!(count >= 1, "no cameras: missing `K1` (camera 1 matrix)");
    let mut cameras = Vec::with_capacity(count);
    for i in 0..count {
        let n = i + 1;
        let intrinsics = read_camera_matrix(fs, n)?;
        let d_key = format!("D{n}");
        let (_, _, d) = read_mat(&required(fs, &d_key, &format!("camera {n} distortion"))?, &d_key)?;
        let distortion = Distortion::from_slice(&d).map_err(|e| anyhow!("`{d_key}`: {e}"))?;
        let image_size = read_size(fs, n)?;
        let cam_from_cam0 = if i == 0 {
            RigidTransform::IDENTITY
        } else if i == 1 && node(fs, "R")?.is_some() {
            read_transform(fs, "R", "T", "camera 2 pose")?
        } else {
            let (r, t) = pose_keys(n);
            read_transform(fs, &r, &t, &format!("camera {n} pose"))?
        };
        cameras.push(CameraParams {
            model: CameraModel {
                intrinsics,
                distortion,
                image_size,
            },
            cam_from_cam0,
        });
    }
    let world_from_cam0 = match node(fs, "R_world")? {
        Some(_) => Some(read_transform(fs, "R_world", "T_world", "registration")?),
        None => None,
    };
    let tool_count = read_int(fs, "tool_count")?.unwrap_or(0);
    let mut tools = Vec::new();
    for j in 1..=tool_count {
        let name = required(fs, &format!("tool{j}_name"), "tool name")?
            .to_string()
            .with_context(|| format!("`tool{j}_name` must be a string"))?;
        let key = format!("tool{j}_leds_mm");
        let leds_mm = match node(fs, &key)? {
            None => Vec::new(),
            Some(n) => {
                let (rows, cols, v) = read_mat(&n, &key)?;
                ensure!(cols == 3, "`{key}` is {rows}×{cols}, expected M×3");
                v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
            }
        };
        let tip_key = format!("tool{j}_tip_mm");
        let tip_mm = match node(fs, &tip_key)? {
            None => None,
            Some(_) => {
                let v = read_fixed(fs, &tip_key, "tool tip", 1, 3)?;
                Some([v[0], v[1], v[2]])
            }
        };
        tools.push(ToolDefinition {
            name,
            leds_mm,
            tip_mm,
        });
    }
    Ok((
        RigParams {
            rig_id,
            created_unix_s,
            cameras,
            world_from_cam0,
            tools,
            calibration: read_calibration(fs)?.map(Box::new),
            placement: Vec::new(),
            timing: read_timing(fs, count)?,
            serial: read_serial(fs)?,
        },
        id_from_name,
    ))
}

/// Reads a rig from OpenCV YAML (or XML/JSON FileStorage: OpenCV detects the format).
/// Does not validate; call [`RigParams::validate`]. A plain OpenCV stereo calibration
/// (`K1 D1 K2 D2 R T image_width image_height`, no `rig_id`) is accepted: the rig id is taken
/// from the file name and a note says so on stderr.
pub fn read_rig_yaml(path: &Path) -> Result<RigParams> {
    let (rig, id_from_name) = read_rig_yaml_noting(path)?;
    if id_from_name {
        eprintln!(
            "note: {} has no `rig_id` (a plain OpenCV calibration); using rig id {:?} from the file name",
            path.display(),
            rig.rig_id
        );
    }
    Ok(rig)
}

/// [`read_rig_yaml`] without the note; the flag says whether the rig id came from the file name.
pub fn read_rig_yaml_noting(path: &Path) -> Result<(RigParams, bool)> {
    ensure!(path.is_file(), "{}: no such file", path.display());
    let fs = FileStorage::new(path_str(path)?, FileStorage_Mode::READ as i32, "")
        .map_err(|e| anyhow!("{}: OpenCV cannot parse it: {}", path.display(), e.message))?;
    ensure!(fs.is_opened()?, "{}: OpenCV cannot open it", path.display());
    ensure!(
        fs.root_def()?.typ()? & FileNode_TYPE_MASK == FileNode_MAP,
        "{}: top level is not a mapping of named values",
        path.display()
    );
    read_all(&fs, &rig_id_from_path(path))
        .with_context(|| format!("{}: not a usable calibration file", path.display()))
}

/// Loads a parameter blob or an OpenCV YAML file, whichever `path` holds.
pub fn load_params_any(path: &Path) -> Result<RigParams> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    if looks_like_blob(&bytes) {
        return RigParams::from_blob(&bytes)
            .with_context(|| format!("{}: bad parameter blob", path.display()));
    }
    let text_start = String::from_utf8_lossy(&bytes[..bytes.len().min(64)])
        .trim_start()
        .to_string();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if text_start.starts_with("%YAML") || matches!(ext.as_str(), "yaml" | "yml" | "xml" | "json") {
        return read_rig_yaml(path);
    }
    bail!(
        "{}: neither a parameter blob (starts with \"IRPB\") nor an OpenCV YAML file (starts with \"%YAML\")",
        path.display()
    )
}

/// Whether a path names a YAML file by its extension (.yaml / .yml).
pub fn is_yaml_path(path: &Path) -> bool {
    matches!(
        path.extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .as_deref(),
        Some("yaml" | "yml")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rig_id_from_file_names() {
        assert_eq!(rig_id_from_path(Path::new("/x/stereo_lab.yml")), "stereo_lab");
        assert_eq!(
            rig_id_from_path(Path::new("my rig ü.yaml")),
            "my-rig-ü".replace('ü', "-")
        );
        assert_eq!(rig_id_from_path(Path::new(".yaml")), ".yaml");
        assert_eq!(
            rig_id_from_path(Path::new(&"a".repeat(100))).len(),
            MAX_RIG_ID_LEN
        );
    }

    #[test]
    fn iso_dates() {
        assert_eq!(iso_utc(0), "1970-01-01T00:00:00Z");
        assert_eq!(iso_utc(1_700_000_000), "2023-11-14T22:13:20Z");
        assert_eq!(iso_utc(951_782_400), "2000-02-29T00:00:00Z");
    }
}
