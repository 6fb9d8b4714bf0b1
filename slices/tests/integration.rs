//! strata-slices' integration tests, one binary (each file a module).

mod assembly;
