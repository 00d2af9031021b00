// Ray-guided DVR and MIP through the virtual memory on the device: the
// twin of `cpu.rs` (same rays, steps, levels, fallback and compositing, in
// f32 where the CPU uses f64 for positions). Appended to vm_common.wgsl
// (bindings 0–2: layout, page tables, pool); request_insert.wgsl follows.
//
// Per frame each invocation (one pixel) marks the pool slots it used
// (frame stamps, and a list of newly used slots for the host), adds its
// misses to the request table (runs of the same brick added at once), and
// counts samples, exact samples and unserved samples.

struct Render {
    width: u32,
    height: u32,
    // 0: DVR, 1: MIP, 2: slice.
    mode: u32,
    levels: u32,
    eye: vec4<f32>,
    right: vec4<f32>,
    up: vec4<f32>,
    forward: vec4<f32>,
    // World box [0, extent], (x, y, z).
    extent: vec4<f32>,
    half_h: f32,
    aspect: f32,
    perspective: u32,
    // A fixed level, or AUTO.
    lod_fixed: u32,
    lod_bias: f32,
    // Pixel footprint at distance t: fp_slope·t (perspective) or fp_const.
    fp_slope: f32,
    fp_const: f32,
    voxel0: f32,
    window0: f32,
    inv_width: f32,
    n_opacity: u32,
    n_color: u32,
    frame: u32,
    buckets: u32,
    channel: u32,
    used_cap: u32,
    // DVR: cross hidden bricks in one jump (1), or sample every step (0).
    skip: u32,
    clear_off: u32,
    // DVR: cross cells of resident bricks the transfer function hides;
    // MIP: cells whose maximum cannot raise the ray's (1), or not (0).
    skip_cells: u32,
    pad1: u32,
    // Cells per brick and axis, voxels per cell edge (z, y, x).
    cell_count: vec4<u32>,
    cell_edge: vec4<u32>,
    // Several channels added up (slice, MIP): how many (0: one channel
    // through the transfer function) and where their styles start in
    // `aux` (8 words each: channel, lo, hi, 0, r, g, b, 0).
    n_channels: u32,
    styles_off: u32,
    pad3: u32,
    pad4: u32,
    // Slice: a point of the plane and its unit normal (x, y, z).
    plane_origin: vec4<f32>,
    plane_normal: vec4<f32>,
    // Per level: voxels per world unit (z, y, x); w unused.
    scale: array<vec4<f32>, 16>,
    // Per level: last voxel index (z, y, x) as floats.
    qmax: array<vec4<f32>, 16>,
    // Per level: (step, opacity-correction exponent, 0, 0).
    step: array<vec4<f32>, 16>,
    // Per level: bricks per axis (z, y, x); w: first brick id of the level.
    bricks: array<vec4<u32>, 16>,
}

@group(0) @binding(3) var<uniform> R: Render;
// The transfer function's opacity points (x, alpha, 0, 0) and colour-map
// points (x, r, g, b) as f32 bits, four words each; from word
// `R.clear_off` on, one bit per brick id: the transfer function maps the
// brick's whole value range to zero opacity (from the store's statistics).
@group(0) @binding(4) var<storage, read> aux: array<u32>;
// Premultiplied RGBA per pixel, rows top to bottom.
@group(0) @binding(5) var<storage, read_write> image: array<vec4<f32>>;
// Per slot of every set (the pool, then the cache of each intermediate
// level: `lay.set_base`): (frame last used, frame last used at its own
// level; pool only).
@group(0) @binding(6) var<storage, read_write> stamps: array<atomic<u32>>;
// 0: samples, 1: exact, 2: unserved, 3: bricks crossed in one jump (per
// ray and brick), 4: used-list length, 5: cells crossed in one jump; from
// 8 on the used list (slot, | EXACT_BIT when used at its own level).
@group(0) @binding(7) var<storage, read_write> counters: array<atomic<u32>>;
@group(0) @binding(8) var<storage, read_write> keys: array<atomic<u32>>;
@group(0) @binding(9) var<storage, read_write> counts: array<atomic<u32>>;
@group(0) @binding(10) var<storage, read_write> dropped: array<atomic<u32>>;
// Per pool slot, the value range (lo, hi) of each cell of its brick (NaN:
// unknown), at the slot's coordinates × cells per axis.
@group(0) @binding(11) var cells: texture_3d<f32>;


const AUTO: u32 = 0xffffffffu;
const EARLY_TERMINATION: f32 = 0.99;
const EXACT_BIT: u32 = 0x80000000u;
const USED_BASE: u32 = 8u;

