//! `brickyard bench SCENARIO`: measured scenarios, each printing one JSON
//! line of figures. Later capabilities add scenarios here.

use anyhow::{bail, Context, Result};
use brickyard_core::{DType, Sample};
use brickyard_store::downsample::downsample;
use brickyard_store::generate::{parse_size, Kind, Procedural};
use brickyard_store::import::raw::RawOptions;
use brickyard_store::Compression;
use clap::Args;
use serde_json::json;
use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

#[derive(Args)]
pub struct BenchCmd {
    /// convert: raw → OME-Zarr pyramid, in a child process (wall time,
    /// input MB/s, peak RSS); downsample: the 2×2×2 mean kernel in memory;
    /// vm-sample: trilinear samples/s through the page tables vs a plain
    /// array; vm-update: LRU + request update per frame for pools of
    /// 1k–64k slots; cache-kernels: the device's LRU and request kernels
    /// beside their CPU twins; process-filters: gauss(2) and sobel of a
    /// generated volume on the CPU and the device (--backend cpu, gpu or
    /// both); loader: decoded GB/s of every level-0 brick (--brick: engine
    /// brick size, --compression: the store's, whose chunks stay 64³); remote: brick reads from disk and over
    /// HTTP on loopback (a `serve` child); latency: one brick and one full
    /// view from an empty cache (paper Table 2); render: DVR (or --mode mip or slice) frame times
    /// through the virtual memory beside the in-core reference; views: an
    /// N-view super-slice against one view and the views one by one, stereo
    /// against mono DVR; octree: DVR through the residency octree beside
    /// the page tables for 1, 4, 16, 64 channels (--channels) of a
    /// generated banded volume or of --store, on the CPU, the GPU or both
    /// (--backend; a table, not JSON).
    scenario: String,
    /// Volume size (N or XxYxZ; default 256, octree 128).
    #[arg(long)]
    size: Option<String>,
    /// Voxel type of the generated volume: u8, u16, f32, ...
    #[arg(long, default_value = "u8")]
    dtype: String,
    /// Where inputs are generated (kept between runs) and outputs written.
    #[arg(long, default_value = "bench-data")]
    dir: PathBuf,
    /// Memory budget handed to the converter.
    #[arg(long, default_value = "1GiB")]
    memory: String,
    /// Brick (inner chunk) edge of the converted store, in voxels.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(2..=1024))]
    brick: u64,
    /// Shard edge of the converted store, in voxels.
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u64).range(2..=16384))]
    shard: u64,
    /// Compression of the converted store: lz4 (blosc), zstd, zstd:LEVEL or none.
    #[arg(long, default_value = "lz4")]
    compression: String,
    /// Repetitions (the best is reported, all are listed).
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// render, views, octree: image size, N (square) or WxH (default 512,
    /// octree 256).
    #[arg(long)]
    image: Option<String>,
    /// render: move the camera this many times closer than the full view
    /// (zoomed in: most rays cross dense data, more bricks per pixel).
    #[arg(long, default_value_t = 1.0)]
    zoom: f64,
    /// render: the transfer function's data window LO,HI (default: the
    /// type's range, 0 to 1 for floats).
    #[arg(long, allow_hyphen_values = true)]
    window: Option<String>,
    /// loader, latency, render: drop the page cache first, for cold-disk
    /// figures (needs root; loader: without root, the store's files are
    /// dropped with posix_fadvise instead).
    #[arg(long)]
    cold: bool,
    /// render: brick-pool budget (default: half the volume plus 32 MiB).
    #[arg(long)]
    pool: Option<String>,
    /// render: leave out the in-core reference renderer (for profiling).
    #[arg(long)]
    no_reference: bool,
    /// render: dvr, mip or slice (a plane through the centre, facing the
    /// camera).
    #[arg(long, default_value = "dvr")]
    mode: String,
    /// render: a procedural Mandelbulb computed brick by brick as the view
    /// asks for it, instead of a store (any size: 4096 is 64 GiB of u8).
    #[arg(long)]
    procedural: bool,
    /// loader: loader thread counts to measure, comma-separated.
    #[arg(long, default_value = "1,2,4")]
    loader_threads: String,
    /// loader: decoded-chunk cache of the loader, all levels together.
    #[arg(long, default_value = "128MiB")]
    chunk_cache: String,
    /// loader: host-cache budget (default: the whole level fits). A budget
    /// smaller than the level makes the scan evict as a flight through a
    /// volume does: the steady state of a long session.
    #[arg(long)]
    host_cache: Option<String>,
    /// loader: queued bricks whose store bytes are hinted to the system
    /// ahead of their loads (default 32; 0: no hints, each read waits for
    /// the disk).
    #[arg(long)]
    read_ahead: Option<usize>,
    /// render: cpu, gpu, auto, both (CPU then GPU, side by side) or all
    /// (CPU, GPU with updates on the device, GPU with updates on the
    /// host); `gpu-host` and `auto-host` have the host decide updates.
    #[arg(long, default_value = "cpu")]
    backend: String,
    /// views: how many views (2 to 16).
    #[arg(long, default_value_t = 8)]
    views: u32,
    /// octree: channel counts to measure, comma-separated (1 to 64 each).
    #[arg(long, default_value = "1,4,16,64")]
    channels: String,
    /// octree: measure this store's first channels instead of generated
    /// volumes; render: this store's channel 0 (a label image drawn as
    /// `render` draws it: label colours in slices, surfaces in DVR).
    #[arg(long)]
    store: Option<PathBuf>,
    /// octree: the octree's depth (1 to 7).
    #[arg(long, default_value_t = 4)]
    octree_depth: u32,
    /// render, with --store of a label image: draw only these labels (as
    /// `render --only-labels` does).
    #[arg(long, value_name = "IDS")]
    only_labels: Option<String>,
}

