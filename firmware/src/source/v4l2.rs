//! V4L2 capture from two or more cameras, paired by kernel timestamp.
//!
//! Each camera is negotiated to the first format of the preference list it supports (8/10/16-bit
//! grey first, YUYV as a fallback whose luma is read straight out of the mmap buffer), streams
//! through a few mmap buffers, and is polled together with the others on one thread. A dequeued
//! frame is converted at once into the caller's pre-allocated [`Frame`] (the only copy), so
//! holding a frame while its partner is awaited costs no driver buffer. A camera whose ioctl
//! fails is reported as [`SourceError::CameraLost`] and reopened with exponential backoff;
//! while one is lost the others are watched for hang-ups, so that a device gone with it is
//! released at once (its stale descriptor would otherwise keep the node number taken and the
//! returning driver would register the camera under another path).

use irtrack_core::slots::SlotGrid;
use std::collections::BTreeMap;
use std::io;
use std::os::raw::c_int;
use std::time::{Duration, Instant};

use serde::Deserialize;
use tracing::{info, warn};
use v4l::buffer::{Flags as BufferFlags, Type as BufferType};
use v4l::capability::Flags as CapFlags;
use v4l::control::{Control, Value as ControlValue};
use v4l::io::traits::{CaptureStream, Stream as _};
use v4l::prelude::MmapStream;
use v4l::video::Capture;
use v4l::video::capture::Parameters;
use v4l::{Device, FourCC};

use super::{Frame, FrameSet, FrameSource, Pixels, SourceError, SourceStats};

/// `[source.v4l2]` section of the irtrackd config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct V4l2Config {
    /// Device paths or /dev/v4l/by-id links, one per camera, camera 0 first.
    pub devices: Vec<String>,
    /// Requested frame width, pixels; the driver must accept it exactly.
    pub width_px: u32,
    /// Requested frame height, pixels; the driver must accept it exactly.
    pub height_px: u32,
    /// Requested frame rate, Hz.
    pub fps: u32,
    /// Pixel formats in order of preference (FourCC codes: GREY, Y10, Y16, YUYV).
    #[serde(default = "default_formats")]
    pub formats: Vec<String>,
    /// mmap buffers per camera (2..=32); few buffers keep latency low.
    #[serde(default = "default_buffer_count")]
    pub buffer_count: u32,
    /// Manual exposure time; applied where the camera has exposure controls, logged if not.
    #[serde(default)]
    pub exposure_us: Option<u32>,
    /// Manual analogue gain in the camera's own units; auto gain is switched off.
    #[serde(default)]
    pub gain: Option<i64>,
    /// Further controls by their V4L2 name (case-insensitive), e.g. `"Test Pattern" = 1`.
    #[serde(default)]
    pub controls: BTreeMap<String, i64>,
    /// Largest timestamp difference accepted between paired frames; default none (one frame per
    /// camera and slot of the frame-period grid, the loop judges the spread).
    #[serde(default)]
    pub max_pairing_error_us: Option<u64>,
    /// A set not complete within this time is reported as a timeout.
    #[serde(default = "default_frame_timeout_ms")]
    pub frame_timeout_ms: u64,
    /// First delay between attempts to reopen a lost camera, ms.
    #[serde(default = "default_reconnect_min_ms")]
    pub reconnect_min_ms: u64,
    /// Largest delay between reopen attempts, ms: the delay doubles after each failure up to this.
    #[serde(default = "default_reconnect_max_ms")]
    pub reconnect_max_ms: u64,
}

fn default_formats() -> Vec<String> {
    ["GREY", "Y16", "Y10", "YUYV"]
        .iter()
        .map(|s| (*s).to_owned())
        .collect()
}
fn default_buffer_count() -> u32 {
    4
}
fn default_frame_timeout_ms() -> u64 {
    1000
}
fn default_reconnect_min_ms() -> u64 {
    250
}
fn default_reconnect_max_ms() -> u64 {
    5000
}

/// Pixel formats this source can deliver to the processing loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    /// 8-bit luma.
    Grey,
    /// 10-bit luma in little-endian 16-bit words.
    Y10,
    /// 16-bit little-endian luma.
    Y16,
    /// 4:2:2 packed Y0 U Y1 V; only the luma bytes are read.
    Yuyv,
}

impl PixelFormat {
    /// The format named by a FourCC code as written in the config (`GREY`/`GRAY`/`Y8`, `Y10`,
    /// `Y16`, `YUYV`; any case); `None` if unknown.
    pub fn parse(name: &str) -> Option<Self> {
        match name.to_ascii_uppercase().as_str() {
            "GREY" | "GRAY" | "Y8" => Some(Self::Grey),
            "Y10" | "Y10 " => Some(Self::Y10),
            "Y16" | "Y16 " => Some(Self::Y16),
            "YUYV" => Some(Self::Yuyv),
            _ => None,
        }
    }

    /// The V4L2 FourCC code of the format.
    pub fn fourcc(self) -> FourCC {
        FourCC::new(match self {
            Self::Grey => b"GREY",
            Self::Y10 => b"Y10 ",
            Self::Y16 => b"Y16 ",
            Self::Yuyv => b"YUYV",
        })
    }

    /// The FourCC code as text, for logs and the status.
    pub fn name(self) -> &'static str {
        match self {
            Self::Grey => "GREY",
            Self::Y10 => "Y10",
            Self::Y16 => "Y16",
            Self::Yuyv => "YUYV",
        }
    }

    /// Significant bits of the luma samples the loop receives.
    pub fn bit_depth(self) -> u8 {
        match self {
            Self::Grey | Self::Yuyv => 8,
            Self::Y10 => 10,
            Self::Y16 => 16,
        }
    }

    /// Bytes per pixel in the driver buffer.
    fn bytes_per_px(self) -> usize {
        match self {
            Self::Grey => 1,
            Self::Y10 | Self::Y16 | Self::Yuyv => 2,
        }
    }
}

