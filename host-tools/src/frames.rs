//! Frame folders as `capture` and `simulate` write them (`cam<i>/<index>.pgm`), read back and
//! run through the board's own blob detector: the offline input of `measure-tool` and `pivot`.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use anyhow::{Context, ensure};
use irtrack_core::blob::{Blob, BlobConfig, BlobDetector, BlobLimits};
use irtrack_core::image::GrayImage;
use irtrack_core::params::RigParams;
use irtrack_core::pgm::{self, PgmPixels};

/// Frame indices present in every camera directory, ascending.
pub fn common_frames(dir: &Path, n_cam: usize) -> anyhow::Result<Vec<u64>> {
    let mut common: Option<BTreeSet<u64>> = None;
    for c in 0..n_cam {
        let d = dir.join(format!("cam{c}"));
        let mut set = BTreeSet::new();
        for e in std::fs::read_dir(&d).with_context(|| {
            format!(
                "listing {} (the parameters describe {n_cam} cameras)",
                d.display()
            )
        })? {
            let name = e?.file_name();
            if let Some(i) = name
                .to_string_lossy()
                .strip_suffix(".pgm")
                .and_then(|s| s.parse().ok())
            {
                set.insert(i);
            }
        }
        common = Some(match common {
            None => set,
            Some(c) => c.intersection(&set).copied().collect(),
        });
    }
    Ok(common.unwrap_or_default().into_iter().collect())
}

/// One blob detector per camera of a frame folder, checked against the parameter set's image
/// sizes.
pub struct FolderDetector {
    dir: PathBuf,
    sizes_px: Vec<(u32, u32)>,
    threshold_dn: Option<u32>,
    detectors: Vec<BlobDetector>,
}

impl FolderDetector {
    /// `threshold_dn`: `None` takes the board's default, 30 DN on an 8-bit scale (scaled to
    /// the frames' maxval).
    pub fn new(dir: &Path, rig: &RigParams, threshold_dn: Option<u32>) -> Self {
        let sizes_px = rig
            .cameras
            .iter()
            .map(|c| (c.model.image_size.width_px, c.model.image_size.height_px))
            .collect();
        Self {
            dir: dir.to_path_buf(),
            sizes_px,
            threshold_dn,
            detectors: Vec::new(),
        }
    }

    /// Reads frame `index` of every camera and detects its blobs; returns them per camera.
    pub fn detect(&mut self, index: u64) -> anyhow::Result<Vec<&[Blob]>> {
        for (c, &(w_px, h_px)) in self.sizes_px.iter().enumerate() {
            let path = self.dir.join(format!("cam{c}/{index:06}.pgm"));
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let pgm = pgm::decode(&bytes).with_context(|| format!("decoding {}", path.display()))?;
            let (w, h) = (pgm.width_px, pgm.height_px);
            ensure!(
                (w, h) == (w_px, h_px),
                "{}: {w}x{h} px, the parameters say {w_px}x{h_px}",
                path.display()
            );
            if self.detectors.len() <= c {
                self.detectors
                    .push(BlobDetector::new(BlobLimits::for_frame(w, h))?);
            }
            let scale = (pgm.maxval as f64 + 1.0) / 256.0;
            let cfg = BlobConfig {
                threshold_dn: self.threshold_dn.unwrap_or((30.0 * scale).round() as u32),
                saturation_dn: Some(pgm.maxval as u32),
                ..BlobConfig::default()
            };
            let detector = &mut self.detectors[c];
            match &pgm.pixels {
                PgmPixels::U8(v) => detector.detect(&GrayImage::new(v, w, h, w)?, None, &cfg)?,
                PgmPixels::U16(v) => detector.detect(&GrayImage::new(v, w, h, w)?, None, &cfg)?,
            };
        }
        Ok(self.detectors.iter().map(|d| d.blobs()).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cmd::simulate;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        sim: simulate::Args,
    }

    #[test]
    fn detects_a_simulated_folder_and_names_a_frame_of_the_wrong_size() {
        let dir = std::env::temp_dir().join(format!("irtrack-frames-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let cli = Cli::parse_from(["x", "--out", dir.to_str().unwrap(), "--frames", "3", "--quiet"]);
        simulate::run(cli.sim).unwrap();
        let rig = RigParams::from_blob(&std::fs::read(dir.join("rig.irp")).unwrap()).unwrap();
        // An index only camera 0 has is not common.
        std::fs::copy(dir.join("cam0/000000.pgm"), dir.join("cam0/000099.pgm")).unwrap();
        assert_eq!(common_frames(&dir, rig.cameras.len()).unwrap(), vec![0, 1, 2]);

        let mut detector = FolderDetector::new(&dir, &rig, None);
        let blobs = detector.detect(1).unwrap();
        assert_eq!(blobs.len(), rig.cameras.len());
        assert!(
            blobs.iter().all(|b| b.len() == 1),
            "one marker per camera: {blobs:?}"
        );

        std::fs::write(dir.join("cam1/000002.pgm"), b"P5\n4 2\n255\n\0\0\0\0\0\0\0\0").unwrap();
        let e = format!("{:#}", detector.detect(2).unwrap_err());
        assert!(e.contains("cam1/000002.pgm") && e.contains("4x2 px"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
