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

/// The largest kernel radius computed: the weights of a Gaussian are summed
/// over its whole radius (the normalisation), so σ is bounded by
/// `(MAX_RADIUS + 0.5) / truncate` voxels (about a million at `truncate = 4`,
/// far wider than any volume: such a kernel is folded to the volume's
/// extent, see [`gaussian_weights_folded`]).
pub const MAX_RADIUS: u64 = 1 << 22;

/// The kernel radius of σ at `truncate`: scipy's `int(truncate · σ + 0.5)`
/// (0 for σ ≤ 0), saturating.
pub fn gaussian_radius(sigma: f64, truncate: f64) -> u64 {
    if sigma > 0.0 {
        (truncate * sigma + 0.5) as u64
    } else {
        0
    }
}

/// The largest σ whose radius at `truncate` is at most [`MAX_RADIUS`].
pub fn max_sigma(truncate: f64) -> f64 {
    MAX_RADIUS as f64 / truncate
}

/// [`gaussian_weights`] on an axis of `n` voxels with boundary mode
/// "nearest" (the edge voxel repeated): every tap farther than `n − 1` from
/// the centre reads an edge voxel whatever voxel is computed, so the weights
/// beyond `reach = min(radius, n − 1)` are summed onto the taps `±reach`
/// (the same result; the halo needed is at most `n − 1`). Equal to
/// [`gaussian_weights`] when the radius is at most `n − 1`. The full kernel
/// is never held: its normalisation is summed in the order
/// [`gaussian_weights`] sums it. The radius must be at most [`MAX_RADIUS`].
pub fn gaussian_weights_folded(sigma: f64, order: u32, truncate: f64, n: u64) -> Vec<f64> {
    assert!(order <= 1, "only orders 0 and 1");
    let radius = gaussian_radius(sigma, truncate);
    assert!(radius <= MAX_RADIUS, "radius {radius} over MAX_RADIUS");
    let reach = radius.min(n.max(1) - 1);
    if reach == radius {
        return gaussian_weights(sigma, order, truncate);
    }
    let (radius, reach) = (radius as i64, reach as i64);
    let s2 = sigma * sigma;
    let phi = |x: i64| (-0.5 / s2 * (x * x) as f64).exp();
    let sum: f64 = (-radius..=radius).map(phi).sum();
    let weight = |x: i64| {
        let p = phi(x) / sum;
        if order == 0 {
            p
        } else {
            x as f64 / s2 * p
        }
    };
    // The folded tail beyond +reach; the one beyond −reach is its mirror
    // (order 0) or its negative (order 1).
    let tail: f64 = (reach..=radius).map(weight).sum();
    let mut w: Vec<f64> = (-reach..=reach).map(weight).collect();
    let last = w.len() - 1;
    w[last] = tail;
    w[0] = if order == 0 { tail } else { -tail };
    w
}

/// `w` on an axis of `n` voxels with boundary mode "nearest": the weights
/// farther than `n − 1` from the centre summed onto the taps `±(n − 1)`
/// (see [`gaussian_weights_folded`]); `w` itself when it is not wider.
pub fn fold_weights(w: &[f64], n: u64) -> Vec<f64> {
    let r = radius(w);
    let reach = (r as u64).min(n.max(1) - 1) as usize;
    if reach == r {
        return w.to_vec();
    }
    let mut f = w[r - reach..=r + reach].to_vec();
    let last = f.len() - 1;
    f[0] = w[..=r - reach].iter().sum();
    f[last] = w[r + reach..].iter().sum();
    f
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
    correlate_nearest(data, dims, axis, w, r as i64, dims[axis] - 2 * r)
}

