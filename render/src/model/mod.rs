//! The model and its CPU twins: the page table and the cut, the one field definition, smooth
//! transitions, the overlay's blend rule, the lighting models and pre-integration in f64, the
//! settings. Nothing here touches the GPU (render/src/lib.rs draws the layers).

pub mod ambient_occlusion;
pub mod blinn_phong;
pub mod camera;
pub mod field;
pub mod layout;
pub mod octree_cut;
pub mod overlay;
pub mod page_table;
pub mod preintegration;
pub mod scattering;
pub mod segment_integral;
pub mod settings;
pub mod shadows;
pub mod smooth_transitions;
pub mod sparse_page_table;
pub mod transfer_function;
