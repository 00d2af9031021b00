//! What the page shows, as a small state that lives in the page's URL
//! (`#store=…&mode=dvr&az=30…`): parsed, checked, written back, and
//! turned into the renderers' parameters exactly as `brickyard render`
//! turns its flags into them, so that a link and a command line with the
//! same values draw the same image.

use crate::zarr::ChannelMeta;
use brickyard_core::camera::{normalize, Camera, Projection};
use brickyard_core::TransferFunction;
use brickyard_render::cpu::{Lod, Scene};
use brickyard_render::octree::{Octree, DEFAULT_DEPTH, MAX_DEPTH, MIN_DEPTH};
use brickyard_render::params::{ChannelStyle, LabelSelect, Traversal};
use brickyard_render::{RenderMode, RenderParams};

/// The view: every field has a default, and the URL carries only what
/// differs from it.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewState {
    pub mode: String,
    pub azimuth: f64,
    pub elevation: f64,
    /// 1 frames the whole volume; 2 is twice as close.
    pub zoom: f64,
    pub fov: f64,
    /// A preset, or `labels` (a label image's slices and surfaces in its
    /// labels' colours); `None`: soft, or `labels` for a label image's
    /// slices and DVR.
    pub tf: Option<String>,
    /// Data window; `None`: the channel's `omero` window, else the data
    /// type's range (0–1 for floats).
    pub window: Option<[f64; 2]>,
    pub channel: usize,
    /// `channel=N` was given: that channel alone, also of a store of
    /// several (as `render --channel N`), and kept in the URL.
    pub channel_given: bool,
    /// Several channels at once (`channels=0,2`): composited per sample in
    /// DVR, added up in MIP and slices, each in its `omero` colour and
    /// window. Empty: one channel (`channel`), or for a store of several
    /// channels its active `omero` ones, as `brickyard render` does.
    pub channels: Vec<usize>,
    pub width: u32,
    pub height: u32,
    pub lod_bias: f64,
    pub slice_z: f64,
    /// `slice=` was given (only with `mode=slice`, as `render --slice-z`).
    pub slice_given: bool,
    /// `labels=NAME`: the store's label image `labels/NAME` laid over the
    /// slice at `label_opacity` (as `render --labels NAME`).
    pub labels: Option<String>,
    pub label_opacity: f64,
    /// `only_labels=IDS` / `hide_labels=IDS`: the labels drawn (of a
    /// label image shown, or of `labels=NAME`).
    pub label_select: Option<LabelSelect>,
    /// `traversal=octree`: DVR through the residency octree, as `render
    /// --traversal octree`; else the page tables.
    pub traversal: Traversal,
    /// `octree_depth=D` (with `traversal=octree`): the octree's depth, as
    /// `render --octree-depth D`; `None`: the default.
    pub octree_depth: Option<u32>,
}

impl Default for ViewState {
    fn default() -> Self {
        ViewState {
            mode: "dvr".into(),
            azimuth: 30.0,
            elevation: 20.0,
            zoom: 1.0,
            fov: 35.0,
            tf: None,
            window: None,
            channel: 0,
            channel_given: false,
            channels: vec![],
            width: 512,
            height: 512,
            lod_bias: 0.0,
            slice_z: 0.5,
            slice_given: false,
            labels: None,
            label_opacity: 0.5,
            label_select: None,
            traversal: Traversal::PageTable,
            octree_depth: None,
        }
    }
}

fn num(k: &str, v: &str) -> Result<f64, String> {
    v.parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| format!("{k}: expected a number, found {v:?}"))
}

/// The view's keys in the page's URL (`#…`), which [`ViewState`] reads.
pub const VIEW_KEYS: &[&str] = &[
    "mode",
    "az",
    "el",
    "zoom",
    "fov",
    "tf",
    "window",
    "channel",
    "channels",
    "size",
    "bias",
    "slice",
    "labels",
    "label_opacity",
    "only_labels",
    "hide_labels",
    "traversal",
    "octree_depth",
];

/// The page's own keys in its URL: what the viewer is opened with (the
/// store, the pool in MiB, who draws, a bearer token), read by the page.
pub const PAGE_KEYS: &[&str] = &["store", "pool", "backend", "token"];

/// The largest LOD bias `bias=` takes, either way (levels).
pub const MAX_BIAS: f64 = 8.0;

