//! Tidy checks in the spirit of rust-analyzer's: the architecture's invariants as tests that
//! read the repository itself, so a change that breaks one fails CI instead of a review.
//!
//! - Dependency lists: render depends on neither storage nor loader (nor on sled, or anything
//!   else that does I/O on the store); storage and the shared types know nothing of GPUs; the
//!   shared types crate stays small.
//! - Module graphs: no module cycle inside any crate (a module and its own ancestors excepted:
//!   a parent declares its children and a child may use what its parent defines).
//! - render's folders: a module uses only its own layer and lower ones (`RENDER_LAYERS`, the
//!   graph render/src/lib.rs draws), and no .wgsl file declares by hand a constant Rust also
//!   defines (the shader's shared constants are generated).
//! - Errors: no function of a library crate returns `Result<_, String>` outside test code
//!   (`STRING_ERRORS_ALLOWED` is empty; an entry naming no such function fails).
//! - Build tools: Rust and a C/C++ compiler are enough to build; nothing in `Cargo.lock` needs
//!   cmake or nasm (read from the lock file: `cargo tree` would need the network for all
//!   targets).
//!
//! `cargo test -p strata-e2e --test integration tidy:: -- --nocapture` prints each crate's module graph.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ sits inside the workspace")
        .to_path_buf()
}

/// Names of every dependency a manifest lists under `[dependencies]` or a
/// `[target.'…'.dependencies]` table (not dev- or build-dependencies). Enough TOML for our
/// manifests: one `name = …` or `name.workspace = true` per line.
fn normal_dependencies(manifest: &Path) -> BTreeSet<String> {
    let text =
        fs::read_to_string(manifest).unwrap_or_else(|e| panic!("{}: {e}", manifest.display()));
    let mut in_deps = false;
    let mut deps = BTreeSet::new();
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('[') {
            let table = line.trim_matches(|c| c == '[' || c == ']');
            in_deps = table == "dependencies"
                || (table.starts_with("target.") && table.ends_with(".dependencies"));
            continue;
        }
        if !in_deps || line.is_empty() || line.starts_with('#') {
            continue;
        }
        let key = line.split(['=', '.']).next().unwrap_or("").trim();
        if !key.is_empty() {
            deps.insert(key.to_string());
        }
    }
    deps
}

/// Every workspace crate a crate reaches through normal dependencies, itself excluded.
fn workspace_closure(dir: &str) -> BTreeSet<String> {
    let crate_dirs: BTreeMap<&str, &str> = [
        ("strata-types", "types"),
        ("strata-storage", "storage"),
        ("strata-source", "source"),
        ("strata-service", "service"),
        ("strata-omezarr", "omezarr"),
        ("strata-loader", "loader"),
        ("strata-headless", "headless"),
        ("strata-render", "render"),
        ("strata-viewer-ui", "viewer-ui"),
        ("strata-web", "web"),
        ("strata-bench", "bench"),
        ("strata-viewer", "viewer"),
        ("strata-app", "app"),
    ]
    .into_iter()
    .collect();
    let mut seen = BTreeSet::new();
    let mut stack = vec![dir.to_string()];
    while let Some(d) = stack.pop() {
        for dep in normal_dependencies(&repo_root().join(&d).join("Cargo.toml")) {
            if let Some(dep_dir) = crate_dirs.get(dep.as_str()) {
                if seen.insert(dep.clone()) {
                    stack.push(dep_dir.to_string());
                }
            }
        }
    }
    seen
}

fn assert_none_of(crate_dir: &str, direct: &BTreeSet<String>, forbidden: &[&str], why: &str) {
    let found: Vec<_> = forbidden.iter().filter(|f| direct.contains(**f)).collect();
    assert!(
        found.is_empty(),
        "{crate_dir}/Cargo.toml depends on {found:?}: {why} (ARCHITECTURE.md, Invariants)"
    );
}

#[test]
fn render_depends_on_neither_storage_nor_loader() {
    let closure = workspace_closure("render");
    for forbidden in ["strata-storage", "strata-loader", "strata-app"] {
        assert!(
            !closure.contains(forbidden),
            "strata-render reaches {forbidden} (through {closure:?}): render takes bricks as \
             &[u16] and geometry from strata-types, never from the store"
        );
    }
    let direct = normal_dependencies(&repo_root().join("render/Cargo.toml"));
    assert_none_of(
        "render",
        &direct,
        &[
            "sled",
            "lz4_flex",
            "zstd",
            "memmap2",
            "dicom-object",
            "eframe",
            "egui",
        ],
        "render knows nothing of the store's format or the UI",
    );
}

#[test]
fn storage_and_types_know_nothing_of_gpus() {
    // The volume-source seam and the data service (server and client) sit below the loader
    // too: serving a store needs no GPU.
    for dir in ["storage", "types", "source", "service", "omezarr"] {
        let closure = workspace_closure(dir);
        for forbidden in ["strata-render", "strata-loader", "strata-app"] {
            assert!(
                !closure.contains(forbidden),
                "{dir} reaches {forbidden}: storage and the shared types have no GPU side"
            );
        }
        let direct = normal_dependencies(&repo_root().join(dir).join("Cargo.toml"));
        assert_none_of(
            dir,
            &direct,
            &["wgpu", "naga", "eframe", "egui", "pollster"],
            "no GPU or UI dependency below the loader",
        );
    }
}

