//! The product renderers' optics: what a sample's value becomes on screen.
//! Transfer-function application (MIP and slice colours), opacity
//! correction for the step length, front-to-back compositing with early
//! termination, and the additive mix of several channels. The CPU modes
//! (`dvr`, `mip`, `slice`) call these; `optics.wgsl` is the device twin.
//! The in-core reference has its own implementation of the same rules.

use crate::lanes::F4;
use crate::params::{ChannelStyle, LabelSelect};
use brickyard_core::transfer::TfEval;
use brickyard_core::TransferFunction;

/// DVR stops a ray once its accumulated opacity reaches this.
pub const EARLY_TERMINATION: f32 = 0.99;

/// Opacity for a step of `exponent = Δ/Δ_ref` reference steps:
/// `1 − (1 − α)^exponent` (exactly `α` when the exponent is 1).
#[inline]
pub fn correct_opacity(alpha: f32, exponent: f32) -> f32 {
    if exponent == 1.0 {
        alpha
    } else if exponent == exponent.trunc() && exponent.abs() <= 64.0 {
        // Whole exponents (a level 2^l coarser than the reference step)
        // by multiplication: much cheaper than a general power.
        1.0 - (1.0 - alpha).powi(exponent as i32)
    } else {
        1.0 - (1.0 - alpha).powf(exponent)
    }
}

/// Front-to-back compositing of one sample of straight-alpha colour `c`
/// (opacity corrected by `exponent`) into the premultiplied `acc`.
/// Returns true when the ray is opaque enough to stop.
#[inline]
pub fn composite(acc: &mut [f32; 4], c: [f32; 4], exponent: f32) -> bool {
    if c[3] <= 0.0 {
        return false;
    }
    composite_visible(acc, c, exponent)
}

/// [`composite`] for a sample known to have positive opacity.
#[inline(always)]
pub fn composite_visible(acc: &mut [f32; 4], c: [f32; 4], exponent: f32) -> bool {
    let a = correct_opacity(c[3], exponent);
    let wgt = (1.0 - acc[3]) * a;
    acc[0] += wgt * c[0];
    acc[1] += wgt * c[1];
    acc[2] += wgt * c[2];
    acc[3] += wgt;
    acc[3] >= EARLY_TERMINATION
}

/// A DVR ray's premultiplied colour in four lanes, opacity first:
/// `[A, R, G, B]` (the layout of [`TfTable`]'s colours).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Acc(F4);

impl Acc {
    #[inline(always)]
    pub(crate) fn new() -> Acc {
        Acc(F4::splat(0.0))
    }

    /// `[R, G, B, A]`, as [`composite`] accumulates.
    #[inline(always)]
    pub(crate) fn rgba(self) -> [f32; 4] {
        let [a, r, g, b] = self.0.to_array();
        [r, g, b, a]
    }

    /// [`composite_visible`] of a sample `[α, r, g, b]` (positive
    /// opacity) from [`TfTable::lookup_visible`]: the same operations, so
    /// the same bits.
    #[inline(always)]
    pub(crate) fn composite_visible(&mut self, c: F4, exponent: f32) -> bool {
        let a = correct_opacity(c.first(), exponent);
        let wgt = (1.0 - self.0.first()) * a;
        let w = F4::splat(wgt);
        // Colour lanes `wgt·c`; the opacity lane `wgt` itself.
        self.0 = self.0.add(w.mul(c).with_first(w));
        self.0.first() >= EARLY_TERMINATION
    }
}

/// Bins of [`TfTable`] (as [`TfEval`]'s; the bin rule is the same).
const BINS: usize = 1024;
/// [`TfTable`] bins: every value transparent, or a control point in the
/// bin (ask [`TfEval`]); else the index of the bin's pieces.
const CLEAR: u16 = u16::MAX;
const SEARCH: u16 = u16::MAX - 1;

/// The four pieces (opacity, red, green, blue) that every windowed value of
/// some bins lies in, as lanes: `v0 + (x − x0)·slope` clamped to
/// `[lo, hi]`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(16))]
struct Pieces {
    x0: [f32; 4],
    v0: [f32; 4],
    slope: [f32; 4],
    lo: [f32; 4],
    hi: [f32; 4],
}

