//! In-core kernels on dense blocks (C order, `[z, y, x]`, x fastest).
//!
//! The filters are separable correlations, computed as in `scipy.ndimage`:
//! one 1D pass per axis, every pass in f64. A block arrives padded by the
//! halo of each axis (the caller fills the halo with the boundary mode), and
//! each pass shrinks its axis by the kernel's two radii ("valid" part only).
//!
//! The float kernels are generic over [`Real`]: in f64 they are the CPU
//! filters; in f32 they are the CPU twins of the device kernels of the same
//! names (`shaders/filter.wgsl`, see [`crate::gpu`]), which run the same
//! operations in the same order.

use std::ops::{Add, AddAssign, Mul, Neg, Sub};

/// The arithmetic of the float kernels: f64 (the CPU filters) or f32 (the
/// twins of the device kernels). Rust never contracts `a + w·b` into a
/// fused multiply-add, so each product and each sum is rounded once.
pub trait Real:
    Copy
    + Default
    + PartialEq
    + Send
    + Sync
    + Add<Output = Self>
    + Sub<Output = Self>
    + Neg<Output = Self>
    + Mul<Output = Self>
    + AddAssign
    + 'static
{
    /// Whether `correlate_valid` pairs symmetric taps (the CPU filter,
    /// f64); the f32 twin of the device kernel sums tap by tap as the
    /// device does.
    const PAIR_TAPS: bool;
    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
    fn sqrt(self) -> Self;
}

impl Real for f64 {
    const PAIR_TAPS: bool = true;
    #[inline]
    fn from_f64(v: f64) -> f64 {
        v
    }
    #[inline]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline]
    fn sqrt(self) -> f64 {
        f64::sqrt(self)
    }
}

impl Real for f32 {
    const PAIR_TAPS: bool = false;
    #[inline]
    fn from_f64(v: f64) -> f32 {
        v as f32
    }
    #[inline]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline]
    fn sqrt(self) -> f32 {
        f32::sqrt(self)
    }
}

/// The weights of scipy's `_gaussian_kernel1d(sigma, order, radius)` with
/// `radius = int(truncate * sigma + 0.5)`, as correlation weights: the
/// result at `i` is `Σ_k w[k] · in[i + k − radius]`. Order 0 is the
/// normalised Gaussian; order 1 its derivative, `w(x) = x/σ² · φ(x)`
/// (scipy's convolution kernel `−x/σ² · φ(x)`, mirrored for correlation).
pub fn gaussian_weights(sigma: f64, order: u32, truncate: f64) -> Vec<f64> {
    assert!(order <= 1, "only orders 0 and 1");
    let radius = (truncate * sigma + 0.5) as i64;
    let s2 = sigma * sigma;
    let phi: Vec<f64> = (-radius..=radius)
        .map(|x| (-0.5 / s2 * (x * x) as f64).exp())
        .collect();
    let sum: f64 = phi.iter().sum();
    (-radius..=radius)
        .zip(phi)
        .map(|(x, p)| {
            let p = p / sum;
            if order == 0 {
                p
            } else {
                x as f64 / s2 * p
            }
        })
        .collect()
}

/// Radius of a weight vector of odd length.
pub fn radius<R>(w: &[R]) -> usize {
    debug_assert!(w.len() % 2 == 1);
    w.len() / 2
}

/// Correlate `data` (`dims`) along `axis` with `w`, keeping the valid part:
/// the result has `dims[axis] − 2·radius(w)` along that axis. Each result is
/// `Σ_k w[k] · in[i + k]`, summed from 0 in increasing `k`.
pub fn correlate_valid<R: Real>(
    data: &[R],
    dims: [usize; 3],
    axis: usize,
    w: &[R],
) -> (Vec<R>, [usize; 3]) {
    let r = radius(w);
    assert!(dims[axis] >= 2 * r, "block thinner than the kernel");
    let mut od = dims;
    od[axis] -= 2 * r;
    let [nz, ny, nx] = od;
    let mut out = vec![R::default(); nz * ny * nx];
    // Input strides.
    let sy = dims[2];
    let sz = dims[1] * dims[2];
    let step = [sz, sy, 1][axis];
    // Gaussians are symmetric and their derivatives antisymmetric: pair
    // the taps `r − k` and `r + k` (one multiplication for two), centre
    // tap first, then the pairs outwards.
    let sym = R::PAIR_TAPS && (0..r).all(|k| w[k] == w[2 * r - k]);
    let anti =
        R::PAIR_TAPS && !sym && w[r] == R::default() && (0..r).all(|k| w[k] == -w[2 * r - k]);
    for z in 0..nz {
        for y in 0..ny {
            let o = (z * ny + y) * nx;
            let orow = &mut out[o..o + nx];
            let base = z * sz + y * sy;
            if sym || anti {
                let c = &data[base + r * step..][..nx];
                for (a, &b) in orow.iter_mut().zip(c) {
                    *a = w[r] * b;
                }
                for k in 1..=r {
                    let lo = &data[base + (r - k) * step..][..nx];
                    let hi = &data[base + (r + k) * step..][..nx];
                    let wk = w[r + k];
                    if sym {
                        for ((a, &l), &h) in orow.iter_mut().zip(lo).zip(hi) {
                            *a += wk * (h + l);
                        }
                    } else {
                        for ((a, &l), &h) in orow.iter_mut().zip(lo).zip(hi) {
                            *a += wk * (h - l);
                        }
                    }
                }
                continue;
            }
            for (k, &wk) in w.iter().enumerate() {
                let s = base + k * step;
                let irow = &data[s..s + nx];
                for (a, &b) in orow.iter_mut().zip(irow) {
                    *a += wk * b;
                }
            }
        }
    }
    (out, od)
}

