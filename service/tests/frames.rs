//! A 4-D store served: the open document gives the frame count, each frame's document carries
//! that frame's skeleton, every brick of every frame is its stored record byte for byte (with
//! its ETag, 304 and the guard's token), frame 0 keeps the route older clients use, and a frame
//! past the last is a 404 naming it. The desktop's remote source opens a later frame from these
//! routes and reads the same voxels as the local store.

use std::path::{Path, PathBuf};
use std::time::Duration;

use strata_service::server::{find_stores, start, RunningServer, ServeOptions};
use strata_service::wire::{
    brick_etag, brick_path, decode_open_document, frame_brick_path, frame_document_path,
};
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::VolumeSource;
use strata_storage::brick::verify_record;
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::Store;
use strata_types::BrickId;

const TOKEN: &str = "0123456789abcdef0123456789abcdef";
/// Two bricks along x and y at level 0, so every frame has several levels and bricks.
const DIMS: [usize; 3] = [40, 36, 20];
const FRAMES: usize = 3;

/// Voxel (i, j, k) of frame t: a ramp, shifted by 600 per frame, so frames differ everywhere.
fn value(i: usize, j: usize, k: usize, t: usize) -> i16 {
    (10 * (i + j + k) + 600 * t) as i16
}

/// A 4-D NIfTI-1 (int16, 1 mm voxels) written byte by byte: dim[0] = 4, dim[4] = frames.
fn write_4d_nifti(path: &Path) {
    let mut bytes = vec![0u8; 352];
    bytes[0..4].copy_from_slice(&348i32.to_le_bytes());
    let dim = [
        4i16,
        DIMS[0] as i16,
        DIMS[1] as i16,
        DIMS[2] as i16,
        FRAMES as i16,
        1,
        1,
        1,
    ];
    for (n, d) in dim.iter().enumerate() {
        bytes[40 + 2 * n..42 + 2 * n].copy_from_slice(&d.to_le_bytes());
    }
    bytes[70..72].copy_from_slice(&4i16.to_le_bytes()); // datatype int16
    bytes[72..74].copy_from_slice(&16i16.to_le_bytes()); // bits per voxel
    for (n, p) in [1f32, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0].iter().enumerate() {
        bytes[76 + 4 * n..80 + 4 * n].copy_from_slice(&p.to_le_bytes());
    }
    bytes[108..112].copy_from_slice(&352f32.to_le_bytes()); // vox_offset
    bytes[252..254].copy_from_slice(&1i16.to_le_bytes()); // qform_code: scanner
    bytes[344..348].copy_from_slice(b"n+1\0");
    for t in 0..FRAMES {
        for k in 0..DIMS[2] {
            for j in 0..DIMS[1] {
                for i in 0..DIMS[0] {
                    bytes.extend_from_slice(&value(i, j, k, t).to_le_bytes());
                }
            }
        }
    }
    std::fs::write(path, bytes).expect("write the 4-D NIfTI");
}

fn four_d_store(dir: &Path) -> PathBuf {
    let nifti = dir.join("cine.nii");
    write_4d_nifti(&nifti);
    let store = dir.join("cine.strata");
    let opened = open_source(&nifti, &ReadOptions::default()).expect("read the 4-D NIfTI");
    import_source(opened, &store, &ImportOptions::default()).expect("import the 4-D NIfTI");
    store
}

/// Every frame's records and encoded skeleton, read locally before the server opens the store.
struct Expected {
    generation: String,
    frame_count: u32,
    /// Per frame: (brick, record) for every brick of every level.
    records: Vec<Vec<(BrickId, Vec<u8>)>>,
    skeletons: Vec<Vec<u8>>,
}

fn expected(path: &Path) -> Expected {
    let store = Store::open(path).expect("open the 4-D store");
    let layout = store.layout().clone();
    let frame_count = store.frame_count();
    let mut records = Vec::new();
    let mut skeletons = Vec::new();
    for frame in 0..frame_count {
        let mut of_frame = Vec::new();
        for level in 0..layout.level_count() {
            let n = layout.bricks_in_level(level);
            for z in 0..n[2] {
                for y in 0..n[1] {
                    for x in 0..n[0] {
                        let id = BrickId::new(level as u8, [x, y, z]);
                        let record = store.read_frame_brick_record(frame, id).unwrap();
                        of_frame.push((id, record));
                    }
                }
            }
        }
        records.push(of_frame);
        skeletons.push(store.frame_skeleton(frame).unwrap().encode());
    }
    Expected {
        generation: store.header().generation_id(),
        frame_count,
        records,
        skeletons,
    }
}

fn serve(path: &Path, options: ServeOptions) -> RunningServer {
    start(find_stores(&[path.to_path_buf()]).unwrap(), options).unwrap()
}

fn client() -> reqwest::Client {
    strata_service::install_tls_provider();
    reqwest::Client::builder()
        .no_proxy()
        .timeout(Duration::from_secs(20))
        .build()
        .unwrap()
}

