//! Direct volume rendering on the CPU: front-to-back emission–absorption
//! along each ray, with automatic level of detail (at a level change the
//! sample there is step 0 of the new level's grid), bricks the transfer
//! function hides crossed in one landing, fixed-point runs through
//! resident bricks that cross clear cells, and the fallback to coarser
//! levels for bricks not resident: after a sample a resident stand-in
//! served, the same kind of run through the stand-in's brick at the
//! finer level's steps (crossing the stand-in's clear cells), and where
//! the stand-in is one value that hides every sample, one landing past
//! its region. A ray may start at its entry depth (`entry.rs`), past
//! clear space the walk would cross without sampling. `dvr.wgsl` is the
//! device twin (it crosses the same cells and bricks, a stand-in's clear
//! cells included, but samples from the ray parameter at each step rather
//! than along runs, and starts at the volume's face; the images are the
//! same, within the runs' rounding of positions).

use crate::cpu::FrameStats;
use crate::lanes::F4;
use crate::optics::{composite_visible, Acc};
use crate::walk::{
    jump_before, start_at_entry, step_t, trilinear, trilinear_lanes, Content, Grid, Run, Walker,
};
use brickyard_cache::vm::Requests;
use brickyard_core::camera::Ray;
use brickyard_core::Sample;

impl<'f, 'a, T: Sample> Walker<'f, 'a, T> {
    /// The pixel of `ray` in a DVR of the scene's channel. `entry`: the
    /// ray's entry depth at a level ([`crate::entry`]): when the ray
    /// starts at that level, no sample before the entry may show, and the
    /// walk starts a step or so before it.
    pub(crate) fn dvr(
        &mut self,
        (ray, entry): (&Ray, Option<(usize, f64)>),
        (req, st): (&mut Requests, &mut FrameStats),
    ) -> [f32; 4] {
        #[cfg(target_arch = "x86_64")]
        if self.f.x86_v3 {
            // SAFETY: `Frame::x86_v3` holds only where the processor has
            // every feature the copy is compiled with (`isa::x86_64_v3`).
            return unsafe {
                if self.f.scene.lanes {
                    self.dvr_v3::<true>(ray, entry, req, st)
                } else {
                    self.dvr_v3::<false>(ray, entry, req, st)
                }
            };
        }
        if self.f.scene.lanes {
            self.dvr_in::<true>(ray, entry, req, st)
        } else {
            self.dvr_in::<false>(ray, entry, req, st)
        }
    }

