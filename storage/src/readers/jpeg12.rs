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

/// libjpeg-turbo's own working memory, in MiB: a progressive 12-bit frame of 8192² keeps
/// 128 MiB of coefficients; a sequential one needs a few rows of blocks.
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
    fn new() -> Option<Self> {
        // SAFETY: tj3Init takes no pointers; a null result is handled by the caller.
        let handle = unsafe { tj::tj3Init(tj::TJINIT_TJINIT_DECOMPRESS as c_int) };
        (!handle.is_null()).then_some(Self(handle))
    }

    fn get(&self, param: tj::TJPARAM) -> c_int {
        // SAFETY: the handle is live (owned by self); tj3Get only reads its state.
        unsafe { tj::tj3Get(self.0, param as c_int) }
    }

    fn set(&self, param: tj::TJPARAM, value: c_int) -> std::result::Result<(), JpegError> {
        // SAFETY: the handle is live; tj3Set validates the parameter and value itself.
        if unsafe { tj::tj3Set(self.0, param as c_int, value) } != 0 {
            return Err(JpegError::Configure(self.message()));
        }
        Ok(())
    }

    /// The decoder's last error or warning.
    fn message(&self) -> String {
        // SAFETY: the handle is live; tj3GetErrorStr returns a NUL-terminated string owned by
        // the handle (or a static one), copied here before any further call on the handle.
        unsafe {
            let s = tj::tj3GetErrorStr(self.0);
            if s.is_null() {
                String::from("unknown error")
            } else {
                CStr::from_ptr(s).to_string_lossy().into_owned()
            }
        }
    }
}

/// Why one decode of a frame failed; the caller prefixes the file and frame.
#[derive(Debug, thiserror::Error)]
enum JpegError {
    #[error("cannot start the JPEG decoder (libjpeg-turbo)")]
    Start,
    #[error("configuring the JPEG decoder: {0}")]
    Configure(String),
    #[error("bad JPEG header: {0}")]
    Header(String),
    #[error("the JPEG image is {width}x{height}, but the DICOM header says {cols}x{rows}")]
    Size {
        width: c_int,
        height: c_int,
        cols: u32,
        rows: u32,
    },
    #[error("JPEG sample precision {0} (9 to 12 expected here)")]
    Precision(c_int),
    /// libjpeg-turbo's own message for the failed decode (or the warning that stopped it).
    #[error("{0}")]
    Decode(String),
}

impl JpegError {
    /// Whether libjpeg stopped on the one warning that a repaired scan header avoids.
    fn is_not_sequential_warning(&self) -> bool {
        match self {
            JpegError::Header(message) | JpegError::Decode(message) => {
                message.contains(NOT_SEQUENTIAL)
            }
            _ => false,
        }
    }
}

/// libjpeg's warning for a sequential scan whose spectral-selection or approximation fields are
/// not 0, 63, 0, 0 (JWRN_NOT_SEQUENTIAL); libjpeg then ignores those fields.
const NOT_SEQUENTIAL: &str = "Invalid SOS parameters for sequential JPEG";

/// Decodes one greyscale JPEG frame of 9 to 12 bits precision, `cols`×`rows`, into samples
/// (row by row), and says what had to be repaired, if anything. `frame` (1-based) only names
/// the frame in errors.
///
/// Every warning stops the decoder, with one exception: a sequential scan header with wrong
/// spectral-selection fields (NEMA's NM1_JPLY, pydicom's JPEG-lossy.dcm: Se = 0), which libjpeg
/// and GDCM ignore. Those fields are set to the only values a sequential scan can have and the
/// frame is decoded again, still stopping on any other warning.
pub(crate) fn decode_12bit_frame(
    path: &Path,
    frame: u32,
    jpeg: &[u8],
    cols: u32,
    rows: u32,
) -> Result<(Vec<u16>, Option<&'static str>)> {
    let what = format!("JPEG Extended (12-bit) frame {frame}");
    match decode_once(jpeg, cols, rows) {
        Ok(samples) => Ok((samples, None)),
        Err(e) if e.is_not_sequential_warning() => match repair_sequential_scans(jpeg) {
            Some(repaired) => decode_once(&repaired, cols, rows)
                .map(|samples| {
                    (
                        samples,
                        Some("JPEG scan header repaired (invalid SOS parameters for sequential JPEG, ignored as libjpeg does)"),
                    )
                })
                .map_err(|e| StorageError::invalid(path, format!("{what}: {e}"))),
            None => Err(StorageError::invalid(path, format!("{what}: {e}"))),
        },
        Err(e) => Err(StorageError::invalid(path, format!("{what}: {e}"))),
    }
}