#[test]
fn every_frame_of_a_4d_store_is_served_as_stored() {
    let dir = tempfile::tempdir().unwrap();
    let path = four_d_store(dir.path());
    let want = expected(&path);
    assert_eq!(
        want.frame_count, FRAMES as u32,
        "the store holds every frame"
    );
    assert_ne!(
        want.records[0], want.records[1],
        "frames differ, so serving frame 0 for every frame would fail below"
    );
    let server = serve(
        &path,
        ServeOptions {
            token: Some(TOKEN.into()),
            ..ServeOptions::default()
        },
    );
    let base = server.base_url();
    let generation = &want.generation;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let http = client();
    let get = |path: String| {
        http.get(format!("{base}{path}"))
            .header("authorization", format!("Bearer {TOKEN}"))
    };
    rt.block_on(async {
        // The store's open document gives the frame count.
        let open = get("/v1/stores/cine".into()).send().await.unwrap();
        assert_eq!(open.status(), 200);
        let (doc, _) = decode_open_document(
            &open.bytes().await.unwrap(),
            strata_storage::store::KNOWN_STORE_FEATURES,
        )
        .unwrap();
        assert_eq!(doc.header.frames, FRAMES as u32);

        for frame in 0..want.frame_count {
            // The frame's document: the same JSON, that frame's skeleton; immutable, revalidated.
            let r = get(frame_document_path("cine", generation, frame))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 200, "frame {frame}'s document");
            let etag = r.headers()["etag"].to_str().unwrap().to_string();
            let bytes = r.bytes().await.unwrap();
            let (frame_doc, skeleton) =
                decode_open_document(&bytes, strata_storage::store::KNOWN_STORE_FEATURES).unwrap();
            assert_eq!(frame_doc, doc, "frame {frame} shares the store's JSON");
            assert_eq!(
                skeleton.encode(),
                want.skeletons[frame as usize],
                "frame {frame}'s own skeleton"
            );
            let r = get(frame_document_path("cine", generation, frame))
                .header("if-none-match", &etag)
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 304, "frame {frame}'s document revalidates");

            // Every brick: the stored record of this frame, byte for byte, with its ETag.
            for (id, record) in &want.records[frame as usize] {
                let path = frame_brick_path("cine", generation, frame, *id);
                let r = get(path.clone()).send().await.unwrap();
                assert_eq!(r.status(), 200, "{path}");
                let checksum = verify_record(*id, record).unwrap();
                assert_eq!(
                    r.headers()["etag"],
                    brick_etag(generation, checksum).as_str()
                );
                assert_eq!(&r.bytes().await.unwrap()[..], &record[..], "{path}");
            }
        }

        // Frame 0 through the frame route is the record of the old route.
        let (id, record) = &want.records[0][0];
        let explicit = format!(
            "/v1/stores/cine/g/{generation}/f/0/bricks/{}/0/0/0",
            id.level
        );
        assert_eq!(
            brick_path("cine", generation, *id),
            frame_brick_path("cine", generation, 0, *id)
        );
        let r = get(explicit).send().await.unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(&r.bytes().await.unwrap()[..], &record[..]);

        // Past the last frame: 404 naming the frame and the count.
        for path in [
            frame_document_path("cine", generation, FRAMES as u32),
            frame_brick_path("cine", generation, FRAMES as u32, *id),
        ] {
            let r = get(path.clone()).send().await.unwrap();
            assert_eq!(r.status(), 404, "{path}");
            let text = r.text().await.unwrap();
            assert!(
                text.contains("frame 3 is past the last frame") && text.contains("3 frames"),
                "{path}: {text}"
            );
        }
        // A frame that is not a number: 400 naming it; a stale generation: 404 as for bricks.
        let r = get(format!("/v1/stores/cine/g/{generation}/f/two"))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 400);
        assert!(r.text().await.unwrap().contains("'two'"));
        let r = get(frame_document_path("cine", "stale", 1))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 404);
        // The guard covers the frame routes: no token, no brick.
        let r = http
            .get(format!(
                "{base}{}",
                frame_brick_path("cine", generation, 1, *id)
            ))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 401);
    });
}

#[test]
fn the_remote_source_opens_a_later_frame_and_reads_its_voxels() {
    let dir = tempfile::tempdir().unwrap();
    let path = four_d_store(dir.path());
    let local: Vec<Vec<(BrickId, Vec<u16>)>> = {
        let store = Store::open(&path).unwrap();
        let layout = store.layout().clone();
        (0..store.frame_count())
            .map(|frame| {
                let level = layout.level_count() - 1;
                let n = layout.bricks_in_level(0);
                [
                    BrickId::new(level as u8, [0, 0, 0]),
                    BrickId::new(0, [n[0] - 1, n[1] - 1, 0]),
                ]
                .into_iter()
                .map(|id| (id, store.read_frame_brick(frame, id).unwrap()))
                .collect()
            })
            .collect()
    };
    let server = serve(&path, ServeOptions::default());
    let remote = std::sync::Arc::new(
        RemoteSource::open(&server.store_url("cine"), RemoteOptions::default()).unwrap(),
    );
    assert_eq!(remote.frame_count(), FRAMES as u32);
    for frame in [2u32, 1, 0] {
        let source = remote
            .clone()
            .frame_source(frame)
            .unwrap_or_else(|| panic!("frame {frame} opens"));
        assert_eq!(source.frame_count(), FRAMES as u32);
        for (id, voxels) in &local[frame as usize] {
            assert_eq!(
                &source.read_brick(*id).unwrap(),
                voxels,
                "frame {frame}, brick {id:?}: the remote reads the local store's voxels"
            );
        }
    }
    assert_ne!(
        local[0], local[2],
        "frames differ: the comparison above can fail"
    );
    assert!(
        remote.clone().frame_source(FRAMES as u32).is_none(),
        "no frame past the last"
    );
}
