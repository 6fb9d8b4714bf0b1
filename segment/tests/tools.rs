//! The editing tools through the crate's public API, against independent models: brute-force
//! CPU models of the brush, scipy for region growing, numpy for statistics.

mod tools {
    pub mod bench;
    pub mod brush;
    #[allow(dead_code)] // shared by files that each use a part
    pub mod common;
    pub mod grow;
    pub mod morphology;
    pub mod stats;
}
