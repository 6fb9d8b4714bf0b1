//! The OME-Zarr 0.5 multiscales document, Strata's own `strata` attribute, and the anatomical
//! orientation labels of the NGFF orientation RFC (RFC-4).
//!
//! Per level L, along the array axes (z, y, x = index axes k, j, i): scale = spacing·2^L and
//! translation = t0 + (spacing·2^L − spacing)/2, which puts level-L voxel `i` at level-0 index
//! (i + ½)·2^L − ½: Strata's cell-centred 2×2×2 averaging. t0[a] = origin · direction[a], the
//! origin along the index axis; it is the origin itself when the axes are the patient's. OME-Zarr
//! 0.5 has no rotation, so the full LPS geometry (direction cosines included) lives in the
//! `strata` attribute, and the axes carry RFC-4 labels only where they are cardinal.

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use strata_storage::histogram::Histogram;
use strata_storage::store::StoreStats;
use strata_storage::StoreHeader;
use strata_types::VolumeGeometry;

use crate::{OmeZarrError, Result};

/// Version of the `strata` attribute's layout (2: the bricks' checksums ride along in
/// [`CHECKSUMS_KEY`]; version-1 exports are read, with the skeleton's ranges as their check).
pub const STRATA_ATTRIBUTE_VERSION: u32 = 2;
/// The object holding each varying brick's core checksum (see `crate::checksums`).
pub const CHECKSUMS_KEY: &str = "strata-checksums.bin";
/// The object (beside the group's zarr.json) holding the octree skeleton: per-node min/max,
/// as the store encodes it (checksummed).
pub const SKELETON_KEY: &str = "strata-skeleton.bin";

/// Strata's own attribute: everything a store's header says, plus its histogram and stats.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StrataAttributes {
    pub version: u32,
    pub header: StoreHeader,
    pub histogram: Histogram,
    pub stats: StoreStats,
    /// Key of the skeleton object, relative to the group.
    pub skeleton: String,
    /// Key of the brick checksums object (absent in version-1 exports).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub checksums: Option<String>,
}

/// One axis of the multiscale.
#[derive(Clone, Debug, PartialEq)]
pub struct Axis {
    pub name: String,
    /// "space", "time", "channel", or empty when absent.
    pub kind: String,
    pub unit: Option<String>,
    /// RFC-4 label ("left-to-right", ...), when given.
    pub orientation: Option<String>,
}

/// One level of the pyramid as the document declares it (scale and translation already
/// combined with the multiscale-wide transformation, when there is one).
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    pub path: String,
    pub scale: Vec<f64>,
    pub translation: Vec<f64>,
}

#[derive(Clone, Debug)]
pub struct Multiscale {
    pub name: String,
    pub axes: Vec<Axis>,
    pub datasets: Vec<Dataset>,
    pub strata: Option<StrataAttributes>,
    /// Per channel, the data range of the `omero` rendering metadata (`window.min`/`max`),
    /// when the writer gave it (finite, min ≤ max); the display window (`start`/`end`) is not
    /// a data range and is not used.
    pub channel_ranges: Vec<Option<[f64; 2]>>,
}

/// RFC-4 label of an index axis whose LPS direction is cardinal (±L, ±P, ±S); `None` when
/// oblique. LPS: +x points to the patient's left, so an axis along +x runs right-to-left.
pub fn orientation_label(direction: [f64; 3]) -> Option<&'static str> {
    const CARDINAL: f64 = 1e-6;
    let (axis, &value) = direction
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))?;
    let others_zero = direction
        .iter()
        .enumerate()
        .all(|(i, v)| i == axis || v.abs() < CARDINAL);
    if !others_zero || (value.abs() - 1.0).abs() > CARDINAL {
        return None;
    }
    Some(match (axis, value > 0.0) {
        (0, true) => "right-to-left",
        (0, false) => "left-to-right",
        (1, true) => "anterior-to-posterior",
        (1, false) => "posterior-to-anterior",
        (2, true) => "inferior-to-superior",
        _ => "superior-to-inferior",
    })
}

