// The device's optics, twin of `optics.rs`: the transfer function read
// from `aux` (windowing, piecewise-linear opacity and colour map, and
// whether it hides a whole value range), opacity correction for the step
// length, and the additive mix of several channels. Compositing itself is
// in dvr.wgsl (a few lines in the ray loop).

const EARLY_TERMINATION: f32 = 0.99;

fn tf(i: u32) -> vec4<f32> {
    return vec4<f32>(
        bitcast<f32>(aux[4u * i]),
        bitcast<f32>(aux[4u * i + 1u]),
        bitcast<f32>(aux[4u * i + 2u]),
        bitcast<f32>(aux[4u * i + 3u]),
    );
}

fn piece_at(x: f32, a: vec2<f32>, b: vec2<f32>) -> f32 {
    let slope = (b.y - a.y) / (b.x - a.x);
    let v = a.y + (x - a.x) * slope;
    return clamp(v, min(a.y, b.y), max(a.y, b.y));
}

// Piecewise-linear opacity at the windowed value x of the `n` opacity
// points from point `o` (constant outside the points, right-continuous at
// steps).
fn opacity_in(o: u32, n: u32, x: f32) -> f32 {
    var i = 0u;
    while (i < n && tf(o + i).x <= x) {
        i = i + 1u;
    }
    if (i == 0u) {
        return tf(o).y;
    }
    if (i == n) {
        return tf(o + n - 1u).y;
    }
    return piece_at(x, tf(o + i - 1u).xy, tf(o + i).xy);
}

// The colour map of the `n` colour points from point `o` at x.
fn color_in(o: u32, n: u32, x: f32) -> vec3<f32> {
    var i = 0u;
    while (i < n && tf(o + i).x <= x) {
        i = i + 1u;
    }
    if (i == 0u) {
        return tf(o).yzw;
    }
    if (i == n) {
        return tf(o + n - 1u).yzw;
    }
    let a = tf(o + i - 1u);
    let b = tf(o + i);
    return vec3<f32>(
        piece_at(x, a.xy, b.xy),
        piece_at(x, a.xz, b.xz),
        piece_at(x, a.xw, b.xw),
    );
}

// Whether the `n` opacity points from point `o` give zero opacity to every
// windowed value in [x0, x1]: the piecewise-linear opacity is largest at
// the ends or at a point inside.
fn opacity_clear(o: u32, n: u32, x0: f32, x1: f32) -> bool {
    if (opacity_in(o, n, x0) > 0.0 || opacity_in(o, n, x1) > 0.0) {
        return false;
    }
    for (var i = 0u; i < n; i = i + 1u) {
        let p = tf(o + i);
        if (p.x >= x0 && p.x <= x1 && p.y > 0.0) {
            return false;
        }
    }
    return true;
}

// The one-channel transfer function's opacity (its points first in `aux`).
fn opacity_at(x: f32) -> f32 {
    return opacity_in(0u, R.n_opacity, x);
}

fn color_at(x: f32) -> vec3<f32> {
    return color_in(R.n_opacity, R.n_color, x);
}

fn windowed(v: f32) -> f32 {
    return clamp((v - R.window0) * R.inv_width, 0.0, 1.0);
}

// Whether the transfer function gives zero opacity to every value in
// [lo, hi] (NaN: unknown, so no): the piecewise-linear opacity is largest
// at the ends of the windowed range or at a point inside it.
fn range_clear(lo: f32, hi: f32) -> bool {
    if (is_nan(lo) || is_nan(hi)) {
        return false;
    }
    return opacity_clear(0u, R.n_opacity, windowed(lo), windowed(hi));
}

fn correct_opacity(a: f32, e: f32) -> f32 {
    if (e == 1.0) {
        return a;
    }
    return 1.0 - pow(1.0 - a, e);
}

// A label's 32-bit hash (optics.rs's `label_hash`).
fn label_hash(id: u32) -> u32 {
    var h = id;
    h = h ^ (h >> 16u);
    h = h * 0x85ebca6bu;
    h = h ^ (h >> 13u);
    h = h * 0xc2b2ae35u;
    return h ^ (h >> 16u);
}

// Linear RGB of hue `h6` (sixths of the circle), saturation `s`, value `v`.
fn hsv(h6: f32, s: f32, v: f32) -> vec3<f32> {
    let i = floor(h6);
    let f = h6 - i;
    let p = v * (1.0 - s);
    let q = v * (1.0 - s * f);
    let t = v * (1.0 - s * (1.0 - f));
    switch i32(i) {
        case 0: {
            return vec3<f32>(v, t, p);
        }
        case 1: {
            return vec3<f32>(q, v, p);
        }
        case 2: {
            return vec3<f32>(p, v, t);
        }
        case 3: {
            return vec3<f32>(p, q, v);
        }
        case 4: {
            return vec3<f32>(t, p, v);
        }
        default: {
            return vec3<f32>(v, p, q);
        }
    }
}

