"""Writes DICOM SEG test files with highdicom and highdicom's own decode of them.

usage: make_dicom_seg.py OUT_DIR

OUT_DIR/malformed/ receives damaged copies of binary.dcm (each header fault a reader must
refuse cleanly: absurd sizes, truncated pixel data, unknown segments, off-grid frames).

OUT_DIR receives, for each case (binary, fractional): CASE.dcm (the SEG, frames shuffled so
they are unordered; empty frames omitted so they are sparse; 7x5 frames, 35 bits, so frames do
not end on byte boundaries) and CASE.json: highdicom's label volume (voxel (i, j, k) = column,
row, slice, i fastest) and its affine (LPS), plus each segment's name and the sRGB that
highdicom computes from its RecommendedDisplayCIELabValue. Overlaps: where several segments
cover a voxel, the highest segment number is expected (Strata's rule). Fractional: a voxel
belongs to a segment where its fraction is at least 0.5.
"""
import json
import sys
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid, CTImageStorage
import highdicom as hd
from pydicom.sr.codedict import codes

ROWS, COLS, SLICES = 7, 5, 6
SPACING = (0.8, 0.6)  # row spacing, column spacing
GAP = 2.5
# Rotated 30 degrees about the patient z axis: the geometry must carry the orientation.
C, S = np.cos(np.radians(30)), np.sin(np.radians(30))
IOP = [C, S, 0.0, -S, C, 0.0]
ORIGIN = np.array([-10.0, 4.0, 20.0])


def source_series():
    study, series, frame_of_ref = generate_uid(), generate_uid(), generate_uid()
    row_dir, col_dir = np.array(IOP[:3]), np.array(IOP[3:])
    normal = np.cross(row_dir, col_dir)
    out = []
    for k in range(SLICES):
        ds = Dataset()
        ds.file_meta = FileMetaDataset()
        ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds.file_meta.MediaStorageSOPClassUID = CTImageStorage
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.StudyInstanceUID, ds.SeriesInstanceUID = study, series
        ds.FrameOfReferenceUID = frame_of_ref
        ds.Modality = "CT"
        ds.PatientID, ds.PatientName, ds.PatientBirthDate, ds.PatientSex = "p", "Test^Seg", "", "O"
        ds.StudyDate, ds.StudyTime, ds.AccessionNumber, ds.ReferringPhysicianName = "20260101", "000000", "", ""
        ds.StudyID, ds.SeriesNumber, ds.InstanceNumber = "1", 1, k + 1
        ds.Manufacturer = "strata-test"
        ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
        ds.ImagePositionPatient = [float(x) for x in ORIGIN + normal * GAP * k]
        ds.ImageOrientationPatient = IOP
        ds.PixelSpacing = list(SPACING)
        ds.SliceThickness = GAP
        ds.Rows, ds.Columns = ROWS, COLS
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, 0
        ds.PixelData = np.zeros((ROWS, COLS), np.int16).tobytes()
        out.append(ds)
    return out


SEGMENTS = [
    ("liver", (58.0, 40.0, 30.0)),
    ("kidney", (70.0, -50.0, 40.0)),
    ("tumour", (40.0, 20.0, -60.0)),
]


def descriptions():
    out = []
    for n, (name, lab) in enumerate(SEGMENTS, start=1):
        d = hd.seg.SegmentDescription(
            segment_number=n,
            segment_label=name,
            segmented_property_category=codes.SCT.Tissue,
            segmented_property_type=codes.SCT.Tissue,
            algorithm_type=hd.seg.SegmentAlgorithmTypeValues.MANUAL,
        )
        d.RecommendedDisplayCIELabValue = list(hd.color.CIELabColor(*lab).value)
        out.append(d)
    return out


def masks(fractional):
    """(slices, rows, cols, segments): slice 1 has nothing (sparse), 2 and 3 overlap."""
    k, r, c = np.meshgrid(np.arange(SLICES), np.arange(ROWS), np.arange(COLS), indexing="ij")
    f = np.zeros((SLICES, ROWS, COLS, len(SEGMENTS)), np.float32)
    f[..., 0] = np.clip(1.2 - 0.25 * (r + c), 0, 1)  # ramps through 0.5: fractional edges
    f[..., 1] = ((r >= 3) & (c >= 2)).astype(np.float32) * np.clip(0.3 + 0.15 * k, 0, 1)
    f[..., 2] = ((r + 2 * c + k) % 5 == 0).astype(np.float32)
    f[1] = 0.0
    if not fractional:
        f = (f >= 0.5).astype(np.uint8)
    return f


def shuffle_frames(path):
    """Reverses the frame order (pixel data and per-frame groups together)."""
    ds = pydicom.dcmread(path)
    n = int(ds.NumberOfFrames)
    order = list(range(n))[::-1]
    frames = ds.pixel_array.reshape(n, ROWS, COLS)[order]
    ds.PerFrameFunctionalGroupsSequence = [ds.PerFrameFunctionalGroupsSequence[i] for i in order]
    if ds.BitsAllocated == 1:
        ds.PixelData = pydicom.pixels.pack_bits(frames.ravel())
    else:
        ds.PixelData = frames.astype(np.uint8).tobytes()
    if "DimensionIndexSequence" in ds:
        pass  # positions and segment numbers stay in each frame's own groups
    ds.save_as(path)


