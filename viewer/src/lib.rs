//! `strata-viewer`: the viewer as a library (issue 47). For now what the desktop viewer, the
//! `strata` command line and the benchmarks (`strata-bench`) share: writing frames and orbit
//! movies, the command line's size and transfer-function options, the flythrough's camera path,
//! the demo volume, where a volume comes from (store, `strata serve`, OME-Zarr) and how an error
//! is told. Not for diagnostic use.

pub mod camera_path;
pub mod error_report;
pub mod export;
pub mod sample;
pub mod volume_location;
