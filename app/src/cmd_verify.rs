use std::path::Path;

use anyhow::{bail, Context, Result};
use strata_storage::Store;

pub fn run(path: &Path) -> Result<()> {
    let store =
        Store::open(path).with_context(|| format!("cannot open store {}", path.display()))?;
    let total = store.layout().total_bricks();
    let bar = crate::progress::count_bar(total, "verifying");
    let problems = store
        .verify(|done, _| bar.set_position(done))
        .with_context(|| format!("verifying {}", path.display()))?;
    bar.finish_and_clear();
    if problems.is_empty() {
        println!("{}: all {total} bricks verified", path.display());
        return Ok(());
    }
    for p in &problems {
        eprintln!("{p}");
    }
    bail!(
        "{}: {} problem(s) found in {total} bricks",
        path.display(),
        problems.len()
    )
}
