//! The retrieve's throughput against a running DICOMweb server, the whole series in one request
//! and one request per instance (`ClientOptions::whole_series`): issue 51's "retrieve alone"
//! beside bench/pacs/run.sh, which starts Orthanc and compares with curl. Ignored (a benchmark,
//! not a test: it prints figures and asserts no time); run it with the server's URL, study and
//! series in the environment:
//!
//! ```text
//! STRATA_PACS_BENCH_URL=http://127.0.0.1:PORT/dicom-web STRATA_PACS_BENCH_STUDY=S \
//!   STRATA_PACS_BENCH_SERIES=T cargo test --workspace --test integration retrieve_speed \
//!   -- --ignored --nocapture
//! ```
//!
//! `STRATA_PACS_BENCH_RUNS` (default 3) runs of each, interleaved; `TMPDIR` holds the folders.

use std::time::Instant;

use strata_pacs::{Auth, Client, ClientOptions};

#[test]
#[ignore = "a benchmark: needs a DICOMweb server (STRATA_PACS_BENCH_URL, _STUDY, _SERIES)"]
fn retrieve_speed_whole_series_and_per_instance() {
    let var = |name: &str| std::env::var(name).ok();
    let (Some(url), Some(study), Some(series)) = (
        var("STRATA_PACS_BENCH_URL"),
        var("STRATA_PACS_BENCH_STUDY"),
        var("STRATA_PACS_BENCH_SERIES"),
    ) else {
        panic!("set STRATA_PACS_BENCH_URL, STRATA_PACS_BENCH_STUDY and STRATA_PACS_BENCH_SERIES");
    };
    let runs: usize = var("STRATA_PACS_BENCH_RUNS")
        .and_then(|r| r.parse().ok())
        .unwrap_or(3);
    let mut seconds = [Vec::new(), Vec::new()];
    let mut megabytes = 0.0;
    for run in 1..=runs {
        for (i, whole_series) in [true, false].into_iter().enumerate() {
            let options = ClientOptions {
                whole_series,
                ..ClientOptions::default()
            };
            let client = Client::new(&url, Auth::None, None, options).unwrap();
            let folder = tempfile::tempdir().unwrap();
            let started = Instant::now();
            let report = client
                .retrieve_series(&study, &series, folder.path(), None, None)
                .unwrap_or_else(|e| panic!("{e}"));
            let s = started.elapsed().as_secs_f64();
            megabytes = report.bytes as f64 / 1e6;
            println!(
                "run {run}, whole_series {whole_series}: {} instances, {megabytes:.1} MB, {} request(s), {s:.3} s, {:.0} MB/s",
                report.fetched,
                report.requests,
                megabytes / s
            );
            seconds[i].push(s);
        }
    }
    for (i, name) in ["whole series", "per instance (4 in flight)"]
        .iter()
        .enumerate()
    {
        let mut s = seconds[i].clone();
        s.sort_by(f64::total_cmp);
        let median = s[s.len() / 2];
        println!(
            "median of {runs}, {name}: {median:.3} s, {:.0} MB/s",
            megabytes / median
        );
    }
}
