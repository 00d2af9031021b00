//! `brickyard bench octree`: DVR through the residency octree beside the
//! page tables on the CPU and the device (`--backend cpu|gpu|both`), for
//! 1, 4, 16 and 64 channels of a generated banded volume or of a given
//! store: warm frame times of a complete frame, samples, steps, nodes and
//! bricks per ray (the bricks: CPU only), peak bricks resident, and how
//! far the two images differ.

use anyhow::{bail, Result};
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, Dims3, TransferFunction};
use brickyard_render::cpu::{render_tiles, FrameStats, Lod, Scene, Tiles};
use brickyard_render::image::Image;
use brickyard_render::octree::Octree;
use brickyard_render::params::{DebugCounts, Traversal};
use brickyard_render::reference::{ChannelStyle, RenderMode, RenderParams};
use brickyard_run::backend::{Backend, GpuUpdate};
use brickyard_store::error::Result as StoreResult;
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::import::zarr;
use brickyard_store::info::inspect;
use brickyard_store::source::{SourceMeta, VolumeSource};
use brickyard_store::{convert, ConvertOptions, NoProgress};
use rayon::prelude::*;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

/// What `bench octree` measures.
pub struct OctreeBench {
    /// Generated volume size `[z, y, x]` (u8).
    pub dims: Dims3,
    /// A store to measure instead of the generated volumes.
    pub store: Option<PathBuf>,
    pub channels: Vec<usize>,
    pub image: [u32; 2],
    pub depth: u32,
    /// Warm frames timed per row (at least 3).
    pub repeat: usize,
    /// Store chunk and shard edges of the generated volumes.
    pub chunk: u64,
    pub shard: u64,
    /// Back ends measured: `cpu`, `gpu` (updates decided on the host, as
    /// the octree needs) or both.
    pub backends: Vec<&'static str>,
}

/// `n` channels of one grid: channel `c` holds the Mandelbulb's values
/// (Marschner–Lobb for odd `c`) inside the `c`-th of `n` overlapping value
/// bands, rescaled to 60–255, and 0 elsewhere (one channel: the Mandelbulb
/// above 0.05). Each channel shows a different shell of the same objects.
struct Banded {
    meta: SourceMeta,
    fields: Vec<Vec<f32>>,
    n: usize,
}

impl Banded {
    fn new(dims: Dims3, n: usize) -> Banded {
        let fields = [Kind::Mandelbulb, Kind::MarschnerLobb]
            .into_iter()
            .take(n.min(2))
            .map(|k| {
                let g = Procedural::new(k, dims, DType::U8);
                let plane = (dims[1] * dims[2]) as usize;
                let mut v = vec![0f32; plane * dims[0] as usize];
                v.par_chunks_mut(dims[2] as usize)
                    .enumerate()
                    .for_each(|(row, o)| {
                        let (z, y) = (
                            (row / dims[1] as usize) as u64,
                            (row % dims[1] as usize) as u64,
                        );
                        for (x, e) in o.iter_mut().enumerate() {
                            *e = g.value(z, y, x as u64) as f32;
                        }
                    });
                v
            })
            .collect();
        let mut meta = SourceMeta::new(format!("<banded {n} channels>"), dims, n, DType::U8);
        meta.channel_names = (0..n).map(|c| format!("band{c}")).collect();
        Banded { meta, fields, n }
    }

    fn value(&self, c: usize, i: usize) -> u8 {
        let v = self.fields[c % 2][i] as f64;
        let (lo, hi) = if self.n == 1 {
            (0.05, 1.0)
        } else {
            let w = 1.0 / self.n as f64;
            ((c as f64 - 0.5) * w, (c as f64 + 1.5) * w)
        };
        if v >= lo && v < hi {
            (60.0 + 195.0 * ((v - lo) / (hi - lo)).clamp(0.0, 1.0)).round() as u8
        } else {
            0
        }
    }
}

impl VolumeSource for Banded {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }

    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> StoreResult<()> {
        let [_, dy, dx] = self.meta.dims;
        let nx = (x.end - x.start) as usize;
        let ny = (y.end - y.start) as usize;
        assert_eq!(out.len(), nx * ny * (z.end - z.start) as usize);
        out.chunks_mut(nx).enumerate().for_each(|(row, o)| {
            let zz = z.start + (row / ny) as u64;
            let yy = y.start + (row % ny) as u64;
            let base = ((zz * dy + yy) * dx + x.start) as usize;
            for (i, e) in o.iter_mut().enumerate() {
                *e = self.value(c, base + i);
            }
        });
        Ok(())
    }
}

