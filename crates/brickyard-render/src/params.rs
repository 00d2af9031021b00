//! What a render draws: the mode (DVR, MIP, slice), the image size,
//! camera and transfer function, the step rate, the opacity reference and
//! the channels added up, the views side by side, with their validation. Every renderer takes
//! these: the CPU and device renderers and the in-core reference.

use brickyard_core::camera::length;
use brickyard_core::views::Views;
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

/// How DVR rays find their bricks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Traversal {
    /// Through the page tables at every step, skipping bricks (and blocks
    /// of bricks, and cells) the transfer function hides.
    #[default]
    PageTable,
    /// Through the residency octree ([`crate::octree`]): empty and
    /// homogeneous nodes skipped, misses substituted from the node's
    /// residency mask; bricks still looked up in the page tables.
    Octree,
}

impl std::str::FromStr for Traversal {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "page-table" => Ok(Traversal::PageTable),
            "octree" => Ok(Traversal::Octree),
            _ => Err(format!("traversal: octree or page-table, got {s:?}")),
        }
    }
}

/// A debug image: per pixel a count, in false colour (black for 0, then
/// blue → green → yellow → white up to the frame's largest count).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DebugCounts {
    /// Octree nodes visited by the ray (0 with page-table traversal).
    Nodes,
    /// Bricks the ray entered (every channel, every level looked up).
    Bricks,
    /// Steps the ray walked (samples and steps before jumps).
    Steps,
}

impl std::str::FromStr for DebugCounts {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "nodes" => Ok(DebugCounts::Nodes),
            "bricks" => Ok(DebugCounts::Bricks),
            "steps" => Ok(DebugCounts::Steps),
            _ => Err(format!("debug: nodes, bricks or steps, got {s:?}")),
        }
    }
}

fn is_default<T: Default + PartialEq>(t: &T) -> bool {
    *t == T::default()
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
    /// Several channels at once (the visible set). Slice and MIP add them
    /// up: each channel's value is windowed to `[0, 1]` and multiplied by
    /// its colour; the sum is clamped to 1 (a MIP takes each channel's
    /// maximum along the ray separately). DVR composites them per sample,
    /// each through its own transfer function ([`ChannelStyle::dvr_tf`],
    /// mixed by [`crate::multi`]'s rule). Empty: one channel through `tf`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub channels: Vec<ChannelStyle>,
    /// Several views side by side (`width` holds them all, see
    /// [`brickyard_core::views`]): DVR and MIP from cameras along a
    /// baseline, slices as super-slices. `None`: one view.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub views: Option<Views>,
    /// DVR: how rays find their bricks (page tables or residency octree).
    #[serde(default, skip_serializing_if = "is_default")]
    pub traversal: Traversal,
    /// DVR: draw a count per pixel instead of the image (CPU renderer).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub debug: Option<DebugCounts>,
    /// DVR and MIP of one channel on the CPU, page-table traversal: take
    /// only the samples inside this world box `[lo, hi]` (`[x, y, z]`, a
    /// sample at `t` counts when the ray is inside the box at `t`, entry
    /// included, exit not), on the step grid of the whole ray, so that the
    /// regions of a partition of the volume split every ray's samples
    /// between them (sort-last rendering). `None`: the whole volume.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// (Boxed: most renders have none, and the parameters travel by value.)
    pub clip: Option<Box<[[f64; 3]; 2]>>,
    /// DVR: end a ray once its opacity reaches 0.99 (the default). Off:
    /// every sample is composited, which the compositing of regions
    /// reproduces exactly.
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub early_termination: bool,
    /// MIP with [`clip`](Self::clip): each pixel is `[maximum, 0, 0, 1]`
    /// (`[0; 4]` where the ray takes no sample) rather than its colour,
    /// for the maxima of regions to be combined before the transfer
    /// function ([`crate::optics::mip_color`]).
    #[serde(default, skip_serializing_if = "is_default")]
    pub mip_values: bool,
    /// A label image (one channel, one view): samples take the nearest
    /// voxel's label (no interpolation between labels, at every level),
    /// shown in the label's own colour ([`crate::optics::label_color`]),
    /// label 0 transparent; `tf` is not used. A slice shows the plane's
    /// labels; DVR mode the first label along each ray, shaded by its
    /// surface ([`crate::labels`]).
    #[serde(default, skip_serializing_if = "is_default")]
    pub labels: bool,
    /// With [`labels`](Self::labels): which labels are drawn (`None`:
    /// all). The others are background: transparent in a slice, and a
    /// ray goes on through them in 3D.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label_select: Option<LabelSelect>,
    /// The image height whose pixel footprint picks the automatic level
    /// of detail (`None`: `height`). A smaller image drawn to find the
    /// bricks a larger one needs (`render`'s request pass, the viewer's
    /// previews) asks for the larger image's levels this way, also where
    /// those pixels span less than a voxel and the rule's floor holds
    /// (a bias could not say that: the pass then asked for finer levels
    /// than the image draws).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lod_height: Option<u32>,
}

