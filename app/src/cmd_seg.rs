//! `strata seg`: label maps from the command line (issue 52): per-segment statistics and export
//! to DICOM SEG, NIfTI or OME-Zarr `labels/`.
//!
//! `stats` streams the label file (and the primary, when `--on` names a scan on the same grid)
//! one slice at a time: voxel count, volume in mL, and the primary's mean, SD, min and max per
//! segment. Note: the editor's statistics module (median, bounding box in mm) is being written
//! beside this; once it lands, `stats` should print through it so the panel and the CLI agree.

use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use clap::{Subcommand, ValueEnum};

use strata_segment::io::{load_label_file, write_dicom_seg, write_nifti, SegOptions};
use strata_segment::LabelRead;

#[derive(Subcommand)]
pub enum SegCommand {
    /// Per segment: voxel count, volume in mL, and (with --on) the primary's mean, SD, min, max.
    Stats(StatsArgs),
    /// Save a label map as DICOM SEG, NIfTI or OME-Zarr labels.
    Export(ExportArgs),
}

#[derive(clap::Args)]
pub struct StatsArgs {
    /// A label map: NIfTI, DICOM SEG, NRRD, MetaImage or MGH.
    labels: PathBuf,
    /// The scan the labels were drawn on (a file or a DICOM folder, on the labels' grid).
    #[arg(long)]
    on: Option<PathBuf>,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum ExportFormat {
    Seg,
    Nifti,
    OmeZarr,
}

#[derive(clap::Args)]
pub struct ExportArgs {
    /// A label map: NIfTI, DICOM SEG, NRRD, MetaImage or MGH.
    labels: PathBuf,
    #[arg(long, value_enum)]
    format: ExportFormat,
    /// The file to write (.dcm, .nii or .nii.gz), or for ome-zarr the image's .zarr folder
    /// (the labels go to OUT/labels/NAME).
    #[arg(short, long)]
    out: PathBuf,
    /// The label image's name under labels/ (ome-zarr only).
    #[arg(long, default_value = "segmentation")]
    name: String,
}

pub fn run(command: SegCommand) -> Result<()> {
    match command {
        SegCommand::Stats(args) => stats(&args.labels, args.on.as_deref()),
        SegCommand::Export(args) => export(&args),
    }
}

fn load(path: &Path) -> Result<strata_segment::LabelLayer> {
    load_label_file(path).with_context(|| format!("loading label map {}", path.display()))
}

fn export(args: &ExportArgs) -> Result<()> {
    let layer = load(&args.labels)?;
    match args.format {
        ExportFormat::Nifti => {
            write_nifti(&layer, &args.out)
                .with_context(|| format!("writing NIfTI {}", args.out.display()))?;
        }
        ExportFormat::Seg => {
            let summary = write_dicom_seg(&layer, &args.out, &SegOptions::default())
                .with_context(|| format!("writing DICOM SEG {}", args.out.display()))?;
            eprintln!(
                "{} segment(s), {} frame(s)",
                summary.segments, summary.frames
            );
        }
        ExportFormat::OmeZarr => {
            strata_segment::io::write_omezarr_labels(&layer, &args.out, &args.name).with_context(
                || {
                    format!(
                        "writing OME-Zarr labels {}/labels/{}",
                        args.out.display(),
                        args.name
                    )
                },
            )?;
        }
    }
    println!("wrote {}", args.out.display());
    Ok(())
}

/// Running sums of one segment.
#[derive(Clone, Copy)]
struct Sums {
    count: u64,
    sum: f64,
    sum_sq: f64,
    min: f64,
    max: f64,
}

fn stats(labels_path: &Path, on: Option<&Path>) -> Result<()> {
    let layer = load(labels_path)?;
    let g = layer.geometry().clone();
    let primary = match on {
        Some(p) => {
            let opened = strata_storage::readers::open_source(p, &Default::default())
                .with_context(|| format!("opening the primary {}", p.display()))?;
            ensure!(
                opened.info.geometry.dims == g.dims,
                "{}: the primary is {:?} voxels, the labels {} are {:?}: statistics need both on one grid",
                p.display(),
                opened.info.geometry.dims,
                labels_path.display(),
                g.dims
            );
            Some(opened)
        }
        None => None,
    };
    let [nx, ny, nz] = g.dims;
    let plane = nx as usize * ny as usize;
    let mut slice = vec![0u16; plane];
    let mut values = Vec::with_capacity(plane);
    let empty = Sums {
        count: 0,
        sum: 0.0,
        sum_sq: 0.0,
        min: f64::INFINITY,
        max: f64::NEG_INFINITY,
    };
    let mut sums = vec![empty; usize::from(u16::MAX) + 1];
    for k in 0..nz {
        layer
            .read_slice_k(k, &mut slice)
            .with_context(|| format!("reading slice {k} of {}", labels_path.display()))?;
        if let Some(p) = &primary {
            p.data.read_slice_f64(u64::from(k), &mut values);
            if values.len() != plane {
                bail!(
                    "the primary's slice {k} has {} voxels, not {plane}",
                    values.len()
                );
            }
        }
        for (n, &label) in slice.iter().enumerate() {
            if label == 0 {
                continue;
            }
            let s = &mut sums[usize::from(label)];
            s.count += 1;
            if let Some(p) = &primary {
                let v = values[n] * p.info.slope + p.info.intercept;
                s.sum += v;
                s.sum_sq += v * v;
                s.min = s.min.min(v);
                s.max = s.max.max(v);
            }
        }
        if let Some(p) = &primary {
            p.data.release_slice(u64::from(k));
        }
    }
    let voxel_ml = layer.grid().voxel_volume_ml();
    let mut header = "label\tname\tvoxels\tvolume_ml".to_string();
    if primary.is_some() {
        header.push_str("\tmean\tsd\tmin\tmax");
    }
    println!("{header}");
    for segment in layer.segments().iter() {
        let s = sums[usize::from(segment.value)];
        let mut line = format!(
            "{}\t{}\t{}\t{:.4}",
            segment.value,
            segment.name,
            s.count,
            s.count as f64 * voxel_ml
        );
        if primary.is_some() {
            if s.count == 0 {
                line.push_str("\t-\t-\t-\t-");
            } else {
                let n = s.count as f64;
                let mean = s.sum / n;
                let var = if s.count > 1 {
                    ((s.sum_sq - s.sum * mean) / (n - 1.0)).max(0.0)
                } else {
                    0.0
                };
                line.push_str(&format!(
                    "\t{mean:.4}\t{:.4}\t{}\t{}",
                    var.sqrt(),
                    s.min,
                    s.max
                ));
            }
        }
        println!("{line}");
    }
    Ok(())
}
