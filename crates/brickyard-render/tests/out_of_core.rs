//! Out-of-core frames through the virtual memory, with a pool far smaller
//! than the volume, converge to the in-core reference image: DVR, MIP and
//! slices, at fixed levels; meanwhile every frame is drawn from whatever is
//! resident, and completeness rises to 100 %.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::reference::{render, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::Path;
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

/// Frames until complete; returns the final image, the number of frames and
/// the completeness of the first frame.
fn converge(
    s: &mut Session,
    scene: &Scene,
    p: &RenderParams,
    lod: Lod,
) -> (brickyard_render::image::Image, usize, f64) {
    let mut first = None;
    for frame in 1..=400 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
        first.get_or_insert(st.completeness());
        s.finish_frame(reqs.iter());
        if st.completeness() == 1.0 {
            return (img, frame, first.unwrap());
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the view never completed: {:?} {lod:?}", p.mode);
}

#[test]
fn out_of_core_frames_converge_to_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let dims = [64, 80, 96];
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U16);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let vol_bytes = (64 * 80 * 96 * 2) as u64;
    let levels: Vec<_> = (0..3)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    let spacing0 = levels[0].spacing;
    let extent = world_extent(dims, spacing0);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let tf = TransferFunction::preset("soft", [0.0, 65535.0]).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let voxel0 = scene.voxel(0);
    for (mode, level, pool_frac) in [
        (RenderMode::Dvr, 1usize, 4u64),
        (RenderMode::Mip, 1, 4),
        (
            RenderMode::Slice {
                origin: [extent[0] / 2.0, extent[1] / 2.0, extent[2] * 0.4],
                normal: [0.02, 0.01, 1.0],
            },
            0,
            2,
        ),
    ] {
        let mut p = RenderParams::new(96, 72, cam, tf.clone(), mode.clone());
        p.reference_step = Some(voxel0);
        // Pool a fraction of the volume.
        let mut s = session(&store, vol_bytes / pool_frac);
        assert!(s.vm().pool_bytes() as u64 * 2 <= vol_bytes);
        let (img, frames, first) = converge(&mut s, &scene, &p, Lod::Fixed(level));
        let want = render(&levels[level], &p);
        let diff = img.max_abs_diff(&want);
        assert!(
            diff <= 1e-5,
            "{mode:?} level {level}: max abs diff {diff} after {frames} frames"
        );
        assert!(
            frames > 1 && first < 1.0,
            "{mode:?}: the first frame cannot be complete"
        );
        assert!(img.coverage(0.01) > 0.05, "{mode:?}: image nearly empty");
        s.vm().check_invariants().unwrap();
    }
}

#[test]
fn automatic_level_of_detail_completes_and_uses_coarser_levels_far_away() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let dims = [64, 64, 64];
    let src = Procedural::new(Kind::MarschnerLobb, dims, DType::U8);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let l0 = Volume::from_store(&store, 0, 0).unwrap();
    let extent = world_extent(dims, l0.spacing);
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let levels: Vec<_> = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap().dims)
        .collect();
    let scene = Scene::new(extent, levels);
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    // A small image of the whole volume: one pixel covers several voxels.
    let cam = Camera::fit(
        extent,
        10.0,
        10.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let p = RenderParams::new(24, 24, cam, tf, RenderMode::Dvr);
    let mut s = session(&store, 64 * 64 * 64 / 4);
    let (img, _frames, _) = converge(&mut s, &scene, &p, Lod::Auto { bias: 0.0 });
    assert!(img.coverage(0.01) > 0.1);
    // Fewer bricks than level 0 has: coarser levels did the work.
    let l0_bricks = 4 * 4 * 4;
    assert!(
        s.vm().resident_bricks() < l0_bricks,
        "resident {}",
        s.vm().resident_bricks()
    );
}

#[test]
fn real_mr_volume_out_of_core_equals_the_reference() {
    let nrrd = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/mr-brain-i16.nrrd");
    assert!(
        nrrd.exists(),
        "{} is missing: this test needs the shared data folder",
        nrrd.display()
    );
    let src = brickyard_store::import::open_input(&nrrd, &Default::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("mr.ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [64; 3],
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
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let levels: Vec<_> = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap())
        .collect();
    let dims = levels[0].dims;
    let extent = world_extent(dims, levels[0].spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let (lo, hi) = levels[0].min_max();
    let vol_bytes = dims.iter().product::<u64>() * 2;
    for (mode, level, tfname) in [
        (RenderMode::Dvr, 1usize, "soft"),
        (RenderMode::Mip, 1, "linear"),
        (
            RenderMode::Slice {
                origin: [extent[0] / 2.0, extent[1] / 2.0, extent[2] * 0.5],
                normal: [0.0, 0.0, 1.0],
            },
            0,
            "linear",
        ),
    ] {
        let tf = TransferFunction::preset(tfname, [lo, hi]).unwrap();
        let cam = match &mode {
            RenderMode::Slice { origin, normal } => {
                Camera::facing_plane(*origin, *normal, extent[0] * 1.05)
            }
            _ => Camera::fit(
                extent,
                40.0,
                25.0,
                Projection::Perspective { fov_y_deg: 35.0 },
            ),
        };
        let mut p = RenderParams::new(80, 80, cam, tf, mode.clone());
        p.reference_step = Some(scene.voxel(0));
        // A slice at level 0 touches a whole layer of 256 bricks, plus the
        // coarser bricks that stand in while they load: the pool holds ~400
        // of the pyramid's 672 padded bricks. (With fewer slots than the
        // finest working set plus its stand-ins the view stalls below 100 %;
        // see docs/ARCHITECTURE.md.)
        let mut s = session(
            &store,
            if level == 0 {
                vol_bytes * 3 / 2
            } else {
                vol_bytes * 3 / 5
            },
        );
        let (img, frames, _) = converge(&mut s, &scene, &p, Lod::Fixed(level));
        let want = render(&levels[level], &p);
        let diff = img.max_abs_diff(&want);
        assert!(
            diff <= 1e-5,
            "{mode:?}: max abs diff {diff} after {frames} frames"
        );
        assert!(img.coverage(0.01) > 0.1, "{mode:?}: image nearly empty");
    }
}
