//! Work that gets a store ready for viewing, each on its own named thread with progress and a
//! cancel flag: generating the demo phantom, importing a scan into the user's data folder, and
//! opening a store (sled recovery can take a moment on a large one).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use anyhow::Context;
use strata_storage::import::{import_source, ImportOptions, ImportProgress};
use strata_storage::phantom::Phantom;
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::Store;

use super::sync::{lock_ignoring_poison, Repaint};

/// What the user asked to look at.
#[derive(Clone, Debug, PartialEq)]
pub enum VolumeToOpen {
    /// The demo phantom of this edge length, generated at `path` on first use.
    Demo { path: PathBuf, size: u64 },
    /// A store, or anything the importer reads (imported into the data folder first).
    Path(PathBuf),
    /// A store served by `strata serve` (`http(s)://HOST:PORT/v1/stores/NAME`), streamed.
    Url {
        url: String,
        token_file: Option<PathBuf>,
        /// A bearer token from a viewer link's `#token=` (links.rs): kept in memory only,
        /// and used instead of `token_file`.
        token: Option<String>,
    },
    /// A series on a DICOMweb server ("Open from PACS…", pacs_dialog.rs): retrieved and
    /// imported into the data folder, or the earlier import of it opened at once.
    Pacs(PacsSeries),
}

/// A series to retrieve from a PACS. No credentials: they come from the servers file's entry
/// when the job connects, and are never shown.
#[derive(Clone, Debug, PartialEq)]
pub struct PacsSeries {
    /// A server's name in the servers file, or a DICOMweb base URL.
    pub server: String,
    /// The servers file names are looked up in (None: the command line's default).
    pub servers_file: Option<PathBuf>,
    pub study_uid: String,
    pub series_uid: String,
    /// What the job's title calls the series ("CT chest, 12 instances").
    pub label: String,
}

/// Where a PACS series' store goes: keyed by the server's base URL and the series UID, so the
/// same series from the same server opens its earlier import at once.
pub fn store_path_for_pacs_series(base_url: &str, series_uid: &str, folder: &Path) -> PathBuf {
    let key = xxhash_of(format!("{base_url}|{series_uid}").as_bytes());
    folder.join(format!("pacs-{key:016x}.strata"))
}

/// The prepared store, or why it could not be prepared (with its chain of causes, which
/// `error_report::describe` words for the user); None while the job runs.
type PrepareOutcome = Arc<Mutex<Option<anyhow::Result<Arc<dyn strata_source::VolumeSource>>>>>;

pub struct PrepareJob {
    pub title: String,
    done: Arc<AtomicU64>,
    total: Arc<AtomicU64>,
    stage: Arc<Mutex<String>>,
    cancel: Arc<AtomicBool>,
    result: PrepareOutcome,
}

pub fn is_store(path: &Path) -> bool {
    path.join("STRATA-STORE").is_file()
}

/// Folder for stores imported by the viewer: `$XDG_DATA_HOME/strata/stores`, or
/// `~/.local/share/strata/stores`, or `./strata-stores` without a home.
pub fn data_folder() -> PathBuf {
    if let Some(d) = std::env::var_os("XDG_DATA_HOME").filter(|d| !d.is_empty()) {
        return PathBuf::from(d).join("strata").join("stores");
    }
    if let Some(h) = std::env::var_os("HOME").filter(|h| !h.is_empty()) {
        return PathBuf::from(h)
            .join(".local")
            .join("share")
            .join("strata")
            .join("stores");
    }
    PathBuf::from("strata-stores")
}

