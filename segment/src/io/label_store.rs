//! A Strata label store: a segmentation saved as a Strata brick store (u16 label values stored
//! as they are, identity value mapping, the segments' names and colours in the header), and a
//! store opened as the read-only base of an editable layer.
//!
//! The store's level-0 bricks are the layer's edit bricks (both 32³ cores, `LABEL_BRICK ==
//! BRICK_CORE`), so a layer over a store reads one stored brick per edit brick it touches and
//! skips every brick whose skeleton range is all background without reading it: editing a
//! label store of any size costs memory in proportion to the bricks edited, as the layer over a
//! file does. The store's coarser levels are the importer's (means); the viewer reads labels at
//! level 0 and builds the 3D pyramid by mode ([`crate::pyramid`]).
//!
//! Saving goes to a fresh sibling store and replaces the target only once that store is
//! complete; a target that exists and is not a Strata store is refused, never replaced.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use strata_storage::import::{import_slices, ImportOptions, SliceProducer, VolumeMeta};
use strata_storage::inventory::survey;
use strata_storage::{
    LabelInfo, SampleType, StorageError, Store, StoredScalar, ValueMappingWithUnit,
};
use strata_types::BrickId;
use strata_types::ValueMapping;

use crate::grid::{BrickKey, LabelGrid, LABEL_BRICK};
use crate::{Label, LabelBase, LabelLayer, LabelRead, Segment, SegmentError, SegmentTable};

/// The `source_format` a label store's header records.
pub const LABEL_STORE_FORMAT: &str = "strata-segmentation";

/// The labels' slices as the importer asks for them (labels are stored values already).
struct LabelSlices<'a> {
    labels: &'a (dyn LabelRead + Sync),
    path: PathBuf,
}

impl SliceProducer for LabelSlices<'_> {
    fn dims(&self) -> [u64; 3] {
        self.labels.geometry().dims.map(u64::from)
    }

    fn stored_slice(&self, k: u64, out: &mut [u16]) -> strata_storage::Result<()> {
        let k = u32::try_from(k)
            .map_err(|_| StorageError::invalid(&self.path, format!("slice {k} out of range")))?;
        self.labels
            .read_slice_k(k, out)
            .map_err(|e| StorageError::invalid(&self.path, format!("slice {k}: {e}")))
    }

    fn source_bytes_per_slice(&self) -> u64 {
        let [nx, ny, _] = self.labels.geometry().dims;
        u64::from(nx) * u64::from(ny) * 2
    }
}

fn storage_error(path: &Path) -> impl Fn(StorageError) -> SegmentError + '_ {
    move |e| SegmentError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// A path beside `target` with a suffix (same folder, so the final rename stays on one disk).
fn sibling(target: &Path, suffix: &str) -> PathBuf {
    let mut name = target
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".{suffix}-{}", std::process::id()));
    target.with_file_name(name)
}

/// Saves `labels` as a Strata store at `path`, replacing a store there only once the new one
/// is complete.
pub fn write_label_store(labels: &(dyn LabelRead + Sync), path: &Path) -> Result<(), SegmentError> {
    if path.exists() && survey(path).marker_format_version.is_none() {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: "exists and is not a Strata store: not replaced".into(),
        });
    }
    let meta = VolumeMeta {
        geometry: labels.geometry().clone(),
        stored: StoredScalar::U16,
        value_mapping: ValueMappingWithUnit {
            mapping: ValueMapping {
                slope: 1.0,
                intercept: 0.0,
            },
            unit: String::new(),
        },
        source_sample_type: SampleType::U16,
        quantization_error: 0.0,
        non_finite_samples: 0,
        modality: "SEG".into(),
        windows: Vec::new(),
        description: "Strata segmentation".into(),
        inputs: Vec::new(),
        source_format: LABEL_STORE_FORMAT.into(),
        labels: labels
            .segments()
            .iter()
            .map(|s| LabelInfo {
                value: u32::from(s.value),
                name: s.name.clone(),
                rgb: Some(s.rgb),
                category: s.category.clone(),
            })
            .collect(),
    };
    let fresh = sibling(path, "saving");
    let _ = std::fs::remove_dir_all(&fresh);
    let slices = LabelSlices {
        labels,
        path: path.to_path_buf(),
    };
    if let Err(e) = import_slices(&slices, meta, &fresh, &ImportOptions::default()) {
        let _ = std::fs::remove_dir_all(&fresh);
        return Err(storage_error(path)(e));
    }
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |source| SegmentError::Io { path: p, source }
    };
    if path.exists() {
        // Directories cannot be renamed over each other: the old store steps aside first and
        // is removed once the new one is in its place.
        let old = sibling(path, "replaced");
        std::fs::rename(path, &old).map_err(io(path))?;
        if let Err(e) = std::fs::rename(&fresh, path) {
            let _ = std::fs::rename(&old, path);
            return Err(io(path)(e));
        }
        let _ = std::fs::remove_dir_all(&old);
    } else {
        std::fs::rename(&fresh, path).map_err(io(path))?;
    }
    super::atomic::sync_dir_of(path)
}

