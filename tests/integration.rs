//! The end-to-end tests as one test binary: one link instead of one per file (issue 34). Each
//! module is one former test file; a new file must be added here: tidy.rs checks that none is
//! left out.

mod hard_cases;
mod real_scans;
mod render_store;
mod store_roundtrip;
mod tidy;