    /// [`dvr_at`](Self::dvr_at), baseline x86-64 (or whatever the build
    /// targets). Out of line, one function per path: with both inlined
    /// into `dvr` the frame took 7 % more instructions (callgrind,
    /// BENCHMARKS.md).
    #[inline(never)]
    fn dvr_in<const LANES: bool>(
        &mut self,
        ray: &Ray,
        entry: Option<(usize, f64)>,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> [f32; 4] {
        self.dvr_at::<LANES>(ray, entry, req, st)
    }

    /// [`dvr_at`](Self::dvr_at) compiled for x86-64-v3 ([`crate::isa`]):
    /// the same source, the same bits.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(
        enable = "avx,avx2,bmi1,bmi2,f16c,fma,lzcnt,movbe,popcnt,sse3,ssse3,sse4.1,sse4.2"
    )]
    #[inline(never)]
    unsafe fn dvr_v3<const LANES: bool>(
        &mut self,
        ray: &Ray,
        entry: Option<(usize, f64)>,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> [f32; 4] {
        self.dvr_at::<LANES>(ray, entry, req, st)
    }

    /// [`dvr`](Self::dvr) with the samples of runs through resident
    /// bricks worked in four lanes (`LANES`: [`trilinear_lanes`],
    /// [`TfTable`](crate::optics::TfTable), [`Acc`]) or by the scalar twin;
    /// the same bits either way. Inlined into each instruction set's copy.
    #[inline(always)]
    fn dvr_at<const LANES: bool>(
        &mut self,
        ray: &Ray,
        entry: Option<(usize, f64)>,
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> [f32; 4] {
        // The scalar twin's colour, or the lanes' (`LANES`).
        let mut acc = [0.0f32; 4];
        let mut lanes = Acc::new();
        // Composites a visible sample `[r, g, b, a]` into whichever is in use.
        let composite = |acc: &mut [f32; 4], lanes: &mut Acc, c: [f32; 4], exponent: f32| {
            if LANES {
                lanes.composite_visible(F4::new([c[3], c[0], c[1], c[2]]), exponent)
            } else {
                composite_visible(acc, c, exponent)
            }
        };
        let f = self.f;
        self.ray_serial += 1;
        let shading = f.tf.shading;
        let d = ray.dir;
        let inv_dir = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
        // A region (sort-last): the whole ray's step grid, samples in
        // [c0, t1) only.
        let Some((t0, c0, t1)) = f.span(ray, inv_dir) else {
            return acc;
        };
        let terminate = f.params.early_termination;
        // Steps keep the reference renderer's positions while the level
        // stays the same; at a level change the sample there becomes step 0
        // of the new level's grid.
        let mut level = f.level_at(t0);
        let mut next_t = f.next_level_t(level);
        // Nothing before the entry shows at this level: start there (as a
        // region would), or not at all when the ray ends first.
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
            if t < c0 {
                // Before the region: another rank's samples, jumped over
                // (a region far along the rays costs no walk).
                k = jump_before(k, c0, next_t, base_t, inv_dt);
                continue;
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
                let j = k - 1;
                // Every step of the run inside the clamp's bounds (most
                // runs; rounding may put a face step just outside): no
                // clamps per step.
                let interior = run.interior(end.saturating_sub(j));
                let r = RunSteps {
                    steps: (j, end),
                    vox,
                    clear,
                    exponent,
                    terminate,
                    at: (base_t, dt, level),
                    ray,
                };
                let io = (&mut acc, &mut lanes);
                let (done, n, passed, _) = match (&shading, interior) {
                    (None, true) => self.run_steps::<LANES, false, true>(&mut run, &r, io, req, st),
                    (None, false) => {
                        self.run_steps::<LANES, false, false>(&mut run, &r, io, req, st)
                    }
                    (Some(_), _) => self.run_steps::<LANES, true, false>(&mut run, &r, io, req, st),
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
            let hidden = match f.tf_eval.lookup_visible(v) {
                Some(mut c) => {
                    if let Some(sh) = &shading {
                        c = self.shade(sh, c, (level, w, d), req, st);
                    }
                    if composite(&mut acc, &mut lanes, c, exponent) && terminate {
                        break;
                    }
                    false
                }
                None => true,
            };
            let g = Grid { base_t, dt, inv_dt };
            let lim = (t1.min(next_t), t1);
            // Served by a resident stand-in: the next steps that the same
            // stand-in brick serves, taken there without the lookups by a
            // fixed-point run at this level's step, as through a resident
            // brick (the same kernel, lanes and exact crossing of clear
            // cells; positions within `Run`'s rounding of `value`'s). Not
            // with shading: gradients look up bricks around each sample,
            // and the bricks a run relies on may change under it.
            let run = match shading {
                None => self.stand_in_run(level, ray, inv_dir, (g, k), lim),
                Some(_) => None,
            };
            let Some((lv, vox, lo, end)) = run else {
                // Hidden: a stand-in may hide the samples after it too.
                if hidden {
                    if let Some(kn) =
                        self.skip_hidden_stand_in(level, ray, inv_dir, w, (g, k), lim, st)
                    {
                        k = kn;
                    }
                }
                continue;
            };
            let (hi, clear) = (self.cache[lv].hi, self.cache[lv].clear_cells);
            let track_lv = self.track_of(lv, ray, inv_dir, t1);
            let mut run = Run::new(f, lv, &track_lv, ray.at(step_t(base_t, k, dt)), lo, hi);
            run.dq = track_lv.dq_at(dt);
            let interior = run.interior(end - k);
            let r = RunSteps {
                steps: (k, end),
                vox,
                clear,
                exponent,
                terminate,
                at: (base_t, dt, level),
                ray,
            };
            let io = (&mut acc, &mut lanes);
            let (done, n, passed, stop) = if interior {
                self.run_steps::<LANES, false, true>(&mut run, &r, io, req, st)
            } else {
                self.run_steps::<LANES, false, false>(&mut run, &r, io, req, st)
            };
            // Each step walked a miss of the brick of `level`; each taken
            // a sample served by the stand-in, as `value` counts them.
            st.samples += n;
            st.skipped_cells += passed;
            st.steps += stop - k;
            let c = &mut self.cache[level];
            c.missed = c.missed.saturating_add((stop - k) as u32);
            if done {
                break;
            }
            k = end;
        }
        if LANES {
            lanes.rgba()
        } else {
            acc
        }
    }

    /// The steps of a run through a resident brick (`r`), from the run's
    /// current step: clear cells crossed, the others sampled, shaded
    /// (`SHADE`) and composited into `acc` or `lanes` (`LANES`). Returns
    /// whether the ray ended (early termination), the samples taken, the
    /// cells crossed and the step it stopped before. `INTERIOR`: every step lies within the clamp's
    /// bounds ([`Run::interior`]). Apart from shading, nothing in the
    /// loop writes through a reference (transparent samples are counted
    /// here, added to `st` at the end), so the frame's tables stay in
    /// registers or are loaded once rather than reloaded every step; and
    /// each variant is a loop of its own.
    #[inline(always)]
    fn run_steps<const LANES: bool, const SHADE: bool, const INTERIOR: bool>(
        &mut self,
        run: &mut Run,
        r: &RunSteps<'a, '_, T>,
        (acc, lanes): (&mut [f32; 4], &mut Acc),
        req: &mut Requests,
        st: &mut FrameStats,
    ) -> (bool, u64, u64, u64) {
        let (f, ray) = (self.f, r.ray);
        let (mut j, end) = r.steps;
        let (vox, clear, exponent) = (r.vox, r.clear, r.exponent);
        let (base_t, dt, level) = r.at;
        let [sz, sy] = f.stride;
        // The brick's voxels from its first voxel past the apron: a step's
        // index is then its base's offset alone (`local_index` less the
        // apron's part, the same index into `vox`).
        let vox = &vox[f.local_index([0; 3], [0; 3])..];
        let (mut n, mut passed, mut transparent) = (0u64, 0u64, 0u64);
        let done = loop {
            if j >= end {
                break false;
            }
            let (u, fr) = if INTERIOR {
                run.current_unclamped()
            } else {
                run.current()
            };
            let cell = f.cell_in_run(u);
            if clear >> cell & 1 != 0 {
                // A cell whose samples are all transparent: on to the step
                // where the ray leaves it.
                passed += 1;
                j = run.cross_cell(f, u, (j, end));
                continue;
            }
            run.advance(1);
            j += 1;
            n += 1;
            let i = u[0] as usize * sz + u[1] as usize * sy + u[2] as usize;
            if LANES {
                let v = trilinear_lanes(vox, i, sz, sy, fr);
                if let Some(mut c) = f
                    .tf_table
                    .lookup_visible(&f.tf_eval, v, T::DTYPE.is_float())
                {
                    if SHADE {
                        if let Some(sh) = &f.tf.shading {
                            let w = ray.at(step_t(base_t, j - 1, dt));
                            let [a, r, g, b] = c.to_array();
                            let [r, g, b, a] =
                                self.shade(sh, [r, g, b, a], (level, w, ray.dir), req, st);
                            c = F4::new([a, r, g, b]);
                        }
                    }
                    if lanes.composite_visible(c, exponent) && r.terminate {
                        break true;
                    }
                } else {
                    transparent += 1;
                }
                continue;
            }
            let v = trilinear(vox, i, sz, sy, fr);
            if let Some(mut c) = f.tf_eval.lookup_visible(v) {
                if SHADE {
                    if let Some(sh) = &f.tf.shading {
                        let w = ray.at(step_t(base_t, j - 1, dt));
                        c = self.shade(sh, c, (level, w, ray.dir), req, st);
                    }
                }
                if composite_visible(acc, c, exponent) && r.terminate {
                    break true;
                }
            } else {
                transparent += 1;
            }
        };
        st.transparent += transparent;
        (done, n, passed, j)
    }
}

/// What a run through a resident brick needs besides the walker and the
/// ray: its steps `j .. end`, the brick's voxels and clear cells, the
/// level's opacity exponent, whether rays end early, the step grid
/// (`base_t`, `dt`) and level, and the ray (for shading).
pub(crate) struct RunSteps<'a, 'r, T> {
    pub(crate) steps: (u64, u64),
    pub(crate) vox: &'a [T],
    pub(crate) clear: u64,
    pub(crate) exponent: f32,
    pub(crate) terminate: bool,
    pub(crate) at: (f64, f64, usize),
    pub(crate) ray: &'r Ray,
}
