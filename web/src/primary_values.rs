//! The primary's level-0 values as the page's segmentation tools read them (issue 52 item 7),
//! out of core: the page streams the primary brick by brick and keeps no level 0, so a tool
//! that reads values (region growing, statistics, the brush's value range) reads them from the
//! level-0 bricks resident here, and names the ones that are not.
//!
//! - [`ResidentBricks`] keeps decoded level-0 bricks, least recently used evicted first, at
//!   most [`PRIMARY_VALUES_CACHE_BYTES`] (about 700 bricks of 36³ u16: a 512³ volume's 4096
//!   bricks do not all fit; a tool whose work reaches more than the bound is refused with
//!   [`PrimaryValuesError::TooManyBricks`] rather than thrashing).
//! - [`ResidentIntensity`] is strata-segment's [`Intensity`] over them, the same conversion a
//!   store read natively goes through (`strata_segment::intensity::label_brick_from_level0`,
//!   the label grid being the primary's own). A brick not resident reads as NaN (no range
//!   admits it) and is recorded: the tool's answer is then discarded by its caller, the bricks
//!   asked for, and the tool run again once they are in, as strata-slices' oblique resampling
//!   answers "not resident yet" (`LevelBricks`). Nothing waits: each run uses what is there.
//! - The fetching itself (the served store's asynchronous path, or the page's in-memory
//!   sample) is `primary_values_page.rs`, wasm32 only; this part is platform independent and
//!   tested natively below (missing bricks named, the cache's bound, its eviction order).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use strata_segment::intensity::{label_brick_from_level0, Intensity};
use strata_segment::{BrickKey, LabelGrid, SegmentError};
use strata_types::{ValueMapping, BRICK_PAYLOAD_VOXELS};

/// Bytes of decoded level-0 bricks the page keeps for its value-reading tools: 64 MiB,
/// [`resident_capacity_bricks`] bricks, beside the slice views' and the 3D view's own caches.
pub const PRIMARY_VALUES_CACHE_BYTES: usize = 64 << 20;

/// Bricks [`PRIMARY_VALUES_CACHE_BYTES`] holds.
pub const fn resident_capacity_bricks(budget_bytes: usize) -> usize {
    let brick_bytes = BRICK_PAYLOAD_VOXELS * 2;
    let bricks = budget_bytes / brick_bytes;
    if bricks == 0 {
        1
    } else {
        bricks
    }
}

/// Why a value-reading tool cannot run in the page.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PrimaryValuesError {
    #[error(
        "this needs {needed} level-0 bricks of the volume at once, and the page keeps at most \
         {capacity} ({budget_mib} MiB): use a smaller region (a lower voxel cap) or the \
         desktop viewer"
    )]
    TooManyBricks {
        needed: usize,
        capacity: usize,
        budget_mib: usize,
    },
}

/// Decoded level-0 bricks (36³ stored values, apron included) by brick coordinates, bounded in
/// count, least recently used evicted first.
pub struct ResidentBricks {
    capacity: usize,
    bricks: HashMap<[u32; 3], (Arc<Vec<u16>>, u64)>,
    /// Ticks at each insert or use, so the least recently used is the smallest stamp.
    clock: u64,
}

impl ResidentBricks {
    /// At most `capacity` bricks (at least one).
    pub fn new(capacity: usize) -> Self {
        ResidentBricks {
            capacity: capacity.max(1),
            bricks: HashMap::new(),
            clock: 0,
        }
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn len(&self) -> usize {
        self.bricks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bricks.is_empty()
    }

    pub fn contains(&self, coords: [u32; 3]) -> bool {
        self.bricks.contains_key(&coords)
    }

    /// The brick, if resident (not marked used: [`Self::touch`] does that after a tool's run,
    /// which reads through a shared reference).
    pub fn get(&self, coords: [u32; 3]) -> Option<&Arc<Vec<u16>>> {
        self.bricks.get(&coords).map(|(brick, _)| brick)
    }

    /// Marks bricks as just used, so the ones a tool is working with outlive older ones.
    pub fn touch(&mut self, used: &[[u32; 3]]) {
        for coords in used {
            self.clock += 1;
            if let Some((_, stamp)) = self.bricks.get_mut(coords) {
                *stamp = self.clock;
            }
        }
    }

    /// Keeps `brick`, evicting the least recently used beyond the bound (a scan of at most a
    /// few hundred stamps, once per arriving brick).
    pub fn insert(&mut self, coords: [u32; 3], brick: Arc<Vec<u16>>) {
        self.clock += 1;
        self.bricks.insert(coords, (brick, self.clock));
        while self.bricks.len() > self.capacity {
            let oldest = self
                .bricks
                .iter()
                .min_by_key(|(_, (_, stamp))| *stamp)
                .map(|(coords, _)| *coords);
            match oldest {
                Some(coords) => {
                    self.bricks.remove(&coords);
                }
                None => break,
            }
        }
    }
}

/// What one run of a tool over [`ResidentIntensity`] read: the bricks it used and those it
/// found missing, each once, in the order first asked for.
#[derive(Debug, Default, PartialEq)]
pub struct BricksRead {
    pub used: Vec<[u32; 3]>,
    pub missing: Vec<[u32; 3]>,
}

impl BricksRead {
    /// `Ok` when the run may be kept as it is; the bricks to fetch otherwise (`Err` when they
    /// and the ones used cannot all be resident at once).
    pub fn check(&self, capacity: usize) -> Result<(), PrimaryValuesError> {
        let needed = self.used.len() + self.missing.len();
        if needed > capacity {
            return Err(PrimaryValuesError::TooManyBricks {
                needed,
                capacity,
                budget_mib: (capacity * BRICK_PAYLOAD_VOXELS * 2) >> 20,
            });
        }
        Ok(())
    }
}

/// The primary's physical values on its own grid from the resident level-0 bricks; a brick not
/// resident reads as NaN and is recorded ([`Self::read`]).
pub struct ResidentIntensity<'a> {
    resident: &'a ResidentBricks,
    mapping: ValueMapping,
    unit: &'a str,
    /// The primary's voxels: the label grid must be the primary's own.
    dims: [u32; 3],
    // The tools take an `Intensity: Send + Sync` by shared reference; the page has one thread,
    // so the lock is never contended.
    read: Mutex<BricksRead>,
}

