//! The multi-resolution pyramid plan: level sizes and per-axis ratios.
//!
//! Level 0 is the full-resolution volume. Each next level divides every axis
//! by 1 or 2; an axis is halved only when its current voxel spacing is less
//! than √2 times the smallest spacing among the axes still longer than one
//! voxel. Anisotropic volumes thus become more isotropic level by level
//! (the thick axis waits while the thin ones catch up). Levels stop when the
//! coarsest level fits in one brick.

use crate::Dims3;
use serde::{Deserialize, Serialize};

/// One level of the pyramid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelPlan {
    /// Size in voxels, `[z, y, x]`.
    pub dims: Dims3,
    /// Downsampling ratio from the previous level (`[1,1,1]` for level 0).
    pub ratio: [u32; 3],
    /// Cumulative ratio from level 0.
    pub cum_ratio: [u64; 3],
    /// Physical voxel spacing at this level.
    pub scale: [f64; 3],
    /// Physical position of the centre of voxel 0 at this level.
    pub translation: [f64; 3],
}

/// All levels of a pyramid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PyramidPlan {
    pub levels: Vec<LevelPlan>,
}

/// Whether `path`, a level's path in an OME-Zarr image's `datasets`, lies
/// inside the image's group: relative, each part a name (no empty part,
/// `.` or `..`, no backslash). A path out of it (`../other/0`, `/etc`)
/// would read another store's files, or any.
pub fn level_path_inside(path: &str) -> bool {
    !path.is_empty()
        && !path.starts_with('/')
        && !path.contains('\\')
        && path
            .split('/')
            .all(|c| !c.is_empty() && c != "." && c != "..")
}

/// How many of level `l`'s voxels span level 0's extent on each axis
/// (`[z, y, x]`) in a pyramid of `levels` (voxels per level, finest
/// first): `dims_0 / R`, with `R` the level's ratio to level 0. Voxel `i`
/// of the level is the mean of the box of level-0 voxels `[R·i, R·(i + 1))`
/// and lies at its centre, `R·(i + ½)` level-0 voxels from the volume's
/// low face (the `scale` and `translation` a store's levels are given), so
/// a position at fraction `p` of the extent is the level's continuous voxel
/// coordinate `p · span − ½`. An axis that is not a multiple of `R` ends
/// inside the level's last voxel: the span is then less than the level's
/// voxels (61 voxels at `R = 8`: 7.625 of 8).
///
/// Each level's ratio to the one before is read from the sizes: their
/// quotient rounded, at least 1 (the planner's halving by `div_ceil` gives
/// 2 for any axis it halves, and other pyramids' integer ratios, rounded
/// up or down, come out as they are).
pub fn level_span(levels: &[Dims3], l: usize) -> [f64; 3] {
    let r = level_ratio(levels, l);
    match levels.first() {
        Some(d0) => [0, 1, 2].map(|a| d0[a] as f64 / r[a] as f64),
        None => [1.0; 3],
    }
}

/// Level `l`'s ratio `R` to level 0 on each axis (see [`level_span`]: its
/// span is `dims_0 / R`, which integer code keeps as that fraction).
pub fn level_ratio(levels: &[Dims3], l: usize) -> [u64; 3] {
    let mut ratio = [1u64; 3];
    for k in 1..=l.min(levels.len().saturating_sub(1)) {
        for a in 0..3 {
            let q = levels[k - 1][a] as f64 / levels[k][a].max(1) as f64;
            ratio[a] = ratio[a].saturating_mul(q.round().max(1.0) as u64);
        }
    }
    ratio
}

/// Per-axis ratios for the next level, from the current spacing.
pub fn next_ratio(dims: Dims3, spacing: [f64; 3]) -> [u32; 3] {
    let smin = (0..3)
        .filter(|&a| dims[a] > 1)
        .map(|a| spacing[a])
        .fold(f64::INFINITY, f64::min);
    let mut r = [1u32; 3];
    for a in 0..3 {
        // As a ratio, which stays exact for spacings at either end of the
        // floating-point range (`smin * √2` rounds back to `smin` for the
        // smallest subnormals).
        if dims[a] > 1 && spacing[a] / smin < std::f64::consts::SQRT_2 * (1.0 - 1e-9) {
            r[a] = 2;
        }
    }
    // Spacings that do not compare (infinite ones): halve every axis
    // longer than a voxel, so that each level is smaller than the last.
    if r == [1; 3] {
        for a in 0..3 {
            if dims[a] > 1 {
                r[a] = 2;
            }
        }
    }
    r
}

