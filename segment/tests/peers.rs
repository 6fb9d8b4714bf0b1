//! Round trips through the files other tools read, each checked by an independent reader
//! (nibabel, highdicom, pydicom) and by loading the file back into a layer.

use strata_segment::io::{load_label_file, write_dicom_seg, write_nifti, SegOptions, SegSource};
use strata_segment::{LabelRead, SegmentError};

use crate::common::{
    all_voxels, oblique_geometry, python_with, run_python, sample_layer, write_raw,
};

const NIBABEL_CHECK: &str = r#"
import sys, json
import numpy as np
import nibabel as nib
path, raw, expected = sys.argv[1], sys.argv[2], json.load(open(sys.argv[3]))
img = nib.load(path)
nx, ny, nz = expected["dims"]
assert img.shape == (nx, ny, nz), img.shape
assert img.get_data_dtype() == np.uint16, img.get_data_dtype()
assert int(img.header["intent_code"]) == 1002, img.header["intent_code"]
want = np.fromfile(raw, "<u2").reshape((nz, ny, nx)).transpose(2, 1, 0)
got = np.asanyarray(img.dataobj)
assert got.dtype == np.uint16
assert np.array_equal(got, want), int((got != want).sum())
affine = np.array(expected["affine"])
assert np.allclose(img.affine, affine, atol=1e-4), (img.affine, affine)
assert np.allclose(img.get_qform(), affine, atol=1e-4), (img.get_qform(), affine)
assert int(img.header["sform_code"]) == 1 and int(img.header["qform_code"]) == 1
print(len(np.unique(got)), "labels")
print("OK")
"#;

/// The RAS affine nibabel should report: LPS direction × spacing with x and y negated.
fn ras_affine(g: &strata_types::VolumeGeometry) -> Vec<Vec<f64>> {
    let mut rows = vec![vec![0.0; 4]; 4];
    for (r, row) in rows.iter_mut().take(3).enumerate() {
        let flip = if r < 2 { -1.0 } else { 1.0 };
        for (a, cell) in row.iter_mut().take(3).enumerate() {
            *cell = flip * g.direction[a][r] * g.spacing_mm[a];
        }
        row[3] = flip * g.origin_lps_mm[r];
    }
    rows[3][3] = 1.0;
    rows
}

#[test]
fn a_nifti_label_map_reads_in_nibabel_and_loads_back_equal() {
    let python = python_with(&["nibabel", "numpy"], "nibabel numpy");
    let dir = tempfile::tempdir().expect("tempdir");
    let layer = sample_layer(oblique_geometry([45, 38, 21]));
    let voxels = all_voxels(&layer);
    assert!(voxels.iter().filter(|&&v| v == 300).count() > 10);
    let raw = dir.path().join("expected.raw");
    write_raw(&raw, &voxels);
    let expected = dir.path().join("expected.json");
    let g = layer.geometry().clone();
    std::fs::write(
        &expected,
        serde_json::json!({ "dims": g.dims, "affine": ras_affine(&g) }).to_string(),
    )
    .expect("json");
    for name in ["labels.nii", "labels.nii.gz"] {
        let path = dir.path().join(name);
        write_nifti(&layer, &path).expect("write NIfTI");
        run_python(&python, NIBABEL_CHECK, &[&path, &raw, &expected]);
        let back = load_label_file(&path).expect("load back");
        assert!(
            all_voxels(&back) == voxels,
            "{name}: voxels differ after loading back"
        );
        let bg = back.geometry();
        assert_eq!(bg.dims, g.dims);
        for a in 0..3 {
            assert!((bg.spacing_mm[a] - g.spacing_mm[a]).abs() < 1e-5);
            assert!((bg.origin_lps_mm[a] - g.origin_lps_mm[a]).abs() < 1e-4);
            for c in 0..3 {
                assert!(
                    (bg.direction[a][c] - g.direction[a][c]).abs() < 1e-5,
                    "{bg:?}"
                );
            }
        }
        let values: Vec<u16> = back.segments().iter().map(|s| s.value).collect();
        assert_eq!(values, [1, 2, 300, 65535]);
    }
    // Nothing but the saved file is left in the folder (the temporary file was renamed).
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .expect("dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 4, "{names:?}");
}

#[test]
fn a_failed_save_keeps_the_previous_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("labels.nii");
    let layer = sample_layer(oblique_geometry([20, 20, 8]));
    write_nifti(&layer, &path).expect("first save");
    let before = std::fs::read(&path).expect("read");
    // A layer that fails mid-way (its slice reads fail after the header is written).
    struct Failing<'a>(&'a dyn LabelRead);
    impl LabelRead for Failing<'_> {
        fn geometry(&self) -> &strata_types::VolumeGeometry {
            self.0.geometry()
        }
        fn segments(&self) -> &strata_segment::SegmentTable {
            self.0.segments()
        }
        fn read_slice_k(&self, k: u32, out: &mut [u16]) -> Result<(), SegmentError> {
            if k == 5 {
                return Err(SegmentError::Cancelled);
            }
            self.0.read_slice_k(k, out)
        }
    }
    let mut changed = sample_layer(oblique_geometry([20, 20, 8]));
    changed.edit("more", |w| w.set([1, 1, 1], 9)).expect("edit");
    assert!(write_nifti(&Failing(&changed), &path).is_err());
    assert!(std::fs::read(&path).expect("read") == before);
    assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 1);
}

