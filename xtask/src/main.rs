//! `cargo run -p xtask -- web`: builds the browser viewer into `web/dist/` (see lib.rs).

use anyhow::{bail, Result};

fn main() -> Result<()> {
    let task = std::env::args().nth(1).unwrap_or_default();
    match task.as_str() {
        "web" => {
            let dist = xtask::build_web(&xtask::workspace_root())?;
            println!("web viewer written to {}", dist.display());
            println!(
                "serve it with `cargo build --release -p strata-app --features web` and `strata serve STORE`"
            );
            Ok(())
        }
        _ => bail!("usage: cargo run -p xtask -- web   (builds the browser viewer into web/dist/)"),
    }
}