/// A frame's transfer function for DVR samples in four lanes: per bin of
/// the windowed values, the opacity's and the colour map's pieces side by
/// side, so a sample costs one bin load and five lane operations instead
/// of two segment loads and four scalar evaluations. Built from the
/// transfer function's points by the rules of
/// `brickyard_core::transfer` (segment = `partition_point(p.x ≤ x)`,
/// constant before the first and after the last point, slope
/// `(v1 − v0)/(x1 − x0)`, clamped to the segment's end values); bins with a
/// control point in or near them, and a degenerate window, fall back to
/// [`TfEval::lookup_visible`]. The results are [`TfEval::lookup_visible`]'s,
/// bit for bit (tested), in the order `[α, r, g, b]`.
#[derive(Debug, Clone)]
pub(crate) struct TfTable {
    w0: f32,
    inv_width: f32,
    /// Windowed values (before the clamp) below this lie in bins that are
    /// all clear: the lower edge of the first bin that is not (`−∞` when
    /// bin 0 is not, `+∞` when none is). Most transparent samples of a
    /// DVR stop at this one comparison.
    clear_below: f32,
    bins: Box<[u16; BINS]>,
    pieces: Vec<Pieces>,
    /// The evaluator's result where the windowed value is exactly 0 and
    /// exactly 1 (values at or past the window's ends: saturated data,
    /// which the end bins, holding the first and last control points,
    /// would otherwise send to the search); `None` if no value gave it.
    ends: [Option<Option<F4>>; 2],
}

/// [`TfTable::lookup_visible`] in a bin with a control point: the
/// evaluator's search (out of line: rare, and it keeps the run loop
/// small).
#[cold]
#[inline(never)]
fn search(eval: &TfEval, value: f32) -> Option<F4> {
    let [r, g, b, a] = eval.lookup_visible(value)?;
    Some(F4::new([a, r, g, b]))
}

/// `TfEval`'s bin of a windowed value `x ∈ [0, 1]` (NaN: the last).
#[inline(always)]
fn bin_of(x: f32) -> usize {
    let last = (BINS - 1) as f32;
    let y = x * BINS as f32;
    let y = if y < last { y } else { last };
    let y = if y > 0.0 { y } else { 0.0 };
    // SAFETY: `y` is finite and in [0, BINS − 1].
    let b = unsafe { y.to_int_unchecked::<i32>() } as usize;
    b & (BINS - 1)
}

/// The piece `(x0, v0, slope, lo, hi)` of segment `i` of points `(x, v)`.
fn piece(pts: &[(f32, f32)], i: usize) -> [f32; 5] {
    if i == 0 || i == pts.len() {
        let v = pts[i.min(pts.len() - 1)].1;
        return [0.0, v, 0.0, v, v];
    }
    let ((x0, v0), (x1, v1)) = (pts[i - 1], pts[i]);
    [x0, v0, (v1 - v0) / (x1 - x0), v0.min(v1), v0.max(v1)]
}

/// The segment every windowed value of bin `b` has, `None` where a point
/// lies in or near the bin.
fn segment(xs: &[f32], b: usize) -> Option<usize> {
    let n = BINS as f32;
    let lo = b as f32 / n - 1e-6;
    let hi = (b + 1) as f32 / n + 1e-6;
    if xs.iter().any(|&x| x >= lo && x <= hi) {
        None
    } else {
        Some(xs.iter().filter(|&&x| x < lo).count())
    }
}

