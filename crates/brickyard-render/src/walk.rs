//! The walk of the CPU renderer: how a ray gets from sample to sample
//! through the virtual memory. This file holds the per-frame constants
//! ([`Frame`]: voxel scales, step lengths, level-of-detail thresholds,
//! transparent bricks and blocks, cell tables), the level a sample asks
//! for, the sampler's voxel coordinates, step positions and the trilinear
//! kernel on a brick of the pool. Beside it: `walk/bricks.rs` (the walker:
//! current brick per level, brick memo, page-table walks, misses and the
//! fallback to coarser levels), `walk/landing.rs` (crossing a box of
//! voxels without sampling: tracks, landings, blocks of transparent
//! bricks) and `walk/cells.rs` (fixed-point runs through a resident brick
//! and jumps over its clear cells). `walk.wgsl` is the device twin.

mod bricks;
mod cells;
mod landing;
#[cfg(test)]
mod testing;

pub(crate) use bricks::{Content, Walker};
pub(crate) use cells::Run;
pub(crate) use landing::{clear_blocks, first_step, max_blocks, Grid, MaxBlocks, Track};

use crate::cpu::{Lod, Scene};
use crate::lanes::F4;
use crate::optics::TfTable;
use crate::params::{RenderMode, RenderParams};
use brickyard_cache::cells::CellGrid;
use brickyard_cache::vm::VirtualMemory;
use brickyard_core::camera::{intersect_box_inv, Projection, Ray, Vec3};
use brickyard_core::transfer::TfEval;
use brickyard_core::{DType, Dims3, Sample, TransferFunction};

/// Per-frame constants.
pub(crate) struct Frame<'a> {
    pub(crate) vm: &'a VirtualMemory,
    pub(crate) scene: &'a Scene,
    pub(crate) params: &'a RenderParams,
    pub(crate) tf: &'a TransferFunction,
    /// The transfer function prepared for this frame's lookups.
    pub(crate) tf_eval: TfEval<'a>,
    /// The same in four lanes, for the DVR's runs through resident bricks.
    pub(crate) tf_table: TfTable,
    pub(crate) lod: Lod,
    /// Voxels per level `[z, y, x]`.
    pub(crate) dims: Vec<Dims3>,
    /// Per level, voxels per world unit along `[z, y, x]`.
    pub(crate) scale: Vec<[f64; 3]>,
    /// Per level, the largest voxel coordinate `dims − 1`.
    pub(crate) qmax: Vec<[f64; 3]>,
    /// The same in [`Run`]'s fixed point.
    pub(crate) qmax_fix: Vec<[i64; 3]>,
    pub(crate) brick: Dims3,
    /// `log2(brick)` per axis when every edge is a power of two.
    pub(crate) brick_shift: Option<[u32; 3]>,
    /// Bricks per axis per level.
    pub(crate) bricks: Vec<Dims3>,
    pub(crate) apron: u64,
    /// Pool strides of a padded brick: `[z, y]` (x is 1).
    pub(crate) stride: [usize; 2],
    pub(crate) voxel: Vec<f64>,
    /// World length of one pixel at distance `t` is `fp_slope·t` in
    /// perspective (0 for orthographic views, where it does not vary).
    pub(crate) fp_slope: f64,
    /// DVR: per level, whether each brick of the scene's channel is
    /// transparent under the transfer function (from the ranges).
    pub(crate) transparent: Vec<Option<Vec<bool>>>,
    /// DVR: per level, for blocks of 2ᵐ×2ᵐ×2ᵐ bricks (`m = 1 ..=`
    /// [`MACRO_LEVELS`](landing::MACRO_LEVELS)), whether every brick of the block is transparent:
    /// `[level][m − 1]`, blocks `[z][y][x]` with their counts per axis.
    pub(crate) clear_blocks: Vec<Vec<(Dims3, Vec<bool>)>>,
    /// MIP: per channel of the ranges and per level, the largest value of
    /// blocks of 2ᵐ×2ᵐ×2ᵐ bricks as `clear_blocks` has them (empty without
    /// ranges).
    pub(crate) max_blocks: Vec<Vec<MaxBlocks>>,
    /// Per level, [`next_level_t`](Self::next_level_t).
    pub(crate) next_t: Vec<f64>,
    /// Per level, DVR and MIP steps: `dt` (world units), `1/dt` and the
    /// opacity-correction exponent `dt / reference step`.
    pub(crate) step: Vec<(f64, f64, f32)>,
    /// Per level, `1 / scale`.
    pub(crate) inv_scale: Vec<[f64; 3]>,
    /// Voxels per cell edge of a brick ([`brickyard_cache::cells`]).
    pub(crate) cells: CellGrid,
    /// `log2(cell edge)` per axis when every edge is a power of two.
    pub(crate) cell_shift: Option<[u32; 3]>,
    /// Per axis, per brick coordinate `x`, its part of the cell index:
    /// `x / edge` times the cells of the faster axes.
    pub(crate) cell_part: [Vec<u16>; 3],
    /// DVR of several channels: this channel's level range
    /// ([`ChannelStyle::levels`](crate::params::ChannelStyle::levels));
    /// `None`: the levels the steps ask for.
    pub(crate) channel_levels: Option<[usize; 2]>,
    /// MIP: a ray ends at its first value of at least this (the window's
    /// [`saturation`](crate::mip::saturation); infinite: never).
    pub(crate) mip_stop: f32,
    /// DVR: walk the rays in the ray loop's x86-64-v3 copy
    /// ([`Scene::x86_v3`] and the processor has the instructions; never
    /// on other architectures, which have no such copy).
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    pub(crate) x86_v3: bool,
}

