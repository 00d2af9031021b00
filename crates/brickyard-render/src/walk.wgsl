// The device's walk, twin of `walk.rs` and `walk/`: the level a sample
// asks for, voxel coordinates, page-table walks that stamp what they pass
// through, the last brick remembered per channel, the fallback to coarser
// levels with misses added to the request table in runs, pool slots marked
// as used, the ray's box, and landings past bricks and cells.

fn is_clear(id: u32) -> bool {
    return ((aux[R.clear_off + (id >> 5u)] >> (id & 31u)) & 1u) == 1u;
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
    misses(id, 1u);
}

// `n` misses of brick `id` (consecutive misses of one brick go into the
// request table together).
fn misses(id: u32, n: u32) {
    if (id != miss_id) {
        flush_misses();
        miss_id = id;
    }
    miss_n = miss_n + n;
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
    if (R.region.w == 1u) {
        // A label image: the nearest voxel, with zero fractions (walk.rs's
        // `nearest`).
        return vec4<f32>(floor(q + vec3<f32>(0.5)), 0.0);
    }
    // A coordinate within f32 rounding of a voxel centre is that centre:
    // the CPU (f64 positions) samples the voxel's own value there, and a
    // fraction of ~1e-5 moved values exactly on a hard step of the
    // transfer function off it (tests/progressive_gpu.rs in brickyard).
    let r = round(q);
    return vec4<f32>(select(q, r, abs(q - r) < vec3<f32>(1e-4)), 0.0);
}

// Every level's bit: a mask that lets every coarser level substitute.
const ALL_LEVELS: u32 = 0xffffffffu;

// The value at world point `w` asked at level `level`, from the finest
// mapped level at or above it: (value, 0 unserved / 1 coarser / 2 exact).
// `q` and `e`: the voxel coordinates and page entry at `level`.
fn sample_from(w: vec3<f32>, level: u32, q: vec3<f32>, e: vec2<u32>) -> vec2<f32> {
    return sample_masked(w, level, q, e, ALL_LEVELS);
}