impl V4l2Config {
    /// Checks the values that do not need a device; `open` calls it first.
    pub fn validate(&self) -> Result<Vec<PixelFormat>, SourceError> {
        let bad = |msg: String| Err(SourceError::Config(msg));
        if self.devices.is_empty() {
            return bad("devices is empty; name at least one camera".into());
        }
        if self.width_px == 0 || self.height_px == 0 || self.fps == 0 {
            return bad(format!(
                "width_px, height_px and fps must be > 0 (got {}x{} @ {})",
                self.width_px, self.height_px, self.fps
            ));
        }
        if !(2..=32).contains(&self.buffer_count) {
            return bad(format!("buffer_count must be 2..=32 (got {})", self.buffer_count));
        }
        if self.reconnect_min_ms == 0 || self.reconnect_max_ms < self.reconnect_min_ms {
            return bad(format!(
                "need 0 < reconnect_min_ms <= reconnect_max_ms (got {} and {})",
                self.reconnect_min_ms, self.reconnect_max_ms
            ));
        }
        let mut formats = Vec::new();
        for name in &self.formats {
            match PixelFormat::parse(name) {
                Some(f) => formats.push(f),
                None => {
                    return bad(format!(
                        "unknown pixel format {name:?} (known: GREY, Y10, Y16, YUYV)"
                    ));
                }
            }
        }
        if formats.is_empty() {
            return bad("formats is empty".into());
        }
        Ok(formats)
    }

    /// Largest spread of a set's timestamps when configured (`max_pairing_error_us`); by
    /// default the pairing takes one frame per camera and slot, and the loop judges the spread.
    fn pairing_tolerance_ns(&self) -> Option<u64> {
        self.max_pairing_error_us.map(|us| us.saturating_mul(1000))
    }

    /// The nominal frame period, ns.
    fn period_ns(&self) -> u64 {
        1_000_000_000 / u64::from(self.fps.max(1))
    }
}

/// Opens every configured camera, negotiates format, size, rate and controls, and starts
/// streaming. All cameras must be present at start; later losses are recovered by reopening.
pub fn open(config: &V4l2Config) -> Result<Box<dyn FrameSource>, SourceError> {
    Ok(Box::new(V4l2Source::open(config)?))
}

/// Copies one driver buffer into a frame, reducing it to luma. `bytes_per_line` is the driver's
/// row pitch; `frame` must already have this camera's size and pixel type.
pub fn convert_into(
    format: PixelFormat,
    src: &[u8],
    bytes_per_line: usize,
    frame: &mut Frame,
) -> Result<(), SourceError> {
    let width = frame.width_px as usize;
    let height = frame.height_px as usize;
    let row_bytes = width * format.bytes_per_px();
    if bytes_per_line < row_bytes || height == 0 || src.len() < bytes_per_line * (height - 1) + row_bytes {
        return Err(SourceError::Config(format!(
            "driver buffer of {} bytes (pitch {bytes_per_line}) too small for {width}x{height} {}",
            src.len(),
            format.name()
        )));
    }
    let stride = frame.stride_px as usize;
    match (&mut frame.pixels, format) {
        (Pixels::U8(dst), PixelFormat::Grey) => {
            for (src_row, dst_row) in src
                .chunks(bytes_per_line)
                .zip(dst.chunks_mut(stride))
                .take(height)
            {
                dst_row[..width].copy_from_slice(&src_row[..width]);
            }
        }
        (Pixels::U8(dst), PixelFormat::Yuyv) => {
            // Luma is every even byte; read it strided straight from the mmap buffer.
            for (src_row, dst_row) in src
                .chunks(bytes_per_line)
                .zip(dst.chunks_mut(stride))
                .take(height)
            {
                for (d, y) in dst_row[..width]
                    .iter_mut()
                    .zip(src_row[..row_bytes].iter().step_by(2))
                {
                    *d = *y;
                }
            }
        }
        (Pixels::U16(dst), PixelFormat::Y10 | PixelFormat::Y16) => {
            for (src_row, dst_row) in src
                .chunks(bytes_per_line)
                .zip(dst.chunks_mut(stride))
                .take(height)
            {
                for (d, le) in dst_row[..width]
                    .iter_mut()
                    .zip(src_row[..row_bytes].chunks_exact(2))
                {
                    *d = u16::from_le_bytes([le[0], le[1]]);
                }
            }
        }
        _ => {
            return Err(SourceError::Config(format!(
                "frame buffer pixel type does not match {}",
                format.name()
            )));
        }
    }
    Ok(())
}

/// Matches frames of several cameras by timestamp.
///
/// Each frame is given a slot of a frame-period grid centred on camera 0's frames
/// ([`irtrack_core::slots`]); a set is every camera's frame of one slot. Free-running USB
/// cameras expose at any phase: three of them a third of a period apart have no three frames
/// within half a period of each other, yet each has one frame per slot. Each camera has one
/// pending frame; a frame of an older slot than another camera's pending one can never pair
/// and is dropped. With `max_spread_ns` (`max_pairing_error_us`), a slot's frames further apart
/// than that are not paired either (the older ones are dropped).
#[derive(Debug, Clone)]
pub struct Pairer {
    /// Per camera: slot and timestamp of its newest unpaired frame.
    pending: Vec<Option<(u64, u64)>>,
    grid: SlotGrid,
    max_spread_ns: Option<u64>,
}

impl Pairer {
    /// A pairer for `cameras` cameras (at least one) delivering a frame every `period_ns`.
    pub fn new(cameras: usize, period_ns: u64, max_spread_ns: Option<u64>) -> Result<Self, SourceError> {
        Ok(Self {
            pending: vec![None; cameras],
            grid: SlotGrid::new(cameras, period_ns.max(1), 0, SlotGrid::DEFAULT_HYSTERESIS)
                .map_err(|e| SourceError::Config(format!("frame pairing: {e}")))?,
            max_spread_ns,
        })
    }

    /// Records a frame; returns how many frames were dropped (1 if it replaced an unpaired one).
    pub fn offer(&mut self, camera: usize, timestamp_ns: u64) -> u64 {
        let Some(slot) = self.grid.assign(camera, timestamp_ns) else {
            return 1;
        };
        let replaced = self.pending[camera].replace((slot.index, timestamp_ns)).is_some();
        u64::from(replaced)
    }

    /// Forgets a camera's pending frame (e.g. the camera was lost); returns frames dropped.
    pub fn clear(&mut self, camera: usize) -> u64 {
        u64::from(self.pending[camera].take().is_some())
    }

    /// Pending frames that were never paired; used when a set is abandoned.
    pub fn clear_all(&mut self) -> u64 {
        (0..self.pending.len()).map(|c| self.clear(c)).sum()
    }

    /// Whether `camera` has a frame waiting for its partners.
    pub fn is_pending(&self, camera: usize) -> bool {
        self.pending[camera].is_some()
    }

    /// How often a camera's frame went to another slot than its previous one's plus the frames
    /// between (drift across a slot boundary, a restarted camera).
    pub fn slot_moves(&self) -> u64 {
        self.grid.moves()
    }

