//! `brickyard bench cache-kernels`: the device's cache-management kernels
//! beside their CPU twins, in one run: LRU compaction of pools of 16k–1M
//! slots, request collection + the capped list for a frame's misses, and
//! the whole update step (every LRU order, slot reservation, referencing)
//! for batches of bricks, and bricks written into the pool one call each
//! against all in one staging buffer.
//! Device times are wall times from submission to completion (read-back of
//! the request list included), on whatever adapter `Gpu::new` picks.
//!
//! `brickyard bench process-filters`: the processing filters on the CPU and
//! on the device, side by side ([`process_filters`]).

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
        outln!(
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
    outln!(
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
        outln!(
            "{}",
            json!({"scenario": "cache-kernels", "kernel": "update-step", "volume": "4096^3 u8",
                   "pool_slots": slots, "page_table_levels": vm.layout().nmax(), "bricks": k,
                   "cpu_twin_ms": cpu_ms, "device_ms": dev_ms,
                   "readback_bytes": 32 + 4 * k, "upload_bytes": 48 * k, "adapter": adapter})
        );
    }
    brick_uploads(gpu, repeat, adapter)
}

/// Padded 34³ u8 bricks (with their cell ranges) written into a device
/// pool one call per brick (`DevicePool::write`, `write_cells`: a staging
/// buffer each) and all in one staging buffer (`write_many`), to the
/// device's completion.
fn brick_uploads(gpu: &Gpu, repeat: usize, adapter: &str) -> Result<()> {
    use brickyard_gpu::pool::DevicePool;
    let padded = [34u32; 3];
    let voxels = padded.iter().product::<u32>() as usize;
    let cells = [4u32; 3];
    let slots = 4096u32;
    let mut pool = DevicePool::new(gpu, brickyard_core::DType::U8, padded, slots)?;
    pool.enable_cells(gpu, cells);
    let mut rng = Lcg(11);
    for &k in &[64usize, 1024, 4096] {
        let bricks: Vec<(u32, Vec<u8>, Vec<[f32; 2]>)> = (0..k)
            .map(|i| {
                let v: Vec<u8> = (0..voxels).map(|_| rng.below(256) as u8).collect();
                (i as u32 % slots, v, vec![[0.0, 255.0]; 64])
            })
            .collect();
        let one_by_one = best(repeat, || {
            for (s, v, c) in &bricks {
                pool.write(gpu, *s, v);
                pool.write_cells(gpu, *s, c);
            }
            gpu.queue.submit([]);
            let _ = gpu.device.poll(wgpu::PollType::wait_indefinitely());
        });
        let items: Vec<brickyard_gpu::pool::BrickWrite> = bricks
            .iter()
            .map(|(s, v, c)| (*s, &v[..], &c[..]))
            .collect();
        let together = best(repeat, || {
            pool.write_many(gpu, &items);
            let _ = gpu.device.poll(wgpu::PollType::wait_indefinitely());
        });
        let bytes = k as u64 * (voxels as u64 + 64 * 8);
        pool.take_uploaded();
        outln!(
            "{}",
            json!({"scenario": "cache-kernels", "kernel": "brick-upload", "bricks": k,
                   "bytes": bytes, "one_by_one_ms": one_by_one, "together_ms": together,
                   "one_by_one_gb_s": bytes as f64 / one_by_one / 1e6,
                   "together_gb_s": bytes as f64 / together / 1e6, "adapter": adapter})
        );
    }
    Ok(())
}

/// A volume held in memory (the benchmark's input, generated once).
struct InMemory {
    meta: brickyard_store::SourceMeta,
    data: Vec<u8>,
}

impl brickyard_store::VolumeSource for InMemory {
    fn meta(&self) -> &brickyard_store::SourceMeta {
        &self.meta
    }
    fn read_region(
        &self,
        _c: usize,
        z: std::ops::Range<u64>,
        y: std::ops::Range<u64>,
        x: std::ops::Range<u64>,
        out: &mut [u8],
    ) -> brickyard_store::Result<()> {
        let s = self.meta.dtype.size();
        let d = self.meta.dims;
        let nx = (x.end - x.start) as usize * s;
        let mut o = 0;
        for zz in z {
            for yy in y.clone() {
                let i = ((zz * d[1] + yy) * d[2] + x.start) as usize * s;
                out[o..o + nx].copy_from_slice(&self.data[i..i + nx]);
                o += nx;
            }
        }
        Ok(())
    }
}

