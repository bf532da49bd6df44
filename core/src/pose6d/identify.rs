//! Step 2, identification: the validated tool layout ([`ToolModel`], with its identification
//! margin) and the interpretation-tree search that assigns candidate points to its LEDs.

use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;

use nalgebra::Vector3;

use super::config::{MAX_TOOL_LEDS, PoseConfig};
use super::fit::{RigidFit, fit_rigid_horn};
use super::matching::TriangulatedPoint;
use crate::params::ToolDefinition;
use crate::{Error, Result};

/// A validated tool layout with its distance table.
#[derive(Debug, Clone, PartialEq)]
pub struct ToolModel {
    pub(super) name: String,
    pub(super) led_count: usize,
    pub(super) leds_mm: [Vector3<f64>; MAX_TOOL_LEDS],
    pub(super) dist_mm: [[f64; MAX_TOOL_LEDS]; MAX_TOOL_LEDS],
    pub(super) margin_mm: f64,
    pub(super) min_leds: usize,
    /// The tip in the tool frame (zero, i.e. the origin, for a tool without one).
    pub(super) tip_mm: Vector3<f64>,
    pub(super) has_tip: bool,
}

impl ToolModel {
    /// Validates `tool`: 3..=[`MAX_TOOL_LEDS`] finite LEDs, no two closer than
    /// `min_led_separation_mm`, not collinear (also with any one LED missing, when that is
    /// allowed), and asymmetric: the identification margin (see [`ToolModel::margin_mm`])
    /// must be ≥ `min_margin_mm`. Errors name the tool and the offending LEDs.
    pub fn new(tool: &ToolDefinition, config: &PoseConfig) -> Result<Self> {
        config.validate()?;
        let n = tool.leds_mm.len();
        let bad = |reason: String| Err(Error::InvalidParams { reason });
        if !(3..=MAX_TOOL_LEDS).contains(&n) {
            return bad(format!(
                "tool {:?} has {n} LEDs; 6-DOF tracking needs 3..={MAX_TOOL_LEDS}",
                tool.name
            ));
        }
        let mut leds_mm = [Vector3::zeros(); MAX_TOOL_LEDS];
        for (i, p) in tool.leds_mm.iter().enumerate() {
            if !p.iter().all(|v| v.is_finite()) {
                return bad(format!("tool {:?}: LED {i} has a non-finite position", tool.name));
            }
            leds_mm[i] = Vector3::from(*p);
        }
        let mut dist_mm = [[0.0; MAX_TOOL_LEDS]; MAX_TOOL_LEDS];
        for i in 0..n {
            for j in 0..n {
                dist_mm[i][j] = (leds_mm[i] - leds_mm[j]).norm();
            }
        }
        for (i, row) in dist_mm.iter().enumerate().take(n) {
            for (j, &d) in row.iter().enumerate().take(n).skip(i + 1) {
                if d < config.min_led_separation_mm {
                    return bad(format!(
                        "tool {:?}: LEDs {i} and {j} are {d:.1} mm apart, below min_led_separation_mm {} \
                         (their blobs would merge)",
                        tool.name, config.min_led_separation_mm
                    ));
                }
            }
        }
        // Poses come from any 3 or more LEDs when LEDs may be missing (docs/six-dof.md).
        let min_leds = if config.allow_missing_led && n >= 4 {
            n.saturating_sub(config.max_missing_leds).max(3)
        } else {
            n
        };
        // Every LED subset the tracker may fit must fix a rotation (a subset's supersets are
        // no closer to a line, so the smallest subsets are the ones to check).
        let mut subset = [0usize; MAX_TOOL_LEDS];
        for mask in 0u32..(1 << n) {
            if mask.count_ones() as usize != min_leds {
                continue;
            }
            let mut k = 0;
            for i in (0..n).filter(|&i| mask & (1 << i) != 0) {
                subset[k] = i;
                k += 1;
            }
            let off = off_line_mm(&leds_mm, &subset[..k]);
            if off < config.min_margin_mm {
                return bad(format!(
                    "tool {:?}: LEDs {:?} are (nearly) collinear ({off:.1} mm off their line, need ≥ {}); \
                     the rotation about that line would be undetermined",
                    tool.name,
                    &subset[..k],
                    config.min_margin_mm
                ));
            }
        }
        let mut model = ToolModel {
            name: tool.name.clone(),
            led_count: n,
            leds_mm,
            dist_mm,
            margin_mm: f64::INFINITY,
            min_leds,
            tip_mm: tool.tip_mm.map_or_else(Vector3::zeros, Vector3::from),
            has_tip: tool.tip_mm.is_some(),
        };
        if !model.tip_mm.iter().all(|v| v.is_finite()) {
            return bad(format!("tool {:?}: the tip has a non-finite position", tool.name));
        }
        let (margin, worst) = min_mismatch(&model, &model, true);
        model.margin_mm = margin;
        if margin < config.min_margin_mm {
            let shown: Vec<String> = worst
                .iter()
                .take(n)
                .enumerate()
                .filter(|(_, m)| **m != NO_LED)
                .map(|(i, m)| format!("{i}→{m}"))
                .collect();
            return bad(format!(
                "tool {:?} is ambiguous: the LED assignment [{}] reproduces every distance within \
                 {margin:.2} mm (need a margin ≥ {} mm); make the layout asymmetric (or allow \
                 fewer missing LEDs, [pose] max_missing_leds)",
                tool.name,
                shown.join(", "),
                config.min_margin_mm
            ));
        }
        Ok(model)
    }