    /// Tries to complete a set: `Ok(pairing_error_ns)` and the slots emptied, or `Err(dropped)`
    /// with frames that can no longer pair removed (0 when still waiting for a camera).
    pub fn try_pair(&mut self) -> Result<u64, u64> {
        let newest_slot = self.pending.iter().flatten().map(|p| p.0).max();
        let Some(newest_slot) = newest_slot else {
            return Err(0);
        };
        // Frames of an older slot than another camera's pending frame never pair.
        let mut dropped = 0;
        for p in &mut self.pending {
            if p.is_some_and(|(slot, _)| slot < newest_slot) {
                *p = None;
                dropped += 1;
            }
        }
        if self.pending.iter().any(Option::is_none) {
            return Err(dropped);
        }
        let ts = || self.pending.iter().flatten().map(|p| p.1);
        let (oldest, newest) = (ts().min().unwrap_or(0), ts().max().unwrap_or(0));
        if let Some(limit) = self.max_spread_ns
            && newest - oldest > limit
        {
            for p in &mut self.pending {
                if p.is_some_and(|(_, t)| newest - t > limit) {
                    *p = None;
                    dropped += 1;
                }
            }
            return Err(dropped);
        }
        self.pending.iter_mut().for_each(|p| *p = None);
        Ok(newest - oldest)
    }
}

