// Sample accumulation on the device, twin of `savr.rs`: the same sample
// positions (frame k samples t0 + (j + o_k)·Δ, o_k = ½ + r₂(k) mod 1), the
// same per-pixel room rule, stand-in marks and retakes, runs taken to
// their own early termination and extended when the blend needs more, and
// the blend in depth order with opacity corrected for the rate reached.
//
// The store is split into bands of image rows (`R.acc_band`: first row,
// rows), one dispatch and one buffer each (so that each fits one storage
// binding); a band's store lives in the image binding after the band's
// image (`image`, words 4·P on, P = width × rows, pixels numbered within
// the band), at the offsets of `R.acc_off`:
//   header   8 words a pixel: t0, t1, Δ (f32 bits), runs, stand-ins kept,
//            short (the last blend ran out of kept samples), S (samples a
//            run can hold), state (0 fresh, 1 begun);
//   runs     N words a pixel (N = R.acc.x frames): length | ENDED;
//   values   B words a pixel (B = R.acc.y samples): run k, sample j at
//            k·S + j, f32 bits;
//   flags    ⌈B/16⌉ words a pixel, 2 bits a sample (STAND_IN, UNSERVED);
//   cosines  B words a pixel when normals are kept (R.acc.w = 1).
// Only the pixel's own invocation touches its words.
//
// Counters (this entry point's meaning of `counters` 0–7): samples, exact,
// unserved, stand-ins retaken, -, samples added by extension, pixels not
// complete, stand-ins kept.

const A_STAND_IN: u32 = 1u;
const A_UNSERVED: u32 = 2u;
const A_ENDED: u32 = 0x80000000u;
const A_EXTEND: u32 = 8u;

var<private> a_samples: u32;
var<private> a_exact: u32;
var<private> a_unserved: u32;
var<private> a_retaken: u32;
var<private> a_extended: u32;

fn st_get(i: u32) -> u32 {
    return image[4u * R.width * R.acc_band.y + i];
}

fn st_set(i: u32, x: u32) {
    image[4u * R.width * R.acc_band.y + i] = x;
}

fn hdr(px: u32, i: u32) -> u32 {
    return st_get(8u * px + i);
}

fn set_hdr(px: u32, i: u32, x: u32) {
    st_set(8u * px + i, x);
}

fn hdr_f(px: u32, i: u32) -> f32 {
    return bitcast<f32>(hdr(px, i));
}

fn run_word(px: u32, k: u32) -> u32 {
    return st_get(R.acc_off.x + px * R.acc.x + k);
}

fn set_run_word(px: u32, k: u32, x: u32) {
    st_set(R.acc_off.x + px * R.acc.x + k, x);
}

fn val_at(px: u32, i: u32) -> f32 {
    return bitcast<f32>(st_get(R.acc_off.y + px * R.acc.y + i));
}

fn set_val(px: u32, i: u32, v: f32) {
    st_set(R.acc_off.y + px * R.acc.y + i, bitcast<u32>(v));
}

fn flag_words() -> u32 {
    return (R.acc.y + 15u) / 16u;
}

fn flag_at(px: u32, i: u32) -> u32 {
    let w = st_get(R.acc_off.z + px * flag_words() + i / 16u);
    return (w >> (2u * (i % 16u))) & 3u;
}

fn set_flag(px: u32, i: u32, f: u32) {
    let a = R.acc_off.z + px * flag_words() + i / 16u;
    let s = 2u * (i % 16u);
    st_set(a, (st_get(a) & ~(3u << s)) | (f << s));
}

fn cos_at(px: u32, i: u32) -> f32 {
    return bitcast<f32>(st_get(R.acc_off.w + px * R.acc.y + i));
}

fn set_cos(px: u32, i: u32, c: f32) {
    st_set(R.acc_off.w + px * R.acc.y + i, bitcast<u32>(c));
}

// Frame k's offset within a step: ½ + r₂(k) (mod 1).
fn acc_offset(k: u32) -> f32 {
    return fract(0.5 + f32(reverseBits(k)) / 4294967296.0);
}

// The i-th of frames 0 … 2^m − 1 by increasing offset.
fn frame_at(i: u32, m: u32) -> u32 {
    if (m == 0u) {
        return 0u;
    }
    let size = 1u << m;
    return reverseBits(((i + size / 2u) & (size - 1u)) << (32u - m));
}

