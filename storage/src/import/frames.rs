//! 4-D import: every volume of a 4-D source (a NIfTI's time points) becomes a frame of one
//! store (layout in [`crate::store::FEATURE_FRAMES`]). One quantiser is planned over all frames,
//! so every frame shares the header's value mapping; frames 1.. are imported first, each into a
//! temporary single-volume store beside the target, then frame 0 into the target exactly as a
//! single volume is, and finally the other frames are copied in and the header names them (in
//! format 3 appended to new packs under their frame numbers, the index renamed in last).

use std::path::{Path, PathBuf};

use crate::error::Result;
use crate::import::{
    import_slices_as, source_meta, ImportOptions, ImportProgress, ImportReport, SliceProducer,
};
use crate::quantize::Quantizer;
use crate::source::{OpenedSource, RawVolume};

/// One frame's slices of a source holding all frames one after the other.
struct FrameSlices<'a> {
    data: &'a RawVolume,
    quantizer: &'a Quantizer,
    first_slice: u64,
    dims: [u64; 3],
}

impl SliceProducer for FrameSlices<'_> {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }
    fn stored_slice(&self, k: u64, out: &mut [u16]) -> Result<()> {
        self.quantizer
            .convert_slice(self.data, self.first_slice + k, out);
        Ok(())
    }
    fn release_slice(&self, k: u64) {
        self.data.release_slice(self.first_slice + k);
    }
    fn source_bytes_per_slice(&self) -> u64 {
        self.data.slice_bytes_len() as u64
    }
}

/// The temporary store of frame `frame` while `store_path` is imported.
fn frame_store_path(store_path: &Path, frame: u32) -> PathBuf {
    let name = store_path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    store_path.with_file_name(format!(".{name}.frame-{frame}.importing"))
}

/// Imports all `opened.info.frames` volumes into one store at `store_path`, of format `format`
/// (`None`: the current one).
pub(crate) fn import_frames(
    opened: OpenedSource,
    store_path: &Path,
    options: &ImportOptions,
    format: Option<u32>,
) -> Result<ImportReport> {
    let info = opened.info;
    let frames = info.frames.max(1);
    let dims = info.geometry.dims_u64();
    let quantizer = Quantizer::plan(&opened.data, info.slope);
    let meta = source_meta(&info, &quantizer);
    let frame = |f: u32| FrameSlices {
        data: &opened.data,
        quantizer: &quantizer,
        first_slice: u64::from(f) * dims[2],
        dims,
    };
    let temporary: Vec<PathBuf> = (1..frames)
        .map(|f| frame_store_path(store_path, f))
        .collect();
    // Progress over all frames: each frame's import reports its own bytes.
    let frame_bytes = opened.data.slice_bytes_len() as u64 * dims[2];
    let total = frame_bytes * u64::from(frames);
    let options_for = |done_before: u64| {
        let progress = options.progress;
        move |p: ImportProgress| {
            if let Some(report) = progress {
                report(ImportProgress {
                    source_bytes_done: done_before + p.source_bytes_done,
                    source_bytes_total: total,
                });
            }
        }
    };
    let import_frame = |f: u32, n: u64, path: &Path, meta| {
        let progress = options_for(n * frame_bytes);
        let frame_options = ImportOptions {
            memory_budget_bytes: options.memory_budget_bytes,
            cancel: options.cancel,
            progress: Some(&progress),
            codec: options.codec,
        };
        import_slices_as(&frame(f), meta, path, &frame_options, format)
    };
    let result = (|| {
        for (f, path) in (1..frames).zip(&temporary) {
            import_frame(f, u64::from(f - 1), path, meta.clone())?;
        }
        let mut report = import_frame(0, u64::from(frames - 1), store_path, meta)?;
        crate::store::append_frames(store_path, &temporary)?;
        report.header = crate::store::Store::open(store_path)?.header().clone();
        Ok(report)
    })();
    for path in &temporary {
        let _ = std::fs::remove_dir_all(path);
    }
    result
}
