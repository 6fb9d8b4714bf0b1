//! The WGSL program, composed at load time: a prelude of constants generated from the Rust
//! definitions (layout.rs), then the shader files in a fixed order. WGSL module-scope
//! declarations are order-independent, so the split into files changes nothing the compiler
//! sees; the prelude means no constant the shader shares with Rust is written by hand.
//!
//! Each file is the twin of a Rust module: `params.wgsl` ↔ `Params` in raycast.rs,
//! `page_table.wgsl` ↔ page_table.rs, `smooth_transitions.wgsl` ↔ smooth_transitions.rs,
//! `field.wgsl` ↔ field.rs, `transfer_function.wgsl` ↔ transfer_function.rs,
//! `preintegration.wgsl` ↔ preintegration.rs, `shading.wgsl` ↔ reference.rs `shade`,
//! `overlay.wgsl` ↔ overlay.rs, `shadows.wgsl` ↔ shadows.rs, `ambient_occlusion.wgsl` ↔
//! ambient_occlusion.rs, `scattering.wgsl` ↔ scattering.rs, `raycast.wgsl` (entry point and ray loop) ↔
//! raycast.rs; `probe.wgsl` ↔ probe.rs, composed into a test-only module of its own;
//! `adaptive.wgsl` ↔ adaptive/gpu.rs (and adaptive/transcription.rs), composed with the field
//! files, `preintegration.wgsl` and the key light's files (`transfer_function.wgsl`,
//! `shadows.wgsl`, `ambient_occlusion.wgsl`, `scattering.wgsl`) into the adaptive pass's module. The field files leave the
//! transition blend's neighbour lookup (`neighbour_page`) to the module: `flat_neighbour.wgsl`
//! in the adaptive pass and the probe, raycast.wgsl's own (flat or octree) in the raycaster.
//!
//! The effect overrides a source declares are read from naga's IR of it
//! (`declared_overrides`); the default source is composed and parsed once per process.

use std::sync::OnceLock;

use crate::layout::{
    BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, DEPTH_OPACITY, FLAG_EMPTY, FLAG_NOT_RESIDENT,
    FLAG_TRANSITION, FLAG_WHOLE_NODE, LEVEL_MASK, LEVEL_SHIFT, OCTREE_ID_MASK, OCTREE_LEAF_BIT,
    OCTREE_NULL, OCTREE_RECORD_WORDS, OCTREE_SIZE_SHIFT, SHADING_FLAT_BELOW, SHADING_LIT_ABOVE,
    SLOT_AXIS_BITS, SLOT_AXIS_MASK, WORKGROUP_SIZE,
};
use crate::overlay::OVERLAY_VOXEL_OPACITY;

/// The files that define the sampled field and its lookups, in composition order.
const FIELD_FILES: [(&str, &str); 4] = [
    ("params.wgsl", include_str!("shaders/params.wgsl")),
    ("page_table.wgsl", include_str!("shaders/page_table.wgsl")),
    (
        "smooth_transitions.wgsl",
        include_str!("shaders/smooth_transitions.wgsl"),
    ),
    ("field.wgsl", include_str!("shaders/field.wgsl")),
];

/// The raycast pass's own files, after [`FIELD_FILES`].
const RAYCAST_FILES: [(&str, &str); 9] = [
    (
        "transfer_function.wgsl",
        include_str!("shaders/transfer_function.wgsl"),
    ),
    (
        "preintegration.wgsl",
        include_str!("shaders/preintegration.wgsl"),
    ),
    SHADING,
    ("octree.wgsl", OCTREE_WGSL),
    ("overlay.wgsl", include_str!("shaders/overlay.wgsl")),
    ("shadows.wgsl", include_str!("shaders/shadows.wgsl")),
    (
        "ambient_occlusion.wgsl",
        include_str!("shaders/ambient_occlusion.wgsl"),
    ),
    ("scattering.wgsl", include_str!("shaders/scattering.wgsl")),
    ("raycast.wgsl", include_str!("shaders/raycast.wgsl")),
];

/// The octree traversal's index lookups (needs only the prelude): in the raycast shader and the
/// test-only leaf walk (octree_probe.rs).
pub(crate) const OCTREE_WGSL: &str = include_str!("shaders/octree.wgsl");

/// A prelude constant's WGSL type and value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum PreludeValue {
    /// An f32 constant, written from its f64 definition (as a WGSL literal would be).
    F32(f64),
    U32(u32),
    /// A u32 bit mask, written in hex.
    Bits(u32),
}

