//! Maximum intensity projections on the CPU: each channel's largest value
//! along the ray at the level of the ray's entry, crossing bricks (and,
//! inside resident bricks, cells) whose maximum cannot raise the ray's,
//! then the transfer function's colour of it (one channel) or the
//! channels' mix, opaque. A ray ends once its maximum saturates the window
//! (the colour of any larger value is the same: [`saturation`]), except
//! where the raw maxima are wanted (`RenderParams::mip_values`). `mip.wgsl`
//! is the device twin.

use crate::cpu::FrameStats;
use crate::optics::{channel_intensity, mix_channels};
use crate::params::{ChannelStyle, RenderMode, RenderParams, MAX_CHANNELS};
use crate::walk::{step_t, trilinear, trilinear_lanes, Content, Frame, Grid, Run, Walker};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::{intersect_box, Ray, Vec3};
use brickyard_core::Sample;
use std::cmp::Ordering;

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
            // `mip_color`'s colour, by the frame's evaluator (the same bits).
            Some(b) if !b.is_nan() => {
                let [r, g, b] = self.f.tf_eval.color(b);
                [r, g, b, 1.0]
            }
            Some(_) => [0.0, 0.0, 0.0, 1.0],
            None => [0.0; 4],
        }
    }

    /// The largest value along the ray inside `(t0, t1)` (NaN ignored; NaN
    /// if every sample was NaN or unserved), `None` when the ray takes no
    /// sample. The ray ends at the first sample of at least the walker's
    /// `mip_stop` (the window's [`saturation`]; infinite: never), which it
    /// returns.
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
        span: (f64, f64),
        clip: (f64, f64),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        #[cfg(target_arch = "x86_64")]
        if self.f.x86_v3 {
            // SAFETY: `Frame::x86_v3` holds only where the processor has
            // every feature the copy is compiled with (`isa::x86_64_v3`).
            return unsafe {
                if self.f.scene.lanes {
                    self.mip_v3::<true>(ray, span, clip, req, st)
                } else {
                    self.mip_v3::<false>(ray, span, clip, req, st)
                }
            };
        }
        if self.f.scene.lanes {
            self.mip_at::<true>(ray, span, clip, req, st)
        } else {
            self.mip_at::<false>(ray, span, clip, req, st)
        }
    }

    /// [`mip_at`](Self::mip_at) compiled for x86-64-v3 ([`crate::isa`]):
    /// the same source, the same bits.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(
        enable = "avx,avx2,bmi1,bmi2,f16c,fma,lzcnt,movbe,popcnt,sse3,ssse3,sse4.1,sse4.2"
    )]
    #[inline(never)]
    unsafe fn mip_v3<const LANES: bool>(
        &mut self,
        ray: &Ray,
        span: (f64, f64),
        clip: (f64, f64),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        self.mip_at::<LANES>(ray, span, clip, req, st)
    }

    /// [`mip_max_in`](Self::mip_max_in)'s walk; `LANES`: the runs'
    /// samples by [`trilinear_lanes`] (the same bits as [`trilinear`]).
    #[inline(always)]
    fn mip_at<const LANES: bool>(
        &mut self,
        ray: &Ray,
        (t0, t1): (f64, f64),
        (c0, c1): (f64, f64),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        let (f, channel, stop) = (self.f, self.channel, self.mip_stop);
        // A new ray: the tracks and exits kept for the last are stale.
        self.ray_serial += 1;
        let t1 = t1.min(c1);
        let level = f.level_at(t0);
        let (dt, inv_dt, _) = f.step[level];
        // One level and step grid for the whole ray.
        let g = Grid {
            base_t: t0,
            dt,
            inv_dt,
        };
        let inv_dir = ray.dir.map(|d| 1.0 / d);
        let track = f.track(level, ray, inv_dir, t1);
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
                // Past the largest block of bricks that cannot raise it.
                let (lo, hi) = f.max_box((channel, level), c.brick, (c.lo, c.hi), best);
                st.skipped_bricks += 1;
                k = f.land(ray, &track, g, k, (lo, hi), t1);
                continue;
            }
            if let Content::Data(vox) = c.content {
                // Resident: a fixed-point run through the brick (as in
                // DVR), crossing cells whose maximum cannot raise `best`.
                let (lo, hi, slot) = (c.lo, c.hi, c.slot);
                let end = track.run_end(g, (lo, hi), t1).max(k);
                let run = Run::new(f, level, &track, w, lo, hi);
                let (n, passed, j) =
                    mip_run::<T, LANES>(f, run, (vox, slot), (k - 1, end), (&mut best, stop));
                st.skipped_cells += passed;
                st.samples += n;
                st.exact += n;
                st.steps += j - (k - 1) - 1;
                if best >= stop {
                    break;
                }
                k = end;
                continue;
            }
            match self.value(level, w, vb, frac, req, st) {
                // f32::max ignores NaN.
                Some(v) => {
                    best = best.max(v);
                    if best >= stop {
                        break;
                    }
                    // Served by a resident stand-in: the next steps the same
                    // stand-in brick serves, in a run through its voxels at
                    // this level's step (as the DVR's), crossing its cells
                    // that cannot raise `best`; each step a miss of the
                    // brick of `level`, as `value` counts them.
                    let Some((lv, vox, lo, end)) =
                        self.stand_in_run(level, ray, inv_dir, (g, k), (t1, t1))
                    else {
                        continue;
                    };
                    let (hi, slot) = (self.cache[lv].hi, self.cache[lv].slot);
                    let track_lv = self.track_of(lv, ray, inv_dir, t1);
                    let mut run = Run::new(f, lv, &track_lv, ray.at(step_t(t0, k, dt)), lo, hi);
                    run.dq = track_lv.dq_at(dt);
                    let (n, passed, j) =
                        mip_run::<T, LANES>(f, run, (vox, slot), (k, end), (&mut best, stop));
                    st.samples += n;
                    st.skipped_cells += passed;
                    st.steps += j - k;
                    let c = &mut self.cache[level];
                    c.missed = c.missed.saturating_add((j - k) as u32);
                    if best >= stop {
                        break;
                    }
                    k = end;
                }
                None => k = self.skip_unserved(level, ray, &track, (g, k), t1, st),
            }
        }
        hit.then_some(best)
    }
}

