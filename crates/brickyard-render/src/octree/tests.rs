//! Tests of the residency octree's CPU model: masks and ranges after every
//! step of random map/evict sequences (and of a virtual memory evicting
//! and orphaning under a small pool) against a brute-force model that
//! recomputes everything from the mapped set, node by node.

use super::*;
use brickyard_cache::brick::{BrickContent, LoadedBrick};
use brickyard_cache::ranges::LevelRanges;
use brickyard_cache::vm::VmConfig;
use brickyard_core::DType;
use std::sync::Arc;

/// Small deterministic generator (xorshift).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// Whether node `i` (per axis) of depth `d` and brick `b` of a level of
/// `dims` overlap: the half-open normalized intervals `[i/2^d, (i+1)/2^d)`
/// and `[b·B/n, min((b+1)·B, n)/n)` intersect on every axis (in f64, exact
/// at these sizes).
fn overlaps(d: u32, i: Dims3, dims: Dims3, brick: Dims3, b: Dims3) -> bool {
    (0..3).all(|a| {
        let s = (1u64 << d) as f64;
        let (n0, n1) = (i[a] as f64 / s, (i[a] + 1) as f64 / s);
        let v0 = (b[a] * brick[a]) as f64 / dims[a] as f64;
        let v1 = (((b[a] + 1) * brick[a]).min(dims[a])) as f64 / dims[a] as f64;
        n0 < v1 && v0 < n1
    })
}

/// Masks recomputed from the mapped set, every node on its own.
fn brute_masks(o: &Octree, mapped: &HashSet<u64>) -> Vec<u32> {
    let mut m = vec![0u32; o.mask.len()];
    for d in 0..=o.depth {
        let s = 1u64 << d;
        for z in 0..s {
            for y in 0..s {
                for x in 0..s {
                    let node = o.node(d, [z, y, x]);
                    for &k in mapped {
                        let key = BrickKey::unpack(k);
                        let l = key.level as usize;
                        let b = key.brick.map(|v| v as u64);
                        if overlaps(d, [z, y, x], o.dims[l], o.brick, b) {
                            m[node * o.channels + key.channel as usize] |= 1 << l;
                        }
                    }
                }
            }
        }
    }
    m
}

fn geometry() -> (Vec<Dims3>, Dims3) {
    // Odd sizes: bricks and nodes do not line up.
    (
        vec![[37, 50, 61], [19, 25, 31], [10, 13, 16], [5, 7, 8]],
        [8, 8, 8],
    )
}

fn ranges_for(dims: &[Dims3], brick: Dims3, channels: usize, rng: &mut Rng) -> BrickRanges {
    BrickRanges {
        levels: dims
            .iter()
            .enumerate()
            .map(|(l, d)| {
                if l == 2 {
                    return None; // a level without statistics
                }
                let nb = [0, 1, 2].map(|a| d[a].div_ceil(brick[a]));
                let n = (nb.iter().product::<u64>() as usize) * channels;
                Some(LevelRanges {
                    bricks: nb,
                    channels,
                    range: (0..n)
                        .map(|i| {
                            if l == 1 && i % 97 == 5 {
                                return [f32::NAN; 2];
                            }
                            let a = rng.below(200) as f32;
                            [a, a + rng.below(40) as f32]
                        })
                        .collect(),
                })
            })
            .collect(),
    }
}

