//! The walker: one thread's view of one channel while it draws. Per level
//! the brick its last sample fell into (page tables walked once per brick,
//! usage marked, value range and transparency known), a direct-mapped memo
//! of every brick resolved this frame, misses counted per brick and handed
//! to the request collector when the walker leaves it, and the general
//! sample path that falls back to the finest resident coarser level.

use super::{first_step, inside, trilinear, Frame, Grid, Track};
use crate::cpu::FrameStats;
use crate::params::RenderMode;
use brickyard_cache::brick::BrickKey;
use brickyard_cache::cells;
use brickyard_cache::vm::{BrickRef, Requests};
use brickyard_core::camera::{Ray, Vec3};
use brickyard_core::{cast_slice, Dims3, Sample};

/// What a walker knows about the brick it is in at one level.
#[derive(Clone, Copy)]
pub(crate) enum Content<'a, T> {
    /// Page tables not walked yet.
    Unresolved,
    Unmapped,
    /// EMPTY (0) or CONSTANT.
    Value(f32),
    Data(&'a [T]),
}

#[derive(Clone, Copy)]
pub(crate) struct Cached<'a, T> {
    /// Voxel box `[lo, hi)` of the brick (empty: nothing cached).
    pub(crate) lo: Dims3,
    pub(crate) hi: Dims3,
    pub(crate) brick: Dims3,
    pub(crate) content: Content<'a, T>,
    /// Value range (apron included); NaN: unknown.
    pub(crate) range: [f32; 2],
    /// DVR: every sample in it is transparent.
    pub(crate) transparent: bool,
    /// DVR, resident bricks: bit `i` set when every sample of cell `i` is
    /// transparent.
    pub(crate) clear_cells: u64,
    /// Samples that missed it, not yet handed to the request collector.
    pub(crate) missed: u32,
    /// Pool slot of a resident brick (`u32::MAX` otherwise).
    pub(crate) slot: u32,
    /// The slot is marked as used at its own level this frame (or needs
    /// no mark).
    pub(crate) marked: bool,
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
    pub(crate) fn contains(&self, v: Dims3) -> bool {
        inside(v, self.lo, self.hi)
    }
}

// A brick's clear cells are one bit each in a u64.
const _: () = assert!(cells::MAX_CELLS <= 64);

/// Entries of a walker's brick memo (a power of two).
pub(crate) const MEMO: usize = 1024;

/// Entries of a walker's table of pending misses (a power of two).
const PENDING: usize = 256;

/// A brick of level `l` as one number (the memo's and the pending
/// misses' key): four bits of level, twenty of brick index per axis.
#[inline(always)]
fn brick_code(l: usize, brick: Dims3) -> u64 {
    ((l as u64) << 60) | (brick[0] << 40) | (brick[1] << 20) | brick[2]
}

/// The slot of `code` in a direct-mapped table of `n` (a power of two).
#[inline(always)]
fn code_slot(code: u64, n: usize) -> usize {
    (code.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> (64 - n.trailing_zeros())) as usize
}

/// A boxed table of `N` copies of `x` (made on the heap, not the stack).
fn table<X: Clone, const N: usize>(x: X) -> Box<[X; N]> {
    vec![x; N]
        .into_boxed_slice()
        .try_into()
        .unwrap_or_else(|_| unreachable!("a vector of N elements"))
}