/// The LPS unit vector an RFC-4 label names (the inverse of [`orientation_label`]).
pub fn direction_of_label(label: &str) -> Option<[f64; 3]> {
    Some(match label {
        "right-to-left" => [1.0, 0.0, 0.0],
        "left-to-right" => [-1.0, 0.0, 0.0],
        "anterior-to-posterior" => [0.0, 1.0, 0.0],
        "posterior-to-anterior" => [0.0, -1.0, 0.0],
        "inferior-to-superior" => [0.0, 0.0, 1.0],
        "superior-to-inferior" => [0.0, 0.0, -1.0],
        _ => return None,
    })
}

/// The origin along each index axis (i, j, k): t0 of the module doc.
pub fn axis_origin(geometry: &VolumeGeometry) -> [f64; 3] {
    let o = geometry.origin_lps_mm;
    geometry
        .direction
        .map(|d| d[0] * o[0] + d[1] * o[1] + d[2] * o[2])
}

/// Scale and translation of level `level`, in array axis order (z, y, x).
pub fn level_transform(geometry: &VolumeGeometry, level: u8) -> ([f64; 3], [f64; 3]) {
    let t0 = axis_origin(geometry);
    let factor = f64::from(1u32 << level);
    let mut scale = [0.0; 3];
    let mut translation = [0.0; 3];
    for (array_axis, index_axis) in [2usize, 1, 0].into_iter().enumerate() {
        let spacing = geometry.spacing_mm[index_axis];
        scale[array_axis] = spacing * factor;
        translation[array_axis] = t0[index_axis] + (spacing * factor - spacing) / 2.0;
    }
    (scale, translation)
}

/// The group attributes of an export: `ome` (0.5 multiscales) and `strata`.
pub fn group_attributes(
    name: &str,
    strata: &StrataAttributes,
) -> Result<serde_json::Map<String, Value>> {
    let geometry = &strata.header.geometry;
    let axes: Vec<Value> = ["z", "y", "x"]
        .iter()
        .zip([2usize, 1, 0])
        .map(|(axis_name, index_axis)| {
            let mut axis = json!({"name": axis_name, "type": "space", "unit": "millimeter"});
            if let Some(label) = orientation_label(geometry.direction[index_axis]) {
                axis["orientation"] = json!({"type": "anatomical", "value": label});
            }
            axis
        })
        .collect();
    let datasets: Vec<Value> = (0..strata.header.layout.level_count())
        .map(|level| {
            let (scale, translation) = level_transform(geometry, level as u8);
            json!({
                "path": level.to_string(),
                "coordinateTransformations": [
                    {"type": "scale", "scale": scale},
                    {"type": "translation", "translation": translation},
                ],
            })
        })
        .collect();
    let ome = json!({
        "version": "0.5",
        "multiscales": [{
            "name": name,
            "axes": axes,
            "datasets": datasets,
            "type": "mean",
            "metadata": {
                "description": "2x2x2 cell-centred means (rounded, halves up); odd axes replicate their edge voxel",
                "method": "strata octree",
            },
        }],
    });
    let strata_value = serde_json::to_value(strata)
        .map_err(|e| OmeZarrError::invalid(name, format!("encoding the strata attribute: {e}")))?;
    let mut attributes = serde_json::Map::new();
    attributes.insert("ome".into(), ome);
    attributes.insert("strata".into(), strata_value);
    Ok(attributes)
}

fn numbers(value: Option<&Value>) -> Option<Vec<f64>> {
    value?.as_array()?.iter().map(Value::as_f64).collect()
}