// Whether label `id` is drawn under the frame's selection (`R.label_sel`;
// optics.rs's `LabelSelect::shows`): a binary search of its list.
fn label_shown(id: i32) -> bool {
    let mode = R.label_sel.x;
    if (mode == 0u) {
        return true;
    }
    let base = R.label_sel.y;
    let n = R.label_sel.z;
    var lo = 0u;
    var hi = n;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        if (bitcast<i32>(aux[base + mid]) < id) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    let listed = lo < n && bitcast<i32>(aux[base + lo]) == id;
    return listed != (mode == 2u);
}

// The first position of the selection's list whose label is not below
// `id` (`above`: above `id`).
fn label_bound(id: i32, above: bool) -> u32 {
    let base = R.label_sel.y;
    var lo = 0u;
    var hi = R.label_sel.z;
    while (lo < hi) {
        let mid = (lo + hi) / 2u;
        let x = bitcast<i32>(aux[base + mid]);
        if (x < id || (above && x == id)) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// Whether values in [lo, hi] (a cell's range) draw nothing: background
// alone, or no label the selection draws (optics.rs's `label_clear`).
fn label_range_clear(lo: f32, hi: f32) -> bool {
    if (is_nan(lo) || is_nan(hi)) {
        return false;
    }
    if (lo == 0.0 && hi == 0.0) {
        return true;
    }
    let mode = R.label_sel.x;
    if (mode == 0u) {
        return false;
    }
    let a = i32(floor(lo + 0.5));
    let b = i32(floor(hi + 0.5));
    if (a > b) {
        return false;
    }
    let listed = label_bound(b, true) - label_bound(a, false);
    if (mode == 1u) {
        return listed == 0u;
    }
    // All but the listed: clear when every label of the range but 0 is
    // listed (the count wraps only for ranges no list can cover).
    var n = bitcast<u32>(b) - bitcast<u32>(a) + 1u;
    if (a <= 0 && b >= 0) {
        n = n - 1u;
    }
    return n == listed;
}

// The pixel of a label image's slice sample `v` (optics.rs's
// `label_color_of`): the label's colour, opaque; label 0, labels the
// selection hides and NaN (nothing served) transparent.
fn label_color(v: f32) -> vec4<f32> {
    if (is_nan(v)) {
        return vec4<f32>(0.0);
    }
    let id = i32(floor(v + 0.5));
    if (id == 0 || !label_shown(id)) {
        return vec4<f32>(0.0);
    }
    let h = label_hash(bitcast<u32>(id));
    let hue = f32(h & 0xffffu) * (6.0 / 65536.0);
    let sat = 0.6 + 0.4 * f32((h >> 16u) & 0xffu) * (1.0 / 255.0);
    let val = 0.75 + 0.25 * f32(h >> 24u) * (1.0 / 255.0);
    return vec4<f32>(hsv(hue, sat, val), 1.0);
}

// Channel `i` of those added up: (channel, lo, hi) and colour.
fn style(i: u32) -> vec4<f32> {
    let o = R.styles_off + 8u * i;
    return vec4<f32>(f32(aux[o]), bitcast<f32>(aux[o + 1u]), bitcast<f32>(aux[o + 2u]), 0.0);
}

fn style_color(i: u32) -> vec3<f32> {
    let o = R.styles_off + 8u * i + 4u;
    return vec3<f32>(bitcast<f32>(aux[o]), bitcast<f32>(aux[o + 1u]), bitcast<f32>(aux[o + 2u]));
}

// The additive mix of the channels' values `v[i]` (bit i of `have` clear,
// or NaN: nothing), as the CPU's `mix_channels`: Σ colour·intensity,
// clamped to 1, opaque.
fn mix(v: array<f32, 16>, have: u32) -> vec4<f32> {
    var rgb = vec3<f32>(0.0);
    for (var i = 0u; i < R.n_channels; i = i + 1u) {
        let st = style(i);
        let raw = (v[i] - st.y) / (st.z - st.y);
        var x = 0.0;
        if (((have >> i) & 1u) == 1u && !is_nan(raw)) {
            x = clamp(raw, 0.0, 1.0);
        }
        rgb = rgb + style_color(i) * x;
    }
    return vec4<f32>(min(rgb, vec3<f32>(1.0)), 1.0);
}
