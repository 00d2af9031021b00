//! Budget-aware level of detail: the per-view LOD bias that makes a view's
//! working set fit the brick pool.
//!
//! A view whose finest working set is larger than the pool can never
//! complete at full resolution: every slot serves a sample at its own level,
//! the bricks still asked for find no slot, and the frame loop would go on
//! forever. [`LodBudget`] watches each frame's signals and coarsens the view
//! (raises the bias of automatic LOD, or the fixed level) until the working
//! set fits; then the view converges to a complete image at that detail. An
//! interactive view refines again, with hysteresis, when the working set
//! has shrunk well below the pool.
//!
//! The same rule serves the CPU and the device back ends and the viewer; it
//! only reads per-frame counts.

use crate::cpu::Lod;
#[cfg(feature = "loader")]
use brickyard_cache::session::{FrameStats, Session};

/// What one frame tells the controller.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FrameSignals {
    /// Every sample was served at the level it asked for.
    pub complete: bool,
    /// Bricks still asked for (the capped list, failed bricks left out).
    pub requests: usize,
    /// Distinct bricks asked for before the cap (failed left out).
    pub requested: usize,
    /// Data bricks that arrived but found no pool slot: every slot served
    /// a sample at its own level this frame.
    pub deferred: usize,
    /// Pool slots used at their own level this frame, pinned ones left
    /// out, when known (`None`: treated as a full pool).
    pub exact_slots: Option<usize>,
    /// Pool slots not pinned.
    pub free_slots: usize,
    /// Something changed this frame: a brick arrived or loads are pending.
    pub progress: bool,
    /// Bricks evicted that one of the views drawn in turn used at their
    /// own level in its latest frame (see [`FrameSignals::shared_with`]).
    pub evicted_in_use: usize,
}

impl FrameSignals {
    #[cfg(feature = "loader")]
    /// The signals of a frame: `fs` is what the session said of it
    /// ([`Session::finish_frame`]), `complete` whether every sample was
    /// served at its own level, `exact_slots` the slots used at their own
    /// level where the back end counts them. Failed bricks are left out of
    /// the request counts: asking for them again cannot help.
    pub fn of_frame(
        s: &Session,
        fs: &FrameStats,
        complete: bool,
        exact_slots: Option<usize>,
    ) -> FrameSignals {
        let failed_in_list = fs
            .frame
            .requests
            .iter()
            .filter(|k| s.vm().is_failed(**k))
            .count();
        FrameSignals {
            complete,
            requests: fs.frame.requests.len() - failed_in_list,
            requested: fs.frame.requested.saturating_sub(failed_in_list),
            deferred: fs.insert.deferred,
            exact_slots,
            free_slots: s.vm().pool_slots() - s.vm().pinned_bricks(),
            progress: fs.insert.inserted + fs.insert.flagged + fs.delivered > 0
                || fs.pending + fs.in_flight + fs.waiting_upload > 0,
            evicted_in_use: fs.insert.evicted_in_use,
        }
    }

    /// Slots this view needs: those it used at their own level and the
    /// bricks it still asks for.
    pub fn need(&self) -> usize {
        self.exact_slots.unwrap_or(self.free_slots) + self.requested.max(self.requests)
    }

    /// The signals of one of several views drawn in turn from one pool,
    /// where the other views still drawing need `others` slots, the
    /// largest of them `largest`, and `contended` says that bricks one of
    /// them used at their own level in its latest frame were evicted
    /// since (their bricks together do not fit: each view's arrivals
    /// evict the others' bricks and theirs its own, frame after frame,
    /// every view making progress and none completing). Then the view
    /// that needs the most (this one, when it needs at least `largest`)
    /// counts the pool as saturated, with what the others leave as its
    /// room, and its budget coarsens; the next largest follows in a later
    /// turn while the contention lasts. (The needs are summed: bricks two
    /// views share count twice, which is why contention must be seen
    /// first.)
    pub fn shared_with(mut self, others: usize, largest: usize, contended: bool) -> FrameSignals {
        let need = self.need();
        if !contended || others == 0 || self.requests == 0 || need < largest {
            return self;
        }
        if need + others > self.free_slots {
            self.deferred = self.deferred.max(1);
            self.free_slots = self.free_slots.saturating_sub(others).max(1);
        }
        self
    }
}

