//! Crossing a box of voxels (a brick, a block of transparent bricks, the
//! rest of a brick nothing resident serves) without sampling it: a ray's
//! track in a level's voxel coordinates, the first grid step past the
//! box's exit (moved early by a bound on the sampler's rounding, checked
//! for rays nearly parallel to a voxel plane), and the blocks of 2, 4 and
//! 8 bricks per axis that a transparent brick may belong to.

use super::{inside, step_t, Frame};
use crate::walk::cells::FIX;
use brickyard_core::camera::{Ray, Vec3};
use brickyard_core::Dims3;

/// The step grid of a ray at one level: step `k` at `base_t + (k + ½)·dt`.
#[derive(Clone, Copy)]
pub(crate) struct Grid {
    pub(crate) base_t: f64,
    pub(crate) dt: f64,
    pub(crate) inv_dt: f64,
}

/// A ray in the voxel coordinates of one level, `q(t) = alpha + beta·t`
/// per axis `[z, y, x]`, for finding where it leaves boxes of voxels.
#[derive(Clone, Copy)]
pub(crate) struct Track {
    pub(crate) alpha: [f64; 3],
    pub(crate) beta: [f64; 3],
    pub(crate) inv_beta: [f64; 3],
    pub(crate) dims: Dims3,
    pub(crate) level: usize,
    /// [`Run`](super::Run)'s fixed-point increment per step of the level: `beta·dt`.
    pub(crate) dq: [i64; 3],
    /// How far (in `t`) a crossing of a voxel plane by the sampler's
    /// coordinates may lie from the crossing of `alpha + beta·t`, on any
    /// axis (infinite for an axis nearly parallel to the planes).
    pub(crate) slack: f64,
}

impl Track {
    /// [`Run`](super::Run)'s fixed-point increment for steps of `dt` (the
    /// track's own level's step gives [`dq`](Self::dq); a stand-in's run
    /// takes the steps of the finer level it serves).
    #[inline]
    pub(crate) fn dq_at(&self, dt: f64) -> [i64; 3] {
        self.beta.map(|b| (b * dt * FIX) as i64)
    }

    /// The first grid step at or after where the ray leaves the box
    /// `[lo, hi)` or reaches `limit`, moved early by `margin` steps and a
    /// thousandth of a step (ties land before; the rounding of the exit,
    /// `step_t` and this expression is far below that for any ray of
    /// fewer than 10⁹ steps); and the margin that makes it safe, `slack`
    /// in steps: with that margin, every step before it has its sampler
    /// voxel base in the box and lies before `limit`.
    #[inline(always)]
    pub(crate) fn first_out(
        &self,
        g: Grid,
        (lo, hi): (Dims3, Dims3),
        limit: f64,
    ) -> (impl Fn(f64) -> u64, f64) {
        let te = self.exit_t(lo, hi, limit);
        let first = move |margin: f64| first_step(g, te, margin);
        (first, self.slack * g.inv_dt)
    }

    /// The step a fixed-point [`Run`](super::Run) through the box `[lo, hi)` ends at:
    /// [`first_out`](Self::first_out) with its margin, or without one for
    /// a ray nearly parallel to a voxel plane (whose steps lie on the box's
    /// face within rounding, where `Run` samples them).
    #[inline(always)]
    pub(crate) fn run_end(&self, g: Grid, bx: (Dims3, Dims3), limit: f64) -> u64 {
        let (first, margin) = self.first_out(g, bx, limit);
        first(if margin < 0.25 { margin } else { 0.0 })
    }