pub fn run(b: BenchCmd) -> Result<()> {
    let octree = b.scenario == "octree";
    let size = b
        .size
        .clone()
        .unwrap_or_else(|| if octree { "128" } else { "256" }.into());
    let dims = parse_size(&size).map_err(|e| anyhow::anyhow!("size: {e}"))?;
    let image = crate::render::parse_image_size(
        b.image
            .as_deref()
            .unwrap_or(if octree { "256" } else { "512" }),
        "--image",
    )?;
    let dtype = DType::parse(&b.dtype).with_context(|| format!("dtype: unknown {:?}", b.dtype))?;
    if b.repeat == 0 {
        bail!("repeat: expected at least 1 repetition, found 0");
    }
    if !(b.zoom.is_finite() && b.zoom > 0.0) {
        bail!("zoom: expected a factor above 0, found {}", b.zoom);
    }
    if b.scenario == "views" && !(2..=16).contains(&b.views) {
        bail!("views: expected 2 to 16 views, found {}", b.views);
    }
    match b.scenario.as_str() {
        "convert" => bench_convert(&b, dims, dtype),
        "downsample" => bench_downsample(&b, dims, dtype),
        "vm-sample" => crate::vmbench::sample(&b.dir, dims, dtype, b.repeat),
        "vm-update" => crate::vmbench::update(b.repeat),
        "cache-kernels" => crate::gpubench::cache_kernels(b.repeat),
        "process-filters" => crate::gpubench::process_filters(dims, dtype, &b.backend, b.repeat),
        "loader" => {
            let threads = b
                .loader_threads
                .split(',')
                .map(|t| t.trim().parse::<usize>())
                .collect::<std::result::Result<Vec<_>, _>>()
                .with_context(|| {
                    format!("--loader-threads: expected numbers, found {:?}", b.loader_threads)
                })?;
            for &t in &threads {
                crate::render::check_loader_threads(t)?;
            }
            let o = crate::vmbench::LoaderBench {
                brick: b.brick,
                threads,
                repeat: b.repeat,
                cold: b.cold,
                chunk_cache: crate::parse_bytes(&b.chunk_cache)?,
                host_cache: b.host_cache.as_deref().map(crate::parse_bytes).transpose()?,
                compression: loader_compression(&b.compression)?,
                read_ahead: b.read_ahead,
            };
            crate::vmbench::loader(&b.dir, dims, dtype, &o)
        }
        "remote" => crate::netbench::remote(&b.dir, dims, dtype),
        "latency" => crate::vmbench::latency(&b.dir, dims, dtype, b.cold),
        "views" => crate::viewbench::views(
            &b.dir,
            dims,
            dtype,
            image,
            b.views,
            b.repeat,
            &match b.backend.as_str() {
                "both" => vec!["cpu".into(), "gpu".into()],
                x => vec![x.to_string()],
            },
        ),
        "render" => {
            let pool = b.pool.as_deref().map(crate::parse_bytes).transpose()?;
            let o = crate::vmbench::RenderBench {
                image,
                zoom: b.zoom,
                window: b
                    .window
                    .as_deref()
                    .map(|w| crate::render::parse_window(w, "--window"))
                    .transpose()?
                    .map(|w| w.map(|x| x as f32)),
                repeat: b.repeat,
                cold: b.cold,
                pool,
                reference: !b.no_reference,
                backends: match b.backend.as_str() {
                    "both" => vec!["cpu".into(), "gpu".into()],
                    "all" => vec!["cpu".into(), "gpu".into(), "gpu-host".into()],
                    x => vec![x.into()],
                },
                procedural: b.procedural,
                store: b.store.clone(),
                only_labels: match &b.only_labels {
                    Some(t) => Some(
                        brickyard_render::params::LabelSelect::parse_ids(t)
                            .map_err(|e| anyhow::anyhow!("only-labels: {e}"))?,
                    ),
                    None => None,
                },
                mode: match b.mode.as_str() {
                    "dvr" => "dvr",
                    "mip" => "mip",
                    "slice" => "slice",
                    m => bail!("--mode: expected dvr, mip or slice, found {m:?}"),
                },
            };
            crate::vmbench::render(&b.dir, dims, dtype, &o)
        }
        "octree" => {
            if !(brickyard_render::octree::MIN_DEPTH..=brickyard_render::octree::MAX_DEPTH)
                .contains(&b.octree_depth)
            {
                bail!("octree-depth: expected 1 to 7, got {}", b.octree_depth);
            }
            let channels = b
                .channels
                .split(',')
                .map(|t| t.trim().parse::<usize>())
                .collect::<std::result::Result<Vec<_>, _>>()
                .with_context(|| {
                    format!("--channels: expected numbers, found {:?}", b.channels)
                })?;
            if let Some(n) = channels
                .iter()
                .find(|&&n| n == 0 || n > brickyard_render::params::MAX_DVR_CHANNELS)
            {
                bail!("--channels: 1 to 64 channels, got {n}");
            }
            let o = crate::octbench::OctreeBench {
                dims,
                store: b.store.clone(),
                channels,
                image,
                depth: b.octree_depth,
                repeat: b.repeat,
                chunk: b.brick,
                shard: b.shard,
                backends: match b.backend.as_str() {
                    "cpu" => vec!["cpu"],
                    "gpu" => vec!["gpu"],
                    "both" => vec!["cpu", "gpu"],
                    x => bail!("--backend: octree measures cpu, gpu or both, found {x:?}"),
                },
            };
            crate::octbench::run(&b.dir, &o)
        }
        s => bail!(
            "scenario: expected convert, downsample, vm-sample, vm-update, cache-kernels, process-filters, loader, latency, render, views or octree, found {s:?}"
        ),
    }
}

