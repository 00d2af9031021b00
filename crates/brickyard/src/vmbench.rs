//! Benchmarks of the virtual memory: sampling through the hierarchy, the
//! per-frame update, the loader, and load latencies.

use anyhow::{bail, Result};
use brickyard_cache::brick::{BrickContent, BrickKey, LoadedBrick};
use brickyard_cache::host_cache::HostCache;
use brickyard_cache::loader::Loader;
use brickyard_cache::session::Session;
use brickyard_cache::vm::{VirtualMemory, VmConfig};
use brickyard_core::{DType, Dims3};
use brickyard_store::builder::{convert, ConvertOptions};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::import::zarr;
use brickyard_store::{Compression, NoProgress, VolumeSource};
use rayon::prelude::*;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A Mandelbulb store in `dir` (made once).
pub(crate) fn store(dir: &Path, dims: Dims3, dtype: DType) -> Result<PathBuf> {
    store_with(dir, dims, dtype, Compression::Lz4, "")
}

/// The benchmark store with the given compression; `tag` names it when the
/// compression is not the default (a store of each kind is kept).
fn store_with(
    dir: &Path,
    dims: Dims3,
    dtype: DType,
    compression: Compression,
    tag: &str,
) -> Result<PathBuf> {
    crate::bench::make_bench_dir(dir)?;
    let p = dir.join(format!(
        "mandelbulb-{}x{}x{}-{}{}.ome.zarr",
        dims[2], dims[1], dims[0], dtype, tag
    ));
    if !p.exists() {
        eprintln!("bench: writing {}", p.display());
        let src = Procedural::new(Kind::Mandelbulb, dims, dtype);
        let o = ConvertOptions {
            shard: [256; 3],
            compression,
            ..Default::default()
        };
        convert(&src, &p, &o, &NoProgress, &AtomicBool::new(false))?;
    }
    Ok(p)
}

fn drop_caches() -> bool {
    unsafe { libc::sync() };
    std::fs::write("/proc/sys/vm/drop_caches", "3").is_ok()
}

