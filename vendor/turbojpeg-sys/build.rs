//! Builds the bundled libjpeg-turbo 3.1.0 (the TurboJPEG library, static) with the `cc` crate, as
//! its CMakeLists.txt would with ENABLE_STATIC, WITH_TURBOJPEG, the default arithmetic coding
//! options and WITH_SIMD off (the SIMD code needs nasm). libjpeg-turbo 3 compiles part of its
//! sources once per data precision (8, 12 and 16 bits, BITS_IN_JSAMPLE); each precision is a
//! separate cc::Build with its own object directory so that the objects do not overwrite each
//! other, and all objects go into one archive.

use std::env;
use std::fs;
use std::path::{Path, PathBuf};

const VERSION: &str = "3.1.0";
const VERSION_NUMBER: &str = "3001000";
const COPYRIGHT_YEAR: &str = "1991-2024";
/// libjpeg API/ABI emulated: v6b, the CMake default (WITH_JPEG7 and WITH_JPEG8 off).
const JPEG_LIB_VERSION: &str = "62";

/// Compiled at 8, 12 and 16 bits (CMakeLists.txt: JPEG16_SOURCES).
const SOURCES_16: &[&str] = &[
    "jcapistd", "jccolor", "jcdiffct", "jclossls", "jcmainct", "jcprepct", "jcsample", "jdapistd",
    "jdcolor", "jddiffct", "jdlossls", "jdmainct", "jdpostct", "jdsample", "jutils",
];
/// Compiled at 8 and 12 bits (JPEG12_SOURCES less JPEG16_SOURCES): the DCT-based parts.
const SOURCES_12: &[&str] = &[
    "jccoefct", "jcdctmgr", "jdcoefct", "jddctmgr", "jdmerge", "jfdctfst", "jfdctint", "jidctflt",
    "jidctfst", "jidctint", "jidctred", "jquant1", "jquant2",
];
/// Compiled once (JPEG_SOURCES less JPEG12_SOURCES, with arithmetic coding, plus the TurboJPEG
/// API's own files).
const SOURCES_8: &[&str] = &[
    "jcapimin",
    "jchuff",
    "jcicc",
    "jcinit",
    "jclhuff",
    "jcmarker",
    "jcmaster",
    "jcomapi",
    "jcparam",
    "jcphuff",
    "jctrans",
    "jdapimin",
    "jdatadst",
    "jdatasrc",
    "jdhuff",
    "jdicc",
    "jdinput",
    "jdlhuff",
    "jdmarker",
    "jdmaster",
    "jdphuff",
    "jdtrans",
    "jerror",
    "jfdctflt",
    "jmemmgr",
    "jmemnobs",
    "jpeg_nbits",
    "jaricom",
    "jcarith",
    "jdarith",
    "turbojpeg",
    "transupp",
    "jdatadst-tj",
    "jdatasrc-tj",
    "rdbmp",
    "rdppm",
    "wrbmp",
    "wrppm",
];
/// The TurboJPEG API's PPM reader and writer at 12 and 16 bits.
const SOURCES_TJ_HIGH: &[&str] = &["rdppm", "wrppm"];

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=libjpeg-turbo");
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("set by cargo"));
    let src = manifest.join("libjpeg-turbo/src");
    let include = out.join("include");
    fs::create_dir_all(&include).expect("creating OUT_DIR/include");
    write_config_headers(&src, &include);

    let base = || {
        let mut build = cc::Build::new();
        build.include(&include).include(&src).warnings(false);
        build
    };
    let mut objects = Vec::new();
    for (bits, names) in [
        ("12", [SOURCES_16, SOURCES_12, SOURCES_TJ_HIGH].concat()),
        ("16", [SOURCES_16, SOURCES_TJ_HIGH].concat()),
    ] {
        let dir = out.join(format!("obj{bits}"));
        fs::create_dir_all(&dir).expect("creating an object directory");
        let mut build = base();
        build
            .out_dir(&dir)
            .define("BITS_IN_JSAMPLE", bits)
            .define("PPM_SUPPORTED", None);
        for name in names {
            build.file(src.join(format!("{name}.c")));
        }
        objects.extend(build.compile_intermediates());
    }
    let mut build = base();
    build
        .define("BMP_SUPPORTED", None)
        .define("PPM_SUPPORTED", None);
    for name in [SOURCES_16, SOURCES_12, SOURCES_8].concat() {
        build.file(src.join(format!("{name}.c")));
    }
    build.objects(objects).compile("turbojpeg");

    println!("cargo:include={}", src.display());
    // The pregenerated FFI of the published crate (no bindgen).
    fs::copy(manifest.join("bindings.rs"), out.join("bindings.rs")).expect("copying bindings.rs");
    println!("cargo:rerun-if-changed=bindings.rs");
}

/// jconfig.h, jconfigint.h and jversion.h from their CMake templates, with the values
/// CMakeLists.txt would choose for gcc or clang on this target.
fn write_config_headers(src: &Path, include: &Path) {
    let pointer_bytes = env::var("CARGO_CFG_TARGET_POINTER_WIDTH")
        .ok()
        .and_then(|bits| bits.parse::<u32>().ok())
        .map_or(8, |bits| bits / 8)
        .to_string();
    let msvc = env::var("CARGO_CFG_TARGET_ENV").as_deref() == Ok("msvc");
    let values: &[(&str, &str)] = &[
        ("JPEG_LIB_VERSION", JPEG_LIB_VERSION),
        ("VERSION", VERSION),
        ("LIBJPEG_TURBO_VERSION_NUMBER", VERSION_NUMBER),
        ("BUILD", "strata-cc"),
        (
            "HIDDEN",
            if msvc {
                ""
            } else {
                "__attribute__((visibility(\"hidden\")))"
            },
        ),
        (
            "INLINE",
            if msvc {
                "__forceinline"
            } else {
                "__inline__ __attribute__((always_inline))"
            },
        ),
        (
            "THREAD_LOCAL",
            if msvc {
                "__declspec(thread)"
            } else {
                "__thread"
            },
        ),
        ("CMAKE_PROJECT_NAME", "libjpeg-turbo"),
        ("SIZE_T", &pointer_bytes),
        ("COPYRIGHT_YEAR", COPYRIGHT_YEAR),
    ];
    let defined: &[&str] = if msvc {
        &[
            "C_ARITH_CODING_SUPPORTED",
            "D_ARITH_CODING_SUPPORTED",
            "HAVE_INTRIN_H",
        ]
    } else {
        &[
            "C_ARITH_CODING_SUPPORTED",
            "D_ARITH_CODING_SUPPORTED",
            "HAVE_BUILTIN_CTZL",
        ]
    };
    for name in ["jconfig.h", "jconfigint.h", "jversion.h"] {
        let template =
            fs::read_to_string(src.join(format!("{name}.in"))).expect("reading a template");
        let mut text = String::with_capacity(template.len());
        for line in template.lines() {
            let mut line = line.to_string();
            if let Some(rest) = line.strip_prefix("#cmakedefine ") {
                let symbol = rest.split_whitespace().next().unwrap_or_default();
                line = if defined.contains(&symbol) {
                    format!("#define {rest}")
                } else {
                    format!("/* #undef {symbol} */")
                };
            }
            for (key, value) in values {
                line = line.replace(&format!("@{key}@"), value);
            }
            assert!(!line.contains('@'), "unsubstituted: {line}");
            text.push_str(&line);
            text.push('\n');
        }
        fs::write(include.join(name), text).expect("writing a configured header");
    }
}