/// `brickyard bench process-filters`: `gauss(2)` and `sobel` of a generated
/// volume (Marschner–Lobb, held in memory) computed through the filter
/// stage as `process` reads it — slabs of 64 z-planes, the CPU in blocks of
/// 64³ on all threads, the device in pieces of up to 2²³ padded voxels —
/// on the CPU, the device or both. Wall time from the first read to the
/// last value on the host (device: host-side padding, upload, kernels and
/// read-back included), best of `repeat`; with both, the largest
/// difference beside the stated tolerance.
pub fn process_filters(
    dims: [u64; 3],
    dtype: brickyard_core::DType,
    backend: &str,
    repeat: usize,
) -> Result<()> {
    use brickyard_process::{build_on, Filter, FilterKernels, Pipeline};
    use brickyard_store::generate::{Kind, Procedural};
    use brickyard_store::VolumeSource;
    use std::sync::Arc;
    let backends: Vec<&str> = match backend {
        "cpu" | "gpu" => vec![backend],
        "both" | "all" => vec!["cpu", "gpu"],
        b => anyhow::bail!("--backend: expected cpu, gpu or both for process-filters, found {b:?}"),
    };
    let t = Instant::now();
    let p = Procedural::new(Kind::MarschnerLobb, dims, dtype);
    let mut data = vec![0u8; dims.iter().product::<u64>() as usize * dtype.size()];
    p.read_region(0, 0..dims[0], 0..dims[1], 0..dims[2], &mut data)?;
    let gen_s = t.elapsed().as_secs_f64();
    let max_abs = brickyard_core::dispatch_dtype!(dtype, T => {
        use brickyard_core::Sample;
        brickyard_core::cast_slice::<T>(&data)
            .iter()
            .fold(0.0f64, |m, v| m.max(v.to_f64().abs()))
    });
    let input: Arc<dyn VolumeSource> = Arc::new(InMemory {
        meta: brickyard_store::SourceMeta::new("generated", dims, 1, dtype),
        data,
    });
    let kernels = if backends.contains(&"gpu") {
        let g = crate::backend::quietly(|| Gpu::new(AdapterChoice::Best))
            .context("process-filters --backend gpu needs a GPU adapter")?;
        Some(FilterKernels::new(Arc::new(g)))
    } else {
        None
    };
    let adapter = kernels.as_ref().map(|k| k.gpu.describe());
    for text in ["gauss(2)", "sobel"] {
        let pipe = Pipeline::parse(text).map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut outs: Vec<Vec<f32>> = vec![];
        for &b in &backends {
            let k = if b == "gpu" { kernels.as_ref() } else { None };
            let built =
                build_on(&pipe, input.clone(), 0, [64; 3], k).map_err(|e| anyhow::anyhow!(e))?;
            let src = built.source;
            let mut out = vec![0f32; dims.iter().product::<u64>() as usize];
            let plane = (dims[1] * dims[2]) as usize;
            let mut runs = vec![];
            for _ in 0..repeat.max(1) {
                let t = Instant::now();
                let mut z = 0;
                while z < dims[0] {
                    let h = 64.min(dims[0] - z);
                    let o = &mut out[z as usize * plane..(z + h) as usize * plane];
                    src.read_region(
                        0,
                        z..z + h,
                        0..dims[1],
                        0..dims[2],
                        brickyard_core::as_bytes_mut(o),
                    )?;
                    z += h;
                }
                runs.push(t.elapsed().as_secs_f64());
            }
            let best_s = runs.iter().cloned().fold(f64::INFINITY, f64::min);
            outln!(
                "{}",
                json!({"scenario": "process-filters", "filter": text, "size": dims,
                       "dtype": dtype.short_name(), "backend": b, "best_s": best_s, "runs_s": runs,
                       "mvoxels_per_s": out.len() as f64 / best_s / 1e6,
                       "cpu_threads": rayon::current_num_threads(),
                       "adapter": if b == "gpu" { adapter.clone() } else { None },
                       "generate_s": gen_s})
            );
            outs.push(out);
        }
        if let [a, b] = &outs[..] {
            let worst = a
                .iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs() as f64)
                .fold(0.0, f64::max);
            let f = match text {
                "sobel" => Filter::Sobel,
                _ => Filter::Gauss([2.0; 3]),
            };
            outln!(
                "{}",
                json!({"scenario": "process-filters", "filter": text, "size": dims,
                       "max_abs_diff_device_vs_cpu": worst,
                       "tolerance": f.device_tolerance(max_abs)})
            );
        }
    }
    Ok(())
}
