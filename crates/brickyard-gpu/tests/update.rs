//! The update step on the device (slot choice by the device's LRU orders,
//! parallel referencing) against its CPU twin, frame after frame, with a
//! pool and page-table caches far smaller than the volume: page tables,
//! stamps, owners, LRU orders, reserved slots and counts must be equal.
//! Separately: bricks that share page-table blocks, referenced in one
//! parallel batch, make exactly one block per region, and the device's
//! own page-table walk finds every brick in its slot.

use brickyard_cache::brick::BrickKey;
use brickyard_cache::vm::{VirtualMemory, VmConfig};
use brickyard_core::{plan_levels, DType, Dims3};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::update::{DeviceCache, Item, UpdateModel, NONE};
use brickyard_gpu::vm::{DeviceVm, Query};
use std::collections::HashSet;

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 33
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

const BRICK: u64 = 4;

fn levels(dims: Dims3) -> Vec<Dims3> {
    plan_levels(dims, [1.0; 3], [0.0; 3], [BRICK; 3])
        .levels
        .iter()
        .map(|l| l.dims)
        .collect()
}

fn vm(dims: Dims3, channels: usize, pool_slots: u64, pt_blocks: u64) -> VirtualMemory {
    let cfg = VmConfig {
        brick: [BRICK; 3],
        apron: 1,
        pt_block: [2; 3],
        // A small directory forces intermediate page-table levels.
        max_dir_entries: 16,
        pool_bytes: pool_slots * 6 * 6 * 6 + 8 * pool_slots,
        pt_cache_blocks: pt_blocks,
        request_cap: 64,
        upload_bytes_per_frame: 1 << 30,
    };
    VirtualMemory::new(&levels(dims), channels, DType::U8, cfg)
}

/// Every brick key of the volume.
fn all_keys(dims: Dims3, channels: usize) -> Vec<BrickKey> {
    let mut keys = vec![];
    for (l, d) in levels(dims).iter().enumerate() {
        let g = d.map(|n| n.div_ceil(BRICK) as u32);
        for c in 0..channels {
            for z in 0..g[0] {
                for y in 0..g[1] {
                    for x in 0..g[2] {
                        keys.push(BrickKey::new(l as u8, c as u16, [z, y, x]));
                    }
                }
            }
        }
    }
    keys
}

/// The renderer's part, on the model: stamp the slot of a resident brick
/// and the page-table blocks on its path.
fn touch(m: &mut UpdateModel, it: &Item, frame: u32) -> bool {
    let path = m.path_of(it);
    let (_, e) = m.entry_for(it);
    if e[0] >> 30 != 1 {
        return false;
    }
    let exact = it.level.is_multiple_of(2) || frame.is_multiple_of(3);
    for (set, slot) in path {
        m.stamp(set, slot, frame, exact);
    }
    true
}

