//! brickyard-gpu: the virtual memory's device side through `wgpu`
//! (Vulkan, Metal, DX12; WGSL kernels).
//!
//! - [`context`]: adapter choice (discrete, integrated, virtual, then
//!   software), conservative limits, optional features, read-back, and the
//!   test policy ([`context::test_gpu`]: no adapter is a failure unless
//!   explicitly opted out).
//! - [`pool`]: the brick pool as one 3D texture (format per data type
//!   and adapter), and the host→device write of padded bricks.
//! - [`lru`]: LRU order by order-preserving compaction.
//! - [`vm`]: the page tables on the device (kept in step with the host's
//!   virtual memory by its changes only), the page-table walk and the
//!   sampler.
//! - [`requests`]: request collection in a bounded table and the capped,
//!   prioritized request list.
//! - [`update`]: the update step on the device: slots chosen by the
//!   device's LRU orders, bricks referenced in parallel (one page-table
//!   block per region, never two).
//!
//! Every kernel is the twin of a CPU function of
//! [`brickyard_cache::bookkeeping`]; `tests/twins.rs` compares them on
//! random inputs.

pub mod context;
pub mod kernel;
pub mod lru;
pub mod pool;
pub mod requests;
pub mod update;
pub mod vm;

pub use context::{AdapterChoice, Gpu, GpuError};

/// Every WGSL module of this crate's kernels, by name, as they are
/// compiled (for checks by other shader compilers, e.g. a browser's).
pub fn shaders() -> Vec<(&'static str, String)> {
    vec![
        ("lru", include_str!("shaders/lru.wgsl").to_string()),
        (
            "requests",
            format!(
                "{}\n{}",
                include_str!("shaders/requests.wgsl"),
                requests::REQUEST_INSERT_WGSL
            ),
        ),
        (
            "update",
            vm::with_vm_common(include_str!("shaders/update.wgsl")),
        ),
        ("vm", vm::with_vm_common(include_str!("shaders/vm.wgsl"))),
    ]
}
