//! What the standard outputs send, independent of any one protocol: the tracked models (tools
//! as rigid bodies, or the single LED) and, per position record, a [`SceneFrame`] in metres in
//! the output's axes.
//!
//! Every tool of the parameter set is a model (rigid body id = tool index + 1); with the loop's
//! per-tool slot ([`SceneBuilder::with_tools`]) each body gets its own tool's pose, so the
//! encoders send a body per tool.

use irtrack_core::params::RigParams;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use nalgebra::{Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3};
use serde::Deserialize;
use tokio::sync::watch;

use crate::engine::ToolSet;

/// Axes of an output (`axes = "..."` in an output's table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Axes {
    /// The tracker's own frame, unchanged: camera 0's (x right, y down, z forward) or, after
    /// the survey's registration, the robot base's.
    #[default]
    Tracker,
    /// Y up, right-handed (Motive's default): camera-0 frame (x, y, z) → (x, −y, −z), a turn of
    /// 180° about x; robot-base frame (z up) → (x, z, −y), a turn of −90° about x.
    YUp,
}

impl Axes {
    /// The rotation from the record's frame (`world_frame`: robot base, else camera 0) to the
    /// output's axes.
    pub fn rotation(self, world_frame: bool) -> Rotation3<f64> {
        let m = match (self, world_frame) {
            (Axes::Tracker, _) => Matrix3::identity(),
            (Axes::YUp, false) => Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0),
            (Axes::YUp, true) => Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0),
        };
        Rotation3::from_matrix_unchecked(m)
    }
}

/// One tracked model as the outputs describe it.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelDef {
    /// Rigid body id (1-based, the tool's index in the parameter set + 1); 0 for the single LED.
    pub id: u32,
    /// The tool's name from the parameter set, or `"led"` for the single LED.
    pub name: String,
    /// Marker (LED) positions in the model's own frame relative to the reported point (the
    /// tool's tip, else its origin), metres. One entry at the origin for the single LED.
    pub markers_m: Vec<[f64; 3]>,
    /// A rigid body (6-DOF tool) rather than a single marker.
    pub rigid_body: bool,
}

/// The models of the active parameter set.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Models {
    /// The models, in id order.
    pub list: Vec<ModelDef>,
}

/// Name of the single-LED model (no tool defined).
pub const SINGLE_LED_NAME: &str = "led";

impl Models {
    /// The tools the loop tracks (every tool of the set, ids 1, 2, … in definition order),
    /// else the single LED.
    pub fn of_rig(rig: Option<&RigParams>) -> Models {
        let tools = rig.map_or(&[][..], |r| r.tools.as_slice());
        let list = match tools {
            [_, ..] => tools
                .iter()
                .enumerate()
                .map(|(i, t)| {
                    let tip = t.tip_mm.unwrap_or([0.0; 3]);
                    ModelDef {
                        id: i as u32 + 1,
                        name: t.name.clone(),
                        markers_m: t
                            .leds_mm
                            .iter()
                            .map(|l| {
                                [
                                    (l[0] - tip[0]) / 1e3,
                                    (l[1] - tip[1]) / 1e3,
                                    (l[2] - tip[2]) / 1e3,
                                ]
                            })
                            .collect(),
                        rigid_body: true,
                    }
                })
                .collect(),
            [] => vec![ModelDef {
                id: 0,
                name: SINGLE_LED_NAME.into(),
                markers_m: vec![[0.0; 3]],
                rigid_body: false,
            }],
        };
        Models { list }
    }

    /// The models that are 6-DOF tools.
    pub fn rigid_bodies(&self) -> impl Iterator<Item = &ModelDef> {
        self.list.iter().filter(|m| m.rigid_body)
    }
}

/// A rigid body's state in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodySample {
    /// Rigid body id, as in [`ModelDef::id`].
    pub id: u32,
    /// Position of the tool's reported point (tip, else origin), metres, in the output's axes.
    pub position_m: [f64; 3],
    /// Unit quaternion, x y z w (NatNet's and ROS's order).
    pub orientation_xyzw: [f64; 4],
    /// RMS residual of the tool's layout fit, metres.
    pub mean_error_m: f64,
    /// The tool's pose was found in this frame; otherwise the pose fields carry no information.
    pub tracked: bool,
}

/// A marker (LED) position in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerSample {
    /// Model id (0: no model) in the high 16 bits, 1-based marker index in the low ones.
    pub id: u32,
    /// Position, metres, in the output's axes.
    pub position_m: [f64; 3],
    /// Ray gap / residual, metres (0 when not known per marker).
    pub residual_m: f64,
    /// Computed from a rigid body's fitted pose and its layout (not triangulated alone).
    pub model_solved: bool,
}