#[test]
fn update_step_equals_cpu_twin_frame_after_frame() {
    let Some(gpu) = test_gpu() else { return };
    let dims = [40, 36, 48];
    for (channels, pool, pt_blocks, seed) in [(1, 40, 5, 1u64), (2, 64, 9, 2), (1, 300, 40, 3)] {
        let mut vm = vm(dims, channels, pool, pt_blocks);
        assert!(vm.layout().nmax() >= 3, "two intermediate levels at least");
        let (dvm, _) = DeviceVm::new(&gpu, &mut vm).unwrap();
        let mut cache = DeviceCache::new(&gpu, &dvm, &vm).unwrap();
        let mut model = UpdateModel::new(&dvm, &vm);
        // Evicted bricks used at their own level in the last 4 frames
        // count as in use (views drawn in turn).
        model.in_use_frames = 4;
        cache.set_in_use_frames(4);
        let mut in_use = 0;
        let keys = all_keys(dims, channels);
        let slots = vm.pool_slots();
        assert!(
            keys.len() > 4 * slots,
            "the volume is far larger than the pool"
        );
        let mut rng = Lcg(seed);
        let mut inserted: Vec<Item> = vec![];
        let mut failed_some = false;
        let mut most_exact = 0;
        for frame in 1..=24u32 {
            // The renderer: use some resident bricks this frame.
            let mut used = 0;
            // Pool slots used at their own level (what the device counts).
            let mut exact = HashSet::new();
            for it in &inserted {
                if rng.below(3) == 0 && touch(&mut model, it, frame) {
                    used += 1;
                    if it.level.is_multiple_of(2) || frame.is_multiple_of(3) {
                        let path = model.path_of(it);
                        let pool = path.iter().find(|(set, _)| *set == 0).unwrap();
                        exact.insert(pool.1);
                    }
                }
            }
            most_exact = most_exact.max(exact.len());
            gpu.queue
                .write_buffer(&cache.stamps, 0, bytemuck::cast_slice(&model.stamps));
            // Slots for a batch of bricks: sometimes more than the pool
            // can give.
            let k = rng.below(slots as u64 + 8) as usize;
            let want = model.end_frame(frame, k);
            let got = cache.end_frame(&gpu, &dvm, frame, k).unwrap();
            assert_eq!(got, want, "reserved slots, frame {frame}");
            assert_eq!(cache.counts(), model.counts, "counts, frame {frame}");
            in_use += model.counts.evicted_in_use;
            assert_eq!(
                cache.counts().exact_pool_slots as usize,
                exact.len(),
                "slots used at their own level, frame {frame}"
            );
            let free: Vec<u32> = got.iter().copied().filter(|&s| s != NONE).collect();
            if free.len() < k {
                assert!(used > 0 || k > slots, "slots withheld only when in use");
            }
            // The batch: distinct keys, data bricks into the reserved
            // slots, empty and constant ones, and some already resident.
            let mut taken = HashSet::new();
            let mut items = vec![];
            let mut free = free.into_iter();
            for _ in 0..k + rng.below(12) as usize {
                let key = keys[rng.below(keys.len() as u64) as usize];
                if !taken.insert(key) {
                    continue;
                }
                let it = match rng.below(10) {
                    0 => Item::empty(key),
                    1 => Item::constant(key, 7 + rng.below(200) as u32),
                    _ => match free.next() {
                        Some(s) => Item::data(key, s),
                        None => continue,
                    },
                };
                items.push(it);
            }
            if rng.below(4) == 0 {
                // A brick delivered twice: already resident, left alone.
                if let Some(old) = inserted.last().copied() {
                    if let Some(s) = free.next() {
                        let key = BrickKey::new(old.level as u8, old.channel as u16, {
                            [old.brick[0], old.brick[1], old.brick[2]]
                        });
                        if taken.insert(key) {
                            items.push(Item::data(key, s));
                        }
                    }
                }
            }
            let before = model.counts.failed;
            model.reference(frame, &items);
            failed_some |= model.counts.failed > before;
            cache.reference(&gpu, &dvm, frame, &items);
            let entries = dvm.read_entries(&gpu).unwrap();
            assert!(entries == model.entries, "page tables, frame {frame}");
            let st = cache.read_state(&gpu).unwrap();
            assert!(st.stamps == model.stamps, "stamps, frame {frame}");
            assert!(st.owner == model.owner, "owners, frame {frame}");
            assert!(st.orders == model.order, "LRU orders, frame {frame}");
            model
                .check()
                .unwrap_or_else(|e| panic!("frame {frame}: {e}"));
            inserted.extend(items);
        }
        // The small caches must have been under pressure.
        let c = model.counts;
        assert!(c.bricks_unmapped > 0 && c.blocks_unmapped > 0, "{c:?}");
        assert!(
            most_exact > 1,
            "slots used at their own level: at most {most_exact}"
        );
        assert!(
            in_use > 0 && in_use < c.bricks_unmapped,
            "evicted in use: {in_use} of {}",
            c.bricks_unmapped
        );
        if pt_blocks < 10 {
            assert!(failed_some, "some items found no page-table block: {c:?}");
        }
    }
}

