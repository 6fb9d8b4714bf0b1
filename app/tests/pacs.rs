//! `strata pacs` and `strata import SERVER --study UID` against a real PACS: Debian's Orthanc
//! with its DICOMweb plugin, started on a free loopback port with a temporary configuration and
//! storage folder, filled through STOW-RS (`strata pacs push`) with a generated CT series and a
//! small MR study, and killed at the end whatever the outcome (`Orthanc`'s Drop).
//!
//! Without Orthanc these tests FAIL with the install command, as CI installs it
//! (.ci/test-packages): a PACS test that passes without a PACS checks nothing.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use strata_pacs::{Auth, Client, ClientOptions, Secret, StudyQuery};

use crate::common::orthanc::*;

fn strata(args: &[&str]) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_strata"))
        .args(args)
        .env("RUST_LOG", "debug")
        .env(
            "STRATA_PACS_SERVERS",
            "/nonexistent/strata-test-servers.json",
        )
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("strata runs");
    // Bounded: a command still running after 5 minutes is killed and the test fails (its own
    // timeouts are shorter; this only keeps a hang from holding the test run).
    let read = |name: &str, mut pipe: Box<dyn std::io::Read + Send>| {
        std::thread::Builder::new()
            .name(name.into())
            .spawn(move || {
                let mut bytes = Vec::new();
                let _ = pipe.read_to_end(&mut bytes);
                bytes
            })
            .unwrap()
    };
    let stdout = read("strata-stdout", Box::new(child.stdout.take().unwrap()));
    let stderr = read("strata-stderr", Box::new(child.stderr.take().unwrap()));
    let deadline = Instant::now() + Duration::from_secs(300);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("strata {args:?} still ran after 300 s: killed");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Output {
        status,
        stdout: stdout.join().unwrap(),
        stderr: stderr.join().unwrap(),
    }
}

