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
/// `dims` voxels spanning `span` of them across the extent overlap: the
/// half-open normalized intervals `[i/2^d, (i+1)/2^d)` and `[b·B/s,
/// min((b+1)·B, n)/s)` intersect on every axis (in f64, exact at these
/// sizes).
fn overlaps(d: u32, i: Dims3, dims: Dims3, span: [f64; 3], brick: Dims3, b: Dims3) -> bool {
    (0..3).all(|a| {
        let s = (1u64 << d) as f64;
        let (n0, n1) = (i[a] as f64 / s, (i[a] + 1) as f64 / s);
        let v0 = (b[a] * brick[a]) as f64 / span[a];
        let v1 = (((b[a] + 1) * brick[a]).min(dims[a])) as f64 / span[a];
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
                        let span = brickyard_core::level_span(&o.dims, l);
                        if overlaps(d, [z, y, x], o.dims[l], span, o.brick, b) {
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
                                                    let span = brickyard_core::level_span(&dims, l);
                                                    if overlaps(d, [z, y, x], *dl, span, brick, b) {
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
    let (lo, hi) = overlap(2, [64; 3], ([64; 3], [1; 3]), [16; 3], [1, 2, 3]);
    assert_eq!((lo, hi), ([1, 2, 3], [2, 3, 4]));
    // 60 voxels: brick 3 is [48, 60) = [0.8, 1): leaf 3 only; brick 1 is
    // [16, 32) = [0.267, 0.533): leaves 1 and 2.
    let (lo, hi) = overlap(2, [60; 3], ([60; 3], [1; 3]), [16; 3], [3, 1, 0]);
    assert_eq!((lo, hi), ([3, 1, 0], [4, 3, 2]));
    // A coarser level of 61 voxels at ratio 2: 31 voxels spanning 30.5.
    // Brick 1 (8 voxels) is [8, 16) of 30.5 = [0.262, 0.525): leaves 1
    // and 2 (of 4); brick 3 is [24, 31): [0.787, 1.016), leaf 3 only;
    // brick 0 is [0, 8): [0, 0.262), reaching into leaf 1 (from 0.25).
    let (lo, hi) = overlap(2, [31; 3], ([61; 3], [2; 3]), [8; 3], [1, 3, 0]);
    assert_eq!((lo, hi), ([1, 3, 0], [3, 4, 2]));
}

#[test]
fn bricks_of_leaf_is_the_inverse_of_overlap() {
    let (dims, brick) = geometry();
    for depth in [1, 2, 3, 4, 6] {
        let o = Octree::new(depth, &dims, brick, 1, None).unwrap();
        let s = 1u64 << depth;
        for (l, &dl) in dims.iter().enumerate() {
            let nb = o.bricks(l);
            for leaf in (0..s * s * s).map(|i| [i / (s * s), i / s % s, i % s]) {
                let (lo, hi) = o.bricks_of_leaf(l, leaf);
                for b in (0..nb[0] * nb[1] * nb[2])
                    .map(|i| [i / (nb[1] * nb[2]), i / nb[2] % nb[1], i % nb[2]])
                {
                    let inside = (0..3).all(|a| lo[a] <= b[a] && b[a] < hi[a]);
                    assert_eq!(
                        inside,
                        overlaps(
                            depth,
                            leaf,
                            dl,
                            brickyard_core::level_span(&dims, l),
                            brick,
                            b
                        ),
                        "depth {depth} level {l} leaf {leaf:?} brick {b:?}"
                    );
                }
            }
        }
    }
}

/// The in-core test volume: per level and channel, u8 voxels `[z][y][x]`:
/// a ball of random values 60–255 (its centre per channel), a slab of
/// the constant 9 at large x, 0 elsewhere.
fn levels_in_core(dims: &[Dims3], channels: usize, rng: &mut Rng) -> Vec<Vec<Vec<u8>>> {
    dims.iter()
        .map(|d| {
            (0..channels)
                .map(|c| {
                    let centre = [0.35 + 0.2 * c as f64, 0.45, 0.3];
                    let mut v = vec![];
                    for z in 0..d[0] {
                        for y in 0..d[1] {
                            for x in 0..d[2] {
                                let p = [z, y, x].map(|i| i as f64 + 0.5);
                                let q = [0, 1, 2].map(|a| p[a] / d[a] as f64 - centre[a]);
                                let r2: f64 = q.iter().map(|x| x * x).sum();
                                v.push(if r2 < 0.04 {
                                    60 + rng.below(196) as u8
                                } else if p[2] / d[2] as f64 > 0.8 {
                                    9
                                } else {
                                    0
                                });
                            }
                        }
                    }
                    v
                })
                .collect()
        })
        .collect()
}

/// Voxel `v` (any coordinates: clamped to the level) of a level array.
fn at(vol: &[u8], d: Dims3, v: [i64; 3]) -> u8 {
    let c = [0, 1, 2].map(|a| v[a].clamp(0, d[a] as i64 - 1) as u64);
    vol[((c[0] * d[1] + c[1]) * d[2] + c[2]) as usize]
}

/// The padded box of brick `b`: level voxels `[lo, hi)` per axis, apron 1.
fn padded_box(brick: Dims3, b: Dims3) -> ([i64; 3], [i64; 3]) {
    (
        [0, 1, 2].map(|a| (b[a] * brick[a]) as i64 - 1),
        [0, 1, 2].map(|a| ((b[a] + 1) * brick[a]) as i64 + 1),
    )
}

#[test]
fn ranges_from_resident_voxels_equal_a_brute_force_under_a_small_pool() {
    // Real voxels (a ball, a constant slab, zeros) through a virtual
    // memory that evicts and orphans under a small pool; after every
    // frame each node's range equals a brute force from the in-core level
    // arrays: per leaf, over the bricks overlapping it, the voxels of the
    // mapped ones within one voxel of the leaf (f64 geometry, every voxel
    // of the padded brick tested), the statistics of the others; inner
    // nodes the union of their leaves. Samples taken inside leaves by an
    // in-core trilinear sampler lie in the leaf's range.
    let (dims, brick) = geometry();
    let channels = 2;
    let mut rng = Rng(0xb0b);
    let vols = levels_in_core(&dims, channels, &mut rng);
    // Statistics: padded ranges from the level arrays; level 2 none, a
    // few unknown bricks at level 1.
    let stats = BrickRanges {
        levels: dims
            .iter()
            .enumerate()
            .map(|(l, &d)| {
                (l != 2).then(|| {
                    let nb = [0, 1, 2].map(|a| d[a].div_ceil(brick[a]));
                    let mut range = vec![];
                    for vol in &vols[l] {
                        for bz in 0..nb[0] {
                            for by in 0..nb[1] {
                                for bx in 0..nb[2] {
                                    if l == 1 && (bz + by + bx) % 5 == 3 {
                                        range.push([f32::NAN; 2]);
                                        continue;
                                    }
                                    let (lo, hi) = padded_box(brick, [bz, by, bx]);
                                    let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                                    for z in lo[0]..hi[0] {
                                        for y in lo[1]..hi[1] {
                                            for x in lo[2]..hi[2] {
                                                let v = at(vol, d, [z, y, x]) as f32;
                                                r = [r[0].min(v), r[1].max(v)];
                                            }
                                        }
                                    }
                                    range.push(r);
                                }
                            }
                        }
                    }
                    LevelRanges {
                        bricks: nb,
                        channels,
                        range,
                    }
                })
            })
            .collect(),
    };
    let padded = 10 * 10 * 10;
    let loaded = |key: BrickKey| {
        let (l, c) = (key.level as usize, key.channel as usize);
        let (lo, _) = padded_box(brick, key.brick.map(|v| v as u64));
        let mut data = Vec::with_capacity(padded);
        for z in 0..10 {
            for y in 0..10 {
                for x in 0..10 {
                    data.push(at(&vols[l][c], dims[l], [lo[0] + z, lo[1] + y, lo[2] + x]));
                }
            }
        }
        let content = if data.iter().all(|&v| v == 0) {
            BrickContent::Empty
        } else if data.iter().all(|&v| v == data[0]) {
            BrickContent::Constant(data[0] as f64)
        } else {
            BrickContent::Data(data.into())
        };
        Arc::new(LoadedBrick {
            key,
            content,
            min: 0.0,
            max: 255.0,
            bytes_read: 0,
        })
    };
    // The brute force: leaf ranges of every node.
    let brute = |o: &Octree, vm: &VirtualMemory| -> Vec<[f32; 2]> {
        let (nl, ch, d) = (dims.len(), channels, o.depth);
        let s = 1u64 << d;
        let mut want = vec![[f32::NAN; 2]; o.range.len()];
        let leaf0 = node_offset(d);
        for leaf in 0..s * s * s {
            let li = [leaf / (s * s), leaf / s % s, leaf % s];
            for c in 0..ch {
                for (l, &dl) in dims.iter().enumerate() {
                    // The leaf's continuous voxel box [a, b) per axis.
                    let span = brickyard_core::level_span(&dims, l);
                    let a = [0, 1, 2].map(|k| li[k] as f64 / s as f64 * span[k]);
                    let b = [0, 1, 2].map(|k| (li[k] + 1) as f64 / s as f64 * span[k]);
                    let nb = o.bricks(l);
                    let mut acc = [f32::INFINITY, f32::NEG_INFINITY];
                    for bz in 0..nb[0] {
                        for by in 0..nb[1] {
                            for bx in 0..nb[2] {
                                let bk = [bz, by, bx];
                                if !overlaps(d, li, dl, span, brick, bk) {
                                    continue;
                                }
                                let key = BrickKey::new(l as u8, c as u16, bk.map(|v| v as u32));
                                let r = if vm.is_resident(key) {
                                    // Voxels j of the padded brick, inside the
                                    // level, whose cell [j, j+1) comes within
                                    // one voxel of [a, b).
                                    let (lo, hi) = padded_box(brick, bk);
                                    let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                                    for z in lo[0]..hi[0] {
                                        for y in lo[1]..hi[1] {
                                            for x in lo[2]..hi[2] {
                                                let j = [z, y, x];
                                                let near = (0..3).all(|k| {
                                                    j[k] >= 0
                                                        && j[k] < dl[k] as i64
                                                        && (j[k] + 1) as f64 > a[k] - 1.0
                                                        && (j[k] as f64) < b[k] + 1.0
                                                });
                                                if near {
                                                    let v = at(&vols[l][c], dl, j) as f32;
                                                    r = [r[0].min(v), r[1].max(v)];
                                                }
                                            }
                                        }
                                    }
                                    if r[0] < r[1] {
                                        let m = r[1].abs().max(r[0].abs()) / 1048576.0;
                                        [r[0] - m, r[1] + m]
                                    } else {
                                        r
                                    }
                                } else {
                                    match stats.level(l) {
                                        Some(lr) => lr.get(c, bk),
                                        None => [f32::NAN; 2],
                                    }
                                };
                                acc = union(acc, r);
                            }
                        }
                    }
                    want[((leaf0 + leaf as usize) * ch + c) * nl + l] = acc;
                }
            }
        }
        // Inner nodes: the union of the leaves below.
        for dd in 0..d {
            let m = 1u64 << dd;
            let sub = 1u64 << (d - dd);
            for node in 0..m * m * m {
                let ni = [node / (m * m), node / m % m, node % m];
                for c in 0..ch {
                    for l in 0..nl {
                        let mut acc = [f32::INFINITY, f32::NEG_INFINITY];
                        for k in 0..sub * sub * sub {
                            let li = [
                                ni[0] * sub + k / (sub * sub),
                                ni[1] * sub + k / sub % sub,
                                ni[2] * sub + k % sub,
                            ];
                            let leaf = leaf0 + ((li[0] * s + li[1]) * s + li[2]) as usize;
                            acc = union(acc, want[(leaf * ch + c) * nl + l]);
                        }
                        want[(o.node(dd, ni) * ch + c) * nl + l] = acc;
                    }
                }
            }
        }
        want
    };
    let same_all = |a: &[[f32; 2]], b: &[[f32; 2]]| {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| same(*x, *y))
    };
    for (depth, frames) in [(3u32, 90), (4, 25)] {
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
        let mut vm = VirtualMemory::new(&dims, channels, DType::U8, cfg);
        let mut o = Octree::attach(depth, &dims, &mut vm, Some(&stats)).unwrap();
        let stats_only = o.range.clone();
        let mut keys = vec![];
        for l in 0..dims.len() {
            let nb = o.bricks(l);
            for c in 0..channels as u16 {
                for i in 0..nb[0] * nb[1] * nb[2] {
                    let b = [i / (nb[1] * nb[2]), i / nb[2] % nb[1], i % nb[2]];
                    keys.push(BrickKey::new(l as u8, c, b.map(|v| v as u32)));
                }
            }
        }
        let (mut evicted, mut tighter, mut kinds) = (0, 0usize, [0usize; 3]);
        for frame in 0..frames {
            vm.begin_frame();
            let bricks: Vec<Arc<LoadedBrick>> = (0..rng.below(12))
                .map(|_| loaded(keys[rng.below(keys.len() as u64) as usize]))
                .collect();
            for b in &bricks {
                kinds[match b.content {
                    BrickContent::Empty => 0,
                    BrickContent::Constant(_) => 1,
                    BrickContent::Data(_) => 2,
                }] += 1;
            }
            let rep = vm.insert(&bricks);
            evicted += rep.evicted_bricks + rep.evicted_pt_blocks + rep.orphans_reclaimed;
            o.sync(&mut vm);
            let want = brute(&o, &vm);
            assert!(same_all(&o.range, &want), "depth {depth}, frame {frame}");
            tighter += o
                .range
                .iter()
                .zip(&stats_only)
                .filter(|(a, b)| !a[0].is_nan() && !b[0].is_nan() && (a[0] > b[0] || a[1] < b[1]))
                .count();
        }
        eprintln!(
            "depth {depth}: {evicted} evictions, {tighter} ranges tighter than the statistics, \
             bricks inserted empty/constant/data {kinds:?}, {} read now",
            o.read_bricks()
        );
        assert!(evicted > 20 && tighter > 100, "{evicted} {tighter}");
        assert!(kinds.iter().all(|&k| k > 3), "{kinds:?}");
        // Samples inside each leaf (corners of the leaf included) lie in
        // its range, by an in-core clamp-to-edge trilinear sampler.
        let s = 1u64 << depth;
        let leaf0 = node_offset(depth);
        let mut checked = 0;
        for leaf in 0..s * s * s {
            let li = [leaf / (s * s), leaf / s % s, leaf % s];
            for (l, &dl) in dims.iter().enumerate() {
                for (c, vol) in vols[l].iter().enumerate() {
                    let r = o.range_of(leaf0 + leaf as usize, c, l);
                    if r[0].is_nan() {
                        continue;
                    }
                    for k in 0..12 {
                        let u = [0, 1, 2].map(|_| match k {
                            0 => 0.0,
                            1 => 1.0 - 1e-9,
                            _ => rng.below(1000) as f64 / 1000.0,
                        });
                        let q = [0, 1, 2].map(|a| {
                            let p = (li[a] as f64 + u[a]) / s as f64;
                            (p * dl[a] as f64 - 0.5).clamp(0.0, dl[a] as f64 - 1.0)
                        });
                        let j = q.map(|x| x.floor() as i64);
                        let f = [0, 1, 2].map(|a| (q[a] - j[a] as f64) as f32);
                        let mut corner = [0f32; 8];
                        for (i, cv) in corner.iter_mut().enumerate() {
                            let v = [
                                j[0] + (i >> 2) as i64,
                                j[1] + (i >> 1 & 1) as i64,
                                j[2] + (i & 1) as i64,
                            ];
                            *cv = at(vol, dl, v) as f32;
                        }
                        let v = brickyard_core::dtype::trilinear(corner, f, false);
                        assert!(
                            r[0] <= v && v <= r[1],
                            "depth {depth} leaf {li:?} c {c} l {l}: sample {v} outside {r:?}"
                        );
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 1000, "{checked}");
        // Kept equals fresh from the virtual memory; everything evicted:
        // the statistics again.
        let fresh = Octree::of_vm(depth, &dims, &vm, Some(&stats)).unwrap();
        assert!(same_all(&o.range, &fresh.range));
        let all: Vec<Event> = keys
            .iter()
            .filter(|k| vm.is_resident(**k))
            .map(|&key| Event { key, mapped: false })
            .collect();
        o.apply(&all);
        assert_eq!(o.read_bricks(), 0);
        assert!(same_all(&o.range, &stats_only));
    }
}