const SEG_CHECK: &str = r#"
import sys, json
import numpy as np
import pydicom
import highdicom as hd
path, raw, expected = sys.argv[1], sys.argv[2], json.load(open(sys.argv[3]))
nx, ny, nz = expected["dims"]
want = np.fromfile(raw, "<u2").reshape((nz, ny, nx))

ds = pydicom.dcmread(path)
assert ds.Modality == "SEG" and ds.SegmentationType == "BINARY"
assert ds.Rows == ny and ds.Columns == nx
# pydicom alone: unpack the frames and place them by segment and position.
frames = ds.pixel_array.reshape((-1, ny, nx))
assert frames.shape[0] == int(ds.NumberOfFrames)
origin = np.array(expected["origin"]); normal = np.array(expected["normal"])
got = np.zeros_like(want)
for f, group in enumerate(ds.PerFrameFunctionalGroupsSequence):
    seg = int(group.SegmentIdentificationSequence[0].ReferencedSegmentNumber)
    ipp = np.array([float(v) for v in group.PlanePositionSequence[0].ImagePositionPatient])
    k = int(round(float(np.dot(ipp - origin, normal)) / expected["spacing_k"]))
    got[k][frames[f] != 0] = seg
assert np.array_equal(got, want), int((got != want).sum())

# highdicom: segments, names, colours, codes, pixels by source instance.
seg = hd.seg.segread(path)
numbers = list(seg.segment_numbers)
assert numbers == [s["number"] for s in expected["segments"]], numbers
for s in expected["segments"]:
    d = seg.get_segment_description(s["number"])
    assert d.segment_label == s["name"], (d.segment_label, s["name"])
    lab = [int(v) for v in d.RecommendedDisplayCIELabValue]
    assert lab == s["lab"], (lab, s["lab"])
    assert d.segmented_property_type.value == s["type"], d.segmented_property_type
uids = expected["source_uids"]
pixels = seg.get_pixels_by_source_instance(
    source_sop_instance_uids=uids, combine_segments=True, ignore_spatial_locations=True
)
assert pixels.shape == (nz, ny, nx), pixels.shape
assert np.array_equal(pixels, want), int((pixels != want).sum())
assert seg.ReferencedSeriesSequence[0].SeriesInstanceUID == expected["series"]
print("OK")
"#;

