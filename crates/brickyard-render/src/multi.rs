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
//!
//! # Runs
//!
//! Where every channel shown reads the step's level and has its brick
//! there resident or hidden, the steps through that brick are taken in
//! one fixed-point run (`Run`, as one-channel DVR's): no lookups per step,
//! the cells every channel hides crossed at once, and a channel whose own
//! cell is clear left out of the step. After a step every channel took
//! from a stand-in of one level (or hid), the next steps the same
//! stand-in bricks serve are taken the same way at this level's step,
//! each a miss of every such channel's brick. A brick of one value that
//! shows adds its colour at every step of a run. Elsewhere (level ranges
//! of their own, stand-ins of different levels, a channel with nothing
//! resident, more than 16 channels) the step is sampled channel by channel. The device twin
//! samples step by step; the positions agree within the runs' rounding.

use crate::cpu::FrameStats;
use crate::optics::{composite_visible, Media, TfTable};
use crate::walk::{
    jump_before, start_at_entry, step_t, trilinear, trilinear_lanes, Content, Frame, Grid, Run,
    Track, Walker,
};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::{Ray, Vec3};
use brickyard_core::transfer::TfEval;
use brickyard_core::{Dims3, Sample};
use smallvec::SmallVec;

/// Most channels a run through resident bricks takes (more are sampled
/// step by step).
const RUN_CHANNELS: usize = 16;

/// The pixel of `ray` in a DVR of several channels, one walker (and frame)
/// per visible channel, all frames of the same geometry and level of
/// detail. `entry`: the ray's entry depth over all channels at a level
/// ([`crate::entry`]).
pub(crate) fn dvr_pixel<T: Sample>(
    walkers: &mut [Walker<'_, '_, T>],
    (ray, entry): (&Ray, Option<(usize, f64)>),
    (req, st): (&mut Requests, &mut FrameStats),
) -> [f32; 4] {
    let mut acc = [0.0f32; 4];
    let f = walkers[0].f;
    // A new ray: the walkers' tracks and exits of the last are stale.
    for wk in walkers.iter_mut() {
        wk.ray_serial += 1;
    }
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
    // No channel shows anything before the entry at this level: start
    // there, as one-channel DVR does.
    let Some(c0) = start_at_entry(entry, level, c0, (t1, next_t)) else {
        return acc;
    };
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
        // Every channel resident at the step's level here (or its brick
        // hidden): the steps through this brick in one run.
        if let Some(r) = resident_run(walkers, level, vb, req) {
            let at = (&track, g, level);
            let (done, end) = take_run(
                f,
                &r,
                at,
                (w, k, limit),
                (exponent, terminate),
                &mut acc,
                st,
            );
            if done {
                break;
            }
            k = end;
            continue;
        }
        // The nearest landing of the channels whose brick is transparent,
        // while every channel so far is.
        let mut land = u64::MAX;
        let mut all_clear = true;
        // Whether every channel so far is either transparent or found
        // nothing resident, both at the step's level (then the ray may
        // jump), and the channels that found nothing.
        let mut passable = true;
        let mut unserved = 0u64;
        let mut mix = Media::NONE;
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
                    mix.add(c);
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
        if let Some(c) = mix.sample() {
            if composite_visible(&mut acc, c, exponent) && terminate {
                break;
            }
        }
        // Every channel shown served by a stand-in of one level (or its
        // brick hidden): the next steps the same stand-in bricks serve,
        // taken there by one run at this level's step, as one-channel DVR
        // does; each step a miss of every such channel's brick.
        let Some((lv, first, r)) = stand_in_run(walkers, level) else {
            continue;
        };
        let wk = &mut walkers[first];
        let end = wk.land_in_bricks(level..lv + 1, ray, inv_dir, (g, k), (limit, t1));
        if end <= k {
            continue;
        }
        let track_lv = wk.track_of(lv, ray, inv_dir, t1);
        let mut run = Run::new(f, lv, &track_lv, ray.at(step_t(base_t, k, dt)), r.lo, r.hi);
        run.dq = track_lv.dq_at(dt);
        let (done, stop, n) = run_steps(f, &r, run, (k, end), (exponent, terminate), &mut acc, st);
        st.samples += n;
        st.steps += stop - k;
        for wk in walkers.iter_mut() {
            let c = &mut wk.cache[level];
            if !c.transparent {
                c.missed = c.missed.saturating_add((stop - k) as u32);
            }
        }
        if done {
            break;
        }
        k = end;
    }
    acc
}

