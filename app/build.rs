//! With the `web` feature, the browser viewer's files are embedded from web/dist/: say how to
//! make them when they are missing, instead of include_bytes!'s bare "file not found".

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    if std::env::var_os("CARGO_FEATURE_WEB").is_none() {
        return;
    }
    let dist = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("web")
        .join("dist");
    for name in [
        "index.html",
        "strata.css",
        "strata_boot.js",
        "strata_web.js",
        "strata_web_bg.wasm",
    ] {
        let path = dist.join(name);
        println!("cargo:rerun-if-changed={}", path.display());
        if !path.is_file() {
            panic!(
                "the `web` feature embeds the browser viewer, and {} is missing: run \
                 `cargo run -p xtask -- web` first (it needs `rustup target add wasm32-unknown-unknown`)",
                path.display()
            );
        }
    }
}
