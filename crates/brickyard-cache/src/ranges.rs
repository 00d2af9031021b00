//! Value ranges of the virtual memory's bricks, known before any brick is
//! loaded: for each padded brick (apron included) the smallest and largest
//! value, taken from the store's per-brick statistics. A renderer skips a
//! brick whose range the transfer function maps to zero opacity (or, in a
//! MIP, whose maximum cannot raise the ray's maximum) without loading it.
//!
//! The range of a padded brick is the union of the statistics of every store
//! brick its padded region touches, so every value a trilinear sample whose
//! base voxel lies in the brick can take is inside it (up to `f32`
//! rounding, which the bounds absorb: they are rounded outwards).

use crate::brick::{BrickGeometry, BrickKey};
use brickyard_core::Dims3;

/// Ranges of one level, `[channel][z][y][x]`; `[NaN, NaN]` where unknown.
#[derive(Debug, Clone)]
pub struct LevelRanges {
    /// Bricks per axis `[z, y, x]`.
    pub bricks: Dims3,
    pub channels: usize,
    pub range: Vec<[f32; 2]>,
}

impl LevelRanges {
    /// Range of brick `b` of channel `c`; `[NaN, NaN]` when unknown.
    #[inline]
    pub fn get(&self, c: usize, b: Dims3) -> [f32; 2] {
        let n = self.bricks;
        self.range[(((c as u64 * n[0] + b[0]) * n[1] + b[1]) * n[2] + b[2]) as usize]
    }
}

/// Ranges of every level that has statistics (and is not too large to hold).
#[derive(Debug, Clone, Default)]
pub struct BrickRanges {
    pub levels: Vec<Option<LevelRanges>>,
}

impl BrickRanges {
    /// The level's ranges, if known.
    #[inline]
    pub fn level(&self, l: usize) -> Option<&LevelRanges> {
        self.levels.get(l).and_then(|r| r.as_ref())
    }

    /// Build the ranges of the padded bricks of `g` from per-store-brick
    /// statistics: `stats(level, channel, store_brick)` gives `(min, max)`
    /// of store brick `store_brick` (bricks of size `store_brick_size`),
    /// `None` when unknown. A level without statistics (`has(level)` false)
    /// or with more than `max_bricks` bricks × channels is left out.
    pub fn build(
        g: &BrickGeometry,
        store_brick_size: Dims3,
        max_bricks: u64,
        has: impl Fn(usize) -> bool,
        stats: impl Fn(usize, usize, Dims3) -> Option<(f64, f64)>,
    ) -> BrickRanges {
        let mut levels = Vec::with_capacity(g.levels.len());
        for l in 0..g.levels.len() {
            let n = g.bricks_per_level(l);
            let count = n.iter().product::<u64>() * g.channels as u64;
            if !has(l) || count > max_bricks {
                levels.push(None);
                continue;
            }
            let dims = g.levels[l];
            let sb = store_brick_size;
            let mut range = Vec::with_capacity(count as usize);
            for c in 0..g.channels {
                for key in g.keys(l, c) {
                    range.push(padded_range(g, &key, dims, sb, |b| stats(l, c, b)));
                }
            }
            levels.push(Some(LevelRanges {
                bricks: n,
                channels: g.channels,
                range,
            }));
        }
        BrickRanges { levels }
    }
}