var<private> last_mark: u32;
// The page entry of the brick last walked to: its level, brick, entry.
// Per channel shown (index `cur_idx`): the last brick walked to.
var<private> memo_level: array<u32, 16>;
var<private> memo_brick: array<vec3<u32>, 16>;
var<private> memo_entry: array<vec2<u32>, 16>;
// The channel being sampled and its index among those shown.
var<private> cur_ch: u32;
var<private> cur_idx: u32;

fn tf(i: u32) -> vec4<f32> {
    return vec4<f32>(
        bitcast<f32>(aux[4u * i]),
        bitcast<f32>(aux[4u * i + 1u]),
        bitcast<f32>(aux[4u * i + 2u]),
        bitcast<f32>(aux[4u * i + 3u]),
    );
}

fn is_clear(id: u32) -> bool {
    return ((aux[R.clear_off + (id >> 5u)] >> (id & 31u)) & 1u) == 1u;
}
var<private> miss_id: u32;
var<private> miss_n: u32;

fn piece_at(x: f32, a: vec2<f32>, b: vec2<f32>) -> f32 {
    let slope = (b.y - a.y) / (b.x - a.x);
    let v = a.y + (x - a.x) * slope;
    return clamp(v, min(a.y, b.y), max(a.y, b.y));
}

// Piecewise-linear opacity at the windowed value x (constant outside the
// points, right-continuous at steps).
fn opacity_at(x: f32) -> f32 {
    let n = R.n_opacity;
    var i = 0u;
    while (i < n && tf(i).x <= x) {
        i = i + 1u;
    }
    if (i == 0u) {
        return tf(0).y;
    }
    if (i == n) {
        return tf(n - 1u).y;
    }
    return piece_at(x, tf(i - 1u).xy, tf(i).xy);
}

