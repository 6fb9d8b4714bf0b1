//! The orbit movie as a download in the page (issue 47; the desktop's Screenshot panel writes
//! PNG frames and an MP4 through ffmpeg, viewer/src/export.rs). A browser runs no ffmpeg and
//! writes no folder, so the page downloads one animated PNG (APNG: lossless, one file, played
//! by every browser), `strata-orbit-MILLIS.png`, at strata-viewer-ui's
//! `ORBIT_FRAMES_PER_SECOND`.
//!
//! The frames' azimuths are strata-viewer-ui's `orbit_azimuth` from the view's azimuth when the
//! movie starts, as the desktop's. The page turns its own 3D view through them, one frame at a
//! time, and takes each once it is final as a still view is: its cut converged and, where its
//! effects refine, the complete mean of the jittered frames (refine.rs), as the desktop's export
//! writes the refined mean. So nothing blocks the page: the frame loop draws, refines and reads
//! back as it always does, and Cancel puts the view back where it was.
//!
//! The model and the encoder are platform independent (tested natively); the side panel's
//! section and what the page publishes for its tests (`data-movie`) are the browser's.

use strata_viewer_ui::orbit_movie::{
    orbit_azimuth, orbit_frame_count, DEFAULT_ORBIT_FRAMES, ORBIT_FRAMES_PER_SECOND,
};

/// Why a movie could not be made.
#[derive(Debug, thiserror::Error)]
pub enum MovieError {
    #[error("the 3D view changed size during the movie ({was:?} to {now:?} pixels)")]
    SizeChanged { was: [u32; 2], now: [u32; 2] },
    #[error("a frame of {width}×{height} pixels has {len} bytes, not 4 per pixel")]
    FrameLength { width: u32, height: u32, len: usize },
    #[error("encoding the animated PNG: {0}")]
    Encoding(#[from] png::EncodingError),
}

/// The frames of one movie so far.
struct Making {
    start_azimuth: f64,
    frames: u32,
    size: Option<[u32; 2]>,
    /// Each frame's premultiplied RGBA8, in order.
    images: Vec<Vec<u8>>,
}

/// The side panel's orbit movie: its frame count, the movie being made, and how the last ended.
pub struct OrbitMovie {
    /// The frame count the panel asks for (strata-viewer-ui's offered range).
    pub frames_asked: u32,
    start_asked: bool,
    making: Option<Making>,
    /// Movies started on this page: a test tells one movie from the next by it.
    runs: u64,
    outcome: Outcome,
}

/// How the last movie ended.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    None,
    Downloaded,
    Cancelled,
    Failed(String),
}

/// A movie finished: the animated PNG, and the azimuth to put the view back at.
pub struct Finished {
    pub apng: Vec<u8>,
    pub start_azimuth: f64,
}

impl Default for OrbitMovie {
    fn default() -> Self {
        OrbitMovie {
            frames_asked: DEFAULT_ORBIT_FRAMES,
            start_asked: false,
            making: None,
            runs: 0,
            outcome: Outcome::None,
        }
    }
}

impl OrbitMovie {
    /// Asks for a movie of `frames_asked` frames, started by the next [`OrbitMovie::begin`].
    pub fn ask(&mut self) {
        self.start_asked = true;
    }

    /// Starts the movie asked for, from the view's azimuth now; nothing while one is made.
    pub fn begin(&mut self, azimuth_now: f64) {
        if !std::mem::take(&mut self.start_asked) || self.making.is_some() {
            return;
        }
        self.making = Some(Making {
            start_azimuth: azimuth_now,
            frames: orbit_frame_count(self.frames_asked),
            size: None,
            images: Vec::new(),
        });
        self.runs += 1;
        self.outcome = Outcome::None;
    }

    /// The azimuth of the frame being made, while a movie is made.
    pub fn azimuth(&self) -> Option<f64> {
        let m = self.making.as_ref()?;
        Some(orbit_azimuth(
            m.start_azimuth,
            m.images.len() as u32,
            m.frames,
        ))
    }

