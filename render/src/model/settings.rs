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

/// Where the key light sits. Lighting needs shading ([`RenderSettings::shading`]); MIP is
/// never lit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum LightDirection {
    /// At the eye: every ray is lit from its own origin (each pixel's own direction in a
    /// perspective view), which is the lighting Strata has always had.
    Headlight,
    /// Directional, pointing towards the light in camera axes: x right, y up, z towards the
    /// viewer ((0, 0, 1) lights from behind the camera, along the view axis).
    Camera([f64; 3]),
    /// Directional, pointing towards the light in patient (LPS) axes: fixed to the anatomy
    /// while the camera orbits.
    Patient([f64; 3]),
}

/// The key light: direction and intensity of its direct (diffuse and specular) term. The
/// ambient term is [`Shading::ambient`], which shadows never darken.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct KeyLight {
    pub direction: LightDirection,
    pub intensity: f32,
}

impl Default for KeyLight {
    /// Today's image: the headlight at full intensity.
    fn default() -> Self {
        KeyLight {
            direction: LightDirection::Headlight,
            intensity: 1.0,
        }
    }
}

impl KeyLight {
    /// Whether this is the default headlight, which the shader lights without any key-light
    /// code (so default images stay byte-identical).
    pub fn is_default(&self) -> bool {
        *self == KeyLight::default()
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ShadowMode {
    Off,
    /// A shadow ray per shaded sample towards the key light through the resident cut
    /// (shadows.rs).
    Exact,
    /// One fetch per shaded sample from a low-resolution transmittance volume built on the GPU
    /// from the resident cut for the current TF and light (light_cache.rs); rebuilt only when
    /// what it was built from changes. Needs a directional light (one direction per frame).
    Cache,
}

/// Volumetric shadows from the key light (shadows.rs: the model, the bias, the reference).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Shadows {
    pub mode: ShadowMode,
    /// Shadow-ray step in finest voxels (the main ray's step is `quality`); the cache's
    /// rays use it too.
    pub step: f64,
    /// Cache mode: finest voxels per cache texel edge (light_cache.rs).
    #[serde(default = "default_light_cache_res")]
    pub cache_res: f64,
}

/// The smallest and largest light-cache resolutions, in finest voxels per texel edge: below 1
/// the cache is larger than the volume; above 16 it holds no shadow smaller than a typical
/// organ.
pub const LIGHT_CACHE_MIN_RES: f64 = 1.0;
pub const LIGHT_CACHE_MAX_RES: f64 = 16.0;

fn default_light_cache_res() -> f64 {
    2.0
}

impl Default for Shadows {
    fn default() -> Self {
        Shadows {
            mode: ShadowMode::Off,
            step: 1.0,
            cache_res: default_light_cache_res(),
        }
    }
}

/// Ambient occlusion from local extinction (ambient_occlusion.rs: the model, its directions
/// and its reference): the ambient term of a lit sample is scaled by the mean transmittance of
/// short rays over `radius_mm`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Occlusion {
    /// Length of the occlusion rays in mm (patient space).
    pub radius_mm: f64,
}

/// Single scattering of the key light (scattering.rs: the phase function, the hybrid rule, the
/// normalisation): the direct term blends the Blinn-Phong BRDF and a Henyey-Greenstein phase
/// by gradient magnitude.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scattering {
    /// Henyey-Greenstein asymmetry, |g| <= [`SCATTERING_MAX_ABS_G`]: > 0 scatters forward
    /// (back-lit samples brighten), 0 is isotropic.
    pub g: f64,
    /// Exposure Render's gradient factor in [0, 1]: 0 is volume-like (phase) everywhere, 1 is
    /// surface-like (BRDF) wherever the gradient is more than a few % of the TF range per voxel.
    pub blend: f64,
}

