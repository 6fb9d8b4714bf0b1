//! strata-slices' integration tests, one binary (each file a module).

mod assembly;
mod memory_bricks;
