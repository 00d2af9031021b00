//! Transfer functions: data value → colour and opacity.
//!
//! Over 800 lines: with its tests: 0.8k lines of code, 0.4k of tests.
//!
//! A value `v` is first mapped through the *window* `[w0, w1]` to
//! `x = clamp((v − w0) / (w1 − w0), 0, 1)`; opacity and colour are then
//! piecewise-linear functions of `x` given by control points:
//!
//! - `opacity`: `(x, alpha)` points,
//! - `colormap`: a named preset or `(x, r, g, b)` points.
//!
//! Control points must have non-decreasing `x` in `[0, 1]`; two points with
//! the same `x` make a step (the function takes the later point's value at
//! that `x`). Left of the first point and right of the last one the
//! function is constant. Values are linear RGB in `[0, 1]` with straight
//! (not premultiplied) alpha; NaN data values are fully transparent.
//!
//! Opacity is *per reference step*: renderers correct it for their actual
//! step `Δ` as `α' = 1 − (1 − α)^(Δ/Δ_ref)` (see `brickyard-render`).

use crate::camera::{brief, ConfigError, Fields};
use crate::DType;
use serde::{Deserialize, Serialize};
use serde_json::Value;

const WHAT: &str = "transfer function";

/// A named colour map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    Grayscale,
    Hot,
    Viridis,
    Coolwarm,
    Bone,
}

const GRAYSCALE: &[[f32; 4]] = &[[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]];
/// Matplotlib's `hot`: black → red → yellow → white.
const HOT: &[[f32; 4]] = &[
    [0.0, 0.0, 0.0, 0.0],
    [0.375, 1.0, 0.0, 0.0],
    [0.75, 1.0, 1.0, 0.0],
    [1.0, 1.0, 1.0, 1.0],
];
/// Viridis at ten evenly spaced stops (`#440154 … #fde725`).
const VIRIDIS: &[[f32; 4]] = &[
    [0.0, 0.267, 0.004, 0.329],
    [1.0 / 9.0, 0.282, 0.157, 0.471],
    [2.0 / 9.0, 0.243, 0.286, 0.537],
    [3.0 / 9.0, 0.192, 0.408, 0.557],
    [4.0 / 9.0, 0.149, 0.510, 0.557],
    [5.0 / 9.0, 0.122, 0.620, 0.537],
    [6.0 / 9.0, 0.208, 0.718, 0.475],
    [7.0 / 9.0, 0.431, 0.808, 0.345],
    [8.0 / 9.0, 0.710, 0.871, 0.169],
    [1.0, 0.992, 0.906, 0.145],
];
/// Moreland's diverging cool–warm map.
const COOLWARM: &[[f32; 4]] = &[
    [0.0, 0.230, 0.299, 0.754],
    [0.25, 0.554, 0.690, 0.996],
    [0.5, 0.865, 0.865, 0.865],
    [0.75, 0.957, 0.598, 0.477],
    [1.0, 0.706, 0.016, 0.150],
];
/// Matplotlib's `bone`: grey with a blue tint.
const BONE: &[[f32; 4]] = &[
    [0.0, 0.0, 0.0, 0.0],
    [0.365079, 0.319444, 0.319444, 0.444444],
    [0.746032, 0.652778, 0.777778, 0.777778],
    [1.0, 1.0, 1.0, 1.0],
];

impl Preset {
    pub const ALL: [Preset; 5] = [
        Preset::Grayscale,
        Preset::Hot,
        Preset::Viridis,
        Preset::Coolwarm,
        Preset::Bone,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Preset::Grayscale => "grayscale",
            Preset::Hot => "hot",
            Preset::Viridis => "viridis",
            Preset::Coolwarm => "coolwarm",
            Preset::Bone => "bone",
        }
    }

    /// Parse a preset name (`gray` and `greyscale` are accepted too).
    pub fn parse(s: &str) -> Option<Preset> {
        let s = s.trim().to_ascii_lowercase();
        Some(match s.as_str() {
            "grayscale" | "greyscale" | "gray" | "grey" => Preset::Grayscale,
            "hot" => Preset::Hot,
            "viridis" => Preset::Viridis,
            "coolwarm" => Preset::Coolwarm,
            "bone" => Preset::Bone,
            _ => return None,
        })
    }

    /// The preset's `(x, r, g, b)` control points.
    pub fn points(self) -> &'static [[f32; 4]] {
        match self {
            Preset::Grayscale => GRAYSCALE,
            Preset::Hot => HOT,
            Preset::Viridis => VIRIDIS,
            Preset::Coolwarm => COOLWARM,
            Preset::Bone => BONE,
        }
    }
}

/// Colour as a function of the windowed value `x ∈ [0, 1]`. In JSON: a
/// preset name (`"viridis"`) or an array of `[x, r, g, b]` points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged, try_from = "serde_json::Value")]
pub enum ColorMap {
    Preset(Preset),
    Points(Vec<[f32; 4]>),
}

impl Default for ColorMap {
    fn default() -> Self {
        ColorMap::Preset(Preset::Grayscale)
    }
}

impl ColorMap {
    /// The `(x, r, g, b)` control points.
    pub fn points(&self) -> &[[f32; 4]] {
        match self {
            ColorMap::Preset(p) => p.points(),
            ColorMap::Points(v) => v,
        }
    }

    /// Colour at `x` (clamped into `[0, 1]`): per channel exactly
    /// [`eval_piecewise`] of that channel, with one search for the segment.
    #[inline]
    pub fn color(&self, x: f32) -> [f32; 3] {
        let pts = self.points();
        color_in_segment(pts, pts.partition_point(|p| p[0] <= x), x)
    }
}

/// One linear piece `[x0, x1)` of a piecewise-linear function from `v0` to
/// `v1`, in the form every evaluation uses (so that a table of pieces gives
/// the same bits as evaluating from the points): `v0 + (x − x0)·slope`,
/// `slope = (v1 − v0)/(x1 − x0)`, clamped to `[min(v0, v1), max(v0, v1)]`.
/// Outside the points the function is constant: `slope = 0`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Piece {
    x0: f32,
    v0: f32,
    slope: f32,
    lo: f32,
    hi: f32,
}

impl Piece {
    #[inline(always)]
    fn new(x0: f32, x1: f32, v0: f32, v1: f32) -> Piece {
        Piece {
            x0,
            v0,
            // x0 <= x < x1 inside a piece, so x1 > x0.
            slope: (v1 - v0) / (x1 - x0),
            lo: v0.min(v1),
            hi: v0.max(v1),
        }
    }

