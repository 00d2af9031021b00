//! Maximum intensity projections on the CPU: each channel's largest value
//! along the ray at the level of the ray's entry, crossing bricks (and,
//! inside resident bricks, cells) whose maximum cannot raise the ray's,
//! then the transfer function's colour of it (one channel) or the
//! channels' mix, opaque. `mip.wgsl` is the device twin.

use crate::cpu::FrameStats;
use crate::optics::{mip_color, mix_channels};
use crate::params::{ChannelStyle, MAX_CHANNELS};
use crate::walk::{step_t, trilinear, Content, Grid, Run, Walker};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::{intersect_box, Ray, Vec3};
use brickyard_core::Sample;

/// The pixel of `ray` in a MIP of several channels added up (`styles`,
/// one walker each): each channel's maximum along the ray, then their mix;
/// transparent where the ray takes no sample.
#[inline]
pub(crate) fn channels_pixel<T: Sample>(
    walkers: &mut [Walker<'_, '_, T>],
    ray: &Ray,
    extent: Vec3,
    styles: &[ChannelStyle],
    (req, st): (&mut Requests, &mut FrameStats),
) -> [f32; 4] {
    let Some(span) = intersect_box(ray, [0.0; 3], extent) else {
        return [0.0; 4];
    };
    let mut best = [f32::NAN; MAX_CHANNELS];
    let mut hit = false;
    for (b, wk) in best.iter_mut().zip(walkers.iter_mut()) {
        if let Some(m) = wk.mip_max(ray, span, req, st) {
            hit = true;
            *b = m;
        }
    }
    if hit {
        mix_channels(styles, best.into_iter())
    } else {
        [0.0; 4]
    }
}

impl<'f, 'a, T: Sample> Walker<'f, 'a, T> {
    /// The pixel of `ray` in a MIP of one channel.
    pub(crate) fn mip(&mut self, ray: &Ray, req: &mut Requests, st: &mut FrameStats) -> [f32; 4] {
        let Some(span) = intersect_box(ray, [0.0; 3], self.f.scene.extent) else {
            return [0.0; 4];
        };
        let best = match self.f.params.clip.as_deref() {
            None => self.mip_max(ray, span, req, st),
            // A region: samples of the whole ray's grid in [c0, c1) only.
            Some(&[lo, hi]) => match intersect_box(ray, lo, hi) {
                Some((c0, c1)) => self.mip_max_in(ray, span, (c0, c1), req, st),
                None => None,
            },
        };
        if self.f.params.mip_values {
            return match best {
                Some(b) => [b, 0.0, 0.0, 1.0],
                None => [0.0; 4],
            };
        }
        match best {
            Some(best) => mip_color(self.f.tf, true, best),
            None => mip_color(self.f.tf, false, f32::NAN),
        }
    }

    /// The largest value along the ray inside `(t0, t1)` (NaN ignored; NaN
    /// if every sample was NaN or unserved), `None` when the ray takes no
    /// sample.
    pub(crate) fn mip_max(
        &mut self,
        ray: &Ray,
        span: (f64, f64),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        self.mip_max_in(ray, span, span, req, st)
    }

    /// [`mip_max`](Self::mip_max) over the samples of the grid of
    /// `(t0, t1)` that lie in `[c0, c1)`.
    pub(crate) fn mip_max_in(
        &mut self,
        ray: &Ray,
        (t0, t1): (f64, f64),
        (c0, c1): (f64, f64),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        let f = self.f;
        let t1 = t1.min(c1);
        let level = f.level_at(t0);
        let (dt, inv_dt, _) = f.step[level];
        let track = f.track(level, ray, ray.dir.map(|d| 1.0 / d), t1);
        let mut best = f32::NAN;
        let mut hit = false;
        // A region far along the ray: start a step or so before it (the
        // steps skipped lie before `c0`).
        let mut k = ((c0 - t0) * inv_dt - 0.5).floor().max(1.0) as u64 - 1;
        loop {
            let t = step_t(t0, k, dt);
            if t >= t1 {
                break;
            }
            k += 1;
            if t < c0 {
                // Before the region: another rank's samples.
                continue;
            }
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
                    let cell = f.cell_in_run(u);
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
}
