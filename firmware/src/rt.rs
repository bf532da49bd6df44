//! Optional real-time settings for the processing thread: SCHED_FIFO, CPU affinity, mlockall.
//! Each is tried only when configured; refusals (no CAP_SYS_NICE / RLIMIT_RTPRIO, no
//! CAP_IPC_LOCK / RLIMIT_MEMLOCK) are logged clearly and the loop runs on without them.

use crate::config::RealtimeConfig;

/// Applies `cfg` to the calling thread; returns one line per setting for the status page.
pub fn apply(cfg: &RealtimeConfig) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some(prio) = cfg.fifo_priority {
        let param = libc::sched_param { sched_priority: prio };
        // SAFETY: pthread_self() is the calling thread; `param` is a valid sched_param.
        let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
        if rc == 0 {
            tracing::info!(priority = prio, "processing thread runs SCHED_FIFO");
            lines.push(format!("SCHED_FIFO priority {prio}: applied"));
        } else {
            let err = std::io::Error::from_raw_os_error(rc);
            tracing::warn!(
                priority = prio,
                error = %err,
                "real-time priority not permitted (needs CAP_SYS_NICE or LimitRTPRIO=); running with normal scheduling"
            );
            lines.push(format!("SCHED_FIFO priority {prio}: not permitted ({err})"));
        }
    }
    if let Some(cpus) = &cfg.cpu_affinity {
        // SAFETY: cpu_set_t is plain data; zeroed is the empty set, CPU_SET stays in bounds
        // because we skip indices beyond CPU_SETSIZE.
        let rc = unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            for &c in cpus.iter().filter(|&&c| c < libc::CPU_SETSIZE as usize) {
                libc::CPU_SET(c, &mut set);
            }
            libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set)
        };
        if rc == 0 {
            tracing::info!(?cpus, "processing thread pinned");
            lines.push(format!("CPU affinity {cpus:?}: applied"));
        } else {
            let err = std::io::Error::last_os_error();
            tracing::warn!(?cpus, error = %err, "CPU affinity not applied; the thread may run on any CPU");
            lines.push(format!("CPU affinity {cpus:?}: failed ({err})"));
        }
    }
    if cfg.lock_memory {
        // SAFETY: plain syscall with constant flags.
        let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
        if rc == 0 {
            tracing::info!("memory locked (mlockall)");
            lines.push("mlockall: applied".into());
        } else {
            let err = std::io::Error::last_os_error();
            tracing::warn!(
                error = %err,
                "memory locking not permitted (needs CAP_IPC_LOCK or LimitMEMLOCK=); page faults may delay the loop"
            );
            lines.push(format!("mlockall: not permitted ({err})"));
        }
    }
    lines
}

/// Zenoh's transport threads carrying observations, by thread name: Zenoh (1.10) runs its
/// links on tokio runtimes of its own whose threads are named `<runtime>-<n>`. A camera board's
/// publishes leave through the `tx` runtime (the default transport's transmit task; the
/// low-latency transport writes on the publishing thread, the processing loop, itself); the
/// solver's arrive on the `rx` runtime (each link's read task runs the subscriber's callback).
pub fn transport_thread_prefix(role: crate::cluster::Role) -> Option<&'static str> {
    match role {
        crate::cluster::Role::Camera => Some("tx-"),
        crate::cluster::Role::Solver => Some("rx-"),
        crate::cluster::Role::Standalone => None,
    }
}

/// What one pass over the process's threads did.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct RaiseOutcome {
    /// Threads found by name (already at the priority or raised now).
    pub matched: usize,
    /// Threads raised in this pass.
    pub raised: usize,
    /// The first refusal in this pass (thread name, error), e.g. no CAP_SYS_NICE or
    /// LimitRTPRIO.
    pub refused: Option<(String, String)>,
}