    pub fn is_making(&self) -> bool {
        self.making.is_some()
    }

    /// Frames taken and the movie's frame count, while one is made.
    pub fn progress(&self) -> Option<(u32, u32)> {
        let m = self.making.as_ref()?;
        Some((m.images.len() as u32, m.frames))
    }

    /// The frame at [`OrbitMovie::azimuth`], final, `size` pixels of premultiplied RGBA8.
    /// After the last frame the movie is encoded and returned. A frame of another size than
    /// the first (the page resized) is an error, which the caller ends the movie with
    /// ([`OrbitMovie::fail`] gives back the azimuth to put the view at).
    pub fn add_frame(
        &mut self,
        rgba: Vec<u8>,
        size: [u32; 2],
    ) -> Result<Option<Finished>, MovieError> {
        let Some(making) = self.making.as_mut() else {
            return Ok(None);
        };
        let was = *making.size.get_or_insert(size);
        if was != size {
            return Err(MovieError::SizeChanged { was, now: size });
        }
        making.images.push(rgba);
        if (making.images.len() as u32) < making.frames {
            return Ok(None);
        }
        let apng = encode_apng(&making.images, size, ORBIT_FRAMES_PER_SECOND)?;
        let start_azimuth = making.start_azimuth;
        self.making = None;
        self.outcome = Outcome::Downloaded;
        Ok(Some(Finished {
            apng,
            start_azimuth,
        }))
    }

    /// Stops the movie being made; the azimuth the view had when it started.
    pub fn cancel(&mut self) -> Option<f64> {
        let making = self.making.take()?;
        self.outcome = Outcome::Cancelled;
        Some(making.start_azimuth)
    }

    /// Ends the movie being made with `problem` (a frame could not be read back).
    pub fn fail(&mut self, problem: &dyn std::fmt::Display) -> Option<f64> {
        let making = self.making.take();
        self.outcome = Outcome::Failed(problem.to_string());
        making.map(|m| m.start_azimuth)
    }

    pub fn outcome(&self) -> &Outcome {
        &self.outcome
    }

    /// What the browser tests read: `run=R;frames=K/N;state=making|downloaded|cancelled|
    /// failed|idle` (K of N frames taken while a movie is made, 0/0 between movies).
    pub fn state_text(&self) -> String {
        let (taken, total) = self.progress().unwrap_or((0, 0));
        let state = match (&self.making, &self.outcome) {
            (Some(_), _) => "making",
            (None, Outcome::None) => "idle",
            (None, Outcome::Downloaded) => "downloaded",
            (None, Outcome::Cancelled) => "cancelled",
            (None, Outcome::Failed(_)) => "failed",
        };
        format!("run={};frames={taken}/{total};state={state}", self.runs)
    }
}

