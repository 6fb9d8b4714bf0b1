//! Locking that survives a panicked thread.
//!
//! The viewer's mutexes hand plain values between the UI thread and its workers (the render
//! thread, the slice reader, store preparation, the file dialog): the pending request, the
//! newest frame or slice image, status and error text, a job's stage and result, the dialog's
//! answer. Every critical section is a few assignments, clones or takes of such values; none
//! keeps an invariant across fields that a panic halfway could break, so the value behind a
//! poisoned lock is still fine to show (at worst a status with some fields from the newer
//! frame). The render thread even reports its own panic through the status mutex
//! (`volume_session`). Unwrapping poison would turn one panicking render or slice thread into
//! a panic on the UI thread as well, so poison is ignored.

use std::sync::{Condvar, Mutex, MutexGuard};

/// Locks `m`, also after a thread panicked while holding it (see the module doc for why that
/// is sound here).
pub(crate) fn lock_ignoring_poison<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// [`Condvar::wait`] on a guard from [`lock_ignoring_poison`], ignoring poison the same way.
pub(crate) fn wait_ignoring_poison<'a, T>(
    condvar: &Condvar,
    guard: MutexGuard<'a, T>,
) -> MutexGuard<'a, T> {
    condvar.wait(guard).unwrap_or_else(|e| e.into_inner())
}

/// Wakes the UI (egui's `request_repaint`), callable from any thread.
pub type Repaint = std::sync::Arc<dyn Fn() + Send + Sync>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lock_poisoned_by_a_panicking_thread_still_locks() {
        let m = std::sync::Arc::new(Mutex::new(1));
        let held = m.clone();
        let poisoner = std::thread::Builder::new()
            .name("strata-test-poisoner".into())
            .spawn(move || {
                let mut g = held.lock().unwrap();
                *g = 2;
                panic!("poisoning the lock on purpose");
            })
            .unwrap();
        let _ = poisoner.join();
        assert!(m.is_poisoned());
        assert_eq!(*lock_ignoring_poison(&m), 2);
    }
}