impl TfTable {
    pub(crate) fn new(tf: &TransferFunction, eval: &TfEval) -> TfTable {
        let [w0, w1] = tf.window;
        let inv_width = 1.0 / (w1 - w0);
        let mut bins = Box::new([SEARCH; BINS]);
        let mut pieces: Vec<Pieces> = vec![];
        let op: Vec<(f32, f32)> = tf.opacity.iter().map(|p| (p[0], p[1])).collect();
        let cm = tf.colormap.points();
        let chans: Vec<Vec<(f32, f32)>> = (1..4)
            .map(|c| cm.iter().map(|p| (p[0], p[c])).collect())
            .collect();
        let op_x: Vec<f32> = op.iter().map(|p| p.0).collect();
        let cm_x: Vec<f32> = cm.iter().map(|p| p[0]).collect();
        if !(inv_width.is_finite() && inv_width > 0.0) || op.is_empty() || cm.is_empty() {
            return TfTable {
                w0,
                inv_width,
                clear_below: f32::NEG_INFINITY,
                bins,
                pieces,
                ends: [None; 2],
            };
        }
        // The evaluator depends on the windowed value only (after NaN):
        // any value whose `x` is exactly 0 (1) gives the result for all.
        let ends = [(w0 - (w1 - w0), 0.0f32), (w1 + (w1 - w0), 1.0)].map(|(v, want)| {
            let x = ((v - w0) * inv_width).clamp(0.0, 1.0);
            (v.is_finite() && x == want).then(|| search(eval, v))
        });
        for (b, slot) in bins.iter_mut().enumerate() {
            // Transparent bins: where the evaluator says so of a value in
            // the bin's middle (its `range_visible` of one value is its bin).
            let v = w0 + (b as f32 + 0.5) / BINS as f32 * (w1 - w0);
            let x = ((v - w0) * inv_width).clamp(0.0, 1.0);
            if bin_of(x) == b && !eval.range_visible(v, v) {
                *slot = CLEAR;
                continue;
            }
            let (Some(i), Some(j)) = (segment(&op_x, b), segment(&cm_x, b)) else {
                continue;
            };
            let ps = [
                piece(&op, i),
                piece(&chans[0], j),
                piece(&chans[1], j),
                piece(&chans[2], j),
            ];
            let p = Pieces {
                x0: ps.map(|p| p[0]),
                v0: ps.map(|p| p[1]),
                slope: ps.map(|p| p[2]),
                lo: ps.map(|p| p[3]),
                hi: ps.map(|p| p[4]),
            };
            *slot = match pieces.iter().position(|q| *q == p) {
                Some(k) => k as u16,
                None => {
                    pieces.push(p);
                    (pieces.len() - 1) as u16
                }
            };
        }
        let clear_below = match bins.iter().position(|&b| b != CLEAR) {
            Some(0) => f32::NEG_INFINITY,
            // A windowed value below b / BINS has its bin below b (the
            // product with BINS, a power of two, is exact).
            Some(b) => b as f32 / BINS as f32,
            None => f32::INFINITY,
        };
        TfTable {
            w0,
            inv_width,
            clear_below,
            bins,
            pieces,
            ends,
        }
    }

    /// [`TfEval::lookup_visible`] of `value` (the same bits), as lanes
    /// `[α, r, g, b]`. `may_nan`: whether `value` may be NaN (samples of
    /// float voxels; a constant where inlined); a sample of integer voxels
    /// never is, and skips the test.
    #[inline(always)]
    pub(crate) fn lookup_visible(&self, eval: &TfEval, value: f32, may_nan: bool) -> Option<F4> {
        let y = (value - self.w0) * self.inv_width;
        // Below every bin that may show (NaN fails this and the next).
        if y < self.clear_below || (may_nan && value.is_nan()) {
            return None;
        }
        let x = y.clamp(0.0, 1.0);
        match self.bins[bin_of(x)] {
            CLEAR => None,
            SEARCH => {
                let end = if x == 1.0 {
                    self.ends[1]
                } else if x == 0.0 {
                    self.ends[0]
                } else {
                    None
                };
                end.unwrap_or_else(|| search(eval, value))
            }
            i => {
                // SAFETY: every index in `bins` below `SEARCH` is one of
                // `pieces`.
                let p = unsafe { self.pieces.get_unchecked(i as usize) };
                let v = F4::new(p.v0)
                    .add(F4::splat(x).sub(F4::new(p.x0)).mul(F4::new(p.slope)))
                    .clamp(F4::new(p.lo), F4::new(p.hi));
                // (`<=` as the evaluator: a NaN opacity is kept.)
                if v.first() <= 0.0 {
                    None
                } else {
                    Some(v)
                }
            }
        }
    }
}

