//! `strata pacs find|push` and the PACS half of `strata import SERVER --study UID`: a DICOMweb
//! server (strata-pacs) named by URL or by its name in the servers file.
//!
//! Credentials come from a file or an environment variable only, never from an argument: a
//! process's arguments are visible to every user of the machine.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use strata_pacs::{Auth, Client, ClientOptions, Secret, ServersFile, StudyQuery};

/// How to reach a DICOMweb server (shared by `pacs find|push` and `import --study`).
#[derive(Args, Clone, Debug)]
pub struct ServerArgs {
    /// Basic authentication: the user name (its password from --password-file or --password-env).
    #[arg(long)]
    pub user: Option<String>,
    /// Basic authentication: a file whose first line is the password.
    #[arg(long)]
    pub password_file: Option<PathBuf>,
    /// Basic authentication: the environment variable holding the password.
    #[arg(long)]
    pub password_env: Option<String>,
    /// Bearer authentication: a file whose first line is the token.
    #[arg(long)]
    pub bearer_token_file: Option<PathBuf>,
    /// Bearer authentication: the environment variable holding the token.
    #[arg(long)]
    pub bearer_token_env: Option<String>,
    /// A PEM certificate to trust besides the system's (a hospital's own CA).
    #[arg(long)]
    pub ca_file: Option<PathBuf>,
    /// The servers file naming servers (default: $STRATA_PACS_SERVERS, else
    /// ~/.config/strata/pacs-servers.json).
    #[arg(long)]
    pub servers_file: Option<PathBuf>,
    /// Retrieve requests in flight at most.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub parallel: u16,
    /// Largest instance accepted, in MiB.
    #[arg(long, default_value_t = 2048)]
    pub max_instance_mib: u64,
}

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

impl ServerArgs {
    /// No credentials or CA besides the servers file's entry, the default limits: how the
    /// viewer connects (credentials only ever come from the servers file there).
    pub fn from_servers_file(servers_file: Option<PathBuf>) -> ServerArgs {
        ServerArgs {
            user: None,
            password_file: None,
            password_env: None,
            bearer_token_file: None,
            bearer_token_env: None,
            ca_file: None,
            servers_file,
            parallel: 4,
            max_instance_mib: 2048,
        }
    }
}

pub fn run(command: PacsCommand) -> Result<()> {
    match command {
        PacsCommand::Find(args) => find(args),
        PacsCommand::Push(args) => push(args),
    }
}

/// The servers file `connect` reads names from when none is given: `$STRATA_PACS_SERVERS`, else
/// `~/.config/strata/pacs-servers.json` (the viewer's "Open from PACS…" lists the same).
pub fn default_servers_file() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("STRATA_PACS_SERVERS") {
        return Some(PathBuf::from(p));
    }
    let config = std::env::var_os("XDG_CONFIG_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".config")))?;
    Some(config.join("strata").join("pacs-servers.json"))
}

