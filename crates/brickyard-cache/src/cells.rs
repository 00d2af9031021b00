//! Value ranges of the cells of a resident brick, for empty-space skipping
//! finer than a brick.
//!
//! Each brick is cut into [`CELLS`]³ cells of [`cell_edge`] voxels per axis.
//! Cell `c` holds the trilinear samples whose base voxel (the lower corner
//! of the 2×2×2 neighbourhood, in the brick's own coordinates without the
//! apron) `u` has `u / edge == c` on every axis; its range covers every
//! voxel such a sample reads, so every sample of the cell lies inside it.
//! A renderer crosses a cell whose range the transfer function maps to zero
//! opacity without sampling it, which gives the same image as sampling it.
//!
//! The ranges are computed from the voxels when a brick is written into the
//! pool (about one read of the padded brick), and are kept per pool slot.

use brickyard_core::{Dims3, Sample};

/// Cells per brick axis.
pub const CELLS: usize = 4;
/// Cells per brick.
pub const CELL_COUNT: usize = CELLS * CELLS * CELLS;

/// Voxels per cell edge for bricks of `brick` voxels per axis.
pub fn cell_edge(brick: Dims3) -> Dims3 {
    brick.map(|b| b.div_ceil(CELLS as u64).max(1))
}

/// Index of the cell holding base voxel `u` (brick coordinates, apron
/// excluded, `u < brick`), `[z][y][x]` order.
#[inline(always)]
pub fn cell_index(u: Dims3, edge: Dims3) -> usize {
    (((u[0] / edge[0]) as usize * CELLS) + (u[1] / edge[1]) as usize) * CELLS
        + (u[2] / edge[2]) as usize
}

