//! What the command line, the desktop viewer and the benchmarks share for writing images and
//! movies and for reading their options: the PNG of a frame, the orbit movie's frames and its
//! MP4 through ffmpeg, the `WxH` size and the transfer function named on a command line.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use strata_render::TransferFunction;
use strata_viewer_ui::orbit_movie::ORBIT_FRAMES_PER_SECOND;

// The orbit's path is shared with the page's movie (strata-viewer-ui's orbit_movie).
pub use strata_viewer_ui::orbit_movie::{orbit_azimuth, MAX_ORBIT_FRAMES};

/// `WxH` (e.g. 512x512) as a width and height, each 1..=8192.
pub fn parse_size(text: &str) -> Result<(u32, u32)> {
    let (w, h) = text
        .split_once(['x', 'X'])
        .with_context(|| format!("--size must look like 512x512, not '{text}'"))?;
    let (w, h): (u32, u32) = (w.trim().parse()?, h.trim().parse()?);
    if !(1..=8192).contains(&w) || !(1..=8192).contains(&h) {
        bail!("--size {w}x{h} is outside 1..8192");
    }
    Ok((w, h))
}

/// The transfer function the user named, or a sensible default for the modality
/// (strata-headless's choice, which `strata render` and `strata.render` make too).
pub fn choose_transfer_function(name: Option<&str>, modality: &str) -> Result<TransferFunction> {
    Ok(strata_headless::choose_transfer_function(name, modality)?)
}

pub fn orbit_frame_name(i: u32) -> String {
    format!("frame-{i:04}.png")
}

/// frame-%04d.png in `folder` → orbit.mp4 through ffmpeg, if ffmpeg runs; None without it.
pub fn encode_mp4(folder: &Path) -> Result<Option<PathBuf>> {
    let probe = std::process::Command::new("ffmpeg")
        .arg("-version")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status();
    if !probe.is_ok_and(|s| s.success()) {
        return Ok(None);
    }
    let movie = folder.join("orbit.mp4");
    let output = std::process::Command::new("ffmpeg")
        .args(["-y", "-loglevel", "error", "-framerate"])
        .arg(ORBIT_FRAMES_PER_SECOND.to_string())
        .arg("-i")
        .arg(folder.join("frame-%04d.png"))
        // Even dimensions and yuv420p: what every player accepts.
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-pix_fmt",
            "yuv420p",
        ])
        .arg(&movie)
        .output()
        .context("running ffmpeg")?;
    if !output.status.success() {
        bail!("ffmpeg: {}", String::from_utf8_lossy(&output.stderr).trim());
    }
    Ok(Some(movie))
}

/// Writes premultiplied RGBA over black (the usual background of medical viewers) as PNG.
pub fn write_png(path: &Path, width: u32, height: u32, premultiplied_rgba: &[u8]) -> Result<()> {
    let mut rgb = Vec::with_capacity((width * height * 3) as usize);
    for px in premultiplied_rgba.chunks_exact(4) {
        rgb.extend_from_slice(&px[..3]);
    }
    image::save_buffer(path, &rgb, width, height, image::ExtendedColorType::Rgb8)
        .with_context(|| format!("writing {}", path.display()))
}
