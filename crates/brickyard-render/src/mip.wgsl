// Maximum intensity projections on the device, twin of `mip.rs`: each
// channel's largest value along the ray at the entry level, crossing cells
// whose maximum cannot raise it, then the transfer function's colour or
// the channels' mix. A ray ends once its maximum saturates the window (any
// larger value has the same colour), unless the raw maxima are wanted.

// The largest value of the current channel along the ray in `span` at the
// entry level (NaN samples and unserved ones left out), and whether there
// was one; crossing cells whose maximum cannot raise it; as the CPU's
// `mip_max`. `multi`: the current channel is one of several (its window
// is its style's).
fn mip_max(ray: Ray, span: vec2<f32>, multi: bool) -> vec2<f32> {
    return mip_max_in(ray, span, span, multi).xy;
}

// Whether the maximum `v` saturates the window of the channel shown (its
// colour is that of every larger value: the ray may end); never where
// the raw maxima are wanted (regions' values meet before the transfer
// function). The CPU's `saturation`.
fn mip_saturated(v: f32, multi: bool) -> bool {
    if (R.region.z == 1u) {
        return false;
    }
    if (multi) {
        let st = style(cur_idx);
        return st.z > st.y && (v - st.y) / (st.z - st.y) >= 1.0;
    }
    return R.inv_width > 0.0 && R.inv_width < 3.0e38 && windowed(v) >= 1.0;
}

// `mip_max` over the samples of the grid of `span` that lie in
// [clip.x, clip.y) (a sort-last region, as the CPU's `mip_max_in`); z: 1
// when the ray took a step there (served or not), 0 otherwise.
fn mip_max_in(ray: Ray, span: vec2<f32>, clip: vec2<f32>, multi: bool) -> vec3<f32> {
    let t1 = min(span.y, clip.y);
    var hit = false;
    let level = level_at(span.x);
    var best = 0.0;
    var found = false;
    var k = 0u;
    var samples = 0u;
    var exact = 0u;
    var unserved = 0u;
    var crossed = 0u;
    loop {
        let t = span.x + (f32(k) + 0.5) * R.step[level].x;
        if (t >= t1) {
            break;
        }
        k = k + 1u;
        if (t < clip.x) {
            // Before the region: another rank's samples.
            continue;
        }
        hit = true;
        let w = ray.o + ray.d * t;
        let q = coords(level, w).xyz;
        let b = vec3<u32>(q);
        let e = entry_at(level, b);
        if (R.skip_cells == 1u && found && flag(e) == MAPPED) {
            let slot = slot_id(e, lay.brick_grid);
            let r = cell_range(slot, b);
            if (!is_nan(r.y) && r.y <= best) {
                mark(slot, true);
                crossed = crossed + 1u;
                k = land_cell(ray, level, b, span.x, k, t1);
                continue;
            }
        }
        let s = sample_from(w, level, q, e);
        samples = samples + 1u;
        if (s.y == 2.0) {
            exact = exact + 1u;
        }
        if (s.y == 0.0) {
            // Nothing resident serves it: on past the brick, as the CPU.
            let kn = skip_unserved(ray, level, b, span.x, k, t1);
            samples = samples + kn - k;
            unserved = unserved + 1u + kn - k;
            k = kn;
            continue;
        }
        if (is_nan(s.x)) {
            continue;
        }
        if (!found || s.x > best) {
            best = s.x;
            found = true;
            if (mip_saturated(best, multi)) {
                break;
            }
        }
    }
    atomicAdd(&counters[0], samples);
    atomicAdd(&counters[1], exact);
    atomicAdd(&counters[2], unserved);
    atomicAdd(&counters[5], crossed);
    return vec3<f32>(best, f32(found), f32(hit));
}

// The pixel of `ray` in a MIP of one channel: the maximum along the ray,
// opaque where the ray took a sample (black when none was served).
fn mip_pixel(ray: Ray) -> vec4<f32> {
    let span = intersect(ray);
    var px = vec4<f32>(0.0);
    if (R.region.x == 1u) {
        // A region (sort-last): its samples of the whole ray's grid.
        let c = region_span(ray);
        if (span.y > span.x && c.y > c.x) {
            let m = mip_max_in(ray, span, c, false);
            if (m.z > 0.0) {
                if (R.region.z == 1u) {
                    // The raw maximum, for the regions' maxima to meet
                    // before the transfer function (NaN: none served).
                    px = vec4<f32>(select(nan_f32(), m.x, m.y > 0.0), 0.0, 0.0, 1.0);
                } else {
                    px = vec4<f32>(0.0, 0.0, 0.0, 1.0);
                    if (m.y > 0.0) {
                        px = vec4<f32>(color_at(windowed(m.x)), 1.0);
                    }
                }
            }
        }
        return px;
    }
    if (span.y > span.x && span.x + 0.5 * R.step[level_at(span.x)].x < span.y) {
        let m = mip_max(ray, span, false);
        px = vec4<f32>(0.0, 0.0, 0.0, 1.0);
        if (m.y > 0.0) {
            px = vec4<f32>(color_at(windowed(m.x)), 1.0);
        }
    }
    return px;
}

// The pixel of `ray` in a MIP of several channels added up: each
// channel's maximum along the ray, then the mix.
fn mip_channels(ray: Ray) -> vec4<f32> {
    var px = vec4<f32>(0.0);
    let span = intersect(ray);
    if (span.y > span.x && span.x + 0.5 * R.step[level_at(span.x)].x < span.y) {
        var v: array<f32, 16>;
        var have = 0u;
        for (var i = 0u; i < R.n_channels; i = i + 1u) {
            use_channel(i);
            let m = mip_max(ray, span, true);
            v[i] = m.x;
            if (m.y > 0.0) {
                have = have | (1u << i);
            }
        }
        px = mix(v, have);
    }
    return px;
}

// A quiet NaN, made at run time (a NaN constant is not valid WGSL).
fn nan_f32() -> f32 {
    return bitcast<f32>(0x7fc00000u | (R.region.w & 0u));
}