#[test]
fn a_dicom_seg_reads_in_highdicom_and_pydicom_and_loads_back_equal() {
    let python = python_with(
        &["highdicom", "pydicom", "numpy"],
        "highdicom pydicom numpy",
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let g = oblique_geometry([41, 36, 17]);
    let layer = sample_layer(g.clone());
    let voxels = all_voxels(&layer);
    let raw = dir.path().join("expected.raw");
    write_raw(&raw, &voxels);
    let source = SegSource {
        study_instance_uid: "1.2.826.0.1.3680043.8.498.1".into(),
        series_instance_uid: "1.2.826.0.1.3680043.8.498.2".into(),
        frame_of_reference_uid: "1.2.826.0.1.3680043.8.498.3".into(),
        sop_class_uid: "1.2.840.10008.5.1.4.1.1.2".into(),
        slice_sop_instance_uids: (0..17)
            .map(|k| format!("1.2.826.0.1.3680043.8.498.10.{}", k + 1))
            .collect(),
        patient_name: "Phantom^Strata".into(),
        patient_id: "P1".into(),
    };
    let path = dir.path().join("labels.dcm");
    let summary = write_dicom_seg(
        &layer,
        &path,
        &SegOptions {
            source: Some(source.clone()),
            ..SegOptions::default()
        },
    )
    .expect("write SEG");
    assert_eq!(summary.segments, 4);
    let segments: Vec<serde_json::Value> = layer
        .segments()
        .iter()
        .map(|s| {
            serde_json::json!({
                "number": s.value,
                "name": s.name,
                "lab": strata_segment::io::dicom_seg::srgb_to_dicom_lab(s.rgb),
                "type": s.category.as_ref().map_or("85756007", |c| c.kind.value.as_str()),
            })
        })
        .collect();
    let normal = g.direction[2];
    let expected = dir.path().join("expected.json");
    std::fs::write(
        &expected,
        serde_json::json!({
            "dims": g.dims,
            "origin": g.origin_lps_mm,
            "normal": normal,
            "spacing_k": g.spacing_mm[2],
            "segments": segments,
            "source_uids": source.slice_sop_instance_uids,
            "series": source.series_instance_uid,
        })
        .to_string(),
    )
    .expect("json");
    run_python(&python, SEG_CHECK, &[&path, &raw, &expected]);

    // Strata's own SEG reader: same grid, voxels, names and colours (±1 through CIELab).
    let back = load_label_file(&path).expect("load SEG back");
    assert_eq!(back.geometry().dims, g.dims);
    assert!(
        all_voxels(&back) == voxels,
        "voxels differ after loading the SEG back"
    );
    for s in layer.segments().iter() {
        let b = back.segments().get(s.value).expect("segment loaded back");
        assert_eq!(b.name, s.name);
        for c in 0..3 {
            assert!(
                (i32::from(b.rgb[c]) - i32::from(s.rgb[c])).abs() <= 1,
                "{:?} {:?}",
                b.rgb,
                s.rgb
            );
        }
    }
}

#[test]
fn a_seg_of_an_empty_table_and_a_wrong_source_are_refused_naming_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("empty.dcm");
    let empty = strata_segment::LabelLayer::new_empty(oblique_geometry([8, 8, 4])).expect("grid");
    let e = write_dicom_seg(&empty, &path, &SegOptions::default())
        .expect_err("no segments")
        .to_string();
    assert!(e.contains("empty.dcm") && e.contains("no segments"), "{e}");
    let layer = sample_layer(oblique_geometry([8, 8, 4]));
    let e = write_dicom_seg(
        &layer,
        &path,
        &SegOptions {
            source: Some(SegSource {
                slice_sop_instance_uids: vec!["1.2.3".into()],
                ..SegSource::default()
            }),
            ..SegOptions::default()
        },
    )
    .expect_err("one source image for four slices")
    .to_string();
    assert!(e.contains("1 images for 4 label slices"), "{e}");
    assert!(!path.exists());
}

#[test]
fn a_file_whose_values_are_not_labels_is_refused_at_load_naming_the_voxel() {
    let python = python_with(&["nibabel", "numpy"], "nibabel numpy");
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("float.nii");
    run_python(
        &python,
        "import sys, numpy as np, nibabel as nib\n\
         a = np.zeros((4, 3, 2), np.float32); a[2, 1, 1] = 1.5\n\
         nib.save(nib.Nifti1Image(a, np.eye(4)), sys.argv[1]); print('OK')",
        &[&path],
    );
    let e = load_label_file(&path).err().expect("refused").to_string();
    assert!(
        e.contains("float.nii") && e.contains("(2, 1, 1) holds 1.5"),
        "{e}"
    );
}

const OMEZARR_CHECK: &str = r#"
import sys, json
import numpy as np
import zarr
from ome_zarr_models.v05.image_label import ImageLabel
from ome_zarr_models.v05.labels import Labels
image, raw, expected = sys.argv[1], sys.argv[2], json.load(open(sys.argv[3]))
nx, ny, nz = expected["dims"]
want = np.fromfile(raw, "<u2").reshape((nz, ny, nx))
labels = Labels.from_zarr(zarr.open_group(image + "/labels", mode="r"))
assert expected["name"] in labels.attributes.ome.labels, labels.attributes
group = zarr.open_group(image + "/labels/" + expected["name"], mode="r")
label = ImageLabel.from_zarr(group)
il = label.attributes.ome.image_label
colors = {c.label_value: list(c.rgba) for c in il.colors}
for s in expected["segments"]:
    assert colors[s["value"]] == s["rgba"], (colors, s)
