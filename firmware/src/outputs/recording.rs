//! `[outputs.mcap]`: irtrackd records its own position records into an MCAP file with ROS 2
//! schemas (writer: `irtrack_interop::mcap`, feature `mcap`). A task reads the latest-value slot and
//! hands records to a writer thread through a bounded queue; when the disk stalls the queue
//! fills and further records are dropped and counted, never waited for. The file is finished
//! (summary and indexes written) when irtrackd shuts down.

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
    /// The recording; relative paths are under `service.state_dir`. An existing file is
    /// replaced.
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
    /// Checks an enabled recording can run: the `mcap` feature is built in and the queue holds at
    /// least one record.
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
        Ok(())
    }

    /// The file to write, relative paths under `state_dir`.
    pub fn resolved_path(&self, state_dir: &Path) -> PathBuf {
        if self.path.is_absolute() {
            self.path.clone()
        } else {
            state_dir.join(&self.path)
        }
    }
}

#[cfg(feature = "mcap")]
pub use imp::{Recorder, SeekWrite};

#[cfg(feature = "mcap")]
mod imp {
    use std::future::Future;
    use std::io::BufWriter;
    use std::path::PathBuf;
    use std::sync::Arc;
    use std::sync::atomic::Ordering;
    use std::sync::mpsc;

    use irtrack_core::stream::PositionRecord;
    use tokio::sync::watch;

    use crate::error::{FirmwareError, Result};
    use crate::outputs::OutputStats;
    use crate::status::SharedStatus;
    use irtrack_interop::mcap::McapRecorder;

    const R: Ordering = Ordering::Relaxed;

    /// Where a recording goes: a file, or (tests) any seekable sink.
    pub trait SeekWrite: std::io::Write + std::io::Seek + Send {}
    impl<T: std::io::Write + std::io::Seek + Send> SeekWrite for T {}

    /// A created recording, not yet running.
    pub struct Recorder {
        path: PathBuf,
        writer: McapRecorder<Box<dyn SeekWrite>>,
        queue: usize,
    }

    impl Recorder {
        /// Creates the file now, so a path that cannot be written fails at start.
        pub fn create(path: PathBuf, queue: usize) -> Result<Self> {
            let file = std::fs::File::create(&path).map_err(|e| FirmwareError::Config {
                reason: format!("outputs.mcap.path: cannot create {}: {e}", path.display()),
            })?;
            Self::with_sink(path, Box::new(BufWriter::new(file)), queue)
        }

        /// A recording into `sink` (`label` names it in logs).
        pub fn with_sink(label: PathBuf, sink: Box<dyn SeekWrite>, queue: usize) -> Result<Self> {
            let writer =
                McapRecorder::new(sink, local_wall_offset_ns()).map_err(|e| FirmwareError::Output {
                    what: "MCAP recording",
                    reason: e.to_string(),
                })?;
            Ok(Self {
                path: label,
                writer,
                queue: queue.max(1),
            })
        }

        /// Records every record the slot shows until `shutdown`, then finishes the file.
        pub async fn run(
            self,
            mut slot: watch::Receiver<Option<PositionRecord>>,
            status: Arc<SharedStatus>,
            stats: Arc<OutputStats>,
            shutdown: impl Future<Output = ()>,
        ) {
            let (tx, rx) = mpsc::sync_channel::<PositionRecord>(self.queue);
            let (path, mut writer) = (self.path, self.writer);
            let stats2 = stats.clone();
            let thread = std::thread::Builder::new()
                .name("irtrackd-mcap".into())
                .spawn(move || {
                    let mut failed = false;
                    for rec in rx {
                        if failed {
                            continue;
                        }
                        match writer.write(&rec) {
                            Ok(()) => {
                                stats2.frames_sent.fetch_add(1, R);
                                // Capture → written into the file's buffer.
                                stats2.record_latency(rec.capture_ts_ns);
                            }
                            Err(e) => {
                                tracing::error!(error = %e, "MCAP recording stopped");
                                failed = true;
                            }
                        }
                    }
                    writer.finish()
                });
            let thread = match thread {
                Ok(t) => t,
                Err(e) => {
                    tracing::error!(error = %e, "MCAP writer thread not started");
                    return;
                }
            };
            tracing::info!(path = %path.display(), "MCAP recording started");
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
                        stats.slot_skips.store(published.saturating_sub(received), R);
                        if tx.try_send(rec).is_err() && stats.send_drops.fetch_add(1, R) == 0 {
                            tracing::warn!("MCAP writer behind; records dropped (counted)");
                        }
                    }
                }
            }
            drop(tx);
            match tokio::task::spawn_blocking(move || thread.join()).await {
                Ok(Ok(Ok(c))) => tracing::info!(
                    path = %path.display(),
                    positions = c.position,
                    poses = c.pose,
                    status = c.status,
                    "MCAP recording finished"
                ),
                Ok(Ok(Err(e))) => {
                    tracing::error!(path = %path.display(), error = %e, "MCAP recording not finished")
                }
                _ => tracing::error!(path = %path.display(), "MCAP writer thread failed"),
            }
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
