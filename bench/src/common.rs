//! What `strata-bench accuracy` and `strata-bench transitions` share, so that both measure
//! the same thing the same way: the input (a store or a generated phantom) with its transfer
//! function, the one oblique view they render, the f64 CPU reference they compare against, the
//! mixed level-0/1 cut of the transitions bench (also a setting of the accuracy sweep), and
//! the median they report.

use std::path::Path;

use anyhow::{Context, Result};
use glam::{DMat3, DVec3};
use strata_loader::ResidentBricks;
use strata_render::model::smooth_transitions::{transition_masks, transition_node_fraction};
use strata_render::reference::{render_reference, ReferenceOptions, ReferenceScene};
use strata_render::{
    Camera, PageEntry, PageTable, Projection, RenderSettings, TransferFunction,
    TransferFunctionTable, ValueMapping, VolumeGeometry,
};
use strata_storage::Store;

use strata_viewer::export::choose_transfer_function;

/// Median of `v` (the upper one of an even count).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// An opened bench input: the store, its render geometry and value mapping, and the transfer
/// function with its table.
pub(crate) struct Volume {
    pub(crate) store: Store,
    pub(crate) geometry: VolumeGeometry,
    pub(crate) mapping: ValueMapping,
    pub(crate) tf: TransferFunction,
    pub(crate) tf_table: TransferFunctionTable,
    pub(crate) name: String,
    _scratch: Option<tempfile::TempDir>,
}

/// Opens `input` (a store, or the word `phantom` for a generated CT phantom of
/// `phantom_size`³ in a scratch folder that lives as long as the [`Volume`]) with the transfer
/// function `tf` (a preset or JSON file; default by modality).
pub(crate) fn open_input(input: &str, phantom_size: u64, tf: Option<&str>) -> Result<Volume> {
    let (store, name, scratch) = if input == "phantom" {
        let dir = tempfile::tempdir().context("creating a scratch folder for the phantom store")?;
        let path = dir.path().join("phantom.strata");
        eprintln!("generating a {}³ CT phantom store", phantom_size);
        strata_storage::phantom::Phantom::cube(phantom_size)
            .write_store(&path, &strata_storage::import::ImportOptions::default())
            .with_context(|| format!("writing phantom store {}", path.display()))?;
        let store = Store::open(&path).with_context(|| format!("opening {}", path.display()))?;
        (store, format!("phantom{}", phantom_size), Some(dir))
    } else {
        let path = Path::new(input);
        let store =
            Store::open(path).with_context(|| format!("cannot open store {}", path.display()))?;
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "store".into());
        (store, name, None)
    };
    let header = store.header().clone();
    let geometry = header.geometry.clone();
    let mapping = header.value_mapping.mapping;
    let tf = choose_transfer_function(tf, &header.modality)?;
    let (a, b) = (
        mapping.physical(header.stored_range[0] as f64),
        mapping.physical(header.stored_range[1] as f64),
    );
    let tf_table = tf.table(a.min(b), a.max(b));
    Ok(Volume {
        store,
        geometry,
        mapping,
        tf,
        tf_table,
        name,
        _scratch: scratch,
    })
}

/// The view every setting of the accuracy-type benches renders: an oblique orbit framing the
/// whole volume.
pub(crate) fn bench_camera(geometry: &VolumeGeometry) -> Camera {
    Camera::orbit(
        geometry,
        30.0,
        20.0,
        1.0,
        Projection::Perspective { fov_y_deg: 30.0 },
    )
}