    /// The tool's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Number of LEDs.
    pub fn led_count(&self) -> usize {
        self.led_count
    }

    /// LED positions in the tool frame (mm).
    pub fn leds_mm(&self) -> &[Vector3<f64>] {
        &self.leds_mm[..self.led_count]
    }

    /// The tip in the tool frame (mm), if the tool has one (pivot calibration).
    pub fn tip_mm(&self) -> Option<Vector3<f64>> {
        self.has_tip.then_some(self.tip_mm)
    }

    /// Fewest LEDs a pose is computed from.
    pub fn min_leds(&self) -> usize {
        self.min_leds
    }

    /// Identification margin (mm): over every wrong assignment of the LEDs the tracker may
    /// see (all, or all but one when a missing LED is allowed) onto the tool's LEDs, the
    /// smallest "largest distance mismatch". Zero for a symmetric layout.
    pub fn margin_mm(&self) -> f64 {
        self.margin_mm
    }

    /// Centroid of the LED layout in the tool frame (mm).
    pub fn centroid_mm(&self) -> Vector3<f64> {
        self.leds_mm().iter().sum::<Vector3<f64>>() / self.led_count as f64
    }

    /// Cross-tool identification margin (mm): how well any `min_leds` or more LEDs of
    /// `other` can pose as this tool — the smallest, over every injective map σ from a subset
    /// of this tool's LEDs (as many as a pose needs) onto `other`'s LEDs, of the largest
    /// distance mismatch. Small means the tracker of this tool could take `other` for it.
    pub fn cross_margin_mm(&self, other: &ToolModel) -> f64 {
        min_mismatch(self, other, false).0
    }
}

/// Exhaustive search of injective maps σ from a visible subset of `x`'s LEDs (all, down to
/// `x.min_leds`) onto `y`'s LEDs; returns the smallest max |d_x(i,j) − d_y(σi,σj)| (over
/// non-identity maps when `skip_identity`, for `x` = `y`) and the map reaching it.
fn min_mismatch(x: &ToolModel, y: &ToolModel, skip_identity: bool) -> (f64, [u8; MAX_TOOL_LEDS]) {
    struct Search<'a> {
        x: &'a ToolModel,
        y: &'a ToolModel,
        skip_identity: bool,
        map: [u8; MAX_TOOL_LEDS],
        best: f64,
        best_map: [u8; MAX_TOOL_LEDS],
    }
    fn rec(s: &mut Search<'_>, led: usize, missing: usize, used: u32, worst: f64) {
        let n = s.x.led_count;
        if worst >= s.best {
            return;
        }
        if led == n {
            let identity = (0..n).all(|i| s.map[i] == NO_LED || s.map[i] as usize == i);
            if !(s.skip_identity && identity) {
                s.best = worst;
                s.best_map = s.map;
            }
            return;
        }
        if n - missing > s.x.min_leds {
            s.map[led] = NO_LED;
            rec(s, led + 1, missing + 1, used, worst);
        }
        for target in 0..s.y.led_count {
            if used & (1 << target) != 0 {
                continue;
            }
            let mut w = worst;
            for prev in 0..led {
                let tp = s.map[prev];
                if tp != NO_LED {
                    let d = libm::fabs(s.x.dist_mm[prev][led] - s.y.dist_mm[tp as usize][target]);
                    w = w.max(d);
                }
            }
            s.map[led] = target as u8;
            rec(s, led + 1, missing, used | (1 << target), w);
        }
        s.map[led] = NO_LED;
    }
    let mut s = Search {
        x,
        y,
        skip_identity,
        map: [NO_LED; MAX_TOOL_LEDS],
        best: f64::INFINITY,
        best_map: [NO_LED; MAX_TOOL_LEDS],
    };
    rec(&mut s, 0, 0, 0, 0.0);
    (s.best, s.best_map)
}