/// The server `name_or_url` names, with the credentials the arguments or its entry give.
pub fn connect(name_or_url: &str, args: &ServerArgs) -> Result<Client> {
    // Retries and count mismatches are reported through tracing: show warnings (RUST_LOG
    // for more).
    let _ = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .try_init();
    let mut url = name_or_url.to_string();
    let mut auth = Auth::None;
    let mut ca_file = args.ca_file.clone();
    if !(name_or_url.starts_with("http://") || name_or_url.starts_with("https://")) {
        let file = args
            .servers_file
            .clone()
            .or_else(default_servers_file)
            .context("no servers file to look the server name up in (give a URL)")?;
        let servers = ServersFile::read(&file)?;
        let entry = servers.find(name_or_url).with_context(|| {
            format!(
                "'{name_or_url}' is neither an http(s):// URL nor a server named in {}",
                file.display()
            )
        })?;
        url = entry.url.clone();
        auth = entry.auth.resolve()?;
        ca_file = ca_file.or(entry.ca_file.clone());
    }
    // Arguments override the servers file's entry.
    match (
        &args.user,
        &args.password_file,
        &args.password_env,
        &args.bearer_token_file,
        &args.bearer_token_env,
    ) {
        (None, None, None, None, None) => {}
        (Some(user), file, env, None, None) => {
            let password = match (file, env) {
                (Some(f), None) => Secret::from_file(f)?,
                (None, Some(v)) => Secret::from_env(v)?,
                _ => bail!("--user needs exactly one of --password-file or --password-env"),
            };
            auth = Auth::Basic {
                user: user.clone(),
                password,
            };
        }
        (None, None, None, Some(f), None) => auth = Auth::Bearer(Secret::from_file(f)?),
        (None, None, None, None, Some(v)) => auth = Auth::Bearer(Secret::from_env(v)?),
        _ => bail!(
            "give either --user with --password-file or --password-env, or one of \
             --bearer-token-file or --bearer-token-env"
        ),
    }
    let ca_pem = match &ca_file {
        Some(f) => Some(std::fs::read(f).with_context(|| format!("cannot read {}", f.display()))?),
        None => None,
    };
    let options = ClientOptions {
        parallelism: usize::from(args.parallel),
        max_part_bytes: args.max_instance_mib.saturating_mul(1 << 20),
        ..ClientOptions::default()
    };
    Ok(Client::new(&url, auth, ca_pem.as_deref(), options)?)
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

/// A series retrieved for `strata import SERVER --study UID [--series UID]`: its folder (beside
/// the store, kept after a failure so that the next try resumes) and the provenance line for
/// the store's description.
pub struct Retrieved {
    pub folder: PathBuf,
    pub provenance: String,
}

impl Retrieved {
    /// Removes the folder once its instances are imported (a failure only warns: the store is
    /// complete).
    pub fn remove(self) {
        if let Err(e) = std::fs::remove_dir_all(&self.folder) {
            eprintln!(
                "warning: cannot remove the retrieved instances in {}: {e}",
                self.folder.display()
            );
        }
    }
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
    let (retrieved, report) =
        retrieve_series_beside(&client, study, &series_uid, store, None, Some(&on_progress))?;
    bar.finish_and_clear();
    if report.already_present > 0 {
        eprintln!(
            "resumed: {} instance(s) already in {}",
            report.already_present,
            retrieved.folder.display()
        );
    }
    eprintln!(
        "retrieved {} instance(s), {:.1} MB, from {} in {} request(s)",
        report.fetched,
        report.bytes as f64 / 1e6,
        client.base_url(),
        report.requests
    );
    if let Some(n) = report.count_mismatch {
        eprintln!(
            "warning: the server counts {n} instance(s) in the series but lists {}",
            report.instances
        );
    }
    Ok(retrieved)
}

/// Retrieves `series_uid` into `STORE.retrieving-SERIESUID` beside `store`, fetching only the
/// instances not there yet (the command line's import and the viewer's "Open from PACS…").
/// `cancel` stops it between instances; what was fetched stays for the next try.
pub fn retrieve_series_beside(
    client: &Client,
    study: &str,
    series_uid: &str,
    store: &Path,
    cancel: Option<&std::sync::atomic::AtomicBool>,
    progress: Option<&dyn Fn(strata_pacs::RetrieveProgress)>,
) -> Result<(Retrieved, strata_pacs::RetrieveReport)> {
    strata_pacs::check_uid(series_uid)
        .map_err(|e| anyhow::anyhow!("{}: series: {e}", client.base_url()))?;
    let name = store
        .file_name()
        .with_context(|| format!("{}: not a store path", store.display()))?;
    let mut folder_name = name.to_os_string();
    folder_name.push(format!(".retrieving-{series_uid}"));
    let folder = store.with_file_name(folder_name);
    let report = client
        .retrieve_series(study, series_uid, &folder, cancel, progress)
        .with_context(|| {
            format!(
                "the instances retrieved so far stay in {} (retrieving the series again resumes)",
                folder.display()
            )
        })?;
    let retrieved = Retrieved {
        folder,
        provenance: format!(
            "retrieved from {} (DICOMweb), study {study}, series {series_uid}",
            client.base_url()
        ),
    };
    Ok((retrieved, report))
}
