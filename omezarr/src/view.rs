//! A store presented as a read-only OME-Zarr 0.5 image, built on the fly from its bricks (for
//! `strata serve`'s `/v1/stores/{name}/zarr/...`): the same multiscales and `strata`
//! attribute as an export, arrays `0..N` with unsharded 32³ chunks (one chunk = one brick's
//! core, apron stripped, zstd), and the skeleton object. A chunk that holds only the fill value
//! is absent (404), which Zarr readers take as the fill value.
//!
//! Metadata and chunk bytes are zarrs' own: each level is an array over an in-memory store,
//! a chunk is stored there, taken out and erased, so no codec is written here.

use std::sync::Arc;

use strata_storage::histogram::Histogram;
use strata_storage::store::{NodeInfo, Provenance, Skeleton, StoreStats};
use strata_storage::{StoreHeader, StoredScalar};
use strata_types::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};
use zarrs::array::{codec, data_type, Array, ArrayBuilder};
use zarrs::storage::store::MemoryStore;
use zarrs::storage::{ReadableStorageTraits, StoreKey, WritableStorageTraits};

use crate::metadata::{group_attributes, StrataAttributes, SKELETON_KEY, STRATA_ATTRIBUTE_VERSION};
use crate::{OmeZarrError, Result};

const CHUNK: u64 = BRICK_CORE as u64;

/// What a view answers for a key.
#[derive(Debug, PartialEq)]
pub enum ViewAnswer {
    Found(Vec<u8>),
    /// Not part of the view, or a chunk holding only the fill value.
    NotFound,
}

pub struct ZarrView {
    group_json: Vec<u8>,
    array_json: Vec<Vec<u8>>,
    skeleton: Vec<u8>,
    levels: Vec<Array<MemoryStore>>,
    memory: Arc<MemoryStore>,
    header: StoreHeader,
    fill: u16,
}

impl ZarrView {
    /// The view of a store with this header (identifiers withheld unless `expose_identifiers`).
    pub fn new(
        name: &str,
        header: &StoreHeader,
        histogram: &Histogram,
        stats: &StoreStats,
        skeleton: &Skeleton,
        expose_identifiers: bool,
    ) -> Result<Self> {
        let fail = |e: &dyn std::fmt::Display| {
            OmeZarrError::invalid(name, format!("building the OME-Zarr view: {e}"))
        };
        let memory = Arc::new(MemoryStore::new());
        let narrow = header.stored == StoredScalar::U8;
        let fill = header.stored_range[0];
        let mut exposed = header.clone();
        if !expose_identifiers {
            exposed.description = String::new();
            exposed.provenance = Provenance {
                inputs: Vec::new(),
                ..header.provenance.clone()
            };
        }
        let strata = StrataAttributes {
            version: STRATA_ATTRIBUTE_VERSION,
            header: exposed,
            histogram: histogram.clone(),
            stats: stats.clone(),
            skeleton: SKELETON_KEY.into(),
            // The served bricks are verified by the service's own record checksums; the view's
            // chunks are checked against the skeleton's ranges.
            checksums: None,
        };
        let mut group = zarrs::group::GroupBuilder::new()
            .build(memory.clone(), "/")
            .map_err(|e| fail(&e))?;
        *group.attributes_mut() = group_attributes(name, &strata)?;
        group.store_metadata().map_err(|e| fail(&e))?;
        let mut levels = Vec::new();
        let mut array_json = Vec::new();
        for (level, d) in header.layout.level_dims.iter().enumerate() {
            let shape = vec![u64::from(d[2]), u64::from(d[1]), u64::from(d[0])];
            let mut builder = if narrow {
                ArrayBuilder::new(shape, vec![CHUNK; 3], data_type::uint8(), fill as u8)
            } else {
                ArrayBuilder::new(shape, vec![CHUNK; 3], data_type::uint16(), fill)
            };
            builder
                .bytes_to_bytes_codecs(vec![Arc::new(codec::ZstdCodec::new(3, false))])
                .dimension_names(Some(["z", "y", "x"]));
            let array = builder
                .build(memory.clone(), &format!("/{level}"))
                .map_err(|e| fail(&e))?;
            array.store_metadata().map_err(|e| fail(&e))?;
            array_json.push(
                get(&memory, &format!("{level}/zarr.json"))
                    .ok_or_else(|| fail(&"no array metadata"))?,
            );
            levels.push(array);
        }
        let group_json = get(&memory, "zarr.json").ok_or_else(|| fail(&"no group metadata"))?;
        Ok(ZarrView {
            group_json,
            array_json,
            skeleton: skeleton.encode(),
            levels,
            memory,
            header: header.clone(),
            fill,
        })
    }