/// A label store's level-0 bricks, read one at a time.
pub struct StoreLabels {
    store: Store,
    apron: usize,
}

impl LabelBase for StoreLabels {
    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [Label],
    ) -> Result<(), SegmentError> {
        out.fill(0);
        if self.brick_is_empty(key) {
            return Ok(());
        }
        let id = BrickId::new(0, key.0);
        let stored = self
            .store
            .read_brick(id)
            .map_err(|e| SegmentError::BaseRead {
                brick: key.0,
                message: format!("{}: {e}", self.store.path().display()),
            })?;
        let b = LABEL_BRICK as usize;
        let side = b + 2 * self.apron;
        if stored.len() != side * side * side {
            return Err(SegmentError::BaseRead {
                brick: key.0,
                message: format!(
                    "{}: brick of {} values, expected {side}³",
                    self.store.path().display(),
                    stored.len()
                ),
            });
        }
        let [nx, ny, nz] = grid.dims();
        let o = grid.brick_origin(key);
        let w = LABEL_BRICK.min(nx.saturating_sub(o[0])) as usize;
        for lk in 0..LABEL_BRICK.min(nz.saturating_sub(o[2])) as usize {
            for lj in 0..LABEL_BRICK.min(ny.saturating_sub(o[1])) as usize {
                let from = self.apron + side * ((lj + self.apron) + side * (lk + self.apron));
                let to = b * (lj + b * lk);
                out[to..to + w].copy_from_slice(&stored[from..from + w]);
            }
        }
        Ok(())
    }

    fn brick_is_empty(&self, key: BrickKey) -> bool {
        self.store
            .node(BrickId::new(0, key.0))
            .is_none_or(|n| n.max == 0)
    }
}

/// Opens a Strata store holding labels as the base of an editable layer on its grid.
pub fn load_label_store(path: &Path) -> Result<LabelLayer, SegmentError> {
    let store = Store::open(path).map_err(storage_error(path))?;
    let header = store.header();
    let mapping = header.value_mapping.mapping;
    if header.stored != StoredScalar::U16 && header.stored != StoredScalar::U8 {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: "its values are not stored as integers".into(),
        });
    }
    if mapping.slope != 1.0 || mapping.intercept != 0.0 || header.quantization_error != 0.0 {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: format!(
                "values are mapped (slope {}, intercept {}) or quantised: a store of labels holds them as they are",
                mapping.slope, mapping.intercept
            ),
        });
    }
    if store.frame_count() != 1 {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: format!(
                "{} frames (a time series): a label map has one",
                store.frame_count()
            ),
        });
    }
    if header.brick_core != u64::from(LABEL_BRICK) {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: format!(
                "bricks of {}³, labels are edited in {LABEL_BRICK}³",
                header.brick_core
            ),
        });
    }
    let mut segments = SegmentTable::new();
    for label in &header.labels {
        let value = Label::try_from(label.value)
            .ok()
            .filter(|&v| v != 0)
            .ok_or_else(|| SegmentError::Format {
                path: path.to_path_buf(),
                message: format!("label value {} is not 1..=65535", label.value),
            })?;
        segments.insert(Segment {
            value,
            name: label.name.clone(),
            rgb: label
                .rgb
                .unwrap_or_else(|| crate::segments::label_colour(i64::from(value))),
            visible: true,
            locked: false,
            category: label.category.clone(),
        })?;
    }
    let unnamed = header.labels.is_empty();
    let geometry = header.geometry.clone();
    let apron = usize::try_from(header.brick_apron).unwrap_or(usize::MAX);
    if apron > 8 {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: format!("brick apron of {apron} voxels"),
        });
    }
    let base = StoreLabels { store, apron };
    let mut layer = LabelLayer::with_base(geometry, Arc::new(base), segments)?;
    if unnamed {
        // A store imported from a plain label map names no labels: name those the data holds,
        // as the file loader does, reading only the bricks the skeleton says are not empty.
        let mut present = vec![false; usize::from(Label::MAX) + 1];
        let [bx, by, bz] = layer.grid().bricks();
        for k in 0..bz {
            for j in 0..by {
                for i in 0..bx {
                    let key = BrickKey([i, j, k]);
                    if layer.brick_is_empty(key) {
                        continue;
                    }
                    for &v in layer.brick(key)?.iter() {
                        present[usize::from(v)] = true;
                    }
                }
            }
        }
        for value in 1..=Label::MAX {
            if present[usize::from(value)] {
                layer.segments_mut().insert(Segment {
                    value,
                    name: format!("segment {value}"),
                    rgb: crate::segments::label_colour(i64::from(value)),
                    visible: true,
                    locked: false,
                    category: None,
                })?;
            }
        }
    }
    Ok(layer)
}

/// Whether `path` is a Strata store folder (its marker names a format), as opposed to a label
/// file or a DICOM folder.
pub fn is_strata_store(path: &Path) -> bool {
    path.is_dir() && survey(path).marker_format_version.is_some()
}