/// Where a scan's store goes: named after the input, keyed by its full path, size and
/// modification time so a changed file is imported again and an unchanged one is reused.
pub fn store_path_for_input(input: &Path, folder: &Path) -> PathBuf {
    let absolute = std::fs::canonicalize(input).unwrap_or_else(|_| input.to_path_buf());
    let meta = std::fs::metadata(&absolute).ok();
    let stamp = meta
        .as_ref()
        .map(|m| {
            (
                m.len(),
                m.modified()
                    .ok()
                    .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                    .map_or(0, |d| d.as_secs()),
            )
        })
        .unwrap_or((0, 0));
    let key = xxhash_of(format!("{}|{}|{}", absolute.display(), stamp.0, stamp.1).as_bytes());
    let name = absolute
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scan".into());
    let stem: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect();
    folder.join(format!("{stem}-{key:016x}.strata"))
}

/// FNV-1a: a stable name key, not a checksum.
fn xxhash_of(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    })
}

impl PrepareJob {
    /// Scans are imported into `import_folder` (normally [`data_folder`]).
    pub fn start(
        source: VolumeToOpen,
        dicom_series: Option<String>,
        import_folder: PathBuf,
        repaint: Repaint,
    ) -> anyhow::Result<PrepareJob> {
        let title = match &source {
            VolumeToOpen::Demo { size, .. } => format!("Preparing the {size}³ demo phantom"),
            VolumeToOpen::Path(p) => format!("Opening {}", p.display()),
            VolumeToOpen::Url { url, .. } => format!("Opening {url}"),
            VolumeToOpen::Pacs(p) => format!(
                "Opening {} from {}",
                p.label,
                strata_pacs::redact_url(&p.server)
            ),
        };
        let job = PrepareJob {
            title,
            done: Arc::new(AtomicU64::new(0)),
            total: Arc::new(AtomicU64::new(0)),
            stage: Arc::new(Mutex::new("starting".into())),
            cancel: Arc::new(AtomicBool::new(false)),
            result: Arc::new(Mutex::new(None)),
        };
        let (done, total, stage, cancel, result) = (
            job.done.clone(),
            job.total.clone(),
            job.stage.clone(),
            job.cancel.clone(),
            job.result.clone(),
        );
        std::thread::Builder::new()
            .name("strata-prepare".into())
            .spawn(move || {
                let progress = |p: ImportProgress| {
                    done.store(p.source_bytes_done, Ordering::Relaxed);
                    total.store(p.source_bytes_total, Ordering::Relaxed);
                    repaint();
                };
                let set_stage = |s: String| {
                    *lock_ignoring_poison(&stage) = s;
                    repaint();
                };
                let outcome = prepare(
                    &source,
                    dicom_series,
                    &import_folder,
                    &progress,
                    &set_stage,
                    &cancel,
                );
                *lock_ignoring_poison(&result) = Some(outcome);
                repaint();
            })?;
        Ok(job)
    }

    /// (done, total) source bytes, and what is happening.
    pub fn progress(&self) -> (u64, u64, String) {
        (
            self.done.load(Ordering::Relaxed),
            self.total.load(Ordering::Relaxed),
            lock_ignoring_poison(&self.stage).clone(),
        )
    }

    pub fn cancel(&self) {
        self.cancel.store(true, Ordering::Release);
    }

    pub fn take_result(&self) -> Option<anyhow::Result<Arc<dyn strata_source::VolumeSource>>> {
        lock_ignoring_poison(&self.result).take()
    }
}