// ⌈log2 n⌉ (n ≥ 1).
fn log2_ceil(n: u32) -> u32 {
    var m = 0u;
    while ((1u << m) < n) {
        m = m + 1u;
    }
    return m;
}

fn room(px: u32, k: u32) -> bool {
    return k == 0u || (k < R.acc.x && (k + 1u) * hdr(px, 6u) <= R.acc.y);
}

struct AccSample {
    v: f32,
    fl: u32,
    cs: f32,
}

// The value at ray parameter `t`, its flags and (keeping normals) the
// cosine of its normal with the ray (negative for a zero gradient). A
// sample whose value or any gradient neighbour was not served at its
// level is a stand-in.
fn acc_sample(ray: Ray, t: f32) -> AccSample {
    let level = level_at(t);
    let w = ray.o + ray.d * t;
    let s = sample_at(w, level);
    a_samples = a_samples + 1u;
    if (s.y == 0.0) {
        a_unserved = a_unserved + 1u;
        return AccSample(0.0, A_STAND_IN | A_UNSERVED, -1.0);
    }
    var fl = A_STAND_IN;
    if (s.y == 2.0) {
        a_exact = a_exact + 1u;
        fl = 0u;
    }
    var cs = -1.0;
    if (R.acc.w == 1u) {
        let ns = nb_samples;
        let ne = nb_exact;
        let g = gradient(level, w);
        if (g.w == 0.0) {
            return AccSample(s.x, A_STAND_IN, -1.0);
        }
        if (nb_exact - ne != nb_samples - ns) {
            fl = A_STAND_IN;
        }
        cs = cosine(g.xyz, ray.d);
    }
    return AccSample(s.x, fl, cs);
}

// Take samples j = len, len + 1, … of run k of pixel `px`, at most
// `limit`, or (`own`) until the run alone would stop a ray blended with
// exponent `e_own`; marks the run ended at the ray's end.
fn acc_take(px: u32, ray: Ray, k: u32, limit: u32, own: bool, e_own: f32) -> u32 {
    let t0 = hdr_f(px, 0u);
    let t1 = hdr_f(px, 1u);
    let dt = hdr_f(px, 2u);
    let cap = hdr(px, 6u);
    let o = acc_offset(k);
    let r = run_word(px, k);
    var j = r & ~A_ENDED;
    var count = 0u;
    var ended = false;
    var stand_ins = 0u;
    var acc = vec4<f32>(0.0);
    loop {
        if (count >= limit) {
            break;
        }
        let t = t0 + (f32(j) + o) * dt;
        if (t >= t1 || j >= cap) {
            ended = true;
            break;
        }
        // Never past the pixel's region of the store (the host chooses a
        // level whose runs fit): a cut ray keeps the pixel incomplete.
        if (k * cap + j >= R.acc.y) {
            ended = true;
            stand_ins = stand_ins + 1u;
            break;
        }
        let s = acc_sample(ray, t);
        let i = k * cap + j;
        set_val(px, i, s.v);
        set_flag(px, i, s.fl);
        if (R.acc.w == 1u) {
            set_cos(px, i, s.cs);
        }
        j = j + 1u;
        count = count + 1u;
        stand_ins = stand_ins + u32((s.fl & A_STAND_IN) != 0u);
        if (own && (s.fl & A_UNSERVED) == 0u && !is_nan(s.v)) {
            let alpha = opacity_at(windowed(s.v));
            if (alpha > 0.0) {
                let a = correct_opacity(alpha, e_own);
                acc.w = acc.w + (1.0 - acc.w) * a;
                if (acc.w >= EARLY_TERMINATION) {
                    break;
                }
            }
        }
    }
    set_hdr(px, 4u, hdr(px, 4u) + stand_ins);
    set_run_word(px, k, j | select(0u, A_ENDED, ended));
    return count;
}

