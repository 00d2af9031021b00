//! Each device kernel against its CPU twin on random inputs: bookkeeping
//! must match exactly. A missing adapter fails these tests unless
//! `BRICKYARD_SKIP_GPU=1` opts out explicitly (see `context::test_gpu`).

use brickyard_cache::bookkeeping::{compact_lru, prioritize, BrickIds, RequestTable};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::lru::{LruBuffers, LruCompaction};
use brickyard_gpu::requests::RequestTableGpu;

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> u32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) as u32
    }
    fn below(&mut self, n: u32) -> u32 {
        ((self.next() as u64 * n as u64) >> 31) as u32
    }
    fn shuffle(&mut self, v: &mut [u32]) {
        for i in (1..v.len()).rev() {
            let j = self.below(i as u32 + 1) as usize;
            v.swap(i, j);
        }
    }
}

#[test]
fn lru_compaction_equals_cpu_twin() {
    let Some(gpu) = test_gpu() else { return };
    let k = LruCompaction::new(&gpu);
    let mut rng = Lcg(7);
    // Sizes around the block (1024) and scan-chunk (256 blocks) edges,
    // and a pool of a million slots.
    for &n in &[1usize, 2, 255, 1023, 1024, 1025, 4097, 262_145, 1 << 20] {
        for &p_used in &[0u32, 1, 30, 99, 100] {
            let mut order: Vec<u32> = (0..n as u32).collect();
            rng.shuffle(&mut order);
            let frame = 1000 + rng.below(50);
            let usage: Vec<u32> = (0..n)
                .map(|_| {
                    if rng.below(100) < p_used {
                        frame
                    } else {
                        frame - 1 - rng.below(900)
                    }
                })
                .collect();
            let b = LruBuffers::new(&gpu, &order, &usage).unwrap();
            k.run(&gpu, &b, frame);
            let got = b.read_order(&gpu).unwrap();
            let want = compact_lru(&order, |s| usage[s as usize] == frame);
            assert!(got == want, "n {n}, {p_used}% used: device order differs");
            // A second frame on the compacted order, with other usage.
            let usage2: Vec<u32> = usage
                .iter()
                .map(|&u| if rng.below(4) == 0 { frame + 1 } else { u })
                .collect();
            gpu.queue
                .write_buffer(&b.usage, 0, bytemuck::cast_slice(&usage2));
            k.run(&gpu, &b, frame + 1);
            let got2 = b.read_order(&gpu).unwrap();
            assert_eq!(
                got2,
                compact_lru(&want, |s| usage2[s as usize] == frame + 1)
            );
        }
    }
}

/// The CPU twin: the table then the list.
fn cpu_list(
    ids: &BrickIds,
    buckets: usize,
    misses: &[[u32; 2]],
    cap: usize,
) -> (Vec<(u32, u32)>, u64) {
    let mut t = RequestTable::new(buckets);
    for m in misses {
        t.add(m[0], m[1]);
    }
    let list = t
        .entries()
        .into_iter()
        .map(|(id, n)| (ids.key(id), n))
        .collect();
    let list = prioritize(list, cap)
        .into_iter()
        .map(|(k, n)| (ids.id(k), n))
        .collect();
    (list, t.dropped)
}

#[test]
fn request_list_equals_cpu_twin() {
    let Some(gpu) = test_gpu() else { return };
    let grid = [[16, 16, 16], [8, 8, 8], [4, 4, 4], [2, 2, 2], [1, 1, 1]];
    let ids = BrickIds::new(&grid, 2).unwrap();
    let mut rng = Lcg(11);
    for &(buckets, distinct, events, cap) in &[
        (1usize, 1u32, 5usize, 1usize),
        (64, 20, 1000, 8),
        (256, 200, 20_000, 256),
        (4096, 1500, 100_000, 256),
        (4096, 4096, 50_000, 512),
        (64, 300, 5000, 16),
    ] {
        // A few popular bricks and many rare ones; counts tie often.
        let pool: Vec<u32> = (0..distinct).map(|_| rng.below(ids.len())).collect();
        let misses: Vec<[u32; 2]> = (0..events)
            .map(|_| {
                let i = if rng.below(4) == 0 {
                    rng.below(distinct.min(5))
                } else {
                    rng.below(distinct)
                };
                [pool[i as usize], 1 + rng.below(3)]
            })
            .collect();
        let mut t = RequestTableGpu::new(&gpu, &ids, buckets);
        assert_eq!(t.buckets(), buckets.next_power_of_two());
        // In two uploads, as several consumers would.
        let (a, b) = misses.split_at(misses.len() / 3);
        t.insert(&gpu, a);
        t.insert(&gpu, b);
        let (got, dropped) = t.list(&gpu, cap).unwrap();
        assert_eq!(
            t.downloaded,
            (got.len() * 8 + 8) as u64,
            "only the list crosses"
        );
        let (want, want_dropped) = cpu_list(&ids, buckets, &misses, cap);
        let full = pool.iter().collect::<std::collections::HashSet<_>>().len() > t.buckets();
        if !full {
            assert_eq!(got, want, "{buckets} buckets, {distinct} keys");
            assert_eq!(dropped, 0);
        } else {
            // Which keys win the last buckets depends on arrival order on
            // both sides: the list is still sorted, full and of held keys.
            assert_eq!(got.len(), want.len());
            assert!(dropped > 0 && want_dropped > 0);
            let mut sorted = got.clone();
            let keyed: Vec<_> = sorted.iter().map(|&(id, n)| (ids.key(id), n)).collect();
            sorted = prioritize(keyed, cap)
                .into_iter()
                .map(|(k, n)| (ids.id(k), n))
                .collect();
            assert_eq!(got, sorted);
        }
        // Cleared, the table starts again.
        t.clear(&gpu);
        t.insert(&gpu, &misses[..1]);
        let (one, _) = t.list(&gpu, cap).unwrap();
        assert_eq!(one, vec![(misses[0][0], misses[0][1])]);
    }
}

#[test]
fn request_counts_saturate() {
    let Some(gpu) = test_gpu() else { return };
    let ids = BrickIds::new(&[[2, 2, 2]], 1).unwrap();
    let mut t = RequestTableGpu::new(&gpu, &ids, 8);
    let misses = vec![[3u32, u32::MAX / 2], [3, u32::MAX / 2], [3, 7], [5, 1]];
    t.insert(&gpu, &misses);
    let (got, _) = t.list(&gpu, 4).unwrap();
    let (want, _) = cpu_list(&ids, 8, &misses, 4);
    assert_eq!(got, want);
    assert_eq!(got[0], (3, u32::MAX));
}
