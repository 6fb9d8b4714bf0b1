//! The shared panels driven through egui_kittest (no GPU: nothing here is rendered, the tests
//! read what the widgets did to their inputs and the accessibility tree's labels). One binary
//! for all of them, as the other crates do: each test file is a module.

mod performance;
mod segment_panel;
mod slice_canvas;
mod target_fps;
mod tf_editor;
