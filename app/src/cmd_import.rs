use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use strata_storage::import::{import_source, ImportOptions, ImportProgress};
use strata_storage::readers::{open_source, RawSpec, ReadOptions};
use strata_storage::{BrickCodec, ByteOrder, SampleType};
use strata_viewer::pacs_client::add_provenance;

#[derive(Args)]
pub struct ImportArgs {
    /// DICOM folder or file, .nii/.nii.gz, .nrrd/.nhdr, .mha/.mhd, raw (with --raw-*), an
    /// OME-Zarr (a folder, s3://BUCKET/PREFIX or http(s)://.../x.ome.zarr), or with --study a
    /// DICOMweb server (its base URL or its name in the servers file).
    pub input: PathBuf,
    /// Store directory to create. An existing store there is refused unless --replace is
    /// given (an interrupted import's leftovers are always replaced).
    pub store: PathBuf,
    /// Replace an existing store at STORE (its bricks, and any edits, are lost).
    #[arg(long)]
    pub replace: bool,
    /// Store format to write: 3 (pack files, the default) or 2 (sled, as earlier builds
    /// wrote; for benchmarks and tests of old stores). Single volumes only.
    #[arg(long, hide = true)]
    pub format: Option<u32>,
    /// DICOM: the series to import when a folder holds several (SeriesInstanceUID or index;
    /// from a DICOMweb server, its SeriesInstanceUID).
    #[arg(long)]
    pub series: Option<String>,
    /// Retrieve this study (StudyInstanceUID) from the DICOMweb server INPUT and import it.
    #[arg(long)]
    pub study: Option<String>,
    #[command(flatten)]
    pub pacs: crate::cmd_pacs::ServerArgs,
    /// Memory budget for the import in MiB (buffers plus database cache).
    #[arg(long, default_value_t = 1024, value_parser = crate::cli_checks::budget_mib)]
    pub memory_mib: u64,
    /// Raw input: dimensions as X,Y,Z (512,512,300 or 512 512 300).
    #[arg(long, value_delimiter = ',', num_args = 1..=3)]
    pub raw_dims: Option<Vec<u64>>,
    /// Raw input: u8, i8, u16, i16, u32, i32, f32, f64.
    #[arg(long)]
    pub raw_type: Option<String>,
    /// Raw input: voxel spacing in mm as X,Y,Z (0.5,0.5,1 or 0.5 0.5 1).
    #[arg(long, value_delimiter = ',', num_args = 1..=3, default_values_t = vec![1.0, 1.0, 1.0])]
    pub raw_spacing: Vec<f64>,
    /// Raw input: byte order, little or big.
    #[arg(long, default_value = "little")]
    pub raw_endian: String,
    /// Raw input: bytes to skip before the voxels.
    #[arg(long, default_value_t = 0)]
    pub raw_header_bytes: u64,
    /// Brick codec: fast (byte shuffle + lz4, the default) or dense (byte shuffle + zstd:
    /// smaller stores, slower to decode).
    #[arg(long, default_value = "fast", value_parser = parse_codec)]
    pub codec: BrickCodec,
    /// Folder for temporary decompressed data (default: the system temp folder).
    #[arg(long)]
    pub staging_dir: Option<PathBuf>,
    /// OME-Zarr: the channel to import when the image has a channel axis (default 0).
    #[arg(long)]
    pub channel: Option<u64>,
    /// OME-Zarr: the time point to import when the image has a time axis (default 0).
    #[arg(long)]
    pub time: Option<u64>,
    #[command(flatten)]
    pub object_store: crate::cmd_omezarr::ObjectStoreArgs,
}

/// `--codec`: the codecs a new store may use (lz4 alone is format 1's, not offered).
fn parse_codec(name: &str) -> Result<BrickCodec> {
    match BrickCodec::parse(name) {
        Some(c @ (BrickCodec::Fast | BrickCodec::Dense)) => Ok(c),
        _ => bail!("'{name}' is not a codec: use fast or dense"),
    }
}

pub fn parse_sample_type(name: &str) -> Result<SampleType> {
    Ok(match name.to_ascii_lowercase().as_str() {
        "u8" | "uint8" => SampleType::U8,
        "i8" | "int8" => SampleType::I8,
        "u16" | "uint16" => SampleType::U16,
        "i16" | "int16" => SampleType::I16,
        "u32" | "uint32" => SampleType::U32,
        "i32" | "int32" => SampleType::I32,
        "f32" | "float32" | "float" => SampleType::F32,
        "f64" | "float64" | "double" => SampleType::F64,
        other => {
            bail!("unknown raw sample type '{other}' (use u8, i8, u16, i16, u32, i32, f32 or f64)")
        }
    })
}

/// Three values of a comma- or space-separated `--flag X,Y,Z`.
fn three<T: Copy + std::fmt::Display>(flag: &str, values: &[T]) -> Result<[T; 3]> {
    match values {
        [x, y, z] => Ok([*x, *y, *z]),
        _ => bail!(
            "--{flag} needs three values as X,Y,Z (or X Y Z), got {}",
            values
                .iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(",")
        ),
    }
}

pub fn run(mut args: ImportArgs) -> Result<()> {
    refuse_existing_store(&args.store, args.replace)?;
    // From a PACS: the series is retrieved into a folder beside the store, imported as any
    // DICOM folder, and the folder removed once the import succeeded. After a failure or an
    // interruption it stays, and the same command resumes: instances there are not fetched
    // again.
    let Some(study) = args.study.clone() else {
        return import(args, None);
    };
    let retrieved = crate::cmd_pacs::retrieve_for_import(
        &args.input.to_string_lossy(),
        &study,
        args.series.as_deref(),
        &args.pacs,
        &args.store,
    )?;
    args.input = retrieved.folder.clone();
    import(args, Some(retrieved.provenance.clone()))?;
    retrieved.remove();
    Ok(())
}