fn color_at(x: f32) -> vec3<f32> {
    let o = R.n_opacity;
    let n = R.n_color;
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

fn windowed(v: f32) -> f32 {
    return clamp((v - R.window0) * R.inv_width, 0.0, 1.0);
}

fn is_nan(v: f32) -> bool {
    return !(v == v);
}

fn append_used(x: u32) {
    let i = atomicAdd(&counters[4], 1u);
    if (i < R.used_cap) {
        atomicStore(&counters[USED_BASE + i], x);
    }
}

// Mark pool slot `s` as used this frame (`exact`: at its own level).
fn mark(s: u32, exact: bool) {
    var key = s;
    if (exact) {
        key = s | EXACT_BIT;
    }
    if (key == last_mark) {
        return;
    }
    last_mark = key;
    if (atomicExchange(&stamps[2u * s], R.frame) != R.frame) {
        append_used(s);
    }
    if (exact && atomicExchange(&stamps[2u * s + 1u], R.frame) != R.frame) {
        append_used(s | EXACT_BIT);
    }
}

fn flush_misses() {
    if (miss_n > 0u) {
        request_add(miss_id, miss_n, R.buckets);
    }
    miss_n = 0u;
}

fn miss(id: u32) {
    if (id != miss_id) {
        flush_misses();
        miss_id = id;
    }
    miss_n = miss_n + 1u;
}

// Brick id (as brickyard_cache::bookkeeping::BrickIds numbers them) of
// voxel `v` of level `l`.
fn brick_id(l: u32, v: vec3<u32>) -> u32 {
    let g = R.bricks[l];
    let b = v / lay.block[lay.nmax].xyz;
    return g.w + (cur_ch * g.x + b.x) * g.y * g.z + b.y * g.z + b.z;
}

// Voxel base and fractions of world point `w` (x, y, z) at level `l`.
fn coords(l: u32, w: vec3<f32>) -> vec4<f32> {
    let s = R.scale[l];
    let q = clamp(vec3<f32>(w.z * s.x, w.y * s.y, w.x * s.z) - vec3<f32>(0.5), vec3<f32>(0.0), R.qmax[l].xyz);
    return vec4<f32>(q, 0.0);
}

// The value at world point `w` asked at level `level`, from the finest
// mapped level at or above it: (value, 0 unserved / 1 coarser / 2 exact).
// `q` and `e`: the voxel coordinates and page entry at `level`.
fn sample_from(w: vec3<f32>, level: u32, q: vec3<f32>, e: vec2<u32>) -> vec2<f32> {
    var lq = q;
    var le = e;
    for (var lv = level; lv < R.levels; lv = lv + 1u) {
        if (lv > level) {
            lq = coords(lv, w).xyz;
            le = entry_at(lv, vec3<u32>(lq));
        }
        let b = vec3<u32>(lq);
        let r = value_of(le, b, lq - vec3<f32>(b));
        if (r.y > 0.0) {
            if (flag(le) == MAPPED) {
                mark(slot_id(le, lay.brick_grid), lv == level);
            }
            if (lv == level) {
                return vec2<f32>(r.x, 2.0);
            }
            return vec2<f32>(r.x, 1.0);
        }
        if (lv == level) {
            miss(brick_id(lv, b));
        }
    }
    // Nothing resident serves it: ask for the coarser bricks too.
    for (var lv = level + 1u; lv < R.levels; lv = lv + 1u) {
        miss(brick_id(lv, vec3<u32>(coords(lv, w).xyz)));
    }
    return vec2<f32>(0.0, 0.0);
}

// `walk` (vm_common.wgsl), stamping the page-table blocks it passes
// through as used this frame.
fn walk_marking(l: u32, c: u32, v: vec3<u32>) -> vec2<u32> {
    let d = lay.dir_base[l].xyz + v / lay.span[0].xyz;
    let dd = lay.dir_dims;
    var e = entries[c * lay.dir_len + (d.x * dd.y + d.y) * dd.z + d.z];
    for (var n = 1u; n < lay.nmax; n = n + 1u) {
        if (flag(e) != MAPPED) {
            return e;
        }
        let b = slot_id(e, lay.pt_grid[n]);
        atomicStore(&stamps[2u * (lay.set_base[n].x + b)], R.frame);
        let o = (v / lay.span[n].xyz) % lay.block[n].xyz;
        let bl = lay.block[n];
        let i = (o.x * bl.y + o.y) * bl.z + o.z;
        e = entries[lay.table_off[n].x + b * lay.pt_grid[n].w + i];
    }
    return e;
}

// `walk`, remembering the last brick: consecutive samples of a ray mostly
// stay in one brick.
fn entry_at(level: u32, v: vec3<u32>) -> vec2<u32> {
    let b = v / lay.block[lay.nmax].xyz;
    let i = cur_idx;
    if (level != memo_level[i] || any(b != memo_brick[i])) {
        memo_level[i] = level;
        memo_brick[i] = b;
        memo_entry[i] = walk_marking(level, cur_ch, v);
    }
    return memo_entry[i];
}

fn sample_at(w: vec3<f32>, level: u32) -> vec2<f32> {
    let q = coords(level, w).xyz;
    return sample_from(w, level, q, entry_at(level, vec3<u32>(q)));
}

fn level_at(t: f32) -> u32 {
    if (R.lod_fixed != AUTO) {
        return min(R.lod_fixed, R.levels - 1u);
    }
    var fp = R.fp_const;
    if (R.perspective == 1u) {
        fp = R.fp_slope * t;
    }
    let l = log2(fp / R.voxel0) + R.lod_bias;
    if (l > 0.0 && l < 1e9) {
        return min(u32(floor(l)), R.levels - 1u);
    }
    return 0u;
}

struct Ray {
    o: vec3<f32>,
    d: vec3<f32>,
}

fn pixel_ray(i: u32, j: u32) -> Ray {
    let px = f32(i) + 0.5;
    let py = f32(j) + 0.5;
    let sx = (2.0 * px / f32(R.width) - 1.0) * R.half_h * R.aspect;
    let sy = (1.0 - 2.0 * py / f32(R.height)) * R.half_h;
    let off = R.right.xyz * sx + R.up.xyz * sy;
    if (R.perspective == 1u) {
        return Ray(R.eye.xyz, normalize(R.forward.xyz + off));
    }
    return Ray(R.eye.xyz + off, R.forward.xyz);
}

// (t0, t1) of the ray in the world box, t0 ≥ 0; t1 ≤ t0 when it misses.
fn intersect(r: Ray) -> vec2<f32> {
    var t0 = 0.0;
    var t1 = 3.0e38;
    for (var a = 0u; a < 3u; a = a + 1u) {
        let o = r.o[a];
        let d = r.d[a];
        let hi = R.extent[a];
        if (d == 0.0) {
            if (o < 0.0 || o > hi) {
                return vec2<f32>(1.0, 0.0);
            }
            continue;
        }
        var ta = (0.0 - o) / d;
        var tb = (hi - o) / d;
        if (ta > tb) {
            let x = ta;
            ta = tb;
            tb = x;
        }
        t0 = max(t0, ta);
        t1 = min(t1, tb);
    }
    return vec2<f32>(t0, t1);
}

// Where the level changes after `level` (automatic LOD; a huge value when
// it never does).
fn next_level_t(level: u32) -> f32 {
    if (R.lod_fixed != AUTO || R.perspective == 0u || level + 1u >= R.levels) {
        return 3.0e38;
    }
    return R.voxel0 * exp2(f32(level) + 1.0 - R.lod_bias) / R.fp_slope;
}

// The ray parameter where the voxel base at `level` leaves the box
// [lo, hi) (voxels, z y x), or `limit` if it does not before.
fn exit_t(r: Ray, level: u32, lo: vec3<u32>, hi: vec3<u32>, limit: f32) -> f32 {
    var t = limit;
    let s = R.scale[level];
    let dims = lay.dims[level];
    for (var a = 0u; a < 3u; a = a + 1u) {
        let o = r.o[2u - a];
        let d = r.d[2u - a];
        if (d > 0.0 && hi[a] < dims[a]) {
            t = min(t, ((f32(hi[a]) + 0.5) / s[a] - o) / d);
        } else if (d < 0.0 && lo[a] > 0u) {
            t = min(t, ((f32(lo[a]) + 0.5) / s[a] - o) / d);
        }
    }
    return t;
}

// The step to go on from after step `k − 1` (in the brick of voxel `b`
// at `level`): the first step past where the ray leaves the brick, a
// hundredth of a step early so that rounding never passes a step outside,
// and never past a change of level (whose restart of the step grid must
// stay where it is without the jump).
fn land(r: Ray, level: u32, b: vec3<u32>, base_t: f32, k: u32, t1: f32) -> u32 {
    let bs = lay.block[lay.nmax].xyz;
    let lo = (b / bs) * bs;
    return land_box(r, level, lo, min(lo + bs, lay.dims[level].xyz), base_t, k, t1);
}

// `land` past the cell of base voxel `b` (inside its brick).
fn land_cell(r: Ray, level: u32, b: vec3<u32>, base_t: f32, k: u32, t1: f32) -> u32 {
    let bs = lay.block[lay.nmax].xyz;
    let b0 = (b / bs) * bs;
    let lo = b0 + ((b - b0) / R.cell_edge.xyz) * R.cell_edge.xyz;
    let hi = min(min(lo + R.cell_edge.xyz, b0 + bs), lay.dims[level].xyz);
    return land_box(r, level, lo, hi, base_t, k, t1);
}

// `land` for the box [lo, hi) of voxel bases (a brick or a cell).
fn land_box(r: Ray, level: u32, lo: vec3<u32>, hi: vec3<u32>, base_t: f32, k: u32, t1: f32) -> u32 {
    let te = exit_t(r, level, lo, hi, min(t1, next_level_t(level)));
    let kn = ceil((te - base_t) / R.step[level].x - 0.5 - 0.01);
    if (kn > f32(k)) {
        return u32(kn);
    }
    return k;
}

// Whether the transfer function gives zero opacity to every value in
// [lo, hi] (NaN: unknown, so no): the piecewise-linear opacity is largest
// at the ends of the windowed range or at a point inside it.
fn range_clear(lo: f32, hi: f32) -> bool {
    if (is_nan(lo) || is_nan(hi)) {
        return false;
    }
    let x0 = windowed(lo);
    let x1 = windowed(hi);
    if (opacity_at(x0) > 0.0 || opacity_at(x1) > 0.0) {
        return false;
    }
    for (var i = 0u; i < R.n_opacity; i = i + 1u) {
        let p = tf(i);
        if (p.x >= x0 && p.x <= x1 && p.y > 0.0) {
            return false;
        }
    }
    return true;
}

// The value range of the cell of resident brick slot `slot` holding base
// voxel `b` (level voxel coordinates).
fn cell_range(slot: u32, b: vec3<u32>) -> vec2<f32> {
    let local = b % lay.block[lay.nmax].xyz;
    let c = local / R.cell_edge.xyz;
    let g = lay.dev_grid;
    let sc = vec3<u32>(slot / (g.z * g.y), (slot / g.z) % g.y, slot % g.z);
    let t = sc * R.cell_count.xyz + c;
    return textureLoad(cells, vec3<i32>(t.zyx), 0).xy;
}

fn correct_opacity(a: f32, e: f32) -> f32 {
    if (e == 1.0) {
        return a;
    }
    return 1.0 - pow(1.0 - a, e);
}

// Where the pixel's ray meets the slice plane inside the closed world box:
// (point, t), or w = −1 when it does not.
fn slice_hit(ray: Ray) -> vec4<f32> {
    let n = R.plane_normal.xyz;
    let denom = dot(ray.d, n);
    if (denom == 0.0) {
        return vec4<f32>(-1.0);
    }
    let t = dot(R.plane_origin.xyz - ray.o, n) / denom;
    if (is_nan(t) || t < 0.0) {
        return vec4<f32>(-1.0);
    }
    let w = ray.o + ray.d * t;
    if (any(w < vec3<f32>(0.0)) || any(w > R.extent.xyz)) {
        return vec4<f32>(-1.0);
    }
    return vec4<f32>(w, t);
}

// A slice: the plane as the camera sees it, sampled where the pixel's ray
// meets it inside the closed world box, opaque there (as on the CPU).
fn slice_pixel(ray: Ray) -> vec4<f32> {
    let hit = slice_hit(ray);
    if (hit.w < 0.0) {
        return vec4<f32>(0.0);
    }
    let w = hit.xyz;
    let level = level_at(hit.w);
    let s = sample_at(w, level);
    atomicAdd(&counters[0], 1u);
    if (s.y == 2.0) {
        atomicAdd(&counters[1], 1u);
    }
    if (s.y == 0.0) {
        atomicAdd(&counters[2], 1u);
        return vec4<f32>(0.0);
    }
    if (is_nan(s.x)) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(color_at(windowed(s.x)), 1.0);
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

fn use_channel(i: u32) {
    cur_idx = i;
    cur_ch = aux[R.styles_off + 8u * i];
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

// A slice of several channels.
fn slice_channels(ray: Ray) -> vec4<f32> {
    let hit = slice_hit(ray);
    if (hit.w < 0.0) {
        return vec4<f32>(0.0);
    }
    let w = hit.xyz;
    let level = level_at(hit.w);
    var v: array<f32, 16>;
    var have = 0u;
    for (var i = 0u; i < R.n_channels; i = i + 1u) {
        use_channel(i);
        let s = sample_at(w, level);
        atomicAdd(&counters[0], 1u);
        if (s.y == 2.0) {
            atomicAdd(&counters[1], 1u);
        }
        if (s.y == 0.0) {
            atomicAdd(&counters[2], 1u);
        } else {
            v[i] = s.x;
            have = have | (1u << i);
        }
    }
    return mix(v, have);
}

// The largest value of the current channel along the ray in `span` at the
// entry level (NaN samples and unserved ones left out), and whether there
// was one; crossing cells whose maximum cannot raise it; as the CPU's
// `mip_max`.
fn mip_max(ray: Ray, span: vec2<f32>) -> vec2<f32> {
    let t1 = span.y;
    let level = level_at(span.x);
    var best = 0.0;
    var found = false;
    var k = 0u;
    var samples = 0u;
    var exact = 0u;
    var unserved = 0u;
    var crossed = 0u;
    loop {
        let t = span.x + (f32(k) + 0.5) * R.step[level].x;
        if (t >= t1) {
            break;
        }
        k = k + 1u;
        let w = ray.o + ray.d * t;
        let q = coords(level, w).xyz;
        let b = vec3<u32>(q);
        let e = entry_at(level, b);
        if (R.skip_cells == 1u && found && flag(e) == MAPPED) {
            let slot = slot_id(e, lay.brick_grid);
            let r = cell_range(slot, b);
            if (!is_nan(r.y) && r.y <= best) {
                mark(slot, true);
                crossed = crossed + 1u;
                k = land_cell(ray, level, b, span.x, k, t1);
                continue;
            }
        }
        let s = sample_from(w, level, q, e);
        samples = samples + 1u;
        if (s.y == 2.0) {
            exact = exact + 1u;
        }
        if (s.y == 0.0 || is_nan(s.x)) {
            unserved = unserved + u32(s.y == 0.0);
            continue;
        }
        if (!found || s.x > best) {
            best = s.x;
            found = true;
        }
    }
    atomicAdd(&counters[0], samples);
    atomicAdd(&counters[1], exact);
    atomicAdd(&counters[2], unserved);
    atomicAdd(&counters[5], crossed);
    return vec2<f32>(best, f32(found));
}

@compute @workgroup_size(8, 8)
fn render(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= R.width || g.y >= R.height) {
        return;
    }
    last_mark = AUTO;
    for (var i = 0u; i < 16u; i = i + 1u) {
        memo_level[i] = AUTO;
    }
    cur_ch = R.channel;
    cur_idx = 0u;
    miss_id = AUTO;
    miss_n = 0u;
    let ray = pixel_ray(g.x, g.y);
    if (R.n_channels > 0u) {
        var px = vec4<f32>(0.0);
        if (R.mode == 2u) {
            px = slice_channels(ray);
        } else {
            // MIP: each channel's maximum along the ray, then the mix.
            let span = intersect(ray);
            if (span.y > span.x && span.x + 0.5 * R.step[level_at(span.x)].x < span.y) {
                var v: array<f32, 16>;
                var have = 0u;
                for (var i = 0u; i < R.n_channels; i = i + 1u) {
                    use_channel(i);
                    let m = mip_max(ray, span);
                    v[i] = m.x;
                    if (m.y > 0.0) {
                        have = have | (1u << i);
                    }
                }
                px = mix(v, have);
            }
        }
        flush_misses();
        image[g.y * R.width + g.x] = px;
        return;
    }
    if (R.mode == 2u) {
        image[g.y * R.width + g.x] = slice_pixel(ray);
        flush_misses();
        return;
    }
    let span = intersect(ray);
    if (R.mode == 1u) {
        // MIP: the maximum along the ray, opaque where the ray took a
        // sample (black when none was served).
        var px = vec4<f32>(0.0);
        if (span.y > span.x && span.x + 0.5 * R.step[level_at(span.x)].x < span.y) {
            let m = mip_max(ray, span);
            px = vec4<f32>(0.0, 0.0, 0.0, 1.0);
            if (m.y > 0.0) {
                px = vec4<f32>(color_at(windowed(m.x)), 1.0);
            }
        }
        flush_misses();
        image[g.y * R.width + g.x] = px;
        return;
    }
    // DVR.
    var acc = vec4<f32>(0.0);
    var samples = 0u;
    var exact = 0u;
    var unserved = 0u;
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
                // A level change: the new level's step grid has this
                // sample as its step 0 (as on the CPU).
                level = l;
                base_t = t - 0.5 * R.step[level].x;
                k = 1u;
            }
            let w = ray.o + ray.d * t;
            let q = coords(level, w).xyz;
            let b = vec3<u32>(q);
            let e = entry_at(level, b);
            let f = flag(e);
            if (R.skip == 1u) {
                // Bricks the transfer function hides (by their value range,
                // or as EMPTY/CONSTANT entries) are crossed in one jump.
                var hidden = is_clear(brick_id(level, b));
                if (!hidden && (f == EMPTY || f == CONSTANT)) {
                    var v = 0.0;
                    if (f == CONSTANT) {
                        v = constant_value(e.y);
                    }
                    hidden = is_nan(v) || opacity_at(windowed(v)) <= 0.0;
                }
                if (hidden) {
                    jumps = jumps + 1u;
                    k = land(ray, level, b, base_t, k, t1);
                    continue;
                }
            }
            if (R.skip_cells == 1u && f == MAPPED) {
                // Inside a resident brick: a cell whose values the transfer
                // function hides is crossed in one jump. Its brick is still
                // in use.
                let slot = slot_id(e, lay.brick_grid);
                let r = cell_range(slot, b);
                if (range_clear(r.x, r.y)) {
                    mark(slot, true);
                    cells_crossed = cells_crossed + 1u;
                    k = land_cell(ray, level, b, base_t, k, t1);
                    continue;
                }
            }
            let s = sample_from(w, level, q, e);
            samples = samples + 1u;
            if (s.y == 2.0) {
                exact = exact + 1u;
            }
            if (s.y == 0.0 || is_nan(s.x)) {
                unserved = unserved + u32(s.y == 0.0);
                continue;
            }
            let x = windowed(s.x);
            let alpha = opacity_at(x);
            if (alpha > 0.0) {
                let a = correct_opacity(alpha, R.step[level].y);
                let w = (1.0 - acc.w) * a;
                acc = acc + vec4<f32>(color_at(x) * w, w);
                if (acc.w >= EARLY_TERMINATION) {
                    break;
                }
            }
        }
    }
    flush_misses();
    image[g.y * R.width + g.x] = acc;
    atomicAdd(&counters[0], samples);
    atomicAdd(&counters[1], exact);
    atomicAdd(&counters[2], unserved);
    atomicAdd(&counters[3], jumps);
    atomicAdd(&counters[5], cells_crossed);
}
