//! Ray-guided rendering on the CPU through the virtual memory: DVR, MIP and
//! slices. Every sample is a lookup `(level, channel, p)`; a miss records a
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
//! - **Tiles.** Work is split into 32×16-pixel tiles (rows of tiles in
//!   parallel on all cores) so that neighbouring rays share bricks.
//! - The level of detail is re-evaluated only where the pixel footprint
//!   crosses a level boundary, not per sample; transparent samples skip
//!   the colour lookup.

use crate::image::Image;
use crate::reference::{
    composite_visible, mip_color, mix_channels, slice_point, step_t, RenderMode, RenderParams,
};
use brickyard_cache::brick::BrickKey;
use brickyard_cache::cells;
use brickyard_cache::ranges::BrickRanges;
use brickyard_cache::vm::{BrickRef, Requests, VirtualMemory};
use brickyard_core::camera::{intersect_box, intersect_box_inv, Projection, Ray, Vec3};
use brickyard_core::transfer::TfEval;
use brickyard_core::{cast_slice, dispatch_dtype, Dims3, Sample, TransferFunction};
use rayon::prelude::*;
use std::sync::Arc;

pub use crate::reference::MAX_CHANNELS;

/// Tile width and height in pixels.
const TILE_W: usize = 32;
const TILE_H: usize = 16;

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
        }
    }

    /// Smallest voxel edge of level `l` in world units.
    pub fn voxel(&self, l: usize) -> f64 {
        let d = self.levels[l];
        let ext_zyx = [self.extent[2], self.extent[1], self.extent[0]];
        (0..3)
            .map(|a| ext_zyx[a] / d[a] as f64)
            .fold(f64::INFINITY, f64::min)
    }
}

