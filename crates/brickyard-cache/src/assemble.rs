//! Padded bricks from a level's voxels: the region a brick reads, its
//! buffer, the apron outside the level, and what the brick turns out to
//! hold (data with its min/max, or one value). Shared by the native loader
//! and the browser's brick source, so both hand out the same bricks.

use crate::brick::{BrickContent, BrickGeometry, BrickKey, LoadedBrick};
use brickyard_core::{dispatch_dtype, Dims3, Sample};
use std::sync::Arc;

/// The part of a padded brick that lies in its level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PaddedRegion {
    /// The level's voxels read, `lo..hi` per axis (never empty: the
    /// brick's first voxel is in it).
    pub lo: Dims3,
    pub hi: Dims3,
    /// Where `lo` sits in the padded brick.
    pub at: Dims3,
}

impl PaddedRegion {
    /// The region `key`'s padded brick reads from its level.
    pub fn of(g: &BrickGeometry, key: &BrickKey) -> PaddedRegion {
        let dims = g.levels[key.level as usize];
        let po = g.padded_origin_of(key);
        let p = g.padded();
        let lo: Dims3 = [0, 1, 2].map(|a| po[a].max(0) as u64);
        let hi: Dims3 = [0, 1, 2].map(|a| ((po[a] + p[a] as i64) as u64).min(dims[a]));
        let at: Dims3 = [0, 1, 2].map(|a| (lo[a] as i64 - po[a]) as u64);
        PaddedRegion { lo, hi, at }
    }

    /// Voxels per axis read.
    pub fn size(&self) -> Dims3 {
        [0, 1, 2].map(|a| self.hi[a] - self.lo[a])
    }
}

/// A zeroed byte buffer of `n` bytes, aligned for every sample type.
pub fn zeroed_bytes(n: usize) -> Arc<[u8]> {
    let mut a = Arc::<[u8]>::new_uninit_slice(n);
    let s = Arc::get_mut(&mut a).expect("a new buffer is not shared");
    // SAFETY: every byte is written before the buffer is taken as
    // initialized `u8`s.
    unsafe {
        std::ptr::write_bytes(s.as_mut_ptr(), 0, n);
        a.assume_init()
    }
}

/// A new (zeroed) buffer for one padded brick of `g`.
pub fn brick_buffer(g: &BrickGeometry) -> Arc<[u8]> {
    zeroed_bytes(g.voxels_per_brick() as usize * g.dtype.size())
}

/// Fill the part of a padded brick of `p` voxels (`es` bytes each) outside
/// the box of `r` voxels at `at` by repeating the box's edge voxels
/// (clamp to edge): along x within the box's rows, then whole rows along y
/// within its planes, then whole planes along z.
pub fn replicate_edges(buf: &mut [u8], p: Dims3, at: Dims3, r: Dims3, es: usize) {
    let [pz, py, px] = p.map(|v| v as usize);
    let [az, ay, ax] = at.map(|v| v as usize);
    let [rz, ry, rx] = r.map(|v| v as usize);
    let row = px * es;
    let plane = py * row;
    for z in az..az + rz {
        for y in ay..ay + ry {
            let o = z * plane + y * row;
            let line = &mut buf[o..o + row];
            let (first, last) = (ax * es, (ax + rx - 1) * es);
            for x in 0..ax {
                line.copy_within(first..first + es, x * es);
            }
            for x in ax + rx..px {
                line.copy_within(last..last + es, x * es);
            }
        }
        let pl = z * plane;
        for y in 0..ay {
            buf.copy_within(pl + ay * row..pl + (ay + 1) * row, pl + y * row);
        }
        for y in ay + ry..py {
            buf.copy_within(pl + (ay + ry - 1) * row..pl + (ay + ry) * row, pl + y * row);
        }
    }
    for z in 0..az {
        buf.copy_within(az * plane..(az + 1) * plane, z * plane);
    }
    for z in az + rz..pz {
        buf.copy_within((az + rz - 1) * plane..(az + rz) * plane, z * plane);
    }
}

/// A brick of one value (`Empty` for 0).
pub fn uniform_brick(key: BrickKey, v: f64, bytes_read: u64) -> LoadedBrick {
    LoadedBrick {
        key,
        content: if v == 0.0 {
            BrickContent::Empty
        } else {
            BrickContent::Constant(v)
        },
        min: v,
        max: v,
        bytes_read,
    }
}