impl<'a> Frame<'a> {
    pub(crate) fn new(
        vm: &'a VirtualMemory,
        scene: &'a Scene,
        params: &'a RenderParams,
        lod: Lod,
    ) -> Frame<'a> {
        let cfg = vm.config();
        let padded = vm.padded();
        let nl = scene.levels.len();
        let fp_slope = match params.camera.projection {
            Projection::Perspective { .. } => {
                params.camera.pixel_footprint(1.0, params.lod_height())
            }
            Projection::Orthographic { .. } => 0.0,
        };
        let transparent: Vec<Option<Vec<bool>>> = (0..nl)
            .map(|l| {
                let sel = params.label_select.as_ref();
                let span = scene.span(l);
                let Some(r) = scene.ranges.as_ref().and_then(|r| r.level(l)) else {
                    // No statistics: a label image drawing only some
                    // labels still crosses the bricks their boxes miss.
                    let boxed = sel.is_some_and(|s| !s.hide && s.boxes.is_some());
                    if !(params.labels && boxed && matches!(params.mode, RenderMode::Dvr)) {
                        return None;
                    }
                    let d = scene.levels[l];
                    let n: u64 = (0..3).map(|a| d[a].div_ceil(cfg.brick[a])).product();
                    return Some(
                        (0..n as usize)
                            .map(|i| {
                                !sel.is_some_and(|s| {
                                    s.may_reach_brick(i, d, span, cfg.brick, cfg.apron)
                                })
                            })
                            .collect(),
                    );
                };
                if !matches!(params.mode, RenderMode::Dvr) || scene.channel >= r.channels {
                    return None;
                }
                let n = r.bricks.iter().product::<u64>() as usize;
                let off = scene.channel * n;
                Some(
                    r.range[off..off + n]
                        .iter()
                        .enumerate()
                        .map(|(i, &[lo, hi])| match params.labels {
                            // (Also bricks no label of a selection reaches.)
                            true => {
                                crate::optics::label_clear(lo, hi, sel)
                                    || sel.is_some_and(|s| {
                                        !s.may_reach_brick(
                                            i,
                                            scene.levels[l],
                                            span,
                                            cfg.brick,
                                            cfg.apron,
                                        )
                                    })
                            }
                            false => params.tf.max_opacity(lo, hi) <= 0.0,
                        })
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
        // Every channel's shown: a MIP of several channels walks them
        // through this one frame.
        let shown = |c: usize| c == scene.channel || params.channels.iter().any(|s| s.channel == c);
        let max_blocks = match scene.ranges.as_ref() {
            Some(r) if matches!(params.mode, RenderMode::Mip) => {
                let channels = (0..nl)
                    .filter_map(|l| r.level(l).map(|x| x.channels))
                    .max()
                    .unwrap_or(0);
                (0..channels)
                    .map(|c| {
                        (0..nl)
                            .map(|l| match r.level(l) {
                                Some(r) if c < r.channels && shown(c) => {
                                    let n = r.bricks.iter().product::<u64>() as usize;
                                    let max: Vec<f32> =
                                        r.range[c * n..(c + 1) * n].iter().map(|x| x[1]).collect();
                                    max_blocks(bricks[l], &max)
                                }
                                _ => vec![],
                            })
                            .collect()
                    })
                    .collect()
            }
            _ => vec![],
        };
        let tf_eval = params.tf.evaluator();
        // Level l's voxel coordinate per world unit: its span over the extent.
        let scale: Vec<[f64; 3]> = (0..nl)
            .map(|l| {
                let s = scene.span(l);
                [0, 1, 2].map(|a| s[a] / scene.extent[2 - a])
            })
            .collect();
        let mut frame = Frame {
            max_blocks,
            tf_table: TfTable::new(&params.tf, &tf_eval),
            clear_blocks,
            next_t: vec![],
            step: (0..nl)
                .map(|l| {
                    let dt = scene.voxel(l) / spv;
                    (dt, 1.0 / dt, (dt / reference) as f32)
                })
                .collect(),
            inv_scale: scale.iter().map(|s| s.map(|x| 1.0 / x)).collect(),
            vm,
            scene,
            params,
            tf: &params.tf,
            tf_eval,
            lod,
            dims: scene.levels.clone(),
            scale,
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
            channel_levels: None,
            mip_stop: crate::mip::stop_of_tf(params),
            x86_v3: scene.x86_v3 && crate::isa::x86_64_v3(),
        };
        frame.next_t = (0..nl).map(|l| frame.compute_next_level_t(l)).collect();
        frame
    }

    /// The level this frame's channel is read at where a step asks for
    /// `level` (its level range, [`Frame::channel_levels`]).
    #[inline]
    pub(crate) fn channel_level(&self, level: usize) -> usize {
        crate::params::ChannelStyle::level_for(self.channel_levels, level, self.dims.len())
    }

    pub(crate) fn levels(&self) -> usize {
        self.dims.len()
    }

    /// Index in a padded brick whose first voxel (apron excluded) is `lo`
    /// of the level's voxel `v`.
    #[inline(always)]
    pub(crate) fn local_index(&self, v: Dims3, lo: Dims3) -> usize {
        let a = self.apron;
        ((v[0] - lo[0] + a) as usize) * self.stride[0]
            + ((v[1] - lo[1] + a) as usize) * self.stride[1]
            + (v[2] - lo[2] + a) as usize
    }

    /// The brick holding voxel `v`.
    #[inline]
    pub(crate) fn brick_of(&self, v: Dims3) -> Dims3 {
        match self.brick_shift {
            Some(s) => [v[0] >> s[0], v[1] >> s[1], v[2] >> s[2]],
            None => [
                v[0] / self.brick[0],
                v[1] / self.brick[1],
                v[2] / self.brick[2],
            ],
        }
    }

    /// The level a sample at distance `t` asks for.
    /// A ray's span in the volume and its part in the frame's region
    /// (sort-last): `(t0, c0, t1)`, samples of the grid from `t0` taken in
    /// `[c0, t1)` (`c0 = t0` without a region); `None` when the ray misses
    /// either. Neighbouring regions share the face's `t` exactly.
    pub(crate) fn span(&self, ray: &Ray, inv_dir: [f64; 3]) -> Option<(f64, f64, f64)> {
        let (t0, t1) = intersect_box_inv(ray, inv_dir, [0.0; 3], self.scene.extent)?;
        match self.params.clip.as_deref() {
            None => Some((t0, t0, t1)),
            Some(&[lo, hi]) => {
                let (c0, c1) = intersect_box_inv(ray, inv_dir, lo, hi)?;
                Some((t0, c0, t1.min(c1)))
            }
        }
    }

    pub(crate) fn level_at(&self, t: f64) -> usize {
        match self.lod {
            Lod::Fixed(l) => l.min(self.levels() - 1),
            // In perspective, before the first threshold (which lies
            // slightly early) the level is 0 without a logarithm: most
            // rays start there.
            Lod::Auto { .. }
                if self.fp_slope > 0.0 && t < self.next_t.first().copied().unwrap_or(0.0) =>
            {
                0
            }
            lod => {
                let fp = match self.fp_slope {
                    0.0 => self
                        .params
                        .camera
                        .pixel_footprint(t, self.params.lod_height()),
                    slope => slope * t,
                };
                lod.level_for(fp, self.voxel[0], self.levels())
            }
        }
    }

    /// The distance from which on the level may be coarser than `level`
    /// (infinity when it never changes).
    pub(crate) fn next_level_t(&self, level: usize) -> f64 {
        self.next_t[level]
    }

    pub(crate) fn compute_next_level_t(&self, level: usize) -> f64 {
        match self.lod {
            // The bias alone reaches the next level: from the eye on.
            Lod::Auto { bias } if level + 1 < self.levels() && bias >= level as f64 + 1.0 => 0.0,
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
    /// (`[x, y, z]`) at level `l`: voxel coordinate `q = w·span/extent −
    /// ½` clamped to `[0, dims − 1]` (the reference sampler's rule, with
    /// the division folded into a scale; `span`:
    /// [`level_span`](brickyard_core::level_span)).
    #[inline(always)]
    pub(crate) fn coords(&self, l: usize, w: Vec3) -> (Dims3, [f32; 3]) {
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

    /// The nearest voxel of level `l` to the world point `w`, as a voxel
    /// base with zero fractions (the interpolation then gives that voxel's
    /// value as it is): `⌊q + ½⌋` of [`coords`](Self::coords)' clamped
    /// coordinate `q`. Label images are sampled so: an interpolated label
    /// would be another label. `walk.wgsl`'s `coords` is its twin.
    pub(crate) fn nearest(&self, l: usize, w: Vec3) -> (Dims3, [f32; 3]) {
        let s = &self.scale[l];
        let m = &self.qmax[l];
        // q + ½ ≥ ½: truncation is floor.
        let n = |x: f64, hi: f64| (clamp(x - 0.5, hi) + 0.5) as u64;
        (
            [
                n(w[2] * s[0], m[0]),
                n(w[1] * s[1], m[1]),
                n(w[0] * s[2], m[2]),
            ],
            [0.0; 3],
        )
    }

    /// The voxel base and fractions a slice samples `w` at on level `l`:
    /// [`nearest`](Self::nearest) for label images, else
    /// [`coords`](Self::coords).
    #[inline(always)]
    pub(crate) fn sample_coords(&self, l: usize, w: Vec3) -> (Dims3, [f32; 3]) {
        if self.params.labels {
            self.nearest(l, w)
        } else {
            self.coords(l, w)
        }
    }
}

/// The step to go on from, before a region beginning at `c0` on a grid
/// from `base_t` of step `1/inv_dt`, stepping at `k`: a step or so short of
/// `c0` (or of `until`, a level change, whichever comes first), never back.
/// The steps passed over all lie before both.
#[inline]
pub(crate) fn jump_before(k: u64, c0: f64, until: f64, base_t: f64, inv_dt: f64) -> u64 {
    let to = ((c0.min(until) - base_t) * inv_dt - 0.5).floor() - 1.0;
    if to > k as f64 {
        to as u64
    } else {
        k
    }
}

/// Where a DVR ray whose samples lie in `[c0, t1)` starts at `level`, given
/// its entry depth (`entry.rs`: no sample of that level before it shows):
/// the entry when it is of this level and later (never past the level's
/// end `next_t`, whose restart of the step grid must stay), else `c0`;
/// `None` when nothing is left to sample.
#[inline]
pub(crate) fn start_at_entry(
    entry: Option<(usize, f64)>,
    level: usize,
    c0: f64,
    (t1, next_t): (f64, f64),
) -> Option<f64> {
    match entry {
        Some((el, e)) if el == level && e > c0 => (e < t1 || next_t < t1).then(|| e.min(next_t)),
        _ => Some(c0),
    }
}

/// The parameter of step `k` on a ray entering the volume at `t0`.
#[inline]
pub(crate) fn step_t(t0: f64, k: u64, dt: f64) -> f64 {
    t0 + (k as f64 + 0.5) * dt
}

/// Whether voxel `v` lies in the box `[lo, hi)`.
#[inline(always)]
pub(crate) fn inside(v: Dims3, lo: Dims3, hi: Dims3) -> bool {
    v[0] >= lo[0] && v[0] < hi[0] && v[1] >= lo[1] && v[1] < hi[1] && v[2] >= lo[2] && v[2] < hi[2]
}

/// `x` clamped to `[0, hi]` for a finite `hi ≥ 0`, NaN to 0: always a
/// finite value in the range (a max and a min, without branches).
#[inline(always)]
pub(crate) fn clamp(x: f64, hi: f64) -> f64 {
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
pub(crate) fn trilinear<T: Sample>(v: &[T], i: usize, sz: usize, sy: usize, f: [f32; 3]) -> f32 {
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

/// [`trilinear`] with the lerps in lanes ([`F4::trilinear`]) for 8- and
/// 16-bit unsigned volumes, the corners gathered in four loads; the same
/// bits as [`trilinear`] (tested). Other types take [`trilinear`].
#[inline(always)]
pub(crate) fn trilinear_lanes<T: Sample>(
    v: &[T],
    i: usize,
    sz: usize,
    sy: usize,
    f: [f32; 3],
) -> f32 {
    let w = &v[i..i + sz + sy + 2];
    // SAFETY: the corners lie in `w` (its last element is the farthest),
    // and `T` is the type named by its `DTYPE`.
    let (lo, hi) = match T::DTYPE {
        DType::U8 => unsafe { F4::corners_u8(w.as_ptr().cast::<u8>(), sz, sy) },
        DType::U16 => unsafe { F4::corners_u16(w.as_ptr().cast::<u16>(), sz, sy) },
        _ => return trilinear(v, i, sz, sy, f),
    };
    F4::trilinear(lo, hi, f)
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_cache::vm::VmConfig;
    use brickyard_core::camera::Camera;

    /// `trilinear_lanes` equals `trilinear` bit for bit on random bricks
    /// of u8, u16 and f32 (the scalar path) at random fractions, including
    /// 0 and just below 1.
    #[test]
    fn trilinear_lanes_equal_the_scalar_kernel() {
        fn check<T: Sample>(make: impl Fn(u64) -> T) {
            let (sz, sy) = (18 * 18, 18);
            let mut s = 99u64;
            let mut rnd = move || {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                s >> 11
            };
            let vox: Vec<T> = (0..18 * 18 * 18).map(|_| make(rnd())).collect();
            for n in 0..50_000 {
                let i = (rnd() % (17 * 17 * 17)) as usize;
                let [z, y, x] = [i / (17 * 17), i / 17 % 17, i % 17];
                let i = z * sz + y * sy + x;
                let f = [0; 3].map(|_| match rnd() % 4 {
                    0 => 0.0,
                    1 => 1.0 - f32::EPSILON / 2.0,
                    _ => (rnd() % (1 << 24)) as f32 / (1 << 24) as f32,
                });
                let want = trilinear(&vox, i, sz, sy, f);
                let got = trilinear_lanes(&vox, i, sz, sy, f);
                assert_eq!(got.to_bits(), want.to_bits(), "{:?} {n} {f:?}", T::DTYPE);
            }
        }
        check(|r| r as u8);
        check(|r| r as u16);
        check(|r| {
            f32::from_bits(r as u32 & 0x7f7f_ffff) * if r & 1 << 40 != 0 { -1.0 } else { 1.0 }
        });
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
                    let l = (fp / f.voxel[0]).log2().max(0.0) + bias;
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