#[test]
fn bricks_sharing_blocks_make_one_block_per_region() {
    let Some(gpu) = test_gpu() else { return };
    let dims = [40, 36, 48];
    let keys: Vec<BrickKey> = all_keys(dims, 1)
        .into_iter()
        .filter(|k| k.level == 0)
        .collect();
    let mut vm = vm(dims, 1, keys.len() as u64, 4096);
    assert!(vm.pool_slots() >= keys.len());
    let nmax = vm.layout().nmax();
    // Regions: one block of level n per distinct entry of level n - 1
    // that the bricks pass through.
    let mut regions = 0;
    for n in 1..nmax {
        let span = vm.layout().entry_span(n - 1);
        let distinct: HashSet<[u64; 3]> = keys
            .iter()
            .map(|k| [0, 1, 2].map(|a| k.brick[a] as u64 * BRICK / span[a]))
            .collect();
        regions += distinct.len() as u32;
    }
    let (dvm, _) = DeviceVm::new(&gpu, &mut vm).unwrap();
    let mut cache = DeviceCache::new(&gpu, &dvm, &vm).unwrap();
    let slots = cache.end_frame(&gpu, &dvm, 1, keys.len()).unwrap();
    assert_eq!(slots.len(), keys.len());
    assert!(slots.iter().all(|&s| s != NONE));
    let items: Vec<Item> = keys
        .iter()
        .zip(&slots)
        .map(|(k, &s)| Item::data(*k, s))
        .collect();
    cache.reference(&gpu, &dvm, 1, &items);
    cache.end_frame(&gpu, &dvm, 2, 0).unwrap();
    let c = cache.counts();
    assert_eq!(c.blocks_mapped, regions, "one block per region: {c:?}");
    assert_eq!(c.bricks_mapped as usize, keys.len());
    assert_eq!(c.failed, 0);
    // The device's own walk (vm.wgsl) finds each brick in its slot.
    let queries: Vec<Query> = keys
        .iter()
        .map(|k| {
            let v = k.brick.map(|b| b as u64 * BRICK);
            Query::new(0, 0, v, [0.0; 3])
        })
        .collect();
    let found = dvm.lookup(&gpu, &queries).unwrap();
    assert_eq!(found.len(), keys.len(), "one answer per query");
    for ((k, s), (_, slot)) in keys.iter().zip(&slots).zip(found) {
        assert_eq!(slot, Some(*s), "brick {k:?}");
    }
}

#[test]
fn fresh_bricks_are_not_taken_back_while_never_used_slots_remain() {
    // A brick written in one frame and not used in the next (the next frame
    // drew another view) must stay: slots never used come first.
    let Some(gpu) = test_gpu() else { return };
    let dims = [40, 36, 48];
    let mut vm = vm(dims, 1, 40, 64);
    let (dvm, _) = DeviceVm::new(&gpu, &mut vm).unwrap();
    let mut cache = DeviceCache::new(&gpu, &dvm, &vm).unwrap();
    let keys: Vec<BrickKey> = all_keys(dims, 1).into_iter().take(12).collect();
    let mut slots_seen = HashSet::new();
    for (frame, batch) in keys.chunks(4).enumerate() {
        let frame = frame as u32 + 1;
        let slots = cache.end_frame(&gpu, &dvm, frame, batch.len()).unwrap();
        assert_eq!(
            slots.len(),
            batch.len(),
            "frame {frame}: one slot per brick"
        );
        for &s in &slots {
            assert!(
                s != NONE && slots_seen.insert(s),
                "frame {frame}: slot {s} taken again"
            );
        }
        let items: Vec<Item> = batch
            .iter()
            .zip(&slots)
            .map(|(k, &s)| Item::data(*k, s))
            .collect();
        cache.reference(&gpu, &dvm, frame, &items);
    }
    // Every brick is still where it was put.
    let queries: Vec<Query> = keys
        .iter()
        .map(|k| {
            Query::new(
                k.level as usize,
                0,
                k.brick.map(|b| b as u64 * BRICK),
                [0.0; 3],
            )
        })
        .collect();
    let found = dvm.lookup(&gpu, &queries).unwrap();
    assert_eq!(found.len(), keys.len(), "one answer per query");
    for (k, (_, slot)) in keys.iter().zip(found) {
        assert!(slot.is_some(), "brick {k:?} was evicted");
    }
}