const V4L2_CID_EXPOSURE: u32 = 0x0098_0911;
const V4L2_CID_AUTOGAIN: u32 = 0x0098_0912;
const V4L2_CID_GAIN: u32 = 0x0098_0913;
const V4L2_CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
const V4L2_CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_EXPOSURE_MANUAL` of the `EXPOSURE_AUTO` menu.
const V4L2_EXPOSURE_MANUAL: i64 = 1;
const ENODEV: i32 = 19;

/// What a camera was negotiated to; fixed for the life of the source.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Negotiated {
    /// Pixel format the camera delivers.
    pub format: PixelFormat,
    /// Frame width the driver set, pixels.
    pub width_px: u32,
    /// Frame height the driver set, pixels.
    pub height_px: u32,
    /// Row length of the driver's buffers, bytes (may exceed width times sample size).
    pub bytes_per_line: u32,
    /// Frame interval the driver accepted, as numerator/denominator seconds.
    pub interval: (u32, u32),
    /// Kernel driver name (`VIDIOC_QUERYCAP`).
    pub driver: String,
    /// Device name the driver reports (`VIDIOC_QUERYCAP`).
    pub card: String,
}

struct OpenCamera {
    stream: MmapStream<'static>,
    fd: c_int,
}

enum CameraState {
    Open(Box<OpenCamera>),
    Lost {
        next_attempt: Instant,
        backoff: Duration,
        reason: String,
    },
}

struct Camera {
    device: String,
    negotiated: Negotiated,
    state: CameraState,
    warned_clock: bool,
    /// Exposure and gain the operator set live (set-up view), in the camera's units. A
    /// reopened device starts from its driver defaults plus the config's values, so these are
    /// written again after every reopen: a camera that glitched keeps the image it was tuned to.
    live_exposure: Option<i64>,
    live_gain: Option<i64>,
}

/// The V4L2 [`FrameSource`].
pub struct V4l2Source {
    config: V4l2Config,
    formats: Vec<PixelFormat>,
    cameras: Vec<Camera>,
    pairer: Pairer,
    stats: SourceStats,
    next_index: u64,
    /// Reused poll set and the camera index of each entry (no per-frame allocation).
    pollfds: Vec<libc::pollfd>,
    poll_cameras: Vec<usize>,
}

fn io_err(device: &str, what: &str, e: io::Error) -> SourceError {
    SourceError::Io {
        path: format!("{device} ({what})"),
        source: e,
    }
}

fn set_control_logged(device: &Device, path: &str, id: u32, name: &str, value: i64) -> bool {
    match device.set_control(Control {
        id,
        value: ControlValue::Integer(value),
    }) {
        Ok(()) => {
            info!(device = path, control = name, value, "camera control set");
            true
        }
        Err(e) => {
            warn!(device = path, control = name, value, error = %e, "camera control not applied");
            false
        }
    }
}

/// Applies exposure, gain and named controls; missing controls are logged, not fatal, because
/// cameras differ in what they expose.
fn apply_controls(device: &Device, path: &str, config: &V4l2Config) {
    let descriptions = match device.query_controls() {
        Ok(d) => d,
        Err(e) => {
            warn!(device = path, error = %e, "cannot list camera controls; none applied");
            return;
        }
    };
    let find = |id: u32| descriptions.iter().find(|d| d.id == id);
    if let Some(exposure_us) = config.exposure_us {
        if find(V4L2_CID_EXPOSURE_AUTO).is_some() {
            set_control_logged(
                device,
                path,
                V4L2_CID_EXPOSURE_AUTO,
                "exposure_auto",
                V4L2_EXPOSURE_MANUAL,
            );
        }
        if let Some(d) = find(V4L2_CID_EXPOSURE_ABSOLUTE) {
            // EXPOSURE_ABSOLUTE counts 100 µs units.
            let units = (i64::from(exposure_us) / 100).clamp(d.minimum, d.maximum);
            set_control_logged(device, path, d.id, "exposure_absolute", units);
        } else if let Some(d) = find(V4L2_CID_EXPOSURE) {
            // Sensor-specific units (often lines); the value is passed through clamped.
            let value = i64::from(exposure_us).clamp(d.minimum, d.maximum);
            set_control_logged(device, path, d.id, "exposure", value);
        } else {
            warn!(
                device = path,
                exposure_us, "camera has no exposure control; exposure not set"
            );
        }
    }
    if let Some(gain) = config.gain {
        if find(V4L2_CID_AUTOGAIN).is_some() {
            set_control_logged(device, path, V4L2_CID_AUTOGAIN, "autogain", 0);
        }
        match find(V4L2_CID_GAIN) {
            Some(d) => {
                set_control_logged(device, path, d.id, "gain", gain.clamp(d.minimum, d.maximum));
            }
            None => warn!(device = path, gain, "camera has no gain control; gain not set"),
        }
    }
    for (name, value) in &config.controls {
        match descriptions.iter().find(|d| d.name.eq_ignore_ascii_case(name)) {
            Some(d) => {
                set_control_logged(device, path, d.id, &d.name, *value);
            }
            None => warn!(device = path, control = %name, "camera has no control of that name"),
        }
    }
}

/// Id and range of a camera control.
#[derive(Debug, Clone, Copy)]
struct ControlRange {
    id: u32,
    min: i64,
    max: i64,
}

/// The exposure and gain controls a device has, read through a second handle on the node
/// (V4L2 controls belong to the device, not to the streaming file descriptor).
fn live_control_ids(device: &Device) -> (Option<ControlRange>, Option<ControlRange>) {
    let Ok(descriptions) = device.query_controls() else {
        return (None, None);
    };
    let find = |id: u32| {
        descriptions.iter().find(|d| d.id == id).map(|d| ControlRange {
            id: d.id,
            min: d.minimum,
            max: d.maximum,
        })
    };
    let exposure = find(V4L2_CID_EXPOSURE_ABSOLUTE).or_else(|| find(V4L2_CID_EXPOSURE));
    (exposure, find(V4L2_CID_GAIN))
}

/// Current exposure and gain of the camera at `path` (unsupported or unreadable = `None`).
fn query_live_controls(path: &str) -> super::CameraControls {
    let Ok(device) = Device::with_path(path) else {
        return super::CameraControls::default();
    };
    let (exposure, gain) = live_control_ids(&device);
    let read = |d: Option<ControlRange>| {
        let d = d?;
        let value = match device.control(d.id).ok()?.value {
            ControlValue::Integer(v) => v,
            ControlValue::Boolean(b) => i64::from(b),
            _ => return None,
        };
        Some(super::ControlValue {
            value,
            min: d.min,
            max: d.max,
        })
    };
    super::CameraControls {
        exposure: read(exposure),
        gain: read(gain),
    }
}

/// Writes an exposure or gain value (clamped to the control's range) through a second handle on
/// the camera's node, switching the automatic mode off first where the camera has one.
fn write_live_control(
    path: &str,
    camera: usize,
    control: super::CameraControl,
    value: i64,
) -> Result<(), SourceError> {
    let device = Device::with_path(path).map_err(|e| io_err(path, "open for controls", e))?;
    let (exposure, gain) = live_control_ids(&device);
    let (desc, auto) = match control {
        super::CameraControl::Exposure => (exposure, (V4L2_CID_EXPOSURE_AUTO, V4L2_EXPOSURE_MANUAL)),
        super::CameraControl::Gain => (gain, (V4L2_CID_AUTOGAIN, 0)),
    };
    let d = desc
        .ok_or_else(|| SourceError::Config(format!("camera {camera} ({path}) has no {control:?} control")))?;
    // Manual mode first, where the camera has an automatic one (ignored if absent).
    let _ = device.set_control(Control {
        id: auto.0,
        value: ControlValue::Integer(auto.1),
    });
    device
        .set_control(Control {
            id: d.id,
            value: ControlValue::Integer(value.clamp(d.min, d.max)),
        })
        .map_err(|e| io_err(path, "set control", e))
}

/// Writes the operator's live values again after a reopen. A failure is logged, not fatal: the
/// camera streams, and the set-up view shows the value it really has.
fn reapply_live_controls(camera: usize, cam: &Camera) {
    let live = [
        (super::CameraControl::Exposure, cam.live_exposure),
        (super::CameraControl::Gain, cam.live_gain),
    ];
    for (control, value) in live {
        let Some(value) = value else { continue };
        match write_live_control(&cam.device, camera, control, value) {
            Ok(()) => {
                info!(camera, device = %cam.device, ?control, value, "live camera setting re-applied after reopen")
            }
            Err(e) => {
                warn!(camera, device = %cam.device, ?control, value, error = %e, "live camera setting lost in the reopen")
            }
        }
    }
}

/// Opens a device, negotiates it and starts streaming, waiting for the first frame.
fn open_camera(
    path: &str,
    config: &V4l2Config,
    formats: &[PixelFormat],
) -> Result<(Negotiated, OpenCamera), SourceError> {
    let device = Device::with_path(path).map_err(|e| io_err(path, "open", e))?;
    let caps = device
        .query_caps()
        .map_err(|e| io_err(path, "VIDIOC_QUERYCAP", e))?;
    if !caps
        .capabilities
        .contains(CapFlags::VIDEO_CAPTURE | CapFlags::STREAMING)
    {
        return Err(SourceError::Config(format!(
            "{path} ({} {}) is not a streaming single-plane video capture device",
            caps.driver, caps.card
        )));
    }
    let offered: Vec<FourCC> = device
        .enum_formats()
        .map_err(|e| io_err(path, "VIDIOC_ENUM_FMT", e))?
        .iter()
        .map(|d| d.fourcc)
        .collect();
    let Some(format) = formats.iter().copied().find(|f| offered.contains(&f.fourcc())) else {
        let names: Vec<String> = offered.iter().map(|f| f.to_string()).collect();
        return Err(SourceError::Config(format!(
            "{path} offers none of the configured formats {:?}; it offers [{}]",
            config.formats,
            names.join(", ")
        )));
    };
    let wanted = v4l::Format::new(config.width_px, config.height_px, format.fourcc());
    let got = device
        .set_format(&wanted)
        .map_err(|e| io_err(path, "VIDIOC_S_FMT", e))?;
    if got.fourcc != wanted.fourcc || got.width != wanted.width || got.height != wanted.height {
        return Err(SourceError::Config(format!(
            "{path} cannot deliver {}x{} {}; the driver offered {}x{} {}",
            wanted.width,
            wanted.height,
            format.name(),
            got.width,
            got.height,
            got.fourcc
        )));
    }
    let params = device
        .set_params(&Parameters::with_fps(config.fps))
        .map_err(|e| io_err(path, "VIDIOC_S_PARM", e))?;
    let interval = (params.interval.numerator, params.interval.denominator);
    if interval.0.saturating_mul(config.fps) != interval.1 {
        warn!(device = path, fps = config.fps, interval = ?interval, "driver chose another frame interval");
    }
    apply_controls(&device, path, config);

    let mut stream = MmapStream::with_buffers(&device, BufferType::VideoCapture, config.buffer_count)
        .map_err(|e| io_err(path, "VIDIOC_REQBUFS/mmap", e))?;
    stream.set_timeout(Duration::from_millis(config.frame_timeout_ms.max(1)));
    let fd = stream.handle().fd();
    // The first `next` queues all buffers and starts streaming; its frame is discarded.
    stream
        .next()
        .map_err(|e| io_err(path, "VIDIOC_STREAMON/first frame", e))?;
    let negotiated = Negotiated {
        format,
        width_px: got.width,
        height_px: got.height,
        bytes_per_line: got.stride,
        interval,
        driver: caps.driver,
        card: caps.card,
    };
    info!(device = path, negotiated = ?negotiated, buffers = config.buffer_count, "camera streaming");
    Ok((negotiated, OpenCamera { stream, fd }))
}

/// Polls `fds` for hang-ups only (`events` is set to 0: POLLERR, POLLHUP and POLLNVAL are
/// always reported, while a camera with frames waiting does not wake the poll). Returns how
/// many descriptors have non-zero `revents`; 0 after the timeout or an interrupted poll.
fn poll_hangups(fds: &mut [libc::pollfd], timeout: Duration) -> io::Result<usize> {
    for p in fds.iter_mut() {
        p.events = 0;
        p.revents = 0;
    }
    // Round up so a sub-millisecond wait does not become a busy loop of zero-timeout polls.
    let timeout_ms = c_int::try_from(timeout.as_micros().div_ceil(1000)).unwrap_or(c_int::MAX);
    // SAFETY: fds is a valid, exclusively borrowed array of its length (poll with none sleeps).
    let ready = unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, timeout_ms) };
    if ready < 0 {
        let e = io::Error::last_os_error();
        if e.kind() == io::ErrorKind::Interrupted {
            return Ok(0);
        }
        return Err(e);
    }
    Ok(ready as usize)
}

/// Stops a stream without letting the v4l crate panic in `Drop` on an unexpected error.
fn close_camera(mut cam: Box<OpenCamera>) {
    match cam.stream.stop() {
        Err(e) if e.raw_os_error() != Some(ENODEV) => {
            // Drop would stop again and panic on the same error; leak this one stream instead.
            warn!(error = %e, "VIDIOC_STREAMOFF failed; leaking the stream to stay up");
            std::mem::forget(cam);
        }
        _ => drop(cam),
    }
}

impl V4l2Source {
    /// Opens the cameras as [`open`] does, returning the concrete type (for [`Self::negotiated`]).
    pub fn open(config: &V4l2Config) -> Result<Self, SourceError> {
        let formats = config.validate()?;
        let mut cameras = Vec::with_capacity(config.devices.len());
        for path in &config.devices {
            let (negotiated, open) = open_camera(path, config, &formats)?;
            cameras.push(Camera {
                device: path.clone(),
                negotiated,
                state: CameraState::Open(Box::new(open)),
                warned_clock: false,
                live_exposure: None,
                live_gain: None,
            });
        }
        let n = cameras.len();
        Ok(Self {
            config: config.clone(),
            formats,
            cameras,
            pairer: Pairer::new(n, config.period_ns(), config.pairing_tolerance_ns())?,
            stats: SourceStats::default(),
            next_index: 0,
            pollfds: Vec::with_capacity(n),
            poll_cameras: Vec::with_capacity(n),
        })
    }

    /// Negotiated format of each camera.
    pub fn negotiated(&self) -> Vec<Negotiated> {
        self.cameras.iter().map(|c| c.negotiated.clone()).collect()
    }

    fn mark_lost(&mut self, camera: usize, reason: String) -> SourceError {
        let cam = &mut self.cameras[camera];
        let backoff = Duration::from_millis(self.config.reconnect_min_ms);
        let old = std::mem::replace(
            &mut cam.state,
            CameraState::Lost {
                next_attempt: Instant::now() + backoff,
                backoff,
                reason: reason.clone(),
            },
        );
        if let CameraState::Open(open) = old {
            close_camera(open);
        }
        self.stats.unpaired_dropped += self.pairer.clear_all();
        warn!(camera, device = %cam.device, %reason, "camera lost; will reopen");
        SourceError::CameraLost {
            camera,
            device: cam.device.clone(),
            reason,
        }
    }

    /// Earliest reopen attempt due among the lost cameras, if any is lost.
    fn earliest_attempt(&self) -> Option<Instant> {
        self.cameras
            .iter()
            .filter_map(|c| match &c.state {
                CameraState::Lost { next_attempt, .. } => Some(*next_attempt),
                CameraState::Open(_) => None,
            })
            .min()
    }

    /// Waits up to `timeout` for an open camera to hang up and closes every one that did.
    ///
    /// While a camera is lost, `next_set` does not poll the others for frames, so a camera that
    /// vanished together with it would keep its file descriptor and mmap buffers. Those hold
    /// the dead device's node number until released: a driver coming back then registers the
    /// camera under another number (video2 instead of video1) and the configured path leads
    /// nowhere, for this process and for the next one.
    fn close_hung_up(&mut self, timeout: Duration) -> Result<(), SourceError> {
        self.pollfds.clear();
        self.poll_cameras.clear();
        for (i, cam) in self.cameras.iter().enumerate() {
            if let CameraState::Open(open) = &cam.state {
                self.pollfds.push(libc::pollfd {
                    fd: open.fd,
                    events: 0,
                    revents: 0,
                });
                self.poll_cameras.push(i);
            }
        }
        let hung_up = poll_hangups(&mut self.pollfds, timeout).map_err(|e| SourceError::Io {
            path: "poll on cameras".into(),
            source: e,
        })?;
        if hung_up == 0 {
            return Ok(());
        }
        for k in 0..self.pollfds.len() {
            let revents = self.pollfds[k].revents;
            if revents != 0 {
                // Reported through the status of the lost camera (mark_lost logs it too).
                let _ = self.mark_lost(
                    self.poll_cameras[k],
                    format!("device hung up (poll revents {revents:#x})"),
                );
            }
        }
        Ok(())
    }

    /// Reopens lost cameras whose backoff has elapsed, waiting until the earliest attempt so a
    /// caller that retries at once does not spin. Open cameras that hang up meanwhile are
    /// closed at once. Returns the first camera still lost.
    fn recover(&mut self) -> Result<(), SourceError> {
        if self.earliest_attempt().is_none() {
            return Ok(());
        }
        self.close_hung_up(Duration::ZERO)?;
        while let Some(earliest) = self.earliest_attempt() {
            let wait = earliest.saturating_duration_since(Instant::now());
            if wait.is_zero() {
                break;
            }
            self.close_hung_up(wait)?;
        }
        let max_backoff = Duration::from_millis(self.config.reconnect_max_ms);
        let mut still_lost = None;
        for (i, cam) in self.cameras.iter_mut().enumerate() {
            let CameraState::Lost {
                next_attempt, reason, ..
            } = &mut cam.state
            else {
                continue;
            };
            if *next_attempt > Instant::now() {
                still_lost.get_or_insert((i, reason.clone()));
                continue;
            }
            match open_camera(&cam.device, &self.config, &self.formats) {
                Ok((negotiated, open)) if negotiated == cam.negotiated => {
                    info!(camera = i, device = %cam.device, "camera reopened");
                    cam.state = CameraState::Open(Box::new(open));
                    reapply_live_controls(i, cam);
                    self.stats.reconnects += 1;
                }
                Ok((negotiated, open)) => {
                    close_camera(Box::new(open));
                    *reason = format!("reopened with a different format {negotiated:?}");
                }
                Err(e) => *reason = e.to_string(),
            }
            if let CameraState::Lost {
                next_attempt,
                backoff,
                reason,
            } = &mut cam.state
            {
                *backoff = (*backoff * 2).min(max_backoff);
                *next_attempt = Instant::now() + *backoff;
                still_lost.get_or_insert((i, reason.clone()));
            }
        }
        match still_lost {
            None => Ok(()),
            Some((camera, reason)) => Err(SourceError::CameraLost {
                camera,
                device: self.cameras[camera].device.clone(),
                reason,
            }),
        }
    }

    /// Dequeues the newest frame of one camera into its slot of `out`.
    fn take_frame(&mut self, camera: usize, out: &mut FrameSet) -> Result<(), SourceError> {
        let cam = &mut self.cameras[camera];
        let CameraState::Open(open) = &mut cam.state else {
            return Ok(());
        };
        let (buf, meta) = match open.stream.next() {
            Ok(x) => x,
            Err(e) => return Err(self.mark_lost(camera, format!("dequeue: {e}"))),
        };
        let timestamp_flags = meta.flags & BufferFlags::TIMESTAMP_MASK;
        if timestamp_flags != BufferFlags::TIMESTAMP_MONOTONIC && !cam.warned_clock {
            cam.warned_clock = true;
            warn!(camera, flags = ?meta.flags, "timestamps are not CLOCK_MONOTONIC; pairing may be off");
        }
        let used = match meta.bytesused as usize {
            0 => buf.len(),
            n => n.min(buf.len()),
        };
        let frame = &mut out.frames[camera];
        convert_into(
            cam.negotiated.format,
            &buf[..used],
            cam.negotiated.bytes_per_line as usize,
            frame,
        )?;
        let ts = &meta.timestamp;
        frame.timestamp_ns = (ts.sec as u64).saturating_mul(1_000_000_000) + (ts.usec as u64) * 1000;
        frame.sequence = u64::from(meta.sequence);
        self.stats.unpaired_dropped += self.pairer.offer(camera, frame.timestamp_ns);
        Ok(())
    }
}

impl FrameSource for V4l2Source {
    fn camera_count(&self) -> usize {
        self.cameras.len()
    }

    fn allocate_set(&self) -> FrameSet {
        let frames = self
            .cameras
            .iter()
            .map(|c| {
                let n = c.negotiated.width_px as usize * c.negotiated.height_px as usize;
                Frame {
                    width_px: c.negotiated.width_px,
                    height_px: c.negotiated.height_px,
                    stride_px: c.negotiated.width_px,
                    bit_depth: c.negotiated.format.bit_depth(),
                    pixels: match c.negotiated.format {
                        PixelFormat::Grey | PixelFormat::Yuyv => Pixels::U8(vec![0; n]),
                        PixelFormat::Y10 | PixelFormat::Y16 => Pixels::U16(vec![0; n]),
                    },
                    timestamp_ns: 0,
                    sequence: 0,
                }
            })
            .collect();
        FrameSet {
            index: 0,
            frames,
            pairing_error_ns: 0,
            render_ns: 0,
        }
    }

    fn next_set(&mut self, out: &mut FrameSet) -> Result<(), SourceError> {
        if out.frames.len() != self.cameras.len() {
            return Err(SourceError::Config(format!(
                "frame set has {} frames for {} cameras; use allocate_set",
                out.frames.len(),
                self.cameras.len()
            )));
        }
        self.recover()?;
        let timeout_ms = self.config.frame_timeout_ms;
        let deadline = Instant::now() + Duration::from_millis(timeout_ms);
        loop {
            self.pollfds.clear();
            self.poll_cameras.clear();
            for (i, cam) in self.cameras.iter().enumerate() {
                if let CameraState::Open(open) = &cam.state {
                    self.pollfds.push(libc::pollfd {
                        fd: open.fd,
                        events: libc::POLLIN,
                        revents: 0,
                    });
                    self.poll_cameras.push(i);
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                self.stats.unpaired_dropped += self.pairer.clear_all();
                return Err(SourceError::Timeout { timeout_ms });
            }
            let left_ms = c_int::try_from(left.as_millis().max(1)).unwrap_or(c_int::MAX);
            // SAFETY: pollfds is a valid, exclusively borrowed array of its length.
            let ready = unsafe {
                libc::poll(
                    self.pollfds.as_mut_ptr(),
                    self.pollfds.len() as libc::nfds_t,
                    left_ms,
                )
            };
            if ready < 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(SourceError::Io {
                    path: "poll on cameras".into(),
                    source: e,
                });
            }
            for k in 0..self.pollfds.len() {
                if self.pollfds[k].revents != 0 {
                    // POLLERR/POLLHUP surface as a failed dequeue, which marks the camera lost.
                    self.take_frame(self.poll_cameras[k], out)?;
                }
            }
            match self.pairer.try_pair() {
                Ok(pairing_error_ns) => {
                    out.index = self.next_index;
                    out.pairing_error_ns = pairing_error_ns;
                    self.next_index += 1;
                    self.stats.sets_delivered += 1;
                    return Ok(());
                }
                Err(dropped) => self.stats.unpaired_dropped += dropped,
            }
        }
    }

    fn stats(&self) -> SourceStats {
        self.stats.clone()
    }

    fn controls(&self) -> Vec<super::CameraControls> {
        self.cameras
            .iter()
            .map(|c| query_live_controls(&c.device))
            .collect()
    }

    fn set_control(
        &mut self,
        camera: usize,
        control: super::CameraControl,
        value: i64,
    ) -> Result<(), SourceError> {
        let cam = self
            .cameras
            .get_mut(camera)
            .ok_or_else(|| SourceError::Config(format!("camera {camera} does not exist")))?;
        write_live_control(&cam.device, camera, control, value)?;
        match control {
            super::CameraControl::Exposure => cam.live_exposure = Some(value),
            super::CameraControl::Gain => cam.live_gain = Some(value),
        }
        Ok(())
    }

    fn describe(&self) -> String {
        let cams: Vec<String> = self
            .cameras
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let n = &c.negotiated;
                let state = match &c.state {
                    CameraState::Open(_) => "streaming".to_owned(),
                    CameraState::Lost { reason, .. } => format!("lost: {reason}"),
                };
                format!(
                    "cam{i} {} [{} {}] {} {}x{} @ {}/{} s, {state}",
                    c.device,
                    n.driver,
                    n.card,
                    n.format.name(),
                    n.width_px,
                    n.height_px,
                    n.interval.0,
                    n.interval.1
                )
            })
            .collect();
        format!("v4l2: {}", cams.join("; "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Deserialize)]
    struct Wrap {
        v4l2: V4l2Config,
    }

    fn parse(body: &str) -> Result<V4l2Config, toml::de::Error> {
        toml::from_str::<Wrap>(&format!("[v4l2]\n{body}")).map(|w| w.v4l2)
    }

    const MINIMAL: &str = "devices = [\"/dev/video0\", \"/dev/v4l/by-id/usb-cam1-video-index0\"]\n\
                           width_px = 640\nheight_px = 360\nfps = 30\n";

    #[test]
    fn minimal_config_gets_defaults() {
        let cfg = parse(MINIMAL).unwrap();
        assert_eq!(cfg.devices.len(), 2);
        assert_eq!(
            cfg.validate().unwrap(),
            vec![
                PixelFormat::Grey,
                PixelFormat::Y16,
                PixelFormat::Y10,
                PixelFormat::Yuyv
            ]
        );
        assert_eq!(cfg.buffer_count, 4);
        // No spread limit unless configured; slots of a period at 30 fps.
        assert_eq!(cfg.pairing_tolerance_ns(), None);
        assert_eq!(cfg.period_ns(), 33_333_333);
    }

    #[test]
    fn full_config_parses() {
        let cfg = parse(&format!(
            "{MINIMAL}formats = [\"yuyv\"]\nbuffer_count = 3\nexposure_us = 500\ngain = 8\n\
             max_pairing_error_us = 2000\n[v4l2.controls]\n\"Test Pattern\" = 20\n"
        ))
        .unwrap();
        assert_eq!(cfg.validate().unwrap(), vec![PixelFormat::Yuyv]);
        assert_eq!(cfg.controls.get("Test Pattern"), Some(&20));
        assert_eq!(cfg.pairing_tolerance_ns(), Some(2_000_000));
    }

    #[test]
    fn unknown_key_is_rejected() {
        let err = parse(&format!("{MINIMAL}exposure = 3\n"))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("exposure"), "{err}");
    }

    #[test]
    fn bad_values_are_named() {
        let mut cfg = parse(MINIMAL).unwrap();
        cfg.formats = vec!["MJPG".into()];
        assert!(cfg.validate().unwrap_err().to_string().contains("MJPG"));
        let mut cfg = parse(MINIMAL).unwrap();
        cfg.buffer_count = 1;
        assert!(cfg.validate().unwrap_err().to_string().contains("buffer_count"));
        let mut cfg = parse(MINIMAL).unwrap();
        cfg.devices.clear();
        assert!(cfg.validate().unwrap_err().to_string().contains("devices"));
    }

    #[test]
    fn missing_device_is_a_clear_error() {
        let mut cfg = parse(MINIMAL).unwrap();
        cfg.devices = vec!["/dev/irtrack-no-such-video".into()];
        let err = open(&cfg).err().unwrap().to_string();
        assert!(err.contains("/dev/irtrack-no-such-video"), "{err}");
    }

    fn frame(width: u32, height: u32, pixels: Pixels) -> Frame {
        Frame {
            width_px: width,
            height_px: height,
            stride_px: width,
            bit_depth: 8,
            pixels,
            timestamp_ns: 0,
            sequence: 0,
        }
    }

    #[test]
    fn yuyv_reduces_to_luma_with_row_padding() {
        // 3x2 image, pitch 8 bytes (6 used + 2 padding).
        let src = [10, 1, 11, 2, 12, 3, 99, 99, 20, 4, 21, 5, 22, 6, 99, 99];
        let mut f = frame(3, 2, Pixels::U8(vec![0; 6]));
        convert_into(PixelFormat::Yuyv, &src, 8, &mut f).unwrap();
        assert_eq!(f.pixels, Pixels::U8(vec![10, 11, 12, 20, 21, 22]));
    }

    #[test]
    fn grey_copies_rows() {
        let src = [1, 2, 3, 0, 4, 5, 6, 0];
        let mut f = frame(3, 2, Pixels::U8(vec![0; 6]));
        convert_into(PixelFormat::Grey, &src, 4, &mut f).unwrap();
        assert_eq!(f.pixels, Pixels::U8(vec![1, 2, 3, 4, 5, 6]));
    }

    #[test]
    fn y10_and_y16_are_little_endian() {
        let src = [0xff, 0x03, 0x01, 0x02];
        let mut f = frame(2, 1, Pixels::U16(vec![0; 2]));
        convert_into(PixelFormat::Y10, &src, 4, &mut f).unwrap();
        assert_eq!(f.pixels, Pixels::U16(vec![1023, 0x0201]));
        convert_into(PixelFormat::Y16, &[0, 0x80, 0xff, 0xff], 4, &mut f).unwrap();
        assert_eq!(f.pixels, Pixels::U16(vec![0x8000, 0xffff]));
    }

    #[test]
    fn short_buffer_and_type_mismatch_are_errors() {
        let mut f = frame(3, 2, Pixels::U8(vec![0; 6]));
        let err = convert_into(PixelFormat::Yuyv, &[0; 11], 6, &mut f)
            .unwrap_err()
            .to_string();
        assert!(err.contains("too small"), "{err}");
        assert!(convert_into(PixelFormat::Y16, &[0; 12], 6, &mut f).is_err());
    }

    const P30: u64 = 33_333_333;

    #[test]
    fn pairer_pairs_one_frame_per_camera_and_slot() {
        let mut p = Pairer::new(2, P30, None).unwrap();
        let t = 1_000 * P30;
        assert_eq!(p.offer(0, t), 0);
        assert_eq!(p.try_pair(), Err(0));
        assert_eq!(p.offer(1, t + 3_000), 0);
        assert_eq!(p.try_pair(), Ok(3_000));
        assert!(!p.is_pending(0) && !p.is_pending(1));
        assert!(Pairer::new(0, P30, None).is_err());
    }

    #[test]
    fn pairer_drops_stale_and_replaced_frames() {
        let mut p = Pairer::new(2, P30, None).unwrap();
        let t = 2_000 * P30;
        p.offer(0, t);
        // A newer frame of the same camera replaces the unpaired one.
        assert_eq!(p.offer(0, t + P30), 1);
        // Camera 1's frame is of the slot before camera 0's: it can never pair.
        p.offer(1, t + 1_000);
        assert_eq!(p.try_pair(), Err(1));
        assert!(p.is_pending(0));
        p.offer(1, t + P30 + 2_500);
        assert_eq!(p.try_pair(), Ok(2_500));
        // A spread limit (`max_pairing_error_us`): frames of one slot further apart are not
        // paired; the older one goes.
        let mut p = Pairer::new(3, P30, Some(1_000)).unwrap();
        p.offer(0, t);
        p.offer(1, t + 500);
        p.offer(2, t + 9_000_000);
        assert_eq!(p.try_pair(), Err(2));
        assert!(p.is_pending(2));
        assert_eq!(p.clear_all(), 1);
    }

    /// Three free-running cameras a third of a period apart (no three frames within half a
    /// period of each other) with ±400 µs timestamp jitter: every slot pairs, one frame each.
    #[test]
    fn pairer_pairs_free_running_cameras_at_any_phase() {
        let mut p = Pairer::new(3, P30, None).unwrap();
        let t0 = 3_000 * P30;
        let mut rng = 5u64;
        let (mut sets, mut dropped) = (0, 0);
        for k in 0..1_000u64 {
            for c in 0..3u64 {
                rng = rng
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let jitter = (rng >> 33) % 800_000;
                let ts = t0 + k * P30 + c * P30 / 3 + jitter - 400_000;
                dropped += p.offer(c as usize, ts);
                match p.try_pair() {
                    Ok(spread) => {
                        sets += 1;
                        assert!(spread < P30, "spread {spread}");
                    }
                    Err(d) => dropped += d,
                }
            }
        }
        assert!(sets >= 999, "{sets} sets of 1000, {dropped} frames dropped");
        assert_eq!(p.slot_moves(), 0);
    }

    fn pipe() -> (c_int, c_int) {
        let mut fds = [0 as c_int; 2];
        // SAFETY: fds has room for the two descriptors pipe writes.
        assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
        (fds[0], fds[1])
    }

    fn pollfd(fd: c_int) -> libc::pollfd {
        libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        }
    }

    #[test]
    fn hangup_poll_ignores_waiting_data_and_reports_hangups() {
        let (live_r, live_w) = pipe();
        let (dead_r, dead_w) = pipe();
        // SAFETY: writing one byte from a valid buffer to our own pipe, then closing our fd.
        unsafe {
            assert_eq!(libc::write(live_w, [1u8].as_ptr().cast(), 1), 1);
            libc::close(dead_w);
        }
        // Data waiting (a camera with a frame ready) must not wake the poll: it times out.
        let mut fds = [pollfd(live_r)];
        let t0 = Instant::now();
        assert_eq!(poll_hangups(&mut fds, Duration::from_millis(30)).unwrap(), 0);
        assert!(t0.elapsed() >= Duration::from_millis(25));
        assert_eq!(fds[0].revents, 0);
        // A hung-up descriptor is reported at once, and only that one.
        let mut fds = [pollfd(live_r), pollfd(dead_r)];
        let t0 = Instant::now();
        assert_eq!(poll_hangups(&mut fds, Duration::from_secs(5)).unwrap(), 1);
        assert!(t0.elapsed() < Duration::from_secs(1));
        assert_eq!(fds[0].revents, 0);
        assert_ne!(fds[1].revents & libc::POLLHUP, 0);
        // SAFETY: closing the descriptors this test opened.
        unsafe {
            libc::close(live_r);
            libc::close(live_w);
            libc::close(dead_r);
        }
    }

    fn lost_source(devices: &[&str], reconnect_min_ms: u64) -> V4l2Source {
        let mut cfg = parse(MINIMAL).unwrap();
        cfg.devices = devices.iter().map(|d| (*d).to_owned()).collect();
        cfg.reconnect_min_ms = reconnect_min_ms;
        cfg.reconnect_max_ms = 4 * reconnect_min_ms;
        let formats = cfg.validate().unwrap();
        let backoff = Duration::from_millis(reconnect_min_ms);
        // One instant for all cameras: under emulation the map below can take long enough for
        // the cameras' first attempts to fall into different retry rounds.
        let first_attempt = Instant::now() + backoff;
        let cameras = cfg
            .devices
            .iter()
            .map(|d| Camera {
                device: d.clone(),
                negotiated: Negotiated {
                    format: PixelFormat::Grey,
                    width_px: 640,
                    height_px: 360,
                    bytes_per_line: 640,
                    interval: (1, 30),
                    driver: "vivid".into(),
                    card: "vivid".into(),
                },
                state: CameraState::Lost {
                    next_attempt: first_attempt,
                    backoff,
                    reason: "test".into(),
                },
                warned_clock: false,
                live_exposure: None,
                live_gain: None,
            })
            .collect();
        V4l2Source {
            pairer: Pairer::new(devices.len(), cfg.period_ns(), cfg.pairing_tolerance_ns()).unwrap(),
            config: cfg,
            formats,
            cameras,
            stats: SourceStats::default(),
            next_index: 0,
            pollfds: Vec::new(),
            poll_cameras: Vec::new(),
        }
    }

    fn backoff_of(src: &V4l2Source, camera: usize) -> Duration {
        match &src.cameras[camera].state {
            CameraState::Lost { backoff, .. } => *backoff,
            CameraState::Open(_) => panic!("camera {camera} is open"),
        }
    }

    #[test]
    fn lost_cameras_are_retried_after_the_backoff_which_doubles_up_to_the_limit() {
        let mut src = lost_source(&["/dev/irtrack-gone-0", "/dev/irtrack-gone-1"], 40);
        let mut set = src.allocate_set();
        let t0 = Instant::now();
        // next_set waits for the first attempt instead of returning at once (no busy loop).
        let err = src.next_set(&mut set).unwrap_err().to_string();
        assert!(t0.elapsed() >= Duration::from_millis(35), "{:?}", t0.elapsed());
        assert!(
            err.contains("/dev/irtrack-gone-0") && err.contains("open"),
            "{err}"
        );
        assert_eq!(backoff_of(&src, 0), Duration::from_millis(80));
        assert_eq!(backoff_of(&src, 1), Duration::from_millis(80));
        for _ in 0..3 {
            assert!(src.next_set(&mut set).is_err());
        }
        // Capped at reconnect_max_ms; nothing was reopened.
        assert_eq!(backoff_of(&src, 0), Duration::from_millis(160));
        assert_eq!(src.stats().reconnects, 0);
        assert_eq!(src.stats().sets_delivered, 0);
        assert!(src.describe().contains("lost: I/O on /dev/irtrack-gone-1 (open)"));
    }
}
