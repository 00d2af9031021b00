//! The CPU frame driver: ray-guided DVR, MIP and slices through the
//! virtual memory, a frame (or its unsettled tiles) at a time. Every sample is a lookup `(level, channel, p)`; a miss records a
//! request and is answered by the finest resident coarser level, so a frame
//! never waits for I/O. Each frame reports its completeness: the fraction of
//! samples served at the level they asked for.
//!
//! Sampling follows the reference renderer's rules (step positions
//! `t0 + (k + ½)·Δ`, opacity correction, early termination at 0.99), so a
//! complete frame at a fixed level equals the in-core reference image.
//!
//! # How it is fast
//!
//! - **Brick walking.** Each thread keeps, per level, the brick its last
//!   sample fell into: the page tables are walked (and usage marked) once
//!   per brick a ray enters, not once per sample. Samples inside the
//!   current brick read the pool directly with a trilinear kernel
//!   specialised for the sample type. Misses are counted per brick and
//!   handed to the request collector when the walker leaves it.
//! - **Empty-space skipping.** A brick whose value range (from the store's
//!   statistics, [`BrickRanges`], or an EMPTY/CONSTANT page entry) the
//!   transfer function maps to zero opacity is crossed in one jump, without
//!   a lookup and without being requested, so it is never loaded. In a MIP
//!   a brick whose maximum cannot raise the ray's maximum is skipped the
//!   same way. Skipping never changes a complete frame: every skipped
//!   sample would have contributed nothing.
//! - **Entry depths.** Before a one-channel DVR frame's rays are walked,
//!   the cells and bricks that may show are projected and every pixel's
//!   nearest hit found (`entry.rs`); each ray starts its walk there,
//!   past the clear space in front of what it shows.
//! - **Tiles.** Work is split into 32×16-pixel tiles (rows of tiles in
//!   parallel on all cores) so that neighbouring rays share bricks.
//! - The level of detail is re-evaluated only where the pixel footprint
//!   crosses a level boundary, not per sample; transparent samples skip
//!   the colour lookup.
//!
//! # Where things are
//!
//! This file holds what a frame is ([`Scene`], [`Lod`], [`FrameStats`],
//! [`Tiles`]) and draws one: tiles in parallel, one walker per channel
//! shown, a pixel per ray handed to its mode. The walk through the bricks
//! (per-frame constants, landing, fixed-point runs and cells, the brick
//! memo and fallback) is `walk`; the modes are `dvr`, `mip` and `slice`;
//! what a sample becomes on screen is `optics`. Each has its WGSL twin
//! beside it (`gpu.rs` is the device's frame driver).
use crate::entry::Entries;
use crate::image::Image;
use crate::octree::dvr::{OctFrame, TableKey};
use crate::octree::{self, Octree};
use crate::params::{DebugCounts, RenderMode, RenderParams, Traversal};
use crate::walk::{Frame, Walker};
use crate::{mip, multi, slice, superslice};
use brickyard_cache::ranges::BrickRanges;
use brickyard_cache::vm::{Requests, VirtualMemory};
use brickyard_core::camera::{normalize, Vec3};
use brickyard_core::views::ViewRays;
use brickyard_core::{dispatch_dtype, Dims3, Sample};
use rayon::prelude::*;
use std::sync::{Arc, RwLock};

pub use crate::params::MAX_CHANNELS;

/// Tile width and height in pixels.
pub const TILE_W: usize = 32;
pub const TILE_H: usize = 16;

