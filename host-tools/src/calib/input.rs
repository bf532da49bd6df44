//! Finding the calibration images of each camera and pairing them into views.
//!
//! Two layouts: subdirectories `cam0/`, `cam1/`, ... (views paired by file stem), or a flat
//! directory with one file-name pattern per camera such as `left*.png,right*.png` (views paired by
//! the text the wildcards matched: `left07.png` and `right07.png` are view `07`).
//! A later "capture from the board" source only has to produce the same [`CameraImages`].

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// File extensions OpenCV's `imread` reads and we look for in `camN/` directories.
const IMAGE_EXTENSIONS: &[&str] = &[
    "png", "pgm", "ppm", "pnm", "jpg", "jpeg", "bmp", "tif", "tiff", "webp",
];

/// The images of one camera, keyed by view name.
#[derive(Debug, Clone)]
pub struct CameraImages {
    /// How the images were selected (`cam1/` or `right*.png`), for messages.
    pub label: String,
    /// Image file per view name.
    pub files: BTreeMap<String, PathBuf>,
}

/// All cameras' images and how they pair into views.
#[derive(Debug, Clone)]
pub struct ImageSet {
    /// One entry per camera, camera 0 first.
    pub cameras: Vec<CameraImages>,
    /// Views with an image in every camera, in name order.
    pub complete_views: Vec<String>,
    /// Views missing in some cameras: (view, cameras without an image).
    pub incomplete_views: Vec<(String, Vec<usize>)>,
}

/// Matches `name` against a pattern with `*` (any run) and `?` (one character); returns the
/// concatenated text matched by the wildcards.
pub fn wildcard_match(pattern: &str, name: &str) -> Option<String> {
    fn go(p: &[char], n: &[char], captured: &mut String) -> bool {
        match p.first() {
            None => n.is_empty(),
            Some('*') => {
                for k in 0..=n.len() {
                    let mark = captured.len();
                    captured.extend(&n[..k]);
                    if go(&p[1..], &n[k..], captured) {
                        return true;
                    }
                    captured.truncate(mark);
                }
                false
            }
            Some('?') => match n.first() {
                Some(c) => {
                    captured.push(*c);
                    if go(&p[1..], &n[1..], captured) {
                        return true;
                    }
                    captured.pop();
                    false
                }
                None => false,
            },
            Some(c) => n.first() == Some(c) && go(&p[1..], &n[1..], captured),
        }
    }
    let p: Vec<char> = pattern.chars().collect();
    let n: Vec<char> = name.chars().collect();
    let mut captured = String::new();
    go(&p, &n, &mut captured).then_some(captured)
}

fn sorted_entries(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).with_context(|| format!("{}: cannot list directory", dir.display()))? {
        out.push(
            e.with_context(|| format!("{}: cannot list directory", dir.display()))?
                .path(),
        );
    }
    out.sort();
    Ok(out)
}

fn is_image(path: &Path) -> bool {
    path.is_file()
        && path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| IMAGE_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
}

/// Camera subdirectories `cam0`, `cam1`, ... of `dir`, in camera order.
fn camera_dirs(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut found = BTreeMap::new();
    for p in sorted_entries(dir)? {
        let Some(name) = p.file_name().and_then(|n| n.to_str()) else {
            continue;
        };
        if let Some(idx) = name.strip_prefix("cam").and_then(|s| s.parse::<usize>().ok())
            && p.is_dir()
        {
            found.insert(idx, p);
        }
    }
    for (expected, idx) in found.keys().enumerate() {
        if *idx != expected {
            bail!(
                "{}: camera directories must be cam0/, cam1/, ... without gaps; cam{expected}/ is missing",
                dir.display()
            );
        }
    }
    Ok(found.into_values().collect())
}

