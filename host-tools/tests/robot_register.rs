//! `host-tools register` recovers a known tracker-to-robot transform from noisy simulated points
//! and writes it into the parameter set.

use irtrack_core::params::RigParams;
use irtrack_host_tools::cmd::register;
use nalgebra::{Rotation3, Unit, Vector3};

/// Deterministic generator (host-tools has no `rand` dependency).
struct Rng(u64);
impl Rng {
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        lo + (hi - lo) * ((self.0 >> 11) as f64 / (1u64 << 53) as f64)
    }
    /// Box-Muller normal sample.
    fn normal(&mut self, sigma: f64) -> f64 {
        let u1 = self.uniform(1e-12, 1.0);
        let u2 = self.uniform(0.0, 1.0);
        sigma * (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

#[test]
fn register_recovers_known_transform_and_writes_params() {
    let dir = std::env::temp_dir().join(format!("irtrack-register-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let r_true =
        *Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::new(-0.2, 0.9, 0.4)), 2.3).matrix();
    let t_true = Vector3::new(640.0, -210.0, 950.0);
    let mut rng = Rng(42);
    let sigma_mm = 0.15; // tracker + touch-up noise
    let mut csv = String::from("tracker_x_mm,tracker_y_mm,tracker_z_mm,robot_x_mm,robot_y_mm,robot_z_mm\n");
    for _ in 0..12 {
        let p = Vector3::new(
            rng.uniform(-250.0, 250.0),
            rng.uniform(-200.0, 200.0),
            rng.uniform(600.0, 1100.0),
        );
        let q = r_true * p + t_true;
        let n = |rng: &mut Rng| rng.normal(sigma_mm);
        csv.push_str(&format!(
            "{},{},{},{},{},{}\n",
            p.x + n(&mut rng),
            p.y + n(&mut rng),
            p.z + n(&mut rng),
            q.x,
            q.y,
            q.z
        ));
    }
    let pairs = dir.join("pairs.csv");
    std::fs::write(&pairs, &csv).unwrap();
    let read = register::read_pairs(&pairs).unwrap();
    let rep = register::register(&read, 4, false).unwrap();
    let (_, held) = rep.holdout.as_ref().unwrap();
    let held_rms = (held.iter().map(|e| e * e).sum::<f64>() / held.len() as f64).sqrt();
    eprintln!(
        "fit RMS {:.3} mm, held-out RMS {:.3} mm",
        rep.all.rms_mm, held_rms
    );
    assert!(rep.all.rms_mm > 0.05 && rep.all.rms_mm < 0.4);
    assert!(held_rms < 0.6, "held-out RMS {held_rms}");

    // Parameter files: input without registration, output with it.
    let cam = irtrack_sim::CameraSpec::default().model(0);
    let rig = irtrack_sim::resolution::ideal_parallel(cam, 120.0);
    let input = dir.join("in.irp");
    std::fs::write(&input, rig.to_blob().unwrap()).unwrap();
    let output = dir.join("out.irp");
    register::run(register::Args {
        pairs: pairs.clone(),
        holdout: 3,
        scale: false,
        params: input,
        out: output.clone(),
        max_rms_mm: 2.0,
    })
    .unwrap();
    let out = RigParams::from_blob(&std::fs::read(&output).unwrap()).unwrap();
    let w = out.world_from_cam0.expect("registration written");
    let rot_err = Rotation3::from_matrix_unchecked(w.rotation() * r_true.transpose()).angle();
    let t_err = (w.translation_mm() - t_true).norm();
    eprintln!(
        "rotation error {:.4} deg, translation error {:.3} mm",
        rot_err.to_degrees(),
        t_err
    );
    assert!(rot_err.to_degrees() < 0.1, "rotation error {rot_err} rad");
    assert!(t_err < 1.0, "translation error {t_err} mm");
    assert_eq!(out.cameras, rig.cameras);

    // Pairs that do not correspond are refused instead of written.
    let bad = dir.join("bad.csv");
    // Robot points of rows 1..4 shifted by one row: the correspondences are wrong.
    let rows: Vec<&str> = csv.lines().collect();
    let mut lines: Vec<String> = rows.iter().map(|r| r.to_string()).collect();
    for i in 1..4 {
        let tracker: Vec<&str> = rows[i].split(',').take(3).collect();
        let robot: Vec<&str> = rows[i + 1].split(',').skip(3).collect();
        lines[i] = format!("{},{}", tracker.join(","), robot.join(","));
    }
    std::fs::write(&bad, lines.join("\n")).unwrap();
    let e = register::run(register::Args {
        pairs: bad,
        holdout: 0,
        scale: false,
        params: dir.join("in.irp"),
        out: dir.join("bad.irp"),
        max_rms_mm: 2.0,
    })
    .unwrap_err();
    assert!(e.to_string().contains("RMS"), "{e}");
    assert!(!dir.join("bad.irp").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn register_rejects_too_few_and_malformed_pairs() {
    let dir = std::env::temp_dir().join(format!("irtrack-register-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("few.csv");
    std::fs::write(
        &p,
        "tracker_x_mm,tracker_y_mm,tracker_z_mm,robot_x_mm,robot_y_mm,robot_z_mm\n1,2,3,4,5,6\n",
    )
    .unwrap();
    let pairs = register::read_pairs(&p).unwrap();
    assert!(
        register::register(&pairs, 0, false)
            .unwrap_err()
            .to_string()
            .contains("at least 4")
    );
    std::fs::write(
        &p,
        "tracker_x_mm,tracker_y_mm,tracker_z_mm,robot_x_mm,robot_y_mm,robot_z_mm\n1,2,x,4,5,6\n",
    )
    .unwrap();
    let e = register::read_pairs(&p).unwrap_err().to_string();
    assert!(e.contains("tracker_z_mm") && e.contains(":2"), "{e}");
    std::fs::write(&p, "a,b\n").unwrap();
    assert!(
        register::read_pairs(&p)
            .unwrap_err()
            .to_string()
            .contains("no column tracker_x_mm")
    );
    let _ = std::fs::remove_dir_all(&dir);
}