/// Sets SCHED_FIFO `priority` on every thread of this process whose name starts with
/// `prefix` and does not have it yet (`/proc/self/task/<tid>/comm`). Other threads are left
/// alone.
pub fn raise_threads(prefix: &str, priority: i32) -> RaiseOutcome {
    let mut out = RaiseOutcome::default();
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        out.refused = Some(("/proc/self/task".into(), "not readable".into()));
        return out;
    };
    for entry in dir.flatten() {
        let Some(tid) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<libc::pid_t>().ok())
        else {
            continue;
        };
        let Ok(comm) = std::fs::read_to_string(entry.path().join("comm")) else {
            continue;
        };
        let name = comm.trim_end();
        if !name.starts_with(prefix) {
            continue;
        }
        out.matched += 1;
        let mut cur = libc::sched_param { sched_priority: 0 };
        // SAFETY: `tid` is a thread id of this process read from /proc; `cur` is a valid
        // out-parameter. A thread that ended since the listing makes these fail (ESRCH),
        // which is skipped below.
        let policy = unsafe { libc::sched_getscheduler(tid) };
        let got = unsafe { libc::sched_getparam(tid, &mut cur) };
        if policy == libc::SCHED_FIFO && got == 0 && cur.sched_priority == priority {
            continue;
        }
        let param = libc::sched_param {
            sched_priority: priority,
        };
        // SAFETY: as above; on Linux the id names one thread, so only that thread changes.
        let rc = unsafe { libc::sched_setscheduler(tid, libc::SCHED_FIFO, &param) };
        if rc == 0 {
            out.raised += 1;
        } else {
            let err = std::io::Error::last_os_error();
            if err.raw_os_error() == Some(libc::ESRCH) {
                out.matched -= 1;
            } else if out.refused.is_none() {
                out.refused = Some((name.to_string(), err.to_string()));
            }
        }
    }
    out
}

/// How often the transport threads are looked for again: Zenoh starts its runtimes when they
/// are first used (a link coming up) and a runtime may start a thread later; such a thread runs
/// with normal scheduling until the next pass (threads started by an already raised thread
/// inherit its priority at once).
pub const TRANSPORT_RESCAN: std::time::Duration = std::time::Duration::from_millis(500);

/// Advice when the transport threads would not preempt the processing loop: at equal
/// SCHED_FIFO priority a loop busy with a frame holds a raised transport thread back until it
/// blocks. Measured (docs/performance.md, "The hop in the product"): with the loops at 50 the
/// transport at 60 kept the hop p99 under 1 ms in every row on a quiet machine, at 50 not in
/// every row.
pub fn transport_priority_advice(transport_priority: i32, loop_priority: Option<i32>) -> Option<String> {
    let loop_priority = loop_priority?;
    (transport_priority <= loop_priority).then(|| {
        let fix = if loop_priority >= 99 {
            "lower the loop's below 99".to_string()
        } else {
            format!("set it above the loop's, e.g. {}", (loop_priority + 10).min(99))
        };
        format!(
            "[cluster] transport_fifo_priority = {transport_priority} is not above [realtime] fifo_priority = \
             {loop_priority}: a busy processing loop delays observations; {fix}"
        )
    })
}