def main(out_dir):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    src = source_series()
    for case, fractional in [("binary", False), ("fractional", True)]:
        seg = hd.seg.Segmentation(
            source_images=src,
            pixel_array=masks(fractional),
            segmentation_type="FRACTIONAL" if fractional else "BINARY",
            segment_descriptions=descriptions(),
            series_instance_uid=generate_uid(),
            series_number=2,
            sop_instance_uid=generate_uid(),
            instance_number=1,
            manufacturer="strata-test",
            manufacturer_model_name="make_dicom_seg",
            software_versions="1",
            device_serial_number="1",
            max_fractional_value=255,
            omit_empty_frames=True,
        )
        path = out_dir / f"{case}.dcm"
        seg.save_as(path)
        shuffle_frames(path)
        back = hd.seg.segread(path)
        vol = back.get_volume(combine_segments=False, rescale_fractional=True, skip_overlap_checks=True)
        arr = np.asarray(vol.array)  # (slices, rows, cols, segments) in highdicom's volume order
        labels = np.zeros(arr.shape[:3], np.int64)
        for s in range(arr.shape[3]):
            labels[arr[..., s] >= 0.5] = s + 1  # highest segment number wins
        segs = []
        for item in pydicom.dcmread(path).SegmentSequence:
            lab = hd.color.CIELabColor.from_dicom_value(tuple(item.RecommendedDisplayCIELabValue))
            segs.append({"number": int(item.SegmentNumber), "name": str(item.SegmentLabel), "rgb": list(lab.to_rgb())})
        json.dump(
            {
                # highdicom's array axes are (slice, row, column); the affine maps
                # (slice, row, column, 1) to LPS millimetres.
                "shape_krc": list(labels.shape),
                "affine": np.asarray(vol.affine).tolist(),
                "labels_krc": labels.ravel().tolist(),
                "frames": int(back.NumberOfFrames),
                "segments": segs,
            },
            open(out_dir / f"{case}.json", "w"),
        )


def malformed(out_dir):
    out = Path(out_dir) / "malformed"
    out.mkdir(exist_ok=True)
    base = Path(out_dir) / "binary.dcm"

    def case(name, edit):
        ds = pydicom.dcmread(base)
        edit(ds)
        ds.save_as(out / f"{name}.dcm", enforce_file_format=False)

    def frames(n):
        def edit(ds):
            ds.NumberOfFrames = n
        return edit

    def attr(name, value):
        def edit(ds):
            setattr(ds, name, value)
        return edit

    def truncate(ds):
        ds.PixelData = ds.PixelData[: len(ds.PixelData) // 2]

    def unknown_segment(ds):
        ds.PerFrameFunctionalGroupsSequence[3].SegmentIdentificationSequence[0].ReferencedSegmentNumber = 9

    def no_segment(ds):
        del ds.PerFrameFunctionalGroupsSequence[2].SegmentIdentificationSequence

    def off_grid(ds):
        ipp = ds.PerFrameFunctionalGroupsSequence[1].PlanePositionSequence[0].ImagePositionPatient
        ds.PerFrameFunctionalGroupsSequence[1].PlanePositionSequence[0].ImagePositionPatient = [ipp[0] + 0.3, ipp[1], ipp[2]]

    def far_apart(ds):
        ipp = ds.PerFrameFunctionalGroupsSequence[0].PlanePositionSequence[0].ImagePositionPatient
        ds.PerFrameFunctionalGroupsSequence[0].PlanePositionSequence[0].ImagePositionPatient = [ipp[0], ipp[1], ipp[2] + 1e9]

    def no_positions(ds):
        del ds.PerFrameFunctionalGroupsSequence[4].PlanePositionSequence

    def no_segments(ds):
        del ds.SegmentSequence

    def duplicate_segment(ds):
        ds.SegmentSequence[1].SegmentNumber = 1

    def fewer_groups(ds):
        ds.PerFrameFunctionalGroupsSequence = ds.PerFrameFunctionalGroupsSequence[:-1]

    def bad_orientation(ds):
        ds.SharedFunctionalGroupsSequence[0].PlaneOrientationSequence[0].ImageOrientationPatient = [1, 0, 0, 1, 0, 0]

    def zero_spacing(ds):
        ds.SharedFunctionalGroupsSequence[0].PixelMeasuresSequence[0].PixelSpacing = [0, 0]
        ds.SharedFunctionalGroupsSequence[0].PixelMeasuresSequence[0].SpacingBetweenSlices = 0

    for name, edit in [
        ("frames_huge", frames(2**31 - 1)),
        ("frames_more_than_data", frames(400)),
        ("frames_zero", frames(0)),
        ("rows_huge", attr("Rows", 65535)),
        ("columns_zero", attr("Columns", 0)),
        ("bits_16_binary", attr("BitsAllocated", 16)),
        ("fractional_no_max", attr("SegmentationType", "FRACTIONAL")),
        ("type_unknown", attr("SegmentationType", "LABELMAP")),
        ("pixel_data_truncated", truncate),
        ("segment_unknown", unknown_segment),
        ("segment_missing", no_segment),
        ("frame_off_grid", off_grid),
        ("frames_far_apart", far_apart),
        ("position_missing", no_positions),
        ("segments_missing", no_segments),
        ("segment_twice", duplicate_segment),
        ("groups_fewer_than_frames", fewer_groups),
        ("orientation_degenerate", bad_orientation),
        ("spacing_zero", zero_spacing),
    ]:
        case(name, edit)


if __name__ == "__main__":
    main(sys.argv[1])
    malformed(sys.argv[1])
