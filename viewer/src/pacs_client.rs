//! A DICOMweb server (strata-pacs) named by URL or by its name in the servers file, as the
//! command line (`strata pacs find|push`, `strata import SERVER --study UID`) and the viewer's
//! "Open from PACS…" reach it, and the series retrieved beside the store it becomes.
//!
//! Credentials come from a file or an environment variable only, never from an argument: a
//! process's arguments are visible to every user of the machine.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use strata_pacs::{Auth, Client, ClientOptions, Secret, ServersFile};

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

/// Adds where the source came from (a PACS's "retrieved from …") to a store's description
/// (the command line's import and the viewer's "Open from PACS…").
pub fn add_provenance(description: &mut String, provenance: &str) {
    // Notes in a description are joined with "; " (SourceInfo::warnings reads them so).
    *description = if description.is_empty() {
        provenance.to_string()
    } else {
        format!("{description}; {provenance}")
    };
}