/// Opens what the user asked for as a volume source: a URL or a store through
/// `volume_location` (which streams from `strata serve` when the server holds the store), a
/// scan after importing it.
fn prepare(
    source: &VolumeToOpen,
    dicom_series: Option<String>,
    import_folder: &Path,
    progress: &(dyn Fn(ImportProgress) + Sync),
    set_stage: &dyn Fn(String),
    cancel: &AtomicBool,
) -> anyhow::Result<Arc<dyn strata_source::VolumeSource>> {
    let cache = strata_storage::store::DEFAULT_READ_CACHE_BYTES;
    match source {
        VolumeToOpen::Url {
            url,
            token: Some(token),
            ..
        } => {
            set_stage(format!("connecting to {url}"));
            let remote: Arc<dyn strata_source::VolumeSource> =
                crate::volume_location::open_remote_with_token(url, Some(token.clone()))?;
            Ok(remote)
        }
        VolumeToOpen::Url {
            url, token_file, ..
        } => {
            set_stage(format!("connecting to {url}"));
            crate::volume_location::open_source(url, token_file.as_deref(), cache)
        }
        VolumeToOpen::Path(p) if crate::volume_location::is_url(&p.to_string_lossy()) => {
            set_stage(format!("connecting to {}", p.display()));
            crate::volume_location::open_source(&p.to_string_lossy(), None, cache)
        }
        VolumeToOpen::Path(p) if is_store(p) => {
            set_stage(format!("opening store {}", p.display()));
            crate::volume_location::open_source(&p.to_string_lossy(), None, cache)
        }
        VolumeToOpen::Pacs(series) => {
            let store = prepare_pacs_store(series, import_folder, progress, set_stage, cancel)?;
            Ok(Arc::new(store))
        }
        _ => {
            let store = prepare_store(
                source,
                dicom_series,
                import_folder,
                progress,
                set_stage,
                cancel,
            )?;
            Ok(Arc::new(store))
        }
    }
}

fn prepare_store(
    source: &VolumeToOpen,
    dicom_series: Option<String>,
    import_folder: &Path,
    progress: &(dyn Fn(ImportProgress) + Sync),
    set_stage: &dyn Fn(String),
    cancel: &AtomicBool,
) -> anyhow::Result<Store> {
    let options = ImportOptions {
        progress: Some(progress),
        cancel: Some(cancel),
        ..Default::default()
    };
    match source {
        VolumeToOpen::Demo { path, size } => {
            if let Ok(store) = Store::open(path) {
                return Ok(store);
            }
            set_stage(format!(
                "generating the demo phantom into {} (first run only)",
                path.display()
            ));
            if let Some(parent) = path.parent() {
                std::fs::create_dir_all(parent)
                    .with_context(|| format!("creating {}", parent.display()))?;
            }
            Phantom::cube(*size)
                .write_store(path, &options)
                .with_context(|| format!("writing {}", path.display()))?;
            set_stage("opening".into());
            Ok(Store::open(path)?)
        }
        VolumeToOpen::Path(input) => {
            if is_store(input) {
                set_stage(format!("opening store {}", input.display()));
                return Store::open(input)
                    .with_context(|| format!("cannot open store {}", input.display()));
            }
            if !input.exists() {
                anyhow::bail!("{} does not exist", input.display());
            }
            let store_path = store_path_for_input(input, import_folder);
            if let Ok(store) = Store::open(&store_path) {
                set_stage(format!(
                    "opening the earlier import {}",
                    store_path.display()
                ));
                return Ok(store);
            }
            set_stage(format!("reading {}", input.display()));
            let read_options = ReadOptions {
                dicom_series,
                ..Default::default()
            };
            let opened = open_source(input, &read_options)
                .with_context(|| format!("cannot read {}", input.display()))?;
            if let Some(parent) = store_path.parent() {
                std::fs::create_dir_all(parent)
                    .with_context(|| format!("creating {}", parent.display()))?;
            }
            set_stage(format!(
                "importing {} into {}",
                input.display(),
                store_path.display()
            ));
            import_source(opened, &store_path, &options).with_context(|| {
                format!(
                    "import of {} into {} failed",
                    input.display(),
                    store_path.display()
                )
            })?;
            set_stage("opening".into());
            Ok(Store::open(&store_path)?)
        }
        VolumeToOpen::Url { url, .. } => {
            anyhow::bail!("{url} is a served store: it is streamed, not imported")
        }
        VolumeToOpen::Pacs(series) => {
            prepare_pacs_store(series, import_folder, progress, set_stage, cancel)
        }
    }
}

