// The virtual memory's page tables on the device: the layout, the
// page-table walk and trilinear sampling from the pool. Shared by the
// kernels of vm.wgsl and the renderers (the file is prepended to theirs;
// it owns bindings 0–2 of group 0).
//
// Entries are `vec2<u32>` (word, value) as on the host: flag in bits
// 30–31 of the word (0 unmapped, 1 mapped, 2 empty, 3 constant), a mapped
// entry's slot in blocks `[z, y, x]` in 3 × 10 bits, a constant's value
// bits in `value`. All tables live in one buffer: the directory
// (channel-major) first, then the cache of each intermediate level.
// Vectors of three coordinates are `[z, y, x]` in `.xyz`.

struct Layout {
    levels: u32,
    nmax: u32,
    channels: u32,
    dir_len: u32,
    apron: u32,
    // Texel × scale = voxel value.
    scale: f32,
    count: u32,
    // 0: unsigned, 1: signed, 2: float (how constants are decoded).
    value_kind: u32,
    dir_dims: vec4<u32>,
    // Slot grid of the brick pool as page entries address it.
    brick_grid: vec4<u32>,
    // Slot grid of the pool texture.
    dev_grid: vec4<u32>,
    padded: vec4<u32>,
    dims: array<vec4<u32>, 16>,
    dir_base: array<vec4<u32>, 16>,
    // Voxels covered by one entry of level n (n = 0 ..= nmax).
    span: array<vec4<u32>, 8>,
    // Block of level n (n = 1 ..= nmax).
    block: array<vec4<u32>, 8>,
    // Slot grid of the cache of intermediate level n; .w: entries a block.
    pt_grid: array<vec4<u32>, 8>,
    // .x: first entry of table n (0: the directory).
    table_off: array<vec4<u32>, 8>,
    // Per slot set (0: the brick pool, n: the cache of intermediate level
    // n): .x its first slot in the per-slot arrays of all sets (usage
    // stamps, owners), .y its slots.
    set_base: array<vec4<u32>, 8>,
}

@group(0) @binding(0) var<uniform> lay: Layout;
@group(0) @binding(1) var<storage, read_write> entries: array<vec2<u32>>;
@group(0) @binding(2) var pool: texture_3d<f32>;

const FLAG_SHIFT: u32 = 30u;
const MAPPED: u32 = 1u;
const EMPTY: u32 = 2u;
const CONSTANT: u32 = 3u;
const SLOT_MASK: u32 = 0x3ffu;
const NONE: u32 = 0xffffffffu;

fn flag(e: vec2<u32>) -> u32 {
    return e.x >> FLAG_SHIFT;
}

// Slot id of a mapped entry in a slot grid `g` (`[z, y, x]`).
fn slot_id(e: vec2<u32>, g: vec4<u32>) -> u32 {
    let z = (e.x >> 20u) & SLOT_MASK;
    let y = (e.x >> 10u) & SLOT_MASK;
    let x = e.x & SLOT_MASK;
    return (z * g.y + y) * g.z + x;
}

// The entry for the brick of voxel `v` of level `l`, channel `c`: the
// first non-mapped entry on the way down, or the brick's.
fn walk(l: u32, c: u32, v: vec3<u32>) -> vec2<u32> {
    let d = lay.dir_base[l].xyz + v / lay.span[0].xyz;
    let dd = lay.dir_dims;
    var e = entries[c * lay.dir_len + (d.x * dd.y + d.y) * dd.z + d.z];
    for (var n = 1u; n < lay.nmax; n = n + 1u) {
        if (flag(e) != MAPPED) {
            return e;
        }
        let b = slot_id(e, lay.pt_grid[n]);
        let o = (v / lay.span[n].xyz) % lay.block[n].xyz;
        let bl = lay.block[n];
        let i = (o.x * bl.y + o.y) * bl.z + o.z;
        e = entries[lay.table_off[n].x + b * lay.pt_grid[n].w + i];
    }
    return e;
}

fn constant_value(bits: u32) -> f32 {
    if (lay.value_kind == 0u) {
        return f32(bits);
    }
    if (lay.value_kind == 1u) {
        return f32(bitcast<i32>(bits));
    }
    return bitcast<f32>(bits);
}

fn texel(p: vec3<u32>) -> f32 {
    // Texture coordinates are (x, y, z).
    return textureLoad(pool, vec3<i32>(p.zyx), 0).x * lay.scale;
}

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    if (t == 0.0) {
        return a;
    }
    return a + (b - a) * t;
}

// Trilinear sample in brick slot `s` at level voxel `v` + `f`: the
// corners are the voxel and its +1 neighbours, in the brick's apron at
// its far faces. Lerps along x, then y, then z, as every sampler does.
fn trilinear_in(s: u32, v: vec3<u32>, f: vec3<f32>) -> f32 {
    let g = lay.dev_grid;
    let slot = vec3<u32>(s / (g.z * g.y), (s / g.z) % g.y, s % g.z);
    let p = slot * lay.padded.xyz + v % lay.block[lay.nmax].xyz + vec3<u32>(lay.apron);
    let x00 = lerp(texel(p), texel(p + vec3<u32>(0u, 0u, 1u)), f.z);
    let x01 = lerp(texel(p + vec3<u32>(0u, 1u, 0u)), texel(p + vec3<u32>(0u, 1u, 1u)), f.z);
    let x10 = lerp(texel(p + vec3<u32>(1u, 0u, 0u)), texel(p + vec3<u32>(1u, 0u, 1u)), f.z);
    let x11 = lerp(texel(p + vec3<u32>(1u, 1u, 0u)), texel(p + vec3<u32>(1u, 1u, 1u)), f.z);
    let y0 = lerp(x00, x01, f.y);
    let y1 = lerp(x10, x11, f.y);
    return lerp(y0, y1, f.x);
}

// The value an entry gives at level voxel `v` + `f`: (value, mapped).
fn value_of(e: vec2<u32>, v: vec3<u32>, f: vec3<f32>) -> vec2<f32> {
    switch flag(e) {
        case 1u: {
            return vec2<f32>(trilinear_in(slot_id(e, lay.brick_grid), v, f), 1.0);
        }
        case 2u: {
            return vec2<f32>(0.0, 1.0);
        }
        case 3u: {
            return vec2<f32>(constant_value(e.y), 1.0);
        }
        default: {
            return vec2<f32>(0.0, 0.0);
        }
    }
}
