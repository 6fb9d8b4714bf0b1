//! `strata export STORE DEST` (OME-Zarr 0.5 to a folder, s3://bucket/prefix) and the
//! OME-Zarr side of `strata import`.

use std::path::Path;

use anyhow::{Context, Result};
use clap::Args;
use strata_omezarr::export::{export, ExportOptions};
use strata_omezarr::import::{import_zarr, ImportZarrOptions};
use strata_omezarr::{ObjectLocation, ObjectStoreOptions};
use strata_storage::import::{ImportOptions, ImportProgress};

/// Object-store flags shared by export and import.
#[derive(Args, Clone, Debug, Default)]
pub struct ObjectStoreArgs {
    /// S3 endpoint, e.g. http://127.0.0.1:8333 (default: AWS_ENDPOINT_URL, else AWS itself).
    /// Credentials come from AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY (/ AWS_SESSION_TOKEN).
    #[arg(long)]
    pub s3_endpoint: Option<String>,
    /// S3 region (default: AWS_REGION, else us-east-1).
    #[arg(long)]
    pub s3_region: Option<String>,
}

impl ObjectStoreArgs {
    pub fn options(&self) -> ObjectStoreOptions {
        ObjectStoreOptions {
            endpoint: self.s3_endpoint.clone(),
            region: self.s3_region.clone(),
            credentials: None,
        }
    }
}

#[derive(Args)]
pub struct ExportArgs {
    /// The store to export (a store directory, or a URL `strata serve` serves).
    pub store: String,
    /// Destination: a folder (created), or s3://BUCKET/PREFIX. A previous Strata export there
    /// is replaced; anything else is refused.
    pub dest: String,
    /// Keep the store's description and provenance (input file paths) in the export; they are
    /// left out by default, as they may name the patient.
    #[arg(long)]
    pub expose_identifiers: bool,
    /// Bearer token for a store served by a server that requires one.
    #[arg(long)]
    pub token_file: Option<std::path::PathBuf>,
    #[command(flatten)]
    pub object_store: ObjectStoreArgs,
}

pub fn run_export(args: ExportArgs) -> Result<()> {
    let source = strata_viewer::volume_location::open_source(
        &args.store,
        args.token_file.as_deref(),
        strata_storage::store::DEFAULT_READ_CACHE_BYTES,
    )?;
    let dest = ObjectLocation::open(&args.dest, &args.object_store.options(), true)
        .with_context(|| format!("cannot open the destination {}", args.dest))?;
    let bar = crate::progress::count_bar(0, "exporting shards");
    let progress = |done: u64, total: u64| {
        bar.set_length(total);
        bar.set_position(done);
    };
    let started = std::time::Instant::now();
    let options = ExportOptions {
        expose_identifiers: args.expose_identifiers,
        ..ExportOptions::default()
    };
    let report = export(source.as_ref(), &dest, &options, &progress)
        .with_context(|| format!("export of {} to {} failed", args.store, args.dest))?;
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "exported {} to {} as OME-Zarr 0.5: {} levels, {} shards written ({} fill-only left out), {:.1} MB of shards + {:.1} kB metadata, {:.2} s ({:.0} MB/s of level-0 voxels)",
        args.store,
        args.dest,
        report.levels,
        report.shards_written,
        report.shards_skipped,
        report.shard_bytes as f64 / 1e6,
        report.metadata_bytes as f64 / 1e3,
        seconds,
        report.level0_bytes as f64 / 1e6 / seconds.max(1e-9),
    );
    if !args.expose_identifiers {
        println!("note: description and provenance withheld (--expose-identifiers keeps them)");
    }
    Ok(())
}

/// `strata import` of an OME-Zarr (folder, s3://, http(s)://).
pub fn run_import(
    input: &str,
    store: &Path,
    zarr: &ImportZarrOptions,
    object_store: &ObjectStoreArgs,
    memory_budget_bytes: u64,
    codec: strata_storage::BrickCodec,
) -> Result<()> {
    let location = ObjectLocation::open(input, &object_store.options(), false)
        .with_context(|| format!("cannot open {input}"))?;
    let stage_bar = crate::progress::count_bar(0, "reading level 0 (slices)");
    let stage_progress = |done: u64, total: u64| {
        stage_bar.set_length(total);
        stage_bar.set_position(done);
    };
    let import_bar = crate::progress::bytes_bar(0, "importing");
    let progress = |p: ImportProgress| {
        import_bar.set_length(p.source_bytes_total);
        import_bar.set_position(p.source_bytes_done);
    };
    let import_options = ImportOptions {
        memory_budget_bytes,
        cancel: None,
        progress: Some(&progress),
        codec,
    };
    let report = import_zarr(location, store, zarr, &stage_progress, &import_options)
        .with_context(|| format!("import of {input} into {} failed", store.display()))?;
    stage_bar.finish_and_clear();
    import_bar.finish_and_clear();
    let g = &report.import.header.geometry;
    println!(
        "imported OME-Zarr {input} into {}: {}x{}x{} voxels, spacing {:.4}x{:.4}x{:.4} mm{}",
        store.display(),
        g.dims[0],
        g.dims[1],
        g.dims[2],
        g.spacing_mm[0],
        g.spacing_mm[1],
        g.spacing_mm[2],
        if report.strata_export {
            ", Strata geometry from the `strata` attribute"
        } else {
            ""
        }
    );
    for note in &report.notes {
        println!("note: {note}");
    }
    Ok(())
}
