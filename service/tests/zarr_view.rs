//! `strata serve` presents every store as a read-only OME-Zarr 0.5 image at
//! `/v1/stores/{name}/zarr/`: zarr-python 3 (over HTTP with fsspec) reads every level as the
//! store's voxels and ome-zarr-models validates it; Strata's own OME-Zarr streaming source
//! reads it over HTTP brick for brick equal to the store (aprons included).

use std::collections::HashMap;
use std::path::Path;

use strata_omezarr::streaming::OmeZarrSource;
use strata_omezarr::{ObjectLocation, ObjectStoreOptions};
use strata_service::server::{find_stores, start, ServeOptions};
use strata_source::VolumeSource;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

const READ_OVER_HTTP: &str = r#"
import sys, json, numpy as np, zarr
from zarr.storage import FsspecStore
url, folder = sys.argv[1], sys.argv[2]
meta = json.load(open(folder + "/meta.json"))
g = zarr.open_group(FsspecStore.from_url(url, read_only=True), mode="r")
ms = g.attrs["ome"]["multiscales"][0]
assert len(ms["datasets"]) == len(meta["shapes"])
for level, ds in enumerate(ms["datasets"]):
    shape = meta["shapes"][level]
    expected = np.fromfile(f"{folder}/level{level}.raw", dtype="<u2").reshape(shape)
    got = g[ds["path"]][:]
    assert np.array_equal(got, expected), f"level {level} differs"
from ome_zarr_models.v05.image import Image
Image.from_zarr(g)
print("ok")
"#;

/// Level voxels (apron stripped), z, y, x order, as raw little-endian u16.
fn write_levels(store: &Store, folder: &Path) -> Vec<[u64; 3]> {
    let layout = store.layout().clone();
    let (core, apron, payload) = (
        u64::from(BRICK_CORE),
        u64::from(BRICK_APRON),
        u64::from(BRICK_PAYLOAD),
    );
    let mut shapes = Vec::new();
    for level in 0..layout.level_count() {
        let d = layout.level_dims[level].map(u64::from);
        let mut out = vec![0u16; (d[0] * d[1] * d[2]) as usize];
        let n = layout.bricks_in_level(level);
        for bz in 0..n[2] {
            for by in 0..n[1] {
                for bx in 0..n[0] {
                    let brick = store
                        .read_brick(BrickId::new(level as u8, [bx, by, bz]))
                        .unwrap();
                    let o = [bx, by, bz].map(|b| u64::from(b) * core);
                    for z in 0..core.min(d[2] - o[2]) {
                        for y in 0..core.min(d[1] - o[1]) {
                            for x in 0..core.min(d[0] - o[0]) {
                                let src = ((z + apron) * payload + y + apron) * payload + x + apron;
                                let dst = ((o[2] + z) * d[1] + o[1] + y) * d[0] + o[0] + x;
                                out[dst as usize] = brick[src as usize];
                            }
                        }
                    }
                }
            }
        }
        let bytes: Vec<u8> = out.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(folder.join(format!("level{level}.raw")), bytes).unwrap();
        shapes.push([d[2], d[1], d[0]]);
    }
    shapes
}

#[test]
fn a_served_store_reads_as_ome_zarr_over_http() {
    let work = tempfile::tempdir().unwrap();
    let path = work.path().join("p.strata");
    Phantom { size: [70, 45, 38] }
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    let (shapes, bricks) = {
        let store = Store::open(&path).unwrap();
        let shapes = write_levels(&store, work.path());
        let layout = store.layout().clone();
        let mut bricks = HashMap::new();
        for level in 0..layout.level_count() {
            let n = layout.bricks_in_level(level);
            for z in 0..n[2] {
                for y in 0..n[1] {
                    for x in 0..n[0] {
                        let id = BrickId::new(level as u8, [x, y, z]);
                        bricks.insert(id, store.read_brick(id).unwrap());
                    }
                }
            }
        }
        (shapes, bricks)
    };
    std::fs::write(work.path().join("meta.json"), serde_json_string(&shapes)).unwrap();
    let server = start(
        find_stores(std::slice::from_ref(&path)).unwrap(),
        ServeOptions::default(),
    )
    .unwrap();
    let url = format!("{}/zarr", server.store_url("p"));

    // Strata's own streaming source over HTTP.
    let location = ObjectLocation::open(&url, &ObjectStoreOptions::default(), false).unwrap();
    let streamed = OmeZarrSource::open(location).unwrap();
    assert_eq!(streamed.layout().level_count(), shapes.len());
    for (id, expected) in &bricks {
        assert!(
            &streamed.read_brick(*id).unwrap() == expected,
            "brick {id:?} over the OME-Zarr view differs"
        );
    }

    // zarr-python 3 over HTTP, and the validator.
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
    let have = std::process::Command::new(&python)
        .args(["-c", "import zarr, fsspec, aiohttp, ome_zarr_models"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        have,
        "zarr-python 3 over HTTP is needed for this test: pip install 'zarr>=3' fsspec aiohttp ome-zarr-models (as .ci/run does)"
    );
    let out = std::process::Command::new(&python)
        .arg("-c")
        .arg(READ_OVER_HTTP)
        .arg(&url)
        .arg(work.path())
        .output()
        .unwrap();
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).contains("ok"),
        "zarr-python over HTTP: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // Keys outside the view are 404, not files.
    let missing = ObjectLocation::open(
        &format!("{url}/../../../../etc"),
        &ObjectStoreOptions::default(),
        false,
    )
    .ok()
    .and_then(|l| OmeZarrSource::open(l).ok());
    assert!(missing.is_none());
    server.stop();
}

fn serde_json_string(shapes: &[[u64; 3]]) -> String {
    let inner: Vec<String> = shapes
        .iter()
        .map(|s| format!("[{},{},{}]", s[0], s[1], s[2]))
        .collect();
    format!("{{\"shapes\":[{}]}}", inner.join(","))
}