/// The largest |g|: at 0.99 the phase's peak is already 2·10⁴ × isotropic (an 8-bit image
/// saturates long before), and closer to 1 its f32 evaluation loses the peak's width
/// (scattering.rs).
pub const SCATTERING_MAX_ABS_G: f64 = 0.99;

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
    /// Ray-start jitter against wood-grain, and with it the shadow and occlusion rays' sample
    /// offset within their step (progressive.rs averages frames of both); off for image
    /// comparisons (the reference has no jitter, and noise would eat the tolerance).
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
    /// The key light of shaded DVR and isosurfaces (default: the headlight).
    #[serde(default)]
    pub light: KeyLight,
    /// Volumetric shadows from the key light (default: off).
    #[serde(default)]
    pub shadows: Shadows,
    /// Ambient occlusion of lit samples (default: off).
    #[serde(default)]
    pub occlusion: Option<Occlusion>,
    /// Single scattering of the key light (default: off).
    #[serde(default)]
    pub scattering: Option<Scattering>,
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
            light: KeyLight::default(),
            shadows: Shadows::default(),
            occlusion: None,
            scattering: None,
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
        let light = match self.light.direction {
            LightDirection::Headlight => None,
            LightDirection::Camera(v) | LightDirection::Patient(v) => Some(v),
        };
        if let Some(v) = light {
            let n = glam::DVec3::from(v).length();
            if !(n.is_finite() && n > 1e-12) {
                return Err(RenderError::InvalidSettings(format!(
                    "light direction must be finite and non-zero, got {v:?}"
                )));
            }
        }
        if !(self.light.intensity.is_finite() && self.light.intensity >= 0.0) {
            return Err(RenderError::InvalidSettings(format!(
                "light intensity must be finite and >= 0, got {}",
                self.light.intensity
            )));
        }
        if self.shadows.mode != ShadowMode::Off
            && !(self.shadows.step.is_finite() && self.shadows.step >= 0.05)
        {
            // Below 1/20 voxel a shadow ray through a 512³ volume takes > 10⁴ samples per
            // shaded sample: a typo, not a setting.
            return Err(RenderError::InvalidSettings(format!(
                "shadow step must be >= 0.05 voxel, got {}",
                self.shadows.step
            )));
        }
        if self.shadows.mode == ShadowMode::Cache {
            if !(self.shadows.cache_res.is_finite()
                && (LIGHT_CACHE_MIN_RES..=LIGHT_CACHE_MAX_RES).contains(&self.shadows.cache_res))
            {
                return Err(RenderError::InvalidSettings(format!(
                    "light cache resolution must be {}..={} voxels per texel, got {}",
                    LIGHT_CACHE_MIN_RES, LIGHT_CACHE_MAX_RES, self.shadows.cache_res
                )));
            }
            if self.light.direction == LightDirection::Headlight {
                // The headlight's direction is each ray's own: no one volume holds it.
                return Err(RenderError::InvalidSettings(
                    "the light cache needs a directional key light, not the headlight".into(),
                ));
            }
        }
        if let Some(o) = &self.occlusion {
            if !(o.radius_mm.is_finite() && o.radius_mm >= 0.0) {
                return Err(RenderError::InvalidSettings(format!(
                    "occlusion radius must be finite and >= 0 mm, got {}",
                    o.radius_mm
                )));
            }
            if !(self.shadows.step.is_finite() && self.shadows.step >= 0.05) {
                // The occlusion rays march at the shadow step (ambient_occlusion.rs).
                return Err(RenderError::InvalidSettings(format!(
                    "occlusion rays march at the shadow step, which must be >= 0.05 voxel, got {}",
                    self.shadows.step
                )));
            }
        }
        if let Some(sc) = &self.scattering {
            if !(sc.g.is_finite() && sc.g.abs() <= SCATTERING_MAX_ABS_G) {
                return Err(RenderError::InvalidSettings(format!(
                    "scattering g must be in [-{m}, {m}], got {}",
                    sc.g,
                    m = SCATTERING_MAX_ABS_G
                )));
            }
            if !(sc.blend.is_finite() && (0.0..=1.0).contains(&sc.blend)) {
                return Err(RenderError::InvalidSettings(format!(
                    "scattering blend must be in [0, 1], got {}",
                    sc.blend
                )));
            }
        }
        Ok(())
    }

    /// Whether ambient occlusion is applied: on and a lit mode (shaded DVR, isosurface).
    pub fn effective_occlusion(&self) -> Option<Occlusion> {
        self.occlusion
            .filter(|_| self.effective_shading().is_some())
    }

    /// Whether the direct term scatters (scattering.rs): on and a lit mode.
    pub fn effective_scattering(&self) -> Option<Scattering> {
        self.scattering
            .filter(|_| self.effective_shading().is_some())
    }

    /// Whether shadow rays are traced: exact shadows on and a lit mode (shaded DVR,
    /// isosurface).
    pub fn effective_shadows(&self) -> bool {
        self.shadows.mode == ShadowMode::Exact && self.effective_shading().is_some()
    }

    /// Whether the shadow term is read from the light cache: cache shadows and a lit mode.
    pub fn effective_light_cache(&self) -> bool {
        self.shadows.mode == ShadowMode::Cache && self.effective_shading().is_some()
    }

    /// Whether the key-light shading path is compiled in: a light other than the default
    /// headlight, shadows, occlusion or scattering (all need the sample's light direction and a split of the
    /// ambient from the direct term).
    pub fn effective_key_light(&self) -> bool {
        self.effective_shading().is_some()
            && (!self.light.is_default()
                || self.effective_shadows()
                || self.effective_light_cache()
                || self.effective_occlusion().is_some()
                || self.effective_scattering().is_some())
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