/// The banded store of `n` channels in `dir`, converted now if missing.
fn banded_store(dir: &Path, dims: Dims3, n: usize, o: &OctreeBench) -> Result<PathBuf> {
    let p = dir.join(format!(
        "octree-banded-{n}ch-{}x{}x{}.ome.zarr",
        dims[2], dims[1], dims[0]
    ));
    if inspect(&p).is_ok_and(|i| i.complete != Some(false)) {
        return Ok(p);
    }
    crate::bench::make_bench_dir(dir)?;
    eprintln!("bench: writing {}", p.display());
    let src = Banded::new(dims, n);
    let opts = ConvertOptions {
        brick: [o.chunk; 3],
        shard: [o.shard; 3],
        overwrite: true,
        ..Default::default()
    };
    convert(&src, &p, &opts, &NoProgress, &AtomicBool::new(false))?;
    Ok(p)
}

/// One row of the table.
struct Row {
    complete_frames: usize,
    complete_s: f64,
    best_ms: f64,
    median_ms: f64,
    stats: FrameStats,
    /// Bricks entered per ray (CPU only: the debug count).
    bricks: Option<f64>,
    peak_resident: usize,
    image: Image,
}

/// `n` visible channels of `store` through `traversal`: frames until the
/// view is complete, then warm frames.
fn measure(
    store: &Path,
    n: usize,
    traversal: Traversal,
    backend: &str,
    o: &OctreeBench,
) -> Result<Row> {
    let l0 = zarr::open(store, 0)?;
    let m = l0.meta().clone();
    let extent = world_extent(m.dims, m.spacing.unwrap_or([1.0; 3]));
    let mut levels = vec![];
    while let Ok(z) = zarr::open(store, levels.len()) {
        levels.push(z.meta().dims);
    }
    let mut scene = Scene::new(extent, levels);
    // The whole pyramid of every channel fits (padded bricks), so that the
    // frames measured are warm.
    let vox: u64 = m.dims.iter().product();
    let pool = vox * m.channels as u64 * m.dtype.size() as u64 * 3 / 2 + (32 << 20);
    let cfg = VmConfig {
        brick: [32; 3],
        pool_bytes: pool,
        upload_bytes_per_frame: pool,
        request_cap: 4096,
        ..Default::default()
    };
    let mut s = Session::open(store, cfg, pool, 2)?;
    s.set_batch(Some(Duration::from_secs(60)));
    let mut be = Backend::choose(backend, GpuUpdate::Host, &mut s, n)?;
    let ranges = Arc::new(s.loader().brick_ranges(1 << 24));
    scene.ranges = Some(ranges.clone());
    if traversal == Traversal::Octree {
        let oc = Octree::attach(o.depth, &scene.levels, s.vm_mut(), Some(&ranges))
            .map_err(|e| anyhow::anyhow!("octree-depth: {e}"))?;
        scene.octree = Some(Arc::new(RwLock::new(oc)));
    }
    let window = match m.dtype {
        DType::U8 => [0.0, 255.0],
        DType::U16 => [0.0, 65535.0],
        _ => {
            let st = inspect(store)?;
            st.levels
                .iter()
                .find_map(|l| l.stats.as_ref().map(|s| [s.min as f32, s.max as f32]))
                .unwrap_or([0.0, 1.0])
        }
    };
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let tf = TransferFunction::preset("soft", window)?;
    let mut p = RenderParams::new(o.image[0], o.image[1], cam, tf, RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(0));
    p.traversal = traversal;
    p.channels = (0..n)
        .map(|c| {
            // Hues around the circle.
            let h = c as f32 / n as f32 * 6.0;
            let col = [
                ((h - 3.0).abs() - 1.0).clamp(0.0, 1.0),
                (2.0 - (h - 2.0).abs()).clamp(0.0, 1.0),
                (2.0 - (h - 4.0).abs()).clamp(0.0, 1.0),
            ];
            ChannelStyle::new(c, col, window)
        })
        .collect();
    p.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    let lod = Lod::Auto { bias: 0.0 };
    let mut peak_resident = 0;
    // A frame through the back end, its octree (if any) synced after it;
    // the time of its render (CPU: drawing; device: drawing and reading
    // back the image and counters).
    let mut frame = |s: &mut Session, p: &RenderParams| -> Result<(Image, FrameStats, f64)> {
        let f = be.frame(s, &scene, p, lod)?;
        peak_resident = peak_resident.max(f.session.frame.resident_bricks);
        Ok((f.image, f.stats, f.render_ms))
    };
    let t0 = Instant::now();
    let mut complete_frames = 0;
    loop {
        complete_frames += 1;
        let (_, st, _) = frame(&mut s, &p)?;
        if st.completeness() >= 1.0 {
            break;
        }
        if complete_frames >= 200 {
            bail!("{n} channels through {traversal:?}: the view did not complete in 200 frames");
        }
    }
    let complete_s = t0.elapsed().as_secs_f64();
    let mut times = vec![];
    let mut last = None;
    for _ in 0..o.repeat.max(3) {
        let (img, st, ms) = frame(&mut s, &p)?;
        times.push(ms);
        last = Some((img, st));
    }
    let (image, stats) = last.expect("frames drawn");
    if stats.completeness() < 1.0 {
        bail!("{n} channels through {traversal:?}: a warm frame was not complete");
    }
    // Bricks entered per ray: the debug image's counts (before false
    // colour), on the CPU.
    let bricks = (backend == "cpu").then(|| {
        let mut dp = p.clone();
        dp.debug = Some(DebugCounts::Bricks);
        let mut counts = Image::new(p.width, p.height);
        s.begin_frame();
        let (_, reqs) = render_tiles(
            s.vm(),
            &scene,
            &dp,
            lod,
            &mut counts,
            &mut Tiles::all(p.width, p.height),
        );
        s.finish_frame(reqs.iter());
        counts.rgba.iter().map(|px| px[0] as f64).sum::<f64>() / (p.width as f64 * p.height as f64)
    });
    times.sort_by(f64::total_cmp);
    Ok(Row {
        complete_frames,
        complete_s,
        best_ms: times[0],
        median_ms: times[times.len() / 2],
        stats,
        bricks,
        peak_resident,
        image,
    })
}

