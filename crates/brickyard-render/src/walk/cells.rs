//! Steps through one resident brick: fixed-point runs (32 fractional bits)
//! from the brick's first step, and jumps over cells (up to 4×4×4 per
//! brick) whose samples need no evaluation, to exactly the step where the
//! ray leaves the cell.

use super::{Frame, Track};
use brickyard_core::camera::Vec3;
use brickyard_core::Dims3;

/// The steps of a ray through one resident brick, by fixed-point increments
/// (32 fractional bits) instead of from the ray parameter: voxel coordinate
/// `q = w·scale − ½` of the first step plus `beta·dt` per step, clamped to
/// the level like the general path's coordinates. The positions differ
/// from the general path's by rounding (below 1e-7 voxel for runs of up to
/// 1000 steps), and so do the samples (trilinear interpolation is
/// continuous). A step that rounding puts just outside the brick is
/// sampled on its face (base clamped, fraction 0 or 1): the same value.
#[derive(Clone)]
pub(crate) struct Run {
    /// The coordinate relative to the brick's first voxel: `q − lo·2³²`.
    pub(crate) q: [i64; 3],
    pub(crate) dq: [i64; 3],
    /// Where `q` is clamped: the volume's last voxel or the brick's last
    /// voxel with fraction 1, whichever comes first (below, the clamp is
    /// 0: the brick's first voxel with fraction 0, which the volume's
    /// first voxel is not above).
    pub(crate) qhi: [i64; 3],
    /// Voxels of the brick per axis, minus one.
    pub(crate) last: [i64; 3],
}

pub(crate) const FIX: f64 = (1u64 << 32) as f64;

/// The fraction bits of a fixed-point coordinate.
pub(crate) const FRAC: i64 = 0xffff_ffff;

impl Run {
    #[inline(always)]
    pub(crate) fn new(f: &Frame, l: usize, track: &Track, w: Vec3, lo: Dims3, hi: Dims3) -> Run {
        let s = f.scale[l];
        let m = f.qmax_fix[l];
        let q = [
            ((w[2] * s[0] - 0.5) * FIX) as i64,
            ((w[1] * s[1] - 0.5) * FIX) as i64,
            ((w[0] * s[2] - 0.5) * FIX) as i64,
        ];
        let last = [0, 1, 2].map(|a| (hi[a] - lo[a]) as i64 - 1);
        Run {
            q: [0, 1, 2].map(|a| q[a] - ((lo[a] as i64) << 32)),
            dq: track.dq,
            // (The fraction of `FRAC` converts to exactly 1.0 in f32.)
            qhi: [0, 1, 2].map(|a| (m[a] - ((lo[a] as i64) << 32)).min((last[a] << 32) | FRAC)),
            last,
        }
    }

    /// The current step's voxel base in the brick (apron excluded) and its
    /// fractions; then advance.
    #[cfg(test)]
    pub(crate) fn next(&mut self) -> (Dims3, [f32; 3]) {
        let r = self.current();
        self.advance(1);
        r
    }

    /// At step `j` (of a run ending at `end`), whose voxel base `u` (from
    /// [`current`](Self::current)) lies in a cell whose samples need no
    /// evaluation: move to the first step whose base lies in another cell
    /// (at least one on, at most `end`) and return it. Exact: the same step
    /// stepping one by one would stop at, found per axis in integer
    /// arithmetic from where the fixed-point coordinate crosses the cell's
    /// face (the base moves monotonically along each axis, and the clamps
    /// of `current` only hold it at the brick's and the volume's faces,
    /// which no cell face beyond them is).
    #[inline(always)]
    pub(crate) fn cross_cell(&mut self, f: &Frame, u: Dims3, (j, end): (u64, u64)) -> u64 {
        let mut m = u64::MAX;
        for (a, &ua) in u.iter().enumerate() {
            let (dq, e) = (self.dq[a], f.cells.edge[a] as i64);
            let c = f.cell_coord(a, ua) as i64;
            // Forwards, the base leaves when it reaches the next cell's
            // first voxel `h` (none past the brick's last voxel): after
            // ⌈(h·2³² − q) / dq⌉ steps. Backwards, when it drops below the
            // cell's first voxel `l` (none below the brick's first): after
            // ⌊(q − l·2³²) / −dq⌋ + 1 = ⌈(q − l·2³² + 1) / −dq⌉ steps.
            let fwd = dq > 0;
            let face = if fwd { (c + 1) * e } else { c * e };
            let exists = if fwd {
                face <= self.last[a]
            } else {
                face > 0 && dq < 0
            };
            let d = if fwd {
                (face << 32) - self.q[a]
            } else {
                self.q[a] - (face << 32) + 1
            };
            if exists {
                debug_assert!(d > 0);
                m = m.min(div_ceil_exact(d, dq.abs()));
            }
        }
        let jn = j.saturating_add(m).clamp(j + 1, end.max(j + 1));
        self.advance(jn - j);
        jn
    }

