//! `brickyard view`: an interactive viewer. A 3D view (DVR, MIP or an
//! oblique plane) and four slice views through a cursor, streamed through
//! the virtual memory on a render thread, with a transfer-function editor
//! over a histogram of the bricks' value ranges, per-channel colours, level
//! of detail and budgets, a live status line, screenshots, and views saved
//! as the camera/transfer-function JSON that `brickyard render` takes.
//! `--script` drives it from a file of input events (tests, recordings).

mod app;
mod probe;
pub mod script;
mod worker;

use crate::backend::GpuUpdate;
use anyhow::{bail, Context, Result};
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera};
use brickyard_core::TransferFunction;
use brickyard_render::cpu::Scene;
use brickyard_render::params::Traversal;
use brickyard_store::import::zarr;
use brickyard_store::info::inspect;
use brickyard_store::VolumeSource;
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::{AtomicI32, Ordering};
use std::sync::Arc;
use std::time::Duration;

#[derive(Args)]
pub struct ViewCmd {
    /// An OME-Zarr store; none: the demo dataset (brickyard-demo/,
    /// generated on first use).
    store: Option<PathBuf>,
    /// auto (a hardware GPU when there is one, else the CPU), gpu or cpu.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// On the GPU, who decides cache updates: device or host. Default:
    /// device, host with --traversal octree.
    #[arg(long, value_name = "device|host")]
    gpu_update: Option<GpuUpdate>,
    /// One budget for the whole viewer: the brick pool, host cache,
    /// decoded-chunk caches, view images and the window are split out of
    /// it. Without it: --pool 256MiB and --host 1GiB (768 MiB on a software
    /// device, whose copy of the pool is host memory too).
    #[arg(long)]
    memory: Option<String>,
    /// Brick-pool budget (default: 256 MiB, or a share of --memory).
    #[arg(long)]
    pool: Option<String>,
    /// Host-cache budget (default: 1 GiB, less the pool's copy on a software
    /// device, or a share of --memory).
    #[arg(long)]
    host: Option<String>,
    /// Engine brick edge (4 to 512 voxels; smaller bricks cost far more in
    /// bookkeeping than they save: a view at 2 took minutes).
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u64).range(4..=512))]
    brick: u64,
    /// Bytes written into the pool per frame (a device back end writes at
    /// most 32 MiB: its staging buffer is set aside in --memory).
    #[arg(long, default_value = "64MiB")]
    upload: String,
    /// Threads that read and decode bricks (1 to 256).
    #[arg(long, default_value_t = 2)]
    loader_threads: usize,
    /// Start with this camera (JSON, as `render --camera` takes).
    #[arg(long)]
    camera: Option<PathBuf>,
    /// Transfer function: a preset or a JSON file.
    #[arg(long, default_value = "soft")]
    tf: String,
    /// 3D view: dvr, mip or slice.
    #[arg(long, default_value = "dvr")]
    mode: String,
    /// Window size WxH in points.
    #[arg(long, default_value = "1400x860")]
    window_size: String,
    /// Run the input events and checks of this file (see the README), then
    /// stay open unless it ends with `quit`.
    #[arg(long)]
    script: Option<PathBuf>,
    /// Write one JSON line per frame received to this file.
    #[arg(long)]
    log: Option<PathBuf>,
    /// Start showing a live derived channel: this processing pipeline
    /// (e.g. `gauss(1.5)|sobel`) over channel 0, computed brick by brick as
    /// the views ask for it (the processing panel changes it).
    #[arg(long)]
    derive: Option<String>,
    /// Slow every brick read down by this many milliseconds (to watch
    /// streaming).
    #[arg(long, default_value_t = 0)]
    read_delay_ms: u64,
    /// While a DVR view is still, accumulate samples over this many
    /// frames (sampling N times as densely; transfer-function edits
    /// re-blend the kept samples); 0: off. Default 16, 0 with
    /// --traversal octree (accumulation walks the page tables).
    #[arg(long, value_name = "N")]
    accumulate: Option<u32>,
    /// How the 3D view's DVR rays find their bricks: page-table (the page
    /// tables at every step) or octree (the residency octree, kept from
    /// the session's virtual memory after every frame: empty and
    /// homogeneous nodes skipped, misses substituted from the levels a
    /// node has). The octree draws unshaded DVR, on the CPU or the GPU (with
    /// updates decided on the host), and does not accumulate samples; the 3D view in
    /// MIP or slice mode and the xy, xz, yz and oblique views always draw
    /// through the page tables.
    #[arg(long, default_value = "page-table", value_name = "octree|page-table")]
    traversal: String,
    /// --traversal octree: the octree's depth, 1 to 7 (default 4).
    #[arg(long, value_name = "D")]
    octree_depth: Option<u32>,
    /// Lay the store's label image labels/NAME over the slice views (and
    /// the 3D view in slice mode), each label in its own colour; the
    /// controls turn it off and on. Its session, on the CPU, takes a
    /// quarter of the pool, host cache and decoded chunks.
    #[arg(long, value_name = "NAME")]
    labels: Option<String>,
    /// --labels: how opaque the labels are over the image (above 0, at
    /// most 1; default 0.5).
    #[arg(long, value_name = "A")]
    label_opacity: Option<f32>,
}

