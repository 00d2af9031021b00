// Adding misses to the request table: shared by requests.wgsl and the
// renderers, which declare `keys`, `counts` (array<atomic<u32>>) and
// `dropped` (array<atomic<u32>>: misses dropped, buckets occupied) and
// append this file.

const NO_BRICK: u32 = 0xffffffffu;

fn bucket(id: u32, mask: u32) -> u32 {
    return ((id * 0x9E3779B1u) >> 7u) & mask;
}

fn add_saturating(b: u32, s: u32) {
    let old = atomicAdd(&counts[b], s);
    if (old + s < old) {
        // Wrapped: every add that wraps sets the maximum after it, so the
        // final count is the maximum whatever the order.
        atomicMax(&counts[b], NO_BRICK);
    }
}

// Add `s` misses of brick `id` to the table of `buckets` buckets (linear
// probing; a key that finds no bucket is dropped and counted).
fn request_add(id: u32, s: u32, buckets: u32) {
    let mask = buckets - 1u;
    var b = bucket(id, mask);
    for (var p = 0u; p < buckets; p = p + 1u) {
        loop {
            let r = atomicCompareExchangeWeak(&keys[b], NO_BRICK, id);
            if (r.exchanged) {
                atomicAdd(&dropped[1], 1u);
            }
            if (r.exchanged || r.old_value == id) {
                add_saturating(b, s);
                return;
            }
            if (r.old_value != NO_BRICK) {
                break;
            }
            // A spurious failure of the weak exchange: try again.
        }
        b = (b + 1u) & mask;
    }
    atomicAdd(&dropped[0], 1u);
}
