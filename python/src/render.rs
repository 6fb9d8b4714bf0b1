//! `strata.render`: one headless frame of an open volume, through strata-headless, the code
//! `strata render` runs, so the two return the same frame for the same options.
//!
//! The render runs on its own thread with the GIL released (Ctrl-C returns at once) and a panic
//! there is reported as `no_panic` does; a bad option is a
//! `ValueError`, no usable GPU adapter (or any failed render) a `RenderError`, a store that
//! cannot be read the store's own exception.

use std::sync::mpsc::RecvTimeoutError;
use std::time::Duration;

use pyo3::create_exception;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyByteArray;
use strata_headless::{HeadlessError, Mode, RenderOptions, ShadowsOption};
use strata_loader::LoaderError;

use crate::{no_panic, store_error, streamed, NativeStore, StrataError};

create_exception!(
    _strata,
    RenderError,
    StrataError,
    "A frame cannot be rendered: no usable GPU adapter (the message says what to install), or \
     the GPU failed."
);

/// The Python exception of a headless render's error.
fn render_error(e: HeadlessError, secret: Option<&str>) -> PyErr {
    match e {
        HeadlessError::Option(_) | HeadlessError::TransferFunction(_) => {
            PyValueError::new_err(e.to_string())
        }
        HeadlessError::Loader(LoaderError::Storage(e)) => store_error(e),
        HeadlessError::Loader(LoaderError::Source(e)) => streamed::source_error(e, secret),
        e => RenderError::new_err(e.to_string()),
    }
}

/// The frame of `store` as `strata render` draws it with the same options (see
/// `strata/_render.py` for each option): returns (width, height, premultiplied RGBA bytes,
/// the progress notes `strata render` prints).
#[pyfunction]
#[pyo3(signature = (
    store, *, width, height, azimuth, elevation, zoom, mode, tf, step, level, up_front,
    max_frames, quality, reference, shading, iso, orthographic, jitter, smooth,
    exact_trilinear, oracle_epsilon, traversal, gpu_mib, shadows, light_dir, shadow_step,
    light_cache_res, occlusion, scattering, scattering_blend, progressive
))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn render<'py>(
    py: Python<'py>,
    store: &NativeStore,
    width: u32,
    height: u32,
    azimuth: f64,
    elevation: f64,
    zoom: f64,
    mode: &str,
    tf: Option<String>,
    step: f64,
    level: u8,
    up_front: bool,
    max_frames: usize,
    quality: f64,
    reference: bool,
    shading: bool,
    iso: f64,
    orthographic: bool,
    jitter: bool,
    smooth: bool,
    exact_trilinear: bool,
    oracle_epsilon: f64,
    traversal: Option<&str>,
    gpu_mib: Option<u64>,
    shadows: &str,
    light_dir: Option<[f64; 3]>,
    shadow_step: f64,
    light_cache_res: f64,
    occlusion: Option<f64>,
    scattering: Option<f64>,
    scattering_blend: f64,
    progressive: Option<u32>,
) -> PyResult<(u32, u32, Bound<'py, PyByteArray>, Vec<String>)> {
    let secret = store.secret.as_deref();
    let bad = |e: HeadlessError| render_error(e, secret);
    let options = RenderOptions {
        width,
        height,
        azimuth,
        elevation,
        zoom,
        mode: Mode::from_name(mode).map_err(bad)?,
        tf,
        step,
        level,
        up_front,
        max_frames,
        quality,
        reference,
        shading,
        iso,
        orthographic,
        jitter,
        smooth,
        exact_trilinear,
        oracle_epsilon,
        traversal: traversal
            .map(strata_headless::traversal_from_name)
            .transpose()
            .map_err(bad)?,
        gpu_mib,
        shadows: ShadowsOption::from_name(shadows).map_err(bad)?,
        light_dir,
        shadow_step,
        light_cache_res,
        occlusion,
        scattering,
        scattering_blend,
        progressive,
    };
    options.validate().map_err(bad)?;
    let opened = store.get()?;
    let source = opened.source();
    let name = store.location.clone();
    // The frame is drawn on a thread of its own while this one waits with the GIL released and
    // looks for Ctrl-C every 50 ms: a pending KeyboardInterrupt returns at once. The GPU work
    // cannot be stopped part-way, so a frame in progress finishes on its thread and is dropped.
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("strata-py-render".into())
        .spawn(move || {
            let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                let mut notes = Vec::new();
                strata_headless::render(source, &name, &options, &mut |note: String| {
                    notes.push(note)
                })
                .map(|frame| (frame, notes))
            }));
            // The caller may have gone (Ctrl-C): then nobody wants the frame.
            let _ = sender.send(outcome);
        })
        .map_err(|e| StrataError::new_err(format!("cannot start the render thread: {e}")))?;
    // The receiver goes into each wait and comes back (it is Send, not Sync).
    let mut receiver = receiver;
    let outcome =
        loop {
            let wait = Duration::from_millis(50);
            let (got, back) = py.allow_threads(move || {
                let got = receiver.recv_timeout(wait);
                (got, receiver)
            });
            receiver = back;
            match got {
                Ok(outcome) => break outcome,
                Err(RecvTimeoutError::Timeout) => py.check_signals()?,
                Err(RecvTimeoutError::Disconnected) => return Err(StrataError::new_err(
                    "the render thread ended without a frame (a bug in Strata: please report it)",
                )),
            }
        };
    // A panic on the render thread is reported as every other (a StrataError naming the bug).
    let (frame, notes) = no_panic("rendering", || match outcome {
        Ok(result) => result.map_err(bad),
        Err(payload) => std::panic::resume_unwind(payload),
    })?;
    let rgba = PyByteArray::new(py, &frame.rgba);
    Ok((frame.width, frame.height, rgba, notes))
}
