//! Axes that run against the world's direction.
//!
//! OME-Zarr places voxels with a positive scale and a translation per axis,
//! so index i of every axis must run along +x, +y, +z. A file whose header
//! says an axis runs the other way (a NIfTI sform or qform with a negative
//! diagonal entry, a NRRD space direction such as `(0,-0.78,0)`) is read
//! with that axis reversed: [`Flip`] mirrors the region asked of the file
//! and reverses the voxels read, in place. The importer then sets the
//! axis's translation to the world position of the voxel that becomes
//! index 0 ([`first_voxel`]) and its scale to the step's length.

use crate::error::Result;
use brickyard_core::Dims3;
use std::ops::Range;

/// Which axes of a volume are read reversed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Flip {
    /// Reversed axes, `[z, y, x]`.
    pub axes: [bool; 3],
    /// Size of the volume, `[z, y, x]`.
    pub dims: Dims3,
}

impl Flip {
    /// Reverse `axes` (`[z, y, x]`) of a volume of `dims` voxels. Axes of
    /// one voxel are left alone (reversing them changes nothing).
    pub fn new(axes: [bool; 3], dims: Dims3) -> Flip {
        Flip {
            axes: [0, 1, 2].map(|a| axes[a] && dims[a] > 1),
            dims,
        }
    }

    /// Whether no axis is reversed.
    pub fn is_identity(&self) -> bool {
        !self.axes.iter().any(|&a| a)
    }

    /// The region of the file that holds `region` (`[z, y, x]`) of the
    /// reversed volume.
    pub fn mirror(&self, region: [Range<u64>; 3]) -> [Range<u64>; 3] {
        let m = |a: usize, r: Range<u64>| {
            if self.axes[a] {
                self.dims[a] - r.end..self.dims[a] - r.start
            } else {
                r
            }
        };
        let [z, y, x] = region;
        [m(0, z), m(1, y), m(2, x)]
    }

    /// Reverse a dense C-order box of `shape` (`[z, y, x]`) voxels of
    /// `size` bytes each along the reversed axes, in place.
    pub fn reverse(&self, buf: &mut [u8], shape: Dims3, size: usize) {
        let [nz, ny, nx] = shape.map(|n| n as usize);
        let row = nx * size;
        let plane = ny * row;
        if row == 0 || plane == 0 || nz == 0 {
            return;
        }
        debug_assert_eq!(buf.len(), nz * plane);
        if self.axes[2] && nx > 1 {
            for r in buf.chunks_exact_mut(row) {
                r.reverse();
                if size > 1 {
                    for e in r.chunks_exact_mut(size) {
                        e.reverse();
                    }
                }
            }
        }
        if self.axes[1] && ny > 1 {
            for p in buf.chunks_exact_mut(plane) {
                swap_ends(p, ny, row);
            }
        }
        if self.axes[0] && nz > 1 {
            swap_ends(buf, nz, plane);
        }
    }

    /// Read `z × y × x` of the reversed volume into `out` (`size` bytes a
    /// voxel): `read` reads the mirrored region of the file, which is then
    /// reversed in place. Reads go straight through when nothing is
    /// reversed.
    pub fn read(
        &self,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
        size: usize,
        read: impl FnOnce(Range<u64>, Range<u64>, Range<u64>, &mut [u8]) -> Result<()>,
    ) -> Result<()> {
        if self.is_identity() {
            return read(z, y, x, out);
        }
        let shape = [&z, &y, &x].map(|r| r.end - r.start);
        let [fz, fy, fx] = self.mirror([z, y, x]);
        read(fz, fy, fx, out)?;
        self.reverse(out, shape, size);
        Ok(())
    }
}

/// Swap block `i` with block `n − 1 − i` of `buf`, `n` blocks of `len`
/// bytes.
fn swap_ends(buf: &mut [u8], n: usize, len: usize) {
    for i in 0..n / 2 {
        let (a, b) = buf.split_at_mut((n - 1 - i) * len);
        a[i * len..(i + 1) * len].swap_with_slice(&mut b[..len]);
    }
}