/// A key the page does not know, named, with the nearest known one where
/// it looks like a typo of it (a letter off, two for longer keys).
fn unknown_key(k: &str) -> String {
    let mut all: Vec<&str> = VIEW_KEYS.iter().chain(PAGE_KEYS).copied().collect();
    let near = all
        .iter()
        .map(|x| (edit_distance(k, x), *x))
        .filter(|(d, _)| *d <= if k.len() <= 4 { 1 } else { 2 })
        .min();
    all.sort_unstable();
    match near {
        Some((_, x)) => format!("{k}: not a key of the page's URL; did you mean {x}?"),
        None => format!(
            "{k}: not a key of the page's URL (the keys: {})",
            all.join(", ")
        ),
    }
}

/// Levenshtein distance (keys are short).
fn edit_distance(a: &str, b: &str) -> usize {
    let (a, b): (Vec<char>, Vec<char>) = (a.chars().collect(), b.chars().collect());
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for i in 1..=a.len() {
        let mut diag = row[0];
        row[0] = i;
        for j in 1..=b.len() {
            let up = row[j];
            row[j] = (row[j] + 1)
                .min(row[j - 1] + 1)
                .min(diag + usize::from(a[i - 1] != b[j - 1]));
            diag = up;
        }
    }
    row[b.len()]
}

impl ViewState {
    /// Read `k=v` pairs (`&`-separated; the page's own keys,
    /// [`PAGE_KEYS`] such as `store`, are left to the caller). Errors name
    /// the key: a bad value, a key given twice, a key the page does not
    /// know (with the nearest known one, for a typo).
    pub fn from_query(q: &str) -> Result<ViewState, String> {
        let mut s = ViewState::default();
        let mut seen: Vec<(&str, String)> = vec![];
        for kv in q
            .trim_start_matches(['#', '?'])
            .split('&')
            .filter(|x| !x.is_empty())
        {
            let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
            let v = decode(v);
            if let Some((_, first)) = seen.iter().find(|(s, _)| *s == k) {
                return Err(format!(
                    "{k}: given twice ({first:?} and {v:?}); give it once"
                ));
            }
            seen.push((k, v.clone()));
            if !VIEW_KEYS.contains(&k) && !PAGE_KEYS.contains(&k) {
                return Err(unknown_key(k));
            }
            match k {
                "mode" => {
                    if !["dvr", "mip", "slice"].contains(&v.as_str()) {
                        return Err(format!("mode: expected dvr, mip or slice, found {v:?}"));
                    }
                    s.mode = v;
                }
                "az" => s.azimuth = num(k, &v)?,
                "el" => s.elevation = num(k, &v)?.clamp(-90.0, 90.0),
                "zoom" => {
                    s.zoom = num(k, &v)?;
                    if s.zoom <= 0.0 {
                        return Err(format!("zoom: expected a positive number, found {v:?}"));
                    }
                }
                "fov" => {
                    s.fov = num(k, &v)?;
                    if !(1.0..=170.0).contains(&s.fov) {
                        return Err(format!("fov: expected 1 to 170 degrees, found {v:?}"));
                    }
                }
                "tf" => {
                    if v != "labels" {
                        TransferFunction::preset(&v, [0.0, 1.0])
                            .map_err(|e| format!("tf: {e} (or labels)"))?;
                    }
                    s.tf = Some(v);
                }
                "window" => {
                    let p: Vec<&str> = v.split(',').collect();
                    if p.len() != 2 {
                        return Err(format!("window: expected LO,HI, found {v:?}"));
                    }
                    let (a, b) = (num(k, p[0])?, num(k, p[1])?);
                    if b <= a {
                        return Err(format!("window: expected LO < HI, found {v:?}"));
                    }
                    s.window = Some([a, b]);
                }
                "channel" => {
                    s.channel = v
                        .parse()
                        .map_err(|_| format!("channel: expected a channel number, found {v:?}"))?;
                    s.channel_given = true;
                }
                "channels" => {
                    s.channels = v
                        .split(',')
                        .filter(|x| !x.is_empty())
                        .map(|x| x.trim().parse::<usize>())
                        .collect::<Result<_, _>>()
                        .map_err(|_| {
                            format!("channels: expected channel numbers C,C,…, found {v:?}")
                        })?;
                    if s.channels.len() > 64 {
                        return Err(format!("channels: at most 64, found {}", s.channels.len()));
                    }
                    for (i, c) in s.channels.iter().enumerate() {
                        if s.channels[..i].contains(c) {
                            return Err(format!(
                                "channels: channel {c} given twice (in {v:?}); give each channel once"
                            ));
                        }
                    }
                }
                "size" => {
                    let (w, h) = v.split_once('x').unwrap_or((&v, &v));
                    let p = |x: &str| x.parse::<u32>().ok().filter(|n| (16..=4096).contains(n));
                    match (p(w), p(h)) {
                        (Some(w), Some(h)) => (s.width, s.height) = (w, h),
                        _ => {
                            return Err(format!(
                                "size: expected WxH, 16 to 4096 pixels each, found {v:?}"
                            ))
                        }
                    }
                }
                "bias" => {
                    s.lod_bias = num(k, &v)?;
                    if !(-MAX_BIAS..=MAX_BIAS).contains(&s.lod_bias) {
                        return Err(format!(
                            "bias: expected a level-of-detail bias from -{MAX_BIAS} to {MAX_BIAS} \
                             levels (negative: finer), found {v:?}"
                        ));
                    }
                }
                "slice" => {
                    s.slice_z = num(k, &v)?;
                    if !(0.0..=1.0).contains(&s.slice_z) {
                        return Err(format!(
                            "slice: expected a fraction of the depth from 0 to 1, found {v:?}"
                        ));
                    }
                    s.slice_given = true;
                }
                "labels" => {
                    let ok = !v.is_empty()
                        && v != "."
                        && v != ".."
                        && v.chars()
                            .all(|c| c.is_ascii_alphanumeric() || "._-".contains(c));
                    if !ok {
                        return Err(format!(
                            "labels: expected the name of a label image (letters, digits, . _ -), found {v:?}"
                        ));
                    }
                    s.labels = Some(v);
                }
                "label_opacity" => {
                    s.label_opacity = num(k, &v)?;
                    if !(s.label_opacity > 0.0 && s.label_opacity <= 1.0) {
                        return Err(format!(
                            "label_opacity: expected an opacity above 0 and at most 1, found {v:?}"
                        ));
                    }
                }
                "only_labels" | "hide_labels" => {
                    if s.label_select.is_some() {
                        return Err(format!("{k}: only_labels or hide_labels, not both"));
                    }
                    let ids = LabelSelect::parse_ids(&v).map_err(|e| format!("{k}: {e}"))?;
                    s.label_select = Some(LabelSelect::new(ids, k == "hide_labels"));
                }
                "traversal" => s.traversal = v.parse()?,
                "octree_depth" => {
                    let d = v
                        .parse::<u32>()
                        .ok()
                        .filter(|d| (MIN_DEPTH..=MAX_DEPTH).contains(d));
                    s.octree_depth = Some(d.ok_or_else(|| {
                        format!("octree_depth: expected {MIN_DEPTH} to {MAX_DEPTH}, found {v:?}")
                    })?);
                }
                _ => {}
            }
        }
        if s.slice_given && s.mode != "slice" {
            return Err(format!(
                "slice: applies to mode=slice only (it places the slice's plane); mode={} draws \
                 the whole volume",
                s.mode
            ));
        }
        if s.channel_given && !s.channels.is_empty() {
            return Err(
                "channel: channel=N shows one channel, channels=… several: give one of them".into(),
            );
        }
        Ok(s)
    }

