//! The viewer driven through egui_kittest and drawn with wgpu (lavapipe in CI): a small phantom
//! opens, the 3D view shows it, presets change it, right-drag windows a slice, the wheel pages.
//!
//! Images stay small: the 3D render is capped at 96 px and the harness window is 560×380.
//! Comparisons use tolerances stated where they are made; nothing is compared to a stored
//! snapshot, because lavapipe's and a GPU's rasterisation differ in the last bits.
//!
//! Compiled as the viewer's unit tests (`#[path]` from src/lib.rs), for private access
//! without test code under src/: one file per feature, `harness.rs` for what they share.

mod export;
mod harness;
mod measurements;
mod opening;
mod overlays;
mod rendering;
mod segment_oblique;
mod segmentation;
mod views;