/// Histogram of brick value ranges over `range`: each brick adds one,
/// spread evenly over the bins its range covers. Takes the finest level
/// with at most 2^18 bricks.
fn histogram(
    ranges: &brickyard_cache::ranges::BrickRanges,
    range: [f32; 2],
    bins: usize,
) -> Vec<f32> {
    let mut h = vec![0f32; bins];
    let level = (0..ranges.levels.len())
        .filter_map(|l| ranges.level(l))
        .find(|r| r.range.len() <= 1 << 18);
    let Some(r) = level else { return h };
    let [lo, hi] = range;
    if hi <= lo {
        return h;
    }
    let bin =
        |v: f32| (((v - lo) / (hi - lo)) * bins as f32).clamp(0.0, bins as f32 - 1.0) as usize;
    for &[a, b] in &r.range {
        if !(a.is_finite() && b.is_finite()) {
            continue;
        }
        let (i, j) = (bin(a), bin(b));
        let w = 1.0 / (j - i + 1) as f32;
        for x in &mut h[i..=j] {
            *x += w;
        }
    }
    h
}

/// The views' images, their textures and the window's frame buffers,
/// for views of `pixels` pixels in all: the labels' slices over them add
/// half as many again.
pub(crate) fn image_pixels(pixels: u64, labels: bool) -> u64 {
    pixels * if labels { 3 } else { 2 } / 2
}

/// [`image_pixels`] in bytes (as the memory split counts them).
pub(crate) fn image_bytes(pixels: u64, labels: bool) -> u64 {
    image_pixels(pixels, labels) * crate::memory::IMAGE_BYTES_PER_PIXEL
}

/// How long the window, once closed, waits for a render thread still
/// drawing a frame before the process ends without it.
const JOIN_WAIT: Duration = Duration::from_secs(10);