/// Premultiplied RGBA8 frames of `size` as an animated PNG that loops forever, each frame shown
/// 1/`frames_per_second` s. Like the desktop's frames (export.rs's write_png) the pixels are
/// RGB over black, the usual background of medical viewers: a movie has no use for alpha.
pub fn encode_apng(
    frames: &[Vec<u8>],
    [width, height]: [u32; 2],
    frames_per_second: u32,
) -> Result<Vec<u8>, MovieError> {
    let pixels = width as usize * height as usize;
    if let Some(bad) = frames.iter().find(|f| f.len() != pixels * 4) {
        return Err(MovieError::FrameLength {
            width,
            height,
            len: bad.len(),
        });
    }
    let mut apng = Vec::new();
    let mut encoder = png::Encoder::new(&mut apng, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    // 0 plays: the movie loops, as an orbit does.
    encoder.set_animated(frames.len() as u32, 0)?;
    let fps = u16::try_from(frames_per_second.max(1)).unwrap_or(u16::MAX);
    encoder.set_frame_delay(1, fps)?;
    let mut writer = encoder.write_header()?;
    let mut rgb = Vec::with_capacity(pixels * 3);
    for frame in frames {
        rgb.clear();
        for px in frame.chunks_exact(4) {
            rgb.extend_from_slice(&px[..3]);
        }
        writer.write_image_data(&rgb)?;
    }
    writer.finish()?;
    Ok(apng)
}

#[cfg(target_arch = "wasm32")]
impl OrbitMovie {
    /// The side panel's Orbit movie: the frame count and the button, or the progress and
    /// Cancel while a movie is made, then how it ended. True when Cancel was pressed.
    pub fn section(&mut self, ui: &mut egui::Ui) -> bool {
        use strata_viewer_ui::orbit_movie::OFFERED_ORBIT_FRAMES;
        let mut cancel = false;
        // Where the controls are, for the browser tests' clicks (`data-movie-controls`).
        let mut placed: Vec<(&str, egui::Rect)> = Vec::new();
        egui::CollapsingHeader::new("Screenshot")
            .default_open(true)
            .show(ui, |ui| match self.progress() {
                Some((taken, total)) => {
                    // Cancel first: the bar takes the rest of the row.
                    ui.horizontal(|ui| {
                        let button = ui.button("Cancel");
                        placed.push(("cancel", button.rect));
                        cancel = button.clicked();
                        ui.add(
                            egui::ProgressBar::new(taken as f32 / total.max(1) as f32)
                                .text(format!("orbit movie: frame {taken} of {total}")),
                        );
                    });
                }
                None => {
                    ui.horizontal(|ui| {
                        let slider = ui.add(
                            egui::Slider::new(&mut self.frames_asked, OFFERED_ORBIT_FRAMES)
                                .text("frames"),
                        );
                        placed.push(("frames", slider.rect));
                        let button = ui.button("Orbit movie").on_hover_text(
                            "Turns the 3D view once around and downloads it as an animated PNG",
                        );
                        placed.push(("start", button.rect));
                        if button.clicked() {
                            self.ask();
                        }
                    });
                    match &self.outcome {
                        Outcome::Failed(problem) => {
                            ui.colored_label(
                                egui::Color32::LIGHT_RED,
                                format!("the movie failed: {problem}"),
                            );
                        }
                        Outcome::Cancelled => {
                            ui.weak("the movie was cancelled");
                        }
                        Outcome::Downloaded | Outcome::None => {}
                    }
                }
            });
        let text: Vec<String> = placed
            .iter()
            .map(|(name, r)| {
                let [x, y, w, h] = [r.min.x, r.min.y, r.width(), r.height()];
                format!("{name}:{x},{y},{w},{h}")
            })
            .collect();
        crate::canvas_attributes::set("data-movie-controls", &text.join(";"));
        cancel
    }

    /// The canvas's `data-movie` for the browser tests.
    pub fn publish(&self) {
        crate::canvas_attributes::set("data-movie", &self.state_text());
    }
}

/// The movie's download name, as the desktop names its orbit folders (`strata-orbit-MILLIS`).
#[cfg(target_arch = "wasm32")]
pub fn movie_name() -> String {
    format!("strata-orbit-{}.png", js_sys::Date::now() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame whose pixels say which frame it is (premultiplied: alpha 255).
    fn frame(index: u8, [w, h]: [u32; 2]) -> Vec<u8> {
        (0..w * h)
            .flat_map(|p| [index, (p % 251) as u8, 255 - index, 255])
            .collect()
    }

    fn decode(apng: &[u8]) -> (png::AnimationControl, Vec<(png::FrameControl, Vec<u8>)>) {
        let mut reader = png::Decoder::new(std::io::Cursor::new(apng))
            .read_info()
            .expect("the movie's header decodes");
        let animation = reader.info().animation_control.expect("an animated PNG");
        let mut frames = Vec::new();
        for _ in 0..animation.num_frames {
            let mut buffer = vec![0; reader.output_buffer_size().expect("a frame size")];
            reader.next_frame(&mut buffer).expect("a frame decodes");
            let control = *reader.info().frame_control().expect("a frame control");
            frames.push((control, buffer));
        }
        (animation, frames)
    }

    #[test]
    fn the_movie_decodes_to_its_frames_at_the_orbit_rate_looping() {
        let size = [5, 3];
        let frames: Vec<Vec<u8>> = (0..4).map(|i| frame(i * 60, size)).collect();
        let apng = encode_apng(&frames, size, ORBIT_FRAMES_PER_SECOND).expect("encodes");
        let (animation, decoded) = decode(&apng);
        assert_eq!(animation.num_frames, 4);
        assert_eq!(animation.num_plays, 0, "an orbit loops");
        for ((control, rgb), sent) in decoded.iter().zip(&frames) {
            assert_eq!((control.width, control.height), (5, 3));
            assert_eq!(
                (control.delay_num, control.delay_den),
                (1, ORBIT_FRAMES_PER_SECOND as u16)
            );
            let expected: Vec<u8> = sent
                .chunks_exact(4)
                .flat_map(|p| [p[0], p[1], p[2]])
                .collect();
            assert_eq!(rgb, &expected, "lossless, RGB over black");
        }
    }

    #[test]
    fn a_movie_takes_its_frames_at_the_shared_azimuths_then_puts_the_view_back() {
        let mut movie = OrbitMovie {
            frames_asked: 4,
            ..OrbitMovie::default()
        };
        assert_eq!(movie.azimuth(), None);
        movie.ask();
        movie.begin(30.0);
        assert_eq!(movie.state_text(), "run=1;frames=0/4;state=making");
        let size = [2, 2];
        let mut seen = Vec::new();
        let finished = loop {
            let azimuth = movie.azimuth().expect("making");
            seen.push(azimuth);
            let taken = seen.len() as u8;
            if let Some(done) = movie.add_frame(frame(taken, size), size).expect("a frame") {
                break done;
            }
        };
        let shared: Vec<f64> = (0..4).map(|i| orbit_azimuth(30.0, i, 4)).collect();
        assert_eq!(seen, shared);
        assert_eq!(finished.start_azimuth, 30.0);
        assert_eq!(decode(&finished.apng).1.len(), 4);
        assert_eq!(movie.state_text(), "run=1;frames=0/0;state=downloaded");
    }

    #[test]
    fn cancel_and_a_resize_end_the_movie_with_the_view_to_restore() {
        let mut movie = OrbitMovie::default();
        movie.ask();
        movie.begin(-10.0);
        assert_eq!(movie.progress(), Some((0, DEFAULT_ORBIT_FRAMES)));
        movie.add_frame(frame(1, [2, 2]), [2, 2]).expect("a frame");
        assert_eq!(movie.cancel(), Some(-10.0));
        assert_eq!(*movie.outcome(), Outcome::Cancelled);
        assert!(!movie.is_making());

        movie.ask();
        movie.begin(0.0);
        movie.add_frame(frame(1, [2, 2]), [2, 2]).expect("a frame");
        let resized = movie
            .add_frame(frame(2, [3, 2]), [3, 2])
            .err()
            .expect("a frame of another size is refused");
        assert!(matches!(resized, MovieError::SizeChanged { .. }));
        assert_eq!(movie.fail(&resized), Some(0.0));
        assert!(matches!(movie.outcome(), Outcome::Failed(_)));
        assert_eq!(movie.state_text(), "run=2;frames=0/0;state=failed");
    }

    #[test]
    fn frames_of_the_wrong_length_are_refused_not_encoded() {
        let error = encode_apng(&[vec![0; 7]], [2, 2], 24).expect_err("7 bytes are no 2×2 frame");
        assert!(matches!(error, MovieError::FrameLength { len: 7, .. }));
    }
}