/// Applies a `coordinateTransformations` list to (scale, translation), in order.
fn apply_transformations(
    list: Option<&Value>,
    scale: &mut [f64],
    translation: &mut [f64],
    location: &str,
) -> Result<()> {
    let Some(list) = list.and_then(Value::as_array) else {
        return Ok(());
    };
    for t in list {
        match t.get("type").and_then(Value::as_str) {
            Some("scale") => {
                let s = numbers(t.get("scale")).ok_or_else(|| {
                    OmeZarrError::invalid(location, "a scale transformation without a numeric `scale` list (paths to binary transforms are not supported)")
                })?;
                if s.len() != scale.len() {
                    return Err(OmeZarrError::invalid(location, format!("a scale of {} values for {} axes", s.len(), scale.len())));
                }
                for ((sc, tr), f) in scale.iter_mut().zip(translation.iter_mut()).zip(&s) {
                    *sc *= f;
                    *tr *= f;
                }
            }
            Some("translation") => {
                let d = numbers(t.get("translation")).ok_or_else(|| {
                    OmeZarrError::invalid(location, "a translation without a numeric `translation` list")
                })?;
                if d.len() != translation.len() {
                    return Err(OmeZarrError::invalid(location, format!("a translation of {} values for {} axes", d.len(), translation.len())));
                }
                for (tr, v) in translation.iter_mut().zip(&d) {
                    *tr += v;
                }
            }
            Some("identity") | None => {}
            Some(other) => {
                return Err(OmeZarrError::invalid(
                    location,
                    format!("coordinate transformation `{other}` is not part of OME-Zarr 0.5 (scale and translation only)"),
                ))
            }
        }
    }
    Ok(())
}

/// Reads the first multiscale of a group's attributes (0.5 under `ome`; 0.4-style top-level
/// `multiscales` accepted too).
pub fn parse_group_attributes(
    attributes: &serde_json::Map<String, Value>,
    location: &str,
) -> Result<Multiscale> {
    let multiscales = attributes
        .get("ome")
        .and_then(|ome| ome.get("multiscales"))
        .or_else(|| attributes.get("multiscales"))
        .and_then(Value::as_array)
        .ok_or_else(|| {
            OmeZarrError::invalid(
                location,
                "zarr.json has no OME multiscales (attributes.ome.multiscales): not an OME-Zarr image",
            )
        })?;
    let first = multiscales
        .first()
        .ok_or_else(|| OmeZarrError::invalid(location, "the multiscales list is empty"))?;
    // A version this build does not know may mean anything: refused, not guessed at.
    for version in [
        attributes.get("ome").and_then(|ome| ome.get("version")),
        first.get("version"),
    ]
    .into_iter()
    .flatten()
    {
        let known = version
            .as_str()
            .is_some_and(|v| v == "0.4" || v == "0.5" || v.starts_with("0.5-"));
        if !known {
            return Err(OmeZarrError::invalid(
                location,
                format!("OME-Zarr version {version} is not one this build reads (0.4, 0.5)"),
            ));
        }
    }
    let axes: Vec<Axis> = first
        .get("axes")
        .and_then(Value::as_array)
        .ok_or_else(|| OmeZarrError::invalid(location, "the multiscale has no `axes`"))?
        .iter()
        .map(|a| {
            let (name, kind, unit, orientation) = match a {
                Value::String(s) => (s.clone(), String::new(), None, None),
                _ => (
                    a.get("name")
                        .and_then(Value::as_str)
                        .unwrap_or("")
                        .to_string(),
                    a.get("type")
                        .and_then(Value::as_str)
                        .unwrap_or("")
                        .to_string(),
                    a.get("unit").and_then(Value::as_str).map(str::to_string),
                    a.pointer("/orientation/value")
                        .and_then(Value::as_str)
                        .map(str::to_string),
                ),
            };
            Axis {
                name,
                kind,
                unit,
                orientation,
            }
        })
        .collect();
    let n = axes.len();
    let datasets_json = first
        .get("datasets")
        .and_then(Value::as_array)
        .filter(|d| !d.is_empty())
        .ok_or_else(|| OmeZarrError::invalid(location, "the multiscale has no `datasets`"))?;
    let mut datasets = Vec::with_capacity(datasets_json.len());
    for d in datasets_json {
        let path = d
            .get("path")
            .and_then(Value::as_str)
            .ok_or_else(|| OmeZarrError::invalid(location, "a dataset without a `path`"))?
            .to_string();
        if path.split('/').any(|part| part == ".." || part.is_empty()) {
            return Err(OmeZarrError::invalid(
                location,
                format!("dataset path `{path}` leaves the group"),
            ));
        }
        let mut scale = vec![1.0; n];
        let mut translation = vec![0.0; n];
        apply_transformations(
            d.get("coordinateTransformations"),
            &mut scale,
            &mut translation,
            location,
        )?;
        apply_transformations(
            first.get("coordinateTransformations"),
            &mut scale,
            &mut translation,
            location,
        )?;
        if scale.iter().any(|s| !s.is_finite() || *s <= 0.0)
            || translation.iter().any(|t| !t.is_finite())
        {
            return Err(OmeZarrError::invalid(
                location,
                format!(
                    "dataset `{path}`: scale {scale:?} and translation {translation:?}: scales must be positive and finite, translations finite"
                ),
            ));
        }
        datasets.push(Dataset {
            path,
            scale,
            translation,
        });
    }
    let strata = match attributes.get("strata") {
        Some(value) => Some(
            serde_json::from_value::<StrataAttributes>(value.clone()).map_err(|e| {
                OmeZarrError::invalid(location, format!("the `strata` attribute is damaged: {e}"))
            })?,
        ),
        None => None,
    };
    if let Some(strata) = &strata {
        check_strata(strata, &datasets, location)?;
    }
    let ome = attributes.get("ome").unwrap_or(&Value::Null);
    let channel_ranges = ome
        .get("omero")
        .or_else(|| attributes.get("omero"))
        .and_then(|o| o.get("channels"))
        .and_then(Value::as_array)
        .map(|channels| {
            channels
                .iter()
                .map(|c| {
                    let min = c.pointer("/window/min").and_then(Value::as_f64)?;
                    let max = c.pointer("/window/max").and_then(Value::as_f64)?;
                    (min.is_finite() && max.is_finite() && min <= max).then_some([min, max])
                })
                .collect()
        })
        .unwrap_or_default();
    Ok(Multiscale {
        channel_ranges,
        name: first
            .get("name")
            .and_then(Value::as_str)
            .unwrap_or("")
            .to_string(),
        axes,
        datasets,
        strata,
    })
}