/// What the renderer needs to know about the volume besides the pages.
#[derive(Debug, Clone)]
pub struct Scene {
    /// World size `[x, y, z]` of the volume.
    pub extent: Vec3,
    /// Voxels per level, `[z, y, x]`.
    pub levels: Vec<Dims3>,
    pub channel: usize,
    /// Value ranges of the bricks, for empty-space skipping (`None`: only
    /// EMPTY/CONSTANT entries are skipped).
    pub ranges: Option<Arc<BrickRanges>>,
    /// DVR: cross the cells of resident bricks that the transfer function
    /// maps to zero opacity without sampling them (the image is the same
    /// either way; off only to measure or test the saving).
    pub skip_cells: bool,
    /// DVR: the per-sample work of runs through resident bricks in four
    /// f32 lanes (trilinear lerps, transfer function, compositing); `false`
    /// takes the scalar twin, which gives the same bits (tests compare
    /// the two).
    pub lanes: bool,
    /// DVR (page tables or the residency octree, one channel or several):
    /// start each ray at its entry depth (`entry.rs`: where it first meets a cell or brick
    /// that may show), found for the frame before the rays are walked;
    /// the image is the same either way (off only to measure or test).
    pub entry_depths: bool,
    /// DVR through the residency octree: where every channel shown has
    /// its brick at the step's level resident (or hidden), the steps
    /// through it in one fixed-point run, as through the page tables (the
    /// node's residency masks serve misses only); the image is the same
    /// within the runs' rounding. Off only to compare the octree's descent
    /// with the device's, which samples step by step.
    pub octree_runs: bool,
    /// DVR: on x86-64 processors with the x86-64-v3 instructions (AVX2,
    /// FMA, BMI1/2, LZCNT, MOVBE, F16C; detected at run time), walk the
    /// rays in a copy of the ray loop compiled for them ([`crate::isa`]);
    /// elsewhere, or `false`, the baseline build of the same code. The
    /// same bits either way (tests compare the two).
    pub x86_v3: bool,
    /// The residency octree kept beside the virtual memory, for
    /// [`Traversal::Octree`](crate::params::Traversal) (`None`: a frame
    /// that asks for it builds one from the virtual memory, of depth
    /// [`DEFAULT_DEPTH`](crate::octree::DEFAULT_DEPTH)). Read by the
    /// renderers during a frame; updated between frames
    /// ([`Octree::sync`](crate::octree::Octree::sync)).
    pub octree: Option<Arc<RwLock<Octree>>>,
    /// Set from outside (Ctrl-C): a frame drawn on the CPU leaves its
    /// remaining bands of tiles undrawn, and the caller drops it.
    pub stop: Option<Arc<std::sync::atomic::AtomicBool>>,
}

impl Scene {
    /// A scene of channel 0 of a volume with world size `extent` (`[x, y, z]`)
    /// and `levels` (voxels per level, `[z, y, x]`).
    pub fn new(extent: Vec3, levels: Vec<Dims3>) -> Scene {
        Scene {
            extent,
            levels,
            channel: 0,
            ranges: None,
            skip_cells: true,
            lanes: true,
            entry_depths: true,
            octree_runs: true,
            x86_v3: true,
            octree: None,
            stop: None,
        }
    }

    /// Whether [`Scene::stop`] was set.
    pub fn stopped(&self) -> bool {
        self.stop
            .as_ref()
            .is_some_and(|s| s.load(std::sync::atomic::Ordering::Relaxed))
    }

    /// Level `l`'s voxels across the extent on each axis (`[z, y, x]`,
    /// [`level_span`](brickyard_core::level_span)): a world point `w` is
    /// the level's continuous voxel coordinate `w·span/extent − ½`.
    pub fn span(&self, l: usize) -> [f64; 3] {
        brickyard_core::level_span(&self.levels, l)
    }

    /// Smallest voxel edge of level `l` in world units.
    pub fn voxel(&self, l: usize) -> f64 {
        let s = self.span(l);
        let ext_zyx = [self.extent[2], self.extent[1], self.extent[0]];
        (0..3)
            .map(|a| ext_zyx[a] / s[a])
            .fold(f64::INFINITY, f64::min)
    }
}

/// Level of detail.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Lod {
    /// Always this level.
    Fixed(usize),
    /// Per sample, the level whose voxel matches the pixel footprint at the
    /// sample's distance (level 0 where a pixel spans less than a level-0
    /// voxel), shifted by `bias` levels (negative: finer). A positive bias
    /// coarsens every sample, also those nearer than where the footprint
    /// reaches a level-0 voxel: a budget that raises it to shrink a view's
    /// working set (a camera inside the volume) gets what it asks for.
    Auto { bias: f64 },
}

impl Lod {
    /// The level a sample asks for where one pixel spans `footprint`
    /// world units, in a volume of `levels` levels whose level-0 voxel is
    /// `voxel0` (its smallest edge, [`Scene::voxel`]). Renderers and the
    /// viewer's readout (which reads what a view draws) share it.
    #[inline]
    pub fn level_for(self, footprint: f64, voxel0: f64, levels: usize) -> usize {
        match self {
            Lod::Fixed(l) => l.min(levels.max(1) - 1),
            Lod::Auto { bias } => {
                let l = (footprint / voxel0).log2().max(0.0) + bias;
                if l.is_finite() && l > 0.0 {
                    (l.floor() as usize).min(levels.max(1) - 1)
                } else {
                    0
                }
            }
        }
    }
}