/// Every constant the shader shares with Rust, by its WGSL name.
pub(crate) fn prelude_constants() -> [(&'static str, PreludeValue); 26] {
    use PreludeValue::*;
    [
        ("CORE", F32(BRICK_CORE as f64)),
        ("APRON", F32(BRICK_APRON as f64)),
        ("PAYLOAD", U32(BRICK_PAYLOAD)),
        ("FLAG_EMPTY", Bits(FLAG_EMPTY)),
        ("FLAG_NOT_RESIDENT", Bits(FLAG_NOT_RESIDENT)),
        ("FLAG_TRANSITION", Bits(FLAG_TRANSITION)),
        ("FLAG_WHOLE_NODE", Bits(FLAG_WHOLE_NODE)),
        ("LEVEL_SHIFT", U32(LEVEL_SHIFT)),
        ("LEVEL_MASK", Bits(LEVEL_MASK)),
        ("SLOT_AXIS_BITS", U32(SLOT_AXIS_BITS)),
        ("SLOT_AXIS_MASK", Bits(SLOT_AXIS_MASK)),
        // Below/above these gradient magnitudes (TF-range fractions per finest voxel) shading
        // fades from unlit to lit.
        ("SHADING_FLAT_BELOW", F32(SHADING_FLAT_BELOW)),
        ("SHADING_LIT_ABOVE", F32(SHADING_LIT_ABOVE)),
        ("WORKGROUP_SIZE", U32(WORKGROUP_SIZE)),
        // DVR depth: where accumulated opacity first reaches this.
        ("DEPTH_OPACITY", F32(DEPTH_OPACITY)),
        // The octree traversal's node buffer (gpu_octree.rs).
        ("OCTREE_RECORD_WORDS", U32(OCTREE_RECORD_WORDS)),
        ("OCTREE_ID_MASK", Bits(OCTREE_ID_MASK)),
        ("OCTREE_SIZE_SHIFT", U32(OCTREE_SIZE_SHIFT)),
        ("OCTREE_LEAF_BIT", Bits(OCTREE_LEAF_BIT)),
        ("OCTREE_NULL", Bits(OCTREE_NULL)),
        // The overlay's opacity floor per finest voxel (overlay.rs, the blend rule).
        ("OVERLAY_VOXEL_OPACITY", F32(OVERLAY_VOXEL_OPACITY)),
        // The longest shadow ray in steps (shadows.rs).
        ("MAX_SHADOW_STEPS", U32(crate::shadows::MAX_SHADOW_STEPS)),
        // The occlusion rays' direction set (ambient_occlusion.rs).
        (
            "OCCLUSION_DIRECTIONS",
            U32(crate::ambient_occlusion::DIRECTIONS),
        ),
        (
            "OCCLUSION_GOLDEN_ANGLE",
            F32(crate::ambient_occlusion::GOLDEN_ANGLE),
        ),
        // The adaptive pass's per-block oracle table (adaptive/block_oracle.rs).
        (
            "ORACLE_BLOCK",
            F32(crate::adaptive::block_oracle::BLOCK as f64),
        ),
        (
            "ORACLE_BLOCKS_PER_AXIS",
            U32(crate::adaptive::block_oracle::BLOCKS_PER_AXIS),
        ),
    ]
}

/// The WGSL declarations of every constant the shader shares with Rust (`prelude_constants`).
pub fn prelude() -> String {
    let mut out = String::from("// Generated from the Rust constants (render/src/shaders.rs).\n");
    for (name, value) in prelude_constants() {
        let line = match value {
            // `{:?}` writes an integral f64 as `32.0`; `{:e}` writes `2e-4`: both are WGSL
            // float literals of exactly the Rust value.
            PreludeValue::F32(v) if v.fract() == 0.0 => format!("const {name}: f32 = {v:?};\n"),
            PreludeValue::F32(v) => format!("const {name}: f32 = {v:e};\n"),
            PreludeValue::U32(v) => format!("const {name}: u32 = {v}u;\n"),
            PreludeValue::Bits(v) => format!("const {name}: u32 = {v:#010x}u;\n"),
        };
        out.push_str(&line);
    }
    out
}

fn compose(files: &[(&str, &str)]) -> String {
    let mut out = prelude();
    for (name, source) in files {
        out.push_str(&format!("\n// ---- {name} ----\n"));
        out.push_str(source);
    }
    out
}

/// A shader that samples the field: prelude, field files, then `files`.
pub(crate) fn compose_with_field(files: &[(&str, &str)]) -> String {
    let all: Vec<(&str, &str)> = FIELD_FILES.iter().chain(files).copied().collect();
    compose(&all)
}

/// The prelude and `files`, no field files (the test-only octree walk).
#[cfg(feature = "test-probe")]
pub(crate) fn compose_alone(files: &[(&str, &str)]) -> String {
    compose(files)
}

/// The composed raycast shader: prelude, field files, the pass's files. The test probe
/// (probe.rs) is a module of its own and not in here.
pub fn raycast_source() -> &'static str {
    static SOURCE: OnceLock<String> = OnceLock::new();
    SOURCE.get_or_init(|| compose_with_field(&RAYCAST_FILES))
}