/// Issue 47: the command line, the viewer and the browser viewer are separate crates. Neither
/// `strata` nor the desktop viewer links the browser crate (what both need of it, the link
/// format, is in strata-viewer-ui), nothing ships the benchmarks, and the viewer, a library,
/// reaches neither the command line nor the benchmarks.
#[test]
fn the_app_the_viewer_and_the_benchmarks_stay_apart() {
    for (dir, forbidden, why) in [
        (
            "app",
            &["strata-web", "strata-bench"][..],
            "the strata binary links neither the browser viewer's crate (the page is embedded \
             from web/dist/ by build.rs) nor the benchmarks",
        ),
        (
            "viewer",
            &["strata-web", "strata-app", "strata-bench"][..],
            "the viewer library reaches neither the browser crate, the command line nor the \
             benchmarks",
        ),
        (
            "headless",
            &[
                "strata-viewer",
                "strata-viewer-ui",
                "strata-app",
                "strata-web",
            ][..],
            "the headless frame (`strata render`, `strata.render`) needs no window and no egui",
        ),
        (
            "python",
            &[
                "strata-viewer",
                "strata-viewer-ui",
                "strata-app",
                "strata-web",
            ][..],
            "the Python wheel links the headless frame, never the viewer (egui, winit)",
        ),
    ] {
        let closure = workspace_closure(dir);
        let found: Vec<_> = forbidden.iter().filter(|f| closure.contains(**f)).collect();
        assert!(
            found.is_empty(),
            "{dir} reaches {found:?} (through {closure:?}): {why}"
        );
    }
    let direct = normal_dependencies(&repo_root().join("app/Cargo.toml"));
    assert_none_of(
        "app",
        &direct,
        &["plotters"],
        "plots are for the benchmarks (strata-bench), not the shipping binary",
    );
    for dir in ["headless", "python"] {
        let direct = normal_dependencies(&repo_root().join(dir).join("Cargo.toml"));
        assert_none_of(
            dir,
            &direct,
            &["eframe", "egui", "winit"],
            "a headless frame opens no window",
        );
    }
}

