//! "Open from PACS…": pick a DICOMweb server (a name from the servers file the command line
//! uses, or a typed URL), search its studies, list a study's series and open one. Opening is a
//! [`PrepareJob`] (jobs.rs, `VolumeToOpen::Pacs`): retrieved and imported on its named thread
//! with progress and Cancel, or the earlier import of the same series from the same server
//! opened at once.
//!
//! [`PacsModel`] holds the platform-independent state (server, search form, results,
//! selection) and runs the searches on named threads; [`PacsDialog`] only draws it. Errors name
//! the server as its redacted URL or its name: credentials come from the servers file only and
//! are never shown.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use egui::{Color32, RichText};
use strata_pacs::{Series, ServersFile, Study, StudyQuery};

use super::jobs::{PacsSeries, PrepareJob, VolumeToOpen};
use super::pacs_thumbnail::Thumbnail;
use super::sync::{lock_ignoring_poison, Repaint};

/// The study search form, as typed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SearchForm {
    /// DICOM wildcards allowed ('DOE^J*').
    pub patient_name: String,
    pub patient_id: String,
    /// YYYYMMDD; either end may be left empty.
    pub date_from: String,
    pub date_to: String,
    pub modality: String,
    pub accession: String,
}

fn field(text: &str) -> Option<String> {
    Some(text.trim().to_string()).filter(|t| !t.is_empty())
}

/// A search form's date that is not DICOM's YYYYMMDD; `which` is "from" or "to".
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("the {which} date must be YYYYMMDD, not '{text}'")]
pub struct BadDate {
    which: &'static str,
    text: String,
}

fn check_date(which: &'static str, text: &str) -> Result<(), BadDate> {
    if text.is_empty() || (text.len() == 8 && text.bytes().all(|b| b.is_ascii_digit())) {
        Ok(())
    } else {
        Err(BadDate {
            which,
            text: text.to_string(),
        })
    }
}

impl SearchForm {
    /// The QIDO query the form asks for, or what is wrong with it.
    pub fn query(&self) -> Result<StudyQuery, BadDate> {
        let (from, to) = (self.date_from.trim(), self.date_to.trim());
        check_date("from", from)?;
        check_date("to", to)?;
        let study_date = match (from, to) {
            ("", "") => None,
            (f, t) if f == t => Some(f.to_string()),
            (f, t) => Some(format!("{f}-{t}")),
        };
        Ok(StudyQuery {
            patient_name: field(&self.patient_name),
            patient_id: field(&self.patient_id),
            study_date,
            modality: field(&self.modality).map(|m| m.to_ascii_uppercase()),
            accession: field(&self.accession),
            study_uid: None,
            limit: Some(200),
        })
    }
}

enum Answer {
    Studies(Result<Vec<Study>, String>),
    Series(Result<Vec<Series>, String>),
}

/// A search on its thread; its answer is taken by [`PacsModel::poll`]. A newer search replaces
/// it, and the older thread's answer then goes nowhere.
struct Pending {
    what: String,
    answer: Arc<Mutex<Option<Answer>>>,
}

/// What the dialog shows and edits, without egui.
pub struct PacsModel {
    /// The servers file the names come from (None: the command line's default, if any).
    pub servers_file: Option<PathBuf>,
    /// The servers named there.
    pub server_names: Vec<String>,
    /// A server's name, or a DICOMweb base URL.
    pub server: String,
    pub form: SearchForm,
    pub studies: Vec<Study>,
    pub selected_study: Option<usize>,
    /// The selected study's series.
    pub series: Vec<Series>,
    pub selected_series: Option<usize>,
    /// The last search's problem, naming the server.
    pub error: Option<String>,
    pending: Option<Pending>,
    /// The listed series' thumbnails by series UID, as they arrive (an error: why none).
    pub thumbnails: HashMap<String, Result<Thumbnail, String>>,
    /// Where the thumbnail thread of the current series list puts them; a new list replaces
    /// it, and an older thread's thumbnails then go nowhere.
    arriving_thumbnails: Arc<Mutex<HashMap<String, Result<Thumbnail, String>>>>,
    repaint: Option<Repaint>,
}

