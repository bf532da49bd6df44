//! Frame sources: the hardware seam for cameras.
//!
//! The processing loop owns one [`FrameSet`] allocated up front and asks the source to fill it
//! in place, so steady-state capture does not allocate.

use irtrack_core::pgm;

/// Pixel storage of one frame. 8-bit sensors use `U8`; 10/12/16-bit sensors use `U16`
/// (values right-aligned, i.e. a 10-bit sensor gives 0..=1023).
#[derive(Debug, Clone, PartialEq)]
pub enum Pixels {
    /// 8-bit samples, row-major with the frame's stride.
    U8(Vec<u8>),
    /// 10- to 16-bit samples, right-aligned, row-major with the frame's stride.
    U16(Vec<u16>),
}

/// One camera frame, filled in place by a [`FrameSource`].
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Image width in pixels.
    pub width_px: u32,
    /// Image height in pixels (rows).
    pub height_px: u32,
    /// Row stride in pixels (not bytes); `>= width_px`.
    pub stride_px: u32,
    /// Significant bits per pixel (8, 10, 12 or 16).
    pub bit_depth: u8,
    /// The samples, `stride_px * height_px` of them.
    pub pixels: Pixels,
    /// Capture time, CLOCK_MONOTONIC ns: the V4L2 buffer's driver timestamp; the simulator's
    /// hand-over instant (the scene is rendered as it is at that instant, ahead of it).
    pub timestamp_ns: u64,
    /// Driver or source sequence number of this camera.
    pub sequence: u64,
}

impl Frame {
    /// The pixels as an image view for the PGM encoder (`irtrack_core::pgm`, docs/frameset.md).
    pub fn image(&self) -> pgm::Image<'_> {
        pgm::Image {
            width_px: self.width_px,
            height_px: self.height_px,
            stride_px: self.stride_px,
            bit_depth: self.bit_depth,
            samples: match &self.pixels {
                Pixels::U8(px) => pgm::Samples::U8(px),
                Pixels::U16(px) => pgm::Samples::U16(px),
            },
        }
    }

    /// An empty frame shaped like the PGM file described by `h` (replay's buffers).
    pub fn shaped_like_pgm(h: &pgm::PgmHeader) -> Frame {
        let n = h.width_px as usize * h.height_px as usize;
        Frame {
            width_px: h.width_px,
            height_px: h.height_px,
            stride_px: h.width_px,
            bit_depth: h.bit_depth(),
            pixels: if h.bytes_per_sample() == 1 {
                Pixels::U8(vec![0; n])
            } else {
                Pixels::U16(vec![0; n])
            },
            timestamp_ns: 0,
            sequence: 0,
        }
    }

    /// Decodes the PGM file `data` into this frame in place: same size and sample width
    /// required, no allocation; the bit depth follows the file's maxval.
    pub fn decode_pgm(&mut self, data: &[u8]) -> Result<(), irtrack_core::Error> {
        let h = pgm::parse_header(data)?;
        if (h.width_px, h.height_px) != (self.width_px, self.height_px) {
            return Err(irtrack_core::Error::Pgm {
                reason: format!(
                    "size {}x{} differs from the first frame's {}x{}",
                    h.width_px, h.height_px, self.width_px, self.height_px
                ),
            });
        }
        let stride = self.stride_px as usize;
        let dst = match &mut self.pixels {
            Pixels::U8(px) => pgm::SamplesMut::U8(px),
            Pixels::U16(px) => pgm::SamplesMut::U16(px),
        };
        pgm::decode_into(data, &h, dst, stride)?;
        self.bit_depth = h.bit_depth();
        Ok(())
    }
}

/// One frame per camera, paired in time.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameSet {
    /// Index of this set, counted by the source (gaps mean dropped sets).
    pub index: u64,
    /// One frame per camera, in camera order.
    pub frames: Vec<Frame>,
    /// Largest timestamp difference between the paired frames.
    pub pairing_error_ns: u64,
    /// Time the source itself spent producing the set before the frames' timestamps (the
    /// simulator's rendering, which it does ahead of the capture instant); 0 for cameras.
    /// Reported as the `render` stage, never as part of capture → published.
    pub render_ns: u64,
}

impl FrameSet {
    /// Each camera's image size, in camera order (what a tracker is built for).
    pub fn image_sizes(&self) -> Vec<irtrack_core::camera::ImageSize> {
        self.frames
            .iter()
            .map(|f| irtrack_core::camera::ImageSize {
                width_px: f.width_px,
                height_px: f.height_px,
            })
            .collect()
    }
}

/// Counters every source keeps.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SourceStats {
    /// Sets handed to the loop.
    pub sets_delivered: u64,
    /// Frames that found no partner in time and were dropped.
    pub unpaired_dropped: u64,
    /// Sets the source skipped (e.g. simulated dropped frames, consumer too slow).
    pub sets_dropped: u64,
    /// Times a camera was lost and reopened.
    pub reconnects: u64,
    /// Bumped when the cameras' live controls changed without the loop asking (a cluster
    /// solver's own cameras placed by a new parameter set): the set-up view re-reads them.
    pub controls_generation: u64,
}