/// Make `--dir` (its own folder only: a folder above it that does not
/// exist is a mistyped path, refused as other writers refuse it).
pub(crate) fn make_bench_dir(dir: &std::path::Path) -> Result<()> {
    if dir.is_dir() {
        return Ok(());
    }
    let parent = match dir.parent() {
        Some(p) if p.as_os_str().is_empty() => std::path::Path::new("."),
        Some(p) => p,
        None => std::path::Path::new("."),
    };
    if !parent.is_dir() {
        anyhow::bail!(
            "dir: {}: the folder it goes in, {}, does not exist",
            dir.display(),
            parent.display()
        );
    }
    std::fs::create_dir(dir).with_context(|| format!("{}: cannot create", dir.display()))
}

fn bench_convert(b: &BenchCmd, dims: [u64; 3], dtype: DType) -> Result<()> {
    make_bench_dir(&b.dir)?;
    let raw = b.dir.join(format!(
        "mandelbulb-{}x{}x{}-{}.raw",
        dims[2], dims[1], dims[0], dtype
    ));
    let sidecar = RawOptions::sidecar_path(&raw);
    if !raw.exists() || !sidecar.exists() {
        eprintln!("bench: generating {}", raw.display());
        let src = Procedural::new(Kind::Mandelbulb, dims, dtype);
        brickyard_store::generate::write_raw(&src, &raw, &brickyard_store::NoProgress)?;
    }
    let out = b.dir.join("bench-out.ome.zarr");
    let exe = std::env::current_exe()?;
    let mut runs = vec![];
    for _ in 0..b.repeat.max(1) {
        let t = Instant::now();
        let o = Command::new(&exe)
            .arg("convert")
            .arg(&raw)
            .arg(&out)
            .args([
                "--overwrite",
                "--json",
                "--quiet",
                "--memory",
                &b.memory,
                "--compression",
                &b.compression,
            ])
            .args([
                "--brick",
                &b.brick.to_string(),
                "--shard",
                &b.shard.to_string(),
            ])
            .output()?;
        let wall = t.elapsed().as_secs_f64();
        if !o.status.success() {
            bail!("convert failed: {}", String::from_utf8_lossy(&o.stderr));
        }
        let r: serde_json::Value =
            serde_json::from_slice(&o.stdout).context("convert --json output")?;
        runs.push((wall, r));
    }
    let (wall, r) = runs
        .iter()
        .min_by(|a, b| a.0.partial_cmp(&b.0).unwrap())
        .cloned()
        .unwrap();
    let bytes_in = r["bytes_in"].as_u64().unwrap_or(0);
    outln!(
        "{}",
        json!({
            "scenario": "convert",
            "size": [dims[2], dims[1], dims[0]],
            "dtype": dtype.short_name(),
            "brick": b.brick, "shard": b.shard, "compression": b.compression,
            "memory_budget": b.memory,
            "threads": rayon::current_num_threads(),
            "wall_s": wall,
            "convert_s": r["seconds"],
            "input_mb_s": bytes_in as f64 / 1e6 / wall,
            "peak_rss_mb": r["peak_rss_bytes"].as_u64().unwrap_or(0) as f64 / 1e6,
            "bytes_in": bytes_in,
            "bytes_out": r["bytes_written"],
            "levels": r["levels"].as_array().map(|a| a.len()),
            "passes": r["passes"].as_array().map(|a| a.len()),
            "all_wall_s": runs.iter().map(|r| r.0).collect::<Vec<_>>(),
        })
    );
    Ok(())
}

