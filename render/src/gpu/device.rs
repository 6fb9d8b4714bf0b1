//! The wgpu device: created headless for tests and the CLI, or adopted from eframe.

use std::sync::{Arc, Mutex};

use crate::error::RenderError;

pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// None when adopted from a device whose adapter we never saw.
    pub adapter_info: Option<wgpu::AdapterInfo>,
    /// The first error wgpu reported outside any error scope (headless devices only: an
    /// adopted device has its owner's handler). wgpu's default handler panics; this one keeps
    /// the error for the next frame or wait to return.
    uncaptured: Arc<Mutex<Option<String>>>,
}

impl GpuContext {
    /// Headless device on the best adapter (lavapipe on CI). Requests R16Unorm textures and
    /// timestamp queries when available and the adapter's full limits, so cache sizing can use
    /// what is really there.
    pub fn headless() -> Result<Self, RenderError> {
        pollster::block_on(Self::headless_async())
    }

    pub async fn headless_async() -> Result<Self, RenderError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                force_fallback_adapter: false,
                compatible_surface: None,
                ..Default::default()
            })
            .await
            .map_err(|e| RenderError::NoAdapter {
                details: e.to_string(),
            })?;
        // Timestamps time the raycast pass for the time-critical controller (gpu_timing.rs).
        let wanted = wgpu::Features::TEXTURE_FORMAT_16BIT_NORM | wgpu::Features::TIMESTAMP_QUERY;
        let features = adapter.features() & wanted;
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("strata-render"),
                required_features: features,
                required_limits: adapter.limits(),
                ..Default::default()
            })
            .await
            .map_err(|e| RenderError::RequestDevice(e.to_string()))?;
        let uncaptured = Arc::new(Mutex::new(None::<String>));
        let slot = uncaptured.clone();
        device.on_uncaptured_error(Arc::new(move |error: wgpu::Error| {
            let mut first = slot.lock().unwrap_or_else(|p| p.into_inner());
            first.get_or_insert_with(|| error.to_string());
        }));
        Ok(GpuContext {
            device,
            queue,
            adapter_info: Some(adapter.get_info()),
            uncaptured,
        })
    }

    /// Adopts a device created elsewhere (eframe). Features and limits are read from it.
    pub fn from_device(device: wgpu::Device, queue: wgpu::Queue) -> Self {
        GpuContext {
            device,
            queue,
            adapter_info: None,
            uncaptured: Arc::default(),
        }
    }

    /// The error wgpu reported outside an error scope since the last call, if any (an
    /// allocation that did not fit, a validation error): taken, so it is reported once.
    pub fn check_uncaptured(&self) -> Result<(), RenderError> {
        let mut first = self.uncaptured.lock().unwrap_or_else(|p| p.into_inner());
        match first.take() {
            None => Ok(()),
            Some(detail) => Err(RenderError::Uncaptured(detail)),
        }
    }

    pub fn supports_r16_unorm(&self) -> bool {
        self.device
            .features()
            .contains(wgpu::Features::TEXTURE_FORMAT_16BIT_NORM)
    }

    pub fn supports_timestamps(&self) -> bool {
        self.device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
    }

    /// Blocks until `submission` has finished on the GPU (frame pacing in headless loops).
    pub fn wait_for_submission(
        &self,
        submission: wgpu::SubmissionIndex,
    ) -> Result<(), RenderError> {
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(submission),
                timeout: None,
            })
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        self.check_uncaptured()
    }

    /// Blocks until all submitted work has finished.
    pub fn wait_idle(&self) -> Result<(), RenderError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        self.check_uncaptured()
    }

    pub fn limits(&self) -> wgpu::Limits {
        self.device.limits()
    }

    pub fn adapter_name(&self) -> String {
        self.adapter_info
            .as_ref()
            .map(|i| format!("{} ({:?})", i.name, i.backend))
            .unwrap_or_else(|| "external device".into())
    }
}

/// Maps `buffer` for reading and waits for it (readbacks of tests, probes and pick queries).
pub(crate) fn map_blocking(
    device: &wgpu::Device,
    buffer: &wgpu::Buffer,
) -> Result<(), RenderError> {
    let (tx, rx) = std::sync::mpsc::channel();
    buffer.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| RenderError::Readback(e.to_string()))?;
    match rx.recv() {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(RenderError::Readback(e.to_string())),
        Err(e) => Err(RenderError::Readback(e.to_string())),
    }
}