/// Whether `w` leaves the data as it is (the weights of a σ whose radius is
/// 0): such a pass is skipped.
pub fn is_identity<R: Real>(w: &[R]) -> bool {
    w.len() == 1 && w[0] == R::from_f64(1.0)
}

/// Apply one weight vector per axis (z, then y, then x — the order in which
/// scipy processes axes 0, 1, 2).
pub fn separable<R: Real>(data: Vec<R>, dims: [usize; 3], w: [&[R]; 3]) -> (Vec<R>, [usize; 3]) {
    let (mut d, mut dd) = (data, dims);
    for (axis, wa) in w.iter().enumerate() {
        if is_identity(wa) {
            continue;
        }
        (d, dd) = correlate_valid(&d, dd, axis, wa);
    }
    (d, dd)
}

/// `acc ← acc + v²` element by element (`acc ← v²` when `first`).
pub fn sum_squares<R: Real>(acc: &mut [R], v: &[R], first: bool) {
    assert_eq!(acc.len(), v.len());
    if first {
        for (a, &x) in acc.iter_mut().zip(v) {
            *a = x * x;
        }
    } else {
        for (a, &x) in acc.iter_mut().zip(v) {
            *a += x * x;
        }
    }
}

/// `v ← √v` element by element.
pub fn square_root<R: Real>(v: &mut [R]) {
    for x in v {
        *x = x.sqrt();
    }
}

/// `sqrt(Σ_axis (separable pass `ws[axis]`)²)`: a gradient magnitude from
/// three separable derivative filters on a block padded by the same halo.
pub fn magnitude<R: Real>(
    data: &[R],
    dims: [usize; 3],
    ws: [[&[R]; 3]; 3],
) -> (Vec<R>, [usize; 3]) {
    let mut acc: Option<(Vec<R>, [usize; 3])> = None;
    for w in ws {
        let (d, od) = separable(data.to_vec(), dims, w);
        match &mut acc {
            None => {
                let mut a = vec![R::default(); d.len()];
                sum_squares(&mut a, &d, true);
                acc = Some((a, od));
            }
            Some((a, ad)) => {
                debug_assert_eq!(*ad, od);
                sum_squares(a, &d, false);
            }
        }
    }
    let (mut a, od) = acc.unwrap();
    square_root(&mut a);
    (a, od)
}

/// 1 where `v > t`, else 0 (compared in f64, as `scipy`'s `x > t` on the
/// values).
pub fn threshold<R: Real>(v: &[R], t: f64) -> Vec<R> {
    let (one, zero) = (R::from_f64(1.0), R::default());
    v.iter()
        .map(|&x| if x.to_f64() > t { one } else { zero })
        .collect()
}

/// 1 where `lo <= v <= hi`, else 0 (compared in f64).
pub fn window<R: Real>(v: &[R], lo: f64, hi: f64) -> Vec<R> {
    let (one, zero) = (R::from_f64(1.0), R::default());
    v.iter()
        .map(|&x| {
            let x = x.to_f64();
            if lo <= x && x <= hi {
                one
            } else {
                zero
            }
        })
        .collect()
}

/// Sobel weights of `scipy.ndimage.sobel`: the derivative `[-1, 0, 1]`
/// along the axis, the smoothing `[1, 2, 1]` along the others.
pub const SOBEL_D: [f64; 3] = [-1.0, 0.0, 1.0];
pub const SOBEL_S: [f64; 3] = [1.0, 2.0, 1.0];

