// Bounded request collection and the capped request list (request_insert.wgsl
// is appended). Twins of
// `brickyard_cache::bookkeeping::{RequestTable, prioritize}`.
//
//   insert: adds misses (brick id, samples) to an open-addressing table of
//           a power-of-two number of buckets (linear probing; a key that
//           finds no bucket is dropped and counted). Counts saturate.
//   sort:   one workgroup gathers the occupied buckets into `sorted` and
//           sorts them (bitonic, over the next power of two): most samples
//           first, then coarser levels, then ids in order. The host reads
//           back only the first min(cap, occupied) entries: the request
//           list. `dropped` holds [misses dropped, buckets occupied].

struct Params {
    buckets: u32,
    count: u32,
    levels: u32,
    pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> misses: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> keys: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> counts: array<atomic<u32>>;
@group(0) @binding(4) var<storage, read_write> dropped: array<atomic<u32>>;
@group(0) @binding(5) var<storage, read> level_starts: array<u32>;
@group(0) @binding(6) var<storage, read_write> sorted: array<vec2<u32>>;

const WG: u32 = 256u;

@compute @workgroup_size(256)
fn insert(@builtin(global_invocation_id) g: vec3<u32>, @builtin(num_workgroups) nw: vec3<u32>) {
    let i = g.x + g.y * nw.x * WG;
    if (i >= params.count) {
        return;
    }
    request_add(misses[i].x, misses[i].y, params.buckets);
}

fn level_of(id: u32) -> u32 {
    var l = 0u;
    for (var i = 1u; i < params.levels; i = i + 1u) {
        if (id >= level_starts[i]) {
            l = i;
        }
    }
    return l;
}

// Whether entry `a` comes before entry `b` in the request list.
fn before(a: vec2<u32>, b: vec2<u32>) -> bool {
    if (a.x == NO_BRICK) {
        return false;
    }
    if (b.x == NO_BRICK) {
        return true;
    }
    if (a.y != b.y) {
        return a.y > b.y;
    }
    let la = level_of(a.x);
    let lb = level_of(b.x);
    if (la != lb) {
        return la > lb;
    }
    return a.x < b.x;
}

var<workgroup> occupied: u32;
var<workgroup> placed: atomic<u32>;

@compute @workgroup_size(256)
fn sort(@builtin(local_invocation_index) t: u32) {
    // The occupied buckets first (in any order), padded with empty entries
    // to a power of two; then only those are sorted.
    if (t == 0u) {
        occupied = atomicLoad(&dropped[1]);
    }
    let m = workgroupUniformLoad(&occupied);
    var n = 1u;
    while (n < m) {
        n = n * 2u;
    }
    for (var i = t; i < params.buckets; i = i + WG) {
        let key = atomicLoad(&keys[i]);
        if (key != NO_BRICK) {
            sorted[atomicAdd(&placed, 1u)] = vec2<u32>(key, atomicLoad(&counts[i]));
        }
    }
    for (var i = m + t; i < n; i = i + WG) {
        sorted[i] = vec2<u32>(NO_BRICK, 0u);
    }
    storageBarrier();
    for (var k = 2u; k <= n; k = k * 2u) {
        for (var j = k / 2u; j > 0u; j = j / 2u) {
            for (var i = t; i < n; i = i + WG) {
                let l = i ^ j;
                if (l > i) {
                    let a = sorted[i];
                    let b = sorted[l];
                    var swap = before(a, b);
                    if ((i & k) == 0u) {
                        swap = before(b, a);
                    }
                    if (swap) {
                        sorted[i] = b;
                        sorted[l] = a;
                    }
                }
            }
            storageBarrier();
        }
    }
}
