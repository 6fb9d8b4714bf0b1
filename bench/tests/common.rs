//! What the benches' end-to-end tests share: the `strata-bench` binary and the phantom store
//! that `strata sample` writes.

use std::path::Path;
use std::process::{Command, Output};

use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;

pub fn strata(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_strata-bench"))
        .args(args)
        .output()
        .expect("strata-bench runs")
}

/// The deterministic CT phantom of edge `size` as a store at `out` (`strata sample --size N`).
pub fn sample_store(out: &Path, size: u64) {
    Phantom::cube(size)
        .write_store(out, &ImportOptions::default())
        .unwrap_or_else(|e| panic!("writing the phantom store {}: {e}", out.display()));
}