/// Why a non-interactive render stops.
#[derive(Debug, Clone, PartialEq)]
pub enum Stop {
    /// Every sample at the level it asked for (under the current bias).
    Complete,
    /// Nothing left to ask for but bricks that failed to load (drawn from
    /// coarser data).
    CompleteButFailed,
    /// No progress for several frames (nothing arrives, nothing can be
    /// placed, the bias is at its limit).
    NoProgress,
}

/// The controller's decision after a frame.
#[derive(Debug, Clone, PartialEq)]
pub enum Decision {
    /// Draw another frame.
    Continue,
    /// The bias changed (coarser or finer); draw another frame.
    Changed { from: f64, to: f64 },
    /// A try at a finer bias ([`LodBudget::try_finer`]) did not fit: the
    /// bias is back at `to`, where the view was complete, and that
    /// complete image is the result.
    Revert { from: f64, to: f64 },
    /// A render may stop here.
    Stop(Stop),
}

/// The per-view LOD bias and its rules.
#[derive(Debug, Clone)]
pub struct LodBudget {
    /// The bias the user asked for (never refined past it).
    pub base: f64,
    /// The bias in force now (≥ `base`).
    pub bias: f64,
    /// The largest bias worth trying (every sample at the coarsest level).
    pub max: f64,
    /// Whether the bias may go down again (views), or only up (renders).
    pub interactive: bool,
    /// Frames in a row with too little room.
    saturated: u32,
    /// Frames in a row with much room to spare (views).
    roomy: u32,
    /// Frames in a row without progress.
    stalled: u32,
    /// What the first frame that did not fit at the user's bias asked for,
    /// in bricks (slots used at their own level and bricks asked for). An
    /// estimate: a frame still waiting for data lets rays run on past
    /// what would have stopped them.
    pub needed_at_base: Option<usize>,
    /// While a render tries a finer bias ([`try_finer`](Self::try_finer)):
    /// the bias it was complete at.
    trying: Option<f64>,
    /// The finest bias a try found too fine for the pool, for the view in
    /// hand (never tried again until the view changes).
    too_fine: Option<f64>,
}

/// Steps of the bias.
const STEP: f64 = 0.5;
/// Frames without progress before a render gives up.
const STALL_FRAMES: u32 = 8;

impl LodBudget {
    /// A controller starting at the user's bias `base`, for a volume of
    /// `levels` levels.
    pub fn new(base: f64, levels: usize, interactive: bool) -> LodBudget {
        LodBudget {
            base,
            bias: base,
            // A bias of `levels − 1` sends every sample to the coarsest
            // level from any distance (`Lod::level_for`: the bias applies
            // also where a pixel spans less than a voxel).
            max: base.max(levels.max(1) as f64 - 1.0),
            interactive,
            saturated: 0,
            roomy: 0,
            stalled: 0,
            needed_at_base: None,
            trying: None,
            too_fine: None,
        }
    }

    /// A render complete at a bias coarser than the user's: try half a
    /// level finer, returning `(from, to)`, or `None` when there is no
    /// finer bias to try (at the user's, or that bias was found too fine
    /// for this view). The caller keeps the complete image: if the finer
    /// bias does not fit, [`update`](Self::update) says
    /// [`Decision::Revert`] and that image is the result.
    ///
    /// The bias is raised from frames still waiting for data, whose rays
    /// run on past what the missing bricks would have stopped: they ask
    /// for more than the view needs, and how much more depends on the
    /// order bricks arrive in (the back ends differ). Trying finer from
    /// a complete view, with the coarser bricks in the pool standing in,
    /// settles every back end at the finest bias that fits.
    pub fn try_finer(&mut self) -> Option<(f64, f64)> {
        self.try_finer_to((self.bias - STEP).max(self.base))
    }