/// Figures of one frame.
#[derive(Debug, Clone, Default)]
pub struct FrameStats {
    /// Samples taken (skipped empty space is not counted).
    pub samples: u64,
    /// Samples served at the level they asked for.
    pub exact: u64,
    /// Samples with nothing resident at all.
    pub unserved: u64,
    /// Bricks crossed without sampling (transparent or, in a MIP, unable
    /// to raise the maximum), counted per ray and brick.
    pub skipped_bricks: u64,
    /// Ray steps walked (DVR, MIP): samples plus steps inside skipped
    /// bricks before a jump.
    pub steps: u64,
    /// DVR: samples whose value the transfer function maps to zero
    /// opacity (taken, but adding nothing).
    pub transparent: u64,
    /// DVR: cells of resident bricks crossed without sampling (every
    /// sample in them transparent), counted per ray and cell.
    pub skipped_cells: u64,
    /// Octree traversal: nodes visited (every node of every descent).
    pub octree_nodes: u64,
    /// Octree traversal: nodes crossed without lookups (hidden for every
    /// channel, or of one value per channel), counted per ray and node.
    pub skipped_nodes: u64,
}

impl FrameStats {
    /// Fraction of samples served at the level they asked for.
    pub fn completeness(&self) -> f64 {
        if self.samples == 0 {
            1.0
        } else {
            self.exact as f64 / self.samples as f64
        }
    }

    /// Add another frame's (or a part's) figures to these.
    pub fn add(&mut self, o: &FrameStats) {
        self.samples += o.samples;
        self.exact += o.exact;
        self.unserved += o.unserved;
        self.skipped_bricks += o.skipped_bricks;
        self.steps += o.steps;
        self.transparent += o.transparent;
        self.skipped_cells += o.skipped_cells;
        self.octree_nodes += o.octree_nodes;
        self.skipped_nodes += o.skipped_nodes;
    }
}

/// Render one frame. Returns the image, its statistics and the request
/// collectors (hand them to `Session::finish_frame`).
pub fn render_frame(
    vm: &VirtualMemory,
    scene: &Scene,
    params: &RenderParams,
    lod: Lod,
) -> (Image, FrameStats, Vec<Requests>) {
    let mut img = Image::new(params.width, params.height);
    let mut tiles = Tiles::all(params.width, params.height);
    let (stats, reqs) = render_tiles(vm, scene, params, lod, &mut img, &mut tiles);
    if params.debug.is_some() {
        false_colour(&mut img);
    }
    (img, stats, reqs)
}

/// Tiles of a frame: which need drawing again. A tile is *settled* when
/// every sample in it was served at the level it asked for: drawn again
/// with the same parameters and level of detail, it gives the same pixels
/// (bricks arriving later change only tiles that were not).
#[derive(Debug, Clone, PartialEq)]
pub struct Tiles {
    pub width: u32,
    pub height: u32,
    /// Row-major over tiles; `true`: to draw.
    pub redo: Vec<bool>,
}

impl Tiles {
    /// Tiles of an image of `width` × `height` pixels, all to draw.
    pub fn all(width: u32, height: u32) -> Tiles {
        let n = (width as usize).div_ceil(TILE_W) * (height as usize).div_ceil(TILE_H);
        Tiles {
            width,
            height,
            redo: vec![true; n],
        }
    }

    /// Tiles of an image of `width` × `height` pixels, those in tile rows
    /// `rows` (of [`Tiles::rows_of`]) to draw: one band of the image.
    pub fn band(width: u32, height: u32, rows: std::ops::Range<u32>) -> Tiles {
        let mut t = Tiles::all(width, height);
        let per_row = (width as usize).div_ceil(TILE_W);
        for (i, r) in t.redo.iter_mut().enumerate() {
            *r = rows.contains(&((i / per_row) as u32));
        }
        t
    }

    /// Rows of tiles of an image `height` pixels tall.
    pub fn rows_of(height: u32) -> u32 {
        (height as usize).div_ceil(TILE_H) as u32
    }

    /// Pixel rows of tile rows `rows` in an image `height` pixels tall.
    pub fn pixel_rows(height: u32, rows: std::ops::Range<u32>) -> std::ops::Range<u32> {
        (rows.start * TILE_H as u32).min(height)..(rows.end * TILE_H as u32).min(height)
    }

    /// Tiles still to draw.
    pub fn count(&self) -> usize {
        self.redo.iter().filter(|r| **r).count()
    }
}

