//! `[outputs.mcap]`: irtrackd records its own position records into MCAP files with ROS 2
//! schemas (writer: `irtrack_interop::mcap`, feature `mcap`). A task reads the latest-value slot and
//! hands records to a writer thread through a bounded queue; when the disk stalls the queue
//! fills and further records are dropped and counted, never waited for.
//!
//! Files are `<stem>-NNNN.<ext>` beside the configured path, numbered on from the highest one
//! present, created only if new: a restart or a resumed recording never overwrites one. The
//! writer closes a chunk at least every second and the file is a readable MCAP after each;
//! a write that fails (a full disk) stops that file with its whole chunks readable, shows a
//! fault on `/status` and counts; the writer then tries a new file with a growing pause (1 s,
//! 2 s, ... 30 s) until one can be written. The file is finished (summary and indexes) when
//! irtrackd shuts down.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::error::{FirmwareError, Result};

/// `[outputs.mcap]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct McapConfig {
    /// Off by default.
    #[serde(default)]
    pub enabled: bool,
    /// Names the recordings: `dir/stem.ext` records into `dir/stem-0001.ext`,
    /// `dir/stem-0002.ext`, ... (never an existing file). Relative paths are under
    /// `service.state_dir`.
    #[serde(default = "default_path")]
    pub path: PathBuf,
    /// Records queued for the writer thread before further ones are dropped.
    #[serde(default = "default_queue")]
    pub queue_records: usize,
}

fn default_path() -> PathBuf {
    PathBuf::from("recording.mcap")
}
fn default_queue() -> usize {
    1024
}

impl Default for McapConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            path: default_path(),
            queue_records: default_queue(),
        }
    }
}

impl McapConfig {
    /// Checks an enabled recording can run: the `mcap` feature is built in, the queue holds at
    /// least one record and the path names a file.
    pub fn validate(&self) -> Result<()> {
        if !self.enabled {
            return Ok(());
        }
        if !cfg!(feature = "mcap") {
            return Err(FirmwareError::Config {
                reason: "outputs.mcap: irtrackd was built without the `mcap` feature".into(),
            });
        }
        if self.queue_records == 0 {
            return Err(FirmwareError::Config {
                reason: "outputs.mcap.queue_records: must be at least 1".into(),
            });
        }
        if self.path.file_stem().is_none() {
            return Err(FirmwareError::Config {
                reason: format!(
                    "outputs.mcap.path: {} names no file (e.g. \"recording.mcap\")",
                    self.path.display()
                ),
            });
        }
        Ok(())
    }

    /// The configured path, relative paths under `state_dir`.
    pub fn resolved_path(&self, state_dir: &Path) -> PathBuf {
        if self.path.is_absolute() {
            self.path.clone()
        } else {
            state_dir.join(&self.path)
        }
    }
}

/// The numbered files of one configured path: `dir/stem.ext` → `dir/stem-NNNN.ext` (at least
/// four digits), each created only if it does not exist.
#[derive(Debug, Clone)]
pub struct NumberedFiles {
    dir: PathBuf,
    stem: String,
    ext: Option<String>,
}

impl NumberedFiles {
    /// The files of `base` (the configured path, resolved).
    pub fn new(base: &Path) -> Self {
        let dir = match base.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        Self {
            dir,
            stem: base
                .file_stem()
                .map_or_else(|| "recording".into(), |s| s.to_string_lossy().into_owned()),
            ext: base.extension().map(|e| e.to_string_lossy().into_owned()),
        }
    }

    /// The directory the files are in.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// File number `n`.
    pub fn path(&self, n: u64) -> PathBuf {
        let name = match &self.ext {
            Some(ext) => format!("{}-{n:04}.{ext}", self.stem),
            None => format!("{}-{n:04}", self.stem),
        };
        self.dir.join(name)
    }

    /// The number of `name` if it is one of these files.
    fn number_of(&self, name: &str) -> Option<u64> {
        let rest = name.strip_prefix(&self.stem)?.strip_prefix('-')?;
        let digits = match &self.ext {
            Some(ext) => rest.strip_suffix(ext.as_str())?.strip_suffix('.')?,
            None => rest,
        };
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        digits.parse().ok()
    }

