//! The page's segmentation downloads beyond the NIfTI label map (issue 52 item 7): a DICOM SEG
//! and OME-Zarr labels, the bytes `strata seg export --format seg|ome-zarr` writes
//! (strata-segment's `io::dicom_seg` and `io::omezarr_labels`), made in memory and handed to
//! the browser's download as a Blob.
//!
//! The SEG: a volume in the page comes from a served store, not a DICOM series, so (as the
//! desktop's SEG of a non-DICOM primary) it references no source images: it gets a new study
//! and frame of reference UID, no ReferencedSeriesSequence, no DerivationImageSequence; its
//! geometry is the primary's grid. Its dates and new UIDs come from the browser's clock and
//! `Math.random` (wasm32 has neither clock nor process id in `std`).
//!
//! OME-Zarr is a folder: it downloads as one zip with the image's Zarr hierarchy at its root
//! (`zarr.json`, `labels/zarr.json`, `labels/segmentation/…`; what zarr-python's `ZipStore`
//! and the NGFF zipped proposal read), entries stored.

use std::path::Path;

use strata_segment::io::{dicom_seg_bytes, omezarr_labels_zip, SegOptions, SegStamp};
use strata_segment::{LabelLayer, SegmentError};
use wasm_bindgen::{JsCast, JsValue};

/// Why a download was not made.
#[derive(Debug, thiserror::Error)]
pub enum DownloadError {
    /// The writer refused the layer (a format's limit, no segment to save).
    #[error(transparent)]
    Labels(#[from] SegmentError),
    /// The browser refused the Blob, its URL or the anchor.
    #[error("download of {name}: {message}")]
    Browser { name: &'static str, message: String },
}

/// The file name the SEG download offers.
pub const SEG_NAME: &str = "segmentation.dcm";
/// The file name the OME-Zarr download offers.
pub const ZARR_NAME: &str = "segmentation.ome.zarr.zip";
/// The label image's name under `labels/` (the desktop's Save as OME-Zarr uses the same).
pub const LABEL_IMAGE_NAME: &str = "segmentation";

/// The downloads besides the NIfTI label map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SegmentDownload {
    DicomSeg,
    OmeZarrZip,
}

impl SegmentDownload {
    pub const ALL: [SegmentDownload; 2] = [SegmentDownload::DicomSeg, SegmentDownload::OmeZarrZip];

    /// The button's text.
    pub fn label(self) -> &'static str {
        match self {
            SegmentDownload::DicomSeg => "Download SEG",
            SegmentDownload::OmeZarrZip => "Download OME-Zarr",
        }
    }

    /// The name in `data-segment-buttons` (the browser tests aim by it).
    pub fn button_name(self) -> &'static str {
        match self {
            SegmentDownload::DicomSeg => "download-seg",
            SegmentDownload::OmeZarrZip => "download-zarr",
        }
    }

    pub fn hover(self) -> String {
        match self {
            SegmentDownload::DicomSeg => {
                format!("Save as a DICOM SEG, BINARY ({SEG_NAME}; no source series: the volume is not DICOM)")
            }
            SegmentDownload::OmeZarrZip => format!(
                "Save as OME-Zarr labels, the Zarr hierarchy zipped ({ZARR_NAME}, labels/{LABEL_IMAGE_NAME})"
            ),
        }
    }

    fn file_name(self) -> &'static str {
        match self {
            SegmentDownload::DicomSeg => SEG_NAME,
            SegmentDownload::OmeZarrZip => ZARR_NAME,
        }
    }

    fn mime(self) -> &'static str {
        match self {
            SegmentDownload::DicomSeg => "application/dicom",
            SegmentDownload::OmeZarrZip => "application/zip",
        }
    }

    /// The file's bytes for `layer`.
    fn bytes(self, layer: &LabelLayer) -> Result<Vec<u8>, SegmentError> {
        let name = Path::new(self.file_name());
        match self {
            SegmentDownload::DicomSeg => {
                let stamp = SegStamp {
                    unix_nanos: (js_sys::Date::now().max(0.0) * 1e6) as u128,
                    unique: (js_sys::Math::random() * 2f64.powi(53)) as u64,
                };
                dicom_seg_bytes(layer, name, &SegOptions::default(), &stamp).map(|(bytes, _)| bytes)
            }
            SegmentDownload::OmeZarrZip => omezarr_labels_zip(layer, name, LABEL_IMAGE_NAME),
        }
    }
}

/// Makes `what` of `layer` and hands it to the browser's download, revoking `previous` (the
/// last download's object URL). Returns the new URL.
pub fn download(
    what: SegmentDownload,
    layer: &LabelLayer,
    previous: Option<String>,
) -> Result<String, DownloadError> {
    let bytes = what.bytes(layer)?;
    save(&bytes, what.file_name(), what.mime(), previous).map_err(|e| DownloadError::Browser {
        name: what.file_name(),
        message: format!("{e:?}"),
    })
}

/// A Blob of `bytes` typed `mime`, an object URL, an anchor with `download=name` clicked.
fn save(bytes: &[u8], name: &str, mime: &str, previous: Option<String>) -> Result<String, JsValue> {
    if let Some(url) = previous {
        web_sys::Url::revoke_object_url(&url)?;
    }
    let parts = js_sys::Array::of1(&js_sys::Uint8Array::from(bytes));
    let options = web_sys::BlobPropertyBag::new();
    options.set_type(mime);
    let blob = web_sys::Blob::new_with_u8_array_sequence_and_options(&parts, &options)?;
    let url = web_sys::Url::create_object_url_with_blob(&blob)?;
    let document = web_sys::window()
        .and_then(|w| w.document())
        .ok_or_else(|| JsValue::from_str("no document"))?;
    let anchor: web_sys::HtmlAnchorElement = document.create_element("a")?.dyn_into()?;
    anchor.set_href(&url);
    anchor.set_download(name);
    anchor.click();
    Ok(url)
}
