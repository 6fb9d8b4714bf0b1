//! strata-pacs through its public API: one test binary (TESTING.md), a module per topic.

mod hostile;
mod retrieve_speed;