    /// The highest number present (0: none).
    pub fn highest(&self) -> std::io::Result<u64> {
        let mut highest = 0;
        for entry in std::fs::read_dir(&self.dir)? {
            let name = entry?.file_name();
            if let Some(n) = name.to_str().and_then(|n| self.number_of(n)) {
                highest = highest.max(n);
            }
        }
        Ok(highest)
    }

    /// Creates the next file: one above the highest present, created only if new (another
    /// writer taking that name moves this one on).
    pub fn create_next(&self) -> std::io::Result<(PathBuf, std::fs::File)> {
        let mut n = self.highest()? + 1;
        loop {
            let path = self.path(n);
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&path)
            {
                Ok(f) => return Ok((path, f)),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && n < u64::MAX => n += 1,
                Err(e) => return Err(e),
            }
        }
    }
}

#[cfg(feature = "mcap")]
pub use imp::Recorder;
#[cfg(feature = "mcap")]
pub use irtrack_interop::mcap::RecordingFile;

#[cfg(feature = "mcap")]
mod imp {
    use std::future::Future;
    use std::path::PathBuf;
    use std::sync::Arc;
    use std::sync::atomic::Ordering;
    use std::sync::mpsc;
    use std::time::{Duration, Instant};

    use std::collections::BTreeMap;

    use irtrack_core::stream::PositionRecord;
    use irtrack_interop::InteropError;
    use irtrack_interop::mcap::{FrameSet, McapRecorder, RecordingFile, ToolPose};
    use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
    use tokio::sync::watch;

    use super::NumberedFiles;
    use crate::engine::{ParamsHandle, ToolSet};
    use crate::error::{FirmwareError, Result};
    use crate::outputs::OutputStats;
    use crate::outputs::scene::{Axes, Models, SceneBuilder, SceneFrame};
    use crate::status::SharedStatus;

    const R: Ordering = Ordering::Relaxed;
    /// First pause before a new file is tried after a failed write; it doubles up to
    /// [`RETRY_MAX`] while tries fail, and starts again once a file has run this long.
    const RETRY_FIRST: Duration = Duration::from_secs(1);
    const RETRY_MAX: Duration = Duration::from_secs(30);
    /// The writer commits an open chunk when no record came for this long (the loop paused).
    const IDLE_COMMIT: Duration = Duration::from_millis(250);

    type Writer = McapRecorder<Box<dyn RecordingFile>>;

    /// Where recordings go.
    enum Target {
        /// Numbered files beside the configured path.
        Files(NumberedFiles),
        /// One given sink (tests): after it fails nothing more is recorded.
        Sink,
    }

    /// A created recording, not yet running.
    pub struct Recorder {
        target: Target,
        /// The first file, open with its header written.
        first: (PathBuf, Writer),
        queue: usize,
        /// The parameter set's models and the loop's per-tool slot: every tool by name, the
        /// loose LEDs. Without them each record is written alone (its tool named `tool`).
        models: Option<(Arc<ParamsHandle>, Option<watch::Receiver<ToolSet>>)>,
    }

    /// What the writer thread gets per record: the set's main record, its per-tool records
    /// (boxed: most of a queue slot otherwise) and the records skipped so far.
    struct Item {
        rec: PositionRecord,
        tools: Option<Box<ToolSet>>,
        skipped: u64,
    }

    impl Recorder {
        /// Creates the first file now, so a path that cannot be written fails at start.
        pub fn create(base: PathBuf, queue: usize) -> Result<Self> {
            let files = NumberedFiles::new(&base);
            let first = open_next(&files).map_err(|e| FirmwareError::Config {
                reason: format!("outputs.mcap.path: {e}"),
            })?;
            Ok(Self {
                target: Target::Files(files),
                first,
                queue: queue.max(1),
                models: None,
            })
        }

        /// A recording into `sink` alone (`label` names it in logs and on `/status`).
        pub fn with_sink(label: PathBuf, sink: Box<dyn RecordingFile>, queue: usize) -> Result<Self> {
            let writer =
                McapRecorder::new(sink, local_wall_offset_ns()).map_err(|e| FirmwareError::Output {
                    what: "MCAP recording",
                    reason: e.to_string(),
                })?;
            Ok(Self {
                target: Target::Sink,
                first: (label, writer),
                queue: queue.max(1),
                models: None,
            })
        }

