//! The record a store's lock holder leaves for others to read (see [`crate::lock`]); a module
//! of its own because errors carry it too.

use serde::{Deserialize, Serialize};

/// What the holder does with the store.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LockPurpose {
    /// An import is writing it.
    Import,
    /// `strata serve` streams it to clients.
    Serve,
    /// A viewer, render, info or verify reads it.
    Read,
}

impl std::fmt::Display for LockPurpose {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            LockPurpose::Import => "an import writing it",
            LockPurpose::Serve => "strata serve",
            LockPurpose::Read => "a strata process reading it",
        })
    }
}

/// The record a holder writes into the lock file.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LockHolder {
    pub pid: u32,
    pub purpose: LockPurpose,
    /// Where `strata serve` streams this store (`http://127.0.0.1:PORT/v1/stores/NAME`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub url: Option<String>,
}

impl std::fmt::Display for LockHolder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (&self.url, self.purpose) {
            (Some(url), _) => write!(
                f,
                "served by strata serve (pid {}) at {url}: open that URL instead",
                self.pid
            ),
            (None, LockPurpose::Import) => write!(
                f,
                "in use by pid {} (an import is writing it); wait for it to finish",
                self.pid
            ),
            (None, purpose) => write!(
                f,
                "in use by pid {} ({purpose}); sled lets one process open a store at a time: \
                 close that process, or serve the store with `strata serve` and open its URL",
                self.pid
            ),
        }
    }
}
