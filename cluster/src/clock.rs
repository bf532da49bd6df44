//! The clock probe: the solver measures each camera board's clock against its own by a
//! two-way exchange, so a board whose clock is off (no PTP, a drifting NTP, a wrong setting)
//! is corrected instead of pairing its frames at the wrong instant (docs/cluster.md, "Clock
//! probe").
//!
//! A one-way measurement (capture time against arrival time, [`crate::pairing`]) cannot tell a
//! board whose clock is behind from a slow link. The probe can: the solver stamps a request
//! when it leaves (`t1`, its clock), the board stamps it when it arrives (`t2`) and stamps the
//! reply when it leaves (`t3`, both on the clock its observations carry), the solver stamps the
//! reply when it arrives (`t4`). With equal transit both ways the board's clock is ahead of the
//! solver's by `((t2 − t1) + (t3 − t4)) / 2`; an unequal split errs by at most half the round
//! trip `(t4 − t1) − (t3 − t2)`, so the sample with the shortest round trip is the one to trust.
//!
//! Plain code: the message (40 bytes, below) and the estimator; the transport sends it.
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `IRCK` |
//! | 4 | 1 | version, 1 |
//! | 5 | 1 | kind: 1 request, 2 reply |
//! | 6 | 2 | reserved, 0 |
//! | 8 | 8 | probe id (the solver's count) |
//! | 16 | 8 | `t1_ns`: the solver's clock as the request left |
//! | 24 | 8 | `t2_ns`: the board's clock as the request arrived (0 in a request) |
//! | 32 | 8 | `t3_ns`: the board's clock as the reply left (0 in a request) |
//!
//! Integers little-endian; times are CLOCK_REALTIME in ns (the clock of
//! `ObsClock::Realtime` observations). A reply echoes the request's id and `t1_ns`.

use crate::error::{ClusterError, Result};

/// Length of a probe message (request and reply alike).
pub const PROBE_LEN: usize = 40;
/// The message's first four bytes.
pub const PROBE_MAGIC: [u8; 4] = *b"IRCK";
/// The version this build writes and reads.
pub const PROBE_VERSION: u8 = 1;

/// Request or reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProbeKind {
    /// From the solver: `t2_ns` and `t3_ns` are 0.
    Request,
    /// From a board: all four times set.
    Reply,
}

/// One probe message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProbeMessage {
    /// Request or reply.
    pub kind: ProbeKind,
    /// The solver's probe count (a reply echoes it).
    pub id: u64,
    /// Solver's clock as the request left, ns.
    pub t1_ns: u64,
    /// Board's clock as the request arrived, ns.
    pub t2_ns: u64,
    /// Board's clock as the reply left, ns.
    pub t3_ns: u64,
}

fn probe_error(reason: String) -> ClusterError {
    ClusterError::Probe { reason }
}

impl ProbeMessage {
    /// A request stamped `t1_ns`.
    pub fn request(id: u64, t1_ns: u64) -> ProbeMessage {
        ProbeMessage {
            kind: ProbeKind::Request,
            id,
            t1_ns,
            t2_ns: 0,
            t3_ns: 0,
        }
    }

    /// The reply to this request, with the board's arrival and departure times.
    pub fn reply(&self, t2_ns: u64, t3_ns: u64) -> ProbeMessage {
        ProbeMessage {
            kind: ProbeKind::Reply,
            t2_ns,
            t3_ns,
            ..*self
        }
    }

    /// The 40 bytes of the message.
    pub fn encode(&self) -> [u8; PROBE_LEN] {
        let mut b = [0u8; PROBE_LEN];
        b[0..4].copy_from_slice(&PROBE_MAGIC);
        b[4] = PROBE_VERSION;
        b[5] = match self.kind {
            ProbeKind::Request => 1,
            ProbeKind::Reply => 2,
        };
        b[8..16].copy_from_slice(&self.id.to_le_bytes());
        b[16..24].copy_from_slice(&self.t1_ns.to_le_bytes());
        b[24..32].copy_from_slice(&self.t2_ns.to_le_bytes());
        b[32..40].copy_from_slice(&self.t3_ns.to_le_bytes());
        b
    }

