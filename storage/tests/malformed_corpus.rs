//! The malformed-input campaign of the reliability issue, kept as a test: a few hundred damaged
//! copies of small valid files per reader (truncations, flipped bytes, absurd header values,
//! compression bombs), generated with fixed seeds. Every case must end, within a time bound, in
//! a clean error that names the file, or in a volume; never a panic or a hang. A compressed
//! input that imports must give exactly the voxels of the undamaged file: its checksum trailer
//! is the only defence against silently wrong voxels, and it must be checked.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use strata_storage::import::{import_source, ImportOptions};
use strata_storage::readers::{open_source, RawSpec, ReadOptions};
use strata_storage::{ByteOrder, SampleType};

/// Per case, on a shared 2-core machine in a debug build: a small volume opens in milliseconds.
const CASE_LIMIT: Duration = Duration::from_secs(20);

/// The largest single allocation a case may make. The inputs are a few KB and their volumes
/// 9×7×5; the import's buffers (its memory budget is 256 MiB, spread over many) stay far below.
/// An allocation sized from a damaged header is what this catches (issue 38 saw one of 722 TB
/// abort a process).
const ALLOCATION_LIMIT: usize = 128 << 20;

/// The system allocator, recording the largest single request since the last reset (over all
/// threads: a case's readers and import threads are counted too).
struct LargestAllocation;

static LARGEST: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

