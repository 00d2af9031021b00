// The device's frame driver: ray-guided DVR, MIP and slices through the
// virtual memory, twin of `cpu.rs` (same rays, steps, levels, fallback and
// compositing, in f32 where the CPU uses f64 for positions). This file
// declares the render uniform, the bindings and the per-invocation state,
// makes each pixel's ray and hands it to its mode; `gpu.rs` appends
// optics.wgsl, walk.wgsl, slice.wgsl, superslice.wgsl, mip.wgsl, dvr.wgsl and multi.wgsl to it, all
// after vm_common.wgsl (bindings 0–2: layout, page tables, pool) and
// before request_insert.wgsl.
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
    // DVR: gradient shading of samples (1) or not (0); its parameters in
    // `shading`.
    shade: u32,
    // Cells per brick and axis, voxels per cell edge (z, y, x).
    cell_count: vec4<u32>,
    cell_edge: vec4<u32>,
    // Several channels (slice, MIP: added up; DVR: composited, see
    // multi.wgsl): how many (0: one channel through the transfer function)
    // and where their styles start in `aux` (8 words each; slice, MIP:
    // channel, lo, hi, 0, r, g, b, 0).
    n_channels: u32,
    styles_off: u32,
    // Views side by side (1: one) and the width of each.
    n_views: u32,
    view_width: u32,
    // Slice: a point of the plane and its unit normal (x, y, z).
    plane_origin: vec4<f32>,
    plane_normal: vec4<f32>,
    // Shading: ambient, diffuse, specular, shininess.
    shading: vec4<f32>,
    // Sample accumulation (savr.wgsl): frames asked for, samples a pixel
    // keeps, 0, normals kept (1); where the runs, values, flags and
    // cosines start in the store; the reference step.
    acc: vec4<u32>,
    acc_off: vec4<u32>,
    acc_ref: vec4<f32>,
    // Views: eye separation, distance to the target plane, super-slice
    // parallax (pixels) and slice spacing (world).
    views: vec4<f32>,
    // The first view of the image (a view drawn alone), 0, 0, 0.
    view_sel: vec4<u32>,
    // DVR through the residency octree (octree/dvr.wgsl): where its node
    // table, masks and deepest depths per level start in `aux`; w: the
    // volume's channels (the masks' stride) when the octree is traversed,
    // 0 otherwise.
    oct: vec4<u32>,
    // Per level: voxels per world unit (z, y, x); w unused.
    scale: array<vec4<f32>, 16>,
    // Per level: last voxel index (z, y, x) as floats.
    qmax: array<vec4<f32>, 16>,
    // Per level: (step, opacity-correction exponent, 0, 0).
    step: array<vec4<f32>, 16>,
    // Per level: bricks per axis (z, y, x); w: first brick id of the level.
    bricks: array<vec4<u32>, 16>,
    // A sort-last region (DVR and MIP of one channel): the world box
    // (x, y, z) whose samples the rays take (walk.wgsl's `region_span`).
    clip_lo: vec4<f32>,
    clip_hi: vec4<f32>,
    // x: the box applies (1); y: no early ray termination (1); z: MIP
    // pixels are (raw maximum, 0, 0, 1), (NaN, 0, 0, 1) when no sample
    // was served, 0 where the ray takes no sample (1); w: a label image
    // (1): nearest voxels, a colour per label (slices; DVR mode: the
    // first label along the ray, labels.wgsl).
    region: vec4<u32>,
    // x: only pixel rows [y, z) are drawn, the others transparent (1): an
    // image-parallel band; w: 0.
    rows: vec4<u32>,
    // A label image's selection: every label (x = 0), only those listed
    // (1) or all but them (2); the list's start in `aux` (increasing,
    // i32 bits) and length; 0.
    label_sel: vec4<u32>,
    // Sample accumulation: the band of image rows this dispatch draws
    // (its store is the image binding): first row, rows; 0, 0.
    acc_band: vec4<u32>,
}

@group(0) @binding(3) var<uniform> R: Render;
// The transfer function's opacity points (x, alpha, 0, 0) and colour-map
// points (x, r, g, b) as f32 bits, four words each; from word
// `R.clear_off` on, one bit per brick id: the transfer function maps the
// brick's whole value range to zero opacity (from the store's statistics).
@group(0) @binding(4) var<storage, read> aux: array<u32>;
// Premultiplied RGBA per pixel (four f32 as bits), rows top to bottom;
// for sample accumulation the store follows (savr.wgsl).
@group(0) @binding(5) var<storage, read_write> image: array<u32>;
// Per slot of every set (the pool, then the cache of each intermediate
// level: `lay.set_base`): (frame last used, frame last used at its own
// level; pool only).
@group(0) @binding(6) var<storage, read_write> stamps: array<atomic<u32>>;
// 0: samples, 1: exact, 2: unserved, 3: bricks crossed in one jump (per
// ray and brick), 4: used-list length, 5: cells crossed in one jump, 6:
// octree nodes visited, 7: octree nodes crossed unsampled; from 8 on the
// used list (slot, | EXACT_BIT when used at its own level).
@group(0) @binding(7) var<storage, read_write> counters: array<atomic<u32>>;
@group(0) @binding(8) var<storage, read_write> keys: array<atomic<u32>>;
@group(0) @binding(9) var<storage, read_write> counts: array<atomic<u32>>;
@group(0) @binding(10) var<storage, read_write> dropped: array<atomic<u32>>;
// Per pool slot, the value range (lo, hi) of each cell of its brick (NaN:
// unknown), at the slot's coordinates × cells per axis.
@group(0) @binding(11) var cells: texture_3d<f32>;

