//! `strata pacs find|push` and the PACS half of `strata import SERVER --study UID`: a DICOMweb
//! server (strata-pacs) named by URL or by its name in the servers file, reached through
//! strata-viewer's `pacs_client` (the viewer's "Open from PACS…" connects the same way).
//!
//! Credentials come from a file or an environment variable only, never from an argument: a
//! process's arguments are visible to every user of the machine.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::{Args, Subcommand};
use strata_pacs::StudyQuery;
pub use strata_viewer::pacs_client::{connect, retrieve_series_beside, Retrieved, ServerArgs};

#[derive(Subcommand)]
pub enum PacsCommand {
    /// Search a DICOMweb server's studies (QIDO-RS); with --study, list that study's series.
    Find(FindArgs),
    /// Store DICOM files (a file, or every DICOM file under a folder) on a server (STOW-RS).
    Push(PushArgs),
}

#[derive(Args)]
pub struct FindArgs {
    /// A DICOMweb base URL (http(s)://HOST/dicom-web) or a server's name in the servers file.
    pub server: String,
    /// Patient name, DICOM wildcards allowed ('DOE^J*').
    #[arg(long)]
    pub patient_name: Option<String>,
    #[arg(long)]
    pub patient_id: Option<String>,
    /// YYYYMMDD or a range YYYYMMDD-YYYYMMDD (either end may be left out).
    #[arg(long)]
    pub study_date: Option<String>,
    /// Studies holding a series of this modality (CT, MR, ...).
    #[arg(long)]
    pub modality: Option<String>,
    #[arg(long)]
    pub accession: Option<String>,
    /// List this study's series instead.
    #[arg(long)]
    pub study: Option<String>,
    /// Studies listed at most.
    #[arg(long, default_value_t = 200)]
    pub limit: u32,
    #[command(flatten)]
    pub connection: ServerArgs,
}

#[derive(Args)]
pub struct PushArgs {
    /// A DICOMweb base URL or a server's name in the servers file.
    pub server: String,
    /// A DICOM file or a folder of them.
    pub input: PathBuf,
    #[command(flatten)]
    pub connection: ServerArgs,
}

pub fn run(command: PacsCommand) -> Result<()> {
    match command {
        PacsCommand::Find(args) => find(args),
        PacsCommand::Push(args) => push(args),
    }
}

fn find(args: FindArgs) -> Result<()> {
    let client = connect(&args.server, &args.connection)?;
    if let Some(study) = &args.study {
        let series = client.series_of(study)?;
        println!(
            "{:<64}  {:<4}  {:>9}  description",
            "series", "mod", "instances"
        );
        for s in &series {
            println!(
                "{:<64}  {:<4}  {:>9}  {}",
                s.series_uid,
                s.modality,
                s.instance_count.map_or("?".to_string(), |n| n.to_string()),
                s.description
            );
        }
        eprintln!("{} series", series.len());
        return Ok(());
    }
    let query = StudyQuery {
        patient_name: args.patient_name,
        patient_id: args.patient_id,
        study_date: args.study_date,
        modality: args.modality,
        accession: args.accession,
        study_uid: None,
        limit: Some(args.limit),
    };
    let studies = client.find_studies(&query)?;
    println!(
        "{:<64}  {:<8}  {:<24}  {:<16}  {:<8}  {:>6}  description",
        "study", "date", "patient", "patient id", "modality", "series"
    );
    for s in &studies {
        println!(
            "{:<64}  {:<8}  {:<24}  {:<16}  {:<8}  {:>6}  {}",
            s.study_uid,
            s.study_date,
            s.patient_name,
            s.patient_id,
            s.modalities.join("\\"),
            s.series_count.map_or("?".to_string(), |n| n.to_string()),
            s.description
        );
    }
    eprintln!("{} studies", studies.len());
    Ok(())
}

fn push(args: PushArgs) -> Result<()> {
    let client = connect(&args.server, &args.connection)?;
    let (files, skipped) = strata_pacs::dicom_files(&args.input)?;
    if files.is_empty() {
        bail!(
            "{}: no DICOM files (Part 10, with the DICM preamble)",
            args.input.display()
        );
    }
    if skipped > 0 {
        eprintln!("skipping {skipped} file(s) that are not DICOM");
    }
    let bar = crate::progress::count_bar(files.len() as u64, "storing");
    let on_progress = |sent: usize| bar.set_position(sent as u64);
    let report = client.store_files(&files, Some(&on_progress))?;
    bar.finish_and_clear();
    println!(
        "stored {} of {} instance(s) on {} ({} request(s))",
        report.stored,
        report.sent,
        client.base_url(),
        report.requests
    );
    if report.failed > 0 {
        bail!(
            "{}: the server refused {} of {} instance(s)",
            client.base_url(),
            report.failed,
            report.sent
        );
    }
    Ok(())
}

/// Retrieves the series to import into `STORE.retrieving-SERIESUID` beside `store`, fetching
/// only the instances not there yet.
pub fn retrieve_for_import(
    server: &str,
    study: &str,
    series: Option<&str>,
    args: &ServerArgs,
    store: &Path,
) -> Result<Retrieved> {
    let client = connect(server, args)?;
    let series_uid = match series {
        Some(s) => s.to_string(),
        None => {
            let all = client.series_of(study)?;
            match all.as_slice() {
                [one] => one.series_uid.clone(),
                [] => bail!("{}: study {study} has no series", client.base_url()),
                many => bail!(
                    "{}: study {study} has {} series; choose one with --series:\n{}",
                    client.base_url(),
                    many.len(),
                    many.iter()
                        .map(|s| format!(
                            "  {}  {}  {} instance(s)  {}",
                            s.series_uid,
                            s.modality,
                            s.instance_count.map_or("?".into(), |n| n.to_string()),
                            s.description
                        ))
                        .collect::<Vec<_>>()
                        .join("\n")
                ),
            }
        }
    };
    let bar = crate::progress::count_bar(0, "retrieving");
    let on_progress = |p: strata_pacs::RetrieveProgress| {
        bar.set_length(p.total as u64);
        bar.set_position(p.done as u64);
    };
    // The retrieve's own time (QIDO lists and WADO-RS transfers), so that a slow import can be
    // told apart from a slow network or server (bench/pacs/run.sh reads this line).
    let started = std::time::Instant::now();
    let (retrieved, report) =
        retrieve_series_beside(&client, study, &series_uid, store, None, Some(&on_progress))?;
    let retrieve_seconds = started.elapsed().as_secs_f64();
    bar.finish_and_clear();
    if report.already_present > 0 {
        eprintln!(
            "resumed: {} instance(s) already in {}",
            report.already_present,
            retrieved.folder.display()
        );
    }
    eprintln!(
        "retrieved {} instance(s), {:.1} MB, from {} in {} request(s), {:.2} s ({:.0} MB/s)",
        report.fetched,
        report.bytes as f64 / 1e6,
        client.base_url(),
        report.requests,
        retrieve_seconds,
        report.bytes as f64 / 1e6 / retrieve_seconds.max(1e-9)
    );
    if let Some(n) = report.count_mismatch {
        eprintln!(
            "warning: the server counts {n} instance(s) in the series but lists {}",
            report.instances
        );
    }
    Ok(retrieved)
}