/// A PACS series as a store: its earlier import from the same server, or retrieved beside the
/// store (`STORE.retrieving-SERIES`, as `strata import SERVER --study`: a cancelled or failed
/// retrieval resumes next time), imported with the store's provenance, the instances removed.
/// Errors name the server (never its credentials).
fn prepare_pacs_store(
    series: &PacsSeries,
    import_folder: &Path,
    progress: &(dyn Fn(ImportProgress) + Sync),
    set_stage: &dyn Fn(String),
    cancel: &AtomicBool,
) -> anyhow::Result<Store> {
    let shown = strata_pacs::redact_url(&series.server);
    let args = crate::pacs_client::ServerArgs::from_servers_file(series.servers_file.clone());
    let client = crate::pacs_client::connect(&series.server, &args)
        .with_context(|| format!("cannot reach the PACS {shown}"))?;
    let store_path =
        store_path_for_pacs_series(client.base_url(), &series.series_uid, import_folder);
    if let Ok(store) = Store::open(&store_path) {
        set_stage(format!(
            "opening the earlier import {}",
            store_path.display()
        ));
        return Ok(store);
    }
    std::fs::create_dir_all(import_folder)
        .with_context(|| format!("creating {}", import_folder.display()))?;
    set_stage(format!("retrieving from {}", client.base_url()));
    let on_retrieved = |p: strata_pacs::RetrieveProgress| {
        progress(ImportProgress {
            source_bytes_done: p.done as u64,
            source_bytes_total: p.total as u64,
        });
        set_stage(format!(
            "retrieving {} of {} instance(s) from {}",
            p.done,
            p.total,
            client.base_url()
        ));
    };
    let (retrieved, report) = crate::pacs_client::retrieve_series_beside(
        &client,
        &series.study_uid,
        &series.series_uid,
        &store_path,
        Some(cancel),
        Some(&on_retrieved),
    )?;
    if cancel.load(Ordering::Acquire) {
        anyhow::bail!(
            "cancelled: the {} instance(s) retrieved so far stay for the next open",
            report.fetched + report.already_present
        );
    }
    set_stage(format!("reading {}", retrieved.folder.display()));
    // The folder holds this series only: read as a folder import would.
    let mut opened =
        open_source(&retrieved.folder, &ReadOptions::default()).with_context(|| {
            format!(
                "cannot read the series retrieved from {}",
                client.base_url()
            )
        })?;
    crate::pacs_client::add_provenance(&mut opened.info.description, &retrieved.provenance);
    set_stage(format!("importing into {}", store_path.display()));
    let options = ImportOptions {
        progress: Some(progress),
        cancel: Some(cancel),
        ..Default::default()
    };
    import_source(opened, &store_path, &options).with_context(|| {
        format!(
            "import of the series from {} into {} failed",
            client.base_url(),
            store_path.display()
        )
    })?;
    retrieved.remove();
    set_stage("opening".into());
    Ok(Store::open(&store_path)?)
}

#[cfg(test)]
mod remote_tests {
    use super::*;
    use std::time::{Duration, Instant};