/// The f64 CPU reference of `table` (with `bricks`) at 1/16 voxel for a base step of 1/2:
/// ground truth for the GPU frames of the same settings (shading and smoothing included).
pub(crate) fn reference_rgba(
    v: &Volume,
    bricks: &ResidentBricks,
    table: &PageTable,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<Vec<u8>> {
    let reference = render_reference(
        &ReferenceScene {
            source: bricks,
            page_table: table,
            geometry: &v.geometry,
            mapping: v.mapping,
            transfer_function: &v.tf,
            tf_range: (v.tf_table.lo, v.tf_table.hi),
        },
        camera,
        settings,
        ReferenceOptions {
            step_refinement: 8.0,
            ..Default::default()
        },
    )?;
    Ok(reference.rgba)
}

/// The mixed level-0/1 cut both benches render (`strata-bench transitions` measures it,
/// `strata-bench accuracy` has it as one family of its sweep). A near-fine / far-coarse cut:
/// level-1 nodes whose centre lies at depth ≤ `threshold` along `forward` (page units) are
/// split into level-0 nodes.
#[derive(Clone, Debug)]
pub(crate) struct Split {
    forward: DVec3,
    threshold: f64,
    /// Transition-node share of the cut (over all resident nodes).
    pub(crate) fraction: f64,
}

/// Depth of a level-1 node's centre along `forward`, in page units.
fn level1_depth(node: [u32; 3], forward: DVec3) -> f64 {
    let centre = DVec3::new(node[0] as f64, node[1] as f64, node[2] as f64) * 2.0 + 1.0;
    centre.dot(forward)
}

impl Split {
    pub(crate) fn level_of(&self, page: [u32; 3]) -> u8 {
        if level1_depth(PageTable::node_of(page, 1), self.forward) <= self.threshold {
            0
        } else {
            1
        }
    }
}

/// A page table of `page_dims` whose position `page` is served by `level_of(page)` (slots are
/// irrelevant to the transition masks).
fn table_of(page_dims: [u32; 3], level_of: impl Fn([u32; 3]) -> u8) -> PageTable {
    let mut table = PageTable::new(page_dims);
    for i in 0..table.entries.len() {
        let level = level_of(table.page_of_linear(i));
        table.entries[i] = PageEntry::resident(0, level);
    }
    table
}

/// The split for `camera`: the plane is perpendicular to the view direction in patient space;
/// in index space a point's depth is (Mᵀ·forward)·index with M = patient_from_index.
pub(crate) fn view_split(v: &Volume, camera: &Camera, target: f64) -> Split {
    let m: DMat3 = v.geometry.patient_from_index_linear();
    choose_split(
        v.geometry.page_dims(),
        m.transpose() * camera.basis().forward,
        target,
    )
}

/// The split plane (perpendicular to `forward`, at a level-1 node boundary) whose cut has the
/// transition-node share closest to `target`. Candidates are the distinct depths of level-1
/// node centres, except the farthest (all level 0, no transitions); at most 256 are tried.
pub(crate) fn choose_split(page_dims: [u32; 3], forward: DVec3, target: f64) -> Split {
    let forward = forward.normalize_or_zero();
    let n1 = page_dims.map(|d| d.div_ceil(2));
    let mut depths = Vec::new();
    for z in 0..n1[2] {
        for y in 0..n1[1] {
            for x in 0..n1[0] {
                depths.push(level1_depth([x, y, z], forward));
            }
        }
    }
    depths.sort_by(|a, b| a.total_cmp(b));
    depths.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    depths.pop();
    let stride = depths.len().div_ceil(256).max(1);
    let mut best = Split {
        forward,
        threshold: f64::NEG_INFINITY,
        fraction: 0.0,
    };
    for &threshold in depths.iter().step_by(stride) {
        let split = Split {
            forward,
            threshold,
            fraction: 0.0,
        };
        let table = table_of(page_dims, |p| split.level_of(p));
        let fraction = transition_node_fraction(&table, &transition_masks(&table));
        if best.threshold == f64::NEG_INFINITY
            || (fraction - target).abs() < (best.fraction - target).abs()
        {
            best = Split { fraction, ..split };
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(page_dims: [u32; 3], forward: DVec3, tolerance: f64) -> Split {
        let split = choose_split(page_dims, forward, 0.25);
        let table = table_of(page_dims, |p| split.level_of(p));
        let levels: std::collections::BTreeSet<u8> =
            table.entries.iter().map(|e| e.level).collect();
        assert_eq!(levels, [0, 1].into_iter().collect(), "{forward:?}");
        // Level 0 in front: the nearest page corner is fine, the farthest coarse.
        let depth = |p: [u32; 3]| DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64).dot(forward);
        let pages: Vec<[u32; 3]> = (0..table.entries.len())
            .map(|i| table.page_of_linear(i))
            .collect();
        let nearest = pages
            .iter()
            .min_by(|a, b| depth(**a).total_cmp(&depth(**b)));
        let farthest = pages
            .iter()
            .max_by(|a, b| depth(**a).total_cmp(&depth(**b)));
        assert_eq!(split.level_of(*nearest.unwrap()), 0);
        assert_eq!(split.level_of(*farthest.unwrap()), 1);
        let fraction = transition_node_fraction(&table, &transition_masks(&table));
        assert!((fraction - split.fraction).abs() < 1e-12);
        assert!(
            (fraction - 0.25).abs() <= tolerance,
            "{forward:?}: fraction {fraction}"
        );
        split
    }

    #[test]
    fn split_of_an_8_cubed_grid_has_about_a_quarter_transition_nodes() {
        // Oblique, like the bench's orbit view, and both signs of each axis.
        check([8, 8, 8], DVec3::new(0.6, -0.7, -0.35), 0.03);
        check([8, 8, 8], DVec3::new(-0.3, 0.5, 0.8), 0.03);
        // Axis-aligned: whole slabs of level-1 nodes; 2 of 4 slabs fine gives 64/288 = 22 %.
        let split = check([8, 8, 8], DVec3::Z, 0.05);
        assert!((split.fraction - 64.0 / 288.0).abs() < 1e-12);
        // Odd page counts (partial level-1 nodes at the far faces).
        check([7, 9, 5], DVec3::new(1.0, 0.2, 0.4), 0.06);
    }
}