/// Lines of Rust code (comments dropped) in `dir` that name a command-line module (`cmd_…`).
fn lines_naming_a_command_module(dir: &Path) -> Vec<String> {
    let mut files = Vec::new();
    rust_files(dir, &mut files);
    let mut found = Vec::new();
    for file in files {
        let text = fs::read_to_string(&file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        for (i, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            if code.contains("cmd_") {
                found.push(format!("{}:{}: {}", file.display(), i + 1, line.trim()));
            }
        }
    }
    found
}

/// No viewer module uses a command module: what both need (PNG and movie writing, sizes, the
/// transfer function by name, volume locations, PACS connections) lives in strata-viewer, and
/// the command line calls it, never the other way round.
#[test]
fn no_viewer_module_imports_a_command_module() {
    let found = lines_naming_a_command_module(&repo_root().join("viewer/src"));
    assert!(
        found.is_empty(),
        "viewer code names a command module (move what it needs into strata-viewer): {found:#?}"
    );
}

#[test]
fn the_command_module_check_can_fail() {
    let dir = tempfile::tempdir().unwrap();
    fs::write(
        dir.path().join("a.rs"),
        "// crate::cmd_render in a comment is fine\nuse crate::cmd_render::write_png;\n",
    )
    .unwrap();
    let found = lines_naming_a_command_module(dir.path());
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(found[0].contains(":2:"), "{found:?}");
}

#[test]
fn shared_types_stay_small() {
    let direct = normal_dependencies(&repo_root().join("types/Cargo.toml"));
    let allowed: BTreeSet<String> = ["glam", "serde", "thiserror"]
        .into_iter()
        .map(String::from)
        .collect();
    let extra: Vec<_> = direct.difference(&allowed).collect();
    assert!(
        extra.is_empty(),
        "types/Cargo.toml gained {extra:?}: every crate builds on strata-types, so each \
         dependency there is paid everywhere; put it in the crate that needs it"
    );
}

/// The workspace's library and app crates whose sources the checks below read.
const CRATE_DIRS: [&str; 14] = [
    "types",
    "storage",
    "source",
    "service",
    "omezarr",
    "loader",
    "render",
    "slices",
    "viewer-ui",
    "viewer",
    "app",
    "bench",
    "pacs",
    "segment",
];

/// Module path of a source file: `src/lib.rs` → "", `src/bench/accuracy.rs` → "bench::accuracy",
/// `src/viewer/mod.rs` → "viewer".
fn module_of(src: &Path, file: &Path) -> String {
    let rel = file
        .strip_prefix(src)
        .expect("file under src")
        .with_extension("");
    let parts: Vec<String> = rel
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    let parts: Vec<&str> = match parts.as_slice() {
        [only] if only == "lib" || only == "main" => vec![],
        [rest @ .., last] if last == "mod" => rest.iter().map(String::as_str).collect(),
        all => all.iter().map(String::as_str).collect(),
    };
    parts.join("::")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// Paths a file names from `crate::` or `super::`, as module-path segment lists (grouped
/// imports `crate::{a::X, b}` yield `a::X` and `b`). Comments are skipped.
fn referenced_paths(module: &str, text: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let code: String = text
        .lines()
        .map(|l| match l.find("//") {
            Some(i) => &l[..i],
            None => l,
        })
        .collect::<Vec<_>>()
        .join("\n");
    let bytes = code.as_bytes();
    let ident_end = |mut i: usize| {
        while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
            i += 1;
        }
        i
    };
    let parent: Vec<String> = {
        let mut p: Vec<String> = module
            .split("::")
            .filter(|s| !s.is_empty())
            .map(String::from)
            .collect();
        p.pop();
        p
    };
    for (root, base) in [("crate::", Vec::new()), ("super::", parent)] {
        let mut from = 0;
        while let Some(pos) = code[from..].find(root) {
            let start = from + pos;
            from = start + root.len();
            if start > 0 && (bytes[start - 1].is_ascii_alphanumeric() || bytes[start - 1] == b'_') {
                continue;
            }
            // One path, or a `{…}` group of paths one level deep.
            let mut heads = Vec::new();
            if bytes.get(from) == Some(&b'{') {
                let mut depth = 0;
                let mut i = from;
                let mut item_start = from + 1;
                while i < bytes.len() {
                    match bytes[i] {
                        b'{' => depth += 1,
                        b'}' => {
                            depth -= 1;
                            if depth == 0 {
                                heads.push(item_start);
                                break;
                            }
                        }
                        b',' if depth == 1 => {
                            heads.push(item_start);
                            item_start = i + 1;
                        }
                        _ => {}
                    }
                    i += 1;
                }
            } else {
                heads.push(from);
            }
            for head in heads {
                let mut segments = base.clone();
                let mut i = head;
                while i < bytes.len() && bytes[i].is_ascii_whitespace() {
                    i += 1;
                }
                loop {
                    let end = ident_end(i);
                    if end == i {
                        break;
                    }
                    segments.push(code[i..end].to_string());
                    if code[end..].starts_with("::") {
                        i = end + 2;
                    } else {
                        break;
                    }
                }
                if segments.len() > base.len() {
                    out.push(segments);
                }
            }
        }
    }
    out
}

/// Module → modules it uses, for one crate's `src/`.
fn module_graph(crate_dir: &str) -> BTreeMap<String, BTreeSet<String>> {
    let src = repo_root().join(crate_dir).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let modules: BTreeSet<String> = files.iter().map(|f| module_of(&src, f)).collect();
    let is_ancestor = |a: &str, b: &str| a.is_empty() || b.starts_with(&format!("{a}::"));
    let mut graph = BTreeMap::new();
    for file in &files {
        let module = module_of(&src, file);
        let text = fs::read_to_string(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        let mut uses = BTreeSet::new();
        for path in referenced_paths(&module, &text) {
            // The longest prefix that is a module of this crate.
            let target = (1..=path.len())
                .rev()
                .map(|n| path[..n].join("::"))
                .find(|p| modules.contains(p));
            if let Some(target) = target {
                if target != module
                    && !is_ancestor(&target, &module)
                    && !is_ancestor(&module, &target)
                {
                    uses.insert(target);
                }
            }
        }
        graph.insert(module, uses);
    }
    graph
}

/// A cycle in the graph, if any, as the modules along it.
fn find_cycle(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        node: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(node.to_string(), 1);
        stack.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            match state.get(next.as_str()).copied().unwrap_or(0) {
                1 => {
                    let from = stack.iter().position(|s| s == next).unwrap_or(0);
                    let mut cycle = stack[from..].to_vec();
                    cycle.push(next.clone());
                    return Some(cycle);
                }
                0 => {
                    if let Some(c) = visit(next, graph, state, stack) {
                        return Some(c);
                    }
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(node.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for node in graph.keys() {
        if state.get(node.as_str()).copied().unwrap_or(0) == 0 {
            let mut stack = Vec::new();
            if let Some(c) = visit(node, graph, &mut state, &mut stack) {
                return Some(c);
            }
        }
    }
    None
}

#[test]
fn no_module_cycles_in_any_crate() {
    let mut cycles = Vec::new();
    for crate_dir in CRATE_DIRS {
        let graph = module_graph(crate_dir);
        println!("{crate_dir}:");
        for (module, uses) in &graph {
            let name = if module.is_empty() { "(root)" } else { module };
            let uses: Vec<&str> = uses.iter().map(String::as_str).collect();
            println!("  {name} -> {}", uses.join(", "));
        }
        if let Some(cycle) = find_cycle(&graph) {
            cycles.push(format!("{crate_dir}: {}", cycle.join(" -> ")));
        }
    }
    assert!(
        cycles.is_empty(),
        "module cycles ({}); move what both sides need into a module of its own",
        cycles.join("; ")
    );
}

#[test]
fn the_cycle_finder_finds_cycles_and_reads_grouped_imports() {
    // The checker itself must be able to fail.
    let paths = referenced_paths(
        "bench::transitions",
        "use super::accuracy::{self, median};\nuse crate::{cmd_render::parse_size, bench};\n// crate::ignored\n",
    );
    let strings = |p: &[&str]| p.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    assert!(
        paths.contains(&strings(&["bench", "accuracy"])),
        "{paths:?}"
    );
    assert!(
        paths.contains(&strings(&["cmd_render", "parse_size"])),
        "{paths:?}"
    );
    assert!(paths.contains(&strings(&["bench"])), "{paths:?}");
    assert!(
        !paths.iter().any(|p| p.contains(&"ignored".to_string())),
        "{paths:?}"
    );
    let mut graph = BTreeMap::new();
    graph.insert("a".to_string(), BTreeSet::from(["b".to_string()]));
    graph.insert("b".to_string(), BTreeSet::from(["c".to_string()]));
    graph.insert("c".to_string(), BTreeSet::from(["a".to_string()]));
    assert_eq!(find_cycle(&graph).map(|c| c.len()), Some(4));
    graph.insert("c".to_string(), BTreeSet::new());
    assert_eq!(find_cycle(&graph), None);
}

/// render/src's folders, lowest layer first, as render/src/lib.rs draws its graph: the shared
/// error, the model and CPU twins, GPU resources, the f64 reference, the passes, the
/// controllers, the test data. A module may use its own layer and the ones before it.
const RENDER_LAYERS: [&str; 7] = [
    "error",
    "model",
    "gpu",
    "reference",
    "passes",
    "control",
    "testdata",
];

/// Position of `module`'s top folder in `layers` (None for the crate root).
fn layer_of(module: &str, layers: &[&str]) -> Option<usize> {
    let top = module.split("::").next().unwrap_or("");
    layers.iter().position(|layer| *layer == top)
}

/// Every `module → used` edge of `graph` that goes to a higher layer, and every module (the
/// root excepted) outside all layers.
fn layering_violations(graph: &BTreeMap<String, BTreeSet<String>>, layers: &[&str]) -> Vec<String> {
    let mut found = Vec::new();
    for (module, uses) in graph {
        if module.is_empty() {
            continue;
        }
        let Some(from) = layer_of(module, layers) else {
            found.push(format!("{module} is in no layer"));
            continue;
        };
        for used in uses {
            if layer_of(used, layers).is_some_and(|to| to > from) {
                found.push(format!(
                    "{module} ({}) uses {used} ({})",
                    layers[from],
                    layers[layer_of(used, layers).unwrap_or(from)]
                ));
            }
        }
    }
    found
}

#[test]
fn render_folders_follow_the_layered_graph() {
    let found = layering_violations(&module_graph("render"), &RENDER_LAYERS);
    assert!(
        found.is_empty(),
        "render modules against the layers {RENDER_LAYERS:?} (render/src/lib.rs): {found:#?}; \
         move what a lower layer needs down, or the module up"
    );
}

#[test]
fn the_layering_check_can_fail() {
    let graph = |edges: &[(&str, &str)]| {
        let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for (from, to) in edges {
            graph
                .entry(from.to_string())
                .or_default()
                .insert(to.to_string());
            graph.entry(to.to_string()).or_default();
        }
        graph
    };
    let layers = ["model", "gpu", "passes"];
    assert!(layering_violations(
        &graph(&[
            ("passes::raycast", "gpu::shaders"),
            ("gpu::shaders", "model::layout")
        ]),
        &layers
    )
    .is_empty());
    let found = layering_violations(
        &graph(&[("gpu::shaders", "passes::adaptive::gpu")]),
        &layers,
    );
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].starts_with("gpu::shaders (gpu) uses passes::adaptive::gpu"),
        "{found:?}"
    );
    let found = layering_violations(&graph(&[("stray", "model::layout")]), &layers);
    assert_eq!(found, ["stray is in no layer"]);
}

/// Names of the `const` items of Rust source (any visibility; `const fn` is no item).
fn rust_const_names(text: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for line in text.lines() {
        let mut rest = line.trim_start();
        for visibility in ["pub(crate) ", "pub(super) ", "pub "] {
            rest = rest.strip_prefix(visibility).unwrap_or(rest);
        }
        if let Some(item) = rest.strip_prefix("const ") {
            let name: String = item
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if !name.is_empty() && name != "fn" {
                names.insert(name);
            }
        }
    }
    names
}

/// The WGSL `const` declarations in `wgsl` (file name, text) whose name is also a Rust
/// constant: copies by hand of what the generated prelude should declare.
fn hand_copied_constants(wgsl: &[(String, String)], rust_consts: &BTreeSet<String>) -> Vec<String> {
    let mut found = Vec::new();
    for (file, text) in wgsl {
        for (i, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            let Some(declaration) = code.trim_start().strip_prefix("const ") else {
                continue;
            };
            let name: String = declaration
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if rust_consts.contains(&name) {
                found.push(format!("{file}:{}: {name}", i + 1));
            }
        }
    }
    found
}

/// Every file under `dir` whose name ends with `extension`, recursively.
fn files_with_extension(dir: &Path, extension: &str, out: &mut Vec<PathBuf>) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            files_with_extension(&path, extension, out);
        } else if path.extension().is_some_and(|e| e == extension) {
            out.push(path);
        }
    }
}