impl PacsModel {
    /// Names from `servers_file` (None: the command line's default file); a file that is
    /// missing lists none, one that cannot be read says so in `error`.
    pub fn new(servers_file: Option<PathBuf>) -> PacsModel {
        let file = servers_file
            .clone()
            .or_else(crate::pacs_client::default_servers_file);
        let mut error = None;
        let server_names = match &file {
            Some(f) if f.exists() => match ServersFile::read(f) {
                Ok(s) => s.servers.iter().map(|s| s.name.clone()).collect(),
                Err(e) => {
                    error = Some(format!("cannot read the servers file {}: {e}", f.display()));
                    Vec::new()
                }
            },
            _ => Vec::new(),
        };
        PacsModel {
            servers_file,
            server: server_names.first().cloned().unwrap_or_default(),
            server_names,
            form: SearchForm::default(),
            studies: Vec::new(),
            selected_study: None,
            series: Vec::new(),
            selected_series: None,
            error,
            pending: None,
            thumbnails: HashMap::new(),
            arriving_thumbnails: Arc::default(),
            repaint: None,
        }
    }

    /// The server as it may be shown: its name, or its URL without credentials.
    pub fn server_shown(&self) -> String {
        strata_pacs::redact_url(self.server.trim())
    }

    /// What is being searched, while a search runs.
    pub fn busy(&self) -> Option<&str> {
        self.pending.as_ref().map(|p| p.what.as_str())
    }

    /// Searches the server's studies with the form's query (on a named thread).
    pub fn search(&mut self, repaint: Repaint) {
        self.studies.clear();
        self.selected_study = None;
        self.series.clear();
        self.selected_series = None;
        self.error = None;
        let query = match self.form.query() {
            Ok(q) => q,
            Err(e) => {
                self.error = Some(e.to_string());
                return;
            }
        };
        self.start(
            "searching studies",
            "strata-pacs-search",
            repaint,
            move |client| Answer::Studies(client.find_studies(&query).map_err(|e| e.to_string())),
        );
    }

    /// Selects study `index` and lists its series (on a named thread).
    pub fn select_study(&mut self, index: usize, repaint: Repaint) {
        let Some(study) = self.studies.get(index) else {
            return;
        };
        let uid = study.study_uid.clone();
        self.selected_study = Some(index);
        self.series.clear();
        self.selected_series = None;
        self.error = None;
        self.repaint = Some(repaint.clone());
        self.start(
            "listing series",
            "strata-pacs-series",
            repaint,
            move |client| Answer::Series(client.series_of(&uid).map_err(|e| e.to_string())),
        );
    }

    fn start(
        &mut self,
        what: &str,
        thread: &str,
        repaint: Repaint,
        ask: impl FnOnce(&strata_pacs::Client) -> Answer + Send + 'static,
    ) {
        let server = self.server.trim().to_string();
        let shown = self.server_shown();
        if server.is_empty() {
            self.error = Some("choose a server, or type a DICOMweb URL".into());
            return;
        }
        let args = crate::pacs_client::ServerArgs::from_servers_file(self.servers_file.clone());
        let answer = Arc::new(Mutex::new(None));
        let slot = answer.clone();
        let is_studies = what.contains("studies");
        let spawned = std::thread::Builder::new()
            .name(thread.into())
            .spawn(move || {
                let result = match crate::pacs_client::connect(&server, &args) {
                    Ok(client) => ask(&client),
                    Err(e) => {
                        let e = crate::error_report::describe(&e);
                        if is_studies {
                            Answer::Studies(Err(e))
                        } else {
                            Answer::Series(Err(e))
                        }
                    }
                };
                // Every error names the server, as it may be shown.
                let name = |e: String| {
                    if e.contains(&shown) {
                        e
                    } else {
                        format!("{shown}: {e}")
                    }
                };
                let result = match result {
                    Answer::Studies(r) => Answer::Studies(r.map_err(name)),
                    Answer::Series(r) => Answer::Series(r.map_err(name)),
                };
                *lock_ignoring_poison(&slot) = Some(result);
                repaint();
            });
        match spawned {
            Ok(_) => {
                self.pending = Some(Pending {
                    what: what.to_string(),
                    answer,
                })
            }
            Err(e) => self.error = Some(format!("cannot start the search: {e}")),
        }
    }