    /// The state as `k=v&…`, only what differs from the defaults.
    pub fn to_query(&self) -> String {
        let d = ViewState::default();
        let mut q = vec![];
        if self.mode != d.mode {
            q.push(format!("mode={}", self.mode));
        }
        if self.azimuth != d.azimuth {
            q.push(format!("az={}", round(self.azimuth)));
        }
        if self.elevation != d.elevation {
            q.push(format!("el={}", round(self.elevation)));
        }
        if self.zoom != d.zoom {
            q.push(format!("zoom={}", round(self.zoom)));
        }
        if self.fov != d.fov {
            q.push(format!("fov={}", self.fov));
        }
        if let Some(tf) = &self.tf {
            q.push(format!("tf={tf}"));
        }
        if let Some([a, b]) = self.window {
            q.push(format!("window={a},{b}"));
        }
        if self.channel != d.channel || self.channel_given {
            q.push(format!("channel={}", self.channel));
        }
        if !self.channels.is_empty() {
            let c: Vec<String> = self.channels.iter().map(|c| c.to_string()).collect();
            q.push(format!("channels={}", c.join(",")));
        }
        if (self.width, self.height) != (d.width, d.height) {
            q.push(format!("size={}x{}", self.width, self.height));
        }
        if self.lod_bias != d.lod_bias {
            q.push(format!("bias={}", self.lod_bias));
        }
        if self.slice_z != d.slice_z || self.slice_given {
            q.push(format!("slice={}", self.slice_z));
        }
        if let Some(n) = &self.labels {
            q.push(format!("labels={n}"));
        }
        if self.label_opacity != d.label_opacity {
            q.push(format!("label_opacity={}", self.label_opacity));
        }
        if let Some(sel) = &self.label_select {
            let k = if sel.hide {
                "hide_labels"
            } else {
                "only_labels"
            };
            q.push(format!("{k}={}", sel.ids_text()));
        }
        if self.traversal == Traversal::Octree {
            q.push("traversal=octree".into());
        }
        if let Some(d) = self.octree_depth {
            q.push(format!("octree_depth={d}"));
        }
        q.join("&")
    }

