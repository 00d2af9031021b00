// Slices on the device, twin of `slice.rs`: the plane as the camera sees
// it, sampled where the pixel's ray meets it inside the closed world box,
// opaque there; one channel through the transfer function's colours (a
// label image: the nearest voxel's label colour), or several added up.

// Where the pixel's ray meets the slice plane inside the closed world box:
// (point, t), or w = −1 when it does not.
fn slice_hit(ray: Ray) -> vec4<f32> {
    return plane_hit_at(ray, R.plane_origin.xyz);
}

// The same for the parallel plane through `origin`.
fn plane_hit_at(ray: Ray, origin: vec3<f32>) -> vec4<f32> {
    let n = R.plane_normal.xyz;
    let denom = dot(ray.d, n);
    if (denom == 0.0) {
        return vec4<f32>(-1.0);
    }
    let t = dot(origin - ray.o, n) / denom;
    if (is_nan(t) || t < 0.0) {
        return vec4<f32>(-1.0);
    }
    let w = ray.o + ray.d * t;
    if (any(w < vec3<f32>(0.0)) || any(w > R.extent.xyz)) {
        return vec4<f32>(-1.0);
    }
    return vec4<f32>(w, t);
}

// A slice: the plane as the camera sees it, sampled where the pixel's ray
// meets it inside the closed world box, opaque there (as on the CPU).
fn slice_pixel(ray: Ray) -> vec4<f32> {
    let hit = slice_hit(ray);
    if (hit.w < 0.0) {
        return vec4<f32>(0.0);
    }
    let v = plane_value(hit);
    if (R.region.w == 1u) {
        return label_color(v);
    }
    if (is_nan(v)) {
        return vec4<f32>(0.0);
    }
    return vec4<f32>(color_at(windowed(v)), 1.0);
}

// The value where a ray meets a plane (`hit`: point, t), at the level the
// footprint asks for, counted; NaN when nothing is resident.
fn plane_value(hit: vec4<f32>) -> f32 {
    let s = sample_at(hit.xyz, level_at(hit.w));
    atomicAdd(&counters[0], 1u);
    if (s.y == 2.0) {
        atomicAdd(&counters[1], 1u);
    }
    if (s.y == 0.0) {
        atomicAdd(&counters[2], 1u);
        return nan_f32();
    }
    return s.x;
}

// A slice of several channels.
fn slice_channels(ray: Ray) -> vec4<f32> {
    let hit = slice_hit(ray);
    if (hit.w < 0.0) {
        return vec4<f32>(0.0);
    }
    let w = hit.xyz;
    let level = level_at(hit.w);
    var v: array<f32, 16>;
    var have = 0u;
    for (var i = 0u; i < R.n_channels; i = i + 1u) {
        use_channel(i);
        let s = sample_at(w, level);
        atomicAdd(&counters[0], 1u);
        if (s.y == 2.0) {
            atomicAdd(&counters[1], 1u);
        }
        if (s.y == 0.0) {
            atomicAdd(&counters[2], 1u);
        } else {
            v[i] = s.x;
            have = have | (1u << i);
        }
    }
    return mix(v, have);
}
