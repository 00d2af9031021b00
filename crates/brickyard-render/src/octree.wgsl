// The residency octree's passes on the device, twins of `octree.rs`
// (`Octree::pass`, `Octree::new`'s ranges): counters of mapped bricks per
// leaf, channel and level changed by map/evict events; leaf masks from
// the counters; inner masks as the OR of their children, one depth at a
// time; node ranges per level: leaves from the bricks they overlap,
// inner nodes as the union of their children. Layouts as on the host:
// node index = level-order offset (8^d − 1)/7 + (z·2^d + y)·2^d + x.

struct Params {
    depth: u32,
    channels: u32,
    levels: u32,
    // Events (apply_events) or nodes of depth `d` (or_up, union_up).
    count: u32,
    d: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
    brick: vec4<u32>,
    // Per level: voxels z, y, x; w: offset of its brick ranges
    // ([channel][z][y][x]) in `brick_ranges`, NONE when unknown.
    dims: array<vec4<u32>, 32>,
    // Per level: its ratio to level 0 (z, y, x): the level spans
    // dims[0] / ratio of its voxels across the extent (`Octree::span`).
    ratio: array<vec4<u32>, 32>,
}

@group(0) @binding(0) var<uniform> params: Params;
// Per event: level | channel << 8 | mapped << 31, then brick z, y, x.
@group(0) @binding(1) var<storage, read> events: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read_write> counts: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> masks: array<u32>;
@group(0) @binding(4) var<storage, read> brick_ranges: array<vec2<f32>>;
@group(0) @binding(5) var<storage, read_write> ranges: array<vec2<f32>>;

const NONE: u32 = 0xffffffffu;

fn node_offset(d: u32) -> u32 {
    return ((1u << (3u * d)) - 1u) / 7u;
}

fn is_nan(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7fffffffu) > 0x7f800000u;
}

// A quiet NaN, made at run time: browsers' WGSL compilers refuse a NaN
// constant.
fn nan() -> f32 {
    return bitcast<f32>(0x7fc00000u | (params.pad2 & 0u));
}

// The union of two ranges; NaN (unknown) wins.
fn union2(a: vec2<f32>, b: vec2<f32>) -> vec2<f32> {
    if (is_nan(a.x) || is_nan(a.y) || is_nan(b.x) || is_nan(b.y)) {
        return vec2<f32>(nan(), nan());
    }
    return vec2<f32>(min(a.x, b.x), max(a.y, b.y));
}

fn flat(wg: vec3<u32>, t: u32) -> u32 {
    return (wg.y * 65535u + wg.x) * 64u + t;
}

// One invocation per event: every leaf the brick overlaps, its counter
// for the brick's channel and level up or down by one.
@compute @workgroup_size(64)
fn apply_events(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let i = flat(wg, t);
    if (i >= params.count) {
        return;
    }
    let e = events[i];
    let l = e.x & 0xffu;
    let c = (e.x >> 8u) & 0xffffu;
    let mapped = (e.x >> 31u) != 0u;
    let n = 1u << params.depth;
    let dims = params.dims[l].xyz;
    let num = params.dims[0].xyz;
    let den = params.ratio[l].xyz;
    let b = e.yzw;
    var lo: vec3<u32>;
    var hi: vec3<u32>;
    for (var a = 0u; a < 3u; a++) {
        let v0 = b[a] * params.brick[a];
        let v1 = min((b[a] + 1u) * params.brick[a], dims[a]);
        // Leaves i with i·num < v1·n·den and v0·n·den < (i + 1)·num.
        lo[a] = min((v0 * n * den[a]) / num[a], n);
        hi[a] = min((v1 * n * den[a] + num[a] - 1u) / num[a], n);
    }
    for (var z = lo.x; z < hi.x; z++) {
        for (var y = lo.y; y < hi.y; y++) {
            for (var x = lo.z; x < hi.z; x++) {
                let leaf = (z * n + y) * n + x;
                let k = (leaf * params.channels + c) * params.levels + l;
                if (mapped) {
                    atomicAdd(&counts[k], 1u);
                } else {
                    atomicSub(&counts[k], 1u);
                }
            }
        }
    }
}

