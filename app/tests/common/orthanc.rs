//! A real PACS for tests: Debian's Orthanc with its DICOMweb plugin, started on a free loopback
//! port with a temporary configuration and storage folder, filled through STOW-RS with a
//! generated CT series and a small MR study, and killed when dropped whatever the outcome.
//!
//! Shared by the integration tests (tests/pacs.rs, as `common::orthanc`) and the viewer's unit
//! tests (src/viewer/mod.rs includes this file by path): one copy of the fixture. Without
//! Orthanc the tests using it FAIL with the install command, as CI installs it
//! (.ci/test-packages): a PACS test that passes without a PACS checks nothing.

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use strata_pacs::{Auth, Client, ClientOptions};

pub const INSTALL: &str = "apt-get install -y orthanc orthanc-dicomweb (CI: .ci/test-packages)";
pub const CT_STUDY: &str = "1.2.826.0.1.3680043.8.498.100";
pub const CT_SERIES: &str = "1.2.826.0.1.3680043.8.498.100.1";
pub const MR_STUDY: &str = "1.2.826.0.1.3680043.8.498.200";
pub const CT_SLICES: usize = 12;

/// A running Orthanc; killed (and waited for) when dropped, panicking test or not.
pub struct Orthanc {
    pub child: Child,
    pub url: String,
    pub _dir: tempfile::TempDir,
}

impl Drop for Orthanc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

pub fn dicomweb_plugin() -> PathBuf {
    ["/usr/share/orthanc/plugins", "/usr/lib/orthanc"]
        .iter()
        .filter_map(|d| std::fs::read_dir(d).ok())
        .flatten()
        .flatten()
        .map(|e| e.path())
        .find(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("libOrthancDicomWeb.so"))
        })
        .unwrap_or_else(|| panic!("Orthanc's DICOMweb plugin is not installed: {INSTALL}"))
}

/// Starts Orthanc; with `user`, basic authentication is on for that user and password.
pub fn start_orthanc(user: Option<(&str, &str)>) -> Orthanc {
    let binary = ["/usr/sbin/Orthanc", "/usr/bin/Orthanc"]
        .into_iter()
        .find(|p| Path::new(p).is_file())
        .unwrap_or_else(|| panic!("Orthanc is not installed: {INSTALL}"));
    let dir = tempfile::tempdir().unwrap();
    let storage = dir.path().join("storage");
    let port = free_port();
    let mut config = serde_json::json!({
        "Name": "strata-test",
        "StorageDirectory": storage,
        "IndexDirectory": storage,
        "HttpPort": port,
        "DicomServerEnabled": false,
        "DicomPort": free_port(),
        "RemoteAccessAllowed": false,
        "AuthenticationEnabled": false,
        "Plugins": [dicomweb_plugin()],
        "DicomWeb": { "Enable": true, "Root": "/dicom-web/", "EnableWado": true },
    });
    if let Some((u, p)) = user {
        config["AuthenticationEnabled"] = true.into();
        config["RegisteredUsers"] = serde_json::json!({ u: p });
    }
    let config_path = dir.path().join("orthanc.json");
    std::fs::write(&config_path, config.to_string()).unwrap();
    let log = std::fs::File::create(dir.path().join("orthanc.log")).unwrap();
    let child = Command::new(binary)
        .arg(&config_path)
        .stdout(Stdio::from(log.try_clone().unwrap()))
        .stderr(Stdio::from(log))
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start Orthanc ({e}): {INSTALL}"));
    let mut orthanc = Orthanc {
        child,
        url: format!("http://127.0.0.1:{port}/dicom-web"),
        _dir: dir,
    };
    let log = |o: &Orthanc| {
        std::fs::read_to_string(o._dir.path().join("orthanc.log")).unwrap_or_default()
    };
    // Ready when its HTTP port answers (401 counts: it is up); an Orthanc that exits (a bad
    // configuration, a plugin that does not load) fails at once with its log.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            break;
        }
        if let Ok(Some(status)) = orthanc.child.try_wait() {
            panic!(
                "Orthanc exited ({status}) before it served; its log:\n{}",
                log(&orthanc)
            );
        }
        assert!(
            Instant::now() < deadline,
            "Orthanc did not open its port within 60 s; its log:\n{}",
            log(&orthanc)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    orthanc
}