/// The steps `j .. end` of a MIP run through a resident brick (its voxels
/// and pool slot): cells whose maximum cannot raise `best` crossed (with
/// `Scene::skip_cells`), the others sampled into `best`, until `best`
/// reaches `stop`. Returns the samples taken, the cells crossed and the
/// step it stopped before. The loop's copy for runs whose every step lies
/// within the clamp's bounds ([`Run::interior`]) takes them unclamped.
#[inline(always)]
fn mip_run<T: Sample, const LANES: bool>(
    f: &Frame,
    mut run: Run,
    (vox, slot): (&[T], u32),
    (j, end): (u64, u64),
    at: (&mut f32, f32),
) -> (u64, u64, u64) {
    let ranges = f.scene.skip_cells.then(|| f.vm.cell_ranges(slot));
    if run.interior(end - j) {
        mip_steps::<T, LANES, true>(f, &mut run, vox, ranges, (j, end), at)
    } else {
        mip_steps::<T, LANES, false>(f, &mut run, vox, ranges, (j, end), at)
    }
}

/// [`mip_run`]'s loop. `INTERIOR`: every step lies within the clamp's
/// bounds; nothing in the loop writes through a reference but `best`'s
/// local copy, as in the DVR's runs.
#[inline(always)]
fn mip_steps<T: Sample, const LANES: bool, const INTERIOR: bool>(
    f: &Frame,
    run: &mut Run,
    vox: &[T],
    ranges: Option<&[[f32; 2]]>,
    (mut j, end): (u64, u64),
    (best_out, stop): (&mut f32, f32),
) -> (u64, u64, u64) {
    let [sz, sy] = f.stride;
    // The voxels from the brick's first past the apron: a step's index is
    // its base's offset alone.
    let vox = &vox[f.local_index([0; 3], [0; 3])..];
    let (mut n, mut passed, mut best) = (0u64, 0u64, *best_out);
    while j < end {
        let (u, fr) = if INTERIOR {
            run.current_unclamped()
        } else {
            run.current()
        };
        let cell = f.cell_in_run(u);
        // NaN bound or best: no skip.
        if ranges.is_some_and(|r| r[cell][1] <= best) {
            passed += 1;
            j = run.cross_cell(f, u, (j, end));
            continue;
        }
        run.advance(1);
        j += 1;
        n += 1;
        let i = u[0] as usize * sz + u[1] as usize * sy + u[2] as usize;
        let v = if LANES {
            trilinear_lanes(vox, i, sz, sy, fr)
        } else {
            trilinear(vox, i, sz, sy, fr)
        };
        // f32::max ignores NaN.
        best = best.max(v);
        if best >= stop {
            break;
        }
    }
    *best_out = best;
    (n, passed, j)
}

