// Direct volume rendering on the device, twin of `dvr.rs`: front to back
// along the pixel's ray with automatic level of detail (at a level change
// the sample there is step 0 of the new level's grid, as on the CPU),
// bricks the transfer function hides crossed in one jump, cells of
// resident bricks it hides crossed the same way, the fallback to coarser
// levels, gradient shading (shading.wgsl), and compositing with opacity
// correction and early termination (unless a sort-last region turns it
// off: `R.region`).

// The pixel of `ray` in a DVR of the scene's channel; adds its counts.
fn dvr_pixel(ray: Ray) -> vec4<f32> {
    let span = intersect(ray);
    var acc = vec4<f32>(0.0);
    var samples = 0u;
    var exact = 0u;
    var unserved = 0u;
    var jumps = 0u;
    var cells_crossed = 0u;
    // A region (sort-last): the whole ray's step grid, samples in
    // [c0, t1) only.
    var c0 = span.x;
    var t1 = span.y;
    if (R.region.x == 1u) {
        let c = region_span(ray);
        c0 = c.x;
        t1 = select(min(t1, c.y), c0, c.y <= c.x);
    }
    if (span.y > span.x && t1 > c0) {
        var level = level_at(span.x);
        var base_t = span.x;
        var k = 0u;
        loop {
            let t = base_t + (f32(k) + 0.5) * R.step[level].x;
            if (t >= t1) {
                break;
            }
            k = k + 1u;
            let l = level_at(t);
            if (l != level) {
                // A level change: the new level's step grid has this
                // sample as its step 0 (as on the CPU).
                level = l;
                base_t = t - 0.5 * R.step[level].x;
                k = 1u;
            }
            if (t < c0) {
                // Before the region: another rank's samples.
                continue;
            }
            let w = ray.o + ray.d * t;
            let q = coords(level, w).xyz;
            let b = vec3<u32>(q);
            let e = entry_at(level, b);
            let f = flag(e);
            if (R.skip == 1u) {
                // Bricks the transfer function hides (by their value range,
                // or as EMPTY/CONSTANT entries) are crossed in one jump.
                var hidden = is_clear(brick_id(level, b));
                if (!hidden && (f == EMPTY || f == CONSTANT)) {
                    var v = 0.0;
                    if (f == CONSTANT) {
                        v = constant_value(e.y);
                    }
                    hidden = is_nan(v) || opacity_at(windowed(v)) <= 0.0;
                }
                if (hidden) {
                    jumps = jumps + 1u;
                    k = land(ray, level, b, base_t, k, t1);
                    continue;
                }
            }
            if (R.skip_cells == 1u && f != EMPTY && f != CONSTANT) {
                // A cell whose values the transfer function hides is
                // crossed in one jump: a cell of this level's resident
                // brick, or else of the finest resident brick standing in
                // (then never past a brick not resident on the way to it:
                // another may serve there). The brick is still in use; each
                // step crossed in a stand-in is a miss of this level's
                // brick, as a sampled one is.
                var c = Serving(level, b, NONE, min(t1, next_level_t(level)));
                if (f == MAPPED) {
                    c.slot = slot_id(e, lay.brick_grid);
                } else {
                    c = stand_in(ray, level, w, b, c.limit);
                }
                if (c.slot != NONE) {
                    let r = cell_range(c.slot, c.base);
                    if (range_clear(r.x, r.y)) {
                        mark(c.slot, c.level == level);
                        cells_crossed = cells_crossed + 1u;
                        let kn = land_at(cell_exit_t(ray, c.level, c.base, c.limit), base_t, k, level);
                        if (c.level != level) {
                            misses(brick_id(level, b), kn + 1u - k);
                        }
                        k = kn;
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
                let kn = skip_unserved(ray, level, b, base_t, k, min(t1, next_level_t(level)));
                samples = samples + kn - k;
                unserved = unserved + 1u + kn - k;
                k = kn;
                continue;
            }
            if (is_nan(s.x)) {
                continue;
            }
            let x = windowed(s.x);
            let alpha = opacity_at(x);
            if (alpha > 0.0) {
                let a = correct_opacity(alpha, R.step[level].y);
                var c = color_at(x);
                if (R.shade == 1u) {
                    c = shade(c, level, w, ray.d);
                }
                let wt = (1.0 - acc.w) * a;
                acc = acc + vec4<f32>(c * wt, wt);
                if (acc.w >= EARLY_TERMINATION && R.region.y == 0u) {
                    break;
                }
            }
        }
    }
    atomicAdd(&counters[0], samples + nb_samples);
    atomicAdd(&counters[1], exact + nb_exact);
    atomicAdd(&counters[2], unserved + nb_unserved);
    atomicAdd(&counters[3], jumps);
    atomicAdd(&counters[5], cells_crossed);
    return acc;
}
