//! Checks of command-line values that clap's types cannot express: bounded budgets, output paths
//! that can be written (the render flags' ranges are strata-headless's, shared with Python). A bad value is refused with the flag's name
//! and its allowed range, before any work starts, never rendered into a black image.

use std::path::Path;

use anyhow::{bail, Result};

/// Largest memory budget accepted for any `--*-mib` flag: 16 TiB, beyond any machine Strata runs
/// on; a larger number is a typo (and would overflow when converted to bytes).
pub const MAX_BUDGET_MIB: u64 = 16 << 20;

/// clap value parser for a budget in MiB: 1 ..= [`MAX_BUDGET_MIB`].
pub fn budget_mib(text: &str) -> Result<u64> {
    let Ok(mib) = text.trim().parse::<u64>() else {
        bail!("'{text}' is not a whole number of MiB");
    };
    if !(1..=MAX_BUDGET_MIB).contains(&mib) {
        bail!("{mib} MiB is outside 1..={MAX_BUDGET_MIB} MiB (16 TiB)");
    }
    Ok(mib)
}

/// An output image path: not a folder, and a PNG (the only format written).
pub fn check_png_output(flag: &str, path: &Path) -> Result<()> {
    if path.is_dir() {
        bail!(
            "--{flag} {} is a folder: give a file name such as {}",
            path.display(),
            path.join("strata.png").display()
        );
    }
    let is_png = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !is_png {
        bail!(
            "--{flag} {}: images are written as PNG, so the name must end in .png",
            path.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn budgets_are_bounded_and_named() {
        assert_eq!(budget_mib("512").unwrap(), 512);
        assert!(budget_mib("0").is_err());
        let e = budget_mib("17592186044416").unwrap_err().to_string();
        assert!(e.contains("16 TiB"), "{e}");
        assert!(budget_mib("lots")
            .unwrap_err()
            .to_string()
            .contains("'lots'"));
    }

    #[test]
    fn non_finite_and_out_of_range_values_name_the_flag() {
        // The render flags are checked by strata-headless (for `strata render` and strata.render
        // alike); the words must still name the CLI's flags.
        use strata_headless::{check_finite, check_range, STEP_RANGE};
        let e = check_finite("azimuth", f64::NAN).unwrap_err().to_string();
        assert!(e.contains("--azimuth") && e.contains("NaN"), "{e}");
        let e = check_range("step", 1e9, STEP_RANGE)
            .unwrap_err()
            .to_string();
        assert!(e.contains("--step") && e.contains("64"), "{e}");
        assert!(check_range("step", 1e-9, STEP_RANGE).is_err());
        assert!(check_range("step", 0.5, STEP_RANGE).is_ok());
    }

    #[test]
    fn output_must_be_a_png_file() {
        let dir = tempfile::tempdir().unwrap();
        let e = check_png_output("out", dir.path()).unwrap_err().to_string();
        assert!(e.contains("is a folder"), "{e}");
        assert!(check_png_output("out", &dir.path().join("a.jpg")).is_err());
        assert!(check_png_output("out", &dir.path().join("a.PNG")).is_ok());
    }
}
