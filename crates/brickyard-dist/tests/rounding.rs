//! How far f32 front-to-back compositing of one long, nearly opaque ray
//! can move when the ray is cut into regions composited apart (sort-last)
//! rather than summed in one pass: the bound the data-parallel
//! accumulation is held to in nearly opaque pixels.
//!
//! The opacity `A` of `A += (1 − A)·α` stops growing a few units in the
//! last place below 1 once an increment `(1 − A)·α` is under half a unit
//! (2⁻²⁵ for `A` in [0.5, 1)); the colour lanes, smaller and so
//! finer-grained, keep taking `(1 − A)·α·c` from every later sample,
//! rounded up to a whole unit of theirs (2⁻²⁵ in [0.25, 0.5)) where it is
//! more than half of one. Past the stall each sample may add up to 2⁻²⁵
//! that the exact sum would not have, and rounding the sum up to half a
//! unit more: one accumulation is within `samples · 2⁻²⁴` of the exact
//! one, and two (a whole ray's, and regions' each starting from 0, which
//! stall at other samples) within `samples · 2⁻²³` of each other.

use brickyard_dist::composite::{in_order, Operator};
use brickyard_render::optics::composite_visible;

/// Premultiplied RGBA of `samples` (colour, opacity) composited front to
/// back in f32, as the renderers do.
fn f32_sum(samples: &[([f32; 3], f32)]) -> [f32; 4] {
    let mut acc = [0.0f32; 4];
    for &(c, a) in samples {
        composite_visible(&mut acc, [c[0], c[1], c[2], a], 1.0);
    }
    acc
}

/// The same in f64.
fn f64_sum(samples: &[([f32; 3], f32)]) -> [f64; 4] {
    let mut acc = [0.0f64; 4];
    for &(c, a) in samples {
        let w = (1.0 - acc[3]) * a as f64;
        for k in 0..3 {
            acc[k] += w * c[k] as f64;
        }
        acc[3] += w;
    }
    acc
}

fn max_diff(a: [f32; 4], b: [f64; 4]) -> f64 {
    (0..4)
        .map(|k| (a[k] as f64 - b[k]).abs())
        .fold(0.0, f64::max)
}

#[test]
fn nearly_opaque_rays_differ_by_rounding_within_the_bound() {
    // A dark front (400 samples) and a bright back (1600), each sample of
    // opacity 0.06: the ray is opaque after about 250 samples.
    let n = 2000;
    let samples: Vec<([f32; 3], f32)> = (0..n)
        .map(|i| match i < 400 {
            true => ([0.3; 3], 0.06),
            false => ([0.8; 3], 0.06),
        })
        .collect();
    let exact = f64_sum(&samples);
    let whole = f32_sum(&samples);
    let bound = n as f64 * 2f64.powi(-24);
    // One pass in f32 stalls below an opacity of 1 and is off the exact
    // sum by more than 1e-5, within the bound.
    assert!(whole[3] < 1.0, "{whole:?}");
    let off = max_diff(whole, exact);
    assert!(
        off > 1e-5 && off <= bound,
        "one pass: {off} (bound {bound})"
    );
    for cuts in [vec![n / 2], vec![n / 5, n / 2, 4 * n / 5], vec![300]] {
        // Each region's samples composited apart, then `over` in order.
        let mut at = 0;
        let parts: Vec<Vec<[f32; 4]>> = cuts
            .iter()
            .chain([n].iter())
            .map(|&end| {
                let p = vec![f32_sum(&samples[at..end])];
                at = end;
                p
            })
            .collect();
        let order: Vec<usize> = (0..parts.len()).collect();
        let split = in_order(Operator::Over, &parts, &order)[0];
        let off_split = max_diff(split, exact);
        assert!(off_split <= bound, "{cuts:?}: {off_split} (bound {bound})");
        let apart = (0..4)
            .map(|k| (split[k] - whole[k]).abs() as f64)
            .fold(0.0, f64::max);
        assert!(apart <= 2.0 * bound, "{cuts:?}: {apart}");
    }
}