fn padded_range(
    g: &BrickGeometry,
    key: &BrickKey,
    dims: Dims3,
    sb: Dims3,
    stats: impl Fn(Dims3) -> Option<(f64, f64)>,
) -> [f32; 2] {
    let po = g.padded_origin_of(key);
    let p = g.padded();
    let lo: Dims3 = [0, 1, 2].map(|a| po[a].max(0) as u64);
    let hi: Dims3 = [0, 1, 2].map(|a| ((po[a] + p[a] as i64) as u64).min(dims[a]));
    let (mut mn, mut mx) = (f64::INFINITY, f64::NEG_INFINITY);
    for z in lo[0] / sb[0]..=(hi[0] - 1) / sb[0] {
        for y in lo[1] / sb[1]..=(hi[1] - 1) / sb[1] {
            for x in lo[2] / sb[2]..=(hi[2] - 1) / sb[2] {
                // A brick of only NaN has NaN statistics: its samples
                // are transparent, so it does not widen the range (nor
                // do the NaN voxels of any other brick).
                let Some((a, b)) = stats([z, y, x]) else {
                    return [f32::NAN; 2];
                };
                if let Some((a, b)) = brickyard_core::brick_stats::finite_range(a, b) {
                    mn = mn.min(a);
                    mx = mx.max(b);
                }
            }
        }
    }
    if mn > mx {
        // Only NaN: nothing visible, but keep it "unknown" to stay simple.
        return [f32::NAN; 2];
    }
    [down(mn), up(mx)]
}

/// The largest `f32` not above `v`.
fn down(v: f64) -> f32 {
    let f = v as f32;
    if (f as f64) > v {
        f.next_down()
    } else {
        f
    }
}

/// The smallest `f32` not below `v`.
fn up(v: f64) -> f32 {
    let f = v as f32;
    if (f as f64) < v {
        f.next_up()
    } else {
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::DType;

    #[test]
    fn padded_ranges_cover_the_neighbours_the_apron_reaches() {
        // 1-D along x: 4 store bricks of 8 voxels with ranges [10i, 10i+5];
        // engine bricks of 8 with apron 1 reach into both neighbours.
        let g = BrickGeometry {
            brick: [1, 1, 8],
            apron: 1,
            levels: vec![[1, 1, 32]],
            channels: 1,
            dtype: DType::U8,
        };
        let r = BrickRanges::build(
            &g,
            [1, 1, 8],
            1 << 20,
            |_| true,
            |_, _, b| Some((10.0 * b[2] as f64, 10.0 * b[2] as f64 + 5.0)),
        );
        let l = r.level(0).unwrap();
        assert_eq!(l.get(0, [0, 0, 0]), [0.0, 15.0]);
        assert_eq!(l.get(0, [0, 0, 1]), [0.0, 25.0]);
        assert_eq!(l.get(0, [0, 0, 3]), [20.0, 35.0]);
        // Unknown statistics make the whole padded brick unknown.
        let r = BrickRanges::build(
            &g,
            [1, 1, 8],
            1 << 20,
            |_| true,
            |_, _, b| (b[2] != 2).then_some((0.0, 1.0)),
        );
        let l = r.level(0).unwrap();
        assert_eq!(l.get(0, [0, 0, 0]), [0.0, 1.0]);
        assert!(l.get(0, [0, 0, 1])[0].is_nan());
        // NaN takes no part: a brick of NaN alone adds nothing, one of a
        // single value beside NaN, `(v, NaN)`, adds `v`.
        let r = BrickRanges::build(
            &g,
            [1, 1, 8],
            1 << 20,
            |_| true,
            |_, _, b| match b[2] {
                0 => Some((4.0, f64::NAN)),
                1 => Some((f64::NAN, f64::NAN)),
                _ => Some((9.0, 12.0)),
            },
        );
        let l = r.level(0).unwrap();
        assert_eq!(l.get(0, [0, 0, 0]), [4.0, 4.0]);
        assert_eq!(l.get(0, [0, 0, 1]), [4.0, 12.0]);
        assert_eq!(l.get(0, [0, 0, 2]), [9.0, 12.0]);
        // Too many bricks: left out.
        let r = BrickRanges::build(&g, [1, 1, 8], 3, |_| true, |_, _, _| None);
        assert!(r.level(0).is_none());
    }

    #[test]
    fn bounds_round_outwards() {
        let v = 0.1f64; // not representable in f32
        assert!((down(v) as f64) <= v && (up(v) as f64) >= v);
        assert_eq!(down(2.0), 2.0);
        assert_eq!(up(2.0), 2.0);
    }
}