pub fn run(dir: &Path, o: &OctreeBench) -> Result<()> {
    if o.channels.is_empty() {
        bail!("channels: expected a list of channel counts, e.g. 1,4,16");
    }
    let given = match &o.store {
        Some(st) => {
            let c = zarr::open(st, 0)?.meta().channels;
            if let Some(n) = o.channels.iter().find(|&&n| n == 0 || n > c) {
                bail!(
                    "channels: {n} asked for but {} has {c} channel(s)",
                    st.display()
                );
            }
            Some(st.clone())
        }
        None => None,
    };
    let what = match &given {
        Some(st) => format!("store {}", st.display()),
        None => format!(
            "generated banded u8 volumes of {}x{}x{} (one store per channel count, chunks {}³)",
            o.dims[2], o.dims[1], o.dims[0], o.chunk
        ),
    };
    outln!(
        "bench octree: {what}; image {}x{}, engine bricks 32³, octree depth {}, CPU {} threads, DVR with automatic level of detail, pool holding every brick; back ends: {}",
        o.image[0],
        o.image[1],
        o.depth,
        rayon::current_num_threads(),
        o.backends.join(", ")
    );
    outln!("per ray: over all {} pixels' rays; frame: the render of a complete, warm frame (best and median of {})", o.image[0] as u64 * o.image[1] as u64, o.repeat.max(3));
    outln!(
        "{:>8} {:>7} {:>10} {:>10} {:>10} {:>9} {:>9} {:>9} {:>10} {:>10} {:>9} {:>13} {:>9}",
        "channels",
        "backend",
        "traversal",
        "best ms",
        "median ms",
        "samples",
        "steps",
        "nodes",
        "skip nodes",
        "bricks",
        "resident",
        "complete",
        "max diff"
    );
    let rays = o.image[0] as f64 * o.image[1] as f64;
    for &n in &o.channels {
        let store = match &given {
            Some(st) => st.clone(),
            None => banded_store(dir, o.dims, n, o)?,
        };
        for &backend in &o.backends {
            let pt = measure(&store, n, Traversal::PageTable, backend, o)?;
            let oc = measure(&store, n, Traversal::Octree, backend, o)?;
            let diff = pt.image.max_abs_diff(&oc.image);
            for (name, r) in [("page-table", &pt), ("octree", &oc)] {
                let st = &r.stats;
                outln!(
                "{:>8} {:>7} {:>10} {:>10.1} {:>10.1} {:>9.1} {:>9} {:>9.1} {:>10.1} {:>10} {:>9} {:>13} {:>9.1e}",
                n,
                backend,
                name,
                r.best_ms,
                r.median_ms,
                st.samples as f64 / rays,
                if backend == "cpu" {
                    format!("{:.1}", st.steps as f64 / rays)
                } else {
                    "-".into()
                },
                st.octree_nodes as f64 / rays,
                st.skipped_nodes as f64 / rays,
                r.bricks.map_or("-".into(), |b| format!("{b:.1}")),
                r.peak_resident,
                format!("{} fr {:.1} s", r.complete_frames, r.complete_s),
                diff
            );
            }
        }
    }
    Ok(())
}