/// The most labels a [`LabelSelect`] names.
pub const MAX_SELECTED_LABELS: usize = 1 << 16;

/// The largest label magnitude the renderers tell apart: label images are
/// sampled as `f32` (on the CPU and the device alike), which holds every
/// integer up to 2²⁴ and only every second one above.
pub const EXACT_LABELS: i64 = 1 << 24;

/// Which labels of a label image are drawn: only those named, or all but
/// those named.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct LabelSelect {
    /// The labels named, in increasing order, each once, none 0.
    pub ids: Vec<i32>,
    /// Every label but `ids` (else only `ids`).
    #[serde(default, skip_serializing_if = "is_default")]
    pub hide: bool,
    /// Where the labels drawn lie (only `ids`): bricks outside every box
    /// are crossed as background. `None`: not known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub boxes: Option<LabelBoxes>,
}

/// The bounding boxes of a selection's labels, from the label image's
/// statistics: voxels `[z, y, x]` of its level 0 (of size `dims`), each
/// box `[min_z, min_y, min_x, max_z, max_y, max_x]`, inclusive.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct LabelBoxes {
    pub dims: [u64; 3],
    pub boxes: Vec<[u64; 6]>,
}

impl LabelBoxes {
    /// Whether the region `[lo, hi)` (normalized `[z, y, x]`) meets a box.
    pub fn meet(&self, lo: [f64; 3], hi: [f64; 3]) -> bool {
        let d = self.dims.map(|n| n.max(1) as f64);
        self.boxes.iter().any(|b| {
            (0..3).all(|a| (b[a] as f64) / d[a] < hi[a] && (b[3 + a] as f64 + 1.0) / d[a] > lo[a])
        })
    }
}

impl LabelSelect {
    /// A selection of `ids` (any order, repeats allowed).
    pub fn new(mut ids: Vec<i32>, hide: bool) -> LabelSelect {
        ids.sort_unstable();
        ids.dedup();
        LabelSelect {
            ids,
            hide,
            boxes: None,
        }
    }

    /// Whether a label it draws may lie in brick `i` (raster order
    /// `[z, y, x]`) of a level of size `dims` spanning `span` of its
    /// voxels across the extent (`Scene::span`) cut into bricks of `brick`
    /// voxels, padded by `apron`: `false` only where its label boxes say
    /// that none reaches the padded brick (widened by a voxel of the level
    /// each way, as coarser levels' voxels only roughly cover level 0's).
    pub fn may_reach_brick(
        &self,
        i: usize,
        dims: [u64; 3],
        span: [f64; 3],
        brick: [u64; 3],
        apron: u64,
    ) -> bool {
        let Some(boxes) = self.boxes.as_ref().filter(|_| !self.hide) else {
            return true;
        };
        let n = [0, 1, 2].map(|a| dims[a].div_ceil(brick[a]).max(1));
        let i = i as u64;
        let b = [i / (n[1] * n[2]), i / n[2] % n[1], i % n[2]];
        let margin = apron as f64 + 1.0;
        let lo = [0, 1, 2].map(|a| ((b[a] * brick[a]) as f64 - margin) / span[a]);
        let hi = [0, 1, 2].map(|a| (((b[a] + 1) * brick[a]) as f64 + margin) / span[a]);
        boxes.meet(lo, hi)
    }