/// The transition blend's neighbour lookup in the flat page table, for the passes that have
/// no octree traversal (adaptive pass, field probe); the raycaster's own is in raycast.wgsl.
pub(crate) const FLAT_NEIGHBOUR: (&str, &str) = (
    "flat_neighbour.wgsl",
    include_str!("shaders/flat_neighbour.wgsl"),
);

/// Blinn-Phong at a gradient (reference.rs `shade`), in the raycaster and the adaptive pass.
const SHADING: (&str, &str) = ("shading.wgsl", include_str!("shaders/shading.wgsl"));

/// The adaptive pass's own files, after [`FIELD_FILES`] (adaptive/gpu.rs). The key light's
/// files (transfer function for the shadow rays' opacity, shadows, occlusion, scattering)
/// come along behind their overrides: a pipeline without them has none of their code.
const ADAPTIVE_FILES: [(&str, &str); 8] = [
    FLAT_NEIGHBOUR,
    (
        "transfer_function.wgsl",
        include_str!("shaders/transfer_function.wgsl"),
    ),
    (
        "preintegration.wgsl",
        include_str!("shaders/preintegration.wgsl"),
    ),
    SHADING,
    ("shadows.wgsl", include_str!("shaders/shadows.wgsl")),
    (
        "ambient_occlusion.wgsl",
        include_str!("shaders/ambient_occlusion.wgsl"),
    ),
    ("scattering.wgsl", include_str!("shaders/scattering.wgsl")),
    ("adaptive.wgsl", include_str!("shaders/adaptive.wgsl")),
];

/// The composed adaptive shader: prelude, field files, pre-integration, the pass.
pub fn adaptive_source() -> &'static str {
    static SOURCE: OnceLock<String> = OnceLock::new();
    SOURCE.get_or_init(|| compose_with_field(&ADAPTIVE_FILES))
}

/// Names of the `override` declarations of `wgsl`, from naga's IR; None if it does not parse
/// (creating the module then reports the error).
pub(crate) fn declared_overrides(wgsl: &str) -> Option<Vec<String>> {
    let module = naga::front::wgsl::parse_str(wgsl).ok()?;
    Some(
        module
            .overrides
            .iter()
            .filter_map(|(_, o)| o.name.clone())
            .collect(),
    )
}

/// [`declared_overrides`] of [`raycast_source`], parsed once.
pub(crate) fn raycast_overrides() -> &'static [String] {
    static OVERRIDES: OnceLock<Vec<String>> = OnceLock::new();
    OVERRIDES.get_or_init(|| declared_overrides(raycast_source()).unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse_and_validate(wgsl: &str) -> naga::Module {
        let module = naga::front::wgsl::parse_str(wgsl)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(wgsl)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{}", e.emit_to_string(wgsl)));
        module
    }

    #[test]
    fn composed_shader_validates_and_its_prelude_has_the_rust_values() {
        let module = parse_and_validate(raycast_source());
        for (name, value) in prelude_constants() {
            let (_, constant) = module
                .constants
                .iter()
                .find(|(_, c)| c.name.as_deref() == Some(name))
                .unwrap_or_else(|| panic!("{name} not in the composed shader"));
            let literal = match module.global_expressions[constant.init] {
                naga::Expression::Literal(l) => l,
                ref e => panic!("{name} is {e:?}, not a literal"),
            };
            let expected = match value {
                PreludeValue::F32(v) => naga::Literal::F32(v as f32),
                PreludeValue::U32(v) | PreludeValue::Bits(v) => naga::Literal::U32(v),
            };
            assert_eq!(literal, expected, "{name}");
        }
        // The production shader has the raycast entry point and the light cache's build
        // (shadows.wgsl) only (the probe is test-only).
        let mut entry_points: Vec<&str> = module
            .entry_points
            .iter()
            .map(|e| e.name.as_str())
            .collect();
        entry_points.sort_unstable();
        assert_eq!(entry_points, ["build_light_cache", "main"]);
    }

    #[test]
    fn adaptive_shader_validates() {
        let module = parse_and_validate(adaptive_source());
        let overrides = declared_overrides(adaptive_source()).unwrap();
        for name in [
            "TILE",
            "L_MAX",
            "ORACLE",
            "MANUAL_TRILINEAR",
            "SMOOTH_TRANSITIONS",
            "KEY_LIGHT",
            "SHADOWS",
            "OCCLUSION",
            "SCATTERING",
        ] {
            assert!(overrides.iter().any(|o| o == name), "{name}");
        }
        // The pass, and shadows.wgsl's light-cache build, which the adaptive pass never
        // creates a pipeline for (it has no cache-mode shadows).
        let mut entry_points: Vec<&str> = module
            .entry_points
            .iter()
            .map(|e| e.name.as_str())
            .collect();
        entry_points.sort_unstable();
        assert_eq!(entry_points, ["build_light_cache", "main"]);
    }
}