// `sample_from`, substituting on a miss only from the coarser levels whose
// bit `mask` has (the residency octree: the others have nothing mapped
// near the sample).
fn sample_masked(w: vec3<f32>, level: u32, q: vec3<f32>, e: vec2<u32>, mask: u32) -> vec2<f32> {
    var lq = q;
    var le = e;
    for (var lv = level; lv < R.levels; lv = lv + 1u) {
        if (lv > level) {
            if (((mask >> lv) & 1u) == 0u) {
                continue;
            }
            lq = coords(lv, w).xyz;
            le = coarse_entry_at(lv, vec3<u32>(lq));
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

// `entry_at` for a coarser level standing in, remembered apart: the
// samples of a ray served by a stand-in walk neither their own level's
// brick nor the stand-in's again at every step.
fn coarse_entry_at(level: u32, v: vec3<u32>) -> vec2<u32> {
    let b = v / lay.block[lay.nmax].xyz;
    let key = cur_idx * 32u + level;
    if (key != cmemo_key || any(b != cmemo_brick)) {
        cmemo_key = key;
        cmemo_brick = b;
        cmemo_entry = walk_marking(level, cur_ch, v);
    }
    return cmemo_entry;
}

fn sample_at(w: vec3<f32>, level: u32) -> vec2<f32> {
    let q = coords(level, w).xyz;
    return sample_from(w, level, q, entry_at(level, vec3<u32>(q)));
}

fn use_channel(i: u32) {
    cur_idx = i;
    cur_ch = aux[R.styles_off + 8u * i];
}

fn level_at(t: f32) -> u32 {
    if (R.lod_fixed != AUTO) {
        return min(R.lod_fixed, R.levels - 1u);
    }
    var fp = R.fp_const;
    if (R.perspective == 1u) {
        fp = R.fp_slope * t;
    }
    // (The rule's level, never finer than level 0, then the bias: as the
    // CPU twin's `Lod::level_for`.)
    let l = max(log2(fp / R.voxel0), 0.0) + R.lod_bias;
    if (l > 0.0 && l < 1e9) {
        return min(u32(floor(l)), R.levels - 1u);
    }
    return 0u;
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

// A sort-last region (`R.region.x == 1`): the span of the ray inside the
// box [R.clip_lo, R.clip_hi] (x, y, z; empty when y <= x), as the CPU's
// `intersect_box`; the samples of the whole ray's step grid in [x, y)
// are this region's. The same planes give the same t on both sides of a
// cut, so neighbouring regions split the samples exactly.
fn region_span(r: Ray) -> vec2<f32> {
    var t0 = 0.0;
    var t1 = 3.0e38;
    for (var a = 0u; a < 3u; a = a + 1u) {
        let o = r.o[a];
        let d = r.d[a];
        if (d == 0.0) {
            if (o < R.clip_lo[a] || o > R.clip_hi[a]) {
                return vec2<f32>(1.0, 0.0);
            }
            continue;
        }
        var ta = (R.clip_lo[a] - o) / d;
        var tb = (R.clip_hi[a] - o) / d;
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
    return land_at(brick_exit_t(r, level, b, min(t1, next_level_t(level))), base_t, k, level);
}

// `land` past the cell of base voxel `b` (inside its brick).
fn land_cell(r: Ray, level: u32, b: vec3<u32>, base_t: f32, k: u32, t1: f32) -> u32 {
    return land_at(cell_exit_t(r, level, b, min(t1, next_level_t(level))), base_t, k, level);
}

// Where the ray's voxel base at `level` leaves the brick of base voxel
// `b`, or `limit` if that comes first.
fn brick_exit_t(r: Ray, level: u32, b: vec3<u32>, limit: f32) -> f32 {
    let bs = lay.block[lay.nmax].xyz;
    let lo = (b / bs) * bs;
    return exit_t(r, level, lo, min(lo + bs, lay.dims[level].xyz), limit);
}

// Where it leaves the cell of base voxel `b` (inside its brick), or
// `limit` if that comes first.
fn cell_exit_t(r: Ray, level: u32, b: vec3<u32>, limit: f32) -> f32 {
    let bs = lay.block[lay.nmax].xyz;
    let b0 = (b / bs) * bs;
    let lo = b0 + ((b - b0) / R.cell_edge.xyz) * R.cell_edge.xyz;
    let hi = min(min(lo + R.cell_edge.xyz, b0 + bs), lay.dims[level].xyz);
    return exit_t(r, level, lo, hi, limit);
}

// After an unserved sample at step `k − 1` (base voxel `b` at `level`),
// as the CPU's `skip_unserved`: the step to go on from, the first past the
// brick (never past `limit`); the steps jumped are unserved samples and
// misses of the brick, added to the table at once. Without it, every step
// through a brick with nothing resident walks all levels and adds a miss
// per level: a first frame from cold did a few atomic adds per sample on
// a handful of table entries.
fn skip_unserved(r: Ray, level: u32, b: vec3<u32>, base_t: f32, k: u32, limit: f32) -> u32 {
    let kn = land_at(brick_exit_t(r, level, b, limit), base_t, k, level);
    if (kn > k) {
        misses(brick_id(level, b), kn - k);
    }
    return kn;
}

// The resident brick that serves a sample, for crossing its cells: its
// level, the sample's base voxel there, its pool slot (NONE: none serves)
// and the ray parameter no jump may pass.
struct Serving {
    level: u32,
    base: vec3<u32>,
    slot: u32,
    limit: f32,
}

// The finest resident brick standing in for the sample at `w` (base voxel
// `b` at `level`, whose brick is not resident), as the CPU's runs through
// a stand-in find it; its limit is also where the ray leaves the bricks
// not resident on the way (this level's and those between). Slot NONE
// when nothing resident stands in, or one value does (sampled as it is).
fn stand_in(r: Ray, level: u32, w: vec3<f32>, b: vec3<u32>, limit: f32) -> Serving {
    var c = Serving(level, b, NONE, limit);
    for (var lv = level; lv < R.levels; lv = lv + 1u) {
        if (lv > level) {
            c.level = lv;
            c.base = vec3<u32>(coords(lv, w).xyz);
            let le = coarse_entry_at(lv, c.base);
            let fl = flag(le);
            if (fl == MAPPED) {
                c.slot = slot_id(le, lay.brick_grid);
                return c;
            }
            if (fl == EMPTY || fl == CONSTANT) {
                return c;
            }
        }
        c.limit = brick_exit_t(r, lv, c.base, c.limit);
    }
    return c;
}

// The first step of `level`'s grid from `base_t` past ray parameter `te`
// (a hundredth of a step early), and never before step `k`.
fn land_at(te: f32, base_t: f32, k: u32, level: u32) -> u32 {
    let kn = ceil((te - base_t) / R.step[level].x - 0.5 - 0.01);
    if (kn > f32(k)) {
        return u32(kn);
    }
    return k;
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
