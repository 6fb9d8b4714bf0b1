//! OME-Zarr → store. Level 0 of the first multiscale (one channel, one time point) is streamed
//! slab by slab into a raw staging file beside the new store, then imported like any other
//! scan: quantised as the readers' data is (exact for 8/16-bit integers, scaled for floats and
//! wide integers, the error recorded), and the octree rebuilt from level 0. Coarser levels of
//! the source are not read: Strata's own 2×2×2 means are rebuilt, which for a Strata export
//! gives the identical pyramid and for a foreign one copes with levels that do not halve.
//!
//! Geometry: a Strata export carries its full header in the `strata` attribute and gets it back
//! unchanged (oblique directions included). A foreign OME-Zarr's level-0 scale and translation
//! give spacing and origin; its RFC-4 orientation labels give the directions; without them the
//! convention assumed is said in the report's notes, never silently.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde_json::Value;
use strata_storage::import::{
    import_slices, ImportOptions, ImportReport, QuantizedSource, VolumeMeta,
};
use strata_storage::quantize::Quantizer;
use strata_storage::store::Skeleton;
use strata_storage::{
    ByteOrder, RawVolume, SampleType, StoredScalar, ValueMapping, ValueMappingWithUnit,
};
use strata_types::{OctreeLayout, VolumeGeometry};
use zarrs::array::{Array, ArraySubset};
use zarrs::storage::ReadableWritableListableStorageTraits;

use crate::metadata::{
    direction_of_label, millimetres_per_unit, parse_group_attributes, Multiscale,
};
use crate::zarr_store::zarr_storage;
use crate::{ObjectLocation, OmeZarrError, Result};

/// Bytes of one staging slab read at a time (bounded memory, whatever the volume).
const SLAB_BYTES: u64 = 128 << 20;

#[derive(Clone, Debug, Default)]
pub struct ImportZarrOptions {
    /// Index along a channel axis (`c`), when there is one (default 0).
    pub channel: Option<u64>,
    /// Index along a time axis (`t`), when there is one (default 0).
    pub time: Option<u64>,
    /// Where the level-0 staging file goes (default: beside the new store).
    pub staging_dir: Option<PathBuf>,
    pub memory_budget_bytes: Option<u64>,
}

/// What the import did, and what it had to assume.
pub struct ZarrImportReport {
    pub import: ImportReport,
    /// One line per assumption or choice (axis picked, orientation assumed, levels ignored).
    pub notes: Vec<String>,
    /// Whether the source was a Strata export (its header came back from the attributes).
    pub strata_export: bool,
}

/// An opened multiscale: the document and the zarrs store under it.
pub struct OpenedMultiscale {
    pub location: ObjectLocation,
    pub storage: zarrs::storage::ReadableWritableListableStorage,
    pub multiscale: Multiscale,
}

/// Opens the group at `location` and parses its first multiscale.
pub fn open_multiscale(location: ObjectLocation) -> Result<OpenedMultiscale> {
    let storage = zarr_storage(&location)?;
    let group = zarrs::group::Group::open(storage.clone(), "/").map_err(|e| {
        OmeZarrError::access(
            &location.display,
            format!("cannot open the Zarr group (zarr.json): {e}"),
        )
    })?;
    let multiscale = parse_group_attributes(group.attributes(), &location.display)?;
    Ok(OpenedMultiscale {
        location,
        storage,
        multiscale,
    })
}

/// A level's array, opened.
pub fn open_level(
    opened: &OpenedMultiscale,
    level: usize,
) -> Result<Array<dyn ReadableWritableListableStorageTraits>> {
    let dataset = opened.multiscale.datasets.get(level).ok_or_else(|| {
        OmeZarrError::invalid(&opened.location.display, format!("no level {level}"))
    })?;
    let array =
        Array::open(opened.storage.clone(), &format!("/{}", dataset.path)).map_err(|e| {
            OmeZarrError::access(
                &opened.location.display,
                format!("array `{}`: {e}", dataset.path),
            )
        })?;
    opened
        .location
        .limits
        .register(array_limits(&array, &dataset.path));
    if array.dimensionality() != opened.multiscale.axes.len() {
        return Err(OmeZarrError::invalid(
            &opened.location.display,
            format!(
                "array `{}` has {} dimensions but the multiscale declares {} axes",
                dataset.path,
                array.dimensionality(),
                opened.multiscale.axes.len()
            ),
        ));
    }
    Ok(array)
}