    /// The renderers' parameters and level of detail for `scene`
    /// (`window`: the default data window; `label_image`: the store is a
    /// label image), as `brickyard render` with `--mode --azimuth
    /// --elevation --fov --tf --window --channel --size --lod-bias
    /// --slice-z` makes them.
    pub fn params(
        &self,
        scene: &Scene,
        window: [f64; 2],
        meta: &[ChannelMeta],
        n_channels: usize,
        label_image: bool,
    ) -> Result<View, String> {
        let [lo, hi] = self.window.unwrap_or(window);
        let tf_name = match self.tf.as_deref() {
            Some(t) => t,
            None if label_image && self.mode != "mip" && self.channels.is_empty() => "labels",
            None => "soft",
        };
        let labels = tf_name == "labels";
        if labels && self.mode == "mip" {
            return Err(
                "tf: labels colours a label image's slices and surfaces (mode=slice or dvr); mode=mip draws its values through another transfer function"
                    .into(),
            );
        }
        if labels && !self.channels.is_empty() {
            return Err("tf: labels draws one channel (no channels=)".into());
        }
        let tf = TransferFunction::preset(
            if labels { "linear" } else { tf_name },
            [lo as f32, hi as f32],
        )
        .map_err(|e| format!("tf: {e}"))?;
        // The channels shown: as asked (`channel=N`: that one alone, as
        // `render --channel N`), else a store's active channels when it
        // has several (as `render` without --channel).
        let shown: Vec<usize> = if !self.channels.is_empty() {
            self.channels.clone()
        } else if n_channels > 1 && !meta.is_empty() && !self.channel_given {
            (0..n_channels.min(meta.len()))
                .filter(|&c| meta[c].active)
                .collect()
        } else {
            vec![]
        };
        if let Some(c) = shown.iter().find(|&&c| c >= n_channels) {
            return Err(format!(
                "channels: {c} asked for but the store has {n_channels} channel(s)"
            ));
        }
        let styles: Vec<ChannelStyle> = shown
            .iter()
            .map(|&c| ChannelStyle {
                channel: c,
                color: meta.get(c).map_or([1.0; 3], |m| m.color),
                window: meta
                    .get(c)
                    .and_then(|m| m.window)
                    .filter(|_| self.window.is_none())
                    .map_or([lo as f32, hi as f32], |w| [w[0] as f32, w[1] as f32]),
                tf: None,
                levels: None,
            })
            .collect();
        let e = scene.extent;
        let mode = match self.mode.as_str() {
            "dvr" => RenderMode::Dvr,
            "mip" => RenderMode::Mip,
            _ => RenderMode::Slice {
                origin: [
                    e[0] / 2.0,
                    e[1] / 2.0,
                    brickyard_core::camera::slice_centre(e[2], scene.levels[0][0], self.slice_z),
                ],
                normal: [0.0, 0.0, 1.0],
            },
        };
        // The default views fit the volume into the image, its width as
        // well as its height (as `render`'s).
        let mut camera = match &mode {
            RenderMode::Slice { origin, normal } => {
                Camera::fit_plane(e, *origin, *normal, self.width, self.height)
            }
            _ => Camera::fit_image(
                e,
                self.azimuth,
                self.elevation,
                Projection::Perspective {
                    fov_y_deg: self.fov,
                },
                self.width,
                self.height,
            ),
        };
        if self.zoom != 1.0 {
            let d = brickyard_core::camera::sub(camera.eye, camera.target);
            camera.eye = brickyard_core::camera::add(
                camera.target,
                brickyard_core::camera::scale(d, 1.0 / self.zoom),
            );
        }
        let dvr = mode == RenderMode::Dvr;
        let mut p = RenderParams::new(self.width, self.height, camera, tf, mode);
        p.reference_step = Some(scene.voxel(0));
        p.labels = labels;
        if let Some(sel) = &self.label_select {
            if labels {
                p.label_select = Some(sel.clone());
            } else if self.labels.is_none() {
                return Err(
                    "only_labels: applies to a label image's colours (a label image shown, or labels=NAME)"
                        .into(),
                );
            }
        }
        if self.labels.is_some() && (labels || self.mode != "slice") {
            return Err(format!(
                "labels: label images are laid over an image's slices (mode=slice), not over {}",
                if labels {
                    "a label image"
                } else {
                    "mode=dvr or mip"
                }
            ));
        }
        // DVR of one channel goes through the transfer function.
        let channel = match styles.as_slice() {
            [one] if dvr => one.channel,
            _ => self.channel,
        };
        if !dvr || styles.len() > 1 {
            p.channels = styles;
        }
        p.traversal = self.traversal;
        p.validate().map_err(|e| e.to_string())?;
        let octree_depth = self.octree_depth.unwrap_or(DEFAULT_DEPTH);
        if self.traversal == Traversal::Octree {
            Octree::check(octree_depth, scene.levels.len(), n_channels)
                .map_err(|e| format!("traversal: {e}"))?;
        } else if self.octree_depth.is_some() {
            return Err("octree_depth: only with traversal=octree".into());
        }
        Ok(View {
            params: p,
            lod: Lod::Auto {
                bias: self.lod_bias,
            },
            channel,
            octree_depth,
        })
    }
}