props = {p.label_value: p for p in il.properties}
for s in expected["segments"]:
    p = props[s["value"]]
    assert getattr(p, "name", None) == s["name"] or p.model_extra.get("name") == s["name"], p
ms = label.attributes.ome.multiscales[0]
ts = ms.datasets[0].coordinateTransformations
assert np.allclose(ts[0].scale, expected["scale"]), ts
arr = zarr.open_array(image + "/labels/" + expected["name"] + "/0", mode="r")
assert arr.dtype == np.uint16 and arr.shape == (nz, ny, nx), (arr.dtype, arr.shape)
got = arr[...]
assert np.array_equal(got, want), int((got != want).sum())
print("OK")
"#;

#[test]
fn omezarr_labels_validate_in_ome_zarr_models_and_read_in_zarr_python() {
    let python = python_with(
        &["zarr", "ome_zarr_models", "numpy"],
        "'zarr>=3' ome-zarr-models numpy",
    );
    let dir = tempfile::tempdir().expect("tempdir");
    // Wider than one 256-voxel tile, so edge chunks and skipped background chunks both occur.
    let g = oblique_geometry([300, 40, 37]);
    let layer = sample_layer(g.clone());
    let voxels = all_voxels(&layer);
    let raw = dir.path().join("expected.raw");
    write_raw(&raw, &voxels);
    let image = dir.path().join("ct.zarr");
    // Twice: the second replaces the first, and a second label image joins the list.
    for name in ["segmentation", "segmentation", "other"] {
        strata_segment::io::write_omezarr_labels(&layer, &image, name).expect("write labels");
    }
    let segments: Vec<serde_json::Value> = layer
        .segments()
        .iter()
        .map(|s| {
            serde_json::json!({
                "value": s.value,
                "name": s.name,
                "rgba": [s.rgb[0], s.rgb[1], s.rgb[2], 255],
            })
        })
        .collect();
    let expected = dir.path().join("expected.json");
    std::fs::write(
        &expected,
        serde_json::json!({
            "dims": g.dims,
            "name": "segmentation",
            "segments": segments,
            "scale": [g.spacing_mm[2], g.spacing_mm[1], g.spacing_mm[0]],
        })
        .to_string(),
    )
    .expect("json");
    run_python(&python, OMEZARR_CHECK, &[&image, &raw, &expected]);
    let listed: serde_json::Value = serde_json::from_slice(
        &std::fs::read(image.join("labels/zarr.json")).expect("labels group"),
    )
    .expect("json");
    assert_eq!(
        listed["attributes"]["ome"]["labels"],
        serde_json::json!(["segmentation", "other"])
    );
    // No temporary or old copies are left beside the label images.
    let mut entries: Vec<String> = std::fs::read_dir(image.join("labels"))
        .expect("dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    entries.sort();
    assert_eq!(entries, ["other", "segmentation", "zarr.json"]);
    // Loaded back: the same voxels, geometry and segments.
    let back = strata_segment::io::load_omezarr_labels(&image.join("labels/segmentation"))
        .expect("load back");
    assert!(
        all_voxels(&back) == voxels,
        "voxels differ after loading back"
    );
    assert_eq!(*back.geometry(), g);
    assert_eq!(back.segments(), layer.segments());
}

#[test]
fn a_strata_label_store_loads_back_equal_reads_bricks_lazily_and_replaces_only_a_store() {
    use strata_segment::io::{load_label_store, write_label_store};
    use strata_segment::BrickKey;

    let dir = tempfile::tempdir().expect("tempdir");
    // Oblique, anisotropic, dims not a multiple of the brick: placement and edges survive.
    let layer = sample_layer(oblique_geometry([70, 45, 38]));
    let store = dir.path().join("labels.strata");
    write_label_store(&layer, &store).expect("saved");
    let back = load_label_file(&store).expect("a store loads through the file loader");
    assert_eq!(back.geometry(), layer.geometry());
    assert_eq!(back.segments(), layer.segments(), "names, colours, values");
    assert!(all_voxels(&back) == all_voxels(&layer), "voxels differ");
    // Bricks the skeleton says are background are skipped without a read. The skeleton's range
    // covers a brick's apron too, so a background brick beside labels is read; but a brick
    // called empty must hold no label (soundness), and a background corner is skipped.
    let [bx, by, bz] = back.grid().bricks();
    let mut skipped = 0;
    for k in 0..bz {
        for j in 0..by {
            for i in 0..bx {
                let key = BrickKey([i, j, k]);
                if back.brick_is_empty(key) {
                    skipped += 1;
                    assert!(
                        layer.brick(key).expect("brick").iter().all(|&l| l == 0),
                        "brick {:?} called empty holds labels",
                        key.0
                    );
                }
            }
        }
    }
    assert!(skipped > 0, "no brick known to be background");

    // Saving over it replaces it once the new store is complete; an edit survives the trip.
    let mut edited = load_label_store(&store).expect("load");
    edited
        .edit("dot", |w| w.set([69, 44, 37], 2))
        .expect("edit")
        .expect("changed");
    write_label_store(&edited, &store).expect("replaced");
    let again = load_label_store(&store).expect("load again");
    assert_eq!(again.get([69, 44, 37]).expect("voxel"), 2);
    assert!(all_voxels(&again) == all_voxels(&edited));
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .expect("list")
        .map(|e| e.expect("entry").file_name())
        .collect();
    assert_eq!(leftovers.len(), 1, "only the store remains: {leftovers:?}");

    // A folder that is not a store is never replaced.
    let other = dir.path().join("not-a-store");
    std::fs::create_dir(&other).expect("mkdir");
    std::fs::write(other.join("notes.txt"), "mine").expect("write");
    let err = write_label_store(&layer, &other).expect_err("refused");
    assert!(
        err.to_string().contains("not-a-store") && err.to_string().contains("not a Strata store"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(other.join("notes.txt")).expect("kept"),
        "mine"
    );

    // A store of a scan (HU = stored − 1024) is refused as labels, naming it.
    let ct = dir.path().join("ct.strata");
    strata_storage::phantom::Phantom::cube(20)
        .write_store(&ct, &Default::default())
        .expect("phantom store");
    let err = match load_label_file(&ct) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a CT store loaded as labels"),
    };
    assert!(err.contains("ct.strata") && err.contains("mapped"), "{err}");
}

/// The zip's entries read back by zarr-python through its ZipStore (the page's OME-Zarr
/// download is read where it lands, unzipped or not).
const ZIPSTORE_CHECK: &str = r#"
import sys, json
import numpy as np
import zarr
path, raw, expected = sys.argv[1], sys.argv[2], json.load(open(sys.argv[3]))
nx, ny, nz = expected["dims"]
want = np.fromfile(raw, "<u2").reshape((nz, ny, nx))
store = zarr.storage.ZipStore(path, mode="r")
labels = zarr.open_group(store=store, path="labels", mode="r")
assert list(labels.attrs["ome"]["labels"]) == ["segmentation"], dict(labels.attrs)
arr = zarr.open_array(store=store, path="labels/segmentation/0", mode="r")
got = arr[...]
assert arr.dtype == np.uint16 and got.shape == want.shape, (arr.dtype, got.shape)
assert np.array_equal(got, want), int((got != want).sum())
print("OK")
"#;

/// The entries of a zip of stored entries (APPNOTE 6.3, no Zip64, no archive comment), by name,
/// read from its central directory and each local header, their CRC-32 checked.
fn stored_zip_entries(bytes: &[u8]) -> std::collections::BTreeMap<String, Vec<u8>> {
    let u16_at = |at: usize| u16::from_le_bytes([bytes[at], bytes[at + 1]]) as usize;
    let u32_at =
        |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
    let end = bytes.len() - 22;
    assert_eq!(
        u32_at(end),
        0x0605_4b50,
        "the end of central directory record"
    );
    let (count, mut at) = (u16_at(end + 10), u32_at(end + 16) as usize);
    let mut entries = std::collections::BTreeMap::new();
    for _ in 0..count {
        assert_eq!(
            u32_at(at),
            0x0201_4b50,
            "a central directory header at {at}"
        );
        assert_eq!(u16_at(at + 10), 0, "stored");
        let (crc, size) = (u32_at(at + 16), u32_at(at + 20) as usize);
        assert_eq!(size, u32_at(at + 24) as usize);
        let name_len = u16_at(at + 28);
        let skip = name_len + u16_at(at + 30) + u16_at(at + 32);
        let name = String::from_utf8(bytes[at + 46..at + 46 + name_len].to_vec()).expect("utf-8");
        let local = u32_at(at + 42) as usize;
        assert_eq!(u32_at(local), 0x0403_4b50, "{name}: its local header");
        let data = local + 30 + u16_at(local + 26) + u16_at(local + 28);
        let content = bytes[data..data + size].to_vec();
        let mut check = flate2::Crc::new();
        check.update(&content);
        assert_eq!(check.sum(), crc, "{name}: CRC-32");
        entries.insert(name, content);
        at += 46 + skip;
    }
    entries
}

/// Every file under `root`, by its `/`-separated path relative to it.
fn files_under(root: &std::path::Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("read_dir") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let relative = path
                    .strip_prefix(root)
                    .expect("under root")
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect::<Vec<_>>()
                    .join("/");
                out.insert(relative, std::fs::read(&path).expect("read"));
            }
        }
    }
    out
}