    fn wait_for(job: &PrepareJob) -> anyhow::Result<Arc<dyn strata_source::VolumeSource>> {
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            if let Some(r) = job.take_result() {
                return r;
            }
            assert!(Instant::now() < deadline, "the prepare job did not finish");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// `strata view URL` and `strata view STORE` while `strata serve` holds it: both stream
    /// from the server (the viewer's status then says "connection lost, retrying" on outages,
    /// see `SessionStatus::source_line`).
    #[test]
    fn the_viewer_opens_a_served_store_by_url_and_by_its_path() {
        // Format 3 admits many readers: its path opens here beside the server. Format 2 (sled,
        // one process at a time) is held by the server: its path streams from the server.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("served.strata");
        Phantom::cube(40)
            .write_store(&path, &ImportOptions::default())
            .unwrap();
        let sled_path = dir.path().join("served-v2.strata");
        Phantom::cube(40)
            .write_store_as_format(&sled_path, &ImportOptions::default(), 2)
            .unwrap();
        let name = strata_service::server::name_for_store(&path);
        let sled_name = strata_service::server::name_for_store(&sled_path);
        let server = strata_service::server::start(
            vec![
                (name.clone(), path.clone()),
                (sled_name.clone(), sled_path.clone()),
            ],
            strata_service::server::ServeOptions::default(),
        )
        .unwrap();
        let url = server.store_url(&name);
        let sled_url = server.store_url(&sled_name);
        let repaint: Repaint = Arc::new(|| {});
        for (source, expected) in [
            (
                VolumeToOpen::Url {
                    url: url.clone(),
                    token_file: None,
                    token: None,
                },
                url.clone(),
            ),
            (VolumeToOpen::Path(path.clone()), path.display().to_string()),
            (VolumeToOpen::Path(sled_path.clone()), sled_url.clone()),
        ] {
            let job = PrepareJob::start(source.clone(), None, dir.path().into(), repaint.clone())
                .unwrap();
            let opened = wait_for(&job).unwrap_or_else(|e| panic!("{source:?}: {e:#}"));
            assert_eq!(opened.header().geometry.dims, [40, 40, 40]);
            assert_eq!(opened.location(), expected, "{source:?}");
        }
        server.stop();
    }
}

#[cfg(test)]
mod pacs_tests {
    use std::sync::atomic::AtomicUsize;

    use super::super::orthanc_fixture::{filled_orthanc, CT_SERIES, CT_SLICES, CT_STUDY};
    use super::*;

    /// Cancel half-way through "Open from PACS": an error saying so, no store; the next open
    /// fetches only what is missing (its first progress counts the instances already there)
    /// and opens the series.
    #[test]
    fn a_cancelled_pacs_open_leaves_no_store_and_the_next_open_resumes() {
        let work = tempfile::tempdir().unwrap();
        let orthanc = filled_orthanc(work.path());
        let series = PacsSeries {
            server: orthanc.url.clone(),
            servers_file: Some(work.path().join("no-servers.json")),
            study_uid: CT_STUDY.into(),
            series_uid: CT_SERIES.into(),
            label: "CT".into(),
        };
        let stores = work.path().join("stores");
        let cancel = AtomicBool::new(false);
        // Cancelled once 3 instances are in (the retrieval reports instances as progress).
        let progress = |p: ImportProgress| {
            if p.source_bytes_total == CT_SLICES as u64 && p.source_bytes_done >= 3 {
                cancel.store(true, Ordering::Release);
            }
        };
        let e = prepare_pacs_store(&series, &stores, &progress, &|_| {}, &cancel)
            .err()
            .expect("a cancelled open fails");
        let e = format!("{e:#}");
        assert!(e.contains("cancel"), "{e}");
        let base = strata_pacs::normalise_base_url(&orthanc.url).unwrap();
        let store = store_path_for_pacs_series(&base, CT_SERIES, &stores);
        assert!(
            Store::open(&store).is_err(),
            "a cancelled open left a store"
        );

        let first_done = AtomicUsize::new(usize::MAX);
        let progress = |p: ImportProgress| {
            if p.source_bytes_total == CT_SLICES as u64 {
                let _ = first_done.compare_exchange(
                    usize::MAX,
                    p.source_bytes_done as usize,
                    Ordering::AcqRel,
                    Ordering::Acquire,
                );
            }
        };
        let opened = prepare_pacs_store(
            &series,
            &stores,
            &progress,
            &|_| {},
            &AtomicBool::new(false),
        )
        .unwrap_or_else(|e| panic!("{e:#}"));
        assert_eq!(opened.header().geometry.dims[2], CT_SLICES as u32);
        let resumed = first_done.load(Ordering::Acquire);
        assert!((3..CT_SLICES).contains(&resumed), "resumed from {resumed}");
    }
}
