//! The codec table of `strata-bench codecs` from the storage crate alone (its release build is
//! far cheaper than the app's): `cargo run --release -p strata-storage --example codec_table
//! [SCAN...]` (default: chris_t1, FLAIR and dicom-mr-3slices of shared/data, after the 256³
//! phantom). Same encode/decode calls and the same timing (thread CPU time) as the app's bench;
//! for fast u8 it also prints where a decode goes (checksum alone, zstd alone, whole decode).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use strata_storage::brick::{decode_brick, encode_brick, value_range};
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::phantom::Phantom;
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::{BrickCodec, Store};
use strata_types::{BrickId, BRICK_PAYLOAD_VOXELS};

type Result<T> = std::result::Result<T, Box<dyn std::error::Error>>;

fn thread_cpu_seconds() -> Option<f64> {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime only writes the timespec we pass, which outlives the call.
    (unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) } == 0)
        .then_some(t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9)
}

fn speeds(store: &Store, codec: BrickCodec) -> Result<(f64, f64)> {
    let layout = store.layout().clone();
    let narrow = store.header().stored == strata_storage::StoredScalar::U8;
    let mut bricks: Vec<(BrickId, Vec<u16>)> = Vec::new();
    'levels: for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let id = BrickId::new(level as u8, [x, y, z]);
                    if store.node(id).is_some_and(|node| !node.is_constant()) {
                        bricks.push((id, store.read_brick(id)?));
                        if bricks.len() >= 400 {
                            break 'levels;
                        }
                    }
                }
            }
        }
    }
    let sample_bytes = (BRICK_PAYLOAD_VOXELS * if narrow { 1 } else { 2 }) as f64;
    let timed = |pass: &mut dyn FnMut()| {
        let (t, cpu, mut passes) = (Instant::now(), thread_cpu_seconds(), 0u32);
        while passes == 0 || t.elapsed() < Duration::from_millis(1000) {
            pass();
            passes += 1;
        }
        let seconds = match (cpu, thread_cpu_seconds()) {
            (Some(a), Some(b)) if b > a => b - a,
            _ => t.elapsed().as_secs_f64(),
        };
        bricks.len() as f64 * f64::from(passes) * sample_bytes / 1e6 / seconds
    };
    let records: Vec<(BrickId, Vec<u8>)> = bricks
        .iter()
        .map(|(id, v)| (*id, encode_brick(*id, v, value_range(v), narrow, codec)))
        .collect();
    let compress = timed(&mut || {
        for (id, v) in &bricks {
            std::hint::black_box(encode_brick(*id, v, value_range(v), narrow, codec));
        }
    });
    for ((id, r), (_, v)) in records.iter().zip(&bricks) {
        if decode_brick(*id, r).as_ref() != Ok(v) {
            return Err(format!("brick {id:?} did not round-trip").into());
        }
    }
    let decompress = timed(&mut || {
        for (id, r) in &records {
            std::hint::black_box(decode_brick(*id, r).ok());
        }
    });
    if narrow && codec == BrickCodec::Fast {
        // Where a fast u8 decode goes: the checksum alone, zstd alone (a reused context into a
        // reused buffer), and the whole decode.
        let checksum = timed(&mut || {
            for (id, r) in &records {
                std::hint::black_box(strata_storage::brick::verify_record(*id, r).ok());
            }
        });
        let mut d = zstd::bulk::Decompressor::new()?;
        let mut buf = Vec::with_capacity(BRICK_PAYLOAD_VOXELS);
        let zstd_only = timed(&mut || {
            for (_, r) in &records {
                buf.clear();
                std::hint::black_box(d.decompress_to_buffer(&r[9..], &mut buf).ok());
            }
        });
        println!("  fast u8 decode profile, MB/s of samples: checksum {checksum:.0}, zstd alone {zstd_only:.0}, whole decode {decompress:.0}");
    }
    Ok((compress, decompress))
}

fn main() -> Result<()> {
    let scratch = tempfile::tempdir()?;
    let mut inputs: Vec<(String, Option<PathBuf>)> = vec![("phantom 256^3".into(), None)];
    let args: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
    let data = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/niivue"
    ));
    let scans = if args.is_empty() {
        ["chris_t1.nii.gz", "FLAIR.nrrd", "dicom-mr-3slices"]
            .iter()
            .map(|s| data.join(s))
            .collect()
    } else {
        args
    };
    inputs.extend(
        scans
            .into_iter()
            .map(|p| (p.display().to_string(), Some(p))),
    );
    println!(
        "{:<60} {:>6} {:>10} {:>8} {:>10} {:>8}",
        "input", "codec", "stored MB", "vs lz4", "comp MB/s", "dec MB/s"
    );
    for (name, path) in inputs {
        let mut lz4 = None;
        for codec in BrickCodec::ALL {
            let store_path = scratch.path().join(format!("{}.strata", codec.name()));
            let _ = std::fs::remove_dir_all(&store_path);
            let options = ImportOptions {
                codec,
                ..Default::default()
            };
            let report = match &path {
                None => Phantom::cube(256).write_store(&store_path, &options)?,
                Some(p) => import_source(
                    open_source(p, &ReadOptions::default())?,
                    &store_path,
                    &options,
                )?,
            };
            let bytes = report.stats.compressed_bytes;
            let base = *lz4.get_or_insert(bytes);
            let store = Store::open(&store_path)?;
            let (c, d) = speeds(&store, codec)?;
            println!(
                "{:<60} {:>6} {:>10.2} {:>7.3}x {:>10.0} {:>8.0}",
                name,
                codec.name(),
                bytes as f64 / 1e6,
                bytes as f64 / base as f64,
                c,
                d
            );
            store.close()?;
        }
    }
    Ok(())
}