    #[inline(always)]
    fn constant(v: f32) -> Piece {
        Piece {
            x0: 0.0,
            v0: v,
            slope: 0.0,
            lo: v,
            hi: v,
        }
    }

    /// The value at `x` (finite); the clamp keeps rounding inside the
    /// piece's range, which keeps `max_opacity` exactly conservative.
    #[inline(always)]
    fn at(&self, x: f32) -> f32 {
        let v = self.v0 + (x - self.x0) * self.slope;
        if v < self.lo {
            self.lo
        } else if v > self.hi {
            self.hi
        } else {
            v
        }
    }
}

/// Piece `i` (the result of `partition_point(p.x <= x)`) of the points
/// `pts` for the value `pv`.
#[inline(always)]
fn piece<P>(pts: &[P], i: usize, px: impl Fn(&P) -> f32, pv: impl Fn(&P) -> f32) -> Piece {
    if i == 0 {
        return Piece::constant(pv(&pts[0]));
    }
    if i == pts.len() {
        return Piece::constant(pv(&pts[i - 1]));
    }
    let (a, b) = (&pts[i - 1], &pts[i]);
    Piece::new(px(a), px(b), pv(a), pv(b))
}

/// The colour at `x` of colour-map points `pts` whose search for `x` gave
/// segment `i`: per channel what [`eval_piecewise`] gives, with one search.
#[inline]
fn color_in_segment(pts: &[[f32; 4]], i: usize, x: f32) -> [f32; 3] {
    [1, 2, 3].map(|c| piece(pts, i, |p| p[0], |p| p[c]).at(x))
}

/// Value of the piecewise-linear function through `pts` at `x`: constant
/// outside the points, right-continuous at steps, each segment's result
/// clamped between its end values (so that rounding can never leave the
/// segment's range, which keeps `max_opacity` exactly conservative).
#[inline]
fn eval_piecewise<P>(pts: &[P], x: f32, px: impl Fn(&P) -> f32, pv: impl Fn(&P) -> f32) -> f32 {
    let i = pts.partition_point(|p| px(p) <= x);
    eval_segment(pts, i, x, px, pv)
}

/// A transfer function. JSON (errors name the field):
///
/// ```json
/// {"window": [0, 1200], "opacity": [[0, 0], [0.2, 0], [1, 0.5]], "colormap": "bone"}
/// {"window": [0, 1], "opacity": [[0, 1]], "colormap": [[0, 0, 0, 1], [1, 1, 1, 0]]}
/// {"preset": "soft", "window": [-200, 900]}
/// ```
///
/// `colormap` defaults to grayscale; with `"preset"` (see
/// [`TransferFunction::PRESETS`]) `opacity` and `colormap` are optional
/// overrides of the preset's. `"shading"` (DVR only) turns gradient
/// shading on: `true` with the defaults of [`Shading`], or an object with
/// any of `ambient`, `diffuse`, `specular`, `shininess`
/// (`{"preset": "soft", "window": [0, 255], "shading": {"specular": 0.5}}`);
/// absent or `false`: off.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "serde_json::Value")]
pub struct TransferFunction {
    /// Data values `[w0, w1]` (`w0 < w1`) mapped to `x = 0` and `x = 1`.
    pub window: [f32; 2],
    /// `(x, alpha)` control points, `x` non-decreasing in `[0, 1]`.
    pub opacity: Vec<[f32; 2]>,
    pub colormap: ColorMap,
    /// DVR gradient shading (`None`: unshaded).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shading: Option<Shading>,
}

/// Gradient shading of DVR samples: Blinn–Phong with a light at the eye.
/// The normal is the normalized gradient of the sampled field (central
/// differences one voxel of the sample's level apart along each axis, on
/// the same clamped trilinear sampler); with the light and the eye along
/// the ray, a sample's colour `c` becomes
/// `c·(ambient + diffuse·|n·l|) + specular·|n·l|^shininess` (two-sided;
/// the half vector is the light direction), opacity unchanged. A zero
/// gradient leaves the colour as it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Shading {
    pub ambient: f32,
    pub diffuse: f32,
    pub specular: f32,
    pub shininess: f32,
}

impl Default for Shading {
    fn default() -> Shading {
        Shading {
            ambient: 0.3,
            diffuse: 0.7,
            specular: 0.2,
            shininess: 32.0,
        }
    }
}

