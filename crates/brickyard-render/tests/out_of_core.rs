//! Out-of-core frames through the virtual memory, with a pool far smaller
//! than the volume, converge to the in-core reference image: DVR, MIP and
//! slices, at fixed levels; meanwhile every frame is drawn from whatever is
//! resident, and completeness rises to 100 %.

mod common;
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, TransferFunction};
use brickyard_render::cpu::{render_frame, FrameStats, Lod, Scene};
use brickyard_render::reference::{render, RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

fn session(store: &Path, pool_bytes: u64) -> Session {
    session_with(store, pool_bytes, 16)
}

fn session_with(store: &Path, pool_bytes: u64, brick: u64) -> Session {
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

/// A generated volume converted to a store `name` in `dir` (16³ bricks).
fn generated(
    dir: &Path,
    name: &str,
    kind: Kind,
    dims: [u64; 3],
    dtype: DType,
    shard: u64,
) -> std::path::PathBuf {
    let store = dir.join(name);
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [shard; 3],
        ..Default::default()
    };
    let src = Procedural::new(kind, dims, dtype);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    store
}

/// Every level of channel 0 of a store, whole.
fn pyramid(store: &Path) -> Vec<Volume> {
    (0..)
        .map_while(|l| Volume::from_store(store, l, 0).ok())
        .collect()
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
    let mut last = String::new();
    for frame in 1..=400 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
        first.get_or_insert(st.completeness());
        let fs = s.finish_frame(reqs.iter());
        if st.completeness() == 1.0 {
            return (img, frame, first.unwrap());
        }
        last = format!(
            "completeness {:.4}, {} of {} slots resident, {} requests, {} inserted, {} deferred, {} evicted",
            st.completeness(),
            s.vm().resident_bricks(),
            s.vm().pool_slots(),
            fs.frame.requests.len(),
            fs.insert.inserted,
            fs.insert.deferred,
            fs.insert.evicted_bricks
        );
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!(
        "the view never completed: {:?} {lod:?}; last frame: {last}",
        p.mode
    );
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

/// The level `Lod::Auto { bias: 0 }` gives a sample at distance `t` from
/// the eye (the rule of `reference::render_auto_lod`).
fn auto_level(p: &RenderParams, voxel0: f64, levels: usize, t: f64) -> usize {
    let l = (p.camera.pixel_footprint(t, p.height) / voxel0).log2();
    if l.is_finite() && l > 0.0 {
        (l.floor() as usize).min(levels - 1)
    } else {
        0
    }
}

/// The smallest distance from the eye to brick `b` (`[z, y, x]`, `edge`
/// voxels) of level `l`.
fn brick_distance(scene: &Scene, eye: [f64; 3], l: usize, b: [u32; 3], edge: u64) -> f64 {
    let dims = scene.levels[l];
    let mut d2 = 0.0;
    for a in 0..3 {
        // World axis 2 - a; a voxel of level l is extent / dims wide.
        let w = scene.extent[2 - a] / dims[a] as f64;
        let lo = (b[a] as u64 * edge) as f64 * w;
        let hi = ((b[a] as u64 + 1) * edge).min(dims[a]) as f64 * w;
        let e = eye[2 - a];
        let d = if e < lo {
            lo - e
        } else if e > hi {
            e - hi
        } else {
            0.0
        };
        d2 += d * d;
    }
    d2.sqrt()
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
    // A small image of the whole volume: one pixel covers several voxels,
    // so the near half is drawn at level 1 and the far half at level 2.
    let cam = Camera::fit(
        extent,
        10.0,
        10.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let p = RenderParams::new(24, 24, cam, tf, RenderMode::Dvr);
    let lod = Lod::Auto { bias: 0.0 };
    let mut s = session(&store, 64 * 64 * 64 / 4);
    // Frames until complete, keeping every brick asked for.
    let mut requested = std::collections::BTreeSet::new();
    let mut done = None;
    for _ in 0..400 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), &scene, &p, lod);
        let fs = s.finish_frame(reqs.iter());
        requested.extend(
            fs.frame
                .requests
                .iter()
                .map(|k| (k.level as usize, k.brick)),
        );
        if st.completeness() == 1.0 && st.samples > 0 {
            done = Some(img);
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let img = done.expect("the view completes");
    assert!(img.coverage(0.01) > 0.1, "image nearly empty");
    // Every brick asked for is of the level the rule gives somewhere in it
    // or coarser (a level-l voxel of margin: the trilinear base of a
    // sample near a face lies in the neighbouring brick).
    let voxel0 = scene.voxel(0);
    let edge = 16;
    let finest_in = |l: usize, b: [u32; 3]| {
        let margin = scene.voxel(l);
        let d = brick_distance(&scene, cam.eye, l, b, edge);
        auto_level(&p, voxel0, nlev, (d - margin).max(0.0))
    };
    assert_eq!(nlev, 3, "levels 64³, 32³, 16³");
    for &(l, b) in &requested {
        assert!(
            l >= finest_in(l, b),
            "level {l} brick {b:?} asked for, but the rule gives level {} at best there",
            finest_in(l, b)
        );
    }
    let asked = |l: usize| requested.iter().filter(|r| r.0 == l).count();
    // Near: level 1 (no level-0 brick at all, the pixels cover more than
    // two voxels everywhere); far: level 2.
    assert_eq!(asked(0), 0, "level 0 asked for: {requested:?}");
    assert!(asked(1) > 0 && asked(2) > 0, "{requested:?}");
    // The back half of level 1 lies where the rule gives level 2: those
    // bricks exist (the test would prove nothing otherwise) and were not
    // asked for.
    let far: Vec<[u32; 3]> = (0..8u32)
        .map(|i| [i / 4, i / 2 % 2, i % 2])
        .filter(|&b| finest_in(1, b) >= 2)
        .collect();
    eprintln!(
        "bricks asked for: {requested:?}; level-1 bricks where the rule gives level 2: {far:?}"
    );
    assert!(
        !far.is_empty() && far.len() < 8,
        "far level-1 bricks: {far:?}"
    );
    assert!(asked(1) + far.len() <= 8, "{requested:?}");
    // And level 0 is not resident either.
    for b in (0..64u32).map(|i| [i / 16, i / 4 % 4, i % 4]) {
        assert!(
            !s.vm()
                .is_resident(brickyard_cache::brick::BrickKey::new(0, 0, b)),
            "level-0 brick {b:?} resident"
        );
    }
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
        // A slice at level 0 touches a whole layer of 256 bricks: the pool
        // (~280 slots of the pyramid's 672 padded bricks) holds them, not
        // them and the coarser bricks standing in while they load; the
        // stand-ins give way (docs/ARCHITECTURE.md).
        let mut s = session(
            &store,
            if level == 0 {
                vol_bytes
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

/// Frames until complete with the given scene; returns the image, the
/// bricks the loader produced and the statistics of one more frame.
fn converge_counting(
    store: &Path,
    pool: u64,
    scene: &Scene,
    p: &RenderParams,
    lod: Lod,
) -> (brickyard_render::image::Image, u64, FrameStats) {
    // Engine bricks of 8 inside store bricks of 16: most padded bricks lie
    // inside one store brick, so their ranges are as tight as the
    // statistics.
    let mut s = session_with(store, pool, 8);
    let (img, _, _) = converge(&mut s, scene, p, lod);
    s.begin_frame();
    let (_, st, _) = render_frame(s.vm(), scene, p, lod);
    (img, s.loader().bricks_loaded(), st)
}

/// A 64³ u16 Mandelbulb store in `dir`, its levels, a scene that samples
/// every step (no ranges, no cells) and one that skips (brick ranges and
/// clear cells), a transfer function hiding values below 30 % of the range
/// and a camera on it.
fn skipping_setup(dir: &Path) -> (PathBuf, Vec<Volume>, Scene, Scene, TransferFunction, Camera) {
    let dims = [64, 64, 64];
    let store = generated(dir, "m.ome.zarr", Kind::Mandelbulb, dims, DType::U16, 32);
    let levels = pyramid(&store);
    let extent = world_extent(dims, levels[0].spacing);
    let mut plain = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let mut skipping = plain.clone();
    plain.skip_cells = false;
    skipping.ranges = Some(std::sync::Arc::new(
        session_with(&store, 1 << 20, 8)
            .loader()
            .brick_ranges(1 << 20),
    ));
    assert!(skipping.ranges.as_ref().unwrap().level(0).is_some());
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
    (store, levels, plain, skipping, tf, cam)
}

#[test]
fn empty_space_skipping_changes_no_pixel_and_loads_less() {
    let dir = tempfile::tempdir().unwrap();
    let (store, levels, mut plain, mut skipping, tf, cam) = skipping_setup(dir.path());
    // The walk's own skipping is counted here: rays walk from the volume's
    // face (entry depths, which start rays past most of it, are compared
    // with the walk in `tests/lanes.rs`).
    plain.entry_depths = false;
    skipping.entry_depths = false;
    // Level 0 whole (64 padded bricks) fits; the saving is in what is loaded.
    let vol_bytes = 64 * 64 * 64 * 2 * 2;
    for mode in [RenderMode::Dvr, RenderMode::Mip] {
        let mut p = RenderParams::new(64, 64, cam, tf.clone(), mode.clone());
        p.reference_step = Some(plain.voxel(0));
        let (a, loaded_a, st_a) = converge_counting(&store, vol_bytes, &plain, &p, Lod::Fixed(0));
        let (b, loaded_b, st_b) =
            converge_counting(&store, vol_bytes, &skipping, &p, Lod::Fixed(0));
        let (skipped_a, skipped_b) = (st_a.skipped_bricks, st_b.skipped_bricks);
        assert_eq!(a.max_abs_diff(&b), 0.0, "{mode:?}: skipping changed pixels");
        assert!(b.coverage(0.01) > 0.05, "{mode:?}: image nearly empty");
        let want = render(&levels[0], &p);
        assert!(b.max_abs_diff(&want) <= 1e-5, "{mode:?}");
        assert!(skipped_b > 0, "{mode:?}: nothing skipped");
        // (A MIP crosses whole blocks of bricks in one landing, counted
        // once.)
        assert!(
            skipped_b >= skipped_a || mode == RenderMode::Mip,
            "{mode:?}: ranges skip more ({skipped_a} → {skipped_b})"
        );
        if mode == RenderMode::Dvr {
            assert_eq!(st_a.skipped_cells, 0);
            assert!(st_b.skipped_cells > 0, "no transparent cell crossed");
            assert!(
                st_b.samples < st_a.samples,
                "cells save samples ({} → {})",
                st_a.samples,
                st_b.samples
            );
            assert!(
                loaded_b < loaded_a,
                "{mode:?}: transparent bricks are not loaded ({loaded_a} → {loaded_b})"
            );
        } else {
            // MIP hides nothing by the transfer function: bricks are
            // crossed by the ray's maximum so far, which a frame with
            // stand-ins or rays that end at saturation may set otherwise
            // than the complete one. A crossed brick is not marked, so in
            // this pool (level 0 and little else) it may be evicted and
            // loaded again later; the counts depend on the loader's
            // timing, within a few per cent.
            assert!(
                loaded_b as f64 <= 1.05 * loaded_a as f64,
                "{mode:?}: {loaded_a} → {loaded_b}"
            );
        }
    }
}

/// A first frame drawn from stand-ins (only the coarse levels resident):
/// the clear cells and hidden bricks of the stand-ins are crossed without
/// sampling, and the image is exactly the one sampling every step gives.
#[test]
fn stand_ins_hide_empty_space_without_changing_a_pixel() {
    let dir = tempfile::tempdir().unwrap();
    let (store, levels, plain, skipping, tf, cam) = skipping_setup(dir.path());
    assert!(levels.len() >= 3);
    let mut p = RenderParams::new(64, 64, cam, tf, RenderMode::Dvr);
    p.reference_step = Some(plain.voxel(0));
    let first = |scene: &Scene| {
        let mut s = session_with(&store, 8 << 20, 8);
        let pin = s
            .pin_coarsest(4096, std::time::Duration::from_secs(60))
            .unwrap();
        // Level 0 is never pinned: every sample is a stand-in's.
        s.begin_frame();
        let (img, st, _) = render_frame(s.vm(), scene, &p, Lod::Fixed(0));
        (img, st, pin)
    };
    let (a, st_a, _) = first(&plain);
    let (b, st_b, _) = first(&skipping);
    assert_eq!(st_a.exact, 0, "level 0 was resident: no stand-ins");
    assert!(st_a.samples > st_a.unserved, "nothing served by stand-ins");
    assert!(a.coverage(0.01) > 0.05, "image nearly empty");
    assert_eq!(
        a.max_abs_diff(&b),
        0.0,
        "crossing hidden stand-ins changed pixels"
    );
    assert_eq!(st_a.skipped_cells, 0);
    assert!(
        st_b.skipped_cells > 0,
        "no clear cell of a stand-in crossed"
    );
    assert!(
        st_b.samples < st_a.samples,
        "stand-ins' clear cells save samples ({} → {})",
        st_a.samples,
        st_b.samples
    );
}

/// A first frame drawn from stand-ins alone (level 0 not resident, the
/// finest pinned level resident whole) is the reference renderer's image
/// of that level sampled at the view's steps (level 0's), with and
/// without the stand-ins' clear cells crossed: what the walk samples from
/// a stand-in, by the sample or along a run through its brick, is that
/// level's value at each step.
///
/// The same for a MIP, whose runs through stand-ins also cross the cells
/// that cannot raise the ray's maximum.
#[test]
fn a_frame_of_stand_ins_is_the_reference_image_of_their_level() {
    let dir = tempfile::tempdir().unwrap();
    let (store, levels, plain, skipping, tf, cam) = skipping_setup(dir.path());
    let mut samples = vec![];
    for (mode, scene) in [
        (RenderMode::Dvr, &plain),
        (RenderMode::Dvr, &skipping),
        (RenderMode::Mip, &plain),
        (RenderMode::Mip, &skipping),
    ] {
        let mut p = RenderParams::new(64, 64, cam, tf.clone(), mode.clone());
        p.reference_step = Some(plain.voxel(0));
        let mut s = session_with(&store, 8 << 20, 8);
        let pin = s
            .pin_coarsest(4096, std::time::Duration::from_secs(60))
            .unwrap();
        let finest = *pin.levels.iter().min().unwrap();
        assert!(finest >= 1, "level 0 pinned");
        s.begin_frame();
        let (img, st, _) = render_frame(s.vm(), scene, &p, Lod::Fixed(0));
        assert_eq!(st.exact, 0, "level 0 was resident: no stand-ins");
        assert_eq!(st.unserved, 0, "a sample found no stand-in");
        assert!(img.coverage(0.01) > 0.05, "image nearly empty");
        // The reference at level 0's step: samples per voxel of the
        // stand-ins' level scaled by its voxel size.
        let mut q = p.clone();
        q.samples_per_voxel *= levels[finest].voxel_size() / levels[0].voxel_size();
        let want = render(&levels[finest], &q);
        let diff = img.max_abs_diff(&want);
        assert!(
            diff <= 1e-5,
            "{mode:?}, skip cells {}: stand-ins of level {finest} differ from its reference by {diff}",
            scene.skip_cells
        );
        samples.push(st.samples);
    }
    // The MIP's runs through stand-ins cross their cells that cannot raise
    // the maximum (14 % of the samples here; 6 % when the runs are lost).
    assert!(
        (samples[3] as f64) < 0.9 * samples[2] as f64,
        "MIP samples with cells crossed {}, without {}",
        samples[3],
        samples[2]
    );
}

#[test]
fn several_channels_add_up_in_slices_and_mips() {
    use brickyard_render::reference::render_channels;
    let dir = tempfile::tempdir().unwrap();
    // Two channels, channel-major: a Mandelbulb and a Marschner–Lobb.
    let (store, extent, levels) = common::two_channel_store(dir.path());
    let mut scene = Scene::new(extent, levels);
    // And a MIP at level 0 whose transfer function (unused with channels)
    // ends below channel 0's window: each channel's rays end where its own
    // window saturates, and cross blocks of bricks by its own maxima.
    let mut views = common::two_channel_views(extent);
    let mut mip0 = views[1].0.clone();
    mip0.tf = TransferFunction::preset("linear", [0.0, 100.0]).unwrap();
    views.push((mip0, 0, 2 * 40 * 48 * 64 * 4));
    for (p, level, pool) in views {
        let mode = p.mode.clone();
        let vols: Vec<_> = (0..2)
            .map(|c| Volume::from_store(&store, level, c).unwrap())
            .collect();
        for with_ranges in [false, true] {
            let mut s = session(&store, pool);
            scene.ranges =
                with_ranges.then(|| std::sync::Arc::new(s.loader().brick_ranges(1 << 20)));
            let (img, frames, _) = converge(&mut s, &scene, &p, Lod::Fixed(level));
            let want = render_channels(&vols, &p);
            let diff = img.max_abs_diff(&want);
            assert!(
                diff <= 1e-5,
                "{mode:?} ranges {with_ranges}: diff {diff} after {frames} frames"
            );
            // Both channels show: red from channel 0, blue from channel 1.
            let sum = |c: usize| img.rgba.iter().map(|px| px[c] as f64).sum::<f64>();
            assert!(
                sum(0) > 1.0 && sum(2) > 1.0,
                "{mode:?}: a channel is missing"
            );
        }
    }
    // More channels than a MIP adds up are refused with a clear error.
    let mut p = RenderParams::new(
        8,
        8,
        Camera::fit(
            extent,
            0.0,
            0.0,
            Projection::Perspective { fov_y_deg: 40.0 },
        ),
        TransferFunction::preset("linear", [0.0, 255.0]).unwrap(),
        RenderMode::Mip,
    );
    p.channels = vec![common::two_channel_styles()[0].clone(); 17];
    let e = p.validate().unwrap_err().to_string();
    assert!(e.contains("channels") && e.contains("16"), "{e}");
}

#[test]
fn a_view_that_fits_completes_even_when_its_stand_ins_do_not() {
    // A slice through one layer of level-0 bricks: 64 bricks, plus 22
    // coarser bricks that stand in while they load. The pool holds 72:
    // enough for the view, not for the view and its stand-ins at once.
    let dir = tempfile::tempdir().unwrap();
    let dims = [32, 128, 128];
    let store = generated(
        dir.path(),
        "ml.ome.zarr",
        Kind::MarschnerLobb,
        dims,
        DType::U16,
        64,
    );
    let levels = pyramid(&store);
    let l0 = &levels[0];
    let extent = world_extent(dims, l0.spacing);
    let scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let mode = RenderMode::Slice {
        origin: [extent[0] / 2.0, extent[1] / 2.0, extent[2] * 0.25],
        normal: [0.0, 0.0, 1.0],
    };
    let cam = match &mode {
        RenderMode::Slice { origin, normal } => Camera::facing_plane(*origin, *normal, extent[0]),
        _ => unreachable!(),
    };
    let tf = TransferFunction::preset("linear", [0.0, 65535.0]).unwrap();
    let p = RenderParams::new(96, 96, cam, tf, mode);
    // A slot: the padded u16 brick and the ranges of its 2³ cells.
    let slot_bytes = 18 * 18 * 18 * 2 + 8 * 8;
    let mut s = session(&store, 72 * slot_bytes);
    assert_eq!(s.vm().pool_slots(), 72);
    let (img, frames, _) = converge(&mut s, &scene, &p, Lod::Fixed(0));
    let diff = img.max_abs_diff(&render(l0, &p));
    assert!(diff <= 1e-5, "diff {diff} after {frames} frames");
    // Not blank: the slice fills the view, and its grey levels vary.
    assert!(img.coverage(0.99) > 0.5, "slice not drawn");
    let (lo, hi) = img.rgba.iter().fold((f32::MAX, f32::MIN), |(a, b), px| {
        (a.min(px[0]), b.max(px[0]))
    });
    assert!(hi - lo > 0.1, "flat slice: {lo}..{hi}");
    s.vm().check_invariants().unwrap();
}

/// Automatic LOD where the level changes inside the volume along most rays
/// equals the plain in-core model of it (`render_auto_lod`): the sample at
/// a level change is step 0 of the new level's grid, and the fixed-point
/// runs must treat it so.
#[test]
fn automatic_level_of_detail_across_level_changes_equals_the_plain_model() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [48, 48, 48];
    let store = generated(
        dir.path(),
        "m.ome.zarr",
        Kind::Mandelbulb,
        dims,
        DType::U8,
        32,
    );
    let levels = pyramid(&store);
    let extent = world_extent(dims, levels[0].spacing);
    let mut scene = Scene::new(extent, levels.iter().map(|v| v.dims).collect());
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut p = RenderParams::new(48, 38, cam, tf, RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(0));
    let mut s = session(&store, 1 << 20);
    scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    let (img, _, _) = converge(&mut s, &scene, &p, Lod::Auto { bias: 0.0 });
    let want = brickyard_render::reference::render_auto_lod(&levels, &p, 0.0);
    let d = img.max_abs_diff(&want);
    assert!(d <= 1e-5, "max abs diff {d}");
    assert!(img.coverage(0.01) > 0.05, "image nearly empty");
    // The premise: the level does change inside the volume along most of
    // the rays that cross it.
    let voxel0 = scene.voxel(0);
    let (mut crossing, mut changing) = (0, 0);
    for j in 0..p.height {
        for i in 0..p.width {
            let ray = cam.ray(i as f64 + 0.5, j as f64 + 0.5, p.width, p.height);
            if let Some((t0, t1)) = brickyard_core::camera::intersect_box(&ray, [0.0; 3], extent) {
                crossing += 1;
                let level = |t| auto_level(&p, voxel0, levels.len(), t);
                changing += (level(t0) != level(t1)) as usize;
            }
        }
    }
    assert!(
        crossing > 100 && changing * 2 > crossing,
        "the level changes along {changing} of {crossing} rays"
    );
}
