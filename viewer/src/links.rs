//! Links to a view of a served store (issue 39, "shareable views"). The browser viewer's
//! address is `http(s)://HOST:PORT/#store=NAME&mode=…&az=…` (strata_viewer_ui::view_state); the
//! desktop viewer copies that link for the served store it streams, and opens one: the store
//! from the server at the link's origin, the view from its fragment. The same camera function
//! builds both viewers' pictures ([`strata_render::Camera::orbit_panned`]), so a link opens the
//! same view in either.
//!
//! A link's `token=` is used for that one connection and kept in memory only: it is never
//! written back into a copied link (links are shared, tokens must not be), logged, or saved.

use strata_render::{CropBox, RenderMode, TransferFunction};
use strata_slices::ColourMap;
use strata_viewer_ui::crop_clip::ClipSettings;
use strata_viewer_ui::lighting::LightPrefs;
use strata_viewer_ui::measurements::Measurement;
use strata_viewer_ui::view_state::{Fragment, Layout as LinkLayout, ViewState};

use super::preferences::Layout;
use super::view3d::OrbitCamera;

/// A link's store and view.
#[derive(Clone, Debug, PartialEq)]
pub struct SharedLink {
    /// `http(s)://HOST:PORT/v1/stores/NAME`, as `strata view` and the Open dialog take it.
    pub store_url: String,
    pub view: ViewState,
    pub token: Option<String>,
}

