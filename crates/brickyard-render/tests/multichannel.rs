//! DVR of several channels, each through its own transfer function: on
//! the CPU (out of core, with and without empty-space skipping) against
//! the in-core reference's own multi-channel DVR, on the device against
//! the CPU, for 1, 3 and 16 channels of a generated volume; and channel
//! switching at run time: bricks of channels still visible stay resident.

use brickyard_cache::brick::BrickKey;
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection, Vec3};
use brickyard_core::{DType, Dims3, TransferFunction};
use brickyard_gpu::context::test_gpu;
use brickyard_gpu::update::DeviceCache;
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::gpu::{update_on_device, GpuRenderer};
use brickyard_render::image::Image;
use brickyard_render::reference::{
    render_channels, ChannelStyle, RenderMode, RenderParams, Volume,
};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

#[path = "common/requests.rs"]
mod requests;
use requests::same_requests;

const TOLERANCE: f32 = 1e-4;

/// Voxels `[z, y, x]` of the generated volumes.
const DIMS: Dims3 = [40, 48, 64];

/// An `n`-channel u8 store: channel `c` holds the Mandelbulb's values
/// (Marschner–Lobb for odd `c`) in the `c`-th of `n` overlapping bands,
/// rescaled to 60–255, and 0 elsewhere: every channel is sparse, and a brick
/// one channel hides often holds another's data.
fn banded_store(dir: &Path, n: usize) -> (PathBuf, Vec3, Vec<Dims3>) {
    banded_store_of(dir, n, DIMS)
}

/// [`banded_store`] of `dims` voxels (`[z, y, x]`).
fn banded_store_of(dir: &Path, n: usize, dims: Dims3) -> (PathBuf, Vec3, Vec<Dims3>) {
    let raw = dir.join(format!("banded{n}.raw"));
    // Each function's values once (the kinds used), then the bands.
    let kinds: Vec<Vec<f64>> = [Kind::Mandelbulb, Kind::MarschnerLobb]
        .into_iter()
        .take(n.min(2))
        .map(|k| {
            let g = Procedural::new(k, dims, DType::U8);
            let mut v = Vec::with_capacity(dims.iter().product::<u64>() as usize);
            for z in 0..dims[0] {
                for y in 0..dims[1] {
                    for x in 0..dims[2] {
                        v.push(g.value(z, y, x));
                    }
                }
            }
            v
        })
        .collect();
    let mut bytes = Vec::with_capacity(n * dims.iter().product::<u64>() as usize);
    for c in 0..n {
        let (lo, hi) = if n == 1 {
            (0.05, 1.0)
        } else {
            let w = 1.0 / n as f64;
            ((c as f64 - 0.5) * w, (c as f64 + 1.5) * w)
        };
        bytes.extend(kinds[c % 2].iter().map(|&v| {
            if v >= lo && v < hi {
                (60.0 + 195.0 * ((v - lo) / (hi - lo)).clamp(0.0, 1.0)).round() as u8
            } else {
                0
            }
        }));
    }
    std::fs::write(&raw, &bytes).unwrap();
    let opts: brickyard_store::import::raw::RawOptions = serde_json::from_str(&format!(
        r#"{{"dims":[{},{},{}],"dtype":"u8","channels":{n}}}"#,
        dims[2], dims[1], dims[0]
    ))
    .unwrap();
    let src = brickyard_store::import::raw::open(&raw, &opts).unwrap();
    let store = dir.join(format!("banded{n}.ome.zarr"));
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let extent = world_extent(dims, Volume::from_store(&store, 0, 0).unwrap().spacing);
    let levels = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap().dims)
        .collect();
    (store, extent, levels)
}

/// Distinct colours for `n` channels (hues around the circle).
fn palette(n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|c| {
            let h = c as f32 / n as f32 * 6.0;
            [
                ((h - 3.0).abs() - 1.0).clamp(0.0, 1.0),
                (2.0 - (h - 2.0).abs()).clamp(0.0, 1.0),
                (2.0 - (h - 4.0).abs()).clamp(0.0, 1.0),
            ]
        })
        .collect()
}