/// Draw again only the tiles of `img` (the last frame of the same view,
/// parameters and level of detail) that `tiles` marks, and mark afresh
/// which of them are still not settled. Pixels of the other tiles are
/// kept: they are what a full frame would draw (see [`Tiles`]). The
/// statistics and requests cover the tiles drawn.
pub fn render_tiles(
    vm: &VirtualMemory,
    scene: &Scene,
    params: &RenderParams,
    lod: Lod,
    img: &mut Image,
    tiles: &mut Tiles,
) -> (FrameStats, Vec<Requests>) {
    assert_eq!(
        (img.width, img.height, tiles.width, tiles.height),
        (params.width, params.height, params.width, params.height),
        "image, tiles and parameters of one size"
    );
    dispatch_dtype!(vm.dtype(), T => { render_typed::<T>(vm, scene, params, lod, img, tiles) })
}

/// A DVR of several channels: per channel shown, the scene of that
/// channel and the parameters of a one-channel DVR through its transfer
/// function, over the same geometry.
pub(crate) fn channel_parts(
    scene: &Scene,
    params: &RenderParams,
) -> (Vec<Scene>, Vec<RenderParams>) {
    params
        .channels
        .iter()
        .map(|c| {
            let sc = Scene {
                channel: c.channel,
                ..scene.clone()
            };
            let p = RenderParams {
                tf: c.dvr_tf(),
                channels: vec![],
                ..params.clone()
            };
            (sc, p)
        })
        .unzip()
}

/// The frames of [`channel_parts`], each with its channel's level range
/// (`params.channels`).
pub(crate) fn channel_frames<'a>(
    vm: &'a VirtualMemory,
    scenes: &'a [Scene],
    ch_params: &'a [RenderParams],
    params: &RenderParams,
    lod: Lod,
) -> Vec<Frame<'a>> {
    scenes
        .iter()
        .zip(ch_params)
        .zip(&params.channels)
        .map(|((sc, p), c)| {
            let mut f = Frame::new(vm, sc, p, lod);
            f.channel_levels = c.levels;
            f
        })
        .collect()
}

/// The scene's residency octree, or one made from what `vm` holds now
/// (at the default depth) when the scene has none.
pub(crate) enum SceneOctree<'a> {
    Kept(std::sync::RwLockReadGuard<'a, Octree>),
    Made(Box<Octree>),
}

impl std::ops::Deref for SceneOctree<'_> {
    type Target = Octree;
    fn deref(&self) -> &Octree {
        match self {
            SceneOctree::Kept(g) => g,
            SceneOctree::Made(o) => o,
        }
    }
}

pub(crate) fn scene_octree<'a>(scene: &'a Scene, vm: &VirtualMemory) -> SceneOctree<'a> {
    match &scene.octree {
        Some(o) => SceneOctree::Kept(o.read().expect("octree lock")),
        None => SceneOctree::Made(Box::new(
            Octree::of_vm(
                octree::DEFAULT_DEPTH,
                &scene.levels,
                vm,
                scene.ranges.as_deref(),
            )
            .expect("the default depth fits"),
        )),
    }
}