/// One thread's view of one channel: the current brick per level, and a
/// memo of every brick resolved this frame (direct-mapped by level and
/// brick), so that the rays of a tile, which enter the same bricks one
/// after another, walk the page tables about once per brick.
pub(crate) struct Walker<'f, 'a, T> {
    pub(crate) f: &'f Frame<'a>,
    pub(crate) channel: usize,
    pub(crate) cache: Vec<Cached<'a, T>>,
    /// (Arrays of the tables' fixed sizes: a slot from [`code_slot`] is
    /// in bounds without a check.)
    pub(crate) memo_key: Box<[u64; MEMO]>,
    pub(crate) memo: Box<[Cached<'a, T>; MEMO]>,
    /// Bricks entered (a change of brick at some level), for debug images.
    pub(crate) touched: u64,
    /// The ray being drawn (a serial number) and its tracks per level, made
    /// when a jump over a hidden stand-in first needs them.
    pub(crate) ray_serial: u64,
    /// MIP: the ray ends at its first value of at least this (the frame's
    /// [`Frame::mip_stop`]; a channel of several: its window's).
    pub(crate) mip_stop: f32,
    pub(crate) tracks: Vec<(u64, Option<Track>)>,
    /// Per level, where the current ray leaves the cached brick: (ray
    /// serial, the brick's first voxel, the exit's parameter with no limit
    /// ([`Track::exit_t`]), the track's slack). A first frame drawn from
    /// stand-ins ends a run at the first exit of three or more bricks a
    /// few times per ray; the coarser ones stay the same over many runs.
    exits: Vec<(u64, Dims3, f64, f64)>,
    /// Misses handed over by bricks the walker left, summed per brick
    /// (direct-mapped by [`brick_code`], `u64::MAX`: free) and passed to
    /// the request collector when a slot is taken by another brick or at
    /// [`flush`](Self::flush): the rays of a tile leave the same few
    /// bricks over and over, and a first frame drawn from stand-ins
    /// leaves one every few steps.
    pending_code: Box<[u64; PENDING]>,
    pending_misses: Box<[u32; PENDING]>,
}

impl<'f, 'a, T: Sample> Walker<'f, 'a, T> {
    pub(crate) fn new(f: &'f Frame<'a>, channel: usize) -> Self {
        Walker {
            f,
            channel,
            cache: vec![Cached::NONE; f.levels()],
            memo_key: Box::new([u64::MAX; MEMO]),
            memo: table(Cached::NONE),
            touched: 0,
            ray_serial: 1,
            mip_stop: f.mip_stop,
            tracks: vec![(0, None); f.levels()],
            exits: vec![(0, [0; 3], 0.0, 0.0); f.levels()],
            pending_code: Box::new([u64::MAX; PENDING]),
            pending_misses: Box::new([0; PENDING]),
        }
    }

    /// The track of the current ray at level `l` (see `ray_serial`).
    pub(crate) fn track_of(&mut self, l: usize, ray: &Ray, inv_dir: Vec3, t_end: f64) -> Track {
        *self.track_ref(l, ray, inv_dir, t_end)
    }

    /// [`track_of`](Self::track_of), not copied.
    #[inline(always)]
    fn track_ref(&mut self, l: usize, ray: &Ray, inv_dir: Vec3, t_end: f64) -> &Track {
        let (serial, t) = &mut self.tracks[l];
        if *serial != self.ray_serial || t.is_none() {
            *t = Some(self.f.track(l, ray, inv_dir, t_end));
            *serial = self.ray_serial;
        }
        t.as_ref().expect("made above")
    }

    /// Hand every pending miss to the collector.
    pub(crate) fn flush(&mut self, req: &mut Requests) {
        for l in 0..self.cache.len() {
            self.flush_level(l, req);
        }
        for slot in 0..PENDING {
            self.spill(slot, req);
        }
    }

    #[inline]
    pub(crate) fn flush_level(&mut self, l: usize, req: &mut Requests) {
        if self.cache[l].missed > 0 {
            self.flush_misses(l, req);
        }
    }

    /// Move the misses of the cached brick of level `l` to the pending
    /// table.
    #[cold]
    pub(crate) fn flush_misses(&mut self, l: usize, req: &mut Requests) {
        let c = &mut self.cache[l];
        let n = std::mem::take(&mut c.missed);
        let code = brick_code(l, c.brick);
        let slot = code_slot(code, PENDING);
        if self.pending_code[slot] == code {
            self.pending_misses[slot] = self.pending_misses[slot].saturating_add(n);
            return;
        }
        self.spill(slot, req);
        self.pending_code[slot] = code;
        self.pending_misses[slot] = n;
    }

    /// Hand the misses of pending slot `slot` (if any) to the collector.
    fn spill(&mut self, slot: usize, req: &mut Requests) {
        let code = std::mem::replace(&mut self.pending_code[slot], u64::MAX);
        if code == u64::MAX {
            return;
        }
        let m = (1 << 20) - 1;
        let brick = [(code >> 40) & m, (code >> 20) & m, code & m].map(|b| b as u32);
        let key = BrickKey::new((code >> 60) as u8, self.channel as u16, brick);
        req.add(key, self.pending_misses[slot]);
    }

    /// Make the cache of level `l` hold the brick of voxel `v`.
    /// `exact`: the sample asks for level `l` (not a stand-in lookup).
    #[inline(always)]
    pub(crate) fn enter(
        &mut self,
        l: usize,
        v: Dims3,
        req: &mut Requests,
        exact: bool,
    ) -> &Cached<'a, T> {
        if !self.cache[l].contains(v) {
            self.refill(l, v, req, exact);
        } else if exact && !self.cache[l].marked {
            self.mark(l);
        }
        &self.cache[l]
    }