/// The bricks of a run through one brick of every channel shown, all of
/// one level: each resident (its voxels, clear cells and transfer
/// function), of one value that shows (its colour, the same at every
/// step), or hidden (left out), at least one not hidden. The channels
/// share the brick's box.
pub(crate) struct ResidentRun<'a, 'f, T> {
    pub(crate) lo: Dims3,
    pub(crate) hi: Dims3,
    /// The channels not hidden, in the order of those shown.
    slots: SmallVec<[Slot<'a, 'f, T>; RUN_CHANNELS]>,
    /// The cells every channel hides (resident ones by their cells, the
    /// others whole).
    all_clear: u64,
}

/// One channel's brick in a run.
struct Slot<'a, 'f, T> {
    /// Its voxels (none for a brick of one value).
    vox: &'a [T],
    /// The cells whose samples it hides.
    clear: u64,
    tf: &'f TfEval<'a>,
    /// The same function in bins ([`TfTable`]), for the voxels' samples.
    table: &'f TfTable,
    /// A brick of one value that shows: its colour (straight alpha).
    konst: Option<[f32; 4]>,
}

/// The run's bricks when every channel shown reads the step's level
/// (no level range of its own there) and has its brick at voxel base
/// `vb` resident (data or one value) or hidden, some not hidden; `None`
/// otherwise (the step is sampled channel by channel).
#[inline]
pub(crate) fn resident_run<'a, 'f, T: Sample>(
    walkers: &mut [Walker<'f, 'a, T>],
    level: usize,
    vb: Dims3,
    req: &mut Requests,
) -> Option<ResidentRun<'a, 'f, T>> {
    if walkers.len() > RUN_CHANNELS {
        return None;
    }
    // First whether the step qualifies (most steps that do not leave at
    // once), then the run's tables.
    let mut resident = false;
    for wk in walkers.iter_mut() {
        if wk.f.channel_level(level) != level {
            return None;
        }
        let c = wk.enter(level, vb, req, true);
        if c.transparent {
            continue;
        }
        if !matches!(c.content, Content::Data(_) | Content::Value(_)) {
            return None;
        }
        resident = true;
    }
    if !resident {
        return None;
    }
    let mut r = ResidentRun::empty();
    for wk in walkers.iter() {
        let c = &wk.cache[level];
        (r.lo, r.hi) = (c.lo, c.hi);
        if !c.transparent {
            r.push(c.content, c.clear_cells, wk.f);
        }
    }
    Some(r)
}

impl<'a, 'f, T> ResidentRun<'a, 'f, T> {
    fn empty() -> Self {
        ResidentRun {
            lo: [0; 3],
            hi: [0; 3],
            slots: SmallVec::new(),
            all_clear: u64::MAX,
        }
    }

    /// A channel's brick (data or one value), its clear cells and transfer
    /// function. A value the function hides adds nothing at any step; one
    /// it shows, the same colour at every step (no cell is clear).
    fn push(&mut self, content: Content<'a, T>, clear: u64, f: &'f Frame<'a>) {
        let (tf, table) = (&f.tf_eval, &f.tf_table);
        let slot = match content {
            Content::Data(vox) => Slot {
                vox,
                clear,
                tf,
                table,
                konst: None,
            },
            Content::Value(v) => {
                let konst = tf.lookup_visible(v);
                Slot {
                    vox: &[],
                    clear: if konst.is_some() { 0 } else { u64::MAX },
                    tf,
                    table,
                    konst,
                }
            }
            Content::Unresolved | Content::Unmapped => unreachable!("a brick that serves"),
        };
        self.all_clear &= slot.clear;
        self.slots.push(slot);
    }
}

/// The run through the bricks of `r` from step `k − 1` (at `w`, the
/// step's position on `track` of grid `g` at `level`) to where the ray
/// leaves them or reaches `limit`: [`run_steps`], its samples and steps
/// added to `st`. Returns whether the ray ended and the step to go on from.
pub(crate) fn take_run<T: Sample>(
    f: &Frame,
    r: &ResidentRun<'_, '_, T>,
    (track, g, level): (&Track, Grid, usize),
    (w, k, limit): (Vec3, u64, f64),
    (exponent, terminate): (f32, bool),
    acc: &mut [f32; 4],
    st: &mut FrameStats,
) -> (bool, u64) {
    let end = track.run_end(g, (r.lo, r.hi), limit).max(k);
    let run = Run::new(f, level, track, w, r.lo, r.hi);
    let (done, stop, n) = run_steps(f, r, run, (k - 1, end), (exponent, terminate), acc, st);
    st.samples += n;
    st.exact += n;
    st.steps += stop - k;
    (done, end)
}

