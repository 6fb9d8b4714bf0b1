use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use strata_storage::import::{ImportOptions, ImportProgress};
use strata_storage::phantom::Phantom;

#[derive(Args)]
pub struct SampleArgs {
    /// Edge length in voxels (cube), up to 2048 (up to 16384 with --sparse).
    #[arg(long, default_value_t = 256)]
    pub size: u64,
    /// A mostly-air micro-CT-like volume (vessel trees, a bone shell, small shells) written
    /// straight as bricks, only the non-constant ones, with a sparse skeleton: big volumes
    /// (8192³-16384³) in minutes. Writes a store only.
    #[arg(long)]
    pub sparse: bool,
    /// Output: a store directory, or a .nrrd file.
    #[arg(long)]
    pub out: PathBuf,
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

fn write_sparse_store(size: u64, out: &Path) -> Result<()> {
    use strata_storage::sparse_phantom::{SparsePhantom, SparseProgress, MAX_SPARSE_SIZE};
    anyhow::ensure!(
        (1..=MAX_SPARSE_SIZE).contains(&size),
        "--size must be between 1 and {MAX_SPARSE_SIZE} with --sparse, got {size}"
    );
    let bar = crate::progress::count_bar(1, "level 0");
    let progress = |p: SparseProgress| {
        bar.set_length(p.total.max(1));
        bar.set_position(p.done);
        bar.set_message(format!("level {} of {}", p.level, p.levels));
    };
    let report = SparsePhantom::new(size)
        .write_store(out, strata_storage::BrickCodec::default(), Some(&progress))
        .with_context(|| format!("writing sparse phantom store {}", out.display()))?;
    bar.finish_and_clear();
    println!(
        "wrote {} ({size}^3 sparse phantom: {} bricks written of {} nodes, {:.1} MB stored, skeleton {} nodes kept, {:.1} KiB) in {:.1} s",
        out.display(),
        report.written_per_level.iter().sum::<u64>(),
        report.header.layout.total_bricks(),
        report.stats.compressed_bytes as f64 / 1e6,
        report.skeleton_stored_nodes,
        report.skeleton_bytes as f64 / 1024.0,
        report.seconds
    );
    Ok(())
}

pub fn run(args: SampleArgs) -> Result<()> {
    if args.sparse {
        anyhow::ensure!(
            !args
                .out
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("nrrd")),
            "--sparse writes a store, not a .nrrd file"
        );
        return write_sparse_store(args.size, &args.out);
    }
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
