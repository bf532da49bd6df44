//! Camera role: publishes each camera's blobs as observations (docs/observation-protocol.md).
//!
//! Capture timestamps are CLOCK_MONOTONIC (V4L2's clock); they are sent on CLOCK_REALTIME,
//! the clock PTP or chrony keeps the boards agreeing on, by adding the current
//! realtime − monotonic difference. The test knobs (clock offset and drift, loss, jitter) act
//! here, in the sender, as the kernel has no netem.

use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::sync::{Arc, Mutex};

use irtrack_cluster::transport::{ClockResponder, ObsPublisher, Session, TransportConfig};
use irtrack_core::blob::Blob;
use irtrack_core::observation::{MAX_OBS_BLOBS, ObsBlob, ObsClock, ObsHeader};

use super::{ClusterConfig, ClusterReport};
use crate::clock;
use crate::engine::ObservationSink;
use crate::error::{FirmwareError, Result};
use crate::source::Frame;

/// One observation waiting in the jitter thread.
struct Pending {
    due_ns: u64,
    camera: usize,
    header_seq: u64,
    capture_rt_ns: u64,
    exposure_us: u32,
    dropped: u32,
    blob_count: usize,
    blobs: [ObsBlob; MAX_OBS_BLOBS],
    /// Measured before the injected delay, so the delay looks like network transit.
    delay_us: u32,
}

/// The camera role's [`ObservationSink`].
pub struct CameraPublisher {
    cfg: ClusterConfig,
    session: Session,
    /// The session is this publisher's own (closed on drop), not the solver's.
    owns_session: bool,
    publishers: Vec<ObsPublisher>,
    report: Arc<Mutex<ClusterReport>>,
    blobs: [ObsBlob; MAX_OBS_BLOBS],
    rng: u64,
    /// The simulated clock error its timestamps and probe answers carry.
    clock_error: ClockError,
    jitter_tx: Option<SyncSender<Pending>>,
    published: u64,
    errors: u64,
    losses: u64,
    /// Answers the solver's clock probe on the clock the observations carry (kept alive).
    _clock: Option<ClockResponder>,
}

fn transport_config(cfg: &ClusterConfig) -> Result<TransportConfig> {
    Ok(TransportConfig {
        listen: cfg.listen.clone(),
        connect: cfg.connect.clone(),
        multicast_scouting: cfg.multicast_scouting,
        low_latency: cfg.low_latency,
        auth: cfg.transport_auth()?,
        tls: cfg.transport_tls()?,
    })
}

/// A camera board's TLS state from its tunnel's log (`/status` → `cluster.tls`).
fn board_tls_report(certificate_file: &std::path::Path) -> super::report::TlsReport {
    let snap = irtrack_cluster::tls::board_log().snapshot();
    super::report::TlsReport {
        side: "board",
        certificate_file: certificate_file.display().to_string(),
        carried: snap.carried,
        solver_refused: snap.solver_refused,
        unreachable: snap.unreachable,
        last_problem_age_s: snap.last_problem.as_ref().map(|(_, age)| *age),
        last_problem: snap.last_problem.map(|(w, _)| w),
    }
}

/// Opens the Zenoh session of `cfg` (blocking), with its credentials; warns when it has none.
pub fn open_session(cfg: &ClusterConfig) -> Result<Session> {
    let tc = transport_config(cfg)?;
    if let Some(line) = cfg.auth_summary() {
        if tc.auth == irtrack_cluster::transport::Auth::None {
            tracing::warn!("{line}");
        } else {
            tracing::info!("{line}");
        }
    }
    Session::open(&tc).map_err(|e| FirmwareError::Config {
        reason: format!("cluster: {e}"),
    })
}

/// The simulated error of a board's clock (test knobs `clock_offset_ms`, `clock_drift_ppm`,
/// `clock_step_ms` every `clock_step_every_s`), counted from `epoch_mono_ns`.
#[derive(Debug, Clone, Copy)]
struct ClockError {
    epoch_mono_ns: u64,
    offset_ms: f64,
    drift_ppm: f64,
    step_ms: f64,
    step_every_s: f64,
}

impl ClockError {
    fn of(cfg: &ClusterConfig, epoch_mono_ns: u64) -> ClockError {
        ClockError {
            epoch_mono_ns,
            offset_ms: cfg.clock_offset_ms,
            drift_ppm: cfg.clock_drift_ppm,
            step_ms: cfg.clock_step_ms,
            step_every_s: cfg.clock_step_every_s,
        }
    }

    /// The board's shared clock at monotonic `mono_ns`, error included.
    fn board_clock_ns(&self, mono_ns: u64) -> u64 {
        let elapsed_s = mono_ns.saturating_sub(self.epoch_mono_ns) as f64 / 1e9;
        // Stepped in every odd period: +step, back, +step, ...
        let stepped = self.step_every_s > 0.0 && (elapsed_s / self.step_every_s) as u64 % 2 == 1;
        let error_ms = self.offset_ms + if stepped { self.step_ms } else { 0.0 };
        let error_ns = error_ms * 1e6 + self.drift_ppm * 1e3 * elapsed_s;
        (i128::from(mono_ns) + clock::realtime_minus_mono_ns() + error_ns as i128).max(0) as u64
    }
}