/// Plan the levels of a volume of `dims` voxels with `spacing` and origin
/// (centre of voxel 0) `origin`, for bricks of `brick` voxels.
pub fn plan_levels(dims: Dims3, spacing: [f64; 3], origin: [f64; 3], brick: Dims3) -> PyramidPlan {
    assert!(dims.iter().all(|&d| d > 0), "empty volume");
    assert!(brick.iter().all(|&b| b > 0), "empty brick");
    let spacing = spacing.map(|s| if s.is_finite() && s > 0.0 { s } else { 1.0 });
    let mut levels = vec![LevelPlan {
        dims,
        ratio: [1; 3],
        cum_ratio: [1; 3],
        scale: spacing,
        translation: origin,
    }];
    loop {
        let cur = levels.last().unwrap();
        if (0..3).all(|a| cur.dims[a] <= brick[a]) {
            break;
        }
        let ratio = next_ratio(cur.dims, cur.scale);
        let mut dims2 = cur.dims;
        let mut cum = cur.cum_ratio;
        let mut scale = cur.scale;
        let mut translation = origin;
        for a in 0..3 {
            dims2[a] = cur.dims[a].div_ceil(ratio[a] as u64);
            cum[a] *= ratio[a] as u64;
            scale[a] = spacing[a] * cum[a] as f64;
            // The centre of a box of `cum` voxels starting at voxel 0.
            translation[a] = origin[a] + (cum[a] as f64 - 1.0) * 0.5 * spacing[a];
        }
        levels.push(LevelPlan {
            dims: dims2,
            ratio,
            cum_ratio: cum,
            scale,
            translation,
        });
    }
    PyramidPlan { levels }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spacings_at_the_ends_of_the_range_still_shrink_each_level() {
        for s in [1e308, f64::MAX, 5e-324, f64::MIN_POSITIVE] {
            let p = plan_levels([256; 3], [s; 3], [0.0; 3], [64; 3]);
            let dims: Vec<_> = p.levels.iter().map(|l| l.dims[0]).collect();
            assert_eq!(dims, vec![256, 128, 64], "spacing {s:e}");
        }
        // One axis so coarse that its ratio to the others is infinite.
        let p = plan_levels([256; 3], [f64::MAX, 1e-300, 1e-300], [0.0; 3], [64; 3]);
        // The thick axis waits until the others are one voxel wide.
        assert_eq!(p.levels.last().unwrap().dims, [64, 1, 1]);
        assert_eq!(p.levels.len(), 11);
        let p = plan_levels([256; 3], [f64::INFINITY; 3], [0.0; 3], [64; 3]);
        assert_eq!(p.levels.len(), 3);
    }

    #[test]
    fn level_spans_follow_the_planners_ratios() {
        // Odd and anisotropic sizes: every planned level's span is level
        // 0's size over the plan's cumulative ratio.
        for (dims, spacing) in [
            ([61, 47, 301], [1.0, 1.0, 1.0]),
            ([33, 200, 129], [4.0, 0.5, 0.5]),
            ([1, 257, 255], [1.0, 1.0, 1.0]),
            ([512, 512, 512], [1.0, 1.0, 1.0]),
        ] {
            let p = plan_levels(dims, spacing, [0.0; 3], [16; 3]);
            let levels: Vec<Dims3> = p.levels.iter().map(|l| l.dims).collect();
            for (l, lp) in p.levels.iter().enumerate() {
                let want = [0, 1, 2].map(|a| dims[a] as f64 / lp.cum_ratio[a] as f64);
                assert_eq!(level_span(&levels, l), want, "{dims:?} level {l}");
                // Never more than the level's voxels, and less than one short.
                for (w, n) in want.iter().zip(lp.dims) {
                    assert!(*w <= n as f64 && *w > n as f64 - 1.0);
                }
            }
        }
        // Another pyramid's ratios (3, sizes rounded down): read as they are.
        let levels = [[90, 91, 92], [30, 30, 30], [10, 10, 10]];
        assert_eq!(level_span(&levels, 1), [30.0, 91.0 / 3.0, 92.0 / 3.0]);
        assert_eq!(level_span(&levels, 2), [10.0, 91.0 / 9.0, 92.0 / 9.0]);
    }

    #[test]
    fn isotropic_cube() {
        let p = plan_levels([1024; 3], [1.0; 3], [0.0; 3], [64; 3]);
        let dims: Vec<_> = p.levels.iter().map(|l| l.dims[0]).collect();
        assert_eq!(dims, vec![1024, 512, 256, 128, 64]);
        assert_eq!(p.levels[1].translation, [0.5; 3]);
        assert_eq!(p.levels[2].scale, [4.0; 3]);
    }

    #[test]
    fn anisotropic_becomes_isotropic() {
        // 256 x 256 x 25 slices at 0.78 x 0.78 x 6.5 mm.
        let p = plan_levels([25, 256, 256], [6.5, 0.78, 0.78], [0.0; 3], [16; 3]);
        let r: Vec<_> = p.levels.iter().skip(1).map(|l| l.ratio).collect();
        assert_eq!(r[0], [1, 2, 2]);
        assert_eq!(r[1], [1, 2, 2]);
        assert_eq!(r[2], [1, 2, 2]);
        // spacing is now 6.5 vs 6.24: isotropic enough, all axes halve.
        assert_eq!(r[3], [2, 2, 2]);
        let last = p.levels.last().unwrap();
        assert!(last.dims.iter().all(|&d| d <= 16));
    }

    #[test]
    fn odd_and_thin() {
        let p = plan_levels([1, 100, 3], [1.0; 3], [0.0; 3], [8; 3]);
        for l in &p.levels[1..] {
            assert_eq!(l.ratio[0], 1, "a one-voxel axis is never halved");
        }
        assert_eq!(p.levels.last().unwrap().dims, [1, 7, 1]);
        let p = plan_levels([5, 5, 5], [1.0; 3], [0.0; 3], [64; 3]);
        assert_eq!(p.levels.len(), 1);
    }
}