/// A copy of `jpeg` whose sequential (SOF0/SOF1) scan headers carry Ss = 0, Se = 63, Ah = Al = 0;
/// `None` when the stream is not sequential, cannot be walked, or needed no change.
fn repair_sequential_scans(jpeg: &[u8]) -> Option<Vec<u8>> {
    if jpeg.get(..2)? != [0xFF, 0xD8] {
        return None;
    }
    let mut out = jpeg.to_vec();
    let mut at = 2usize;
    let mut sequential = false;
    let mut changed = false;
    loop {
        // Markers may be preceded by fill bytes (0xFF).
        while *jpeg.get(at)? == 0xFF && *jpeg.get(at + 1)? == 0xFF {
            at += 1;
        }
        if *jpeg.get(at)? != 0xFF {
            return None;
        }
        let marker = *jpeg.get(at + 1)?;
        let len = usize::from(u16::from_be_bytes([*jpeg.get(at + 2)?, *jpeg.get(at + 3)?]));
        let segment = jpeg.get(at + 2..at + 2 + len)?;
        match marker {
            0xC0 | 0xC1 => sequential = true,
            0xC2..=0xCF if marker != 0xC4 && marker != 0xC8 && marker != 0xCC => return None,
            0xDA => {
                if !sequential {
                    return None;
                }
                // Ls(2) Ns(1) Ns × (Cs, Td|Ta) then Ss, Se, Ah|Al.
                let ns = usize::from(*segment.get(2)?);
                let fields = at + 2 + 3 + 2 * ns;
                if fields + 3 > at + 2 + len {
                    return None;
                }
                if out[fields..fields + 3] != [0, 63, 0] {
                    out[fields..fields + 3].copy_from_slice(&[0, 63, 0]);
                    changed = true;
                }
                // One scan per component at most for greyscale; the entropy-coded data follows.
                return changed.then_some(out);
            }
            _ => {}
        }
        at += 2 + len;
    }
}

/// One decode with every warning fatal; the error is libjpeg-turbo's message.
fn decode_once(jpeg: &[u8], cols: u32, rows: u32) -> std::result::Result<Vec<u16>, JpegError> {
    let d = Decompressor::new().ok_or(JpegError::Start)?;
    d.set(tj::TJPARAM_TJPARAM_STOPONWARNING, 1)?;
    d.set(tj::TJPARAM_TJPARAM_SCANLIMIT, MAX_SCANS)?;
    d.set(tj::TJPARAM_TJPARAM_MAXMEMORY, MAX_DECODER_MEMORY_MIB)?;
    // The frame may not hold more pixels than the DICOM header says it has.
    let pixels = (cols as u64) * (rows as u64);
    d.set(
        tj::TJPARAM_TJPARAM_MAXPIXELS,
        c_int::try_from(pixels).unwrap_or(c_int::MAX),
    )?;
    // SAFETY: the pointer and length describe `jpeg`, which outlives the call; TurboJPEG only
    // reads from it.
    if unsafe { tj::tj3DecompressHeader(d.0, jpeg.as_ptr(), jpeg.len() as _) } != 0 {
        return Err(JpegError::Header(d.message()));
    }
    let width = d.get(tj::TJPARAM_TJPARAM_JPEGWIDTH);
    let height = d.get(tj::TJPARAM_TJPARAM_JPEGHEIGHT);
    let precision = d.get(tj::TJPARAM_TJPARAM_PRECISION);
    if (width, height) != (cols as c_int, rows as c_int) {
        return Err(JpegError::Size {
            width,
            height,
            cols,
            rows,
        });
    }
    if !(9..=12).contains(&precision) {
        return Err(JpegError::Precision(precision));
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
        return Err(JpegError::Decode(d.message()));
    }
    Ok(samples.into_iter().map(|s| s as u16).collect())
}
