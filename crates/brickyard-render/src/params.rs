//! What a render draws: the mode (DVR, MIP, slice), the image size,
//! camera and transfer function, the step rate, the opacity reference and
//! the channels added up, with their validation. Every renderer takes
//! these: the CPU and device renderers and the in-core reference.

use brickyard_core::camera::length;
use brickyard_core::{Camera, ConfigError, TransferFunction};
use serde::{Deserialize, Serialize};

/// What to render.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "mode", rename_all = "lowercase")]
pub enum RenderMode {
    /// Direct volume rendering (emission–absorption).
    Dvr,
    /// Maximum intensity projection.
    Mip,
    /// The plane through `origin` (world `[x, y, z]`) perpendicular to
    /// `normal` (any length but zero), **as the camera sees it**: each
    /// pixel's ray is intersected with the plane (`t ≥ 0`); where the point
    /// lies inside the closed world box the volume is sampled there and the
    /// pixel gets the transfer function's colour with alpha 1; elsewhere it
    /// stays transparent. Any camera works (an oblique plane in perspective
    /// is fine); [`Camera::facing_plane`] gives the usual face-on view.
    Slice { origin: [f64; 3], normal: [f64; 3] },
}

/// Everything a render needs besides the volume.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderParams {
    pub width: u32,
    pub height: u32,
    pub camera: Camera,
    pub tf: TransferFunction,
    pub mode: RenderMode,
    /// Samples per voxel along a ray: `Δ = voxel / samples_per_voxel`.
    #[serde(default = "one")]
    pub samples_per_voxel: f64,
    /// The world length the transfer function's opacity refers to
    /// (`Δ_ref`); `None`: one voxel of the rendered level
    /// ([`crate::Volume::voxel_size`]). Set it (e.g. to level 0's voxel) to keep
    /// images of different levels equally opaque.
    #[serde(default)]
    pub reference_step: Option<f64>,
    /// Several channels at once, added up (slice and MIP only): each
    /// channel's value is windowed to `[0, 1]` and multiplied by its
    /// colour; the sum is clamped to 1. A MIP takes each channel's maximum
    /// along the ray separately. Empty: one channel through `tf`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub channels: Vec<ChannelStyle>,
}

/// Most channels one image shows at once.
pub const MAX_CHANNELS: usize = 16;

/// How one channel of a multi-channel image is shown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelStyle {
    pub channel: usize,
    /// Linear RGB in `[0, 1]` added at full intensity.
    pub color: [f32; 3],
    /// Data values `[lo, hi]` mapped to intensity 0 and 1.
    pub window: [f32; 2],
}

fn one() -> f64 {
    1.0
}

impl RenderParams {
    /// Parameters with one sample per voxel and `Δ_ref` = one voxel.
    pub fn new(
        width: u32,
        height: u32,
        camera: Camera,
        tf: TransferFunction,
        mode: RenderMode,
    ) -> RenderParams {
        RenderParams {
            width,
            height,
            camera,
            tf,
            mode,
            samples_per_voxel: 1.0,
            reference_step: None,
            channels: vec![],
        }
    }

    /// Check everything the renderers rely on.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |f: &str, m: String| Err(ConfigError::new("render parameters", f, m));
        if self.width == 0 || self.height == 0 {
            return bad(
                "width",
                format!(
                    "image size must be positive, got {}×{}",
                    self.width, self.height
                ),
            );
        }
        if !(self.samples_per_voxel > 0.0 && self.samples_per_voxel.is_finite()) {
            return bad(
                "samples_per_voxel",
                format!("must be positive, got {}", self.samples_per_voxel),
            );
        }
        if let Some(r) = self.reference_step {
            if !(r > 0.0 && r.is_finite()) {
                return bad("reference_step", format!("must be positive, got {r}"));
            }
        }
        if let RenderMode::Slice { origin, normal } = &self.mode {
            if origin.iter().chain(normal).any(|x| !x.is_finite()) || length(*normal) == 0.0 {
                return bad(
                    "mode.normal",
                    format!("slice needs a finite origin and a non-zero normal, got {origin:?}, {normal:?}"),
                );
            }
        }
        if !self.channels.is_empty() && matches!(self.mode, RenderMode::Dvr) {
            return bad(
                "channels",
                "several channels are shown additively in mip and slice modes; dvr takes one channel and a transfer function".into(),
            );
        }
        if self.channels.len() > MAX_CHANNELS {
            return bad(
                "channels",
                format!(
                    "at most {MAX_CHANNELS} channels at once, got {}",
                    self.channels.len()
                ),
            );
        }
        for (i, c) in self.channels.iter().enumerate() {
            let [lo, hi] = c.window;
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return bad(
                    &format!("channels[{i}].window"),
                    format!("needs finite lo < hi, got {:?}", c.window),
                );
            }
            if !c.color.iter().all(|x| x.is_finite() && *x >= 0.0) {
                return bad(
                    &format!("channels[{i}].color"),
                    format!("needs finite non-negative RGB, got {:?}", c.color),
                );
            }
        }
        self.camera.validate()?;
        self.tf.validate()
    }
}
