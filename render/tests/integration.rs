//! The crate's integration tests as one test binary: one link instead of one per file
//! (issue 34). Each module is one former test file; a new file in tests/ must be added
//! here (or as a [[test]] of its own in Cargo.toml): tests/tidy.rs checks that none is left out.

mod adaptive;
mod cinematic;
mod common;
mod features;
mod gpu_vs_reference;
mod node_extent;
mod octree_traversal;
mod overlay;
mod progressive;
mod shadows;
mod slot_independence;
mod smooth_transitions;
mod time_critical;
