//! zstd frame decoding for the brick kinds that hold zstd frames, by two decoders: C zstd
//! (the `zstd` crate, with the feature `local`) and the pure-Rust ruzstd (always built). C zstd
//! decodes wherever it is compiled in (it is the faster of the two); ruzstd decodes where it is
//! not: wasm32, where zstd-sys would need clang. The decoders are type parameters of the brick
//! decoder, so the native path is monomorphised to C zstd with no dispatch, and the tests decode
//! the same records through both.
//!
//! Both decode into a caller's buffer of one brick at most: a frame that claims more is an error,
//! never an allocation of what it claims.

use super::BrickDecodeError;

/// A zstd frame decoder the brick decoder is instantiated with.
pub(crate) trait ZstdFrames {
    /// Decompresses the frame(s) of `frame` into `dst`, returning the length written; output that
    /// would not fit in `dst` is an error.
    fn decode_into(frame: &[u8], dst: &mut [u8]) -> Result<usize, BrickDecodeError>;

    /// Decompresses into a fresh buffer of at most `expected` bytes (its length is what the
    /// frame held; the caller checks it is `expected`).
    fn decode_vec(frame: &[u8], expected: usize) -> Result<Vec<u8>, BrickDecodeError> {
        let mut out = vec![0u8; expected];
        let n = Self::decode_into(frame, &mut out)?;
        out.truncate(n);
        Ok(out)
    }
}

/// The decoder this build uses: C zstd with `local`, ruzstd without.
#[cfg(feature = "local")]
pub(crate) type Native = CZstd;
#[cfg(not(feature = "local"))]
pub(crate) type Native = PureZstd;

/// C zstd, with one reused decompression context per thread.
#[cfg(feature = "local")]
pub(crate) struct CZstd;

#[cfg(feature = "local")]
thread_local! {
    /// One zstd context per thread, reused: a context costs more to set up than a brick costs to
    /// decompress.
    static ZSTD_DECOMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

#[cfg(feature = "local")]
fn c_failed(e: std::io::Error) -> BrickDecodeError {
    BrickDecodeError::Decompress(format!("zstd: {e}"))
}

#[cfg(feature = "local")]
impl ZstdFrames for CZstd {
    fn decode_into(frame: &[u8], dst: &mut [u8]) -> Result<usize, BrickDecodeError> {
        ZSTD_DECOMPRESSOR.with(|cell| match cell.try_borrow_mut() {
            Ok(mut slot) => {
                if slot.is_none() {
                    *slot = Some(zstd::bulk::Decompressor::new().map_err(c_failed)?);
                }
                match slot.as_mut() {
                    Some(d) => d.decompress_to_buffer(frame, dst).map_err(c_failed),
                    None => Err(BrickDecodeError::Decompress("zstd: no context".into())),
                }
            }
            // Re-entered on this thread (cannot happen today): a fresh context.
            Err(_) => zstd::bulk::Decompressor::new()
                .and_then(|mut d| d.decompress_to_buffer(frame, dst))
                .map_err(c_failed),
        })
    }

    /// Into the spare capacity of a fresh vector: C zstd writes there without the vector being
    /// zeroed first (what the store's decoder always did).
    fn decode_vec(frame: &[u8], expected: usize) -> Result<Vec<u8>, BrickDecodeError> {
        ZSTD_DECOMPRESSOR.with(|cell| {
            let mut out = Vec::with_capacity(expected);
            match cell.try_borrow_mut() {
                Ok(mut slot) => {
                    if slot.is_none() {
                        *slot = Some(zstd::bulk::Decompressor::new().map_err(c_failed)?);
                    }
                    if let Some(d) = slot.as_mut() {
                        d.decompress_to_buffer(frame, &mut out).map_err(c_failed)?;
                    }
                }
                Err(_) => out = zstd::bulk::decompress(frame, expected).map_err(c_failed)?,
            }
            Ok(out)
        })
    }
}

/// ruzstd, with one reused frame decoder per thread (its buffers are kept between frames).
pub(crate) struct PureZstd;

thread_local! {
    static RUZSTD_DECODER: std::cell::RefCell<Option<ruzstd::decoding::FrameDecoder>> =
        const { std::cell::RefCell::new(None) };
}

impl ZstdFrames for PureZstd {
    fn decode_into(frame: &[u8], dst: &mut [u8]) -> Result<usize, BrickDecodeError> {
        let failed = |e: ruzstd::decoding::errors::FrameDecoderError| {
            BrickDecodeError::Decompress(format!("zstd: {e}"))
        };
        // An empty input is no frame: C zstd says so, and ruzstd would return 0 bytes.
        if frame.is_empty() {
            return Err(BrickDecodeError::Decompress("zstd: empty frame".into()));
        }
        RUZSTD_DECODER.with(|cell| match cell.try_borrow_mut() {
            Ok(mut slot) => slot
                .get_or_insert_with(ruzstd::decoding::FrameDecoder::new)
                .decode_all(frame, dst)
                .map_err(failed),
            Err(_) => ruzstd::decoding::FrameDecoder::new()
                .decode_all(frame, dst)
                .map_err(failed),
        })
    }
}