    /// [`try_finer`](Self::try_finer) for a fixed level, which the bias
    /// moves by whole levels ([`apply`](Self::apply)): the next finer level
    /// drawn (half a level finer would often draw the same one).
    pub fn try_finer_level(&mut self) -> Option<(f64, f64)> {
        let extra = (self.bias - self.base).max(0.0).ceil();
        self.try_finer_to(self.base + (extra - 1.0).max(0.0))
    }

    fn try_finer_to(&mut self, to: f64) -> Option<(f64, f64)> {
        if self.interactive || self.bias <= self.base {
            return None;
        }
        if self.too_fine.is_some_and(|t| to <= t) {
            return None;
        }
        let from = self.bias;
        self.trying = Some(from);
        self.bias = to;
        self.saturated = 0;
        self.stalled = 0;
        Some((from, to))
    }

    /// Whether a finer bias is being tried.
    pub fn trying_finer(&self) -> bool {
        self.trying.is_some()
    }

    /// Give up the try at a finer bias (the render ends before it could
    /// tell): the bias goes back to the one that was complete.
    pub fn abandon_try(&mut self) -> Option<Decision> {
        let to = self.trying.take()?;
        let from = self.bias;
        self.too_fine = Some(from);
        self.bias = to;
        Some(Decision::Revert { from, to })
    }

    /// The level of detail to draw with: `lod` shifted by the bias in
    /// force (automatic LOD: the bias replaces the user's; a fixed level
    /// moves to a coarser one by the whole levels of the extra bias).
    pub fn apply(&self, lod: Lod, levels: usize) -> Lod {
        match lod {
            Lod::Auto { .. } => Lod::Auto { bias: self.bias },
            Lod::Fixed(l) => {
                let extra = (self.bias - self.base).max(0.0).ceil() as usize;
                Lod::Fixed((l + extra).min(levels.saturating_sub(1)))
            }
        }
    }

    /// The extra bias in force (0 when the view fits at the asked detail).
    pub fn extra(&self) -> f64 {
        self.bias - self.base
    }

    /// The view changed (camera, mode): forget the counts of frames, keep
    /// the bias (the next frames correct it either way).
    pub fn view_changed(&mut self) {
        self.saturated = 0;
        self.roomy = 0;
        self.stalled = 0;
        self.too_fine = None;
        if let Some(to) = self.trying.take() {
            self.bias = to;
        }
    }

