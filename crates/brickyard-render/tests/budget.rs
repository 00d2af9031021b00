//! A pool smaller than the view's working set costs detail, never
//! completeness: with the coarsest levels pinned and the LOD budget
//! coarsening the view, frames through pools from far below to above the
//! working set complete within a bounded number of frames, leave no pixel
//! empty where the full-detail image has data, and equal the in-core
//! reference rendered at the bias that was reached.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_render::budget::{Decision, FrameSignals, LodBudget, Stop};
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::image::Image;
use brickyard_render::reference::{render_auto_lod, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

const BRICK: u64 = 16;

fn session(store: &Path, pool_bricks: u64, dtype: DType) -> Session {
    let slot = (BRICK + 2).pow(3) * dtype.size() as u64 + 64 * 8;
    let cfg = VmConfig {
        brick: [BRICK; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes: pool_bricks * slot,
        pt_cache_blocks: 512,
        request_cap: 4096,
        upload_bytes_per_frame: pool_bricks * slot,
    };
    let mut s = Session::open(store, cfg, 256 << 20, 2).unwrap();
    s.set_batch(Some(Duration::from_secs(30)));
    s
}

fn read_levels(store: &Path) -> Vec<Volume> {
    (0..)
        .map_while(|l| Volume::from_store(store, l, 0).ok())
        .collect()
}

/// The CLI's batch loop, written out: frames until the budget says stop.
/// Returns the image, the frames taken, the final bias and why it stopped.
fn drive(s: &mut Session, scene: &Scene, p: &RenderParams) -> (Image, usize, f64, Stop) {
    let mut b = LodBudget::new(0.0, scene.levels.len(), false);
    for frame in 1..=60 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, b.apply(Lod::Auto { bias: 0.0 }, 9));
        let fs = s.finish_frame(reqs.iter());
        let sig =
            FrameSignals::of_frame(s, &fs, st.completeness() >= 1.0, Some(fs.frame.exact_slots));
        // Every sample found data at some level.
        assert_eq!(st.unserved, 0, "frame {frame}: samples with no data at all");
        let used = b.bias;
        if let Decision::Stop(why) = b.update(&sig) {
            return (img, frame, used, why);
        }
    }
    panic!("no stop within 60 frames (bias {})", b.bias);
}

/// Pixels with content in `full` that are empty in `img`.
fn holes(full: &Image, img: &Image) -> usize {
    full.rgba
        .iter()
        .zip(&img.rgba)
        .filter(|(a, b)| a[3] > 0.05 && b[3] <= 1e-4)
        .count()
}

fn check_pools(store: &Path, dtype: DType, tf_window: [f32; 2], pools: &[u64], size: u32) {
    let levels = read_levels(store);
    let extent = world_extent(levels[0].dims, levels[0].spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let tf = TransferFunction::preset("soft", tf_window).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let mut p = RenderParams::new(size, size, cam, tf, RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(0));
    let mut full = None;
    let mut biases = vec![];
    for &pool in pools {
        let mut s = session(store, pool, dtype);
        scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
        let pin = s.pin_coarsest(512, Duration::from_secs(30)).unwrap();
        assert!(pin.bricks + pin.flagged > 0);
        let (img, frames, bias, why) = drive(&mut s, &scene, &p);
        assert_eq!(why, Stop::Complete, "pool {pool}: {why:?}");
        assert!(frames <= 30, "pool {pool}: {frames} frames");
        // The image is the in-core reference at the bias reached.
        let want = render_auto_lod(&levels, &p, bias);
        let d = img.max_abs_diff(&want);
        assert!(d < 1e-4, "pool {pool} bricks, bias {bias}: differs by {d}");
        let full = full.get_or_insert_with(|| {
            assert_eq!(bias, 0.0, "the largest pool must hold the full working set");
            img.clone()
        });
        assert!(
            full.rgba.iter().filter(|p| p[3] > 0.05).count() > full.rgba.len() / 20,
            "the full-detail image has too little content to test holes"
        );
        // No pixel the in-core renderer draws at this bias is empty here.
        assert_eq!(holes(&want, &img), 0, "pool {pool} bricks, bias {bias}");
        // Against full detail, coarser data may only thin out features
        // finer than its voxels at silhouettes (a hole would be a brick's
        // whole footprint).
        // (Or no more than the in-core renderer loses at that bias: a
        // scan of few thick slices thins out more at its coarse levels.)
        let content = full.rgba.iter().filter(|p| p[3] > 0.05).count();
        let lost = holes(full, &img);
        let lost_in_core = holes(full, &want);
        assert!(
            lost * 50 <= content || lost <= lost_in_core,
            "pool {pool} bricks, bias {bias}: {lost} of {content} pixels with content are empty \
             ({lost_in_core} in core)"
        );
        s.vm().check_invariants().unwrap();
        biases.push(bias);
    }
    // The small pools did cost detail.
    assert!(
        biases.last() > biases.first(),
        "biases {biases:?}: the smallest pool should coarsen the view"
    );
}

#[test]
fn pools_from_far_below_to_above_the_working_set_complete_on_a_generated_volume() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let o = ConvertOptions {
        brick: [32; 3],
        shard: [64; 3],
        ..Default::default()
    };
    let src = Procedural::new(Kind::Mandelbulb, [128; 3], DType::U16);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    // Largest first (its image is the full-detail one): 1024 slots hold
    // every level-0 brick (512 + coarser); 16 is barely more than the
    // pinned coarsest levels.
    check_pools(
        &store,
        DType::U16,
        [0.0, 65535.0],
        &[1024, 160, 48, 16],
        128,
    );
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

#[test]
fn pools_from_far_below_to_above_the_working_set_complete_on_a_real_scan() {
    let input = shared_data("mr-brain-i16.nrrd");
    let src = brickyard_store::import::open_input(&input, &Default::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("mr.ome.zarr");
    let o = ConvertOptions {
        brick: [32; 3],
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
    let levels = read_levels(&store);
    let (lo, hi) = levels[0].min_max();
    let bricks0: u64 = levels[0].dims.iter().map(|d| d.div_ceil(BRICK)).product();
    check_pools(
        &store,
        DType::I16,
        [lo + 0.1 * (hi - lo), hi],
        &[2 * bricks0, bricks0 / 6, bricks0 / 30, 20],
        160,
    );
}