    /// About the ray parameter where the clamped voxel base leaves the box
    /// `[lo, hi)` (voxels), or `t_max` if it does not before (an estimate:
    /// [`Frame::land`] checks it).
    #[inline]
    pub(crate) fn exit_t(&self, lo: Dims3, hi: Dims3, t_max: f64) -> f64 {
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

/// The first step of grid `g` at or after parameter `te`, moved early by
/// `margin` steps and a thousandth of a step (never before step 0): the
/// rule of [`Track::first_out`].
#[inline(always)]
pub(crate) fn first_step(g: Grid, te: f64, margin: f64) -> u64 {
    let x = (te - g.base_t) * g.inv_dt - 0.5 - margin - 1e-3;
    let i = x as i64; // finite; the cast saturates
    (if (i as f64) < x { i + 1 } else { i }).max(0) as u64
}

impl Frame<'_> {
    /// The voxel box `[lo, hi)` of the largest block of transparent bricks
    /// (see `clear_blocks`) around the transparent brick `b` of level `l`
    /// whose box is `[lo, hi)`.
    #[inline]
    pub(crate) fn clear_box(&self, l: usize, b: Dims3, lo: Dims3, hi: Dims3) -> (Dims3, Dims3) {
        let mut found = (lo, hi);
        for (m, (n, clear)) in self.clear_blocks[l].iter().enumerate() {
            let s = m as u32 + 1;
            let c = b.map(|x| x >> s);
            if !clear[((c[0] * n[1] + c[1]) * n[2] + c[2]) as usize] {
                break;
            }
            found = self.block_box(l, c, s);
        }
        found
    }

    /// The voxel box `[lo, hi)` of block `c` of 2ˢ bricks per axis at
    /// level `l` (clipped to the level).
    #[inline]
    fn block_box(&self, l: usize, c: Dims3, s: u32) -> (Dims3, Dims3) {
        let d = self.dims[l];
        let blo = [0, 1, 2].map(|a| (c[a] << s) * self.brick[a]);
        let bhi = [0, 1, 2].map(|a| (blo[a] + (self.brick[a] << s)).min(d[a]));
        (blo, bhi)
    }

    /// The voxel box `[lo, hi)` of the largest block of bricks (see
    /// `max_blocks`) of channel `c` around brick `b` of level `l` (box
    /// `[lo, hi)`) whose largest value is at most `best` (MIP: a block that
    /// cannot raise the ray's maximum); `b`'s own box when there is none or
    /// the frame has no blocks.
    #[inline]
    pub(crate) fn max_box(
        &self,
        (c, l): (usize, usize),
        b: Dims3,
        (lo, hi): (Dims3, Dims3),
        best: f32,
    ) -> (Dims3, Dims3) {
        let mut found = (lo, hi);
        let Some(blocks) = self.max_blocks.get(c).and_then(|x| x.get(l)) else {
            return found;
        };
        for (m, (n, max)) in blocks.iter().enumerate() {
            let s = m as u32 + 1;
            let c = b.map(|x| x >> s);
            // NaN (unknown): no.
            let m = max[((c[0] * n[1] + c[1]) * n[2] + c[2]) as usize];
            if m.is_nan() || m > best {
                break;
            }
            found = self.block_box(l, c, s);
        }
        found
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
    pub(crate) fn land(
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
    pub(crate) fn track(&self, l: usize, ray: &Ray, inv_dir: Vec3, t_end: f64) -> Track {
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

/// Blocks of 2ᵐ×2ᵐ×2ᵐ bricks.
pub(crate) const MACRO_LEVELS: usize = 3;

/// For `m = 1 ..= MACRO_LEVELS`: the block counts per axis and whether
/// every brick of each block of 2ᵐ bricks per axis is transparent, from the
/// per-brick flags `t` (`[z][y][x]`, `n` bricks per axis).
pub(crate) fn clear_blocks(n: Dims3, t: &[bool]) -> Vec<(Dims3, Vec<bool>)> {
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

/// A level's [`max_blocks`].
pub(crate) type MaxBlocks = Vec<(Dims3, Vec<f32>)>;

/// For `m = 1 ..= MACRO_LEVELS`: the block counts per axis and the
/// largest value of each block of 2ᵐ bricks per axis (NaN when a brick's
/// is unknown), from the per-brick maxima `max` (`[z][y][x]`, `n` bricks
/// per axis).
pub(crate) fn max_blocks(n: Dims3, max: &[f32]) -> MaxBlocks {
    let mut out: Vec<(Dims3, Vec<f32>)> = Vec::with_capacity(MACRO_LEVELS);
    let (mut prev_n, mut prev) = (n, max.to_vec());
    for _ in 0..MACRO_LEVELS {
        let nn = prev_n.map(|x| x.div_ceil(2));
        let mut cur = vec![f32::NEG_INFINITY; (nn[0] * nn[1] * nn[2]) as usize];
        for z in 0..prev_n[0] {
            for y in 0..prev_n[1] {
                for x in 0..prev_n[2] {
                    let v = prev[((z * prev_n[1] + y) * prev_n[2] + x) as usize];
                    let c = &mut cur[(((z / 2) * nn[1] + y / 2) * nn[2] + x / 2) as usize];
                    // A NaN stays (f32::max would drop it).
                    if v.is_nan() || v > *c {
                        *c = if c.is_nan() { *c } else { v };
                    }
                }
            }
        }
        out.push((nn, cur.clone()));
        (prev_n, prev) = (nn, cur);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;

    /// `land` against stepping one by one: it never passes a step whose
    /// voxel base leaves the box (or that reaches the limit), and it lands
    /// at most one step early — on random rays, including ones nearly
    /// parallel to the voxel planes and ones from far away. The fast path's
    /// fixed-point run through a brick takes the same steps at the same
    /// positions (to 1e-6 voxel).
    /// `max_box` gives the largest aligned block of 2ᵐ bricks around the
    /// brick whose every brick's maximum is at most `best` (by the bricks'
    /// own maxima, worked out here), the brick's own box where even the
    /// smallest block has a larger or unknown maximum; on random maxima
    /// with unknown ones, and grids whose sizes are not powers of two.
    #[test]
    fn max_box_is_the_largest_block_that_cannot_raise_the_maximum() {
        let dims = [70u64, 45, 96];
        let (vm, scene, params) = fixture(dims, [8, 8, 16], [1.0, 1.0, 1.0]);
        let mut f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let n = f.bricks[0];
        let mut rnd = uniform(0xb10c_0005);
        let count = (n[0] * n[1] * n[2]) as usize;
        // Mostly low maxima, so that large blocks qualify.
        let max: Vec<f32> = (0..count)
            .map(|_| match rnd() {
                r if r < 0.02 => f32::NAN,
                r if r < 0.1 => (rnd() * 100.0) as f32,
                _ => (rnd() * 5.0) as f32,
            })
            .collect();
        f.max_blocks = vec![vec![max_blocks(n, &max)]];
        let brick_max = |b: Dims3| max[((b[0] * n[1] + b[1]) * n[2] + b[2]) as usize];
        let (mut grown, mut kept) = (0, 0);
        for _ in 0..5000 {
            let b = [0, 1, 2].map(|a| (rnd() * n[a] as f64) as u64);
            let lo = [0, 1, 2].map(|a| b[a] * f.brick[a]);
            let hi = [0, 1, 2].map(|a| (lo[a] + f.brick[a]).min(dims[a]));
            let best = (rnd() * 8.0) as f32;
            let (blo, bhi) = f.max_box((0, 0), b, (lo, hi), best);
            // The block whose every brick is at most `best`, largest first.
            let mut want = (lo, hi);
            for s in 1..=super::MACRO_LEVELS as u32 {
                let c = b.map(|x| x >> s);
                let (mut ok, mut any) = (true, false);
                for z in c[0] << s..((c[0] + 1) << s).min(n[0]) {
                    for y in c[1] << s..((c[1] + 1) << s).min(n[1]) {
                        for x in c[2] << s..((c[2] + 1) << s).min(n[2]) {
                            ok &= brick_max([z, y, x]) <= best;
                            any = true;
                        }
                    }
                }
                if !(ok && any) {
                    break;
                }
                let wlo = [0, 1, 2].map(|a| (c[a] << s) * f.brick[a]);
                let whi = [0, 1, 2].map(|a| (wlo[a] + (f.brick[a] << s)).min(dims[a]));
                want = (wlo, whi);
            }
            assert_eq!((blo, bhi), want, "brick {b:?}, best {best}");
            if want.0 != lo || want.1 != hi {
                grown += 1;
            } else {
                kept += 1;
            }
        }
        assert!(grown > 500 && kept > 500, "{grown} blocks, {kept} bricks");
    }

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
}