    /// Fetches the listed series' thumbnails one after another on a named thread (a PACS is
    /// asked for one instance at a time; the list stays usable meanwhile).
    fn start_thumbnails(&mut self) {
        self.thumbnails.clear();
        self.arriving_thumbnails = Arc::default();
        let (Some(study), Some(repaint)) = (
            self.studies.get(self.selected_study.unwrap_or(usize::MAX)),
            self.repaint.clone(),
        ) else {
            return;
        };
        let study_uid = study.study_uid.clone();
        let series: Vec<String> = self.series.iter().map(|s| s.series_uid.clone()).collect();
        let server = self.server.trim().to_string();
        let args = crate::pacs_client::ServerArgs::from_servers_file(self.servers_file.clone());
        let slot = self.arriving_thumbnails.clone();
        let _ = std::thread::Builder::new()
            .name("strata-pacs-thumbnails".into())
            .spawn(move || {
                let client = crate::pacs_client::connect(&server, &args)
                    .map_err(|e| crate::error_report::describe(&e));
                for uid in series {
                    // A newer list took over: stop asking the server.
                    if Arc::strong_count(&slot) == 1 {
                        return;
                    }
                    let thumbnail = match &client {
                        Ok(client) => super::pacs_thumbnail::fetch(client, &study_uid, &uid)
                            .map_err(|e| e.to_string()),
                        Err(e) => Err(e.clone()),
                    };
                    lock_ignoring_poison(&slot).insert(uid, thumbnail);
                    repaint();
                }
            });
    }

    /// Takes a finished search's answer and the thumbnails that arrived; true when something
    /// changed.
    pub fn poll(&mut self) -> bool {
        let arrived: Vec<_> = lock_ignoring_poison(&self.arriving_thumbnails)
            .drain()
            .collect();
        let thumbnails_came = !arrived.is_empty();
        self.thumbnails.extend(arrived);
        let Some(answer) = self
            .pending
            .as_ref()
            .and_then(|p| lock_ignoring_poison(&p.answer).take())
        else {
            return thumbnails_came;
        };
        self.pending = None;
        match answer {
            Answer::Studies(Ok(studies)) => self.studies = studies,
            Answer::Series(Ok(series)) => {
                self.selected_series = (series.len() == 1).then_some(0);
                self.series = series;
                self.start_thumbnails();
            }
            Answer::Studies(Err(e)) | Answer::Series(Err(e)) => self.error = Some(e),
        }
        true
    }

    /// The selected series, as what to open.
    pub fn open_request(&self) -> Option<PacsSeries> {
        let study = self.studies.get(self.selected_study?)?;
        let series = self.series.get(self.selected_series?)?;
        Some(PacsSeries {
            server: self.server.trim().to_string(),
            servers_file: self.servers_file.clone(),
            study_uid: study.study_uid.clone(),
            series_uid: series.series_uid.clone(),
            label: series_label(study, series),
        })
    }
}

/// A series' row: modality, description, instances.
pub fn series_row(series: &Series) -> [String; 3] {
    [
        series.modality.clone(),
        series.description.clone(),
        series
            .instance_count
            .map_or("?".to_string(), |n| n.to_string()),
    ]
}

fn series_label(study: &Study, series: &Series) -> String {
    let [modality, description, count] = series_row(series);
    let description = if description.is_empty() {
        series.series_uid.clone()
    } else {
        description
    };
    format!(
        "{} {modality} {description} ({count} instances)",
        study.patient_name
    )
}

/// The window.
pub struct PacsDialog {
    pub open: bool,
    pub model: PacsModel,
    /// The thumbnails' textures by instance UID (uploaded once each).
    thumbnail_textures: HashMap<String, egui::TextureHandle>,
}

