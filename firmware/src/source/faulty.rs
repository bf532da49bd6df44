//! Fault injection for tests and soak runs: wraps another [`FrameSource`] and, on a schedule
//! keyed by the number of sets requested so far, drops, duplicates or reorders sets, skews one
//! camera's timestamps, or makes a camera disappear for a number of sets. The spare set used for
//! reordering is allocated up front, so the wrapper does not allocate per set either.

use super::{FrameSet, FrameSource, SourceError, SourceStats};

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
    Skew { camera: usize, skew_ns: u64 },
    /// Camera `camera` reports lost for `sets` requests, then returns.
    Disappear { camera: usize, sets: u32 },
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
}

impl FaultySource {
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
        match self.fault_at(request) {
            None => self.inner.next_set(out),
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
    fn stats(&self) -> SourceStats {
        self.inner.stats()
    }
    fn describe(&self) -> String {
        format!("{} with injected faults", self.inner.describe())
    }
}
