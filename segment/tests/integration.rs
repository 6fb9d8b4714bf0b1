//! strata-segment through its public API: one test binary (see TESTING.md).

mod common;
mod peers;
