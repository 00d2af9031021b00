//! Out-of-core rendering under realistic conditions: a slow store (every
//! read delayed) never stalls the frame loop, a paused loader leaves frames
//! coming and unchanged, and real scans (NIfTI, TIFF) rendered through a
//! pool far smaller than the volume equal the in-core reference, on the CPU
//! and on the device.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::gpu::GpuRenderer;
use brickyard_render::image::Image;
use brickyard_render::reference::{render, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

/// Engine bricks of 16³ (apron 1), `request_cap` requests and up to
/// `upload_bricks` padded bricks written per frame, two loader threads.
fn session(
    store: &Path,
    dtype: DType,
    pool_bytes: u64,
    request_cap: usize,
    upload_bricks: u64,
) -> Session {
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes,
        pt_cache_blocks: 256,
        request_cap,
        upload_bytes_per_frame: upload_bricks * 18 * 18 * 18 * dtype.size() as u64,
    };
    Session::open(store, cfg, 64 << 20, 2).unwrap()
}

/// Every level of a store, whole, for the reference.
fn read_levels(store: &Path) -> Vec<Volume> {
    let n = (0..)
        .take_while(|&l| Volume::from_store(store, l, 0).is_ok())
        .count();
    (0..n)
        .map(|l| Volume::from_store(store, l, 0).unwrap())
        .collect()
}

fn scene_of(levels: &[Volume]) -> Scene {
    let extent = world_extent(levels[0].dims, levels[0].spacing);
    Scene::new(extent, levels.iter().map(|v| v.dims).collect())
}