    /// Take one frame's signals and decide.
    pub fn update(&mut self, s: &FrameSignals) -> Decision {
        // Saturated: bricks are wanted, and what arrived found no room.
        // Bricks that arrived and wait for a slot are not asked for again
        // (on the device they are not: a streamed view whose waiting
        // bricks found no slot, frame after frame, asked for nothing and
        // ran until it was killed): an incomplete view counts them as
        // wanted.
        let full = s.deferred > 0 && (s.requests > 0 || !s.complete);
        if full {
            self.saturated += 1;
        } else {
            self.saturated = 0;
        }
        if s.progress || full {
            self.stalled = 0;
        } else if !s.complete {
            self.stalled += 1;
        }
        if self.trying.is_some() {
            // A finer try: complete, it holds (the caller may try finer
            // still); anything else (no room, a stall, bricks that failed)
            // and the complete image at the coarser bias is the result.
            if s.complete {
                self.trying = None;
                return Decision::Stop(Stop::Complete);
            }
            let failed = s.requests == 0 && !s.progress;
            if full || failed || self.stalled >= STALL_FRAMES {
                return self.abandon_try().expect("trying");
            }
            return Decision::Continue;
        }
        if full && self.saturated >= 1 && self.bias < self.max {
            // How much too big is the working set? Slots used at their own
            // level plus bricks still asked for, against the room there is.
            let used = s.exact_slots.unwrap_or(s.free_slots);
            let need = used + s.requested.max(s.requests).max(s.deferred);
            if self.bias == self.base && self.needed_at_base.is_none() {
                self.needed_at_base = Some(need);
            }
            let room = (s.free_slots as f64 * 0.85).max(1.0);
            // A working set shrinks about 4× per level for surfaces (rays
            // end early) and 8× for volumes seen through: take the surface
            // rate, the safe one, and step at least half a level.
            let levels = ((need as f64 / room).log2() / 2.0).max(STEP);
            let step = ((levels / STEP).ceil() * STEP).min(2.0);
            let from = self.bias;
            self.bias = (self.bias + step).min(self.max);
            self.saturated = 0;
            self.roomy = 0;
            return Decision::Changed {
                from,
                to: self.bias,
            };
        }
        // At the bias limit and still saturated frame after frame (bricks
        // arrive and find no slot): every sample at the coarsest level,
        // which stays resident, needs no slot, so the frames ask for
        // bricks of levels they do not draw. A render stops rather than
        // go on until its frames run out; what it drew is not complete.
        if !self.interactive && full && self.bias >= self.max && self.saturated >= STALL_FRAMES {
            return Decision::Stop(Stop::NoProgress);
        }
        if self.interactive {
            // Refine when the working set would still fit at the finer
            // bias (twice as many bricks for half a level, with a margin).
            let roomy = s.complete
                && self.bias > self.base
                && s.exact_slots
                    .is_some_and(|u| (u as f64) * 2.0 < 0.7 * s.free_slots as f64);
            if roomy {
                self.roomy += 1;
            } else {
                self.roomy = 0;
            }
            if self.roomy >= 3 {
                let from = self.bias;
                self.bias = (self.bias - STEP).max(self.base);
                self.roomy = 0;
                return Decision::Changed {
                    from,
                    to: self.bias,
                };
            }
            return Decision::Continue;
        }
        if s.complete {
            return Decision::Stop(Stop::Complete);
        }
        if s.requests == 0 && !s.progress {
            // Nothing left to load: what is missing failed.
            return Decision::Stop(Stop::CompleteButFailed);
        }
        if self.stalled >= STALL_FRAMES {
            return Decision::Stop(Stop::NoProgress);
        }
        Decision::Continue
    }
}

/// The time a frame of a moving view aims at (ms).
pub const MOVING_FRAME_MS: f64 = 40.0;

/// While a 3D view moves (the camera dragged or zoomed), the fraction of its
/// size per axis its frames are drawn at, from what a full-size redraw took
/// (`full_ms`): full size where that keeps up with [`MOVING_FRAME_MS`], else
/// the size that should (pixels cost alike), from half to a quarter. The
/// viewer and the web page share it; once the view rests it is drawn at
/// full size again.
///
/// `last` is the fraction the view's last moving frame was drawn at (1:
/// full size, or none yet). Once smaller, a moving view returns to full
/// size only where full-size redraws take at most three quarters of the
/// target, so that redraws timed near the line do not switch its size back
/// and forth from one drag (or one frame) to the next.
pub fn moving_scale(full_ms: f64, last: f64) -> f64 {
    let line = if last < 1.0 {
        0.75 * MOVING_FRAME_MS
    } else {
        MOVING_FRAME_MS
    };
    if full_ms.is_nan() || full_ms <= line {
        return 1.0;
    }
    (MOVING_FRAME_MS / full_ms).sqrt().clamp(0.25, 0.5)
}