impl TransferFunction {
    /// Names accepted by [`TransferFunction::preset`].
    pub const PRESETS: [&'static str; 6] =
        ["linear", "soft", "hot", "viridis", "coolwarm", "opaque"];

    /// A validated transfer function.
    pub fn new(
        window: [f32; 2],
        opacity: Vec<[f32; 2]>,
        colormap: ColorMap,
    ) -> Result<TransferFunction, ConfigError> {
        let tf = TransferFunction {
            window,
            opacity,
            colormap,
            shading: None,
        };
        tf.validate()?;
        Ok(tf)
    }

    /// A named transfer function over `window`:
    ///
    /// | name | colour map | opacity |
    /// |---|---|---|
    /// | `linear` | grayscale | 0 → 1 over the window |
    /// | `soft` | bone | 0 up to x = 0.15, then → 0.35 |
    /// | `hot` | hot | 0 up to x = 0.1, then → 0.8 |
    /// | `viridis` | viridis | 0 up to x = 0.1, then → 0.6 |
    /// | `coolwarm` | coolwarm | 0.6 at both ends, 0 over x ∈ [0.4, 0.6] |
    /// | `opaque` | grayscale | 1 everywhere (slices, MIP) |
    pub fn preset(name: &str, window: [f32; 2]) -> Result<TransferFunction, ConfigError> {
        let (cm, op): (Preset, &[[f32; 2]]) = match name.trim().to_ascii_lowercase().as_str() {
            "linear" => (Preset::Grayscale, &[[0.0, 0.0], [1.0, 1.0]]),
            "soft" => (Preset::Bone, &[[0.0, 0.0], [0.15, 0.0], [1.0, 0.35]]),
            "hot" => (Preset::Hot, &[[0.0, 0.0], [0.1, 0.0], [1.0, 0.8]]),
            "viridis" => (Preset::Viridis, &[[0.0, 0.0], [0.1, 0.0], [1.0, 0.6]]),
            "coolwarm" => (
                Preset::Coolwarm,
                &[[0.0, 0.6], [0.4, 0.0], [0.6, 0.0], [1.0, 0.6]],
            ),
            "opaque" => (Preset::Grayscale, &[[0.0, 1.0]]),
            other => {
                return Err(ConfigError::new(
                    WHAT,
                    "preset",
                    format!(
                        "unknown preset {other:?}; expected one of {:?}",
                        Self::PRESETS
                    ),
                ))
            }
        };
        TransferFunction::new(window, op.to_vec(), ColorMap::Preset(cm))
    }

    /// A window `[level − width/2, level + width/2]` from window/level
    /// (centre/width) as radiology viewers give it.
    pub fn window_level(level: f32, width: f32) -> [f32; 2] {
        [level - 0.5 * width, level + 0.5 * width]
    }

    /// A default for data of type `dtype` whose values span `[min, max]`
    /// (from the store's statistics): window `[min, max]`, grayscale,
    /// opacity 0 over the lowest 10 % of the window (background, noise)
    /// then rising linearly to 0.5. When the range is unusable (NaN,
    /// infinite, or `max ≤ min`): a constant finite `min` gets
    /// `[min, min + 1]`, anything else the type's full range (`[0, 1]`
    /// for floating-point types).
    pub fn default_for(dtype: DType, min: f64, max: f64) -> TransferFunction {
        let (lo, hi) = if min.is_finite() && max.is_finite() && max > min {
            (min, max)
        } else if min.is_finite() && (max.is_nan() || max <= min) && !max.is_infinite() {
            (min, min + 1.0)
        } else {
            match dtype {
                DType::U8 => (0.0, 255.0),
                DType::I8 => (-128.0, 127.0),
                DType::U16 => (0.0, 65535.0),
                DType::I16 => (-32768.0, 32767.0),
                DType::U32 => (0.0, u32::MAX as f64),
                DType::I32 => (i32::MIN as f64, i32::MAX as f64),
                DType::F32 | DType::F64 => (0.0, 1.0),
            }
        };
        let mut w = [lo as f32, hi as f32];
        if w[1] <= w[0] {
            // The range collapsed in f32.
            w[1] = w[0] + (w[0].abs() * 1e-6).max(1.0);
        }
        TransferFunction {
            window: w,
            opacity: vec![[0.0, 0.0], [0.1, 0.0], [1.0, 0.5]],
            colormap: ColorMap::default(),
            shading: None,
        }
    }

    /// The windowed value `x = clamp((v − w0) / (w1 − w0), 0, 1)` (NaN
    /// stays NaN). Monotone non-decreasing in `v`.
    #[inline]
    pub fn normalize(&self, value: f32) -> f32 {
        let [w0, w1] = self.window;
        ((value - w0) * (1.0 / (w1 - w0))).clamp(0.0, 1.0)
    }

    /// Opacity at the windowed value `x`.
    #[inline]
    pub fn opacity_at(&self, x: f32) -> f32 {
        eval_piecewise(&self.opacity, x, |p| p[0], |p| p[1])
    }

    /// `[r, g, b, alpha]` (straight alpha) of the data value `value`;
    /// NaN gives `[0, 0, 0, 0]`.
    #[inline]
    pub fn lookup(&self, value: f32) -> [f32; 4] {
        if value.is_nan() {
            return [0.0; 4];
        }
        let x = self.normalize(value);
        let [r, g, b] = self.colormap.color(x);
        [r, g, b, self.opacity_at(x)]
    }

    /// [`lookup`](Self::lookup) for values it gives a positive opacity,
    /// `None` for the rest (NaN included), without computing their colour:
    /// what front-to-back compositing needs, as it ignores transparent
    /// samples.
    #[inline]
    pub fn lookup_visible(&self, value: f32) -> Option<[f32; 4]> {
        if value.is_nan() {
            return None;
        }
        let x = self.normalize(value);
        let a = self.opacity_at(x);
        if a > 0.0 {
            let [r, g, b] = self.colormap.color(x);
            Some([r, g, b, a])
        } else {
            None
        }
    }

    /// `n` entries of `lookup` at the windowed values `x_i = i / (n − 1)`
    /// (for `n = 1`: `x = 0`), i.e. index `round(x · (n − 1))`.
    pub fn lut(&self, n: usize) -> Vec<[f32; 4]> {
        (0..n)
            .map(|i| {
                let x = if n > 1 {
                    i as f32 / (n - 1) as f32
                } else {
                    0.0
                };
                let [r, g, b] = self.colormap.color(x);
                [r, g, b, self.opacity_at(x)]
            })
            .collect()
    }

    /// The largest opacity [`lookup`](Self::lookup) gives to any value in
    /// `[lo, hi]` (order does not matter). Exactly conservative: never
    /// smaller than `lookup(v)[3]` for any `v` in the interval, and equal to
    /// the largest control-point or end-point opacity in it (a step inside
    /// the interval counts both its values). Renderers skip a brick whose
    /// value range gets 0 here. A NaN bound gives the maximum over all
    /// values.
    pub fn max_opacity(&self, lo: f32, hi: f32) -> f32 {
        let all = || self.opacity.iter().map(|p| p[1]).fold(0.0f32, f32::max);
        if lo.is_nan() || hi.is_nan() {
            return all();
        }
        let (lo, hi) = if lo <= hi { (lo, hi) } else { (hi, lo) };
        self.max_opacity_x(self.normalize(lo), self.normalize(hi))
    }

    /// The largest opacity at any windowed value in `[xa, xb]` (`xa ≤ xb`),
    /// exactly conservative as [`max_opacity`](Self::max_opacity).
    fn max_opacity_x(&self, xa: f32, xb: f32) -> f32 {
        let mut m = self.opacity_at(xa).max(self.opacity_at(xb));
        for p in &self.opacity {
            if p[0] >= xa && p[0] <= xb {
                m = m.max(p[1]);
            }
        }
        m
    }

    /// Check the window and the control points.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let [w0, w1] = self.window;
        if !(w0.is_finite() && w1.is_finite()) {
            return Err(ConfigError::new(
                WHAT,
                "window",
                format!(
                    "must be finite numbers within ±3.4e38 (single precision), got {:?}",
                    self.window
                ),
            ));
        }
        if w0 >= w1 {
            return Err(ConfigError::new(
                WHAT,
                "window",
                format!("needs window[0] < window[1], got {:?}", self.window),
            ));
        }
        check_points(
            "opacity",
            self.opacity.iter().map(|p| (p[0], &p[1..])),
            "alpha",
        )?;
        if let ColorMap::Points(v) = &self.colormap {
            check_points("colormap", v.iter().map(|p| (p[0], &p[1..])), "r, g, b")?;
        }
        if let Some(sh) = &self.shading {
            for (k, x) in [
                ("ambient", sh.ambient),
                ("diffuse", sh.diffuse),
                ("specular", sh.specular),
            ] {
                if !(x.is_finite() && x >= 0.0) {
                    return Err(ConfigError::new(
                        WHAT,
                        &format!("shading.{k}"),
                        format!("must be a finite number ≥ 0, got {x}"),
                    ));
                }
            }
            if !(sh.shininess.is_finite() && sh.shininess >= 1.0) {
                return Err(ConfigError::new(
                    WHAT,
                    "shading.shininess",
                    format!("must be a finite number ≥ 1, got {}", sh.shininess),
                ));
            }
        }
        Ok(())
    }

