//! The crate's integration tests as one test binary: one link instead of one per file
//! (issue 34). Each module is one former test file; a new file in tests/ must be added
//! here (or as a [[test]] of its own in Cargo.toml): tests/tidy.rs checks that none is left out.

mod common;
mod dicom_pacs;
mod dicom_seg;
mod frames;
mod mgh;
mod readers;
mod sparse_skeleton;
mod store_damage;
mod store_formats;
mod store_v3;
