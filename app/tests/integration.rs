//! The crate's integration tests as one test binary: one link instead of one per file
//! (issue 34). Each module is one former test file; a new file in tests/ must be added
//! here (or as a [[test]] of its own in Cargo.toml): tests/tidy.rs checks that none is left out.

mod cli;
mod common;
mod omezarr_foreign;
mod omezarr_s3;
mod orbit;
mod pacs;
mod reliability;
mod remote;
mod render_adaptive;
mod render_progressive;
mod render_traversal;
mod seg;
mod viewer_window;