    /// Reads a message; names what is wrong with a bad one.
    pub fn decode(bytes: &[u8]) -> Result<ProbeMessage> {
        if bytes.len() != PROBE_LEN {
            return Err(probe_error(format!(
                "{} bytes; a clock probe message has {PROBE_LEN}",
                bytes.len()
            )));
        }
        if bytes[0..4] != PROBE_MAGIC {
            return Err(probe_error(format!("magic {:02x?}, not \"IRCK\"", &bytes[0..4])));
        }
        if bytes[4] != PROBE_VERSION {
            return Err(probe_error(format!(
                "version {}; this build reads {PROBE_VERSION}",
                bytes[4]
            )));
        }
        let kind = match bytes[5] {
            1 => ProbeKind::Request,
            2 => ProbeKind::Reply,
            k => {
                return Err(probe_error(format!(
                    "kind {k}: neither request (1) nor reply (2)"
                )));
            }
        };
        if bytes[6..8] != [0, 0] {
            return Err(probe_error("reserved bytes 6..8 are not 0".into()));
        }
        let u = |r: core::ops::Range<usize>| {
            let mut a = [0u8; 8];
            a.copy_from_slice(&bytes[r]);
            u64::from_le_bytes(a)
        };
        Ok(ProbeMessage {
            kind,
            id: u(8..16),
            t1_ns: u(16..24),
            t2_ns: u(24..32),
            t3_ns: u(32..40),
        })
    }
}

/// One completed exchange: the reply's three times and the solver's arrival time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProbeSample {
    /// Solver's clock as it began to send the request.
    pub t1_ns: u64,
    /// How long sending took (the transport's call): the request left somewhere in
    /// `t1_ns ..= t1_ns + send_span_ns`, ns.
    pub send_span_ns: u64,
    /// Board's clock as the request arrived.
    pub t2_ns: u64,
    /// Board's clock as the reply left.
    pub t3_ns: u64,
    /// Solver's clock as the reply arrived.
    pub t4_ns: u64,
}

impl ProbeSample {
    /// Board clock minus solver clock, assuming equal transit both ways and the request
    /// leaving as the send call ends (Zenoh queues it last), ns.
    pub fn offset_ns(&self) -> i64 {
        let (t1, t2, t3, t4) = (
            i128::from(self.t1_ns) + i128::from(self.send_span_ns),
            i128::from(self.t2_ns),
            i128::from(self.t3_ns),
            i128::from(self.t4_ns),
        );
        (((t2 - t1) + (t3 - t4)) / 2).clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64
    }

    /// Round trip less the board's own time between arrival and reply, counted from the start
    /// of the send call (so it bounds the true one), ns; `None` when either span is negative
    /// (a clock stepped during the exchange, or a forged reply).
    pub fn rtt_ns(&self) -> Option<u64> {
        let total = self.t4_ns.checked_sub(self.t1_ns)?;
        let held = self.t3_ns.checked_sub(self.t2_ns)?;
        total.checked_sub(held)
    }

    /// Midpoint of the exchange on the solver's clock, ns.
    pub fn mid_ns(&self) -> u64 {
        self.t1_ns / 2 + self.t4_ns / 2
    }

    /// The worst error of [`Self::offset_ns`]: half the round trip (an unequal split of the
    /// transit) plus half the send call (the request may have left at its start), ns.
    pub fn uncertainty_ns(&self) -> Option<u64> {
        Some(self.rtt_ns()? / 2 + self.send_span_ns / 2)
    }
}

/// What the probe knows of one board's clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockEstimate {
    /// Board clock minus solver clock at the instant asked for, ns.
    pub offset_ns: i64,
    /// The best sample's bound ([`ProbeSample::uncertainty_ns`]): the worst error an
    /// unequal split of transit could cause, ns.
    pub uncertainty_ns: u64,
    /// Board clock rate against the solver's, ppm (0 until the samples span a second).
    pub drift_ppm: f64,
    /// Samples used.
    pub samples: usize,
    /// The best sample's round trip, ns.
    pub rtt_ns: u64,
    /// Time since the newest sample, ns.
    pub age_ns: u64,
}

#[derive(Debug, Clone, Copy)]
struct Entry {
    mid_ns: u64,
    offset_ns: i64,
    rtt_ns: u64,
    uncertainty_ns: u64,
}

/// What became of a sample the estimator took.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Taken {
    /// Added to the samples.
    Added,
    /// Its interval of possible offsets lies outside the estimate's by more than
    /// [`ClockEstimator::STEP_SLACK_NS`]: the board's clock stepped (an NTP step, two time
    /// daemons fighting, someone setting the date). The older samples were forgotten; this one
    /// starts a new estimate. `by_ns` is the sample's offset less the estimate's.
    Stepped {
        /// New offset minus the estimated one, ns.
        by_ns: i64,
        /// How far `by_ns` may be from the true step: the sample's bound plus the estimate's,
        /// ns (one sample's round trip: over a millisecond on a loaded machine).
        uncertainty_ns: u64,
    },
}