    /// Parse from JSON (see the type's docs); errors name the field.
    pub fn from_json(s: &str) -> Result<TransferFunction, ConfigError> {
        let v: Value = serde_json::from_str(s).map_err(|e| ConfigError::syntax(WHAT, &e))?;
        TransferFunction::try_from(v)
    }

    /// Pretty JSON that [`TransferFunction::from_json`] reads back.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a transfer function always serializes")
    }
}

fn check_points<'a>(
    field: &str,
    pts: impl Iterator<Item = (f32, &'a [f32])>,
    vname: &str,
) -> Result<(), ConfigError> {
    let mut prev = f32::NEG_INFINITY;
    let mut n = 0;
    for (i, (x, vals)) in pts.enumerate() {
        n += 1;
        let f = format!("{field}[{i}]");
        if !(0.0..=1.0).contains(&x) {
            return Err(ConfigError::new(
                WHAT,
                &f,
                format!("x = {x} is outside [0, 1] (x is the windowed value)"),
            ));
        }
        if x < prev {
            return Err(ConfigError::new(
                WHAT,
                &f,
                format!("x values must be non-decreasing, got {x} after {prev}"),
            ));
        }
        if vals.iter().any(|v| !(0.0..=1.0).contains(v)) {
            return Err(ConfigError::new(
                WHAT,
                &f,
                format!("{vname} must be in [0, 1], got {vals:?}"),
            ));
        }
        prev = x;
    }
    if n == 0 {
        return Err(ConfigError::new(
            WHAT,
            field,
            "needs at least one control point",
        ));
    }
    Ok(())
}

fn parse_points<const N: usize>(
    o: &Fields,
    field: &str,
    v: &Value,
    example: &str,
) -> Result<Vec<[f32; N]>, ConfigError> {
    let a = v.as_array().ok_or_else(|| {
        o.err(
            field,
            format!(
                "expected an array of control points like {example}, got {}",
                brief(v)
            ),
        )
    })?;
    a.iter()
        .enumerate()
        .map(|(i, p)| {
            o.numbers::<N>(&format!("{field}[{i}]"), p)
                .map(|x| x.map(|c| c as f32))
        })
        .collect()
}

/// `"shading"`: `true`, `false` or an object of [`Shading`]'s fields.
fn parse_shading(o: &Fields, v: &Value) -> Result<Option<Shading>, ConfigError> {
    if let Some(b) = v.as_bool() {
        return Ok(b.then(Shading::default));
    }
    let keys = ["ambient", "diffuse", "specular", "shininess"];
    let s = Fields::new("transfer function shading", v, &keys).map_err(|_| {
        o.err(
            "shading",
            format!(
                "expected true, false or an object with {keys:?}, got {}",
                brief(v)
            ),
        )
    })?;
    let mut sh = Shading::default();
    for (k, dst) in keys.iter().zip([
        &mut sh.ambient,
        &mut sh.diffuse,
        &mut sh.specular,
        &mut sh.shininess,
    ]) {
        if let Some(x) = s.obj.get(*k) {
            *dst = x.as_f64().ok_or_else(|| {
                o.err(
                    &format!("shading.{k}"),
                    format!("expected a number, got {}", brief(x)),
                )
            })? as f32;
        }
    }
    Ok(Some(sh))
}

fn parse_colormap(o: &Fields, v: &Value) -> Result<ColorMap, ConfigError> {
    match v {
        Value::String(s) => Preset::parse(s).map(ColorMap::Preset).ok_or_else(|| {
            o.err(
                "colormap",
                format!(
                    "unknown colour map {s:?}; expected one of {:?} or an array of [x, r, g, b] points",
                    Preset::ALL.map(Preset::name)
                ),
            )
        }),
        _ => parse_points::<4>(o, "colormap", v, "[[0, 0, 0, 0], [1, 1, 1, 1]]").map(ColorMap::Points),
    }
}

impl TryFrom<Value> for TransferFunction {
    type Error = ConfigError;
    fn try_from(v: Value) -> Result<TransferFunction, ConfigError> {
        let o = Fields::new(
            WHAT,
            &v,
            &["preset", "window", "opacity", "colormap", "shading"],
        )?;
        let w = o.numbers::<2>("window", o.required("window")?)?;
        let window = [w[0] as f32, w[1] as f32];
        let mut tf = match o.obj.get("preset") {
            Some(p) => {
                let name = p.as_str().ok_or_else(|| {
                    o.err(
                        "preset",
                        format!("expected a preset name, got {}", brief(p)),
                    )
                })?;
                // Validate the window first so a bad one is reported as such.
                TransferFunction {
                    window,
                    opacity: vec![[0.0, 0.0]],
                    colormap: ColorMap::default(),
                    shading: None,
                }
                .validate()?;
                TransferFunction::preset(name, window)?
            }
            None => TransferFunction {
                window,
                opacity: Vec::new(),
                colormap: ColorMap::default(),
                shading: None,
            },
        };
        match o.obj.get("opacity") {
            Some(v) => tf.opacity = parse_points::<2>(&o, "opacity", v, "[[0, 0], [1, 0.5]]")?,
            None if o.obj.get("preset").is_none() => return Err(o.missing("opacity")),
            None => {}
        }
        if let Some(v) = o.obj.get("colormap") {
            tf.colormap = parse_colormap(&o, v)?;
        }
        if let Some(v) = o.obj.get("shading") {
            tf.shading = parse_shading(&o, v)?;
        }
        tf.validate()?;
        Ok(tf)
    }
}

impl TryFrom<Value> for ColorMap {
    type Error = ConfigError;
    fn try_from(v: Value) -> Result<ColorMap, ConfigError> {
        let wrapper = serde_json::json!({});
        let o = Fields::new(WHAT, &wrapper, &[])?;
        let cm = parse_colormap(&o, &v)?;
        if let ColorMap::Points(p) = &cm {
            check_points("colormap", p.iter().map(|p| (p[0], &p[1..])), "r, g, b")?;
        }
        Ok(cm)
    }
}