impl<'a> ResidentIntensity<'a> {
    pub fn new(
        resident: &'a ResidentBricks,
        mapping: ValueMapping,
        unit: &'a str,
        dims: [u32; 3],
    ) -> Self {
        ResidentIntensity {
            resident,
            mapping,
            unit,
            dims,
            read: Mutex::new(BricksRead::default()),
        }
    }

    /// The bricks the run used and those it found missing.
    pub fn read(self) -> BricksRead {
        self.read
            .into_inner()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn note(&self, coords: [u32; 3], resident: bool) {
        let mut read = self
            .read
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let list = if resident {
            &mut read.used
        } else {
            &mut read.missing
        };
        if !list.contains(&coords) {
            list.push(coords);
        }
    }
}

impl Intensity for ResidentIntensity<'_> {
    fn value(&self, grid: &LabelGrid, voxel: [u32; 3]) -> Result<f32, SegmentError> {
        if !grid.contains(voxel.map(i64::from)) {
            return Err(SegmentError::OutOfBounds {
                voxel: voxel.map(i64::from),
                dims: grid.dims(),
            });
        }
        let (key, at) = grid.brick_of(voxel);
        let mut out = vec![0.0; strata_segment::LABEL_BRICK_VOXELS];
        self.read_brick(grid, key, &mut out)?;
        Ok(out[at])
    }

    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [f32],
    ) -> Result<(), SegmentError> {
        if grid.dims() != self.dims {
            return Err(SegmentError::Grid(format!(
                "the page reads the primary's values on its own {:?} grid, asked for {:?}",
                self.dims,
                grid.dims()
            )));
        }
        match self.resident.get(key.0) {
            Some(payload) => {
                self.note(key.0, true);
                let mapping = self.mapping;
                label_brick_from_level0(
                    grid,
                    key,
                    payload,
                    &|s| mapping.physical(f64::from(s)),
                    out,
                )
            }
            None => {
                self.note(key.0, false);
                out.fill(f32::NAN);
                Ok(())
            }
        }
    }

    fn unit(&self) -> &str {
        self.unit
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_segment::tools::grow::{plan_grow, GrowCriterion};
    use strata_segment::LabelLayer;
    use strata_types::{VolumeGeometry, BRICK_APRON, BRICK_PAYLOAD};

    /// A level-0 payload whose every voxel stores `value`.
    fn flat_brick(value: u16) -> Arc<Vec<u16>> {
        Arc::new(vec![value; BRICK_PAYLOAD_VOXELS])
    }

    #[test]
    fn the_cache_keeps_its_bound_and_evicts_the_least_recently_used() {
        let mut cache = ResidentBricks::new(3);
        for i in 0..3 {
            cache.insert([i, 0, 0], flat_brick(i as u16));
        }
        // Brick 0 used by a tool: brick 1 is now the oldest.
        cache.touch(&[[0, 0, 0]]);
        cache.insert([3, 0, 0], flat_brick(3));
        assert_eq!(cache.len(), 3);
        assert!(cache.contains([0, 0, 0]) && !cache.contains([1, 0, 0]));
        assert!(cache.contains([2, 0, 0]) && cache.contains([3, 0, 0]));
        for i in 4..40 {
            cache.insert([i, 0, 0], flat_brick(0));
            assert!(cache.len() <= 3, "{} bricks past the bound", cache.len());
        }
        assert_eq!(
            resident_capacity_bricks(PRIMARY_VALUES_CACHE_BYTES),
            (64 << 20) / (BRICK_PAYLOAD_VOXELS * 2)
        );
        assert_eq!(resident_capacity_bricks(0), 1);
    }

    #[test]
    fn missing_bricks_read_as_nan_and_are_named_once_each() {
        let grid = LabelGrid::new(VolumeGeometry::axis_aligned([64, 40, 32], [1.0; 3])).unwrap();
        let mut cache = ResidentBricks::new(8);
        cache.insert([0, 0, 0], flat_brick(1100));
        let mapping = ValueMapping {
            slope: 1.0,
            intercept: -1024.0,
        };
        let intensity = ResidentIntensity::new(&cache, mapping, "HU", grid.dims());
        let mut out = vec![0.0; strata_segment::LABEL_BRICK_VOXELS];
        intensity
            .read_brick(&grid, BrickKey([0, 0, 0]), &mut out)
            .unwrap();
        assert!(out.iter().all(|&v| v == 76.0), "1100 stored is 76 HU");
        for _ in 0..2 {
            intensity
                .read_brick(&grid, BrickKey([1, 0, 0]), &mut out)
                .unwrap();
            assert!(out.iter().all(|v| v.is_nan()));
        }
        assert!(intensity.value(&grid, [40, 0, 0]).unwrap().is_nan());
        intensity
            .read_brick(&grid, BrickKey([0, 1, 0]), &mut out)
            .unwrap();
        assert_eq!(intensity.unit(), "HU");
        let read = intensity.read();
        assert_eq!(read.used, vec![[0, 0, 0]]);
        assert_eq!(read.missing, vec![[1, 0, 0], [0, 1, 0]]);
        assert_eq!(read.check(3), Ok(()));
        assert!(matches!(
            read.check(2),
            Err(PrimaryValuesError::TooManyBricks {
                needed: 3,
                capacity: 2,
                ..
            })
        ));
        // Another grid than the primary's is refused, not read wrongly.
        let other = LabelGrid::new(VolumeGeometry::axis_aligned([64, 40, 33], [1.0; 3])).unwrap();
        let intensity = ResidentIntensity::new(&cache, mapping, "HU", grid.dims());
        assert!(intensity
            .read_brick(&other, BrickKey([0, 0, 0]), &mut out)
            .is_err());
    }

    /// A grow over resident bricks only reaches the missing one's border and names it; once it
    /// is resident the grow's run is complete and takes both bricks.
    #[test]
    fn a_grow_names_the_brick_it_lacks_and_completes_once_it_is_resident() {
        let grid_geometry = VolumeGeometry::axis_aligned([64, 32, 32], [1.0; 3]);
        let mut layer = LabelLayer::new_empty(grid_geometry).unwrap();
        let label = layer.segments_mut().add("grown").unwrap();
        let mapping = ValueMapping::default();
        // Both bricks hold 500 in their core; the apron's values are never read.
        let brick = |core: u16| {
            let edge = BRICK_PAYLOAD as usize;
            let apron = BRICK_APRON as usize;
            let mut v = vec![0u16; BRICK_PAYLOAD_VOXELS];
            for k in apron..edge - apron {
                for j in apron..edge - apron {
                    for i in apron..edge - apron {
                        v[(k * edge + j) * edge + i] = core;
                    }
                }
            }
            Arc::new(v)
        };
        let mut cache = ResidentBricks::new(4);
        cache.insert([0, 0, 0], brick(500));
        let criterion =
            GrowCriterion::Range(strata_segment::intensity::ValueRange::new(400.0, 600.0).unwrap());
        let run = |cache: &ResidentBricks, layer: &LabelLayer| {
            let intensity = ResidentIntensity::new(cache, mapping, "", [64, 32, 32]);
            let plan = plan_grow(
                layer,
                &intensity,
                [3, 4, 5],
                label,
                criterion,
                u64::MAX,
                &mut |_| {},
                None,
            )
            .unwrap();
            (plan, intensity.read())
        };
        let (partial, read) = run(&cache, &layer);
        assert_eq!(partial.voxels(), 32 * 32 * 32);
        assert_eq!(read.missing, vec![[1, 0, 0]]);
        cache.insert([1, 0, 0], brick(500));
        let (whole, read) = run(&cache, &layer);
        assert!(read.missing.is_empty());
        assert_eq!(whole.voxels(), 64 * 32 * 32);
        let outcome = whole.apply(&mut layer).unwrap();
        assert!(outcome.edit.is_some() && !outcome.stopped_at_cap);
        assert_eq!(layer.get([63, 31, 31]).unwrap(), label);
    }
}
