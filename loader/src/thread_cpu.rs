//! CPU time of the calling thread (`CLOCK_THREAD_CPUTIME_ID`): what the loader costs the frame
//! thread, unlike wall time, which on a shared machine also counts the time other processes
//! held the core.

/// Seconds of CPU the calling thread has used so far; None where the clock is unavailable
/// (non-Unix, or the call failed).
pub fn thread_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut now = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `now` is a valid, writable timespec for the duration of the call, and
        // CLOCK_THREAD_CPUTIME_ID is a clock id every supported Unix defines.
        let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut now) };
        (rc == 0).then_some(now.tv_sec as f64 + now.tv_nsec as f64 * 1e-9)
    }
    #[cfg(not(unix))]
    {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_this_threads_work_not_sleep() {
        let Some(start) = thread_cpu_seconds() else {
            eprintln!("thread CPU clock unavailable here; nothing to check");
            return;
        };
        std::thread::sleep(std::time::Duration::from_millis(30));
        let after_sleep = thread_cpu_seconds().unwrap_or(start);
        // Busy work the optimiser cannot remove.
        let mut x = 1u64;
        let mut spins = 0u64;
        while thread_cpu_seconds().unwrap_or(f64::MAX) - after_sleep < 0.005 {
            for i in 0..10_000u64 {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(i);
            }
            spins += 1;
        }
        std::hint::black_box(x);
        assert!(spins > 0);
        // Sleeping 30 ms costs (almost) no CPU; the clock is monotonic.
        assert!(after_sleep - start < 0.025, "{start} -> {after_sleep}");
        assert!(thread_cpu_seconds().unwrap_or(0.0) >= after_sleep);
    }
}
