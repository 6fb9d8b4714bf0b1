//! The crate's integration tests as one test binary: one link instead of one per file
//! (issue 34). Each module is one former test file; a new file in tests/ must be added
//! here (or as a [[test]] of its own in Cargo.toml): tests/tidy.rs checks that none is left out.

mod capacity;
mod client;
mod frames;
mod load;
mod proxy;
mod server;
mod zarr_view;
