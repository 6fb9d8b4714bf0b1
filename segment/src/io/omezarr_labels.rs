//! OME-Zarr labels: a layer written as `IMAGE.zarr/labels/NAME/` (NGFF 0.5 image-label, Zarr v3).
//!
//! Layout: `labels/zarr.json` is a group whose `ome.labels` lists the label images (merged with
//! any already there); `labels/NAME/zarr.json` is a group with `ome.image-label` (a colour and
//! the properties — name, visibility, lock, category — per label value, `source.image` = `../../`)
//! and a one-level `ome.multiscales` (axes z, y, x in millimetres; scale = spacing and
//! translation = the origin along each index axis, as `strata_omezarr`'s export writes an image);
//! OME-Zarr 0.5 has no rotation, so the full LPS geometry rides in a `strata.geometry` attribute.
//! `labels/NAME/0` is a Zarr v3 uint16 array (z, y, x), fill value 0, codecs `bytes` (little
//! endian) + `zstd` (level 1), chunks of up to 256 × 256 voxels in-plane and as many slices as fit
//! in 64 MiB of one slab (at most 32). Chunks that are all background are not written (Zarr's fill
//! value stands for them), so a sparse segmentation costs disk for its labelled chunks only.
//!
//! Voxels stream through [`LabelRead::read_slice_k`] one slab of slices at a time. The label
//! image is written under a temporary name beside its final one and renamed into place (the
//! previous one, if any, is removed only after), then `labels/zarr.json` is replaced atomically.
//! Checked with ome-zarr-models (validation) and zarr-python (voxels) in `segment/tests/peers.rs`.
//!
//! [`omezarr_labels_zip`] writes the same files into one zip in memory (the browser page's
//! download: a folder cannot be one): the image's Zarr hierarchy at the zip's root (`zarr.json`,
//! `labels/zarr.json`, `labels/NAME/…`), entries stored (the chunks are zstd already;
//! [`super::stored_zip`]), as
//! zarr-python's `ZipStore` and the NGFF zipped-OME-Zarr proposal read it. Its chunks are
//! compressed by C zstd where `local` builds it, else by ruzstd's pure-Rust encoder (wasm32): a
//! zstd frame either way, so the JSON is byte for byte the folder's and the chunks decode to the
//! same voxels.

#[cfg(feature = "local")]
use std::io::Write;
use std::path::Path;
#[cfg(feature = "local")]
use std::path::PathBuf;

use serde_json::{json, Value};

#[cfg(feature = "local")]
use crate::io::atomic::{sync_dir_of, write_file_atomically};
use crate::io::stored_zip::StoredZip;
use crate::{Label, LabelRead, SegmentError};

const TILE: u32 = 256;
const MAX_SLAB_BYTES: u64 = 64 << 20;
const MAX_SLAB_SLICES: u32 = 32;

#[cfg(feature = "local")]
fn io_error(path: &Path) -> impl Fn(std::io::Error) -> SegmentError + '_ {
    move |e| SegmentError::Io {
        path: path.to_path_buf(),
        source: e,
    }
}

fn json_bytes(path: &Path, value: &Value) -> Result<Vec<u8>, SegmentError> {
    serde_json::to_vec_pretty(value).map_err(|e| SegmentError::Format {
        path: path.to_path_buf(),
        message: format!("JSON: {e}"),
    })
}

#[cfg(feature = "local")]
fn write_json(path: &Path, value: &Value) -> Result<(), SegmentError> {
    let text = json_bytes(path, value)?;
    write_file_atomically(path, |out| out.write_all(&text).map_err(io_error(path)))
}

/// The image group written where there is none: a bare Zarr v3 group.
fn bare_image_group() -> Value {
    json!({"zarr_format": 3, "node_type": "group", "attributes": {}})
}

/// `labels/zarr.json`: the label images listed.
fn labels_group(names: &[String]) -> Value {
    json!({
        "zarr_format": 3,
        "node_type": "group",
        "attributes": {"ome": {"version": "0.5", "labels": names}},
    })
}

/// Where a label image's files go: a folder on disk or a zip in memory. `relative` is a
/// `/`-separated path under the label image.
trait LabelImageSink {
    fn put(&mut self, relative: &str, bytes: &[u8]) -> Result<(), SegmentError>;
}

/// Files under a folder (the label image's temporary folder: it is renamed into place whole,
/// so its files need no atomic replace of their own).
#[cfg(feature = "local")]
struct FolderSink {
    root: PathBuf,
}