    /// Whether label `id` is drawn.
    #[inline]
    pub fn shows(&self, id: i32) -> bool {
        self.ids.binary_search(&id).is_ok() != self.hide
    }

    /// Whether any label it draws may lie among values `[lo, hi]` (a
    /// brick's or cell's range; labels are values rounded to the nearest
    /// integer, 0 is never drawn). `true` where the range is not a range
    /// of labels (NaN).
    pub fn draws_any(&self, lo: f32, hi: f32) -> bool {
        if lo.is_nan() || hi.is_nan() {
            return true;
        }
        let [a, b] = [lo, hi].map(|v| (v as f64 + 0.5).floor() as i64);
        if a > b {
            return true;
        }
        let from = self.ids.partition_point(|&x| (x as i64) < a);
        let to = self.ids.partition_point(|&x| (x as i64) <= b);
        let listed = (to - from) as i64;
        match self.hide {
            false => listed > 0,
            // Every label of the range but 0 hidden?
            true => b - a + 1 - (a <= 0 && b >= 0) as i64 > listed,
        }
    }

    /// The labels as [`LabelSelect::parse_ids`] reads them, runs of
    /// consecutive labels as ranges (`3,17,40-45`).
    pub fn ids_text(&self) -> String {
        let mut out: Vec<String> = vec![];
        let mut i = 0;
        while i < self.ids.len() {
            let mut j = i;
            while j + 1 < self.ids.len() && self.ids[j + 1] == self.ids[j] + 1 {
                j += 1;
            }
            out.push(match j - i {
                0 => self.ids[i].to_string(),
                1 => format!("{},{}", self.ids[i], self.ids[j]),
                _ => format!("{}-{}", self.ids[i], self.ids[j]),
            });
            i = j + 1;
        }
        out.join(",")
    }

    /// Parse a list such as `3,17,40-45` (labels and inclusive ranges;
    /// 0, the background, is refused).
    pub fn parse_ids(text: &str) -> Result<Vec<i32>, String> {
        let mut ids = vec![];
        for part in text.split(',').map(str::trim) {
            if part.is_empty() {
                return Err(format!(
                    "an empty item in {text:?}: expected labels such as 3,17,40-45"
                ));
            }
            let num = |s: &str| {
                let v = s
                    .trim()
                    .parse::<i64>()
                    .map_err(|_| format!("expected labels such as 3,17,40-45, found {part:?}"))?;
                if v.abs() > EXACT_LABELS {
                    return Err(format!(
                        "labels from -{EXACT_LABELS} to {EXACT_LABELS} (2^24) can be chosen, \
                         found {v}: label images are drawn from 32-bit floats, which tell \
                         larger labels apart only in pairs"
                    ));
                }
                Ok(v as i32)
            };
            let (a, b) = match part.split_once('-').filter(|(a, _)| !a.is_empty()) {
                Some((a, b)) => (num(a)?, num(b)?),
                None => (num(part)?, num(part)?),
            };
            if a > b {
                return Err(format!("the range {part:?} runs backwards"));
            }
            if (b as i64 - a as i64) as usize + ids.len() >= MAX_SELECTED_LABELS {
                return Err(format!("at most {MAX_SELECTED_LABELS} labels"));
            }
            ids.extend(a..=b);
        }
        if ids.is_empty() {
            return Err(format!(
                "expected labels such as 3,17,40-45, found {text:?}"
            ));
        }
        if ids.contains(&0) {
            return Err("0 is the background, never drawn; expected labels other than 0".into());
        }
        Ok(ids)
    }
}