/// The DVR of channels `shown` with default transfer functions (window 0–255,
/// each in its colour), except that channel 1, when shown, gets a transfer
/// function of its own (a ramp of two colours).
fn dvr_params(extent: Vec3, shown: &[usize], n: usize) -> RenderParams {
    let cam = Camera::fit(
        extent,
        35.0,
        25.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    let mut p = RenderParams::new(56, 48, cam, tf, RenderMode::Dvr);
    let colours = palette(n);
    p.channels = shown
        .iter()
        .map(|&c| {
            let mut s = ChannelStyle::new(c, colours[c], [0.0, 255.0]);
            if c == 1 {
                s.tf = Some(
                    TransferFunction::from_json(
                        r#"{"window": [30, 255], "opacity": [[0, 0], [0.2, 0], [0.6, 0.3], [1, 0.8]],
                            "colormap": [[0, 0.1, 0.9, 0.2], [1, 1, 1, 0.1]]}"#,
                    )
                    .unwrap_or_else(|e| panic!("{e}")),
                );
            }
            s
        })
        .collect();
    p
}

fn cfg(pool_bytes: u64) -> VmConfig {
    VmConfig {
        brick: [16; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes,
        pt_cache_blocks: 256,
        request_cap: 64,
        upload_bytes_per_frame: 48 * 18 * 18 * 18,
    }
}

/// CPU frames until complete; the image and every brick requested on the
/// way.
fn converge(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> (Image, Vec<BrickKey>) {
    let mut asked = vec![];
    for _ in 0..600 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
        let fs = s.finish_frame(reqs.iter());
        asked.extend(fs.frame.requests.iter().copied());
        if st.completeness() == 1.0 {
            return (img, asked);
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the view never completed ({} channels)", p.channels.len());
}

/// The image shows something of at least `k` channels' colours.
fn not_blank(img: &Image, what: &str) {
    let a: f64 = img.rgba.iter().map(|px| px[3] as f64).sum();
    let n = img.rgba.len() as f64;
    assert!(a > 0.05 * n, "{what}: image nearly empty (alpha sum {a})");
}

fn reference(store: &Path, p: &RenderParams, level: usize) -> Image {
    let vols: Vec<Volume> = p
        .channels
        .iter()
        .map(|c| Volume::from_store(store, level, c.channel).unwrap())
        .collect();
    render_channels(&vols, p)
}

#[test]
fn cpu_multichannel_dvr_equals_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    for n in [1usize, 3, 16] {
        let (store, extent, levels) = banded_store(dir.path(), n);
        let shown: Vec<usize> = (0..n).collect();
        let p = dvr_params(extent, &shown, n);
        let want = reference(&store, &p, 0);
        not_blank(&want, &format!("{n} channels, reference"));
        let vol_bytes = n as u64 * DIMS.iter().product::<u64>();
        let mut scene = Scene::new(extent, levels);
        for with_ranges in [false, true] {
            let mut s = Session::open(&store, cfg(2 * vol_bytes), 8 << 20, 2).unwrap();
            scene.ranges = with_ranges.then(|| Arc::new(s.loader().brick_ranges(1 << 20)));
            let (img, _) = converge(&mut s, &scene, &p, Lod::Fixed(0));
            let d = img.max_abs_diff(&want);
            if d > TOLERANCE {
                for (i, (a, b)) in img.rgba.iter().zip(&want.rgba).enumerate() {
                    if (0..4).any(|c| (a[c] - b[c]).abs() > TOLERANCE) {
                        eprintln!("pixel {i}: {a:?} vs {b:?}");
                    }
                }
            }
            eprintln!(
                "{n} channels, ranges {with_ranges}: max abs diff {d}, {} bricks loaded",
                s.loader().bricks_loaded()
            );
            assert!(
                d <= TOLERANCE,
                "{n} channels, ranges {with_ranges}: diff {d}"
            );
        }
    }
}

/// The runs of several channels in four lanes (`Scene::lanes`) give the
/// scalar twin's bits, for u8 channels (the lanes' own kernel) with and
/// without the store's statistics.
#[test]
fn channels_in_four_lanes_are_the_scalar_twin() {
    let dir = tempfile::tempdir().unwrap();
    let n = 3;
    let (store, extent, levels) = banded_store(dir.path(), n);
    let p = dvr_params(extent, &[0, 1, 2], n);
    let vol_bytes = n as u64 * DIMS.iter().product::<u64>();
    for ranges in [false, true] {
        let mut scene = Scene::new(extent, levels.clone());
        let mut s = Session::open(&store, cfg(2 * vol_bytes), 8 << 20, 2).unwrap();
        scene.ranges = ranges.then(|| Arc::new(s.loader().brick_ranges(1 << 20)));
        let (lanes, _) = converge(&mut s, &scene, &p, Lod::Fixed(0));
        scene.lanes = false;
        let (scalar, _) = converge(&mut s, &scene, &p, Lod::Fixed(0));
        not_blank(&lanes, "lanes");
        let bits = |img: &Image| -> Vec<u32> {
            img.rgba
                .iter()
                .flat_map(|px| px.map(f32::to_bits))
                .collect()
        };
        assert!(
            bits(&lanes) == bits(&scalar),
            "statistics {ranges}: the lanes' image differs"
        );
    }
}

#[test]
fn a_brick_is_skipped_only_when_every_visible_channel_hides_it() {
    // Channel 0 is hidden everywhere by its transfer function (opacity 0
    // over its whole window), channel 1 shows: the image is channel 1's
    // alone, and bricks hidden for channel 0 but not for channel 1 are not
    // jumped over.
    let dir = tempfile::tempdir().unwrap();
    let (store, extent, levels) = banded_store(dir.path(), 3);
    let mut p = dvr_params(extent, &[0, 1], 3);
    p.channels[0].tf = Some(
        TransferFunction::from_json(
            r#"{"window": [0, 255], "opacity": [[0, 0], [1, 0]], "colormap": "grayscale"}"#,
        )
        .unwrap(),
    );
    let mut only1 = p.clone();
    only1.channels.remove(0);
    let want = reference(&store, &only1, 0);
    not_blank(&want, "channel 1 alone");
    assert!(reference(&store, &p, 0).max_abs_diff(&want) <= 1e-6);
    let mut scene = Scene::new(extent, levels);
    let mut s = Session::open(&store, cfg(1 << 22), 8 << 20, 2).unwrap();
    scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
    let (img, asked) = converge(&mut s, &scene, &p, Lod::Fixed(0));
    let d = img.max_abs_diff(&want);
    assert!(d <= TOLERANCE, "diff {d}");
    // Channel 0 is never sampled, so never asked for.
    assert!(
        !asked.iter().any(|k| k.channel == 0),
        "a hidden channel's bricks were requested"
    );
}

#[test]
fn switching_channels_keeps_the_bricks_of_channels_still_visible() {
    // Channels {0, 1} until complete, then {0, 2}, {0, 1, 2} and {2}: after
    // a switch no brick of a channel that stayed visible and was resident
    // is requested (loaded) again; every image equals the reference of its
    // set.
    // (A still-visible channel may need bricks it did not need before: a
    // channel hidden now no longer occludes them.) The pool holds about
    // two channels' working sets, so channel 1's bricks make room for
    // channel 2's.
    let dir = tempfile::tempdir().unwrap();
    let (store, extent, levels) = banded_store(dir.path(), 3);
    let mut scene = Scene::new(extent, levels.clone());
    let vol_bytes = DIMS.iter().product::<u64>();
    let mut s = Session::open(&store, cfg(5 * vol_bytes), 8 << 20, 2).unwrap();
    scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
    // Every brick key of a channel at level 0, the level drawn (coarser
    // bricks serve only as stand-ins and may go).
    let keys_of = |c: usize| -> Vec<BrickKey> {
        let mut v = vec![];
        for (l, d) in levels.iter().enumerate().take(1) {
            let nb = d.map(|x| x.div_ceil(16) as u32);
            for z in 0..nb[0] {
                for y in 0..nb[1] {
                    for x in 0..nb[2] {
                        v.push(BrickKey::new(l as u8, c as u16, [z, y, x]));
                    }
                }
            }
        }
        v
    };
    let mut before: Vec<usize> = vec![];
    let mut kept_total = 0;
    for set in [vec![0, 1], vec![0, 2], vec![0, 1, 2], vec![2]] {
        // What the channels staying visible have resident now.
        let kept: Vec<BrickKey> = set
            .iter()
            .filter(|c| before.contains(c))
            .flat_map(|&c| keys_of(c))
            .filter(|&k| s.vm().is_resident(k))
            .collect();
        kept_total += kept.len();
        let p = dvr_params(extent, &set, 3);
        let (img, asked) = converge(&mut s, &scene, &p, Lod::Fixed(0));
        let want = reference(&store, &p, 0);
        not_blank(&want, &format!("set {set:?}"));
        let d = img.max_abs_diff(&want);
        assert!(d <= TOLERANCE, "set {set:?}: diff {d}");
        for k in &kept {
            assert!(
                !asked.contains(k),
                "switch {before:?} → {set:?}: {k:?} (resident, still visible) was requested again"
            );
        }
        before = set;
    }
    assert!(
        kept_total > 50,
        "too few bricks kept to show anything: {kept_total}"
    );
}

/// Device frames (its own update step) until complete.
fn gpu_converge(
    gpu: &brickyard_gpu::context::Gpu,
    store: &Path,
    scene: &Scene,
    p: &RenderParams,
    pool: u64,
) -> Option<(Image, brickyard_render::cpu::FrameStats)> {
    let mut renderer = GpuRenderer::new(gpu);
    let mut s = Session::open(store, cfg(pool), 8 << 20, 2).unwrap();
    let (mut dvm, _) = DeviceVm::new(gpu, s.vm_mut()).unwrap();
    let mut cache = DeviceCache::new(gpu, &dvm, s.vm()).unwrap();
    for _ in 0..600 {
        s.begin_frame();
        let n = s.vm().frame();
        let f = renderer
            .render_with(gpu, &dvm, s.vm(), Some(&cache), scene, p, Lod::Fixed(0))
            .unwrap();
        update_on_device(gpu, &mut dvm, &mut cache, &mut s, n, &f.list).unwrap();
        if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
            return Some((f.image, f.stats));
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!(
        "the device view never completed ({} channels)",
        p.channels.len()
    );
}

#[test]
fn gpu_multichannel_dvr_equals_the_cpu_and_the_reference() {
    let Some(gpu) = test_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    for n in [1usize, 3, 16] {
        let (store, extent, levels) = banded_store(dir.path(), n);
        let shown: Vec<usize> = (0..n).collect();
        let p = dvr_params(extent, &shown, n);
        let vol_bytes = n as u64 * DIMS.iter().product::<u64>();
        let mut scene = Scene::new(extent, levels);
        let mut s = Session::open(&store, cfg(2 * vol_bytes), 8 << 20, 2).unwrap();
        scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
        let (cpu, _) = converge(&mut s, &scene, &p, Lod::Fixed(0));
        let (img, _) = gpu_converge(&gpu, &store, &scene, &p, 2 * vol_bytes).unwrap();
        not_blank(&img, &format!("{n} channels, device"));
        let want = reference(&store, &p, 0);
        let (dc, dr) = (img.max_abs_diff(&cpu), img.max_abs_diff(&want));
        eprintln!("{n} channels: device vs CPU {dc}, vs reference {dr}");
        assert!(
            dc <= TOLERANCE && dr <= TOLERANCE,
            "{n} channels: device vs CPU {dc}, vs reference {dr}"
        );
        if n == 3 {
            // The cells every channel hides are crossed (as the CPU's runs
            // cross them): the same image as sampling them, fewer samples.
            // (Transfer functions that hide the bands' background, 60, so
            // that cells of it are clear for every channel.)
            let mut pc = p.clone();
            for c in &mut pc.channels {
                c.tf = Some(
                    TransferFunction::from_json(
                        r#"{"window": [100, 255], "opacity": [[0, 0], [0.1, 0], [1, 0.6]],
                            "colormap": "hot"}"#,
                    )
                    .unwrap(),
                );
            }
            let (crossed, st) = gpu_converge(&gpu, &store, &scene, &pc, 2 * vol_bytes).unwrap();
            scene.skip_cells = false;
            let (every, st_every) = gpu_converge(&gpu, &store, &scene, &pc, 2 * vol_bytes).unwrap();
            scene.skip_cells = true;
            not_blank(&crossed, "cells crossed");
            let d = crossed.max_abs_diff(&every);
            eprintln!(
                "{n} channels: {} samples, {} cells crossed; {} samples crossing none; diff {d}",
                st.samples, st.skipped_cells, st_every.samples
            );
            assert_eq!(st_every.skipped_cells, 0);
            assert!(st.skipped_cells > 0, "no cell crossed");
            assert!(
                st.samples < st_every.samples * 9 / 10,
                "{} samples crossing cells, {} without",
                st.samples,
                st_every.samples
            );
            assert!(d <= 1e-6, "crossing cells changed the image by {d}");
            let dr = crossed.max_abs_diff(&reference(&store, &pc, 0));
            assert!(dr <= TOLERANCE, "cells crossed: {dr} from the reference");
            // Without the store's statistics (as the web client draws): no
            // brick is known clear, none may be skipped as one.
            scene.ranges = None;
            let (img, _) = gpu_converge(&gpu, &store, &scene, &p, 2 * vol_bytes).unwrap();
            let dr = img.max_abs_diff(&want);
            eprintln!("{n} channels without statistics: device vs reference {dr}");
            assert!(
                dr <= TOLERANCE,
                "{n} channels without statistics: device vs reference {dr}"
            );
        }
    }
}

/// A first frame of several channels from cold (nothing resident) asks
/// for what the CPU twin asks for, brick by brick with the same counts,
/// with the store's statistics (the bricks they hide asked for by
/// neither) and without (where the device once read other words of its
/// buffer as clear-brick bits and skipped 14 bricks): on both,
/// where no channel shows and some found nothing resident, the ray goes
/// on past the brick in one jump, adding the steps as misses of each such
/// channel's brick. (Before, the device added a miss per level and
/// channel at every step, the CPU walked every step.)
#[test]
fn a_cold_frame_of_channels_asks_for_what_the_cpu_asks_for() {
    let Some(gpu) = test_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let n = 3;
    let (store, extent, levels) = banded_store_of(dir.path(), n, [64, 64, 64]);
    let mut renderer = GpuRenderer::new(&gpu);
    for (shown, ranges) in [
        (vec![0, 1, 2], true),
        (vec![2, 0], true),
        (vec![0, 1, 2], false),
    ] {
        let p = dvr_params(extent, &shown, n);
        let what = format!("channels {shown:?}, statistics {ranges}");
        let mut scene = Scene::new(extent, levels.clone());
        let mut c = cfg(1 << 20);
        c.request_cap = 4096;
        let mut s = Session::open(&store, c, 8 << 20, 2).unwrap();
        if ranges {
            scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
        }
        let (dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
        s.begin_frame();
        let f = renderer
            .render(&gpu, &dvm, s.vm(), &scene, &p, Lod::Fixed(0))
            .unwrap();
        let (_, st, reqs) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
        assert_eq!(st.exact + f.stats.exact, 0, "nothing is resident");
        assert_eq!(f.dropped, 0);
        let cpu = same_requests(&reqs, &f.requests, &what);
        assert!(cpu.len() > 30, "{} bricks asked for", cpu.len());
        for &ch in &shown {
            let ch = ch as u16;
            assert!(
                cpu.keys().any(|k| k.channel == ch && k.level == 0)
                    && cpu.keys().any(|k| k.channel == ch && k.level > 0),
                "channel {ch}: fine and coarse bricks"
            );
        }
        let (ud, uc) = (f.stats.unserved as f64, st.unserved as f64);
        assert!(
            (ud - uc).abs() <= 0.01 * uc,
            "{what}: unserved samples {ud} on the device, {uc} on the CPU"
        );
    }
}

/// A first frame of channels drawn from stand-ins alone (level 0 never
/// resident, the coarse levels pinned): the CPU's runs through the
/// stand-ins' bricks give the reference image of the finest pinned level
/// sampled at level 0's steps, and ask for the bricks the device asks for
/// sampling step by step (each step of a run a miss of every channel
/// drawn from a stand-in); with and without the store's statistics, and
/// with a channel hidden by its transfer function.
#[test]
fn a_first_frame_of_channels_from_stand_ins_is_their_level_and_asks_as_the_device() {
    let dir = tempfile::tempdir().unwrap();
    let n = 3;
    let (store, extent, levels) = banded_store_of(dir.path(), n, [64, 64, 64]);
    let gpu = test_gpu();
    let mut renderer = gpu.as_ref().map(GpuRenderer::new);
    let hidden = TransferFunction::from_json(
        r#"{"window": [0, 255], "opacity": [[0, 0], [1, 0]], "colormap": "grayscale"}"#,
    )
    .unwrap();
    for (shown, ranges, hide) in [
        (vec![0, 1, 2], true, false),
        (vec![2, 0], false, false),
        (vec![0, 1, 2], true, true),
    ] {
        let mut p = dvr_params(extent, &shown, n);
        if hide {
            p.channels[1].tf = Some(hidden.clone());
        }
        let what = format!("channels {shown:?}, statistics {ranges}, one hidden {hide}");
        let mut scene = Scene::new(extent, levels.clone());
        let mut c = cfg(4 << 20);
        c.request_cap = 4096;
        let mut s = Session::open(&store, c, 8 << 20, 2).unwrap();
        if ranges {
            scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
        }
        let pin = s
            .pin_coarsest(4096, std::time::Duration::from_secs(60))
            .unwrap();
        let finest = *pin.levels.iter().min().unwrap();
        assert!(finest >= 1, "{what}: level 0 pinned");
        let voxel = |l: usize| Volume::from_store(&store, l, 0).unwrap().voxel_size();
        p.reference_step = Some(voxel(0));
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
        assert_eq!(st.exact, 0, "{what}: level 0 was resident");
        assert_eq!(st.unserved, 0, "{what}: a sample found no stand-in");
        not_blank(&img, &what);
        // The reference at level 0's step from the stand-ins' level.
        let mut q = p.clone();
        q.samples_per_voxel *= voxel(finest) / voxel(0);
        let want = reference(&store, &q, finest);
        let d = img.max_abs_diff(&want);
        assert!(
            d <= TOLERANCE,
            "{what}: {d} from level {finest}'s reference"
        );
        let (Some(gpu), Some(renderer)) = (&gpu, renderer.as_mut()) else {
            continue; // BRICKYARD_SKIP_GPU=1, reported by `test_gpu`
        };
        let (dvm, _) = DeviceVm::new(gpu, s.vm_mut()).unwrap();
        s.begin_frame();
        let f = renderer
            .render(gpu, &dvm, s.vm(), &scene, &p, Lod::Fixed(0))
            .unwrap();
        let (_, st2, reqs2) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
        assert_eq!(st2.samples, st.samples, "{what}: the same frame again");
        assert_eq!(reqs2.len(), reqs.len());
        assert_eq!(f.stats.exact, 0);
        let cpu = same_requests(&reqs2, &f.requests, &what);
        assert!(cpu.len() > 10, "{what}: {} bricks asked for", cpu.len());
    }
}

/// The three MNI152 files (T1, grey matter, white matter) as one
/// three-channel store, or `None` (said on stderr) when the shared data
/// folder is absent.
fn mni_store(dir: &Path) -> Option<(PathBuf, Vec3, Vec<Dims3>)> {
    use brickyard_store::import::stack::ChannelStack;
    use brickyard_store::import::{open_input, ImportOptions};
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data");
    let files =
        ["mni152-t1-u8", "mni152-gm-u8", "mni152-wm-u8"].map(|f| data.join(format!("{f}.nii.gz")));
    if !files.iter().all(|f| f.exists()) {
        eprintln!(
            "{}: the MNI152 files are missing; test skipped",
            data.display()
        );
        return None;
    }
    let sources = files
        .iter()
        .map(|f| open_input(f, &ImportOptions::default()).unwrap())
        .collect();
    let src = ChannelStack::new(sources).unwrap();
    let store = dir.join("mni.ome.zarr");
    let o = ConvertOptions {
        brick: [32; 3],
        shard: [64; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let nlev = (0..)
        .take_while(|&l| Volume::from_store(&store, l, 0).is_ok())
        .count();
    let v0 = Volume::from_store(&store, 0, 0).unwrap();
    let extent = world_extent(v0.dims, v0.spacing);
    let levels = (0..nlev)
        .map(|l| Volume::from_store(&store, l, 0).unwrap().dims)
        .collect();
    Some((store, extent, levels))
}

#[test]
fn mni152_three_channels_on_cpu_and_device_equal_the_reference() {
    // T1 in grey, grey matter in magenta, white matter in cyan (the
    // store's `omero` colours), windows from the `omero` metadata.
    let dir = tempfile::tempdir().unwrap();
    let Some((store, extent, levels)) = mni_store(dir.path()) else {
        return;
    };
    let omero = brickyard_store::omezarr::read_omero(&store)
        .unwrap()
        .unwrap();
    assert_eq!(
        omero.iter().map(|c| c.label.as_str()).collect::<Vec<_>>(),
        ["mni152-t1-u8", "mni152-gm-u8", "mni152-wm-u8"]
    );
    let cam = Camera::fit(
        extent,
        120.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    let mut p = RenderParams::new(64, 56, cam, tf, RenderMode::Dvr);
    p.channels = omero
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let w = c.window.expect("omero windows");
            ChannelStyle::new(
                i,
                c.color.map(|x| x as f32 / 255.0),
                [w[0] as f32, w[1] as f32],
            )
        })
        .collect();
    let level = 1;
    let mut scene = Scene::new(extent, levels);
    // Opacity per level-0 voxel, as `render` sets it.
    p.reference_step = Some(scene.voxel(0));
    let want = reference(&store, &p, level);
    not_blank(&want, "MNI152 reference");
    let pool = 64 << 20;
    let mut s = Session::open(&store, cfg(pool), 32 << 20, 2).unwrap();
    scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
    let (cpu, _) = converge(&mut s, &scene, &p, Lod::Fixed(level));
    let d = cpu.max_abs_diff(&want);
    eprintln!("MNI152, 3 channels: CPU vs reference {d}");
    assert!(d <= TOLERANCE, "MNI152: CPU vs reference {d}");
    // Each channel shows: the mix differs from every channel alone.
    for c in 0..3 {
        let mut one = p.clone();
        one.channels = vec![p.channels[c].clone()];
        let alone = reference(&store, &one, level);
        assert!(alone.max_abs_diff(&want) > 0.05, "channel {c} adds nothing");
    }
    let Some(gpu) = test_gpu() else { return };
    let mut renderer = GpuRenderer::new(&gpu);
    let mut s = Session::open(&store, cfg(pool), 32 << 20, 2).unwrap();
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut cache = DeviceCache::new(&gpu, &dvm, s.vm()).unwrap();
    let mut img = None;
    for _ in 0..600 {
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
            img = Some(f.image);
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    let img = img.expect("the device view completes");
    let (dc, dr) = (img.max_abs_diff(&cpu), img.max_abs_diff(&want));
    eprintln!("MNI152, 3 channels: device vs CPU {dc}, vs reference {dr}");
    assert!(
        dc <= TOLERANCE && dr <= TOLERANCE,
        "device vs CPU {dc}, vs reference {dr}"
    );
}

/// Frame times of multi-channel DVR, CPU and device, once everything is
/// resident (a full frame each, no loading): `cargo test --release -p
/// brickyard-render --test multichannel -- --ignored bench --nocapture`.
#[test]
#[ignore]
fn bench_multichannel_dvr_frame_times() {
    let size: u64 = std::env::var("BENCH_SIZE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(128);
    let image: u32 = std::env::var("BENCH_IMAGE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(512);
    let counts: Vec<usize> = std::env::var("BENCH_CHANNELS")
        .ok()
        .map(|s| s.split(',').map(|x| x.parse().unwrap()).collect())
        .unwrap_or(vec![1, 4, 16]);
    let dims = [size; 3];
    let dir = tempfile::tempdir().unwrap();
    // BENCH_NO_DEVICE=1: the CPU only.
    let gpu = if std::env::var("BENCH_NO_DEVICE").as_deref() == Ok("1") {
        None
    } else {
        test_gpu()
    };
    let mut base: Option<(f64, f64)> = None;
    for &n in &counts {
        let sub = dir.path().join(n.to_string());
        std::fs::create_dir_all(&sub).unwrap();
        let (store, extent, levels) = banded_store_of(&sub, n, dims);
        let shown: Vec<usize> = (0..n).collect();
        let mut p = dvr_params(extent, &shown, n);
        p.width = image;
        p.height = image;
        let bytes = n as u64 * dims.iter().product::<u64>();
        let pool = 2 * bytes + (16 << 20);
        let bcfg = VmConfig {
            request_cap: 1024,
            upload_bytes_per_frame: pool,
            pt_cache_blocks: 4096,
            ..cfg(pool)
        };
        let mut scene = Scene::new(extent, levels);
        let mut s = Session::open(&store, bcfg.clone(), 64 << 20, 2).unwrap();
        scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
        converge(&mut s, &scene, &p, Lod::Fixed(0));
        let reps = 5;
        let mut cpu_ms = f64::INFINITY;
        let mut samples = 0;
        for _ in 0..reps {
            s.begin_frame();
            let t = std::time::Instant::now();
            let (_, st, reqs) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
            cpu_ms = cpu_ms.min(t.elapsed().as_secs_f64() * 1e3);
            samples = st.samples;
            s.finish_frame(reqs.iter());
        }
        // Channel 0 of the same store alone: the same volume, one channel.
        let mut alone = p.clone();
        alone.channels.truncate(1);
        converge(&mut s, &scene, &alone, Lod::Fixed(0));
        let mut one_ms = f64::INFINITY;
        for _ in 0..reps {
            s.begin_frame();
            let t = std::time::Instant::now();
            let (_, _, reqs) = render_frame(s.vm(), &scene, &alone, Lod::Fixed(0));
            one_ms = one_ms.min(t.elapsed().as_secs_f64() * 1e3);
            s.finish_frame(reqs.iter());
        }
        let mut dev_ms = f64::NAN;
        if let Some(gpu) = &gpu {
            let mut renderer = GpuRenderer::new(gpu);
            let mut s = Session::open(&store, bcfg.clone(), 64 << 20, 2).unwrap();
            let (mut dvm, _) = DeviceVm::new(gpu, s.vm_mut()).unwrap();
            let mut cache = DeviceCache::new(gpu, &dvm, s.vm()).unwrap();
            let mut complete = 0;
            for _ in 0..600 {
                s.begin_frame();
                let fr = s.vm().frame();
                let t = std::time::Instant::now();
                let f = renderer
                    .render_with(gpu, &dvm, s.vm(), Some(&cache), &scene, &p, Lod::Fixed(0))
                    .unwrap();
                let ms = t.elapsed().as_secs_f64() * 1e3;
                update_on_device(gpu, &mut dvm, &mut cache, &mut s, fr, &f.list).unwrap();
                if f.stats.completeness() == 1.0 {
                    complete += 1;
                    if complete > 1 {
                        dev_ms = if dev_ms.is_nan() { ms } else { dev_ms.min(ms) };
                    }
                    if complete > reps {
                        break;
                    }
                }
            }
        }
        let (c1, d1) = *base.get_or_insert((cpu_ms, dev_ms));
        println!(
            "channels {n:2}: {size}³ u8, {image}² image: CPU {cpu_ms:8.1} ms ({:.2}× one; channel 0 alone {one_ms:.1} ms, {:.2}×), device {dev_ms:8.1} ms ({:.2}× one), {samples} samples",
            cpu_ms / c1,
            cpu_ms / one_ms,
            dev_ms / d1
        );
    }
}
