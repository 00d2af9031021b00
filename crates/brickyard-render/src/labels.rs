//! Label images in 3D on the CPU ([`RenderParams::labels`] with DVR): each
//! ray stops at its first voxel holding a label (not 0), stepping as a MIP
//! does (the level of the ray's entry, one step grid, nearest voxels), and
//! the pixel is that label's colour ([`label_color`]) shaded by the label's
//! surface there: the normal from the label's indicator (1 where a voxel
//! holds the label, 0 elsewhere and outside the volume) around the hit
//! voxel by Sobel's 3×3×3 operator ([`indicator_gradient`]), lit from the
//! eye ([`surface_shade`]). Bricks that hold only background (by the store's
//! statistics) are crossed without sampling. `labels.wgsl` is the device
//! twin; `reference::render` draws the same from a whole level.
//!
//! [`RenderParams::labels`]: crate::params::RenderParams::labels

use crate::cpu::FrameStats;
use crate::optics::{label_clear, label_color, label_drawn, label_of};
use crate::walk::{inside, jump_before, step_t, Content, Grid, Walker};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::{intersect_box, Ray, Vec3};
use brickyard_core::{Dims3, Sample};

/// The share of a label surface's shade that does not depend on its
/// normal; the rest follows `|cos|` of the angle to the ray.
pub const AMBIENT: f32 = 0.25;