/// The pixel of a MIP ray: the transfer function's colour of the maximum,
/// opaque where the ray took a sample.
#[inline]
pub fn mip_color(tf: &TransferFunction, hit: bool, best: f32) -> [f32; 4] {
    if !hit || best.is_nan() {
        return if hit { [0.0, 0.0, 0.0, 1.0] } else { [0.0; 4] };
    }
    let c = tf.lookup(best);
    [c[0], c[1], c[2], 1.0]
}

/// The pixel of a slice of one channel: the transfer function's colour of
/// the value (by the frame's evaluator: `TransferFunction::lookup`'s colour,
/// bit for bit), opaque; transparent where nothing served the sample or
/// the value is NaN.
#[inline]
pub fn slice_color(tf: &TfEval, value: Option<f32>) -> [f32; 4] {
    match value {
        Some(v) if !v.is_nan() => {
            let [r, g, b] = tf.color(v);
            [r, g, b, 1.0]
        }
        _ => [0.0; 4],
    }
}

/// A label's 32-bit hash (the finalizer of MurmurHash3): labels next to
/// each other get unrelated colours. `optics.wgsl`'s `label_hash` is its
/// twin.
#[inline]
pub fn label_hash(id: u32) -> u32 {
    let mut h = id;
    h ^= h >> 16;
    h = h.wrapping_mul(0x85eb_ca6b);
    h ^= h >> 13;
    h = h.wrapping_mul(0xc2b2_ae35);
    h ^ (h >> 16)
}

/// The label a sample of a label image holds: its value rounded to the
/// nearest integer (`⌊v + ½⌋`, saturating at the ends of `i32`); `None`
/// for NaN. (Labels beyond 2²⁴ are sampled as `f32` and share their
/// rounded value, on the CPU and the device alike.)
#[inline]
pub fn label_of(v: f32) -> Option<i32> {
    (!v.is_nan()).then(|| (v + 0.5).floor() as i32)
}

/// Whether a brick or cell whose values lie in `[lo, hi]` holds background
/// alone (label 0 and nothing else): what a label image's rays cross
/// without sampling, on the CPU and the device.
#[inline]
pub fn label_background(lo: f32, hi: f32) -> bool {
    lo == 0.0 && hi == 0.0
}

/// Whether a brick or cell whose values lie in `[lo, hi]` draws nothing
/// under `select`: background alone ([`label_background`]), or only
/// labels the selection leaves out. What a label image's rays cross
/// without sampling, on the CPU and the device.
#[inline]
pub fn label_clear(lo: f32, hi: f32, select: Option<&LabelSelect>) -> bool {
    label_background(lo, hi) || select.is_some_and(|s| !s.draws_any(lo, hi))
}

