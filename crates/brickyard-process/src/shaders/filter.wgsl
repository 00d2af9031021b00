// The filter kernels on the device. Each entry point is the twin of the CPU
// function of the same name in `brickyard_process::kernels`, run in f32:
// the same operations in the same order.
//
// Blocks are dense f32 arrays in C order ([z, y, x], x fastest). One
// invocation computes one output voxel; voxel i of a dispatch is
// (workgroup_id.y * num_workgroups.x + workgroup_id.x) * 256 + local index,
// so a dispatch covers any count (the host spreads the workgroups over x and
// y, each at most 65535).

struct Params {
    // Output dimensions (x fastest) and voxel count.
    nx: u32,
    ny: u32,
    nz: u32,
    count: u32,
    // correlate_valid: input strides of a y row and a z plane, the stride
    // between taps (along the pass's axis), the number of taps and the
    // offset of the pass's weights in `weights`.
    sy: u32,
    sz: u32,
    step: u32,
    taps: u32,
    w0: u32,
    // sum_squares: 1 for the first component (dst = v²), else 0.
    first: u32,
    pad0: u32,
    pad1: u32,
    // threshold: v > lo. window: lo <= v <= hi. The host rounds the f64
    // bounds outward to f32 (lo of threshold and hi down, lo of window up),
    // so that for every f32 v the comparison is the f64 one.
    lo: f32,
    hi: f32,
    pad2: f32,
    pad3: f32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> weights: array<f32>;
@group(0) @binding(2) var<storage, read> src: array<f32>;
@group(0) @binding(3) var<storage, read_write> dst: array<f32>;

const WG: u32 = 256u;

fn voxel(wg: vec3<u32>, groups: vec3<u32>, t: u32) -> u32 {
    return (wg.y * groups.x + wg.x) * WG + t;
}

// Correlation along one axis, valid part: dst[z, y, x] = Σ_k w[k] ·
// src[(z, y, x) + k along the axis], summed from 0 in increasing k. The
// input has the output's dimensions plus taps - 1 along the axis.
@compute @workgroup_size(256)
fn correlate_valid(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) t: u32,
) {
    let i = voxel(wg, groups, t);
    if (i >= params.count) {
        return;
    }
    let x = i % params.nx;
    let r = i / params.nx;
    let y = r % params.ny;
    let z = r / params.ny;
    var s = z * params.sz + y * params.sy + x;
    var acc = 0.0;
    for (var k = 0u; k < params.taps; k = k + 1u) {
        acc = acc + weights[params.w0 + k] * src[s];
        s = s + params.step;
    }
    dst[i] = acc;
}

// dst = dst + src² (dst = src² for the first component).
@compute @workgroup_size(256)
fn sum_squares(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) t: u32,
) {
    let i = voxel(wg, groups, t);
    if (i >= params.count) {
        return;
    }
    let v = src[i];
    if (params.first != 0u) {
        dst[i] = v * v;
    } else {
        dst[i] = dst[i] + v * v;
    }
}

// dst = √dst (src is not read).
@compute @workgroup_size(256)
fn square_root(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) t: u32,
) {
    let i = voxel(wg, groups, t);
    if (i >= params.count) {
        return;
    }
    dst[i] = sqrt(dst[i]);
}

// dst = 1 where src > lo, else 0.
@compute @workgroup_size(256)
fn threshold(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) t: u32,
) {
    let i = voxel(wg, groups, t);
    if (i >= params.count) {
        return;
    }
    dst[i] = select(0.0, 1.0, src[i] > params.lo);
}

// dst = 1 where lo <= src <= hi, else 0.
@compute @workgroup_size(256)
fn window(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) t: u32,
) {
    let i = voxel(wg, groups, t);
    if (i >= params.count) {
        return;
    }
    let v = src[i];
    dst[i] = select(0.0, 1.0, params.lo <= v && v <= params.hi);
}