#[test]
fn ranges_are_the_union_of_the_overlapping_bricks() {
    let (dims, brick) = geometry();
    let mut rng = Rng(7);
    for depth in [1, 2, 3] {
        let r = ranges_for(&dims, brick, 2, &mut rng);
        let o = Octree::new(depth, &dims, brick, 2, Some(&r)).unwrap();
        let mut known = 0;
        for d in 0..=depth {
            let s = 1u64 << d;
            for z in 0..s {
                for y in 0..s {
                    for x in 0..s {
                        let node = o.node(d, [z, y, x]);
                        for c in 0..2 {
                            for (l, dl) in dims.iter().enumerate() {
                                let mut want = [f32::INFINITY, f32::NEG_INFINITY];
                                match r.level(l) {
                                    None => want = [f32::NAN; 2],
                                    Some(lr) => {
                                        let nb = o.bricks(l);
                                        for bz in 0..nb[0] {
                                            for by in 0..nb[1] {
                                                for bx in 0..nb[2] {
                                                    let b = [bz, by, bx];
                                                    if overlaps(d, [z, y, x], *dl, brick, b) {
                                                        want = union(want, lr.get(c, b));
                                                    }
                                                }
                                            }
                                        }
                                    }
                                }
                                let got = o.range_of(node, c, l);
                                if want[0].is_nan() {
                                    assert!(got[0].is_nan(), "d {d} node {node} c {c} l {l}");
                                } else {
                                    known += 1;
                                    assert_eq!(got, want, "d {d} node {node} c {c} l {l}");
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(known > 20, "depth {depth}: {known} known ranges");
    }
}

#[test]
fn random_map_and_evict_sequences_equal_the_brute_force_model() {
    let (dims, brick) = geometry();
    let channels = 3;
    for (depth, seed) in [(1, 1u64), (2, 2), (3, 3), (4, 4)] {
        let mut rng = Rng(seed * 0x9E37_79B9 + 1);
        let mut o = Octree::new(depth, &dims, brick, channels, None).unwrap();
        let mut mapped: HashSet<u64> = HashSet::new();
        let mut changes = 0;
        for step in 0..60 {
            // A frame: a few maps and evicts, some repeated or invalid.
            let mut events = vec![];
            for _ in 0..rng.below(25) {
                let l = rng.below(dims.len() as u64) as usize;
                let nb = o.bricks(l);
                let key = BrickKey::new(
                    l as u8,
                    rng.below(channels as u64) as u16,
                    [0, 1, 2].map(|a| rng.below(nb[a]) as u32),
                );
                let map = rng.below(3) != 0;
                events.push(Event { key, mapped: map });
            }
            // Evict some keys actually mapped too.
            let keys: Vec<u64> = mapped.iter().copied().collect();
            for _ in 0..rng.below(8).min(keys.len() as u64) {
                let k = keys[rng.below(keys.len() as u64) as usize];
                events.push(Event {
                    key: BrickKey::unpack(k),
                    mapped: false,
                });
            }
            for e in &events {
                let k = e.key.pack();
                if e.mapped {
                    changes += mapped.insert(k) as u32;
                } else {
                    changes += mapped.remove(&k) as u32;
                }
            }
            o.apply(&events);
            assert_eq!(o.mapped_count(), mapped.len());
            let want = brute_masks(&o, &mapped);
            assert_eq!(o.mask, want, "depth {depth}, step {step}");
        }
        assert!(changes > 200, "{changes}");
        // Everything evicted: all masks clear again.
        let all: Vec<Event> = mapped
            .iter()
            .map(|&k| Event {
                key: BrickKey::unpack(k),
                mapped: false,
            })
            .collect();
        o.apply(&all);
        assert!(o.mask.iter().all(|&m| m == 0));
        assert!(o.count.iter().all(|&c| c == 0));
    }
}

#[test]
fn sync_follows_a_virtual_memory_that_evicts_and_orphans() {
    // A small pool and page-table cache: inserts evict bricks and orphan
    // page-table blocks with what lies below; after every frame the masks
    // equal the brute force over the keys the virtual memory has mapped.
    let (dims, _) = geometry();
    let brick = [8u64; 3];
    let cfg = VmConfig {
        brick,
        apron: 1,
        pt_block: [2; 3],
        max_dir_entries: 64,
        pool_bytes: 20 * 1008,
        pt_cache_blocks: 24,
        request_cap: 64,
        upload_bytes_per_frame: 1 << 30,
    };
    let mut vm = VirtualMemory::new(&dims, 2, DType::U8, cfg);
    let padded = 10 * 10 * 10;
    let mut o = Octree::attach(3, &dims, &mut vm, None).unwrap();
    assert_eq!(o.mapped_count(), 0);
    let mut rng = Rng(99);
    let (mut evicted, mut lost_frames) = (0usize, 0);
    let all_keys = |o: &Octree| {
        let mut v = vec![];
        for l in 0..dims.len() {
            let nb = o.bricks(l);
            for c in 0..2u16 {
                for z in 0..nb[0] {
                    for y in 0..nb[1] {
                        for x in 0..nb[2] {
                            v.push(BrickKey::new(l as u8, c, [z as u32, y as u32, x as u32]));
                        }
                    }
                }
            }
        }
        v
    };
    let keys = all_keys(&o);
    for frame in 0..150 {
        vm.begin_frame();
        let n = rng.below(12) as usize;
        let bricks: Vec<Arc<LoadedBrick>> = (0..n)
            .map(|_| {
                let key = keys[rng.below(keys.len() as u64) as usize];
                let content = match rng.below(6) {
                    0 => BrickContent::Empty,
                    1 => BrickContent::Constant(3.0),
                    _ => BrickContent::Data(vec![7u8; padded].into()),
                };
                Arc::new(LoadedBrick {
                    key,
                    content,
                    min: 0.0,
                    max: 7.0,
                    bytes_read: 0,
                })
            })
            .collect();
        let rep = vm.insert(&bricks);
        evicted += rep.evicted_bricks + rep.evicted_pt_blocks + rep.orphans_reclaimed;
        let events = o.sync(&mut vm);
        lost_frames += events.iter().any(|e| !e.mapped) as u32;
        let mapped: HashSet<u64> = keys
            .iter()
            .filter(|&&k| vm.is_resident(k))
            .map(|k| k.pack())
            .collect();
        assert_eq!(o.mapped_count(), mapped.len(), "frame {frame}");
        assert_eq!(o.mask, brute_masks(&o, &mapped), "frame {frame}");
    }
    eprintln!("{evicted} evictions and orphans, {lost_frames} frames with evict events");
    assert!(evicted > 40 && lost_frames > 15, "{evicted} {lost_frames}");
    // A fresh octree attached now sees the same.
    let o2 = Octree::attach(3, &dims, &mut vm, None).unwrap();
    assert_eq!(o2.mask, o.mask);
}

#[test]
fn depths_out_of_range_are_refused_naming_the_depth() {
    let (dims, brick) = geometry();
    for d in [0, 8, 20] {
        let e = Octree::new(d, &dims, brick, 1, None)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("octree_depth") && e.contains(&d.to_string()),
            "{e}"
        );
    }
    let e = Octree::new(7, &dims, brick, 64, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("smaller depth"), "{e}");
}

#[test]
fn overlap_is_exact_at_node_and_brick_boundaries() {
    // 64 voxels, bricks of 16, depth 2: brick b covers exactly leaf b.
    let (lo, hi) = overlap(2, [64; 3], [16; 3], [1, 2, 3]);
    assert_eq!((lo, hi), ([1, 2, 3], [2, 3, 4]));
    // 60 voxels: brick 3 is [48, 60) = [0.8, 1): leaf 3 only; brick 1 is
    // [16, 32) = [0.267, 0.533): leaves 1 and 2.
    let (lo, hi) = overlap(2, [60; 3], [16; 3], [3, 1, 0]);
    assert_eq!((lo, hi), ([3, 1, 0], [4, 3, 2]));
}