    /// Move on by `m` steps (exactly `m` single steps: integer arithmetic).
    #[inline(always)]
    pub(crate) fn advance(&mut self, m: u64) {
        for a in 0..3 {
            self.q[a] += self.dq[a] * m as i64;
        }
    }

    /// Whether the next `steps` steps (from the current one) all lie within
    /// the clamp's bounds, so that [`current_unclamped`](Self::current_unclamped)
    /// gives what [`current`](Self::current) does for each (the coordinate
    /// moves monotonically along each axis: its ends decide).
    #[inline(always)]
    pub(crate) fn interior(&self, steps: u64) -> bool {
        let n = steps.saturating_sub(1).min(1 << 20) as i64;
        (0..3).all(|a| {
            let (q0, q1) = (self.q[a], self.q[a] + self.dq[a] * n);
            q0 >= 0 && q0 <= self.qhi[a] && q1 >= 0 && q1 <= self.qhi[a]
        })
    }

    /// [`current`](Self::current) for a step known to lie within the
    /// clamp's bounds ([`interior`](Self::interior)).
    #[inline(always)]
    pub(crate) fn current_unclamped(&self) -> (Dims3, [f32; 3]) {
        let mut u = [0u64; 3];
        let mut fr = [0f32; 3];
        for a in 0..3 {
            let q = self.q[a];
            u[a] = (q >> 32) as u64;
            fr[a] = (q & FRAC) as f32 * (1.0 / FIX as f32);
        }
        (u, fr)
    }

    /// The current step's voxel base in the brick (apron excluded) and its
    /// fractions.
    #[inline(always)]
    pub(crate) fn current(&self) -> (Dims3, [f32; 3]) {
        let mut u = [0u64; 3];
        let mut fr = [0f32; 3];
        for a in 0..3 {
            // (`max`/`min`: `clamp` checks its bounds every time.)
            let q = self.q[a].max(0).min(self.qhi[a]);
            u[a] = (q >> 32) as u64;
            fr[a] = (q & FRAC) as f32 * (1.0 / FIX as f32);
        }
        (u, fr)
    }
}

