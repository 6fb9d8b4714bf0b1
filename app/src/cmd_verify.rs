use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use strata_storage::store::VerifyDepth;
use strata_viewer::volume_location::{open, Opened};

/// Requests in flight while verifying a remote store (each a blocking read on its thread).
const REMOTE_VERIFY_THREADS: usize = 32;

#[derive(clap::Args)]
pub struct VerifyArgs {
    /// A store directory, or http://HOST:PORT/v1/stores/NAME served by `strata serve`.
    store: String,
    /// Bearer token for a server that requires one.
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Also decode every record of a format-3 store and compare its value range with the
    /// skeleton's (CPU-bound). Without it a format-3 store's packs are streamed and each record
    /// checked against its checksum and the index, at the disk's speed. Stores of formats 1-2
    /// and remote stores are always decoded.
    #[arg(long)]
    decode: bool,
}

pub fn run(args: &VerifyArgs) -> Result<()> {
    let location = args.store.as_str();
    let token_file: Option<&Path> = args.token_file.as_deref();
    let depth = if args.decode {
        VerifyDepth::Decode
    } else {
        VerifyDepth::Checksums
    };
    let opened = open(
        location,
        token_file,
        strata_storage::store::DEFAULT_READ_CACHE_BYTES,
    )?;
    let source = opened.source();
    let total = source.layout().total_bricks();
    let bar = crate::progress::count_bar(total, "verifying");
    // What the check reads: every node of the octree, or in a store whose constant bricks are
    // implied by its sparse skeleton only the stored records (the store's verify says which).
    let checked = std::cell::Cell::new(total);
    let mut verdict = None;
    let problems = match &opened {
        // The store's own check also counts the records against the octree.
        Opened::Local(store) => {
            let report = store
                .verify_report_to(depth, |done, of| {
                    if of != checked.get() {
                        checked.set(of);
                        bar.set_length(of);
                    }
                    bar.set_position(done)
                })
                .with_context(|| format!("verifying {location}"))?;
            verdict = report.verdict;
            report.problems
        }
        Opened::Remote(_) | Opened::OmeZarr(_) => {
            strata_source::verify_source(source.as_ref(), REMOTE_VERIFY_THREADS, &|done, _| {
                bar.set_position(done)
            })
        }
    };
    bar.finish_and_clear();
    let checked = checked.get();
    if problems.is_empty() {
        if checked < total {
            println!(
                "{location}: all {checked} nodes of the sparse skeleton verified; the other {} \
                 of the octree's {total} nodes are constant, implied by a stored ancestor",
                total - checked
            );
        } else {
            println!("{location}: all {checked} bricks verified");
        }
        return Ok(());
    }
    for p in &problems {
        eprintln!("{p}");
    }
    if let Some(verdict) = verdict {
        eprintln!("{verdict}");
    }
    bail!(
        "{location}: {} problem(s) found in {} bricks",
        problems.len(),
        checked
    )
}