/// Level of detail.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Lod {
    /// Always this level.
    Fixed(usize),
    /// Per sample, the level whose voxel matches the pixel footprint at the
    /// sample's distance, shifted by `bias` levels (negative: finer).
    Auto { bias: f64 },
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

    fn add(&mut self, o: &FrameStats) {
        self.samples += o.samples;
        self.exact += o.exact;
        self.unserved += o.unserved;
        self.skipped_bricks += o.skipped_bricks;
        self.steps += o.steps;
        self.transparent += o.transparent;
        self.skipped_cells += o.skipped_cells;
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

fn render_typed<T: Sample>(
    vm: &VirtualMemory,
    scene: &Scene,
    params: &RenderParams,
    lod: Lod,
    img: &mut Image,
    tiles: &mut Tiles,
) -> (FrameStats, Vec<Requests>) {
    let frame = Frame::new(vm, scene, params, lod);
    let w = params.width as usize;
    let tiles_x = w.div_ceil(TILE_W);
    let rg = params.camera.ray_gen(params.width, params.height);
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
                let walkers = if params.channels.is_empty() {
                    vec![Walker::new(&frame, scene.channel)]
                } else {
                    params
                        .channels
                        .iter()
                        .map(|c| Walker::new(&frame, c.channel))
                        .collect()
                };
                (walkers, vm.requests(), FrameStats::default())
            },
            |(mut walkers, mut req, mut st), (band, rows, redo)| {
                let multi = !params.channels.is_empty();
                let nrows = rows.len() / w;
                for (tx, x0) in (0..w).step_by(TILE_W).enumerate() {
                    if !redo[tx] {
                        continue;
                    }
                    let (samples, exact) = (st.samples, st.exact);
                    for r in 0..nrows {
                        let j = (band * TILE_H + r) as u32;
                        for i in x0..(x0 + TILE_W).min(w) {
                            let ray = rg.pixel_ray(i as u32, j);
                            rows[r * w + i] = match &params.mode {
                                RenderMode::Dvr => walkers[0].dvr(&ray, &mut req, &mut st),
                                RenderMode::Mip if multi => {
                                    match intersect_box(&ray, [0.0; 3], scene.extent) {
                                        Some(span) => {
                                            let mut best = [f32::NAN; MAX_CHANNELS];
                                            let mut hit = false;
                                            for (b, wk) in best.iter_mut().zip(walkers.iter_mut()) {
                                                if let Some(m) =
                                                    wk.mip_max(&ray, span, &mut req, &mut st)
                                                {
                                                    hit = true;
                                                    *b = m;
                                                }
                                            }
                                            if hit {
                                                mix_channels(&params.channels, best.into_iter())
                                            } else {
                                                [0.0; 4]
                                            }
                                        }
                                        None => [0.0; 4],
                                    }
                                }
                                RenderMode::Mip => walkers[0].mip(&ray, &mut req, &mut st),
                                RenderMode::Slice { origin, normal } => {
                                    match slice_point(&ray, *origin, *normal, scene.extent) {
                                        Some((wp, t)) if multi => {
                                            let mut v = [f32::NAN; MAX_CHANNELS];
                                            for (x, wk) in v.iter_mut().zip(walkers.iter_mut()) {
                                                *x = wk
                                                    .slice_value(wp, t, &mut req, &mut st)
                                                    .unwrap_or(f32::NAN);
                                            }
                                            mix_channels(&params.channels, v.into_iter())
                                        }
                                        Some((wp, t)) => {
                                            match walkers[0].slice_value(wp, t, &mut req, &mut st) {
                                                Some(v) if !v.is_nan() => {
                                                    let c = params.tf.lookup(v);
                                                    [c[0], c[1], c[2], 1.0]
                                                }
                                                _ => [0.0; 4],
                                            }
                                        }
                                        None => [0.0; 4],
                                    }
                                }
                            };
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

/// Per-frame constants.
struct Frame<'a> {
    vm: &'a VirtualMemory,
    scene: &'a Scene,
    params: &'a RenderParams,
    tf: &'a TransferFunction,
    /// The transfer function prepared for this frame's lookups.
    tf_eval: TfEval<'a>,
    lod: Lod,
    /// Voxels per level `[z, y, x]`.
    dims: Vec<Dims3>,
    /// Per level, voxels per world unit along `[z, y, x]`.
    scale: Vec<[f64; 3]>,
    /// Per level, the largest voxel coordinate `dims − 1`.
    qmax: Vec<[f64; 3]>,
    /// The same in [`Run`]'s fixed point.
    qmax_fix: Vec<[i64; 3]>,
    brick: Dims3,
    /// `log2(brick)` per axis when every edge is a power of two.
    brick_shift: Option<[u32; 3]>,
    /// Bricks per axis per level.
    bricks: Vec<Dims3>,
    apron: u64,
    /// Pool strides of a padded brick: `[z, y]` (x is 1).
    stride: [usize; 2],
    voxel: Vec<f64>,
    /// World length of one pixel at distance `t` is `fp_slope·t` in
    /// perspective (0 for orthographic views, where it does not vary).
    fp_slope: f64,
    /// DVR: per level, whether each brick of the scene's channel is
    /// transparent under the transfer function (from the ranges).
    transparent: Vec<Option<Vec<bool>>>,
    /// DVR: per level, for blocks of 2ᵐ×2ᵐ×2ᵐ bricks (`m = 1 ..=`
    /// [`MACRO_LEVELS`]), whether every brick of the block is transparent:
    /// `[level][m − 1]`, blocks `[z][y][x]` with their counts per axis.
    clear_blocks: Vec<Vec<(Dims3, Vec<bool>)>>,
    /// Per level, [`next_level_t`](Self::next_level_t).
    next_t: Vec<f64>,
    /// Per level, DVR and MIP steps: `dt` (world units), `1/dt` and the
    /// opacity-correction exponent `dt / reference step`.
    step: Vec<(f64, f64, f32)>,
    /// Per level, `1 / scale`.
    inv_scale: Vec<[f64; 3]>,
    /// Voxels per cell edge of a brick ([`brickyard_cache::cells`]).
    cells: cells::CellGrid,
    /// `log2(cell edge)` per axis when every edge is a power of two.
    cell_shift: Option<[u32; 3]>,
    /// Per axis, per brick coordinate `x`, its part of the cell index:
    /// `x / edge` times the cells of the faster axes.
    cell_part: [Vec<u16>; 3],
}

impl<'a> Frame<'a> {
    fn new(
        vm: &'a VirtualMemory,
        scene: &'a Scene,
        params: &'a RenderParams,
        lod: Lod,
    ) -> Frame<'a> {
        let cfg = vm.config();
        let padded = vm.padded();
        let nl = scene.levels.len();
        let fp_slope = match params.camera.projection {
            Projection::Perspective { .. } => params.camera.pixel_footprint(1.0, params.height),
            Projection::Orthographic { .. } => 0.0,
        };
        let transparent: Vec<Option<Vec<bool>>> = (0..nl)
            .map(|l| {
                let r = scene.ranges.as_ref()?.level(l)?;
                if !matches!(params.mode, RenderMode::Dvr) || scene.channel >= r.channels {
                    return None;
                }
                let n = r.bricks.iter().product::<u64>() as usize;
                let off = scene.channel * n;
                Some(
                    r.range[off..off + n]
                        .iter()
                        .map(|&[lo, hi]| params.tf.max_opacity(lo, hi) <= 0.0)
                        .collect(),
                )
            })
            .collect();
        let spv = params.samples_per_voxel;
        let reference = params.reference_step.unwrap_or(scene.voxel(0));
        let bricks: Vec<Dims3> = scene
            .levels
            .iter()
            .map(|d| [0, 1, 2].map(|a| d[a].div_ceil(cfg.brick[a])))
            .collect();
        let clear_blocks = (0..nl)
            .map(|l| match &transparent[l] {
                Some(t) => clear_blocks(bricks[l], t),
                None => vec![],
            })
            .collect();
        let mut frame = Frame {
            clear_blocks,
            next_t: vec![],
            step: (0..nl)
                .map(|l| {
                    let dt = scene.voxel(l) / spv;
                    (dt, 1.0 / dt, (dt / reference) as f32)
                })
                .collect(),
            inv_scale: scene
                .levels
                .iter()
                .map(|d| [0, 1, 2].map(|a| 1.0 / (d[a] as f64 / scene.extent[2 - a])))
                .collect(),
            vm,
            scene,
            params,
            tf: &params.tf,
            tf_eval: params.tf.evaluator(),
            lod,
            dims: scene.levels.clone(),
            scale: scene
                .levels
                .iter()
                .map(|d| [0, 1, 2].map(|a| d[a] as f64 / scene.extent[2 - a]))
                .collect(),
            qmax: scene
                .levels
                .iter()
                .map(|d| d.map(|x| (x - 1) as f64))
                .collect(),
            qmax_fix: scene
                .levels
                .iter()
                .map(|d| d.map(|x| ((x - 1) as i64) << 32))
                .collect(),
            brick: cfg.brick,
            brick_shift: cfg
                .brick
                .iter()
                .all(|b| b.is_power_of_two())
                .then(|| cfg.brick.map(|b| b.trailing_zeros())),
            bricks,
            apron: cfg.apron,
            stride: [padded[1] * padded[2], padded[2]],
            voxel: (0..nl).map(|l| scene.voxel(l)).collect(),
            fp_slope,
            transparent,
            cells: vm.cell_grid(),
            cell_part: {
                let g = vm.cell_grid();
                let stride = [g.count[1] * g.count[2], g.count[2], 1];
                [0, 1, 2].map(|a| {
                    (0..cfg.brick[a])
                        .map(|x| ((x / g.edge[a]) * stride[a]) as u16)
                        .collect()
                })
            },
            cell_shift: vm
                .cell_grid()
                .edge
                .iter()
                .all(|e| e.is_power_of_two())
                .then(|| vm.cell_grid().edge.map(|e| e.trailing_zeros())),
        };
        frame.next_t = (0..nl).map(|l| frame.compute_next_level_t(l)).collect();
        frame
    }

    fn levels(&self) -> usize {
        self.dims.len()
    }

    /// Index in a padded brick whose first voxel (apron excluded) is `lo`
    /// of the level's voxel `v`.
    #[inline(always)]
    fn local_index(&self, v: Dims3, lo: Dims3) -> usize {
        let a = self.apron;
        ((v[0] - lo[0] + a) as usize) * self.stride[0]
            + ((v[1] - lo[1] + a) as usize) * self.stride[1]
            + (v[2] - lo[2] + a) as usize
    }

    /// The brick holding voxel `v`.
    #[inline]
    fn brick_of(&self, v: Dims3) -> Dims3 {
        match self.brick_shift {
            Some(s) => [v[0] >> s[0], v[1] >> s[1], v[2] >> s[2]],
            None => [
                v[0] / self.brick[0],
                v[1] / self.brick[1],
                v[2] / self.brick[2],
            ],
        }
    }

    /// The cell of base voxel `u` of a brick (brick coordinates, apron
    /// excluded): [`cells::CellGrid::index`] by table.
    #[inline(always)]
    fn cell_of(&self, u: Dims3) -> usize {
        let [z, y, x] = &self.cell_part;
        (z[u[0] as usize] + y[u[1] as usize] + x[u[2] as usize]) as usize
    }

    /// The cell coordinate along axis `a` of brick coordinate `x`.
    #[inline(always)]
    fn cell_coord(&self, a: usize, x: u64) -> u64 {
        match self.cell_shift {
            Some(s) => x >> s[a],
            None => x / self.cells.edge[a],
        }
    }

    /// The voxel box `[lo, hi)` of the largest block of transparent bricks
    /// (see `clear_blocks`) around the transparent brick `b` of level `l`
    /// whose box is `[lo, hi)`.
    #[inline]
    fn clear_box(&self, l: usize, b: Dims3, lo: Dims3, hi: Dims3) -> (Dims3, Dims3) {
        let mut found = (lo, hi);
        for (m, (n, clear)) in self.clear_blocks[l].iter().enumerate() {
            let s = m as u32 + 1;
            let c = b.map(|x| x >> s);
            if !clear[((c[0] * n[1] + c[1]) * n[2] + c[2]) as usize] {
                break;
            }
            let d = self.dims[l];
            let blo = [0, 1, 2].map(|a| (c[a] << s) * self.brick[a]);
            let bhi = [0, 1, 2].map(|a| (blo[a] + (self.brick[a] << s)).min(d[a]));
            found = (blo, bhi);
        }
        found
    }

    /// The voxel box `[lo, hi)` of cell `cell` of the brick `[blo, bhi)`.
    #[cfg(test)]
    fn cell_box(&self, cell: usize, blo: Dims3, bhi: Dims3) -> (Dims3, Dims3) {
        let c = self.cells.coords(cell);
        let e = self.cells.edge;
        let lo = [0, 1, 2].map(|a| blo[a] + c[a] * e[a]);
        let hi = [0, 1, 2].map(|a| (lo[a] + e[a]).min(bhi[a]));
        (lo, hi)
    }

    /// The level a sample at distance `t` asks for.
    fn level_at(&self, t: f64) -> usize {
        let n = self.levels();
        match self.lod {
            Lod::Fixed(l) => l.min(n - 1),
            // In perspective, before the first threshold (which lies
            // slightly early) the level is 0 without a logarithm: most
            // rays start there.
            Lod::Auto { .. }
                if self.fp_slope > 0.0 && t < self.next_t.first().copied().unwrap_or(0.0) =>
            {
                0
            }
            Lod::Auto { bias } => {
                let fp = match self.fp_slope {
                    0.0 => self.params.camera.pixel_footprint(t, self.params.height),
                    slope => slope * t,
                };
                let l = (fp / self.voxel[0]).log2() + bias;
                if l.is_finite() && l > 0.0 {
                    (l.floor() as usize).min(n - 1)
                } else {
                    0
                }
            }
        }
    }

    /// The distance from which on the level may be coarser than `level`
    /// (infinity when it never changes).
    fn next_level_t(&self, level: usize) -> f64 {
        self.next_t[level]
    }

    fn compute_next_level_t(&self, level: usize) -> f64 {
        match self.lod {
            Lod::Auto { bias } if level + 1 < self.levels() && self.fp_slope > 0.0 => {
                // fp(t) / voxel0 = 2^(level + 1 − bias)
                let t = self.voxel[0] * (level as f64 + 1.0 - bias).exp2() / self.fp_slope;
                // Slightly early rather than late: `level_at` decides.
                t * (1.0 - 1e-9)
            }
            _ => f64::INFINITY,
        }
    }

    /// Clamped voxel base and trilinear fractions of the world point `w`
    /// (`[x, y, z]`) at level `l`: voxel coordinate `q = w·dims/extent −
    /// ½` clamped to `[0, dims − 1]` (the reference sampler's rule, with
    /// the division folded into a scale).
    #[inline(always)]
    fn coords(&self, l: usize, w: Vec3) -> (Dims3, [f32; 3]) {
        let s = &self.scale[l];
        let m = &self.qmax[l];
        // Written out per axis (no closures) to keep the hot loop flat.
        let qz = clamp(w[2] * s[0] - 0.5, m[0]);
        let qy = clamp(w[1] * s[1] - 0.5, m[1]);
        let qx = clamp(w[0] * s[2] - 0.5, m[2]);
        // q ≥ 0: truncation is floor; through i64, which converts in one
        // instruction each way (u64 does not).
        // SAFETY: `clamp` gives a finite value in [0, dims − 1].
        let (bz, by, bx) = unsafe {
            (
                qz.to_int_unchecked::<i64>(),
                qy.to_int_unchecked::<i64>(),
                qx.to_int_unchecked::<i64>(),
            )
        };
        (
            [bz as u64, by as u64, bx as u64],
            [
                (qz - bz as f64) as f32,
                (qy - by as f64) as f32,
                (qx - bx as f64) as f32,
            ],
        )
    }

    /// After step `k − 1`, which lies in the box `[lo, hi)` (voxels) of the
    /// track's level, the box is crossed without sampling: the step to go
    /// on from, the first from `k` on whose voxel base may lie outside the
    /// box or whose parameter reaches `limit` (or one step earlier).
    /// Estimated from where the ray leaves the box, moved early by a bound
    /// on the rounding of the sampler's coordinates. Where that bound is
    /// over a quarter step (a ray nearly parallel to a voxel plane), the
    /// landing is checked on the step before and backed off: the voxel base
    /// moves monotonically along the ray, so the steps inside a box are
    /// consecutive, and a landing whose previous step is inside (and before
    /// `limit`) skips only steps inside.
    #[inline]
    fn land(
        &self,
        ray: &Ray,
        track: &Track,
        g: Grid,
        k: u64,
        (lo, hi): (Dims3, Dims3),
        limit: f64,
    ) -> u64 {
        let (first, margin) = track.first_out(g, (lo, hi), limit);
        if margin < 0.25 {
            // The steps before it lie before the sampler's exit.
            return first(margin).max(k);
        }
        // A ray nearly parallel to a voxel plane: land on the estimate,
        // check the step before, and back off an overshoot.
        let mut kk = first(0.0);
        while kk > k {
            let t = step_t(g.base_t, kk - 1, g.dt);
            if t < limit && inside(self.coords(track.level, ray.at(t)).0, lo, hi) {
                break;
            }
            kk -= 1;
        }
        kk.max(k)
    }

    /// Ray `ray` in the voxel coordinates of level `l`.
    /// `inv_dir`: `1 / ray.dir`; `t_end`: where the ray leaves the volume.
    fn track(&self, l: usize, ray: &Ray, inv_dir: Vec3, t_end: f64) -> Track {
        let s = self.scale[l];
        let alpha = [0, 1, 2].map(|a| ray.origin[2 - a] * s[a] - 0.5);
        let beta = [0, 1, 2].map(|a| ray.dir[2 - a] * s[a]);
        // 1/beta within an ulp or two (estimates only).
        let inv_beta = [0, 1, 2].map(|a| inv_dir[2 - a] * self.inv_scale[l][a]);
        // The sampler's voxel coordinate (`coords` of `ray.at(t)`) differs
        // from `alpha + beta·t` by a few ulps of the terms: bound it by
        // 1e-15 (about 9 ulps) of their magnitude, in voxels, and turn that
        // into a distance along the ray through the axis' 1/beta.
        let slack = (0..3)
            .filter(|&a| beta[a] != 0.0)
            .map(|a| {
                let err = 1e-15 * (alpha[a].abs() + (beta[a] * t_end).abs() + 2.0);
                err * inv_beta[a].abs()
            })
            .fold(0.0, f64::max);
        let dt = self.step[l].0;
        Track {
            alpha,
            beta,
            inv_beta,
            dims: self.dims[l],
            level: l,
            dq: beta.map(|b| (b * dt * FIX) as i64),
            slack,
        }
    }
}

/// The step grid of a ray at one level: step `k` at `base_t + (k + ½)·dt`.
#[derive(Clone, Copy)]
struct Grid {
    base_t: f64,
    dt: f64,
    inv_dt: f64,
}

/// The steps of a ray through one resident brick, by fixed-point increments
/// (32 fractional bits) instead of from the ray parameter: voxel coordinate
/// `q = w·scale − ½` of the first step plus `beta·dt` per step, clamped to
/// the level like the general path's coordinates. The positions differ
/// from the general path's by rounding (below 1e-7 voxel for runs of up to
/// 1000 steps), and so do the samples (trilinear interpolation is
/// continuous). A step that rounding puts just outside the brick is
/// sampled on its face (base clamped, fraction 0 or 1): the same value.
#[derive(Clone)]
struct Run {
    /// The coordinate relative to the brick's first voxel: `q − lo·2³²`.
    q: [i64; 3],
    dq: [i64; 3],
    /// Where `q` is clamped: the volume's last voxel or the brick's last
    /// voxel with fraction 1, whichever comes first (below, the clamp is
    /// 0: the brick's first voxel with fraction 0, which the volume's
    /// first voxel is not above).
    qhi: [i64; 3],
    /// Voxels of the brick per axis, minus one.
    last: [i64; 3],
}

const FIX: f64 = (1u64 << 32) as f64;
/// The fraction bits of a fixed-point coordinate.
const FRAC: i64 = 0xffff_ffff;

impl Run {
    #[inline(always)]
    fn new(f: &Frame, l: usize, track: &Track, w: Vec3, lo: Dims3, hi: Dims3) -> Run {
        let s = f.scale[l];
        let m = f.qmax_fix[l];
        let q = [
            ((w[2] * s[0] - 0.5) * FIX) as i64,
            ((w[1] * s[1] - 0.5) * FIX) as i64,
            ((w[0] * s[2] - 0.5) * FIX) as i64,
        ];
        let last = [0, 1, 2].map(|a| (hi[a] - lo[a]) as i64 - 1);
        Run {
            q: [0, 1, 2].map(|a| q[a] - ((lo[a] as i64) << 32)),
            dq: track.dq,
            // (The fraction of `FRAC` converts to exactly 1.0 in f32.)
            qhi: [0, 1, 2].map(|a| (m[a] - ((lo[a] as i64) << 32)).min((last[a] << 32) | FRAC)),
            last,
        }
    }

    /// The current step's voxel base in the brick (apron excluded) and its
    /// fractions; then advance.
    #[cfg(test)]
    fn next(&mut self) -> (Dims3, [f32; 3]) {
        let r = self.current();
        self.advance(1);
        r
    }

    /// At step `j` (of a run ending at `end`), whose voxel base `u` (from
    /// [`current`](Self::current)) lies in a cell whose samples need no
    /// evaluation: move to the first step whose base lies in another cell
    /// (at least one on, at most `end`) and return it. Exact: the same step
    /// stepping one by one would stop at, found per axis in integer
    /// arithmetic from where the fixed-point coordinate crosses the cell's
    /// face (the base moves monotonically along each axis, and the clamps
    /// of `current` only hold it at the brick's and the volume's faces,
    /// which no cell face beyond them is).
    #[inline(always)]
    fn cross_cell(&mut self, f: &Frame, u: Dims3, (j, end): (u64, u64)) -> u64 {
        let mut m = u64::MAX;
        for (a, &ua) in u.iter().enumerate() {
            let (dq, e) = (self.dq[a], f.cells.edge[a] as i64);
            let c = f.cell_coord(a, ua) as i64;
            // Forwards, the base leaves when it reaches the next cell's
            // first voxel `h` (none past the brick's last voxel): after
            // ⌈(h·2³² − q) / dq⌉ steps. Backwards, when it drops below the
            // cell's first voxel `l` (none below the brick's first): after
            // ⌊(q − l·2³²) / −dq⌋ + 1 = ⌈(q − l·2³² + 1) / −dq⌉ steps.
            let fwd = dq > 0;
            let face = if fwd { (c + 1) * e } else { c * e };
            let exists = if fwd {
                face <= self.last[a]
            } else {
                face > 0 && dq < 0
            };
            let d = if fwd {
                (face << 32) - self.q[a]
            } else {
                self.q[a] - (face << 32) + 1
            };
            if exists {
                debug_assert!(d > 0);
                m = m.min(div_ceil_exact(d, dq.abs()));
            }
        }
        let jn = j.saturating_add(m).clamp(j + 1, end.max(j + 1));
        self.advance(jn - j);
        jn
    }

    /// Move on by `m` steps (exactly `m` single steps: integer arithmetic).
    #[inline(always)]
    fn advance(&mut self, m: u64) {
        for a in 0..3 {
            self.q[a] += self.dq[a] * m as i64;
        }
    }

    /// The current step's voxel base in the brick (apron excluded) and its
    /// fractions.
    #[inline(always)]
    fn current(&self) -> (Dims3, [f32; 3]) {
        let mut u = [0u64; 3];
        let mut fr = [0f32; 3];
        for a in 0..3 {
            // (`max`/`min`: `clamp` checks its bounds every time.)
            let q = self.q[a].max(0).min(self.qhi[a]);
            u[a] = (q >> 32) as u64;
            fr[a] = (q & FRAC) as f32 * (1.0 / FIX as f32);
        }
        (u, fr)
    }
}

/// A ray in the voxel coordinates of one level, `q(t) = alpha + beta·t`
/// per axis `[z, y, x]`, for finding where it leaves boxes of voxels.
#[derive(Clone, Copy)]
struct Track {
    alpha: [f64; 3],
    beta: [f64; 3],
    inv_beta: [f64; 3],
    dims: Dims3,
    level: usize,
    /// [`Run`]'s fixed-point increment per step of the level: `beta·dt`.
    dq: [i64; 3],
    /// How far (in `t`) a crossing of a voxel plane by the sampler's
    /// coordinates may lie from the crossing of `alpha + beta·t`, on any
    /// axis (infinite for an axis nearly parallel to the planes).
    slack: f64,
}

impl Track {
    /// The first grid step at or after where the ray leaves the box
    /// `[lo, hi)` or reaches `limit`, moved early by `margin` steps and a
    /// thousandth of a step (ties land before; the rounding of the exit,
    /// `step_t` and this expression is far below that for any ray of
    /// fewer than 10⁹ steps); and the margin that makes it safe, `slack`
    /// in steps: with that margin, every step before it has its sampler
    /// voxel base in the box and lies before `limit`.
    #[inline(always)]
    fn first_out(
        &self,
        g: Grid,
        (lo, hi): (Dims3, Dims3),
        limit: f64,
    ) -> (impl Fn(f64) -> u64, f64) {
        let te = self.exit_t(lo, hi, limit);
        let first = move |margin: f64| {
            let x = (te - g.base_t) * g.inv_dt - 0.5 - margin - 1e-3;
            let i = x as i64; // finite; the cast saturates
            (if (i as f64) < x { i + 1 } else { i }).max(0) as u64
        };
        (first, self.slack * g.inv_dt)
    }

    /// The step a fixed-point [`Run`] through the box `[lo, hi)` ends at:
    /// [`first_out`](Self::first_out) with its margin, or without one for
    /// a ray nearly parallel to a voxel plane (whose steps lie on the box's
    /// face within rounding, where `Run` samples them).
    #[inline(always)]
    fn run_end(&self, g: Grid, bx: (Dims3, Dims3), limit: f64) -> u64 {
        let (first, margin) = self.first_out(g, bx, limit);
        first(if margin < 0.25 { margin } else { 0.0 })
    }

    /// About the ray parameter where the clamped voxel base leaves the box
    /// `[lo, hi)` (voxels), or `t_max` if it does not before (an estimate:
    /// [`Frame::land`] checks it).
    #[inline]
    fn exit_t(&self, lo: Dims3, hi: Dims3, t_max: f64) -> f64 {
        let mut t = t_max;
        for a in 0..3 {
            let b = self.beta[a];
            // (A comparison, not `f64::min`: a NaN is ignored either way,
            // and this is cheaper.)
            let ta = if b > 0.0 && hi[a] < self.dims[a] {
                (hi[a] as f64 - self.alpha[a]) * self.inv_beta[a]
            } else if b < 0.0 && lo[a] > 0 {
                (lo[a] as f64 - self.alpha[a]) * self.inv_beta[a]
            } else {
                continue;
            };
            if ta < t {
                t = ta;
            }
        }
        t
    }
}

/// What a walker knows about the brick it is in at one level.
#[derive(Clone, Copy)]
enum Content<'a, T> {
    /// Page tables not walked yet.
    Unresolved,
    Unmapped,
    /// EMPTY (0) or CONSTANT.
    Value(f32),
    Data(&'a [T]),
}

#[derive(Clone, Copy)]
struct Cached<'a, T> {
    /// Voxel box `[lo, hi)` of the brick (empty: nothing cached).
    lo: Dims3,
    hi: Dims3,
    brick: Dims3,
    content: Content<'a, T>,
    /// Value range (apron included); NaN: unknown.
    range: [f32; 2],
    /// DVR: every sample in it is transparent.
    transparent: bool,
    /// DVR, resident bricks: bit `i` set when every sample of cell `i` is
    /// transparent.
    clear_cells: u64,
    /// Samples that missed it, not yet handed to the request collector.
    missed: u32,
    /// Pool slot of a resident brick (`u32::MAX` otherwise).
    slot: u32,
    /// The slot is marked as used at its own level this frame (or needs
    /// no mark).
    marked: bool,
}

impl<T> Cached<'_, T> {
    const NONE: Self = Cached {
        lo: [1; 3],
        hi: [0; 3],
        brick: [0; 3],
        content: Content::Unresolved,
        range: [f32::NAN; 2],
        transparent: false,
        clear_cells: 0,
        missed: 0,
        slot: u32::MAX,
        marked: true,
    };

    #[inline(always)]
    fn contains(&self, v: Dims3) -> bool {
        inside(v, self.lo, self.hi)
    }
}

// A brick's clear cells are one bit each in a u64.
const _: () = assert!(cells::MAX_CELLS <= 64);

/// Entries of a walker's brick memo (a power of two).
const MEMO: usize = 1024;

/// One thread's view of one channel: the current brick per level, and a
/// memo of every brick resolved this frame (direct-mapped by level and
/// brick), so that the rays of a tile, which enter the same bricks one
/// after another, walk the page tables about once per brick.
struct Walker<'f, 'a, T> {
    f: &'f Frame<'a>,
    channel: usize,
    cache: Vec<Cached<'a, T>>,
    memo_key: Vec<u64>,
    memo: Vec<Cached<'a, T>>,
}

impl<'f, 'a, T: Sample> Walker<'f, 'a, T> {
    fn new(f: &'f Frame<'a>, channel: usize) -> Self {
        Walker {
            f,
            channel,
            cache: vec![Cached::NONE; f.levels()],
            memo_key: vec![u64::MAX; MEMO],
            memo: vec![Cached::NONE; MEMO],
        }
    }

    /// Hand every pending miss to the collector.
    fn flush(&mut self, req: &mut Requests) {
        for l in 0..self.cache.len() {
            self.flush_level(l, req);
        }
    }

    #[inline]
    fn flush_level(&mut self, l: usize, req: &mut Requests) {
        if self.cache[l].missed > 0 {
            self.flush_misses(l, req);
        }
    }

    #[cold]
    fn flush_misses(&mut self, l: usize, req: &mut Requests) {
        let c = &mut self.cache[l];
        let b = c.brick;
        req.add(
            BrickKey::new(
                l as u8,
                self.channel as u16,
                [b[0] as u32, b[1] as u32, b[2] as u32],
            ),
            c.missed,
        );
        c.missed = 0;
    }

    /// Make the cache of level `l` hold the brick of voxel `v`.
    /// `exact`: the sample asks for level `l` (not a stand-in lookup).
    #[inline(always)]
    fn enter(&mut self, l: usize, v: Dims3, req: &mut Requests, exact: bool) -> &Cached<'a, T> {
        if !self.cache[l].contains(v) {
            self.refill(l, v, req, exact);
        } else if exact && !self.cache[l].marked {
            self.mark(l);
        }
        &self.cache[l]
    }

    #[cold]
    fn refill(&mut self, l: usize, v: Dims3, req: &mut Requests, exact: bool) {
        self.flush_level(l, req);
        let f = self.f;
        let brick = f.brick_of(v);
        let key = ((l as u64) << 60) | (brick[0] << 40) | (brick[1] << 20) | brick[2];
        let slot =
            (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> (64 - MEMO.trailing_zeros())) as usize;
        if self.memo_key[slot] == key {
            self.cache[l] = self.memo[slot];
            if exact && !self.cache[l].marked {
                self.mark(l);
            }
            return;
        }
        let bs = f.brick;
        let d = f.dims[l];
        let lo = [brick[0] * bs[0], brick[1] * bs[1], brick[2] * bs[2]];
        let hi = [
            (lo[0] + bs[0]).min(d[0]),
            (lo[1] + bs[1]).min(d[1]),
            (lo[2] + bs[2]).min(d[2]),
        ];
        let range = f
            .scene
            .ranges
            .as_ref()
            .and_then(|r| r.level(l))
            .filter(|r| self.channel < r.channels)
            .map(|r| r.get(self.channel, brick))
            .unwrap_or([f32::NAN; 2]);
        let transparent = self.channel == f.scene.channel
            && f.transparent[l].as_ref().is_some_and(|t| {
                let nb = f.bricks[l];
                t[((brick[0] * nb[1] + brick[1]) * nb[2] + brick[2]) as usize]
            });
        self.cache[l] = Cached {
            lo,
            hi,
            brick,
            content: Content::Unresolved,
            range,
            transparent,
            clear_cells: 0,
            missed: 0,
            slot: u32::MAX,
            marked: true,
        };
        if !transparent {
            self.resolve(l, exact);
        }
        self.memo_key[slot] = key;
        self.memo[slot] = self.cache[l];
    }

    /// Mark the cached brick of level `l` as used at its own level.
    #[cold]
    fn mark(&mut self, l: usize) {
        let c = &mut self.cache[l];
        self.f.vm.mark_exact(c.slot);
        c.marked = true;
    }

    /// Walk the page tables for the cached brick of level `l`.
    #[cold]
    fn resolve(&mut self, l: usize, exact: bool) {
        let f = self.f;
        let c = &mut self.cache[l];
        c.content = match f.vm.brick(l, self.channel, c.brick, exact) {
            BrickRef::Unmapped => Content::Unmapped,
            BrickRef::Empty => Content::Value(0.0),
            BrickRef::Constant(v) => Content::Value(v),
            BrickRef::Data { voxels, slot } => {
                c.slot = slot;
                c.marked = exact;
                if matches!(f.params.mode, RenderMode::Dvr)
                    && self.channel == f.scene.channel
                    && f.scene.skip_cells
                {
                    let mut m = 0u64;
                    for (i, &[lo, hi]) in f.vm.cell_ranges(slot).iter().enumerate() {
                        if !f.tf_eval.range_visible(lo, hi) {
                            m |= 1 << i;
                        }
                    }
                    c.clear_cells = m;
                }
                Content::Data(cast_slice::<T>(voxels))
            }
        };
        if let Content::Value(v) = c.content {
            c.range = [v, v];
            if matches!(f.params.mode, RenderMode::Dvr) && self.channel == f.scene.channel {
                c.transparent = f.tf.lookup_visible(v).is_none();
            }
        }
    }

    /// The value at normalized position `p` asked at level `l`, whose
    /// voxel base `base` and fractions `frac` are given and whose brick is
    /// cached; falls back to coarser levels on a miss. Counts the sample.
    #[inline(always)]
    fn value(
        &mut self,
        l: usize,
        w: Vec3,
        base: Dims3,
        frac: [f32; 3],
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        st.samples += 1;
        let (mut base, mut frac) = (base, frac);
        for lv in l..self.cache.len() {
            if lv > l {
                (base, frac) = self.f.coords(lv, w);
                self.enter(lv, base, req, false);
            }
            if matches!(self.cache[lv].content, Content::Unresolved) {
                self.resolve(lv, lv == l);
            }
            let c = &mut self.cache[lv];
            match c.content {
                Content::Data(vox) => {
                    st.exact += (lv == l) as u64;
                    let [sz, sy] = self.f.stride;
                    let i = self.f.local_index(base, c.lo);
                    return Some(trilinear(vox, i, sz, sy, frac));
                }
                Content::Value(v) => {
                    st.exact += (lv == l) as u64;
                    return Some(v);
                }
                Content::Unmapped if lv == l => c.missed += 1,
                Content::Unmapped => {}
                Content::Unresolved => unreachable!("resolved above"),
            }
        }
        // Nothing resident serves the sample: request the coarser bricks
        // on the way too, so something shows soon. (A sample served by a
        // stand-in requests only its own level: stand-ins evicted for
        // finer bricks are not fetched back.)
        for c in &mut self.cache[l + 1..] {
            c.missed += 1;
        }
        st.unserved += 1;
        None
    }

    fn dvr(&mut self, ray: &Ray, req: &mut Requests, st: &mut FrameStats) -> [f32; 4] {
        let mut acc = [0.0f32; 4];
        let f = self.f;
        let extent = f.scene.extent;
        let d = ray.dir;
        let inv_dir = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        let Some((t0, t1)) = intersect_box_inv(ray, inv_dir, [0.0; 3], extent) else {
            return acc;
        };
        // Steps keep the reference renderer's positions while the level
        // stays the same; at a level change the sample there becomes step 0
        // of the new level's grid.
        let mut level = f.level_at(t0);
        let mut next_t = f.next_level_t(level);
        let (mut dt, mut inv_dt, mut exponent) = f.step[level];
        let mut track = f.track(level, ray, inv_dir, t1);
        let mut base_t = t0;
        let mut k = 0u64;
        loop {
            let t = step_t(base_t, k, dt);
            if t >= t1 {
                break;
            }
            k += 1;
            if t >= next_t {
                let l = f.level_at(t);
                if l != level {
                    // The new level's step grid has this sample as its
                    // step 0: the next one lies a step of the new level on.
                    level = l;
                    (dt, inv_dt, exponent) = f.step[level];
                    base_t = t - 0.5 * dt;
                    k = 1;
                    track = f.track(level, ray, inv_dir, t1);
                }
                next_t = f.next_level_t(level);
                if next_t <= t {
                    // At the boundary `level_at` and the threshold may
                    // disagree by a rounding: ask again at the next step.
                    next_t = t + dt;
                }
            }
            st.steps += 1;
            let w = ray.at(t);
            let (vb, frac) = f.coords(level, w);
            let c = self.enter(level, vb, req, true);
            if c.transparent {
                let (lo, hi) = f.clear_box(level, c.brick, c.lo, c.hi);
                st.skipped_bricks += 1;
                let g = Grid { base_t, dt, inv_dt };
                k = f.land(ray, &track, g, k, (lo, hi), t1.min(next_t));
                continue;
            }
            if let Content::Data(vox) = c.content {
                // Resident at the level asked for: take every step the ray
                // makes in this brick here.
                let (lo, hi, clear) = (c.lo, c.hi, c.clear_cells);
                let g = Grid { base_t, dt, inv_dt };
                let limit = t1.min(next_t);
                // Steps k − 1 … end − 1 lie in the brick (up to rounding:
                // see `Run`).
                let end = track.run_end(g, (lo, hi), limit).max(k);
                let mut run = Run::new(f, level, &track, w, lo, hi);
                let (mut n, mut passed) = (0u64, 0u64);
                let mut j = k - 1;
                let done = loop {
                    if j >= end {
                        break false;
                    }
                    let (u, fr) = run.current();
                    let cell = f.cell_of(u);
                    if clear >> cell & 1 != 0 {
                        // A cell whose samples are all transparent: on to
                        // the step where the ray leaves it.
                        passed += 1;
                        j = run.cross_cell(f, u, (j, end));
                        continue;
                    }
                    run.advance(1);
                    j += 1;
                    n += 1;
                    let v = trilinear(vox, f.local_index(u, [0; 3]), f.stride[0], f.stride[1], fr);
                    if let Some(c) = f.tf_eval.lookup_visible(v) {
                        if composite_visible(&mut acc, c, exponent) {
                            break true;
                        }
                    } else {
                        st.transparent += 1;
                    }
                };
                st.samples += n;
                st.exact += n;
                st.skipped_cells += passed;
                st.steps += end - k;
                if done {
                    break;
                }
                k = end;
                continue;
            }
            let Some(v) = self.value(level, w, vb, frac, req, st) else {
                let g = Grid { base_t, dt, inv_dt };
                k = self.skip_unserved(level, ray, &track, (g, k), t1.min(next_t), st);
                continue;
            };
            if let Some(c) = f.tf_eval.lookup_visible(v) {
                if composite_visible(&mut acc, c, exponent) {
                    break;
                }
            }
        }
        acc
    }

    /// After a sample that nothing resident could serve: cross the rest of
    /// the level's brick in one jump (first frames would otherwise walk
    /// the whole fallback chain for every sample of a region with nothing
    /// to show). The steps jumped count as unserved samples and as misses
    /// of the brick, so its request keeps its weight. Returns the step
    /// index to continue from.
    fn skip_unserved(
        &mut self,
        level: usize,
        ray: &Ray,
        track: &Track,
        (g, k): (Grid, u64),
        limit: f64,
        st: &mut FrameStats,
    ) -> u64 {
        let c = &self.cache[level];
        let kn = self.f.land(ray, track, g, k, (c.lo, c.hi), limit);
        let c = &mut self.cache[level];
        let n = kn - k;
        st.samples += n;
        st.unserved += n;
        st.steps += n;
        c.missed = c.missed.saturating_add(n as u32);
        kn
    }

    fn mip(&mut self, ray: &Ray, req: &mut Requests, st: &mut FrameStats) -> [f32; 4] {
        let Some(span) = intersect_box(ray, [0.0; 3], self.f.scene.extent) else {
            return [0.0; 4];
        };
        match self.mip_max(ray, span, req, st) {
            Some(best) => mip_color(self.f.tf, true, best),
            None => mip_color(self.f.tf, false, f32::NAN),
        }
    }

    /// The largest value along the ray inside `(t0, t1)` (NaN ignored; NaN
    /// if every sample was NaN or unserved), `None` when the ray takes no
    /// sample.
    fn mip_max(
        &mut self,
        ray: &Ray,
        (t0, t1): (f64, f64),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        let f = self.f;
        let level = f.level_at(t0);
        let (dt, inv_dt, _) = f.step[level];
        let track = f.track(level, ray, ray.dir.map(|d| 1.0 / d), t1);
        let mut best = f32::NAN;
        let mut hit = false;
        let mut k = 0u64;
        loop {
            let t = step_t(t0, k, dt);
            if t >= t1 {
                break;
            }
            k += 1;
            hit = true;
            st.steps += 1;
            let w = ray.at(t);
            let (vb, frac) = f.coords(level, w);
            let c = self.enter(level, vb, req, true);
            // NaN range or best: no skip.
            if c.range[1] <= best {
                let (lo, hi) = (c.lo, c.hi);
                st.skipped_bricks += 1;
                let g = Grid {
                    base_t: t0,
                    dt,
                    inv_dt,
                };
                k = f.land(ray, &track, g, k, (lo, hi), t1);
                continue;
            }
            if let Content::Data(vox) = c.content {
                // Resident: a fixed-point run through the brick (as in
                // DVR), crossing cells whose maximum cannot raise `best`.
                let (lo, hi, slot) = (c.lo, c.hi, c.slot);
                let g = Grid {
                    base_t: t0,
                    dt,
                    inv_dt,
                };
                let end = track.run_end(g, (lo, hi), t1).max(k);
                let ranges = f.scene.skip_cells.then(|| f.vm.cell_ranges(slot));
                let mut run = Run::new(f, level, &track, w, lo, hi);
                let (mut n, mut j) = (0u64, k - 1);
                while j < end {
                    let (u, fr) = run.current();
                    let cell = f.cell_of(u);
                    // NaN bound or best: no skip.
                    if ranges.is_some_and(|r| r[cell][1] <= best) {
                        st.skipped_cells += 1;
                        j = run.cross_cell(f, u, (j, end));
                        continue;
                    }
                    run.advance(1);
                    j += 1;
                    n += 1;
                    let v = trilinear(vox, f.local_index(u, [0; 3]), f.stride[0], f.stride[1], fr);
                    // f32::max ignores NaN.
                    best = best.max(v);
                }
                st.samples += n;
                st.exact += n;
                st.steps += end - k;
                k = end;
                continue;
            }
            match self.value(level, w, vb, frac, req, st) {
                // f32::max ignores NaN.
                Some(v) => best = best.max(v),
                None => {
                    let g = Grid {
                        base_t: t0,
                        dt,
                        inv_dt,
                    };
                    k = self.skip_unserved(level, ray, &track, (g, k), t1, st)
                }
            }
        }
        hit.then_some(best)
    }

    /// The value at the world point `w` of a slice, `t` along the ray.
    fn slice_value(
        &mut self,
        w: Vec3,
        t: f64,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        let f = self.f;
        let level = f.level_at(t);
        let (vb, frac) = f.coords(level, w);
        self.enter(level, vb, req, true);
        self.value(level, w, vb, frac, req, st)
    }
}

