//! Fault injection for tests and soak runs: wraps another [`FrameSource`] and, on a schedule
//! keyed by the number of sets requested so far, drops, duplicates or reorders sets, skews one
//! camera's timestamps, or makes a camera disappear for a number of sets. Pixel faults change
//! what a camera sees for a number of sets: a reflection of the marker (a second, equally bright
//! spot that moves with it), a partly covered spot, or a spot hidden from that camera. The spare
//! set used for reordering is allocated up front, so the wrapper does not allocate per set either.

use super::{Frame, FrameSet, FrameSource, Pixels, SourceError, SourceStats};

/// One injected fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// The set is fetched and thrown away (the consumer sees an index gap).
    Drop,
    /// The previous set is delivered again, unchanged.
    Duplicate,
    /// This set and the next are delivered in swapped order.
    Reorder,
    /// Camera `camera`'s timestamp is shifted by `skew_ns` in this set.
    Skew {
        /// Camera index, configuration order.
        camera: usize,
        /// Added to the frame's capture timestamp, ns.
        skew_ns: u64,
    },
    /// Camera `camera` reports lost for `sets` requests, then returns.
    Disappear {
        /// Camera index, configuration order.
        camera: usize,
        /// How many sets (requests) the fault lasts.
        sets: u32,
    },
    /// For `sets` sets, camera `camera` sees the marker's spot a second time, shifted by
    /// (`du_px`, `dv_px`): a reflection on a shiny surface.
    Reflection {
        /// Camera index, configuration order.
        camera: usize,
        /// How many sets (requests) the fault lasts.
        sets: u32,
        /// Shift of the copy along image columns, pixels.
        du_px: i32,
        /// Shift of the copy along image rows, pixels.
        dv_px: i32,
    },
    /// For `sets` sets, the left half of the marker's spot (columns left of its peak) is
    /// covered in camera `camera`: an edge of the tool or the hand in front of the LED.
    HalfOccluded {
        /// Camera index, configuration order.
        camera: usize,
        /// How many sets (requests) the fault lasts.
        sets: u32,
    },
    /// For `sets` sets, the marker's spot is covered completely in camera `camera`.
    Hidden {
        /// Camera index, configuration order.
        camera: usize,
        /// How many sets (requests) the fault lasts.
        sets: u32,
    },
}

/// Half size of the window around the brightest pixel treated as the marker's spot.
const SPOT_HALF_PX: i64 = 7;

/// A pixel fault in progress and the sets it still applies to.
#[derive(Debug, Clone, Copy)]
struct ActivePixelFault {
    fault: Fault,
    sets_left: u32,
}

/// A [`FrameSource`] that injects `(request number, fault)` pairs.
pub struct FaultySource {
    inner: Box<dyn FrameSource>,
    schedule: Vec<(u64, Fault)>,
    requests: u64,
    spare: FrameSet,
    /// A set held back by [`Fault::Reorder`], delivered on the next request.
    held: bool,
    lost_left: u32,
    lost_camera: usize,
    pixel_fault: Option<ActivePixelFault>,
}

impl FaultySource {
    /// Wraps `inner`; each `(n, fault)` of `schedule` is applied to the `n`-th call of
    /// `next_set` (0-based, counting every call).
    pub fn new(inner: Box<dyn FrameSource>, mut schedule: Vec<(u64, Fault)>) -> Self {
        schedule.sort_by_key(|&(at, _)| at);
        let spare = inner.allocate_set();
        Self {
            inner,
            schedule,
            requests: 0,
            spare,
            held: false,
            lost_left: 0,
            lost_camera: 0,
            pixel_fault: None,
        }
    }

    /// Applies the pixel fault in progress (if any) to a delivered set.
    fn apply_pixel_fault(&mut self, out: &mut FrameSet) {
        let Some(active) = &mut self.pixel_fault else {
            return;
        };
        let (camera, edit) = match active.fault {
            Fault::Reflection {
                camera, du_px, dv_px, ..
            } => (camera, SpotEdit::Copy { du_px, dv_px }),
            Fault::HalfOccluded { camera, .. } => (camera, SpotEdit::CoverLeft),
            Fault::Hidden { camera, .. } => (camera, SpotEdit::Cover),
            _ => return,
        };
        if let Some(frame) = out.frames.get_mut(camera) {
            edit_spot(frame, edit);
        }
        active.sets_left = active.sets_left.saturating_sub(1);
        if active.sets_left == 0 {
            self.pixel_fault = None;
        }
    }

    fn fault_at(&self, request: u64) -> Option<Fault> {
        self.schedule
            .iter()
            .find(|&&(at, _)| at == request)
            .map(|&(_, f)| f)
    }
}