impl ViewState {
    /// What the label image of `labels=NAME` draws under the image's
    /// `view` (`None`: no labels): the same slice, camera, size and level
    /// of detail, in the labels' colours (as `render --labels NAME`).
    pub fn label_view(&self, view: &View) -> Option<View> {
        self.labels.as_ref()?;
        Some(View {
            params: view.params.labels_over(self.label_select.clone()),
            lod: view.lod,
            channel: 0,
            octree_depth: view.octree_depth,
        })
    }
}

/// What a frame draws: the parameters, the level of detail, and the
/// scene's channel (DVR of one channel).
#[derive(Clone, Debug)]
pub struct View {
    pub params: RenderParams,
    pub lod: Lod,
    pub channel: usize,
    /// The residency octree's depth, where the DVR goes through it.
    pub octree_depth: u32,
}

impl View {
    /// A label image's view drawing only some labels, with where they lie
    /// (`table`: every label's bounding box, from the statistics, in the
    /// voxels of level 0 of size `dims`): bricks none of them reaches are
    /// crossed. Other views are left as they are.
    pub fn with_label_boxes(
        mut self,
        table: &std::collections::HashMap<u64, [u64; 6]>,
        dims: [u64; 3],
    ) -> View {
        if let Some(s) = self.params.label_select.as_mut().filter(|s| !s.hide) {
            if self.params.labels {
                let boxes = s
                    .ids
                    .iter()
                    .filter(|&&id| id > 0)
                    .filter_map(|&id| table.get(&(id as u64)).copied())
                    .collect();
                s.boxes = Some(brickyard_render::params::LabelBoxes { dims, boxes });
            }
        }
        self
    }

    /// The world point under pixel position `(x, y)` (pixel `(i, j)` spans
    /// `[i, i + 1) × [j, j + 1)`) of a slice view: where the pixel's ray
    /// meets the plane; `None` for other modes and off the volume
    /// (`extent`). Also the world length one pixel spans there (its
    /// footprint, by which the renderers choose the level).
    pub fn slice_point(&self, extent: [f64; 3], x: f64, y: f64) -> Option<([f64; 3], f64)> {
        let RenderMode::Slice { origin, normal } = self.params.mode else {
            return None;
        };
        let p = &self.params;
        let ray = p.camera.ray(x, y, p.width, p.height);
        // (The point the slice renderer samples for that pixel.)
        brickyard_render::slice_point(&ray, origin, normalize(normal), extent)
            .map(|(w, t)| (w, p.camera.pixel_footprint(t, p.height)))
    }
}

fn round(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// Who draws the page's frames (its `backend=`, which stays out of the
/// view's state: it changes how a view is drawn, not what it shows).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// WebGPU where the browser offers a hardware adapter; the CPU in
    /// WebAssembly where there is none or only a software one (its
    /// frames take hundreds of times the CPU renderer's there).
    Auto,
    /// WebGPU whenever the browser has it, a software adapter included.
    Gpu,
    /// The CPU in WebAssembly.
    Cpu,
}

impl Backend {
    /// `auto` (also the empty value), `gpu` or `cpu`.
    pub fn parse(v: &str) -> Result<Backend, String> {
        match v {
            "" | "auto" => Ok(Backend::Auto),
            "gpu" => Ok(Backend::Gpu),
            "cpu" => Ok(Backend::Cpu),
            _ => Err(format!("backend: expected auto, gpu or cpu, found {v:?}")),
        }
    }
}

/// The brick pool of the page's `pool=` (MiB) when none is given.
pub const DEFAULT_POOL_MIB: u64 = 256;
/// The largest `pool=` (MiB): a page's WebAssembly memory holds 4 GiB at
/// most, and decoded chunks, images and the page's own data need room too.
pub const MAX_POOL_MIB: u64 = 2048;

