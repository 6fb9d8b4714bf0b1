//! What to render: shared verbatim by the GPU raycaster and the CPU reference so a comparison
//! can only differ in arithmetic, never in intent.

use serde::{Deserialize, Serialize};

use crate::error::RenderError;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum RenderMode {
    /// Emission-absorption, front to back.
    Dvr,
    /// Maximum intensity: pixel = (colour · α, α) of the TF at the ray's maximum value.
    /// Empty pages are still skipped, which is exact for monotonic opacity ramps.
    Mip,
    /// First crossing of `iso_value` (physical units), refined by bisection, shaded.
    Isosurface,
}

/// Blinn-Phong with a headlight (light at the eye, so half vector = view vector).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Shading {
    pub ambient: f32,
    pub diffuse: f32,
    pub specular: f32,
    pub shininess: f32,
}

impl Default for Shading {
    fn default() -> Self {
        Shading {
            ambient: 0.3,
            diffuse: 0.7,
            specular: 0.2,
            shininess: 32.0,
        }
    }
}

/// Axis-aligned crop in fractions of the volume extent per index axis (0 = first cell face,
/// 1 = last cell face).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CropBox {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Default for CropBox {
    fn default() -> Self {
        CropBox {
            min: [0.0; 3],
            max: [1.0; 3],
        }
    }
}

/// Keeps patient points x with dot(normal, x) >= offset_mm.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipPlane {
    pub normal: [f64; 3],
    pub offset_mm: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    pub mode: RenderMode,
    /// Base step in units of the finest voxel edge (0.5 = half a voxel). In a level-L node the
    /// step grows to quality · 2^L voxels (octree paper §5): coarse data has no finer detail.
    pub quality: f64,
    /// Ray-start jitter against wood-grain; off for image comparisons (the reference has no
    /// jitter, and noise would eat the tolerance).
    pub jitter: bool,
    /// Seeds the jitter hash; vary per frame for temporal accumulation.
    pub frame_index: u32,
    /// Stop a ray once accumulated opacity reaches this (DVR only). None = never.
    pub early_termination: Option<f32>,
    /// Jump over page entries flagged empty.
    pub skip_empty: bool,
    /// Shading for DVR (optional) and isosurface (always; None there means default shading).
    pub shading: Option<Shading>,
    /// Physical value of the isosurface.
    pub iso_value: f64,
    pub crop: CropBox,
    pub clip_plane: Option<ClipPlane>,
    /// Count samples into an atomic counter (benchmarks; costs one atomic per ray).
    pub count_samples: bool,
    /// Trilinear by 8 textureLoads in f32 instead of the sampler. Lavapipe's sampler uses
    /// 8-bit interpolation weights; exact mode isolates that error in tests.
    pub exact_trilinear: bool,
    /// DVR integrates each segment between two samples through a pre-integrated TF table
    /// (segment_integral.rs, length-free) instead of classifying the sample alone: narrow or
    /// step-shaped TFs no longer need tiny steps.
    pub preintegrated: bool,
    /// C0-continuous field where nodes of different levels meet (smooth_transitions.rs):
    /// off reproduces the discontinuous baseline. Compiled in only when the cut has a node
    /// next to a coarser one.
    #[serde(default = "default_true")]
    pub smooth_transitions: bool,
}

fn default_true() -> bool {
    true
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            width: 512,
            height: 512,
            mode: RenderMode::Dvr,
            quality: 0.5,
            jitter: true,
            frame_index: 0,
            early_termination: Some(0.99),
            skip_empty: true,
            shading: None,
            iso_value: 300.0,
            crop: CropBox::default(),
            clip_plane: None,
            count_samples: false,
            exact_trilinear: false,
            preintegrated: false,
            smooth_transitions: true,
        }
    }
}

impl RenderSettings {
    pub fn validate(&self) -> Result<(), RenderError> {
        if self.width == 0 || self.height == 0 {
            return Err(RenderError::InvalidSettings(format!(
                "image size {}x{}",
                self.width, self.height
            )));
        }
        if !(self.quality.is_finite() && self.quality > 1e-4) {
            return Err(RenderError::InvalidSettings(format!(
                "quality must be > 0, got {}",
                self.quality
            )));
        }
        if let Some(t) = self.early_termination {
            if !(t > 0.0 && t <= 1.0) {
                return Err(RenderError::InvalidSettings(format!(
                    "early termination threshold {t} not in (0,1]"
                )));
            }
        }
        if let Some(p) = &self.clip_plane {
            let n = glam::DVec3::from(p.normal);
            if n.length().is_nan() || n.length() <= 1e-12 || !p.offset_mm.is_finite() {
                return Err(RenderError::InvalidSettings(
                    "clip plane normal must be non-zero".into(),
                ));
            }
        }
        Ok(())
    }

    /// Shading actually applied: isosurfaces are always shaded.
    pub fn effective_shading(&self) -> Option<Shading> {
        match self.mode {
            RenderMode::Isosurface => Some(self.shading.unwrap_or_default()),
            RenderMode::Dvr => self.shading,
            RenderMode::Mip => None,
        }
    }
}
