//! Several views in one frame: super-slices for multi-view displays and
//! off-axis camera views (stereo, N-view DVR), on the CPU and the device,
//! against the in-core oracle, plain single-view renders and a hand-built
//! volume whose answer is worked out by hand.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{add, scale, world_extent, Camera, Projection};
use brickyard_core::views::Views;
use brickyard_core::{DType, TransferFunction};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::gpu::GpuRenderer;
use brickyard_render::image::Image;
use brickyard_render::reference::{render, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

fn session(store: &Path, pool_bytes: u64) -> Session {
    let cfg = VmConfig {
        brick: [16; 3],
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

/// Frames until complete; the image and the request lists of every frame.
fn converge(
    s: &mut Session,
    scene: &Scene,
    p: &RenderParams,
    lod: Lod,
) -> (Image, Vec<Vec<brickyard_cache::brick::BrickKey>>) {
    let mut lists = vec![];
    let mut last = String::new();
    for _ in 1..=600 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
        last = format!(
            "completeness {:.4}, {} of {} slots resident",
            st.completeness(),
            s.vm().resident_bricks(),
            s.vm().pool_slots()
        );
        let report = s.finish_frame(reqs.iter());
        lists.push(report.frame.requests);
        if st.completeness() == 1.0 && st.samples > 0 {
            return (img, lists);
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the view never completed: {last}");
}

/// Frames on the device until complete, and the request lists.
fn converge_device(
    s: &mut Session,
    scene: &Scene,
    p: &RenderParams,
    lod: Lod,
) -> Option<(Image, Vec<Vec<brickyard_cache::brick::BrickKey>>)> {
    let gpu = test_gpu()?;
    let mut renderer = GpuRenderer::new(&gpu);
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut lists = vec![];
    for _ in 1..=600 {
        s.begin_frame();
        let f = renderer.render(&gpu, &dvm, s.vm(), scene, p, lod).unwrap();
        s.finish_frame([&f.requests]);
        lists.push(f.list.clone());
        dvm.sync(&gpu, s.vm_mut());
        if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
            return Some((f.image, lists));
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the device view never completed");
}

fn no_brick_twice(lists: &[Vec<brickyard_cache::brick::BrickKey>]) {
    assert!(lists.iter().any(|l| !l.is_empty()), "nothing was requested");
    for l in lists {
        let set: HashSet<_> = l.iter().collect();
        assert_eq!(set.len(), l.len(), "a brick requested twice in one frame");
    }
}

struct Fixture {
    _dir: tempfile::TempDir,
    store: PathBuf,
    level0: Volume,
    scene: Scene,
}

fn fixture() -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let dims = [48, 64, 56];
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U8);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let levels: Vec<Volume> = (0..)
        .map_while(|l| Volume::from_store(&store, l, 0).ok())
        .collect();
    let extent = world_extent(dims, levels[0].spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    Fixture {
        _dir: dir,
        store,
        level0: levels.into_iter().next().unwrap(),
        scene,
    }
}

/// An 8-view super-slice (the thesis's display: Δx = 4 pixels, Δz = 1
/// slice) and a 5-view one with a fractional parallax, through an oblique
/// plane seen in perspective: the CPU (rows of samples shared between
/// views) and the device (each pixel samples its own slices) equal the
/// oracle, which samples every slice of every pixel of every view; views
/// differ from each other; every frame's request list names a brick once.
#[test]
fn super_slices_equal_the_oracle_on_both_back_ends() {
    let f = fixture();
    let e = f.scene.extent;
    let centre = scale(e, 0.5);
    for (count, parallax, normal, perspective) in [
        (8u32, 4.0, [0.0, 0.0, 1.0], false),
        (5, 1.5, [0.2, 0.3, 1.0], true),
    ] {
        let mut cam = Camera::facing_plane(centre, normal, e[1]);
        if perspective {
            cam.projection = Projection::Perspective { fov_y_deg: 40.0 };
            cam.eye = add(
                centre,
                scale(brickyard_core::camera::sub(cam.eye, centre), 1.6),
            );
        }
        let tf = TransferFunction {
            opacity: vec![[0.0, 0.0], [0.3, 0.0], [1.0, 0.6]],
            ..TransferFunction::preset("viridis", [0.0, 255.0]).unwrap()
        };
        let vw = 40;
        let mut p = RenderParams::new(
            vw * count,
            36,
            cam,
            tf,
            RenderMode::Slice {
                origin: centre,
                normal,
            },
        );
        p.views = Some(Views {
            count,
            separation: 0.0,
            parallax,
            spacing: f.scene.voxel(0) * 1.5,
            alone: None,
        });
        let want = render(&f.level0, &p);
        assert!(
            want.coverage(0.05) > 0.2,
            "the oracle's image is nearly empty"
        );
        let views: Vec<Image> = (0..count).map(|v| crop(&want, v * vw, vw)).collect();
        assert!(
            views[0].max_abs_diff(&views[count as usize - 1]) > 0.05,
            "views alike"
        );

        let mut s = session(&f.store, 64 << 20);
        let (img, lists) = converge(&mut s, &f.scene, &p, Lod::Fixed(0));
        let d = img.max_abs_diff(&want);
        assert!(d <= 1e-5, "{count} views, CPU: max abs diff {d}");
        no_brick_twice(&lists);

        let mut s = session(&f.store, 64 << 20);
        let Some((img, lists)) = converge_device(&mut s, &f.scene, &p, Lod::Fixed(0)) else {
            continue;
        };
        let d = img.max_abs_diff(&want);
        eprintln!("{count} views, device: max abs diff to the oracle {d}");
        assert!(d <= 1e-4, "{count} views, device: max abs diff {d}");
        no_brick_twice(&lists);
    }
}

/// Columns `x0 … x0 + w − 1` of `img`.
fn crop(img: &Image, x0: u32, w: u32) -> Image {
    let mut out = Image::new(w, img.height);
    for y in 0..img.height {
        for x in 0..w {
            out.set(x, y, img.get(x0 + x, y));
        }
    }
    out
}

/// Off-axis views are cameras moved along the baseline whose image is
/// shifted: with the eye separation chosen so that the frustum shift is a
/// whole number of pixels, view `v` is exactly a plain render of the
/// camera moved by its offset (eye and target), read that many pixels
/// further on. Checked for the oracle, the CPU and the device, stereo and
/// four views, DVR and MIP.
#[test]
fn each_view_is_a_plain_render_of_its_own_camera() {
    let f = fixture();
    let e = f.scene.extent;
    let tf = TransferFunction {
        opacity: vec![[0.0, 0.0], [0.3, 0.0], [1.0, 0.5]],
        ..TransferFunction::preset("hot", [0.0, 255.0]).unwrap()
    };
    let cam = Camera::fit(e, 25.0, 15.0, Projection::Perspective { fov_y_deg: 40.0 });
    let (vw, h) = (48u32, 40u32);
    let half_h = (20f64).to_radians().tan();
    let distance = brickyard_core::camera::length(brickyard_core::camera::sub(cam.target, cam.eye));
    // One pixel of frustum shift per unit of view offset.
    let separation = 2.0 * 2.0 * half_h * distance / h as f64;
    let right = cam.basis().right;
    for (count, mode) in [(2u32, RenderMode::Dvr), (4, RenderMode::Mip)] {
        let mut p = RenderParams::new(vw * count, h, cam, tf.clone(), mode.clone());
        p.views = Some(Views {
            count,
            separation,
            parallax: 0.0,
            spacing: 0.0,
            alone: None,
        });
        let want = render(&f.level0, &p);
        assert!(
            want.coverage(0.05) > 0.1,
            "coverage {}",
            want.coverage(0.05)
        );
        let margin = 8;
        for v in 0..count {
            let off = v as f64 - (count as f64 - 1.0) / 2.0;
            let b = off * separation;
            // The frustum shift in pixels: 2·off (a half-pixel for odd
            // offsets of an even count: then step by whole pixels twice).
            let shift = 2.0 * off;
            let mut plain_cam = cam;
            plain_cam.eye = add(cam.eye, scale(right, b));
            plain_cam.target = add(cam.target, scale(right, b));
            let plain = RenderParams::new(vw + 2 * margin, h, plain_cam, tf.clone(), mode.clone());
            let wide = render(&f.level0, &plain);
            // View pixel x sees what the wide image shows at
            // x + margin − shift.
            let x0 = (margin as f64 - shift) as u32;
            let d = crop(&want, v * vw, vw).max_abs_diff(&crop(&wide, x0, vw));
            assert!(
                d <= 1e-5,
                "{count} views, view {v}: max abs diff {d} to its own camera"
            );
        }
        let mut s = session(&f.store, 64 << 20);
        let (img, lists) = converge(&mut s, &f.scene, &p, Lod::Fixed(0));
        let d = img.max_abs_diff(&want);
        assert!(d <= 1e-5, "{count} views, CPU: max abs diff {d}");
        no_brick_twice(&lists);
        let mut s = session(&f.store, 64 << 20);
        if let Some((img, _)) = converge_device(&mut s, &f.scene, &p, Lod::Fixed(0)) {
            let d = img.max_abs_diff(&want);
            eprintln!("{count} views, device: max abs diff to the oracle {d}");
            assert!(d <= 1e-4, "{count} views, device: max abs diff {d}");
        }
    }
}

/// Two slabs, red below z = 8 and blue above, each of opacity 0.5, and a
/// three-slice super-slice seen from below (camera towards +z) with the
/// reference slice in the blue slab: slice 2 (nearest the camera) lies in
/// the red slab, slices 1 (reference) and 0 in the blue. The thesis's
/// order puts the reference first, then slice 0 behind it, then slice 2:
/// blue 0.5 + 0.25, red 0.125, alpha 0.875. Depth order (red in front)
/// would give red 0.5.
#[test]
fn super_slices_composite_in_the_thesis_order() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("slabs.raw");
    let n = 16usize;
    let bytes: Vec<u8> = (0..n * n * n)
        .map(|i| if i / (n * n) < 8 { 100 } else { 200 })
        .collect();
    std::fs::write(&raw, &bytes).unwrap();
    let opts: brickyard_store::import::raw::RawOptions =
        serde_json::from_str(r#"{"dims":[16,16,16],"dtype":"u8"}"#).unwrap();
    let src = brickyard_store::import::raw::open(&raw, &opts).unwrap();
    let store = dir.path().join("slabs.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [16; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let level0 = Volume::from_store(&store, 0, 0).unwrap();
    let extent = level0.extent();
    let scene = Scene::new(extent, vec![level0.dims]);
    let tf = TransferFunction {
        window: [0.0, 255.0],
        opacity: vec![[0.0, 0.0], [0.2, 0.0], [0.25, 0.5], [1.0, 0.5]],
        colormap: brickyard_core::ColorMap::Points(vec![
            [0.0, 1.0, 0.0, 0.0],
            [0.5, 1.0, 0.0, 0.0],
            [0.7, 0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0, 1.0],
        ]),
        shading: None,
    };
    let vz = extent[2] / 16.0;
    // The reference slice at z = 11.5 voxels (blue); slices 4 voxels apart.
    let origin = [extent[0] / 2.0, extent[1] / 2.0, 11.5 * vz];
    let normal = [0.0, 0.0, 1.0];
    let cam = Camera::facing_plane(origin, normal, extent[1]);
    assert!(cam.basis().forward[2] > 0.0, "the camera looks towards +z");
    let mut p = RenderParams::new(3 * 16, 16, cam, tf, RenderMode::Slice { origin, normal });
    p.views = Some(Views {
        count: 3,
        separation: 0.0,
        parallax: 1.0,
        spacing: 4.0 * vz,
        alone: None,
    });
    let expect = [0.125f32, 0.0, 0.75, 0.875];
    let check = |img: &Image, who: &str| {
        for v in 0..3 {
            let px = img.get(v * 16 + 8, 8);
            for c in 0..4 {
                assert!(
                    (px[c] - expect[c]).abs() < 1e-5,
                    "{who}, view {v}: {px:?}, expected {expect:?}"
                );
            }
        }
    };
    check(&render(&level0, &p), "oracle");
    let mut s = session(&store, 64 << 20);
    check(&converge(&mut s, &scene, &p, Lod::Fixed(0)).0, "CPU");
    let mut s = session(&store, 64 << 20);
    if let Some((img, _)) = converge_device(&mut s, &scene, &p, Lod::Fixed(0)) {
        check(&img, "device");
    }
}

/// An N-view frame from cold asks for the bricks of all views in one list,
/// each once, and with a pool too small for the whole volume still
/// completes, equal to the oracle.
#[test]
fn views_share_one_request_list_under_a_small_pool() {
    let f = fixture();
    let e = f.scene.extent;
    let cam = Camera::fit(e, 40.0, 20.0, Projection::Perspective { fov_y_deg: 40.0 });
    let tf = TransferFunction {
        opacity: vec![[0.0, 0.0], [0.5, 0.0], [0.7, 0.85], [1.0, 0.85]],
        ..TransferFunction::preset("viridis", [0.0, 255.0]).unwrap()
    };
    let mut p = RenderParams::new(2 * 40, 32, cam, tf, RenderMode::Dvr);
    p.views = Some(Views {
        count: 2,
        separation: e[0] * 0.06,
        parallax: 0.0,
        spacing: 0.0,
        alone: None,
    });
    let want = render(&f.level0, &p);
    // 48·64·56 voxels in 16³ bricks: 48 bricks of level 0 (and 8 of
    // the coarser levels); slots for about 44 (padded 18³ bytes each).
    let mut s = session(&f.store, 44 * 18 * 18 * 18);
    assert!(s.vm().pool_slots() < 48, "{}", s.vm().pool_slots());
    let mut scene = f.scene.clone();
    // Bricks the function hides are crossed without loading them.
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    let (img, lists) = converge(&mut s, &scene, &p, Lod::Fixed(0));
    no_brick_twice(&lists);
    let d = img.max_abs_diff(&want);
    assert!(d <= 1e-5, "max abs diff {d}");
}

/// A view drawn alone (`Views::alone`) is that view of the whole image,
/// on the CPU (its own layers only) and the device.
#[test]
fn a_view_drawn_alone_equals_its_part_of_the_whole() {
    let f = fixture();
    let e = f.scene.extent;
    let centre = scale(e, 0.5);
    let normal = [0.0, 0.0, 1.0];
    let cam = Camera::facing_plane(centre, normal, e[1]);
    let tf = TransferFunction {
        opacity: vec![[0.0, 0.0], [0.3, 0.0], [1.0, 0.6]],
        ..TransferFunction::preset("viridis", [0.0, 255.0]).unwrap()
    };
    let all = Views {
        count: 6,
        separation: 0.0,
        parallax: 2.0,
        spacing: f.scene.voxel(0),
        alone: None,
    };
    let mode = RenderMode::Slice {
        origin: centre,
        normal,
    };
    let mut p = RenderParams::new(6 * 30, 28, cam, tf, mode);
    p.views = Some(all);
    let mut s = session(&f.store, 64 << 20);
    let (whole, _) = converge(&mut s, &f.scene, &p, Lod::Fixed(0));
    for v in [0u32, 4] {
        let mut one = p.clone();
        one.width = 30;
        one.views = Some(Views {
            alone: Some(v),
            ..all
        });
        let part = crop(&whole, v * 30, 30);
        assert!(part.coverage(0.05) > 0.2);
        let (img, _) = converge(&mut s, &f.scene, &one, Lod::Fixed(0));
        assert_eq!(img.max_abs_diff(&part), 0.0, "CPU, view {v} alone");
        let want = render(&f.level0, &one);
        assert!(want.max_abs_diff(&part) <= 1e-5, "oracle, view {v} alone");
        let mut sd = session(&f.store, 64 << 20);
        if let Some((img, _)) = converge_device(&mut sd, &f.scene, &one, Lod::Fixed(0)) {
            let d = img.max_abs_diff(&part);
            assert!(d <= 1e-4, "device, view {v} alone: {d}");
        }
    }
}