// Retake pixel `px`'s stand-in samples; those now served at their level
// lose the mark.
fn acc_retake(px: u32, ray: Ray) {
    let t0 = hdr_f(px, 0u);
    let dt = hdr_f(px, 2u);
    let cap = hdr(px, 6u);
    let n = hdr(px, 3u);
    var left = hdr(px, 4u);
    for (var k = 0u; k < n; k = k + 1u) {
        let o = acc_offset(k);
        let len = run_word(px, k) & ~A_ENDED;
        for (var j = 0u; j < len; j = j + 1u) {
            let i = k * cap + j;
            if ((flag_at(px, i) & A_STAND_IN) == 0u) {
                continue;
            }
            let s = acc_sample(ray, t0 + (f32(j) + o) * dt);
            if (R.acc.w == 1u && (s.fl & A_UNSERVED) == 0u) {
                set_cos(px, i, s.cs);
            }
            if (s.fl == 0u) {
                set_val(px, i, s.v);
                set_flag(px, i, 0u);
                left = left - 1u;
                a_retaken = a_retaken + 1u;
            } else if ((s.fl & A_UNSERVED) == 0u) {
                set_val(px, i, s.v);
                set_flag(px, i, s.fl);
            }
        }
    }
    set_hdr(px, 4u, left);
}

// Where a blend stands: its colour so far, and the next sample to blend
// (step j, the q-th run by offset; `any`: a run of step j held a sample
// before it).
struct BlendAt {
    acc: vec4<f32>,
    j: u32,
    q: u32,
    any: u32,
}

// The result of a blend whose loops ended before any of their exits: the
// device cut them short (lavapipe ends every loop of an invocation once
// its loops have run 65535 iterations in all).
const A_CUT: u32 = 0xfffffffeu;

// Blend pixel `px`'s n runs in depth order (j outer, runs by offset
// inner) with exponent `e`, from `at` on. Returns AUTO when the blend is
// done (its colour in `at.acc`), or the run that ran out before the ray
// stopped, with `at` at that run's next sample: once the run is extended,
// the blend goes on from there (the samples before are unchanged, so the
// colour is that of blending again from the start, as the CPU twin does,
// without the cost: that grew with the square of the samples added and
// ran past the device's limit on loop iterations for rays whose opacity
// stays just under the threshold).
fn acc_blend(px: u32, n: u32, e: f32, at: ptr<function, BlendAt>) -> u32 {
    let cap = hdr(px, 6u);
    let m = log2_ceil(n);
    let size = 1u << m;
    var acc = (*at).acc;
    var j = (*at).j;
    var q0 = (*at).q;
    var any = (*at).any == 1u;
    loop {
        for (var q = q0; q < size; q = q + 1u) {
            let k = frame_at(q, m);
            if (k >= n) {
                continue;
            }
            let r = run_word(px, k);
            if (j >= (r & ~A_ENDED)) {
                if ((r & A_ENDED) == 0u) {
                    *at = BlendAt(acc, j, q, u32(any));
                    return k;
                }
                continue;
            }
            any = true;
            let i = k * cap + j;
            if ((flag_at(px, i) & A_UNSERVED) != 0u) {
                continue;
            }
            let v = val_at(px, i);
            if (is_nan(v)) {
                continue;
            }
            let x = windowed(v);
            let alpha = opacity_at(x);
            if (alpha > 0.0) {
                var c = color_at(x);
                if (R.shade == 1u && R.acc.w == 1u) {
                    let cs = cos_at(px, i);
                    if (cs >= 0.0) {
                        c = lit(c, cs);
                    }
                }
                let a = correct_opacity(alpha, e);
                let wt = (1.0 - acc.w) * a;
                acc = acc + vec4<f32>(c * wt, wt);
                if (acc.w >= EARLY_TERMINATION) {
                    (*at).acc = acc;
                    return AUTO;
                }
            }
        }
        if (!any) {
            (*at).acc = acc;
            return AUTO;
        }
        q0 = 0u;
        any = false;
        j = j + 1u;
    }
    (*at).acc = acc;
    return A_CUT;
}

// The blend's opacity-correction exponent: (Δ/n)/Δ_ref.
fn acc_exponent(px: u32) -> f32 {
    return (hdr_f(px, 2u) / f32(hdr(px, 3u))) / R.acc_ref.x;
}

// The colour pixel `px` shows: the last frame's (the image is this
// accumulation's own, at the store's head).
fn shown(px: u32) -> vec4<f32> {
    return vec4<f32>(bitcast<f32>(image[4u * px]), bitcast<f32>(image[4u * px + 1u]),
                     bitcast<f32>(image[4u * px + 2u]), bitcast<f32>(image[4u * px + 3u]));
}