/// Marks "this LED is missing" in an assignment.
pub(super) const NO_LED: u8 = u8::MAX;

/// Largest distance (mm) of a point of `idx` from the line through its two farthest points.
fn off_line_mm(p: &[Vector3<f64>], idx: &[usize]) -> f64 {
    let (mut a, mut b, mut dmax) = (0, 0, -1.0);
    for (k, &i) in idx.iter().enumerate() {
        for &j in &idx[k + 1..] {
            let d = (p[i] - p[j]).norm();
            if d > dmax {
                (a, b, dmax) = (i, j, d);
            }
        }
    }
    if dmax.is_nan() || dmax <= 0.0 {
        return 0.0;
    }
    let u = (p[b] - p[a]) / dmax;
    idx.iter()
        .map(|&i| {
            let v = p[i] - p[a];
            (v - u * v.dot(&u)).norm()
        })
        .fold(0.0, f64::max)
}

/// One complete assignment of candidate points to the tool's LEDs, with its fit.
#[derive(Debug, Clone, Copy)]
pub(super) struct Hypothesis {
    /// Candidate index per LED, [`NO_LED`] when missing.
    pub(super) assign: [u8; MAX_TOOL_LEDS],
    pub(super) count: u32,
    pub(super) fit: RigidFit,
}

/// Interpretation-tree search: fills `out` (cleared first) with every complete assignment of
/// `points` to the tool's LEDs whose pairwise distances match the layout within `tol_mm`.
/// Returns `true` when `out`'s capacity was reached (the search stopped early: overflow).
pub(super) fn find_assignments(
    tool: &ToolModel,
    points: &[TriangulatedPoint],
    tol_mm: f64,
    out: &mut Vec<Hypothesis>,
) -> bool {
    out.clear();
    let mut overflow = false;
    let mut st = SearchState {
        tool,
        points,
        tol: tol_mm,
        assign: [NO_LED; MAX_TOOL_LEDS],
        out,
        overflow: &mut overflow,
        best_count: 0,
    };
    assign_rec(&mut st, 0, 0);
    overflow
}

struct SearchState<'a> {
    tool: &'a ToolModel,
    points: &'a [TriangulatedPoint],
    tol: f64,
    assign: [u8; MAX_TOOL_LEDS],
    out: &'a mut Vec<Hypothesis>,
    overflow: &'a mut bool,
    /// Most LEDs of any assignment found so far.
    best_count: usize,
}

fn assign_rec(st: &mut SearchState<'_>, led: usize, missing: usize) {
    let n = st.tool.led_count;
    if *st.overflow {
        return;
    }
    if led == n {
        emit_hypothesis(st);
        return;
    }
    for (ci, cand) in st.points.iter().enumerate().take(NO_LED as usize) {
        let ok = (0..led).all(|prev| {
            let pc = st.assign[prev];
            if pc == NO_LED {
                return true;
            }
            let other = &st.points[pc as usize];
            if pc as usize == ci || cand.shares_blob(other) {
                return false;
            }
            let d = (cand.point_mm - other.point_mm).norm();
            libm::fabs(d - st.tool.dist_mm[prev][led]) <= st.tol
        });
        if ok {
            st.assign[led] = ci as u8;
            assign_rec(st, led + 1, missing);
        }
    }
    // Leave this LED out only while a pose with fewer LEDs may still compete: once an
    // assignment with more LEDs exists, smaller ones never win (and would fill the buffer).
    if n - missing > st.tool.min_leds && n - missing > st.best_count {
        st.assign[led] = NO_LED;
        assign_rec(st, led + 1, missing + 1);
    }
    st.assign[led] = NO_LED;
}