/// The steps `j .. end` of a run through the bricks of `r`: cells every
/// channel hides crossed, each other step's channels sampled from their
/// voxels (a channel whose cell is clear adds nothing and is left out),
/// mixed as [`dvr_pixel`] mixes them and composited into `acc`. The
/// positions are the run's (fixed point, `Run`), the step path's within
/// rounding. Returns whether the ray ended (early termination), the step
/// it stopped before and the samples taken (channels sampled at a step).
/// Adds the cells crossed and the transparent samples to `st`.
pub(crate) fn run_steps<T: Sample>(
    f: &Frame,
    r: &ResidentRun<'_, '_, T>,
    mut run: Run,
    (mut j, end): (u64, u64),
    (exponent, terminate): (f32, bool),
    acc: &mut [f32; 4],
    st: &mut FrameStats,
) -> (bool, u64, u64) {
    let [sz, sy] = f.stride;
    let lanes = f.scene.lanes;
    let first = f.local_index([0; 3], [0; 3]);
    let (mut samples, mut transparent, mut passed) = (0u64, 0u64, 0u64);
    let done = loop {
        if j >= end {
            break false;
        }
        let (u, fr) = run.current();
        let cell = f.cell_in_run(u);
        if r.all_clear >> cell & 1 != 0 {
            passed += 1;
            j = run.cross_cell(f, u, (j, end));
            continue;
        }
        run.advance(1);
        j += 1;
        let i = first + u[0] as usize * sz + u[1] as usize * sy + u[2] as usize;
        let mut mix = Media::NONE;
        for ch in &r.slots {
            if ch.clear >> cell & 1 != 0 {
                continue;
            }
            samples += 1;
            let found = match ch.konst {
                Some(k) => Some(k),
                // Four lanes (`Scene::lanes`): the scalar twin's bits.
                None if lanes => ch
                    .table
                    .lookup_visible(
                        ch.tf,
                        trilinear_lanes(ch.vox, i, sz, sy, fr),
                        T::DTYPE.is_float(),
                    )
                    .map(|c| {
                        let [a, r, g, b] = c.to_array();
                        [r, g, b, a]
                    }),
                None => ch.tf.lookup_visible(trilinear(ch.vox, i, sz, sy, fr)),
            };
            match found {
                Some(c) => {
                    mix.add(c);
                }
                None => transparent += 1,
            }
        }
        if let Some(c) = mix.sample() {
            if composite_visible(acc, c, exponent) && terminate {
                break true;
            }
        }
    };
    st.transparent += transparent;
    st.skipped_cells += passed;
    (done, j, samples)
}

/// After a step every channel shown took from a stand-in of one level
/// (its brick at the step's level `level` not resident, the finest
/// resident coarser one, data or one value, of the same level `lv` for all) or
/// hid by its value range, some from a stand-in: `lv`, the index of the
/// first such channel and the run's bricks (the stand-ins', which share
/// their box). `None` otherwise.
fn stand_in_run<'a, 'f, T: Sample>(
    walkers: &[Walker<'f, 'a, T>],
    level: usize,
) -> Option<(usize, usize, ResidentRun<'a, 'f, T>)> {
    if walkers.len() > RUN_CHANNELS {
        return None;
    }
    let mut at: Option<(usize, usize)> = None;
    for (i, wk) in walkers.iter().enumerate() {
        let c = &wk.cache[level];
        if wk.f.channel_level(level) != level {
            return None;
        }
        if c.transparent {
            continue;
        }
        if !matches!(c.content, Content::Unmapped) {
            return None;
        }
        let lv = wk.stand_in_level(level)?;
        match at {
            None => at = Some((lv, i)),
            Some((l, _)) if l != lv => return None,
            Some(_) => {}
        }
    }
    let (lv, first) = at?;
    let mut r = ResidentRun::empty();
    for wk in walkers {
        let s = &wk.cache[lv];
        if !wk.cache[level].transparent {
            (r.lo, r.hi) = (s.lo, s.hi);
            r.push(s.content, s.clear_cells, wk.f);
        }
    }
    Some((lv, first, r))
}