/// Refuses a `strata` attribute this build cannot read or that contradicts itself or the
/// multiscales beside it (a damaged export must not import or stream as something else).
fn check_strata(strata: &StrataAttributes, datasets: &[Dataset], location: &str) -> Result<()> {
    use strata_storage::store::{
        KNOWN_STORE_FEATURES, OLDEST_READABLE_FORMAT_VERSION, STORE_FORMAT_VERSION,
    };
    let bad = |message: String| {
        Err(OmeZarrError::invalid(
            location,
            format!("the `strata` attribute {message}"),
        ))
    };
    if !(1..=STRATA_ATTRIBUTE_VERSION).contains(&strata.version) {
        return bad(format!(
            "is version {} (this build reads 1 to {STRATA_ATTRIBUTE_VERSION}): update Strata",
            strata.version
        ));
    }
    let h = &strata.header;
    let v = h.format_version;
    if !(OLDEST_READABLE_FORMAT_VERSION..=STORE_FORMAT_VERSION).contains(&v) {
        return bad(format!(
            "names store format version {v} (this build reads {OLDEST_READABLE_FORMAT_VERSION} to {STORE_FORMAT_VERSION})"
        ));
    }
    if let Some(unknown) = h
        .required_features
        .iter()
        .find(|f| !KNOWN_STORE_FEATURES.contains(&f.as_str()))
    {
        return bad(format!(
            "requires the feature '{unknown}', which this build does not know: update Strata"
        ));
    }
    if let Err(e) = h.geometry.validate() {
        return bad(format!("has an unusable geometry: {e}"));
    }
    if h.layout != strata_types::OctreeLayout::new(h.geometry.dims) {
        return bad(format!(
            "has an octree layout that does not fit its {:?} voxels",
            h.geometry.dims
        ));
    }
    if h.brick_core != u64::from(strata_types::BRICK_CORE)
        || h.brick_apron != u64::from(strata_types::BRICK_APRON)
    {
        return bad(format!(
            "has bricks of {} + {} voxels (this build's are {} + {})",
            h.brick_core,
            h.brick_apron,
            strata_types::BRICK_CORE,
            strata_types::BRICK_APRON
        ));
    }
    let m = &h.value_mapping.mapping;
    if !(m.slope.is_finite() && m.slope != 0.0 && m.intercept.is_finite()) {
        return bad(format!(
            "has the value mapping slope {} intercept {}: the slope must be finite and non-zero",
            m.slope, m.intercept
        ));
    }
    let max = h.stored.max_value();
    if h.stored_range[0] > h.stored_range[1] || h.stored_range[1] > max {
        return bad(format!("has the stored range {:?}", h.stored_range));
    }
    if datasets.len() != h.layout.level_count() {
        return bad(format!(
            "describes {} levels but the multiscale has {} datasets",
            h.layout.level_count(),
            datasets.len()
        ));
    }
    // The multiscales' transformations are the attribute's geometry written out: a
    // disagreement is damage to one of them.
    for (level, d) in datasets.iter().enumerate() {
        let (scale, translation) = level_transform(&h.geometry, level as u8);
        let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 1e-6 * scale.abs().max(1.0);
        let agrees = d.scale.len() == 3
            && d.translation.len() == 3
            && (0..3).all(|a| {
                close(d.scale[a], scale[a], scale[a])
                    && close(
                        d.translation[a],
                        translation[a],
                        scale[a].abs().max(translation[a].abs()),
                    )
            });
        if !agrees {
            return bad(format!(
                "and dataset `{}` disagree: scale {:?} translation {:?} in the multiscales, {scale:?} {translation:?} from the attribute's geometry",
                d.path, d.scale, d.translation
            ));
        }
    }
    Ok(())
}

