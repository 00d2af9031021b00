//! The request lists of the CPU and the device for one frame, compared.

use brickyard_cache::brick::BrickKey;
use brickyard_cache::vm::Requests;
use std::collections::HashMap;

/// The CPU's requests of a frame (one collector per piece) and the
/// device's name the same bricks, each asked for as many times within
/// 2 + 5 % (positions are f32 on the device: near a brick's face a ray may
/// land a step apart, or take one more sample), and within 2 % in all.
/// Returns the CPU's count per brick.
pub fn same_requests(cpu: &[Requests], dev: &Requests, what: &str) -> HashMap<BrickKey, u32> {
    let mut want: HashMap<BrickKey, u32> = HashMap::new();
    for r in cpu {
        for (k, n) in r.iter() {
            *want.entry(k).or_default() += n;
        }
    }
    let got: HashMap<BrickKey, u32> = dev.iter().collect();
    let mut a: Vec<_> = want.keys().collect();
    let mut b: Vec<_> = got.keys().collect();
    a.sort();
    b.sort();
    assert_eq!(b, a, "{what}: the bricks asked for");
    let mut off = 0u64;
    for (k, &n) in &want {
        let d = got[k];
        off += d.abs_diff(n) as u64;
        assert!(
            d.abs_diff(n) <= 2 + n / 20,
            "{what}: brick {k:?}: the device asks {d} times, the CPU {n}"
        );
    }
    let total: u64 = want.values().map(|&n| n as u64).sum();
    eprintln!(
        "{what}: {} bricks, {total} misses on the CPU, {} on the device, {off} apart",
        want.len(),
        got.values().sum::<u32>()
    );
    assert!(
        off * 50 <= total,
        "{what}: the counts differ by {off} in all, of {total}"
    );
    want
}