// One invocation per leaf and channel: bit l when its counter of level l
// is not zero.
@compute @workgroup_size(64)
fn leaf_masks(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let i = flat(wg, t);
    let n = 1u << params.depth;
    if (i >= n * n * n * params.channels) {
        return;
    }
    var m = 0u;
    for (var l = 0u; l < params.levels; l++) {
        if (atomicLoad(&counts[i * params.levels + l]) > 0u) {
            m = m | (1u << l);
        }
    }
    masks[node_offset(params.depth) * params.channels + i] = m;
}

// Children of node `p` (index within depth d) of depth d: index within
// depth d + 1 of child k.
fn child(p: u32, d: u32, k: u32) -> u32 {
    let s = 1u << d;
    let z = p / (s * s);
    let y = (p / s) % s;
    let x = p % s;
    let m = 2u * s;
    return ((2u * z + (k >> 2u)) * m + 2u * y + ((k >> 1u) & 1u)) * m + 2u * x + (k & 1u);
}

// One invocation per node of depth d and channel: the OR of its children.
@compute @workgroup_size(64)
fn or_up(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let i = flat(wg, t);
    if (i >= params.count * params.channels) {
        return;
    }
    let p = i / params.channels;
    let c = i % params.channels;
    let d = params.d;
    var m = 0u;
    for (var k = 0u; k < 8u; k++) {
        m = m | masks[(node_offset(d + 1u) + child(p, d, k)) * params.channels + c];
    }
    masks[(node_offset(d) + p) * params.channels + c] = m;
}

// One invocation per leaf, channel and level: the union of the ranges of
// the level's bricks that overlap the leaf (NaN without statistics).
@compute @workgroup_size(64)
fn leaf_ranges(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let i = flat(wg, t);
    let n = 1u << params.depth;
    let nl = params.levels;
    if (i >= n * n * n * params.channels * nl) {
        return;
    }
    let l = i % nl;
    let c = (i / nl) % params.channels;
    let leaf = i / (nl * params.channels);
    let out = (node_offset(params.depth) * params.channels) * nl + i;
    let dl = params.dims[l];
    if (dl.w == NONE) {
        ranges[out] = vec2<f32>(nan(), nan());
        return;
    }
    let q = vec3<u32>(leaf / (n * n), (leaf / n) % n, leaf % n);
    let num = params.dims[0].xyz;
    let den = params.ratio[l].xyz;
    var lo: vec3<u32>;
    var hi: vec3<u32>;
    var nb: vec3<u32>;
    for (var a = 0u; a < 3u; a++) {
        let bs = params.brick[a];
        nb[a] = (dl[a] + bs - 1u) / bs;
        // The leaf's voxels [v0, v1) (`Octree::bricks_of_leaf`), then
        // the bricks holding them.
        let v0 = (q[a] * num[a]) / (den[a] << params.depth);
        let v1 = ((q[a] + 1u) * num[a] + (den[a] << params.depth) - 1u) / (den[a] << params.depth);
        lo[a] = v0 / bs;
        hi[a] = min((v1 + bs - 1u) / bs, nb[a]);
    }
    let inf = bitcast<f32>(0x7f800000u | (params.pad2 & 0u));
    var acc = vec2<f32>(inf, -inf);
    for (var z = lo.x; z < hi.x; z++) {
        for (var y = lo.y; y < hi.y; y++) {
            for (var x = lo.z; x < hi.z; x++) {
                let b = ((c * nb.x + z) * nb.y + y) * nb.z + x;
                acc = union2(acc, brick_ranges[dl.w + b]);
            }
        }
    }
    ranges[out] = acc;
}

// One invocation per node of depth d, channel and level: the union of
// its children.
@compute @workgroup_size(64)
fn union_up(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let i = flat(wg, t);
    let nl = params.levels;
    let per = params.channels * nl;
    if (i >= params.count * per) {
        return;
    }
    let p = i / per;
    let r = i % per;
    let d = params.d;
    let inf = bitcast<f32>(0x7f800000u | (params.pad2 & 0u));
    var acc = vec2<f32>(inf, -inf);
    for (var k = 0u; k < 8u; k++) {
        acc = union2(acc, ranges[(node_offset(d + 1u) + child(p, d, k)) * per + r]);
    }
    ranges[(node_offset(d) + p) * per + r] = acc;
}
