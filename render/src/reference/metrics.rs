//! Image error between two RGBA8 images: how "accuracy is shown, not claimed".

use crate::error::RenderError;

#[derive(Clone, Copy, Debug)]
pub struct ImageComparison {
    /// Over all channels, in 8-bit units.
    pub rmse: f64,
    /// 20·log10(255 / rmse); +inf for identical images.
    pub psnr_db: f64,
    pub max_abs_error: u8,
    /// Pixels with any channel off by more than 1/255.
    pub pixels_off_by_more_than_one: usize,
}

pub fn compare_rgba8(a: &[u8], b: &[u8]) -> Result<ImageComparison, RenderError> {
    if a.len() != b.len() || !a.len().is_multiple_of(4) {
        return Err(RenderError::ImageMismatch(format!(
            "sizes differ or not RGBA: {} vs {}",
            a.len(),
            b.len()
        )));
    }
    let mut sq = 0.0f64;
    let mut max = 0u8;
    for (x, y) in a.iter().zip(b) {
        let d = x.abs_diff(*y);
        max = max.max(d);
        sq += (d as f64) * (d as f64);
    }
    let pixels_off = a
        .chunks_exact(4)
        .zip(b.chunks_exact(4))
        .filter(|(p, q)| p.iter().zip(q.iter()).any(|(x, y)| x.abs_diff(*y) > 1))
        .count();
    let rmse = if a.is_empty() {
        0.0
    } else {
        (sq / a.len() as f64).sqrt()
    };
    let psnr_db = if rmse == 0.0 {
        f64::INFINITY
    } else {
        20.0 * (255.0 / rmse).log10()
    };
    Ok(ImageComparison {
        rmse,
        psnr_db,
        max_abs_error: max,
        pixels_off_by_more_than_one: pixels_off,
    })
}

/// Writes a binary PPM (RGB, alpha dropped) for eyeballing failures without image crates.
pub fn write_ppm(
    path: &std::path::Path,
    width: u32,
    height: u32,
    rgba: &[u8],
) -> Result<(), RenderError> {
    let mut out = format!("P6\n{width} {height}\n255\n").into_bytes();
    for p in rgba.chunks_exact(4) {
        out.extend_from_slice(&p[..3]);
    }
    std::fs::write(path, out).map_err(|source| RenderError::Io {
        path: path.display().to_string(),
        source,
    })
}