impl FrameSource for FaultySource {
    fn camera_count(&self) -> usize {
        self.inner.camera_count()
    }
    fn allocate_set(&self) -> FrameSet {
        self.inner.allocate_set()
    }
    fn next_set(&mut self, out: &mut FrameSet) -> Result<(), SourceError> {
        let request = self.requests;
        self.requests += 1;
        if self.lost_left > 0 {
            self.lost_left -= 1;
            return Err(SourceError::CameraLost {
                camera: self.lost_camera,
                device: "fault injection".into(),
                reason: "camera disappeared".into(),
            });
        }
        if self.held {
            self.held = false;
            std::mem::swap(out, &mut self.spare);
            return Ok(());
        }
        let result = self.next_set_scheduled(request, out);
        if result.is_ok() {
            self.apply_pixel_fault(out);
        }
        result
    }
    fn stats(&self) -> SourceStats {
        self.inner.stats()
    }
    fn nominal_fps(&self) -> Option<f64> {
        self.inner.nominal_fps()
    }
    fn describe(&self) -> String {
        format!("{} with injected faults", self.inner.describe())
    }

    fn end_summary(&self) -> Option<String> {
        self.inner.end_summary()
    }

    fn remote_blobs(&self, camera: usize) -> Option<&[irtrack_core::blob::Blob]> {
        self.inner.remote_blobs(camera)
    }

    fn vet_solution(&mut self, tracker: &mut irtrack_core::pipeline::Tracker) -> bool {
        self.inner.vet_solution(tracker)
    }

    fn has_pixels(&self, camera: usize) -> bool {
        self.inner.has_pixels(camera)
    }

    fn refresh_pixels(&mut self, out: &mut FrameSet) {
        self.inner.refresh_pixels(out)
    }

    fn set_detection(&mut self, cfg: &irtrack_core::pipeline::TrackerConfig) -> Result<(), SourceError> {
        self.inner.set_detection(cfg)
    }

    fn controls(&self) -> Vec<super::CameraControls> {
        self.inner.controls()
    }

    fn set_control(
        &mut self,
        camera: usize,
        control: super::CameraControl,
        value: i64,
    ) -> Result<(), SourceError> {
        self.inner.set_control(camera, control, value)
    }
}

impl FaultySource {
    /// The set for request `request` with the scheduled set-level fault applied.
    fn next_set_scheduled(&mut self, request: u64, out: &mut FrameSet) -> Result<(), SourceError> {
        match self.fault_at(request) {
            None => self.inner.next_set(out),
            Some(
                f @ (Fault::Reflection { sets, .. }
                | Fault::HalfOccluded { sets, .. }
                | Fault::Hidden { sets, .. }),
            ) => {
                self.pixel_fault = Some(ActivePixelFault {
                    fault: f,
                    sets_left: sets,
                });
                self.inner.next_set(out)
            }
            Some(Fault::Drop) => {
                self.inner.next_set(out)?;
                self.inner.next_set(out)
            }
            // `out` still holds the previous set.
            Some(Fault::Duplicate) => Ok(()),
            Some(Fault::Reorder) => {
                self.inner.next_set(&mut self.spare)?;
                self.inner.next_set(out)?;
                self.held = true;
                Ok(())
            }
            Some(Fault::Skew { camera, skew_ns }) => {
                self.inner.next_set(out)?;
                if let Some(f) = out.frames.get_mut(camera) {
                    f.timestamp_ns = f.timestamp_ns.saturating_add(skew_ns);
                    out.pairing_error_ns = out.pairing_error_ns.max(skew_ns);
                }
                Ok(())
            }
            Some(Fault::Disappear { camera, sets }) => {
                self.lost_camera = camera;
                self.lost_left = sets.saturating_sub(1);
                Err(SourceError::CameraLost {
                    camera,
                    device: "fault injection".into(),
                    reason: "camera disappeared".into(),
                })
            }
        }
    }
}

/// What a pixel fault does to the marker's spot.
#[derive(Debug, Clone, Copy)]
enum SpotEdit {
    Copy { du_px: i32, dv_px: i32 },
    CoverLeft,
    Cover,
}

fn edit_spot(frame: &mut Frame, edit: SpotEdit) {
    let (w, h, stride) = (
        i64::from(frame.width_px),
        i64::from(frame.height_px),
        i64::from(frame.stride_px),
    );
    match &mut frame.pixels {
        Pixels::U8(px) => edit_spot_in(px, w, h, stride, edit),
        Pixels::U16(px) => edit_spot_in(px, w, h, stride, edit),
    }
}

