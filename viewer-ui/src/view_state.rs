//! The view a URL fragment describes, and the fragment of a view (issue 39, "shareable
//! views"): `#mode=dvr&preset=ct-bone&az=30&el=20&zoom=1.2` opens the same picture elsewhere.
//!
//! Platform-independent on purpose: the browser build reads and writes fragments with it, and
//! the native tests build the very same camera, settings and transfer function from a
//! fragment to render the reference image the browser's frame is compared with.
//!
//! The fragment is `key=value` pairs joined by `&`. Keys this build does not know are ignored
//! (a link made by a newer viewer still opens); a known key with a bad value is an error that
//! names the key, so a mangled link says what is wrong instead of showing another view. The
//! bearer token (`token=`) is read once and never written back: fragments are shared, tokens
//! must not be.

use strata_render::testdata::phantom::ct_phantom;
use strata_render::{
    BrickedVolume, Camera, CropBox, Projection, RenderError, RenderMode, RenderSettings,
    ShadowMode, TransferFunction, VolumeGeometry,
};

use strata_slices::ColourMap;

use crate::crop_clip::{ClipSettings, CLIP_AXIS_NAMES, MIN_CROP_EXTENT};
use crate::lighting::{
    render_lighting, LightPrefs, LitView, AMBIENT_RANGE, AZIMUTH_RANGE, ELEVATION_RANGE,
    INTENSITY_RANGE, OCCLUSION_RADIUS_RANGE, SCATTERING_BLEND_RANGE, SCATTERING_G_RANGE,
};
use crate::measurements::{self, Measurement};

/// Edge of the built-in sample volume when the fragment names none (voxels).
pub const DEFAULT_VOLUME_EDGE: u32 = 128;
/// Largest built-in volume edge a fragment may ask for: generated on the page's one thread,
/// 256³ takes seconds; more would freeze the tab.
pub const MAX_VOLUME_EDGE: u32 = 256;
/// Largest image edge a fragment may fix (`size=`); the canvas size decides otherwise.
pub const MAX_IMAGE_EDGE: u32 = 4096;
/// Frames a `capture=unconverged` page draws before it captures (test hook).
pub const UNCONVERGED_CAPTURE_FRAMES: u64 = 12;
/// Most frames a `bench=` fragment may orbit (each is a full frame on a software adapter).
pub const MAX_BENCH_FRAMES: u32 = 1000;
/// The largest `frame=` a link may name (a store's frame count is bounded as an axis is); a
/// frame past the opened store's last is refused there.
pub const MAX_LINK_FRAME: u32 = 1 << 20;
/// The orbit camera's field of view, as `strata render`'s perspective default.
pub const FOV_Y_DEG: f64 = 30.0;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FragmentError {
    #[error("the link's `{key}` is `{value}`: {expected}")]
    BadValue {
        key: String,
        value: String,
        expected: String,
    },
}

/// How the page lays out its views, named as `strata view --layout` names them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// The 3D view alone.
    Single,
    /// The 2×2: the 3D view and the axial, coronal and sagittal slices, of a served store or
    /// of the built-in sample alike.
    FourUp,
    /// The 3D view over a row of the three slices (Slicer's "conventional", `strata view
    /// --layout conventional`): `layout=conventional`.
    ThreeDOverSlices,
}

/// What the view shows and from where.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewState {
    pub mode: RenderMode,
    /// A transfer-function preset ([`TransferFunction::PRESETS`]).
    pub preset: String,
    /// The function as edited from that preset (`tf=`, compact_tf.rs); None: the preset as
    /// it is. Named "PRESET (edited)", as the desktop names an edited function.
    pub tf: Option<TransferFunction>,
    /// Orbit angles in degrees and zoom (1 frames the volume's bounding sphere), as
    /// `strata render --azimuth --elevation --zoom`.
    pub azimuth_deg: f64,
    pub elevation_deg: f64,
    pub zoom: f64,
    /// The target moved in the view plane (right, up) in units of the volume's bounding
    /// radius, as the desktop viewer pans ([`Camera::orbit_panned`]).
    pub pan: [f64; 2],
    /// Parallel projection (the desktop's "orthographic" switch) instead of perspective.
    pub orthographic: bool,
    pub layout: Layout,
    /// The slice views' linked crosshair (level-0 continuous voxel index); None: the volume's
    /// centre. Applied when a served store opens, clamped to its dimensions.
    pub cursor: Option<[f64; 3]>,
    /// The slice views' window (centre, width) in the volume's physical unit; None: the
    /// store's own first window.
    pub window: Option<[f64; 2]>,
    /// The slice views' colour map (`cmap=hot`; absent: grey).
    pub colour_map: ColourMap,
    /// The oblique view, shown (in the sagittal's place in the 2×2, a fourth slice under the
    /// 3D view) and turned `[yaw, pitch, roll]` degrees off axial (`oblique=YAW,PITCH[,ROLL]`,
    /// strata_slices' `ObliquePlane::from_orientation_deg`); None: not shown.
    pub oblique: Option<[f64; 3]>,
    /// The frame of a 4-D store every view shows (`frame=N`, numbered from 0; absent: 0).
    /// A frame past the store's last is refused by the viewer that opens it, which knows
    /// the count.
    pub frame: u32,
    /// Isosurface value in the volume's physical unit (HU for the CT sample).
    pub iso_value: f64,
    /// The crop box (`crop=I0,J0,K0,I1,J1,K1`, fractions of each index axis).
    pub crop: CropBox,
    /// The clip plane (`clip=AXIS,FRACTION` with AXIS lr, ap or si, `,flip` to keep the other
    /// side); absent: no clip.
    pub clip: ClipSettings,
    /// Shaded DVR and isosurfaces (the desktop's "Shading" switch); `shade=off` draws them
    /// unshaded. MIP is never shaded.
    pub shading: bool,
    /// The key light and its effects, named as `strata render` names them: `light=AZ,EL` a
    /// directional light at these camera-relative degrees (absent: the headlight),
    /// `shadows=exact|cache`, `occlusion=MM` (radius), `scattering=G[,BLEND]` (asymmetry, blend),
    /// `intensity=I` (the key light's direct term), `ambient=A` (what shadows never darken),
    /// each absent at its default; the shadow step at its default.
    pub light: LightPrefs,
    /// Adaptive sampling of the still view with this oracle ε (`adaptive=EPS`, the desktop's
    /// Rendering-panel setting; crate::adaptive); None: the raycaster's frame is final.
    pub adaptive_epsilon: Option<f64>,
    /// The measurements on the slices (`m=`, strata-viewer-ui's measurements: rulers, angles,
    /// regions with their points' level-0 indices at two decimals; a region's statistics are
    /// computed again by the viewer that opens the link). Empty: no `m=`.
    pub measurements: Vec<Measurement>,
    /// Edge of the built-in sample volume (voxels).
    pub volume_edge: u32,
    /// A store of the server that served the page, streamed; None: the built-in sample.
    pub store: Option<String>,
    /// A second served store drawn over the slices (`overlay=`, crate::overlay).
    pub overlay: crate::overlay::OverlayLink,
    /// A fixed image size (width, height) instead of the canvas's: links that must give the
    /// same pixels anywhere (screenshots, tests).
    pub image_size: Option<[u32; 2]>,
    /// Test hook: post the first complete frame's pixels back to the server that served the
    /// page (`strata serve` accepts them only when started with its test sink).
    pub capture: bool,
    /// With `capture=unconverged`: the frame after [`UNCONVERGED_CAPTURE_FRAMES`] drawn,
    /// converged or not (a page whose server stalls must go on drawing); `capture=1` waits
    /// for a streamed view to converge.
    pub capture_unconverged: bool,
    /// Benchmark hook (`bench=N`): once the view converged, orbit N frames and report their
    /// frame time with the capture. Not written back into the address.
    pub bench_frames: u32,
}

