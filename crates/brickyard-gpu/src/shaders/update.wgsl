// The update step on the device: which slots new bricks take, and their
// references in the page tables. Twin of `update::UpdateModel`.
//
// Slot sets: 0 is the brick pool, n (1 ..= nmax-1) the cache of
// intermediate level n. Per slot of every set: two usage stamps (frame last
// used; for the pool, also frame last used at its own level) and its owner
// (index in `entries` of the entry that maps it, NONE if none). A slot is
// unmapped only through its owner, and only if that entry still maps it:
// a slot orphaned with its parent block keeps a stale owner that may by
// now hold another mapping.
//
// Per frame, after the renderer has stamped what it used:
//   compaction of every set's LRU order (lru.wgsl; the pool by the frame
//             last used at its own level, so stand-ins for finer bricks
//             age and give way to them);
//   reserve:  the k least recently used pool slots not used at their own
//             level this frame, unmapped from their owners (the host
//             writes the bricks);
//   start:    each item's directory entry;
//   per intermediate level n:
//     path:    stamp the blocks of level n the items pass through (so none
//              of them is taken below), then compaction of set n again;
//     claim:   items whose entry is not mapped claim it in a hash table;
//              the lowest item index wins;
//     assign:  the winners in item order take the least recently used
//              blocks not used this frame (one workgroup, a scan);
//     take:    each winner unmaps its block from the old owner, clears it
//              and maps it into its entry: one block per entry, never two;
//     descend: every item moves to its entry in the block of level n;
//   finish:   each item's entry is set: mapped to its slot, empty or
//             constant (left alone if something is there already).
// After reserve, and after take at each level, `rotate` moves the slots
// just taken to the front of their order (most recently used).

struct Params {
    frame: u32,
    // Items, or slots to reserve.
    k: u32,
    // Intermediate level of this pass.
    n: u32,
    // Buckets of the claim table (a power of two).
    h: u32,
    // Frames, this one included, whose use at its own level makes an
    // evicted brick count as in use (word 15 of `out`).
    in_use: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

struct Item {
    level: u32,
    channel: u32,
    // 1: data (slot in brick.w), 2: empty, 3: constant (bits in value).
    kind: u32,
    value: u32,
    // Brick coordinates [z, y, x] and, for data, the pool slot.
    brick: vec4<u32>,
    // Index of the item's entry at the current level (NONE: failed).
    cursor: u32,
    // The block this item takes at the current level (NONE: none).
    leader: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(3) var<uniform> P: Params;
@group(0) @binding(4) var<storage, read_write> stamps: array<u32>;
@group(0) @binding(5) var<storage, read_write> owner: array<u32>;
@group(0) @binding(6) var<storage, read> order: array<u32>;
@group(0) @binding(7) var<storage, read_write> items: array<Item>;
@group(0) @binding(8) var<storage, read_write> claims: array<atomic<u32>>;
// Counters (cumulative): 0 bricks unmapped, 1 blocks unmapped, 2 bricks
// mapped, 3 flags set, 4 items failed, 5 blocks mapped; this frame: 6 pool
// slots used at their own level, 7 pool slots reserved, 8 + n blocks taken
// at level n (n < 7), 15 bricks evicted that a frame among the last
// `P.in_use` used at their own level; from 16 on the reserved slots.
@group(0) @binding(9) var<storage, read_write> out: array<atomic<u32>>;

const RESERVED: u32 = 16u;

// Where the count of slots of set `which` taken this frame is kept.
fn taken_index(which: u32) -> u32 {
    if (which == 0u) {
        return 7u;
    }
    return 8u + which;
}

fn mapped_word(s: u32, g: vec4<u32>) -> u32 {
    let z = s / (g.z * g.y);
    let y = (s / g.z) % g.y;
    let x = s % g.z;
    return (MAPPED << FLAG_SHIFT) | (z << 20u) | (y << 10u) | x;
}

fn maps(e: vec2<u32>, s: u32, g: vec4<u32>) -> bool {
    return flag(e) == MAPPED && slot_id(e, g) == s;
}

fn voxel_of(it: Item) -> vec3<u32> {
    return it.brick.xyz * lay.block[lay.nmax].xyz;
}

@compute @workgroup_size(64)
fn reserve(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= P.k) {
        return;
    }
    let cnt = lay.set_base[0].y;
    if (i >= cnt) {
        atomicStore(&out[RESERVED + i], NONE);
        return;
    }
    // Slots used at their own level come first after compaction: the
    // tail up to the first of them may be taken (bricks that only stood
    // in for finer ones this frame included).
    let s = order[cnt - 1u - i];
    if (stamps[2u * s + 1u] == P.frame) {
        atomicStore(&out[RESERVED + i], NONE);
        return;
    }
    let o = owner[s];
    if (o != NONE && maps(entries[o], s, lay.brick_grid)) {
        entries[o] = vec2<u32>(0u, 0u);
        atomicAdd(&out[0], 1u);
        let used = stamps[2u * s + 1u];
        if (used != 0u && P.frame - used < P.in_use) {
            atomicAdd(&out[15], 1u);
        }
    }
    owner[s] = NONE;
    stamps[2u * s] = P.frame;
    stamps[2u * s + 1u] = P.frame;
    atomicStore(&out[RESERVED + i], s);
    atomicAdd(&out[7], 1u);
}

// The slots just taken (the tail of set `P.n`'s order) become the most
// recently used: the order rotated by their count, into `claims` (copied
// back by the host). Otherwise a fresh brick that the next frame does not
// use (another view is drawn, say) would sit at the tail, behind slots
// never used, and be taken again at once.
@compute @workgroup_size(64)
fn rotate(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    let cnt = lay.set_base[P.n].y;
    if (i >= cnt) {
        return;
    }
    let r = atomicLoad(&out[taken_index(P.n)]);
    atomicStore(&claims[i], order[(i + cnt - r % cnt) % cnt]);
}

@compute @workgroup_size(64)
fn start(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= P.k) {
        return;
    }
    let it = items[i];
    let d = lay.dir_base[it.level].xyz + voxel_of(it) / lay.span[0].xyz;
    let dd = lay.dir_dims;
    items[i].cursor = it.channel * lay.dir_len + (d.x * dd.y + d.y) * dd.z + d.z;
    items[i].leader = NONE;
}