impl Frame<'_> {
    /// The cell of base voxel `u` of a brick (brick coordinates, apron
    /// excluded): [`brickyard_cache::cells::CellGrid::index`] by table.
    #[inline(always)]
    pub(crate) fn cell_of(&self, u: Dims3) -> usize {
        let [z, y, x] = &self.cell_part;
        (z[u[0] as usize] + y[u[1] as usize] + x[u[2] as usize]) as usize
    }

    /// [`cell_of`](Self::cell_of) for a voxel base from a [`Run`]'s
    /// [`current`](Run::current) or, for an interior run,
    /// [`current_unclamped`](Run::current_unclamped), without bounds checks
    /// (the hot loop of DVR and MIP runs).
    #[inline(always)]
    pub(crate) fn cell_in_run(&self, u: Dims3) -> usize {
        let [z, y, x] = &self.cell_part;
        let u = u.map(|v| v as usize);
        debug_assert!(u[0] < z.len() && u[1] < y.len() && u[2] < x.len());
        // SAFETY: a run's voxel base lies in its brick (apron excluded):
        // `current` clamps it to the brick's last voxel, and an interior
        // run's steps lie within that clamp; the tables have an entry per
        // voxel of a brick along their axis.
        unsafe {
            (*z.get_unchecked(u[0]) + *y.get_unchecked(u[1]) + *x.get_unchecked(u[2])) as usize
        }
    }

    /// The cell coordinate along axis `a` of brick coordinate `x`.
    #[inline(always)]
    pub(crate) fn cell_coord(&self, a: usize, x: u64) -> u64 {
        match self.cell_shift {
            Some(s) => x >> s[a],
            None => x / self.cells.edge[a],
        }
    }

    /// The voxel box `[lo, hi)` of cell `cell` of the brick `[blo, bhi)`.
    pub(crate) fn cell_box(&self, cell: usize, blo: Dims3, bhi: Dims3) -> (Dims3, Dims3) {
        let c = self.cells.coords(cell);
        let e = self.cells.edge;
        let lo = [0, 1, 2].map(|a| blo[a] + c[a] * e[a]);
        let hi = [0, 1, 2].map(|a| (lo[a] + e[a]).min(bhi[a]));
        (lo, hi)
    }
}