/// Bins of a [`TfEval`] segment table.
const TF_BINS: usize = 1024;

/// For each of [`TF_BINS`] equal bins of `x ∈ [0, 1]`: the segment index
/// `partition_point(p.x <= x)` that every `x` of the bin has, or
/// `u16::MAX` where a control point lies in or near the bin (those `x` are
/// searched as usual).
fn segment_table(xs: impl Iterator<Item = f32> + Clone) -> Vec<u16> {
    let n = TF_BINS as f32;
    (0..TF_BINS)
        .map(|b| {
            // A margin of a few ulps around the bin's edges covers any
            // rounding of `x · TF_BINS`.
            let lo = b as f32 / n - 1e-6;
            let hi = (b + 1) as f32 / n + 1e-6;
            if xs.clone().any(|x| x >= lo && x <= hi) {
                u16::MAX
            } else {
                xs.clone()
                    .filter(|&x| x < lo)
                    .count()
                    .min(u16::MAX as usize - 1) as u16
            }
        })
        .collect()
}

/// The bin of a windowed value `x ∈ [0, 1]` (NaN, from a degenerate
/// window, gives the last).
#[inline(always)]
fn bin_of(x: f32) -> usize {
    debug_assert!(x.is_nan() || (0.0..=1.0).contains(&x));
    // `y < last` is false for NaN: after the two selects (a min and a max)
    // y is finite and in [0, TF_BINS − 1] whatever `x` is.
    let last = (TF_BINS - 1) as f32;
    let y = x * TF_BINS as f32;
    let y = if y < last { y } else { last };
    let y = if y > 0.0 { y } else { 0.0 };
    // SAFETY: `y` is finite and in [0, TF_BINS − 1], which i32 holds.
    // (Unchecked: one conversion instruction instead of a saturating
    // conversion and a clamp.)
    let b = unsafe { y.to_int_unchecked::<i32>() } as usize;
    // (The mask proves the range to the compiler: no bounds checks.)
    b & (TF_BINS - 1)
}

// `bin_of` masks with `TF_BINS − 1`.
const _: () = assert!(TF_BINS.is_power_of_two());

/// Per bin of the windowed values: what [`TfEval::lookup_visible`] needs
/// first, in one load.
#[derive(Debug, Clone, Copy)]
struct Bin {
    /// The opacity's and the colour map's segment for every `x` of the bin
    /// (`u16::MAX`: a control point lies in the bin, search).
    opacity_seg: u16,
    color_seg: u16,
    /// Every `x` of the bin has opacity 0, so the lookup ends there.
    clear: bool,
}

/// A transfer function prepared for many lookups (one per frame): the
/// same results as [`TransferFunction::lookup_visible`], bit for bit, with
/// the control-point searches replaced by a table of segments.
#[derive(Debug, Clone)]
pub struct TfEval<'a> {
    tf: &'a TransferFunction,
    /// `1 / (w1 − w0)`, as [`TransferFunction::normalize`] computes it.
    inv_width: f32,
    bins: Box<[Bin; TF_BINS]>,
    /// Bins not `clear` before bin `i` (`TF_BINS + 1` entries).
    open_before: Vec<u32>,
    /// The pieces of the opacity and of the colour map's three channels,
    /// by segment index.
    opacity_pieces: Vec<Piece>,
    color_pieces: Vec<[Piece; 3]>,
}

impl TransferFunction {
    /// An evaluator for many lookups.
    pub fn evaluator(&self) -> TfEval<'_> {
        let op = &self.opacity;
        let cm = self.colormap.points();
        let opacity_seg = segment_table(op.iter().map(|p| p[0]));
        let opacity_pieces: Vec<Piece> = (0..=op.len())
            .map(|i| piece(op, i, |p| p[0], |p| p[1]))
            .collect();
        // The windowed values of bin b are in [b/n, (b+1)/n] (x·n is exact).
        let n = TF_BINS as f32;
        let clear: Vec<bool> = (0..TF_BINS)
            .map(|b| self.max_opacity_x(b as f32 / n, (b + 1) as f32 / n) <= 0.0)
            .collect();
        let open_before = std::iter::once(0)
            .chain(clear.iter().scan(0u32, |n, &c| {
                *n += !c as u32;
                Some(*n)
            }))
            .collect();
        let color_seg = segment_table(cm.iter().map(|p| p[0]));
        let bins = Box::new(std::array::from_fn(|b| Bin {
            opacity_seg: opacity_seg[b],
            color_seg: color_seg[b],
            clear: clear[b],
        }));
        TfEval {
            tf: self,
            inv_width: 1.0 / (self.window[1] - self.window[0]),
            bins,
            open_before,
            opacity_pieces,
            color_pieces: (0..=cm.len())
                .map(|i| [1, 2, 3].map(|c| piece(cm, i, |p| p[0], |p| p[c])))
                .collect(),
        }
    }
}

/// [`eval_piecewise`]'s value of segment `i` (the result of its search).
#[inline(always)]
fn eval_segment<P>(
    pts: &[P],
    i: usize,
    x: f32,
    px: impl Fn(&P) -> f32,
    pv: impl Fn(&P) -> f32,
) -> f32 {
    piece(pts, i, px, pv).at(x)
}

