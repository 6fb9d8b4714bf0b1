//! 12-bit JPEG (DICOM "JPEG Extended", transfer syntax 1.2.840.10008.1.2.4.51, common for CT and
//! NM): decoded by libjpeg-turbo 3 (TurboJPEG API, through `turbojpeg-sys`). jpeg-decoder, which
//! dicom-pixeldata uses for the other JPEG processes, decodes 8-bit DCT data only.
//!
//! libjpeg-turbo is told to stop on warnings (a truncated or corrupt entropy-coded segment is
//! otherwise filled in with grey and reported only as a warning) and is bounded in memory, pixels
//! and progressive scans, so a damaged header cannot make it allocate without limit.

use std::ffi::{c_int, CStr};
use std::path::Path;

use turbojpeg_sys as tj;

use crate::error::{Result, StorageError};

/// libjpeg-turbo's own working memory, in MiB; a 12-bit frame of 8192² needs about 130.
const MAX_DECODER_MEMORY_MIB: c_int = 1024;
/// Progressive JPEG with thousands of scans is a known decompression bomb; real ones have ~10.
const MAX_SCANS: c_int = 500;

/// Owns a TurboJPEG decompressor and destroys it on drop (also on early returns).
struct Decompressor(tj::tjhandle);

impl Drop for Decompressor {
    fn drop(&mut self) {
        // SAFETY: the handle came from tj3Init, is non-null, and is destroyed exactly once here.
        unsafe { tj::tj3Destroy(self.0) }
    }
}

impl Decompressor {
    fn new(path: &Path) -> Result<Self> {
        // SAFETY: tj3Init takes no pointers; a null result is handled below.
        let handle = unsafe { tj::tj3Init(tj::TJINIT_TJINIT_DECOMPRESS as c_int) };
        if handle.is_null() {
            return Err(StorageError::invalid(
                path,
                "cannot start the JPEG decoder (libjpeg-turbo)",
            ));
        }
        Ok(Self(handle))
    }

    fn get(&self, param: tj::TJPARAM) -> c_int {
        // SAFETY: the handle is live (owned by self); tj3Get only reads its state.
        unsafe { tj::tj3Get(self.0, param as c_int) }
    }

    fn set(&self, path: &Path, param: tj::TJPARAM, value: c_int) -> Result<()> {
        // SAFETY: the handle is live; tj3Set validates the parameter and value itself.
        if unsafe { tj::tj3Set(self.0, param as c_int, value) } != 0 {
            return Err(self.error(path, "configuring the JPEG decoder"));
        }
        Ok(())
    }

    fn error(&self, path: &Path, what: &str) -> StorageError {
        // SAFETY: the handle is live; tj3GetErrorStr returns a NUL-terminated string owned by
        // the handle (or a static one), read here before any further call on the handle.
        let message = unsafe {
            let s = tj::tj3GetErrorStr(self.0);
            if s.is_null() {
                String::from("unknown error")
            } else {
                CStr::from_ptr(s).to_string_lossy().into_owned()
            }
        };
        StorageError::invalid(path, format!("{what}: {message}"))
    }
}

/// Decodes one greyscale JPEG frame of 9 to 12 bits precision, `cols`×`rows`, into samples
/// (row by row). `frame` (1-based) only names the frame in errors.
pub(crate) fn decode_12bit_frame(
    path: &Path,
    frame: u32,
    jpeg: &[u8],
    cols: u32,
    rows: u32,
) -> Result<Vec<u16>> {
    let what = format!("JPEG Extended (12-bit) frame {frame}");
    let d = Decompressor::new(path)?;
    d.set(path, tj::TJPARAM_TJPARAM_STOPONWARNING, 1)?;
    d.set(path, tj::TJPARAM_TJPARAM_SCANLIMIT, MAX_SCANS)?;
    d.set(path, tj::TJPARAM_TJPARAM_MAXMEMORY, MAX_DECODER_MEMORY_MIB)?;
    // The frame may not hold more pixels than the DICOM header says it has.
    let pixels = (cols as u64) * (rows as u64);
    d.set(
        path,
        tj::TJPARAM_TJPARAM_MAXPIXELS,
        c_int::try_from(pixels).unwrap_or(c_int::MAX),
    )?;
    // SAFETY: the pointer and length describe `jpeg`, which outlives the call; TurboJPEG only
    // reads from it.
    if unsafe { tj::tj3DecompressHeader(d.0, jpeg.as_ptr(), jpeg.len() as _) } != 0 {
        return Err(d.error(path, &format!("{what}: bad JPEG header")));
    }
    let width = d.get(tj::TJPARAM_TJPARAM_JPEGWIDTH);
    let height = d.get(tj::TJPARAM_TJPARAM_JPEGHEIGHT);
    let precision = d.get(tj::TJPARAM_TJPARAM_PRECISION);
    if (width, height) != (cols as c_int, rows as c_int) {
        return Err(StorageError::invalid(
            path,
            format!("{what} is {width}x{height}, but the DICOM header says {cols}x{rows}"),
        ));
    }
    if !(9..=12).contains(&precision) {
        return Err(StorageError::unsupported(
            path,
            format!("{what}: JPEG sample precision {precision} (9 to 12 expected here)"),
        ));
    }
    let mut samples = vec![0i16; pixels as usize];
    // SAFETY: `samples` holds width·height greyscale samples (checked equal to cols·rows above),
    // pitch 0 means "width samples per row", TJPF_GRAY writes one sample per pixel; the input
    // slice outlives the call.
    let rc = unsafe {
        tj::tj3Decompress12(
            d.0,
            jpeg.as_ptr(),
            jpeg.len() as _,
            samples.as_mut_ptr(),
            0,
            tj::TJPF_TJPF_GRAY,
        )
    };
    if rc != 0 {
        return Err(d.error(path, &what));
    }
    Ok(samples.into_iter().map(|s| s as u16).collect())
}