/// Why a store is incomplete, if it is: the one rule that `info`, the
/// readers (native and web) and `serve` share. A store is incomplete when
/// its folder is a `.partial` one (a conversion still writing, or killed),
/// or when its root group's `brickyard` attributes (`brickyard`, given as
/// found) do not say `complete: true`: the writer sets `false` first and
/// `true` only once every chunk is in place, so a missing or non-boolean
/// field is not taken as complete either. A store without `brickyard`
/// attributes (another writer's) is taken as complete.
pub fn incomplete_reason(
    store: &str,
    brickyard: Option<&serde_json::Value>,
) -> Option<&'static str> {
    if store.trim_end_matches('/').ends_with(".partial") {
        return Some("a conversion still writing it, or interrupted (its folder ends in .partial)");
    }
    match brickyard.map(|b| b.get("complete")) {
        None => None,
        Some(Some(serde_json::Value::Bool(true))) => None,
        Some(Some(serde_json::Value::Bool(false))) => {
            Some("an interrupted conversion (its root metadata says complete: false)")
        }
        Some(_) => Some("its root metadata's brickyard attributes do not say complete: true"),
    }
}

#[cfg(test)]
mod incomplete_tests {
    use super::incomplete_reason;
    use serde_json::json;

    #[test]
    fn one_rule_for_every_reading_of_complete() {
        assert_eq!(incomplete_reason("a.zarr", None), None);
        assert_eq!(
            incomplete_reason("a.zarr", Some(&json!({"complete": true}))),
            None
        );
        assert!(incomplete_reason("a.zarr", Some(&json!({"complete": false}))).is_some());
        assert!(incomplete_reason("a.zarr", Some(&json!({"version": 1}))).is_some());
        assert!(incomplete_reason("a.zarr", Some(&json!({"complete": "yes"}))).is_some());
        assert!(incomplete_reason("a.zarr.partial", None).is_some());
        assert!(incomplete_reason("a.zarr.partial/", Some(&json!({"complete": true}))).is_some());
    }
}