#[cfg(feature = "local")]
impl LabelImageSink for FolderSink {
    fn put(&mut self, relative: &str, bytes: &[u8]) -> Result<(), SegmentError> {
        let path = relative
            .split('/')
            .fold(self.root.clone(), |path, part| path.join(part));
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(io_error(parent))?;
        }
        std::fs::write(&path, bytes).map_err(io_error(&path))
    }
}

/// Stored entries of a zip in memory, each under `prefix`.
struct ZipSink {
    zip: StoredZip,
    prefix: String,
}

impl LabelImageSink for ZipSink {
    fn put(&mut self, relative: &str, bytes: &[u8]) -> Result<(), SegmentError> {
        self.zip.add(&format!("{}{relative}", self.prefix), bytes)
    }
}

/// The label name must be one path component (it becomes a folder under `labels/`).
fn check_name(image: &Path, name: &str) -> Result<(), SegmentError> {
    let ok = !name.is_empty()
        && name != "."
        && name != ".."
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
    if ok {
        Ok(())
    } else {
        Err(SegmentError::Format {
            path: image.join("labels").join(name),
            message: "a label image name is letters, digits, '-', '_' and '.' (not first)".into(),
        })
    }
}

/// Writes `labels` as `image/labels/name/`; `image` is created as a bare Zarr group if absent.
/// Returns the label image's folder.
#[cfg(feature = "local")]
pub fn write_omezarr_labels(
    labels: &dyn LabelRead,
    image: &Path,
    name: &str,
) -> Result<PathBuf, SegmentError> {
    check_name(image, name)?;
    let labels_dir = image.join("labels");
    std::fs::create_dir_all(&labels_dir).map_err(io_error(&labels_dir))?;
    let image_json = image.join("zarr.json");
    if !image_json.exists() {
        write_json(&image_json, &bare_image_group())?;
    }
    let final_dir = labels_dir.join(name);
    let temp_dir = labels_dir.join(format!(".{name}.partial-{}", std::process::id()));
    if temp_dir.exists() {
        std::fs::remove_dir_all(&temp_dir).map_err(io_error(&temp_dir))?;
    }
    let mut sink = FolderSink {
        root: temp_dir.clone(),
    };
    let result = write_label_image(labels, &mut sink, &temp_dir, name);
    if let Err(e) = result {
        let _ = std::fs::remove_dir_all(&temp_dir);
        return Err(e);
    }
    // Swap: the old image (if any) aside, the new one in, then the old one removed.
    let old_dir = labels_dir.join(format!(".{name}.old-{}", std::process::id()));
    let had_old = final_dir.exists();
    if had_old {
        std::fs::rename(&final_dir, &old_dir).map_err(io_error(&final_dir))?;
    }
    if let Err(e) = std::fs::rename(&temp_dir, &final_dir) {
        if had_old {
            let _ = std::fs::rename(&old_dir, &final_dir);
        }
        let _ = std::fs::remove_dir_all(&temp_dir);
        return Err(io_error(&final_dir)(e));
    }
    sync_dir_of(&final_dir)?;
    if had_old {
        std::fs::remove_dir_all(&old_dir).map_err(io_error(&old_dir))?;
    }

    // labels/zarr.json: this name added to whatever label images are listed already.
    let group_json = labels_dir.join("zarr.json");
    let mut names: Vec<String> = std::fs::read(&group_json)
        .ok()
        .and_then(|b| serde_json::from_slice::<Value>(&b).ok())
        .and_then(|v| {
            v.pointer("/attributes/ome/labels")?
                .as_array()?
                .iter()
                .map(|n| n.as_str().map(str::to_owned))
                .collect()
        })
        .unwrap_or_default();
    if !names.iter().any(|n| n == name) {
        names.push(name.to_owned());
    }
    write_json(&group_json, &labels_group(&names))?;
    Ok(final_dir)
}

/// The files [`write_omezarr_labels`] writes into an image folder that had none, as one zip in
/// memory with that folder's hierarchy at its root (see the module doc); `zip_name` is what
/// errors call it.
pub fn omezarr_labels_zip(
    labels: &dyn LabelRead,
    zip_name: &Path,
    name: &str,
) -> Result<Vec<u8>, SegmentError> {
    check_name(zip_name, name)?;
    let mut sink = ZipSink {
        zip: StoredZip::new(zip_name),
        prefix: String::new(),
    };
    sink.put("zarr.json", &json_bytes(zip_name, &bare_image_group())?)?;
    sink.put(
        "labels/zarr.json",
        &json_bytes(zip_name, &labels_group(&[name.to_owned()]))?,
    )?;
    sink.prefix = format!("labels/{name}/");
    write_label_image(labels, &mut sink, zip_name, name)?;
    sink.zip.finish()
}

