//! Memory a closed volume leaves behind: glibc's per-thread malloc arenas.
//!
//! Every [`crate::StreamingVolume`] starts its own fetch and prediction threads, and those
//! threads allocate the bricks (36³ u16, 91 KiB each: below malloc's mmap threshold, so from
//! an arena). glibc gives each new thread an arena (up to 8 per core), frees a brick back
//! into the arena it came from, and returns an arena's free memory to the system only from
//! the arena's top. So when a volume closes, its bricks' memory stays in the arenas its
//! threads used, and the next volume's threads, handed other arenas, fill those up again:
//! measured (loader/tests/memory_cycles.rs, random budgets), RSS after each of 4 volumes
//! 223 → 248 → 258 → 265 MiB with heap in use flat at 61-63 MiB and free heap 57 → 94 MiB;
//! with one arena 200 → 225 → 228 → 229 MiB. The 30-minute soak rose from 318 to 562 MiB.
//!
//! [`limit_malloc_arenas`] caps the arenas (`mallopt(M_ARENA_MAX)`), so the memory a volume
//! gave back is what the next one reuses. It must run before the process has started many
//! threads (glibc fixes its arena limit when it first needs more than 8 arenas): the
//! `strata` binary calls it first thing in `main`, tests that measure memory at their start,
//! and `StreamingVolume::new` once more for library users (harmless when already done).

/// The arenas kept: two, so the frame thread and the fetch threads do not all wait on one
/// lock (measured with one: the same bound; two is glibc's usual advice for servers).
pub const MALLOC_ARENAS: i32 = 2;

/// Caps glibc's malloc arenas at [`MALLOC_ARENAS`] unless the user chose a number
/// (`MALLOC_ARENA_MAX`) or asked for glibc's default (`STRATA_MALLOC_ARENAS=default`, to
/// measure the difference). Returns whether it set the cap. No-op off glibc.
pub fn limit_malloc_arenas() -> bool {
    use std::sync::OnceLock;
    static SET: OnceLock<bool> = OnceLock::new();
    *SET.get_or_init(|| {
        let user_chose = std::env::var_os("MALLOC_ARENA_MAX").is_some()
            || std::env::var("STRATA_MALLOC_ARENAS").is_ok_and(|v| v == "default");
        !user_chose && set_arena_max(MALLOC_ARENAS)
    })
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn set_arena_max(arenas: i32) -> bool {
    // SAFETY: mallopt only changes malloc's tuning; M_ARENA_MAX takes any positive count.
    unsafe { libc::mallopt(libc::M_ARENA_MAX, arenas) == 1 }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn set_arena_max(_arenas: i32) -> bool {
    false
}
