//! brickyard-render: images and renderers.
//!
//! - [`image`]: premultiplied float RGBA images, PNG output, comparisons.
//! - [`params`]: what a render draws (mode, camera, transfer function,
//!   channels), for every renderer.
//! - [`reference`](mod@reference): the in-core reference renderer (whole level in RAM,
//!   plain trilinear) — the oracle for every out-of-core image. It shares
//!   no code with the renderers below.
//! - [`cpu`]: ray-guided DVR, MIP and slices through the virtual memory
//!   (the CPU frame driver), made of `walk` (bricks, landing, cells),
//!   `dvr`, `mip`, `slice` (one module per mode), `superslice` (the views
//!   of a slice stack for multi-view displays), [`multi`] (DVR of
//!   several channels, each through its own transfer function) and
//!   [`optics`] (transfer function, opacity correction, compositing,
//!   channel mix).
//! - [`gpu`]: DVR, MIP and slices on the device (the device frame driver):
//!   the WGSL twin of each of those modules sits beside it (`walk.wgsl`,
//!   `dvr.wgsl`, …) and `gpu.rs` joins them into one shader.
//! - [`savr`]: progressive DVR by sample accumulation on the CPU (kept
//!   samples per pixel, depth-order blends, re-blends under a new transfer
//!   function); `shading` holds DVR gradient shading.
//! - [`octree`]: the residency octree (per node and channel: levels with
//!   mapped bricks, value ranges per level) kept from the virtual memory's
//!   map and evict events, and DVR traversal through it.
//! - [`budget`]: the level-of-detail budget of a view.
//! - [`views`]: what an image of several views becomes for a display
//!   (tiles, side by side, top-bottom, anaglyph, multiplexed sub-pixels).
//!
//! Cameras and transfer functions live in `brickyard_core::{camera,
//! transfer}`. **World coordinates are `[x, y, z]`**; volumes, spacing and
//! normalized positions are `[z, y, x]` (see `brickyard_core::camera`).

pub mod budget;
pub mod cpu;
mod dvr;
mod entry;
pub mod gpu;
pub mod image;
pub mod isa;
pub mod labels;
mod lanes;
mod mip;
pub mod multi;
pub mod octree;
pub mod optics;
pub mod params;
pub mod readout;
pub mod reference;
pub mod savr;
mod shading;
mod slice;
mod superslice;
pub mod views;
mod walk;

pub use image::Image;
pub use params::{RenderMode, RenderParams};
pub use reference::{render, Volume};
pub use slice::slice_point;

/// This crate's WGSL modules, by name, as they are compiled: the render
/// kernel (DVR, MIP, slices, octree traversal, accumulation) and the
/// residency octree's update passes.
pub fn device_shaders() -> Vec<(&'static str, String)> {
    vec![
        ("render", gpu::render_source()),
        ("octree", include_str!("octree.wgsl").to_string()),
    ]
}

/// The oracle stands alone: the reference renderer names no module of the
/// product renderers, and they do not name it, so that no rule is shared
/// between what is tested and what it is tested against.
#[cfg(test)]
mod independence {
    /// Every `crate::…` module a source file names.
    fn crate_paths(source: &str) -> Vec<String> {
        let mut found = vec![];
        for (i, _) in source.match_indices("crate::") {
            let before = source[..i].chars().next_back();
            if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
                continue; // e.g. `brickyard_crate::`
            }
            let rest = &source[i + "crate::".len()..];
            let end = rest
                .find(|c: char| !(c.is_alphanumeric() || c == '_'))
                .unwrap_or(rest.len());
            found.push(rest[..end].to_string());
        }
        found
    }

    #[test]
    fn the_reference_names_no_product_module() {
        let names = crate_paths(include_str!("reference.rs"));
        assert!(names.iter().any(|n| n == "params"), "{names:?}");
        for n in &names {
            assert!(
                ["image", "params"].contains(&n.as_str()),
                "reference.rs names crate::{n}"
            );
        }
        assert!(!include_str!("reference.rs").contains("super::"));
    }

    #[test]
    fn the_product_does_not_name_the_reference() {
        for (file, source) in [
            ("cpu.rs", include_str!("cpu.rs")),
            ("gpu.rs", include_str!("gpu.rs")),
            ("optics.rs", include_str!("optics.rs")),
            ("walk.rs", include_str!("walk.rs")),
            ("walk/bricks.rs", include_str!("walk/bricks.rs")),
            ("walk/cells.rs", include_str!("walk/cells.rs")),
            ("walk/landing.rs", include_str!("walk/landing.rs")),
            ("dvr.rs", include_str!("dvr.rs")),
            ("mip.rs", include_str!("mip.rs")),
            ("slice.rs", include_str!("slice.rs")),
            ("superslice.rs", include_str!("superslice.rs")),
            ("budget.rs", include_str!("budget.rs")),
            ("savr.rs", include_str!("savr.rs")),
            ("shading.rs", include_str!("shading.rs")),
        ] {
            let names = crate_paths(source);
            assert!(
                !names.iter().any(|n| n == "reference"),
                "{file} names crate::reference"
            );
        }
    }
}
