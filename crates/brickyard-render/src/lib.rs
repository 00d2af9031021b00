//! brickyard-render: images and renderers.
//!
//! - [`image`]: premultiplied float RGBA images, PNG output, comparisons.
//! - [`reference`](mod@reference): the in-core reference renderer (whole level in RAM,
//!   plain trilinear) — the oracle for every out-of-core image.
//! - [`cpu`]: ray-guided DVR, MIP and slices through the virtual memory.
//! - [`gpu`]: DVR, MIP and slices on the device (WGSL), the twin of `cpu`.
//!
//! Cameras and transfer functions live in `brickyard_core::{camera,
//! transfer}`. **World coordinates are `[x, y, z]`**; volumes, spacing and
//! normalized positions are `[z, y, x]` (see `brickyard_core::camera`).

pub mod budget;
pub mod cpu;
pub mod gpu;
pub mod image;
pub mod reference;

pub use image::Image;
pub use reference::{render, RenderMode, RenderParams, Volume};
