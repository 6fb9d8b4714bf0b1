//! `strata`: the viewer and its command line. Not for diagnostic use.

mod cli_checks;
mod cmd_flythrough;
mod cmd_import;
mod cmd_info;
mod cmd_omezarr;
mod cmd_pacs;
mod cmd_render;
mod cmd_sample;
mod cmd_seg;
mod cmd_serve;
mod cmd_store;
mod cmd_verify;
mod progress;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "strata",
    version,
    about = "Out-of-core viewer for large medical volumes (not for diagnostic use)"
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Import a scan (DICOM folder or file, NIfTI, NRRD, MetaImage, raw) into a brick store.
    Import(cmd_import::ImportArgs),
    /// Export a store as OME-Zarr 0.5 (sharded Zarr v3) to a folder or s3://bucket/prefix.
    Export(cmd_omezarr::ExportArgs),
    /// Print a store's geometry, orientation, value range, levels and sizes.
    Info(StoreArg),
    /// Read and check every brick of a store (checksums, decompression, ranges).
    Verify(cmd_verify::VerifyArgs),
    /// Serve stores read-only over HTTP/1.1 and HTTP/2 (loopback unless told otherwise).
    Serve(cmd_serve::ServeArgs),
    /// Render one frame of a store headless to PNG (GPU, or the f64 CPU reference).
    Render(cmd_render::RenderArgs),
    /// Write the deterministic CT phantom as a store or as NRRD (by the extension of --out).
    Sample(cmd_sample::SampleArgs),
    /// Open the viewer on a store, or on a scan (imported into your data folder first).
    View(ViewArgs),
    /// Replay a scripted camera path with the streaming loader; per-frame stats to CSV.
    Flythrough(cmd_flythrough::FlythroughArgs),
    /// The stores of the viewer's data folder: list them, prune what can go.
    #[command(subcommand)]
    Store(cmd_store::StoreCommand),
    /// Label maps (segmentations): per-segment statistics, export to DICOM SEG, NIfTI, OME-Zarr.
    #[command(subcommand)]
    Seg(cmd_seg::SegCommand),
    /// A DICOMweb server (PACS): find studies and series, push DICOM files.
    #[command(subcommand)]
    Pacs(cmd_pacs::PacsCommand),
}