/// One frame: begin, render, finish. Returns the image and its completeness.
fn frame(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> (Image, f64) {
    s.begin_frame();
    let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
    s.finish_frame(reqs.iter());
    (img, st.completeness())
}

/// Frames (without pauses) until complete; returns the final image and the
/// number of frames.
fn converge(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> (Image, usize) {
    let start = Instant::now();
    let mut frames = 0;
    while start.elapsed() < Duration::from_secs(60) {
        let (img, c) = frame(s, scene, p, lod);
        frames += 1;
        if c == 1.0 {
            return (img, frames);
        }
    }
    panic!(
        "{:?} {lod:?}: the view did not complete within 60 s ({frames} frames)",
        p.mode
    );
}

fn mandelbulb_store(dir: &Path, n: u64) -> PathBuf {
    let store = dir.join("m.ome.zarr");
    let src = Procedural::new(Kind::Mandelbulb, [n; 3], DType::U16);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    store
}

#[test]
fn frames_keep_coming_while_io_is_slow() {
    let dir = tempfile::tempdir().unwrap();
    // 128³: level 1 (the one rendered) has 64 bricks of 16³, so with two
    // loader threads the view takes many delayed reads to complete.
    let store = mandelbulb_store(dir.path(), 128);
    let levels = read_levels(&store);
    let scene = scene_of(&levels);
    let extent = scene.extent;
    let vol_bytes = 128u64.pow(3) * 2;
    let tf = TransferFunction::preset("soft", [0.0, 65535.0]).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let level = 1;
    let mut p = RenderParams::new(64, 64, cam, tf, RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(level));
    let lod = Lod::Fixed(level);
    let want = render(&levels[level], &p);

    // Slow store: every read takes 100 ms more (about 65 reads on two
    // threads: more than 3 s in all, against frames of a few ms).
    let delay = Duration::from_millis(100);
    let mut s = session(&store, DType::U16, vol_bytes / 4, 64, 48);
    assert!(s.vm().pool_bytes() as u64 * 2 <= vol_bytes);
    s.loader().set_read_delay(delay);
    let start = Instant::now();
    let mut history: Vec<f64> = Vec::new();
    let mut slowest = Duration::ZERO;
    let img = loop {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the view did not complete within 60 s: {} frames, completeness {:?}",
            history.len(),
            history.last()
        );
        let t = Instant::now();
        let (img, c) = frame(&mut s, &scene, &p, lod);
        let took = t.elapsed();
        slowest = slowest.max(took);
        // The frame loop never waits for the loader: one frame costs far
        // less than the reads of the bricks it is missing (the bound leaves
        // room for a busy machine).
        assert!(
            took < delay * 4,
            "frame {} took {took:?} with completeness {c}",
            history.len()
        );
        if let Some(&prev) = history.last() {
            assert!(
                c >= prev - 1e-3,
                "completeness fell from {prev} to {c} at frame {}",
                history.len()
            );
        }
        history.push(c);
        if c == 1.0 {
            break img;
        }
    };
    let loaded = s.loader().stats();
    assert!(
        loaded.bricks_loaded - loaded.bricks_empty - loaded.bricks_constant >= 8,
        "too few reads to exercise the delay: {loaded:?}"
    );
    assert!(
        history.len() >= 10,
        "only {} frames before completion: {history:?}",
        history.len()
    );
    assert!(history[0] < 1.0);
    let diff = img.max_abs_diff(&want);
    assert!(
        diff <= 1e-5,
        "max abs diff {diff} after {} frames",
        history.len()
    );
    assert!(img.coverage(0.01) > 0.05, "image nearly empty");
    s.vm().check_invariants().unwrap();
    // Once complete, the view stays complete and the image stops changing.
    for _ in 0..5 {
        let (again, c) = frame(&mut s, &scene, &p, lod);
        assert_eq!(c, 1.0, "completeness fell after the view completed");
        assert_eq!(again.max_abs_diff(&img), 0.0, "a complete view changed");
    }
    let largest_drop = history
        .windows(2)
        .map(|w| w[0] - w[1])
        .fold(0.0f64, f64::max);
    eprintln!(
        "slow store: {} frames in {:?}, slowest frame {slowest:?}, largest completeness drop {largest_drop}, {loaded:?}",
        history.len(),
        start.elapsed()
    );

    // Paused loader, deterministic: nothing arrives, frames keep coming and
    // stay the same.
    let mut s = session(&store, DType::U16, vol_bytes / 4, 64, 48);
    s.loader().set_paused(true);
    let (first_img, first) = frame(&mut s, &scene, &p, lod);
    assert!(first < 1.0);
    for i in 0..20 {
        let (img, c) = frame(&mut s, &scene, &p, lod);
        assert_eq!(c, first, "frame {i} while paused");
        assert_eq!(img.max_abs_diff(&first_img), 0.0, "frame {i} while paused");
    }
    assert_eq!(s.vm().resident_bricks(), 0);
    assert!(s.loader().pending() > 0);

    // Paused half-way: once the loads in flight have landed, the view
    // freezes where it is. The pause follows the loader's first brick
    // closely (a poll, not a frame: on a busy machine a frame can wait
    // behind other work in the thread pool for longer than the whole view
    // takes to load).
    s.loader().set_read_delay(delay);
    s.loader().set_paused(false);
    let start = Instant::now();
    while s.loader().bricks_loaded() == 0 {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "no brick arrived within 60 s after resuming"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    s.loader().set_paused(true);
    while s.loader().in_flight() > 0 {
        assert!(start.elapsed() < Duration::from_secs(60));
        std::thread::sleep(Duration::from_millis(5));
    }
    // Two frames take in what arrived (within the upload budget).
    frame(&mut s, &scene, &p, lod);
    let (frozen_img, frozen) = frame(&mut s, &scene, &p, lod);
    // Frozen part-way: more than the paused start, not complete.
    eprintln!("paused half-way: completeness {first} while paused from the start, {frozen} frozen");
    assert!(frozen > first && frozen < 1.0, "frozen at {frozen}");
    let resident = s.vm().resident_bricks();
    for i in 0..20 {
        let (img, c) = frame(&mut s, &scene, &p, lod);
        assert_eq!(c, frozen, "frame {i} while paused half-way");
        assert_eq!(img.max_abs_diff(&frozen_img), 0.0);
    }
    assert_eq!(s.vm().resident_bricks(), resident);
    s.loader().set_paused(false);
    let (img, frames) = converge(&mut s, &scene, &p, lod);
    let diff = img.max_abs_diff(&want);
    assert!(
        diff <= 1e-5,
        "after pausing: max abs diff {diff} after {frames} frames"
    );
    s.vm().check_invariants().unwrap();
}

fn shared_data(name: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(name);
    assert!(
        path.exists(),
        "{} is missing: this test needs the shared data folder",
        path.display()
    );
    path
}

/// Convert `input` and render DVR and MIP at level 1 and an oblique slice
/// at level 0 through pools of `pools.0` / `pools.1` of the volume's bytes;
/// each must equal the reference within 1e-5 on the CPU and 1e-4 on the
/// device (f32 positions).
///
/// A slice at level 0 needs its whole layer of level-0 bricks at once; the
/// coarser bricks standing in while they load give way to them when the
/// pool is full (docs/ARCHITECTURE.md), so the pool only has to hold the
/// layer.
fn real_volume_equals_the_reference(
    input: &Path,
    spacing: Option<[f64; 3]>,
    store_brick: u64,
    size: u32,
    pools: (f64, f64),
) {
    let t0 = Instant::now();
    let src = brickyard_store::import::open_input(input, &Default::default()).unwrap();
    let dtype = src.meta().dtype;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("real.ome.zarr");
    let o = ConvertOptions {
        brick: [store_brick; 3],
        shard: [64; 3],
        spacing,
        ..Default::default()
    };
    convert(
        src.as_ref(),
        &store,
        &o,
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    let levels = read_levels(&store);
    assert!(levels.len() >= 3, "{} levels", levels.len());
    let scene = scene_of(&levels);
    let extent = scene.extent;
    let dims = levels[0].dims;
    let vol_bytes = dims.iter().product::<u64>() * dtype.size() as u64;
    let (lo, hi) = levels[0].min_max();
    let t_convert = t0.elapsed();
    let gpu = brickyard_gpu::context::test_gpu();
    let slice = RenderMode::Slice {
        origin: [extent[0] * 0.45, extent[1] * 0.55, extent[2] * 0.5],
        normal: [0.25, -0.2, 1.0],
    };
    for (mode, level, tfname) in [
        (RenderMode::Dvr, 1usize, "soft"),
        (RenderMode::Mip, 1, "linear"),
        (slice, 0, "linear"),
    ] {
        let t = Instant::now();
        let tf = TransferFunction::preset(tfname, [lo, hi]).unwrap();
        let cam = match &mode {
            RenderMode::Slice { origin, normal } => {
                Camera::facing_plane(*origin, *normal, extent[0].max(extent[1]) * 1.1)
            }
            _ => Camera::fit(
                extent,
                40.0,
                25.0,
                Projection::Perspective { fov_y_deg: 35.0 },
            ),
        };
        let mut p = RenderParams::new(size, size, cam, tf, mode.clone());
        p.reference_step = Some(scene.voxel(level));
        let frac = if level == 0 { pools.1 } else { pools.0 };
        let mut s = session(&store, dtype, (vol_bytes as f64 * frac) as u64, 256, 256);
        if level == 0 {
            assert!((s.vm().pool_bytes() as u64) < vol_bytes);
        } else {
            assert!(s.vm().pool_bytes() as u64 * 2 <= vol_bytes);
        }
        let (img, frames) = converge(&mut s, &scene, &p, Lod::Fixed(level));
        let want = render(&levels[level], &p);
        let diff = img.max_abs_diff(&want);
        assert!(
            diff <= 1e-5,
            "{}: {mode:?} level {level}: max abs diff {diff} after {frames} frames",
            input.display()
        );
        assert!(img.coverage(0.01) > 0.1, "{mode:?}: image nearly empty");
        s.vm().check_invariants().unwrap();
        if let Some(gpu) = &gpu {
            // The same view on the device, through a new pool of the same size.
            let mut s = session(&store, dtype, (vol_bytes as f64 * frac) as u64, 256, 256);
            let (mut dvm, _) = DeviceVm::new(gpu, s.vm_mut()).unwrap();
            let mut r = GpuRenderer::new(gpu);
            let start = Instant::now();
            let img = loop {
                s.begin_frame();
                let f = r
                    .render(gpu, &dvm, s.vm(), &scene, &p, Lod::Fixed(level))
                    .unwrap();
                s.finish_frame([&f.requests]);
                dvm.sync(gpu, s.vm_mut());
                if f.stats.completeness() == 1.0 {
                    break f.image;
                }
                assert!(
                    start.elapsed() < Duration::from_secs(60),
                    "{mode:?}: device view incomplete"
                );
            };
            let diff = img.max_abs_diff(&want);
            eprintln!(
                "{}: {mode:?} level {level} on the device: max abs diff {diff}",
                input.display()
            );
            assert!(
                diff <= 1e-4,
                "{}: {mode:?} level {level} on the device: max abs diff {diff}",
                input.display()
            );
            s.vm().check_invariants().unwrap();
        }
        eprintln!(
            "{}: {mode:?} level {level}: {frames} frames, {} of {} slots resident, {:?}",
            input.display(),
            s.vm().resident_bricks(),
            s.vm().pool_slots(),
            t.elapsed()
        );
    }
    eprintln!(
        "{}: dims {dims:?}, {} levels, convert + read {t_convert:?}, total {:?}",
        input.display(),
        levels.len(),
        t0.elapsed()
    );
}

#[test]
fn nifti_volume_out_of_core_equals_the_reference() {
    // 301 × 370 × 316 uint8, 0.5 mm isotropic. A quarter of the volume is
    // 1509 padded bricks of 18³, which the pool's slot grid rounds down to
    // 1024; DVR needs ~560 of them, MIP ~890, the oblique slice ~640.
    let input = shared_data("colin27-t1-0.5mm.nii.gz");
    real_volume_equals_the_reference(&input, None, 32, 80, (0.25, 0.25));
}

#[test]
fn tiff_volume_out_of_core_equals_the_reference() {
    // 256 × 256 × 60 uint16 without spacing: give it an anisotropic one
    // (z 4× coarser), so the pyramid halves x and y before z. Level 1
    // (60 × 128 × 128) is a quarter of the volume and MIP needs all of it
    // (half the volume gives 337 slots); so does the oblique slice at
    // level 0, whose stand-ins give way.
    let input = shared_data("nuclei-confocal-u16.tif");
    real_volume_equals_the_reference(&input, Some([1.0, 0.25, 0.25]), 16, 80, (0.5, 0.5));
}
