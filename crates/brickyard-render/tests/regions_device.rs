//! Sort-last regions on the device (`RenderParams::clip`, no early
//! termination, MIP raw maxima) against their CPU twin on the same resident
//! data, and an image-parallel band of rows (`GpuRenderer::rows`) against
//! the whole frame. The regions of a split also put the whole image back
//! together on the device: composited front to back (DVR) or by maximum
//! (MIP), they equal the device's own image of the whole volume.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::gpu::GpuRenderer;
use brickyard_render::reference::{RenderMode, RenderParams, Volume};
use brickyard_render::Image;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::sync::atomic::AtomicBool;

/// The device against the CPU (as in the other device tests: f32 positions
/// against f64).
const TOLERANCE: f32 = 1e-4;

/// Largest difference of any channel; NaN equals NaN (a MIP region with no
/// sample served), NaN against a number is infinitely far.
fn diff(a: &Image, b: &Image) -> f32 {
    assert_eq!((a.width, a.height), (b.width, b.height));
    a.rgba
        .iter()
        .zip(&b.rgba)
        .flat_map(|(p, q)| (0..4).map(move |i| (p[i], q[i])))
        .map(|(x, y)| match (x.is_nan(), y.is_nan()) {
            (true, true) => 0.0,
            (false, false) => (x - y).abs(),
            _ => f32::INFINITY,
        })
        .fold(0.0, f32::max)
}

/// `front` over `back`, premultiplied.
fn over(front: &Image, back: &Image) -> Image {
    let mut out = front.clone();
    for (f, b) in out.rgba.iter_mut().zip(&back.rgba) {
        let t = 1.0 - f[3];
        for c in 0..4 {
            f[c] += t * b[c];
        }
    }
    out
}

fn maximum(a: &Image, b: &Image) -> Image {
    let mut out = a.clone();
    for (p, q) in out.rgba.iter_mut().zip(&b.rgba) {
        for c in 0..4 {
            p[c] = p[c].max(q[c]);
        }
    }
    out
}

/// MIP raw maxima through the transfer function, as one process maps its
/// rays' maxima.
fn colours(raw: &Image, tf: &TransferFunction) -> Image {
    let mut img = raw.clone();
    for px in &mut img.rgba {
        *px = brickyard_render::optics::mip_color(tf, px[3] > 0.0, px[0]);
    }
    img
}

