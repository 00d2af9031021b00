// DVR through the residency octree on the device, twin of `octree/dvr.rs`
// (Algorithm 1 of the residency-octree paper per step): the octree is
// descended from the root to the deepest depth the step size allows; a
// node every shown channel hides at the step's level is crossed in one
// landing; a node where every shown channel is hidden or of one value is
// composited with its one mixed colour at every step inside, without
// lookups; a node where no shown channel has anything mapped is requested
// and crossed; otherwise the steps inside the node are sampled, each
// channel the node does not hide through its page tables and, on a miss,
// substituted only from the coarser levels the node's residency mask
// names. Channels are those of `multi.wgsl` (R.n_channels ≥ 1, their
// styles and transfer functions), and so are the steps and the mixing.
//
// The frame's tables lie in `aux` (written by the host from its octree,
// `OctFrame::device_words`):
// - from R.oct.x, per node and level (node · R.levels + level), 8 words:
//   bits of the shown channels the node hides (two words: channels 0–31,
//   32–63), kind (0: descend or sample, 1: every channel hidden, 2: one
//   mixed colour, in the last four words as f32 bits, alpha 0: nothing
//   visible), 0;
// - from R.oct.y, per node and channel of the volume (R.oct.w of them),
//   the residency mask (bit l: some level-l brick overlapping the node is
//   mapped), copied from the device's own octree (`octree.wgsl`'s passes
//   keep it from the map and evict events);
// - from R.oct.z, per level, the deepest depth the step size allows.
// Counters 6 and 7: octree nodes visited, nodes crossed without sampling.

// A thousandth of a step: landings lie this much early, and a step this
// close to a node's face is taken as outside it.
const OCT_MARGIN: f32 = 1e-3;

fn oct_offset(d: u32) -> u32 {
    return ((1u << (3u * d)) - 1u) / 7u;
}

fn oct_bit(bits: vec2<u32>, i: u32) -> bool {
    if (i < 32u) {
        return ((bits.x >> i) & 1u) == 1u;
    }
    return ((bits.y >> (i - 32u)) & 1u) == 1u;
}

// The residency mask of node `node` for shown channel i.
fn oct_mask(node: u32, i: u32) -> u32 {
    return aux[R.oct.y + node * R.oct.w + ch_word(i, 0u)];
}

// Bits of all shown channels.
fn oct_all() -> vec2<u32> {
    let n = R.n_channels;
    if (n >= 64u) {
        return vec2<u32>(0xffffffffu, 0xffffffffu);
    }
    if (n >= 32u) {
        if (n == 32u) {
            return vec2<u32>(0xffffffffu, 0u);
        }
        return vec2<u32>(0xffffffffu, (1u << (n - 32u)) - 1u);
    }
    return vec2<u32>((1u << n) - 1u, 0u);
}

// The ray parameter where `ray` leaves node `c` (z, y, x) of depth `d`.
fn oct_node_exit(ray: Ray, d: u32, c: vec3<u32>) -> f32 {
    let s = f32(1u << d);
    var t = 3.0e38;
    for (var j = 0u; j < 3u; j = j + 1u) {
        // World axis j is octree axis 2 − j.
        let i = f32(c[2u - j]);
        let dj = ray.d[j];
        if (dj > 0.0) {
            t = min(t, ((i + 1.0) / s * R.extent[j] - ray.o[j]) / dj);
        } else if (dj < 0.0) {
            t = min(t, (i / s * R.extent[j] - ray.o[j]) / dj);
        }
    }
    return t;
}

// The first step index whose parameter is at least `t` less a margin.
fn oct_first_step(t: f32, base_t: f32, dt: f32) -> u32 {
    let x = (t - base_t) / dt - 0.5 - OCT_MARGIN;
    if (x <= 0.0) {
        return 0u;
    }
    return u32(ceil(x));
}

// Front-to-back compositing of straight-alpha `c` with the opacity
// correction of `level`; true when the ray is done.
fn oct_composite(acc: ptr<function, vec4<f32>>, c: vec4<f32>, level: u32) -> bool {
    let a = correct_opacity(c.w, R.step[level].y);
    let wt = (1.0 - (*acc).w) * a;
    *acc = *acc + vec4<f32>(c.xyz * wt, wt);
    return (*acc).w >= EARLY_TERMINATION;
}