/// What reads under an array may ask for, from its metadata: an encoded chunk no longer than
/// its samples plus any codec's expansion; for a sharded array, the index layout.
pub fn array_limits(
    array: &Array<dyn ReadableWritableListableStorageTraits>,
    path: &str,
) -> crate::read_guard::ArrayLimits {
    use crate::read_guard::{max_encoded_bytes, ArrayLimits, ShardSpec};
    let sample_bytes: u64 = match data_type_name(array).as_str() {
        "bool" | "uint8" | "int8" => 1,
        "uint16" | "int16" | "float16" | "bfloat16" => 2,
        "uint32" | "int32" | "float32" => 4,
        "uint64" | "int64" | "float64" => 8,
        // Anything wider or unknown: generous (the bound stays a bound).
        _ => 16,
    };
    let metadata = serde_json::to_value(array.metadata()).unwrap_or_default();
    let shape_of = |v: Option<&Value>| -> Vec<u64> {
        v.and_then(Value::as_array)
            .map(|a| a.iter().filter_map(Value::as_u64).collect())
            .unwrap_or_default()
    };
    let outer = shape_of(metadata.pointer("/chunk_grid/configuration/chunk_shape"));
    let sharding = metadata
        .pointer("/codecs/0")
        .filter(|c| c.get("name").and_then(Value::as_str) == Some("sharding_indexed"))
        .and_then(|c| c.get("configuration"));
    let voxels = |shape: &[u64]| {
        shape
            .iter()
            .fold(1u64, |n, &d| n.saturating_mul(d.max(1)))
            .saturating_mul(sample_bytes)
    };
    let (max_chunk_bytes, shard) = match sharding {
        Some(config) => {
            let inner = shape_of(config.get("chunk_shape"));
            let entries = outer
                .iter()
                .zip(&inner)
                .fold(1u64, |n, (&o, &i)| n.saturating_mul(o.div_ceil(i.max(1))));
            let checksum = config
                .get("index_codecs")
                .and_then(Value::as_array)
                .is_some_and(|codecs| {
                    codecs
                        .iter()
                        .any(|c| c.get("name").and_then(Value::as_str) == Some("crc32c"))
                });
            let at_end = config.get("index_location").and_then(Value::as_str) != Some("start");
            (
                max_encoded_bytes(voxels(&inner)),
                Some(ShardSpec {
                    entries,
                    index_at_end: at_end,
                    index_bytes: entries.saturating_mul(16) + if checksum { 4 } else { 0 },
                }),
            )
        }
        None => (max_encoded_bytes(voxels(&outer)), None),
    };
    ArrayLimits {
        prefix: format!("{}/", path.trim_end_matches('/')),
        max_chunk_bytes,
        shard,
    }
}

/// A note when a foreign level's array holds no chunk at all: Zarr reads it as the fill value
/// throughout, which is what the image then shows (a Strata export is checked instead).
pub fn absent_level_note(opened: &OpenedMultiscale, level: usize) -> Option<String> {
    use futures::StreamExt;
    let dataset = opened.multiscale.datasets.get(level)?;
    let prefix = object_store::path::Path::from(dataset.path.as_str());
    let store = opened.location.store.clone();
    let any_chunk = crate::zarr_store::block_on(async move {
        let mut listing = store.list(Some(&prefix));
        while let Some(entry) = listing.next().await {
            match entry {
                Ok(meta) if !meta.location.as_ref().ends_with("zarr.json") => return true,
                Ok(_) => {}
                // Listing failed: say nothing rather than something wrong.
                Err(_) => return true,
            }
        }
        false
    })
    .unwrap_or(true);
    (!any_chunk).then(|| {
        format!(
            "level {level} (`{}`) holds no chunk at all: every voxel reads as the array's fill value",
            dataset.path
        )
    })
}