/// Bricks pinned in the host's virtual memory before the device mirrors it
/// (the coarsest levels, as `Session::pin_coarsest` does) survive any
/// pressure on the device: every frame asks for more slots than the pool
/// has and references far more bricks than fit, yet the pinned bricks keep
/// their slots and page-table paths, on the device and in its twin alike.
#[test]
fn pinned_bricks_are_never_taken() {
    use brickyard_cache::brick::{BrickContent, LoadedBrick};
    use std::sync::Arc;
    let Some(gpu) = test_gpu() else { return };
    let dims = [40, 36, 48];
    let mut vm = vm(dims, 1, 40, 6);
    let keys = all_keys(dims, 1);
    let coarsest = levels(dims).len() - 1;
    let pinned_keys: Vec<BrickKey> = keys
        .iter()
        .copied()
        .filter(|k| k.level as usize >= coarsest - 1)
        .collect();
    assert!(pinned_keys.len() >= 2 && pinned_keys.len() < 20);
    let bricks: Vec<Arc<LoadedBrick>> = pinned_keys
        .iter()
        .map(|&key| {
            Arc::new(LoadedBrick {
                key,
                content: BrickContent::Data(Arc::from(vec![9u8; 216])),
                min: 9.0,
                max: 9.0,
                bytes_read: 216,
            })
        })
        .collect();
    vm.begin_frame();
    let r = vm.insert(&bricks);
    assert_eq!(r.inserted, bricks.len());
    for k in &pinned_keys {
        assert!(vm.pin(*k));
    }
    let pins = vm.pinned_slots();
    assert_eq!(pins.iter().filter(|p| p.0 == 0).count(), pinned_keys.len());
    assert!(pins.iter().any(|p| p.0 > 0), "page-table blocks pinned too");
    let (dvm, _) = DeviceVm::new(&gpu, &mut vm).unwrap();
    let mut cache = DeviceCache::new(&gpu, &dvm, &vm).unwrap();
    let mut model = UpdateModel::new(&dvm, &vm);
    let pinned_items: Vec<Item> = pinned_keys
        .iter()
        .map(|&k| {
            let (_, e) = model.entry_for(&Item::empty(k));
            assert_eq!(e[0] >> 30, 1, "pinned brick mapped at start");
            Item::empty(k)
        })
        .collect();
    let before: Vec<[u32; 2]> = pinned_items
        .iter()
        .map(|it| model.entry_for(it).1)
        .collect();
    let slots = vm.pool_slots();
    let mut rng = Lcg(7);
    let mut taken_total = 0;
    for frame in 2..=16u32 {
        gpu.queue
            .write_buffer(&cache.stamps, 0, bytemuck::cast_slice(&model.stamps));
        // More than the pool: everything not pinned is taken.
        let k = slots + 4;
        let want = model.end_frame(frame, k);
        let got = cache.end_frame(&gpu, &dvm, frame, k).unwrap();
        assert_eq!(got, want, "reserved slots, frame {frame}");
        let free: Vec<u32> = got.iter().copied().filter(|&s| s != NONE).collect();
        assert_eq!(free.len(), slots - pinned_keys.len(), "frame {frame}");
        taken_total += free.len();
        let mut items = vec![];
        let mut used = HashSet::new();
        for s in free {
            loop {
                let key = keys[rng.below(keys.len() as u64) as usize];
                if !pinned_keys.contains(&key) && used.insert(key) {
                    items.push(Item::data(key, s));
                    break;
                }
            }
        }
        model.reference(frame, &items);
        cache.reference(&gpu, &dvm, frame, &items);
        let entries = dvm.read_entries(&gpu).unwrap();
        assert!(entries == model.entries, "page tables, frame {frame}");
        let st = cache.read_state(&gpu).unwrap();
        assert!(st.stamps == model.stamps, "stamps, frame {frame}");
        model
            .check()
            .unwrap_or_else(|e| panic!("frame {frame}: {e}"));
        let now: Vec<[u32; 2]> = pinned_items
            .iter()
            .map(|it| model.entry_for(it).1)
            .collect();
        assert_eq!(now, before, "pinned bricks moved, frame {frame}");
    }
    assert!(taken_total > 10 * slots, "the pool was under pressure");
    assert!(
        model.counts.blocks_unmapped > 0,
        "page-table blocks were evicted"
    );
}