pub fn run(c: ViewCmd, demo_store: impl FnOnce() -> Result<PathBuf>) -> Result<i32> {
    // The rules of `render --traversal` (checked before anything is read).
    let crate::render::TraversalChoice {
        traversal,
        depth: octree_depth,
        backend,
        gpu_update,
        ..
    } = crate::render::check_traversal(&crate::render::TraversalFlags {
        gpu_update: c.gpu_update,
        traversal: &c.traversal,
        octree_depth: c.octree_depth,
        debug: None,
        mode: None,
        accumulation: c.accumulate.filter(|&n| n > 0).map(|_| "--accumulate"),
        backend: &c.backend,
    })?;
    let octree = traversal == Traversal::Octree;
    let accumulate = c.accumulate.unwrap_or(if octree { 0 } else { 16 });
    let store = match c.store.clone() {
        Some(s) => s,
        None => demo_store()?,
    };
    let info = inspect(&store)?;
    if let Some(why) = info.incomplete {
        bail!("{}: the store is incomplete: {why}", store.display());
    }
    // `--labels NAME`: checked before any window opens.
    let label_dir = match (&c.labels, c.label_opacity) {
        (None, Some(_)) => {
            bail!(
                "label-opacity: applies with --labels NAME (the label image laid over the slices)"
            )
        }
        (None, None) => None,
        (Some(name), opacity) => {
            if let Some(a) = opacity.filter(|a| !(*a > 0.0 && *a <= 1.0)) {
                bail!("label-opacity: expected an opacity above 0 and at most 1, found {a}");
            }
            if info.label_image {
                bail!(
                    "labels: {} is itself a label image (its views show its labels); --labels \
                     lays a label image over an image",
                    store.display()
                );
            }
            Some(brickyard_run::labels::label_store(&store, name)?)
        }
    };
    let l0 = zarr::open(&store, 0)?;
    let m = l0.meta().clone();
    let extent = world_extent(m.dims, m.spacing.unwrap_or([1.0; 3]));
    let levels = (0..info.levels.len())
        .map(|l| Ok(zarr::open(&store, l)?.meta().dims))
        .collect::<Result<Vec<_>>>()?;
    let range = info
        .levels
        .iter()
        .rev()
        .find_map(|l| l.stats.as_ref().map(|s| [s.min as f32, s.max as f32]))
        .filter(|r| r[1] > r[0])
        .unwrap_or([0.0, 1.0]);
    let tf = if c.tf.ends_with(".json") {
        let text =
            std::fs::read_to_string(&c.tf).with_context(|| format!("{}: cannot read", c.tf))?;
        TransferFunction::from_json(&text).map_err(|e| anyhow::anyhow!("{}: {e}", c.tf))?
    } else {
        // The window `render` takes by default (robust percentiles).
        let window = crate::window::auto_window(&store, levels.len(), 0)?
            .map(|(lo, hi)| [lo as f32, hi as f32])
            .filter(|w| w[1] > w[0])
            .unwrap_or(range);
        TransferFunction::preset(&c.tf, window).map_err(|e| anyhow::anyhow!("tf: {e}"))?
    };
    crate::render::check_octree_shading(traversal, &tf, &c.tf, true)?;
    if !["dvr", "mip", "slice"].contains(&c.mode.as_str()) {
        bail!("mode: expected dvr, mip or slice, found {:?}", c.mode);
    }
    let camera = match &c.camera {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("{}: cannot read", p.display()))?;
            Some(Camera::from_json(&text).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?)
        }
        None => None,
    };
    let script = match &c.script {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("{}: cannot read", p.display()))?;
            script::parse(p, &text)?
        }
        None => vec![],
    };
    let log = match &c.log {
        Some(p) => Some(
            std::fs::File::create(p).with_context(|| format!("{}: cannot create", p.display()))?,
        ),
        None => None,
    };
    let [ww, wh] = crate::render::parse_image_size(&c.window_size, "window-size")?;
    let opt = |v: &Option<String>, flag: &str| {
        v.as_deref()
            .map(|x| crate::parse_bytes(x).with_context(|| format!("--{flag}")))
            .transpose()
    };
    let (memory, mut pool, mut host) = (
        opt(&c.memory, "memory")?,
        opt(&c.pool, "pool")?,
        opt(&c.host, "host")?,
    );
    if memory.is_none() {
        pool.get_or_insert(256 << 20);
        host.get_or_insert(1 << 30);
    }
    crate::render::check_read_delay(c.read_delay_ms)?;
    crate::render::check_loader_threads(c.loader_threads)?;
    if accumulate > brickyard_render::savr::MAX_FRAMES {
        bail!(
            "accumulate: N frames between 0 and {}, got {}",
            brickyard_render::savr::MAX_FRAMES,
            accumulate
        );
    }
    // Kept samples of the accumulating view: an eighth of the budget, at
    // most 256 MiB.
    let accum_bytes = match accumulate {
        0 => 0,
        _ => (memory.unwrap_or_else(crate::memory::default_memory) / 8).min(256 << 20),
    };
    // `--derive`: the filters get at most a quarter of --memory (as
    // `render --derive` and `process` give theirs), set aside before the
    // pool and host cache take their shares; refused now when even one
    // block per stage at a time does not fit.
    let derived_within = match &c.derive {
        Some(p) => Some(crate::derive::Derived::new_within(
            &store,
            p,
            0,
            memory,
            c.loader_threads,
            c.brick,
        )?),
        None => None,
    };
    // A device back end's driver lives in this process too.
    let device = crate::backend::plan_device(&backend, 0, memory);
    if let Some(n) = &device.note {
        eprintln!("{n}");
    }
    let backend = device.choice.clone();
    // The voxel readout's readers (the image's channels, and the labels).
    let label_levels = match &label_dir {
        Some(dir) => {
            Some(brickyard_store::omezarr::read_multiscale(dir)?.map_or(1, |m| m.datasets.len()))
        }
        None => None,
    };
    let probe_bytes = probe::bytes(levels.len(), m.channels, label_levels);
    // The residency octree's tables count in --memory, and a depth that
    // would take more than a quarter of it is lowered, as `render` does.
    let (octree_depth, octree_bytes) = if octree {
        let total = memory.unwrap_or_else(crate::memory::default_memory);
        let fit = crate::render::fit_octree_depth(octree_depth, levels.len(), m.channels, total);
        if let Some(n) = &fit.note {
            eprintln!("{n}");
        }
        (fit.depth, fit.bytes)
    } else {
        (octree_depth, 0)
    };
    let mut split = crate::memory::split_with_shares(
        memory,
        pool,
        host,
        // The views' images, their textures and the window's frame
        // buffers: together about the window's pixels; the labels' slices
        // add half as many again.
        image_pixels(ww as u64 * wh as u64, label_dir.is_some()),
        levels.len(),
        crate::memory::WINDOW_BYTES + accum_bytes + device.bytes + probe_bytes + octree_bytes,
        (derived_within.as_ref().map_or(0, |(_, b)| *b), 0),
    )?;
    device.take_from(&mut split, pool)?;
    // Freed memory goes back to the system near the budget, as the loader
    // loads (as in `render`).
    crate::memory::watch(split.total);
    // The label image's session: a quarter of the pool, the host cache
    // and the decoded chunks (it draws slices only).
    let label_bytes = label_dir.as_ref().map(|_| {
        let q = [split.pool / 4, split.host / 4, split.chunks / 4];
        split.pool -= q[0];
        split.host -= q[1];
        split.chunks -= q[2];
        q
    });
    let mut cfg = VmConfig {
        brick: [c.brick; 3],
        pool_bytes: split.pool,
        // A device's staging buffer holds at most its cap of bricks.
        upload_bytes_per_frame: crate::parse_bytes(&c.upload)
            .context("--upload")?
            .min(device.upload_cap().unwrap_or(u64::MAX)),
        ..Default::default()
    };
    // Budgets that cannot work, said now as `render` says them, not in
    // the window once it opens: less than a brick a frame (nothing could
    // ever reach the pool, and the views waited for ever), and a pool too
    // small for the coarsest level (the session's own rule).
    let geometry = brickyard_cache::brick::BrickGeometry {
        brick: [c.brick; 3],
        apron: cfg.apron,
        levels: levels.clone(),
        channels: m.channels,
        dtype: m.dtype,
    };
    let brick_bytes = geometry.bytes_per_brick();
    if cfg.upload_bytes_per_frame < brick_bytes {
        anyhow::bail!(
            "upload: {} bytes per frame is less than one padded brick ({brick_bytes} bytes): no brick could ever be written into the pool",
            cfg.upload_bytes_per_frame
        );
    }
    let slots = cfg.pool_slots(m.dtype, geometry.total_bricks() as u64) as usize;
    if let Err(e) = geometry.pinned_levels(slots, cfg.slot_bytes(m.dtype), 512) {
        if pool.is_some() {
            anyhow::bail!("pool: {e} (--pool)");
        }
        // A share of --memory: the host cache lends the pool what it
        // lacks where it can (as `render` does), else the run says which
        // knob moves it.
        let Some(moved) = split.lend_pool(e.minimum_bytes) else {
            anyhow::bail!(
                "pool: {e}; the pool is a share of --memory ({}): raise --memory ({}MiB holds \
                 it)",
                brickyard_store::info::human_bytes(split.total),
                split.total_holding_pool(e.minimum_bytes) >> 20
            );
        };
        eprintln!(
            "note: the pool takes {} of the host cache's share, to keep the coarsest level \
             resident (pool {}, host cache {})",
            brickyard_store::info::human_bytes(moved),
            brickyard_store::info::human_bytes(split.pool),
            brickyard_store::info::human_bytes(split.host)
        );
        cfg.pool_bytes = split.pool;
    }
    cfg.request_cap = crate::frames::requests_per_frame(
        split.pool,
        split.host,
        cfg.slot_bytes(m.dtype),
        crate::frames::STREAM_REQUESTS,
    );
    let setup = worker::Setup {
        store: store.clone(),
        cfg,
        host_bytes: split.host,
        chunk_bytes: split.chunks,
        memory_budget: split.total,
        loader_threads: c.loader_threads,
        backend,
        gpu_update,
        channels: m.channels,
        read_delay: Duration::from_millis(c.read_delay_ms),
        derive: None,
        accumulate,
        accum_bytes,
        octree: octree.then_some(octree_depth),
        image_bytes: image_bytes(ww as u64 * wh as u64, label_dir.is_some()),
        memory_given: memory.is_some(),
    };
    // The histogram from the bricks' value ranges (statistics only).
    let loader = brickyard_cache::loader::Loader::open(
        &store,
        setup.cfg.brick,
        setup.cfg.apron,
        1,
        Arc::new(brickyard_cache::host_cache::HostCache::new(1 << 20)),
    )?;
    let ranges = Arc::new(loader.brick_ranges(1 << 24));
    drop(loader);
    let ds = Arc::new(app::Dataset {
        store: store.clone(),
        extent,
        histogram: histogram(&ranges, range, 128),
        levels: levels.clone(),
        dtype: m.dtype,
        channels: m.channels,
        range,
        labels: m.channels == 1 && info.label_image,
    });
    // The label image's session and scene (its own pyramid on the same
    // grid), drawn on the CPU by a render thread of its own.
    let labels = match (&label_dir, label_bytes) {
        (Some(dir), Some([lpool, lhost, lchunks])) => {
            // (Its levels' sizes only: the worker reads its statistics.)
            let nl = label_levels.unwrap_or(1);
            let lmeta = zarr::open(dir, 0)?.meta().clone();
            let llevels = (0..nl)
                .map(|l| Ok(zarr::open(dir, l)?.meta().dims))
                .collect::<Result<Vec<_>>>()?;
            let mut lcfg = setup.cfg.clone();
            lcfg.pool_bytes = lpool;
            lcfg.request_cap = crate::frames::requests_per_frame(
                lpool,
                lhost,
                lcfg.slot_bytes(lmeta.dtype),
                crate::frames::STREAM_REQUESTS,
            );
            let lsetup = worker::Setup {
                store: dir.clone(),
                cfg: lcfg,
                host_bytes: lhost,
                chunk_bytes: lchunks,
                backend: "cpu".into(),
                channels: 1,
                derive: None,
                accumulate: 0,
                accum_bytes: 0,
                octree: None,
                ..setup.clone()
            };
            let name = c.labels.clone().unwrap_or_default();
            Some((lsetup, Scene::new(extent, llevels), name))
        }
        _ => None,
    };
    let mut setup = setup;
    let mut tf = tf;
    // `--derive`: the window starts on the derived channel.
    let (ds, derived) = match derived_within {
        Some((d, _)) => {
            let dds = app::derived_dataset(&ds, &d)?;
            let stored_window = tf.window;
            if !c.tf.ends_with(".json") {
                tf.window = dds.range;
            }
            let shown = (d.pipeline.text(), 0, stored_window);
            setup.derive = Some(Arc::new(d));
            setup.channels = 1;
            (Arc::new(dds), Some((ds, shown)))
        }
        None => (ds, None),
    };
    let (to_worker, worker_rx) = std::sync::mpsc::channel();
    let (worker_tx, from_worker) = std::sync::mpsc::channel();
    let exit = Arc::new(AtomicI32::new(0));
    let opts = eframe::NativeOptions {
        viewport: eframe::egui::ViewportBuilder::default()
            .with_inner_size([ww as f32, wh as f32])
            .with_title(format!("brickyard view — {}", store.display())),
        ..Default::default()
    };
    let mut scene = Scene::new(extent, levels);
    // The render thread uses the same brick ranges (read once).
    scene.ranges = Some(ranges.clone());
    let exit2 = exit.clone();
    let mode = c.mode.clone();
    // The render thread is joined before the process ends: it holds the
    // device (with the software drivers, threads of their own), and a
    // process that exits while a driver still works can die in the
    // libraries' exit-time teardown.
    let render_thread = Arc::new(std::sync::Mutex::new(None));
    let render_thread2 = render_thread.clone();
    let label_thread = Arc::new(std::sync::Mutex::new(None));
    let label_thread2 = label_thread.clone();
    let opacity = c.label_opacity.unwrap_or(0.5);
    let probe_setup = probe::Setup {
        store: store.clone(),
        labels: label_dir.clone(),
        stats: label_dir
            .clone()
            .or_else(|| (m.channels == 1 && info.label_image).then(|| store.clone())),
        image_labels: m.channels == 1 && info.label_image,
        extent,
        read_delay: Duration::from_millis(c.read_delay_ms),
    };
    let r = eframe::run_native(
        "brickyard view",
        opts,
        Box::new(move |cc| {
            let ctx = cc.egui_ctx.clone();
            let setup2 = setup.clone();
            let handle = std::thread::Builder::new()
                .name("render".into())
                .spawn(move || {
                    worker::run(setup2, scene, worker_rx, worker_tx, move || {
                        ctx.request_repaint()
                    })
                })
                .map_err(|e| format!("render thread: {e}"))?;
            *render_thread2.lock().unwrap() = Some(handle);
            let layer = match labels {
                Some((lsetup, lscene, name)) => {
                    let (ltx, lrx) = std::sync::mpsc::channel();
                    let (lwtx, lfrom) = std::sync::mpsc::channel();
                    let ctx = cc.egui_ctx.clone();
                    let (levels, voxel0) = (lscene.levels.len(), lscene.voxel(0));
                    let h = std::thread::Builder::new()
                        .name("render-labels".into())
                        .spawn(move || {
                            worker::run(lsetup, lscene, lrx, lwtx, move || ctx.request_repaint())
                        })
                        .map_err(|e| format!("label render thread: {e}"))?;
                    *label_thread2.lock().unwrap() = Some(h);
                    Some(app::LabelLayer::new(
                        name, ltx, lfrom, opacity, levels, voxel0,
                    ))
                }
                None => None,
            };
            // The voxel under the pointer, read by a thread of its own.
            let ctx = cc.egui_ctx.clone();
            let probe = probe::Probe::start(probe_setup, move || ctx.request_repaint())
                .map_err(|e| eprintln!("view: no voxel readout: {e:#}"))
                .ok();
            Ok(Box::new(app::ViewerApp::new(
                ds,
                setup,
                to_worker,
                from_worker,
                camera,
                tf,
                mode,
                script,
                log,
                exit2,
                derived,
                layer,
                probe,
            )))
        }),
    );
    // The window is gone and with it the sender of the worker's messages:
    // the worker sees that (or the `Quit` sent on exit) and returns.
    // A thread still in a long frame (it reads its messages between
    // frames) is waited for a while, then left: closing the window must
    // not wait for ever.
    let until = std::time::Instant::now() + JOIN_WAIT;
    for (thread, what) in [(&render_thread, "render"), (&label_thread, "label render")] {
        let handle = thread.lock().unwrap().take();
        if let Some(h) = handle {
            while !h.is_finished() && std::time::Instant::now() < until {
                std::thread::sleep(Duration::from_millis(20));
            }
            if !h.is_finished() {
                eprintln!(
                    "view: the {what} thread is still drawing a frame {} s after the window closed; exiting without it",
                    JOIN_WAIT.as_secs()
                );
                if let Err(e) = &r {
                    eprintln!("view: cannot open a window: {e}");
                    std::process::exit(1);
                }
                std::process::exit(exit.load(Ordering::SeqCst));
            }
            if h.join().is_err() {
                eprintln!("view: the {what} thread panicked");
            }
        }
    }
    if let Err(e) = r {
        bail!("view: cannot open a window: {e} (is a display available? under CI use xvfb-run)");
    }
    Ok(exit.load(Ordering::SeqCst))
}