/// One chunk as a zstd frame at level 1: C zstd where it is built (`local`), else ruzstd's
/// encoder at its level-1 equivalent.
fn compress_chunk(chunk: &[u8], path: &Path) -> Result<Vec<u8>, SegmentError> {
    #[cfg(feature = "local")]
    {
        zstd::bulk::compress(chunk, 1).map_err(io_error(path))
    }
    #[cfg(not(feature = "local"))]
    {
        let _ = path;
        Ok(ruzstd::encoding::compress_to_vec(
            chunk,
            ruzstd::encoding::CompressionLevel::Fastest,
        ))
    }
}

/// The label image's group, array metadata and chunks into `sink`; `dir` is what errors name.
fn write_label_image(
    labels: &dyn LabelRead,
    sink: &mut dyn LabelImageSink,
    dir: &Path,
    name: &str,
) -> Result<(), SegmentError> {
    let g = labels.geometry();
    let [nx, ny, nz] = g.dims;

    let t0 = g
        .direction
        .map(|d| d[0] * g.origin_lps_mm[0] + d[1] * g.origin_lps_mm[1] + d[2] * g.origin_lps_mm[2]);
    let scale = [g.spacing_mm[2], g.spacing_mm[1], g.spacing_mm[0]];
    let translation = [t0[2], t0[1], t0[0]];
    let colors: Vec<Value> = labels
        .segments()
        .iter()
        .map(|s| json!({"label-value": s.value, "rgba": [s.rgb[0], s.rgb[1], s.rgb[2], 255]}))
        .collect();
    let properties: Vec<Value> = labels
        .segments()
        .iter()
        .map(|s| {
            let mut p = json!({
                "label-value": s.value,
                "name": s.name,
                "visible": s.visible,
                "locked": s.locked,
            });
            if let Some(c) = &s.category {
                p["category"] = serde_json::to_value(c).unwrap_or(Value::Null);
            }
            p
        })
        .collect();
    let group = json!({
        "zarr_format": 3,
        "node_type": "group",
        "attributes": {
            "ome": {
                "version": "0.5",
                "image-label": {
                    "colors": colors,
                    "properties": properties,
                    "source": {"image": "../../"},
                },
                "multiscales": [{
                    "name": name,
                    "axes": [
                        {"name": "z", "type": "space", "unit": "millimeter"},
                        {"name": "y", "type": "space", "unit": "millimeter"},
                        {"name": "x", "type": "space", "unit": "millimeter"},
                    ],
                    "datasets": [{
                        "path": "0",
                        "coordinateTransformations": [
                            {"type": "scale", "scale": scale},
                            {"type": "translation", "translation": translation},
                        ],
                    }],
                }],
            },
            "strata": {"geometry": g},
        },
    });
    sink.put("zarr.json", &json_bytes(dir, &group)?)?;

    let plane = u64::from(nx) * u64::from(ny);
    let slab = ((MAX_SLAB_BYTES / (plane * 2).max(1)) as u32)
        .clamp(1, MAX_SLAB_SLICES)
        .min(nz);
    let (tile_y, tile_x) = (TILE.min(ny), TILE.min(nx));
    let array = json!({
        "zarr_format": 3,
        "node_type": "array",
        "shape": [nz, ny, nx],
        "data_type": "uint16",
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [slab, tile_y, tile_x]}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": 0,
        "codecs": [
            {"name": "bytes", "configuration": {"endian": "little"}},
            {"name": "zstd", "configuration": {"level": 1, "checksum": false}},
        ],
        "dimension_names": ["z", "y", "x"],
        "attributes": {},
    });
    sink.put("0/zarr.json", &json_bytes(dir, &array)?)?;

    let plane = plane as usize;
    let mut slices: Vec<Label> = vec![0; plane * slab as usize];
    let mut chunk: Vec<u8> = Vec::with_capacity((slab * tile_y * tile_x * 2) as usize);
    for cz in 0..nz.div_ceil(slab) {
        let k0 = cz * slab;
        let depth = slab.min(nz - k0);
        for (n, slice) in slices.chunks_mut(plane).take(depth as usize).enumerate() {
            labels.read_slice_k(k0 + n as u32, slice)?;
        }
        for cy in 0..ny.div_ceil(tile_y) {
            for cx in 0..nx.div_ceil(tile_x) {
                chunk.clear();
                let mut any = false;
                // A whole chunk, edge chunks padded with the fill value (0).
                for dz in 0..slab {
                    for dy in 0..tile_y {
                        for dx in 0..tile_x {
                            let (i, j) = (cx * tile_x + dx, cy * tile_y + dy);
                            let v = if dz < depth && i < nx && j < ny {
                                slices[dz as usize * plane + (j * nx + i) as usize]
                            } else {
                                0
                            };
                            any |= v != 0;
                            chunk.extend_from_slice(&v.to_le_bytes());
                        }
                    }
                }
                if !any {
                    continue;
                }
                let key = format!("0/c/{cz}/{cy}/{cx}");
                let compressed = compress_chunk(&chunk, &dir.join(&key))?;
                sink.put(&key, &compressed)?;
            }
        }
    }
    Ok(())
}