/// ARCHITECTURE.md's invariant: a constant the shader shares with Rust is generated from the
/// Rust one (render's `shaders::prelude_constants`, a pass's own list such as the adaptive
/// pass's `shader_constants`), never declared again in a .wgsl file.
#[test]
fn no_wgsl_constant_shared_with_rust_is_written_by_hand() {
    let src = repo_root().join("render/src");
    let mut rust = Vec::new();
    rust_files(&src, &mut rust);
    let rust_consts: BTreeSet<String> = rust
        .iter()
        .flat_map(|f| {
            rust_const_names(
                &fs::read_to_string(f).unwrap_or_else(|e| panic!("{}: {e}", f.display())),
            )
        })
        .collect();
    let mut wgsl_files = Vec::new();
    files_with_extension(&src, "wgsl", &mut wgsl_files);
    assert!(!wgsl_files.is_empty(), "no .wgsl under {}", src.display());
    let wgsl: Vec<(String, String)> = wgsl_files
        .iter()
        .map(|f| {
            let text = fs::read_to_string(f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            (f.display().to_string(), text)
        })
        .collect();
    let found = hand_copied_constants(&wgsl, &rust_consts);
    assert!(
        found.is_empty(),
        "WGSL constants that copy a Rust constant by hand: {found:#?}; add them to the generated \
         prelude (render's shaders::prelude_constants, or the pass's own list) and delete the \
         WGSL declaration"
    );
}

#[test]
fn the_hand_copied_constant_check_can_fail() {
    let rust = rust_const_names(
        "pub(crate) const PYRAMID_CAP: u32 = 460;\nconst fn pyramid() {}\n    pub const COUNTERS: u32 = 16;\n",
    );
    assert_eq!(
        rust,
        BTreeSet::from(["PYRAMID_CAP".to_string(), "COUNTERS".to_string()])
    );
    let wgsl = vec![(
        "adaptive.wgsl".to_string(),
        "// const COUNTERS in a comment is fine\nconst LOCAL_ONLY: f32 = 1.0;\nconst PYRAMID_CAP: u32 = 460u;\n"
            .to_string(),
    )];
    assert_eq!(
        hand_copied_constants(&wgsl, &rust),
        ["adaptive.wgsl:3: PYRAMID_CAP"]
    );
}

/// The `path = "…"` of every `[[test]]` a manifest declares.
fn declared_test_paths(manifest: &Path) -> Vec<String> {
    let text =
        fs::read_to_string(manifest).unwrap_or_else(|e| panic!("{}: {e}", manifest.display()));
    let mut in_test = false;
    let mut paths = Vec::new();
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('[') {
            in_test = line == "[[test]]";
            continue;
        }
        if in_test {
            if let Some(value) = line.strip_prefix("path") {
                let value = value
                    .trim_start_matches([' ', '='])
                    .trim()
                    .trim_matches('"');
                paths.push(value.to_string());
            }
        }
    }
    paths
}

/// The files a test root includes with `mod name;` (a sibling `name.rs` or `name/mod.rs`).
fn declared_modules(root: &Path) -> BTreeSet<String> {
    let text = fs::read_to_string(root).unwrap_or_else(|e| panic!("{}: {e}", root.display()));
    text.lines()
        .filter_map(|l| l.trim().strip_prefix("mod ")?.strip_suffix(';'))
        .map(|m| m.trim().to_string())
        .collect()
}

/// The `.rs` files of a test folder that no test target compiles: with `autotests = false`
/// (one integration binary per crate) a new file is silently left out unless it is a
/// `[[test]]` or a module of one.
fn uncompiled_test_files(crate_dir: &Path, tests_dir: &Path, lib: Option<&str>) -> Vec<String> {
    let mut compiled = BTreeSet::new();
    for path in declared_test_paths(&crate_dir.join("Cargo.toml")) {
        let root = crate_dir.join(&path);
        compiled.insert(root.file_name().unwrap().to_string_lossy().into_owned());
        for module in declared_modules(&root) {
            compiled.insert(format!("{module}.rs"));
        }
    }
    let mut missing = Vec::new();
    let Ok(entries) = fs::read_dir(tests_dir) else {
        return missing;
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.ends_with(".rs") && Some(name.as_str()) != lib && !compiled.contains(&name) {
            missing.push(format!("{}", tests_dir.join(&name).display()));
        }
    }
    missing
}