/// The brick pool in bytes from the page's `pool=` (MiB; absent or empty:
/// [`DEFAULT_POOL_MIB`]): a whole number from 1 to [`MAX_POOL_MIB`], else
/// an error naming the key and what was found.
pub fn pool_bytes(v: Option<&str>) -> Result<u64, String> {
    let v = v.unwrap_or("").trim();
    if v.is_empty() {
        return Ok(DEFAULT_POOL_MIB << 20);
    }
    match v.parse::<u64>() {
        Ok(m) if (1..=MAX_POOL_MIB).contains(&m) => Ok(m << 20),
        _ => Err(format!(
            "pool: expected the brick pool in MiB, a whole number from 1 to {MAX_POOL_MIB} \
             (a page's WebAssembly memory holds 4 GiB at most), found {v:?}"
        )),
    }
}

/// Which share of the page's pool a session gets: all of it, the image's
/// three quarters beside a label image (`labels=`), or the label image's
/// quarter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoolShare {
    All,
    Image,
    Labels,
}

impl PoolShare {
    /// The bytes of this share of a pool of `pool` bytes (the page's
    /// split: the label image gets `pool / 4`).
    pub fn of(self, pool: u64) -> u64 {
        match self {
            PoolShare::All => pool,
            PoolShare::Image => pool - pool / 4,
            PoolShare::Labels => pool / 4,
        }
    }

    /// The least `pool=` (whole MiB) whose share holds `bytes`.
    pub fn least_mib(self, bytes: u64) -> u64 {
        let per_mib = self.of(1 << 20);
        bytes.div_ceil(per_mib).max(1)
    }
}

/// A pool too small for the coarsest levels, in the page's words: the
/// `pool=` that holds them (whole MiB, as `pool=` takes), or that no page
/// can hold it.
pub fn pool_too_small(e: &brickyard_cache::brick::PoolTooSmall, share: PoolShare) -> String {
    let whose = match share {
        PoolShare::Labels => "the label image's quarter of the pool",
        _ => "the pool",
    };
    let mib = share.least_mib(e.minimum_bytes);
    let give = if mib <= MAX_POOL_MIB {
        format!("give pool={mib} (MiB) or more")
    } else {
        format!(
            "that takes pool={mib} (MiB), more than a page holds (pool={MAX_POOL_MIB} at most): \
             `brickyard render` or `brickyard view` draw it"
        )
    };
    format!(
        "pool: {whose} holds {} bricks, but the coarsest level alone needs {} (kept resident so \
         that every part of the volume can be drawn) plus as many to work with: {give}",
        e.slots, e.needed
    )
}

