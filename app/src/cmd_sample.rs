use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use strata_storage::import::{ImportOptions, ImportProgress};
use strata_storage::phantom::Phantom;

#[derive(Args)]
pub struct SampleArgs {
    /// Edge length in voxels (cube), up to 2048.
    #[arg(long, default_value_t = 256)]
    pub size: u64,
    /// Output: a store directory, or a .nrrd file.
    #[arg(long)]
    pub out: PathBuf,
}

pub const DEMO_SIZE: u64 = 256;

/// The demo volume in the workspace's sample-data folder (or beside the executable when the
/// workspace is not around), generated on first use.
pub fn demo_store_path() -> PathBuf {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("sample-data");
    let base = if workspace.is_dir() {
        workspace
    } else {
        PathBuf::from("sample-data")
    };
    base.join(format!("demo-phantom-{DEMO_SIZE}.strata"))
}

fn write_store(phantom: &Phantom, out: &Path) -> Result<()> {
    let total = phantom.size.iter().product::<u64>() * 2;
    let bar = crate::progress::bytes_bar(total, "generating");
    let progress = |p: ImportProgress| bar.set_position(p.source_bytes_done);
    let options = ImportOptions {
        progress: Some(&progress),
        ..Default::default()
    };
    let report = phantom
        .write_store(out, &options)
        .with_context(|| format!("writing phantom store {}", out.display()))?;
    bar.finish_and_clear();
    println!(
        "wrote {} ({}^3 phantom, {:.1} MB stored) in {:.2} s",
        out.display(),
        phantom.size[0],
        report.stats.compressed_bytes as f64 / 1e6,
        report.stats.import_seconds
    );
    Ok(())
}

pub fn run(args: SampleArgs) -> Result<()> {
    anyhow::ensure!(
        (1..=2048).contains(&args.size),
        "--size must be between 1 and 2048, got {}",
        args.size
    );
    let phantom = Phantom::cube(args.size);
    if args
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("nrrd"))
    {
        let bar = crate::progress::count_bar(args.size, "writing slices");
        phantom
            .write_nrrd(&args.out, Some(&|done, _| bar.set_position(done)))
            .with_context(|| format!("writing {}", args.out.display()))?;
        bar.finish_and_clear();
        println!(
            "wrote {} ({}^3 int16 HU phantom)",
            args.out.display(),
            args.size
        );
        Ok(())
    } else {
        write_store(&phantom, &args.out)
    }
}