/// Refuses to import over an existing store (complete, in use or damaged) without `--replace`,
/// naming it and what it holds. What an interrupted import left is replaced: it holds nothing
/// that opens.
fn refuse_existing_store(store: &std::path::Path, replace: bool) -> Result<()> {
    use strata_storage::inventory::{survey, StoreState};
    if replace || !store.join("STRATA-STORE").exists() {
        return Ok(());
    }
    let entry = survey(store);
    let holds = match &entry.state {
        StoreState::Incomplete => return Ok(()),
        StoreState::Complete {
            format_version,
            codec,
            inputs,
        } => format!(
            "a complete store of format {format_version} ({codec:?} codec, {:.1} MB) imported from {}",
            entry.size_bytes as f64 / 1e6,
            if inputs.is_empty() {
                "an unnamed source".to_string()
            } else {
                inputs.join(", ")
            }
        ),
        StoreState::InUse(holder) => format!("a store in use ({holder})"),
        StoreState::Damaged(e) => format!("a damaged store ({e})"),
        StoreState::Unsupported(e) => format!("a store this build cannot read ({e})"),
    };
    bail!(
        "{} already holds {holds}; give --replace to replace it (its bricks are lost), or choose another path",
        store.display()
    )
}

fn import(args: ImportArgs, provenance: Option<String>) -> Result<()> {
    let input = args.input.to_string_lossy().into_owned();
    if strata_omezarr::looks_like_ome_zarr(&input) {
        let zarr = strata_omezarr::import::ImportZarrOptions {
            channel: args.channel,
            time: args.time,
            staging_dir: args.staging_dir.clone(),
            memory_budget_bytes: None,
        };
        return crate::cmd_omezarr::run_import(
            &input,
            &args.store,
            &zarr,
            &args.object_store,
            args.memory_mib << 20,
            args.codec,
        );
    }
    let raw = match (&args.raw_dims, &args.raw_type) {
        (Some(d), Some(t)) => Some(RawSpec {
            dims: three("raw-dims", d)?,
            sample_type: parse_sample_type(t)?,
            spacing_mm: three("raw-spacing", &args.raw_spacing)?,
            byte_order: match args.raw_endian.as_str() {
                "little" => ByteOrder::Little,
                "big" => ByteOrder::Big,
                other => bail!("--raw-endian must be little or big, not '{other}'"),
            },
            header_bytes: args.raw_header_bytes,
        }),
        (None, None) => None,
        _ => bail!("raw input needs both --raw-dims and --raw-type"),
    };
    let options = ReadOptions {
        dicom_series: args.series.clone(),
        raw,
        staging_dir: args.staging_dir.clone(),
    };
    let mut opened = open_source(&args.input, &options)
        .with_context(|| format!("cannot read {}", args.input.display()))?;
    if let Some(p) = provenance {
        add_provenance(&mut opened.info.description, &p);
    }
    let g = &opened.info.geometry;
    eprintln!(
        "{} {}: {}x{}x{} {} voxels, spacing {:.4}x{:.4}x{:.4} mm",
        opened.info.format,
        args.input.display(),
        g.dims[0],
        g.dims[1],
        g.dims[2],
        opened.info.sample_type.name(),
        g.spacing_mm[0],
        g.spacing_mm[1],
        g.spacing_mm[2]
    );
    // Header values replaced by an assumption: said here, and kept in the store's description.
    for warning in opened.info.warnings() {
        eprintln!("warning: {}: {warning}", args.input.display());
    }
    if opened.info.frames > 1 {
        eprintln!(
            "{} frames (time points), each a frame of the store",
            opened.info.frames
        );
    }
    let total = opened.data.slice_bytes_len() as u64 * opened.data.dims[2];
    let bar = crate::progress::bytes_bar(total, "importing");
    let progress = |p: ImportProgress| bar.set_position(p.source_bytes_done);
    let import_options = ImportOptions {
        memory_budget_bytes: args.memory_mib << 20,
        cancel: None,
        progress: Some(&progress),
        codec: args.codec,
    };
    let imported = match args.format {
        Some(format) => strata_storage::import::import_source_as_format(
            opened,
            &args.store,
            &import_options,
            format,
        ),
        None => import_source(opened, &args.store, &import_options),
    };
    let report = imported.with_context(|| {
        format!(
            "import of {} into {} failed",
            args.input.display(),
            args.store.display()
        )
    })?;
    bar.finish_and_clear();
    let s = &report.stats;
    println!(
        "imported {} into {}: {:.1} MB source in {:.2} s ({:.0} MB/s), {} bricks, {:.1} MB stored with the {} codec (ratio {:.2})",
        args.input.display(),
        args.store.display(),
        s.source_bytes as f64 / 1e6,
        s.import_seconds,
        s.source_bytes as f64 / 1e6 / s.import_seconds.max(1e-9),
        s.bricks_per_level.iter().map(|l| l.0).sum::<u64>(),
        s.compressed_bytes as f64 / 1e6,
        report.header.codec.name(),
        s.uncompressed_bytes as f64 / s.compressed_bytes.max(1) as f64,
    );
    if report.header.quantization_error > 0.0 {
        println!(
            "note: the source was quantised to 16 bits; worst-case error {:.6} (physical units)",
            report.header.quantization_error
        );
    }
    if report.header.non_finite_samples > 0 {
        println!(
            "note: {} NaN/Inf samples were mapped to the range ends (NaN and -Inf to the lowest value, +Inf to the highest)",
            report.header.non_finite_samples
        );
    }
    Ok(())
}