@compute @workgroup_size(64)
fn path(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= P.k) {
        return;
    }
    let p = items[i].cursor;
    if (p == NONE) {
        return;
    }
    let e = entries[p];
    if (flag(e) == MAPPED) {
        let b = slot_id(e, lay.pt_grid[P.n]);
        stamps[2u * (lay.set_base[P.n].x + b)] = P.frame;
    }
}

fn bucket_of(p: u32) -> u32 {
    return (p * 2654435761u) & (P.h - 1u);
}

@compute @workgroup_size(64)
fn claim(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= P.k) {
        return;
    }
    let p = items[i].cursor;
    if (p == NONE || flag(entries[p]) == MAPPED) {
        return;
    }
    var b = bucket_of(p);
    // At most k distinct keys in at least 2k buckets: a free one exists.
    for (var tries = 0u; tries < 2u * P.h; tries = tries + 1u) {
        let r = atomicCompareExchangeWeak(&claims[2u * b], 0u, p + 1u);
        if (r.exchanged || r.old_value == p + 1u) {
            // Largest complement: smallest item index.
            atomicMax(&claims[2u * b + 1u], ~i);
            return;
        }
        if (r.old_value != 0u) {
            b = (b + 1u) & (P.h - 1u);
        }
    }
}

fn claimed_by(p: u32) -> u32 {
    var b = bucket_of(p);
    for (var tries = 0u; tries < P.h; tries = tries + 1u) {
        let key = atomicLoad(&claims[2u * b]);
        if (key == p + 1u) {
            return ~atomicLoad(&claims[2u * b + 1u]);
        }
        if (key == 0u) {
            return NONE;
        }
        b = (b + 1u) & (P.h - 1u);
    }
    return NONE;
}

var<workgroup> sums: array<u32, 256>;

