//! Multi-channel DVR on the CPU: the channels of the visible set sampled
//! at every step of one ray, each through its own transfer function, mixed
//! into one sample and composited front to back. `multi.wgsl` is the device
//! twin; the in-core reference has its own f64 implementation of the rule.
//!
//! # The mixing rule
//!
//! At a sample the channels are coincident media: with straight colours
//! `c_i` and opacities `α_i` (their transfer functions at their values;
//! NaN and unserved samples give nothing), the mixed sample has opacity
//! `α = 1 − Π(1 − α_i)` and colour `Σ α_i·c_i / Σ α_i`. Opacity correction
//! of `α` for the step length equals correcting every `α_i` (the products
//! commute), so the usual compositing applies unchanged; with one channel
//! this is exactly single-channel DVR.
//!
//! # Skipping
//!
//! Each channel has its own walker, bound to a frame of its own (its
//! transfer function's transparent bricks and blocks). A channel whose
//! brick is transparent under its transfer function contributes nothing
//! there and is not looked up; the ray jumps only when every visible
//! channel's brick is transparent, to the nearest of their landings, so a
//! brick is crossed only if all visible channels hide it.

use crate::cpu::FrameStats;
use crate::optics::composite_visible;
use crate::walk::{jump_before, step_t, Grid, Walker};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::Ray;
use brickyard_core::Sample;

/// The pixel of `ray` in a DVR of several channels, one walker (and frame)
/// per visible channel, all frames of the same geometry and level of
/// detail.
pub(crate) fn dvr_pixel<T: Sample>(
    walkers: &mut [Walker<'_, '_, T>],
    ray: &Ray,
    (req, st): (&mut Requests, &mut FrameStats),
) -> [f32; 4] {
    let mut acc = [0.0f32; 4];
    let f = walkers[0].f;
    let d = ray.dir;
    let inv_dir = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
    // A region (sort-last): the whole ray's step grid, samples in
    // [c0, t1) only.
    let Some((t0, c0, t1)) = f.span(ray, inv_dir) else {
        return acc;
    };
    let terminate = f.params.early_termination;
    // The step grid and level changes of `dvr.rs`.
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
                level = l;
                (dt, inv_dt, exponent) = f.step[level];
                base_t = t - 0.5 * dt;
                k = 1;
                track = f.track(level, ray, inv_dir, t1);
            }
            next_t = f.next_level_t(level);
            if next_t <= t {
                next_t = t + dt;
            }
        }
        if t < c0 {
            // Before the region: another rank's samples, jumped over
            // (a region far along the rays costs no walk).
            k = jump_before(k, c0, next_t, base_t, inv_dt);
            continue;
        }
        st.steps += 1;
        let w = ray.at(t);
        let (vb, frac) = f.coords(level, w);
        let g = Grid { base_t, dt, inv_dt };
        let limit = t1.min(next_t);
        // The nearest landing of the channels whose brick is transparent,
        // while every channel so far is.
        let mut land = u64::MAX;
        let mut all_clear = true;
        // Whether every channel so far is either transparent or found
        // nothing resident, both at the step's level (then the ray may
        // jump), and the channels that found nothing.
        let mut passable = true;
        let mut unserved = 0u64;
        let mut keep = 1.0f32;
        let mut rgb = [0.0f32; 3];
        let mut weight = 0.0f32;
        for (i, wk) in walkers.iter_mut().enumerate() {
            // The channel's own level (its level range), usually the step's.
            let lc = wk.f.channel_level(level);
            let (cb, cf) = if lc == level {
                (vb, frac)
            } else {
                f.coords(lc, w)
            };
            let (clear, brick, lo, hi) = {
                let c = wk.enter(lc, cb, req, true);
                (c.transparent, c.brick, c.lo, c.hi)
            };
            if clear {
                if lc == level {
                    if passable {
                        let bx = wk.f.clear_box(level, brick, lo, hi);
                        land = land.min(wk.f.land(ray, &track, g, k, bx, limit));
                    }
                } else {
                    // A brick of another level than the step's: no landing
                    // from it; the ray steps on.
                    all_clear = false;
                    passable = false;
                }
                continue;
            }
            all_clear = false;
            let Some(v) = wk.value(lc, w, cb, cf, req, st) else {
                if lc == level && passable {
                    unserved |= 1 << i;
                    land = land.min(wk.f.land(ray, &track, g, k, (lo, hi), limit));
                } else {
                    passable = false;
                }
                continue;
            };
            passable = false;
            match wk.f.tf_eval.lookup_visible(v) {
                Some(c) => {
                    keep *= 1.0 - c[3];
                    rgb[0] += c[3] * c[0];
                    rgb[1] += c[3] * c[1];
                    rgb[2] += c[3] * c[2];
                    weight += c[3];
                }
                None => st.transparent += 1,
            }
        }
        if all_clear {
            st.skipped_bricks += 1;
            k = land.max(k);
            continue;
        }
        if passable && unserved != 0 {
            // No channel shows here and some found nothing resident: on
            // past their brick (or a nearer landing) in one jump, as
            // single-channel DVR does; the steps jumped are unserved
            // samples and misses of each such channel's brick.
            let kn = land.max(k);
            let n = kn - k;
            let u = unserved.count_ones() as u64;
            for (i, wk) in walkers.iter_mut().enumerate() {
                if unserved >> i & 1 == 1 {
                    let c = &mut wk.cache[level];
                    c.missed = c.missed.saturating_add(n as u32);
                }
            }
            st.samples += n * u;
            st.unserved += n * u;
            st.steps += n;
            k = kn;
            continue;
        }
        if weight > 0.0 {
            let inv = 1.0 / weight;
            let c = [rgb[0] * inv, rgb[1] * inv, rgb[2] * inv, 1.0 - keep];
            if composite_visible(&mut acc, c, exponent) && terminate {
                break;
            }
        }
    }
    acc
}