/// The shade of a label's surface (in `[AMBIENT, 1]`): `g` holds the
/// indicator's gradient around the hit voxel ([`indicator_gradient`],
/// `[z, y, x]`, pointing out), `scale` the level's voxels per world unit
/// (`[z, y, x]`), `dir` the ray's direction (`[x, y, z]`, any length). The
/// differences per world unit point out of the label; the shade is
/// `AMBIENT + (1 − AMBIENT)·|cos|` of their angle to the ray, 1 where they
/// are all 0 (a voxel whose neighbours along every axis agree).
pub fn surface_shade(g: [f32; 3], scale: [f64; 3], dir: Vec3) -> f32 {
    let n = [
        g[2] * scale[2] as f32,
        g[1] * scale[1] as f32,
        g[0] * scale[0] as f32,
    ];
    let d = dir.map(|x| x as f32);
    let nn = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    let dd = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if nn == 0.0 || dd == 0.0 {
        return 1.0;
    }
    let c = ((n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / (nn * dd))
        .abs()
        .min(1.0);
    AMBIENT + (1.0 - AMBIENT) * c
}

/// The pixel of a label surface: the label's colour times `shade`, opaque.
pub fn surface_color(id: i32, shade: f32) -> [f32; 4] {
    let c = label_color(Some(id as f32));
    [c[0] * shade, c[1] * shade, c[2] * shade, 1.0]
}

impl<'f, 'a, T: Sample> Walker<'f, 'a, T> {
    /// The pixel of `ray` through a label image in 3D (see the module);
    /// transparent where the ray meets no label. `entry`: the ray's entry
    /// depth at a level ([`crate::entry`]): when the ray is of that level,
    /// no step before it meets a label, and the walk starts a step or so
    /// before it.
    pub(crate) fn label_surface(
        &mut self,
        (ray, entry): (&Ray, Option<(usize, f64)>),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> [f32; 4] {
        let f = self.f;
        let select = f.params.label_select.as_ref();
        let Some((t0, t1)) = intersect_box(ray, [0.0; 3], f.scene.extent) else {
            return [0.0; 4];
        };
        // A new ray: the tracks and exits kept for the last are stale.
        self.ray_serial += 1;
        let level = f.level_at(t0);
        let (dt, inv_dt, _) = f.step[level];
        let g = Grid {
            base_t: t0,
            dt,
            inv_dt,
        };
        let inv_dir = ray.dir.map(|d| 1.0 / d);
        let track = f.track(level, ray, inv_dir, t1);
        let mut k = match entry {
            Some((el, e)) if el == level && e > t0 => {
                if e >= t1 {
                    return [0.0; 4];
                }
                jump_before(0, e, t1, t0, inv_dt)
            }
            _ => 0,
        };
        loop {
            let t = step_t(t0, k, dt);
            if t >= t1 {
                return [0.0; 4];
            }
            k += 1;
            st.steps += 1;
            let w = ray.at(t);
            let (vb, frac) = f.nearest(level, w);
            let c = self.enter(level, vb, req, true);
            if label_clear(c.range[0], c.range[1], select) {
                // Background alone. A step whose voxel base (the
                // interpolating sampler's, which the landing follows) lies
                // in the brick less its last voxel on each axis has its
                // nearest voxel in the brick: cross those steps.
                let (lo, hi) = (c.lo, c.hi.map(|x| x.saturating_sub(1)));
                if inside(f.coords(level, w).0, lo, hi) {
                    st.skipped_bricks += 1;
                    k = f.land(ray, &track, g, k, (lo, hi), t1);
                }
                continue;
            }
            if matches!(self.cache[level].content, Content::Unresolved) {
                self.resolve(level, true);
            }
            if let Content::Data(vox) = self.cache[level].content {
                // A resident brick of voxels: step through it reading each
                // step's nearest voxel straight from it (what `value` reads
                // there, without its per-sample lookups), crossing cells
                // that hold only background, until a label or the brick's
                // end.
                let c = &self.cache[level];
                let (lo, hi, clear) = (c.lo, c.hi, c.clear_cells);
                let (mut w, mut q) = (w, vb);
                loop {
                    // Step k − 1 is at `w`, its nearest voxel `q` in the
                    // brick. A cell of background alone holds the voxels
                    // of every step whose voxel base lies in it (its range
                    // covers each base and the voxel after it on every
                    // axis, the nearest voxel among them): cross it.
                    let (u, _) = f.coords(level, w);
                    let cell = (clear != 0 && inside(u, lo, hi))
                        .then(|| f.cell_of([0, 1, 2].map(|a| u[a] - lo[a])))
                        .filter(|&cell| clear >> cell & 1 == 1);
                    if let Some(cell) = cell {
                        st.skipped_cells += 1;
                        k = f.land(ray, &track, g, k, f.cell_box(cell, lo, hi), t1);
                    } else {
                        st.samples += 1;
                        st.exact += 1;
                        let v = vox[f.local_index(q, lo)].to_f32();
                        if let Some(id) = label_drawn(Some(v), select) {
                            let gr = self.indicator_around(level, q, id, req, st);
                            return surface_color(id, surface_shade(gr, f.scale[level], ray.dir));
                        }
                    }
                    let t = step_t(t0, k, dt);
                    if t >= t1 {
                        return [0.0; 4];
                    }
                    w = ray.at(t);
                    let (next, _) = f.nearest(level, w);
                    if !inside(next, lo, hi) {
                        // The next brick: the outer loop takes step k.
                        break;
                    }
                    k += 1;
                    st.steps += 1;
                    q = next;
                }
                continue;
            }
            match self.value(level, w, vb, frac, req, st) {
                Some(v) => {
                    if let Some(id) = label_drawn(Some(v), select) {
                        let gr = self.indicator_around(level, vb, id, req, st);
                        return surface_color(id, surface_shade(gr, f.scale[level], ray.dir));
                    }
                }
                None => k = self.skip_unserved(level, ray, &track, (g, k), t1, st),
            }
        }
    }

    /// [`indicator_gradient`] of label `id` around the voxel `v` of
    /// `level`: its 26 neighbours looked up at `level` (one outside the
    /// volume is background; one whose brick is not resident counts as the
    /// label).
    fn indicator_around(
        &mut self,
        level: usize,
        v: Dims3,
        id: i32,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> [f32; 3] {
        let d = self.f.dims[level];
        let mut ind = [0f32; 27];
        for (i, x) in ind.iter_mut().enumerate() {
            let o = [i / 9, i / 3 % 3, i % 3].map(|x| x as i64 - 1);
            if o == [0; 3] {
                *x = 1.0;
                continue;
            }
            let q = [0, 1, 2].map(|a| v[a] as i64 + o[a]);
            if (0..3).any(|a| q[a] < 0 || q[a] >= d[a] as i64) {
                continue;
            }
            let holds = match self.voxel_at_level(level, q.map(|x| x as u64), req, st) {
                Some(x) => label_of(x) == Some(id),
                None => true,
            };
            *x = holds as u8 as f32;
        }
        indicator_gradient(&ind)
    }

    /// The value of voxel `q` of `level` from its own brick: `None` where
    /// that brick is not resident (no coarser level stands in: the
    /// neighbours only shade), counted as a miss of the brick. Not as an
    /// unserved sample: the pixel is drawn (the neighbour counts as the
    /// label), and a brick that failed to load would otherwise make its
    /// neighbours' pixels count as holes that no level fills.
    fn voxel_at_level(
        &mut self,
        level: usize,
        q: Dims3,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        st.samples += 1;
        self.enter(level, q, req, true);
        if matches!(self.cache[level].content, Content::Unresolved) {
            self.resolve(level, true);
        }
        let f = self.f;
        let c = &mut self.cache[level];
        match c.content {
            Content::Data(vox) => {
                st.exact += 1;
                Some(vox[f.local_index(q, c.lo)].to_f32())
            }
            Content::Value(v) => {
                st.exact += 1;
                Some(v)
            }
            Content::Unmapped => {
                c.missed += 1;
                None
            }
            Content::Unresolved => unreachable!("resolved above"),
        }
    }
}

/// Sobel's 3×3×3 operator on a label's indicator `ind` (1 where a voxel
/// holds the label; `[z][y][x]` offsets −1, 0, 1, flattened): per axis
/// `[z, y, x]`, the differences `I(−1) − I(+1)` across it weighted by
/// `(1, 2, 1) ⊗ (1, 2, 1)` over the other two axes. It points out of the
/// label, and smooths the staircase of voxel faces into a surface's
/// normal.
pub fn indicator_gradient(ind: &[f32; 27]) -> [f32; 3] {
    let at = |z: usize, y: usize, x: usize| ind[z * 9 + y * 3 + x];
    let w = [1.0f32, 2.0, 1.0];
    let mut g = [0f32; 3];
    for i in 0..3 {
        for j in 0..3 {
            let k = w[i] * w[j];
            g[0] += k * (at(0, i, j) - at(2, i, j));
            g[1] += k * (at(i, 0, j) - at(i, 2, j));
            g[2] += k * (at(i, j, 0) - at(i, j, 2));
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sobel_on_an_indicator() {
        // A label filling z ≤ 0: the gradient points to +z alone, 16 (the
        // weights' sum) per unit step.
        let mut ind = [0f32; 27];
        for (i, x) in ind.iter_mut().enumerate() {
            *x = (i / 9 <= 1) as u8 as f32;
        }
        assert_eq!(indicator_gradient(&ind), [16.0, 0.0, 0.0]);
        // Filling x ≥ 0: −x.
        for (i, x) in ind.iter_mut().enumerate() {
            *x = (i % 3 >= 1) as u8 as f32;
        }
        assert_eq!(indicator_gradient(&ind), [0.0, 0.0, -16.0]);
        // Only the corner voxel (z, y, x) = (−1, −1, −1) beside the centre:
        // equal parts along every axis, from the corner's weight 1 and the
        // centre's face weights (the centre itself is on no difference).
        let mut ind = [0f32; 27];
        ind[13] = 1.0;
        ind[0] = 1.0;
        assert_eq!(indicator_gradient(&ind), [1.0, 1.0, 1.0]);
    }

    #[test]
    fn surfaces_are_lit_from_the_eye() {
        // A face across x seen along x: fully lit; along y: ambient only.
        let g = [0.0, 0.0, -1.0];
        assert_eq!(surface_shade(g, [1.0; 3], [2.0, 0.0, 0.0]), 1.0);
        assert_eq!(surface_shade(g, [1.0; 3], [0.0, -3.0, 0.0]), AMBIENT);
        // 45° in a cube of equal spacing; an anisotropic scale turns the
        // normal (z voxels 4× thicker: z differences per world unit are a
        // quarter).
        let c45 = 0.5f32.sqrt();
        let s = surface_shade([1.0, 0.0, 1.0], [1.0; 3], [1.0, 0.0, 0.0]);
        assert!((s - (AMBIENT + (1.0 - AMBIENT) * c45)).abs() < 1e-6, "{s}");
        let s = surface_shade([1.0, 0.0, 1.0], [0.25, 1.0, 1.0], [1.0, 0.0, 0.0]);
        let c = 1.0 / (1.0f32 + 0.0625).sqrt();
        assert!((s - (AMBIENT + (1.0 - AMBIENT) * c)).abs() < 1e-6, "{s}");
        // Inside a label (every neighbour agrees): unshaded.
        assert_eq!(surface_shade([0.0; 3], [1.0; 3], [1.0, 1.0, 1.0]), 1.0);
        let col = surface_color(7, 0.5);
        let full = label_color(Some(7.0));
        assert_eq!(col, [full[0] * 0.5, full[1] * 0.5, full[2] * 0.5, 1.0]);
    }
}