impl CameraPublisher {
    /// Declares one publisher per local camera (blocking).
    pub fn new(cfg: &ClusterConfig, cameras: usize, report: Arc<Mutex<ClusterReport>>) -> Result<Self> {
        let session = open_session(cfg)?;
        let mut p = Self::on_session(session, cfg, cameras, report)?;
        p.owns_session = true;
        // The probe is stamped on the observations' clock, simulated error included, so the
        // solver measures (and corrects) the same clock it pairs by.
        let error = p.clock_error;
        p._clock = Some(
            ClockResponder::new(&p.session, &cfg.rig, &cfg.board, move || {
                error.board_clock_ns(clock::monotonic_ns())
            })
            .map_err(|e| FirmwareError::Config {
                reason: format!("cluster: {e}"),
            })?,
        );
        Ok(p)
    }

    /// Publishes on an open `session` (the solver's own cameras: their observations reach
    /// its subscriber through the same session), which stays open on drop.
    pub fn on_session(
        session: Session,
        cfg: &ClusterConfig,
        cameras: usize,
        report: Arc<Mutex<ClusterReport>>,
    ) -> Result<Self> {
        let mk = |session: &Session, rig: &str, board: &str, c: usize| {
            ObsPublisher::new(session, rig, board, c).map_err(|e| FirmwareError::Config {
                reason: format!("cluster: {e}"),
            })
        };
        let publishers = (0..cameras)
            .map(|c| mk(&session, &cfg.rig, &cfg.board, c))
            .collect::<Result<Vec<_>>>()?;
        let jitter_tx = if cfg.inject_jitter_ms > 0.0 {
            let (tx, rx) = sync_channel::<Pending>(64);
            let pubs = (0..cameras)
                .map(|c| mk(&session, &cfg.rig, &cfg.board, c))
                .collect::<Result<Vec<_>>>()?;
            let (c2, r2) = (cfg.clone(), report.clone());
            std::thread::Builder::new()
                .name("cluster-jitter".into())
                .spawn(move || jitter_thread(rx, pubs, c2, r2))
                .map_err(|e| FirmwareError::Thread {
                    what: "cluster jitter sender",
                    reason: e.to_string(),
                })?;
            Some(tx)
        } else {
            None
        };
        if let Ok(mut r) = report.lock() {
            r.role = "camera";
            r.rig = cfg.rig.clone();
            r.board = cfg.board.clone();
        }
        tracing::info!(rig = %cfg.rig, board = %cfg.board, cameras, "cluster camera role: publishing observations");
        Ok(CameraPublisher {
            cfg: cfg.clone(),
            session,
            owns_session: false,
            publishers,
            report,
            blobs: [ObsBlob::default(); MAX_OBS_BLOBS],
            rng: 0x9e37_79b9_7f4a_7c15
                ^ cfg
                    .board
                    .bytes()
                    .fold(0u64, |a, b| a.rotate_left(8) ^ u64::from(b)),
            clock_error: ClockError::of(cfg, clock::monotonic_ns()),
            jitter_tx,
            published: 0,
            errors: 0,
            losses: 0,
            _clock: None,
        })
    }

    fn next_uniform(&mut self) -> f64 {
        // xorshift64*: a repeatable test knob, not cryptography.
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        (self.rng.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// The capture time on the shared clock, with the simulated clock error.
    fn capture_rt_ns(&self, mono_ns: u64) -> u64 {
        self.clock_error.board_clock_ns(mono_ns)
    }

    fn update_report(&self) {
        if let Ok(mut r) = self.report.try_lock() {
            r.published = self.published;
            r.publish_errors = self.errors;
            r.injected_losses = self.losses;
            if let Some(c) = &self.cfg.tls_solver_certificate_file {
                r.tls = Some(board_tls_report(c));
            }
        }
    }
}

impl Drop for CameraPublisher {
    fn drop(&mut self) {
        self.jitter_tx = None;
        if self.owns_session {
            self.session.close();
        }
    }
}

fn header<'a>(
    cfg: &'a ClusterConfig,
    camera: usize,
    seq: u64,
    rt: u64,
    exposure_us: u32,
    dropped: u32,
    delay_us: u32,
) -> ObsHeader<'a> {
    ObsHeader {
        rig: &cfg.rig,
        board: &cfg.board,
        camera: camera as u8,
        sequence: seq,
        trigger_count: None,
        capture_ts_ns: rt,
        clock: ObsClock::Realtime,
        exposure_us,
        dropped,
        send_delay_us: delay_us,
    }
}