fn bench_downsample(b: &BenchCmd, dims: [u64; 3], dtype: DType) -> Result<()> {
    let n = (dims[0] * dims[1] * dims[2]) as usize;
    brickyard_core::dispatch_dtype!(dtype, T => {
        let src: Vec<T> = vec![T::default(); n];
        let o = [dims[0].div_ceil(2), dims[1].div_ceil(2), dims[2].div_ceil(2)];
        let mut dst: Vec<T> = vec![T::default(); (o[0] * o[1] * o[2]) as usize];
        let mut best = f64::INFINITY;
        for _ in 0..b.repeat.max(1) {
            let t = Instant::now();
            downsample(&src, [dims[0] as usize, dims[1] as usize, dims[2] as usize], [2, 2, 2], false, &mut dst);
            best = best.min(t.elapsed().as_secs_f64());
        }
        let bytes = (n * std::mem::size_of::<T>()) as f64;
        outln!("{}", json!({"scenario": "downsample", "size": [dims[2], dims[1], dims[0]], "dtype": dtype.short_name(),
            "seconds": best, "input_gb_s": bytes / 1e9 / best, "threads": rayon::current_num_threads()}));
        let _ = <T as Sample>::DTYPE;
    });
    Ok(())
}

/// The loader bench's store compression, and the tag its store's name gets
/// (none for lz4, the default, so that existing stores are reused).
fn loader_compression(s: &str) -> Result<(Compression, String)> {
    let c = crate::parse_compression(s)?;
    let tag = match c {
        Compression::Lz4 => String::new(),
        _ => format!("-{}", s.replace(':', "")),
    };
    Ok((c, tag))
}