/// Blocks of 2ᵐ×2ᵐ×2ᵐ bricks.
const MACRO_LEVELS: usize = 3;

/// For `m = 1 ..= MACRO_LEVELS`: the block counts per axis and whether
/// every brick of each block of 2ᵐ bricks per axis is transparent, from the
/// per-brick flags `t` (`[z][y][x]`, `n` bricks per axis).
fn clear_blocks(n: Dims3, t: &[bool]) -> Vec<(Dims3, Vec<bool>)> {
    let mut out: Vec<(Dims3, Vec<bool>)> = Vec::with_capacity(MACRO_LEVELS);
    let (mut prev_n, mut prev) = (n, t.to_vec());
    for _ in 0..MACRO_LEVELS {
        let nn = prev_n.map(|x| x.div_ceil(2));
        let mut cur = vec![true; (nn[0] * nn[1] * nn[2]) as usize];
        for z in 0..prev_n[0] {
            for y in 0..prev_n[1] {
                for x in 0..prev_n[2] {
                    if !prev[((z * prev_n[1] + y) * prev_n[2] + x) as usize] {
                        cur[(((z / 2) * nn[1] + y / 2) * nn[2] + x / 2) as usize] = false;
                    }
                }
            }
        }
        out.push((nn, cur.clone()));
        (prev_n, prev) = (nn, cur);
    }
    out
}