/// The data type name of an array (`uint16`, `float32`, ...).
pub fn data_type_name(array: &Array<dyn ReadableWritableListableStorageTraits>) -> String {
    serde_json::to_value(array.metadata())
        .ok()
        .and_then(|m| match m.get("data_type") {
            Some(Value::String(s)) => Some(s.clone()),
            Some(other) => other
                .get("name")
                .and_then(Value::as_str)
                .map(str::to_string),
            None => None,
        })
        .unwrap_or_default()
}

/// Which array axes are space (z, y, x = k, j, i) and which index the other axes take.
pub struct AxisChoice {
    /// Array axis of k, j, i.
    pub space: [usize; 3],
    /// Fixed index per non-space array axis.
    pub fixed: Vec<(usize, u64)>,
    pub notes: Vec<String>,
}

pub fn choose_axes(
    multiscale: &Multiscale,
    shape: &[u64],
    options: &ImportZarrOptions,
    location: &str,
) -> Result<AxisChoice> {
    let is_space = |a: &crate::metadata::Axis| {
        a.kind == "space" || (a.kind.is_empty() && matches!(a.name.as_str(), "x" | "y" | "z"))
    };
    let space: Vec<usize> = (0..multiscale.axes.len())
        .filter(|&i| is_space(&multiscale.axes[i]))
        .collect();
    if space.len() != 3 {
        return Err(OmeZarrError::invalid(
            location,
            format!(
                "Strata needs 3 space axes; this image has {} ({})",
                space.len(),
                multiscale
                    .axes
                    .iter()
                    .map(|a| a.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    }
    let mut fixed = Vec::new();
    let mut notes = Vec::new();
    for (i, axis) in multiscale.axes.iter().enumerate() {
        if space.contains(&i) {
            continue;
        }
        let is_time = axis.kind == "time" || axis.name == "t";
        let (wanted, flag) = if is_time {
            (options.time, "--time")
        } else {
            (options.channel, "--channel")
        };
        let index = wanted.unwrap_or(0);
        if index >= shape[i] {
            return Err(OmeZarrError::invalid(
                location,
                format!(
                    "{flag} {index} is out of range: axis `{}` has {} entries",
                    axis.name, shape[i]
                ),
            ));
        }
        if shape[i] > 1 {
            notes.push(format!(
                "axis `{}` ({}) has {} entries: took {index}{}",
                axis.name,
                if axis.kind.is_empty() {
                    "non-space"
                } else {
                    &axis.kind
                },
                shape[i],
                if wanted.is_none() {
                    format!(" (pick another with {flag} N)")
                } else {
                    String::new()
                }
            ));
        }
        fixed.push((i, index));
    }
    Ok(AxisChoice {
        space: [space[0], space[1], space[2]],
        fixed,
        notes,
    })
}

/// Geometry of a foreign OME-Zarr's level 0, and the notes on what was assumed.
pub fn foreign_geometry(
    multiscale: &Multiscale,
    choice: &AxisChoice,
    dims: [u32; 3],
    location: &str,
) -> Result<(VolumeGeometry, Vec<String>)> {
    let mut notes = Vec::new();
    let level0 = &multiscale.datasets[0];
    let mut spacing = [1.0; 3];
    let mut t0 = [0.0; 3];
    let mut labels: [Option<&str>; 3] = [None; 3];
    let mut unit_missing = false;
    for (index_axis, &array_axis) in choice.space.iter().rev().enumerate() {
        let axis = &multiscale.axes[array_axis];
        let mm = match millimetres_per_unit(axis.unit.as_deref()) {
            Some(f) => f,
            None => {
                unit_missing = true;
                1.0
            }
        };
        spacing[index_axis] = level0.scale[array_axis] * mm;
        t0[index_axis] = level0.translation[array_axis] * mm;
        labels[index_axis] = axis.orientation.as_deref();
    }
    if unit_missing {
        notes.push("a space axis has no known unit: taken as millimetres".into());
    }
    let directions: Option<[[f64; 3]; 3]> = match labels {
        [Some(a), Some(b), Some(c)] => match (
            direction_of_label(a),
            direction_of_label(b),
            direction_of_label(c),
        ) {
            (Some(a), Some(b), Some(c)) => Some([a, b, c]),
            _ => None,
        },
        _ => None,
    };
    let direction = match directions {
        Some(d) => {
            notes.push(format!(
                "orientation from the axes' anatomical labels: x {}, y {}, z {}",
                labels[0].unwrap_or(""),
                labels[1].unwrap_or(""),
                labels[2].unwrap_or("")
            ));
            d
        }
        None => {
            notes.push(
                "no anatomical orientation in the OME-Zarr: assumed x runs right-to-left, y anterior-to-posterior, z inferior-to-superior (LPS, as DICOM and ITK)"
                    .into(),
            );
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        }
    };
    // t0[a] = origin · direction[a] with orthonormal directions: origin = Σ t0[a]·direction[a].
    let mut origin = [0.0; 3];
    for (t, axis) in t0.iter().zip(&direction) {
        for (o, d) in origin.iter_mut().zip(axis) {
            *o += t * d;
        }
    }
    let geometry = VolumeGeometry {
        dims,
        spacing_mm: spacing,
        origin_lps_mm: origin,
        direction,
    };
    geometry.validate().map_err(|e| {
        OmeZarrError::invalid(location, format!("the level-0 geometry is not usable: {e}"))
    })?;
    if multiscale.datasets.len() > 1 {
        notes.push(format!(
            "{} coarser levels in the source not read: the octree is rebuilt from level 0",
            multiscale.datasets.len() - 1
        ));
    }
    Ok((geometry, notes))
}

fn sample_type_of(name: &str) -> Option<SampleType> {
    Some(match name {
        "bool" | "uint8" => SampleType::U8,
        "int8" => SampleType::I8,
        "uint16" => SampleType::U16,
        "int16" => SampleType::I16,
        "uint32" => SampleType::U32,
        "int32" => SampleType::I32,
        "float32" => SampleType::F32,
        "float64" | "uint64" | "int64" | "float16" => SampleType::F64,
        _ => return None,
    })
}

/// Reads array subset `subset` of level 0 as little-endian samples of `sample_type`.
fn read_le(
    array: &Array<dyn ReadableWritableListableStorageTraits>,
    dtype: &str,
    subset: &ArraySubset,
    location: &str,
) -> Result<Vec<u8>> {
    let fail = |e: zarrs::array::ArrayError| OmeZarrError::access(location, e);
    macro_rules! le {
        ($t:ty) => {
            array
                .retrieve_array_subset::<Vec<$t>>(subset)
                .map_err(fail)?
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect()
        };
    }
    macro_rules! as_f64 {
        ($t:ty) => {
            array
                .retrieve_array_subset::<Vec<$t>>(subset)
                .map_err(fail)?
                .iter()
                .flat_map(|&v| (v as f64).to_le_bytes())
                .collect()
        };
    }
    Ok(match dtype {
        "bool" => array
            .retrieve_array_subset::<Vec<bool>>(subset)
            .map_err(fail)?
            .iter()
            .map(|&v| u8::from(v))
            .collect(),
        "uint8" => le!(u8),
        "int8" => le!(i8),
        "uint16" => le!(u16),
        "int16" => le!(i16),
        "uint32" => le!(u32),
        "int32" => le!(i32),
        "float32" => le!(f32),
        "float64" => le!(f64),
        "uint64" => as_f64!(u64),
        "int64" => as_f64!(i64),
        other => {
            return Err(OmeZarrError::invalid(
                location,
                format!("data type `{other}` cannot be imported (integers, bool, float32/64 can)"),
            ))
        }
    })
}

/// What a Strata export's chunks are checked against (its skeleton and, from version 2, its
/// bricks' checksums); `None` for a foreign OME-Zarr, whose absent chunks are the fill value.
pub fn chunk_check(opened: &OpenedMultiscale) -> Result<Option<crate::checksums::ChunkCheck>> {
    let Some(strata) = &opened.multiscale.strata else {
        return Ok(None);
    };
    let layout = strata.header.layout.clone();
    let skeleton = read_skeleton(opened, &strata.skeleton, &layout)?;
    let checksums = match &strata.checksums {
        None => None,
        Some(key) => {
            if key != crate::metadata::CHECKSUMS_KEY {
                return Err(OmeZarrError::invalid(
                    &opened.location.display,
                    format!("unexpected checksums object `{key}`"),
                ));
            }
            use object_store::ObjectStoreExt;
            let path = object_store::path::Path::from(key.as_str());
            let store = opened.location.store.clone();
            let bytes = crate::zarr_store::block_on(async move {
                let got = store.get(&path).await?;
                got.bytes().await
            })?
            .map_err(|e| OmeZarrError::access(&opened.location.display, format!("{key}: {e}")))?;
            Some(crate::checksums::decode(&bytes, &layout).map_err(|e| {
                OmeZarrError::invalid(
                    &opened.location.display,
                    format!("{key}: the bricks' checksums {e}: the export is damaged"),
                )
            })?)
        }
    };
    Ok(Some(crate::checksums::ChunkCheck {
        skeleton,
        layout,
        checksums,
        narrow: strata.header.stored == StoredScalar::U8,
        fill: strata.header.stored_range[0],
    }))
}

/// Checks level 0 of a Strata export as it is staged, slab by slab: one digest per brick of
/// the current row of bricks (12 bytes each), checked when the row's last slice has passed.
struct StagingCheck<'a> {
    check: &'a crate::checksums::ChunkCheck,
    dims: [u64; 3],
    bricks: [u64; 2],
    row: Vec<crate::checksums::DigestState>,
}

/// A level-0 brick of a staged import that differs from what the export wrote.
#[derive(Debug, thiserror::Error)]
#[error(
    "level 0 brick {:?} (chunk z {} y {} x {}) {problem}",
    .id.coords,
    .id.coords[2],
    .id.coords[1],
    .id.coords[0]
)]
struct StagedBrickError {
    id: strata_types::BrickId,
    problem: crate::checksums::ChunkCheckError,
}

impl<'a> StagingCheck<'a> {
    fn new(check: &'a crate::checksums::ChunkCheck, dims: [u64; 3]) -> Self {
        let core = u64::from(strata_types::BRICK_CORE);
        let bricks = [dims[0].div_ceil(core), dims[1].div_ceil(core)];
        StagingCheck {
            check,
            dims,
            bricks,
            row: vec![Default::default(); (bricks[0] * bricks[1]) as usize],
        }
    }

    /// Slices `z0..` of level 0 (z, y, x order, stored bytes) have been read.
    fn feed(&mut self, z0: u64, bytes: &[u8]) -> std::result::Result<(), StagedBrickError> {
        let core = u64::from(strata_types::BRICK_CORE);
        let narrow = self.check.narrow;
        let sample = if narrow { 1 } else { 2 };
        let [nx, ny, nz] = self.dims;
        let slice = (nx * ny) as usize * sample;
        for (dz, plane) in bytes.chunks_exact(slice).enumerate() {
            let z = z0 + dz as u64;
            for y in 0..ny {
                let row = &plane[(y * nx) as usize * sample..((y + 1) * nx) as usize * sample];
                for bx in 0..self.bricks[0] {
                    let x0 = (bx * core) as usize * sample;
                    let x1 = ((bx + 1) * core).min(nx) as usize * sample;
                    let state = &mut self.row[((y / core) * self.bricks[0] + bx) as usize];
                    state.add_row_bytes(&row[x0..x1], narrow);
                }
            }
            if (z + 1).is_multiple_of(core) || z + 1 == nz {
                for (i, state) in self.row.iter_mut().enumerate() {
                    let i = i as u64;
                    let id = strata_types::BrickId::new(
                        0,
                        [
                            (i % self.bricks[0]) as u32,
                            (i / self.bricks[0]) as u32,
                            (z / core) as u32,
                        ],
                    );
                    let digest = std::mem::take(state).finish();
                    self.check
                        .check(id, digest)
                        .map_err(|problem| StagedBrickError { id, problem })?;
                }
            }
        }
        Ok(())
    }
}

/// Imports the OME-Zarr at `location` into a new store at `store_path`.
pub fn import_zarr(
    location: ObjectLocation,
    store_path: &Path,
    options: &ImportZarrOptions,
    on_stage_progress: &(dyn Fn(u64, u64) + Sync),
    import_options: &ImportOptions,
) -> Result<ZarrImportReport> {
    let opened = open_multiscale(location)?;
    let display = opened.location.display.clone();
    let array = open_level(&opened, 0)?;
    let shape = array.shape().to_vec();
    let choice = choose_axes(&opened.multiscale, &shape, options, &display)?;
    let dims_u64 = [choice.space[2], choice.space[1], choice.space[0]].map(|a| shape[a]);
    let dims = VolumeGeometry::checked_dims(dims_u64)
        .map_err(|e| OmeZarrError::invalid(&display, format!("level 0: {e}")))?;
    let dtype = data_type_name(&array);
    let sample_type = sample_type_of(&dtype).ok_or_else(|| {
        OmeZarrError::invalid(
            &display,
            format!("data type `{dtype}` cannot be imported (integers, bool, float32/64 can)"),
        )
    })?;
    let mut notes = choice.notes.clone();
    let check = chunk_check(&opened)?;
    let mut staging_check = match &check {
        Some(check) if shape.len() == 3 => Some(StagingCheck::new(check, dims_u64)),
        _ => None,
    };
    if check.is_none() {
        notes.extend(absent_level_note(&opened, 0));
    }
    if matches!(dtype.as_str(), "uint64" | "int64") {
        notes.push(format!(
            "{dtype} samples converted to float64 before quantisation"
        ));
    }

    // Stage level 0 (the chosen channel and time point), slab by slab.
    let staging_dir = options.staging_dir.clone().unwrap_or_else(|| {
        store_path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .map_or_else(std::env::temp_dir, Path::to_path_buf)
    });
    let mut staging = tempfile::Builder::new()
        .prefix("strata-zarr-staging-")
        .suffix(".raw")
        .tempfile_in(&staging_dir)
        .map_err(|e| OmeZarrError::access(staging_dir.display(), e))?;
    let slice_bytes = dims_u64[0] * dims_u64[1] * sample_type.size_bytes() as u64;
    let chunk_z = array
        .chunk_shape(&vec![0; shape.len()])
        .map(|c| c[choice.space[0]].get())
        .unwrap_or(32);
    let slab = (SLAB_BYTES / slice_bytes.max(1)).max(1);
    let slab = if slab >= chunk_z {
        slab / chunk_z * chunk_z
    } else {
        slab
    };
    {
        let mut out = std::io::BufWriter::with_capacity(1 << 20, staging.as_file_mut());
        let mut z = 0;
        while z < dims_u64[2] {
            let z_end = (z + slab).min(dims_u64[2]);
            let mut ranges: Vec<std::ops::Range<u64>> = shape.iter().map(|&n| 0..n).collect();
            for &(axis, index) in &choice.fixed {
                ranges[axis] = index..index + 1;
            }
            ranges[choice.space[0]] = z..z_end;
            let subset = ArraySubset::new_with_ranges(&ranges);
            let bytes = read_le(&array, &dtype, &subset, &display)?;
            if let Some(check) = &mut staging_check {
                check
                    .feed(z, &bytes)
                    .map_err(|e| OmeZarrError::invalid(&display, e.to_string()))?;
            }
            out.write_all(&bytes)
                .map_err(|e| OmeZarrError::access(staging_dir.display(), e))?;
            z = z_end;
            on_stage_progress(z, dims_u64[2]);
        }
        out.flush()
            .map_err(|e| OmeZarrError::access(staging_dir.display(), e))?;
    }
    let raw = RawVolume::map_file(staging.path(), 0, sample_type, ByteOrder::Little, dims_u64)?;
    let quantizer = Quantizer::plan(&raw, 1.0);

    let (meta, strata_export) = match &opened.multiscale.strata {
        Some(strata) => {
            let h = &strata.header;
            if h.geometry.dims != dims {
                return Err(OmeZarrError::invalid(
                    &display,
                    format!(
                        "the strata attribute describes {:?} voxels but level 0 has {dims:?}",
                        h.geometry.dims
                    ),
                ));
            }
            let expected = if h.stored == StoredScalar::U8 {
                "uint8"
            } else {
                "uint16"
            };
            if dtype != expected {
                return Err(OmeZarrError::invalid(
                    &display,
                    format!(
                        "the strata attribute says {expected} samples but level 0 holds {dtype}"
                    ),
                ));
            }
            let mut inputs = h.provenance.inputs.clone();
            inputs.push(display.clone());
            (
                VolumeMeta {
                    geometry: h.geometry.clone(),
                    stored: h.stored,
                    value_mapping: h.value_mapping.clone(),
                    source_sample_type: h.source_sample_type,
                    quantization_error: h.quantization_error,
                    non_finite_samples: h.non_finite_samples,
                    modality: h.modality.clone(),
                    windows: h.windows.clone(),
                    description: h.description.clone(),
                    inputs,
                    source_format: h.provenance.source_format.clone(),
                    labels: h.labels.clone(),
                },
                true,
            )
        }
        None => {
            let (geometry, geometry_notes) =
                foreign_geometry(&opened.multiscale, &choice, dims, &display)?;
            notes.extend(geometry_notes);
            if quantizer.max_error_physical > 0.0 {
                notes.push(format!(
                    "{dtype} values scaled onto 16 bits: worst-case error {:.3e}",
                    quantizer.max_error_physical
                ));
            }
            notes.push("no value range in the source: computed while importing".into());
            let (slope, intercept) = quantizer.physical_mapping(1.0, 0.0);
            (
                VolumeMeta {
                    geometry,
                    stored: quantizer.stored,
                    value_mapping: ValueMappingWithUnit {
                        mapping: ValueMapping { slope, intercept },
                        unit: String::new(),
                    },
                    source_sample_type: sample_type,
                    quantization_error: quantizer.max_error_physical,
                    non_finite_samples: quantizer.non_finite_samples,
                    modality: String::new(),
                    windows: Vec::new(),
                    description: opened.multiscale.name.clone(),
                    inputs: vec![display.clone()],
                    source_format: "ome-zarr".into(),
                    labels: Vec::new(),
                },
                false,
            )
        }
    };
    if strata_export
        && (quantizer.stored != meta.stored || quantizer.offset != 0.0 || quantizer.scale != 1.0)
    {
        return Err(OmeZarrError::invalid(
            &display,
            "level 0's samples do not map one to one onto stored values",
        ));
    }
    let producer = QuantizedSource {
        data: raw,
        quantizer,
    };
    let options = ImportOptions {
        memory_budget_bytes: options
            .memory_budget_bytes
            .unwrap_or(import_options.memory_budget_bytes),
        cancel: import_options.cancel,
        progress: import_options.progress,
        codec: import_options.codec,
    };
    let import = import_slices(&producer, meta, store_path, &options)?;
    drop(producer);
    drop(staging);
    Ok(ZarrImportReport {
        import,
        notes,
        strata_export,
    })
}

/// The skeleton object a Strata export names in its `strata` attribute (import and streaming).
pub(crate) fn read_skeleton(
    opened: &OpenedMultiscale,
    key: &str,
    layout: &OctreeLayout,
) -> Result<Skeleton> {
    if key != crate::metadata::SKELETON_KEY {
        return Err(OmeZarrError::invalid(
            &opened.location.display,
            format!("unexpected skeleton object `{key}`"),
        ));
    }
    use object_store::ObjectStoreExt;
    let path = object_store::path::Path::from(key);
    let store = opened.location.store.clone();
    let bytes = crate::zarr_store::block_on(async move {
        let got = store.get(&path).await?;
        got.bytes().await
    })?
    .map_err(|e| OmeZarrError::access(&opened.location.display, format!("{key}: {e}")))?;
    Skeleton::decode(&bytes, layout).map_err(|e| {
        OmeZarrError::invalid(
            &opened.location.display,
            format!("{key}: the skeleton {e} (for the strata attribute's layout)"),
        )
    })
}