/// Undo `%XX` escapes (and `+` for space).
pub fn decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'%' if i + 2 < b.len() => match u8::from_str_radix(&s[i + 1..i + 3], 16) {
                Ok(v) => {
                    out.push(v);
                    i += 3;
                    continue;
                }
                Err(_) => out.push(b'%'),
            },
            b'+' => out.push(b' '),
            c => out.push(c),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pools_are_whole_mib_within_what_a_page_can_hold() {
        assert_eq!(pool_bytes(None), Ok(256 << 20));
        assert_eq!(pool_bytes(Some("")), Ok(256 << 20));
        assert_eq!(pool_bytes(Some("16")), Ok(16 << 20));
        assert_eq!(pool_bytes(Some("2048")), Ok(2048 << 20));
        for bad in ["0", "-5", "abc", "1.5", "2049", "99999999", "NaN"] {
            let e = pool_bytes(Some(bad)).unwrap_err();
            assert!(
                e.starts_with("pool:") && e.contains(&format!("{bad:?}")) && e.contains("2048"),
                "{e}"
            );
        }
    }

    #[test]
    fn unknown_and_repeated_keys_and_biases_out_of_range_are_refused_by_name() {
        // The page's own keys pass (the page reads them).
        ViewState::from_query("store=..%2Fx%2F&pool=16&backend=cpu&token=t&mode=mip").unwrap();
        let e = ViewState::from_query("mode=mip&frobnicate=1").unwrap_err();
        assert!(
            e.starts_with("frobnicate: not a key of the page's URL")
                && e.contains("mode, octree_depth"),
            "{e}"
        );
        let e = ViewState::from_query("windw=0,100").unwrap_err();
        assert!(
            e.starts_with("windw:") && e.contains("did you mean window?"),
            "{e}"
        );
        // (No guess for a short key far from every one.)
        let e = ViewState::from_query("x=1").unwrap_err();
        assert!(e.starts_with("x:") && !e.contains("did you mean"), "{e}");
        let e = ViewState::from_query("mode=mip&az=3&mode=slice").unwrap_err();
        assert_eq!(e, "mode: given twice (\"mip\" and \"slice\"); give it once");
        let e = ViewState::from_query("pool=8&pool=16").unwrap_err();
        assert!(e.starts_with("pool: given twice"), "{e}");
        // The bias: -8 to 8 levels, not clamped silently.
        assert_eq!(ViewState::from_query("bias=8").unwrap().lod_bias, 8.0);
        assert_eq!(ViewState::from_query("bias=-8").unwrap().lod_bias, -8.0);
        for bad in ["99", "-8.5", "8.01"] {
            let e = ViewState::from_query(&format!("bias={bad}")).unwrap_err();
            assert!(
                e.starts_with("bias:") && e.contains("-8 to 8") && e.contains(bad),
                "{e}"
            );
        }
    }

    #[test]
    fn a_pool_too_small_names_the_whole_mib_that_holds_the_coarsest_levels() {
        use brickyard_cache::brick::PoolTooSmall;
        // 1.9 MiB needed: pool=2, as `pool` takes whole MiB.
        let e = PoolTooSmall {
            slots: 26,
            needed: 25,
            minimum_bytes: 50 * 39304,
        };
        let t = pool_too_small(&e, PoolShare::All);
        assert!(t.contains("give pool=2 (MiB)") && !t.contains("1.9"), "{t}");
        for share in [PoolShare::All, PoolShare::Image, PoolShare::Labels] {
            let m = share.least_mib(e.minimum_bytes);
            assert!(share.of(m << 20) >= e.minimum_bytes, "{share:?}");
            assert!(share.of((m - 1) << 20) < e.minimum_bytes, "{share:?}");
        }
        // Beside labels the image has three quarters, the labels one.
        assert_eq!(PoolShare::Image.least_mib(3 << 20), 4);
        assert_eq!(PoolShare::Labels.least_mib(1 << 20), 4);
        let t = pool_too_small(&e, PoolShare::Labels);
        assert!(
            t.contains("label image's quarter") && t.contains("pool=8 (MiB)"),
            "{t}"
        );
        let huge = PoolTooSmall {
            minimum_bytes: 5000 << 20,
            ..e
        };
        let t = pool_too_small(&huge, PoolShare::All);
        assert!(t.contains("pool=5000") && t.contains("2048 at most"), "{t}");
    }

    #[test]
    fn backends_are_auto_gpu_or_cpu() {
        assert_eq!(Backend::parse(""), Ok(Backend::Auto));
        assert_eq!(Backend::parse("auto"), Ok(Backend::Auto));
        assert_eq!(Backend::parse("gpu"), Ok(Backend::Gpu));
        assert_eq!(Backend::parse("cpu"), Ok(Backend::Cpu));
        let e = Backend::parse("webgpu").unwrap_err();
        assert!(e.starts_with("backend:") && e.contains("\"webgpu\""), "{e}");
    }

    #[test]
    fn the_query_round_trips_and_names_bad_keys() {
        let s = ViewState::from_query("#store=x&mode=mip&az=12.5&el=-30&zoom=2&tf=hot&window=0,200&channel=1&size=640x480&bias=-1").unwrap();
        assert_eq!(
            (s.mode.as_str(), s.azimuth, s.elevation, s.zoom),
            ("mip", 12.5, -30.0, 2.0)
        );
        assert_eq!(
            (s.width, s.height, s.window),
            (640, 480, Some([0.0, 200.0]))
        );
        assert_eq!(ViewState::from_query(&s.to_query()).unwrap(), s);
        assert_eq!(ViewState::default().to_query(), "");
        for (q, key) in [
            ("mode=xyz", "mode"),
            ("az=abc", "az"),
            ("window=5,1", "window"),
            ("size=3x3", "size"),
            ("tf=nope", "tf"),
            ("zoom=0", "zoom"),
            ("traversal=kd", "traversal"),
            ("octree_depth=9", "octree_depth"),
            ("octree_depth=x", "octree_depth"),
        ] {
            let e = ViewState::from_query(q).unwrap_err();
            assert!(e.starts_with(key), "{q}: {e}");
        }
        assert_eq!(decode("a%2Cb+c"), "a,b c");
        // `tf=labels` is kept as asked; no tf stays the default.
        let s = ViewState::from_query("mode=slice&tf=labels").unwrap();
        assert_eq!(s.tf.as_deref(), Some("labels"));
        assert_eq!(ViewState::from_query(&s.to_query()).unwrap(), s);
        assert_eq!(ViewState::from_query("mode=slice").unwrap().tf, None);
        let s = ViewState::from_query("traversal=octree&az=10").unwrap();
        assert_eq!(s.traversal, Traversal::Octree);
        assert_eq!(s.to_query(), "az=10&traversal=octree");
        let s = ViewState::from_query("traversal=octree&octree_depth=2").unwrap();
        assert_eq!(ViewState::from_query(&s.to_query()).unwrap(), s);
    }

    #[test]
    fn channel_and_slice_keys_mean_what_render_makes_of_them() {
        let scene = Scene::new([1.0; 3], vec![[64, 64, 64], [32, 32, 32]]);
        let meta: Vec<ChannelMeta> = (0..3)
            .map(|i| ChannelMeta {
                label: format!("c{i}"),
                color: [1.0, 0.0, 0.0],
                window: Some([0.0, 100.0 * (i + 1) as f64]),
                active: true,
            })
            .collect();
        let view = |q: &str| {
            ViewState::from_query(q).and_then(|s| s.params(&scene, [0.0, 255.0], &meta, 3, false))
        };
        // `channel=1` of a store of three active channels: channel 1
        // alone (as `render --channel 1`), in every mode, and kept in the
        // URL, `channel=0` too.
        for mode in ["dvr", "mip", "slice"] {
            let v = view(&format!("mode={mode}&channel=1")).unwrap();
            assert_eq!(v.channel, 1, "{mode}");
            assert!(
                v.params.channels.len() <= 1,
                "{mode}: {:?}",
                v.params.channels
            );
        }
        // (Without it, the three active ones.)
        assert_eq!(view("").unwrap().params.channels.len(), 3);
        assert_eq!(view("mode=mip").unwrap().params.channels.len(), 3);
        let s = ViewState::from_query("channel=0").unwrap();
        assert_eq!(s.to_query(), "channel=0");
        assert_eq!(view("mode=mip&channel=0").unwrap().params.channels.len(), 0);
        // A channel given twice, or channel and channels together: refused.
        let e = ViewState::from_query("channels=0,0").unwrap_err();
        assert!(
            e.starts_with("channels:") && e.contains("channel 0 given twice"),
            "{e}"
        );
        let e = ViewState::from_query("channel=1&channels=0,2").unwrap_err();
        assert!(e.starts_with("channel:"), "{e}");
        // `slice` is a fraction of the depth (0 to 1), of slices only.
        for bad in ["slice=2", "slice=-0.5", "slice=1.01"] {
            let e = ViewState::from_query(&format!("mode=slice&{bad}")).unwrap_err();
            assert!(
                e.starts_with("slice:") && e.contains("0 to 1"),
                "{bad}: {e}"
            );
        }
        for q in ["slice=0.3", "mode=mip&slice=0.3", "slice=0.5"] {
            let e = ViewState::from_query(q).unwrap_err();
            assert!(
                e.starts_with("slice:") && e.contains("mode=slice"),
                "{q}: {e}"
            );
        }
        let s = ViewState::from_query("mode=slice&slice=1").unwrap();
        assert_eq!(s.slice_z, 1.0);
        assert_eq!(ViewState::from_query(&s.to_query()).unwrap(), s);
    }

    #[test]
    fn the_octree_traversal_draws_dvr_and_says_so_elsewhere() {
        let scene = Scene::new([1.0; 3], vec![[64, 64, 64], [32, 32, 32]]);
        let view = |q: &str, channels: usize| {
            ViewState::from_query(q)
                .unwrap()
                .params(&scene, [0.0, 255.0], &[], channels, false)
        };
        let v = view("traversal=octree", 1).unwrap();
        assert_eq!(v.params.traversal, Traversal::Octree);
        assert_eq!(v.octree_depth, DEFAULT_DEPTH);
        assert_eq!(
            view("traversal=octree&octree_depth=2", 1)
                .unwrap()
                .octree_depth,
            2
        );
        let e = view("octree_depth=2", 1).unwrap_err();
        assert!(
            e.starts_with("octree_depth:") && e.contains("traversal=octree"),
            "{e}"
        );
        assert_eq!(view("", 1).unwrap().params.traversal, Traversal::PageTable);
        for q in ["mode=mip&traversal=octree", "mode=slice&traversal=octree"] {
            let e = view(q, 1).unwrap_err();
            assert!(e.contains("`traversal`") && e.contains("DVR"), "{q}: {e}");
        }
        // An octree too large for its tables: refused up front, not when
        // a frame attaches it.
        let e = view("traversal=octree&channels=0", 1 << 16).unwrap_err();
        assert!(e.starts_with("traversal:") && e.contains("depth"), "{e}");
    }
}
