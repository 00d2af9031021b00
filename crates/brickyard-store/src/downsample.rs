//! Box downsampling of one slab by per-axis ratios of 1 or 2.
//!
//! Intensities: the mean of the voxels of the box that exist (edge boxes of
//! odd-sized axes hold fewer voxels), rounded as [`Sample::mean`] documents.
//! Labels: the mode of the box; ties go to the smallest value.

use brickyard_core::Sample;
use rayon::prelude::*;

/// Downsample `src` (`[h, sy, sx]`, x fastest) by `r` into `dst`
/// (`[ceil(h/rz), ceil(sy/ry), ceil(sx/rx)]`).
pub fn downsample<T: Sample>(
    src: &[T],
    sdims: [usize; 3],
    r: [u32; 3],
    labels: bool,
    dst: &mut [T],
) {
    let [h, sy, sx] = sdims;
    let (rz, ry, rx) = (r[0] as usize, r[1] as usize, r[2] as usize);
    let (dh, dy, dx) = (h.div_ceil(rz), sy.div_ceil(ry), sx.div_ceil(rx));
    assert_eq!(src.len(), h * sy * sx);
    assert_eq!(dst.len(), dh * dy * dx);
    if dst.is_empty() {
        return;
    }
    dst.par_chunks_mut(dx).enumerate().for_each(|(row, out)| {
        let oz = row / dy;
        let oy = row % dy;
        let z0 = oz * rz;
        let z1 = (z0 + rz).min(h);
        let y0 = oy * ry;
        let y1 = (y0 + ry).min(sy);
        if labels {
            let mut vals: Vec<T> = Vec::with_capacity(8);
            for (ox, o) in out.iter_mut().enumerate() {
                let x0 = ox * rx;
                let x1 = (x0 + rx).min(sx);
                vals.clear();
                for z in z0..z1 {
                    for y in y0..y1 {
                        let b = (z * sy + y) * sx;
                        vals.extend_from_slice(&src[b + x0..b + x1]);
                    }
                }
                *o = mode(&vals);
            }
        } else if rx == 2 && sx % 2 == 0 {
            // Fast path: pairs along x never straddle the edge.
            let mut acc: Vec<T::Acc> = vec![T::Acc::default(); dx];
            let n = ((z1 - z0) * (y1 - y0) * 2) as u32;
            for z in z0..z1 {
                for y in y0..y1 {
                    let b = (z * sy + y) * sx;
                    let s = &src[b..b + sx];
                    for (a, p) in acc.iter_mut().zip(s.chunks_exact(2)) {
                        *a += p[0].acc();
                        *a += p[1].acc();
                    }
                }
            }
            for (o, a) in out.iter_mut().zip(acc) {
                *o = T::mean(a, n);
            }
        } else {
            for (ox, o) in out.iter_mut().enumerate() {
                let x0 = ox * rx;
                let x1 = (x0 + rx).min(sx);
                let mut a = T::Acc::default();
                for z in z0..z1 {
                    for y in y0..y1 {
                        let b = (z * sy + y) * sx;
                        for v in &src[b + x0..b + x1] {
                            a += v.acc();
                        }
                    }
                }
                *o = T::mean(a, ((z1 - z0) * (y1 - y0) * (x1 - x0)) as u32);
            }
        }
    });
}

/// Most frequent value; ties go to the smallest value.
fn mode<T: Sample>(v: &[T]) -> T {
    let mut best = v[0];
    let mut best_n = 0;
    for (i, &a) in v.iter().enumerate() {
        // Count each distinct value once, at its first occurrence.
        if v[..i].iter().any(|&b| b.bits() == a.bits()) {
            continue;
        }
        let n = v.iter().filter(|&&b| b.bits() == a.bits()).count();
        if n > best_n || (n == best_n && a < best) {
            best = a;
            best_n = n;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Naive reference: loops over every output voxel and its box.
    fn naive(src: &[u16], d: [usize; 3], r: [usize; 3]) -> Vec<u16> {
        let o = [
            d[0].div_ceil(r[0]),
            d[1].div_ceil(r[1]),
            d[2].div_ceil(r[2]),
        ];
        let mut out = vec![];
        for z in 0..o[0] {
            for y in 0..o[1] {
                for x in 0..o[2] {
                    let (mut s, mut n) = (0u64, 0u64);
                    for k in z * r[0]..((z + 1) * r[0]).min(d[0]) {
                        for j in y * r[1]..((y + 1) * r[1]).min(d[1]) {
                            for i in x * r[2]..((x + 1) * r[2]).min(d[2]) {
                                s += src[(k * d[1] + j) * d[2] + i] as u64;
                                n += 1;
                            }
                        }
                    }
                    // round half up
                    out.push(((2 * s + n) / (2 * n)) as u16);
                }
            }
        }
        out
    }

    #[test]
    fn matches_naive_on_odd_shapes() {
        let mut seed = 12345u64;
        for d in [[5usize, 7, 9], [4, 6, 8], [1, 3, 1], [3, 1, 2], [2, 2, 2]] {
            for r in [[2usize, 2, 2], [1, 2, 2], [2, 1, 1], [1, 1, 2]] {
                let src: Vec<u16> = (0..d[0] * d[1] * d[2])
                    .map(|_| {
                        seed = seed
                            .wrapping_mul(6364136223846793005)
                            .wrapping_add(1442695040888963407);
                        (seed >> 48) as u16
                    })
                    .collect();
                let o = [
                    d[0].div_ceil(r[0]),
                    d[1].div_ceil(r[1]),
                    d[2].div_ceil(r[2]),
                ];
                let mut dst = vec![0u16; o[0] * o[1] * o[2]];
                downsample(
                    &src,
                    d,
                    [r[0] as u32, r[1] as u32, r[2] as u32],
                    false,
                    &mut dst,
                );
                assert_eq!(dst, naive(&src, d, r), "dims {d:?} ratio {r:?}");
            }
        }
    }

    #[test]
    fn mode_prefers_frequent_then_smallest() {
        assert_eq!(mode(&[3u8, 1, 3, 1, 2]), 1);
        assert_eq!(mode(&[5u8, 5, 1]), 5);
        let src = [7u32, 7, 2, 9, 9, 9, 1, 1];
        let mut dst = [0u32; 1];
        downsample(&src, [2, 2, 2], [2, 2, 2], true, &mut dst);
        assert_eq!(dst[0], 9);
    }
}