/// A CT series (`CT_SLICES` slices, 40×48, int16 with a slope) and a two-slice MR study.
pub fn write_dicom(dir: &Path) {
    let script = format!(
        r#"
import os, numpy as np, pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian
def write(path, study, series, n, name, pid, date, modality, k):
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = '1.2.840.10008.5.1.4.1.1.2'
    ds.file_meta.MediaStorageSOPInstanceUID = f'{{series}}.{{k}}'
    ds.SOPClassUID = '1.2.840.10008.5.1.4.1.1.2'
    ds.SOPInstanceUID = f'{{series}}.{{k}}'
    ds.StudyInstanceUID = study; ds.SeriesInstanceUID = series
    ds.PatientName = name; ds.PatientID = pid; ds.StudyDate = date; ds.Modality = modality
    ds.StudyID = '1'; ds.SeriesNumber = 1; ds.InstanceNumber = k + 1
    ds.ImagePositionPatient = [-20.0, -24.0, 2.5 * k]
    ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    ds.PixelSpacing = [0.8, 0.8]; ds.SliceThickness = 2.5
    ds.Rows = 48; ds.Columns = 40
    ds.SamplesPerPixel = 1; ds.PhotometricInterpretation = 'MONOCHROME2'
    ds.BitsAllocated = 16; ds.BitsStored = 16; ds.HighBit = 15; ds.PixelRepresentation = 1
    ds.RescaleSlope = 1; ds.RescaleIntercept = -1024
    y, x = np.mgrid[0:48, 0:40]
    img = ((x * 37 + y * 11 + k * 101) % 2000 - 200).astype('<i2')
    ds.PixelData = img.tobytes()
    ds.save_as(path, enforce_file_format=True)
os.makedirs(r'{dir}/ct'); os.makedirs(r'{dir}/mr')
for k in range({n}):
    write(rf'{dir}/ct/{{k:03}}.dcm', '{ct_study}', '{ct_series}', {n}, 'DOE^JOHN', 'P-1', '20240315', 'CT', k)
for k in range(2):
    write(rf'{dir}/mr/{{k:03}}.dcm', '{mr_study}', '{mr_study}.1', 2, 'ROE^JANE', 'P-2', '20230101', 'MR', k)
"#,
        dir = dir.display(),
        n = CT_SLICES,
        ct_study = CT_STUDY,
        ct_series = CT_SERIES,
        mr_study = MR_STUDY,
    );
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .output()
        .unwrap_or_else(|e| panic!("python3 not runnable ({e}): pip install pydicom numpy"));
    assert!(
        out.status.success(),
        "writing the DICOM series failed (pip install pydicom numpy):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

pub fn same_stores(a: &Path, b: &Path) {
    let a = strata_storage::Store::open(a).unwrap();
    let b = strata_storage::Store::open(b).unwrap();
    assert_eq!(a.header().geometry, b.header().geometry);
    let layout = a.layout().clone();
    for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let id = strata_types::BrickId::new(level as u8, [x, y, z]);
                    assert!(
                        a.read_brick(id).unwrap() == b.read_brick(id).unwrap(),
                        "{id:?}"
                    );
                }
            }
        }
    }
}

/// Orthanc filled with the generated CT series (and the MR study) through STOW-RS.
pub fn filled_orthanc(work: &Path) -> Orthanc {
    let orthanc = start_orthanc(None);
    let src = work.join("src");
    write_dicom(&src);
    let client = Client::new(&orthanc.url, Auth::None, None, ClientOptions::default()).unwrap();
    let (files, _) = strata_pacs::dicom_files(&src).unwrap();
    let report = client.store_files(&files, None).unwrap();
    assert_eq!(report.stored, CT_SLICES + 2, "{report:?}");
    orthanc
}

pub fn dcm_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    files
}