const AUTO: u32 = 0xffffffffu;

const EXACT_BIT: u32 = 0x80000000u;

const USED_BASE: u32 = 8u;

var<private> last_mark: u32;
// The page entry of the brick last walked to: its level, brick, entry.
// Per channel shown (index `cur_idx`): the last brick walked to.
// Up to 64 channels (multi-channel DVR).
var<private> memo_level: array<u32, 64>;
var<private> memo_brick: array<vec3<u32>, 64>;
var<private> memo_entry: array<vec2<u32>, 64>;
// The last coarser brick walked to for a stand-in (`coarse_entry_at`):
// channel index × 32 + level, brick, entry. Kept apart from the memo
// above, which stays on the brick of the sample's own level.
var<private> cmemo_key: u32;
var<private> cmemo_brick: vec3<u32>;
var<private> cmemo_entry: vec2<u32>;
// The channel being sampled and its index among those shown.
var<private> cur_ch: u32;
var<private> cur_idx: u32;

var<private> miss_id: u32;
var<private> miss_n: u32;

fn is_nan(v: f32) -> bool {
    return !(v == v);
}

struct Ray {
    o: vec3<f32>,
    d: vec3<f32>,
}

// The ray of view `v` through its continuous position (px, py): the
// camera moved along its right vector, its frustum shifted so that the
// target plane looks the same in every view (`brickyard_core::views`).
fn view_ray(v: u32, px: f32, py: f32) -> Ray {
    let sx = (2.0 * px / f32(R.view_width) - 1.0) * R.half_h * R.aspect;
    let sy = (1.0 - 2.0 * py / f32(R.height)) * R.half_h;
    let shift = (f32(v) - 0.5 * f32(R.n_views - 1u)) * R.views.x;
    if (shift == 0.0) {
        let off = R.right.xyz * sx + R.up.xyz * sy;
        if (R.perspective == 1u) {
            return Ray(R.eye.xyz, normalize(R.forward.xyz + off));
        }
        return Ray(R.eye.xyz + off, R.forward.xyz);
    }
    let slope = shift / R.views.y;
    if (R.perspective == 1u) {
        let off = R.right.xyz * (sx - slope) + R.up.xyz * sy;
        return Ray(R.eye.xyz + R.right.xyz * shift, normalize(R.forward.xyz + off));
    }
    let off = R.right.xyz * (sx + shift) + R.up.xyz * sy;
    return Ray(R.eye.xyz + off, normalize(R.forward.xyz - R.right.xyz * slope));
}

// The view of pixel column i and the column within it.
fn view_of(i: u32) -> vec2<u32> {
    let v = min(i / R.view_width, R.n_views - 1u - R.view_sel.x);
    return vec2<u32>(R.view_sel.x + v, i - v * R.view_width);
}

fn pixel_ray(i: u32, j: u32) -> Ray {
    let v = view_of(i);
    return view_ray(v.x, f32(v.y) + 0.5, f32(j) + 0.5);
}

fn put_pixel(i: u32, c: vec4<f32>) {
    image[4u * i] = bitcast<u32>(c.x);
    image[4u * i + 1u] = bitcast<u32>(c.y);
    image[4u * i + 2u] = bitcast<u32>(c.z);
    image[4u * i + 3u] = bitcast<u32>(c.w);
}

// The per-invocation state's start.
fn begin_invocation() {
    last_mark = AUTO;
    for (var i = 0u; i < max(R.n_channels, 1u); i = i + 1u) {
        memo_level[i] = AUTO;
    }
    cmemo_key = AUTO;
    cur_ch = R.channel;
    cur_idx = 0u;
    miss_id = AUTO;
    miss_n = 0u;
}

@compute @workgroup_size(8, 8)
fn render(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= R.width || g.y >= R.height) {
        return;
    }
    if (R.rows.x == 1u && (g.y < R.rows.y || g.y >= R.rows.z)) {
        // Another rank's band.
        put_pixel(g.y * R.width + g.x, vec4<f32>(0.0));
        return;
    }
    begin_invocation();
    let ray = pixel_ray(g.x, g.y);
    var px = vec4<f32>(0.0);
    if (R.mode == 2u && R.n_views > 1u) {
        px = superslice_pixel(g.x, g.y);
    } else if (R.n_channels > 0u) {
        if (R.mode == 2u) {
            px = slice_channels(ray);
        } else if (R.mode == 1u) {
            px = mip_channels(ray);
        } else if (R.oct.w != 0u) {
            px = dvr_octree(ray);
        } else {
            px = dvr_channels(ray);
        }
    } else if (R.mode == 2u) {
        px = slice_pixel(ray);
    } else if (R.mode == 1u) {
        px = mip_pixel(ray);
    } else if (R.region.w == 1u) {
        px = label_surface(ray);
    } else {
        px = dvr_pixel(ray);
    }
    flush_misses();
    put_pixel(g.y * R.width + g.x, px);
}