/// `size` (width, height) at [`moving_scale`]'s fraction `k`, at least 8
/// pixels a side.
pub fn scaled_size(size: [u32; 2], k: f64) -> [u32; 2] {
    if k >= 1.0 {
        return size;
    }
    size.map(|s| ((s as f64 * k) as u32).max(8).min(s))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moving_views_shrink_only_when_full_frames_are_slow() {
        // Fast enough at full size (or not measured): full size.
        for ms in [0.0, 5.0, 40.0, f64::NAN] {
            assert_eq!(moving_scale(ms, 1.0), 1.0, "{ms}");
        }
        // Slower: half size from just above the target up to 4x it,
        // then the size that keeps up, down to a quarter.
        assert_eq!(moving_scale(41.0, 1.0), 0.5);
        assert_eq!(moving_scale(160.0, 1.0), 0.5);
        assert!((moving_scale(360.0, 1.0) - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(moving_scale(640.0, 1.0), 0.25);
        assert_eq!(moving_scale(1e6, 1.0), 0.25);
        // Once smaller, full size again only well under the line: redraws
        // timed at 38-42 ms keep the size they had.
        for ms in [31.0, 38.0, 40.0] {
            assert_eq!(moving_scale(ms, 0.5), 0.5, "{ms}");
        }
        assert_eq!(moving_scale(42.0, 0.5), 0.5);
        assert_eq!(moving_scale(38.0, 1.0), 1.0);
        assert_eq!(moving_scale(30.0, 0.5), 1.0);
        assert_eq!(moving_scale(f64::NAN, 0.5), 1.0);
        assert!((moving_scale(360.0, 0.25) - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(scaled_size([512, 300], 1.0), [512, 300]);
        assert_eq!(scaled_size([512, 300], 0.5), [256, 150]);
        assert_eq!(scaled_size([20, 12], 0.25), [8, 8]);
        assert_eq!(scaled_size([6, 20], 0.25), [6, 8]);
    }

    fn sig(complete: bool, requests: usize, deferred: usize, exact: usize) -> FrameSignals {
        FrameSignals {
            complete,
            requests,
            requested: requests,
            deferred,
            exact_slots: Some(exact),
            free_slots: 100,
            progress: deferred > 0 || requests > 0,
            evicted_in_use: 0,
        }
    }

    #[test]
    fn views_that_share_a_pool_coarsen_when_together_they_do_not_fit() {
        // 30 slots used and 20 asked for: 50 needed. Alone (100 slots) it
        // fits, and its arrivals find room (nothing deferred).
        let alone = sig(false, 20, 0, 30);
        assert_eq!(alone.need(), 50);
        assert_eq!(alone.shared_with(0, 0, true), alone);
        assert_eq!(alone.shared_with(50, 30, true), alone);
        // Beside views needing 60 slots (the largest 40) it does not fit.
        // Without contention seen (the views may share bricks) nothing
        // changes; with it: saturated, with the 40 slots they leave as its
        // room, and the budget coarsens.
        assert_eq!(alone.shared_with(60, 40, false), alone);
        let shared = alone.shared_with(60, 40, true);
        assert_eq!((shared.deferred, shared.free_slots), (1, 40));
        let mut b = LodBudget::new(0.0, 5, true);
        assert!(matches!(b.update(&shared), Decision::Changed { .. }));
        assert!(b.extra() > 0.0);
        // Another view needs more: that one coarsens first.
        assert_eq!(alone.shared_with(60, 55, true), alone);
        // Nothing left of the pool for it: a room of one slot.
        assert_eq!(alone.shared_with(120, 50, true).free_slots, 1);
        // A view that asks for nothing more is left alone.
        let done = sig(true, 0, 0, 30);
        assert_eq!(done.shared_with(90, 10, true), done);
    }

    #[test]
    fn a_saturated_pool_coarsens_by_the_working_sets_excess() {
        let mut b = LodBudget::new(0.0, 6, false);
        // 100 used + 1500 wanted in a pool of 100: 16× too big → 2 levels
        // at the surface rate (capped at 2).
        match b.update(&sig(false, 1500, 10, 100)) {
            Decision::Changed { from, to } => assert_eq!((from, to), (0.0, 2.0)),
            d => panic!("{d:?}"),
        }
        assert_eq!(b.needed_at_base, Some(1600));
        // Slightly too big: the smallest step.
        match b.update(&sig(false, 10, 1, 100)) {
            Decision::Changed { from, to } => assert_eq!((from, to), (2.0, 2.5)),
            d => panic!("{d:?}"),
        }
        // Fits: the render stops when complete, at that bias.
        assert_eq!(b.update(&sig(false, 5, 0, 60)), Decision::Continue);
        assert_eq!(
            b.update(&sig(true, 0, 0, 60)),
            Decision::Stop(Stop::Complete)
        );
        assert_eq!(b.bias, 2.5);
    }

    #[test]
    fn a_render_tries_finer_before_it_ends_and_reverts_when_that_does_not_fit() {
        let mut b = LodBudget::new(0.0, 6, false);
        // Raised by two levels from a frame that overstated its needs.
        assert!(matches!(
            b.update(&sig(false, 1500, 10, 100)),
            Decision::Changed { .. }
        ));
        assert_eq!(b.bias, 2.0);
        assert_eq!(
            b.update(&sig(true, 0, 0, 30)),
            Decision::Stop(Stop::Complete)
        );
        // Complete: half a level finer fits, and so does the next half.
        assert_eq!(b.try_finer(), Some((2.0, 1.5)));
        assert!(b.trying_finer());
        assert_eq!(b.update(&sig(false, 20, 0, 40)), Decision::Continue);
        assert_eq!(
            b.update(&sig(true, 0, 0, 60)),
            Decision::Stop(Stop::Complete)
        );
        assert!(!b.trying_finer());
        assert_eq!(b.try_finer(), Some((1.5, 1.0)));
        // 1.0 does not: back to 1.5, where the render was complete, and
        // 1.0 is not tried again for this view.
        assert_eq!(
            b.update(&sig(false, 30, 4, 100)),
            Decision::Revert { from: 1.0, to: 1.5 }
        );
        assert_eq!((b.bias, b.trying_finer()), (1.5, false));
        assert_eq!(b.try_finer(), None);
        // The next view may try it again.
        b.view_changed();
        assert_eq!(b.try_finer(), Some((1.5, 1.0)));
        // A stall, or only failed bricks left, also ends the try.
        let stuck = FrameSignals {
            progress: false,
            ..sig(false, 5, 0, 50)
        };
        let mut d = Decision::Continue;
        for _ in 0..STALL_FRAMES {
            d = b.update(&stuck);
        }
        assert_eq!(d, Decision::Revert { from: 1.0, to: 1.5 });
        b.view_changed();
        assert_eq!(b.try_finer(), Some((1.5, 1.0)));
        let failed = FrameSignals {
            progress: false,
            ..sig(false, 0, 0, 50)
        };
        assert_eq!(b.update(&failed), Decision::Revert { from: 1.0, to: 1.5 });
        // Out of frames while trying: the caller abandons the try.
        b.view_changed();
        assert_eq!(b.try_finer(), Some((1.5, 1.0)));
        assert_eq!(
            b.abandon_try(),
            Some(Decision::Revert { from: 1.0, to: 1.5 })
        );
        assert_eq!(b.abandon_try(), None);
        // Never past the user's bias, and views never try.
        let mut b = LodBudget::new(0.5, 6, false);
        assert_eq!(b.try_finer(), None);
        b.bias = 0.75;
        assert_eq!(b.try_finer(), Some((0.75, 0.5)));
        let mut v = LodBudget::new(0.0, 6, true);
        v.bias = 2.0;
        assert_eq!(v.try_finer(), None);
        // A fixed level moves by whole levels: from 1.5 (two levels
        // coarser) to 1.0 (one), then to the level asked for.
        let mut f = LodBudget::new(0.0, 6, false);
        f.bias = 1.5;
        assert_eq!(f.apply(Lod::Fixed(1), 6), Lod::Fixed(3));
        assert_eq!(f.try_finer_level(), Some((1.5, 1.0)));
        assert_eq!(f.apply(Lod::Fixed(1), 6), Lod::Fixed(2));
        assert_eq!(
            f.update(&sig(true, 0, 0, 10)),
            Decision::Stop(Stop::Complete)
        );
        assert_eq!(f.try_finer_level(), Some((1.0, 0.0)));
        assert_eq!(f.apply(Lod::Fixed(1), 6), Lod::Fixed(1));
    }

    /// A streamed view on the device: bricks that arrived wait for a slot
    /// and are not asked for again, so its frames ask for nothing while
    /// incomplete. It ran until it was killed; it coarsens, and at the
    /// bias limit it stops.
    #[test]
    fn bricks_waiting_for_a_slot_count_as_wanted() {
        let mut b = LodBudget::new(0.0, 3, false);
        let waiting = sig(false, 0, 71, 100);
        assert!(matches!(b.update(&waiting), Decision::Changed { .. }));
        let mut frames = 1;
        let d = loop {
            frames += 1;
            if let Decision::Stop(s) = b.update(&waiting) {
                break s;
            }
            assert!(frames < 100, "no end");
        };
        assert_eq!(d, Stop::NoProgress);
        assert_eq!(b.bias, b.max);
        // Complete with bricks left waiting: done, not saturated.
        let mut b = LodBudget::new(0.0, 3, false);
        assert_eq!(
            b.update(&sig(true, 0, 5, 100)),
            Decision::Stop(Stop::Complete)
        );
    }

    #[test]
    fn the_bias_never_passes_its_limit_and_a_stalled_render_stops() {
        let mut b = LodBudget::new(0.0, 2, false);
        for _ in 0..20 {
            b.update(&sig(false, 50, 5, 100));
        }
        assert_eq!(b.bias, b.max);
        // No progress: nothing arrives, nothing pending, requests remain.
        let stuck = FrameSignals {
            progress: false,
            deferred: 0,
            ..sig(false, 50, 0, 100)
        };
        let mut d = Decision::Continue;
        for _ in 0..STALL_FRAMES {
            d = b.update(&stuck);
        }
        assert_eq!(d, Decision::Stop(Stop::NoProgress));
    }

    #[test]
    fn a_render_saturated_at_the_bias_limit_stops() {
        let mut b = LodBudget::new(0.0, 3, false);
        let full = sig(false, 28, 28, 100);
        let mut frames = 0;
        let d = loop {
            frames += 1;
            assert!(frames < 100, "no end");
            match b.update(&full) {
                Decision::Stop(why) => break why,
                _ => continue,
            }
        };
        assert_eq!(b.bias, b.max);
        assert_eq!(d, Stop::NoProgress);
        assert!(frames <= 4 + STALL_FRAMES as usize, "{frames} frames");
        // A view goes on (the user moves it).
        let mut v = LodBudget::new(0.0, 3, true);
        for _ in 0..50 {
            assert!(!matches!(v.update(&full), Decision::Stop(_)));
        }
    }

    #[test]
    fn only_failed_bricks_left_stops_a_render() {
        let mut b = LodBudget::new(0.0, 4, false);
        let s = FrameSignals {
            progress: false,
            ..sig(false, 0, 0, 10)
        };
        assert_eq!(b.update(&s), Decision::Stop(Stop::CompleteButFailed));
    }

    #[test]
    fn a_view_refines_with_hysteresis_but_never_past_the_users_bias() {
        let mut b = LodBudget::new(-0.5, 6, true);
        b.update(&sig(false, 400, 10, 100));
        let raised = b.bias;
        assert!(raised > -0.5);
        // Two roomy frames are not enough; the third refines by one step.
        assert_eq!(b.update(&sig(true, 0, 0, 20)), Decision::Continue);
        assert_eq!(b.update(&sig(true, 0, 0, 20)), Decision::Continue);
        assert_eq!(
            b.update(&sig(true, 0, 0, 20)),
            Decision::Changed {
                from: raised,
                to: raised - STEP
            }
        );
        // A working set using half the pool stays where it is.
        for _ in 0..10 {
            assert_eq!(b.update(&sig(true, 0, 0, 50)), Decision::Continue);
        }
        // Never below the user's bias.
        for _ in 0..100 {
            b.update(&sig(true, 0, 0, 1));
        }
        assert_eq!(b.bias, -0.5);
        // Views never stop.
        assert_eq!(b.update(&sig(true, 0, 0, 60)), Decision::Continue);
    }

    #[test]
    fn a_fixed_level_moves_by_whole_levels() {
        let mut b = LodBudget::new(0.0, 5, false);
        assert_eq!(b.apply(Lod::Fixed(1), 5), Lod::Fixed(1));
        b.bias = 0.5;
        assert_eq!(b.apply(Lod::Fixed(1), 5), Lod::Fixed(2));
        b.bias = 9.0;
        assert_eq!(b.apply(Lod::Fixed(1), 5), Lod::Fixed(4));
        assert_eq!(b.apply(Lod::Auto { bias: 0.0 }, 5), Lod::Auto { bias: 9.0 });
    }
}
