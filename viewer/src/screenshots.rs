//! Screenshots of a view or of the whole layout, as the user sees them (orientation marker,
//! slice outlines, measurements, the not-for-diagnosis label), at full resolution, into the
//! folder the user picks.
//!
//! Steps: the 3D view renders at the screen's full pixel density (not the interactive render
//! scale) until its frame for that size has converged; then egui is asked for a screenshot of
//! the window (`ViewportCommand::Screenshot`), the target's rectangle is cut out and written as
//! PNG on a named thread. 2× and 4× go through the render thread's offscreen path instead (the
//! 3D image alone, without the annotations, which egui draws at screen resolution only).

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use egui::{ColorImage, Rect};

use super::preferences::ViewSlot;
use super::sync::lock_ignoring_poison;

/// What to capture.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ShotTarget {
    View(ViewSlot),
    /// All views as laid out.
    Layout,
}

#[derive(Clone, Debug, PartialEq)]
enum Stage {
    /// Waiting for the 3D view's full-resolution frame to converge (bounded).
    Rendering { since: Instant },
    /// The window screenshot is requested; its image lands in `captured`.
    Capturing,
    /// The PNG is being written.
    Writing,
}

/// One screenshot on its way.
pub struct ScreenshotJob {
    pub target: ShotTarget,
    pub path: PathBuf,
    stage: Stage,
    captured: Arc<Mutex<Option<Arc<ColorImage>>>>,
    written: Arc<Mutex<Option<Result<PathBuf, ScreenshotError>>>>,
}

/// Why a screenshot was not written.
#[derive(Debug, thiserror::Error)]
pub enum ScreenshotError {
    #[error("the view to capture is no longer shown")]
    ViewGone,
    #[error("cannot start the writer thread: {0}")]
    WriterThread(std::io::Error),
    #[error("cannot create the folder {}: {source}", .dir.display())]
    CreateFolder {
        dir: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {}: {source}", .path.display())]
    Write {
        path: PathBuf,
        source: image::ImageError,
    },
}

/// Longest wait for a converged 3D frame before capturing what is there.
const RENDER_WAIT: Duration = Duration::from_secs(20);

impl ScreenshotJob {
    pub fn new(target: ShotTarget, folder: &std::path::Path) -> Self {
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        let what = match target {
            ShotTarget::View(ViewSlot::ThreeD) => "3d".to_string(),
            ShotTarget::View(ViewSlot::Slice(view)) => view.name().to_lowercase(),
            ShotTarget::View(ViewSlot::Oblique) => "oblique".to_string(),
            ShotTarget::Layout => "layout".to_string(),
        };
        ScreenshotJob {
            target,
            path: folder.join(format!("strata-{what}-{stamp}.png")),
            stage: Stage::Rendering {
                since: Instant::now(),
            },
            captured: Arc::new(Mutex::new(None)),
            written: Arc::new(Mutex::new(None)),
        }
    }

    /// The 3D view should render at full resolution while this is true.
    pub fn wants_full_resolution(&self) -> bool {
        matches!(self.stage, Stage::Rendering { .. })
    }

    /// Advances the job; `frame_ready` says the 3D view shows its converged full-resolution
    /// frame (or there is no 3D view in the shot). `rect` is the target's rectangle now.
    /// Returns the outcome once the file is written (or failed).
    pub fn step(
        &mut self,
        ctx: &egui::Context,
        frame_ready: bool,
        rect: Option<Rect>,
    ) -> Option<Result<PathBuf, ScreenshotError>> {
        match self.stage.clone() {
            Stage::Rendering { since } => {
                if frame_ready || since.elapsed() > RENDER_WAIT {
                    let slot = self.captured.clone();
                    let repaint = ctx.clone();
                    ctx.send_viewport_cmd(egui::ViewportCommand::Screenshot(
                        egui::ScreenshotCallback::new(move |image| {
                            *lock_ignoring_poison(&slot) = Some(image);
                            repaint.request_repaint();
                        }),
                    ));
                    self.stage = Stage::Capturing;
                }
                ctx.request_repaint_after(Duration::from_millis(50));
                None
            }
            Stage::Capturing => {
                let image = lock_ignoring_poison(&self.captured).take()?;
                let Some(rect) = rect else {
                    return Some(Err(ScreenshotError::ViewGone));
                };
                let crop = crop(&image, rect, ctx.pixels_per_point());
                let path = self.path.clone();
                let written = self.written.clone();
                let repaint = ctx.clone();
                let spawned = std::thread::Builder::new()
                    .name("strata-screenshot-writer".into())
                    .spawn(move || {
                        let result = write(&path, &crop).map(|_| path.clone());
                        *lock_ignoring_poison(&written) = Some(result);
                        repaint.request_repaint();
                    });
                if let Err(e) = spawned {
                    return Some(Err(ScreenshotError::WriterThread(e)));
                }
                self.stage = Stage::Writing;
                None
            }
            Stage::Writing => lock_ignoring_poison(&self.written).take(),
        }
    }
}

/// The pixels of `rect` (points) of a window screenshot taken at `pixels_per_point`.
pub fn crop(image: &ColorImage, rect: Rect, pixels_per_point: f32) -> ColorImage {
    let [w, h] = image.size;
    let x0 = ((rect.left() * pixels_per_point).round().max(0.0) as usize).min(w);
    let y0 = ((rect.top() * pixels_per_point).round().max(0.0) as usize).min(h);
    let x1 = ((rect.right() * pixels_per_point).round().max(0.0) as usize).clamp(x0, w);
    let y1 = ((rect.bottom() * pixels_per_point).round().max(0.0) as usize).clamp(y0, h);
    let mut pixels = Vec::with_capacity((x1 - x0) * (y1 - y0));
    for y in y0..y1 {
        pixels.extend_from_slice(&image.pixels[y * w + x0..y * w + x1]);
    }
    ColorImage::new([x1 - x0, y1 - y0], pixels)
}

fn write(path: &std::path::Path, image: &ColorImage) -> Result<(), ScreenshotError> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| ScreenshotError::CreateFolder {
            dir: dir.to_path_buf(),
            source,
        })?;
    }
    let [w, h] = image.size;
    let mut rgb = Vec::with_capacity(w * h * 3);
    for p in &image.pixels {
        // The window is opaque: its pixels' colour is what the screen shows.
        rgb.extend_from_slice(&[p.r(), p.g(), p.b()]);
    }
    image::save_buffer(
        path,
        &rgb,
        w as u32,
        h as u32,
        image::ExtendedColorType::Rgb8,
    )
    .map_err(|source| ScreenshotError::Write {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use egui::{Color32, Pos2};

    #[test]
    fn crop_takes_the_rectangle_at_the_pixel_density() {
        let mut image = ColorImage::new([8, 6], vec![Color32::BLACK; 48]);
        image.pixels[3 * 8 + 5] = Color32::WHITE;
        // Points (2, 1)-(3, 2.5) at 2 px per point: pixels x 4..6, y 2..5.
        let rect = Rect::from_min_max(Pos2::new(2.0, 1.0), Pos2::new(3.0, 2.5));
        let cut = crop(&image, rect, 2.0);
        assert_eq!(cut.size, [2, 3]);
        assert_eq!(cut.pixels[2 + 1], Color32::WHITE);
        // Out of the image: clamped, never a panic.
        let outside = Rect::from_min_max(Pos2::new(3.0, 2.0), Pos2::new(50.0, 50.0));
        assert_eq!(crop(&image, outside, 2.0).size, [2, 2]);
    }
}