        /// Records every tool of the parameter set (by name, on the live ROS 2 output's
        /// topics) from the loop's per-tool slot, the loose LEDs, and the registration.
        pub fn with_models(
            mut self,
            params: Arc<ParamsHandle>,
            tools: Option<watch::Receiver<ToolSet>>,
        ) -> Self {
            self.models = Some((params, tools));
            self
        }

        /// Records every record the slot shows until `shutdown`, then finishes the file.
        pub async fn run(
            self,
            mut slot: watch::Receiver<Option<PositionRecord>>,
            status: Arc<SharedStatus>,
            stats: Arc<OutputStats>,
            shutdown: impl Future<Output = ()>,
        ) {
            let (tx, rx) = mpsc::sync_channel::<Item>(self.queue);
            let (params, tools) = match self.models {
                Some((p, t)) => (Some(p), t),
                None => (None, None),
            };
            let mut session = Session::new(self.target, self.first, stats.clone(), params);
            let thread = std::thread::Builder::new()
                .name("irtrackd-mcap".into())
                .spawn(move || {
                    loop {
                        match rx.recv_timeout(IDLE_COMMIT) {
                            Ok(item) => session.record(&item),
                            Err(mpsc::RecvTimeoutError::Timeout) => session.idle(),
                            Err(mpsc::RecvTimeoutError::Disconnected) => break,
                        }
                    }
                    session.finish();
                });
            let thread = match thread {
                Ok(t) => t,
                Err(e) => {
                    tracing::error!(error = %e, "MCAP writer thread not started");
                    return;
                }
            };
            tokio::pin!(shutdown);
            let mut received = 0u64;
            loop {
                tokio::select! {
                    _ = &mut shutdown => break,
                    changed = slot.changed() => {
                        if changed.is_err() {
                            break;
                        }
                        let rec = *slot.borrow_and_update();
                        let Some(rec) = rec else { continue };
                        received += 1;
                        let published = status.published.load(R);
                        let skipped = published.saturating_sub(received);
                        stats.slot_skips.store(skipped, R);
                        let tool_set = tools
                            .as_ref()
                            .map(|t| *t.borrow())
                            .filter(|t| t.frame == rec.frame)
                            .map(Box::new);
                        let item = Item { rec, tools: tool_set, skipped };
                        if tx.try_send(item).is_err() && stats.send_drops.fetch_add(1, R) == 0 {
                            tracing::warn!("MCAP writer behind; records dropped (counted)");
                        }
                    }
                }
            }
            // Records published after the last one this task saw were skipped too.
            let published = status.published.load(R);
            stats.slot_skips.store(published.saturating_sub(received), R);
            drop(tx);
            if tokio::task::spawn_blocking(move || thread.join()).await.is_err() {
                tracing::error!("MCAP writer thread failed");
            }
        }
    }

    /// Creates the next numbered file and writes its header; a file that could not take even
    /// that is removed again.
    fn open_next(files: &NumberedFiles) -> std::result::Result<(PathBuf, Writer), String> {
        let (path, file) = files
            .create_next()
            .map_err(|e| format!("cannot create a recording in {}: {e}", files.dir().display()))?;
        match McapRecorder::new(Box::new(file) as Box<dyn RecordingFile>, local_wall_offset_ns()) {
            Ok(w) => Ok((path, w)),
            Err(e) => {
                let _ = std::fs::remove_file(&path);
                Err(format!("cannot start {}: {}", path.display(), short_reason(&e)))
            }
        }
    }

    /// The OS's words for a failed write, without what the recorder adds.
    fn short_reason(e: &InteropError) -> String {
        match e {
            InteropError::RecordingStopped { reason, .. } => reason.clone(),
            other => other.to_string(),
        }
    }

    /// The file being written.
    struct Current {
        path: PathBuf,
        writer: Writer,
        opened: Instant,
        /// Records of this file already counted as sent (on file).
        counted: u64,
        /// The recorder's counters when the file started (for its metadata).
        skipped_at_start: u64,
        dropped_at_start: u64,
        /// The parameter generation whose registration this file has.
        generation: u64,
    }