/// Millimetres per unit of an OME-Zarr space axis (UDUNITS-2 names as the spec lists them).
pub fn millimetres_per_unit(unit: Option<&str>) -> Option<f64> {
    Some(match unit? {
        "meter" => 1e3,
        "decimeter" => 1e2,
        "centimeter" => 10.0,
        "millimeter" => 1.0,
        "micrometer" => 1e-3,
        "nanometer" => 1e-6,
        "picometer" => 1e-9,
        "angstrom" => 1e-7,
        "kilometer" => 1e6,
        "inch" => 25.4,
        "foot" => 304.8,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cardinal_directions_get_labels_and_back() {
        for d in [
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
        ] {
            let label = orientation_label(d).unwrap();
            assert_eq!(direction_of_label(label), Some(d), "{label}");
        }
        let s = std::f64::consts::FRAC_1_SQRT_2;
        assert_eq!(orientation_label([s, s, 0.0]), None);
    }

    #[test]
    fn level_translation_centres_coarse_voxels_on_their_children() {
        let mut g = VolumeGeometry::axis_aligned([10, 20, 30], [0.5, 1.0, 2.0]);
        g.origin_lps_mm = [5.0, -3.0, 7.0];
        let (scale, translation) = level_transform(&g, 2);
        // z axis (k): spacing 2 mm, level 2 = 8 mm; voxel 0 covers level-0 k 0..4, centred at
        // k = 1.5, i.e. 7 + 1.5·2 = 10 mm.
        assert_eq!(scale, [8.0, 4.0, 2.0]);
        assert_eq!(translation, [10.0, -3.0 + 1.5, 5.0 + 0.75]);
    }
}