/// Everything an output sends for one position record. Buffers are reused from frame to
/// frame ([`SceneBuilder::fill`] clears and refills them), so steady state does not allocate.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SceneFrame {
    /// Index of the frame set the record comes from.
    pub frame: u64,
    /// Capture time of the set, CLOCK_MONOTONIC ns.
    pub capture_ts_ns: u64,
    /// Capture to publication by the processing loop, ns.
    pub latency_ns: u64,
    /// Positions were in the robot base frame (else in camera 0's) before the output's axes
    /// were applied.
    pub world_frame: bool,
    /// Per model of [`Models::list`], in that order: its markers (zeros when not tracked).
    pub marker_sets: Vec<Vec<[f64; 3]>>,
    /// One entry per rigid body model, in id order.
    pub bodies: Vec<BodySample>,
    /// Every 3-D marker of the frame (labelled list); the single LED and loose LEDs have model
    /// id 0 ([`loose_marker_id`]).
    pub markers: Vec<MarkerSample>,
    /// Markers that belong to no model: the single LED, or with tools the loose single LEDs
    /// of the set (from the per-tool slot, by increasing loose id).
    pub unlabelled_m: Vec<[f64; 3]>,
    /// With tools: the set's tracked loose single LEDs with their stable ids (the stream's
    /// `loose_id`), by increasing id; the same points as the tail of `unlabelled_m`.
    pub loose: Vec<LooseSample>,
    /// The loop's per-tool records of this very set were read (else, with several tools, the
    /// bodies are untracked and `loose` is empty for lack of data, not for lack of LEDs).
    pub per_tool: bool,
}

/// A loose single LED (no tool) in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LooseSample {
    /// Stable id (the stream's `loose_id`).
    pub loose_id: u32,
    /// Position, metres, in the output's axes.
    pub position_m: [f64; 3],
}

/// The labelled-marker id of a loose LED: model 0, marker number from its stable `loose_id`
/// (1 … 65535: ids wrap after 65535, far more than the 16 loose LEDs a set can hold at once).
pub fn loose_marker_id(loose_id: u32) -> u32 {
    loose_id % 0xFFFF + 1
}

/// Turns position records into [`SceneFrame`]s for a set of [`Models`] and [`Axes`].
#[derive(Debug, Clone)]
pub struct SceneBuilder {
    /// The models every frame describes.
    pub models: Models,
    /// The axes positions and orientations are given in.
    pub axes: Axes,
    /// The loop's per-tool records; without them (or for a set without them) only a set with
    /// a single tool has a tracked body, from the main record.
    pub tools: Option<watch::Receiver<ToolSet>>,
}

impl SceneBuilder {
    /// A builder for `models` in `axes`, reading only the main record (no per-tool slot).
    pub fn new(models: Models, axes: Axes) -> Self {
        Self {
            models,
            axes,
            tools: None,
        }
    }

    /// Reads every tool's pose from the loop's per-tool slot (`engine::Engine::with_tool_slot`).
    pub fn with_tools(mut self, tools: Option<watch::Receiver<ToolSet>>) -> Self {
        self.tools = tools;
        self
    }

    /// A record's position in the output axes, metres (the transform applied to every point).
    pub fn position_m(&self, rec: &PositionRecord) -> Option<[f64; 3]> {
        let p = rec.position_mm?;
        let v = self.axes.rotation(rec.world_frame) * Vector3::from(p) / 1e3;
        Some([v.x, v.y, v.z])
    }

    /// Fills `out` from `rec` (clears its lists first).
    pub fn fill(&self, rec: &PositionRecord, out: &mut SceneFrame) {
        let tool_set = self.tools.as_ref().map(|t| *t.borrow());
        self.fill_with(rec, tool_set.as_ref(), out);
    }