    /// The parameter set's models, turned into frame sets.
    struct ModelState {
        params: Arc<ParamsHandle>,
        generation: u64,
        builder: SceneBuilder,
        scene: SceneFrame,
        /// Robot base from tracker (x y z w, metres), from the set's registration.
        registration: Option<([f64; 4], [f64; 3])>,
        loose: Vec<(u32, [f64; 3])>,
    }

    impl ModelState {
        fn refresh(&mut self) {
            let generation = self.params.generation();
            if generation == self.generation {
                return;
            }
            self.generation = generation;
            let current = self.params.current();
            let rig = current.as_ref().map(|p| &p.rig);
            self.builder.models = Models::of_rig(rig);
            self.registration = rig.and_then(|r| r.world_from_cam0.as_ref()).map(|w| {
                let r = Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(&w.r_row_major));
                let q = UnitQuaternion::from_rotation_matrix(&r);
                (
                    [q.i, q.j, q.k, q.w],
                    [w.t_mm[0] / 1e3, w.t_mm[1] / 1e3, w.t_mm[2] / 1e3],
                )
            });
        }

        /// Writes one set: every tracked tool by name, the single LED, the loose LEDs.
        fn write(&mut self, writer: &mut Writer, item: &Item) -> std::result::Result<(), InteropError> {
            self.builder
                .fill_with(&item.rec, item.tools.as_deref(), &mut self.scene);
            let models = &self.builder.models.list;
            let scene = &self.scene;
            let tools: Vec<ToolPose<'_>> = scene
                .bodies
                .iter()
                .filter(|b| b.tracked)
                .filter_map(|b| {
                    let m = models.iter().find(|m| m.id == b.id)?;
                    Some(ToolPose {
                        name: &m.name,
                        position_m: b.position_m,
                        orientation_xyzw: b.orientation_xyzw,
                    })
                })
                .collect();
            let led_m = models
                .iter()
                .zip(&scene.marker_sets)
                .find(|(m, _)| !m.rigid_body)
                .filter(|_| !scene.unlabelled_m.is_empty())
                .and_then(|(_, set)| set.first().copied());
            self.loose.clear();
            self.loose
                .extend(scene.loose.iter().map(|l| (l.loose_id, l.position_m)));
            // Loose LEDs are reported beside tools only, for sets with per-tool records.
            let has_tools = models.iter().any(|m| m.rigid_body);
            let loose = (has_tools && scene.per_tool).then_some(self.loose.as_slice());
            writer.write_set(&FrameSet {
                record: &item.rec,
                tools: &tools,
                led_m,
                loose,
                skipped: item.skipped,
            })
        }
    }

    /// The writer thread's state: the file being written, or when to try the next one.
    /// `sent` counts records once they are on file (their chunk written); records of a chunk
    /// a failed write lost, and records that come while no file can be written, are dropped.
    struct Session {
        target: Target,
        current: Option<Current>,
        /// While no file is written: when to try a new one, and the pause after that.
        retry_at: Option<Instant>,
        retry_delay: Duration,
        /// How the last file stopped (for the fault text while new ones fail too).
        stopped: Option<String>,
        stats: Arc<OutputStats>,
        models: Option<ModelState>,
    }

    impl Session {
        fn new(
            target: Target,
            first: (PathBuf, Writer),
            stats: Arc<OutputStats>,
            params: Option<Arc<ParamsHandle>>,
        ) -> Self {
            let mut s = Self {
                target,
                current: None,
                retry_at: None,
                retry_delay: RETRY_FIRST,
                stopped: None,
                stats,
                models: params.map(|params| ModelState {
                    params,
                    generation: u64::MAX,
                    builder: SceneBuilder::new(Models::default(), Axes::Tracker),
                    scene: SceneFrame::default(),
                    registration: None,
                    loose: Vec::new(),
                }),
            };
            s.started(first.0, first.1);
            s
        }

        fn started(&mut self, path: PathBuf, writer: Writer) {
            tracing::info!(path = %path.display(), "MCAP recording started");
            self.stats.files.fetch_add(1, R);
            set(&self.stats.file, Some(path.display().to_string()));
            set(&self.stats.fault, None);
            self.current = Some(Current {
                path,
                writer,
                opened: Instant::now(),
                counted: 0,
                skipped_at_start: self.stats.slot_skips.load(R),
                dropped_at_start: self.stats.send_drops.load(R),
                generation: u64::MAX,
            });
            self.retry_at = None;
            self.stopped = None;
        }

        /// After a write or commit of the current file: counts what reached the file, and on
        /// failure what was lost, then stops the file.
        fn settle(&mut self, res: std::result::Result<(), InteropError>) {
            let Some(cur) = self.current.as_mut() else {
                return;
            };
            let committed = cur.writer.records_committed();
            self.stats
                .frames_sent
                .fetch_add(committed.saturating_sub(cur.counted), R);
            cur.counted = committed;
            if let Err(e) = res {
                let lost = cur.writer.records_written().saturating_sub(committed);
                self.stats.send_drops.fetch_add(lost, R);
                self.failed(&e);
            }
        }

        fn record(&mut self, item: &Item) {
            self.resume_if_due();
            let Some(cur) = self.current.as_mut() else {
                // Not recorded: no file can be written now.
                self.stats.send_drops.fetch_add(1, R);
                return;
            };
            let res = match self.models.as_mut() {
                Some(m) => {
                    m.refresh();
                    // Each file gets the registration of the set in use (on /tf_static).
                    let registered = if cur.generation != m.generation {
                        cur.generation = m.generation;
                        cur.writer
                            .set_registration(m.registration, item.rec.capture_ts_ns)
                    } else {
                        Ok(())
                    };
                    registered.and_then(|()| m.write(&mut cur.writer, item))
                }
                None => cur.writer.write(&item.rec),
            };
            if res.is_ok() {
                // Capture → written into the open chunk.
                self.stats.record_latency(item.rec.capture_ts_ns);
            }
            self.settle(res);
        }

        /// No record for a while: put the open chunk on file; try a new file when due.
        fn idle(&mut self) {
            if let Some(cur) = self.current.as_mut()
                && cur.writer.has_open_chunk()
            {
                let res = cur.writer.commit();
                self.settle(res);
            }
            self.resume_if_due();
        }

        /// The current file's write failed: it stops (its whole chunks stay readable), a
        /// fault says so, and a new file is tried after a pause.
        fn failed(&mut self, e: &InteropError) {
            let Some(cur) = self.current.take() else {
                return;
            };
            self.stats.write_errors.fetch_add(1, R);
            set(&self.stats.file, None);
            if cur.opened.elapsed() > RETRY_MAX {
                self.retry_delay = RETRY_FIRST;
            }
            tracing::error!(path = %cur.path.display(), error = %e, "MCAP recording stopped");
            self.stopped = Some(format!("MCAP recording into {} stopped: {e}", cur.path.display()));
            self.schedule_retry(None);
        }

        /// Sets the next try and the fault text (with why the last try failed, if one did).
        fn schedule_retry(&mut self, try_error: Option<&str>) {
            let stopped = self.stopped.clone().unwrap_or_default();
            let text = match (&self.target, try_error) {
                (Target::Sink, _) => format!("{stopped}; nothing more is recorded"),
                (Target::Files(files), None) => format!(
                    "{stopped} — free space in {}; irtrackd records into a new file once it can (next try in {} s)",
                    files.dir().display(),
                    self.retry_delay.as_secs()
                ),
                (Target::Files(files), Some(why)) => format!(
                    "{stopped} — free space in {}; a new file cannot be written either ({why}); next try in {} s",
                    files.dir().display(),
                    self.retry_delay.as_secs()
                ),
            };
            set(&self.stats.fault, Some(text));
            self.retry_at = match self.target {
                Target::Files(_) => Some(Instant::now() + self.retry_delay),
                Target::Sink => None,
            };
            self.retry_delay = (self.retry_delay * 2).min(RETRY_MAX);
        }

        fn resume_if_due(&mut self) {
            if self.current.is_some() || self.retry_at.is_none_or(|t| Instant::now() < t) {
                return;
            }
            let Target::Files(files) = &self.target else {
                return;
            };
            match open_next(files) {
                Ok((path, writer)) => {
                    tracing::info!(path = %path.display(), "MCAP recording resumed into a new file");
                    self.started(path, writer);
                }
                Err(why) => {
                    self.stats.write_errors.fetch_add(1, R);
                    tracing::warn!(error = %why, "MCAP recording: no new file yet");
                    self.schedule_retry(Some(&why));
                }
            }
        }

        /// Shutdown: writes the last chunk and the recorder's counts for this file (a
        /// metadata record `irtrack_recorder`), then the summary and indexes.
        fn finish(mut self) {
            if let Some(cur) = self.current.as_mut() {
                let res = cur.writer.commit();
                self.settle(res);
            }
            if let Some(cur) = self.current.as_mut() {
                let counts = BTreeMap::from([
                    (
                        "records_written".to_string(),
                        cur.writer.records_committed().to_string(),
                    ),
                    (
                        "records_skipped".to_string(),
                        (self.stats.slot_skips.load(R).saturating_sub(cur.skipped_at_start)).to_string(),
                    ),
                    (
                        "records_dropped".to_string(),
                        (self.stats.send_drops.load(R).saturating_sub(cur.dropped_at_start)).to_string(),
                    ),
                    ("irtrackd".to_string(), env!("CARGO_PKG_VERSION").to_string()),
                ]);
                let res = cur.writer.write_metadata("irtrack_recorder", counts);
                self.settle(res);
            }
            let Some(cur) = self.current.take() else {
                return;
            };
            match cur.writer.finish() {
                Ok(c) => tracing::info!(
                    path = %cur.path.display(),
                    positions = c.position,
                    poses = c.pose,
                    status = c.status,
                    "MCAP recording finished"
                ),
                Err(e) => {
                    // The chunks are on file; only the summary (indexes) is missing.
                    self.stats.write_errors.fetch_add(1, R);
                    set(
                        &self.stats.fault,
                        Some(format!(
                            "MCAP recording into {} has no summary (readers read it front to back): {e}",
                            cur.path.display()
                        )),
                    );
                    tracing::error!(path = %cur.path.display(), error = %e, "MCAP recording not finished");
                }
            }
            set(&self.stats.file, None);
        }
    }

    fn set(slot: &std::sync::Mutex<Option<String>>, value: Option<String>) {
        if let Ok(mut g) = slot.lock() {
            *g = value;
        }
    }

    /// Wall clock minus the monotonic clock, now: the offset that turns capture times (this
    /// machine's monotonic clock) into the wall-clock stamps ROS tools expect.
    fn local_wall_offset_ns() -> i128 {
        let wall = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as i128);
        wall - i128::from(crate::clock::monotonic_ns())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("irtrack-numbered-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn numbered_files_go_on_from_the_highest_and_never_reuse_a_name() {
        let dir = temp_dir("next");
        let files = NumberedFiles::new(&dir.join("rec.mcap"));
        let (p1, _) = files.create_next().unwrap();
        assert_eq!(p1, dir.join("rec-0001.mcap"));
        // Other names beside them do not count; a gap keeps the highest.
        for other in [
            "rec.mcap",
            "rec-12.txt",
            "rec-x.mcap",
            "other-0050.mcap",
            "rec-0007.mcap",
        ] {
            std::fs::write(dir.join(other), b"x").unwrap();
        }
        let (p8, _) = files.create_next().unwrap();
        assert_eq!(p8, dir.join("rec-0008.mcap"));
        std::fs::write(dir.join("rec-12345.mcap"), b"x").unwrap();
        assert_eq!(files.create_next().unwrap().0, dir.join("rec-12346.mcap"));
        // The earlier files are untouched.
        assert_eq!(std::fs::read(dir.join("rec-0007.mcap")).unwrap(), b"x");
        let bare = NumberedFiles::new(&dir.join("log"));
        assert_eq!(bare.create_next().unwrap().0, dir.join("log-0001"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(feature = "mcap")]
    #[test]
    fn a_path_without_a_file_name_is_refused() {
        let cfg = McapConfig {
            enabled: true,
            path: PathBuf::from("/"),
            ..McapConfig::default()
        };
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains("outputs.mcap.path: / names no file"), "{e}");
    }
}
