// Multi-channel DVR on the device, twin of `multi.rs`: at every step each
// channel shown (`use_channel`: its own page-table walk memo, its own clear
// bits) through its own transfer function, mixed as coincident media
// (opacity 1 − Π(1 − α_i), colour Σ α_i·c_i / Σ α_i) and composited front to
// back. The ray jumps over a brick only when every channel hides it, and
// over a cell of resident bricks when every channel hides the cell (or its
// brick).
//
// Per channel i shown, 8 words of `aux` from R.styles_off + 8·i: channel,
// window start (f32 bits), 1 / window width (f32 bits), index of its first
// transfer-function point (in 4-word points), opacity points, colour
// points, the finest and the coarsest level it is read at (0 and AUTO:
// every level). The points themselves lie in `aux` like the one-channel
// transfer function's, so 64 channels take one binding.

fn ch_word(i: u32, k: u32) -> u32 {
    return aux[R.styles_off + 8u * i + k];
}

fn ch_windowed(i: u32, v: f32) -> f32 {
    return clamp((v - bitcast<f32>(ch_word(i, 1u))) * bitcast<f32>(ch_word(i, 2u)), 0.0, 1.0);
}

// Channel i's opacity at the windowed value x (as `opacity_at`).
fn ch_opacity(i: u32, x: f32) -> f32 {
    return opacity_in(ch_word(i, 3u), ch_word(i, 4u), x);
}

// Channel i's colour at the windowed value x (as `color_at`).
fn ch_color(i: u32, x: f32) -> vec3<f32> {
    return color_in(ch_word(i, 3u) + ch_word(i, 4u), ch_word(i, 5u), x);
}

// Channel i's transfer function hides every value in [lo, hi] (as
// `range_clear` for the one-channel function).
fn ch_range_clear(i: u32, lo: f32, hi: f32) -> bool {
    if (is_nan(lo) || is_nan(hi)) {
        return false;
    }
    return opacity_clear(ch_word(i, 3u), ch_word(i, 4u), ch_windowed(i, lo), ch_windowed(i, hi));
}

// Whether channel i hides the brick of voxel base `b` at `level`, whose
// page entry is `e`: known clear (the store's statistics), or an EMPTY or
// CONSTANT entry its transfer function maps to zero opacity.
fn ch_hides_brick(i: u32, level: u32, b: vec3<u32>, e: vec2<u32>) -> bool {
    let f = flag(e);
    if (is_clear(brick_id(level, b))) {
        return true;
    }
    if (f != EMPTY && f != CONSTANT) {
        return false;
    }
    var v = 0.0;
    if (f == CONSTANT) {
        v = constant_value(e.y);
    }
    return is_nan(v) || ch_opacity(i, ch_windowed(i, v)) <= 0.0;
}

// Whether channel i adds nothing anywhere in the cell of voxel base `b` of
// the step's level `level`: it reads that level there and hides its brick
// (`skip`, as `channel_sample`: 2), or the brick is resident there and the
// cell's value range is hidden (1; its slot marked as used); 0 otherwise.
fn ch_cell_clear(i: u32, level: u32, b: vec3<u32>, skip: bool) -> u32 {
    use_channel(i);
    if (ch_level(i, level) != level) {
        return 0u;
    }
    let e = entry_at(level, b);
    if (skip && ch_hides_brick(i, level, b, e)) {
        return 2u;
    }
    if (flag(e) != MAPPED) {
        return 0u;
    }
    let slot = slot_id(e, lay.brick_grid);
    let r = cell_range(slot, b);
    if (!ch_range_clear(i, r.x, r.y)) {
        return 0u;
    }
    mark(slot, true);
    return 1u;
}

// α of a channel's sample that nothing resident served at the step's level.
const UNSERVED_HERE: f32 = -2.0;

// Samples, exact samples and unserved samples of the channels shown (this
// invocation's, added to the counters at the ray's end).
var<private> ch_samples: u32;
var<private> ch_exact: u32;
var<private> ch_unserved: u32;

// The level channel i is read at where a step asks for `level` (its level
// range, `ChannelStyle::level_for`).
fn ch_level(i: u32, level: u32) -> u32 {
    return min(clamp(level, ch_word(i, 6u), ch_word(i, 7u)), R.levels - 1u);
}

