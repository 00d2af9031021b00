//! Gradient shading in DVR against the in-core oracle's own rule: in core
//! at fixed levels and with automatic level of detail, and out of core with
//! small bricks and a pool far smaller than the volume (a normal taken
//! across a brick border from the wrong data would show as a seam, a
//! difference from the oracle along the borders).

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, Shading, TransferFunction};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::gpu::GpuRenderer;
use brickyard_render::image::Image;
use brickyard_render::reference::{render, render_auto_lod, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::Path;
use std::sync::atomic::AtomicBool;

fn session(store: &Path, pool_bytes: u64, brick: u64) -> Session {
    let cfg = VmConfig {
        brick: [brick; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes,
        pt_cache_blocks: 256,
        request_cap: 64,
        upload_bytes_per_frame: 48 * 18 * 18 * 18 * 2,
    };
    Session::open(store, cfg, 8 << 20, 2).unwrap()
}

/// Frames until complete; the final image and the frames drawn.
fn converge(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> (Image, usize) {
    let mut last = String::new();
    for frame in 1..=600 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
        s.finish_frame(reqs.iter());
        if st.completeness() == 1.0 {
            return (img, frame);
        }
        last = format!(
            "completeness {:.4}, {} of {} slots resident",
            st.completeness(),
            s.vm().resident_bricks(),
            s.vm().pool_slots()
        );
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the view never completed: {last}");
}

struct Fixture {
    _dir: tempfile::TempDir,
    store: std::path::PathBuf,
    levels: Vec<Volume>,
    scene: Scene,
    params: RenderParams,
    bytes: u64,
}

fn fixture(kind: Kind, brick: u64) -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let dims = [48, 64, 56];
    let src = Procedural::new(kind, dims, DType::U8);
    let o = ConvertOptions {
        brick: [brick; 3],
        shard: [brick * 2; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let levels: Vec<Volume> = (0..)
        .map_while(|l| Volume::from_store(&store, l, 0).ok())
        .collect();
    let extent = world_extent(dims, levels[0].spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let mut tf = TransferFunction::preset("viridis", [0.0, 255.0]).unwrap();
    tf.shading = Some(Shading {
        ambient: 0.2,
        diffuse: 0.7,
        specular: 0.4,
        shininess: 16.0,
    });
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut params = RenderParams::new(64, 48, cam, tf, RenderMode::Dvr);
    params.reference_step = Some(scene.voxel(0));
    Fixture {
        _dir: dir,
        store,
        levels,
        scene,
        params,
        bytes: dims.iter().product(),
    }
}

#[test]
fn shaded_dvr_equals_the_oracle() {
    let f = fixture(Kind::MarschnerLobb, 16);
    let mut unshaded = f.params.clone();
    unshaded.tf.shading = None;
    for level in [0usize, 1] {
        let mut s = session(&f.store, 64 << 20, 16);
        let (img, _) = converge(&mut s, &f.scene, &f.params, Lod::Fixed(level));
        let want = render(&f.levels[level], &f.params);
        let d = img.max_abs_diff(&want);
        assert!(d <= 1e-5, "level {level}: max abs diff {d}");
        assert!(want.coverage(0.01) > 0.2);
        // Shading changes the image.
        let plain = render(&f.levels[level], &unshaded);
        assert!(want.max_abs_diff(&plain) > 0.05, "shading did nothing");
    }
    // Automatic level of detail: each sample's normal at its own level.
    let mut s = session(&f.store, 64 << 20, 16);
    let (img, _) = converge(&mut s, &f.scene, &f.params, Lod::Auto { bias: 0.5 });
    let want = render_auto_lod(&f.levels, &f.params, 0.5);
    let d = img.max_abs_diff(&want);
    assert!(d <= 1e-5, "automatic LOD: max abs diff {d}");
}

/// A Mandelbulb (an object in empty space) in 8³ bricks (a border every 8
/// voxels), a denser transfer function (rays
/// end sooner: a working set the pool holds) and a pool of a quarter of
/// the volume's bricks: the complete shaded frame equals the oracle, which has no
/// bricks. Normals next to a border read the next brick (resident by the
/// time the frame is complete), never a stand-in or a clamp at the brick.
#[test]
fn no_seams_at_brick_borders_with_a_small_pool() {
    let mut f = fixture(Kind::Mandelbulb, 8);
    // (Not 0.9: two samples of 0.9 reach 0.99, the threshold, exactly.)
    f.params.tf.opacity = vec![[0.0, 0.0], [0.45, 0.0], [0.6, 0.85], [1.0, 0.85]];
    let mut s = session(&f.store, f.bytes, 8);
    // Bricks the function hides are crossed without loading them.
    f.scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    // Padded bricks of 10³: slots for about half of the 336 bricks of
    // level 0 alone.
    assert!(s.vm().pool_slots() * 3 < 336 * 2, "{}", s.vm().pool_slots());
    let (img, frames) = converge(&mut s, &f.scene, &f.params, Lod::Fixed(0));
    assert!(frames > 1);
    let want = render(&f.levels[0], &f.params);
    let d = img.max_abs_diff(&want);
    assert!(d <= 1e-5, "max abs diff {d} after {frames} frames");
    s.vm().check_invariants().unwrap();
}

/// Frames on the device (updates decided on the host, mirrored) until
/// complete; the final image. `None`: no adapter and BRICKYARD_SKIP_GPU=1.
fn converge_device(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> Option<Image> {
    let gpu = test_gpu()?;
    let mut renderer = GpuRenderer::new(&gpu);
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    for _ in 1..=600 {
        s.begin_frame();
        let f = renderer.render(&gpu, &dvm, s.vm(), scene, p, lod).unwrap();
        s.finish_frame([&f.requests]);
        dvm.sync(&gpu, s.vm_mut());
        if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
            return Some(f.image);
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the device view never completed");
}

/// The device's shading (`shading.wgsl`) against the oracle and the CPU
/// twin: in core at two levels, and with 8³ bricks and a pool of a quarter
/// of the volume (seams would show along the borders). Positions are f32
/// on the device: within 1e-4, the device tolerance of `tests/gpu.rs`.
#[test]
fn device_shading_equals_the_oracle_without_seams() {
    let f = fixture(Kind::MarschnerLobb, 16);
    let mut unshaded = f.params.clone();
    unshaded.tf.shading = None;
    for level in [0usize, 1] {
        let mut s = session(&f.store, 64 << 20, 16);
        let Some(img) = converge_device(&mut s, &f.scene, &f.params, Lod::Fixed(level)) else {
            return;
        };
        let want = render(&f.levels[level], &f.params);
        let d = img.max_abs_diff(&want);
        eprintln!("device, level {level}: max abs diff to the oracle {d}");
        assert!(d <= 1e-4, "device, level {level}: max abs diff {d}");
        let plain = render(&f.levels[level], &unshaded);
        assert!(
            img.max_abs_diff(&plain) > 0.05,
            "device shading did nothing"
        );
    }
    let mut f = fixture(Kind::Mandelbulb, 8);
    f.params.tf.opacity = vec![[0.0, 0.0], [0.45, 0.0], [0.6, 0.85], [1.0, 0.85]];
    let mut s = session(&f.store, f.bytes, 8);
    f.scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    assert!(s.vm().pool_slots() * 3 < 336 * 2, "{}", s.vm().pool_slots());
    let img = converge_device(&mut s, &f.scene, &f.params, Lod::Fixed(0)).unwrap();
    let want = render(&f.levels[0], &f.params);
    assert!(want.coverage(0.01) > 0.05, "image nearly empty");
    let d = img.max_abs_diff(&want);
    eprintln!("device, small pool: max abs diff to the oracle {d}");
    assert!(d <= 1e-4, "device, small pool: max abs diff {d}");
    // The CPU twin on the same resident data.
    s.begin_frame();
    let (cpu, st, reqs) = render_frame(s.vm(), &f.scene, &f.params, Lod::Fixed(0));
    s.finish_frame(reqs.iter());
    if st.completeness() == 1.0 {
        let d = img.max_abs_diff(&cpu);
        assert!(d <= 1e-4, "device and CPU differ by {d}");
    }
}
