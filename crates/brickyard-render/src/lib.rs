//! brickyard-render: images and renderers.
//!
//! - [`image`]: premultiplied float RGBA images, PNG output, comparisons.
//! - [`params`]: what a render draws (mode, camera, transfer function,
//!   channels), for every renderer.
//! - [`reference`](mod@reference): the in-core reference renderer (whole level in RAM,
//!   plain trilinear) — the oracle for every out-of-core image.
//! - [`cpu`]: ray-guided DVR, MIP and slices through the virtual memory
//!   (the CPU frame driver), made of `walk` (bricks, landing, cells),
//!   `dvr`, `mip`, `slice` (one module per mode) and [`optics`] (transfer
//!   function, opacity correction, compositing, channel mix).
//! - [`gpu`]: DVR, MIP and slices on the device (the device frame driver):
//!   the WGSL twin of each of those modules sits beside it (`walk.wgsl`,
//!   `dvr.wgsl`, …) and `gpu.rs` joins them into one shader.
//! - [`budget`]: the level-of-detail budget of a view.
//!
//! Cameras and transfer functions live in `brickyard_core::{camera,
//! transfer}`. **World coordinates are `[x, y, z]`**; volumes, spacing and
//! normalized positions are `[z, y, x]` (see `brickyard_core::camera`).

pub mod budget;
pub mod cpu;
mod dvr;
pub mod gpu;
pub mod image;
mod mip;
pub mod optics;
pub mod params;
pub mod reference;
mod slice;
mod walk;

pub use image::Image;
pub use params::{RenderMode, RenderParams};
pub use reference::{render, Volume};
