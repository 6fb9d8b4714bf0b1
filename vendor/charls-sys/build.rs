//! Compiles the bundled CharLS 2.4.5 sources with the `cc` crate (upstream builds them with
//! cmake). The definitions are those CharLS's own CMakeLists.txt sets for a static library.

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=charls");
    let sources = [
        "charls_jpegls_decoder.cpp",
        "charls_jpegls_encoder.cpp",
        "jpeg_stream_reader.cpp",
        "jpeg_stream_writer.cpp",
        "jpegls.cpp",
        "jpegls_error.cpp",
        "validate_spiff_header.cpp",
        "version.cpp",
    ];
    let mut build = cc::Build::new();
    build
        .cpp(true)
        .std("c++14")
        .include("charls/include")
        .define("CHARLS_STATIC", None)
        .define("CHARLS_LIBRARY_BUILD", None)
        .warnings(false);
    for source in sources {
        build.file(format!("charls/src/{source}"));
    }
    build.compile("charls");
    println!(
        "cargo:include={}",
        std::path::Path::new(&std::env::var("CARGO_MANIFEST_DIR").unwrap())
            .join("charls/include")
            .display()
    );
}
