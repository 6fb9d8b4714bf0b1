//! `strata seg`: label maps from the command line (issue 52): per-segment statistics and export
//! to DICOM SEG, NIfTI, OME-Zarr `labels/` or a Strata label store.
//!
//! `stats` prints the editor's statistics (`strata_segment::stats`, the viewer's table), so the
//! panel and the command line agree: voxel count, volume in mL, bounding box in LPS mm, and with
//! `--on` the primary's mean, SD (population, as numpy's), min, max and median. `export --onto`
//! moves the labels onto a scan's grid first (nearest neighbour, and says so).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Subcommand, ValueEnum};

use strata_segment::intensity::Intensity;
use strata_segment::io::{
    load_label_file, write_dicom_seg, write_nifti, SegOptions, SourceIntensity,
};
use strata_segment::resample::resample_nearest;
use strata_segment::stats::{segment_statistics, to_csv};

#[derive(Subcommand)]
pub enum SegCommand {
    /// Per segment: voxel count, volume in mL, bounding box in LPS mm, and (with --on) the
    /// primary's mean, SD, min, max and median in its unit.
    Stats(StatsArgs),
    /// Save a label map as DICOM SEG, NIfTI, OME-Zarr labels or a Strata label store.
    Export(ExportArgs),
}

#[derive(clap::Args)]
pub struct StatsArgs {
    /// A label map: NIfTI, DICOM SEG, NRRD, MetaImage or MGH.
    labels: PathBuf,
    /// The scan the labels were drawn on (a file or a DICOM folder); on another grid, each label
    /// voxel takes the value of the scan's voxel nearest its centre (and a note says so).
    #[arg(long)]
    on: Option<PathBuf>,
    /// Print the table as CSV (the viewer's "Copy as CSV"), not as aligned text.
    #[arg(long)]
    csv: bool,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum ExportFormat {
    Seg,
    Nifti,
    OmeZarr,
    /// A Strata store of the labels (opens in the viewer and `strata serve` as any store).
    Store,
}

#[derive(clap::Args)]
pub struct ExportArgs {
    /// A label map: NIfTI, DICOM SEG, NRRD, MetaImage or MGH.
    labels: PathBuf,
    #[arg(long, value_enum)]
    format: ExportFormat,
    /// The file to write (.dcm, .nii or .nii.gz), for ome-zarr the image's .zarr folder (the
    /// labels go to OUT/labels/NAME), for store the store's folder (an existing store there is
    /// replaced once the new one is complete).
    #[arg(short, long)]
    out: PathBuf,
    /// The label image's name under labels/ (ome-zarr only).
    #[arg(long, default_value = "segmentation")]
    name: String,
    /// Move the labels onto this scan's grid first (a file or a DICOM folder; nearest
    /// neighbour), e.g. to save a SEG on the series it belongs to.
    #[arg(long)]
    onto: Option<PathBuf>,
}

pub fn run(command: SegCommand) -> Result<()> {
    match command {
        SegCommand::Stats(args) => stats(&args),
        SegCommand::Export(args) => export(&args),
    }
}

fn load(path: &Path) -> Result<strata_segment::LabelLayer> {
    load_label_file(path).with_context(|| format!("loading label map {}", path.display()))
}

fn export(args: &ExportArgs) -> Result<()> {
    let mut layer = load(&args.labels)?;
    if let Some(onto) = &args.onto {
        let scan = strata_storage::readers::open_source(onto, &Default::default())
            .with_context(|| format!("opening {}", onto.display()))?;
        let (moved, report) = resample_nearest(&layer, scan.info.geometry.clone())
            .with_context(|| format!("moving {} onto {}", args.labels.display(), onto.display()))?;
        if moved.grid() != layer.grid() {
            eprintln!(
                "note: resampled {} ({:?} voxels) onto the grid of {} ({:?} voxels), nearest neighbour: {} labelled voxels",
                args.labels.display(),
                report.from_dims,
                onto.display(),
                report.to_dims,
                report.labelled_voxels
            );
        }
        layer = moved;
    }
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
        ExportFormat::Store => {
            strata_segment::io::write_label_store(&layer, &args.out)
                .with_context(|| format!("writing the label store {}", args.out.display()))?;
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

fn stats(args: &StatsArgs) -> Result<()> {
    let layer = load(&args.labels)?;
    let primary = match &args.on {
        Some(p) => {
            let opened = strata_storage::readers::open_source(p, &Default::default())
                .with_context(|| format!("opening the primary {}", p.display()))?;
            let intensity = SourceIntensity::new(opened, layer.grid())
                .with_context(|| format!("sampling the primary {}", p.display()))?;
            if intensity.resampled() {
                let own = &intensity.info().geometry;
                eprintln!(
                    "note: the primary {} ({:?} voxels of {:?} mm) is on another grid than the labels {} ({:?} voxels of {:?} mm): each label voxel takes the value of the primary's voxel nearest its centre (none outside the primary)",
                    p.display(),
                    own.dims,
                    own.spacing_mm,
                    args.labels.display(),
                    layer.grid().dims(),
                    layer.grid().geometry().spacing_mm,
                );
            }
            Some(intensity)
        }
        None => None,
    };
    let stats = segment_statistics(
        &layer,
        primary.as_ref().map(|p| p as &dyn Intensity),
        None,
        &mut |_, _| {},
    )
    .with_context(|| format!("statistics of {}", args.labels.display()))?;
    if args.csv {
        print!("{}", to_csv(&stats));
        return Ok(());
    }
    let unit = if stats.unit.is_empty() {
        String::new()
    } else {
        format!(" ({})", stats.unit)
    };
    let mut header = "label\tname\tvoxels\tvolume_ml".to_string();
    if primary.is_some() {
        header.push_str(&format!(
            "\tmean{unit}\tsd{unit}\tmin{unit}\tmax{unit}\tmedian{unit}"
        ));
    }
    header.push_str("\tbox_lps_mm");
    println!("{header}");
    let number = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{v:.4}"));
    for s in &stats.segments {
        let mut line = format!("{}\t{}\t{}\t{:.4}", s.label, s.name, s.voxels, s.volume_ml);
        if primary.is_some() {
            for v in [s.mean, s.sd, s.min, s.max, s.median] {
                line.push('\t');
                line.push_str(&number(v));
            }
        }
        line.push('\t');
        line.push_str(&match s.lps_box_mm {
            Some((lo, hi)) => format!(
                "[{:.2}, {:.2}, {:.2}]..[{:.2}, {:.2}, {:.2}]",
                lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
            ),
            None => "-".into(),
        });
        println!("{line}");
    }
    Ok(())
}