#[test]
fn every_test_file_is_compiled() {
    let root = repo_root();
    let mut missing = Vec::new();
    for crate_dir in CRATE_DIRS {
        let dir = root.join(crate_dir);
        missing.extend(uncompiled_test_files(&dir, &dir.join("tests"), None));
    }
    // strata-e2e: the crate is tests/ itself, its library is common.rs.
    let e2e = root.join("tests");
    missing.extend(uncompiled_test_files(&e2e, &e2e, Some("common.rs")));
    assert!(
        missing.is_empty(),
        "test files no test target compiles: {missing:?}; add `mod <file>;` to the crate's \
         tests/integration.rs (or a [[test]] of its own in Cargo.toml)"
    );
}

/// Unit-test folders a crate compiles from `tests/` by path (`#[path = "../tests/ui/mod.rs"]`
/// in `src/lib.rs`: the viewer's UI tests, which need private access but stay out of `src/`),
/// and the `.rs` files in them that their `mod.rs` does not declare.
fn uncompiled_path_test_files(crate_dir: &Path) -> Vec<String> {
    let Ok(lib) = fs::read_to_string(crate_dir.join("src/lib.rs")) else {
        return Vec::new();
    };
    let mut missing = Vec::new();
    for line in lib.lines() {
        let Some(root) = line
            .trim()
            .strip_prefix("#[path = \"../tests/")
            .and_then(|rest| rest.strip_suffix("/mod.rs\"]"))
        else {
            continue;
        };
        let folder = crate_dir.join("tests").join(root);
        let declared = declared_modules(&folder.join("mod.rs"));
        let Ok(entries) = fs::read_dir(&folder) else {
            missing.push(format!(
                "{} (the folder src/lib.rs names)",
                folder.display()
            ));
            continue;
        };
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            let module = name.strip_suffix(".rs").unwrap_or("");
            if !module.is_empty() && module != "mod" && !declared.contains(module) {
                missing.push(format!("{}", folder.join(&name).display()));
            }
        }
    }
    missing
}

#[test]
fn every_unit_test_file_under_tests_is_compiled() {
    let root = repo_root();
    let missing: Vec<String> = CRATE_DIRS
        .iter()
        .flat_map(|dir| uncompiled_path_test_files(&root.join(dir)))
        .collect();
    assert!(
        missing.is_empty(),
        "unit-test files under a crate's tests/ that no `mod` declares: {missing:?}; add \
         `mod <file>;` to that folder's mod.rs"
    );
    // The viewer's UI tests live there, none under src/ (issue 54 item 6).
    let viewer_src = root.join("viewer/src");
    let mut files = Vec::new();
    rust_files(&viewer_src, &mut files);
    let in_src: Vec<_> = files
        .iter()
        .filter(|f| {
            f.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("ui_tests"))
        })
        .collect();
    assert!(
        in_src.is_empty(),
        "UI tests under viewer/src: {in_src:?}; they belong in viewer/tests/ui/"
    );
}

#[test]
fn the_path_test_file_check_can_fail() {
    let dir = tempfile::tempdir().unwrap();
    let ui = dir.path().join("tests/ui");
    fs::create_dir_all(&ui).unwrap();
    fs::create_dir(dir.path().join("src")).unwrap();
    fs::write(
        dir.path().join("src/lib.rs"),
        "#[cfg(test)]\n#[path = \"../tests/ui/mod.rs\"]\nmod ui_tests;\n",
    )
    .unwrap();
    fs::write(ui.join("mod.rs"), "mod harness;\nmod views;\n").unwrap();
    fs::write(ui.join("harness.rs"), "").unwrap();
    fs::write(ui.join("views.rs"), "").unwrap();
    assert!(uncompiled_path_test_files(dir.path()).is_empty());
    fs::write(ui.join("forgotten.rs"), "").unwrap();
    let missing = uncompiled_path_test_files(dir.path());
    assert_eq!(missing.len(), 1, "{missing:?}");
    assert!(missing[0].ends_with("forgotten.rs"), "{missing:?}");
}

#[test]
fn the_test_file_check_can_fail() {
    let dir = tempfile::tempdir().unwrap();
    let tests = dir.path().join("tests");
    fs::create_dir(&tests).unwrap();
    fs::write(
        dir.path().join("Cargo.toml"),
        "[package]\nname = \"x\"\nautotests = false\n\n[[test]]\nname = \"integration\"\npath = \"tests/integration.rs\"\n",
    )
    .unwrap();
    fs::write(tests.join("integration.rs"), "mod listed;\n").unwrap();
    fs::write(tests.join("listed.rs"), "").unwrap();
    assert!(uncompiled_test_files(dir.path(), &tests, None).is_empty());
    fs::write(tests.join("forgotten.rs"), "").unwrap();
    let missing = uncompiled_test_files(dir.path(), &tests, None);
    assert_eq!(missing.len(), 1, "{missing:?}");
    assert!(missing[0].ends_with("forgotten.rs"), "{missing:?}");
}

/// The Debian packages of a list file under `.ci/` (one per line, `#` comments).
fn package_list(name: &str) -> Vec<String> {
    let path = repo_root().join(".ci").join(name);
    fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .map(|l| l.split('#').next().unwrap_or("").trim())
        .filter(|l| !l.is_empty())
        .map(str::to_string)
        .collect()
}