fn render_typed<T: Sample>(
    vm: &VirtualMemory,
    scene: &Scene,
    params: &RenderParams,
    lod: Lod,
    img: &mut Image,
    tiles: &mut Tiles,
) -> (FrameStats, Vec<Requests>) {
    let frame = Frame::new(vm, scene, params, lod);
    if let (RenderMode::Slice { origin, normal }, Some(views)) = (&params.mode, &params.views) {
        return superslice::draw::<T>(&frame, scene, (*origin, *normal), views, img, tiles);
    }
    // DVR of several channels: a frame per channel (its transfer function's
    // transparent bricks), over the same geometry.
    let dvr_multi = matches!(params.mode, RenderMode::Dvr) && !params.channels.is_empty();
    let (ch_scenes, ch_params) = if dvr_multi {
        channel_parts(scene, params)
    } else {
        (vec![], vec![])
    };
    let ch_frames = channel_frames(vm, &ch_scenes, &ch_params, params, lod);
    // MIP of several channels: where each channel's rays end (its window's).
    let ch_stops: Vec<f32> = params
        .channels
        .iter()
        .map(|c| crate::mip::stop_of_channel(params, c))
        .collect();
    // DVR through the residency octree: its tables for this frame.
    let by_octree = matches!(params.mode, RenderMode::Dvr) && params.traversal == Traversal::Octree;
    let tree = by_octree.then(|| scene_octree(scene, vm));
    let oct_frame = tree.as_deref().map(|t| {
        let frames: Vec<&Frame> = if dvr_multi {
            ch_frames.iter().collect()
        } else {
            vec![&frame]
        };
        let key = TableKey::new(t, scene, params, lod);
        OctFrame::cached(t, &frames, &key.used.clone(), key)
    });
    let w = params.width as usize;
    let tiles_x = w.div_ceil(TILE_W);
    let rg = ViewRays::new(
        &params.camera,
        params.views.as_ref(),
        params.width,
        params.height,
    );
    // DVR (page tables or octree, one channel or several): every ray's entry depth,
    // and the bricks rays now pass before it marked as the walk would.
    let entries =
        (matches!(params.mode, RenderMode::Dvr) && params.views.is_none() && scene.entry_depths)
            .then(|| {
                if dvr_multi {
                    Entries::of_channels(&ch_frames, &rg, tiles)
                } else {
                    Entries::new(&frame, &rg, tiles)
                }
            })
            .flatten();
    if let Some(e) = &entries {
        e.mark_passed(&frame, &rg);
    }
    let one = rg.single();
    // A slice's unit normal, once per frame.
    let slice_unit = match params.mode {
        RenderMode::Slice { normal, .. } => normalize(normal),
        _ => [0.0; 3],
    };
    // One view, one channel, no debug counts: a slice's pixels by its own
    // loop, without the per-pixel choices of the general one.
    let plane = match (&params.mode, one) {
        (RenderMode::Slice { origin, .. }, Some(g))
            if params.channels.is_empty() && params.debug.is_none() =>
        {
            let eye = g.is_perspective().then(|| g.eye());
            Some(slice::Plane::new(*origin, slice_unit, scene.extent, eye))
        }
        _ => None,
    };
    let parts: Vec<(FrameStats, Requests)> = img
        .rgba
        .par_chunks_mut(w * TILE_H)
        .zip(tiles.redo.par_chunks_mut(tiles_x))
        .enumerate()
        .map(|(band, (rows, redo))| (band, rows, redo))
        .fold(
            || -> (Vec<Walker<T>>, Requests, FrameStats) {
                // One walker per channel shown and one request collector,
                // per piece of work rayon splits the frame into (their
                // brick memos live for this frame).
                let walkers = if dvr_multi {
                    ch_frames
                        .iter()
                        .map(|f| Walker::new(f, f.scene.channel))
                        .collect()
                } else if params.channels.is_empty() {
                    vec![Walker::new(&frame, scene.channel)]
                } else {
                    params
                        .channels
                        .iter()
                        .zip(&ch_stops)
                        .map(|(c, &stop)| {
                            let mut wk = Walker::new(&frame, c.channel);
                            wk.mip_stop = stop;
                            wk
                        })
                        .collect()
                };
                (walkers, vm.requests(), FrameStats::default())
            },
            |(mut walkers, mut req, mut st), (band, rows, redo)| {
                // Stopped: the frame's other bands are left undrawn (a
                // band of a large image at many samples per voxel takes a
                // tenth of a second, the frame many seconds).
                if scene.stopped() {
                    return (walkers, req, st);
                }
                let multi = !params.channels.is_empty();
                let nrows = rows.len() / w;
                for (tx, x0) in (0..w).step_by(TILE_W).enumerate() {
                    if !redo[tx] {
                        continue;
                    }
                    let (samples, exact) = (st.samples, st.exact);
                    let x1 = (x0 + TILE_W).min(w);
                    // One view: the rays' offsets per column once per
                    // tile, per row once per row (the same rays).
                    let mut cols = [0.0; TILE_W];
                    if let Some(g) = one {
                        for i in x0..x1 {
                            cols[i - x0] = g.column(i as f64 + 0.5);
                        }
                    }
                    if let (Some(pl), Some(g)) = (&plane, one) {
                        for r in 0..nrows {
                            let sy = g.row((band * TILE_H + r) as f64 + 0.5);
                            let row = &mut rows[r * w + x0..r * w + x1];
                            for (px, &sx) in row.iter_mut().zip(&cols) {
                                let ray = g.ray_at(sx, sy);
                                *px = pl.pixel_one(&mut walkers[0], &ray, (&mut req, &mut st));
                            }
                        }
                        redo[tx] = st.exact - exact != st.samples - samples;
                        continue;
                    }
                    for r in 0..nrows {
                        let j = (band * TILE_H + r) as u32;
                        let sy = one.map(|g| g.row(j as f64 + 0.5));
                        for i in x0..x1 {
                            if entries
                                .as_ref()
                                .is_some_and(|e| e.shows_nothing(i, j as usize))
                            {
                                // What the walk would return, without a ray.
                                rows[r * w + i] = [0.0; 4];
                                continue;
                            }
                            let ray = match (one, sy) {
                                (Some(g), Some(sy)) => g.ray_at(cols[i - x0], sy),
                                _ => rg.pixel_ray(i as u32, j),
                            };
                            let before = params.debug.map(|d| counts(d, &st, &walkers));
                            rows[r * w + i] = match &params.mode {
                                RenderMode::Dvr if params.labels => {
                                    let entry =
                                        entries.as_ref().map(|e| (e.level, e.at(i, j as usize)));
                                    walkers[0].label_surface((&ray, entry), &mut req, &mut st)
                                }
                                RenderMode::Dvr if oct_frame.is_some() => {
                                    let entry =
                                        entries.as_ref().map(|e| (e.level, e.at(i, j as usize)));
                                    octree::dvr::dvr_pixel(
                                        &mut walkers,
                                        oct_frame.as_ref().expect("checked"),
                                        (&ray, entry),
                                        (&mut req, &mut st),
                                    )
                                }
                                RenderMode::Dvr if multi => {
                                    let entry =
                                        entries.as_ref().map(|e| (e.level, e.at(i, j as usize)));
                                    multi::dvr_pixel(
                                        &mut walkers,
                                        (&ray, entry),
                                        (&mut req, &mut st),
                                    )
                                }
                                RenderMode::Dvr => {
                                    let entry =
                                        entries.as_ref().map(|e| (e.level, e.at(i, j as usize)));
                                    walkers[0].dvr((&ray, entry), (&mut req, &mut st))
                                }
                                RenderMode::Mip if multi => mip::channels_pixel(
                                    &mut walkers,
                                    &ray,
                                    scene.extent,
                                    &params.channels,
                                    (&mut req, &mut st),
                                ),
                                RenderMode::Mip => walkers[0].mip(&ray, &mut req, &mut st),
                                RenderMode::Slice { origin, .. } => slice::pixel(
                                    &mut walkers,
                                    &ray,
                                    (*origin, slice_unit),
                                    params,
                                    scene.extent,
                                    (&mut req, &mut st),
                                ),
                            };
                            if let (Some(d), Some(b)) = (params.debug, before) {
                                let n = counts(d, &st, &walkers) - b;
                                rows[r * w + i] = [n as f32, 0.0, 0.0, 0.0];
                            }
                        }
                    }
                    // Settled: every sample of the tile at its own level.
                    redo[tx] = st.exact - exact != st.samples - samples;
                }
                (walkers, req, st)
            },
        )
        .map(|(mut walkers, mut req, st)| {
            for wk in walkers.iter_mut() {
                wk.flush(&mut req);
            }
            (st, req)
        })
        .collect();
    let mut stats = FrameStats::default();
    let mut reqs = Vec::with_capacity(parts.len());
    for (s, r) in parts {
        stats.add(&s);
        reqs.push(r);
    }
    (stats, reqs)
}

