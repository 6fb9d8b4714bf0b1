//! The crate's integration tests as one test binary: one link instead of one per file
//! (issue 34). Each module is one former test file; a new file in tests/ must be added
//! here (or as a [[test]] of its own in Cargo.toml): tests/tidy.rs checks that none is left out.

mod budget_settles;
mod common;
mod cut_payloads;
mod memory_cycles;
mod octree_streaming;
mod slow_storage;
mod soak;
mod sparse_streaming;
mod still_settles;
mod streaming;
