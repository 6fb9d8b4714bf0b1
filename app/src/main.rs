//! `strata`: the viewer and its command line. Not for diagnostic use.

mod bench;
mod cmd_import;
mod cmd_info;
mod cmd_render;
mod cmd_sample;
mod cmd_verify;
mod progress;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "strata", version, about = "Out-of-core viewer for large medical volumes (not for diagnostic use)")]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Import a scan (DICOM folder or file, NIfTI, NRRD, MetaImage, raw) into a brick store.
    Import(cmd_import::ImportArgs),
    /// Print a store's geometry, orientation, value range, levels and sizes.
    Info {
        store: PathBuf,
    },
    /// Read and check every brick of a store (checksums, decompression, ranges).
    Verify {
        store: PathBuf,
    },
    /// Render one frame of a store headless to PNG (GPU, or the f64 CPU reference).
    Render(cmd_render::RenderArgs),
    /// Write the deterministic CT phantom as a store or as NRRD (by the extension of --out).
    Sample(cmd_sample::SampleArgs),
    /// Benchmarks (figures for the issue notes).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

fn main() -> std::process::ExitCode {
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Some(Command::Import(args)) => cmd_import::run(args),
        Some(Command::Info { store }) => cmd_info::run(&store),
        Some(Command::Verify { store }) => cmd_verify::run(&store),
        Some(Command::Sample(args)) => cmd_sample::run(args),
        Some(Command::Render(args)) => cmd_render::run(args),
        Some(Command::Bench(cmd)) => bench::run(cmd),
        None => demo(),
    }
}

/// The main job until the interactive viewer lands: make sure the demo volume exists, then
/// render it headless on the GPU to a PNG beside it.
fn demo() -> Result<()> {
    let store = cmd_sample::ensure_demo_volume()?;
    let out = store.with_extension("png");
    cmd_render::run(cmd_render::RenderArgs {
        store: store.clone(),
        out: out.clone(),
        size: "512x512".into(),
        azimuth: 30.0,
        elevation: 15.0,
        zoom: 1.0,
        mode: cmd_render::ModeArg::Dvr,
        tf: Some("ct-bone".into()),
        step: 0.5,
        level: 0,
        reference: false,
        shading: true,
        iso: 300.0,
        orthographic: false,
        no_jitter: false,
    })?;
    println!("The interactive viewer is not built yet (clinician-app issue); this run rendered {} headless.", out.display());
    println!("Try: strata info {0} | strata render {0} --mode mip --out mip.png", store.display());
    Ok(())
}