    /// The brick a chunk key (`L/c/z/y/x`) names, if it is one of the view's chunks.
    pub fn chunk_brick(&self, key: &str) -> Option<BrickId> {
        let parts: Vec<&str> = key.split('/').collect();
        let [level, "c", z, y, x] = parts.as_slice() else {
            return None;
        };
        let level: u8 = level.parse().ok()?;
        let coords = [x.parse().ok()?, y.parse().ok()?, z.parse().ok()?];
        let id = BrickId::new(level, coords);
        self.header.layout.contains(id).then_some(id)
    }

    /// Answers a metadata key without touching any brick; `None` for a chunk key.
    pub fn metadata(&self, key: &str) -> Option<ViewAnswer> {
        if key == "zarr.json" {
            return Some(ViewAnswer::Found(self.group_json.clone()));
        }
        if key == SKELETON_KEY {
            return Some(ViewAnswer::Found(self.skeleton.clone()));
        }
        if let Some(level) = key.strip_suffix("/zarr.json") {
            return Some(
                match level
                    .parse::<usize>()
                    .ok()
                    .and_then(|l| self.array_json.get(l))
                {
                    Some(json) => ViewAnswer::Found(json.clone()),
                    None => ViewAnswer::NotFound,
                },
            );
        }
        if self.chunk_brick(key).is_some() {
            return None;
        }
        Some(ViewAnswer::NotFound)
    }

    /// Whether a chunk holds only the fill value, from the brick's node (no read).
    pub fn chunk_is_fill(&self, node: Option<NodeInfo>) -> bool {
        node.is_some_and(|n| n.min == self.fill && n.max == self.fill)
    }

    /// Encodes brick `id`'s core (from its 36³ payload) as the chunk's bytes.
    pub fn encode_chunk(&self, id: BrickId, payload: &[u16]) -> Result<ViewAnswer> {
        let level = id.level as usize;
        let array = &self.levels[level];
        let (core, apron, p) = (CHUNK as usize, BRICK_APRON as usize, BRICK_PAYLOAD as usize);
        if payload.len() != p * p * p {
            return Err(OmeZarrError::invalid(
                &self.header.generation,
                "brick payload of the wrong size",
            ));
        }
        // The chunk is the full 32³ even at the volume's edge (zarr's regular grid); voxels past
        // the edge are the apron's replicas, which readers ignore.
        let mut chunk = Vec::with_capacity(core * core * core);
        for z in 0..core {
            for y in 0..core {
                let start = ((z + apron) * p + y + apron) * p + apron;
                chunk.extend_from_slice(&payload[start..start + core]);
            }
        }
        let indices = [
            u64::from(id.coords[2]),
            u64::from(id.coords[1]),
            u64::from(id.coords[0]),
        ];
        let fail = |e: &dyn std::fmt::Display| {
            OmeZarrError::invalid(
                &self.header.generation,
                format!("encoding chunk {indices:?}: {e}"),
            )
        };
        if self.header.stored == StoredScalar::U8 {
            let bytes: Vec<u8> = chunk.iter().map(|&v| v as u8).collect();
            array.store_chunk(&indices, bytes).map_err(|e| fail(&e))?;
        } else {
            array.store_chunk(&indices, chunk).map_err(|e| fail(&e))?;
        }
        let key = format!("{level}/c/{}/{}/{}", indices[0], indices[1], indices[2]);
        let answer = match get(&self.memory, &key) {
            Some(bytes) => ViewAnswer::Found(bytes),
            None => ViewAnswer::NotFound,
        };
        if let Ok(k) = StoreKey::new(&key) {
            let _ = self.memory.erase(&k);
        }
        Ok(answer)
    }
}

fn get(memory: &MemoryStore, key: &str) -> Option<Vec<u8>> {
    let key = StoreKey::new(key).ok()?;
    memory.get(&key).ok().flatten().map(|b| b.to_vec())
}
