// Kernels of the device's page tables: entry updates (the host's changes),
// the page-table walk and the sampler. Twins of
// `brickyard_cache::vm::VirtualMemory::{entry_of, sample_at}`. Appended to
// vm_common.wgsl.

struct Query {
    level: u32,
    channel: u32,
    pad0: u32,
    pad1: u32,
    // Voxel (base) `[z, y, x]`.
    v: vec4<u32>,
    // Fractions `[z, y, x]`.
    frac: vec4<f32>,
}

// Updates: (entry index, word, value, unused).
@group(0) @binding(3) var<storage, read> updates: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read> queries: array<Query>;
@group(0) @binding(5) var<storage, read_write> results: array<vec4<u32>>;

@compute @workgroup_size(64)
fn apply(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= lay.count) {
        return;
    }
    let u = updates[g.x];
    entries[u.x] = vec2<u32>(u.y, u.z);
}

// results[i] = (word, value, brick slot id or NONE, 0).
@compute @workgroup_size(64)
fn lookup(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= lay.count) {
        return;
    }
    let q = queries[g.x];
    let e = walk(q.level, q.channel, q.v.xyz);
    var s = NONE;
    if (flag(e) == MAPPED) {
        s = slot_id(e, lay.brick_grid);
    }
    results[g.x] = vec4<u32>(e.x, e.y, s, 0u);
}

// results[i] = (value bits, 1 if mapped else 0, 0, 0).
@compute @workgroup_size(64)
fn sample(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= lay.count) {
        return;
    }
    let q = queries[g.x];
    let r = value_of(walk(q.level, q.channel, q.v.xyz), q.v.xyz, q.frac.xyz);
    results[g.x] = vec4<u32>(bitcast<u32>(r.x), u32(r.y), 0u, 0u);
}
