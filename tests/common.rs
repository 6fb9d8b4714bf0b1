//! Shared helpers of the end-to-end tests: an independent definition of the octree to check
//! stores against, a voxel reader over a store, and access to ../shared/data.

use std::collections::HashMap;
use std::path::PathBuf;

use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

// The brick constants at the width this checker's index arithmetic uses.
const CORE: u64 = BRICK_CORE as u64;
const APRON: u64 = BRICK_APRON as u64;
const PAYLOAD: u64 = BRICK_PAYLOAD as u64;

/// `../shared/data` beside the project, or `None` after printing why the caller skips.
pub fn shared_data(test: &str) -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if dir.is_dir() {
        Some(dir)
    } else {
        println!(
            "SKIP {test}: {} is absent (a fresh clone has no ../shared); real-scan checks not run",
            dir.display()
        );
        None
    }
}

/// Every level built in memory straight from the definition: level L+1 voxel = rounded
/// (halves up) mean of the 2×2×2 level-L voxels at 2i, 2i+1, indices clamped to the level.
pub fn expected_levels(
    dims: [u64; 3],
    level0: Vec<u16>,
    level_count: usize,
) -> Vec<(Vec<u16>, [u64; 3])> {
    let mut levels = vec![(level0, dims)];
    for _ in 1..level_count {
        let (prev, d) = levels.last().expect("level 0 is there");
        let nd = [d[0].div_ceil(2), d[1].div_ceil(2), d[2].div_ceil(2)];
        let at = |x: u64, y: u64, z: u64| {
            prev[(x.min(d[0] - 1) + d[0] * (y.min(d[1] - 1) + d[1] * z.min(d[2] - 1))) as usize]
                as u32
        };
        let mut next = Vec::with_capacity((nd[0] * nd[1] * nd[2]) as usize);
        for z in 0..nd[2] {
            for y in 0..nd[1] {
                for x in 0..nd[0] {
                    let mut sum = 0;
                    for dz in 0..2 {
                        for dy in 0..2 {
                            for dx in 0..2 {
                                sum += at(2 * x + dx, 2 * y + dy, 2 * z + dz);
                            }
                        }
                    }
                    next.push(((sum + 4) / 8) as u16);
                }
            }
        }
        levels.push((next, nd));
    }
    levels
}

/// Asserts every voxel of every brick (core and apron) of every level equals the definition,
/// and the skeleton's ranges and constant flags match the bricks.
pub fn check_store_against(store: &Store, level0: Vec<u16>) {
    let layout = store.layout().clone();
    let dims = store.header().geometry.dims_u64();
    let levels = expected_levels(dims, level0, layout.level_count());
    for (level, (data, d)) in levels.iter().enumerate() {
        assert_eq!(*d, layout.level_dims[level].map(u64::from));
        let nb = layout.bricks_in_level(level).map(u64::from);
        for bz in 0..nb[2] {
            for by in 0..nb[1] {
                for bx in 0..nb[0] {
                    let id = BrickId::new(level as u8, [bx as u32, by as u32, bz as u32]);
                    let brick = store.read_brick(id).expect("brick reads");
                    let node = store.node(id).expect("node in skeleton");
                    let (mut lo, mut hi) = (u16::MAX, 0u16);
                    for (n, &v) in brick.iter().enumerate() {
                        let n = n as u64;
                        let (ex, ey, ez) = (
                            n % PAYLOAD,
                            (n / PAYLOAD) % PAYLOAD,
                            n / (PAYLOAD * PAYLOAD),
                        );
                        // Apron voxels outside the level replicate the edge voxel.
                        let g = |b: u64, e: u64, n: u64| {
                            ((b * CORE + e) as i64 - APRON as i64).clamp(0, n as i64 - 1) as u64
                        };
                        let (x, y, z) = (g(bx, ex, d[0]), g(by, ey, d[1]), g(bz, ez, d[2]));
                        let want = data[(x + d[0] * (y + d[1] * z)) as usize];
                        assert_eq!(
                            v, want,
                            "level {level} brick {:?} voxel ({ex},{ey},{ez})",
                            id.coords
                        );
                        lo = lo.min(v);
                        hi = hi.max(v);
                    }
                    assert_eq!((node.min, node.max), (lo, hi), "skeleton range of {id:?}");
                    assert_eq!(node.is_constant(), lo == hi);
                }
            }
        }
    }
}