    /// Fills `out` from `rec` and the per-tool records `tool_set` taken with it (used only
    /// when they are of the same set), instead of the per-tool slot.
    pub fn fill_with(&self, rec: &PositionRecord, tool_set: Option<&ToolSet>, out: &mut SceneFrame) {
        out.frame = rec.frame;
        out.capture_ts_ns = rec.capture_ts_ns;
        out.latency_ns = u64::from(rec.latency_us) * 1000;
        out.world_frame = rec.world_frame;
        out.bodies.clear();
        out.markers.clear();
        out.unlabelled_m.clear();
        out.loose.clear();
        out.marker_sets.resize_with(self.models.list.len(), Vec::new);
        let rot = self.axes.rotation(rec.world_frame);
        let sample = |r: &PositionRecord| {
            let tracked = r.status == TrackStatus::Ok && r.position_mm.is_some();
            let p_m = r
                .position_mm
                .map(|p| rot * Vector3::from(p) / 1e3)
                .unwrap_or_else(Vector3::zeros);
            let error_m = if r.gap_mm.is_finite() { r.gap_mm / 1e3 } else { 0.0 };
            (tracked, p_m, error_m)
        };
        // The tool records of this very set (a newer set's are not mixed in).
        let tool_set = tool_set.filter(|t| t.frame == rec.frame && t.count > 0);
        out.per_tool = tool_set.is_some();
        let single_body = self.models.rigid_bodies().count() == 1;
        for (model, set) in self.models.list.iter().zip(out.marker_sets.iter_mut()) {
            set.clear();
            let body_rec = match &tool_set {
                Some(ts) if model.rigid_body => ts
                    .tools
                    .get(model.id.saturating_sub(1) as usize)
                    .and_then(|t| t.as_ref())
                    .map(|t| t.record),
                // Without per-tool records the main record is the (only) tool's.
                _ if !model.rigid_body || single_body => Some(*rec),
                _ => None,
            };
            let (tracked, p_m, error_m) = body_rec.as_ref().map_or((false, Vector3::zeros(), 0.0), sample);
            let orientation = body_rec.and_then(|r| r.orientation_wxyz);
            if model.rigid_body {
                let q = match (tracked, orientation) {
                    (true, Some(q)) => {
                        let q_rec = UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
                        UnitQuaternion::from_rotation_matrix(&rot) * q_rec
                    }
                    _ => UnitQuaternion::identity(),
                };
                let ok = tracked && orientation.is_some();
                let pos = if ok { p_m } else { Vector3::zeros() };
                out.bodies.push(BodySample {
                    id: model.id,
                    position_m: pos.into(),
                    orientation_xyzw: [q.i, q.j, q.k, q.w],
                    mean_error_m: if ok { error_m } else { 0.0 },
                    tracked: ok,
                });
                for (i, m) in model.markers_m.iter().enumerate() {
                    let world = if ok {
                        pos + q * Vector3::from(*m)
                    } else {
                        Vector3::zeros()
                    };
                    set.push(world.into());
                    if ok {
                        out.markers.push(MarkerSample {
                            id: (model.id << 16) | (i as u32 + 1),
                            position_m: world.into(),
                            residual_m: 0.0,
                            model_solved: true,
                        });
                    }
                }
            } else {
                set.push(if tracked { p_m.into() } else { [0.0; 3] });
                if tracked {
                    out.unlabelled_m.push(p_m.into());
                    out.markers.push(MarkerSample {
                        id: (model.id << 16) | 1,
                        position_m: p_m.into(),
                        residual_m: error_m,
                        model_solved: false,
                    });
                }
            }
        }
        // Loose single LEDs (no model): the legacy unlabelled list of NatNet 2 clients, and
        // labelled markers of model 0 flagged unlabelled, which NatNet 3+ clients read instead.
        if let Some(ts) = &tool_set {
            for l in ts.loose_records() {
                let (tracked, p_m, error_m) = sample(&l.record);
                if tracked {
                    out.unlabelled_m.push(p_m.into());
                    out.markers.push(MarkerSample {
                        id: loose_marker_id(l.loose_id),
                        position_m: p_m.into(),
                        residual_m: error_m,
                        model_solved: false,
                    });
                    out.loose.push(LooseSample {
                        loose_id: l.loose_id,
                        position_m: p_m.into(),
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(p: [f64; 3], q: Option<[f64; 4]>, world: bool) -> PositionRecord {
        PositionRecord {
            frame: 7,
            capture_ts_ns: 1_000,
            position_mm: Some(p),
            orientation_wxyz: q,
            gap_mm: 0.5,
            status: TrackStatus::Ok,
            cameras_used: 2,
            world_frame: world,
            latency_us: 3,
            params_crc: 0,
        }
    }

    #[test]
    fn y_up_turns_camera_and_robot_frames_so_that_up_is_y() {
        // Camera 0: "up" is −y. Robot base: "up" is +z. Both must come out as +y.
        let cam = Axes::YUp.rotation(false) * Vector3::new(0.0, -1.0, 0.0);
        let base = Axes::YUp.rotation(true) * Vector3::new(0.0, 0.0, 1.0);
        assert!((cam - Vector3::y()).norm() < 1e-12, "{cam}");
        assert!((base - Vector3::y()).norm() < 1e-12, "{base}");
        for w in [false, true] {
            assert!((Axes::YUp.rotation(w).matrix().determinant() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn rigid_body_markers_follow_the_pose_in_the_output_axes() {
        let rig_tool = irtrack_core::params::ToolDefinition {
            name: "t".into(),
            leds_mm: vec![[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 50.0, 0.0]],
            tip_mm: Some([0.0, 0.0, -20.0]),
        };
        let models = Models {
            list: vec![ModelDef {
                id: 1,
                name: "t".into(),
                markers_m: rig_tool
                    .leds_mm
                    .iter()
                    .map(|l| [l[0] / 1e3, l[1] / 1e3, (l[2] + 20.0) / 1e3])
                    .collect(),
                rigid_body: true,
            }],
        };
        // 90° about z: tool x → frame y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let r = rec([10.0, 20.0, 1000.0], Some([h, 0.0, 0.0, h]), true);
        let b = SceneBuilder::new(models, Axes::YUp);
        let mut f = SceneFrame::default();
        b.fill(&r, &mut f);
        assert_eq!(f.bodies.len(), 1);
        // Robot base (x, y, z) → (x, z, −y), metres.
        let p = f.bodies[0].position_m;
        assert!(
            (p[0] - 0.010).abs() < 1e-12 && (p[1] - 1.0).abs() < 1e-12 && (p[2] + 0.020).abs() < 1e-12,
            "{p:?}"
        );
        // LED 1 at tool x = 100 mm → base +y → output −z.
        let m1 = f.marker_sets[0][1];
        assert!(
            (m1[0] - 0.010).abs() < 1e-9 && (m1[1] - 1.020).abs() < 1e-9 && (m1[2] + 0.120).abs() < 1e-9,
            "{m1:?}"
        );
        assert_eq!(f.markers.len(), 3);
        assert_eq!(f.markers[2].id, (1 << 16) | 3);
        assert!((f.bodies[0].mean_error_m - 0.0005).abs() < 1e-15);
        let q = f.bodies[0].orientation_xyzw;
        assert!(((q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn single_led_is_an_unlabelled_marker_and_lost_records_send_zeros() {
        let b = SceneBuilder::new(Models::of_rig(None), Axes::Tracker);
        let mut f = SceneFrame::default();
        b.fill(&rec([1.0, 2.0, 3.0], None, false), &mut f);
        assert_eq!(f.unlabelled_m, vec![[0.001, 0.002, 0.003]]);
        assert_eq!(f.marker_sets, vec![vec![[0.001, 0.002, 0.003]]]);
        assert!(f.bodies.is_empty());
        let mut lost = rec([1.0, 2.0, 3.0], None, false);
        lost.status = TrackStatus::Lost;
        lost.position_mm = None;
        b.fill(&lost, &mut f);
        assert!(f.unlabelled_m.is_empty() && f.markers.is_empty());
        assert_eq!(f.marker_sets, vec![vec![[0.0; 3]]]);
    }

    #[test]
    fn loose_leds_are_unlabelled_markers_of_model_0_and_in_the_legacy_list() {
        use crate::engine::ToolSet;
        use irtrack_core::stream::LooseRecord;
        let models = Models {
            list: vec![ModelDef {
                id: 1,
                name: "t".into(),
                markers_m: vec![[0.0; 3], [0.1, 0.0, 0.0], [0.0, 0.05, 0.0]],
                rigid_body: true,
            }],
        };
        let main = rec([10.0, 20.0, 1000.0], Some([1.0, 0.0, 0.0, 0.0]), false);
        let mut ts = ToolSet::EMPTY;
        ts.frame = main.frame;
        ts.count = 1;
        ts.tools[0] = Some(irtrack_core::stream::ToolRecord::new(0, 1, "t", main).unwrap());
        for (k, (id, p)) in [(4u32, [1.0, 2.0, 3.0]), (70_000, [4.0, 5.0, 6.0])]
            .into_iter()
            .enumerate()
        {
            let mut r = rec(p, None, false);
            r.gap_mm = 0.25;
            ts.loose[k] = Some(LooseRecord {
                loose_id: id,
                loose_count: 2,
                frames_tracked: 9,
                record: r,
            });
        }
        ts.loose_leds = 2;
        let b = SceneBuilder::new(models, Axes::Tracker);
        let mut f = SceneFrame::default();
        b.fill_with(&main, Some(&ts), &mut f);
        assert_eq!(f.unlabelled_m, vec![[0.001, 0.002, 0.003], [0.004, 0.005, 0.006]]);
        // The tool's 3 LEDs, then the loose LEDs as model 0, numbered from their stable ids.
        assert_eq!(f.markers.len(), 5);
        let loose: Vec<(u32, [f64; 3], f64, bool)> = f.markers[3..]
            .iter()
            .map(|m| (m.id, m.position_m, m.residual_m, m.model_solved))
            .collect();
        assert_eq!(
            loose,
            vec![
                (5, [0.001, 0.002, 0.003], 0.00025, false),
                (70_000 % 65_535 + 1, [0.004, 0.005, 0.006], 0.00025, false)
            ]
        );
        assert!(f.markers[3..].iter().all(|m| m.id >> 16 == 0));
        assert_eq!(loose_marker_id(65_534), 65_535);
        assert_eq!(loose_marker_id(65_535), 1);
    }
}
