//! One error type for the crate; messages say what to do where the user can act.

use thiserror::Error;

/// Install hint shown whenever no adapter can be found; CI and users on headless boxes need it.
pub const ADAPTER_INSTALL_HINT: &str = "apt-get install -y mesa-vulkan-drivers libvulkan1";

#[derive(Debug, Error)]
pub enum RenderError {
    #[error("no wgpu adapter found ({details}); on Debian/Ubuntu without a GPU install the Vulkan CPU driver: {hint}", hint = ADAPTER_INSTALL_HINT)]
    NoAdapter { details: String },
    #[error("could not create a wgpu device: {0}")]
    RequestDevice(String),
    #[error("brick payload has {got} values, expected {expected} (36^3)")]
    BrickSize { got: usize, expected: usize },
    #[error("cache slot {slot} is out of range (cache has {slots} slots)")]
    SlotOutOfRange { slot: u32, slots: u32 },
    #[error("brick cache cannot hold a single 36^3 slot within budget {budget_bytes} bytes / device limits")]
    CacheTooSmall { budget_bytes: u64 },
    /// wgpu refused an allocation (out of memory, or beyond a limit it validates): captured in
    /// an error scope instead of reaching the uncaptured-error handler. The detail keeps wgpu's
    /// words ("Out of Memory"), which the viewer's recovery classifies.
    #[error(
        "the GPU could not allocate {what}: {detail}; the adapter reports a largest single \
         allocation of {reported_limit_mib} MiB: give a smaller budget (--gpu-mib)"
    )]
    GpuAllocation {
        what: String,
        detail: String,
        reported_limit_mib: u64,
    },
    #[error("the GPU reported an error: {0}")]
    Uncaptured(String),
    #[error("invalid volume: {0}")]
    InvalidVolume(String),
    #[error("invalid volume geometry: {0}")]
    InvalidGeometry(#[from] strata_types::GeometryError),
    #[error("invalid transfer function: {0}")]
    InvalidTransferFunction(String),
    #[error("transfer function JSON: {0}")]
    TransferFunctionJson(#[from] serde_json::Error),
    #[error(
        "the flat page table is too large: {pages} page cells ({page_dims:?}) need {bytes} bytes \
         in its per-page buffers, the largest binding {binding_bytes} bytes, over {limit_source} \
         of {limit_bytes} bytes; use --traversal octree, whose index grows with the cut"
    )]
    FlatTableTooLarge {
        pages: u64,
        page_dims: [u32; 3],
        bytes: u64,
        binding_bytes: u64,
        limit_bytes: u64,
        limit_source: String,
    },
    #[error("page table does not match the volume: {0}")]
    PageTableMismatch(String),
    #[error("invalid render settings: {0}")]
    InvalidSettings(String),
    #[error("GPU readback failed: {0}")]
    Readback(String),
    #[error("image comparison: {0}")]
    ImageMismatch(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}