// SAFETY: every call is forwarded unchanged to the system allocator; only a size is recorded.
unsafe impl std::alloc::GlobalAlloc for LargestAllocation {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), std::sync::atomic::Ordering::Relaxed);
        // SAFETY: the caller's contract is the system allocator's.
        unsafe { std::alloc::System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: as above.
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), std::sync::atomic::Ordering::Relaxed);
        // SAFETY: as above.
        unsafe { std::alloc::System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new_size: usize) -> *mut u8 {
        LARGEST.fetch_max(new_size, std::sync::atomic::Ordering::Relaxed);
        // SAFETY: as above.
        unsafe { std::alloc::System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: LargestAllocation = LargestAllocation;

const DIMS: [usize; 3] = [9, 7, 5];

fn voxel(i: usize, j: usize, k: usize) -> i16 {
    (i as i16) * 7 + (j as i16) * 3 - (k as i16) * 11 + 100
}

fn voxels_le() -> Vec<u8> {
    let mut out = Vec::new();
    for k in 0..DIMS[2] {
        for j in 0..DIMS[1] {
            for i in 0..DIMS[0] {
                out.extend_from_slice(&voxel(i, j, k).to_le_bytes());
            }
        }
    }
    out
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

fn zlib(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// xorshift64*: fixed seeds, no dependency.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// One valid input and how its damaged copies are judged.
struct Base {
    name: &'static str,
    bytes: Vec<u8>,
    /// Where compressed data starts (a gzip or zlib stream that ends in a checksum), if any.
    compressed_from: Option<usize>,
    /// Text header keys whose values the campaign replaces.
    text_keys: &'static [&'static str],
    raw: Option<RawSpec>,
}

fn nrrd(encoding: &str, data: &[u8]) -> Vec<u8> {
    let mut out = format!(
        "NRRD0004\ntype: int16\ndimension: 3\nsizes: {} {} {}\nspacings: 0.5 0.75 2\nendian: little\nencoding: {encoding}\n\n",
        DIMS[0], DIMS[1], DIMS[2]
    )
    .into_bytes();
    out.extend_from_slice(data);
    out
}

fn mha(compressed: bool, data: &[u8]) -> Vec<u8> {
    let mut out = format!(
        "ObjectType = Image\nNDims = 3\nDimSize = {} {} {}\nElementSpacing = 0.5 0.75 2\nElementType = MET_SHORT\nElementByteOrderMSB = False\nCompressedData = {}\n{}ElementDataFile = LOCAL\n",
        DIMS[0],
        DIMS[1],
        DIMS[2],
        if compressed { "True" } else { "False" },
        if compressed {
            format!("CompressedDataSize = {}\n", data.len())
        } else {
            String::new()
        }
    )
    .into_bytes();
    out.extend_from_slice(data);
    out
}

fn nifti1(data: &[u8]) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    let dim = [
        3i16,
        DIMS[0] as i16,
        DIMS[1] as i16,
        DIMS[2] as i16,
        1,
        1,
        1,
        1,
    ];
    for (i, d) in dim.iter().enumerate() {
        h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
    }
    h[70..72].copy_from_slice(&4i16.to_le_bytes()); // int16
    h[72..74].copy_from_slice(&16i16.to_le_bytes());
    let pixdim = [1f32, 0.5, 0.75, 2.0, 0.0, 0.0, 0.0, 0.0];
    for (i, p) in pixdim.iter().enumerate() {
        h[76 + 4 * i..80 + 4 * i].copy_from_slice(&p.to_le_bytes());
    }
    h[108..112].copy_from_slice(&352f32.to_le_bytes());
    h[252..254].copy_from_slice(&1i16.to_le_bytes()); // qform_code: scanner
    h[344..348].copy_from_slice(b"n+1\0");
    h.extend_from_slice(data);
    h
}

/// A FreeSurfer MGH of the test volume: big-endian header (284 bytes) and int16 voxels.
fn mgh() -> Vec<u8> {
    let mut h = Vec::new();
    for v in [1, DIMS[0] as i32, DIMS[1] as i32, DIMS[2] as i32, 1, 4, 0] {
        h.extend_from_slice(&v.to_be_bytes());
    }
    h.extend_from_slice(&1i16.to_be_bytes()); // goodRASflag
    let floats = [
        0.5f32, 0.75, 2.0, // voxel sizes
        -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, // Mdc: LIA
        1.0, 2.0, 3.0, // centre (RAS)
    ];
    for f in floats {
        h.extend_from_slice(&f.to_be_bytes());
    }
    h.resize(284, 0);
    for c in voxels_le().chunks_exact(2) {
        h.extend_from_slice(&[c[1], c[0]]);
    }
    h
}

fn dicom_slice(k: usize) -> Vec<u8> {
    dicom_slice_edited(k, |_| {})
}

/// One CT slice of the test volume, with `edit` applied to its data set before writing.
fn dicom_slice_edited(k: usize, edit: impl FnOnce(&mut dicom_object::InMemDicomObject)) -> Vec<u8> {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::{tags, uids};
    use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
    let sop_uid = format!("1.2.3.4.{}", k + 1);
    let mut obj = InMemDicomObject::new_empty();
    let mut put = |tag, vr, v: PrimitiveValue| obj.put(DataElement::new(tag, vr, v));
    put(tags::SOP_CLASS_UID, VR::UI, uids::CT_IMAGE_STORAGE.into());
    put(tags::SOP_INSTANCE_UID, VR::UI, sop_uid.clone().into());
    put(tags::MODALITY, VR::CS, "CT".into());
    put(tags::SERIES_INSTANCE_UID, VR::UI, "1.2.3.9".into());
    put(
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        format!("0\\0\\{}", 2 * k).into(),
    );
    put(
        tags::IMAGE_ORIENTATION_PATIENT,
        VR::DS,
        "1\\0\\0\\0\\1\\0".into(),
    );
    put(tags::PIXEL_SPACING, VR::DS, "0.75\\0.5".into());
    put(tags::ROWS, VR::US, PrimitiveValue::from(DIMS[1] as u16));
    put(tags::COLUMNS, VR::US, PrimitiveValue::from(DIMS[0] as u16));
    put(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(1u16));
    put(
        tags::PHOTOMETRIC_INTERPRETATION,
        VR::CS,
        "MONOCHROME2".into(),
    );
    put(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(16u16));
    put(tags::BITS_STORED, VR::US, PrimitiveValue::from(16u16));
    put(tags::HIGH_BIT, VR::US, PrimitiveValue::from(15u16));
    put(
        tags::PIXEL_REPRESENTATION,
        VR::US,
        PrimitiveValue::from(1u16),
    );
    put(tags::RESCALE_SLOPE, VR::DS, "1".into());
    put(tags::RESCALE_INTERCEPT, VR::DS, "0".into());
    let px: Vec<u16> = (0..DIMS[1])
        .flat_map(|j| (0..DIMS[0]).map(move |i| voxel(i, j, k) as u16))
        .collect();
    put(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(px.into()));
    edit(&mut obj);
    let file = obj
        .with_meta(
            FileMetaTableBuilder::new()
                .transfer_syntax(uids::EXPLICIT_VR_LITTLE_ENDIAN)
                .media_storage_sop_class_uid(uids::CT_IMAGE_STORAGE)
                .media_storage_sop_instance_uid(sop_uid),
        )
        .unwrap();
    let mut out = Vec::new();
    file.write_all(&mut out).unwrap();
    out
}

fn bases() -> Vec<Base> {
    let data = voxels_le();
    let nrrd_header_len = nrrd("raw", &[]).len();
    let mha_header_len = mha(true, &zlib(&data)).len() - zlib(&data).len();
    vec![
        Base {
            name: "raw.nrrd",
            bytes: nrrd("raw", &data),
            compressed_from: None,
            text_keys: &[
                "sizes",
                "type",
                "dimension",
                "spacings",
                "endian",
                "encoding",
            ],
            raw: None,
        },
        Base {
            name: "gzip.nrrd",
            bytes: nrrd("gzip", &gzip(&data)),
            compressed_from: Some(nrrd_header_len + 10),
            text_keys: &["sizes", "type", "encoding"],
            raw: None,
        },
        Base {
            name: "plain.nii",
            bytes: nifti1(&data),
            compressed_from: None,
            text_keys: &[],
            raw: None,
        },
        Base {
            name: "packed.nii.gz",
            bytes: gzip(&nifti1(&data)),
            compressed_from: Some(10),
            text_keys: &[],
            raw: None,
        },
        Base {
            name: "raw.mha",
            bytes: mha(false, &data),
            compressed_from: None,
            text_keys: &["DimSize", "ElementType", "NDims", "ElementSpacing"],
            raw: None,
        },
        Base {
            name: "zlib.mha",
            bytes: mha(true, &zlib(&data)),
            compressed_from: Some(mha_header_len + 2),
            text_keys: &["DimSize", "CompressedDataSize", "CompressedData"],
            raw: None,
        },
        Base {
            name: "slice.dcm",
            bytes: dicom_slice(0),
            compressed_from: None,
            text_keys: &[],
            raw: None,
        },
        Base {
            name: "volume.mgh",
            bytes: mgh(),
            compressed_from: None,
            text_keys: &[],
            raw: None,
        },
        Base {
            name: "volume.mgz",
            bytes: gzip(&mgh()),
            compressed_from: Some(10),
            text_keys: &[],
            raw: None,
        },
        Base {
            name: "volume.raw",
            bytes: data.clone(),
            compressed_from: None,
            text_keys: &[],
            raw: Some(RawSpec {
                dims: DIMS.map(|d| d as u64),
                sample_type: SampleType::I16,
                spacing_mm: [1.0, 1.0, 1.0],
                byte_order: ByteOrder::Little,
                header_bytes: 0,
            }),
        },
    ]
}

/// Damaged copies of a base: truncations, single flipped bytes over the whole file, and for text
/// headers each key's value replaced by something absurd.
fn mutations(base: &Base, seed: u64) -> Vec<(String, Vec<u8>)> {
    let mut rng = Rng(seed);
    let len = base.bytes.len();
    let mut out = Vec::new();
    let mut cuts: Vec<usize> = vec![
        0,
        1,
        2,
        4,
        8,
        16,
        128,
        132,
        348,
        352,
        len / 2,
        len - 8,
        len - 4,
        len - 1,
    ];
    for _ in 0..16 {
        cuts.push(rng.below(len));
    }
    for cut in cuts.into_iter().filter(|&c| c < len) {
        out.push((format!("truncated at {cut}"), base.bytes[..cut].to_vec()));
    }
    for _ in 0..60 {
        // Half the flips in the first 400 bytes, where the headers are.
        let at = if rng.below(2) == 0 {
            rng.below(len.min(400))
        } else {
            rng.below(len)
        };
        let mut bytes = base.bytes.clone();
        bytes[at] ^= 1 << rng.below(8);
        out.push((format!("bit flipped at {at}"), bytes));
    }
    let absurd = [
        "",
        "0",
        "-1",
        "abc",
        "nan",
        "1e308",
        "-1e308",
        "1e-30",
        "4294967296",
        "99999 99999 99999",
        "0 0 0",
        "7 7",
        "1 2 3 4 5",
        "inf",
    ];
    let text = String::from_utf8_lossy(&base.bytes).into_owned();
    for key in base.text_keys {
        for value in absurd {
            let Some(start) = text.find(key) else {
                continue;
            };
            let Some(line_end) = text[start..].find('\n') else {
                continue;
            };
            let sep = if text[start..].contains(": ") && !text.starts_with("ObjectType") {
                ": "
            } else {
                " = "
            };
            let mut bytes = base.bytes[..start].to_vec();
            bytes.extend_from_slice(format!("{key}{sep}{value}").as_bytes());
            bytes.extend_from_slice(&base.bytes[start + line_end..]);
            out.push((format!("{key} set to {value:?}"), bytes));
        }
    }
    out
}

enum Outcome {
    Opened { values: Vec<f64>, spacing: [f64; 3] },
    Failed(String),
}

/// Opens and imports `path` on a thread of its own, with a time limit; a panic or a hang is a
/// test failure reported with the case.
fn run_case(path: &Path, options: &ReadOptions, store_dir: &Path) -> Result<Outcome, String> {
    let (path, options, store) = (
        path.to_path_buf(),
        options.clone(),
        store_dir.join("case.strata"),
    );
    let (done, outcome) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("corpus-case".into())
        .spawn(move || {
            let result = std::panic::catch_unwind(|| -> Result<Outcome, String> {
                let opened = match open_source(&path, &options) {
                    Ok(o) => o,
                    Err(e) => return Ok(Outcome::Failed(e.to_string())),
                };
                let mut values = Vec::new();
                let mut slice = Vec::new();
                for k in 0..opened.data.dims[2] {
                    opened.data.read_slice_f64(k, &mut slice);
                    values.extend_from_slice(&slice);
                }
                let spacing = opened.info.geometry.spacing_mm;
                let budget = ImportOptions {
                    memory_budget_bytes: 256 << 20,
                    ..Default::default()
                };
                match import_source(opened, &store, &budget) {
                    Ok(_) => Ok(Outcome::Opened { values, spacing }),
                    Err(e) => Ok(Outcome::Failed(e.to_string())),
                }
            });
            let _ = done.send(result.unwrap_or_else(|p| {
                Err(format!(
                    "PANIC: {}",
                    p.downcast_ref::<String>()
                        .cloned()
                        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default()
                ))
            }));
        })
        .map_err(|e| e.to_string())?;
    outcome
        .recv_timeout(CASE_LIMIT)
        .map_err(|_| format!("HANG: no result within {CASE_LIMIT:?}"))?
}

#[test]
fn every_malformed_input_ends_in_a_clean_error_or_the_right_voxels() {
    let cases = run_corpus(1);
    assert!(cases > 500, "the corpus shrank to {cases} cases");
}

/// The long campaign: the corpus with 100 seeds per reader (about 90 000 cases, minutes).
/// `cargo test -p strata-storage --test malformed_corpus -- --ignored`
#[test]
#[ignore = "long campaign: run with --ignored"]
fn the_corpus_times_one_hundred() {
    let cases = run_corpus(100);
    assert!(cases > 50_000, "{cases}");
}

/// Runs the corpus with `rounds` seeds per base file; panics listing every failed case.
fn run_corpus(rounds: u64) -> usize {
    let dir = tempfile::tempdir().unwrap();
    let staging = dir.path().join("staging");
    std::fs::create_dir_all(&staging).unwrap();
    let expected: Vec<f64> = voxels_le()
        .chunks_exact(2)
        .map(|b| f64::from(i16::from_le_bytes([b[0], b[1]])))
        .collect();
    let mut failures = Vec::new();
    let mut cases = 0usize;
    let mut errors = 0usize;
    let mut max_allocation = 0usize;
    for (b, base) in bases().iter().enumerate() {
        let options = ReadOptions {
            raw: base.raw.clone(),
            staging_dir: Some(staging.clone()),
            ..Default::default()
        };
        // The undamaged file opens with the right voxels (or the corpus proves nothing).
        let case_dir = dir.path().join(format!("case-{b}"));
        std::fs::create_dir_all(&case_dir).unwrap();
        let path = case_dir.join(base.name);
        std::fs::write(&path, &base.bytes).unwrap();
        let reference = match run_case(&path, &options, &case_dir) {
            Ok(Outcome::Opened { values, .. }) => values,
            Ok(Outcome::Failed(e)) => panic!("undamaged {} fails: {e}", base.name),
            Err(e) => panic!("undamaged {}: {e}", base.name),
        };
        // The DICOM base is one slice of the volume; every other base is all of it.
        let whole = if base.name.ends_with(".dcm") {
            DIMS[0] * DIMS[1]
        } else {
            expected.len()
        };
        assert_eq!(reference, expected[..whole], "{}", base.name);
        let seeded =
            (0..rounds).flat_map(|round| mutations(base, 0x5eed_0000 + b as u64 + (round << 32)));
        for (what, bytes) in seeded {
            cases += 1;
            std::fs::write(&path, &bytes).unwrap();
            let first_difference = bytes
                .iter()
                .zip(&base.bytes)
                .position(|(a, b)| a != b)
                .unwrap_or(bytes.len().min(base.bytes.len()));
            LARGEST.store(0, std::sync::atomic::Ordering::Relaxed);
            let outcome = run_case(&path, &options, &case_dir);
            let largest = LARGEST.load(std::sync::atomic::Ordering::Relaxed);
            if largest > ALLOCATION_LIMIT {
                failures.push(format!(
                    "{} ({what}): allocated {largest} bytes at once (limit {ALLOCATION_LIMIT})",
                    base.name
                ));
            }
            max_allocation = max_allocation.max(largest);
            match outcome {
                Err(e) => failures.push(format!("{} ({what}): {e}", base.name)),
                Ok(Outcome::Failed(message)) => {
                    errors += 1;
                    if !message.contains(base.name) {
                        failures.push(format!(
                            "{} ({what}): the error does not name the file: {message}",
                            base.name
                        ));
                    }
                }
                Ok(Outcome::Opened { values, spacing }) => {
                    if spacing
                        .iter()
                        .any(|s| !s.is_finite() || *s < 1e-6 || *s > 1e6)
                    {
                        failures.push(format!(
                            "{} ({what}): imported with absurd spacing {spacing:?}",
                            base.name
                        ));
                    }
                    let in_compressed = base
                        .compressed_from
                        .is_some_and(|from| first_difference >= from);
                    if in_compressed && values != reference {
                        failures.push(format!(
                            "{} ({what}): damaged compressed data imported as different voxels",
                            base.name
                        ));
                    }
                }
            }
        }
    }
    let leaked: Vec<_> = std::fs::read_dir(&staging).unwrap().flatten().collect();
    assert!(
        leaked.is_empty(),
        "staging files left behind: {:?}",
        leaked.iter().map(|e| e.path()).collect::<Vec<PathBuf>>()
    );
    println!(
        "{cases} malformed inputs, {errors} refused with an error naming the file; largest single allocation {max_allocation} bytes"
    );
    assert!(
        failures.is_empty(),
        "{} of {cases} cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
    cases
}

#[test]
fn compression_bombs_and_absurd_claims_are_refused_quickly() {
    let dir = tempfile::tempdir().unwrap();
    let staging = dir.path().join("staging");
    std::fs::create_dir_all(&staging).unwrap();
    let options = ReadOptions {
        staging_dir: Some(staging.clone()),
        ..Default::default()
    };
    // 256 MB of zeros behind a header that promises a 9×7×5 volume: the trailing data is read
    // to reach the CRC, but only up to a bound.
    let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..256 {
        encoder.write_all(&zeros).unwrap();
    }
    let bomb = nrrd("gzip", &encoder.finish().unwrap());
    let path = dir.path().join("bomb.nrrd");
    std::fs::write(&path, bomb).unwrap();
    match run_case(&path, &options, dir.path()) {
        Ok(Outcome::Failed(e)) => assert!(
            e.contains("bomb.nrrd") && e.contains("after the volume"),
            "{e}"
        ),
        Ok(Outcome::Opened { .. }) => {
            panic!("a 256 MB stream behind a 630-byte volume was accepted")
        }
        Err(e) => panic!("{e}"),
    }
    // A header that claims petabytes of gzip data: refused before staging (free space), naming
    // the staging folder and the input.
    let claim = "NRRD0004\ntype: int16\ndimension: 3\nsizes: 60000 60000 60000\nencoding: gzip\n\n";
    let mut bytes = claim.as_bytes().to_vec();
    bytes.extend_from_slice(&gzip(&[0u8; 1024]));
    let path = dir.path().join("claims.nrrd");
    std::fs::write(&path, bytes).unwrap();
    match run_case(&path, &options, dir.path()) {
        Ok(Outcome::Failed(e)) => assert!(e.contains("claims.nrrd"), "{e}"),
        Ok(Outcome::Opened { .. }) => panic!("a petabyte claim was accepted"),
        Err(e) => panic!("{e}"),
    }
    assert_eq!(
        std::fs::read_dir(&staging).unwrap().count(),
        0,
        "staging leaked"
    );
}

#[test]
fn stale_staging_files_of_dead_processes_are_removed_and_live_ones_kept() {
    let dir = tempfile::tempdir().unwrap();
    // A file as a killed import leaves it: no process holds its lock.
    let stale = dir.path().join("strata-staging-dead1234.raw");
    std::fs::write(&stale, b"left by a killed import").unwrap();
    // A live one: locked by its owner.
    let live = dir.path().join("strata-staging-live5678.raw");
    let held = std::fs::File::create(&live).unwrap();
    held.lock().unwrap();
    // Unrelated files are never touched.
    let other = dir.path().join("notes.raw");
    std::fs::write(&other, b"mine").unwrap();
    // Just created (its owner may be about to lock it): left alone until it has aged.
    let fresh = dir.path().join("strata-staging-fresh999.raw");
    std::fs::write(&fresh, b"being created").unwrap();
    let an_hour_ago = std::time::SystemTime::now() - Duration::from_secs(3600);
    for old in [&stale, &live] {
        std::fs::File::options()
            .write(true)
            .open(old)
            .unwrap()
            .set_modified(an_hour_ago)
            .unwrap();
    }
    let removed = strata_storage::readers::remove_stale_staging_files(dir.path());
    assert_eq!(removed, 1);
    assert!(!stale.exists() && live.exists() && other.exists() && fresh.exists());
    drop(held);
}

/// A DICOM folder with link cycles, a FIFO and a damaged slice: the scan ends at once (no
/// exponential fan-out, no blocking read) and the damaged slice is an error, never a gap.
#[cfg(unix)]
#[test]
fn dicom_folder_hazards_end_quickly_and_loudly() {
    let dir = tempfile::tempdir().unwrap();
    let series = dir.path().join("series");
    std::fs::create_dir_all(&series).unwrap();
    for k in 0..DIMS[2] {
        std::fs::write(series.join(format!("s{k}.dcm")), dicom_slice(k)).unwrap();
    }
    // Five links back to the folder itself: followed naively that is 5^depth folders.
    for i in 0..5 {
        std::os::unix::fs::symlink(&series, series.join(format!("loop{i}"))).unwrap();
    }
    let fifo = series.join("pipe.dcm");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    assert!(
        made.is_ok_and(|s| s.success()),
        "mkfifo (coreutils) is needed for this test"
    );
    let options = ReadOptions::default();
    match run_case(&series, &options, dir.path()) {
        Ok(Outcome::Opened { values, .. }) => {
            assert_eq!(values.len(), DIMS.iter().product::<usize>())
        }
        Ok(Outcome::Failed(e)) => panic!("the series should open: {e}"),
        Err(e) => panic!("{e}"),
    }
    // A FIFO given as the input itself.
    match run_case(&fifo, &options, dir.path()) {
        Ok(Outcome::Failed(e)) => assert!(
            e.contains("pipe.dcm") && e.contains("not a regular file"),
            "{e}"
        ),
        Ok(Outcome::Opened { .. }) => panic!("a FIFO opened as a volume"),
        Err(e) => panic!("{e}"),
    }
    // One damaged slice: an error that names it, not a volume with a slice missing.
    let mut damaged = dicom_slice(DIMS[2] - 1);
    damaged.truncate(200);
    std::fs::write(series.join(format!("s{}.dcm", DIMS[2] - 1)), damaged).unwrap();
    match run_case(&series, &options, dir.path()) {
        Ok(Outcome::Failed(e)) => {
            assert!(e.contains("cannot be read") && e.contains("s4.dcm"), "{e}")
        }
        Ok(Outcome::Opened { .. }) => panic!("a series with a damaged slice imported silently"),
        Err(e) => panic!("{e}"),
    }
}

/// Header values that used to be accepted silently (one frame of six, 16-bit data read as
/// 8-bit, voxels read one byte shifted) are errors that say what is wrong.
#[test]
fn inconsistent_headers_are_errors_not_guesses() {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::tags;
    let dir = tempfile::tempdir().unwrap();
    let options = ReadOptions::default();
    let expect_error = |name: &str, bytes: Vec<u8>, needle: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).unwrap();
        match run_case(&path, &options, dir.path()) {
            Ok(Outcome::Failed(e)) => {
                assert!(e.contains(name) && e.contains(needle), "{name}: {e}")
            }
            Ok(Outcome::Opened { .. }) => panic!("{name} was accepted"),
            Err(e) => panic!("{name}: {e}"),
        }
    };
    for frames in ["0", "-1", "abc"] {
        let bytes = dicom_slice_edited(0, |o| {
            o.put(DataElement::new(
                tags::NUMBER_OF_FRAMES,
                VR::IS,
                PrimitiveValue::from(frames),
            ));
        });
        expect_error("frames.dcm", bytes, "NumberOfFrames");
    }
    let bytes = dicom_slice_edited(0, |o| {
        o.put(DataElement::new(
            tags::BITS_ALLOCATED,
            VR::US,
            PrimitiveValue::from(8u16),
        ));
        o.put(DataElement::new(
            tags::BITS_STORED,
            VR::US,
            PrimitiveValue::from(8u16),
        ));
        o.put(DataElement::new(
            tags::HIGH_BIT,
            VR::US,
            PrimitiveValue::from(7u16),
        ));
    });
    expect_error("bits8.dcm", bytes, "PixelData holds");
    for stored in [0u16, 255] {
        let bytes = dicom_slice_edited(0, |o| {
            o.put(DataElement::new(
                tags::BITS_STORED,
                VR::US,
                PrimitiveValue::from(stored),
            ));
        });
        expect_error("stored.dcm", bytes, "BitsStored");
    }
    for offset in [348.0f32, 349.0, 351.0, 352.5] {
        let mut bytes = nifti1(&voxels_le());
        bytes[108..112].copy_from_slice(&offset.to_le_bytes());
        expect_error("offset.nii", bytes, "vox_offset");
    }
}

/// Compressed DICOM (JPEG 2000, JPEG-LS, 12-bit JPEG: pydicom's bundled files) damaged the same
/// way: a clean error naming the file or a volume of the right size, never a panic or a hang.
/// These codestreams carry no checksum, so a flipped bit inside one may decode to other
/// plausible voxels: that cannot be detected and is not judged here. Without pydicom this FAILS
/// with the install command (CI installs it: .ci/run).
#[test]
fn damaged_compressed_dicom_ends_in_a_clean_error_or_a_volume() {
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import pydicom.data, os; print(os.path.join(os.path.dirname(pydicom.data.__file__), 'test_files'))",
        ])
        .output()
        .expect("python3 with pydicom needed: pip install pydicom (CI: .ci/run)");
    assert!(
        out.status.success(),
        "pydicom missing: pip install pydicom (CI: .ci/run)\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let test_files = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
    let dir = tempfile::tempdir().unwrap();
    let staging = dir.path().join("staging");
    std::fs::create_dir_all(&staging).unwrap();
    let options = ReadOptions {
        staging_dir: Some(staging.clone()),
        ..Default::default()
    };
    let mut failures = Vec::new();
    let mut cases = 0;
    for (b, (source, name)) in [
        ("MR_small_jp2klossless.dcm", "j2k.dcm"),
        ("MR_small_jpeg_ls_lossless.dcm", "jls.dcm"),
        ("JPEG2000.dcm", "j2k_lossy.dcm"),
        ("JPGExtended.dcm", "jpeg12.dcm"),
    ]
    .into_iter()
    .enumerate()
    {
        let bytes = std::fs::read(test_files.join(source))
            .unwrap_or_else(|e| panic!("{source} not in pydicom's test files: {e}"));
        let case_dir = dir.path().join(format!("case-{b}"));
        std::fs::create_dir_all(&case_dir).unwrap();
        let path = case_dir.join(name);
        std::fs::write(&path, &bytes).unwrap();
        let size = match run_case(&path, &options, &case_dir) {
            Ok(Outcome::Opened { values, .. }) => values.len(),
            Ok(Outcome::Failed(e)) => panic!("undamaged {source} fails: {e}"),
            Err(e) => panic!("undamaged {source}: {e}"),
        };
        let base = Base {
            name,
            bytes,
            compressed_from: None,
            text_keys: &[],
            raw: None,
        };
        for (what, damaged) in mutations(&base, 0xc0de_0000 + b as u64) {
            cases += 1;
            std::fs::write(&path, &damaged).unwrap();
            match run_case(&path, &options, &case_dir) {
                Err(e) => failures.push(format!("{source} ({what}): {e}")),
                Ok(Outcome::Failed(message)) => {
                    if !message.contains(name) {
                        failures.push(format!(
                            "{source} ({what}): the error does not name the file: {message}"
                        ));
                    }
                }
                Ok(Outcome::Opened { values, .. }) => {
                    // Header damage may legitimately change the size (Rows and Columns are
                    // checked against the codestream); a volume is never larger than claimed.
                    if values.is_empty() || values.len() > 16 * size {
                        failures.push(format!(
                            "{source} ({what}): opened with {} voxels",
                            values.len()
                        ));
                    }
                }
            }
        }
    }
    let leaked: Vec<_> = std::fs::read_dir(&staging).unwrap().flatten().collect();
    assert!(leaked.is_empty(), "staging files left behind: {leaked:?}");
    assert!(cases > 300, "only {cases} cases");
    assert!(
        failures.is_empty(),
        "{} of {cases} cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// Store format 2's bricks join the campaign: damaged records of both codecs (flipped bytes,
/// truncations, extensions, unknown kinds) are refused by the checksum; bodies that pass it but
/// lie (resealed garbage) end in an error or a brick of the right size, never a panic or a large
/// allocation; a damaged brick in a store is reported naming the store; a header naming an
/// unknown codec does not open.
#[test]
fn damaged_format_2_bricks_and_unknown_codecs_end_in_clean_errors() {
    use strata_storage::brick::{decode_brick, seal_record_for_tests};
    use strata_storage::phantom::Phantom;
    use strata_storage::{BrickCodec, Store};
    use strata_types::BrickId;

    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(0x5EED_0017);
    for codec in [BrickCodec::Fast, BrickCodec::Dense] {
        let path = dir.path().join(format!("{}.strata", codec.name()));
        let options = ImportOptions {
            codec,
            ..Default::default()
        };
        // Format 2: its sled header is edited below (format 3's damage: store_v3.rs).
        Phantom::cube(40)
            .write_store_as_format(&path, &options, 2)
            .unwrap();
        // The phantom's body: not a constant brick.
        let id = BrickId::new(0, [0, 0, 0]);
        let record = {
            let store = Store::open(&path).unwrap();
            store.read_brick_record(id).unwrap()
        };
        damage_record(id, &record, codec.name(), &mut rng);
        // Garbage bodies of every kind, resealed.
        for kind in 0..=8u8 {
            let body: Vec<u8> = (0..3 + rng.below(4000)).map(|_| rng.next() as u8).collect();
            let sealed = seal_record_for_tests(id, kind, &body);
            assert!(decode_brick(id, &sealed).is_err(), "kind {kind}");
        }
        // Through the store: read and verify name the store.
        Store::corrupt_brick_for_tests(&path, id, record.len() / 2).unwrap();
        let store = Store::open(&path).unwrap();
        let err = store.read_brick(id).unwrap_err().to_string();
        assert!(err.contains(&format!("{}.strata", codec.name())), "{err}");
        assert_eq!(store.verify(|_, _| {}).unwrap().len(), 1);
    }

    // A header naming a codec this build does not know.
    let path = dir.path().join("fast.strata");
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    let db = loop {
        match sled::open(path.join("db")) {
            Ok(db) => break db,
            Err(_) if std::time::Instant::now() < deadline => {
                std::thread::sleep(Duration::from_millis(20))
            }
            Err(e) => panic!("{e}"),
        }
    };
    let meta = db.open_tree("meta").unwrap();
    let mut header: serde_json::Value =
        serde_json::from_slice(&meta.get("header").unwrap().unwrap()).unwrap();
    header["codec"] = serde_json::json!("brotli-9");
    meta.insert("header", serde_json::to_vec(&header).unwrap())
        .unwrap();
    db.flush().unwrap();
    drop(meta);
    drop(db);
    let err = Store::open(&path).err().unwrap().to_string();
    assert!(err.contains("fast.strata"), "{err}");
    assert!(err.contains("header is unreadable"), "{err}");
    assert!(err.contains("brotli-9"), "{err}");
}

/// Flipped bits, truncations, extensions and changed kinds of a valid brick record: each is
/// refused by the checksum, and the same bytes resealed (checksum right, body lying) end in an
/// error or a brick of the right size.
fn damage_record(id: strata_types::BrickId, record: &[u8], name: &str, rng: &mut Rng) {
    use strata_storage::brick::{decode_brick, seal_record_for_tests};
    use strata_types::BRICK_PAYLOAD_VOXELS;
    for case in 0..300 {
        let mut bad = record.to_vec();
        match case % 4 {
            0 => {
                let at = rng.below(bad.len());
                bad[at] ^= 1 << rng.below(8);
            }
            1 => bad.truncate(rng.below(bad.len())),
            2 => bad.extend((0..1 + rng.below(64)).map(|_| rng.next() as u8)),
            // Any other kind (a u8 record's own kind, 6, is among 6..=255).
            _ => bad[0] = record[0].wrapping_add(1 + rng.below(255) as u8),
        }
        assert!(
            decode_brick(id, &bad).is_err(),
            "{} case {case}: damage not detected",
            name
        );
        // The same bytes resealed: the checksum passes, the decoder must still cope.
        if bad.len() >= 9 {
            let kind = if case % 2 == 0 { record[0] } else { bad[0] };
            let sealed = seal_record_for_tests(id, kind, &bad[9..]);
            if let Ok(voxels) = decode_brick(id, &sealed) {
                assert_eq!(voxels.len(), BRICK_PAYLOAD_VOXELS);
            }
        }
    }
}

/// The u8 kinds (9: column delta, 8: 3-D linear in context streams) under the same campaign: no u8
/// phantom exists, so the records are encoded here from an MR-like brick (a smooth field plus
/// noise) and from full-range noise.
#[test]
fn damaged_u8_bricks_of_the_predicted_kinds_end_in_clean_errors() {
    use strata_storage::brick::{decode_brick, encode_brick, value_range};
    use strata_storage::BrickCodec;
    use strata_types::{BrickId, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};

    let edge = BRICK_PAYLOAD as usize;
    let mut rng = Rng(0x5EED_0008);
    let mr_like: Vec<u16> = (0..BRICK_PAYLOAD_VOXELS)
        .map(|i| {
            let (x, y, z) = (i % edge, i / edge % edge, i / (edge * edge));
            (30 + 2 * x + 3 * y + z + rng.below(9)).min(255) as u16
        })
        .collect();
    let noise: Vec<u16> = (0..BRICK_PAYLOAD_VOXELS)
        .map(|_| rng.below(256) as u16)
        .collect();
    let id = BrickId::new(0, [1, 2, 3]);
    for codec in [BrickCodec::Fast, BrickCodec::Dense] {
        for voxels in [&mr_like, &noise] {
            let record = encode_brick(id, voxels, value_range(voxels), true, codec);
            assert_eq!(decode_brick(id, &record).as_ref(), Ok(voxels));
            damage_record(id, &record, codec.name(), &mut rng);
        }
    }
}

/// DICOM SEG joins the campaign: hand-made header faults (absurd frame counts and sizes,
/// truncated pixel data, frames naming unknown segments or lying off the grid, see
/// `support/make_dicom_seg.py`) must each end in a clean error naming the file; byte
/// truncations and flips of a valid SEG end in such an error or a bounded label volume. Without
/// highdicom this FAILS with the install command (CI installs it: .ci/run).
#[test]
fn malformed_dicom_segs_end_in_clean_errors() {
    let dir = tempfile::tempdir().unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/support/make_dicom_seg.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(dir.path())
        .output()
        .expect("python3 needed");
    assert!(
        out.status.success(),
        "make_dicom_seg.py failed (needs highdicom: pip install highdicom; CI: .ci/run)\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let staging = dir.path().join("staging");
    std::fs::create_dir_all(&staging).unwrap();
    let options = ReadOptions {
        staging_dir: Some(staging.clone()),
        ..Default::default()
    };
    let mut failures = Vec::new();
    let mut cases = 0;
    let mut names: Vec<_> = std::fs::read_dir(dir.path().join("malformed"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    names.sort();
    for path in &names {
        cases += 1;
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        match run_case(path, &options, dir.path()) {
            Err(e) => failures.push(format!("{name}: {e}")),
            Ok(Outcome::Failed(message)) if message.contains(&name) => {}
            Ok(Outcome::Failed(message)) => failures.push(format!(
                "{name}: the error does not name the file: {message}"
            )),
            Ok(Outcome::Opened { .. }) => failures.push(format!("{name}: opened")),
        }
    }
    assert!(cases >= 19, "only {cases} hand-made cases");
    let base = Base {
        name: "seg.dcm",
        bytes: std::fs::read(dir.path().join("binary.dcm")).unwrap(),
        compressed_from: None,
        text_keys: &[],
        raw: None,
    };
    let case_dir = dir.path().join("mutated");
    std::fs::create_dir_all(&case_dir).unwrap();
    let path = case_dir.join("seg.dcm");
    for (what, damaged) in mutations(&base, 0x5e9_0000) {
        cases += 1;
        std::fs::write(&path, &damaged).unwrap();
        match run_case(&path, &options, &case_dir) {
            Err(e) => failures.push(format!("seg.dcm ({what}): {e}")),
            Ok(Outcome::Failed(message)) => {
                if !message.contains("seg.dcm") {
                    failures.push(format!(
                        "seg.dcm ({what}): the error does not name the file: {message}"
                    ));
                }
            }
            Ok(Outcome::Opened { values, .. }) => {
                // A flipped digit of a position may move a frame (more slices); never absurd.
                if values.is_empty() || values.len() > 1 << 24 {
                    failures.push(format!("seg.dcm ({what}): {} voxels", values.len()));
                }
            }
        }
    }
    let leaked: Vec<_> = std::fs::read_dir(&staging).unwrap().flatten().collect();
    assert!(leaked.is_empty(), "staging files left behind: {leaked:?}");
    assert!(cases > 100, "only {cases} cases");
    assert!(
        failures.is_empty(),
        "{} of {cases} cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}
