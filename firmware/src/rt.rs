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