#[test]
fn the_readme_prerequisites_are_the_package_list_ci_installs() {
    // One source of truth: .ci/packages lists what the README's two commands need on a fresh
    // Debian machine; .ci/run installs exactly that list (plus .ci/test-packages for the tests'
    // own tools) and the README's prerequisites show it as one apt line.
    let packages = package_list("packages");
    let line = format!("apt-get install -y {}", packages.join(" "));
    let readme = fs::read_to_string(repo_root().join("README.md")).unwrap();
    let prerequisites = readme
        .split("## Prerequisites")
        .nth(1)
        .expect("README.md has a Prerequisites section")
        .split("\n## ")
        .next()
        .unwrap();
    assert!(
        prerequisites.contains(&line),
        "README.md's prerequisites must show exactly `{line}` (from .ci/packages)"
    );
    assert_eq!(
        prerequisites.matches("apt-get install").count(),
        1,
        "one apt line in the README's prerequisites"
    );
    let ci = fs::read_to_string(repo_root().join(".ci/run")).unwrap();
    for list in ["packages", "test-packages"] {
        assert!(
            ci.contains(&format!(".ci/{list}")),
            ".ci/run must install from .ci/{list}"
        );
    }
    for not_needed in ["cmake", "nasm"] {
        assert!(
            !packages
                .iter()
                .chain(&package_list("test-packages"))
                .any(|p| p == not_needed),
            "{not_needed} is not needed to build (issue 34): keep it out of .ci's package lists"
        );
    }
}

/// Crates whose build runs a tool beyond Rust and a C/C++ compiler: `cmake` (the crate that
/// drives the cmake program, a build-dependency of every cmake-built -sys crate) and `nasm-rs`
/// (drives nasm).
const NEEDS_EXTRA_BUILD_TOOL: &[&str] = &["cmake", "nasm-rs"];

/// The packages of a `Cargo.lock` (format version 3 or 4): name -> (has a registry or git
/// source, names of its dependencies). Enough of TOML for what cargo writes: one `[[package]]`
/// table each, `name = "…"`, `source = …`, and `dependencies = [` with one `"name[ version[
/// (source)]]"` per line. A name locked at two versions keeps the union of their dependencies.
fn lock_packages(lock: &str) -> BTreeMap<String, (bool, BTreeSet<String>)> {
    let mut packages: BTreeMap<String, (bool, BTreeSet<String>)> = BTreeMap::new();
    let mut name: Option<String> = None;
    let mut in_deps = false;
    let unquote = |s: &str| s.trim().trim_end_matches(',').trim_matches('"').to_string();
    for line in lock.lines() {
        let line = line.trim();
        if line == "[[package]]" || line.starts_with('[') && !line.starts_with("[\"") {
            name = None;
            in_deps = false;
            continue;
        }
        if in_deps {
            if line.starts_with(']') {
                in_deps = false;
            } else if let Some(n) = &name {
                let dep = unquote(line);
                let dep = dep.split(' ').next().unwrap_or_default().to_string();
                packages.entry(n.clone()).or_default().1.insert(dep);
            }
            continue;
        }
        if let Some(v) = line.strip_prefix("name = ") {
            let n = unquote(v);
            packages.entry(n.clone()).or_default();
            name = Some(n);
        } else if let (Some(_), Some(n)) = (line.strip_prefix("source = "), &name) {
            packages.entry(n.clone()).or_default().0 = true;
        } else if line.starts_with("dependencies = [") {
            in_deps = !line.ends_with(']');
        }
    }
    packages
}

/// For each forbidden package reachable from a package without a source (the workspace's own
/// crates and its patched copies), one chain from such a package to it, shortest first found.
fn chains_to(lock: &str, forbidden: &[&str]) -> Vec<Vec<String>> {
    let packages = lock_packages(lock);
    let mut parent: BTreeMap<String, Option<String>> = BTreeMap::new();
    let mut queue = std::collections::VecDeque::new();
    for (name, (sourced, _)) in &packages {
        if !sourced {
            parent.insert(name.clone(), None);
            queue.push_back(name.clone());
        }
    }
    while let Some(name) = queue.pop_front() {
        for dep in packages.get(&name).map(|p| &p.1).into_iter().flatten() {
            if !parent.contains_key(dep) {
                parent.insert(dep.clone(), Some(name.clone()));
                queue.push_back(dep.clone());
            }
        }
    }
    let mut chains = Vec::new();
    for f in forbidden {
        if parent.contains_key(*f) {
            let mut chain = vec![f.to_string()];
            while let Some(Some(p)) = parent.get(chain.last().expect("never empty")) {
                chain.push(p.clone());
            }
            chain.reverse();
            chains.push(chain);
        }
    }
    chains
}

#[test]
fn rust_and_a_c_compiler_are_enough_to_build() {
    let path = repo_root().join("Cargo.lock");
    let lock = fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        lock_packages(&lock).contains_key("strata-storage"),
        "{} lists no strata-storage: the lock parser no longer reads it",
        path.display()
    );
    let chains: Vec<String> = chains_to(&lock, NEEDS_EXTRA_BUILD_TOOL)
        .iter()
        .map(|c| c.join(" -> "))
        .collect();
    assert!(
        chains.is_empty(),
        "the build graph needs a tool beyond Rust and a C/C++ compiler: {}. Pick a pure-Rust or \
         cc-built alternative, or patch the -sys crate to build through cc (as vendor/ does for \
         charls-sys and turbojpeg-sys)",
        chains.join("; ")
    );
}

#[test]
fn the_lock_reader_finds_a_chain_to_cmake() {
    // The checker itself must be able to fail: a cmake-built -sys crate two steps down.
    let lock = r#"version = 4

[[package]]
name = "strata-storage"
version = "0.1.0"
dependencies = [
 "dicom-pixeldata",
 "serde",
]

[[package]]
name = "dicom-pixeldata"
version = "0.10.1"
source = "registry+https://github.com/rust-lang/crates.io-index"
dependencies = [
 "charls-sys 2.4.6+charls.2.4.5 (registry+https://github.com/rust-lang/crates.io-index)",
]

[[package]]
name = "charls-sys"
version = "2.4.6+charls.2.4.5"
source = "registry+https://github.com/rust-lang/crates.io-index"
dependencies = [
 "cmake",
]

[[package]]
name = "cmake"
version = "0.1.58"
source = "registry+https://github.com/rust-lang/crates.io-index"
dependencies = ["cc"]

[[package]]
name = "serde"
version = "1.0.0"
source = "registry+https://github.com/rust-lang/crates.io-index"

[[package]]
name = "nasm-rs"
version = "0.3.0"
source = "registry+https://github.com/rust-lang/crates.io-index"
"#;
    assert_eq!(
        chains_to(lock, NEEDS_EXTRA_BUILD_TOOL),
        vec![vec![
            "strata-storage".to_string(),
            "dicom-pixeldata".to_string(),
            "charls-sys".to_string(),
            "cmake".to_string()
        ]],
        "nasm-rs is locked but unreachable, so only cmake's chain counts"
    );
    let without = lock.replace(" \"cmake\",\n", "");
    assert_eq!(
        chains_to(&without, NEEDS_EXTRA_BUILD_TOOL),
        Vec::<Vec<String>>::new()
    );
}