/// Finds the images of every camera under `dir`.
pub fn discover(dir: &Path, pattern: Option<&str>) -> Result<ImageSet> {
    if !dir.is_dir() {
        bail!("{}: no such directory", dir.display());
    }
    let mut cameras = Vec::new();
    match pattern {
        Some(patterns) => {
            let entries = sorted_entries(dir)?;
            for pat in patterns.split(',').map(str::trim).filter(|p| !p.is_empty()) {
                if pat.contains('/') {
                    bail!("pattern `{pat}`: give file-name patterns only (the directory is --images)");
                }
                let mut files = BTreeMap::new();
                for p in &entries {
                    let Some(name) = p.file_name().and_then(|n| n.to_str()) else {
                        continue;
                    };
                    if let Some(key) = wildcard_match(pat, name)
                        && p.is_file()
                    {
                        files.insert(key, p.clone());
                    }
                }
                if files.is_empty() {
                    bail!("no file in {} matches `{pat}`", dir.display());
                }
                cameras.push(CameraImages {
                    label: pat.to_string(),
                    files,
                });
            }
        }
        None => {
            for cdir in camera_dirs(dir)? {
                let label = format!("{}/", cdir.file_name().and_then(|n| n.to_str()).unwrap_or("?"));
                let mut files = BTreeMap::new();
                for p in sorted_entries(&cdir)? {
                    if is_image(&p) {
                        let stem = p
                            .file_stem()
                            .and_then(|s| s.to_str())
                            .unwrap_or_default()
                            .to_string();
                        if let Some(prev) = files.insert(stem.clone(), p.clone()) {
                            bail!(
                                "{} and {} are both view `{stem}`; keep one",
                                prev.display(),
                                p.display()
                            );
                        }
                    }
                }
                if files.is_empty() {
                    bail!("{}: no images ({})", cdir.display(), IMAGE_EXTENSIONS.join(", "));
                }
                cameras.push(CameraImages { label, files });
            }
        }
    }
    if cameras.len() < 2 {
        bail!(
            "found {} camera(s) in {}; need at least 2: use subdirectories cam0/, cam1/, ... or \
             --pattern 'left*.png,right*.png'",
            cameras.len(),
            dir.display()
        );
    }
    let all: BTreeSet<&String> = cameras.iter().flat_map(|c| c.files.keys()).collect();
    let mut complete_views = Vec::new();
    let mut incomplete_views = Vec::new();
    for view in all {
        let missing: Vec<usize> = cameras
            .iter()
            .enumerate()
            .filter(|(_, c)| !c.files.contains_key(view))
            .map(|(i, _)| i)
            .collect();
        if missing.is_empty() {
            complete_views.push(view.clone());
        } else {
            incomplete_views.push((view.clone(), missing));
        }
    }
    Ok(ImageSet {
        cameras,
        complete_views,
        incomplete_views,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wildcards_capture_the_view_name() {
        assert_eq!(wildcard_match("left*.png", "left07.png").as_deref(), Some("07"));
        assert_eq!(wildcard_match("left*.png", "right07.png"), None);
        assert_eq!(
            wildcard_match("img_?_*.jpg", "img_a_12.jpg").as_deref(),
            Some("a12")
        );
        assert_eq!(wildcard_match("*", "x").as_deref(), Some("x"));
        assert_eq!(wildcard_match("a*b", "ab").as_deref(), Some(""));
        assert_eq!(wildcard_match("a*b", "abc"), None);
    }

    #[test]
    fn pairs_views_across_camera_dirs_and_lists_incomplete_ones() {
        let dir = std::env::temp_dir().join(format!("irtrack-calib-input-{}", std::process::id()));
        for (cam, views) in [("cam0", &["v1", "v2", "v3"][..]), ("cam1", &["v1", "v3"][..])] {
            std::fs::create_dir_all(dir.join(cam)).unwrap();
            for v in views {
                std::fs::write(dir.join(cam).join(format!("{v}.png")), b"x").unwrap();
            }
        }
        std::fs::write(dir.join("cam1").join("notes.txt"), b"x").unwrap();
        let set = discover(&dir, None).unwrap();
        assert_eq!(set.cameras.len(), 2);
        assert_eq!(set.complete_views, vec!["v1".to_string(), "v3".to_string()]);
        assert_eq!(set.incomplete_views, vec![("v2".to_string(), vec![1])]);
        // Flat layout with patterns.
        let flat = dir.join("flat");
        std::fs::create_dir_all(&flat).unwrap();
        for n in ["left01.png", "left02.png", "right01.png"] {
            std::fs::write(flat.join(n), b"x").unwrap();
        }
        let set = discover(&flat, Some("left*.png,right*.png")).unwrap();
        assert_eq!(set.complete_views, vec!["01".to_string()]);
        let e = discover(&flat, Some("left*.png,top*.png"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("top*.png"), "{e}");
        let e = discover(&flat, None).unwrap_err().to_string();
        assert!(e.contains("need at least 2"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