/// A series' thumbnail in its row: the image once it arrived, a spinner until then, a dash
/// (with the reason on hover) when there is none.
fn thumbnail_cell(
    ui: &mut egui::Ui,
    textures: &mut HashMap<String, egui::TextureHandle>,
    thumbnail: Option<&Result<Thumbnail, String>>,
) {
    const SHOWN: f32 = super::pacs_thumbnail::THUMBNAIL_SIDE as f32;
    match thumbnail {
        None => {
            ui.add_sized([SHOWN, SHOWN], egui::Spinner::new());
        }
        Some(Err(e)) => {
            ui.add_sized([SHOWN, SHOWN], egui::Label::new("—"))
                .on_hover_text(format!("no thumbnail: {e}"));
        }
        Some(Ok(t)) => {
            let texture = textures.entry(t.instance_uid.clone()).or_insert_with(|| {
                ui.ctx().load_texture(
                    format!("pacs-thumbnail-{}", t.instance_uid),
                    egui::ColorImage::from_gray(t.size, &t.gray),
                    egui::TextureOptions::LINEAR,
                )
            });
            // Fitted into a square cell, aspect kept.
            let scale = SHOWN / t.size[0].max(t.size[1]).max(1) as f32;
            let size = egui::vec2(t.size[0] as f32 * scale, t.size[1] as f32 * scale);
            ui.add_sized([SHOWN, SHOWN], egui::Image::new((texture.id(), size)))
                .on_hover_text(format!("instance {}", t.instance_uid));
        }
    }
}

fn labelled_text(ui: &mut egui::Ui, label: &str, text: &mut String, width: f32, hint: &str) {
    let label = ui.label(label);
    ui.add(
        egui::TextEdit::singleline(text)
            .desired_width(width)
            .hint_text(hint),
    )
    .labelled_by(label.id);
}

impl PacsDialog {
    pub fn new(servers_file: Option<PathBuf>) -> PacsDialog {
        PacsDialog {
            open: false,
            model: PacsModel::new(servers_file),
            thumbnail_textures: HashMap::new(),
        }
    }