/// What the desktop's 3D view shows, as a link describes it.
#[derive(Clone, Debug, PartialEq)]
pub struct DesktopView {
    pub orbit: OrbitCamera,
    pub mode: RenderMode,
    pub preset: String,
    /// The transfer function as edited (or loaded from a file) when it is not the preset's:
    /// the link's `tf=`. None: the preset as it is.
    pub tf: Option<TransferFunction>,
    /// In the volume's physical unit.
    pub iso_value: f64,
    /// The 3D view alone, or with the slices (the page's 2×2; the desktop's conventional
    /// 3D + 1×3 is shared as the 2×2, its nearest in the page).
    pub layout: Layout,
    /// The slices' crosshair (level-0 voxel index) and window (centre, width; physical unit);
    /// None where a link leaves them to the store.
    pub cursor: Option<[f64; 3]>,
    pub window: Option<[f64; 2]>,
    /// The slices' colour map (`cmap=`).
    pub colour_map: ColourMap,
    /// The cut: crop box and clip plane, as the rendering panel sets them.
    pub crop: CropBox,
    pub clip: ClipSettings,
    /// The rendering panel's "Shading" switch.
    pub shading: bool,
    /// The oblique view, shown and turned `[yaw, pitch, roll]` degrees off axial (the link's
    /// `oblique=`, strata_slices' `ObliquePlane::orientation_deg`); None: not shown.
    pub oblique: Option<[f64; 3]>,
    /// The frame of a 4-D volume every view shows (the link's `frame=`; 0 for a 3-D one).
    pub frame: u32,
    /// The rendering panel's light. A link carries its direction, shadows, occlusion radius,
    /// scattering asymmetry and blend, intensity and ambient (view_state.rs); a light opened
    /// from a link has the shadow step at its default, as the browser draws it.
    pub light: LightPrefs,
    /// The slices' measurements (the link's `m=`): points at two decimals; a region's
    /// statistics are computed again from the slice when it is shown.
    pub measurements: Vec<Measurement>,
    /// Adaptive sampling of the still view with this ε (the link's `adaptive=`, the Rendering
    /// panel's switch and slider); None: off.
    pub adaptive_epsilon: Option<f64>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LinkError {
    #[error("{link}: the link names no store (`#store=NAME`); open the page's store list and copy a store's link")]
    NoStore { link: String },
    #[error("{link}: {source}")]
    Fragment {
        link: String,
        source: strata_viewer_ui::view_state::FragmentError,
    },
}

/// The server's origin (`http(s)://HOST[:PORT]`) and the store's name of a served store's URL
/// (`…/v1/stores/NAME`); None for anything else (a local store, an OME-Zarr).
pub fn served_store(store_url: &str) -> Option<(&str, &str)> {
    let after_scheme = store_url
        .strip_prefix("http://")
        .or_else(|| store_url.strip_prefix("https://"))?;
    let host_end = after_scheme.find('/')?;
    let origin = &store_url[..store_url.len() - after_scheme.len() + host_end];
    let name = after_scheme[host_end..]
        .strip_prefix("/v1/stores/")?
        .trim_end_matches('/');
    strata_source::wire::is_valid_store_name(name).then_some((origin, name))
}

/// True when `text` is a viewer link (an http(s) address with a `#` fragment), not a store's URL.
pub fn is_link(text: &str) -> bool {
    (text.starts_with("http://") || text.starts_with("https://")) && text.contains('#')
}

/// Reads a viewer link; the fragment must name a store.
pub fn parse_link(link: &str) -> Result<SharedLink, LinkError> {
    let link = link.trim();
    let (address, fragment) = link.split_once('#').unwrap_or((link, ""));
    let Fragment { view, token, .. } = Fragment::parse(fragment).map_err(|source| {
        // The error names the key and its value; a token's value is never echoed: a bad
        // token key cannot occur (any non-empty value is taken).
        LinkError::Fragment {
            link: without_token(link),
            source,
        }
    })?;
    let Some(store) = view.store.clone() else {
        return Err(LinkError::NoStore {
            link: without_token(link),
        });
    };
    let after_scheme = address
        .strip_prefix("http://")
        .or_else(|| address.strip_prefix("https://"))
        .unwrap_or(address);
    let host_len = after_scheme.find('/').unwrap_or(after_scheme.len());
    let origin = &address[..address.len() - after_scheme.len() + host_len];
    Ok(SharedLink {
        store_url: format!("{origin}/v1/stores/{store}"),
        view,
        token,
    })
}

/// `link` with any `token=` value blanked, for messages.
fn without_token(link: &str) -> String {
    match link.split_once('#') {
        Some((address, fragment)) => {
            let kept: Vec<&str> = fragment
                .split('&')
                .filter(|pair| !pair.starts_with("token="))
                .collect();
            format!("{address}#{}", kept.join("&"))
        }
        None => link.to_string(),
    }
}

/// The browser viewer's link to `view` of the served store at `store_url`; None when the
/// volume is not a served store (a link could not open it elsewhere).
pub fn link_for(store_url: &str, view: &DesktopView) -> Option<String> {
    let (origin, name) = served_store(store_url)?;
    let state = ViewState {
        mode: view.mode,
        preset: view.preset.clone(),
        tf: view.tf.clone(),
        azimuth_deg: view.orbit.azimuth_deg,
        elevation_deg: view.orbit.elevation_deg,
        zoom: view.orbit.zoom,
        pan: view.orbit.pan,
        orthographic: view.orbit.orthographic,
        iso_value: view.iso_value,
        layout: match view.layout {
            Layout::Single => LinkLayout::Single,
            Layout::ThreeDOverSlices => LinkLayout::ThreeDOverSlices,
            Layout::TwoByTwo => LinkLayout::FourUp,
        },
        cursor: view.cursor,
        window: view.window,
        colour_map: view.colour_map,
        crop: view.crop,
        clip: view.clip,
        shading: view.shading,
        light: view.light,
        measurements: view.measurements.clone(),
        oblique: view.oblique,
        frame: view.frame,
        adaptive_epsilon: view.adaptive_epsilon,
        store: Some(name.to_string()),
        ..ViewState::default()
    };
    Some(format!("{origin}/{}", state.to_fragment()))
}

/// The desktop view a link's view describes.
pub fn desktop_view(view: &ViewState) -> DesktopView {
    DesktopView {
        orbit: OrbitCamera {
            azimuth_deg: view.azimuth_deg,
            elevation_deg: view.elevation_deg,
            zoom: view.zoom,
            pan: view.pan,
            orthographic: view.orthographic,
        },
        mode: view.mode,
        preset: view.preset.clone(),
        tf: view.tf.clone(),
        iso_value: view.iso_value,
        layout: match view.layout {
            LinkLayout::Single => Layout::Single,
            LinkLayout::FourUp => Layout::TwoByTwo,
            LinkLayout::ThreeDOverSlices => Layout::ThreeDOverSlices,
        },
        cursor: view.cursor,
        window: view.window,
        colour_map: view.colour_map,
        crop: view.crop,
        clip: view.clip,
        shading: view.shading,
        light: view.light,
        measurements: view.measurements.clone(),
        oblique: view.oblique,
        frame: view.frame,
        adaptive_epsilon: view.adaptive_epsilon,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_render::{ShadowMode, VolumeGeometry};
    use strata_slices::SliceView;
    use strata_viewer_ui::measurements::{RoiStats, Shape};

    fn desktop() -> DesktopView {
        DesktopView {
            orbit: OrbitCamera {
                azimuth_deg: -37.5,
                elevation_deg: 22.125,
                zoom: 1.6,
                pan: [0.25, -0.125],
                orthographic: true,
            },
            mode: RenderMode::Isosurface,
            preset: "ct-soft-tissue".into(),
            tf: None,
            iso_value: 150.5,
            layout: Layout::Single,
            cursor: Some([12.0, 30.5, 7.0]),
            window: Some([-600.0, 1500.0]),
            colour_map: ColourMap::Hot,
            crop: CropBox {
                min: [0.25, 0.0, 0.125],
                max: [0.75, 1.0, 1.0],
            },
            clip: ClipSettings {
                enabled: true,
                axis: 0,
                flip: false,
                fraction: 0.625,
            },
            shading: false,
            light: LightPrefs {
                headlight: false,
                azimuth_deg: 62.5,
                elevation_deg: -15.125,
                shadows: ShadowMode::Exact,
                occlusion: true,
                occlusion_radius_mm: 7.5,
                ..LightPrefs::default()
            },
            // As read from a link: ids in order, regions without statistics yet.
            measurements: vec![
                Measurement {
                    id: 0,
                    shape: Shape::Distance {
                        a: [3.25, 4.0, 7.0],
                        b: [20.5, 31.75, 7.0],
                    },
                },
                Measurement {
                    id: 1,
                    shape: Shape::Roi {
                        view: SliceView::Axial,
                        ellipse: true,
                        a: [10.0, 12.0, 7.0],
                        b: [18.0, 20.5, 7.0],
                        stats: None,
                    },
                },
            ],
            oblique: Some([25.5, -10.25, 3.125]),
            frame: 2,
            adaptive_epsilon: Some(0.0025),
        }
    }

    /// The desktop's measurements travel in its link (`m=`) and come back as they went, a
    /// region's statistics left for the opening viewer to compute from its slice.
    #[test]
    fn a_links_measurements_are_the_desktops_and_statistics_are_not_written() {
        let store_url = "http://127.0.0.1:8080/v1/stores/head-ct";
        let mut view = desktop();
        if let Shape::Roi { stats, .. } = &mut view.measurements[1].shape {
            *stats = Some(RoiStats {
                mean: 40.0,
                sd: 2.0,
                min: 35.0,
                max: 45.0,
                voxels: 60,
                area_mm2: 50.0,
                level: 0,
            });
        }
        let link = link_for(store_url, &view).expect("link");
        assert!(
            link.contains("&m=r:3.25,4,7,20.5,31.75,7;ea:10,12,7,18,20.5,7"),
            "{link}"
        );
        let opened = desktop_view(&parse_link(&link).expect("parses").view);
        assert_eq!(opened.measurements, desktop().measurements);
        let none = DesktopView {
            measurements: Vec::new(),
            ..desktop()
        };
        assert!(!link_for(store_url, &none).expect("link").contains("&m="));
    }

    #[test]
    fn a_served_stores_url_gives_its_origin_and_name() {
        assert_eq!(
            served_store("http://127.0.0.1:8080/v1/stores/head-ct.v2"),
            Some(("http://127.0.0.1:8080", "head-ct.v2"))
        );
        assert_eq!(
            served_store("https://lab.example:443/v1/stores/abc/"),
            Some(("https://lab.example:443", "abc"))
        );
        for other in [
            "/data/stores/head",
            "s3://bucket/x.ome.zarr",
            "https://lab.example/x.ome.zarr",
            "http://h:1/v1/stores/../etc",
            "http://h:1",
        ] {
            assert_eq!(served_store(other), None, "{other}");
        }
    }

    #[test]
    fn a_copied_link_opens_the_same_store_and_camera() {
        let store_url = "http://127.0.0.1:8080/v1/stores/head-ct";
        let link = link_for(store_url, &desktop()).expect("a served store has a link");
        assert!(
            link.starts_with("http://127.0.0.1:8080/#store=head-ct&"),
            "{link}"
        );
        let opened = parse_link(&link).expect("own link parses");
        assert_eq!(opened.store_url, store_url);
        assert_eq!(opened.token, None);
        let back = desktop_view(&opened.view);
        assert_eq!(back, desktop());
        assert!(link.contains("&cmap=hot"), "{link}");
        assert!(link.contains("&adaptive=0.0025"), "{link}");
        // The same picture: the browser's camera of the link equals the desktop's.
        let geometry = VolumeGeometry::axis_aligned([96, 80, 64], [0.8, 0.8, 1.5]);
        assert_eq!(
            opened.view.camera(&geometry),
            desktop().orbit.camera(&geometry)
        );
        let perspective = DesktopView {
            orbit: OrbitCamera::default(),
            ..desktop()
        };
        let link = link_for(store_url, &perspective).expect("link");
        let view = parse_link(&link).expect("parses").view;
        assert_eq!(view.camera(&geometry), perspective.orbit.camera(&geometry));
        assert_eq!(link_for("/data/stores/head", &desktop()), None);
    }

    #[test]
    fn a_links_light_is_the_desktops_light_and_the_headlight_writes_nothing() {
        let store_url = "http://127.0.0.1:8080/v1/stores/head-ct";
        // Adaptive sampling off: with it on, both viewers refuse the light's effects.
        let unadaptive = DesktopView {
            adaptive_epsilon: None,
            ..desktop()
        };
        let link = link_for(store_url, &unadaptive).expect("link");
        for key in ["light=62.5,-15.125", "shadows=exact", "occlusion=7.5"] {
            assert!(link.contains(key), "{key} in {link}");
        }
        assert!(!link.contains("scattering="), "{link}");
        // The same lighting: the link's settings are the desktop's preferences' settings.
        let opened = parse_link(&link).expect("parses").view;
        let geometry = VolumeGeometry::axis_aligned([32, 32, 32], [1.0, 1.0, 1.0]);
        let prefs = crate::preferences::Preferences {
            mode: RenderMode::Dvr,
            shading: false,
            light: desktop().light,
            ..Default::default()
        };
        let from_link = ViewState {
            mode: RenderMode::Dvr,
            ..opened
        }
        .settings(&geometry, 16, 16);
        let mut from_desktop = strata_render::RenderSettings::default();
        crate::preferences::render_lighting(&prefs).apply_to(&mut from_desktop);
        assert_eq!(from_link.light, from_desktop.light);
        assert_eq!(from_link.shadows, from_desktop.shadows);
        assert_eq!(from_link.occlusion, from_desktop.occlusion);
        assert_eq!(from_link.shading, from_desktop.shading);
        let headlit = DesktopView {
            light: LightPrefs::default(),
            ..desktop()
        };
        let link = link_for(store_url, &headlit).expect("link");
        for key in ["light=", "shadows=", "occlusion=", "scattering="] {
            assert!(!link.contains(key), "{key} in {link}");
        }
        assert_eq!(
            desktop_view(&parse_link(&link).expect("parses").view),
            headlit
        );
    }

    #[test]
    fn an_edited_transfer_function_travels_with_the_link() {
        let mut tf = TransferFunction::preset("ct-soft-tissue").expect("preset");
        tf.opacity[3].opacity = f64::from(0.6183_f32);
        tf.color[2].rgb = [0.25_f32, 0.5, 0.8725].map(f64::from);
        tf.name = strata_viewer_ui::view_state::edited_name("ct-soft-tissue");
        let edited = DesktopView {
            tf: Some(tf),
            ..desktop()
        };
        let store_url = "http://127.0.0.1:8080/v1/stores/head-ct";
        let link = link_for(store_url, &edited).expect("link");
        assert!(link.contains("&tf="), "{link}");
        let opened = parse_link(&link).expect("own link parses");
        assert_eq!(desktop_view(&opened.view), edited);
        let plain = link_for(store_url, &desktop()).expect("link");
        assert!(!plain.contains("tf="), "{plain}");
    }

    /// The oblique view travels with a link while shown: its angles turn back into the plane
    /// the desktop showed (strata_slices' orientation angles), and a link without it opens
    /// without it.
    #[test]
    fn the_oblique_view_travels_with_the_link_while_shown() {
        use glam::DVec3;
        use strata_slices::oblique::ObliquePlane;
        let store_url = "http://127.0.0.1:8080/v1/stores/head-ct";
        let shown = ObliquePlane::axial(DVec3::ZERO, 300.0).turned_by_drag(40.0, -25.0);
        let view = DesktopView {
            oblique: Some(shown.orientation_deg()),
            ..desktop()
        };
        let link = link_for(store_url, &view).expect("link");
        assert!(link.contains("&oblique="), "{link}");
        let angles = desktop_view(&parse_link(&link).expect("parses").view)
            .oblique
            .expect("the oblique view is shown");
        let opened = ObliquePlane::from_orientation_deg(DVec3::ZERO, 300.0, angles);
        // The link's three decimals of a degree: 1e-3° is 1.7e-5 rad.
        assert!(
            (opened.right - shown.right).length() < 1e-4,
            "{opened:?} {shown:?}"
        );
        assert!(
            (opened.down - shown.down).length() < 1e-4,
            "{opened:?} {shown:?}"
        );
        let hidden = DesktopView {
            oblique: None,
            ..desktop()
        };
        let link = link_for(store_url, &hidden).expect("link");
        assert!(!link.contains("oblique"), "{link}");
        assert_eq!(
            desktop_view(&parse_link(&link).expect("parses").view).oblique,
            None
        );
    }

    #[test]
    fn a_links_token_is_read_but_never_copied_or_echoed() {
        let link = "https://lab.example:8443/#store=abc&token=s3cret-s3cret-1&mode=mip";
        assert!(is_link(link));
        assert!(!is_link("https://lab.example:8443/v1/stores/abc"));
        let opened = parse_link(link).expect("parses");
        assert_eq!(opened.token.as_deref(), Some("s3cret-s3cret-1"));
        assert_eq!(opened.store_url, "https://lab.example:8443/v1/stores/abc");
        assert_eq!(opened.view.mode, RenderMode::Mip);
        let copied = link_for(&opened.store_url, &desktop_view(&opened.view)).expect("link");
        assert!(!copied.contains("s3cret"), "{copied}");
        let e = parse_link("http://h:1/#token=s3cret-s3cret-1&mode=dvr").expect_err("no store");
        assert!(matches!(e, LinkError::NoStore { .. }));
        assert!(!e.to_string().contains("s3cret"), "{e}");
        let e = parse_link("http://h:1/#token=s3cret-s3cret-1&store=a&az=north")
            .expect_err("bad azimuth");
        assert!(e.to_string().contains("`az`"), "{e}");
        assert!(!e.to_string().contains("s3cret"), "{e}");
    }
}
