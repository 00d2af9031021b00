//! `brickyard bench cache-kernels`: the device's cache-management kernels
//! beside their CPU twins, in one run: LRU compaction of pools of 16k–1M
//! slots, request collection + the capped list for a frame's misses, and
//! the whole update step (every LRU order, slot reservation, referencing)
//! for batches of bricks.
//! Device times are wall times from submission to completion (read-back of
//! the request list included), on whatever adapter `Gpu::new` picks.

use anyhow::{Context, Result};
use brickyard_cache::bookkeeping::{compact_lru, prioritize, BrickIds, RequestTable};
use brickyard_gpu::lru::{LruBuffers, LruCompaction};
use brickyard_gpu::requests::RequestTableGpu;
use brickyard_gpu::{AdapterChoice, Gpu};
use serde_json::json;
use std::time::Instant;

struct Lcg(u64);
impl Lcg {
    fn below(&mut self, n: u32) -> u32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (((self.0 >> 33) * n as u64) >> 31) as u32
    }
}

/// Best of `repeat` runs of `f`, in milliseconds.
fn best(repeat: usize, mut f: impl FnMut()) -> f64 {
    (0..repeat.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
}

pub fn cache_kernels(repeat: usize) -> Result<()> {
    let gpu = Gpu::new(AdapterChoice::Best).context("cache-kernels needs a GPU adapter")?;
    let adapter = gpu.describe();
    let lru = LruCompaction::new(&gpu);
    let mut rng = Lcg(3);
    for &n in &[1u32 << 14, 1 << 18, 1 << 20] {
        let mut order: Vec<u32> = (0..n).collect();
        for i in (1..n as usize).rev() {
            order.swap(i, rng.below(i as u32 + 1) as usize);
        }
        // A quarter of the slots used this frame.
        let frame = 10;
        let usage: Vec<u32> = (0..n)
            .map(|_| if rng.below(4) == 0 { frame } else { frame - 1 })
            .collect();
        let cpu_ms = best(repeat, || {
            std::hint::black_box(compact_lru(&order, |s| usage[s as usize] == frame));
        });
        let b = LruBuffers::new(&gpu, &order, &usage)?;
        let dev_ms = best(repeat, || {
            lru.run(&gpu, &b, frame);
            let _ = gpu.device.poll(wgpu::PollType::wait_indefinitely());
        });
        println!(
            "{}",
            json!({"scenario": "cache-kernels", "kernel": "lru-compaction", "slots": n,
                   "cpu_ms": cpu_ms, "device_ms": dev_ms, "adapter": adapter})
        );
    }
    // A frame's misses: 200k events over 3000 bricks of a 5-level volume,
    // 4096 buckets, the list capped at 256.
    let grid = [
        [64, 64, 64],
        [32, 32, 32],
        [16, 16, 16],
        [8, 8, 8],
        [4, 4, 4],
    ];
    let ids = BrickIds::new(&grid, 1).context("brick ids")?;
    let keys: Vec<u32> = (0..3000).map(|_| rng.below(ids.len())).collect();
    let misses: Vec<[u32; 2]> = (0..200_000)
        .map(|_| [keys[rng.below(3000) as usize], 1])
        .collect();
    let (buckets, cap) = (4096, 256);
    let cpu_ms = best(repeat, || {
        let mut t = RequestTable::new(buckets);
        for m in &misses {
            t.add(m[0], m[1]);
        }
        let list = t
            .entries()
            .into_iter()
            .map(|(id, n)| (ids.key(id), n))
            .collect();
        std::hint::black_box(prioritize(list, cap));
    });
    let mut t = RequestTableGpu::new(&gpu, &ids, buckets);
    let mut list_ms = f64::INFINITY;
    let dev_ms = best(repeat, || {
        t.clear(&gpu);
        t.insert(&gpu, &misses);
        let s = Instant::now();
        let _ = t.list(&gpu, cap);
        list_ms = list_ms.min(s.elapsed().as_secs_f64() * 1e3);
    });
    println!(
        "{}",
        json!({"scenario": "cache-kernels", "kernel": "requests", "misses": misses.len(),
               "distinct": 3000, "buckets": buckets, "cap": cap,
               "cpu_ms": cpu_ms, "device_ms": dev_ms, "device_sort_and_readback_ms": list_ms,
               "readback_bytes": t.downloaded, "adapter": adapter})
    );
    update_step(&gpu, repeat, &adapter)
}

/// The update step (compaction of every LRU order, slot reservation and
/// referencing of a batch of bricks) for the virtual memory of a 4096³
/// volume (64 GiB of u8) with a 512 MiB pool: the device's kernels beside
/// their CPU twin ([`UpdateModel`]), bookkeeping only (no brick data).
fn update_step(gpu: &Gpu, repeat: usize, adapter: &str) -> Result<()> {
    use brickyard_cache::brick::BrickKey;
    use brickyard_cache::vm::{VirtualMemory, VmConfig};
    use brickyard_gpu::update::{DeviceCache, Item, UpdateModel};
    use brickyard_gpu::vm::DeviceVm;
    let dims = [4096u64; 3];
    let levels: Vec<[u64; 3]> = (0..8).map(|l| dims.map(|d| (d >> l).max(1))).collect();
    let cfg = VmConfig {
        pool_bytes: 512 << 20,
        ..Default::default()
    };
    let mut vm = VirtualMemory::new(&levels, 1, brickyard_core::DType::U8, cfg);
    let (dvm, _) = DeviceVm::new(gpu, &mut vm)?;
    let mut cache = DeviceCache::new(gpu, &dvm, &vm)?;
    let mut model = UpdateModel::new(&dvm, &vm);
    let slots = vm.pool_slots();
    for &k in &[64usize, 1024] {
        let (mut cpu_ms, mut dev_ms) = (f64::INFINITY, f64::INFINITY);
        for r in 0..repeat.max(1) + 1 {
            let frame = 2 * r as u32 + 1 + if k == 64 { 0 } else { 1000 };
            // A batch of neighbouring bricks of level 0 (sharing page-table
            // blocks), a different region each time.
            let z = (r * 8 + k / 64) as u32 % 128;
            let items: Vec<Item> = (0..k as u32)
                .map(|i| {
                    let key = BrickKey::new(0, 0, [z, i / 32 % 128, i % 32 + (r as u32 % 4) * 32]);
                    Item::data(key, 0)
                })
                .collect();
            let t = Instant::now();
            let got = model.end_frame(frame, k);
            let items_m: Vec<Item> = items
                .iter()
                .zip(&got)
                .map(|(it, &s)| {
                    Item::data(
                        BrickKey::new(0, 0, [it.brick[0], it.brick[1], it.brick[2]]),
                        s,
                    )
                })
                .collect();
            model.reference(frame, &items_m);
            cpu_ms = cpu_ms.min(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            let got = cache.end_frame(gpu, &dvm, frame, k)?;
            let items_d: Vec<Item> = items
                .iter()
                .zip(&got)
                .map(|(it, &s)| {
                    Item::data(
                        BrickKey::new(0, 0, [it.brick[0], it.brick[1], it.brick[2]]),
                        s,
                    )
                })
                .collect();
            cache.reference(gpu, &dvm, frame, &items_d);
            let _ = gpu.device.poll(wgpu::PollType::wait_indefinitely());
            if r > 0 {
                dev_ms = dev_ms.min(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        println!(
            "{}",
            json!({"scenario": "cache-kernels", "kernel": "update-step", "volume": "4096^3 u8",
                   "pool_slots": slots, "page_table_levels": vm.layout().nmax(), "bricks": k,
                   "cpu_twin_ms": cpu_ms, "device_ms": dev_ms,
                   "readback_bytes": 32 + 4 * k, "upload_bytes": 48 * k, "adapter": adapter})
        );
    }
    Ok(())
}
