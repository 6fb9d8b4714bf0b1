//! Surviving the GPU: a lost device (driver reset, a watchdog timeout, an external GPU
//! unplugged) or an out-of-memory allocation (a brick cache larger than the adapter has) must
//! not end the session. The render thread (`volume_session.rs`) watches its device here, sorts
//! every way a step on the device can end into "the GPU failed" or "a real error" at one seam
//! ([`DeviceWatch::classify`]), and on a GPU failure drops the device and everything on it,
//! creates a new one with a smaller brick cache ([`smaller_budget`]) and renders the newest
//! request again. The session itself (volume, camera, transfer function, window, crop,
//! measurements) lives on the UI side and is never touched, so the user sees the view come
//! back as it was, with a line in the status bar saying what happened.
//!
//! Why a watch and not only the returned errors: wgpu reports device loss through a callback
//! (operations on a lost device fail silently, "surfaced via callback"), and allocation
//! failures through the uncaptured-error handler, whose default panics. Installing our own
//! handler turns both into state the render thread reads after every step.

use std::fmt;
use std::sync::{Arc, Mutex};

use super::sync::lock_ignoring_poison;

/// The smallest brick cache worth rebuilding with: 32 MiB holds ~170 slots of 36³ u16, enough
/// for a coarse cut of any volume. Below this a failure is reported, not retried.
pub const MIN_GPU_BUDGET_BYTES: u64 = 32 << 20;

/// A rebuilt device that fails again before it has shown a single frame this many times in a
/// row ends the session's 3D view with an error instead of looping.
pub const MAX_FAILURES_WITHOUT_A_FRAME: u32 = 3;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GpuFailureKind {
    DeviceLost,
    OutOfMemory,
}

/// The GPU, not the request, failed: the device must be recreated.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GpuFailure {
    pub kind: GpuFailureKind,
    /// wgpu's or the driver's words.
    pub detail: String,
}

impl fmt::Display for GpuFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.kind {
            GpuFailureKind::DeviceLost => write!(f, "the GPU device was lost ({})", self.detail),
            GpuFailureKind::OutOfMemory => write!(f, "the GPU ran out of memory ({})", self.detail),
        }
    }
}

/// How a step on the device ended, once classified.
#[derive(Debug)]
pub enum StepError {
    /// Recreate the device (smaller budget) and carry on.
    Gpu(GpuFailure),
    /// Anything else (a store that cannot be read, a bug): the 3D view shows it and stops.
    Other(anyhow::Error),
}

impl From<anyhow::Error> for StepError {
    fn from(e: anyhow::Error) -> Self {
        StepError::Other(e)
    }
}

#[derive(Default)]
struct WatchState {
    lost: Option<String>,
    out_of_memory: Option<String>,
    /// A validation or internal error: before the watch these panicked the render thread.
    other: Option<String>,
}

/// What one device has reported through its callbacks. Cloned into the callbacks.
#[derive(Clone, Default)]
pub struct DeviceWatch {
    state: Arc<Mutex<WatchState>>,
}

impl DeviceWatch {
    /// Installs the device-lost callback and the uncaptured-error handler on `device`. Call it
    /// right after the device is created, before anything is allocated on it.
    pub fn install(device: &wgpu::Device) -> Self {
        let watch = DeviceWatch::default();
        let on_lost = watch.clone();
        device.set_device_lost_callback(move |reason, message| {
            on_lost.record_lost(format!("{reason:?}: {message}"));
        });
        let on_error = watch.clone();
        device.on_uncaptured_error(Arc::new(move |error| on_error.record_error(error)));
        watch
    }

    pub fn record_lost(&self, detail: String) {
        let mut state = lock_ignoring_poison(&self.state);
        state.lost.get_or_insert(detail);
    }

    /// Where wgpu's uncaptured errors land (and where a test injects a simulated allocation
    /// failure: the same path a real one takes).
    pub fn record_error(&self, error: wgpu::Error) {
        let mut state = lock_ignoring_poison(&self.state);
        match error {
            wgpu::Error::OutOfMemory { .. } => {
                state.out_of_memory.get_or_insert_with(|| error.to_string());
            }
            other => {
                state.other.get_or_insert_with(|| other.to_string());
            }
        }
    }

    /// The seam: how a step on this device ended. A lost device or a recorded allocation
    /// failure wins over the step's own result (a frame from a lost device is not a frame,
    /// and a failed allocation leaves invalid resources behind it); an error whose text says
    /// "out of memory" or "lost" (readbacks and device creation report them as strings) is one
    /// too; other recorded errors and the step's own error are real errors.
    pub fn classify<T>(&self, result: anyhow::Result<T>) -> Result<T, StepError> {
        let state = lock_ignoring_poison(&self.state);
        if let Some(detail) = &state.lost {
            return Err(StepError::Gpu(GpuFailure {
                kind: GpuFailureKind::DeviceLost,
                detail: detail.clone(),
            }));
        }
        if let Some(detail) = &state.out_of_memory {
            return Err(StepError::Gpu(GpuFailure {
                kind: GpuFailureKind::OutOfMemory,
                detail: detail.clone(),
            }));
        }
        match result {
            Err(e) => Err(match classify_message(&format!("{e:#}")) {
                Some(failure) => StepError::Gpu(failure),
                None => StepError::Other(e),
            }),
            Ok(value) => match &state.other {
                Some(message) => Err(StepError::Other(anyhow::anyhow!("GPU error: {message}"))),
                None => Ok(value),
            },
        }
    }
}