/// Lines of a manifest that turn a test-only feature on outside `[dev-dependencies]` and
/// outside that feature's own definition: a release build would then carry the hooks.
fn test_features_outside_dev_dependencies(manifest: &str) -> Vec<String> {
    const TEST_ONLY: [&str; 2] = ["test-hooks", "test-probe"];
    let mut table = String::new();
    let mut found = Vec::new();
    for line in manifest.lines() {
        let trimmed = line.trim();
        if trimmed.starts_with('[') {
            table = trimmed.trim_matches(|c| c == '[' || c == ']').to_string();
            continue;
        }
        if trimmed.starts_with('#') || !TEST_ONLY.iter().any(|f| trimmed.contains(f)) {
            continue;
        }
        let dev = table == "dev-dependencies" || table.ends_with(".dev-dependencies");
        let own_definition =
            table == "features" && TEST_ONLY.iter().any(|f| trimmed == format!("{f} = []"));
        if !dev && !own_definition {
            found.push(format!("[{table}] {trimmed}"));
        }
    }
    found
}

/// `pub fn …_for_tests` items of a source file that are compiled into every build (no
/// `cfg` naming the tests or the test hooks among the attributes above them).
fn ungated_test_functions(source: &str) -> Vec<String> {
    let lines: Vec<&str> = source.lines().collect();
    let mut found = Vec::new();
    for (i, line) in lines.iter().enumerate() {
        let trimmed = line.trim();
        let Some(rest) = trimmed.strip_prefix("pub fn ") else {
            continue;
        };
        let name = rest.split(['(', '<']).next().unwrap_or("");
        if !name.ends_with("_for_tests") {
            continue;
        }
        let gated = lines[..i]
            .iter()
            .rev()
            .map(|l| l.trim())
            .take_while(|l| l.starts_with("#[") || l.starts_with("///"))
            .any(|l| l.starts_with("#[cfg(") && l.contains("test"));
        if !gated {
            found.push(format!("line {}: {name}", i + 1));
        }
    }
    found
}

#[test]
fn test_hooks_are_compiled_only_into_test_builds() {
    let root = repo_root();
    let mut problems = Vec::new();
    for entry in fs::read_dir(&root).expect("the workspace folder") {
        let dir = entry.expect("a workspace entry").path();
        let manifest = dir.join("Cargo.toml");
        let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if !manifest.is_file() || name == "vendor" {
            continue;
        }
        let text = fs::read_to_string(&manifest).expect("a manifest");
        for line in test_features_outside_dev_dependencies(&text) {
            problems.push(format!("{}: {line}", manifest.display()));
        }
        let mut files = Vec::new();
        rust_files(&dir.join("src"), &mut files);
        for file in files {
            let source = fs::read_to_string(&file).expect("a source file");
            for item in ungated_test_functions(&source) {
                problems.push(format!("{}: {item}", file.display()));
            }
        }
    }
    assert!(
        problems.is_empty(),
        "test hooks reach release builds (gate them with #[cfg(any(test, feature = \"test-hooks\"))] \
         and enable the feature only under [dev-dependencies]):\n{}",
        problems.join("\n")
    );
}

#[test]
fn the_test_hook_checks_can_fail() {
    let manifest = "[features]\ntest-hooks = []\nweb = [\"strata-service/test-hooks\"]\n\n\
                    [dependencies]\nstrata-storage = { path = \"../storage\", features = [\"test-hooks\"] }\n\n\
                    [dev-dependencies]\nstrata-service = { path = \"../service\", features = [\"test-hooks\"] }\n";
    assert_eq!(
        test_features_outside_dev_dependencies(manifest),
        vec![
            "[features] web = [\"strata-service/test-hooks\"]".to_string(),
            "[dependencies] strata-storage = { path = \"../storage\", features = [\"test-hooks\"] }"
                .to_string()
        ]
    );
    let source =
        "/// Gated.\n#[cfg(any(test, feature = \"test-hooks\"))]\npub fn a_for_tests() {}\n\n\
                  /// Not gated.\n#[doc(hidden)]\npub fn b_for_tests(x: u8) {}\npub fn c() {}\n";
    assert_eq!(
        ungated_test_functions(source),
        vec!["line 7: b_for_tests".to_string()]
    );
}

/// Functions of library crates that may still return `Result<_, String>`, by file and name, each
/// with why it may. Empty since issue 54 item 4 converted the last ones to typed errors; an
/// entry that no longer names such a function fails the check, so the list cannot rot.
const STRING_ERRORS_ALLOWED: &[(&str, &str, &str)] = &[];

/// `fn` items of a source file, outside test code, whose return type is `Result<_, String>`
/// (also spelled `std::result::Result`), as `(line, name)`. Test code is a `#[cfg(…test…)]`
/// item (a `mod tests { … }` or a gated function), skipped by brace depth; `Option<Result<_,
/// String>>` is a shown outcome, not a function's error, and is not reported.
fn functions_returning_string_errors(source: &str) -> Vec<(usize, String)> {
    let lines: Vec<&str> = source.lines().collect();
    let mut found = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let trimmed = lines[i].trim();
        if trimmed.starts_with("#[cfg(")
            && trimmed.contains("test")
            && !trimmed.contains("not(test")
        {
            // Skip the gated item: up to its first `{` and then to the matching `}` (or to
            // a `;` that ends it first, e.g. `mod ui_tests;`).
            let mut depth = 0i64;
            let mut opened = false;
            i += 1;
            while i < lines.len() {
                let code = lines[i].split("//").next().unwrap_or("");
                for c in code.chars() {
                    match c {
                        '{' => {
                            depth += 1;
                            opened = true;
                        }
                        '}' => depth -= 1,
                        _ => {}
                    }
                }
                let ends_unopened = !opened && code.trim_end().ends_with(';');
                i += 1;
                if ends_unopened || (opened && depth <= 0) {
                    break;
                }
            }
            continue;
        }
        let is_fn = trimmed.starts_with("fn ")
            || (trimmed.contains(" fn ") && !trimmed.starts_with("//") && !trimmed.contains('|'));
        if !is_fn {
            i += 1;
            continue;
        }
        // The signature: from `fn` to the `{` or `;` that ends it.
        let start = i;
        let mut signature = String::new();
        while i < lines.len() {
            let code = lines[i].split("//").next().unwrap_or("");
            signature.push_str(code);
            signature.push(' ');
            i += 1;
            if code.contains('{') || code.trim_end().ends_with(';') {
                break;
            }
        }
        if let Some(name) = string_error_function(&signature) {
            found.push((start + 1, name));
        }
    }
    found
}