// One accumulation frame of pixel `px`: its colour.
fn acc_pixel(px: u32, ray: Ray) -> vec4<f32> {
    if (hdr(px, 7u) == 0u) {
        set_hdr(px, 7u, 1u);
        let span = intersect(ray);
        var dt = 0.0;
        if (span.y > span.x) {
            dt = R.step[level_at(span.x)].x;
            set_hdr(px, 0u, bitcast<u32>(span.x));
            set_hdr(px, 1u, bitcast<u32>(span.y));
            set_hdr(px, 6u, u32(ceil((span.y - span.x) / dt)) + 1u);
        }
        set_hdr(px, 2u, bitcast<u32>(dt));
    }
    let dt = hdr_f(px, 2u);
    if (dt == 0.0) {
        return vec4<f32>(0.0);
    }
    let retaken = hdr(px, 4u) > 0u;
    if (retaken) {
        acc_retake(px, ray);
    }
    let k = hdr(px, 3u);
    // Nothing new to blend (no room for a run, no stand-in retaken, the
    // last blend not short): the colour it shows stays (the CPU twin's
    // rule; the image is this accumulation's own, at the store's head).
    if (!retaken && hdr(px, 5u) == 0u && !room(px, k)) {
        return shown(px);
    }
    if (room(px, k)) {
        set_hdr(px, 3u, k + 1u);
        set_run_word(px, k, 0u);
        acc_take(px, ray, k, 0xffffffffu, true, dt / R.acc_ref.x);
        if (R.acc.z == 1u && room(px, k + 1u)) {
            // Blending the last run only (R.acc.z), and more runs to come:
            // the blend waits for them (marked short, so that the pixel is
            // not taken for complete).
            set_hdr(px, 5u, 1u);
            return shown(px);
        }
    }
    let n = hdr(px, 3u);
    let e = acc_exponent(px);
    var at = BlendAt(vec4<f32>(0.0), 0u, 0u, 0u);
    loop {
        let k = acc_blend(px, n, e, &at);
        if (k == AUTO) {
            set_hdr(px, 5u, 0u);
            return at.acc;
        }
        if (k == A_CUT) {
            break;
        }
        // An extension takes A_EXTEND samples or ends the run; one that
        // did neither was cut short.
        let r = run_word(px, k);
        a_extended = a_extended + acc_take(px, ray, k, A_EXTEND, false, 0.0);
        if (run_word(px, k) == r) {
            break;
        }
    }
    // Cut short by the device: the pixel stays incomplete (short) and
    // shows what it showed before; the next frame blends it again.
    set_hdr(px, 5u, 1u);
    return shown(px);
}

// Whether pixel `px` is complete: no stand-in, no short run, and every
// frame asked for taken or no room for the next.
fn acc_complete(px: u32) -> bool {
    if (hdr_f(px, 2u) == 0.0) {
        return true;
    }
    let n = hdr(px, 3u);
    return hdr(px, 4u) == 0u && hdr(px, 5u) == 0u && (n == R.acc.x || !room(px, n));
}

fn put_acc_counts(px: u32) {
    atomicAdd(&counters[0], a_samples);
    atomicAdd(&counters[1], a_exact);
    atomicAdd(&counters[2], a_unserved);
    atomicAdd(&counters[3], a_retaken);
    atomicAdd(&counters[5], a_extended);
    atomicAdd(&counters[6], u32(!acc_complete(px)));
    atomicAdd(&counters[7], hdr(px, 4u));
}

@compute @workgroup_size(8, 8)
fn accumulate(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= R.width || g.y >= R.acc_band.y) {
        return;
    }
    begin_invocation();
    let px = g.y * R.width + g.x;
    let c = acc_pixel(px, pixel_ray(g.x, R.acc_band.x + g.y));
    flush_misses();
    put_pixel(px, c);
    put_acc_counts(px);
}

// Blend the kept samples again under the transfer function of `aux`,
// without volume access: pixels that run out of kept samples show the
// blend so far and are marked short (the next frame extends them).
@compute @workgroup_size(8, 8)
fn reblend(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= R.width || g.y >= R.acc_band.y) {
        return;
    }
    let px = g.y * R.width + g.x;
    var c = vec4<f32>(0.0);
    if (hdr(px, 7u) == 1u && hdr_f(px, 2u) != 0.0 && hdr(px, 3u) > 0u) {
        var at = BlendAt(vec4<f32>(0.0), 0u, 0u, 0u);
        let k = acc_blend(px, hdr(px, 3u), acc_exponent(px), &at);
        c = at.acc;
        set_hdr(px, 5u, u32(k != AUTO));
    }
    put_pixel(px, c);
    put_acc_counts(px);
}
