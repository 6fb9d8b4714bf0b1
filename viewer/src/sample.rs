//! The demo volume the viewer opens without a path: where it lives and its size (`strata
//! sample` writes the same phantom on request).

use std::path::{Path, PathBuf};

/// Edge of the demo phantom, voxels.
pub const DEMO_SIZE: u64 = 256;

/// The demo volume in the workspace's sample-data folder (or beside the executable when the
/// workspace is not around), generated on first use.
pub fn demo_store_path() -> PathBuf {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("sample-data");
    let base = if workspace.is_dir() {
        workspace
    } else {
        PathBuf::from("sample-data")
    };
    base.join(format!("demo-phantom-{DEMO_SIZE}.strata"))
}
