//! Core types of brickyard: voxel data types, dataset layout and the
//! multi-resolution pyramid plan, the virtual-address math, cameras and
//! transfer functions, and the views of stereo and multi-view images.
//!
//! This crate does no I/O and never touches a GPU.

pub mod brick_stats;
pub mod camera;
pub mod dtype;
pub mod grid;
pub mod label_table;
pub mod pyramid;
pub mod transfer;
pub mod views;
pub mod vm;

pub use camera::{Camera, ConfigError, Projection, Ray};
pub use dtype::{
    as_bytes, as_bytes_mut, cast_slice, cast_slice_mut, trilinear, trilinear_of, DType, Sample,
};
pub use pyramid::{level_ratio, level_span, plan_levels, LevelPlan, PyramidPlan};
pub use transfer::{ColorMap, Shading, TransferFunction};

/// Axis order used everywhere inside brickyard: `[z, y, x]`, x fastest.
pub type Dims3 = [u64; 3];

/// Number of voxels in a 3D box.
pub fn voxel_count(d: Dims3) -> u64 {
    d[0] * d[1] * d[2]
}

/// Ceiling division.
pub fn div_ceil(a: u64, b: u64) -> u64 {
    a.div_ceil(b)
}