impl ObservationSink for CameraPublisher {
    fn observe(&mut self, camera: usize, frame: &Frame, blobs: &[Blob], dropped: u64) {
        if self.cfg.inject_loss > 0.0 && self.next_uniform() < self.cfg.inject_loss {
            self.losses += 1;
            self.update_report();
            return;
        }
        // Largest blobs first: the best candidates survive the 32-blob limit.
        let n = blobs.len().min(MAX_OBS_BLOBS);
        for (o, b) in self.blobs.iter_mut().zip(blobs) {
            *o = ObsBlob::from_blob(b);
        }
        self.blobs[..n].sort_unstable_by_key(|b| std::cmp::Reverse(b.area_px));
        let rt = self.capture_rt_ns(frame.timestamp_ns);
        let dropped = u32::try_from(dropped).unwrap_or(u32::MAX);
        if self.jitter_tx.is_some() {
            let jitter_ns = (self.next_uniform() * self.cfg.inject_jitter_ms * 1e6) as u64;
            let p = Pending {
                due_ns: clock::monotonic_ns() + jitter_ns,
                camera,
                header_seq: frame.sequence,
                capture_rt_ns: rt,
                exposure_us: 0,
                dropped,
                blob_count: n,
                blobs: self.blobs,
                delay_us: (clock::monotonic_ns().saturating_sub(frame.timestamp_ns) / 1000) as u32,
            };
            if self.jitter_tx.as_ref().is_some_and(|tx| tx.try_send(p).is_err()) {
                self.errors += 1;
            }
            return;
        }
        let delay_us = clock::monotonic_ns().saturating_sub(frame.timestamp_ns) / 1000;
        let h = header(&self.cfg, camera, frame.sequence, rt, 0, dropped, delay_us as u32);
        match self
            .publishers
            .get_mut(camera)
            .map(|p| p.publish(&h, &self.blobs[..n]))
        {
            Some(Ok(_)) => self.published += 1,
            Some(Err(e)) => {
                if self.errors == 0 {
                    tracing::warn!(camera, error = %e, "observation not sent");
                }
                self.errors += 1;
            }
            None => self.errors += 1,
        }
        if self.published.is_multiple_of(32) {
            self.update_report();
        }
    }
}

/// Sends observations at their due times (jitter injection), in arrival order.
fn jitter_thread(
    rx: Receiver<Pending>,
    mut pubs: Vec<ObsPublisher>,
    cfg: ClusterConfig,
    report: Arc<Mutex<ClusterReport>>,
) {
    let mut sent = 0u64;
    while let Ok(p) = rx.recv() {
        clock::sleep_until_ns(p.due_ns);
        let h = header(
            &cfg,
            p.camera,
            p.header_seq,
            p.capture_rt_ns,
            p.exposure_us,
            p.dropped,
            p.delay_us,
        );
        if let Some(Ok(_)) = pubs
            .get_mut(p.camera)
            .map(|pb| pb.publish(&h, &p.blobs[..p.blob_count]))
        {
            sent += 1;
        }
        if sent.is_multiple_of(32)
            && let Ok(mut r) = report.try_lock()
        {
            r.published = sent;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The simulated stepping clock: in line, +step for a period, back, +step again; drift on
    /// top; a negative or non-finite period is refused by the config check.
    #[test]
    fn a_stepping_clock_steps_and_comes_back() {
        let cfg = ClusterConfig {
            clock_offset_ms: 1.0,
            clock_drift_ppm: 10.0,
            clock_step_ms: 8.0,
            clock_step_every_s: 2.0,
            ..ClusterConfig::default()
        };
        let e = ClockError::of(&cfg, 1_000_000_000);
        let error_ms = |s: f64| {
            let mono = 1_000_000_000 + (s * 1e9) as u64;
            let plain = ClockError {
                offset_ms: 0.0,
                drift_ppm: 0.0,
                step_ms: 0.0,
                ..e
            };
            (e.board_clock_ns(mono) as i64 - plain.board_clock_ns(mono) as i64) as f64 / 1e6
        };
        for (s, want) in [(0.5, 1.0), (2.5, 9.0), (4.5, 1.0), (6.5, 9.0)] {
            let got = error_ms(s) - 10e-6 * s * 1e3;
            // Two reads of the realtime-monotonic gap differ by µs under load.
            assert!((got - want).abs() < 0.1, "at {s} s: {got} ms, want {want}");
        }
        let good = ClusterConfig {
            role: crate::cluster::Role::Camera,
            connect: vec!["tcp/127.0.0.1:7447".into()],
            ..cfg
        };
        good.validate().unwrap();
        for (step, every) in [(f64::NAN, 1.0), (1.0, -1.0), (1.0, f64::INFINITY)] {
            let bad = ClusterConfig {
                role: crate::cluster::Role::Camera,
                connect: vec!["tcp/127.0.0.1:7447".into()],
                clock_step_ms: step,
                clock_step_every_s: every,
                ..ClusterConfig::default()
            };
            let err = bad.validate().unwrap_err().to_string();
            assert!(err.contains("clock_step_ms"), "{err}");
        }
    }
}
