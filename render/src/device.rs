//! The wgpu device: created headless for tests and the CLI, or adopted from eframe.

use crate::error::RenderError;

pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// None when adopted from a device whose adapter we never saw.
    pub adapter_info: Option<wgpu::AdapterInfo>,
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
        Ok(GpuContext {
            device,
            queue,
            adapter_info: Some(adapter.get_info()),
        })
    }

    /// Adopts a device created elsewhere (eframe). Features and limits are read from it.
    pub fn from_device(device: wgpu::Device, queue: wgpu::Queue) -> Self {
        GpuContext {
            device,
            queue,
            adapter_info: None,
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
            .map(|_| ())
            .map_err(|e| RenderError::Readback(e.to_string()))
    }

    /// Blocks until all submitted work has finished.
    pub fn wait_idle(&self) -> Result<(), RenderError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| RenderError::Readback(e.to_string()))
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
