// Label images in 3D on the device, twin of `labels.rs`: each ray stops at
// its first voxel holding a label (not 0), at the level of the ray's entry
// on one step grid, nearest voxels (`coords`), and the pixel is the label's
// colour shaded by its surface there (the indicator's differences between
// the voxel's neighbours, lit from the eye).

const LABEL_AMBIENT: f32 = 0.25;

fn label_id(v: f32) -> i32 {
    return i32(floor(v + 0.5));
}

// Whether voxel `q` ([z, y, x]) of `level` holds label `id` (1) or not
// (0), from its own brick: outside the volume, not; its brick not
// resident, yes, and a miss of it, not an unserved sample (the pixel is
// drawn; labels.rs's `voxel_at_level`). Counted as a sample.
fn label_holds(level: u32, q: vec3<i32>, id: i32) -> f32 {
    if (any(q < vec3<i32>(0)) || any(vec3<f32>(q) > R.qmax[level].xyz)) {
        return 0.0;
    }
    let b = vec3<u32>(q);
    let e = entry_at(level, b);
    let r = value_of(e, b, vec3<f32>(0.0));
    atomicAdd(&counters[0], 1u);
    if (r.y == 0.0) {
        miss(brick_id(level, b));
        return 1.0;
    }
    if (flag(e) == MAPPED) {
        mark(slot_id(e, lay.brick_grid), true);
    }
    atomicAdd(&counters[1], 1u);
    return select(0.0, 1.0, !is_nan(r.x) && label_id(r.x) == id);
}

// Sobel's 3×3×3 operator on label `id`'s indicator around voxel `v`
// (labels.rs's `indicator_gradient`): (z, y, x), pointing out.
fn label_gradient(level: u32, v: vec3<i32>, id: i32) -> vec3<f32> {
    var g = vec3<f32>(0.0);
    for (var i = 0; i < 27; i = i + 1) {
        let o = vec3<i32>(i / 9, (i / 3) % 3, i % 3);
        if (i == 13) {
            continue;
        }
        let h = label_holds(level, v + o - vec3<i32>(1), id);
        if (h == 0.0) {
            continue;
        }
        // Weights (1, 2, 1) across the other two axes; the sign by the
        // side of the axis itself.
        let w = vec3<f32>(2.0) - abs(vec3<f32>(o - vec3<i32>(1)));
        let side = -vec3<f32>(o - vec3<i32>(1));
        g = g + h * side * vec3<f32>(w.y * w.z, w.x * w.z, w.x * w.y);
    }
    // The centre holds the label but lies on no difference.
    return g;
}

// `labels.rs`'s `surface_shade`: `g` the differences along (z, y, x).
fn label_shade(level: u32, g: vec3<f32>, dir: vec3<f32>) -> f32 {
    let s = R.scale[level];
    let n = vec3<f32>(g.z * s.z, g.y * s.y, g.x * s.x);
    let nn = sqrt(dot(n, n));
    let dd = sqrt(dot(dir, dir));
    if (nn == 0.0 || dd == 0.0) {
        return 1.0;
    }
    let c = min(abs(dot(n, dir) / (nn * dd)), 1.0);
    return LABEL_AMBIENT + (1.0 - LABEL_AMBIENT) * c;
}

fn label_surface(ray: Ray) -> vec4<f32> {
    let span = intersect(ray);
    if (!(span.y > span.x)) {
        return vec4<f32>(0.0);
    }
    let level = level_at(span.x);
    let dt = R.step[level].x;
    var k = 0u;
    var samples = 0u;
    var exact = 0u;
    var unserved = 0u;
    var jumps = 0u;
    var cells_crossed = 0u;
    var px = vec4<f32>(0.0);
    loop {
        let t = span.x + (f32(k) + 0.5) * dt;
        if (t >= span.y) {
            break;
        }
        k = k + 1u;
        let w = ray.o + ray.d * t;
        let q = coords(level, w).xyz;
        let b = vec3<u32>(q);
        let e = entry_at(level, b);
        if (R.skip == 1u) {
            // Background alone (by the statistics' clear bits, or an EMPTY
            // or CONSTANT 0 entry): cross the steps whose interpolating
            // voxel base lies in the brick less its last voxel per axis
            // (their nearest voxels lie in the brick), as the CPU does.
            let f = flag(e);
            var clear = is_clear(brick_id(level, b)) || f == EMPTY;
            if (!clear && f == CONSTANT) {
                let v = constant_value(e.y);
                clear = !is_nan(v) && (label_id(v) == 0 || !label_shown(label_id(v)));
            }
            if (clear) {
                let bs = lay.block[lay.nmax].xyz;
                let lo = (b / bs) * bs;
                let hi = min(lo + bs, lay.dims[level].xyz) - vec3<u32>(1u);
                let s = R.scale[level];
                let base = vec3<u32>(clamp(vec3<f32>(w.z * s.x, w.y * s.y, w.x * s.z) - vec3<f32>(0.5), vec3<f32>(0.0), R.qmax[level].xyz));
                if (all(base >= lo) && all(base < hi)) {
                    jumps = jumps + 1u;
                    k = land_at(exit_t(ray, level, lo, hi, span.y), span.x, k, level);
                    continue;
                }
            }
        }
        if (R.skip_cells == 1u && flag(e) == MAPPED) {
            // A cell of this level's resident brick that draws nothing
            // (its value range: background alone, or no label drawn):
            // cross the steps whose interpolating voxel base lies in it,
            // as the CPU's run loop does.
            let s = R.scale[level];
            let base = vec3<u32>(clamp(vec3<f32>(w.z * s.x, w.y * s.y, w.x * s.z) - vec3<f32>(0.5), vec3<f32>(0.0), R.qmax[level].xyz));
            let bs = lay.block[lay.nmax].xyz;
            let lo = (b / bs) * bs;
            let hi = min(lo + bs, lay.dims[level].xyz);
            if (all(base >= lo) && all(base < hi)) {
                let slot = slot_id(e, lay.brick_grid);
                let r = cell_range(slot, base);
                if (label_range_clear(r.x, r.y)) {
                    mark(slot, true);
                    cells_crossed = cells_crossed + 1u;
                    k = land_at(cell_exit_t(ray, level, base, span.y), span.x, k, level);
                    continue;
                }
            }
        }
        let s = sample_from(w, level, q, e);
        samples = samples + 1u;
        if (s.y == 2.0) {
            exact = exact + 1u;
        }
        if (s.y == 0.0) {
            // Nothing resident serves it: on past the brick, as the CPU.
            let kn = skip_unserved(ray, level, b, span.x, k, span.y);
            samples = samples + kn - k;
            unserved = unserved + 1u + kn - k;
            k = kn;
            continue;
        }
        if (is_nan(s.x)) {
            continue;
        }
        let id = label_id(s.x);
        if (id != 0 && label_shown(id)) {
            let g = label_gradient(level, vec3<i32>(b), id);
            let c = label_color(s.x);
            px = vec4<f32>(c.xyz * label_shade(level, g, ray.d), 1.0);
            break;
        }
    }
    atomicAdd(&counters[0], samples);
    atomicAdd(&counters[1], exact);
    atomicAdd(&counters[2], unserved);
    atomicAdd(&counters[3], jumps);
    atomicAdd(&counters[5], cells_crossed);
    return px;
}