/// Finds the brightest pixel (the marker's spot centre) and edits the window around it. A
/// covered pixel takes the window's darkest value, i.e. the local background.
fn edit_spot_in<T: Copy + Ord>(px: &mut [T], w: i64, h: i64, stride: i64, edit: SpotEdit) {
    let at = |u: i64, v: i64| usize::try_from(v * stride + u).ok();
    let mut peak: Option<(i64, i64, T)> = None;
    for v in 0..h {
        for u in 0..w {
            if let Some(&p) = at(u, v).and_then(|i| px.get(i))
                && peak.is_none_or(|(_, _, best)| p > best)
            {
                peak = Some((u, v, p));
            }
        }
    }
    let Some((pu, pv, _)) = peak else { return };
    let window = |f: &mut dyn FnMut(i64, i64)| {
        for v in (pv - SPOT_HALF_PX).max(0)..=(pv + SPOT_HALF_PX).min(h - 1) {
            for u in (pu - SPOT_HALF_PX).max(0)..=(pu + SPOT_HALF_PX).min(w - 1) {
                f(u, v);
            }
        }
    };
    let mut background: Option<T> = None;
    window(&mut |u, v| {
        if let Some(&p) = at(u, v).and_then(|i| px.get(i)) {
            background = Some(background.map_or(p, |b| b.min(p)));
        }
    });
    let Some(background) = background else { return };
    match edit {
        SpotEdit::Copy { du_px, dv_px } => {
            let (du, dv) = (i64::from(du_px), i64::from(dv_px));
            window(&mut |u, v| {
                let (tu, tv) = (u + du, v + dv);
                if !(0..w).contains(&tu) || !(0..h).contains(&tv) {
                    return;
                }
                if let (Some(src), Some(dst)) = (at(u, v), at(tu, tv))
                    && let Some(&p) = px.get(src)
                    && let Some(d) = px.get_mut(dst)
                {
                    *d = (*d).max(p);
                }
            });
        }
        SpotEdit::CoverLeft | SpotEdit::Cover => {
            let left_only = matches!(edit, SpotEdit::CoverLeft);
            window(&mut |u, v| {
                if left_only && u >= pu {
                    return;
                }
                if let Some(p) = at(u, v).and_then(|i| px.get_mut(i)) {
                    *p = background;
                }
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use irtrack_core::blob::{BlobConfig, BlobDetector, BlobLimits};
    use irtrack_core::image::GrayImage;

    const W: u32 = 96;
    const H: u32 = 64;

    /// A frame with one Gaussian spot (σ 1.5 px, peak 200 DN) at (40.3, 30.6) on 10 DN.
    fn frame() -> Frame {
        let mut px = vec![0u8; (W * H) as usize];
        for v in 0..H {
            for u in 0..W {
                let d2 = (f64::from(u) - 40.3).powi(2) + (f64::from(v) - 30.6).powi(2);
                px[(v * W + u) as usize] = (10.0 + 200.0 * (-d2 / (2.0 * 1.5 * 1.5)).exp()).round() as u8;
            }
        }
        Frame {
            width_px: W,
            height_px: H,
            stride_px: W,
            bit_depth: 8,
            pixels: Pixels::U8(px),
            timestamp_ns: 0,
            sequence: 0,
        }
    }

    fn blobs(f: &Frame) -> Vec<(f64, f64)> {
        let Pixels::U8(px) = &f.pixels else { panic!() };
        let mut d = BlobDetector::new(BlobLimits::for_frame(W, H)).unwrap();
        d.detect(
            &GrayImage::new(px, W, H, W).unwrap(),
            None,
            &BlobConfig::default(),
        )
        .unwrap();
        d.blobs().iter().map(|b| (b.x_px, b.y_px)).collect()
    }

    #[test]
    fn spot_edits_do_what_their_names_say() {
        let clean = blobs(&frame());
        assert_eq!(clean.len(), 1);
        let mut f = frame();
        edit_spot(&mut f, SpotEdit::Copy { du_px: 30, dv_px: 12 });
        let mut two = blobs(&f);
        two.sort_by(|a, b| a.0.total_cmp(&b.0));
        assert_eq!(two.len(), 2, "{two:?}");
        assert!((two[1].0 - two[0].0 - 30.0).abs() < 0.05 && (two[1].1 - two[0].1 - 12.0).abs() < 0.05);
        let mut f = frame();
        edit_spot(&mut f, SpotEdit::CoverLeft);
        let half = blobs(&f);
        assert_eq!(half.len(), 1);
        assert!(
            half[0].0 - clean[0].0 > 0.3,
            "centroid not pushed right: {half:?} vs {clean:?}"
        );
        let mut f = frame();
        edit_spot(&mut f, SpotEdit::Cover);
        assert!(blobs(&f).is_empty());
    }
}