// The pixel of `ray` in a DVR of the channels shown through the octree;
// adds its counts.
fn dvr_octree(ray: Ray) -> vec4<f32> {
    let span = intersect(ray);
    var acc = vec4<f32>(0.0);
    ch_samples = 0u;
    ch_exact = 0u;
    ch_unserved = 0u;
    var nodes = 0u;
    var skipped = 0u;
    let all = oct_all();
    let n = R.n_channels;
    if (span.y > span.x) {
        let t1 = span.y;
        var level = level_at(span.x);
        var base_t = span.x;
        var k = 0u;
        // The node being sampled (AUTO: none) and until where.
        var in_node = AUTO;
        var in_level = 0u;
        var in_until = 0.0;
        var in_clear = vec2<u32>(0u);
        var done = false;
        loop {
            let t = base_t + (f32(k) + 0.5) * R.step[level].x;
            if (t >= t1 || done) {
                break;
            }
            k = k + 1u;
            let l = level_at(t);
            if (l != level) {
                level = l;
                base_t = t - 0.5 * R.step[level].x;
                k = 1u;
                in_node = AUTO;
            }
            let dt = R.step[level].x;
            let limit = min(t1, next_level_t(level));
            let w = ray.o + ray.d * t;
            if (in_node == AUTO || in_level != level || t >= in_until) {
                in_node = AUTO;
                let p = vec3<f32>(w.z / R.extent.z, w.y / R.extent.y, w.x / R.extent.x);
                let dm = aux[R.oct.z + level];
                var crossed = false;
                for (var dd = 0u; dd <= dm; dd = dd + 1u) {
                    let s = 1u << dd;
                    let c = min(vec3<u32>(p * f32(s)), vec3<u32>(s - 1u));
                    let node = oct_offset(dd) + (c.x * s + c.y) * s + c.z;
                    nodes = nodes + 1u;
                    let base = R.oct.x + 8u * (node * R.levels + level);
                    let clear = vec2<u32>(aux[base], aux[base + 1u]);
                    let kind = aux[base + 2u];
                    let te = oct_node_exit(ray, dd, c);
                    if (kind == 1u) {
                        // Hidden for every channel: land past it.
                        skipped = skipped + 1u;
                        k = max(oct_first_step(min(te, limit), base_t, dt), k);
                        crossed = true;
                        break;
                    }
                    if (kind == 2u) {
                        // One value per channel: its colour at every step
                        // inside.
                        skipped = skipped + 1u;
                        let kn = max(oct_first_step(min(te, limit), base_t, dt), k);
                        let col = vec4<f32>(
                            bitcast<f32>(aux[base + 4u]),
                            bitcast<f32>(aux[base + 5u]),
                            bitcast<f32>(aux[base + 6u]),
                            bitcast<f32>(aux[base + 7u]),
                        );
                        if (col.w > 0.0) {
                            for (var j = k - 1u; j < kn; j = j + 1u) {
                                if (oct_composite(&acc, col, level)) {
                                    done = true;
                                    break;
                                }
                            }
                        }
                        k = kn;
                        crossed = true;
                        break;
                    }
                    let open = all & ~clear;
                    var mapped = false;
                    for (var i = 0u; i < n; i = i + 1u) {
                        if (oct_bit(open, i) && oct_mask(node, i) != 0u) {
                            mapped = true;
                            break;
                        }
                    }
                    if (!mapped) {
                        // Nothing mapped for any channel shown: ask for the
                        // bricks here and cross the node.
                        let kn = max(oct_first_step(min(te, limit), base_t, dt), k);
                        let m = kn - (k - 1u);
                        for (var i = 0u; i < n; i = i + 1u) {
                            if (oct_bit(open, i)) {
                                use_channel(i);
                                let lc = ch_level(i, level);
                                let id = brick_id(lc, vec3<u32>(coords(lc, w).xyz));
                                if (id != miss_id) {
                                    flush_misses();
                                    miss_id = id;
                                }
                                miss_n = miss_n + m;
                            }
                        }
                        ch_samples = ch_samples + m;
                        ch_unserved = ch_unserved + m;
                        k = kn;
                        crossed = true;
                        break;
                    }
                    if (dd == dm) {
                        in_node = node;
                        in_level = level;
                        in_until = te - OCT_MARGIN * dt;
                        in_clear = clear;
                    }
                }
                if (crossed) {
                    continue;
                }
            }
            // Sample every channel the node does not hide.
            let q = coords(level, w).xyz;
            var keep = 1.0;
            var rgb = vec3<f32>(0.0);
            var weight = 0.0;
            for (var i = 0u; i < n; i = i + 1u) {
                if (oct_bit(in_clear, i)) {
                    continue;
                }
                let c = channel_sample(i, level, w, q, oct_mask(in_node, i), true);
                if (c.w > 0.0) {
                    keep = keep * (1.0 - c.w);
                    rgb = rgb + c.xyz;
                    weight = weight + c.w;
                }
            }
            if (weight > 0.0) {
                if (oct_composite(&acc, vec4<f32>(rgb * (1.0 / weight), 1.0 - keep), level)) {
                    break;
                }
            }
        }
    }
    atomicAdd(&counters[0], ch_samples);
    atomicAdd(&counters[1], ch_exact);
    atomicAdd(&counters[2], ch_unserved);
    atomicAdd(&counters[6], nodes);
    atomicAdd(&counters[7], skipped);
    return acc;
}