/// Raises Zenoh's transport threads of `role` to SCHED_FIFO `priority` now and every
/// [`TRANSPORT_RESCAN`] on a thread of its own (normal scheduling), writing one line to
/// `status.realtime_transport` and logging each change of outcome. Ends with the status (the
/// service stopped).
pub fn watch_transport_threads(
    role: crate::cluster::Role,
    priority: i32,
    status: std::sync::Weak<crate::status::SharedStatus>,
) -> std::io::Result<()> {
    let Some(prefix) = transport_thread_prefix(role) else {
        return Ok(());
    };
    std::thread::Builder::new()
        .name("irtrackd-rtwatch".into())
        .spawn(move || {
            let mut last_line = String::new();
            let mut total_raised = 0usize;
            loop {
                let Some(st) = status.upgrade() else { return };
                let o = raise_threads(prefix, priority);
                total_raised += o.raised;
                let line = match &o.refused {
                    Some((thread, err)) => format!(
                        "Zenoh transport threads ({prefix}*) SCHED_FIFO priority {priority}: not permitted on {thread} ({err}); running with normal scheduling"
                    ),
                    None if o.matched == 0 => format!(
                        "Zenoh transport threads ({prefix}*) SCHED_FIFO priority {priority}: no such thread yet (no link up)"
                    ),
                    None => format!(
                        "Zenoh transport threads ({prefix}*) SCHED_FIFO priority {priority}: applied to {} threads",
                        o.matched
                    ),
                };
                if line != last_line {
                    if o.refused.is_some() {
                        tracing::warn!(
                            priority,
                            threads = prefix,
                            "{line} (needs CAP_SYS_NICE or LimitRTPRIO=, see systemd/irtrackd-realtime.conf)"
                        );
                    } else {
                        tracing::info!(priority, threads = prefix, raised_total = total_raised, "{line}");
                    }
                    if let Ok(mut g) = st.realtime_transport.lock() {
                        *g = Some(line.clone());
                    }
                    last_line = line;
                }
                drop(st);
                std::thread::sleep(TRANSPORT_RESCAN);
            }
        })
        .map(|_| ())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transport_priority_not_above_the_loop_is_named() {
        assert_eq!(transport_priority_advice(60, Some(50)), None);
        assert_eq!(transport_priority_advice(50, None), None);
        let same = transport_priority_advice(50, Some(50)).unwrap_or_default();
        assert!(
            same.contains("= 50 is not above") && same.contains("e.g. 60"),
            "{same}"
        );
        let below = transport_priority_advice(40, Some(95)).unwrap_or_default();
        assert!(below.contains("e.g. 99"), "{below}");
        let top = transport_priority_advice(99, Some(99)).unwrap_or_default();
        assert!(top.contains("lower the loop's below 99"), "{top}");
    }

    /// Policy and priority of thread `tid` of this process.
    fn sched_of(tid: libc::pid_t) -> (i32, i32) {
        let mut p = libc::sched_param { sched_priority: 0 };
        // SAFETY: plain queries on a thread of this process; `p` is a valid out-parameter.
        let policy = unsafe { libc::sched_getscheduler(tid) };
        // SAFETY: as above.
        assert_eq!(unsafe { libc::sched_getparam(tid, &mut p) }, 0);
        (policy, p.sched_priority)
    }

    #[test]
    fn raises_only_threads_of_the_prefix_and_once() {
        let spawn = |name: &str| {
            let (tx, rx) = std::sync::mpsc::channel();
            let (stop_tx, stop_rx) = std::sync::mpsc::channel::<()>();
            let h = std::thread::Builder::new()
                .name(name.into())
                .spawn(move || {
                    // SAFETY: gettid has no preconditions.
                    tx.send(unsafe { libc::gettid() }).unwrap();
                    let _ = stop_rx.recv();
                })
                .unwrap();
            (rx.recv().unwrap(), stop_tx, h)
        };
        let (a, stop_a, ha) = spawn("rtzt-a");
        let (b, stop_b, hb) = spawn("rtzt-b");
        let (other, stop_o, ho) = spawn("other-rtzt");
        let o = raise_threads("rtzt-", 7);
        assert_eq!(o.matched, 2, "{o:?}");
        match &o.refused {
            // Not root / no RLIMIT_RTPRIO here: the refusal is named and nothing changed.
            Some((thread, err)) => {
                assert!(thread.starts_with("rtzt-"), "{thread}");
                assert!(!err.is_empty());
                assert_eq!(sched_of(a).0, libc::SCHED_OTHER);
            }
            None => {
                assert_eq!(o.raised, 2, "{o:?}");
                assert_eq!(sched_of(a), (libc::SCHED_FIFO, 7));
                assert_eq!(sched_of(b), (libc::SCHED_FIFO, 7));
                assert_eq!(sched_of(other).0, libc::SCHED_OTHER);
                // A second pass finds them raised and changes nothing.
                let again = raise_threads("rtzt-", 7);
                assert_eq!((again.matched, again.raised), (2, 0), "{again:?}");
            }
        }
        for (s, h) in [(stop_a, ha), (stop_b, hb), (stop_o, ho)] {
            drop(s);
            h.join().unwrap();
        }
    }
}