fn ok(out: Output, what: &str) -> String {
    assert!(
        out.status.success(),
        "{what} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

fn uids(studies: &[strata_pacs::Study]) -> Vec<&str> {
    let mut u: Vec<&str> = studies.iter().map(|s| s.study_uid.as_str()).collect();
    u.sort();
    u
}

#[test]
fn pacs_find_push_retrieve_and_resume_against_orthanc() {
    let orthanc = start_orthanc(None);
    let work = tempfile::tempdir().unwrap();
    let src = work.path().join("src");
    write_dicom(&src);
    let url = orthanc.url.as_str();

    let pushed = ok(
        strata(&["pacs", "push", url, src.to_str().unwrap()]),
        "pacs push",
    );
    assert!(
        pushed.contains(&format!("stored {0} of {0}", CT_SLICES + 2)),
        "{pushed}"
    );

    // QIDO: name wildcard, date range, modality.
    let client = Client::new(url, Auth::None, None, ClientOptions::default()).unwrap();
    let find = |q: StudyQuery| client.find_studies(&q).unwrap();
    let by_name = find(StudyQuery {
        patient_name: Some("DOE^J*".into()),
        ..StudyQuery::default()
    });
    assert_eq!(uids(&by_name), [CT_STUDY]);
    assert_eq!(by_name[0].patient_id, "P-1");
    let by_date = find(StudyQuery {
        study_date: Some("20240101-20241231".into()),
        ..StudyQuery::default()
    });
    assert_eq!(uids(&by_date), [CT_STUDY]);
    let by_modality = find(StudyQuery {
        modality: Some("MR".into()),
        ..StudyQuery::default()
    });
    assert_eq!(uids(&by_modality), [MR_STUDY]);
    assert_eq!(uids(&find(StudyQuery::default())), [CT_STUDY, MR_STUDY]);
    let series = client.series_of(CT_STUDY).unwrap();
    assert_eq!(series.len(), 1);
    assert_eq!(series[0].series_uid, CT_SERIES);
    assert_eq!(series[0].modality, "CT");
    assert_eq!(series[0].instance_count, Some(CT_SLICES as u64));

    // The command line prints the same.
    let listed = ok(
        strata(&["pacs", "find", url, "--patient-name", "DOE^J*"]),
        "pacs find",
    );
    assert!(
        listed.contains(CT_STUDY) && !listed.contains(MR_STUDY),
        "{listed}"
    );
    let listed = ok(
        strata(&["pacs", "find", url, "--study", CT_STUDY]),
        "pacs find --study",
    );
    assert!(
        listed.contains(CT_SERIES) && listed.contains("CT"),
        "{listed}"
    );

    // Retrieve + import equals importing the same files from the folder.
    let from_pacs = work.path().join("from-pacs");
    let from_folder = work.path().join("from-folder");
    ok(
        strata(&[
            "import",
            url,
            "--study",
            CT_STUDY,
            from_pacs.to_str().unwrap(),
        ]),
        "import from the PACS",
    );
    ok(
        strata(&[
            "import",
            src.join("ct").to_str().unwrap(),
            from_folder.to_str().unwrap(),
        ]),
        "import from the folder",
    );
    same_stores(&from_pacs, &from_folder);
    let info = ok(strata(&["info", from_pacs.to_str().unwrap()]), "info");
    assert!(
        info.contains(&format!("retrieved from {url}"))
            && info.contains(CT_STUDY)
            && info.contains(CT_SERIES),
        "{info}"
    );

    // Resume: only what is missing is fetched, one request each.
    let folder = work.path().join("retrieved");
    let first = client
        .retrieve_series(CT_STUDY, CT_SERIES, &folder, None, None)
        .unwrap();
    // A fresh series comes as one multipart answer: one WADO-RS request for all instances.
    assert_eq!(
        (first.fetched, first.already_present, first.requests),
        (CT_SLICES, 0, 1)
    );
    assert_eq!(first.count_mismatch, None);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&folder)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    assert_eq!(files.len(), CT_SLICES);
    for f in &files[..3] {
        std::fs::remove_file(f).unwrap();
    }
    let second = client
        .retrieve_series(CT_STUDY, CT_SERIES, &folder, None, None)
        .unwrap();
    assert_eq!(
        (second.fetched, second.already_present, second.requests),
        (3, CT_SLICES - 3, 3)
    );
    let third = client
        .retrieve_series(CT_STUDY, CT_SERIES, &folder, None, None)
        .unwrap();
    assert_eq!((third.fetched, third.requests), (0, 0));

    // The command line resumes too: what an interrupted import left beside the store is not
    // fetched again, and the folder goes once the store is complete.
    let resumed_store = work.path().join("resumed");
    let partial = work.path().join(format!("resumed.retrieving-{CT_SERIES}"));
    std::fs::create_dir(&partial).unwrap();
    for f in &dcm_files(&folder)[..5] {
        std::fs::copy(f, partial.join(f.file_name().unwrap())).unwrap();
    }
    let said = ok(
        strata(&[
            "import",
            url,
            "--study",
            CT_STUDY,
            resumed_store.to_str().unwrap(),
        ]),
        "resumed import from the PACS",
    );
    assert!(
        said.contains("resumed: 5 instance(s)")
            && said.contains(&format!("retrieved {} instance(s)", CT_SLICES - 5)),
        "{said}"
    );
    assert!(!partial.exists(), "{} left", partial.display());
    same_stores(&resumed_store, &from_folder);
}

#[test]
fn pacs_basic_auth_keeps_the_password_out_of_errors_logs_and_stores() {
    const PASSWORD: &str = "Pw-9f3kXq-not-in-any-output";
    let orthanc = start_orthanc(Some(("alice", PASSWORD)));
    let work = tempfile::tempdir().unwrap();
    let src = work.path().join("src");
    write_dicom(&src);
    let url = orthanc.url.as_str();
    let good = work.path().join("password");
    std::fs::write(&good, format!("{PASSWORD}\n")).unwrap();
    let auth = ["--user", "alice", "--password-file", good.to_str().unwrap()];
    let mut everything = String::new();

    // Without credentials, and with wrong ones: refused, said so, no password echoed.
    let denied = strata(&["pacs", "find", url]);
    assert!(!denied.status.success());
    let text = String::from_utf8_lossy(&denied.stderr).to_string();
    assert!(text.contains("401") && text.contains(url), "{text}");
    let wrong = work.path().join("wrong");
    std::fs::write(&wrong, "wrong-password-xyz\n").unwrap();
    let denied = strata(&[
        "pacs",
        "find",
        url,
        "--user",
        "alice",
        "--password-file",
        wrong.to_str().unwrap(),
    ]);
    assert!(!denied.status.success());
    let text = String::from_utf8_lossy(&denied.stderr).to_string();
    assert!(
        text.contains("401") && !text.contains("wrong-password-xyz"),
        "{text}"
    );

    let mut push = vec!["pacs", "push", url, src.to_str().unwrap()];
    push.extend(auth);
    everything += &ok(strata(&push), "pacs push with basic auth");
    let mut find = vec!["pacs", "find", url, "--modality", "CT"];
    find.extend(auth);
    let listed = ok(strata(&find), "pacs find with basic auth");
    assert!(listed.contains(CT_STUDY), "{listed}");
    everything += &listed;
    let store = work.path().join("store");
    let mut import = vec!["import", url, "--study", CT_STUDY, store.to_str().unwrap()];
    import.extend(auth);
    everything += &ok(strata(&import), "import with basic auth");
    everything += &ok(strata(&["info", store.to_str().unwrap()]), "info");
    let header = std::fs::read_to_string(store.join("header.json")).unwrap_or_default();
    everything += &header;
    assert!(everything.contains(CT_SERIES), "{everything}");
    assert!(!everything.contains(PASSWORD), "{everything}");

    // The library: a wrong password's error names the server and the status, not the secret.
    let client = Client::new(
        url,
        Auth::Basic {
            user: "alice".into(),
            password: Secret::new("another-wrong-one"),
        },
        None,
        ClientOptions::default(),
    )
    .unwrap();
    let e = client.series_of(CT_STUDY).unwrap_err().to_string();
    assert!(e.contains("401") && !e.contains("another-wrong-one"), "{e}");
}

#[test]
fn pacs_cancel_half_way_then_resume_fetches_only_the_missing_instances() {
    let work = tempfile::tempdir().unwrap();
    let orthanc = filled_orthanc(work.path());
    // The cancel lands between instances, after half of them (the whole series' answer is
    // checked for it after each instance; the resume's requests go one at a time).
    let options = ClientOptions {
        parallelism: 1,
        ..ClientOptions::default()
    };
    let client = Client::new(&orthanc.url, Auth::None, None, options).unwrap();
    let folder = work.path().join("retrieved");
    let cancel = std::sync::atomic::AtomicBool::new(false);
    let before_cancelled = client.requests();
    let on_progress = |p: strata_pacs::RetrieveProgress| {
        if p.done >= CT_SLICES / 2 {
            cancel.store(true, std::sync::atomic::Ordering::Relaxed);
        }
    };
    let cancelled = client
        .retrieve_series(
            CT_STUDY,
            CT_SERIES,
            &folder,
            Some(&cancel),
            Some(&on_progress),
        )
        .unwrap_err();
    assert!(
        matches!(cancelled, strata_pacs::PacsError::Cancelled),
        "{cancelled}"
    );
    // Whole instances only: no `.part` left, and fewer than the series.
    let kept = dcm_files(&folder);
    assert!(
        kept.iter()
            .all(|f| f.extension().is_some_and(|e| e == "dcm")),
        "{kept:?}"
    );
    // The cancel is checked after each instance of the series' one answer: exactly the first
    // half stays.
    let present = kept.len();
    assert_eq!(present, CT_SLICES / 2, "{kept:?}");

    let cancelled_requests = client.requests() - before_cancelled;
    let before_resumed = client.requests();
    let resumed = client
        .retrieve_series(CT_STUDY, CT_SERIES, &folder, None, None)
        .unwrap();
    // The cancelled run asked for the whole series in one request, besides its searches (as
    // many as the resume's); the resume asks for each missing instance alone.
    let searches = client.requests() - before_resumed - resumed.requests;
    assert_eq!(cancelled_requests - searches, 1);
    assert_eq!(
        (resumed.already_present, resumed.fetched, resumed.requests),
        (present, CT_SLICES - present, (CT_SLICES - present) as u64),
        "{resumed:?}"
    );
    assert_eq!(dcm_files(&folder).len(), CT_SLICES);
}

#[test]
fn pacs_orthanc_killed_during_a_retrieve_is_a_clear_error_and_no_store() {
    let work = tempfile::tempdir().unwrap();
    let orthanc = std::sync::Mutex::new(filled_orthanc(work.path()));
    let url = orthanc.lock().unwrap().url.clone();
    // One instance per request: the 12 small instances of a whole-series answer arrive in one
    // read, before the kill could cut them.
    let options = ClientOptions {
        parallelism: 1,
        whole_series: false,
        attempts: 2,
        backoff: Duration::from_millis(50),
        ..ClientOptions::default()
    };
    let client = Client::new(&url, Auth::None, None, options).unwrap();
    let folder = work.path().join("retrieved");
    // Orthanc is killed once the first instance is in: the next request finds nobody.
    let on_progress = |p: strata_pacs::RetrieveProgress| {
        if p.done == 1 {
            let mut o = orthanc.lock().unwrap();
            let _ = o.child.kill();
            let _ = o.child.wait();
        }
    };
    let e = client
        .retrieve_series(CT_STUDY, CT_SERIES, &folder, None, Some(&on_progress))
        .unwrap_err()
        .to_string();
    assert!(e.contains(&url) && e.contains("instance"), "{e}");
    let kept = dcm_files(&folder);
    assert!(
        kept.len() < CT_SLICES
            && kept
                .iter()
                .all(|f| f.extension().is_some_and(|x| x == "dcm")),
        "{kept:?}"
    );

    // The command line against the dead server: an error naming it, and no store at the path.
    let store = work.path().join("store");
    let out = strata(&["import", &url, "--study", CT_STUDY, store.to_str().unwrap()]);
    assert!(!out.status.success());
    let text = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(text.contains(&url), "{text}");
    assert!(
        strata_storage::Store::open(&store).is_err(),
        "a store is presented at {}",
        store.display()
    );
}

const COMPRESSED_STUDY: &str = "1.2.826.0.1.3680043.8.498.300";
/// (folder, pydicom's name, transfer syntax UID) of each compressed series.
const CODECS: [(&str, &str, &str); 3] = [
    ("rle", "RLELossless", "1.2.840.10008.1.2.5"),
    ("jls", "JPEGLSLossless", "1.2.840.10008.1.2.4.80"),
    ("j2k", "JPEG2000Lossless", "1.2.840.10008.1.2.4.90"),
];

/// One four-slice series per codec (RLE, JPEG-LS, JPEG 2000, all lossless), compressed by
/// pydicom, in one study: `dir/rle`, `dir/jls`, `dir/j2k`.
fn write_compressed_dicom(dir: &Path) {
    let script = format!(
        r#"
import os, numpy as np, pydicom, pydicom.uid
from pydicom.dataset import Dataset, FileMetaDataset
codecs = {codecs}
for i, (name, syntax, _) in enumerate(codecs):
    os.makedirs(os.path.join(r'{dir}', name))
    series = '{study}.%d' % (i + 1)
    for k in range(4):
        ds = Dataset()
        ds.file_meta = FileMetaDataset()
        ds.file_meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
        ds.file_meta.MediaStorageSOPClassUID = '1.2.840.10008.5.1.4.1.1.2'
        ds.file_meta.MediaStorageSOPInstanceUID = '%s.%d' % (series, k)
        ds.SOPClassUID = '1.2.840.10008.5.1.4.1.1.2'
        ds.SOPInstanceUID = '%s.%d' % (series, k)
        ds.StudyInstanceUID = '{study}'; ds.SeriesInstanceUID = series
        ds.PatientName = 'COE^CODEC'; ds.PatientID = 'P-3'; ds.StudyDate = '20220202'
        ds.Modality = 'CT'; ds.StudyID = '3'; ds.SeriesNumber = i + 1; ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [-10.0, -12.0, 3.0 * k]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [0.5, 0.5]; ds.SliceThickness = 3.0
        ds.Rows = 64; ds.Columns = 48  # OpenJPEG's 6 resolutions need 32 or more
        ds.SamplesPerPixel = 1; ds.PhotometricInterpretation = 'MONOCHROME2'
        ds.BitsAllocated = 16; ds.BitsStored = 12; ds.HighBit = 11; ds.PixelRepresentation = 0
        ds.RescaleSlope = 1; ds.RescaleIntercept = -1024
        y, x = np.mgrid[0:64, 0:48]
        img = ((x * 37 + y * 11 + k * 101 + i * 7) % 4000).astype('<u2')
        ds.PixelData = img.tobytes()
        ds.compress(getattr(pydicom.uid, syntax), img)
        ds.save_as(os.path.join(r'{dir}', name, '%03d.dcm' % k), enforce_file_format=True)
"#,
        dir = dir.display(),
        study = COMPRESSED_STUDY,
        codecs = format!("{CODECS:?}").replace('(', "[").replace(')', "]"),
    );
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .output()
        .unwrap_or_else(|e| panic!("python3 not runnable ({e}): pip install pydicom numpy"));
    assert!(
        out.status.success(),
        "writing the compressed series failed (pip install pydicom pylibjpeg \
         pylibjpeg-openjpeg pyjpegls numpy):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn pacs_compressed_series_retrieved_and_imported_equal_the_folder_import() {
    let work = tempfile::tempdir().unwrap();
    let orthanc = start_orthanc(None);
    let src = work.path().join("compressed");
    write_compressed_dicom(&src);
    let url = orthanc.url.as_str();
    ok(
        strata(&["pacs", "push", url, src.to_str().unwrap()]),
        "pacs push of the compressed series",
    );
    let client = Client::new(url, Auth::None, None, ClientOptions::default()).unwrap();
    for (i, (codec, _, syntax)) in CODECS.iter().enumerate() {
        let series = format!("{COMPRESSED_STUDY}.{}", i + 1);
        // Retrieved as stored (transfer-syntax=*): still compressed with the same codec.
        let retrieved = work.path().join(format!("{codec}-retrieved"));
        client
            .retrieve_series(COMPRESSED_STUDY, &series, &retrieved, None, None)
            .unwrap();
        let files = dcm_files(&retrieved);
        assert_eq!(files.len(), 4, "{files:?}");
        for f in &files {
            let head = std::fs::read(f).unwrap();
            let head = &head[..head.len().min(1024)];
            assert!(
                head.windows(syntax.len()).any(|w| w == syntax.as_bytes()),
                "{} is not in {syntax}",
                f.display()
            );
        }
        let from_pacs = work.path().join(format!("{codec}-pacs"));
        let from_folder = work.path().join(format!("{codec}-folder"));
        ok(
            strata(&[
                "import",
                url,
                "--study",
                COMPRESSED_STUDY,
                "--series",
                &series,
                from_pacs.to_str().unwrap(),
            ]),
            &format!("import of the {codec} series from the PACS"),
        );
        ok(
            strata(&[
                "import",
                src.join(codec).to_str().unwrap(),
                from_folder.to_str().unwrap(),
            ]),
            &format!("import of the {codec} series from the folder"),
        );
        same_stores(&from_pacs, &from_folder);
    }
}