/// Errors that come back as text (a failed readback, a device request) and say the GPU failed.
fn classify_message(message: &str) -> Option<GpuFailure> {
    let lower = message.to_ascii_lowercase();
    let kind = if lower.contains("out of memory") || lower.contains("outofmemory") {
        GpuFailureKind::OutOfMemory
    } else if lower.contains("device lost")
        || lower.contains("device is lost")
        || lower.contains("device is invalid")
    {
        GpuFailureKind::DeviceLost
    } else {
        return None;
    };
    Some(GpuFailure {
        kind,
        detail: message.to_string(),
    })
}

/// The brick cache to rebuild with after a failure: half, never below
/// [`MIN_GPU_BUDGET_BYTES`]; None when already there (nothing smaller is worth trying).
pub fn smaller_budget(current: u64) -> Option<u64> {
    (current > MIN_GPU_BUDGET_BYTES).then(|| (current / 2).max(MIN_GPU_BUDGET_BYTES))
}

/// What the status bar says after a rebuild.
pub fn recovery_line(failure: &GpuFailure, new_budget: u64, recoveries: u32) -> String {
    let times = if recoveries > 1 {
        format!(" ({recoveries} times)")
    } else {
        String::new()
    };
    format!(
        "{failure}; the renderer was restarted with a {} MiB brick cache{times}",
        new_budget >> 20
    )
}

/// Test hook: faults the render thread applies to its own device at the start of its next
/// step, so tests exercise the real recovery path on lavapipe.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
// Constructed by tests only; the render thread's side of the hook is always compiled in, so
// the path tests take is the path a real failure takes.
#[cfg_attr(not(test), allow(dead_code))]
pub enum InjectedFault {
    /// `wgpu::Device::destroy`: wgpu loses the device for real and calls the lost callback.
    DestroyDevice,
    /// An `OutOfMemory` through the uncaptured-error handler, as a failed allocation reports.
    OutOfMemory,
}

#[derive(Debug)]
struct SimulatedAllocationFailure;

impl fmt::Display for SimulatedAllocationFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("simulated allocation failure (test hook)")
    }
}

impl std::error::Error for SimulatedAllocationFailure {}

impl InjectedFault {
    pub fn apply(self, device: &wgpu::Device, watch: &DeviceWatch) {
        match self {
            InjectedFault::DestroyDevice => device.destroy(),
            InjectedFault::OutOfMemory => watch.record_error(wgpu::Error::OutOfMemory {
                source: Box::new(SimulatedAllocationFailure),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_budget_halves_down_to_the_floor_then_stops() {
        assert_eq!(smaller_budget(384 << 20), Some(192 << 20));
        assert_eq!(smaller_budget(48 << 20), Some(MIN_GPU_BUDGET_BYTES));
        assert_eq!(smaller_budget(MIN_GPU_BUDGET_BYTES), None);
        // A budget larger than any adapter (the OOM case of the issue) gets there in steps.
        let mut budget = 1u64 << 40;
        let mut steps = 0;
        while let Some(next) = smaller_budget(budget) {
            assert!(next < budget);
            budget = next;
            steps += 1;
        }
        assert_eq!(budget, MIN_GPU_BUDGET_BYTES);
        assert_eq!(steps, 15);
    }

    #[test]
    fn recorded_loss_and_oom_win_over_the_steps_result_and_other_errors_stay_errors() {
        let watch = DeviceWatch::default();
        assert!(matches!(watch.classify(Ok(3)), Ok(3)));
        let real = watch.classify::<()>(Err(anyhow::anyhow!("brick 7: checksum mismatch")));
        assert!(matches!(real, Err(StepError::Other(_))), "{real:?}");
        let readback =
            watch.classify::<()>(Err(anyhow::anyhow!("GPU readback failed: Out of Memory")));
        assert!(
            matches!(&readback, Err(StepError::Gpu(f)) if f.kind == GpuFailureKind::OutOfMemory),
            "{readback:?}"
        );
        watch.record_error(wgpu::Error::OutOfMemory {
            source: Box::new(SimulatedAllocationFailure),
        });
        let oom = watch.classify(Ok(()));
        assert!(
            matches!(&oom, Err(StepError::Gpu(f)) if f.kind == GpuFailureKind::OutOfMemory),
            "{oom:?}"
        );
        watch.record_lost("Destroyed: device destroyed".into());
        let lost = watch.classify(Ok(()));
        assert!(
            matches!(&lost, Err(StepError::Gpu(f)) if f.kind == GpuFailureKind::DeviceLost),
            "{lost:?}"
        );
    }

    #[test]
    fn a_validation_error_is_an_error_not_a_recovery() {
        let watch = DeviceWatch::default();
        watch.record_error(wgpu::Error::Validation {
            source: Box::new(SimulatedAllocationFailure),
            description: "texture binding mismatch".into(),
        });
        let result = watch.classify(Ok(()));
        match result {
            Err(StepError::Other(e)) => assert!(format!("{e}").contains("texture binding")),
            other => panic!("expected a plain error, got {other:?}"),
        }
    }

    #[test]
    fn the_status_line_names_the_failure_and_the_new_budget() {
        let failure = GpuFailure {
            kind: GpuFailureKind::DeviceLost,
            detail: "Unknown: driver reset".into(),
        };
        let line = recovery_line(&failure, 192 << 20, 1);
        assert_eq!(
            line,
            "the GPU device was lost (Unknown: driver reset); the renderer was restarted with a \
             192 MiB brick cache"
        );
        assert!(recovery_line(&failure, 96 << 20, 2).ends_with("(2 times)"));
    }
}