/// The value ranges of the [`CELL_COUNT`] cells of a padded brick `vox`
/// (`padded` voxels per axis, `[z, y, x]`, x fastest; `brick` voxels per
/// axis inside an apron of `apron`), written to `out`.
///
/// NaN voxels are left out: a sample that gives one a weight is NaN, which
/// every renderer treats as transparent, and one that does not lies within
/// the other voxels' range. A cell with no other value gets `[NaN, NaN]`
/// ("unknown": never skipped). Bounds are widened by 2⁻²⁰ of their
/// magnitude so that the rounding of the interpolation (a few ulps) stays
/// inside.
pub fn cell_ranges<T: Sample>(
    vox: &[T],
    padded: [usize; 3],
    brick: Dims3,
    apron: u64,
    out: &mut [[f32; 2]],
) {
    assert_eq!(out.len(), CELL_COUNT, "one range per cell");
    assert_eq!(vox.len(), padded.iter().product::<usize>(), "padded brick");
    let edge = cell_edge(brick);
    // Per axis and cell: the inclusive padded index range a cell's samples
    // read (empty when the cell lies past the brick).
    let span = |a: usize, c: usize| -> (usize, usize) {
        let e = edge[a] as usize;
        let lo = c * e + apron as usize;
        let hi = ((c + 1) * e).min(brick[a] as usize) + apron as usize;
        (lo, hi.min(padded[a] - 1))
    };
    let [pz, py, px] = padded;
    // Row minima and maxima per x-cell: rows[(z·py + y)·CELLS + cx].
    let mut rows = vec![[f32::INFINITY, f32::NEG_INFINITY]; pz * py * CELLS];
    for z in 0..pz {
        for y in 0..py {
            let row = &vox[(z * py + y) * px..(z * py + y + 1) * px];
            for cx in 0..CELLS {
                let (x0, x1) = span(2, cx);
                if x0 > x1 {
                    continue;
                }
                let (mut mn, mut mx) = (f32::INFINITY, f32::NEG_INFINITY);
                for v in &row[x0..=x1] {
                    let v = v.to_f32();
                    // NaN compares false both ways: left out.
                    if v < mn {
                        mn = v;
                    }
                    if v > mx {
                        mx = v;
                    }
                }
                rows[(z * py + y) * CELLS + cx] = [mn, mx];
            }
        }
    }
    for cz in 0..CELLS {
        let (z0, z1) = span(0, cz);
        for cy in 0..CELLS {
            let (y0, y1) = span(1, cy);
            for cx in 0..CELLS {
                let (mut mn, mut mx) = (f32::INFINITY, f32::NEG_INFINITY);
                if z0 <= z1 && y0 <= y1 {
                    for z in z0..=z1 {
                        for y in y0..=y1 {
                            let [a, b] = rows[(z * py + y) * CELLS + cx];
                            mn = mn.min(a);
                            mx = mx.max(b);
                        }
                    }
                }
                out[(cz * CELLS + cy) * CELLS + cx] = if mn > mx {
                    [f32::NAN; 2]
                } else {
                    let m = mn.abs().max(mx.abs()) * (1.0 / (1u32 << 20) as f32);
                    [mn - m, mx + m]
                };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::trilinear;

    /// Every trilinear sample whose base voxel lies in a cell is inside
    /// that cell's range (random data, several brick shapes and aprons).
    #[test]
    fn samples_stay_inside_their_cell() {
        let mut seed = 0x1234_5678_9abc_def0u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as u32
        };
        for (brick, apron) in [([8, 8, 8], 1), ([10, 6, 5], 1), ([4, 4, 4], 2)] {
            let padded = brick.map(|b: u64| (b + 2 * apron) as usize);
            let n = padded.iter().product::<usize>();
            let vox: Vec<f32> = (0..n)
                .map(|_| (rnd() % 1000) as f32 * 0.37 - 100.0)
                .collect();
            let mut out = [[0.0f32; 2]; CELL_COUNT];
            cell_ranges(&vox, padded, brick, apron, &mut out);
            let edge = cell_edge(brick);
            let at = |z: usize, y: usize, x: usize| vox[(z * padded[1] + y) * padded[2] + x];
            for _ in 0..2000 {
                let u: Dims3 = [0, 1, 2].map(|a| rnd() as u64 % brick[a]);
                let p = u.map(|x| (x + apron) as usize);
                let f = [0, 1, 2].map(|_| (rnd() % 4096) as f32 / 4096.0);
                let c = [0, 1].map(|dz| {
                    [0, 1].map(|dy| [0, 1].map(|dx| at(p[0] + dz, p[1] + dy, p[2] + dx)))
                });
                let c = [
                    c[0][0][0], c[0][0][1], c[0][1][0], c[0][1][1], c[1][0][0], c[1][0][1],
                    c[1][1][0], c[1][1][1],
                ];
                let v = trilinear(c, f, true);
                let [lo, hi] = out[cell_index(u, edge)];
                assert!(v >= lo && v <= hi, "{v} outside [{lo}, {hi}] at {u:?}");
            }
        }
    }

    #[test]
    fn ranges_are_tight_and_nan_is_left_out() {
        // A 4³ brick with apron 1 (6³ padded), edge 1: cell c reads padded
        // voxels [c + 1, c + 2] per axis.
        let padded = [6usize; 3];
        let mut vox = vec![5u8; 216];
        let idx = |z: usize, y: usize, x: usize| (z * 6 + y) * 6 + x;
        vox[idx(1, 1, 1)] = 1;
        vox[idx(5, 5, 5)] = 200;
        let mut out = [[0.0f32; 2]; CELL_COUNT];
        cell_ranges(&vox, padded, [4; 3], 1, &mut out);
        let m = |v: f32| v / (1u32 << 20) as f32;
        assert_eq!(out[0], [1.0 - m(5.0), 5.0 + m(5.0)]);
        assert_eq!(out[CELL_COUNT - 1], [5.0 - m(200.0), 200.0 + m(200.0)]);
        assert_eq!(out[1], [5.0 - m(5.0), 5.0 + m(5.0)]);

        let mut f = vec![f32::NAN; 216];
        f[idx(2, 2, 2)] = 3.0;
        cell_ranges(&f, padded, [4; 3], 1, &mut out);
        assert_eq!(out[0], [3.0 - m(3.0), 3.0 + m(3.0)]);
        assert!(out[CELL_COUNT - 1][0].is_nan(), "only NaN: unknown");
    }
}