/// Finish a padded brick whose region `reg` of the level has been read
/// into `data` (a buffer of [`brick_buffer`]'s size): the apron outside
/// the level repeats the edge, then the brick is classified. A brick
/// whose every voxel has the same bits (not NaN) is uniform; otherwise it
/// is data with the min/max of the brick proper (NaN ignored).
pub fn finish_brick(
    g: &BrickGeometry,
    key: BrickKey,
    mut data: Arc<[u8]>,
    reg: &PaddedRegion,
) -> LoadedBrick {
    let p = g.padded();
    let es = g.dtype.size();
    let r = reg.size();
    let bytes_read = r.iter().product::<u64>() * es as u64;
    if r != p {
        let buf = Arc::get_mut(&mut data).expect("a brick buffer being filled is not shared");
        replicate_edges(buf, p, reg.at, r, es);
    }
    let a = g.apron as usize;
    let ext = g.extent_of(&key);
    dispatch_dtype!(g.dtype, T => {
        let out: &[T] = brickyard_core::cast_slice(&data);
        let (mn, mx) = brick_min_max(out, p, a, ext);
        let v0 = out[0].to_f64();
        // Uniform only if the brick proper is (a pass over the apron only
        // then). Every voxel has the first one's bits exactly when the
        // buffer equals itself shifted by one voxel (one memcmp).
        if !v0.is_nan() && mn == mx && data[es..] == data[..data.len() - es] {
            return uniform_brick(key, v0, bytes_read);
        }
        LoadedBrick {
            key,
            content: BrickContent::Data(data.clone()),
            min: mn,
            max: mx,
            bytes_read,
        }
    })
}

/// Element-wise minimum and maximum for the lanes of [`brick_min_max`]:
/// NaN is ignored (the other operand wins), as by `f64::min` / `max`.
trait Lanes: Sample {
    const LO: Self;
    const HI: Self;
    fn lmin(a: Self, b: Self) -> Self;
    fn lmax(a: Self, b: Self) -> Self;
}

macro_rules! int_lanes {
    ($($t:ty),*) => {$(
        impl Lanes for $t {
            const LO: Self = <$t>::MAX;
            const HI: Self = <$t>::MIN;
            #[inline(always)]
            fn lmin(a: Self, b: Self) -> Self {
                a.min(b)
            }
            #[inline(always)]
            fn lmax(a: Self, b: Self) -> Self {
                a.max(b)
            }
        }
    )*};
}
int_lanes!(u8, i8, u16, i16, u32, i32);

macro_rules! float_lanes {
    ($($t:ty),*) => {$(
        impl Lanes for $t {
            const LO: Self = <$t>::NAN;
            const HI: Self = <$t>::NAN;
            #[inline(always)]
            fn lmin(a: Self, b: Self) -> Self {
                a.min(b)
            }
            #[inline(always)]
            fn lmax(a: Self, b: Self) -> Self {
                a.max(b)
            }
        }
    )*};
}
float_lanes!(f32, f64);

/// (min, max) of the brick proper (`ext` voxels at `a, a, a` in a padded
/// brick of `p` voxels), NaN ignored (both NaN when every voxel is).
/// Lane-wise over 32 columns at a time, reduced once at the end, so that
/// the rows (as short as 64 voxels) cost no reduction each.
fn brick_min_max<T: Lanes>(out: &[T], p: Dims3, a: usize, ext: Dims3) -> (f64, f64) {
    const L: usize = 32;
    let (p1, p2) = (p[1] as usize, p[2] as usize);
    let mut mn = [T::LO; L];
    let mut mx = [T::HI; L];
    for z in a..a + ext[0] as usize {
        for y in a..a + ext[1] as usize {
            let s = (z * p1 + y) * p2 + a;
            let row = &out[s..s + ext[2] as usize];
            let mut it = row.chunks_exact(L);
            for c in &mut it {
                for i in 0..L {
                    mn[i] = T::lmin(mn[i], c[i]);
                    mx[i] = T::lmax(mx[i], c[i]);
                }
            }
            for (i, &v) in it.remainder().iter().enumerate() {
                mn[i] = T::lmin(mn[i], v);
                mx[i] = T::lmax(mx[i], v);
            }
        }
    }
    // f64::min / max ignore a NaN operand.
    let lo = mn.iter().fold(f64::NAN, |m, v| m.min(v.to_f64()));
    let hi = mx.iter().fold(f64::NAN, |m, v| m.max(v.to_f64()));
    (lo, hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::DType;

    #[test]
    fn bricks_are_classified_by_their_voxels() {
        let g = BrickGeometry {
            brick: [4, 4, 4],
            apron: 1,
            levels: vec![[6, 6, 6]],
            channels: 1,
            dtype: DType::U8,
        };
        let key = BrickKey::new(0, 0, [0, 0, 0]);
        let reg = PaddedRegion::of(&g, &key);
        assert_eq!((reg.lo, reg.hi, reg.at), ([0; 3], [5; 3], [1; 3]));
        let b = finish_brick(&g, key, brick_buffer(&g), &reg);
        assert_eq!(b.content, BrickContent::Empty);
        assert_eq!(b.bytes_read, 125);
        let mut d = brick_buffer(&g);
        Arc::get_mut(&mut d).unwrap().fill(7);
        let b = finish_brick(&g, key, d, &reg);
        assert_eq!(b.content, BrickContent::Constant(7.0));
        // One voxel of the brick proper differs: data, with its range.
        let mut d = brick_buffer(&g);
        {
            let buf = Arc::get_mut(&mut d).unwrap();
            buf.fill(7);
            buf[(2 * 6 + 2) * 6 + 2] = 9;
        }
        let b = finish_brick(&g, key, d, &reg);
        assert!(matches!(b.content, BrickContent::Data(_)));
        assert_eq!((b.min, b.max), (7.0, 9.0));
    }
}