pub fn phantom_level0(p: &Phantom) -> Vec<u16> {
    let [nx, ny, nz] = p.size;
    let mut all = vec![0u16; (nx * ny * nz) as usize];
    for (k, chunk) in all.chunks_mut((nx * ny) as usize).enumerate() {
        p.stored_slice(k as u64, chunk);
    }
    all
}

/// Reads single level-0 voxels through the store's bricks, caching decoded bricks.
pub struct VoxelReader<'a> {
    store: &'a Store,
    cache: HashMap<BrickId, Vec<u16>>,
}

impl<'a> VoxelReader<'a> {
    pub fn new(store: &'a Store) -> Self {
        VoxelReader {
            store,
            cache: HashMap::new(),
        }
    }

    pub fn stored(&mut self, index: [u64; 3]) -> u16 {
        let coords = index.map(|i| (i / CORE) as u32);
        let id = BrickId::new(0, coords);
        let brick = self
            .cache
            .entry(id)
            .or_insert_with(|| self.store.read_brick(id).expect("brick reads"));
        let local = index.map(|i| i % CORE + APRON);
        brick[(local[0] + PAYLOAD * (local[1] + PAYLOAD * local[2])) as usize]
    }

    pub fn physical(&mut self, index: [u64; 3]) -> f64 {
        let s = self.stored(index);
        self.store.header().value_mapping.physical(s)
    }
}

/// GPU frame and f64 reference of the same cut of a store (uniform `level`), for image tests.
pub mod render_pair {
    use strata_loader::store_volume::{classify_empty, page_table_for_cut, GpuCut};
    use strata_loader::ResidentBricks;
    use strata_render::reference::{render_reference, ReferenceOptions, ReferenceScene};
    use strata_render::{
        Camera, GpuContext, RenderMode, RenderSettings, TransferFunction, VolumeGeometry,
    };
    use strata_storage::Store;

    pub struct Pair {
        pub gpu: Vec<u8>,
        pub reference: Vec<u8>,
    }

    /// A headless device or a failed test carrying the install hint (never a silent pass).
    pub fn gpu() -> GpuContext {
        GpuContext::headless().unwrap_or_else(|e| panic!("{e}"))
    }

    /// Renders `store` at `level` with `tf` on the GPU and with the reference. `geometry_override`
    /// replaces the store's geometry (to prove a test would notice geometry being ignored).
    pub fn render(
        ctx: &GpuContext,
        store: &Store,
        level: u8,
        tf: &TransferFunction,
        camera_of: impl Fn(&VolumeGeometry) -> Camera,
        settings: &RenderSettings,
        geometry_override: Option<VolumeGeometry>,
    ) -> Pair {
        let header = store.header();
        let geometry = geometry_override.unwrap_or_else(|| header.geometry.clone());
        let mapping = header.value_mapping.mapping;
        let lo = mapping.physical(header.stored_range[0] as f64);
        let hi = mapping.physical(header.stored_range[1] as f64);
        let tf_table = tf.table(lo.min(hi), lo.max(hi));
        let mut table = page_table_for_cut(store, &geometry, |_| level);
        if settings.mode == RenderMode::Dvr {
            classify_empty(store, &mut table, mapping, &tf_table);
        }
        let bricks = ResidentBricks::load(store, &table).unwrap();
        let camera = camera_of(&geometry);
        let mut cut =
            GpuCut::upload(ctx, &bricks, &table, geometry.page_dims(), &tf_table).unwrap();
        let gpu = cut
            .render_blocking(ctx, &geometry, mapping, &camera, settings)
            .unwrap()
            .rgba;
        let reference_scene = ReferenceScene {
            source: &bricks,
            page_table: &table,
            geometry: &geometry,
            mapping,
            transfer_function: tf,
            tf_range: (tf_table.lo, tf_table.hi),
        };
        let reference = render_reference(
            &reference_scene,
            &camera,
            settings,
            ReferenceOptions::default(),
        )
        .unwrap()
        .rgba;
        Pair { gpu, reference }
    }
}
