//! `strata store list|prune`: the stores in the viewer's data folder (or another), their size,
//! format, codec, source and state, and freeing the space of those that can go.

use std::io::IsTerminal;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use strata_storage::inventory::{list_stores, remove_store, StoreEntry, StoreState};

#[derive(Subcommand)]
pub enum StoreCommand {
    /// Convert a format-2 store to format 3 (pack files, opened without writing), atomically:
    /// the old store stays until the new one verifies.
    Upgrade {
        /// The store folder.
        store: PathBuf,
    },
    /// Rewrite a format-3 store without the superseded versions of its brick records,
    /// atomically: the compacted copy is verified before it replaces the store.
    Compact {
        /// The store folder.
        store: PathBuf,
    },
    /// List the stores of the data folder: size, format, codec, source, complete or not.
    List(FolderArg),
    /// Remove incomplete, damaged, orphaned (source gone) and old-format (source still there)
    /// stores; never one in use. Shows what it would remove unless given --yes.
    Prune {
        #[command(flatten)]
        folder: FolderArg,
        /// Only show what would be removed.
        #[arg(long)]
        dry_run: bool,
        /// Remove without asking (needed when not run in a terminal).
        #[arg(long)]
        yes: bool,
    },
}

#[derive(Args)]
pub struct FolderArg {
    /// Folder holding the stores (default: the viewer's data folder).
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
}

impl FolderArg {
    fn folder(&self) -> PathBuf {
        self.data_dir
            .clone()
            .unwrap_or_else(strata_viewer::jobs::data_folder)
    }
}

pub fn run(cmd: StoreCommand) -> Result<()> {
    match cmd {
        StoreCommand::List(folder) => list(&folder.folder()),
        StoreCommand::Upgrade { store } => {
            let report = strata_storage::store::upgrade_store(&store)
                .with_context(|| format!("upgrade of {} failed", store.display()))?;
            println!(
                "{}: now format 3 ({} brick records verified)",
                store.display(),
                report.records_read
            );
            Ok(())
        }
        StoreCommand::Compact { store } => {
            let report = strata_storage::store::compact_store(&store)
                .with_context(|| format!("compaction of {} failed", store.display()))?;
            println!(
                "{}: {} brick records kept, packs {} -> {}",
                store.display(),
                report.records,
                mb(report.bytes_before),
                mb(report.bytes_after)
            );
            Ok(())
        }
        StoreCommand::Prune {
            folder,
            dry_run,
            yes,
        } => prune(&folder.folder(), dry_run, yes),
    }
}

fn mb(bytes: u64) -> String {
    format!("{:.1} MB", bytes as f64 / 1e6)
}

/// One line: state, format and codec, source.
fn describe(entry: &StoreEntry) -> String {
    let format = entry
        .marker_format_version
        .map_or_else(|| "format ?".to_string(), |v| format!("format {v}"));
    match &entry.state {
        StoreState::Complete {
            format_version,
            codec,
            inputs,
        } => {
            let source = match inputs.as_slice() {
                [] => "(generated)".to_string(),
                [one] => one.clone(),
                [first, rest @ ..] => format!("{first} and {} more", rest.len()),
            };
            format!(
                "complete    format {format_version}, {} codec, source {source}",
                codec.name()
            )
        }
        StoreState::Incomplete => format!("incomplete  {format} (an import that did not finish)"),
        StoreState::InUse(holder) => format!("in use      {format}, {holder}"),
        StoreState::Unsupported(why) => format!("unsupported {format}: {why}"),
        StoreState::Damaged(why) => format!("damaged     {format}: {why}"),
    }
}

fn list(folder: &std::path::Path) -> Result<()> {
    let stores =
        list_stores(folder).with_context(|| format!("cannot list {}", folder.display()))?;
    println!("stores in {}", folder.display());
    if stores.is_empty() {
        println!("  (none)");
        return Ok(());
    }
    for s in &stores {
        let name = s.path.file_name().map_or_else(
            || s.path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        println!("  {name}  {:>10}  {}", mb(s.size_bytes), describe(s));
    }
    let total: u64 = stores.iter().map(|s| s.size_bytes).sum();
    let prunable: u64 = stores
        .iter()
        .filter(|s| s.prune_reason().is_some())
        .map(|s| s.size_bytes)
        .sum();
    println!(
        "{} stores, {} in all; `strata store prune` would free {}",
        stores.len(),
        mb(total),
        mb(prunable)
    );
    Ok(())
}

fn prune(folder: &std::path::Path, dry_run: bool, yes: bool) -> Result<()> {
    let stores =
        list_stores(folder).with_context(|| format!("cannot list {}", folder.display()))?;
    let doomed: Vec<_> = stores
        .iter()
        .filter_map(|s| s.prune_reason().map(|r| (s, r)))
        .collect();
    for s in stores
        .iter()
        .filter(|s| matches!(s.state, StoreState::InUse(_)))
    {
        println!("keeping {} ({})", s.path.display(), describe(s));
    }
    if doomed.is_empty() {
        println!("nothing to prune in {}", folder.display());
        return Ok(());
    }
    let total: u64 = doomed.iter().map(|(s, _)| s.size_bytes).sum();
    for (s, reason) in &doomed {
        println!(
            "{} {} ({}, {})",
            if dry_run { "would remove" } else { "remove" },
            s.path.display(),
            mb(s.size_bytes),
            reason.describe()
        );
    }
    if dry_run {
        println!("dry run: {} would be freed", mb(total));
        return Ok(());
    }
    if !yes {
        if !std::io::stdin().is_terminal() {
            anyhow::bail!("nothing removed: pass --yes to remove these stores (or --dry-run to only list them)");
        }
        eprint!(
            "remove these {} stores ({})? [y/N] ",
            doomed.len(),
            mb(total)
        );
        let mut answer = String::new();
        std::io::stdin().read_line(&mut answer)?;
        if !matches!(answer.trim(), "y" | "Y" | "yes") {
            println!("nothing removed");
            return Ok(());
        }
    }
    let mut freed = 0;
    let mut failures = 0;
    for (s, _) in &doomed {
        // Taken under the store's own lock: a store opened since the listing is refused here.
        match remove_store(&s.path) {
            Ok(bytes) => freed += bytes,
            Err(e) => {
                failures += 1;
                eprintln!("not removed: {e}");
            }
        }
    }
    println!("freed {}", mb(freed));
    anyhow::ensure!(failures == 0, "{failures} store(s) could not be removed");
    Ok(())
}