struct Rng(u64);
impl Rng {
    fn unit(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Sample positions along random rays (coherent like a ray caster's).
fn ray_points(n: usize, dims: Dims3, seed: u64) -> Vec<[f64; 3]> {
    let mut r = Rng(seed);
    let mut pts = Vec::with_capacity(n);
    let step = 1.0 / dims.iter().copied().max().unwrap() as f64;
    while pts.len() < n {
        let o = [r.unit(), r.unit(), r.unit()];
        let mut d = [r.unit() - 0.5, r.unit() - 0.5, r.unit() - 0.5];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
        d = d.map(|v| v / len * step);
        let mut p = o;
        while p.iter().all(|v| (0.0..1.0).contains(v)) && pts.len() < n {
            pts.push(p);
            p = [p[0] + d[0], p[1] + d[1], p[2] + d[2]];
        }
    }
    pts
}

/// Trilinear samples/s through the hierarchy (all resident) vs direct
/// sampling of the same level in a plain array.
pub fn sample(dir: &Path, dims: Dims3, dtype: DType, repeat: usize) -> Result<()> {
    let st = store(dir, dims, dtype)?;
    let vox: u64 = dims.iter().product();
    // The default hierarchy, then one forced to use intermediate page tables.
    for max_dir in [1u64 << 15, 8] {
        let cfg = VmConfig {
            brick: [32; 3],
            pool_bytes: (vox * dtype.size() as u64) * 2 + (64 << 20),
            pt_cache_blocks: 4096,
            request_cap: 4096,
            upload_bytes_per_frame: u64::MAX,
            max_dir_entries: max_dir,
            ..Default::default()
        };
        let mut s = Session::open(&st, cfg, 1 << 30, 2)?;
        let pts = ray_points(2_000_000, dims, 1);
        // Warm: until every sample is served at level 0.
        let t = Instant::now();
        let mut frames = 0;
        loop {
            s.begin_frame();
            let mut req = s.vm().requests();
            let mut exact = 0usize;
            for p in pts.iter().step_by(7) {
                exact += (s.vm().sample(0, 0, *p, true, &mut req).level == Some(0)) as usize;
            }
            s.finish_frame([&req]);
            frames += 1;
            if exact == pts.len().div_ceil(7) {
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        let warm_s = t.elapsed().as_secs_f64();
        // Plain array of level 0.
        let src = zarr::open(&st, 0)?;
        let mut raw = vec![0u8; (vox as usize) * dtype.size()];
        src.read_region(0, 0..dims[0], 0..dims[1], 0..dims[2], &mut raw)?;
        let plain: Vec<f32> = brickyard_core::dispatch_dtype!(dtype, T => {
            brickyard_core::cast_slice::<T>(&raw).iter().map(|v| brickyard_core::Sample::to_f64(*v) as f32).collect()
        });
        let direct = |p: [f64; 3]| -> f32 {
            let q =
                [0, 1, 2].map(|a| (p[a] * dims[a] as f64 - 0.5).clamp(0.0, (dims[a] - 1) as f64));
            let b = q.map(|x| x.floor() as usize);
            let f = [0, 1, 2].map(|a| (q[a] - b[a] as f64) as f32);
            let (dy, dx) = (dims[1] as usize, dims[2] as usize);
            let at = |z: usize, y: usize, x: usize| {
                plain[(z.min(dims[0] as usize - 1) * dy + y.min(dy - 1)) * dx + x.min(dx - 1)]
            };
            let mut acc = 0.0;
            for dz in 0..2 {
                for yy in 0..2 {
                    for xx in 0..2 {
                        let w = (if dz == 1 { f[0] } else { 1.0 - f[0] })
                            * (if yy == 1 { f[1] } else { 1.0 - f[1] })
                            * (if xx == 1 { f[2] } else { 1.0 - f[2] });
                        acc += w * at(b[0] + dz, b[1] + yy, b[2] + xx);
                    }
                }
            }
            acc
        };
        let mut best_vm = f64::INFINITY;
        let mut best_direct = f64::INFINITY;
        let mut best_vm_par = f64::INFINITY;
        let mut checksum = (0.0f64, 0.0f64);
        for _ in 0..repeat.max(1) {
            s.begin_frame();
            let t = Instant::now();
            let mut req = s.vm().requests();
            let mut sum = 0.0f64;
            for p in &pts {
                sum += s.vm().sample(0, 0, *p, true, &mut req).value as f64;
            }
            best_vm = best_vm.min(t.elapsed().as_secs_f64());
            let t = Instant::now();
            let sum_par: f64 = pts
                .par_chunks(4096)
                .map(|c| {
                    let mut req = s.vm().requests();
                    c.iter()
                        .map(|p| s.vm().sample(0, 0, *p, true, &mut req).value as f64)
                        .sum::<f64>()
                })
                .sum();
            best_vm_par = best_vm_par.min(t.elapsed().as_secs_f64());
            s.finish_frame([&req]);
            let t = Instant::now();
            let mut sum2 = 0.0f64;
            for p in &pts {
                sum2 += direct(*p) as f64;
            }
            best_direct = best_direct.min(t.elapsed().as_secs_f64());
            checksum = (sum, sum2);
            let _ = sum_par;
        }
        let n = pts.len() as f64;
        outln!(
            "{}",
            json!({"scenario": "vm-sample", "size": [dims[2], dims[1], dims[0]], "dtype": dtype.short_name(),
                "samples": pts.len(), "pt_levels": s.vm().layout().pt_levels(),
                "vm_msamples_s_1thread": n / best_vm / 1e6,
                "vm_msamples_s_all_threads": n / best_vm_par / 1e6,
                "direct_msamples_s_1thread": n / best_direct / 1e6,
                "vm_over_direct_time": best_vm / best_direct,
                "max_abs_checksum_diff_per_sample": (checksum.0 - checksum.1).abs() / n,
                "warm_frames": frames, "warm_s": warm_s})
        );
    }
    Ok(())
}

/// LRU compaction + request merge + insert time per frame for pools of
/// 1k–64k slots (bricks of 8³ u8 so that 64k slots stay small).
pub fn update(repeat: usize) -> Result<()> {
    for slots in [1024u64, 4096, 16384, 65536] {
        let side = ((slots as f64).cbrt().ceil() as u64 * 8 * 2).max(64);
        let levels = vec![[side; 3], [side / 2; 3], [side / 4; 3]];
        let cfg = VmConfig {
            brick: [8; 3],
            apron: 1,
            pt_block: [8; 3],
            pool_bytes: slots * 1000,
            pt_cache_blocks: 4096,
            request_cap: 256,
            upload_bytes_per_frame: 64 * 1000,
            ..Default::default()
        };
        let mut vm = VirtualMemory::new(&levels, 1, DType::U8, cfg);
        let per = side / 8;
        let data: Arc<[u8]> = vec![7u8; 1000].into();
        let mut next = 0u64;
        let brick = |n: u64| -> Arc<LoadedBrick> {
            let i = n % (per * per * per);
            Arc::new(LoadedBrick {
                key: BrickKey {
                    level: 0,
                    channel: 0,
                    brick: [
                        (i / (per * per)) as u32,
                        ((i / per) % per) as u32,
                        (i % per) as u32,
                    ],
                },
                content: BrickContent::Data(data.clone()),
                min: 7.0,
                max: 7.0,
                bytes_read: 0,
            })
        };
        // Fill the pool.
        while vm.resident_bricks() < vm.pool_slots() {
            vm.begin_frame();
            let b: Vec<_> = (0..64)
                .map(|_| {
                    next += 1;
                    brick(next)
                })
                .collect();
            vm.insert(&b);
            if next > slots * 4 {
                break;
            }
        }
        let mut times = vec![];
        let mut rng = Rng(5);
        for _ in 0..repeat.max(1) * 20 {
            vm.begin_frame();
            // Touch half of the bricks and miss 1024 others.
            let mut req = vm.requests();
            for i in 0..(slots / 2 + 1024) {
                let p = [rng.unit(), rng.unit(), rng.unit()];
                let _ = i;
                vm.sample(0, 0, p, false, &mut req);
            }
            let t = Instant::now();
            let rep = vm.end_frame([&req]);
            let b: Vec<_> = rep
                .requests
                .iter()
                .take(64)
                .map(|k| {
                    Arc::new(LoadedBrick {
                        key: *k,
                        content: BrickContent::Data(data.clone()),
                        min: 7.0,
                        max: 7.0,
                        bytes_read: 0,
                    })
                })
                .collect();
            vm.insert(&b);
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(|a, b| a.partial_cmp(b).unwrap());
        outln!(
            "{}",
            json!({"scenario": "vm-update", "pool_slots": vm.pool_slots(), "pt_levels": vm.layout().pt_levels(),
                "median_ms_per_frame": times[times.len() / 2], "max_ms": times[times.len() - 1],
                "requests_per_frame": 256, "inserts_per_frame": 64})
        );
    }
    Ok(())
}

/// Decoded GB/s of the loader reading every brick of level 0.
/// Options of the loader benchmark.
pub struct LoaderBench {
    /// Engine brick size (the store's chunks are 64³ in 256³ shards).
    pub brick: u64,
    pub threads: Vec<usize>,
    /// Runs per thread count (each printed).
    pub repeat: usize,
    /// Drop the store from the page cache before each run.
    pub cold: bool,
    /// Decoded-chunk cache of the loader (all levels).
    pub chunk_cache: u64,
    /// Host-cache budget (`None`: the whole level fits).
    pub host_cache: Option<u64>,
    /// The store's compression and its name's tag ("" for the default).
    pub compression: (Compression, String),
    /// Bricks hinted ahead of the loads (`None`: the loader's default).
    pub read_ahead: Option<usize>,
}

/// This process's CPU time so far (user, system, in seconds) and its minor
/// page faults (fresh pages the kernel provided).
fn usage() -> (f64, f64, u64) {
    // SAFETY: getrusage writes the struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    (s(u.ru_utime), s(u.ru_stime), u.ru_minflt as u64)
}

/// Drop every file of `dir` from the page cache with posix_fadvise
/// (DONTNEED; no root needed, clean pages only). Returns the bytes asked.
fn fadvise_dont_need(dir: &Path) -> u64 {
    let mut n = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if let Ok(f) = std::fs::File::open(&p) {
                use std::os::fd::AsRawFd;
                // SAFETY: a plain system call on an open descriptor.
                unsafe { libc::posix_fadvise(f.as_raw_fd(), 0, 0, libc::POSIX_FADV_DONTNEED) };
                n += f.metadata().map(|m| m.len()).unwrap_or(0);
            }
        }
    }
    n
}

/// Wait until `n` requested bricks came back from `l` (polled every 200
/// µs, so that the time around it measures the loads); `(bricks, data
/// bricks)`. A brick that failed never arrives: an error with the
/// failures, as one bricks still missing after 600 s.
pub fn await_bricks(l: &Loader, n: usize) -> Result<(usize, usize)> {
    let t = Instant::now();
    let (mut got, mut data, mut failed) = (0, 0, vec![]);
    while got + failed.len() < n {
        for b in l.poll() {
            got += 1;
            data += matches!(b.content, BrickContent::Data(_)) as usize;
        }
        // Each call empties the loader's list: kept here.
        failed.extend(l.take_failures());
        if let Some(f) = failed.first() {
            anyhow::bail!("{} bricks failed: {}", failed.len(), f.message);
        }
        if t.elapsed() > Duration::from_secs(600) {
            anyhow::bail!("{} of {n} bricks still missing after 600 s", n - got);
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    Ok((got, data))
}

/// Every brick of level 0, loaded by the loader's threads into a host
/// cache that holds them all; decoded GB/s counts the padded data bricks
/// (empty and constant ones come from the statistics without a read),
/// level GB/s the level's bytes (what a reader of the whole array gets).
pub fn loader(dir: &Path, dims: Dims3, dtype: DType, o: &LoaderBench) -> Result<()> {
    let st = store_with(dir, dims, dtype, o.compression.0, &o.compression.1)?;
    let level_bytes = dims.iter().product::<u64>() * dtype.size() as u64;
    for &threads in &o.threads {
        for _ in 0..o.repeat.max(1) {
            let cold = if !o.cold {
                "no"
            } else if drop_caches() {
                "drop_caches"
            } else {
                fadvise_dont_need(&st);
                "fadvise"
            };
            let cache = Arc::new(HostCache::new(
                o.host_cache.unwrap_or(4 * level_bytes + (256 << 20)),
            ));
            let l = Loader::open_with_chunk_cache(
                &st,
                [o.brick; 3],
                1,
                threads,
                cache.clone(),
                o.chunk_cache,
            )?;
            if let Some(n) = o.read_ahead {
                l.set_read_ahead(n);
            }
            let keys: Vec<(BrickKey, u32)> = l.geometry().keys(0, 0).map(|k| (k, 1)).collect();
            let decodes = zarr::chunks_decoded();
            let u0 = usage();
            let t = Instant::now();
            l.request(&keys);
            let (_, data_bricks) = await_bricks(&l, keys.len())?;
            let s = t.elapsed().as_secs_f64();
            let u1 = usage();
            let bytes = l.bytes_read();
            let padded = (o.brick + 2).pow(3);
            let decoded = (data_bricks as u64) * padded * dtype.size() as u64;
            outln!(
                "{}",
                json!({"scenario": "loader", "size": [dims[2], dims[1], dims[0]], "dtype": dtype.short_name(),
                    "store": st.file_name().map(|n| n.to_string_lossy().into_owned()),
                    "brick": o.brick, "threads": threads, "cold": cold, "bricks": keys.len(), "data_bricks": data_bricks,
                    "seconds": s, "decoded_gb_s": decoded as f64 / 1e9 / s, "read_gb_s": bytes as f64 / 1e9 / s,
                    "level_gb_s": level_bytes as f64 / 1e9 / s,
                    "chunks_decoded": zarr::chunks_decoded() - decodes,
                    "host_cache_bytes": cache.budget(), "evictions": cache.evictions(),
                    "ranges_hinted": l.stats().ranges_hinted,
                    "cpu_user_s": u1.0 - u0.0, "cpu_sys_s": u1.1 - u0.1, "minor_faults": u1.2 - u0.2})
            );
        }
    }
    Ok(())
}

/// One brick and one full view (a 1920×1080 slice through the middle at
/// level 0) from an empty device pool: from host cache and from disk.
pub fn latency(dir: &Path, dims: Dims3, dtype: DType, cold: bool) -> Result<()> {
    let st = store(dir, dims, dtype)?;
    let cfg = VmConfig {
        brick: [64; 3],
        pool_bytes: 1 << 30,
        pt_cache_blocks: 512,
        request_cap: 512,
        upload_bytes_per_frame: 256 << 20,
        ..Default::default()
    };
    let view: Vec<[f64; 3]> = (0..1080)
        .flat_map(|y| {
            (0..1920).map(move |x| [0.5, (y as f64 + 0.5) / 1080.0, (x as f64 + 0.5) / 1920.0])
        })
        .collect();
    let host = Arc::new(HostCache::new(2 << 30));
    for source in ["disk", "host cache"] {
        let dropped = source == "disk" && cold && drop_caches();
        // One brick.
        let mut s = Session::open(&st, cfg.clone(), 2 << 30, 2)?;
        if source == "host cache" {
            // Share the warm host cache of the previous run.
            s = session_with_cache(&st, cfg.clone(), host.clone())?;
        }
        let t = Instant::now();
        let p = [0.5, 0.5, 0.5];
        loop {
            s.begin_frame();
            let mut req = s.vm().requests();
            let r = s.vm().sample(0, 0, p, false, &mut req);
            s.finish_frame([&req]);
            if r.level == Some(0) {
                break;
            }
            std::thread::sleep(Duration::from_micros(100));
        }
        let one = t.elapsed().as_secs_f64() * 1e3;
        // Full view.
        let t = Instant::now();
        let mut frames = 0;
        loop {
            s.begin_frame();
            let exact: usize = view
                .par_chunks(8192)
                .map(|c| {
                    let mut req = s.vm().requests();
                    c.iter()
                        .filter(|p| s.vm().sample(0, 0, **p, true, &mut req).level == Some(0))
                        .count()
                })
                .sum();
            let mut req = s.vm().requests();
            for p in view.iter().step_by(97) {
                s.vm().sample(0, 0, *p, true, &mut req);
            }
            s.finish_frame([&req]);
            frames += 1;
            if exact == view.len() {
                break;
            }
        }
        let full = t.elapsed().as_secs_f64();
        for b in s.loader().cache().keys_by_recency() {
            if let Some(x) = s.loader().cache().get(&b) {
                host.insert(x);
            }
        }
        outln!(
            "{}",
            json!({"scenario": "latency", "size": [dims[2], dims[1], dims[0]], "dtype": dtype.short_name(), "from": source,
                "cold": dropped, "one_brick_ms": one, "full_view_s": full, "frames": frames,
                "bricks_resident": s.vm().resident_bricks()})
        );
    }
    Ok(())
}

fn session_with_cache(st: &Path, cfg: VmConfig, cache: Arc<HostCache>) -> Result<Session> {
    Ok(Session::with_cache(st, cfg, cache, 2)?)
}

/// DVR frame times through the virtual memory (warm: everything resident;
/// cold: from an empty pool to a complete view) beside the in-core
/// reference renderer on the same level, same camera and transfer function.
/// Options of the render benchmark.
pub struct RenderBench {
    /// Image width and height in pixels.
    pub image: [u32; 2],
    /// Camera this many times closer than the full view.
    pub zoom: f64,
    /// The transfer function's data window (default: the type's range).
    pub window: Option<[f32; 2]>,
    pub repeat: usize,
    /// Drop the page cache first.
    pub cold: bool,
    /// Brick-pool budget (default: half the volume plus 32 MiB).
    pub pool: Option<u64>,
    /// Also time the in-core reference renderer.
    pub reference: bool,
    /// `dvr`, `mip`, or `slice` (a plane through the volume's centre
    /// facing the camera).
    pub mode: &'static str,
    /// Back ends to measure, one after the other (`cpu`, `gpu`).
    pub backends: Vec<String>,
    /// A procedural Mandelbulb computed brick by brick as it is asked for
    /// (no store: any size, e.g. 4096³ = 64 GiB of u8).
    pub procedural: bool,
    /// This store's channel 0 instead of a generated one (its size and
    /// type; a label image is drawn as `render` draws it: label colours
    /// in slices, label surfaces in DVR).
    pub store: Option<std::path::PathBuf>,
    /// A label image's labels drawn (`None`: all).
    pub only_labels: Option<Vec<i32>>,
}

pub fn render(dir: &Path, dims: Dims3, dtype: DType, o: &RenderBench) -> Result<()> {
    let RenderBench {
        image,
        zoom,
        window,
        repeat,
        cold,
        pool,
        reference: with_reference,
        mode: mode_name,
        procedural,
        ..
    } = *o;
    use brickyard_core::camera::{world_extent, Camera, Projection};
    use brickyard_core::TransferFunction;
    use brickyard_render::cpu::{Lod, Scene};
    use brickyard_render::reference::{render as render_ref, RenderMode, RenderParams, Volume};
    let brick = [32u64; 3];
    let (st, dims, dtype, labels) = match (&o.store, procedural) {
        (Some(_), true) => bail!("bench render: --store or --procedural, not both"),
        (Some(st), false) => {
            let info = brickyard_store::info::inspect(st)?;
            let m = zarr::open(st, 0)?.meta().clone();
            (Some(st.clone()), m.dims, m.dtype, info.label_image)
        }
        (None, true) => (None, dims, dtype, false),
        (None, false) => (Some(store(dir, dims, dtype)?), dims, dtype, false),
    };
    if labels && mode_name == "mip" {
        bail!(
            "bench render: a label image is drawn in slices and DVR (--mode slice or dvr), not mip"
        );
    }
    let (extent, levels) = match &st {
        Some(st) => {
            let spacing = zarr::open(st, 0)?.meta().spacing.unwrap_or([1.0; 3]);
            let mut levels = vec![];
            for l in 0.. {
                match zarr::open(st, l) {
                    Ok(s) => levels.push(s.meta().dims),
                    Err(_) => break,
                }
            }
            (world_extent(dims, spacing), levels)
        }
        None => (
            world_extent(dims, [1.0; 3]),
            brickyard_core::plan_levels(dims, [1.0; 3], [0.0; 3], brick)
                .levels
                .iter()
                .map(|l| l.dims)
                .collect(),
        ),
    };
    let mut scene = Scene::new(extent, levels);
    let max = match dtype {
        DType::U8 => 255.0,
        DType::U16 => 65535.0,
        _ => 1.0,
    };
    let tf = TransferFunction::preset("soft", window.unwrap_or([0.0, max]))?;
    let full = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    // Zoomed in: the eye moves towards the target.
    let eye = [0, 1, 2].map(|a| full.target[a] + (full.eye[a] - full.target[a]) / zoom.max(1e-3));
    let cam = Camera { eye, ..full };
    let mode = match mode_name {
        "mip" => RenderMode::Mip,
        "slice" => {
            let origin = extent.map(|e| e / 2.0);
            let d = [0, 1, 2].map(|a| cam.eye[a] - cam.target[a]);
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            RenderMode::Slice {
                origin,
                normal: d.map(|x| x / n),
            }
        }
        _ => RenderMode::Dvr,
    };
    let mut p = RenderParams::new(image[0], image[1], cam, tf, mode);
    p.reference_step = Some(scene.voxel(0));
    if labels {
        // As `render` draws a label image (the window unused).
        p.tf = TransferFunction::preset("linear", [0.0, 1.0])?;
        p.labels = true;
    }
    if let Some(ids) = &o.only_labels {
        if !labels {
            bail!("bench render: --only-labels takes a label image (--store STORE/labels/NAME)");
        }
        let sel = brickyard_render::params::LabelSelect::new(ids.clone(), false);
        // (Where the labels lie, from the statistics, as `render` takes
        // them.)
        let sel = match &st {
            Some(dir) => brickyard_run::label_stats::with_boxes(sel, dir, dims)?,
            None => sel,
        };
        p.label_select = Some(sel);
        p.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let vox: u64 = dims.iter().product();
    let default_pool = vox * dtype.size() as u64 / 2 + (32 << 20);
    let cfg = VmConfig {
        brick,
        pool_bytes: pool.unwrap_or(if procedural {
            default_pool.min(2 << 30)
        } else {
            default_pool
        }),
        pt_cache_blocks: 4096,
        request_cap: 1024,
        upload_bytes_per_frame: 256 << 20,
        ..Default::default()
    };
    let vox_bytes = vox * dtype.size() as u64;
    let mut reference = f64::NAN;
    let vol = match (&st, with_reference) {
        (Some(st), true) => Some(Volume::from_store(st, 0, 0)?),
        _ => None,
    };
    for vol in std::iter::repeat_n(vol.as_ref(), repeat.max(1)).flatten() {
        let t = Instant::now();
        let _ = render_ref(vol, &p);
        reference = reference.min(t.elapsed().as_secs_f64());
    }
    for name in &o.backends {
        let host = std::sync::Arc::new(brickyard_cache::host_cache::HostCache::new(1 << 30));
        // Cold: empty pool and host cache (and, with --cold, an empty page
        // cache) to a complete view; then again with a new pool but the
        // host cache kept: bricks come from RAM.
        let dropped = cold && drop_caches();
        let mut runs = vec![];
        // What the cold run read from the store (the later runs find the
        // bricks in the warm host cache and read nothing).
        let mut cold_bytes_read = 0;
        let mut warm_session = None;
        for _ in 0..2 {
            let mut s = match &st {
                Some(st) => {
                    let s = Session::with_cache(st, cfg.clone(), host.clone(), 2)?;
                    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
                    s
                }
                None => {
                    // Computing bricks takes cores, not disks: one loader
                    // thread per core.
                    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
                    let l = brickyard_cache::loader::Loader::procedural(
                        brickyard_store::generate::Kind::Mandelbulb,
                        dims,
                        dtype,
                        brick,
                        cfg.apron,
                        threads,
                        host.clone(),
                    )?;
                    scene.ranges = None;
                    Session::from_loader(l, cfg.clone())
                }
            };
            // A pool that cannot keep the coarsest level resident never
            // completes a view: refused before the frame loops, as
            // `render --pool` is (the loops spun until their time ran out).
            s.loader()
                .geometry()
                .pinned_levels(s.vm().pool_slots(), s.vm().slot_bytes() as u64, 512)
                .map_err(|e| anyhow::anyhow!("--pool {}: {e}", cfg.pool_bytes))?;
            let (choice, update) = match name.strip_suffix("-host") {
                Some(c) => (c, crate::backend::GpuUpdate::Host),
                None => (name.as_str(), crate::backend::GpuUpdate::Device),
            };
            let mut backend = crate::backend::Backend::choose(choice, update, &mut s, 1)?;
            backend.set_read_image(false);
            let t = Instant::now();
            let (mut frames, mut first_frame_ms) = (0, 0.0);
            let (mut up, mut down, mut upload_ms) = (0u64, 0u64, 0.0);
            let mut completeness: f64;
            // As the viewer streams a view: on the CPU each frame after the
            // first draws again only the tiles that were not settled.
            let mut last = None;
            let lod = Lod::Auto { bias: 0.0 };
            let mut next_note = Duration::from_secs(5);
            loop {
                let mut f = match last.take() {
                    Some((img, tiles)) => {
                        backend.frame_again(&mut s, &scene, &p, lod, img, tiles)?
                    }
                    None => backend.frame(&mut s, &scene, &p, lod)?,
                };
                if let Some(tiles) = f.tiles.take() {
                    last = Some((
                        std::mem::replace(&mut f.image, brickyard_render::Image::new(0, 0)),
                        tiles,
                    ));
                }
                (up, down, upload_ms) = (up + f.up, down + f.down, upload_ms + f.upload_ms);
                if frames == 0 {
                    first_frame_ms = t.elapsed().as_secs_f64() * 1e3;
                }
                frames += 1;
                completeness = f.stats.completeness();
                // Where a long run is (a run stopped by a time limit
                // otherwise says nothing).
                if t.elapsed() >= next_note {
                    next_note += Duration::from_secs(5);
                    eprintln!(
                        "bench render: {name}, run {}: frame {frames}, {:.2} % complete, {:.1} s, {} requests, {} bricks in",
                        runs.len() + 1,
                        completeness * 100.0,
                        t.elapsed().as_secs_f64(),
                        f.session.frame.requested,
                        f.session.insert.inserted
                    );
                }
                // A procedural volume's bricks are computed, which takes
                // long on few cores: give up after 90 s (reported).
                let out_of_time = if procedural {
                    t.elapsed().as_secs() >= 90
                } else {
                    frames > 500
                };
                if completeness >= 1.0 || out_of_time {
                    break;
                }
            }
            if runs.is_empty() {
                cold_bytes_read = s.loader().bytes_read();
            }
            // A run stopped by its limit is no time to complete: null,
            // and said (its completeness is in the report beside it).
            if completeness < 1.0 {
                eprintln!(
                    "bench render: {name}, run {}: stopped at {:.2} % complete after {frames} frame(s), {:.1} s (its limit): no time to complete is reported",
                    runs.len() + 1,
                    completeness * 100.0,
                    t.elapsed().as_secs_f64()
                );
            }
            runs.push((
                (completeness >= 1.0).then(|| t.elapsed().as_secs_f64()),
                frames,
                first_frame_ms,
                up,
                down,
                upload_ms,
                completeness,
            ));
            warm_session = Some((s, backend));
        }
        // From the warm host cache again, the way `render` draws a view:
        // requests and uploads sized to the pool and host cache, the
        // coarsest levels pinned (loaded first, timed), then batch mode
        // (a request pass at a fraction of the pixels, frames waiting for
        // their bricks), to a complete view.
        let batch_s = match &st {
            Some(st) => {
                let t = Instant::now();
                let batch_cfg = VmConfig {
                    request_cap: crate::frames::requests_per_frame(
                        cfg.pool_bytes,
                        host.budget(),
                        cfg.slot_bytes(dtype),
                        crate::frames::BATCH_REQUESTS,
                    ),
                    upload_bytes_per_frame: cfg.pool_bytes,
                    ..cfg.clone()
                };
                let mut s = Session::with_cache(st, batch_cfg, host.clone(), 2)?;
                s.set_batch(Some(Duration::from_secs(30)));
                s.pin_coarsest(512, Duration::from_secs(120))
                    .map_err(|e| anyhow::anyhow!("pool: {e}"))?;
                let (choice, update) = match name.strip_suffix("-host") {
                    Some(c) => (c, crate::backend::GpuUpdate::Host),
                    None => (name.as_str(), crate::backend::GpuUpdate::Device),
                };
                let mut backend = crate::backend::Backend::choose(choice, update, &mut s, 1)?;
                backend.set_read_image(false);
                let mut budget =
                    brickyard_render::budget::LodBudget::new(0.0, scene.levels.len(), false);
                let opt = crate::frames::DriveOptions {
                    batch: true,
                    max_frames: 500,
                    lod: Lod::Auto { bias: 0.0 },
                    band: None,
                };
                let mut next_note = Duration::from_secs(5);
                let out = crate::frames::drive(
                    &mut backend,
                    &mut s,
                    &scene,
                    &p,
                    opt,
                    &mut budget,
                    |fi| {
                        if t.elapsed() >= next_note {
                            next_note += Duration::from_secs(5);
                            eprintln!(
                                "bench render: {name}, batch: frame {}, {:.2} % complete, {:.1} s, bias {:+.1}",
                                fi.frame,
                                fi.f.stats.completeness() * 100.0,
                                t.elapsed().as_secs_f64(),
                                fi.bias
                            );
                        }
                    },
                )?;
                (out.completeness >= 1.0).then(|| t.elapsed().as_secs_f64())
            }
            None => None,
        };
        let (mut s, mut backend) = warm_session.expect("two runs");
        // (A mark for profilers that should see only the warm frames.)
        tracing::debug!("render bench: warm frames start");
        let mut warm = f64::INFINITY;
        let (mut cache_ms, mut warm_down) = (f64::INFINITY, 0);
        let mut last = None;
        for _ in 0..repeat.max(1) {
            let f = backend.frame(&mut s, &scene, &p, Lod::Auto { bias: 0.0 })?;
            warm = warm.min(f.render_ms / 1e3);
            cache_ms = f64::min(cache_ms, f.cache_ms);
            warm_down = f.down;
            last = Some(f.stats);
        }
        let stt = last.expect("one warm frame");
        let (cold_s, frames, first_frame_ms, up, down, upload_ms, cold_done) = runs[0];
        let (host_s, host_frames, .., host_done) = runs[1];
        let bytes_read = cold_bytes_read;
        let pool_bytes = s.vm().pool_bytes();
        outln!(
            "{}",
            json!({"scenario": "render", "procedural": procedural, "store": o.store, "labels": labels, "backend": backend.describe(), "mode": mode_name, "size": [dims[2], dims[1], dims[0]], "dtype": dtype.short_name(),
                "image": image, "zoom": zoom, "window": p.tf.window, "pool_bytes": pool_bytes, "volume_bytes": vox_bytes,
                "cold": dropped, "first_frame_ms": first_frame_ms, "cold_to_complete_s": cold_s, "cold_frames": frames,
                "cold_completeness": cold_done, "host_cache_completeness": host_done,
                "host_cache_to_complete_s": host_s, "host_cache_frames": host_frames, "host_cache_batch_to_complete_s": batch_s, "bytes_read": bytes_read,
                "cold_host_to_device_bytes": up, "cold_device_to_host_bytes": down,
                "cold_upload_ms": upload_ms, "upload_gb_s": if upload_ms > 0.0 { up as f64 / upload_ms / 1e6 } else { f64::NAN },
                "warm_frame_ms": warm * 1e3, "warm_cache_ms": cache_ms, "warm_device_to_host_bytes": warm_down,
                "warm_samples": stt.samples, "warm_steps": stt.steps, "warm_skipped_bricks": stt.skipped_bricks, "warm_transparent_samples": stt.transparent, "warm_skipped_cells": stt.skipped_cells, "warm_msamples_s": stt.samples as f64 / warm / 1e6,
                "reference_frame_ms": reference * 1e3, "threads": rayon::current_num_threads()})
        );
    }
    Ok(())
}