/// `⌈n / d⌉` for `0 ≤ n, 0 < d < 2⁵³` through a float division (fewer
/// instructions than an integer one), exact: both convert exactly, the
/// quotient is correctly rounded, and a quotient `k + r/d` that is not a
/// whole number lies at least `1/d` from one, more than half an ulp of it.
#[inline(always)]
pub(crate) fn div_ceil_exact(n: i64, d: i64) -> u64 {
    debug_assert!(n >= 0 && d > 0 && n < 1 << 53 && d < 1 << 53);
    let q = n as f64 / d as f64;
    // (Not `ceil`, which is a library call without SSE4.1.)
    let t = q as i64;
    (t + ((t as f64) < q) as i64) as u64
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;
    use super::*;
    use brickyard_core::camera::Ray;

    /// From step `j` of `run`, stepping one by one: the first step (at most
    /// `end`) whose voxel base lies in another cell, and the run there.
    fn step_out_of_cell(f: &Frame, run: &Run, (j, end): (u64, u64)) -> (u64, Run) {
        let cell = f.cell_of(run.current().0);
        let mut step = run.clone();
        let mut k = j;
        while k < end {
            step.advance(1);
            k += 1;
            if f.cell_of(step.current().0) != cell {
                break;
            }
        }
        (k, step)
    }

    /// `Run::current` (one clamp of the brick-relative coordinate) equals
    /// clamping to the volume first and then to the brick (base to the
    /// brick's first or last voxel, fraction 0 or 1), near every face.
    #[test]
    fn current_equals_clamping_to_volume_then_brick() {
        let dims = [70u64, 61, 77];
        let brick = [32u64, 32, 16];
        let (vm, scene, params) = fixture(dims, brick, [1.1, 0.8, 1.4]);
        let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let mut rnd = uniform(5);
        let track = f.track(
            0,
            &Ray {
                origin: [0.0; 3],
                dir: [0.6, 0.0, 0.8],
            },
            [1.0 / 0.6, f64::INFINITY, 1.25],
            10.0,
        );
        for b in [[0u64, 0, 0], [2, 1, 4], [1, 1, 2]] {
            let lo = [0, 1, 2].map(|a| b[a] * brick[a]);
            let hi = [0, 1, 2].map(|a| (lo[a] + brick[a]).min(dims[a]));
            let mut run = Run::new(&f, 0, &track, [0.0; 3], lo, hi);
            for _ in 0..20_000 {
                // Absolute coordinates around the brick and the volume.
                let qa = [0, 1, 2].map(|a| {
                    let v = lo[a] as f64 - 2.0 + (hi[a] - lo[a] + 4) as f64 * rnd();
                    let x = (v * FIX) as i64;
                    match (rnd() * 4.0) as u32 {
                        0 => x & !FRAC,
                        1 => x | FRAC,
                        _ => x,
                    }
                });
                run.q = [0, 1, 2].map(|a| qa[a] - ((lo[a] as i64) << 32));
                let want: (Dims3, [f32; 3]) = {
                    let mut u = [0u64; 3];
                    let mut fr = [0f32; 3];
                    for a in 0..3 {
                        let qmax = (f.qmax[0][a] * FIX) as i64;
                        let q = qa[a].clamp(0, qmax);
                        let bb = (q >> 32) - lo[a] as i64;
                        let last = (hi[a] - lo[a]) as i64 - 1;
                        (u[a], fr[a]) = if bb < 0 {
                            (0, 0.0)
                        } else if bb > last {
                            (last as u64, 1.0)
                        } else {
                            (bb as u64, (q & FRAC) as f32 / FIX as f32)
                        };
                    }
                    (u, fr)
                };
                assert_eq!(run.current(), want, "brick {b:?} q {qa:?}");
            }
        }
    }

    /// Where `Run::interior` says a run's steps lie within the clamp's
    /// bounds, `current_unclamped` equals `current` at every one of them;
    /// runs that start or end just outside a face are not interior.
    #[test]
    fn interior_runs_need_no_clamp() {
        let mut rnd = uniform(41);
        let (mut interior, mut outside) = (0, 0);
        for _ in 0..20_000 {
            let last = [31i64, 31, 15];
            let qhi = last.map(|l| (l << 32) | FRAC);
            let steps = 1 + (rnd() * 60.0) as u64;
            let mut run = Run {
                q: [0, 1, 2].map(|a| ((rnd() * 1.1 - 0.05) * (qhi[a] as f64)) as i64),
                dq: [0; 3].map(|_| ((rnd() - 0.5) * 0.6 * FIX) as i64),
                qhi,
                last,
            };
            if !run.interior(steps) {
                outside += 1;
                continue;
            }
            interior += 1;
            for _ in 0..steps {
                assert_eq!(run.current_unclamped(), run.current(), "{:?}", run.q);
                run.advance(1);
            }
        }
        assert!(
            interior > 5_000 && outside > 5_000,
            "{interior} / {outside}"
        );
    }

    /// `Run::cross_cell` against stepping where the fixed-point coordinate
    /// lands exactly on a cell face after a whole number of steps (which
    /// random rays almost never do).
    #[test]
    fn crossing_onto_a_face_equals_stepping() {
        let dims = [70u64, 61, 77];
        let brick = [64u64, 64, 32];
        let (vm, scene, params) = fixture(dims, brick, [1.1, 0.8, 1.4]);
        let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
        let mut rnd = uniform(23);
        let (lo, hi) = ([0u64; 3], [64u64, 61, 32]);
        let last = [0, 1, 2].map(|a| (hi[a] - lo[a]) as i64 - 1);
        let mut on_plane = 0;
        for _ in 0..20_000 {
            let steps = 1 + (rnd() * 12.0) as i64;
            let mut run = Run {
                q: [0; 3],
                dq: [0; 3],
                qhi: [0, 1, 2].map(|a| (last[a] << 32) | FRAC),
                last,
            };
            for (a, &la) in last.iter().enumerate() {
                let e = f.cells.edge[a] as i64;
                let faces = (la + e) / e;
                let face = e * (1 + (rnd() * (faces - 1).max(1) as f64) as i64).min(faces - 1);
                let dq =
                    ((1i64 << 32) as f64 * (0.05 + rnd())) as i64 * [1, -1][(rnd() * 2.0) as usize];
                // `steps` steps from exactly on the face (or a random start).
                let q = if rnd() < 0.7 {
                    (face << 32) - steps * dq
                } else {
                    (rnd() * (la << 32) as f64) as i64
                };
                run.q[a] = q.clamp(0, la << 32);
                run.dq[a] = dq;
            }
            let end = 200;
            let (u, _) = run.current();
            let (want, _) = step_out_of_cell(&f, &run, (0, end));
            let mut jump = run.clone();
            assert_eq!(
                jump.cross_cell(&f, u, (0, end)),
                want,
                "{:?} {:?}",
                run.q,
                run.dq
            );
            // The case this test is for: the jump ends exactly on a voxel
            // plane.
            on_plane += jump.q.iter().any(|&q| q & FRAC == 0) as u32;
        }
        assert!(on_plane > 5_000, "{on_plane} jumps onto a voxel plane");
    }

    /// The float division of `Run::cross_cell` equals the integer one, for
    /// whole quotients, their neighbours and random ones.
    #[test]
    fn float_division_is_exact() {
        let mut rnd = uniform(17);
        for i in 0..200_000u64 {
            let d = match i % 4 {
                0 => 1 + (rnd() * 16.0) as i64,
                1 => 1 + (rnd() * (1u64 << 34) as f64) as i64,
                2 => (1i64 << 32) + (rnd() * 1000.0) as i64 - 500,
                _ => 1 + (rnd() * (1u64 << 52) as f64) as i64,
            };
            let k = (rnd() * 2000.0) as i64;
            let n = match i % 3 {
                0 => k * d,
                1 => (k * d + (rnd() * 3.0) as i64 - 1).max(0),
                _ => (rnd() * (1u64 << 44) as f64) as i64,
            }
            .min((1i64 << 53) - 1);
            assert_eq!(div_ceil_exact(n, d), ((n + d - 1) / d) as u64, "{n} / {d}");
        }
    }

    /// `Run::cross_cell` lands exactly where stepping one by one leaves
    /// the cell (or at the run's end), for power-of-two cells and others,
    /// on random rays including ones parallel to voxel planes.
    #[test]
    fn crossing_a_cell_equals_stepping_out_of_it() {
        for brick in [[32u64, 32, 16], [24, 20, 32]] {
            let dims = [70u64, 61, 77];
            let extent = [1.1, 0.8, 1.4];
            let (vm, scene, params) = fixture(dims, brick, extent);
            let f = Frame::new(&vm, &scene, &params, Lod::Fixed(0));
            assert!(f.cells.len() > 4, "{:?}", f.cells);
            let mut rnd = uniform(0x51ed_2701_f00d_cafe);
            let (mut crossings, mut multi) = (0, 0);
            for trial in 0..3000 {
                let target = [0, 1, 2].map(|a| rnd() * extent[a]);
                let mut dir = [0, 1, 2].map(|_| rnd() - 0.5);
                match trial % 4 {
                    0 => dir[trial % 3] = 0.0,
                    1 => dir[trial % 3] = 1e-12 * (rnd() - 0.5),
                    _ => {}
                }
                let dt = f.voxel[0] * (0.2 + 1.5 * rnd());
                let Some((ray, (t0, t1), g, track, k0)) =
                    random_step(&f, extent, (target, dir, 3.0), dt, rnd())
                else {
                    continue;
                };
                let w = ray.at(step_t(t0, k0 - 1, dt));
                let (v, _) = f.coords(0, w);
                let b = f.brick_of(v);
                let lo = [0, 1, 2].map(|a| b[a] * brick[a]);
                let hi = [0, 1, 2].map(|a| (lo[a] + brick[a]).min(dims[a]));
                let end = track.run_end(g, (lo, hi), t1).max(k0);
                let mut run = Run::new(&f, 0, &track, w, lo, hi);
                let mut j = k0 - 1;
                while j < end {
                    let (u, _) = run.current();
                    let (want, step) = step_out_of_cell(&f, &run, (j, end));
                    let mut jump = run.clone();
                    let got = jump.cross_cell(&f, u, (j, end));
                    assert_eq!(got, want, "brick {brick:?} trial {trial} from step {j}");
                    assert_eq!(jump.q, step.q, "brick {brick:?} trial {trial}");
                    crossings += 1;
                    multi += (got > j + 1) as u32;
                    run.advance(1);
                    j += 1;
                }
            }
            assert!(
                crossings > 20_000 && multi > 5_000,
                "{crossings} crossings, {multi} long"
            );
        }
    }
}
