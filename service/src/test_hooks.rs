//! Failure injection for tests of the clients' error handling: a server that corrupts an
//! answer in transit, or accepts brick requests below the root and never answers them.
//!
//! Compiled in only with the `test-hooks` feature, which no release build enables: the tests
//! that need it get it through their dev-dependencies (the `strata` binary that the app's
//! tests run is then built with it). `strata serve` reads the hooks from the environment
//! ([`apply_from_env`]), so its command line carries no test flags.

use crate::server::ServeOptions;

/// `LEVEL/Z/Y/X`: flip a byte of this brick's answers after the server verified the record.
pub const CORRUPT_BRICK_VAR: &str = "STRATA_SERVE_TEST_CORRUPT_BRICK";
/// How many of that brick's answers to corrupt (default 1).
pub const CORRUPT_TIMES_VAR: &str = "STRATA_SERVE_TEST_CORRUPT_TIMES";
/// Any value: accept brick requests below the root and never answer them.
pub const STALL_BELOW_ROOT_VAR: &str = "STRATA_SERVE_TEST_STALL_BELOW_ROOT";

/// A hook variable that does not parse.
#[derive(Debug, thiserror::Error)]
#[error("{var}: {problem}")]
pub struct TestHookError {
    pub var: &'static str,
    pub problem: String,
}

/// Sets the hooks the environment names on `options`. Without the `test-hooks` feature it
/// does nothing: a release server has no hooks to set.
pub fn apply_from_env(options: &mut ServeOptions) -> Result<(), TestHookError> {
    #[cfg(feature = "test-hooks")]
    {
        if let Ok(text) = std::env::var(CORRUPT_BRICK_VAR) {
            let id = parse_brick(&text).ok_or_else(|| TestHookError {
                var: CORRUPT_BRICK_VAR,
                problem: format!("a brick is LEVEL/Z/Y/X, not '{text}'"),
            })?;
            let times = match std::env::var(CORRUPT_TIMES_VAR) {
                Ok(n) => n.parse::<u32>().map_err(|_| TestHookError {
                    var: CORRUPT_TIMES_VAR,
                    problem: format!("a count of answers, not '{n}'"),
                })?,
                Err(_) => 1,
            };
            options.corrupt_answers = Some((id, times));
        }
        if std::env::var_os(STALL_BELOW_ROOT_VAR).is_some() {
            options.stall_below_root = true;
        }
    }
    #[cfg(not(feature = "test-hooks"))]
    let _ = options;
    Ok(())
}

#[cfg(feature = "test-hooks")]
fn parse_brick(text: &str) -> Option<strata_types::BrickId> {
    let parts: Vec<u32> = text
        .split('/')
        .map(|p| p.parse::<u32>().ok())
        .collect::<Option<_>>()?;
    let [level, z, y, x] = parts[..] else {
        return None;
    };
    Some(strata_types::BrickId::new(
        u8::try_from(level).ok()?,
        [x, y, z],
    ))
}

#[cfg(all(test, feature = "test-hooks"))]
mod tests {
    use super::*;

    #[test]
    fn a_brick_is_level_then_z_y_x() {
        let id = parse_brick("1/2/3/4").expect("parses");
        assert_eq!(id, strata_types::BrickId::new(1, [4, 3, 2]));
        for bad in ["1/2/3", "1/2/3/4/5", "300/0/0/0", "a/0/0/0", ""] {
            assert!(parse_brick(bad).is_none(), "{bad}");
        }
    }
}
