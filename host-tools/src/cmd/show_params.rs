//! `host-tools show-params FILE`: human-readable dump of a parameter blob or OpenCV YAML,
//! with the signature status of a blob (verified against `--trusted-key` files if given).

use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::Result;
use irtrack_core::params::{BlobHeader, RigParams, looks_like_blob};
use irtrack_core::signing::{self, SignaturePolicy, SignatureStatus};
use irtrack_core::timing::Shutter;

use crate::cmd::keygen::{load_params_file, read_public_key};
use crate::opencv_yaml::iso_utc;

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Parameter blob or OpenCV YAML calibration.
    pub file: PathBuf,
    /// Public key file(s) to verify a signed blob against (repeatable).
    #[arg(long, value_name = "FILE")]
    pub trusted_key: Vec<PathBuf>,
    /// Compare with another calibration of the same rig (blob or YAML): per camera, how far
    /// the pose and intrinsics moved (e.g. last week's calibration, or a simulator's truth).
    #[arg(long, value_name = "FILE")]
    pub compare: Option<PathBuf>,
}

/// Adding 0.0 turns -0.0 into 0.0, so exact zeros never print as "-0.000".
fn nz(x: f64) -> f64 {
    x + 0.0
}

fn fmt_vec(v: &[f64]) -> String {
    let parts: Vec<String> = v.iter().map(|x| format!("{:.6}", nz(*x))).collect();
    format!("[{}]", parts.join(", "))
}

/// The report text for `rig`; `source` describes where it came from.
pub fn describe(rig: &RigParams, source: &str) -> Result<String> {
    let mut s = String::new();
    writeln!(s, "source:       {source}")?;
    writeln!(s, "rig id:       {}", rig.rig_id)?;
    writeln!(
        s,
        "created:      {} ({} Unix s)",
        iso_utc(rig.created_unix_s),
        rig.created_unix_s
    )?;
    if rig.serial == 0 {
        writeln!(
            s,
            "serial:       none (written before serials; compared by creation time)"
        )?;
    } else {
        writeln!(s, "serial:       {}", rig.serial)?;
    }
    writeln!(s, "cameras:      {}", rig.cameras.len())?;
    for (i, cam) in rig.cameras.iter().enumerate() {
        let m = &cam.model;
        let k = &m.intrinsics;
        let d = &m.distortion;
        writeln!(s, "camera {i}{}:", if i == 0 { " (reference frame)" } else { "" })?;
        writeln!(
            s,
            "  image:      {} x {} px",
            m.image_size.width_px, m.image_size.height_px
        )?;
        writeln!(s, "  focal:      fx {:.3} px, fy {:.3} px", k.fx_px, k.fy_px)?;
        writeln!(s, "  principal:  cx {:.3} px, cy {:.3} px", k.cx_px, k.cy_px)?;
        writeln!(
            s,
            "  distortion: k1 {:.6}, k2 {:.6}, p1 {:.6}, p2 {:.6}, k3 {:.6}",
            d.k1, d.k2, d.p1, d.p2, d.k3
        )?;
        writeln!(s, "  timing:     {}", timing_words(rig, i))?;
        if let Some(p) = rig.placement.get(i) {
            writeln!(
                s,
                "  placement:  board {:?}, camera {} there",
                p.board, p.local_index
            )?;
        }
        if i > 0 {
            let t = &cam.cam_from_cam0;
            let c = rig.camera_centre_cam0_mm(i)?;
            writeln!(
                s,
                "  pose:       baseline {:.3} mm from camera 0, optical axes {:.3} deg apart",
                rig.baseline_mm(i)?,
                rig.optical_axis_angle_deg(i)?
            )?;
            writeln!(
                s,
                "  centre:     ({:.3}, {:.3}, {:.3}) mm in camera-0 frame",
                nz(c.x),
                nz(c.y),
                nz(c.z)
            )?;
            writeln!(
                s,
                "  R, T:       x_cam{i} = R x_cam0 + T, R rows {} {} {}, T {} mm",
                fmt_vec(&t.r_row_major[0..3]),
                fmt_vec(&t.r_row_major[3..6]),
                fmt_vec(&t.r_row_major[6..9]),
                fmt_vec(&t.t_mm)
            )?;
        }
    }
    if rig.placement.is_empty() {
        writeln!(s, "placement:    one board (no camera placement)")?;
    } else {
        let mut boards: Vec<&str> = rig.placement.iter().map(|p| p.board.as_str()).collect();
        boards.sort_unstable();
        boards.dedup();
        writeln!(
            s,
            "placement:    {} cameras on {} boards ({})",
            rig.placement.len(),
            boards.len(),
            boards.join(", ")
        )?;
        for (i, p) in rig.placement.iter().enumerate() {
            writeln!(s, "  camera {i} = board {:?} camera {}", p.board, p.local_index)?;
        }
    }
    match &rig.world_from_cam0 {
        None => writeln!(s, "registration: none (positions in camera-0 frame)")?,
        Some(w) => writeln!(
            s,
            "registration: world from camera 0, R rows {} {} {}, T {} mm",
            fmt_vec(&w.r_row_major[0..3]),
            fmt_vec(&w.r_row_major[3..6]),
            fmt_vec(&w.r_row_major[6..9]),
            fmt_vec(&w.t_mm)
        )?,
    }
    if rig.tools.is_empty() {
        writeln!(s, "tools:        none")?;
    }
    for tool in &rig.tools {
        writeln!(s, "tool {:?}: {} LEDs", tool.name, tool.leds_mm.len())?;
        for p in &tool.leds_mm {
            writeln!(s, "  LED {} mm", fmt_vec(p))?;
        }
        match &tool.tip_mm {
            Some(t) => writeln!(s, "  tip {} mm (reported point)", fmt_vec(t))?,
            None => writeln!(s, "  tip none (the tool origin is reported)")?,
        }
    }
    match &rig.calibration {
        None => writeln!(
            s,
            "calibration:  no record (written before calibration records, or by hand)"
        )?,
        Some(c) => {
            writeln!(
                s,
                "calibration:  {}, {} by {}, verdict {}",
                c.method,
                iso_utc(c.calibrated_unix_s),
                c.tool_version,
                c.verdict.as_str().to_uppercase()
            )?;
            if !c.rms_px.is_empty() {
                let rms: Vec<String> = c.rms_px.iter().map(|v| format!("{v:.4}")).collect();
                writeln!(s, "  RMS px:     {}", rms.join(", "))?;
            }
            for f in &c.figures {
                writeln!(s, "  {}: {}", f.name, f.value)?;
            }
            if !c.summary.is_empty() {
                writeln!(s, "  {}", c.summary)?;
            }
        }
    }
    match rig.validate() {
        Ok(()) => writeln!(s, "validation:   OK")?,
        Err(e) => writeln!(s, "validation:   INVALID: {e}")?,
    }
    Ok(s)
}