    /// Draws the window while it is open; returns what to open when the user asked for it.
    /// `job` and `job_error` are the viewer's preparation (its progress and Cancel shown here
    /// while it retrieves).
    pub fn ui(
        &mut self,
        ctx: &egui::Context,
        job: Option<&PrepareJob>,
        job_error: &mut Option<String>,
    ) -> Option<VolumeToOpen> {
        if !self.open {
            return None;
        }
        self.model.poll();
        let repaint: Repaint = {
            let ctx = ctx.clone();
            Arc::new(move || ctx.request_repaint())
        };
        let mut open = true;
        let mut start = None;
        let model = &mut self.model;
        let textures = &mut self.thumbnail_textures;
        egui::Window::new("Open from PACS")
            .open(&mut open)
            .default_width(620.0)
            .show(ctx, |ui| {
                ui.horizontal(|ui| {
                    let label = ui.label("Server");
                    if !model.server_names.is_empty() {
                        egui::ComboBox::from_id_salt("pacs-server")
                            .selected_text(model.server_shown())
                            .show_ui(ui, |ui| {
                                for name in model.server_names.clone() {
                                    ui.selectable_value(&mut model.server, name.clone(), name);
                                }
                            });
                    }
                    ui.add(
                        egui::TextEdit::singleline(&mut model.server)
                            .desired_width(300.0)
                            .hint_text("https://pacs.example/dicom-web or a name"),
                    )
                    .labelled_by(label.id);
                });
                egui::Grid::new("pacs-form").num_columns(4).show(ui, |ui| {
                    labelled_text(
                        ui,
                        "Patient name",
                        &mut model.form.patient_name,
                        160.0,
                        "DOE^J*",
                    );
                    labelled_text(ui, "Patient ID", &mut model.form.patient_id, 120.0, "");
                    ui.end_row();
                    labelled_text(
                        ui,
                        "Date from",
                        &mut model.form.date_from,
                        160.0,
                        "YYYYMMDD",
                    );
                    labelled_text(ui, "Date to", &mut model.form.date_to, 120.0, "YYYYMMDD");
                    ui.end_row();
                    labelled_text(ui, "Modality", &mut model.form.modality, 160.0, "CT, MR…");
                    labelled_text(ui, "Accession", &mut model.form.accession, 120.0, "");
                    ui.end_row();
                });
                ui.horizontal(|ui| {
                    let busy = model.busy().map(str::to_string);
                    if ui
                        .add_enabled(busy.is_none(), egui::Button::new("Search"))
                        .clicked()
                    {
                        model.search(repaint.clone());
                    }
                    if let Some(what) = busy {
                        ui.spinner();
                        ui.label(format!("{what} on {}…", model.server_shown()));
                    }
                });
                if !model.studies.is_empty() {
                    ui.separator();
                    ui.label(format!("{} studies", model.studies.len()));
                    let mut clicked = None;
                    egui::ScrollArea::vertical()
                        .id_salt("pacs-studies")
                        .max_height(160.0)
                        .show(ui, |ui| {
                            egui::Grid::new("pacs-studies-grid")
                                .striped(true)
                                .show(ui, |ui| {
                                    for h in [
                                        "Patient",
                                        "ID",
                                        "Date",
                                        "Modalities",
                                        "Accession",
                                        "Description",
                                    ] {
                                        ui.strong(h);
                                    }
                                    ui.end_row();
                                    for (i, s) in model.studies.iter().enumerate() {
                                        let selected = model.selected_study == Some(i);
                                        if ui.selectable_label(selected, &s.patient_name).clicked()
                                        {
                                            clicked = Some(i);
                                        }
                                        ui.label(&s.patient_id);
                                        ui.label(&s.study_date);
                                        ui.label(s.modalities.join("\\"));
                                        ui.label(&s.accession);
                                        ui.label(&s.description);
                                        ui.end_row();
                                    }
                                });
                        });
                    if let Some(i) = clicked {
                        model.select_study(i, repaint.clone());
                    }
                }
                if !model.series.is_empty() {
                    ui.separator();
                    egui::ScrollArea::vertical()
                        .id_salt("pacs-series")
                        .max_height(140.0)
                        .show(ui, |ui| {
                            egui::Grid::new("pacs-series-grid")
                                .striped(true)
                                .show(ui, |ui| {
                                    for h in ["", "Modality", "Description", "Instances"] {
                                        ui.strong(h);
                                    }
                                    ui.end_row();
                                    for (i, s) in model.series.iter().enumerate() {
                                        thumbnail_cell(
                                            ui,
                                            textures,
                                            model.thumbnails.get(&s.series_uid),
                                        );
                                        let [modality, description, count] = series_row(s);
                                        let selected = model.selected_series == Some(i);
                                        if ui.selectable_label(selected, modality).clicked() {
                                            model.selected_series = Some(i);
                                        }
                                        ui.label(description);
                                        ui.label(count);
                                        ui.end_row();
                                    }
                                });
                        });
                    let request = model.open_request();
                    if ui
                        .add_enabled(
                            job.is_none() && request.is_some(),
                            egui::Button::new("Open series"),
                        )
                        .on_hover_text(
                            "Retrieve and import it (an earlier import of it opens at once)",
                        )
                        .clicked()
                    {
                        start = request.map(VolumeToOpen::Pacs);
                    }
                }
                if let Some(job) = job {
                    ui.separator();
                    super::dialogs::job_progress(ui, job);
                }
                for (title, e) in [
                    ("Search failed", model.error.clone()),
                    ("Could not open", job_error.clone()),
                ] {
                    let Some(e) = e else { continue };
                    ui.separator();
                    egui::Frame::NONE
                        .fill(Color32::from_rgb(70, 20, 20))
                        .inner_margin(8.0)
                        .corner_radius(4.0)
                        .show(ui, |ui| {
                            ui.colored_label(
                                Color32::from_rgb(255, 190, 190),
                                RichText::new(title).strong(),
                            );
                            ui.label(RichText::new(&e).color(Color32::from_rgb(255, 220, 220)));
                        });
                }
            });
        if !open {
            self.open = false;
        }
        start
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_form_makes_the_query_and_refuses_bad_dates() {
        let mut form = SearchForm {
            patient_name: " DOE^J* ".into(),
            date_from: "20240101".into(),
            modality: "ct".into(),
            ..SearchForm::default()
        };
        let q = form.query().unwrap();
        assert_eq!(q.patient_name.as_deref(), Some("DOE^J*"));
        assert_eq!(q.study_date.as_deref(), Some("20240101-"));
        assert_eq!(q.modality.as_deref(), Some("CT"));
        assert_eq!(q.patient_id, None);
        form.date_to = "20241231".into();
        assert_eq!(
            form.query().unwrap().study_date.as_deref(),
            Some("20240101-20241231")
        );
        form.date_to = "2024-12-31".into();
        assert!(form.query().unwrap_err().to_string().contains("YYYYMMDD"));
    }

    #[test]
    fn a_search_without_a_server_says_so_and_credentials_in_a_url_are_not_shown() {
        let mut model = PacsModel::new(Some("/nonexistent/strata-servers.json".into()));
        assert!(model.server_names.is_empty() && model.error.is_none());
        model.search(Arc::new(|| {}));
        assert!(model.error.as_deref().unwrap().contains("server"));
        model.server = "http://alice:secret-pw@127.0.0.1:9/dicom-web".into();
        assert_eq!(model.server_shown(), "http://127.0.0.1:9/dicom-web");
    }

    #[test]
    fn an_unreachable_server_is_an_error_naming_it_without_its_password() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .unwrap();
        let mut model = PacsModel::new(Some("/nonexistent/strata-servers.json".into()));
        model.server = format!("http://alice:Pw-secret-9@127.0.0.1:{port}/dicom-web");
        model.search(Arc::new(|| {}));
        let start = std::time::Instant::now();
        while !model.poll() {
            assert!(start.elapsed() < std::time::Duration::from_secs(120));
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let e = model.error.clone().expect("an error");
        assert!(e.contains(&format!("127.0.0.1:{port}")), "{e}");
        assert!(!e.contains("Pw-secret-9"), "{e}");
        assert!(model.studies.is_empty() && model.busy().is_none());
    }

    /// Against a real PACS (Orthanc on loopback, the integration tests' fixture).
    mod orthanc {
        use std::time::{Duration, Instant};

        use egui_kittest::kittest::Queryable;
        use egui_kittest::Harness;
        use strata_storage::import::{import_source, ImportOptions};
        use strata_storage::readers::{open_source, ReadOptions};

        use super::*;
        use crate::orthanc_fixture::*;

        const WAIT: Duration = Duration::from_secs(120);

        fn wait(model: &mut PacsModel, what: &str) {
            let start = Instant::now();
            while !model.poll() {
                assert!(start.elapsed() < WAIT, "{what}: no answer");
                std::thread::sleep(Duration::from_millis(20));
            }
            assert_eq!(model.error, None, "{what}");
        }

        fn finish(job: &PrepareJob) -> Arc<dyn strata_source::VolumeSource> {
            let start = Instant::now();
            loop {
                if let Some(r) = job.take_result() {
                    return r.unwrap_or_else(|e| panic!("opening from the PACS failed: {e:#}"));
                }
                assert!(start.elapsed() < WAIT, "the PACS job did not finish");
                std::thread::sleep(Duration::from_millis(20));
            }
        }

        #[test]
        fn pacs_dialog_model_finds_lists_and_opens_a_series_equal_to_the_folder_import() {
            let work = tempfile::tempdir().unwrap();
            let orthanc = filled_orthanc(work.path());
            let repaint: Repaint = Arc::new(|| {});
            let mut model = PacsModel::new(Some(work.path().join("no-servers.json")));
            model.server = orthanc.url.clone();
            model.form.patient_name = "DOE^J*".into();
            model.search(repaint.clone());
            assert!(model.busy().is_some());
            wait(&mut model, "search");
            let uids: Vec<&str> = model.studies.iter().map(|s| s.study_uid.as_str()).collect();
            assert_eq!(uids, [CT_STUDY]);
            model.form.patient_name.clear();
            model.form.modality = "MR".into();
            model.search(repaint.clone());
            wait(&mut model, "search by modality");
            let uids: Vec<&str> = model.studies.iter().map(|s| s.study_uid.as_str()).collect();
            assert_eq!(uids, [MR_STUDY]);
            model.form = SearchForm {
                date_from: "20240101".into(),
                date_to: "20241231".into(),
                ..SearchForm::default()
            };
            model.search(repaint.clone());
            wait(&mut model, "search by dates");
            assert_eq!(model.studies.len(), 1);
            assert_eq!(model.studies[0].study_uid, CT_STUDY);

            model.select_study(0, repaint.clone());
            wait(&mut model, "series");
            assert_eq!(model.series.len(), 1);
            let [modality, _description, count] = series_row(&model.series[0]);
            assert_eq!((modality.as_str(), count), ("CT", CT_SLICES.to_string()));
            let request = model.open_request().expect("the only series is selected");
            assert_eq!(request.series_uid, CT_SERIES);
            // The series' thumbnail: its middle instance by number, read as the importer reads
            // it (the fixture's slices are 40 columns by 48 rows: not enlarged).
            let start = Instant::now();
            while !model.thumbnails.contains_key(CT_SERIES) {
                assert!(start.elapsed() < WAIT, "no thumbnail");
                std::thread::sleep(Duration::from_millis(20));
                model.poll();
            }
            let thumbnail = model.thumbnails[CT_SERIES].clone().expect("a thumbnail");
            assert_eq!(thumbnail.size, [40, 48]);
            let base = strata_pacs::normalise_base_url(&orthanc.url).unwrap();
            let client = strata_pacs::Client::new(
                &base,
                strata_pacs::Auth::None,
                None,
                strata_pacs::ClientOptions::default(),
            )
            .unwrap();
            let middle = client
                .middle_instance(CT_STUDY, CT_SERIES)
                .unwrap()
                .unwrap();
            assert_eq!(thumbnail.instance_uid, middle);
            let slice = work.path().join("middle");
            std::fs::create_dir_all(&slice).unwrap();
            let file = client
                .retrieve_instance(CT_STUDY, CT_SERIES, &middle, &slice)
                .unwrap();
            let opened = open_source(&file, &ReadOptions::default()).unwrap();
            let mut values = Vec::new();
            opened.data.read_slice_f64(0, &mut values);
            let want = crate::pacs_thumbnail::thumbnail_from_slice(
                &values,
                [40, 48],
                crate::pacs_thumbnail::THUMBNAIL_SIDE,
                middle.clone(),
            );
            assert_eq!(thumbnail, want);
            assert!(
                thumbnail.gray.iter().any(|&g| g != thumbnail.gray[0]),
                "a phantom slice is not flat"
            );

            // Open: retrieved and imported by the background job, equal to a folder import.
            let stores = work.path().join("stores");
            let job = PrepareJob::start(
                VolumeToOpen::Pacs(request.clone()),
                None,
                stores.clone(),
                repaint.clone(),
            )
            .unwrap();
            assert!(job.title.contains(&orthanc.url), "{}", job.title);
            let opened = finish(&job);
            assert_eq!(opened.header().geometry.dims, [40, 48, CT_SLICES as u32]);
            let base = strata_pacs::normalise_base_url(&orthanc.url).unwrap();
            let store = crate::jobs::store_path_for_pacs_series(&base, CT_SERIES, &stores);
            assert!(opened.header().description.contains("retrieved from"));
            // Its store is locked while open.
            drop(opened);
            let folder = work.path().join("from-folder");
            let source =
                open_source(&work.path().join("src").join("ct"), &ReadOptions::default()).unwrap();
            import_source(source, &folder, &ImportOptions::default()).unwrap();
            same_stores(&store, &folder);
            let left: Vec<_> = std::fs::read_dir(&stores)
                .unwrap()
                .map(|e| e.unwrap().file_name())
                .collect();
            assert_eq!(left.len(), 1, "the retrieved instances stay: {left:?}");

            // The same series from the same server again opens at once: the PACS is gone.
            drop(orthanc);
            let again =
                PrepareJob::start(VolumeToOpen::Pacs(request), None, stores, repaint).unwrap();
            assert_eq!(finish(&again).header().geometry.dims[2], CT_SLICES as u32);
        }

        #[test]
        fn pacs_dialog_kittest_types_a_patient_name_searches_and_shows_the_study() {
            let work = tempfile::tempdir().unwrap();
            let orthanc = filled_orthanc(work.path());
            let mut dialog = PacsDialog::new(Some(work.path().join("no-servers.json")));
            dialog.open = true;
            dialog.model.server = orthanc.url.clone();
            let mut h = Harness::builder()
                .with_size(egui::Vec2::new(900.0, 700.0))
                .build_ui_state(
                    |ui, d: &mut PacsDialog| {
                        let ctx = ui.ctx().clone();
                        d.ui(&ctx, None, &mut None);
                    },
                    dialog,
                );
            h.step();
            let name = h.get_by_label("Patient name");
            name.focus();
            name.type_text("DOE^J*");
            h.step();
            assert_eq!(h.state().model.form.patient_name, "DOE^J*");
            h.get_by_label("Search").click();
            let start = Instant::now();
            while h.query_by_label("DOE^JOHN").is_none() {
                assert_eq!(h.state().model.error, None);
                assert!(start.elapsed() < WAIT, "no study row after the search");
                std::thread::sleep(Duration::from_millis(20));
                h.step();
            }
            assert!(h.query_by_label("ROE^JANE").is_none());
        }
    }
}