impl Default for ViewState {
    fn default() -> Self {
        ViewState {
            mode: RenderMode::Dvr,
            preset: "ct-bone".into(),
            tf: None,
            azimuth_deg: 30.0,
            elevation_deg: 15.0,
            zoom: 1.0,
            pan: [0.0, 0.0],
            orthographic: false,
            layout: Layout::FourUp,
            cursor: None,
            window: None,
            colour_map: ColourMap::Grey,
            oblique: None,
            frame: 0,
            iso_value: 300.0,
            crop: CropBox::default(),
            clip: ClipSettings::default(),
            shading: true,
            light: LightPrefs::default(),
            measurements: Vec::new(),
            volume_edge: DEFAULT_VOLUME_EDGE,
            store: None,
            overlay: Default::default(),
            image_size: None,
            capture: false,
            capture_unconverged: false,
            bench_frames: 0,
            adaptive_epsilon: None,
        }
    }
}

/// A parsed fragment: the view, and the bearer token if the link carried one.
#[derive(Clone, Debug, PartialEq)]
pub struct Fragment {
    pub view: ViewState,
    pub token: Option<String>,
    /// The link named its preset (`preset=` or `tf=`): the volume's own choice
    /// ([`crate::presets::initial_preset`]) does not replace it.
    pub preset_named: bool,
}

fn mode_name(mode: RenderMode) -> &'static str {
    match mode {
        RenderMode::Dvr => "dvr",
        RenderMode::Mip => "mip",
        RenderMode::Isosurface => "iso",
    }
}

/// The most of a bad value an error quotes: a pasted link can carry kilobytes in one value,
/// and the message must stay a line on the page.
pub const MAX_QUOTED_BYTES: usize = 100;

fn bad(key: &str, value: &str, expected: impl Into<String>) -> FragmentError {
    FragmentError::BadValue {
        key: key.into(),
        value: quoted(value),
        expected: expected.into(),
    }
}

/// `value` whole, or its first [`MAX_QUOTED_BYTES`] (cut at a character boundary) and how
/// long it was.
fn quoted(value: &str) -> String {
    if value.len() <= MAX_QUOTED_BYTES {
        return value.to_string();
    }
    let mut end = MAX_QUOTED_BYTES;
    while !value.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}… ({} bytes in all)", &value[..end], value.len())
}

fn finite(
    key: &str,
    value: &str,
    range: std::ops::RangeInclusive<f64>,
) -> Result<f64, FragmentError> {
    match value.parse::<f64>() {
        Ok(v) if v.is_finite() && range.contains(&v) => Ok(v),
        _ => Err(bad(
            key,
            value,
            format!("a number from {} to {}", range.start(), range.end()),
        )),
    }
}

