// Order-preserving compaction of the LRU order: the slots used in this
// frame first, then the others, each group in its previous order. Twin of
// `brickyard_cache::bookkeeping::compact_lru`.
//
// Three passes over blocks of 1024 entries (256 invocations × 4):
//   scan_blocks: per entry, the used entries before it in its block; per
//                block, its count;
//   scan_sums:   exclusive prefix of the block counts (one workgroup), and
//                the total after the last block;
//   scatter:     each entry to its place.

struct Params {
    n: u32,
    frame: u32,
    blocks: u32,
    // Slot i's stamp is usage[stride * (base + i) + word] (the device
    // cache keeps every set's stamps in one buffer, two words a slot).
    base: u32,
    stride: u32,
    word: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> order_in: array<u32>;
@group(0) @binding(2) var<storage, read> usage: array<u32>;
@group(0) @binding(3) var<storage, read_write> prefix: array<u32>;
@group(0) @binding(4) var<storage, read_write> block_sums: array<u32>;
@group(0) @binding(5) var<storage, read_write> order_out: array<u32>;

const WG: u32 = 256u;
const PER: u32 = 4u;
const BLOCK: u32 = 1024u;

var<workgroup> sums: array<u32, 256>;

fn used(i: u32) -> u32 {
    if (i < params.n && usage[params.stride * (params.base + order_in[i]) + params.word] == params.frame) {
        return 1u;
    }
    return 0u;
}

// Inclusive scan of `sums` (every invocation of the workgroup calls it).
fn scan_workgroup(t: u32) {
    for (var off = 1u; off < WG; off = off * 2u) {
        var v = 0u;
        if (t >= off) {
            v = sums[t - off];
        }
        workgroupBarrier();
        sums[t] = sums[t] + v;
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn scan_blocks(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let base = wg.x * BLOCK + t * PER;
    var f: array<u32, 4>;
    var s = 0u;
    for (var k = 0u; k < PER; k = k + 1u) {
        f[k] = used(base + k);
        s = s + f[k];
    }
    sums[t] = s;
    workgroupBarrier();
    scan_workgroup(t);
    var run = sums[t] - s;
    for (var k = 0u; k < PER; k = k + 1u) {
        if (base + k < params.n) {
            prefix[base + k] = run;
        }
        run = run + f[k];
    }
    if (t == WG - 1u) {
        block_sums[wg.x] = sums[WG - 1u];
    }
}

@compute @workgroup_size(256)
fn scan_sums(@builtin(local_invocation_index) t: u32) {
    var carry = 0u;
    for (var c = 0u; c < params.blocks; c = c + WG) {
        let i = c + t;
        var v = 0u;
        if (i < params.blocks) {
            v = block_sums[i];
        }
        sums[t] = v;
        workgroupBarrier();
        scan_workgroup(t);
        if (i < params.blocks) {
            block_sums[i] = carry + sums[t] - v;
        }
        carry = carry + sums[WG - 1u];
        workgroupBarrier();
    }
    if (t == 0u) {
        block_sums[params.blocks] = carry;
    }
}

@compute @workgroup_size(256)
fn scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let total = block_sums[params.blocks];
    let offset = block_sums[wg.x];
    for (var k = 0u; k < PER; k = k + 1u) {
        let i = wg.x * BLOCK + t * PER + k;
        if (i < params.n) {
            let p = offset + prefix[i];
            var dst = total + i - p;
            if (used(i) == 1u) {
                dst = p;
            }
            order_out[dst] = order_in[i];
        }
    }
}
