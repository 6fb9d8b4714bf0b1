//! Test data: the CT phantom tests, benchmarks and demos render (render/src/lib.rs draws the
//! layers).

pub mod phantom;