/// Undoes the percent-encoding a browser may apply to a fragment (`%20`, `%2C`); anything
/// malformed is kept as written.
fn percent_decode(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |b: u8| (b as char).to_digit(16);
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            if let (Some(h), Some(l)) = (hex(bytes[i + 1]), hex(bytes[i + 2])) {
                out.push((h * 16 + l) as u8);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

impl Fragment {
    /// Parses `#k=v&k=v` (the leading `#` optional).
    pub fn parse(fragment: &str) -> Result<Fragment, FragmentError> {
        let mut view = ViewState::default();
        let mut token = None;
        let mut preset_named = false;
        let text = fragment.strip_prefix('#').unwrap_or(fragment);
        for pair in text.split('&').filter(|p| !p.is_empty()) {
            let (key, raw) = pair.split_once('=').unwrap_or((pair, ""));
            let value = percent_decode(raw);
            let value = value.as_str();
            match key {
                "mode" => {
                    view.mode = match value {
                        "dvr" => RenderMode::Dvr,
                        "mip" => RenderMode::Mip,
                        "iso" => RenderMode::Isosurface,
                        _ => return Err(bad(key, value, "dvr, mip or iso")),
                    }
                }
                "preset" => {
                    if TransferFunction::preset(value).is_none() {
                        return Err(bad(
                            key,
                            value,
                            format!("one of {}", TransferFunction::PRESETS.join(", ")),
                        ));
                    }
                    view.preset = value.into();
                    preset_named = true;
                }
                "tf" => {
                    preset_named = true;
                    let tf = crate::compact_tf::decode(value, "").map_err(|e| {
                        // The value may be kilobytes: the message quotes its start only.
                        let shown: String = value.chars().take(40).collect();
                        bad(key, &shown, e.0)
                    })?;
                    view.tf = Some(tf);
                }
                "az" => view.azimuth_deg = finite(key, value, -3600.0..=3600.0)?,
                "el" => view.elevation_deg = finite(key, value, -90.0..=90.0)?,
                "zoom" => view.zoom = finite(key, value, 0.05..=100.0)?,
                "iso" => view.iso_value = finite(key, value, -1.0e6..=1.0e6)?,
                "crop" => view.crop = crop_of(key, value)?,
                "m" => {
                    view.measurements = measurements::from_link_text(value)
                        .map_err(|e| bad(key, value, e.to_string()))?
                }
                "clip" => view.clip = clip_of(key, value)?,
                "shade" => {
                    view.shading = match value {
                        "on" => true,
                        "off" => false,
                        _ => return Err(bad(key, value, "on or off")),
                    }
                }
                "light" => {
                    let (az, el) = value
                        .split_once(',')
                        .ok_or_else(|| bad(key, value, "AZ,EL in degrees"))?;
                    view.light.headlight = false;
                    view.light.azimuth_deg = finite(key, az, AZIMUTH_RANGE)?;
                    view.light.elevation_deg = finite(key, el, ELEVATION_RANGE)?;
                }
                "shadows" => {
                    view.light.shadows = match value {
                        "off" => ShadowMode::Off,
                        "exact" => ShadowMode::Exact,
                        "cache" => ShadowMode::Cache,
                        _ => return Err(bad(key, value, "off, exact or cache")),
                    }
                }
                "occlusion" => {
                    view.light.occlusion = true;
                    view.light.occlusion_radius_mm = finite(key, value, OCCLUSION_RADIUS_RANGE)?;
                }
                "scattering" => {
                    // `G` or `G,BLEND` (the blend a cinematic preset sets).
                    let (g, blend) = match value.split_once(',') {
                        Some((g, blend)) => (g, Some(blend)),
                        None => (value, None),
                    };
                    view.light.scattering = true;
                    view.light.scattering_g = finite(key, g, SCATTERING_G_RANGE)?;
                    if let Some(blend) = blend {
                        view.light.scattering_blend = finite(key, blend, SCATTERING_BLEND_RANGE)?;
                    }
                }
                "intensity" => view.light.intensity = finite(key, value, INTENSITY_RANGE)? as f32,
                "ambient" => view.light.ambient = finite(key, value, AMBIENT_RANGE)? as f32,
                "adaptive" => {
                    let (lo, hi) = crate::adaptive::EPSILON_RANGE;
                    view.adaptive_epsilon = Some(finite(key, value, lo..=hi)?);
                }
                "pan" => {
                    let (x, y) = value
                        .split_once(',')
                        .ok_or_else(|| bad(key, value, "two numbers X,Y"))?;
                    view.pan = [
                        finite(key, x, -100.0..=100.0)?,
                        finite(key, y, -100.0..=100.0)?,
                    ];
                }
                "cursor" => {
                    let parts: Vec<&str> = value.split(',').collect();
                    let [x, y, z] = parts[..] else {
                        return Err(bad(key, value, "three voxel indices X,Y,Z"));
                    };
                    let range = 0.0..=1.0e6;
                    view.cursor = Some([
                        finite(key, x, range.clone())?,
                        finite(key, y, range.clone())?,
                        finite(key, z, range)?,
                    ]);
                }
                "frame" => {
                    view.frame = value
                        .parse::<u32>()
                        .ok()
                        .filter(|&frame| frame <= MAX_LINK_FRAME)
                        .ok_or_else(|| {
                            bad(key, value, "a frame number from 0 (frames numbered from 0)")
                        })?
                }
                "oblique" => {
                    let parts: Vec<&str> = value.split(',').collect();
                    let (yaw, pitch, roll) = match parts[..] {
                        [yaw, pitch] => (yaw, pitch, "0"),
                        [yaw, pitch, roll] => (yaw, pitch, roll),
                        _ => return Err(bad(key, value, "YAW,PITCH[,ROLL] in degrees")),
                    };
                    view.oblique = Some([
                        finite(key, yaw, -180.0..=180.0)?,
                        finite(key, pitch, -90.0..=90.0)?,
                        finite(key, roll, -180.0..=180.0)?,
                    ]);
                }
                "window" => {
                    let (centre, width) = value
                        .split_once(',')
                        .ok_or_else(|| bad(key, value, "CENTRE,WIDTH"))?;
                    view.window = Some([
                        finite(key, centre, -1.0e9..=1.0e9)?,
                        finite(key, width, 1.0e-6..=1.0e9)?,
                    ]);
                }
                "cmap" => {
                    view.colour_map = ColourMap::ALL
                        .into_iter()
                        .find(|map| colour_map_name(*map) == value)
                        .ok_or_else(|| {
                            let names: Vec<_> =
                                ColourMap::ALL.into_iter().map(colour_map_name).collect();
                            bad(key, value, format!("one of {}", names.join(", ")))
                        })?;
                }
                "layout" => {
                    view.layout = match value {
                        "single" => Layout::Single,
                        "four-up" => Layout::FourUp,
                        "conventional" => Layout::ThreeDOverSlices,
                        _ => return Err(bad(key, value, "single, four-up or conventional")),
                    }
                }
                "proj" => {
                    view.orthographic = match value {
                        "persp" => false,
                        "ortho" => true,
                        _ => return Err(bad(key, value, "persp or ortho")),
                    }
                }
                "volume" => {
                    view.volume_edge = match value.parse::<u32>() {
                        Ok(n) if (8..=MAX_VOLUME_EDGE).contains(&n) => n,
                        _ => {
                            return Err(bad(
                                key,
                                value,
                                format!("a whole number from 8 to {MAX_VOLUME_EDGE}"),
                            ))
                        }
                    }
                }
                "size" => {
                    let parsed = value
                        .split_once('x')
                        .and_then(|(w, h)| Some([w.parse::<u32>().ok()?, h.parse::<u32>().ok()?]));
                    view.image_size = match parsed {
                        Some([w, h])
                            if (1..=MAX_IMAGE_EDGE).contains(&w)
                                && (1..=MAX_IMAGE_EDGE).contains(&h) =>
                        {
                            Some([w, h])
                        }
                        _ => {
                            return Err(bad(
                                key,
                                value,
                                format!("WIDTHxHEIGHT, each 1 to {MAX_IMAGE_EDGE}"),
                            ))
                        }
                    }
                }
                "store" => {
                    if !strata_source::wire::is_valid_store_name(value) {
                        return Err(bad(
                            key,
                            value,
                            "a store name of letters, digits, '-', '_' and '.' (as `strata \
                             serve` lists them)",
                        ));
                    }
                    view.store = Some(value.to_string());
                }
                key if crate::overlay::OverlayLink::KEYS.contains(&key) => view
                    .overlay
                    .parse_key(key, value)
                    .map_err(|e| bad(key, value, e.expected))?,
                "capture" => {
                    view.capture = value == "1" || value == "unconverged";
                    view.capture_unconverged = value == "unconverged";
                }
                "bench" => {
                    view.bench_frames = match value.parse::<u32>() {
                        Ok(n) if n <= MAX_BENCH_FRAMES => n,
                        _ => {
                            return Err(bad(
                                key,
                                value,
                                format!("a whole number of frames up to {MAX_BENCH_FRAMES}"),
                            ))
                        }
                    }
                }
                "token" if !value.is_empty() => token = Some(value.to_string()),
                _ => {}
            }
        }
        if let Some(tf) = view.tf.as_mut() {
            tf.name = edited_name(&view.preset);
        }
        Ok(Fragment {
            view,
            token,
            preset_named,
        })
    }
}

impl ViewState {
    /// The fragment that opens this view (no token, whatever the page was opened with).
    pub fn to_fragment(&self) -> String {
        let mut parts = Vec::new();
        if let Some(store) = &self.store {
            parts.push(format!("store={store}"));
        }
        parts.extend(self.overlay.link_parts());
        parts.extend([
            format!("mode={}", mode_name(self.mode)),
            format!("preset={}", self.preset),
        ]);
        // A function beyond the link's bounds (compact_tf::unwritable) is left out: the link
        // then opens the preset, which callers that can say so check first.
        if let Some(Ok(text)) = self.tf.as_ref().map(crate::compact_tf::encode) {
            parts.push(format!("tf={text}"));
        }
        parts.extend([
            format!("az={}", round3(self.azimuth_deg)),
            format!("el={}", round3(self.elevation_deg)),
            format!("zoom={}", round3(self.zoom)),
        ]);
        if self.pan != [0.0, 0.0] {
            parts.push(format!(
                "pan={},{}",
                round3(self.pan[0]),
                round3(self.pan[1])
            ));
        }
        if self.orthographic {
            parts.push("proj=ortho".into());
        }
        match self.layout {
            Layout::Single => parts.push("layout=single".into()),
            Layout::ThreeDOverSlices => parts.push("layout=conventional".into()),
            Layout::FourUp => {}
        }
        if let Some([x, y, z]) = self.cursor {
            parts.push(format!("cursor={},{},{}", round3(x), round3(y), round3(z)));
        }
        if let Some([centre, width]) = self.window {
            parts.push(format!("window={},{}", round3(centre), round3(width)));
        }
        if self.colour_map != ColourMap::Grey {
            parts.push(format!("cmap={}", colour_map_name(self.colour_map)));
        }
        if let Some([yaw, pitch, roll]) = self.oblique.map(|angles| angles.map(round3)) {
            if roll == 0.0 {
                parts.push(format!("oblique={yaw},{pitch}"));
            } else {
                parts.push(format!("oblique={yaw},{pitch},{roll}"));
            }
        }
        if self.frame != 0 {
            parts.push(format!("frame={}", self.frame));
        }
        if self.mode == RenderMode::Isosurface {
            parts.push(format!("iso={}", round3(self.iso_value)));
        }
        if self.crop != CropBox::default() {
            let [i0, j0, k0] = self.crop.min.map(|v| round3(f64::from(v)));
            let [i1, j1, k1] = self.crop.max.map(|v| round3(f64::from(v)));
            parts.push(format!("crop={i0},{j0},{k0},{i1},{j1},{k1}"));
        }
        if self.clip.enabled {
            let axis = CLIP_AXIS_NAMES[self.clip.axis.min(2)];
            let flip = if self.clip.flip { ",flip" } else { "" };
            parts.push(format!("clip={axis},{}{flip}", round3(self.clip.fraction)));
        }
        if !self.shading {
            parts.push("shade=off".into());
        }
        let light = &self.light;
        if !light.headlight {
            let (az, el) = (round3(light.azimuth_deg), round3(light.elevation_deg));
            parts.push(format!("light={az},{el}"));
        }
        match light.shadows {
            ShadowMode::Off => {}
            ShadowMode::Exact => parts.push("shadows=exact".into()),
            ShadowMode::Cache => parts.push("shadows=cache".into()),
        }
        if light.occlusion {
            parts.push(format!("occlusion={}", round3(light.occlusion_radius_mm)));
        }
        let defaults = LightPrefs::default();
        if light.scattering {
            let g = round3(light.scattering_g);
            parts.push(if light.scattering_blend == defaults.scattering_blend {
                format!("scattering={g}")
            } else {
                format!("scattering={g},{}", round3(light.scattering_blend))
            });
        }
        if light.intensity != defaults.intensity {
            parts.push(format!("intensity={}", round3(f64::from(light.intensity))));
        }
        if light.ambient != defaults.ambient {
            parts.push(format!("ambient={}", round3(f64::from(light.ambient))));
        }
        if let Some(epsilon) = self.adaptive_epsilon {
            parts.push(format!(
                "adaptive={}",
                crate::adaptive::format_epsilon(epsilon)
            ));
        }
        if let Some(text) = measurements::to_link_text(&self.measurements) {
            parts.push(format!("m={text}"));
        }
        if self.store.is_none() && self.volume_edge != DEFAULT_VOLUME_EDGE {
            parts.push(format!("volume={}", self.volume_edge));
        }
        if let Some([w, h]) = self.image_size {
            parts.push(format!("size={w}x{h}"));
        }
        format!("#{}", parts.join("&"))
    }

    /// What the 3D view shows: this view without the slice views' crosshair, window and
    /// colour map and measurements, so that paging a slice, windowing it, colouring it or
    /// measuring does not redraw the volume.
    pub fn of_3d_view(&self) -> ViewState {
        ViewState {
            cursor: None,
            window: None,
            measurements: Vec::new(),
            colour_map: ColourMap::Grey,
            oblique: None,
            ..self.clone()
        }
    }

    /// The built-in sample volume's geometry: a cube of 1 mm voxels.
    pub fn geometry(&self) -> VolumeGeometry {
        VolumeGeometry::axis_aligned([self.volume_edge; 3], [1.0; 3])
    }

    /// The built-in sample volume: the render crate's CT phantom (HU in u16 + 1024).
    pub fn sample_volume(&self) -> Result<BrickedVolume, RenderError> {
        ct_phantom(self.geometry(), None, None)
    }

    /// The orbit camera, as `strata render --azimuth --elevation --zoom` and the desktop
    /// viewer build it (the same function: a link opens the same picture in both).
    pub fn camera(&self, geometry: &VolumeGeometry) -> Camera {
        let projection = if self.orthographic {
            // orbit_panned sizes the height from the zoom.
            Projection::Orthographic { height_mm: 1.0 }
        } else {
            Projection::Perspective {
                fov_y_deg: FOV_Y_DEG,
            }
        };
        Camera::orbit_panned(
            geometry,
            self.azimuth_deg,
            self.elevation_deg,
            self.zoom,
            self.pan,
            projection,
        )
    }

    /// The view's transfer function: the edited one if the link carries it, else its preset's
    /// (the default preset if the name is unknown, which [`Fragment::parse`] does not let
    /// through).
    pub fn transfer_function(&self) -> TransferFunction {
        if let Some(tf) = &self.tf {
            return tf.clone();
        }
        TransferFunction::preset(&self.preset)
            .or_else(|| TransferFunction::preset("ct-bone"))
            .unwrap_or_else(|| TransferFunction::new("ramp", &[(0.0, 0.0), (1.0, 1.0)], &[]))
    }

    /// Render settings for a `width` × `height` image of a volume on `geometry`: the
    /// raycaster's defaults with the view's mode, crop box and clip plane, lit by the view's
    /// light through the desktop's own function ([`render_lighting`]): shaded for DVR and
    /// isosurfaces unless the view turns shading off, never for MIP.
    pub fn settings(&self, geometry: &VolumeGeometry, width: u32, height: u32) -> RenderSettings {
        let mut settings = RenderSettings {
            width,
            height,
            mode: self.mode,
            iso_value: self.iso_value,
            crop: self.crop,
            clip_plane: self.clip.plane_if_enabled(geometry),
            ..RenderSettings::default()
        };
        let lit = LitView {
            mode: self.mode,
            // MIP is never lit; the desktop's switch is ignored by render there, a link's
            // settings say so.
            shading: self.shading && self.mode != RenderMode::Mip,
            // The adaptive pass draws none of the light's effects: refused as the desktop
            // refuses them (web/src/adaptive.rs draws the still view).
            adaptive_sampling: self.adaptive_epsilon.is_some(),
        };
        render_lighting(&self.light, lit).apply_to(&mut settings);
        settings
    }
}

/// A colour map's name in a link (`cmap=`): its label in lower case ("hot", "viridis").
pub fn colour_map_name(map: ColourMap) -> &'static str {
    match map {
        ColourMap::Grey => "grey",
        ColourMap::Inverted => "inverted",
        ColourMap::Hot => "hot",
        ColourMap::Turbo => "turbo",
        ColourMap::Viridis => "viridis",
    }
}

/// The name of a function edited from `preset` (the desktop's naming, scene.rs).
pub fn edited_name(preset: &str) -> String {
    format!("{preset} (edited)")
}

/// `crop=I0,J0,K0,I1,J1,K1`: six fractions, each axis's `from` below its `to` by at least
/// [`MIN_CROP_EXTENT`] (what the controls allow).
fn crop_of(key: &str, value: &str) -> Result<CropBox, FragmentError> {
    let expected = "six fractions I0,J0,K0,I1,J1,K1 from 0 to 1, each from below its to";
    let parts: Vec<&str> = value.split(',').collect();
    if parts.len() != 6 {
        return Err(bad(key, value, expected));
    }
    let mut f = [0.0f32; 6];
    for (slot, part) in f.iter_mut().zip(&parts) {
        // The crop box is f32 (the shader's); a link's three decimals are kept to within its
        // rounding.
        *slot = finite(key, part, 0.0..=1.0)? as f32;
    }
    let crop = CropBox {
        min: [f[0], f[1], f[2]],
        max: [f[3], f[4], f[5]],
    };
    if (0..3).any(|a| crop.max[a] - crop.min[a] < MIN_CROP_EXTENT - 1e-6) {
        return Err(bad(key, value, expected));
    }
    Ok(crop)
}

/// `clip=AXIS,FRACTION[,flip]`.
fn clip_of(key: &str, value: &str) -> Result<ClipSettings, FragmentError> {
    let expected = "AXIS,FRACTION[,flip] with AXIS lr, ap or si and FRACTION from 0 to 1";
    let parts: Vec<&str> = value.split(',').collect();
    let (axis, fraction, flip) = match parts[..] {
        [axis, fraction] => (axis, fraction, false),
        [axis, fraction, "flip"] => (axis, fraction, true),
        _ => return Err(bad(key, value, expected)),
    };
    let axis = CLIP_AXIS_NAMES
        .iter()
        .position(|name| *name == axis)
        .ok_or_else(|| bad(key, value, expected))?;
    Ok(ClipSettings {
        enabled: true,
        axis,
        flip,
        fraction: finite(key, fraction, 0.0..=1.0)?,
    })
}

/// Three decimals: enough for a view, short enough for a link.
fn round3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_bad_value_is_quoted_in_part_at_a_character_boundary() {
        let long = format!("{}é{}", "x".repeat(99), "y".repeat(5000));
        let message = Fragment::parse(&format!("#mode={long}"))
            .unwrap_err()
            .to_string();
        assert!(
            message.contains(&format!("`{}… (5101 bytes in all)`", "x".repeat(99))),
            "{message}"
        );
        assert!(message.len() < 200, "{} bytes: {message}", message.len());
        let short = Fragment::parse("#mode=volume").unwrap_err().to_string();
        assert!(short.contains("`volume`"), "{short}");
    }

    #[test]
    fn a_bad_overlay_value_names_its_key() {
        for (key, value) in [
            ("overlay", "../etc"),
            ("overlay_kind", "pet"),
            ("overlay_opacity", "2"),
            ("overlay_hidden", "1,x"),
        ] {
            let e = Fragment::parse(&format!("#overlay=labels&{key}={value}"))
                .expect_err("a bad overlay value");
            assert!(e.to_string().contains(&format!("`{key}`")), "{key}: {e}");
        }
    }

    #[test]
    fn a_view_survives_its_fragment() {
        let view = ViewState {
            mode: RenderMode::Isosurface,
            preset: "ct-soft-tissue".into(),
            tf: None,
            azimuth_deg: -42.5,
            elevation_deg: 12.25,
            zoom: 1.75,
            pan: [0.125, -0.5],
            orthographic: true,
            layout: Layout::Single,
            cursor: Some([10.5, 20.0, 3.25]),
            window: Some([40.0, 400.0]),
            colour_map: ColourMap::Viridis,
            oblique: Some([30.5, -12.25, 7.125]),
            frame: 3,
            iso_value: 250.0,
            crop: CropBox {
                min: [0.125, 0.0, 0.25],
                max: [1.0, 0.5, 0.875],
            },
            clip: ClipSettings {
                enabled: true,
                axis: 2,
                flip: true,
                fraction: 0.375,
            },
            shading: false,
            light: LightPrefs {
                headlight: false,
                azimuth_deg: -45.5,
                elevation_deg: 30.25,
                shadows: ShadowMode::Cache,
                occlusion: true,
                occlusion_radius_mm: 6.5,
                scattering: true,
                scattering_g: -0.25,
                scattering_blend: 0.75,
                intensity: 1.375,
                ambient: 0.25,
                ..LightPrefs::default()
            },
            measurements: measurements::from_link_text("r:1.25,2,3,4,5.5,3;ea:1,2,3,4,5,3")
                .expect("measurements"),
            volume_edge: 64,
            store: None,
            overlay: crate::overlay::OverlayLink {
                name: Some("labels".into()),
                kind: Some(crate::overlay::OverlayKind::Continuous),
                opacity: 0.75,
                hidden_labels: [1, 3].into_iter().collect(),
                colour_map: Some(ColourMap::Turbo),
                range: Some((-0.25, 1234.5)),
                threshold: Some(0.1),
            },
            image_size: Some([160, 120]),
            capture: false,
            capture_unconverged: false,
            bench_frames: 0,
            adaptive_epsilon: Some(0.0025),
        };
        let parsed = Fragment::parse(&view.to_fragment()).expect("own fragment parses");
        assert_eq!(parsed.view, view);
        assert_eq!(parsed.token, None);
        let served = ViewState {
            store: Some("head-ct.v2".into()),
            volume_edge: DEFAULT_VOLUME_EDGE,
            ..view
        };
        let written = served.to_fragment();
        assert!(written.starts_with("#store=head-ct.v2&"), "{written}");
        assert_eq!(Fragment::parse(&written).expect("parses").view, served);
        // Every layout survives too (the default, four-up, is left out of the link).
        for layout in [Layout::Single, Layout::FourUp, Layout::ThreeDOverSlices] {
            let laid_out = ViewState {
                layout,
                ..served.clone()
            };
            let written = laid_out.to_fragment();
            assert_eq!(
                Fragment::parse(&written).expect("parses").view.layout,
                layout,
                "{written}"
            );
        }
    }

    #[test]
    fn the_token_is_read_and_never_written_back() {
        let parsed = Fragment::parse("#mode=mip&token=s3cr%65t&az=10").expect("parses");
        assert_eq!(parsed.token.as_deref(), Some("s3cret"));
        assert_eq!(parsed.view.mode, RenderMode::Mip);
        let written = parsed.view.to_fragment();
        assert!(!written.contains("token"), "{written}");
        assert!(!written.contains("s3cret"), "{written}");
    }

    #[test]
    fn a_bad_value_names_its_key_and_unknown_keys_are_ignored() {
        let e = Fragment::parse("#mode=volume").expect_err("unknown mode");
        assert!(e.to_string().contains("`mode`"), "{e}");
        let e = Fragment::parse("#el=91").expect_err("elevation past the pole");
        assert!(e.to_string().contains("`el`"), "{e}");
        let e = Fragment::parse("#zoom=NaN").expect_err("NaN zoom");
        assert!(e.to_string().contains("`zoom`"), "{e}");
        let e = Fragment::parse("#volume=100000").expect_err("huge volume");
        assert!(e.to_string().contains("256"), "{e}");
        let e = Fragment::parse("#pan=0.1").expect_err("one pan coordinate");
        assert!(e.to_string().contains("`pan`"), "{e}");
        let e = Fragment::parse("#pan=0.1,inf").expect_err("infinite pan");
        assert!(e.to_string().contains("`pan`"), "{e}");
        let e = Fragment::parse("#proj=fisheye").expect_err("unknown projection");
        assert!(e.to_string().contains("`proj`"), "{e}");
        let e = Fragment::parse("#size=0x5").expect_err("empty image");
        assert!(e.to_string().contains("`size`"), "{e}");
        for name in ["../etc", "a/b", ".hidden", ""] {
            let e = Fragment::parse(&format!("#store={name}")).expect_err("bad store name");
            assert!(e.to_string().contains("`store`"), "{name}: {e}");
        }
        let e = Fragment::parse("#preset=nope").expect_err("unknown preset");
        assert!(e.to_string().contains("ct-bone"), "{e}");
        let e = Fragment::parse("#cursor=1,2").expect_err("two coordinates");
        assert!(e.to_string().contains("`cursor`"), "{e}");
        let e = Fragment::parse("#cursor=1,2,-3").expect_err("negative index");
        assert!(e.to_string().contains("`cursor`"), "{e}");
        let e = Fragment::parse("#window=40,0").expect_err("empty window");
        assert!(e.to_string().contains("`window`"), "{e}");
        let e = Fragment::parse("#layout=quad").expect_err("unknown layout");
        assert!(e.to_string().contains("`layout`"), "{e}");
        let e = Fragment::parse("#cmap=rainbow").expect_err("unknown colour map");
        assert!(e.to_string().contains("`cmap`"), "{e}");
        assert!(e.to_string().contains("hot"), "{e}");
        let ok = Fragment::parse("#colour=hot&mode=dvr").expect("unknown key ignored");
        assert_eq!(ok.view, ViewState::default());
        assert_eq!(
            Fragment::parse("").expect("empty").view,
            ViewState::default()
        );
    }

    #[test]
    fn an_edited_transfer_function_survives_its_fragment() {
        let mut tf = TransferFunction::preset("ct-vessels").expect("preset");
        // As the editor leaves a dragged point: a value and an opacity from f32 pixel maths.
        tf.opacity[2].value = -1024.0 + f64::from(0.3101_f32) * 4095.0;
        tf.opacity[2].opacity = f64::from(0.4873_f32);
        tf.color[1].rgb = [0.91_f32, 0.2, 0.05].map(f64::from);
        tf.name = edited_name("ct-vessels");
        let view = ViewState {
            preset: "ct-vessels".into(),
            tf: Some(tf.clone()),
            store: Some("head-ct".into()),
            ..ViewState::default()
        };
        let written = view.to_fragment();
        assert!(written.contains("&preset=ct-vessels&tf="), "{written}");
        let parsed = Fragment::parse(&written).expect("own fragment parses").view;
        assert_eq!(parsed, view);
        assert_eq!(parsed.transfer_function(), tf);
        // The key's order does not matter, and a browser's percent-encoding is undone.
        let text = crate::compact_tf::encode(&tf).expect("writes");
        let reordered = format!("#tf={}&preset=ct-vessels", text.replace(',', "%2C"));
        assert_eq!(
            Fragment::parse(&reordered).expect("parses").view.tf,
            Some(tf)
        );
        // Unedited: the preset alone.
        let plain = ViewState::default().to_fragment();
        assert!(!plain.contains("tf="), "{plain}");
        assert_eq!(
            ViewState::default().transfer_function(),
            TransferFunction::preset("ct-bone").expect("preset")
        );
    }

    #[test]
    fn a_bad_or_oversized_tf_names_its_key() {
        for value in ["0,0_1,2~", "0,0", "1,0_0,1~", "~", "0,x~0,1,1,1"] {
            let e = Fragment::parse(&format!("#tf={value}")).expect_err(value);
            assert!(e.to_string().contains("`tf`"), "{value}: {e}");
        }
        let huge = format!("#tf=0,0_1,1~{}", "0,1,1,1_".repeat(3000));
        let e = Fragment::parse(&huge).expect_err("oversized");
        let message = e.to_string();
        assert!(message.contains("`tf`"), "{message}");
        assert!(
            message.len() < 400,
            "the message quotes the value's start only"
        );
        // A function beyond the bounds is not written (the link opens the preset instead).
        let many: Vec<(f64, f64)> = (0..=crate::compact_tf::MAX_TF_STOPS)
            .map(|i| (i as f64, 0.5))
            .collect();
        let view = ViewState {
            tf: Some(TransferFunction::new("x", &many, &[])),
            ..ViewState::default()
        };
        let written = view.to_fragment();
        assert!(!written.contains("tf="), "{written}");
        assert!(Fragment::parse(&written).is_ok());
    }

    #[test]
    fn settings_follow_the_mode() {
        let mut view = ViewState::default();
        let geometry = view.geometry();
        assert!(view.settings(&geometry, 8, 8).shading.is_some());
        view.mode = RenderMode::Mip;
        let s = view.settings(&geometry, 64, 32);
        assert!(s.shading.is_none());
        assert_eq!((s.width, s.height, s.mode), (64, 32, RenderMode::Mip));
        assert!(s.validate().is_ok());
    }

    #[test]
    fn crop_clip_and_shading_reach_the_settings() {
        let view = Fragment::parse("#mode=dvr&crop=0,0.25,0,1,1,0.5&clip=lr,0.75,flip&shade=off")
            .expect("parses")
            .view;
        let geometry = VolumeGeometry::axis_aligned([40, 50, 60], [1.0, 2.0, 0.5]);
        let s = view.settings(&geometry, 32, 32);
        assert_eq!(s.crop.min, [0.0, 0.25, 0.0]);
        assert_eq!(s.crop.max, [1.0, 1.0, 0.5]);
        assert_eq!(s.clip_plane, Some(view.clip.plane(&geometry)));
        assert_eq!(s.clip_plane.map(|p| p.normal), Some([-1.0, 0.0, 0.0]));
        assert!(s.shading.is_none(), "shade=off");
        assert!(s.validate().is_ok());
        // Without the keys: the whole volume, no plane, shaded.
        let plain = ViewState::default().settings(&geometry, 32, 32);
        assert_eq!(ViewState::default().colour_map, ColourMap::Grey);
        assert_eq!(plain.crop, CropBox::default());
        assert_eq!(plain.clip_plane, None);
        assert!(plain.shading.is_some());
        let written = ViewState::default().to_fragment();
        for key in ["crop=", "clip=", "shade=", "cmap="] {
            assert!(!written.contains(key), "{written}");
        }
    }

    #[test]
    fn the_light_reaches_the_settings_as_the_desktop_lights_it() {
        let view = Fragment::parse("#mode=dvr&shade=off&light=30,-20&shadows=exact&occlusion=3")
            .expect("parses")
            .view;
        let geometry = view.geometry();
        let s = view.settings(&geometry, 32, 32);
        let desktop = render_lighting(
            &view.light,
            LitView {
                mode: RenderMode::Dvr,
                shading: false,
                adaptive_sampling: false,
            },
        );
        assert_eq!(s.light, desktop.light);
        assert_eq!(
            s.light.direction,
            strata_render::LightDirection::Camera(view.light.camera_direction())
        );
        assert_eq!(s.shadows.mode, ShadowMode::Exact);
        assert_eq!(s.occlusion.map(|o| o.radius_mm), Some(3.0));
        assert_eq!(s.scattering, None);
        assert!(
            s.shading.is_some(),
            "effects turn shading on, as on the desktop"
        );
        assert!(s.validate().is_ok());
        // Cache shadows with the headlight are drawn exact, as the desktop draws them.
        let cached = Fragment::parse("#shadows=cache").expect("parses").view;
        assert_eq!(
            cached.settings(&geometry, 8, 8).shadows.mode,
            ShadowMode::Exact
        );
        // MIP is never lit, whatever the link asks.
        let mip = Fragment::parse("#mode=mip&shadows=exact&scattering=0.5")
            .expect("parses")
            .view
            .settings(&geometry, 8, 8);
        assert_eq!((mip.shading, mip.shadows.mode), (None, ShadowMode::Off));
        // The default light writes nothing and draws render's default light.
        let plain = ViewState::default();
        assert_eq!(
            plain.settings(&geometry, 8, 8).light,
            strata_render::KeyLight::default()
        );
        let written = plain.to_fragment();
        for key in [
            "light=",
            "shadows=",
            "occlusion=",
            "scattering=",
            "intensity=",
            "ambient=",
        ] {
            assert!(!written.contains(key), "{written}");
        }
        // Intensity and ambient reach the settings as the desktop's light gives them.
        let lit = Fragment::parse("#intensity=1.5&ambient=0.05")
            .expect("parses")
            .view;
        assert_eq!((lit.light.intensity, lit.light.ambient), (1.5, 0.05));
        let s = lit.settings(&geometry, 8, 8);
        assert_eq!(s.light.intensity, 1.5);
        assert_eq!(s.shading.map(|shading| shading.ambient), Some(0.05));
        let written = lit.to_fragment();
        assert!(
            written.contains("&intensity=1.5") && written.contains("&ambient=0.05"),
            "{written}"
        );
    }

    /// The oblique view is in a link only while shown (`oblique=` absent: not shown), its
    /// angles rounded as the link rounds, the roll written only when there is one.
    #[test]
    fn the_oblique_view_is_in_the_link_only_while_shown() {
        let plain = ViewState::default();
        assert!(
            !plain.to_fragment().contains("oblique"),
            "{}",
            plain.to_fragment()
        );
        assert_eq!(
            Fragment::parse("#mode=mip").expect("parses").view.oblique,
            None
        );
        let axial = ViewState {
            oblique: Some([0.0, 0.0, 0.0]),
            ..ViewState::default()
        };
        let written = axial.to_fragment();
        assert!(written.split('&').any(|p| p == "oblique=0,0"), "{written}");
        assert_eq!(Fragment::parse(&written).expect("parses").view, axial);
        let tilted = Fragment::parse("#oblique=30,-20.5").expect("two angles");
        assert_eq!(tilted.view.oblique, Some([30.0, -20.5, 0.0]));
        let rolled = ViewState {
            oblique: Some([-170.12345, 89.9996, 12.0004]),
            ..ViewState::default()
        };
        let written = rolled.to_fragment();
        assert!(
            written.split('&').any(|p| p == "oblique=-170.123,90,12"),
            "{written}"
        );
        assert_eq!(
            Fragment::parse(&written).expect("parses").view.oblique,
            Some([-170.123, 90.0, 12.0])
        );
        // Turning the oblique view does not redraw the 3D view.
        assert_eq!(rolled.of_3d_view(), plain.of_3d_view());
    }

    #[test]
    fn a_bad_crop_clip_or_shade_names_its_key() {
        for (key, value) in [
            ("crop", "0,0,0,1,1"),
            ("crop", "0,0,0,1,1,1.5"),
            ("crop", "0.5,0,0,0.5,1,1"),
            ("crop", "0.6,0,0,0.4,1,1"),
            ("clip", "up,0.5"),
            ("clip", "ap"),
            ("clip", "ap,2"),
            ("clip", "ap,0.5,flop"),
            ("shade", "maybe"),
            ("light", "30"),
            ("light", "30,95"),
            ("light", "abc,10"),
            ("shadows", "soft"),
            ("occlusion", "0.5"),
            ("occlusion", "mm"),
            ("scattering", "1.5"),
            ("scattering", "0.5,2"),
            ("scattering", "0.5,"),
            ("intensity", "-1"),
            ("intensity", "bright"),
            ("ambient", "1.5"),
            ("oblique", "30"),
            ("oblique", "30,95"),
            ("oblique", "30,10,0,5"),
            ("oblique", "north,10"),
            ("oblique", "200,0,0"),
            ("frame", "-1"),
            ("frame", "two"),
            ("frame", "1.5"),
            ("frame", "99999999999"),
        ] {
            let e = Fragment::parse(&format!("#{key}={value}")).expect_err(value);
            assert!(
                e.to_string().contains(&format!("`{key}`")),
                "{key}={value}: {e}"
            );
        }
    }

    /// A 4-D store's frame is in the link only past frame 0, read back as written.
    #[test]
    fn the_frame_is_in_the_link_only_past_frame_0() {
        let plain = ViewState::default().to_fragment();
        assert!(!plain.contains("frame"), "{plain}");
        let view = ViewState {
            frame: 2,
            ..ViewState::default()
        };
        let written = view.to_fragment();
        assert!(written.split('&').any(|p| p == "frame=2"), "{written}");
        assert_eq!(Fragment::parse(&written).expect("parses").view.frame, 2);
        assert_eq!(
            Fragment::parse("#frame=0").expect("parses").view.frame,
            0,
            "frame=0 is the default, accepted"
        );
    }

    /// `m=` carries the slices' measurements: written only when there are some, read back
    /// exactly at its two decimals (the measurements module's format), and a bad value names
    /// the key and the measurement at fault.
    #[test]
    fn measurements_travel_in_m_and_a_bad_one_names_its_key() {
        let plain = ViewState::default().to_fragment();
        assert!(!plain.contains("&m="), "{plain}");
        let text = "r:10.5,20.25,3,40,20.25,3;a:1,0,2,0,0,2,0,1,2;bc:5,9,5,12,9,18";
        let view = Fragment::parse(&format!("#mode=mip&m={text}"))
            .expect("a link with measurements")
            .view;
        assert_eq!(view.measurements.len(), 3);
        let written = view.to_fragment();
        assert!(written.contains(&format!("&m={text}")), "{written}");
        assert_eq!(Fragment::parse(&written).expect("parses").view, view);
        assert!(view.of_3d_view().measurements.is_empty());
        for value in ["r:1,2", "q:1,2,3,4,5,6", "r:1,2,3,4,5,x"] {
            let e = Fragment::parse(&format!("#m={value}")).expect_err(value);
            let message = e.to_string();
            assert!(
                message.contains("`m`") && message.contains("measurement 0"),
                "{message}"
            );
        }
    }
}