/// Errors of a frame source. `Transient` errors are retried by the loop; the others stop it.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// A camera stopped delivering or could not be opened; the loop retries it.
    #[error("camera {camera} ({device}) unavailable: {reason}")]
    CameraLost {
        /// Camera index (configuration order).
        camera: usize,
        /// Device path or name, e.g. `/dev/video0`.
        device: String,
        /// The driver's or the source's explanation.
        reason: String,
    },
    /// No set arrived within the source's wait limit.
    #[error("no frame within {timeout_ms} ms")]
    Timeout {
        /// How long the source waited, ms.
        timeout_ms: u64,
    },
    /// A finite source (replay) has delivered its last set.
    #[error("end of recorded frames")]
    EndOfStream,
    /// The source holds its first set until something it was told to wait for is there (a
    /// replay's `wait_for_params`, `wait_for_client`); the loop asks again, publishing nothing.
    #[error("waiting: {reason}")]
    Waiting {
        /// What it waits for, in words (also on `/status` → `source.waiting`).
        reason: String,
    },
    /// The source's configuration cannot be used; the text says what is wrong.
    #[error("source configuration: {0}")]
    Config(String),
    /// Reading or writing the file at `path` failed.
    #[error("I/O on {path}: {source}")]
    Io {
        /// The file or device concerned.
        path: String,
        /// The operating system's error.
        source: std::io::Error,
    },
}

/// A camera setting the set-up view may change live.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraControl {
    /// Exposure time in the camera's units (V4L2: 100 µs; simulator: the same).
    Exposure,
    /// Analogue gain in the camera's units.
    Gain,
}

/// Current value and range of one control.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct ControlValue {
    /// Current setting, in the control's units.
    pub value: i64,
    /// Smallest allowed setting.
    pub min: i64,
    /// Largest allowed setting.
    pub max: i64,
}

/// The live controls of one camera; `None` = the camera has no such control.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct CameraControls {
    /// Exposure time (see [`CameraControl::Exposure`] for its units).
    pub exposure: Option<ControlValue>,
    /// Analogue gain, in the camera's units.
    pub gain: Option<ControlValue>,
}

impl CameraControls {
    /// Value and range of `control`, if the camera has it.
    pub fn get(&self, control: CameraControl) -> Option<ControlValue> {
        match control {
            CameraControl::Exposure => self.exposure,
            CameraControl::Gain => self.gain,
        }
    }
}

/// A synchronized multi-camera source.
pub trait FrameSource: Send {
    /// Number of cameras.
    fn camera_count(&self) -> usize;
    /// A frame set shaped for this source (allocated once by the caller).
    fn allocate_set(&self) -> FrameSet;
    /// Blocks until the next paired frame set is available and writes it into `out`.
    fn next_set(&mut self, out: &mut FrameSet) -> Result<(), SourceError>;
    /// Counters since start.
    fn stats(&self) -> SourceStats;
    /// Hands the source the loop's status, once, when the loop is built: a replay that waits
    /// for a parameter set or a client looks there and says there that it waits.
    fn attach_status(&mut self, _status: &std::sync::Arc<crate::status::SharedStatus>) {}
    /// The rate the source really delivers at, when it knows better than the config (a
    /// replay: its recording's timestamps); the loop's deadline follows it.
    fn nominal_fps(&self) -> Option<f64> {
        None
    }
    /// Human-readable description for status and logs.
    fn describe(&self) -> String;
    /// Why a finite source ended, in words (replay: sets delivered of recorded, and what was
    /// skipped); said by the loop when the stream ends.
    fn end_summary(&self) -> Option<String> {
        None
    }
    /// Blobs of `camera` for the set just delivered, found elsewhere (a cluster solver's
    /// camera boards): the loop uses them instead of detecting in the frame. `None`: detect.
    fn remote_blobs(&self, _camera: usize) -> Option<&[irtrack_core::blob::Blob]> {
        None
    }
    /// Called by the loop right after `tracker` solved the set just delivered. A source whose
    /// cameras come from several boards (the cluster solver) checks that they agree, may
    /// solve again without a board's cameras ([`irtrack_core::pipeline::Tracker::solve_excluding`];
    /// the loop then publishes the tracker's measurement), and returns false when the set must
    /// give no position. By default every solve stands.
    fn vet_solution(&mut self, _tracker: &mut irtrack_core::pipeline::Tracker) -> bool {
        true
    }

    /// Whether `camera`'s frames hold its pixels here. A cluster solver's camera-board
    /// cameras do not (their blobs come as [`FrameSource::remote_blobs`], the frame stays
    /// blank): the set-up view shows them as blobs only and judges no pixels of theirs.
    fn has_pixels(&self, _camera: usize) -> bool {
        true
    }
    /// Writes the newest pixels of cameras captured elsewhere in this process (a solver's own
    /// cameras, captured on a thread of their own) into `out`. The loop calls it only when a
    /// viewer's copy is due, never per set; by default there is nothing to fill.
    fn refresh_pixels(&mut self, _out: &mut FrameSet) {}
    /// The detector settings changed (set-up view): a source that detects blobs itself (a
    /// solver's own cameras) applies them. By default there is nothing to do.
    fn set_detection(&mut self, _cfg: &irtrack_core::pipeline::TrackerConfig) -> Result<(), SourceError> {
        Ok(())
    }

    /// Exposure and gain of every camera (camera order); by default none are supported.
    fn controls(&self) -> Vec<CameraControls> {
        vec![CameraControls::default(); self.camera_count()]
    }
    /// Sets one control of one camera, effective for the next frames. Called by the
    /// processing loop between sets, only when the operator changes a value.
    fn set_control(&mut self, camera: usize, control: CameraControl, value: i64) -> Result<(), SourceError> {
        let _ = value;
        Err(SourceError::Config(format!(
            "camera {camera}: {control:?} cannot be changed on this source ({})",
            self.describe()
        )))
    }
}

pub mod faulty;
pub mod replay;
pub mod sim;
pub mod v4l2;