// Channel i shown at world point `w` of the step's level `step_level`
// (voxel coordinates `step_q`), read at its own level (`ch_level`):
// (α·colour, α) through its transfer function, α 0 where nothing shows;
// α −1 when `skip` and the channel hides the brick there (known clear, or
// an EMPTY/CONSTANT entry it maps to zero opacity) and that brick is of the
// step's level (a brick of another level gives no landing: α 0); α −2
// (`UNSERVED_HERE`) when nothing resident serves it and its level is the
// step's. On a miss, only the coarser levels whose bit `mask` has
// substitute.
fn channel_sample(i: u32, step_level: u32, w: vec3<f32>, step_q: vec3<f32>, mask: u32, skip: bool) -> vec4<f32> {
    use_channel(i);
    let level = ch_level(i, step_level);
    var q = step_q;
    if (level != step_level) {
        q = coords(level, w).xyz;
    }
    let b = vec3<u32>(q);
    let e = entry_at(level, b);
    if (skip && ch_hides_brick(i, level, b, e)) {
        if (level != step_level) {
            return vec4<f32>(0.0);
        }
        return vec4<f32>(0.0, 0.0, 0.0, -1.0);
    }
    let s = sample_masked(w, level, q, e, mask);
    ch_samples = ch_samples + 1u;
    if (s.y == 2.0) {
        ch_exact = ch_exact + 1u;
    }
    if (s.y == 0.0) {
        ch_unserved = ch_unserved + 1u;
        if (level == step_level) {
            return vec4<f32>(0.0, 0.0, 0.0, UNSERVED_HERE);
        }
        return vec4<f32>(0.0);
    }
    if (is_nan(s.x)) {
        return vec4<f32>(0.0);
    }
    let x = ch_windowed(i, s.x);
    let a = ch_opacity(i, x);
    if (a > 0.0) {
        return vec4<f32>(a * ch_color(i, x), a);
    }
    return vec4<f32>(0.0);
}

// The pixel of `ray` in a DVR of the channels shown; adds its counts.
fn dvr_channels(ray: Ray) -> vec4<f32> {
    let span = intersect(ray);
    var acc = vec4<f32>(0.0);
    ch_samples = 0u;
    ch_exact = 0u;
    ch_unserved = 0u;
    var jumps = 0u;
    var cells_crossed = 0u;
    if (span.y > span.x) {
        let t1 = span.y;
        var level = level_at(span.x);
        var base_t = span.x;
        var k = 0u;
        loop {
            let t = base_t + (f32(k) + 0.5) * R.step[level].x;
            if (t >= t1) {
                break;
            }
            k = k + 1u;
            let l = level_at(t);
            if (l != level) {
                level = l;
                base_t = t - 0.5 * R.step[level].x;
                k = 1u;
            }
            let w = ray.o + ray.d * t;
            let q = coords(level, w).xyz;
            let b = vec3<u32>(q);
            if (R.skip_cells == 1u) {
                // Every channel resident here with the cell clear, or
                // hiding its brick (some resident): on past the cell in one
                // jump, as the CPU's runs cross it.
                var clear = 2u;
                for (var i = 0u; i < R.n_channels; i = i + 1u) {
                    let c = ch_cell_clear(i, level, b, R.skip == 1u);
                    if (c == 0u) {
                        clear = 0u;
                        break;
                    }
                    clear = min(clear, c);
                }
                if (clear == 1u) {
                    cells_crossed = cells_crossed + 1u;
                    k = land_cell(ray, level, b, base_t, k, t1);
                    continue;
                }
            }
            var all_clear = true;
            // Every channel either hides the brick or found nothing
            // resident (then the ray may jump), and which found nothing.
            var passable = true;
            var unserved = vec2<u32>(0u);
            var keep = 1.0;
            var rgb = vec3<f32>(0.0);
            var weight = 0.0;
            for (var i = 0u; i < R.n_channels; i = i + 1u) {
                let c = channel_sample(i, level, w, q, ALL_LEVELS, R.skip == 1u);
                if (c.w == -1.0) {
                    continue;
                }
                all_clear = false;
                if (c.w == UNSERVED_HERE) {
                    unserved[i / 32u] = unserved[i / 32u] | (1u << (i % 32u));
                    continue;
                }
                passable = false;
                if (c.w > 0.0) {
                    keep = keep * (1.0 - c.w);
                    rgb = rgb + c.xyz;
                    weight = weight + c.w;
                }
            }
            if (all_clear) {
                // Every channel hides this brick: one jump (the same for
                // all, as the brick is).
                jumps = jumps + 1u;
                k = land(ray, level, b, base_t, k, t1);
                continue;
            }
            if (passable && any(unserved != vec2<u32>(0u))) {
                // No channel shows here and some found nothing resident: on
                // past the brick in one jump, as the CPU; the steps jumped
                // are unserved samples and misses of each such channel's
                // brick.
                let kn = land(ray, level, b, base_t, k, t1);
                let n = kn - k;
                for (var i = 0u; i < R.n_channels; i = i + 1u) {
                    if (((unserved[i / 32u] >> (i % 32u)) & 1u) == 1u) {
                        use_channel(i);
                        misses(brick_id(level, b), n);
                        ch_samples = ch_samples + n;
                        ch_unserved = ch_unserved + n;
                    }
                }
                k = kn;
                continue;
            }
            if (weight > 0.0) {
                let a = correct_opacity(1.0 - keep, R.step[level].y);
                let wt = (1.0 - acc.w) * a;
                acc = acc + vec4<f32>(rgb * (1.0 / weight) * wt, wt);
                if (acc.w >= EARLY_TERMINATION) {
                    break;
                }
            }
        }
    }
    atomicAdd(&counters[0], ch_samples);
    atomicAdd(&counters[1], ch_exact);
    atomicAdd(&counters[2], ch_unserved);
    atomicAdd(&counters[3], jumps);
    atomicAdd(&counters[5], cells_crossed);
    return acc;
}