fn yes() -> bool {
    true
}

fn is_true(b: &bool) -> bool {
    *b
}

/// Most channels a slice or MIP adds up at once.
pub const MAX_CHANNELS: usize = 16;

/// Most channels a DVR composites at once (CPU and device).
pub const MAX_DVR_CHANNELS: usize = 64;

/// How one channel of a multi-channel image is shown.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelStyle {
    pub channel: usize,
    /// Linear RGB in `[0, 1]` added at full intensity.
    pub color: [f32; 3],
    /// Data values `[lo, hi]` mapped to intensity 0 and 1.
    pub window: [f32; 2],
    /// DVR: this channel's transfer function (colour and opacity); `None`:
    /// the default made from `color` and `window` ([`ChannelStyle::dvr_tf`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tf: Option<TransferFunction>,
    /// DVR: the finest and coarsest pyramid level this channel is drawn
    /// at (`[lo, hi]`, `lo <= hi`): a step asking for level `l` reads the
    /// channel at `l` clamped to that range (and to the volume's levels).
    /// `None`: every level, as the step asks.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub levels: Option<[usize; 2]>,
}

impl ChannelStyle {
    /// The level this channel is read at where a DVR step asks for `level`
    /// of a volume of `count` levels ([`ChannelStyle::levels`]).
    #[inline]
    pub fn level_for(levels: Option<[usize; 2]>, level: usize, count: usize) -> usize {
        match levels {
            Some([lo, hi]) => level.clamp(lo, hi).min(count - 1),
            None => level,
        }
    }

    /// A channel shown with `color` over `window`, with the default DVR
    /// transfer function.
    pub fn new(channel: usize, color: [f32; 3], window: [f32; 2]) -> ChannelStyle {
        ChannelStyle {
            channel,
            color,
            window,
            tf: None,
            levels: None,
        }
    }

    /// The channel's DVR transfer function: `tf` if given, else over
    /// `window` the constant colour `color` (each component at most 1) with
    /// opacity 0 up to a tenth of the window, then rising linearly to 0.45
    /// at its top.
    pub fn dvr_tf(&self) -> TransferFunction {
        if let Some(tf) = &self.tf {
            return tf.clone();
        }
        let [r, g, b] = self.color.map(|c| c.min(1.0));
        TransferFunction {
            window: self.window,
            opacity: vec![[0.0, 0.0], [0.1, 0.0], [1.0, 0.45]],
            colormap: brickyard_core::transfer::ColorMap::Points(vec![
                [0.0, r, g, b],
                [1.0, r, g, b],
            ]),
            shading: None,
        }
    }
}

fn one() -> f64 {
    1.0
}