/// Connected components of the non-zero voxels of a dense block: local
/// labels `1..=n` in raster order (z, y, x) of each component's first
/// voxel; background 0. Returns the labels and `n`.
pub fn label_block(mask: &[bool], dims: [usize; 3], conn: u8) -> (Vec<u32>, u32) {
    let [nz, ny, nx] = dims;
    // Work in a copy padded by one background voxel on every side, so that
    // neighbours are plain index offsets without bounds checks.
    let (py, px) = (ny + 2, nx + 2);
    let plane = py * px;
    let mut lab = vec![0u32; (nz + 2) * plane];
    // u32::MAX marks foreground not yet labelled.
    for z in 0..nz {
        for y in 0..ny {
            let s = (z * ny + y) * nx;
            let d = ((z + 1) * py + y + 1) * px + 1;
            for (o, &m) in lab[d..d + nx].iter_mut().zip(&mask[s..s + nx]) {
                *o = if m { u32::MAX } else { 0 };
            }
        }
    }
    let offs: Vec<isize> = neighbour_offsets(conn)
        .iter()
        .map(|[dz, dy, dx]| {
            (*dz as isize) * plane as isize + (*dy as isize) * px as isize + *dx as isize
        })
        .collect();
    let mut n = 0u32;
    let mut stack: Vec<usize> = vec![];
    for z in 0..nz {
        for y in 0..ny {
            let row = ((z + 1) * py + y + 1) * px + 1;
            for start in row..row + nx {
                if lab[start] != u32::MAX {
                    continue;
                }
                n += 1;
                lab[start] = n;
                stack.push(start);
                while let Some(i) = stack.pop() {
                    for &o in &offs {
                        let j = (i as isize + o) as usize;
                        if lab[j] == u32::MAX {
                            lab[j] = n;
                            stack.push(j);
                        }
                    }
                }
            }
        }
    }
    let mut labels = Vec::with_capacity(mask.len());
    for z in 0..nz {
        for y in 0..ny {
            let s = ((z + 1) * py + y + 1) * px + 1;
            labels.extend_from_slice(&lab[s..s + nx]);
        }
    }
    (labels, n)
}

/// The neighbour offsets `[dz, dy, dx]` of 6- or 26-connectivity.
pub fn neighbour_offsets(conn: u8) -> Vec<[i64; 3]> {
    let mut v = vec![];
    for dz in -1..=1i64 {
        for dy in -1..=1i64 {
            for dx in -1..=1i64 {
                let n = dz.abs() + dy.abs() + dx.abs();
                if n == 0 || (conn == 6 && n != 1) {
                    continue;
                }
                v.push([dz, dy, dx]);
            }
        }
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_weights_match_scipy() {
        // scipy.ndimage._filters._gaussian_kernel1d(1.0, 0, 4)
        let w = gaussian_weights(1.0, 0, 4.0);
        let want = [
            1.33830625e-04,
            4.43186162e-03,
            5.39911274e-02,
            2.41971446e-01,
            3.98943469e-01,
            2.41971446e-01,
            5.39911274e-02,
            4.43186162e-03,
            1.33830625e-04,
        ];
        assert_eq!(w.len(), want.len());
        for (a, b) in w.iter().zip(want) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        // sigma 1.5, truncate 4: radius int(6.5) = 6.
        assert_eq!(gaussian_weights(1.5, 0, 4.0).len(), 13);
        // Order 1: odd, and the correlation of a ramp x is its slope 1
        // (up to the discretisation: Σ m²φ(m)/σ² over the integers).
        let d = gaussian_weights(1.3, 1, 4.0);
        let r = radius(&d) as i64;
        let slope: f64 = d
            .iter()
            .enumerate()
            .map(|(k, w)| w * (k as i64 - r) as f64)
            .sum();
        assert!((slope - 1.0).abs() < 1e-3, "{slope}");
        assert!(d.iter().zip(d.iter().rev()).all(|(a, b)| a == &-b));
    }

    #[test]
    fn correlate_shrinks_the_axis() {
        let data: Vec<f64> = (0..5 * 4 * 3).map(|v| v as f64).collect();
        let (o, d) = correlate_valid(&data, [5, 4, 3], 0, &SOBEL_D);
        assert_eq!(d, [3, 4, 3]);
        // in[z+2] - in[z]: 2 planes of 12 apart.
        assert!(o.iter().all(|&v| v == 24.0));
        let (o, d) = correlate_valid(&data, [5, 4, 3], 2, &SOBEL_D);
        assert_eq!(d, [5, 4, 1]);
        assert!(o.iter().all(|&v| v == 2.0));
    }

    #[test]
    fn label_block_orders_by_first_voxel() {
        // Two diagonal voxels: one component with 26, two with 6.
        // (0,0,0), (1,1,1), (2,2,2) on a diagonal, (0,0,4) apart.
        let mut m = vec![false; 45];
        for i in [0, 21, 42, 4] {
            m[i] = true;
        }
        let (l, n) = label_block(&m, [3, 3, 5], 26);
        assert_eq!(n, 2);
        assert_eq!((l[0], l[4], l[21], l[42]), (1, 2, 1, 1));
        let (l, n) = label_block(&m, [3, 3, 5], 6);
        assert_eq!(n, 4);
        assert_eq!((l[0], l[4], l[21], l[42]), (1, 2, 3, 4));
    }
}