/// Why a sample was not taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleRefusal {
    /// A span of the exchange is negative.
    Negative,
    /// The round trip is longer than the estimator takes.
    TooSlow,
}

/// The board's clock from its recent probe samples: the samples whose round trip is near the
/// shortest (the others met a queue on the way), fitted with a line once they span a second so
/// a drifting clock is followed between probes.
#[derive(Debug, Clone)]
pub struct ClockEstimator {
    ring: [Option<Entry>; Self::SAMPLES],
    next: usize,
    max_rtt_ns: u64,
    max_age_ns: u64,
}

impl ClockEstimator {
    /// Samples kept (at four probes a second, eight seconds: enough good ones, spread far
    /// enough, for the drift).
    pub const SAMPLES: usize = 32;
    /// Fewest samples before an estimate is given: one lucky exchange is not enough.
    pub const MIN_SAMPLES: usize = 3;
    /// Drift is fitted once at least [`Self::DRIFT_SAMPLES`] good samples span this long:
    /// the line is read about half the window after its samples' middle, so a slope from a
    /// short span (measured: −63 ppm from 1.2 s of a board that does not drift) costs more
    /// than the drift it follows.
    pub const DRIFT_SPAN_NS: u64 = 2_000_000_000;
    /// See [`Self::DRIFT_SPAN_NS`].
    pub const DRIFT_SAMPLES: usize = 5;
    /// Fitted drift is held within ± this (a quartz is within ±100 ppm; more is a stepping
    /// clock, which the line must not follow).
    pub const MAX_DRIFT_PPM: f64 = 500.0;
    /// A sample's offset is sure to lie within its bound of the true one (the request cannot
    /// arrive before it left, nor the reply leave after it arrived), so one outside the
    /// estimate's bound plus its own means the clock changed. This slack covers what the
    /// estimate itself may have missed (drift not yet fitted: 100 ppm over the 2 s before a fit
    /// is 200 µs) before a sample is called a step.
    pub const STEP_SLACK_NS: u64 = 500_000;

    /// An estimator taking samples whose round trip is at most `max_rtt_ns`, giving estimates
    /// while its newest sample is at most `max_age_ns` old.
    pub fn new(max_rtt_ns: u64, max_age_ns: u64) -> ClockEstimator {
        ClockEstimator {
            ring: [None; Self::SAMPLES],
            next: 0,
            max_rtt_ns,
            max_age_ns,
        }
    }

    /// Forgets every sample (the board restarted: its clock may be another).
    pub fn reset(&mut self) {
        self.ring = [None; Self::SAMPLES];
        self.next = 0;
    }

    /// Takes a sample (forgetting the older ones when it shows the clock stepped), or says why
    /// not.
    pub fn push(&mut self, s: &ProbeSample) -> core::result::Result<Taken, SampleRefusal> {
        let rtt_ns = s.rtt_ns().ok_or(SampleRefusal::Negative)?;
        if rtt_ns > self.max_rtt_ns {
            return Err(SampleRefusal::TooSlow);
        }
        let entry = Entry {
            mid_ns: s.mid_ns(),
            offset_ns: s.offset_ns(),
            rtt_ns,
            uncertainty_ns: s.uncertainty_ns().unwrap_or(u64::MAX),
        };
        let mut taken = Taken::Added;
        if let Some(e) = self.estimate(entry.mid_ns) {
            let by_ns = entry.offset_ns.saturating_sub(e.offset_ns);
            let allowed = entry
                .uncertainty_ns
                .saturating_add(e.uncertainty_ns)
                .saturating_add(Self::STEP_SLACK_NS);
            if by_ns.unsigned_abs() > allowed {
                self.reset();
                taken = Taken::Stepped {
                    by_ns,
                    uncertainty_ns: entry.uncertainty_ns.saturating_add(e.uncertainty_ns),
                };
            }
        }
        self.ring[self.next] = Some(entry);
        self.next = (self.next + 1) % Self::SAMPLES;
        Ok(taken)
    }