fn main() -> std::process::ExitCode {
    // Before any thread starts: memory a closed volume gave back stays reusable.
    strata_loader::malloc_arenas::limit_malloc_arenas();
    install_interrupt_cleanup();
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", strata_viewer::error_report::describe(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// Ctrl-C and SIGTERM end the process without running destructors, which would leave the
/// decompressed staging copy of a compressed input behind (gigabytes for a large scan): delete
/// it first. (SIGKILL cannot be caught: the next run removes such files, see
/// `remove_stale_staging_files`.)
fn install_interrupt_cleanup() {
    let installed = ctrlc::set_handler(|| {
        let removed = strata_storage::readers::remove_live_staging_files();
        if removed > 0 {
            eprintln!("interrupted: removed {removed} temporary staging file(s)");
        } else {
            eprintln!("interrupted");
        }
        // `_exit`, not `exit`: `exit` runs the GPU driver's atexit teardown while the main
        // thread may still be polling the device, which then panics with "Parent device is
        // lost" (the H200 run of 2026-12-04 read a step killed by its timeout as a lost
        // device that way).
        // SAFETY: `_exit` takes no pointers and never returns; skipping destructors and
        // atexit handlers is the point (the staging files are already removed).
        unsafe { libc::_exit(130) }
    });
    if let Err(e) = installed {
        eprintln!("warning: cannot install the interrupt handler ({e}); an interrupted import may leave its staging file in the temp folder");
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Some(Command::Import(args)) => cmd_import::run(args),
        Some(Command::Export(args)) => cmd_omezarr::run_export(args),
        Some(Command::Info(a)) => cmd_info::run(&a.store, a.token_file.as_deref()),
        Some(Command::Verify(a)) => cmd_verify::run(&a),
        Some(Command::Serve(args)) => cmd_serve::run(args),
        Some(Command::Sample(args)) => cmd_sample::run(args),
        Some(Command::Render(args)) => cmd_render::run(args),
        Some(Command::Pacs(cmd)) => cmd_pacs::run(cmd),
        Some(Command::Seg(cmd)) => cmd_seg::run(cmd),
        Some(Command::Store(cmd)) => cmd_store::run(cmd),
        Some(Command::Flythrough(args)) => cmd_flythrough::run(args),
        Some(Command::View(args)) => view(args),
        None => strata_viewer::run(strata_viewer::ViewerOptions::new(
            strata_viewer::demo_source(),
        )),
    }
}

#[derive(clap::Args)]
struct StoreArg {
    /// A store directory, or http://HOST:PORT/v1/stores/NAME served by `strata serve`.
    store: String,
    /// Bearer token for a server that requires one.
    #[arg(long)]
    token_file: Option<PathBuf>,
}

#[derive(clap::Args)]
struct ViewArgs {
    /// A store, a scan to import first (DICOM folder or file, NIfTI, NRRD, MetaImage),
    /// http://HOST:PORT/v1/stores/NAME served by `strata serve`, or a web viewer's link
    /// (http://HOST:PORT/#store=NAME&az=…: that store and view). Without it, the demo phantom.
    path: Option<PathBuf>,
    /// Bearer token for a server that requires one.
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// DICOM: the series to open when a folder holds several (SeriesInstanceUID or index).
    #[arg(long)]
    series: Option<String>,
    /// Close after this many seconds (smoke tests, measurements).
    #[arg(long)]
    exit_after: Option<f64>,
    /// Orbit the 3D view continuously at this many degrees per second (measurements).
    #[arg(long)]
    orbit: Option<f64>,
    /// Write UI and volume frame times as CSV on exit.
    #[arg(long)]
    frame_log: Option<PathBuf>,
    /// Window size WxH in points.
    #[arg(long, default_value = "1360x860")]
    window: String,
    /// Layout to start with: single, conventional (3D over three slices) or four-up.
    #[arg(long)]
    layout: Option<String>,
    /// Start the 3D view from this side: A, P, L, R, S or I.
    #[arg(long)]
    view: Option<String>,
    /// Transfer-function preset to start with (ct-bone, ct-soft-tissue, ct-lung, ct-vessels, mr-default).
    #[arg(long)]
    preset: Option<String>,
    /// A label map (store or scan) to show over the volume, as the Overlay panel opens it.
    #[arg(long)]
    overlay: Vec<PathBuf>,
    /// Start from default settings and do not remember them.
    #[arg(long)]
    fresh: bool,
}

fn view(args: ViewArgs) -> Result<()> {
    let source = match args.path {
        Some(path)
            if strata_viewer::volume_location::is_url(&path.to_string_lossy())
                || strata_omezarr::looks_like_ome_zarr(&path.to_string_lossy()) =>
        {
            strata_viewer::url_source(path.to_string_lossy().into_owned(), args.token_file)
        }
        Some(path) => strata_viewer::path_source(path),
        None => strata_viewer::demo_source(),
    };
    let (width, height) = strata_viewer::export::parse_size(&args.window)?;
    let mut options = strata_viewer::ViewerOptions::new(source);
    options.dicom_series = args.series;
    options.exit_after_seconds = args.exit_after;
    options.auto_orbit_deg_per_second = args.orbit;
    options.frame_log = args.frame_log;
    options.window_size = [width as f32, height as f32];
    options.persist_settings = !args.fresh;
    options.initial_layout = match args.layout.as_deref() {
        None => None,
        Some("single") => Some(strata_viewer::app::Layout::Single),
        Some("conventional") => Some(strata_viewer::app::Layout::ThreeDOverSlices),
        Some("four-up") => Some(strata_viewer::app::Layout::TwoByTwo),
        Some(other) => {
            anyhow::bail!("--layout must be single, conventional or four-up, not '{other}'")
        }
    };
    options.initial_view = match args.view.as_deref() {
        None => None,
        Some(letter) => Some(
            strata_viewer_ui::orbit::StandardView::ALL
                .into_iter()
                .find(|v| v.letter().eq_ignore_ascii_case(letter))
                .ok_or_else(|| {
                    anyhow::anyhow!("--view must be one of A, P, L, R, S, I, not '{letter}'")
                })?,
        ),
    };
    options.initial_preset = args.preset;
    if args.overlay.len() > 1 {
        // The viewer holds one overlay at a time (overlay.rs); say so rather than drop some.
        anyhow::bail!(
            "--overlay was given {} times; the viewer shows one overlay at a time",
            args.overlay.len()
        );
    }
    options.overlay = args.overlay.into_iter().next();
    strata_viewer::run(options)
}
