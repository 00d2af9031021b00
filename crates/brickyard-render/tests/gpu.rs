//! The device renderer through the device's copy of the virtual memory,
//! with a pool a quarter of the volume: frames come while bricks stream in,
//! completeness reaches 100 %, and the final image equals the in-core
//! reference and the CPU renderer within the stated tolerance (positions
//! are f32 on the device, f64 on the host). Runs on lavapipe in CI.

mod common;
#[path = "common/requests.rs"]
mod requests;
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::update::DeviceCache;
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{render_frame, FrameStats, Lod, Scene};
use brickyard_render::gpu::{update_on_device, GpuRenderer};
use brickyard_render::reference::{render, render_auto_lod, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::source::{check_region, SourceMeta, VolumeSource};
use requests::same_requests;
use std::sync::atomic::AtomicBool;

/// Largest difference of any channel of any pixel allowed between the
/// device's image and the host's (premultiplied RGBA in [0, 1]).
const TOLERANCE: f32 = 1e-4;

/// `pool`: the pool as a fraction of the volume's bytes; `image`: edge.
#[allow(clippy::too_many_arguments)]
fn case(
    src: &dyn VolumeSource,
    window: [f32; 2],
    mode: RenderMode,
    lod: Lod,
    pool: f64,
    image: u32,
) -> Option<FrameStats> {
    // `None`: no adapter and BRICKYARD_SKIP_GPU=1 (`test_gpu` says so).
    let gpu = test_gpu()?;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("v.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    let (dims, dtype) = (src.meta().dims, src.meta().dtype);
    convert(src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let levels: Vec<Volume> = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    let extent = world_extent(dims, levels[0].spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let vol_bytes = dims.iter().product::<u64>() * dtype.size() as u64;
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes: (vol_bytes as f64 * pool) as u64,
        pt_cache_blocks: 256,
        request_cap: 64,
        upload_bytes_per_frame: 24 * 18 * 18 * 18 * dtype.size() as u64,
    };
    let mut s = Session::open(&store, cfg.clone(), 8 << 20, 2).unwrap();
    // Brick value ranges from the store's statistics: transparent bricks
    // are crossed in one jump on both back ends.
    let mut scene = scene;
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    let mut renderer = GpuRenderer::new(&gpu);
    let tf = TransferFunction::preset("soft", window).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut p = RenderParams::new(image, image * 4 / 5, cam, tf, mode.clone());
    p.reference_step = Some(scene.voxel(0));
    // Updates decided on the device: a fresh session of its own.
    let mut sd = Session::open(&store, cfg.clone(), 8 << 20, 2).unwrap();
    let (mut ddvm, _) = DeviceVm::new(&gpu, sd.vm_mut()).unwrap();
    let mut cache = DeviceCache::new(&gpu, &ddvm, sd.vm()).unwrap();
    let mut first_d = None;
    let mut done_d = None;
    for frame in 1..=400 {
        sd.begin_frame();
        let n = sd.vm().frame();
        let f = renderer
            .render_with(&gpu, &ddvm, sd.vm(), Some(&cache), &scene, &p, lod)
            .unwrap();
        first_d.get_or_insert(f.stats.completeness());
        // Only the counters and the request list (up to twice the cap of
        // 64) come back.
        assert!(f.bytes_down <= 32 + 2 * 64 * 8 + 8, "{}", f.bytes_down);
        let x = update_on_device(&gpu, &mut ddvm, &mut cache, &mut sd, n, &f.list).unwrap();
        assert!(x.down <= 32 + 4 * sd.vm().config().request_cap as u64 * 2);
        if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
            done_d = Some((frame, f));
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let (frames_d, fd) = done_d.expect("the view completes with updates on the device");
    assert!(
        frames_d > 1 && first_d.unwrap() < 1.0,
        "{mode:?}: frames came before the data (device updates)"
    );
    // Updates decided on the host, mirrored.
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut first = None;
    let mut done = None;
    for frame in 1..=400 {
        s.begin_frame();
        let f = renderer
            .render(&gpu, &dvm, s.vm(), &scene, &p, lod)
            .unwrap();
        first.get_or_insert(f.stats.completeness());
        assert!(f.bytes_down <= 32 + 4 * 2 * s.vm().pool_slots() as u64 + 2 * 64 * 8 + 8);
        s.finish_frame([&f.requests]);
        dvm.sync(&gpu, s.vm_mut());
        if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
            done = Some((frame, f));
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let (frames, f) = done.expect("the view completes");
    assert!(
        frames > 1 && first.unwrap() < 1.0,
        "{mode:?}: frames came before the data"
    );
    assert!(
        f.image.coverage(0.01) > 0.05,
        "{mode:?}: image nearly empty"
    );
    // Complete views sample the same data whoever decided the updates.
    let d = fd.image.max_abs_diff(&f.image);
    eprintln!("{mode:?} {dtype:?}: {frames_d} frames with device updates, {frames} with host updates; max abs diff {d}");
    assert!(d <= 1e-6, "{mode:?}: device and host updates differ by {d}");
    // The in-core reference at the level shown (fixed LOD).
    if let Lod::Fixed(l) = lod {
        let want = render(&levels[l], &p);
        let d = f.image.max_abs_diff(&want);
        eprintln!(
            "{mode:?} {dtype:?}: {frames} frames, max abs diff to the reference {d}, mean {}",
            f.image.mean_abs_diff(&want)
        );
        assert!(
            d <= TOLERANCE,
            "{mode:?} {dtype:?}: max abs diff {d} to the reference"
        );
    }
    // Automatic LOD: against the plain f64 model of level changes.
    if let (Lod::Auto { bias: 0.0 }, RenderMode::Dvr) = (lod, &mode) {
        let want = render_auto_lod(&levels, &p, 0.0);
        let d = f.image.max_abs_diff(&want);
        eprintln!("auto LOD: max abs diff to the plain model {d}");
        assert!(
            d <= TOLERANCE,
            "auto LOD: max abs diff {d} to the plain model"
        );
    }
    // The CPU renderer on the same resident data.
    s.begin_frame();
    let (cpu, st, reqs) = render_frame(s.vm(), &scene, &p, lod);
    s.finish_frame(reqs.iter());
    assert_eq!(st.completeness(), 1.0);
    let d = f.image.max_abs_diff(&cpu);
    eprintln!("{mode:?} {dtype:?}: max abs diff to the CPU renderer {d}");
    assert!(
        d <= TOLERANCE,
        "{mode:?} {dtype:?}: max abs diff {d} to the CPU renderer"
    );
    s.vm().check_invariants().unwrap();
    Some(f.stats)
}

#[test]
fn gpu_dvr_converges_to_the_reference_u16() {
    case(
        &Procedural::new(Kind::Mandelbulb, [64, 80, 96], DType::U16),
        [0.0, 65535.0],
        RenderMode::Dvr,
        Lod::Fixed(1),
        0.25,
        80,
    );
}

#[test]
fn gpu_dvr_converges_to_the_reference_u8_level0() {
    // Level 0 in full: 64 bricks of 18³ padded voxels; the pool holds them
    // (it is bigger than the 64³ voxels), and they still stream in over
    // several frames.
    case(
        &Procedural::new(Kind::MarschnerLobb, [64, 64, 64], DType::U8),
        [0.0, 255.0],
        RenderMode::Dvr,
        Lod::Fixed(0),
        1.5,
        64,
    );
}

#[test]
fn gpu_mip_converges_to_the_reference() {
    case(
        &Procedural::new(Kind::Mandelbulb, [64, 80, 96], DType::U16),
        [0.0, 65535.0],
        RenderMode::Mip,
        Lod::Fixed(1),
        0.25,
        80,
    );
}

#[test]
fn gpu_oblique_slice_converges_to_the_reference() {
    let dims = [64, 80, 96];
    let extent = [96.0, 80.0, 64.0];
    case(
        &Procedural::new(Kind::Mandelbulb, dims, DType::U16),
        [0.0, 65535.0],
        RenderMode::Slice {
            origin: [extent[0] / 2.0, extent[1] / 2.0, extent[2] * 0.4],
            normal: [0.02, 0.01, 1.0],
        },
        Lod::Fixed(0),
        0.5,
        80,
    );
}

#[test]
fn gpu_automatic_lod_equals_the_cpu_renderer() {
    // A small image: one pixel covers several voxels, coarser levels serve.
    case(
        &Procedural::new(Kind::MarschnerLobb, [64, 64, 64], DType::U8),
        [0.0, 255.0],
        RenderMode::Dvr,
        Lod::Auto { bias: 0.0 },
        0.25,
        24,
    );
}

#[test]
fn gpu_automatic_lod_across_level_changes() {
    // Levels change inside the volume along most rays.
    case(
        &Procedural::new(Kind::Mandelbulb, [48, 48, 48], DType::U8),
        [0.0, 255.0],
        RenderMode::Dvr,
        Lod::Auto { bias: 0.0 },
        1.5,
        48,
    );
}

/// Empty, then data with a hard edge between: y below 33 is 0 (EMPTY
/// bricks; the side the test camera looks from), the rest a varying
/// pattern in [100, 227].
struct HalfEmpty(SourceMeta);

impl VolumeSource for HalfEmpty {
    fn meta(&self) -> &SourceMeta {
        &self.0
    }
    fn read_region(
        &self,
        c: usize,
        z: std::ops::Range<u64>,
        y: std::ops::Range<u64>,
        x: std::ops::Range<u64>,
        out: &mut [u8],
    ) -> brickyard_store::Result<()> {
        check_region(&self.0, c, &z, &y, &x, out);
        // One voxel past a brick border (16): the first sample past the
        // last EMPTY brick already mixes in data.
        let half = 33;
        let mut i = 0;
        for zz in z {
            for yy in y.clone() {
                for xx in x.clone() {
                    out[i] = if yy < half {
                        0
                    } else {
                        100 + ((xx * 7 + yy * 3 + zz * 5) % 128) as u8
                    };
                    i += 1;
                }
            }
        }
        Ok(())
    }
}

/// Rays that cross empty bricks in one jump must land before the first
/// step past them: landing one step late skips the first sample that
/// mixes in the data behind the hard edge (checked: the image then differs
/// by 0.22).
#[test]
fn gpu_jumps_over_empty_bricks_land_on_time() {
    let src = HalfEmpty(SourceMeta::new("<half-empty>", [48, 48, 64], 1, DType::U8));
    let Some(st) = case(&src, [0.0, 255.0], RenderMode::Dvr, Lod::Fixed(0), 1.5, 64) else {
        return; // BRICKYARD_SKIP_GPU=1, reported by `test_gpu`
    };
    assert!(st.skipped_bricks > 100, "jumps: {}", st.skipped_bricks);
}

#[test]
fn device_updates_evict_and_every_view_completes_correctly() {
    // Four slices, each to completion, through a pool of 30 slots: the
    // bricks of one slice fit, those of all four do not, so the device's
    // LRU evicts (and reuses page-table blocks) between views. Each
    // complete view equals the in-core reference. The pool is tight: a
    // slice's level-0 bricks and the coarser ones standing in while they
    // load do not fit together (with the pool ordered by last use at any
    // level, view 1 stalls), so stand-ins must give way to finer bricks.
    let Some(gpu) = test_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("v.ome.zarr");
    let dims = [64, 80, 96];
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U16);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let level0 = Volume::from_store(&store, 0, 0).unwrap();
    let extent = world_extent(dims, level0.spacing);
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let levels: Vec<_> = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap().dims)
        .collect();
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [2; 3],
        max_dir_entries: 8,
        pool_bytes: 30 * (18 * 18 * 18 * 2 + 512),
        pt_cache_blocks: 16,
        request_cap: 64,
        upload_bytes_per_frame: 8 * 18 * 18 * 18 * 2,
    };
    let mut s = Session::open(&store, cfg, 8 << 20, 2).unwrap();
    assert!(
        s.vm().layout().nmax() >= 3,
        "two intermediate levels at least"
    );
    let slots = s.vm().pool_slots();
    assert!((28..=32).contains(&slots), "{slots} slots");
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut cache = DeviceCache::new(&gpu, &dvm, s.vm()).unwrap();
    let mut renderer = GpuRenderer::new(&gpu);
    let scene = Scene::new(extent, levels);
    let tf = TransferFunction::preset("soft", [0.0, 65535.0]).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut loaded = 0;
    for (v, z) in [0.15, 0.4, 0.65, 0.9, 0.15].into_iter().enumerate() {
        let mode = RenderMode::Slice {
            origin: [extent[0] / 2.0, extent[1] / 2.0, extent[2] * z],
            normal: [0.0, 0.0, 1.0],
        };
        let p = RenderParams::new(96, 80, cam, tf.clone(), mode);
        let mut done = None;
        for _ in 0..200 {
            s.begin_frame();
            let n = s.vm().frame();
            let f = renderer
                .render_with(&gpu, &dvm, s.vm(), Some(&cache), &scene, &p, Lod::Fixed(0))
                .unwrap();
            let x = update_on_device(&gpu, &mut dvm, &mut cache, &mut s, n, &f.list).unwrap();
            loaded += x.inserted;
            if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
                done = Some(f);
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        let f = done.unwrap_or_else(|| panic!("view {v} completes"));
        let want = render(&level0, &p);
        let d = f.image.max_abs_diff(&want);
        eprintln!("view {v}: max abs diff {d}, {:?}", cache.counts());
        assert!(d <= TOLERANCE, "view {v}: max abs diff {d}");
        assert!(
            f.image.coverage(0.01) > 0.05,
            "view {v}: image nearly empty"
        );
    }
    cache.end_frame(&gpu, &dvm, s.vm().frame() + 1, 0).unwrap();
    let c = cache.counts();
    assert!(
        loaded > slots,
        "{loaded} bricks loaded through {slots} slots"
    );
    assert!(
        c.bricks_unmapped > 0 && c.blocks_unmapped > 0,
        "bricks and page-table blocks were evicted: {c:?}"
    );
}

/// A 64³ u8 Mandelbulb store in `dir` (chunks of `brick`³ in shards of
/// twice that): the store, its level 0, world extent and levels.
fn mandelbulb_64(
    dir: &std::path::Path,
    brick: u64,
) -> (std::path::PathBuf, Volume, [f64; 3], Vec<[u64; 3]>) {
    let store = dir.join("v.ome.zarr");
    let dims = [64, 64, 64];
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U8);
    let o = ConvertOptions {
        brick: [brick; 3],
        shard: [2 * brick; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let level0 = Volume::from_store(&store, 0, 0).unwrap();
    let extent = world_extent(dims, level0.spacing);
    let levels = (0..)
        .map_while(|l| Volume::from_store(&store, l, 0).ok())
        .map(|v| v.dims)
        .collect();
    (store, level0, extent, levels)
}

/// A virtual memory of `brick`³ engine bricks in a 64 MiB pool.
fn vm_config(brick: u64) -> VmConfig {
    VmConfig {
        brick: [brick; 3],
        pool_bytes: 64 << 20,
        ..Default::default()
    }
}

#[test]
fn gpu_cells_are_crossed_without_changing_the_image() {
    // Cells of resident bricks that the transfer function hides (DVR), or
    // whose maximum cannot raise the ray's (MIP), are crossed in one jump:
    // fewer samples, the same complete image, with updates on the device.
    let Some(gpu) = test_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (store, level0, extent, levels) = mandelbulb_64(dir.path(), 32);
    let mut s = Session::open(&store, vm_config(32), 64 << 20, 2).unwrap();
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut cache = DeviceCache::new(&gpu, &dvm, s.vm()).unwrap();
    let mut renderer = GpuRenderer::new(&gpu);
    let mut scene = Scene::new(extent, levels);
    // No store statistics: only cells (ranges computed from the bricks as
    // they arrive) can hide anything.
    scene.ranges = None;
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    for mode in [RenderMode::Dvr, RenderMode::Mip] {
        let tf = TransferFunction::preset("hot", [0.0, 255.0]).unwrap();
        let p = RenderParams::new(96, 80, cam, tf, mode.clone());
        let mut frame = |s: &mut Session, sc: &Scene| {
            s.begin_frame();
            let n = s.vm().frame();
            let f = renderer
                .render_with(&gpu, &dvm, s.vm(), Some(&cache), sc, &p, Lod::Fixed(0))
                .unwrap();
            update_on_device(&gpu, &mut dvm, &mut cache, s, n, &f.list).unwrap();
            f
        };
        let mut done = None;
        for _ in 0..100 {
            let f = frame(&mut s, &scene);
            if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
                done = Some(f);
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        let with = done.expect("the view completes");
        scene.skip_cells = false;
        let without = frame(&mut s, &scene);
        scene.skip_cells = true;
        assert_eq!(without.stats.completeness(), 1.0);
        let d = with.image.max_abs_diff(&without.image);
        eprintln!(
            "{mode:?}: samples {} with cells ({} cells crossed), {} without; max abs diff {d}",
            with.stats.samples, with.stats.skipped_cells, without.stats.samples
        );
        assert!(
            d <= 1e-6,
            "{mode:?}: crossing cells changed the image by {d}"
        );
        assert!(with.stats.skipped_cells > 0, "{mode:?}: no cell crossed");
        assert!(
            (with.stats.samples as f64) < 0.9 * without.stats.samples as f64,
            "{mode:?}: cells saved too few samples"
        );
        let want = render(&level0, &p);
        let r = with.image.max_abs_diff(&want);
        assert!(
            r <= TOLERANCE,
            "{mode:?}: max abs diff {r} to the reference"
        );
        // The images compared are not blank.
        assert!(
            with.image.coverage(0.01) > 0.05,
            "{mode:?}: image nearly empty"
        );
    }
}

/// A device MIP ray ends once its maximum saturates the window, as on the
/// CPU: a Mandelbulb whose window ends below its maximum gives the same
/// complete image as rays that walk on (`mip_values`, which outside a
/// region only turns the early end off), with fewer samples, and the
/// reference's image.
#[test]
fn gpu_mip_rays_end_where_the_window_saturates() {
    let Some(gpu) = test_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (store, level0, extent, levels) = mandelbulb_64(dir.path(), 16);
    let mut s = Session::open(&store, vm_config(16), 64 << 20, 2).unwrap();
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut cache = DeviceCache::new(&gpu, &dvm, s.vm()).unwrap();
    let mut renderer = GpuRenderer::new(&gpu);
    let mut scene = Scene::new(extent, levels);
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 20)));
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let tf = TransferFunction::preset("hot", [0.0, 160.0]).unwrap();
    let p = RenderParams::new(96, 80, cam, tf, RenderMode::Mip);
    let mut frame = |s: &mut Session, p: &RenderParams| {
        s.begin_frame();
        let n = s.vm().frame();
        let f = renderer
            .render_with(&gpu, &dvm, s.vm(), Some(&cache), &scene, p, Lod::Fixed(0))
            .unwrap();
        update_on_device(&gpu, &mut dvm, &mut cache, s, n, &f.list).unwrap();
        f
    };
    let mut done = None;
    for _ in 0..100 {
        let f = frame(&mut s, &p);
        if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
            done = Some(f);
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    let ended = done.expect("the view completes");
    let mut walk_on = p.clone();
    walk_on.mip_values = true;
    let walked = frame(&mut s, &walk_on);
    assert_eq!(walked.stats.completeness(), 1.0);
    let d = ended.image.max_abs_diff(&walked.image);
    eprintln!(
        "samples {} ending at saturation, {} walking on; max abs diff {d}",
        ended.stats.samples, walked.stats.samples
    );
    assert!(d <= 1e-6, "ending rays early changed the image by {d}");
    assert!(
        (ended.stats.samples as f64) < 0.8 * walked.stats.samples as f64,
        "too few samples saved: {} against {}",
        ended.stats.samples,
        walked.stats.samples
    );
    let r = ended.image.max_abs_diff(&render(&level0, &p));
    assert!(r <= TOLERANCE, "max abs diff {r} to the reference");
    // Saturated and unsaturated pixels both: the check is not vacuous.
    let top = ended
        .image
        .rgba
        .iter()
        .filter(|px| px[0] >= 0.999 && px[1] >= 0.999)
        .count();
    let mid = ended
        .image
        .rgba
        .iter()
        .filter(|px| px[0] > 0.05 && px[0] < 0.95)
        .count();
    assert!(top > 100 && mid > 100, "{top} saturated, {mid} in between");
}

#[test]
fn gpu_channels_add_up_in_slices_and_mips() {
    // Two channels (a Mandelbulb and a Marschner–Lobb), each windowed and
    // tinted, added up on the device with its own update step: complete
    // images equal the in-core `render_channels` within the tolerance.
    use brickyard_render::reference::render_channels;
    let Some(gpu) = test_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (store, extent, levels) = common::two_channel_store(dir.path());
    let scene = Scene::new(extent, levels);
    let mut renderer = GpuRenderer::new(&gpu);
    for (p, level, pool) in common::two_channel_views(extent) {
        let mode = p.mode.clone();
        let vols: Vec<_> = (0..2)
            .map(|c| Volume::from_store(&store, level, c).unwrap())
            .collect();
        let cfg = VmConfig {
            brick: [16; 3],
            pool_bytes: pool,
            request_cap: 64,
            ..Default::default()
        };
        let mut s = Session::open(&store, cfg, 8 << 20, 2).unwrap();
        let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
        let mut cache = DeviceCache::new(&gpu, &dvm, s.vm()).unwrap();
        let mut done = None;
        for frame in 1..=300 {
            s.begin_frame();
            let n = s.vm().frame();
            let f = renderer
                .render_with(
                    &gpu,
                    &dvm,
                    s.vm(),
                    Some(&cache),
                    &scene,
                    &p,
                    Lod::Fixed(level),
                )
                .unwrap();
            update_on_device(&gpu, &mut dvm, &mut cache, &mut s, n, &f.list).unwrap();
            if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
                done = Some((frame, f));
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        let (frames, f) = done.expect("the view completes");
        let want = render_channels(&vols, &p);
        let d = f.image.max_abs_diff(&want);
        eprintln!("{mode:?}: {frames} frames, max abs diff {d} to render_channels");
        assert!(
            d <= TOLERANCE,
            "{mode:?}: max abs diff {d} to render_channels"
        );
        let sum = |c: usize| f.image.rgba.iter().map(|px| px[c] as f64).sum::<f64>();
        assert!(
            sum(0) > 1.0 && sum(2) > 1.0,
            "{mode:?}: a channel is missing"
        );
    }
}

/// The first frame from cold (nothing resident, nothing pinned) asks for
/// what the CPU twin asks for, brick by brick and with the same counts:
/// both go on past a brick that nothing serves, adding its steps as misses
/// of that brick at once, and ask for each coarser brick once per brick
/// crossed. (Before, the device sampled every step of such a brick, walked
/// every level and added a miss per level per step: a coarse brick's count
/// was tens of times the CPU's, and a first frame of a 1024³ volume on
/// lavapipe took ten warm frames.)
#[test]
fn a_cold_frame_asks_for_what_the_cpu_asks_for() {
    let Some(gpu) = test_gpu() else {
        return; // BRICKYARD_SKIP_GPU=1, reported by `test_gpu`
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("v.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    let src = Procedural::new(Kind::Mandelbulb, [96, 96, 96], DType::U8);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    assert!(nlev >= 3, "{nlev} levels");
    let levels: Vec<Volume> = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    let extent = world_extent([96; 3], levels[0].spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes: 96 * 96 * 96,
        pt_cache_blocks: 256,
        // The device hands back twice the cap: every brick asked for.
        request_cap: 4096,
        upload_bytes_per_frame: 1 << 20,
    };
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut renderer = GpuRenderer::new(&gpu);
    for mode in [RenderMode::Dvr, RenderMode::Mip] {
        for lod in [Lod::Fixed(0), Lod::Auto { bias: 0.0 }] {
            let mut s = Session::open(&store, cfg.clone(), 8 << 20, 2).unwrap();
            let p = RenderParams::new(96, 80, cam, tf.clone(), mode.clone());
            let (dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
            s.begin_frame();
            let f = renderer
                .render(&gpu, &dvm, s.vm(), &scene, &p, lod)
                .unwrap();
            let (_, st, reqs) = render_frame(s.vm(), &scene, &p, lod);
            let what = format!("{mode:?} {lod:?}");
            assert_eq!(st.exact, 0, "{what}: nothing is resident");
            assert_eq!(f.stats.exact, 0, "{what}: nothing is resident");
            assert_eq!(f.dropped, 0, "{what}");
            let cpu = same_requests(&reqs, &f.requests, &what);
            assert!(cpu.len() > 20, "{what}: {} bricks asked for", cpu.len());
            assert!(
                cpu.keys().any(|k| k.level > 0) && cpu.keys().any(|k| k.level == 0),
                "{what}: coarse and fine bricks"
            );
            let (sd, sc) = (f.stats.unserved as f64, st.unserved as f64);
            assert!(
                (sd - sc).abs() <= 0.01 * sc,
                "{what}: unserved samples {sd} on the device, {sc} on the CPU"
            );
        }
    }
}

/// A first frame drawn from stand-ins alone (level 0 never resident, the
/// coarse levels pinned) on the device: the stand-ins' clear cells are
/// crossed without changing a pixel, with far fewer samples, and the image
/// is the CPU twin's (which crosses them in its runs through stand-ins).
#[test]
fn gpu_crosses_the_clear_cells_of_stand_ins() {
    let Some(gpu) = test_gpu() else {
        return; // BRICKYARD_SKIP_GPU=1, reported by `test_gpu`
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let dims = [64, 64, 64];
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U16);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let levels: Vec<Volume> = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    let extent = world_extent(dims, levels[0].spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    // No store statistics: only the stand-ins' cells can hide anything.
    scene.ranges = None;
    let cfg = VmConfig {
        brick: [8; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes: 8 << 20,
        pt_cache_blocks: 256,
        request_cap: 64,
        upload_bytes_per_frame: 48 * 18 * 18 * 18 * 2,
    };
    let mut s = Session::open(&store, cfg, 8 << 20, 2).unwrap();
    let pin = s
        .pin_coarsest(4096, std::time::Duration::from_secs(60))
        .unwrap();
    assert!(
        *pin.levels.iter().min().unwrap() >= 1,
        "level 0 pinned: no stand-ins"
    );
    let (dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let tf = TransferFunction::new(
        [0.0, 65535.0],
        vec![[0.0, 0.0], [0.3, 0.0], [1.0, 0.6]],
        brickyard_core::transfer::ColorMap::Preset(brickyard_core::transfer::Preset::Hot),
    )
    .unwrap();
    let cam = Camera::fit(
        extent,
        35.0,
        25.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let p = RenderParams::new(64, 64, cam, tf, RenderMode::Dvr);
    let mut renderer = GpuRenderer::new(&gpu);
    let mut frame = |sc: &Scene| {
        s.begin_frame();
        let f = renderer
            .render(&gpu, &dvm, s.vm(), sc, &p, Lod::Fixed(0))
            .unwrap();
        let (cpu, st, _) = render_frame(s.vm(), sc, &p, Lod::Fixed(0));
        (f, cpu, st)
    };
    let (with, cpu, st) = frame(&scene);
    scene.skip_cells = false;
    let (without, _, _) = frame(&scene);
    for f in [&with, &without] {
        assert_eq!(f.stats.exact, 0, "level 0 was resident: no stand-ins");
        assert_eq!(f.stats.unserved, 0, "a sample found no stand-in");
    }
    assert!(with.image.coverage(0.01) > 0.05, "image nearly empty");
    let d = with.image.max_abs_diff(&without.image);
    let c = with.image.max_abs_diff(&cpu);
    eprintln!(
        "samples {} with cells ({} crossed), {} without, {} on the CPU ({} cells); \
         max abs diff {d}, to the CPU {c}",
        with.stats.samples,
        with.stats.skipped_cells,
        without.stats.samples,
        st.samples,
        st.skipped_cells
    );
    assert!(
        d <= 1e-6,
        "crossing stand-ins' cells changed the image by {d}"
    );
    assert!(c <= TOLERANCE, "the device differs from the CPU by {c}");
    assert_eq!(without.stats.skipped_cells, 0);
    assert!(
        with.stats.skipped_cells > 0,
        "no clear cell of a stand-in crossed"
    );
    assert!(
        (with.stats.samples as f64) < 0.9 * without.stats.samples as f64,
        "stand-ins' clear cells saved too few samples ({} → {})",
        without.stats.samples,
        with.stats.samples
    );
}
