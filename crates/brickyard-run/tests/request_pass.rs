//! A batch render's request pass: drawn at the image's size over
//! `pass_divisor`, at the level of detail the full image asks for, it finds
//! nearly all of the working set, and the view it leads to is the complete
//! view a fully resident pool gives.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_render::budget::LodBudget;
use brickyard_render::cpu::{Lod, Scene};
use brickyard_render::reference::{RenderMode, RenderParams};
use brickyard_run::backend::{Backend, GpuUpdate};
use brickyard_run::frames::{drive, pass_divisor, DriveOptions};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::VolumeSource;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

#[test]
fn the_request_pass_finds_the_working_set_at_a_fraction_of_the_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("m.ome.zarr");
    let o = ConvertOptions {
        brick: [32; 3],
        shard: [64; 3],
        ..Default::default()
    };
    let dims = [256u64; 3];
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U8);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let slot = 18u64.pow(3) + 64 * 8;
    // The pool holds the view's working set: it completes at the detail
    // asked. Levels 2 and coarser are pinned (an eighth of the pool).
    let cfg = VmConfig {
        brick: [16; 3],
        apron: 1,
        pool_bytes: 2048 * slot,
        request_cap: 4096,
        upload_bytes_per_frame: 2048 * slot,
        ..Default::default()
    };
    let mut s = Session::open(&store, cfg, 256 << 20, 2).unwrap();
    s.set_batch(Some(Duration::from_secs(30)));
    s.pin_coarsest(512, Duration::from_secs(30)).unwrap();
    let levels: Vec<_> = (0..)
        .map_while(|l| brickyard_store::import::zarr::open(&store, l).ok())
        .map(|a| a.meta().dims)
        .collect();
    assert!(levels.len() >= 3, "{levels:?}");
    let extent = world_extent(dims, [1.0; 3]);
    let mut scene = Scene::new(extent, levels.clone());
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 20)));
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 35.0 },
    );
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    // 1100² pixels: a pass at a quarter of the width and height. At this
    // size a pixel spans less than a voxel of level 0 everywhere, where
    // the automatic rule holds at its floor: a bias of 1 draws level 1
    // throughout. The pass's pixels span more than a voxel: a pass whose
    // bias was lowered by the divisor's log2 (as it once was) asked for
    // level 0, bricks the image never draws, and with a pool too small for
    // them a render went on until its frames ran out.
    let (w, h) = (1100, 1100);
    let div = pass_divisor(w, h);
    assert_eq!(div, 4);
    let p = RenderParams::new(w, h, cam, tf, RenderMode::Dvr);
    let lod = Lod::Auto { bias: 1.0 };
    let mut backend = Backend::choose("cpu", GpuUpdate::Host, &mut s, 1).unwrap();
    let mut budget = LodBudget::new(1.0, levels.len(), false);
    let opt = DriveOptions {
        batch: true,
        max_frames: 50,
        lod,
        band: None,
    };
    // Per frame: a pass?, its image size, the bricks it asked for (by level).
    let mut seen: Vec<(bool, (u32, u32), Vec<usize>)> = vec![];
    let out = drive(&mut backend, &mut s, &scene, &p, opt, &mut budget, |fi| {
        let mut by_level = vec![0; 8];
        for k in &fi.f.session.frame.requests {
            by_level[k.level as usize] += 1;
        }
        seen.push((fi.pass, (fi.f.image.width, fi.f.image.height), by_level));
    })
    .unwrap();
    assert_eq!(out.completeness, 1.0);
    assert!(seen[0].0, "the run starts with a request pass");
    for (pass, size, _) in &seen {
        let want = if *pass { (w / div, h / div) } else { (w, h) };
        assert_eq!(*size, want, "pass {pass}");
    }
    let sum = |pass: bool| -> Vec<usize> {
        let mut t = vec![0; 8];
        for (p, _, by) in &seen {
            if *p == pass {
                for (l, n) in by.iter().enumerate() {
                    t[l] += n;
                }
            }
        }
        t
    };
    let (by_pass, by_full) = (sum(true), sum(false));
    let (n_pass, n_full): (usize, usize) = (by_pass.iter().sum(), by_full.iter().sum());
    // The pass asked for the level the image draws, and only for it (a
    // pass at another level of detail asks for other bricks), and the
    // full image found few it had missed.
    assert_eq!(by_pass[0] + by_full[0], 0, "{by_pass:?} {by_full:?}");
    assert!(by_pass[1] > 50, "{by_pass:?}");
    assert!(n_pass > 50, "{by_pass:?}");
    assert!(
        n_full * 10 <= n_pass,
        "the full image asked for {by_full:?} after the pass's {by_pass:?}"
    );
    // The view is the one a pool holding its working set draws.
    let again = backend
        .frame(&mut s, &scene, &p, budget.apply(lod, levels.len()))
        .unwrap();
    assert_eq!(again.stats.completeness(), 1.0);
    assert_eq!(again.session.frame.requests.len(), 0);
    let differ = out
        .image
        .rgba
        .iter()
        .zip(&again.image.rgba)
        .filter(|(a, b)| a != b)
        .count();
    assert_eq!(differ, 0, "pixels differ from a frame of the resident view");
    let shown = out.image.rgba.iter().filter(|px| px[3] > 0.0).count();
    assert!(shown > (w * h / 20) as usize, "{shown} pixels show");
}