/// The count a debug image shows, so far in this piece of work.
fn counts<T: Sample>(d: DebugCounts, st: &FrameStats, walkers: &[Walker<T>]) -> u64 {
    match d {
        DebugCounts::Nodes => st.octree_nodes,
        DebugCounts::Bricks => walkers.iter().map(|w| w.touched).sum(),
        DebugCounts::Steps => st.steps,
    }
}

/// A debug image's counts to false colour: 0 black, then blue, green,
/// yellow and white at the largest count; opaque. [`render_frame`] does
/// this; after [`render_tiles`] the pixels hold the counts (in red, alpha
/// 0) until the caller calls this.
pub fn false_colour(img: &mut Image) {
    let px = &mut img.rgba;
    let most = px.iter().map(|p| p[0]).fold(0.0f32, f32::max);
    for p in px.iter_mut() {
        let n = p[0];
        *p = if n <= 0.0 {
            [0.0, 0.0, 0.0, 1.0]
        } else {
            let x = n / most * 4.0;
            let ramp = |a: f32| (x - a).clamp(0.0, 1.0);
            // blue rises, then green, then red, then blue back to white.
            let b = ramp(0.0) * (1.0 - ramp(1.0)) + ramp(3.0);
            [ramp(2.0), ramp(1.0), b.min(1.0), 1.0]
        };
    }
}
