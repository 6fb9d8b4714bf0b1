//! The benches' end-to-end tests as one test binary (issue 34): each module is one former test
//! file; a new file in tests/ must be added here: tests/tidy.rs checks that none is left out.

mod bench_accuracy;
mod bench_timecritical;
mod bench_transitions;
mod common;