/// `⌈n / d⌉` for `0 ≤ n, 0 < d < 2⁵³` through a float division (fewer
/// instructions than an integer one), exact: both convert exactly, the
/// quotient is correctly rounded, and a quotient `k + r/d` that is not a
/// whole number lies at least `1/d` from one, more than half an ulp of it.
#[inline(always)]
fn div_ceil_exact(n: i64, d: i64) -> u64 {
    debug_assert!(n >= 0 && d > 0 && n < 1 << 53 && d < 1 << 53);
    let q = n as f64 / d as f64;
    // (Not `ceil`, which is a library call without SSE4.1.)
    let t = q as i64;
    (t + ((t as f64) < q) as i64) as u64
}

/// Whether voxel `v` lies in the box `[lo, hi)`.
#[inline(always)]
fn inside(v: Dims3, lo: Dims3, hi: Dims3) -> bool {
    v[0] >= lo[0] && v[0] < hi[0] && v[1] >= lo[1] && v[1] < hi[1] && v[2] >= lo[2] && v[2] < hi[2]
}

/// `x` clamped to `[0, hi]` for a finite `hi ≥ 0`, NaN to 0: always a
/// finite value in the range (a max and a min, without branches).
#[inline(always)]
fn clamp(x: f64, hi: f64) -> f64 {
    let y = if x > 0.0 { x } else { 0.0 };
    if y < hi {
        y
    } else {
        hi
    }
}