/// The function's name when `signature` (`… fn name<…>(…) -> Ret {`) returns `Result<_, String>`.
fn string_error_function(signature: &str) -> Option<String> {
    // `->` inside generics or parameters (`F: Fn() -> T`) must not count as a closing `>`.
    let text = signature.replace("->", "→");
    let after_fn = &text[text.find("fn ")? + 3..];
    let name: String = after_fn
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    let mut rest = after_fn[name.len()..].trim_start();
    if rest.starts_with('<') {
        rest = &rest[balanced_end(rest, '<', '>')?..];
    }
    let rest = rest.trim_start();
    if !rest.starts_with('(') {
        return None;
    }
    let rest = rest[balanced_end(rest, '(', ')')?..].trim_start();
    let returned = rest.strip_prefix('→')?;
    let returned = returned
        .split(['{', ';'])
        .next()
        .unwrap_or("")
        .split(" where ")
        .next()
        .unwrap_or("");
    let returned: String = returned.chars().filter(|c| !c.is_whitespace()).collect();
    let inner = ["Result<", "std::result::Result<", "core::result::Result<"]
        .iter()
        .find_map(|prefix| returned.strip_prefix(prefix))?
        .strip_suffix('>')?
        .trim_end_matches(',');
    let mut depth = 0i32;
    let mut last_argument_start = 0;
    for (at, c) in inner.char_indices() {
        match c {
            '<' | '(' | '[' => depth += 1,
            '>' | ')' | ']' => depth -= 1,
            ',' if depth == 0 => last_argument_start = at + 1,
            _ => {}
        }
    }
    let error = &inner[last_argument_start..];
    (last_argument_start > 0 && (error == "String" || error == "std::string::String"))
        .then_some(name)
}

/// Byte offset just past the bracket that closes the one `text` starts with.
fn balanced_end(text: &str, open: char, close: char) -> Option<usize> {
    let mut depth = 0;
    for (at, c) in text.char_indices() {
        if c == open {
            depth += 1;
        } else if c == close {
            depth -= 1;
            if depth == 0 {
                return Some(at + c.len_utf8());
            }
        }
    }
    None
}

#[test]
fn library_functions_return_typed_errors_not_strings() {
    let root = repo_root();
    let mut found = Vec::new();
    let mut seen_allowed = BTreeSet::new();
    for entry in fs::read_dir(&root).expect("the workspace folder") {
        let dir = entry.expect("a workspace entry").path();
        // A library crate: a `src/lib.rs` and no binary of its own (app and bench use anyhow).
        if !dir.join("src/lib.rs").is_file() || dir.join("src/main.rs").is_file() {
            continue;
        }
        let mut files = Vec::new();
        rust_files(&dir.join("src"), &mut files);
        for file in files {
            let relative = file
                .strip_prefix(&root)
                .expect("file under the workspace")
                .to_string_lossy()
                .replace('\\', "/");
            let source = fs::read_to_string(&file).expect("a source file");
            for (line, name) in functions_returning_string_errors(&source) {
                let allowed = STRING_ERRORS_ALLOWED
                    .iter()
                    .any(|(path, function, _)| *path == relative && *function == name);
                if allowed {
                    seen_allowed.insert((relative.clone(), name));
                } else {
                    found.push(format!("{relative}:{line}: fn {name}"));
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "library functions returning Result<_, String> (give them a thiserror enum whose Display \
         keeps the wording, CODE_STYLE.md \"Errors\"):\n{}",
        found.join("\n")
    );
    let stale: Vec<String> = STRING_ERRORS_ALLOWED
        .iter()
        .filter(|(path, function, _)| {
            !seen_allowed.contains(&(path.to_string(), function.to_string()))
        })
        .map(|(path, function, _)| format!("{path} fn {function}"))
        .collect();
    assert!(
        stale.is_empty(),
        "STRING_ERRORS_ALLOWED lists functions that no longer return Result<_, String> \
         (remove them from the list):\n{}",
        stale.join("\n")
    );
}

#[test]
fn the_string_error_check_can_fail() {
    let source = "pub fn plain(x: u8) -> Result<u8, String> {\n    Ok(x)\n}\n\
                  fn typed(x: u8) -> Result<u8, ParseError> {\n    Ok(x)\n}\n\
                  pub(crate) async fn spread<F: Fn(u8) -> Result<u8, String>>(\n    f: F,\n) \
                  -> std::result::Result<\n    Vec<u8>,\n    String,\n> {\n    todo()\n}\n\
                  fn takes(f: impl Fn() -> Result<(), String>) -> bool {\n    true\n}\n\
                  fn outcome() -> Option<Result<u8, String>> {\n    None\n}\n\
                  fn pair() -> Result<(String, String), std::io::Error> {\n    todo()\n}\n\
                  #[cfg(test)]\nmod tests {\n    fn helper() -> Result<(), String> {\n        \
                  Ok(())\n    }\n}\n\
                  #[cfg(any(test, feature = \"test-hooks\"))]\npub fn hook() -> Result<(), String> {\n    \
                  Ok(())\n}\n\
                  #[cfg(test)]\nmod ui_tests;\n\
                  impl Reader {\n    fn take(&mut self) -> Result<&[u8], String> {\n        todo()\n    }\n}\n";
    let names: Vec<String> = functions_returning_string_errors(source)
        .into_iter()
        .map(|(line, name)| format!("{line} {name}"))
        .collect();
    assert_eq!(names, ["1 plain", "7 spread", "37 take"]);
}