@compute @workgroup_size(256)
fn assign(@builtin(local_invocation_index) t: u32) {
    let cnt = lay.set_base[P.n].y;
    let base = lay.set_base[P.n].x;
    var carry = 0u;
    for (var c = 0u; c < P.k; c = c + 256u) {
        let i = c + t;
        var lead = 0u;
        if (i < P.k) {
            let p = items[i].cursor;
            if (p != NONE && flag(entries[p]) != MAPPED && claimed_by(p) == i) {
                lead = 1u;
            }
        }
        sums[t] = lead;
        workgroupBarrier();
        for (var off = 1u; off < 256u; off = off * 2u) {
            var v = 0u;
            if (t >= off) {
                v = sums[t - off];
            }
            workgroupBarrier();
            sums[t] = sums[t] + v;
            workgroupBarrier();
        }
        if (i < P.k) {
            var block = NONE;
            if (lead == 1u) {
                let r = carry + sums[t] - 1u;
                if (r < cnt) {
                    let b = order[cnt - 1u - r];
                    if (stamps[2u * (base + b)] != P.frame) {
                        block = b;
                    }
                }
            }
            items[i].leader = block;
        }
        carry = carry + sums[255];
        workgroupBarrier();
    }
}

@compute @workgroup_size(64)
fn take(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= P.k) {
        return;
    }
    let b = items[i].leader;
    if (b == NONE) {
        return;
    }
    let p = items[i].cursor;
    let g = lay.pt_grid[P.n];
    let base = lay.set_base[P.n].x;
    let o = owner[base + b];
    if (o != NONE && maps(entries[o], b, g)) {
        entries[o] = vec2<u32>(0u, 0u);
        atomicAdd(&out[1], 1u);
    }
    owner[base + b] = p;
    stamps[2u * (base + b)] = P.frame;
    // A fresh block: what the old one mapped is orphaned (its slots keep
    // stale owners and age out of their LRU orders).
    let len = g.w;
    let first = lay.table_off[P.n].x + b * len;
    var orphans = 0u;
    for (var j = 0u; j < len; j = j + 1u) {
        if (flag(entries[first + j]) == MAPPED) {
            orphans = orphans + 1u;
        }
        entries[first + j] = vec2<u32>(0u, 0u);
    }
    if (P.n + 1u == lay.nmax) {
        atomicAdd(&out[0], orphans);
    } else {
        atomicAdd(&out[1], orphans);
    }
    entries[p] = vec2<u32>(mapped_word(b, g), 0u);
    atomicAdd(&out[5], 1u);
    atomicAdd(&out[taken_index(P.n)], 1u);
}

@compute @workgroup_size(64)
fn descend(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= P.k) {
        return;
    }
    let it = items[i];
    if (it.cursor == NONE) {
        return;
    }
    let e = entries[it.cursor];
    if (flag(e) != MAPPED) {
        items[i].cursor = NONE;
        atomicAdd(&out[4], 1u);
        return;
    }
    let n = P.n;
    let b = slot_id(e, lay.pt_grid[n]);
    let o = (voxel_of(it) / lay.span[n].xyz) % lay.block[n].xyz;
    let bl = lay.block[n];
    let j = (o.x * bl.y + o.y) * bl.z + o.z;
    items[i].cursor = lay.table_off[n].x + b * lay.pt_grid[n].w + j;
}

@compute @workgroup_size(64)
fn finish(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= P.k) {
        return;
    }
    let it = items[i];
    let p = it.cursor;
    if (p == NONE || flag(entries[p]) != 0u) {
        return;
    }
    switch it.kind {
        case 1u: {
            let s = it.brick.w;
            entries[p] = vec2<u32>(mapped_word(s, lay.brick_grid), 0u);
            owner[s] = p;
            stamps[2u * s] = P.frame;
            stamps[2u * s + 1u] = P.frame;
            atomicAdd(&out[2], 1u);
        }
        case 2u: {
            entries[p] = vec2<u32>(EMPTY << FLAG_SHIFT, 0u);
            atomicAdd(&out[3], 1u);
        }
        default: {
            entries[p] = vec2<u32>(CONSTANT << FLAG_SHIFT, it.value);
            atomicAdd(&out[3], 1u);
        }
    }
}