impl RenderParams {
    /// The height whose pixel footprint picks the level of detail
    /// ([`lod_height`](Self::lod_height), else `height`).
    pub fn lod_height(&self) -> u32 {
        self.lod_height.unwrap_or(self.height)
    }

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
            views: None,
            traversal: Traversal::PageTable,
            debug: None,
            clip: None,
            early_termination: true,
            mip_values: false,
            labels: false,
            label_select: None,
            lod_height: None,
        }
    }

    /// What a label image draws over the slice these parameters draw (as
    /// `render --labels NAME` lays it): the same plane, camera and size,
    /// in the labels' colours (`select`: the labels drawn), one channel,
    /// through the page tables, with a fixed transfer function (label
    /// colours take nothing from it).
    pub fn labels_over(&self, select: Option<LabelSelect>) -> RenderParams {
        let mut p = self.clone();
        p.labels = true;
        p.label_select = select;
        p.channels = vec![];
        p.tf = TransferFunction::preset("linear", [0.0, 1.0]).expect("a preset");
        p.traversal = Traversal::PageTable;
        p
    }

    /// Check everything the renderers rely on.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |f: &str, m: String| Err(ConfigError::new("render parameters", f, m));
        if let Some(&[lo, hi]) = self.clip.as_deref() {
            if !(0..3).all(|a| lo[a].is_finite() && hi[a].is_finite() && lo[a] <= hi[a]) {
                return bad(
                    "clip",
                    format!("expected a box lo <= hi, got {lo:?} {hi:?}"),
                );
            }
            let one_channel = self.channels.len() <= 1 || matches!(self.mode, RenderMode::Dvr);
            if matches!(self.mode, RenderMode::Slice { .. })
                || !self.channels.is_empty() && !one_channel
                || self.traversal != Traversal::PageTable
                || self.views.is_some()
                || self.debug.is_some()
            {
                return bad(
                    "clip",
                    "regions are drawn for DVR and MIP of one channel, one view, \
                     page-table traversal"
                        .into(),
                );
            }
        }
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
        if let Some(v) = &self.views {
            v.validate(self.width)?;
            if matches!(self.mode, RenderMode::Slice { .. }) {
                if !self.channels.is_empty() {
                    return bad(
                        "views",
                        "a super-slice shows one channel through the transfer function".into(),
                    );
                }
                if v.separation != 0.0 {
                    return bad(
                        "views.separation",
                        format!(
                            "super-slices take parallax and spacing, not a camera separation (got {})",
                            v.separation
                        ),
                    );
                }
            }
        }
        let dvr = matches!(self.mode, RenderMode::Dvr);
        if self.labels
            && (matches!(self.mode, RenderMode::Mip)
                || !self.channels.is_empty()
                || self.views.is_some()
                || self.clip.is_some()
                || self.debug.is_some()
                || self.traversal != Traversal::PageTable
                || self.tf.shading.is_some())
        {
            return bad(
                "labels",
                "label colours are drawn in slices and in 3D (DVR mode) of one channel, one \
                 view, through the page tables, unshaded by the transfer function (a MIP \
                 draws a label image's values)"
                    .into(),
            );
        }
        if let Some(sel) = &self.label_select {
            if !self.labels {
                return bad(
                    "label_select",
                    "a selection of labels applies to a label image's colours".into(),
                );
            }
            if sel.ids.len() > MAX_SELECTED_LABELS
                || sel.ids.windows(2).any(|w| w[0] >= w[1])
                || sel.ids.contains(&0)
            {
                return bad(
                    "label_select",
                    format!(
                        "expected at most {MAX_SELECTED_LABELS} labels in increasing order, \
                         each once, none 0 (the background)"
                    ),
                );
            }
        }
        if self.traversal == Traversal::Octree {
            if !dvr {
                return bad("traversal", "the octree traversal draws DVR only".into());
            }
            if self.channels.is_empty() && self.tf.shading.is_some() {
                return bad(
                    "traversal",
                    "the octree traversal draws unshaded DVR (turn shading off or use page-table)"
                        .into(),
                );
            }
        }
        if self.debug.is_some() && !dvr {
            return bad("debug", "debug images are drawn for DVR only".into());
        }
        let most = if dvr { MAX_DVR_CHANNELS } else { MAX_CHANNELS };
        if self.channels.len() > most {
            return bad(
                "channels",
                format!(
                    "at most {most} channels at once in this mode, got {}",
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
            if let Some(tf) = &c.tf {
                tf.validate().map_err(|e| {
                    ConfigError::new(
                        "render parameters",
                        &format!("channels[{i}].tf"),
                        e.to_string(),
                    )
                })?;
                if tf.shading.is_some() && dvr {
                    return bad(
                        &format!("channels[{i}].tf.shading"),
                        "gradient shading takes one channel; several channels are composited unshaded".into(),
                    );
                }
            }
        }
        self.camera.validate()?;
        self.tf.validate()
    }
}