/// Linear RGB of the colour with hue `h6` (in sixths of the circle,
/// `[0, 6)`), saturation `s` and value `v`.
#[inline]
fn hsv(h6: f32, s: f32, v: f32) -> [f32; 3] {
    let i = h6.floor();
    let f = h6 - i;
    let p = v * (1.0 - s);
    let q = v * (1.0 - s * f);
    let t = v * (1.0 - s * (1.0 - f));
    match i as i32 {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// The pixel of a slice of a label image ([`RenderParams::labels`](crate::params::RenderParams::labels)):
/// the colour of the sample's label, opaque; transparent for label 0 (the
/// background), where nothing served the sample, and for NaN. The colour
/// comes from the label's hash: a hue anywhere on the circle, saturation
/// 0.6–1 and value 0.75–1, so that every label stands out from black and
/// from its neighbours. `optics.wgsl`'s `label_color` is its twin.
#[inline]
pub fn label_color(value: Option<f32>) -> [f32; 4] {
    let Some(id) = value.and_then(label_of).filter(|&id| id != 0) else {
        return [0.0; 4];
    };
    let h = label_hash(id as u32);
    let hue = (h & 0xffff) as f32 * (6.0 / 65536.0);
    let sat = 0.6 + 0.4 * ((h >> 16) & 0xff) as f32 * (1.0 / 255.0);
    let val = 0.75 + 0.25 * (h >> 24) as f32 * (1.0 / 255.0);
    let [r, g, b] = hsv(hue, sat, val);
    [r, g, b, 1.0]
}

/// The label drawn for a sample of a label image: its label
/// ([`label_of`]) when that is not 0 and `select` (if any) shows it.
#[inline]
pub fn label_drawn(value: Option<f32>, select: Option<&LabelSelect>) -> Option<i32> {
    value
        .and_then(label_of)
        .filter(|&id| id != 0 && select.is_none_or(|s| s.shows(id)))
}

/// [`label_color`] of the labels `select` shows; the others are
/// transparent, as the background.
#[inline]
pub fn label_color_of(value: Option<f32>, select: Option<&LabelSelect>) -> [f32; 4] {
    match label_drawn(value, select) {
        Some(id) => label_color(Some(id as f32)),
        None => [0.0; 4],
    }
}

/// Intensity of `value` for a channel shown with `style`: its window
/// mapped to `[0, 1]`, clamped (NaN: 0).
#[inline]
pub fn channel_intensity(style: &ChannelStyle, value: f32) -> f32 {
    let [lo, hi] = style.window;
    let x = ((value - lo) / (hi - lo)).clamp(0.0, 1.0);
    if x.is_nan() {
        0.0
    } else {
        x
    }
}

/// Several channels' samples at one point mixed as coincident media
/// (`multi.rs`): opacity `1 − Π(1 − α_i)`, colour `Σ α_i·c_i / Σ α_i`.
#[derive(Clone, Copy)]
pub(crate) struct Media {
    keep: f32,
    rgb: [f32; 3],
    weight: f32,
}

impl Media {
    /// No channel yet.
    pub(crate) const NONE: Media = Media {
        keep: 1.0,
        rgb: [0.0; 3],
        weight: 0.0,
    };

    /// Add a channel's sample `[r, g, b, α]` (straight colour).
    #[inline(always)]
    pub(crate) fn add(&mut self, c: [f32; 4]) {
        self.keep *= 1.0 - c[3];
        self.rgb[0] += c[3] * c[0];
        self.rgb[1] += c[3] * c[1];
        self.rgb[2] += c[3] * c[2];
        self.weight += c[3];
    }

    /// The mixed sample (straight colour and opacity); `None` when no
    /// channel shows.
    #[inline(always)]
    pub(crate) fn sample(&self) -> Option<[f32; 4]> {
        (self.weight > 0.0).then(|| {
            let inv = 1.0 / self.weight;
            let [r, g, b] = self.rgb;
            [r * inv, g * inv, b * inv, 1.0 - self.keep]
        })
    }
}

/// Additive mix of channel intensities: `Σ colour·intensity`, clamped to 1,
/// opaque.
#[inline]
pub fn mix_channels(styles: &[ChannelStyle], values: impl Iterator<Item = f32>) -> [f32; 4] {
    let mut rgb = [0.0f32; 3];
    for (s, v) in styles.iter().zip(values) {
        let i = channel_intensity(s, v);
        for (c, w) in rgb.iter_mut().zip(s.color) {
            *c += w * i;
        }
    }
    [rgb[0].min(1.0), rgb[1].min(1.0), rgb[2].min(1.0), 1.0]
}

/// Each rule against values worked out by hand (not against the
/// reference renderer, which has its own implementation).
#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::transfer::ColorMap;

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() <= 1e-6
    }

    /// `TfTable` (lanes) equals the evaluator bit for bit, and `Acc`
    /// composites as `composite_visible`, on random transfer functions
    /// (steps, clear stretches, presets and point colour maps, narrow and
    /// wide windows) at random values, bin edges, control points and NaN.
    #[test]
    fn tf_table_and_lanes_compositing_equal_the_scalar_twin() {
        use brickyard_core::transfer::Preset;
        let mut s = 0x007a_b1e5_u64;
        let mut rnd = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        let (mut tabled, mut visible) = (0, 0);
        for trial in 0..300 {
            let n = 1 + (rnd() * 7.0) as usize;
            let mut xs: Vec<f32> = (0..n).map(|_| rnd()).collect();
            xs.sort_by(f32::total_cmp);
            if n > 2 && trial % 3 == 0 {
                xs[1] = xs[2];
            }
            let opacity = xs
                .iter()
                .map(|&x| [x, if rnd() < 0.3 { 0.0 } else { rnd() }])
                .collect();
            let colormap = if trial % 2 == 0 {
                let p = [
                    Preset::Grayscale,
                    Preset::Hot,
                    Preset::Viridis,
                    Preset::Coolwarm,
                ];
                ColorMap::Preset(p[trial % 4])
            } else {
                let m = 1 + (rnd() * 5.0) as usize;
                let mut xs: Vec<f32> = (0..m).map(|_| rnd()).collect();
                xs.sort_by(f32::total_cmp);
                ColorMap::Points(xs.iter().map(|&x| [x, rnd(), rnd(), rnd()]).collect())
            };
            let w0 = (rnd() - 0.5) * 1000.0;
            let w1 = w0 + [1e-3, 1.0, 255.0, 65535.0][trial % 4] * (0.1 + rnd());
            let tf = TransferFunction::new([w0, w1], opacity, colormap).unwrap();
            let eval = tf.evaluator();
            let table = TfTable::new(&tf, &eval);
            let span = w1 - w0;
            let mut values: Vec<f32> = (0..2000).map(|_| w0 + span * (rnd() * 1.4 - 0.2)).collect();
            values.extend((0..=1024).map(|b| w0 + span * b as f32 / 1024.0));
            values.extend(tf.opacity.iter().map(|p| w0 + span * p[0]));
            values.extend(tf.colormap.points().iter().map(|p| w0 + span * p[0]));
            values.extend([f32::NAN, w0, w1, f32::INFINITY, f32::NEG_INFINITY]);
            for &v in &values {
                let want = eval.lookup_visible(v);
                let got = table.lookup_visible(&eval, v, true).map(|c| {
                    let [a, r, g, b] = c.to_array();
                    [r, g, b, a]
                });
                if !v.is_nan() {
                    // Without the NaN test (samples of integer voxels).
                    let plain = table.lookup_visible(&eval, v, false);
                    assert_eq!(
                        plain.map(|c| c.to_array().map(f32::to_bits)),
                        got.map(|[r, g, b, a]| [a, r, g, b].map(f32::to_bits)),
                        "trial {trial} value {v}"
                    );
                }
                assert_eq!(
                    got.map(|c| c.map(f32::to_bits)),
                    want.map(|c| c.map(f32::to_bits)),
                    "trial {trial} value {v}"
                );
                let x = ((v - w0) * table.inv_width).clamp(0.0, 1.0);
                tabled += (table.bins[bin_of(x)] < SEARCH) as u32;
                // Compositing this sample after a random one.
                if let Some(c) = want {
                    visible += 1;
                    let first = [rnd(), rnd(), rnd(), rnd() * 0.9];
                    let exponent = [1.0, 0.5, 2.0, 1.7][visible % 4];
                    let mut acc = [0.0f32; 4];
                    let mut lanes = Acc::new();
                    for c in [first, c] {
                        let a = composite_visible(&mut acc, c, exponent);
                        let b =
                            lanes.composite_visible(F4::new([c[3], c[0], c[1], c[2]]), exponent);
                        assert_eq!(a, b);
                    }
                    assert_eq!(lanes.rgba().map(f32::to_bits), acc.map(f32::to_bits));
                }
            }
        }
        // Most lookups take the table, not the fallback.
        assert!(
            tabled > 300_000 && visible > 100_000,
            "{tabled} tabled, {visible} visible"
        );
    }

    #[test]
    fn opacity_correction() {
        // Exponent 1: the opacity itself, bit for bit.
        assert_eq!(correct_opacity(0.3, 1.0), 0.3);
        // Two reference steps at 0.5: 1 − 0.5² = 0.75; three at 0.2:
        // 1 − 0.8³ = 0.488.
        assert!(close(correct_opacity(0.5, 2.0), 0.75));
        assert!(close(correct_opacity(0.2, 3.0), 0.488));
        // Half a step at 0.75: 1 − √0.25 = 0.5; a quarter at 0.9375:
        // 1 − 0.0625^¼ = 0.5.
        assert!(close(correct_opacity(0.75, 0.5), 0.5));
        assert!(close(correct_opacity(0.9375, 0.25), 0.5));
        // Opaque stays opaque, transparent stays transparent.
        assert_eq!(correct_opacity(1.0, 0.5), 1.0);
        assert_eq!(correct_opacity(0.0, 3.0), 0.0);
    }

    #[test]
    fn compositing_front_to_back() {
        let mut acc = [0.0f32; 4];
        // Red at 0.5: C = 0.5·(1, 0, 0), A = 0.5.
        assert!(!composite(&mut acc, [1.0, 0.0, 0.0, 0.5], 1.0));
        assert_eq!(acc, [0.5, 0.0, 0.0, 0.5]);
        // Blue at 0.5 behind it: weight (1 − 0.5)·0.5 = 0.25.
        assert!(!composite(&mut acc, [0.0, 0.0, 1.0, 0.5], 1.0));
        assert_eq!(acc, [0.5, 0.0, 0.25, 0.75]);
        // A transparent sample changes nothing.
        assert!(!composite(&mut acc, [0.0, 1.0, 0.0, 0.0], 1.0));
        assert_eq!(acc, [0.5, 0.0, 0.25, 0.75]);
        // Green at 0.5 over two reference steps: α' = 0.75, weight
        // 0.25·0.75 = 0.1875, A = 0.9375.
        assert!(!composite(&mut acc, [0.0, 1.0, 0.0, 0.5], 2.0));
        assert!(close(acc[1], 0.1875) && close(acc[3], 0.9375), "{acc:?}");
        // An opaque sample ends the ray: A = 1 ≥ 0.99.
        assert!(composite(&mut acc, [1.0, 1.0, 1.0, 1.0], 1.0));
        assert!(close(acc[3], 1.0) && close(acc[0], 0.5625), "{acc:?}");
    }

    #[test]
    fn early_termination_at_the_threshold() {
        // Alpha 0.5 per step: A = 1 − 0.5ⁿ reaches 0.99 at n = 7 (0.9921875),
        // not at n = 6 (0.984375).
        let mut acc = [0.0f32; 4];
        let mut n = 0;
        loop {
            n += 1;
            if composite(&mut acc, [1.0, 1.0, 1.0, 0.5], 1.0) {
                break;
            }
        }
        assert_eq!(n, 7);
        assert_eq!(acc[3], 0.9921875);
    }

    #[test]
    fn mip_and_slice_colours() {
        // Grey ramp over the window [0, 10], opacity 0 (neither mode uses
        // the opacity).
        let tf = TransferFunction::new(
            [0.0, 10.0],
            vec![[0.0, 0.0]],
            ColorMap::Points(vec![[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]]),
        )
        .unwrap();
        assert_eq!(mip_color(&tf, true, 5.0), [0.5, 0.5, 0.5, 1.0]);
        assert_eq!(mip_color(&tf, true, 20.0), [1.0, 1.0, 1.0, 1.0]);
        // A ray that took only NaN samples is black; one that took none
        // stays transparent.
        assert_eq!(mip_color(&tf, true, f32::NAN), [0.0, 0.0, 0.0, 1.0]);
        assert_eq!(mip_color(&tf, false, 5.0), [0.0; 4]);
        let ev = tf.evaluator();
        assert_eq!(slice_color(&ev, Some(2.5)), [0.25, 0.25, 0.25, 1.0]);
        assert_eq!(slice_color(&ev, Some(f32::NAN)), [0.0; 4]);
        assert_eq!(slice_color(&ev, None), [0.0; 4]);
    }

    #[test]
    fn label_colours() {
        // MurmurHash3's finalizer on known inputs.
        assert_eq!(label_hash(0), 0);
        assert_eq!(label_hash(1), 0x514e_28b7);
        // Background, NaN and unserved samples are transparent.
        assert_eq!(label_color(Some(0.0)), [0.0; 4]);
        assert_eq!(label_color(Some(0.4)), [0.0; 4]);
        assert_eq!(label_color(Some(f32::NAN)), [0.0; 4]);
        assert_eq!(label_color(None), [0.0; 4]);
        // A value within half of a label is that label.
        assert_eq!(label_color(Some(6.6)), label_color(Some(7.0)));
        assert_eq!(label_color(Some(-3.4)), label_color(Some(-3.0)));
        // Every label of 1..2000 is opaque and bright (its largest
        // component at least 0.75, within [0, 1]), and neighbouring labels
        // differ clearly.
        let mut prev = label_color(Some(1.0));
        for id in 1..2000 {
            let c = label_color(Some(id as f32));
            assert_eq!(c[3], 1.0);
            assert!(
                c[..3].iter().all(|x| (0.0..=1.0).contains(x)),
                "{id}: {c:?}"
            );
            assert!(
                c[..3].iter().cloned().fold(0.0, f32::max) >= 0.75 - 1e-6,
                "{id}"
            );
            if id > 1 {
                let d: f32 = (0..3).map(|i| (c[i] - prev[i]).abs()).sum();
                assert!(d > 0.0, "{id} looks like {}", id - 1);
            }
            prev = c;
        }
        // Hues cover the circle: all six sectors among the first 100.
        let mut sectors = [false; 6];
        for id in 1..100u32 {
            sectors[((label_hash(id) & 0xffff) * 6 / 65536) as usize] = true;
        }
        assert!(sectors.iter().all(|&s| s));
        // The colour from hue, saturation and value: pure red, grey.
        assert_eq!(hsv(0.0, 1.0, 1.0), [1.0, 0.0, 0.0]);
        assert_eq!(hsv(2.0, 1.0, 1.0), [0.0, 1.0, 0.0]);
        assert_eq!(hsv(4.0, 1.0, 1.0), [0.0, 0.0, 1.0]);
        assert_eq!(hsv(3.5, 0.0, 0.5), [0.5, 0.5, 0.5]);
    }

    #[test]
    fn channels_add_up() {
        let green = ChannelStyle {
            channel: 0,
            color: [0.0, 1.0, 0.0],
            window: [0.0, 200.0],
            tf: None,
            levels: None,
        };
        let magenta = ChannelStyle {
            channel: 1,
            color: [1.0, 0.0, 1.0],
            window: [100.0, 300.0],
            tf: None,
            levels: None,
        };
        assert_eq!(channel_intensity(&green, 50.0), 0.25);
        assert_eq!(channel_intensity(&green, -5.0), 0.0);
        assert_eq!(channel_intensity(&green, 500.0), 1.0);
        assert_eq!(channel_intensity(&green, f32::NAN), 0.0);
        let styles = [green, magenta];
        // 0.25 green and 0.5 magenta.
        let px = mix_channels(&styles, [50.0, 200.0].into_iter());
        assert_eq!(px, [0.5, 0.25, 0.5, 1.0]);
        // The sum is clamped to 1 per component.
        let both = [
            ChannelStyle {
                color: [0.8, 0.8, 0.0],
                ..styles[0].clone()
            },
            ChannelStyle {
                color: [0.6, 0.0, 0.0],
                ..styles[1].clone()
            },
        ];
        let px = mix_channels(&both, [200.0, 300.0].into_iter());
        assert_eq!(px, [1.0, 0.8, 0.0, 1.0]);
        // No value: black, still opaque.
        let px = mix_channels(&styles, [f32::NAN, f32::NAN].into_iter());
        assert_eq!(px, [0.0, 0.0, 0.0, 1.0]);
    }
}