/// Camera `i`'s timing in words (µs), saying when the set carries none.
pub fn timing_words(rig: &RigParams, i: usize) -> String {
    let t = rig.camera_timing(i);
    let us = |ns: f64| ns / 1000.0;
    let mut text = match t.shutter {
        Shutter::Global => "global shutter".to_string(),
        Shutter::Rolling => format!(
            "rolling shutter, line time {:.3} us",
            us(f64::from(t.line_time_ns))
        ),
    };
    if t.exposure_ns != 0 {
        text += &format!(", exposure {:.3} us", us(f64::from(t.exposure_ns)));
    }
    text += &format!(", offset {:+.3} us", us(t.offset_ns as f64));
    if !rig.has_timing() {
        text += " (the set carries no timing: irtrackd's [[camera_timing]] or the default applies)";
    }
    text
}

/// Per camera, how `rig` differs from `other` (camera 0 is both rigs' reference frame, so its
/// pose cannot differ; its intrinsics can).
pub fn compare(rig: &RigParams, other: &RigParams, other_name: &str) -> Result<String> {
    anyhow::ensure!(
        rig.cameras.len() == other.cameras.len(),
        "cannot compare with {other_name}: it has {} cameras, this file {}",
        other.cameras.len(),
        rig.cameras.len()
    );
    let mut s = String::new();
    writeln!(s, "compared with {other_name} (rig id {}):", other.rig_id)?;
    for (i, (a, b)) in rig.cameras.iter().zip(&other.cameras).enumerate() {
        let (ka, kb) = (&a.model.intrinsics, &b.model.intrinsics);
        let mut line = format!(
            "  camera {i}: focal {:+.3} px, principal point ({:+.3}, {:+.3}) px",
            ka.fx_px - kb.fx_px,
            ka.cx_px - kb.cx_px,
            ka.cy_px - kb.cy_px
        );
        if i > 0 {
            let r = a.cam_from_cam0.rotation() * b.cam_from_cam0.rotation().transpose();
            let angle_deg = ((r.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
            let centre_mm = (rig.camera_centre_cam0_mm(i)? - other.camera_centre_cam0_mm(i)?).norm();
            let baseline_mm = rig.baseline_mm(i)? - other.baseline_mm(i)?;
            write!(
                line,
                ", rotation {angle_deg:.4} deg, centre {centre_mm:.3} mm (baseline {baseline_mm:+.3} mm)"
            )?;
        }
        writeln!(s, "{line}")?;
    }
    Ok(s)
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let loaded = load_params_file(&args.file)?;
    let trusted = args
        .trusted_key
        .iter()
        .map(|p| read_public_key(p))
        .collect::<Result<Vec<_>>>()?;
    let bytes = std::fs::read(&args.file)?;
    let (source, signature) = if looks_like_blob(&bytes) {
        let h = BlobHeader::parse_allow_signed(&bytes)?;
        let source = format!(
            "{} (parameter blob v{}, {} bytes, CRC-32 {:08x})",
            args.file.display(),
            h.version,
            bytes.len(),
            h.crc32
        );
        let signature = match (&loaded.signed, trusted.is_empty()) {
            (None, _) => "none (unsigned blob)".to_string(),
            (Some((id, _)), true) => {
                format!("key {id}, not verified (give --trusted-key FILE to verify)")
            }
            (Some(_), false) => {
                match signing::verify_blob(&bytes, &trusted, SignaturePolicy::RequireSigned) {
                    Ok((_, SignatureStatus::Signed { key_id })) => format!("key {key_id}, verified"),
                    Ok((_, SignatureStatus::UnsignedAccepted)) => "none".to_string(),
                    Err(e) => format!("INVALID: {e}"),
                }
            }
        };
        (source, Some(signature))
    } else {
        (format!("{} (OpenCV YAML)", args.file.display()), None)
    };
    print!("{}", describe(&loaded.rig, &source)?);
    if let Some(sig) = signature {
        println!("signature:    {sig}");
        println!("params CRC:   {:08x}", loaded.rig.params_crc()?);
    }
    if let Some(other) = &args.compare {
        let other_rig = load_params_file(other)?.rig;
        print!(
            "{}",
            compare(&loaded.rig, &other_rig, &other.display().to_string())?
        );
    }
    Ok(())
}