/// Trilinear sample of a padded brick at local index `i` (the base voxel)
/// with strides `sz`, `sy` (x: 1), by [`brickyard_core::trilinear`].
#[inline(always)]
fn trilinear<T: Sample>(v: &[T], i: usize, sz: usize, sy: usize, f: [f32; 3]) -> f32 {
    // One bounds check for the farthest corner instead of eight.
    let v = &v[i..i + sz + sy + 2];
    brickyard_core::trilinear_of(
        // SAFETY: every corner index is at most `sz + sy + 1`, the last
        // element of the slice just checked.
        |dz, dy, dx| unsafe { v.get_unchecked(dz * sz + dy * sy + dx) }.to_f32(),
        f,
        T::DTYPE.is_float(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_cache::vm::VmConfig;
    use brickyard_core::camera::{Camera, Projection};
    use brickyard_core::DType;

    /// A ray, its span, step grid and track, and a step on it.
    type RandomStep = (Ray, (f64, f64), Grid, Track, u64);

    /// One level of `dims` voxels in bricks of `brick`, world size
    /// `extent`, a DVR view of it (for frames at level 0).
    fn fixture(dims: Dims3, brick: Dims3, extent: Vec3) -> (VirtualMemory, Scene, RenderParams) {
        let levels = vec![dims];
        let cfg = VmConfig {
            brick,
            pool_bytes: 1 << 22,
            ..Default::default()
        };
        let vm = VirtualMemory::new(&levels, 1, DType::U8, cfg);
        let scene = Scene::new(extent, levels);
        let cam = Camera::fit(
            extent,
            30.0,
            20.0,
            Projection::Perspective { fov_y_deg: 35.0 },
        );
        let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
        (vm, scene, RenderParams::new(4, 4, cam, tf, RenderMode::Dvr))
    }

    /// Uniform numbers in `[0, 1)` from a linear congruential generator.
    fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
        move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// The ray towards `target` along `dir` (normalized here) from `far`
    /// away, its span through the volume, its step grid of `dt` and track
    /// at level 0, and the step at fraction `u` of its steps (at least
    /// step 1); `None` when it misses the volume or takes under 2 steps.
    fn random_step(
        f: &Frame,
        extent: Vec3,
        (target, dir, far): (Vec3, Vec3, f64),
        dt: f64,
        u: f64,
    ) -> Option<RandomStep> {
        let n = dir.iter().map(|d| d * d).sum::<f64>().sqrt();
        let dir = dir.map(|d| d / n);
        let origin = [0, 1, 2].map(|a| target[a] - far * dir[a]);
        let ray = Ray { origin, dir };
        let (t0, t1) = intersect_box(&ray, [0.0; 3], extent)?;
        let g = Grid {
            base_t: t0,
            dt,
            inv_dt: 1.0 / dt,
        };
        // The track of this step size (not the level's).
        let track = f.track(0, &ray, ray.dir.map(|d| 1.0 / d), t1);
        let track = Track {
            dq: track.beta.map(|b| (b * dt * FIX) as i64),
            ..track
        };
        let steps = ((t1 - t0) / dt) as u64;
        if steps < 2 {
            return None;
        }
        let k0 = 1 + (u * (steps - 1) as f64) as u64;
        Some((ray, (t0, t1), g, track, k0))
    }

    /// `land` against stepping one by one: it never passes a step whose
    /// voxel base leaves the box (or that reaches the limit), and it lands
    /// at most one step early — on random rays, including ones nearly
    /// parallel to the voxel planes and ones from far away. The fast path's
    /// fixed-point run through a brick takes the same steps at the same
    /// positions (to 1e-6 voxel).
    #[test]
    fn landing_equals_stepping_through_the_box() {
        let dims = [40u64, 56, 48];
        let extent = [1.3, 0.9, 1.7];
        let (vm, scene, params) = fixture(dims, [8; 3], extent);
        let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let mut rnd = uniform(0x9e37_79b9_7f4a_7c15);
        let (mut checked, mut exact) = (0, 0);
        for trial in 0..4000 {
            let far = if trial % 4 == 0 { 1e4 } else { 3.0 };
            let target = [0, 1, 2].map(|a| rnd() * extent[a]);
            let mut dir = [0, 1, 2].map(|_| rnd() - 0.5);
            match trial % 5 {
                // Nearly or exactly parallel to a family of planes.
                0 => dir[trial % 3] = 1e-13 * (rnd() - 0.5),
                1 => dir[(trial + 1) % 3] = 0.0,
                2 => dir[trial % 3] = 1e-17,
                _ => {}
            }
            let dt = f.voxel[0] * (0.3 + 1.2 * rnd());
            // A step inside the volume, the box of its brick or of a cell.
            let Some((ray, (t0, t1), g, track, k0)) =
                random_step(&f, extent, (target, dir, far), dt, rnd())
            else {
                continue;
            };
            let (v, _) = f.coords(0, ray.at(step_t(t0, k0 - 1, dt)));
            let b = f.brick_of(v);
            let blo = [0, 1, 2].map(|a| b[a] * 8);
            let bhi = [0, 1, 2].map(|a| (blo[a] + 8).min(dims[a]));
            let (lo, hi) = if trial % 2 == 0 {
                (blo, bhi)
            } else {
                f.cell_box(f.cell_of([0, 1, 2].map(|a| v[a] - blo[a])), blo, bhi)
            };
            let limit = if trial % 3 == 0 {
                t0 + rnd() * (t1 - t0)
            } else {
                t1
            };
            let mut want = k0;
            loop {
                let t = step_t(t0, want, dt);
                if t >= limit || !inside(f.coords(0, ray.at(t)).0, lo, hi) {
                    break;
                }
                want += 1;
            }
            let got = f.land(&ray, &track, g, k0, (lo, hi), limit);
            assert!(
                got <= want && got + 1 >= want,
                "trial {trial}: landed at {got}, first step out is {want} (from {k0})"
            );
            checked += 1;
            exact += (got == want) as u32;
            if trial % 2 == 0 {
                // The fast path's run through the brick: the same steps,
                // at the general path's positions up to rounding.
                let end = track.run_end(g, (lo, hi), limit).max(k0);
                assert!(
                    end <= want && end + 1 >= want,
                    "trial {trial}: run ends at {end}"
                );
                let w = ray.at(step_t(t0, k0 - 1, dt));
                let mut run = Run::new(&f, 0, &track, w, lo, hi);
                for k in k0 - 1..end {
                    let (u, fr) = run.next();
                    let (b, frac) = f.coords(0, ray.at(step_t(t0, k, dt)));
                    for a in 0..3 {
                        let q_run = (lo[a] + u[a]) as f64 + fr[a] as f64;
                        let q = b[a] as f64 + frac[a] as f64;
                        assert!(
                            (q_run - q).abs() < 1e-6,
                            "trial {trial} step {k}: {q_run} vs {q}"
                        );
                    }
                }
            }
        }
        assert!(checked > 2000, "{checked} rays checked");
        assert!(exact * 10 > checked * 9, "{exact} of {checked} exact");
    }

    /// From step `j` of `run`, stepping one by one: the first step (at most
    /// `end`) whose voxel base lies in another cell, and the run there.
    fn step_out_of_cell(f: &Frame, run: &Run, (j, end): (u64, u64)) -> (u64, Run) {
        let cell = f.cell_of(run.current().0);
        let mut step = run.clone();
        let mut k = j;
        while k < end {
            step.advance(1);
            k += 1;
            if f.cell_of(step.current().0) != cell {
                break;
            }
        }
        (k, step)
    }

    /// `Run::current` (one clamp of the brick-relative coordinate) equals
    /// clamping to the volume first and then to the brick (base to the
    /// brick's first or last voxel, fraction 0 or 1), near every face.
    #[test]
    fn current_equals_clamping_to_volume_then_brick() {
        let dims = [70u64, 61, 77];
        let brick = [32u64, 32, 16];
        let (vm, scene, params) = fixture(dims, brick, [1.1, 0.8, 1.4]);
        let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let mut rnd = uniform(5);
        let track = f.track(
            0,
            &Ray {
                origin: [0.0; 3],
                dir: [0.6, 0.0, 0.8],
            },
            [1.0 / 0.6, f64::INFINITY, 1.25],
            10.0,
        );
        for b in [[0u64, 0, 0], [2, 1, 4], [1, 1, 2]] {
            let lo = [0, 1, 2].map(|a| b[a] * brick[a]);
            let hi = [0, 1, 2].map(|a| (lo[a] + brick[a]).min(dims[a]));
            let mut run = Run::new(&f, 0, &track, [0.0; 3], lo, hi);
            for _ in 0..20_000 {
                // Absolute coordinates around the brick and the volume.
                let qa = [0, 1, 2].map(|a| {
                    let v = lo[a] as f64 - 2.0 + (hi[a] - lo[a] + 4) as f64 * rnd();
                    let x = (v * FIX) as i64;
                    match (rnd() * 4.0) as u32 {
                        0 => x & !FRAC,
                        1 => x | FRAC,
                        _ => x,
                    }
                });
                run.q = [0, 1, 2].map(|a| qa[a] - ((lo[a] as i64) << 32));
                let want: (Dims3, [f32; 3]) = {
                    let mut u = [0u64; 3];
                    let mut fr = [0f32; 3];
                    for a in 0..3 {
                        let qmax = (f.qmax[0][a] * FIX) as i64;
                        let q = qa[a].clamp(0, qmax);
                        let bb = (q >> 32) - lo[a] as i64;
                        let last = (hi[a] - lo[a]) as i64 - 1;
                        (u[a], fr[a]) = if bb < 0 {
                            (0, 0.0)
                        } else if bb > last {
                            (last as u64, 1.0)
                        } else {
                            (bb as u64, (q & FRAC) as f32 / FIX as f32)
                        };
                    }
                    (u, fr)
                };
                assert_eq!(run.current(), want, "brick {b:?} q {qa:?}");
            }
        }
    }

    /// `Run::cross_cell` against stepping where the fixed-point coordinate
    /// lands exactly on a cell face after a whole number of steps (which
    /// random rays almost never do).
    #[test]
    fn crossing_onto_a_face_equals_stepping() {
        let dims = [70u64, 61, 77];
        let brick = [64u64, 64, 32];
        let (vm, scene, params) = fixture(dims, brick, [1.1, 0.8, 1.4]);
        let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let mut rnd = uniform(23);
        let (lo, hi) = ([0u64; 3], [64u64, 61, 32]);
        let last = [0, 1, 2].map(|a| (hi[a] - lo[a]) as i64 - 1);
        let mut on_plane = 0;
        for _ in 0..20_000 {
            let steps = 1 + (rnd() * 12.0) as i64;
            let mut run = Run {
                q: [0; 3],
                dq: [0; 3],
                qhi: [0, 1, 2].map(|a| (last[a] << 32) | FRAC),
                last,
            };
            for (a, &la) in last.iter().enumerate() {
                let e = f.cells.edge[a] as i64;
                let faces = (la + e) / e;
                let face = e * (1 + (rnd() * (faces - 1).max(1) as f64) as i64).min(faces - 1);
                let dq =
                    ((1i64 << 32) as f64 * (0.05 + rnd())) as i64 * [1, -1][(rnd() * 2.0) as usize];
                // `steps` steps from exactly on the face (or a random start).
                let q = if rnd() < 0.7 {
                    (face << 32) - steps * dq
                } else {
                    (rnd() * (la << 32) as f64) as i64
                };
                run.q[a] = q.clamp(0, la << 32);
                run.dq[a] = dq;
            }
            let end = 200;
            let (u, _) = run.current();
            let (want, _) = step_out_of_cell(&f, &run, (0, end));
            let mut jump = run.clone();
            assert_eq!(
                jump.cross_cell(&f, u, (0, end)),
                want,
                "{:?} {:?}",
                run.q,
                run.dq
            );
            // The case this test is for: the jump ends exactly on a voxel
            // plane.
            on_plane += jump.q.iter().any(|&q| q & FRAC == 0) as u32;
        }
        assert!(on_plane > 5_000, "{on_plane} jumps onto a voxel plane");
    }

    /// The float division of `Run::cross_cell` equals the integer one, for
    /// whole quotients, their neighbours and random ones.
    #[test]
    fn float_division_is_exact() {
        let mut rnd = uniform(17);
        for i in 0..200_000u64 {
            let d = match i % 4 {
                0 => 1 + (rnd() * 16.0) as i64,
                1 => 1 + (rnd() * (1u64 << 34) as f64) as i64,
                2 => (1i64 << 32) + (rnd() * 1000.0) as i64 - 500,
                _ => 1 + (rnd() * (1u64 << 52) as f64) as i64,
            };
            let k = (rnd() * 2000.0) as i64;
            let n = match i % 3 {
                0 => k * d,
                1 => (k * d + (rnd() * 3.0) as i64 - 1).max(0),
                _ => (rnd() * (1u64 << 44) as f64) as i64,
            }
            .min((1i64 << 53) - 1);
            assert_eq!(div_ceil_exact(n, d), ((n + d - 1) / d) as u64, "{n} / {d}");
        }
    }

    /// `Run::cross_cell` lands exactly where stepping one by one leaves
    /// the cell (or at the run's end), for power-of-two cells and others,
    /// on random rays including ones parallel to voxel planes.
    #[test]
    fn crossing_a_cell_equals_stepping_out_of_it() {
        for brick in [[32u64, 32, 16], [24, 20, 32]] {
            let dims = [70u64, 61, 77];
            let extent = [1.1, 0.8, 1.4];
            let (vm, scene, params) = fixture(dims, brick, extent);
            let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
            assert!(f.cells.len() > 4, "{:?}", f.cells);
            let mut rnd = uniform(0x51ed_2701_f00d_cafe);
            let (mut crossings, mut multi) = (0, 0);
            for trial in 0..3000 {
                let target = [0, 1, 2].map(|a| rnd() * extent[a]);
                let mut dir = [0, 1, 2].map(|_| rnd() - 0.5);
                match trial % 4 {
                    0 => dir[trial % 3] = 0.0,
                    1 => dir[trial % 3] = 1e-12 * (rnd() - 0.5),
                    _ => {}
                }
                let dt = f.voxel[0] * (0.2 + 1.5 * rnd());
                let Some((ray, (t0, t1), g, track, k0)) =
                    random_step(&f, extent, (target, dir, 3.0), dt, rnd())
                else {
                    continue;
                };
                let w = ray.at(step_t(t0, k0 - 1, dt));
                let (v, _) = f.coords(0, w);
                let b = f.brick_of(v);
                let lo = [0, 1, 2].map(|a| b[a] * brick[a]);
                let hi = [0, 1, 2].map(|a| (lo[a] + brick[a]).min(dims[a]));
                let end = track.run_end(g, (lo, hi), t1).max(k0);
                let mut run = Run::new(&f, 0, &track, w, lo, hi);
                let mut j = k0 - 1;
                while j < end {
                    let (u, _) = run.current();
                    let (want, step) = step_out_of_cell(&f, &run, (j, end));
                    let mut jump = run.clone();
                    let got = jump.cross_cell(&f, u, (j, end));
                    assert_eq!(got, want, "brick {brick:?} trial {trial} from step {j}");
                    assert_eq!(jump.q, step.q, "brick {brick:?} trial {trial}");
                    crossings += 1;
                    multi += (got > j + 1) as u32;
                    run.advance(1);
                    j += 1;
                }
            }
            assert!(
                crossings > 20_000 && multi > 5_000,
                "{crossings} crossings, {multi} long"
            );
        }
    }

    /// `level_at`'s shortcut before the first threshold gives the level
    /// of the footprint formula, in perspective and orthographic views
    /// (where it does not apply) and for several biases.
    #[test]
    fn level_shortcut_equals_the_footprint_formula() {
        let levels = vec![[64u64, 64, 64], [32, 32, 32], [16, 16, 16], [8, 8, 8]];
        let vm = VirtualMemory::new(&levels, 1, DType::U8, VmConfig::default());
        let extent = [1.0, 1.0, 1.0];
        let scene = Scene::new(extent, levels);
        let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
        let mut checked = 0;
        for proj in [
            Projection::Perspective { fov_y_deg: 40.0 },
            Projection::Orthographic { height: 3.0 },
        ] {
            let cam = Camera::fit(extent, 30.0, 20.0, proj);
            for bias in [-1.5, 0.0, 0.7, 2.0] {
                let params = RenderParams::new(40, 30, cam, tf.clone(), RenderMode::Dvr);
                let f = Frame::new(&vm, &scene, &params, Lod::Auto { bias });
                for i in 0..20_000 {
                    let t = i as f64 * 1e-3;
                    let fp = cam.pixel_footprint(t, 30);
                    let l = (fp / f.voxel[0]).log2() + bias;
                    let want = if l.is_finite() && l > 0.0 {
                        (l.floor() as usize).min(3)
                    } else {
                        0
                    };
                    assert_eq!(f.level_at(t), want, "{proj:?} bias {bias} t {t}");
                    checked += (want > 0) as u32;
                }
            }
        }
        assert!(checked > 10_000, "{checked}");
    }
}