#[test]
fn device_regions_equal_the_cpu_twin_and_compose_the_whole() {
    let Some(gpu) = test_gpu() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("v.ome.zarr");
    let src = Procedural::new(Kind::Mandelbulb, [48, 64, 80], DType::U8);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let levels: Vec<Volume> = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    let extent = world_extent([48, 64, 80], levels[0].spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        // Every brick of every level fits.
        pool_bytes: 4 * 48 * 64 * 80,
        pt_cache_blocks: 256,
        request_cap: 256,
        upload_bytes_per_frame: 1 << 24,
    };
    let mut s = Session::open(&store, cfg, 8 << 20, 2).unwrap();
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut renderer = GpuRenderer::new(&gpu);
    // An oblique view, the eye on the low-x side.
    let cam = Camera::fit(
        extent,
        -65.0,
        25.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let tf = TransferFunction::preset("soft", [10.0, 230.0]).unwrap();
    // Cuts at brick borders (16 voxels), as the k-d split makes them:
    // x at 48 of 80, then y at 32 of 64 on the high-x side.
    let [ex, ey, ez] = [extent[0], extent[1], extent[2]];
    let (x_cut, y_cut) = (ex * 48.0 / 80.0, ey * 32.0 / 64.0);
    let boxes = [
        [[0.0, 0.0, 0.0], [x_cut, ey, ez]],
        [[x_cut, 0.0, 0.0], [ex, y_cut, ez]],
        [[x_cut, y_cut, 0.0], [ex, ey, ez]],
    ];
    for (mode, lod) in [
        (RenderMode::Dvr, Lod::Fixed(0)),
        (RenderMode::Mip, Lod::Fixed(0)),
        // A small image: coarser levels serve, the level changes along
        // the ray (the step grid restarts there, in every region alike).
        (RenderMode::Dvr, Lod::Auto { bias: 0.0 }),
    ] {
        let size = if matches!(lod, Lod::Fixed(_)) { 96 } else { 24 };
        let mut p = RenderParams::new(size, size * 3 / 4, cam, tf.clone(), mode.clone());
        p.reference_step = Some(scene.voxel(0));
        p.early_termination = false;
        // The whole volume, until complete (updates decided on the host).
        let mut whole = None;
        for _ in 0..200 {
            s.begin_frame();
            let f = renderer
                .render(&gpu, &dvm, s.vm(), &scene, &p, lod)
                .unwrap();
            s.finish_frame([&f.requests]);
            dvm.sync(&gpu, s.vm_mut());
            if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
                whole = Some(f.image);
                break;
            }
        }
        let whole = whole.expect("the view completes");
        assert!(whole.coverage(0.05) > 0.1, "{mode:?}: image nearly empty");
        // A band of rows: those rows as in the whole frame, the others
        // transparent.
        renderer.rows = Some((10, 40));
        s.begin_frame();
        let f = renderer
            .render(&gpu, &dvm, s.vm(), &scene, &p, lod)
            .unwrap();
        s.finish_frame([&f.requests]);
        renderer.rows = None;
        let w = p.width as usize;
        for (i, (a, b)) in f.image.rgba.iter().zip(&whole.rgba).enumerate() {
            let row = i / w;
            let want = if (10..40).contains(&row) {
                *b
            } else {
                [0.0; 4]
            };
            assert_eq!(*a, want, "{mode:?}: band, pixel {i}");
        }
        // The regions: the device against the CPU, each on its own.
        let mut parts = vec![];
        for (r, b) in boxes.iter().enumerate() {
            let mut q = p.clone();
            q.clip = Some(Box::new(*b));
            q.mip_values = mode == RenderMode::Mip;
            q.validate().unwrap();
            s.begin_frame();
            let f = renderer
                .render(&gpu, &dvm, s.vm(), &scene, &q, lod)
                .unwrap();
            s.finish_frame([&f.requests]);
            assert_eq!(f.stats.completeness(), 1.0, "{mode:?} region {r}");
            s.begin_frame();
            let (cpu, st, reqs) = render_frame(s.vm(), &scene, &q, lod);
            s.finish_frame(reqs.iter());
            assert_eq!(st.completeness(), 1.0);
            let d = match mode {
                // Raw maxima (voxel values): compared as colours, through
                // the transfer function; which rays took a sample, exactly.
                RenderMode::Mip => {
                    for (a, b) in f.image.rgba.iter().zip(&cpu.rgba) {
                        assert_eq!(a[3], b[3], "{mode:?} region {r}: a ray's samples");
                    }
                    diff(&colours(&f.image, &tf), &colours(&cpu, &tf))
                }
                _ => diff(&f.image, &cpu),
            };
            let lit = cpu.rgba.iter().filter(|p| p[3] > 0.0).count();
            eprintln!("{mode:?} {lod:?} region {r}: {lit} pixels lit; device against CPU {d}");
            assert!(lit > 0, "{mode:?} region {r}: nothing drawn");
            assert!(
                d <= TOLERANCE,
                "{mode:?} {lod:?} region {r}: device and CPU differ by {d}"
            );
            parts.push(f.image);
        }
        // Front to back from the eye (low x, then low y on the high side,
        // the eye's side of each cut).
        let eye = cam.eye;
        let x_front = eye[0] < x_cut;
        let y_front = eye[1] < y_cut;
        let high = if y_front {
            [&parts[1], &parts[2]]
        } else {
            [&parts[2], &parts[1]]
        };
        let (composed, whole) = match mode {
            RenderMode::Mip => {
                // The regions' raw maxima against the whole ray's (the
                // whole volume as one region): exactly the same samples.
                let mut q = p.clone();
                q.clip = Some(Box::new([[0.0; 3], extent]));
                q.mip_values = true;
                s.begin_frame();
                let f = renderer
                    .render(&gpu, &dvm, s.vm(), &scene, &q, lod)
                    .unwrap();
                s.finish_frame([&f.requests]);
                (maximum(&maximum(&parts[0], &parts[1]), &parts[2]), f.image)
            }
            _ => {
                let hi = over(high[0], high[1]);
                let img = if x_front {
                    over(&parts[0], &hi)
                } else {
                    over(&hi, &parts[0])
                };
                (img, whole)
            }
        };
        let d = diff(&composed, &whole);
        eprintln!("{mode:?} {lod:?}: regions composited against the whole volume {d}");
        assert!(
            d <= 1e-5,
            "{mode:?} {lod:?}: regions composited differ from the whole by {d}"
        );
    }
    // Early termination off changes a DVR on the device as on the CPU (it
    // used to be ignored there): the opaque core ends rays early.
    let mut p = RenderParams::new(64, 48, cam, tf.clone(), RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(0));
    let mut imgs = vec![];
    for early in [true, false] {
        p.early_termination = early;
        s.begin_frame();
        let f = renderer
            .render(&gpu, &dvm, s.vm(), &scene, &p, Lod::Fixed(0))
            .unwrap();
        s.finish_frame([&f.requests]);
        s.begin_frame();
        let (cpu, _, reqs) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
        s.finish_frame(reqs.iter());
        let d = diff(&f.image, &cpu);
        assert!(d <= TOLERANCE, "early termination {early}: {d}");
        imgs.push(f.image);
    }
    assert!(
        diff(&imgs[0], &imgs[1]) > 1e-4,
        "early termination made no difference (the test view is too thin)"
    );
}