    /// The board's offset at `now_ns` (solver clock); `None` with fewer than
    /// [`Self::MIN_SAMPLES`] samples or when the newest is older than the age limit.
    pub fn estimate(&self, now_ns: u64) -> Option<ClockEstimate> {
        let entries = || self.ring.iter().flatten();
        let newest = entries().map(|e| e.mid_ns).max()?;
        let age_ns = now_ns.saturating_sub(newest);
        if age_ns > self.max_age_ns || entries().count() < Self::MIN_SAMPLES {
            return None;
        }
        let best = entries().min_by_key(|e| e.uncertainty_ns)?;
        // Near the best bound: a sample whose round trip is longer by `q` met a queue of `q`
        // on one way or the other, which moves its offset by up to `q / 2`; so within a
        // quarter of the best or 50 µs (scheduling), each sample errs by at most that beyond
        // the best one's own bound.
        let limit = best
            .uncertainty_ns
            .saturating_add((best.uncertainty_ns / 4).max(50_000));
        let good = || entries().filter(move |e| e.uncertainty_ns <= limit);
        let n = good().count();
        // Times relative to the newest sample, in seconds; offsets relative to the first
        // good one, in ns (keeps f64 exact enough).
        let base = good().next()?.offset_ns;
        let xs = |e: &Entry| (e.mid_ns as f64 - newest as f64) / 1e9;
        let ys = |e: &Entry| (e.offset_ns - base) as f64;
        let (lo, hi) = good().fold((u64::MAX, 0u64), |(lo, hi), e| {
            (lo.min(e.mid_ns), hi.max(e.mid_ns))
        });
        let mean_x = good().map(xs).sum::<f64>() / n as f64;
        let mean_y = good().map(ys).sum::<f64>() / n as f64;
        let slope_ns_per_s = if n >= Self::DRIFT_SAMPLES && hi - lo >= Self::DRIFT_SPAN_NS {
            let sxx: f64 = good().map(|e| (xs(e) - mean_x).powi(2)).sum();
            let sxy: f64 = good().map(|e| (xs(e) - mean_x) * (ys(e) - mean_y)).sum();
            let max = Self::MAX_DRIFT_PPM * 1e3;
            if sxx > 0.0 {
                (sxy / sxx).clamp(-max, max)
            } else {
                0.0
            }
        } else {
            0.0
        };
        let at_s = (now_ns as f64 - newest as f64) / 1e9;
        let offset = base as f64 + mean_y + slope_ns_per_s * (at_s - mean_x);
        Some(ClockEstimate {
            offset_ns: offset.round() as i64,
            uncertainty_ns: best.uncertainty_ns,
            drift_ppm: slope_ns_per_s / 1e3,
            samples: n,
            rtt_ns: best.rtt_ns,
            age_ns,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_bytes() {
        let req = ProbeMessage::request(0x0102_0304_0506_0708, 1_764_000_000_123_456_789);
        let reply = req.reply(1_764_000_000_129_000_000, 1_764_000_000_129_050_000);
        let want_req: [u8; PROBE_LEN] = [
            b'I', b'R', b'C', b'K', 1, 1, 0, 0, //
            0x08, 0x07, 0x06, 0x05, 0x04, 0x03, 0x02, 0x01, //
            0x15, 0xcd, 0x25, 0x6f, 0xa7, 0xfc, 0x7a, 0x18, //
            0, 0, 0, 0, 0, 0, 0, 0, //
            0, 0, 0, 0, 0, 0, 0, 0,
        ];
        assert_eq!(req.encode(), want_req);
        let b = reply.encode();
        assert_eq!(b[5], 2);
        assert_eq!(&b[16..24], &want_req[16..24], "the reply echoes t1");
        assert_eq!(
            u64::from_le_bytes(b[24..32].try_into().unwrap()),
            1_764_000_000_129_000_000
        );
        assert_eq!(ProbeMessage::decode(&b).unwrap(), reply);
        assert_eq!(ProbeMessage::decode(&want_req).unwrap(), req);
    }

    #[test]
    fn bad_messages_are_named() {
        let good = ProbeMessage::request(1, 2).encode();
        let err = |b: &[u8]| ProbeMessage::decode(b).unwrap_err().to_string();
        assert!(err(&good[..39]).contains("39 bytes"), "{}", err(&good[..39]));
        let mut b = good;
        b[0] = b'X';
        assert!(err(&b).contains("magic"));
        let mut b = good;
        b[4] = 2;
        assert!(err(&b).contains("version 2"));
        let mut b = good;
        b[5] = 7;
        assert!(err(&b).contains("kind 7"));
        let mut b = good;
        b[7] = 1;
        assert!(err(&b).contains("reserved"));
    }

    /// xorshift, for repeatable delays.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// A board 6 ms ahead drifting +40, 0 and −80 ppm, probed four times a second over a link whose two
    /// directions differ (80 µs base each way, random queueing up to 2 ms on a third of the
    /// exchanges): the estimate is within 60 µs of the truth, between probes too.
    #[test]
    fn offset_and_drift_are_found_through_a_queueing_link() {
        for drift_ppm in [40.0, 0.0, -80.0] {
            probed_through_a_queueing_link(drift_ppm);
        }
    }

    fn probed_through_a_queueing_link(drift_ppm: f64) {
        let true_offset = move |t_ns: u64| 6_000_000.0 + drift_ppm * 1e-6 * (t_ns as f64 - 1e9);
        let mut rng = Rng(0x1234_5678_9abc_def1);
        let mut est = ClockEstimator::new(10_000_000, 5_000_000_000);
        let mut t = 1_000_000_000u64;
        assert!(est.estimate(t).is_none(), "no estimate without samples");
        let mut worst = 0.0f64;
        for k in 0..80 {
            let queue = |r: &mut Rng| {
                if r.next() < 0.33 {
                    r.next() * 2e6
                } else {
                    r.next() * 30e3
                }
            };
            let up = 80_000.0 + queue(&mut rng);
            let down = 80_000.0 + queue(&mut rng);
            let t1 = t;
            let arrive = t1 as f64 + up;
            let t2 = (arrive + true_offset(arrive as u64)) as u64;
            let leave = arrive + 20_000.0;
            let t3 = (leave + true_offset(leave as u64)) as u64;
            let t4 = (leave + down) as u64;
            let taken = est
                .push(&ProbeSample {
                    t1_ns: t1,
                    send_span_ns: 0,
                    t2_ns: t2,
                    t3_ns: t3,
                    t4_ns: t4,
                })
                .unwrap();
            // Queueing and drift are not a step.
            assert_eq!(taken, Taken::Added, "{drift_ppm} ppm, probe {k}");
            if k >= 8 {
                // Asked between this probe and the next.
                let at = t4 + 120_000_000;
                let e = est.estimate(at).unwrap();
                let err = (e.offset_ns as f64 - true_offset(at)).abs();
                worst = worst.max(err);
                assert!(e.uncertainty_ns < 100_000, "{e:?}");
                if k >= 20 {
                    assert!((e.drift_ppm - drift_ppm).abs() < 15.0, "{drift_ppm} ppm: {e:?}");
                }
            }
            t += 250_000_000;
        }
        assert!(worst < 60_000.0, "{drift_ppm} ppm: worst error {worst} ns");
    }

    /// A request that left at the end of a long send call: the sample counts the call in its
    /// round trip and its bound (the request might have left at its start), takes the call's
    /// end as the departure, and a sample with a short call wins over one with a long call.
    #[test]
    fn the_send_call_counts_in_the_bound_and_its_end_is_the_departure() {
        // Board 2 ms ahead, 100 µs each way; the call took 300 µs and the request left at its end.
        let t1 = 1_000_000_000u64;
        let left = t1 + 300_000;
        let long = ProbeSample {
            t1_ns: t1,
            send_span_ns: 300_000,
            t2_ns: left + 100_000 + 2_000_000,
            t3_ns: left + 110_000 + 2_000_000,
            t4_ns: left + 210_000,
        };
        assert_eq!(long.rtt_ns(), Some(500_000));
        assert_eq!(long.offset_ns(), 2_000_000);
        assert_eq!(long.uncertainty_ns(), Some(250_000 + 150_000));
        let short = ProbeSample {
            t1_ns: t1 + 250_000_000,
            send_span_ns: 20_000,
            t2_ns: t1 + 250_000_000 + 20_000 + 100_000 + 2_000_000,
            t3_ns: t1 + 250_000_000 + 20_000 + 110_000 + 2_000_000,
            t4_ns: t1 + 250_000_000 + 20_000 + 210_000,
        };
        let mut est = ClockEstimator::new(5_000_000, 2_000_000_000);
        for s in [long, short, short, short] {
            est.push(&s).unwrap();
        }
        let e = est.estimate(t1 + 300_000_000).unwrap();
        assert_eq!(e.samples, 3, "the long call's sample is left out: {e:?}");
        assert_eq!(e.offset_ns, 2_000_000);
        assert_eq!(e.uncertainty_ns, 110_000 + 10_000);
    }

    #[test]
    fn negative_and_slow_exchanges_are_refused_and_old_estimates_expire() {
        let mut est = ClockEstimator::new(5_000_000, 2_000_000_000);
        let s = ProbeSample {
            t1_ns: 100,
            send_span_ns: 0,
            t2_ns: 50,
            t3_ns: 40,
            t4_ns: 200,
        };
        assert_eq!(est.push(&s), Err(SampleRefusal::Negative));
        let s = ProbeSample {
            t1_ns: 0,
            send_span_ns: 0,
            t2_ns: 10,
            t3_ns: 20,
            t4_ns: 6_000_000,
        };
        assert_eq!(est.push(&s), Err(SampleRefusal::TooSlow));
        for k in 0..3u64 {
            let t1 = 1_000_000_000 + k * 250_000_000;
            // A board 2 ms behind over a symmetric 100 µs link.
            let s = ProbeSample {
                t1_ns: t1,
                send_span_ns: 0,
                t2_ns: t1 + 100_000 - 2_000_000,
                t3_ns: t1 + 110_000 - 2_000_000,
                t4_ns: t1 + 210_000,
            };
            assert_eq!(s.rtt_ns(), Some(200_000));
            est.push(&s).unwrap();
            if k < 2 {
                assert!(est.estimate(t1 + 300_000).is_none(), "{} samples", k + 1);
            }
        }
        let e = est.estimate(1_600_000_000).unwrap();
        assert_eq!(e.offset_ns, -2_000_000);
        assert_eq!(e.uncertainty_ns, 100_000);
        assert_eq!(e.samples, 3);
        assert!(est.estimate(1_500_000_000 + 2_100_000_000).is_none(), "expired");
        est.reset();
        assert!(est.estimate(1_600_000_000).is_none());
    }

    /// A board whose clock steps (+8 ms, then back −8 ms, as two time daemons fighting over
    /// it would): the first sample after each step is called a step by how much, the older
    /// samples are forgotten (no estimate until three new ones), and the new offset is found;
    /// a sample that only met a queue (2 ms round trip) is not a step.
    #[test]
    fn a_clock_step_is_recognised_and_the_estimate_starts_again() {
        let mut est = ClockEstimator::new(10_000_000, 5_000_000_000);
        let sample = |t1: u64, offset_ns: i64, up_ns: u64, down_ns: u64| {
            let board = |t: u64| (t as i64 + offset_ns) as u64;
            ProbeSample {
                t1_ns: t1,
                send_span_ns: 0,
                t2_ns: board(t1 + up_ns),
                t3_ns: board(t1 + up_ns + 20_000),
                t4_ns: t1 + up_ns + 20_000 + down_ns,
            }
        };
        let mut t = 1_000_000_000u64;
        let mut next = |offset_ns: i64, up_ns: u64, down_ns: u64| {
            t += 250_000_000;
            (
                t,
                est.push(&sample(t, offset_ns, up_ns, down_ns)).unwrap(),
                est.clone(),
            )
        };
        for _ in 0..10 {
            assert_eq!(next(1_000_000, 80_000, 80_000).1, Taken::Added);
        }
        // Queued 1.9 ms one way: its offset is 0.95 ms off, within its own bound.
        assert_eq!(next(1_000_000, 1_900_000, 80_000).1, Taken::Added);
        let (at, taken, e) = next(9_000_000, 80_000, 80_000);
        let Taken::Stepped {
            by_ns,
            uncertainty_ns,
        } = taken
        else {
            panic!("+8 ms not seen as a step: {taken:?}");
        };
        assert!((by_ns - 8_000_000).abs() < 100_000, "stepped by {by_ns} ns");
        // Two samples' bounds of 80 µs each way: 80 µs each.
        assert!(
            (150_000..=200_000).contains(&uncertainty_ns),
            "{uncertainty_ns} ns"
        );
        assert!(e.estimate(at + 1_000_000).is_none(), "one sample after a step");
        assert_eq!(next(9_000_000, 80_000, 80_000).1, Taken::Added);
        let (at, taken, e) = next(9_000_000, 80_000, 80_000);
        assert_eq!(taken, Taken::Added);
        let got = e.estimate(at + 1_000_000).expect("three samples after the step");
        assert!((got.offset_ns - 9_000_000).abs() < 100_000, "{got:?}");
        assert_eq!(got.samples, 3);
        let (_, taken, _) = next(1_000_000, 80_000, 80_000);
        assert!(
            matches!(taken, Taken::Stepped { by_ns, .. } if (by_ns + 8_000_000).abs() < 100_000),
            "{taken:?}"
        );
    }
}