impl TfEval<'_> {
    /// Whether some value in `[lo, hi]` (either order) may be visible: when
    /// this is false, [`lookup_visible`](Self::lookup_visible) gives `None`
    /// for every value in it. A constant-time, conservative
    /// [`TransferFunction::max_opacity`] (it may say true for a range that
    /// is transparent, by the resolution of its bins). A NaN bound: true.
    #[inline]
    pub fn range_visible(&self, lo: f32, hi: f32) -> bool {
        if lo.is_nan() || hi.is_nan() {
            return true;
        }
        let (lo, hi) = if lo <= hi { (lo, hi) } else { (hi, lo) };
        let (b0, b1) = (bin_of(self.windowed(lo)), bin_of(self.windowed(hi)));
        self.open_before[b1 + 1] > self.open_before[b0]
    }

    /// The colour `[r, g, b]` of [`TransferFunction::lookup`] for a value
    /// that is not NaN, exactly (a slice's pixel).
    #[inline(always)]
    pub fn color(&self, value: f32) -> [f32; 3] {
        let x = self.windowed(value);
        self.color_at(x, self.bins[bin_of(x)])
    }

    /// The windowed value `x ∈ [0, 1]` of a data value, as
    /// [`TransferFunction::normalize`] computes it.
    #[inline(always)]
    fn windowed(&self, value: f32) -> f32 {
        ((value - self.tf.window[0]) * self.inv_width).clamp(0.0, 1.0)
    }

    /// The colour map at the windowed value `x`, whose bin is `bin`.
    #[inline(always)]
    fn color_at(&self, x: f32, bin: Bin) -> [f32; 3] {
        let i = match bin.color_seg {
            u16::MAX => self.tf.colormap.points().partition_point(|p| p[0] <= x),
            s => s as usize,
        };
        let [r, g, b] = &self.color_pieces[i];
        [r.at(x), g.at(x), b.at(x)]
    }

    /// Exactly [`TransferFunction::lookup_visible`].
    #[inline(always)]
    pub fn lookup_visible(&self, value: f32) -> Option<[f32; 4]> {
        if value.is_nan() {
            return None;
        }
        let x = self.windowed(value);
        let bin = self.bins[bin_of(x)];
        if bin.clear {
            return None;
        }
        let i = match bin.opacity_seg {
            u16::MAX => self.tf.opacity.partition_point(|p| p[0] <= x),
            s => s as usize,
        };
        let a = self.opacity_pieces[i].at(x);
        if a <= 0.0 {
            return None;
        }
        let [r, g, b] = self.color_at(x, bin);
        Some([r, g, b, a])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    fn tf(opacity: Vec<[f32; 2]>) -> TransferFunction {
        TransferFunction::new([100.0, 300.0], opacity, ColorMap::default()).unwrap()
    }

    #[test]
    fn evaluator_equals_lookup_visible_and_lookup_bit_for_bit() {
        let mut tfs: Vec<TransferFunction> = TransferFunction::PRESETS
            .iter()
            .map(|p| TransferFunction::preset(p, [-3.0, 1000.0]).unwrap())
            .collect();
        // Steps, points on bin edges, many points.
        tfs.push(
            TransferFunction::new(
                [0.0, 1.0],
                vec![
                    [0.0, 0.0],
                    [0.25, 0.0],
                    [0.25, 0.5],
                    [0.5, 1.0],
                    [0.75, 0.0],
                    [1.0, 0.3],
                ],
                ColorMap::Points(vec![
                    [0.0, 1.0, 0.0, 0.0],
                    [0.5, 0.0, 1.0, 0.0],
                    [0.5, 0.0, 0.0, 1.0],
                    [1.0, 1.0, 1.0, 1.0],
                ]),
            )
            .unwrap(),
        );
        let mut seed = 7u64;
        for tf in &tfs {
            let ev = tf.evaluator();
            let [w0, w1] = tf.window;
            let mut xs: Vec<f32> = (0..=20_000)
                .map(|k| w0 - 5.0 + (w1 - w0 + 10.0) * k as f32 / 20_000.0)
                .collect();
            for p in tf
                .opacity
                .iter()
                .map(|p| p[0])
                .chain(tf.colormap.points().iter().map(|p| p[0]))
            {
                let v = w0 + p * (w1 - w0);
                xs.extend([v, v.next_up(), v.next_down()]);
            }
            for _ in 0..20_000 {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                xs.push(w0 + (w1 - w0) * ((seed >> 40) as f32 / (1u64 << 24) as f32));
            }
            xs.push(f32::NAN);
            for v in xs {
                let (a, b) = (ev.lookup_visible(v), tf.lookup_visible(v));
                assert_eq!(
                    a.map(|c| c.map(f32::to_bits)),
                    b.map(|c| c.map(f32::to_bits)),
                    "{v}"
                );
                // The colour alone, also where the opacity is 0.
                if !v.is_nan() {
                    let [r, g, b, _] = tf.lookup(v);
                    assert_eq!(
                        ev.color(v).map(f32::to_bits),
                        [r, g, b].map(f32::to_bits),
                        "{v}"
                    );
                }
            }
        }
    }

    #[test]
    fn range_visible_is_conservative_and_close_to_max_opacity() {
        let mut rnd = Lcg(99);
        let mut tfs: Vec<TransferFunction> = TransferFunction::PRESETS
            .iter()
            .map(|p| TransferFunction::preset(p, [0.0, 255.0]).unwrap())
            .collect();
        tfs.push(tf(vec![
            [0.0, 0.0],
            [0.3, 0.0],
            [0.31, 0.5],
            [0.6, 0.0],
            [1.0, 0.0],
        ]));
        let (mut agree, mut total) = (0, 0);
        for tf in &tfs {
            let ev = tf.evaluator();
            let [w0, w1] = tf.window;
            for _ in 0..20_000 {
                let a = w0 - 10.0 + (w1 - w0 + 20.0) * rnd.next();
                let b = a + (w1 - w0) * 0.2 * rnd.next() * rnd.next();
                let visible = ev.range_visible(a, b);
                let max = tf.max_opacity(a, b);
                if !visible {
                    assert!(max <= 0.0, "[{a}, {b}]: said clear, max opacity {max}");
                    for i in 0..=16 {
                        let v = a + (b - a) * i as f32 / 16.0;
                        assert!(ev.lookup_visible(v).is_none(), "{v} in [{a}, {b}]");
                    }
                }
                total += 1;
                agree += (visible == (max > 0.0)) as u32;
            }
            assert!(ev.range_visible(f32::NAN, 1.0));
        }
        // Conservative only near the edges of the transparent ranges.
        assert!(agree * 100 > total * 95, "{agree} of {total}");
        // "soft": transparent up to 15 % of the window.
        let soft = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
        let ev = soft.evaluator();
        assert!(!ev.range_visible(0.0, 30.0));
        assert!(ev.range_visible(0.0, 60.0));
    }

    #[test]
    fn one_search_colour_equals_per_channel_evaluation() {
        for p in Preset::ALL {
            let pts = p.points();
            for k in 0..=1000 {
                let x = k as f32 / 1000.0 - 0.01;
                let want = [1, 2, 3].map(|c| eval_piecewise(pts, x, |p| p[0], |p| p[c]));
                assert_eq!(ColorMap::Preset(p).color(x), want, "{p:?} at {x}");
            }
        }
    }

    #[test]
    fn lookup_at_and_between_control_points() {
        let t = TransferFunction::new(
            [100.0, 300.0],
            vec![[0.0, 0.0], [0.25, 0.0], [0.5, 0.8], [1.0, 0.4]],
            ColorMap::Points(vec![[0.0, 0.0, 0.0, 1.0], [1.0, 1.0, 0.5, 0.0]]),
        )
        .unwrap();
        // At control points (value = 100 + 200 x), exactly.
        assert_eq!(t.lookup(100.0), [0.0, 0.0, 1.0, 0.0]);
        assert_eq!(t.lookup(150.0)[3], 0.0);
        assert_eq!(t.lookup(200.0), [0.5, 0.25, 0.5, 0.8]);
        assert_eq!(t.lookup(300.0), [1.0, 0.5, 0.0, 0.4]);
        // Between: linear.
        assert!((t.lookup(175.0)[3] - 0.4).abs() < 1e-6);
        assert!((t.lookup(250.0)[3] - 0.6).abs() < 1e-6);
        assert!((t.lookup(250.0)[0] - 0.75).abs() < 1e-6);
        // Outside the window: clamped.
        assert_eq!(t.lookup(-1e9), t.lookup(100.0));
        assert_eq!(t.lookup(1e9), t.lookup(300.0));
        assert_eq!(t.lookup(f32::NAN), [0.0; 4]);
        // Constant outside the points.
        let t = tf(vec![[0.2, 0.3], [0.6, 0.9]]);
        assert_eq!(t.lookup(100.0)[3], 0.3);
        assert_eq!(t.lookup(130.0)[3], 0.3);
        assert_eq!(t.lookup(290.0)[3], 0.9);
        // A single point: constant.
        assert_eq!(tf(vec![[0.5, 0.7]]).lookup(123.0)[3], 0.7);
    }

    #[test]
    fn steps_take_the_later_value() {
        let t = tf(vec![[0.0, 0.0], [0.5, 0.0], [0.5, 1.0], [1.0, 1.0]]);
        assert_eq!(t.lookup(199.99)[3], 0.0);
        assert_eq!(t.lookup(200.0)[3], 1.0);
        assert_eq!(t.max_opacity(150.0, 200.0), 1.0);
        assert_eq!(t.max_opacity(150.0, 199.0), 0.0);
    }

    #[test]
    fn max_opacity_is_conservative_and_tight() {
        let mut r = Lcg(7);
        for case in 0..300 {
            // A random TF with some zero runs and steps.
            let n = 1 + (r.next() * 6.0) as usize;
            let mut xs: Vec<f32> = (0..n).map(|_| r.next()).collect();
            xs.sort_by(|a, b| a.partial_cmp(b).unwrap());
            if n > 2 && case % 3 == 0 {
                xs[2] = xs[1];
            }
            let op: Vec<[f32; 2]> = xs
                .iter()
                .map(|&x| [x, if r.next() < 0.4 { 0.0 } else { r.next() }])
                .collect();
            let t = TransferFunction::new([-50.0, 1000.0], op, ColorMap::default()).unwrap();
            for _ in 0..40 {
                let a = r.next() * 1200.0 - 100.0;
                let b = a + r.next() * r.next() * 400.0;
                let m = t.max_opacity(a, b);
                assert_eq!(m, t.max_opacity(b, a));
                // Dense sampling, the end points and their neighbours included.
                let mut dense = 0.0f32;
                let steps = 2000;
                for k in 0..=steps {
                    let v = a + (b - a) * k as f32 / steps as f32;
                    let v = v.clamp(a, b);
                    dense = dense.max(t.lookup(v)[3]);
                }
                for v in [a, b, a.next_up(), b.next_down()] {
                    if v >= a && v <= b {
                        dense = dense.max(t.lookup(v)[3]);
                    }
                }
                assert!(
                    m >= dense,
                    "not conservative: {m} < {dense} on [{a}, {b}] {t:?}"
                );
                // Tight: the excess comes only from control points inside
                // the interval, which dense sampling may step over.
                let mut upper = dense;
                for p in &t.opacity {
                    let v = -50.0 + p[0] * 1050.0;
                    if v >= a - 1e-3 && v <= b + 1e-3 {
                        upper = upper.max(p[1]);
                    }
                }
                assert!(m <= upper, "too large: {m} > {upper} on [{a}, {b}]");
            }
            // Exact at single values and at control points.
            for p in &t.opacity {
                let v = -50.0 + p[0] * 1050.0;
                assert!(t.max_opacity(v - 1e-3, v + 1e-3) >= p[1]);
            }
            for _ in 0..50 {
                let v = r.next() * 1200.0 - 100.0;
                assert_eq!(t.max_opacity(v, v), t.lookup(v)[3]);
            }
        }
        // Zero opacity over the whole range: the brick can be skipped.
        let t = tf(vec![[0.0, 0.0], [0.5, 0.0], [1.0, 1.0]]);
        assert_eq!(t.max_opacity(-1e6, 200.0), 0.0);
        assert!(t.max_opacity(-1e6, 200.01) > 0.0);
        assert_eq!(t.max_opacity(f32::NAN, 0.0), 1.0);
    }

    #[test]
    fn lut_and_presets() {
        let t = TransferFunction::preset("hot", [0.0, 10.0]).unwrap();
        let l = t.lut(256);
        assert_eq!(l.len(), 256);
        assert_eq!(l[0], t.lookup(0.0));
        assert_eq!(l[255], t.lookup(10.0));
        assert_eq!(l[255], [1.0, 1.0, 1.0, 0.8]);
        for name in TransferFunction::PRESETS {
            let t = TransferFunction::preset(name, [0.0, 1.0]).unwrap();
            t.validate().unwrap();
            assert_eq!(TransferFunction::from_json(&t.to_json()).unwrap(), t);
        }
        assert!(TransferFunction::preset("nope", [0.0, 1.0])
            .unwrap_err()
            .to_string()
            .contains("`preset`"));
        for p in Preset::ALL {
            assert_eq!(Preset::parse(p.name()), Some(p));
            let cm = ColorMap::Preset(p);
            TransferFunction::new([0.0, 1.0], vec![[0.0, 1.0]], cm.clone())
                .unwrap()
                .validate()
                .unwrap();
            let (c0, c1) = (cm.color(0.0), cm.color(1.0));
            assert!(c0.iter().chain(&c1).all(|v| (0.0..=1.0).contains(v)));
        }
        assert_eq!(ColorMap::Preset(Preset::Grayscale).color(0.25), [0.25; 3]);
        assert_eq!(ColorMap::Preset(Preset::Hot).color(0.375), [1.0, 0.0, 0.0]);
        assert_eq!(TransferFunction::window_level(40.0, 400.0), [-160.0, 240.0]);
    }

    #[test]
    fn default_for_uses_the_data_range() {
        let t = TransferFunction::default_for(DType::I16, -1000.0, 3000.0);
        assert_eq!(t.window, [-1000.0, 3000.0]);
        assert_eq!(t.lookup(-1000.0)[3], 0.0);
        assert_eq!(t.lookup(3000.0)[3], 0.5);
        assert_eq!(t.max_opacity(-1000.0, -600.0), 0.0);
        t.validate().unwrap();
        // Constant data, unusable ranges.
        assert_eq!(
            TransferFunction::default_for(DType::U8, 7.0, 7.0).window,
            [7.0, 8.0]
        );
        assert_eq!(
            TransferFunction::default_for(DType::U16, f64::NAN, f64::NAN).window,
            [0.0, 65535.0]
        );
        assert_eq!(
            TransferFunction::default_for(DType::F32, f64::NEG_INFINITY, 1.0).window,
            [0.0, 1.0]
        );
        let t = TransferFunction::default_for(DType::F32, 1e30, 1e30 * (1.0 + 1e-12));
        t.validate().unwrap();
    }

    #[test]
    fn json_round_trip() {
        let cases = [
            TransferFunction::new(
                [-3.5, 1e4],
                vec![[0.0, 0.0], [0.3, 0.5], [0.3, 0.25], [1.0, 1.0]],
                ColorMap::Preset(Preset::Viridis),
            )
            .unwrap(),
            TransferFunction::new(
                [0.0, 1.0],
                vec![[0.5, 1.0]],
                ColorMap::Points(vec![[0.0, 0.0, 0.5, 1.0], [1.0, 1.0, 0.5, 0.0]]),
            )
            .unwrap(),
        ];
        for t in cases {
            let s = t.to_json();
            assert_eq!(TransferFunction::from_json(&s).unwrap(), t, "{s}");
            assert_eq!(serde_json::from_str::<TransferFunction>(&s).unwrap(), t);
        }
        // A preset with overrides.
        let t = TransferFunction::from_json(
            r#"{"preset": "soft", "window": [0, 10], "colormap": "hot"}"#,
        )
        .unwrap();
        assert_eq!(t.colormap, ColorMap::Preset(Preset::Hot));
        assert_eq!(
            t.opacity,
            TransferFunction::preset("soft", [0.0, 10.0])
                .unwrap()
                .opacity
        );
        let t = TransferFunction::from_json(r#"{"window": [0, 10], "opacity": [[0, 1]]}"#).unwrap();
        assert_eq!(t.colormap, ColorMap::Preset(Preset::Grayscale));
        let cm: ColorMap = serde_json::from_str(r#""bone""#).unwrap();
        assert_eq!(cm, ColorMap::Preset(Preset::Bone));
        let cm: ColorMap = serde_json::from_str("[[0, 1, 1, 1]]").unwrap();
        assert_eq!(cm, ColorMap::Points(vec![[0.0, 1.0, 1.0, 1.0]]));
    }

    /// Shading: off when absent or `false`, the defaults with `true`, an
    /// object overrides some fields; it survives a round trip; bad values
    /// name their field.
    #[test]
    fn shading_in_json() {
        let base = r#""preset": "soft", "window": [0, 10]"#;
        let tf = |extra: &str| TransferFunction::from_json(&format!("{{{base}{extra}}}"));
        assert_eq!(tf("").unwrap().shading, None);
        assert_eq!(tf(r#", "shading": false"#).unwrap().shading, None);
        assert_eq!(
            tf(r#", "shading": true"#).unwrap().shading,
            Some(Shading::default())
        );
        let t = tf(r#", "shading": {"specular": 0.5, "shininess": 8}"#).unwrap();
        let want = Shading {
            specular: 0.5,
            shininess: 8.0,
            ..Shading::default()
        };
        assert_eq!(t.shading, Some(want));
        assert_eq!(TransferFunction::from_json(&t.to_json()).unwrap(), t);
        assert!(!tf("").unwrap().to_json().contains("shading"));
        for (extra, field) in [
            (r#", "shading": {"diffuse": -1}"#, "shading.diffuse"),
            (r#", "shading": {"shininess": 0.5}"#, "shading.shininess"),
            (r#", "shading": {"gloss": 1}"#, "shading"),
            (r#", "shading": {"ambient": "x"}"#, "shading.ambient"),
            (r#", "shading": 3"#, "shading"),
        ] {
            let e = tf(extra).unwrap_err().to_string();
            assert!(e.contains(field), "{extra}: {e}");
        }
    }

    #[test]
    fn bad_json_names_the_field() {
        let cases = [
            (r#"{"opacity": [[0, 1]]}"#, "`window`", "missing"),
            (
                r#"{"window": [0], "opacity": [[0, 1]]}"#,
                "`window`",
                "2 numbers",
            ),
            (
                r#"{"window": [5, 5], "opacity": [[0, 1]]}"#,
                "`window`",
                "window[0] < window[1]",
            ),
            (r#"{"window": [0, 1]}"#, "`opacity`", "missing"),
            (
                r#"{"window": [0, 1], "opacity": []}"#,
                "`opacity`",
                "at least one",
            ),
            (
                r#"{"window": [0, 1], "opacity": {"a": 1}}"#,
                "`opacity`",
                "array of control points",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 0], [1.5, 1]]}"#,
                "`opacity[1]`",
                "outside [0, 1]",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 0], [0.5, 2]]}"#,
                "`opacity[1]`",
                "alpha",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0.6, 0], [0.5, 1]]}"#,
                "`opacity[1]`",
                "non-decreasing",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 0], [0.5]]}"#,
                "`opacity[1]`",
                "2 numbers",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 1]], "colormap": "jet"}"#,
                "`colormap`",
                "unknown colour map",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 1]], "colormap": [[0, 1, 1]]}"#,
                "`colormap[0]`",
                "4 numbers",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 1]], "colormap": [[0, 1, 1, 3]]}"#,
                "`colormap[0]`",
                "r, g, b",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 1]], "color": "hot"}"#,
                "`color`",
                "unknown field",
            ),
            (
                r#"{"preset": "sharp", "window": [0, 1]}"#,
                "`preset`",
                "unknown preset",
            ),
            (
                r#"{"preset": "soft", "window": [1, 0]}"#,
                "`window`",
                "window[0] < window[1]",
            ),
            (
                r#"{"window": [0, 1], "opacity": [[0, 1]"#,
                "",
                "invalid JSON",
            ),
        ];
        for (json, field, msg) in cases {
            let e = TransferFunction::from_json(json).unwrap_err().to_string();
            assert!(e.starts_with("transfer function: "), "{e}");
            assert!(e.contains(field) && e.contains(msg), "{json}\n→ {e}");
        }
        let e = serde_json::from_str::<ColorMap>(r#""jet""#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown colour map"), "{e}");
    }
}