    #[cold]
    pub(crate) fn refill(&mut self, l: usize, v: Dims3, req: &mut Requests, exact: bool) {
        self.flush_level(l, req);
        self.touched += 1;
        let f = self.f;
        let brick = f.brick_of(v);
        let key = brick_code(l, brick);
        let slot = code_slot(key, MEMO);
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
    pub(crate) fn mark(&mut self, l: usize) {
        let c = &mut self.cache[l];
        self.f.vm.mark_exact(c.slot);
        c.marked = true;
    }

    /// Walk the page tables for the cached brick of level `l`.
    #[cold]
    pub(crate) fn resolve(&mut self, l: usize, exact: bool) {
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
                        // (A label image's rays cross background alone.)
                        let clear = match f.params.labels {
                            true => {
                                crate::optics::label_clear(lo, hi, f.params.label_select.as_ref())
                            }
                            false => !f.tf_eval.range_visible(lo, hi),
                        };
                        if clear {
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
    pub(crate) fn value(
        &mut self,
        l: usize,
        w: Vec3,
        base: Dims3,
        frac: [f32; 3],
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        self.value_masked(l, w, base, frac, u32::MAX, req, st)
    }

    /// [`value`](Self::value), falling back only to the coarser levels
    /// whose bit is set in `mask` (the residency octree's: levels with
    /// nothing mapped nearby are not looked up).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(crate) fn value_masked(
        &mut self,
        l: usize,
        w: Vec3,
        base: Dims3,
        frac: [f32; 3],
        mask: u32,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> Option<f32> {
        st.samples += 1;
        let (mut base, mut frac) = (base, frac);
        for lv in l..self.cache.len() {
            if lv > l {
                if mask >> lv & 1 == 0 {
                    continue;
                }
                (base, frac) = self.f.sample_coords(lv, w);
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
        for lv in l + 1..self.cache.len() {
            if mask >> lv & 1 == 0 {
                let (b, _) = self.f.coords(lv, w);
                self.enter(lv, b, req, false);
            }
            self.cache[lv].missed += 1;
        }
        st.unserved += 1;
        None
    }

    /// After a transparent sample served by a stand-in (the brick of
    /// `level` is not resident; the finest resident coarser level served
    /// it): when the stand-in hides every sample around it, cross the
    /// region where it would serve and hide them all, without sampling.
    /// The stand-in hides the region when the transfer function hides its
    /// whole brick (by its value range) or the clear cell holding the
    /// sample's voxel base at its level; the region is that box, within the
    /// box of every level's brick the lookup passed through (not resident,
    /// so the same stand-in serves the next samples). Each landing comes at
    /// or before the first step that may lie outside its box, so only steps
    /// that would have been looked up and found transparent are jumped:
    /// the image is the same. First frames of a streamed view, drawn mostly
    /// from stand-ins, otherwise take every step through empty space. The
    /// steps jumped count as steps (not samples), the jump as a skipped
    /// cell (or brick), and the steps as misses of the brick of `level`
    /// (its request keeps its weight). Returns the step
    /// index to continue from; `None` when the stand-in does not hide the
    /// region.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn skip_hidden_stand_in(
        &mut self,
        level: usize,
        ray: &Ray,
        inv_dir: Vec3,
        w: Vec3,
        (g, k): (Grid, u64),
        (limit, t_end): (f64, f64),
        st: &mut FrameStats,
    ) -> Option<u64> {
        let f = self.f;
        if !matches!(f.params.mode, RenderMode::Dvr)
            || self.channel != f.scene.channel
            || !matches!(self.cache[level].content, Content::Unmapped)
        {
            return None;
        }
        let lv = self.stand_in_level(level)?;
        let c = &self.cache[lv];
        let whole = c.transparent;
        let (lo, hi) = if whole {
            (c.lo, c.hi)
        } else if c.clear_cells != 0 && matches!(c.content, Content::Data(_)) {
            let (u, _) = f.coords(lv, w);
            let cell = f.cell_of([0, 1, 2].map(|a| u[a] - c.lo[a]));
            if c.clear_cells >> cell & 1 == 0 {
                return None;
            }
            f.cell_box(cell, c.lo, c.hi)
        } else {
            return None;
        };
        let track = self.track_ref(lv, ray, inv_dir, t_end);
        let kn = f
            .land(ray, track, g, k, (lo, hi), limit)
            .min(self.land_in_bricks(level..lv, ray, inv_dir, (g, k), (limit, t_end)));
        let n = kn.saturating_sub(k);
        st.steps += n;
        if whole {
            st.skipped_bricks += 1;
        } else {
            st.skipped_cells += 1;
        }
        let c = &mut self.cache[level];
        c.missed = c.missed.saturating_add(n as u32);
        Some(kn.max(k))
    }

    /// After a sample at `level` that a resident stand-in served (the
    /// brick of `level` not resident; the finest coarser level that is
    /// holds data): the stand-in's level, voxels and box, and the step a
    /// run through it ends at, the first from `k` whose voxel base may
    /// leave the brick of `level`, of the stand-in or of any level between
    /// (not resident either), or whose parameter reaches `limit`. Every
    /// step before it would be served by the same stand-in brick, the
    /// way [`value`](Self::value) serves it, so a run may sample it there
    /// without the lookups. `None` when the sample was not served so, or
    /// the run would be empty.
    #[allow(clippy::type_complexity)]
    pub(crate) fn stand_in_run(
        &mut self,
        level: usize,
        ray: &Ray,
        inv_dir: Vec3,
        (g, k): (Grid, u64),
        (limit, t_end): (f64, f64),
    ) -> Option<(usize, &'a [T], Dims3, u64)> {
        if !matches!(self.cache[level].content, Content::Unmapped) {
            return None;
        }
        let lv = self.stand_in_level(level)?;
        let Content::Data(vox) = self.cache[lv].content else {
            return None;
        };
        let lo = self.cache[lv].lo;
        let end = self.land_in_bricks(level..lv + 1, ray, inv_dir, (g, k), (limit, t_end));
        (end > k).then_some((lv, vox, lo, end))
    }

    /// The finest level coarser than `level` whose cached brick holds data
    /// or one value: the stand-in that served the last sample of `level`.
    pub(crate) fn stand_in_level(&self, level: usize) -> Option<usize> {
        (level + 1..self.cache.len())
            .find(|&m| matches!(self.cache[m].content, Content::Data(_) | Content::Value(_)))
    }

    /// The first step from `k` that may leave the cached brick of any of
    /// `levels` (step `k − 1` lies in each) or reach `limit`: the smallest
    /// of their landings; `u64::MAX` for no level.
    pub(crate) fn land_in_bricks(
        &mut self,
        levels: std::ops::Range<usize>,
        ray: &Ray,
        inv_dir: Vec3,
        (g, k): (Grid, u64),
        (limit, t_end): (f64, f64),
    ) -> u64 {
        let f = self.f;
        let mut end = u64::MAX;
        for m in levels {
            let (lo, hi) = (self.cache[m].lo, self.cache[m].hi);
            let (serial, at, exit, slack) = self.exits[m];
            let (exit, slack) = if serial == self.ray_serial && at == lo {
                (exit, slack)
            } else {
                let track = self.track_ref(m, ray, inv_dir, t_end);
                let (exit, slack) = (track.exit_t(lo, hi, f64::INFINITY), track.slack);
                self.exits[m] = (self.ray_serial, lo, exit, slack);
                (exit, slack)
            };
            // `Frame::land`: the estimate where the margin is under a
            // quarter step (`exit_t` with the limit is the smaller of the
            // two, the limit when it is NaN, as here).
            let margin = slack * g.inv_dt;
            let kn = if margin < 0.25 {
                let te = if exit < limit { exit } else { limit };
                first_step(g, te, margin).max(k)
            } else {
                f.land(
                    ray,
                    self.track_ref(m, ray, inv_dir, t_end),
                    g,
                    k,
                    (lo, hi),
                    limit,
                )
            };
            end = end.min(kn);
        }
        end
    }

    /// After a sample that nothing resident could serve: cross the rest of
    /// the level's brick in one jump (first frames would otherwise walk
    /// the whole fallback chain for every sample of a region with nothing
    /// to show). The steps jumped count as unserved samples and as misses
    /// of the brick, so its request keeps its weight. Returns the step
    /// index to continue from.
    pub(crate) fn skip_unserved(
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
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::*;
    use crate::cpu::Lod;
    use std::collections::HashMap;

    /// Misses handed over brick by brick reach the collector with the
    /// same sum per brick as adding each at once: bricks seen again and
    /// again (hits in the pending table), many bricks colliding in it
    /// (spills), and what is still pending at the end (`flush`).
    #[test]
    fn pending_misses_reach_the_collector_summed_per_brick() {
        let (vm, scene, params) = fixture([64, 64, 64], [8, 8, 8], [1.0; 3]);
        let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let mut wk = Walker::<u8>::new(&f, 0);
        let mut req = Requests::with_capacity(1 << 16);
        let mut model: HashMap<BrickKey, u32> = HashMap::new();
        let mut rnd = uniform(11);
        for i in 0..40_000 {
            // Alternately from 27 bricks and from 4096 (over the table's
            // size: slots taken by other bricks).
            let n = if i % 2 == 0 { 3.0 } else { 16.0 };
            let b = [0, 1, 2].map(|_| (rnd() * n) as u64);
            let m = 1 + (rnd() * 9.0) as u32;
            // Leaving a brick with misses, as `refill` does.
            wk.cache[0].brick = b;
            wk.cache[0].missed = m;
            wk.flush_level(0, &mut req);
            assert_eq!(wk.cache[0].missed, 0);
            let key = BrickKey::new(0, 0, b.map(|v| v as u32));
            *model.entry(key).or_default() += m;
        }
        wk.flush(&mut req);
        let got: HashMap<BrickKey, u32> = req.iter().collect();
        assert_eq!(got.len(), model.len());
        assert_eq!(got, model);
        assert_eq!(req.dropped, 0);
    }

    /// The landing in the bricks of several levels at once, with their
    /// exits remembered per ray and brick, is the first of the bricks' own
    /// landings (`Frame::land`): over rays, steps and limits, with the
    /// cached bricks changing under one ray and staying over several
    /// calls, and rays nearly parallel to a voxel plane.
    #[test]
    fn landing_in_several_bricks_is_the_first_of_their_landings() {
        let levels = vec![[40u64, 56, 48], [20, 28, 24], [10, 14, 12]];
        let extent = [1.3, 0.9, 1.7];
        let (vm, scene, params) = fixture_of(levels.clone(), [8; 3], extent);
        let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let mut wk = Walker::<u8>::new(&f, 0);
        let mut rnd = uniform(0x5eed);
        let (mut calls, mut parallel) = (0, 0);
        for trial in 0..3000 {
            let target = [0, 1, 2].map(|a| rnd() * extent[a]);
            let mut dir = [0, 1, 2].map(|_| rnd() - 0.5);
            if trial % 7 == 0 {
                dir[trial % 3] = 1e-13 * (rnd() - 0.5);
            }
            let dt = f.voxel[0] * (0.3 + 1.2 * rnd());
            let Some((ray, (_, t1), g, _, _)) =
                random_step(&f, extent, (target, dir, 3.0), dt, rnd())
            else {
                continue;
            };
            wk.ray_serial += 1;
            let inv_dir = ray.dir.map(|d| 1.0 / d);
            parallel += (f.track(0, &ray, inv_dir, t1).slack * g.inv_dt >= 0.25) as u32;
            // Several calls along the ray, from steps further and further
            // on: the bricks of the step before at every level, or (one
            // call in four) the brick of another step at one level.
            let steps = ((t1 - g.base_t) * g.inv_dt) as u64;
            let mut k = 1 + (rnd() * steps as f64 / 2.0) as u64;
            while k < steps {
                for (m, dims) in levels.iter().enumerate() {
                    let kk = if rnd() < 0.25 {
                        (rnd() * steps as f64) as u64
                    } else {
                        k - 1
                    };
                    let (v, _) = f.coords(m, ray.at(super::super::step_t(g.base_t, kk, dt)));
                    let b = f.brick_of(v);
                    let lo = [0, 1, 2].map(|a| b[a] * 8);
                    let hi = [0, 1, 2].map(|a| (lo[a] + 8).min(dims[a]));
                    (wk.cache[m].lo, wk.cache[m].hi) = (lo, hi);
                }
                let limit = if rnd() < 0.3 {
                    g.base_t + rnd() * (t1 - g.base_t)
                } else {
                    t1
                };
                let want = (0..3)
                    .map(|m| {
                        let track = f.track(m, &ray, inv_dir, t1);
                        let (lo, hi) = (wk.cache[m].lo, wk.cache[m].hi);
                        f.land(&ray, &track, g, k, (lo, hi), limit)
                    })
                    .min()
                    .unwrap();
                let got = wk.land_in_bricks(0..3, &ray, inv_dir, (g, k), (limit, t1));
                assert_eq!(got, want, "trial {trial}, step {k}");
                calls += 1;
                k += 1 + (rnd() * 6.0) as u64;
            }
        }
        assert!(calls > 20_000, "{calls} landings checked");
        assert!(parallel > 50, "{parallel} rays nearly parallel to a plane");
    }
}