/// The most voxels [`load_omezarr_labels`] holds in memory (u16: 1 GiB).
#[cfg(feature = "local")]
pub const MAX_LOADED_VOXELS: u64 = 512 << 20;

#[cfg(feature = "local")]
fn read_json(path: &Path) -> Result<Value, SegmentError> {
    let bytes = std::fs::read(path).map_err(io_error(path))?;
    serde_json::from_slice(&bytes).map_err(|e| SegmentError::Format {
        path: path.to_path_buf(),
        message: format!("not JSON: {e}"),
    })
}

/// Loads a label image written by [`write_omezarr_labels`] (`IMAGE/labels/NAME`) back as a layer:
/// voxels, geometry (from the `strata` attribute; else axis-aligned from scale and translation)
/// and segments (names, colours, visibility, locks, categories). Reads the `bytes` + `zstd`
/// codec chain this module writes; other codecs (blosc, sharding) are refused by name. Held in
/// memory as [`crate::DenseLabels`], up to [`MAX_LOADED_VOXELS`].
#[cfg(feature = "local")]
pub fn load_omezarr_labels(label_dir: &Path) -> Result<crate::LabelLayer, SegmentError> {
    let bad = |path: &Path, message: String| SegmentError::Format {
        path: path.to_path_buf(),
        message,
    };
    let group_path = label_dir.join("zarr.json");
    let group = read_json(&group_path)?;
    let ome = group.pointer("/attributes/ome").ok_or_else(|| {
        bad(
            &group_path,
            "no `ome` attributes: not an OME-Zarr label image".into(),
        )
    })?;
    let array_path = label_dir.join("0").join("zarr.json");
    let array = read_json(&array_path)?;
    let shape: Vec<u64> = array["shape"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_u64).collect())
        .unwrap_or_default();
    let chunk: Vec<u64> = array
        .pointer("/chunk_grid/configuration/chunk_shape")
        .and_then(Value::as_array)
        .map(|a| a.iter().filter_map(Value::as_u64).collect())
        .unwrap_or_default();
    if shape.len() != 3 || chunk.len() != 3 || chunk.contains(&0) || array["data_type"] != "uint16"
    {
        return Err(bad(
            &array_path,
            format!(
                "a 3-D uint16 array is read; this is {} of shape {shape:?}, chunks {chunk:?}",
                array["data_type"]
            ),
        ));
    }
    let codecs: Vec<&str> = array["codecs"]
        .as_array()
        .map(|a| a.iter().filter_map(|c| c["name"].as_str()).collect())
        .unwrap_or_default();
    let little = array.pointer("/codecs/0/configuration/endian") == Some(&json!("little"));
    if codecs != ["bytes", "zstd"] || !little {
        return Err(bad(
            &array_path,
            format!(
                "codecs {codecs:?}: only Strata's own chain (bytes little-endian, zstd) is read"
            ),
        ));
    }
    let (nz, ny, nx) = (shape[0], shape[1], shape[2]);
    let total = nx.saturating_mul(ny).saturating_mul(nz);
    if total > MAX_LOADED_VOXELS || total == 0 || nx > u64::from(u32::MAX) {
        return Err(bad(
            &array_path,
            format!(
                "{nx} x {ny} x {nz} voxels: a label image is loaded whole up to {MAX_LOADED_VOXELS} voxels"
            ),
        ));
    }
    let dims = [nx as u32, ny as u32, nz as u32];
    let geometry: strata_types::VolumeGeometry = match group.pointer("/attributes/strata/geometry")
    {
        Some(g) => serde_json::from_value(g.clone())
            .map_err(|e| bad(&group_path, format!("strata.geometry unreadable: {e}")))?,
        None => {
            let t = ome.pointer("/multiscales/0/datasets/0/coordinateTransformations");
            let find = |kind: &str| -> Option<Vec<f64>> {
                t?.as_array()?.iter().find(|x| x["type"] == kind)?[kind]
                    .as_array()?
                    .iter()
                    .map(Value::as_f64)
                    .collect()
            };
            let s = find("scale").unwrap_or_else(|| vec![1.0; 3]);
            let o = find("translation").unwrap_or_else(|| vec![0.0; 3]);
            let mut g = strata_types::VolumeGeometry::axis_aligned(dims, [s[2], s[1], s[0]]);
            g.origin_lps_mm = [o[2], o[1], o[0]];
            g
        }
    };
    if geometry.dims != dims {
        return Err(bad(
            &group_path,
            format!(
                "strata.geometry is {:?} voxels, the array {dims:?}",
                geometry.dims
            ),
        ));
    }
    let mut voxels: Vec<Label> = vec![0; total as usize];
    let chunk_voxels = (chunk[0] * chunk[1] * chunk[2]) as usize;
    let mut raw = vec![0u8; chunk_voxels * 2];
    let mut decoder = zstd::bulk::Decompressor::new().map_err(io_error(&array_path))?;
    for cz in 0..nz.div_ceil(chunk[0]) {
        for cy in 0..ny.div_ceil(chunk[1]) {
            for cx in 0..nx.div_ceil(chunk[2]) {
                let path = label_dir
                    .join("0/c")
                    .join(cz.to_string())
                    .join(cy.to_string())
                    .join(cx.to_string());
                let bytes = match std::fs::read(&path) {
                    Ok(b) => b,
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                    Err(e) => return Err(io_error(&path)(e)),
                };
                let got = decoder
                    .decompress_to_buffer(&bytes, &mut raw)
                    .map_err(|e| bad(&path, format!("chunk does not decompress: {e}")))?;
                if got != raw.len() {
                    return Err(bad(
                        &path,
                        format!("chunk of {got} bytes, not {}", raw.len()),
                    ));
                }
                for dz in 0..chunk[0] {
                    for dy in 0..chunk[1] {
                        for dx in 0..chunk[2] {
                            let (x, y, z) =
                                (cx * chunk[2] + dx, cy * chunk[1] + dy, cz * chunk[0] + dz);
                            if x < nx && y < ny && z < nz {
                                let at = 2 * (((dz * chunk[1]) + dy) * chunk[2] + dx) as usize;
                                voxels[((z * ny + y) * nx + x) as usize] =
                                    Label::from_le_bytes([raw[at], raw[at + 1]]);
                            }
                        }
                    }
                }
            }
        }
    }
    let mut segments = crate::SegmentTable::new();
    let image_label = ome.get("image-label");
    let colours = image_label.and_then(|l| l["colors"].as_array());
    let properties = image_label.and_then(|l| l["properties"].as_array());
    let value_of = |v: &Value| {
        v["label-value"]
            .as_u64()
            .and_then(|n| Label::try_from(n).ok())
    };
    for p in properties.into_iter().flatten() {
        let Some(value) = value_of(p).filter(|&v| v != 0) else {
            continue;
        };
        let rgb = colours
            .into_iter()
            .flatten()
            .find(|c| value_of(c) == Some(value))
            .and_then(|c| {
                let a = c["rgba"].as_array()?;
                let ch = |n: usize| a.get(n)?.as_u64().and_then(|v| u8::try_from(v).ok());
                Some([ch(0)?, ch(1)?, ch(2)?])
            })
            .unwrap_or_else(|| crate::segments::label_colour(i64::from(value)));
        segments.insert(crate::Segment {
            value,
            name: p["name"]
                .as_str()
                .map_or_else(|| format!("segment {value}"), str::to_owned),
            rgb,
            visible: p["visible"].as_bool().unwrap_or(true),
            locked: p["locked"].as_bool().unwrap_or(false),
            category: p
                .get("category")
                .and_then(|c| serde_json::from_value(c.clone()).ok()),
        })?;
    }
    crate::LabelLayer::with_base(
        geometry,
        std::sync::Arc::new(crate::DenseLabels {
            dims,
            labels: voxels,
        }),
        segments,
    )
}
