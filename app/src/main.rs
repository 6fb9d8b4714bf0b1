//! `strata`: the viewer and its command line. Not for diagnostic use.

mod bench;
mod cmd_import;
mod cmd_info;
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
        Some(Command::Bench(cmd)) => bench::run(cmd),
        None => cmd_sample::ensure_demo_volume().map(|path| {
            println!("Demo volume ready at {}", path.display());
            println!("The interactive viewer arrives with the clinician-app issue; meanwhile try `strata info {}`.", path.display());
        }),
    }
}