fn emit_hypothesis(st: &mut SearchState<'_>) {
    let mut model = [Vector3::zeros(); MAX_TOOL_LEDS];
    let mut measured = [Vector3::zeros(); MAX_TOOL_LEDS];
    let mut k = 0;
    for led in 0..st.tool.led_count {
        let c = st.assign[led];
        if c != NO_LED {
            model[k] = st.tool.leds_mm[led];
            measured[k] = st.points[c as usize].point_mm;
            k += 1;
        }
    }
    let Some(fit) = fit_rigid_horn(&model[..k], &measured[..k]) else {
        return;
    };
    let h = Hypothesis {
        assign: st.assign,
        count: k as u32,
        fit,
    };
    st.best_count = st.best_count.max(k);
    if st.out.len() == st.out.capacity() {
        // Full: a hypothesis with fewer LEDs gives way (it cannot win against this one);
        // otherwise the frame has too many plausible readings (overflow).
        let weakest = st
            .out
            .iter()
            .enumerate()
            .min_by_key(|(_, h)| h.count)
            .map(|(i, h)| (i, h.count));
        match weakest {
            Some((i, c)) if (c as usize) < k => st.out[i] = h,
            _ => *st.overflow = true,
        }
        return;
    }
    st.out.push(h);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose6d::config::{MAX_CAMERAS, NO_BLOB};

    fn tool(leds_mm: &[[f64; 3]]) -> ToolDefinition {
        ToolDefinition {
            name: "t".into(),
            leds_mm: leds_mm.to_vec(),
            tip_mm: None,
        }
    }

    /// Right triangle with legs 100 and 60 mm.
    const RIGHT: [[f64; 3]; 3] = [[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 60.0, 0.0]];

    #[test]
    fn margin_of_a_right_triangle_is_hypotenuse_minus_long_leg() {
        // The best wrong assignment swaps LEDs 0 and 2: the sides 100 and hypotenuse trade
        // places, so it misses by √(100² + 60²) − 100.
        let m = ToolModel::new(&tool(&RIGHT), &PoseConfig::default()).unwrap();
        let want = (100.0f64 * 100.0 + 60.0 * 60.0).sqrt() - 100.0;
        assert!((m.margin_mm() - want).abs() < 1e-9, "{}", m.margin_mm());
        assert_eq!((m.led_count(), m.min_leds()), (3, 3));
        assert!(m.tip_mm().is_none());
    }

    #[test]
    fn refuses_symmetric_collinear_and_crowded_layouts() {
        let cfg = PoseConfig::default();
        let s = 3.0f64.sqrt();
        let equilateral = [[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [50.0, 50.0 * s, 0.0]];
        let e = ToolModel::new(&tool(&equilateral), &cfg).unwrap_err().to_string();
        assert!(e.contains("ambiguous"), "{e}");
        let line = [[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [100.0, 0.0, 0.0]];
        let e = ToolModel::new(&tool(&line), &cfg).unwrap_err().to_string();
        assert!(e.contains("collinear"), "{e}");
        let crowded = [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 60.0, 0.0]];
        let e = ToolModel::new(&tool(&crowded), &cfg).unwrap_err().to_string();
        assert!(e.contains("LEDs 0 and 1") && e.contains("10.0 mm"), "{e}");
    }

    fn point(p: Vector3<f64>, blob: u8) -> TriangulatedPoint {
        let mut blobs = [NO_BLOB; MAX_CAMERAS];
        blobs[0] = blob;
        blobs[1] = blob;
        TriangulatedPoint {
            point_mm: p,
            gap_mm: 0.0,
            blobs,
            cameras: 2,
        }
    }

    #[test]
    fn search_assigns_each_led_to_its_point_despite_a_distractor() {
        let m = ToolModel::new(&tool(&RIGHT), &PoseConfig::default()).unwrap();
        // The tool moved by t (no rotation); candidates in shuffled order plus a reflection.
        let t = Vector3::new(-30.0, 20.0, 900.0);
        let leds = m.leds_mm();
        let points = [
            point(leds[2] + t, 0),
            point(Vector3::new(400.0, 400.0, 900.0), 1),
            point(leds[0] + t, 2),
            point(leds[1] + t, 3),
        ];
        let mut out = Vec::with_capacity(8);
        assert!(!find_assignments(&m, &points, 2.5, &mut out));
        assert_eq!(out.len(), 1, "{out:?}");
        let h = &out[0];
        assert_eq!(&h.assign[..3], &[2, 3, 0]);
        assert_eq!(h.count, 3);
        assert!((h.fit.translation_mm - t).norm() < 1e-9);
        assert!(h.fit.rms_mm < 1e-9);
        // Two points share a blob: they cannot both be LEDs, so nothing is assigned.
        let mut shared = points;
        shared[3].blobs[0] = 2;
        assert!(!find_assignments(&m, &shared, 2.5, &mut out));
        assert!(out.is_empty());
        // A full hypothesis buffer reports overflow instead of dropping silently.
        let mut tiny = Vec::with_capacity(0);
        assert!(find_assignments(&m, &points, 2.5, &mut tiny));
    }
}