#[test]
fn the_in_memory_seg_and_zipped_omezarr_are_the_files_the_exports_write() {
    use strata_segment::io::{
        dicom_seg_bytes, load_omezarr_labels, omezarr_labels_zip, write_omezarr_labels, SegStamp,
    };
    // zarr-python's ZipStore reads the zip through Python's zipfile (which checks CRCs).
    let python = python_with(&["zarr", "numpy"], "'zarr>=3' numpy");
    let dir = tempfile::tempdir().expect("tempdir");
    // Wider than one 256-voxel tile: edge chunks and skipped background chunks both occur.
    let g = oblique_geometry([300, 40, 37]);
    let layer = sample_layer(g.clone());
    let voxels = all_voxels(&layer);

    // The zip holds exactly the files `strata seg export --format ome-zarr` writes into a new
    // image folder, byte for byte, at its root.
    let zip_bytes = omezarr_labels_zip(&layer, std::path::Path::new("labels.zip"), "segmentation")
        .expect("zip in memory");
    let image = dir.path().join("ct.zarr");
    write_omezarr_labels(&layer, &image, "segmentation").expect("write labels");
    let folder = files_under(&image);
    let zipped = stored_zip_entries(&zip_bytes);
    assert_eq!(
        zipped.keys().collect::<Vec<_>>(),
        folder.keys().collect::<Vec<_>>(),
        "the zip's entries are the folder's files"
    );
    assert!(
        zipped.len() > 5
            && zipped
                .keys()
                .any(|k| k.starts_with("labels/segmentation/0/c/"))
    );
    for (name, bytes) in &folder {
        assert!(
            zipped[name] == *bytes,
            "{name} differs between the zip and the folder"
        );
    }
    // Unzipped where it lands, it loads back equal.
    let unzipped = dir.path().join("unzipped.zarr");
    for (name, bytes) in &zipped {
        let path = unzipped.join(name);
        std::fs::create_dir_all(path.parent().expect("parent")).expect("mkdir");
        std::fs::write(&path, bytes).expect("write entry");
    }
    let back = load_omezarr_labels(&unzipped.join("labels/segmentation")).expect("load back");
    assert!(all_voxels(&back) == voxels, "voxels differ after the zip");
    assert_eq!(back.segments(), layer.segments());
    let zip_path = dir.path().join("labels.ome.zarr.zip");
    std::fs::write(&zip_path, &zip_bytes).expect("write zip");
    let raw = dir.path().join("expected.raw");
    write_raw(&raw, &voxels);
    let expected = dir.path().join("expected.json");
    std::fs::write(&expected, serde_json::json!({"dims": g.dims}).to_string()).expect("json");
    run_python(&python, ZIPSTORE_CHECK, &[&zip_path, &raw, &expected]);

    // The SEG's bytes in memory load back as the file does.
    let stamp = SegStamp {
        unix_nanos: 1_780_000_000_000_000_000,
        unique: 7,
    };
    let (bytes, summary) = dicom_seg_bytes(
        &layer,
        std::path::Path::new("labels.dcm"),
        &SegOptions::default(),
        &stamp,
    )
    .expect("SEG in memory");
    assert_eq!(summary.segments, layer.segments().len());
    let path = dir.path().join("labels.dcm");
    std::fs::write(&path, &bytes).expect("write SEG");
    let back = load_label_file(&path).expect("load SEG back");
    assert!(all_voxels(&back) == voxels, "voxels differ after the SEG");
    for s in layer.segments().iter() {
        assert_eq!(back.segments().get(s.value).map(|b| &b.name), Some(&s.name));
    }
}