/// Correlate `data` (`dims`) along `axis` with `w`, boundary mode
/// "nearest" applied at the ends of `data`: result `j` (of `len` along the
/// axis) is centred on position `first + j` of `data` along the axis, and a
/// tap outside `data` reads its nearest end. This is [`correlate_valid`] on
/// `data` padded by repeating its end voxels, with the same operations in
/// the same order (the same bits), without the padding: when `data` is a
/// block's box grown by the halo and clamped to the volume, the ends of
/// `data` beyond which taps fall are the volume's.
pub fn correlate_nearest<R: Real>(
    data: &[R],
    dims: [usize; 3],
    axis: usize,
    w: &[R],
    first: i64,
    len: usize,
) -> (Vec<R>, [usize; 3]) {
    let r = radius(w);
    let n = dims[axis];
    assert!(n > 0 || len == 0, "no data along the axis");
    let mut od = dims;
    od[axis] = len;
    let [nz, ny, nx] = od;
    let mut out = vec![R::default(); nz * ny * nx];
    if out.is_empty() {
        return (out, od);
    }
    // Position in `data` (along the axis) read by tap position `q`: output
    // `j`'s tap `k` is `q = j + k`.
    let lo = first - r as i64;
    let taps = len + 2 * r;
    let idx: Vec<usize> = (0..taps)
        .map(|q| (lo + q as i64).clamp(0, n as i64 - 1) as usize)
        .collect();
    let inside = lo >= 0 && lo + taps as i64 <= n as i64;
    // Input strides.
    let sy = dims[2];
    let sz = dims[1] * dims[2];
    // Gaussians are symmetric and their derivatives antisymmetric: pair
    // the taps `r − k` and `r + k` (one multiplication for two), centre
    // tap first, then the pairs outwards.
    let sym = R::PAIR_TAPS && (0..r).all(|k| w[k] == w[2 * r - k]);
    let anti =
        R::PAIR_TAPS && !sym && w[r] == R::default() && (0..r).all(|k| w[k] == -w[2 * r - k]);
    let mut scratch: Vec<R> = vec![];
    for z in 0..nz {
        for y in 0..ny {
            let o = (z * ny + y) * nx;
            let orow = &mut out[o..o + nx];
            // Along x, the taps of a row are one padded row (in place when
            // no tap leaves `data`).
            let xrow: &[R] = if axis == 2 {
                let base = z * sz + y * sy;
                if inside {
                    &data[base + lo as usize..][..taps]
                } else {
                    scratch.clear();
                    scratch.extend(idx.iter().map(|&i| data[base + i]));
                    &scratch
                }
            } else {
                &[]
            };
            // The input row of tap `k` (nx values).
            let row = |k: usize| -> &[R] {
                match axis {
                    0 => &data[idx[z + k] * sz + y * sy..][..nx],
                    1 => &data[z * sz + idx[y + k] * sy..][..nx],
                    _ => &xrow[k..k + nx],
                }
            };
            if sym || anti {
                for (a, &b) in orow.iter_mut().zip(row(r)) {
                    *a = w[r] * b;
                }
                for k in 1..=r {
                    let (lo, hi) = (row(r - k), row(r + k));
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
                for (a, &b) in orow.iter_mut().zip(row(k)) {
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
    let (first, len) = valid_part(dims, w);
    separable_nearest(data, dims, w, first, len)
}

/// Where the valid part of a block padded by the radii of `w` lies: the
/// first position and the length per axis.
pub fn valid_part<R>(dims: [usize; 3], w: [&[R]; 3]) -> ([i64; 3], [usize; 3]) {
    let r = w.map(radius);
    for a in 0..3 {
        assert!(dims[a] >= 2 * r[a], "block thinner than the kernel");
    }
    (r.map(|v| v as i64), [0, 1, 2].map(|a| dims[a] - 2 * r[a]))
}

/// [`separable`] with [`correlate_nearest`]: the results at positions
/// `first..first + len` (per axis) of `data`, taps outside `data` reading
/// its nearest end. An identity pass (skipped) must have `first` 0 and
/// `len` the whole axis.
pub fn separable_nearest<R: Real>(
    data: Vec<R>,
    dims: [usize; 3],
    w: [&[R]; 3],
    first: [i64; 3],
    len: [usize; 3],
) -> (Vec<R>, [usize; 3]) {
    let (mut d, mut dd) = (data, dims);
    for (axis, wa) in w.iter().enumerate() {
        if is_identity(wa) {
            debug_assert!(first[axis] == 0 && len[axis] == dims[axis]);
            continue;
        }
        (d, dd) = correlate_nearest(&d, dd, axis, wa, first[axis], len[axis]);
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
    let (first, len) = valid_part(dims, ws[0]);
    magnitude_nearest(data, dims, ws, first, len)
}

/// [`magnitude`] with [`separable_nearest`] passes.
pub fn magnitude_nearest<R: Real>(
    data: &[R],
    dims: [usize; 3],
    ws: [[&[R]; 3]; 3],
    first: [i64; 3],
    len: [usize; 3],
) -> (Vec<R>, [usize; 3]) {
    let mut acc: Option<(Vec<R>, [usize; 3])> = None;
    for w in ws {
        let (d, od) = separable_nearest(data.to_vec(), dims, w, first, len);
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

/// The most voxels a median filter's window reaches from its centre along
/// one axis (a window of up to 15³ values per voxel).
pub const MAX_MEDIAN_RADIUS: usize = 7;

/// The median of the `(2r+1)` box around each position `first..first +
/// len` (per axis) of `data` (`dims`, `[z, y, x]`), a tap outside `data`
/// reading its nearest end (scipy's `median_filter(x, size=2r+1,
/// mode="nearest")`). Values are ordered by `f64::total_cmp` (NaN above
/// every number); the window holds an odd count, so the median is one of
/// its values, exact in any type. Planes in parallel.
pub fn median_nearest<R: Real>(
    data: &[R],
    dims: [usize; 3],
    r: [usize; 3],
    first: [i64; 3],
    len: [usize; 3],
) -> Vec<R> {
    median_nearest_until(data, dims, r, first, len, None)
}

/// [`median_nearest`] that gives up once `stop` is set (looked at every
/// row: a wide window takes seconds a block, and Ctrl-C waited for it);
/// what it returns then is unfinished, for the caller to throw away.
pub fn median_nearest_until<R: Real>(
    data: &[R],
    dims: [usize; 3],
    r: [usize; 3],
    first: [i64; 3],
    len: [usize; 3],
    stop: Option<&std::sync::atomic::AtomicBool>,
) -> Vec<R> {
    use rayon::prelude::*;
    let stopped = || stop.is_some_and(|s| s.load(std::sync::atomic::Ordering::Relaxed));
    let n = len.iter().product::<usize>();
    let mut out = vec![R::default(); n];
    if n == 0 {
        return out;
    }
    // For each output coordinate along an axis, its taps' clamped indices.
    let taps = |a: usize| -> Vec<Vec<usize>> {
        (0..len[a])
            .map(|i| {
                let c = first[a] + i as i64;
                (-(r[a] as i64)..=r[a] as i64)
                    .map(|d| (c + d).clamp(0, dims[a] as i64 - 1) as usize)
                    .collect()
            })
            .collect()
    };
    let (tz, ty, tx) = (taps(0), taps(1), taps(2));
    let w = (2 * r[0] + 1) * (2 * r[1] + 1) * (2 * r[2] + 1);
    let mid = w / 2;
    out.par_chunks_mut(len[1] * len[2])
        .enumerate()
        .for_each(|(k, plane)| {
            let mut win: Vec<f64> = Vec::with_capacity(w);
            for j in 0..len[1] {
                if stopped() {
                    return;
                }
                for i in 0..len[2] {
                    win.clear();
                    for &zz in &tz[k] {
                        for &yy in &ty[j] {
                            let row = (zz * dims[1] + yy) * dims[2];
                            win.extend(tx[i].iter().map(|&xx| data[row + xx].to_f64()));
                        }
                    }
                    let (_, m, _) = win.select_nth_unstable_by(mid, f64::total_cmp);
                    plane[j * len[2] + i] = R::from_f64(*m);
                }
            }
        });
    out
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

    /// The median against its definition: every tap clamped into the
    /// volume, the window sorted, its middle value; halos wider than the
    /// volume, a region inside a larger block, radii 0 on some axes.
    #[test]
    fn median_is_the_middle_of_the_sorted_window() {
        let dims = [3usize, 5, 4];
        let n: usize = dims.iter().product();
        // Values with ties, from a fixed sequence.
        let data: Vec<f64> = (0..n).map(|i| ((i * 37 + 11) % 17) as f64 - 3.0).collect();
        let at = |z: i64, y: i64, x: i64| {
            let c = |v: i64, d: usize| v.clamp(0, d as i64 - 1) as usize;
            data[(c(z, dims[0]) * dims[1] + c(y, dims[1])) * dims[2] + c(x, dims[2])]
        };
        for (r, first, len) in [
            ([1, 1, 1], [0i64, 0, 0], [3usize, 5, 4]),
            ([2, 0, 3], [0, 0, 0], [3, 5, 4]),
            ([0, 2, 1], [1, 1, 1], [2, 3, 2]),
            ([4, 4, 4], [0, 0, 0], [3, 5, 4]),
        ] {
            let got = median_nearest(&data, dims, r, first, len);
            let mut k = 0;
            for z in 0..len[0] as i64 {
                for y in 0..len[1] as i64 {
                    for x in 0..len[2] as i64 {
                        let (cz, cy, cx) = (first[0] + z, first[1] + y, first[2] + x);
                        let mut w = vec![];
                        for dz in -(r[0] as i64)..=r[0] as i64 {
                            for dy in -(r[1] as i64)..=r[1] as i64 {
                                for dx in -(r[2] as i64)..=r[2] as i64 {
                                    w.push(at(cz + dz, cy + dy, cx + dx));
                                }
                            }
                        }
                        w.sort_by(f64::total_cmp);
                        assert_eq!(got[k], w[w.len() / 2], "r {r:?} at {cz},{cy},{cx}");
                        k += 1;
                    }
                }
            }
        }
    }

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
    fn folded_weights_sum_the_taps_past_the_volume() {
        for (sigma, order, n) in [
            (3.0, 0, 5),
            (3.0, 1, 5),
            (7.3, 0, 1),
            (7.3, 1, 2),
            (2.0, 0, 40),
        ] {
            let w = gaussian_weights(sigma, order, 4.0);
            let f = gaussian_weights_folded(sigma, order, 4.0, n);
            let g = fold_weights(&w, n);
            assert_eq!(f.len(), g.len());
            assert_eq!(f.len() as u64, (w.len() as u64).min(2 * n - 1));
            for (a, b) in f.iter().zip(&g) {
                assert!(
                    (a - b).abs() < 1e-15,
                    "σ {sigma} order {order} n {n}: {a} vs {b}"
                );
            }
        }
        assert_eq!(
            gaussian_weights_folded(2.0, 0, 4.0, 40),
            gaussian_weights(2.0, 0, 4.0)
        );
    }

    #[test]
    fn correlate_nearest_is_correlate_valid_on_the_padded_data() {
        // Random data, padded by repeating its ends along each axis in
        // turn: the same bits, for symmetric, antisymmetric and other
        // weights, and for outputs that need more padding than the data.
        let dims = [5, 4, 6];
        let mut s = 7u64;
        let data: Vec<f64> = (0..120)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
                (s >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect();
        for w in [
            gaussian_weights(2.0, 0, 4.0),
            gaussian_weights(2.0, 1, 4.0),
            vec![0.5, 0.25, -1.0],
        ] {
            let r = radius(&w);
            for axis in 0..3 {
                let n = dims[axis];
                for (first, len) in [(0i64, n), (-3, 2), (2, n + 1), (r as i64, 1)] {
                    let (got, gd) = correlate_nearest(&data, dims, axis, &w, first, len);
                    // Pad: positions first − r .. first + len + r, clamped.
                    let mut pd = dims;
                    pd[axis] = len + 2 * r;
                    let mut padded = vec![];
                    for z in 0..pd[0] {
                        for y in 0..pd[1] {
                            for x in 0..pd[2] {
                                let mut p = [z as i64, y as i64, x as i64];
                                p[axis] = (p[axis] + first - r as i64).clamp(0, n as i64 - 1);
                                padded.push(
                                    data[((p[0] as usize * dims[1]) + p[1] as usize) * dims[2]
                                        + p[2] as usize],
                                );
                            }
                        }
                    }
                    let (want, wd) = correlate_valid(&padded, pd, axis, &w);
                    assert_eq!(gd, wd);
                    assert_eq!(got, want, "axis {axis} first {first} len {len}");
                }
            }
        }
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