/// World position of the voxel that becomes index 0 when an axis of `n`
/// voxels whose file steps by `step` (negative) from `origin` is reversed:
/// the file's last voxel, `origin + (n − 1) · step`.
pub fn first_voxel(origin: f64, n: u64, step: f64) -> f64 {
    origin + n.saturating_sub(1) as f64 * step
}

/// A number for a report: its shortest float32 form (7 significant
/// digits), `0` for negative zero.
pub fn short(v: f64) -> String {
    let f = v as f32;
    if f == 0.0 {
        "0".to_string()
    } else {
        format!("{f}")
    }
}

/// The report's words for reversed axes: "x runs against the file's
/// direction −1.5: stored reversed so that it runs along +x (translation
/// 6.5, the file's last x voxel)", one clause per axis joined by "; ".
/// `steps` are `(axis name, the file's step as written, translation)`.
pub fn describe(steps: &[(&str, String, Option<f64>)]) -> String {
    steps
        .iter()
        .map(|(name, step, t)| {
            let at = match t {
                Some(t) => format!(
                    " (translation {}, the position of the file's last {name} voxel)",
                    short(*t)
                ),
                None => String::new(),
            };
            format!(
                "{name} runs against the file's direction {step}: stored reversed so that it \
                 runs along +{name}{at}"
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3×4×5 volume of u16 with value = linear index.
    fn volume() -> (Dims3, Vec<u16>) {
        let d = [3u64, 4, 5];
        (d, (0..60).collect())
    }

    fn bytes(v: &[u16]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_ne_bytes()).collect()
    }

    /// Every combination of axes and many boxes: a read through the flip
    /// equals the reversed volume cut at the box.
    #[test]
    fn reads_match_the_reversed_volume() {
        let (d, v) = volume();
        let at = |z: u64, y: u64, x: u64| v[((z * d[1] + y) * d[2] + x) as usize];
        for bits in 0..8u8 {
            let axes = [bits & 4 != 0, bits & 2 != 0, bits & 1 != 0];
            let f = Flip::new(axes, d);
            let m = |a: usize, i: u64| if axes[a] { d[a] - 1 - i } else { i };
            for (z, y, x) in [
                (0..3, 0..4, 0..5),
                (1..3, 0..2, 2..5),
                (2..3, 3..4, 4..5),
                (0..2, 1..4, 0..1),
                (1..1, 0..4, 0..5),
            ] {
                let n = (z.end - z.start) * (y.end - y.start) * (x.end - x.start);
                let mut out = vec![0u8; n as usize * 2];
                f.read(
                    z.clone(),
                    y.clone(),
                    x.clone(),
                    &mut out,
                    2,
                    |fz, fy, fx, buf| {
                        let mut w = Vec::new();
                        for k in fz {
                            for j in fy.clone() {
                                for i in fx.clone() {
                                    w.push(at(k, j, i));
                                }
                            }
                        }
                        buf.copy_from_slice(&bytes(&w));
                        Ok(())
                    },
                )
                .unwrap();
                let mut want = Vec::new();
                for k in z.clone() {
                    for j in y.clone() {
                        for i in x.clone() {
                            want.push(at(m(0, k), m(1, j), m(2, i)));
                        }
                    }
                }
                assert_eq!(out, bytes(&want), "axes {axes:?} box {z:?} {y:?} {x:?}");
            }
        }
    }

    #[test]
    fn one_voxel_axes_are_not_reversed() {
        let f = Flip::new([true, true, false], [1, 4, 5]);
        assert_eq!(f.axes, [false, true, false]);
        assert!(Flip::new([true, false, false], [1, 4, 5]).is_identity());
    }

    #[test]
    fn first_voxel_and_words() {
        assert_eq!(first_voxel(50.0, 30, -1.5), 6.5);
        assert_eq!(short(-99.60937499999997), "-99.609375");
        assert_eq!(short(-0.0), "0");
        assert_eq!(short(0.781_249_999_999_999_9), "0.78125");
        assert_eq!(
            describe(&[("x", "-1.5".into(), Some(6.5))]),
            "x runs against the file's direction -1.5: stored reversed so that it runs along \
             +x (translation 6.5, the position of the file's last x voxel)"
        );
    }
}