/// Where a MIP ray of one channel (`params.tf`) ends: the window's
/// [`saturation`]; infinite where the raw maxima are wanted (regions'
/// maxima meet before the transfer function), outside MIP, or for an
/// empty or inverted window.
pub(crate) fn stop_of_tf(params: &RenderParams) -> f32 {
    let [w0, w1] = params.tf.window;
    if params.mip_values
        || params.mode != RenderMode::Mip
        || w1.partial_cmp(&w0) != Some(Ordering::Greater)
    {
        return f32::INFINITY;
    }
    saturation(|v| params.tf.normalize(v), w1)
}

/// [`stop_of_tf`] for channel `style` of a MIP of several channels, by
/// its window's intensity ([`channel_intensity`]).
pub(crate) fn stop_of_channel(params: &RenderParams, style: &ChannelStyle) -> f32 {
    let [lo, hi] = style.window;
    if params.mip_values
        || params.mode != RenderMode::Mip
        || hi.partial_cmp(&lo) != Some(Ordering::Greater)
    {
        return f32::INFINITY;
    }
    saturation(|v| channel_intensity(style, v), hi)
}

/// The least value `s` of at least `hi` whose windowed value `x(s)` is
/// at least 1; infinite when there is none (or `hi` is not finite). `x` is
/// the window's map, monotone (the clamp of a subtraction and a division
/// or product by a positive width), so every value from `s` on maps to 1 as
/// well, to the same colour: a ray whose maximum reaches `s` ends there
/// without a change in its pixel. Found by bisection over the floats in
/// order (the top itself may map just below 1 after rounding).
pub(crate) fn saturation(x: impl Fn(f32) -> f32, hi: f32) -> f32 {
    if !hi.is_finite() {
        return f32::INFINITY;
    }
    if x(hi) >= 1.0 {
        return hi;
    }
    // A value that maps to 1: from a millionth of the top's size up.
    let mut step = (hi.abs() * 1e-6).max(f32::MIN_POSITIVE);
    let mut up = None;
    for _ in 0..160 {
        let u = hi + step;
        if !u.is_finite() {
            break;
        }
        if x(u) >= 1.0 {
            up = Some(u);
            break;
        }
        step *= 2.0;
    }
    let Some(up) = up else {
        return f32::INFINITY;
    };
    // Floats in order as integers: x(key⁻¹(a)) < 1 ≤ x(key⁻¹(b)).
    let key = |v: f32| {
        let b = v.to_bits();
        if b >> 31 == 1 {
            !b
        } else {
            b | 1 << 31
        }
    };
    let value = |k: u32| f32::from_bits(if k >> 31 == 1 { k & !(1 << 31) } else { !k });
    let (mut a, mut b) = (key(hi), key(up));
    while b - a > 1 {
        let m = a + (b - a) / 2;
        if x(value(m)) >= 1.0 {
            b = m;
        } else {
            a = m;
        }
    }
    value(b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::TransferFunction;

    /// `saturation` is the least value whose windowed value is 1, and
    /// every larger value maps to 1 too: for the transfer function's
    /// window (a product by the inverse width) and a channel's (a
    /// quotient), on random windows from tiny to huge, negative and
    /// positive, where the top itself may map just below 1.
    #[test]
    fn saturation_is_the_least_value_of_the_window_top_colour() {
        let mut s = 0x5a7u64;
        let mut rnd = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut above_top = 0;
        for i in 0..20_000 {
            let scale = 10f64.powf(rnd() * 12.0 - 6.0);
            let lo = ((rnd() - 0.5) * scale) as f32;
            let hi = lo + ((rnd() + 1e-3) * scale) as f32;
            if hi <= lo || hi.is_nan() || lo.is_nan() {
                continue;
            }
            let tf = TransferFunction::preset("linear", [lo, hi]).unwrap();
            let style = ChannelStyle::new(0, [1.0; 3], [lo, hi]);
            let maps: [&dyn Fn(f32) -> f32; 2] =
                [&|v| tf.normalize(v), &|v| channel_intensity(&style, v)];
            for (m, x) in maps.iter().enumerate() {
                let st = saturation(x, hi);
                assert!(
                    st.is_finite() && x(st) >= 1.0,
                    "{i}: [{lo}, {hi}] map {m}: {st}"
                );
                if st > hi {
                    above_top += 1;
                    assert!(x(st.next_down()) < 1.0, "{i}: not the least");
                }
                for k in 0..8 {
                    let v = st + (st.abs() as f64 * rnd() * 10f64.powi(k - 6)) as f32;
                    assert_eq!(x(v), 1.0, "{i}: {v} above {st}");
                }
            }
        }
        // The window's top itself maps below 1 in some windows.
        assert!(above_top > 100, "{above_top}");
        assert_eq!(saturation(|_| 0.5, 1.0), f32::INFINITY);
        assert_eq!(saturation(|_| 1.0, f32::NAN), f32::INFINITY);
    }
}
