//! Sample accumulation: after 2^m frames the accumulated image is a single
//! pass at 2^m times the sampling rate (same positions), in core and out of
//! core with a pool far smaller than the volume; a complete image holds no
//! stand-in sample; a transfer-function re-blend equals a fresh
//! accumulation under the new function.
//!
//! The single pass is written here, on the in-core oracle's sampler
//! (`Volume::sample_world`) and a compositing loop of its own.

mod accumulation;

use accumulation::{fixture, scale_opacity, session, Fixture};
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{intersect_box_inv, world_extent, Camera, Projection, Vec3};
use brickyard_core::{DType, Shading, TransferFunction};
use brickyard_render::cpu::{Lod, Scene};
use brickyard_render::image::Image;
use brickyard_render::reference::{render, RenderMode, RenderParams, Volume};
use brickyard_render::savr::Accumulation;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::Path;
use std::sync::atomic::AtomicBool;

/// A single DVR pass at `rate` samples per frame step of level `level`:
/// samples at `t0 + i·Δ/rate`, `i = 0, 1, …`, on the oracle's sampler,
/// composited front to back with opacity corrected by `(Δ/rate)/Δ_ref`
/// and stopped at opacity 0.99.
fn single_pass(vol: &Volume, f: &Fixture, tf: &TransferFunction, level: usize, rate: u32) -> Image {
    single_pass_to(vol, f, tf, level, rate, true)
}

/// [`single_pass`], stopping at opacity 0.99 only when `early`.
fn single_pass_to(
    vol: &Volume,
    f: &Fixture,
    tf: &TransferFunction,
    level: usize,
    rate: u32,
    early: bool,
) -> Image {
    let p = &f.params;
    let extent = f.scene.extent;
    let dt = f.scene.voxel(level) / p.samples_per_voxel / rate as f64;
    let e = (dt / p.reference_step.unwrap()) as f32;
    let rg = brickyard_core::views::ViewRays::new(&p.camera, p.views.as_ref(), p.width, p.height);
    let mut img = Image::new(p.width, p.height);
    for j in 0..p.height {
        for i in 0..p.width {
            let ray = rg.pixel_ray(i, j);
            let inv = ray.dir.map(|d| 1.0 / d);
            let Some((t0, t1)) = intersect_box_inv(&ray, inv, [0.0; 3], extent) else {
                continue;
            };
            let mut acc = [0.0f32; 4];
            let mut k = 0u64;
            loop {
                let t = t0 + k as f64 * dt;
                if t >= t1 {
                    break;
                }
                k += 1;
                let w = ray.at(t);
                let mut c = tf.lookup(vol.sample_world(w, extent));
                if c[3] <= 0.0 {
                    continue;
                }
                if let Some(sh) = &tf.shading {
                    c = shade(vol, sh, c, w, ray.dir, extent);
                }
                let a = 1.0 - (1.0 - c[3]).powf(e);
                let w = (1.0 - acc[3]) * a;
                for ch in 0..3 {
                    acc[ch] += w * c[ch];
                }
                acc[3] += w;
                if early && acc[3] >= 0.99 {
                    break;
                }
            }
            img.rgba[(j * p.width + i) as usize] = acc;
        }
    }
    img
}

/// The shading rule of `brickyard_core::Shading`, written out: central
/// differences a voxel apart per world axis on the oracle's sampler, the
/// cosine with the ray, Blinn–Phong with the light at the eye.
fn shade(vol: &Volume, sh: &Shading, c: [f32; 4], w: Vec3, d: Vec3, extent: Vec3) -> [f32; 4] {
    let g: Vec<f64> = (0..3)
        .map(|a| {
            let h = extent[a] / vol.dims[2 - a] as f64;
            let (mut p, mut q) = (w, w);
            p[a] += h;
            q[a] -= h;
            (vol.sample_world(p, extent) as f64 - vol.sample_world(q, extent) as f64) / (2.0 * h)
        })
        .collect();
    let gn = g.iter().map(|x| x * x).sum::<f64>().sqrt();
    if gn == 0.0 {
        return c;
    }
    let dn = d.iter().map(|x| x * x).sum::<f64>().sqrt();
    let x = (g.iter().zip(d).map(|(a, b)| a * b).sum::<f64>() / (gn * dn)).abs();
    let k = sh.ambient as f64 + sh.diffuse as f64 * x;
    let s = sh.specular as f64 * x.powf(sh.shininess as f64);
    let mut out = c;
    for ch in 0..3 {
        out[ch] = (c[ch] as f64 * k + s) as f32;
    }
    out
}

/// Accumulation frames through session `s` until the accumulation is
/// complete; returns the frames drawn and the stand-ins kept after the
/// first.
fn accumulate(s: &mut Session, f: &Fixture, acc: &mut Accumulation, lod: Lod) -> (usize, u64) {
    let mut first = None;
    // 600 frames, or 30 s on a machine busy with other tests (the loader
    // threads then deliver late, and a pool smaller than the view takes
    // many more frames of retakes).
    let t0 = std::time::Instant::now();
    for frame in 1.. {
        if frame > 600 && t0.elapsed() > std::time::Duration::from_secs(30) {
            break;
        }
        s.begin_frame();
        let (st, reqs) = acc.frame(s.vm(), &f.scene, &f.params, lod);
        first.get_or_insert(st.stand_ins);
        s.finish_frame(reqs.iter());
        if acc.complete() {
            return (frame, first.unwrap());
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!(
        "the accumulation never completed: {} stand-ins",
        acc.stand_ins()
    );
}

#[test]
fn accumulated_frames_equal_a_single_pass_at_the_rate_reached() {
    let f = fixture();
    for (n, level) in [(1u32, 0usize), (8, 0), (16, 1)] {
        let mut s = session(&f.store, 64 << 20);
        let mut acc = Accumulation::new(f.params.width, f.params.height, n, 1 << 20);
        let (frames, _) = accumulate(&mut s, &f, &mut acc, Lod::Fixed(level));
        assert_eq!(acc.frames(), n);
        assert!(frames >= n as usize);
        // One frame is the plain renderer's grid, `t0 + (k + ½)·Δ`: the
        // oracle itself.
        let want = match n {
            1 => render(&f.levels[level], &f.params),
            _ => single_pass(&f.levels[level], &f, &f.params.tf, level, n),
        };
        let d = acc.image().max_abs_diff(&want);
        assert!(d <= 1e-5, "{n} frames, level {level}: max abs diff {d}");
        assert!(want.coverage(0.01) > 0.2, "image nearly empty");
        if n > 1 {
            // Not the single frame's image: the rate matters here.
            let one = single_pass(&f.levels[level], &f, &f.params.tf, level, 1);
            assert!(acc.image().max_abs_diff(&one) > 1e-3);
        }
    }
}

/// A stereo pair accumulates like one view: each eye's rays (off-axis,
/// `brickyard_core::views`) reach the single pass at 8 times the rate.
#[test]
fn a_stereo_pair_accumulates_as_its_single_pass() {
    let mut f = fixture();
    f.params.width *= 2;
    let d = brickyard_core::camera::length(brickyard_core::camera::sub(
        f.params.camera.target,
        f.params.camera.eye,
    ));
    f.params.views = Some(brickyard_core::views::Views {
        count: 2,
        separation: d / 20.0,
        parallax: 0.0,
        spacing: 0.0,
        alone: None,
    });
    let mut s = session(&f.store, 64 << 20);
    let mut acc = Accumulation::new(f.params.width, f.params.height, 8, 1 << 20);
    accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
    let want = single_pass(&f.levels[0], &f, &f.params.tf, 0, 8);
    let diff = acc.image().max_abs_diff(&want);
    assert!(diff <= 1e-5, "max abs diff {diff}");
    assert!(want.coverage(0.01) > 0.2, "image nearly empty");
    // The eyes see different images.
    let w = f.params.width / 2;
    let (l, r) = (
        brickyard_render::views::view(&want, 2, 0),
        brickyard_render::views::view(&want, 2, 1),
    );
    assert_eq!(l.width, w);
    assert!(l.max_abs_diff(&r) > 0.05);
}

/// Out of core (a pool of a third of the volume, bricks arriving a few per
/// frame): the first frames are drawn from coarser stand-ins, which are
/// retaken as the finer bricks arrive. The complete image equals the
/// in-core single pass; a stand-in left in it would not.
#[test]
fn a_complete_image_holds_no_stand_in() {
    let f = fixture();
    let mut s = session(&f.store, f.bytes / 3);
    assert!((s.vm().pool_bytes() as u64) * 2 < f.bytes);
    let mut acc = Accumulation::new(f.params.width, f.params.height, 8, 1 << 20);
    let (frames, first) = accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
    assert!(first > 0, "the first frame must hold stand-ins");
    assert!(frames > 8, "{frames} frames");
    assert_eq!(acc.stand_ins(), 0);
    let want = single_pass(&f.levels[0], &f, &f.params.tf, 0, 8);
    let d = acc.image().max_abs_diff(&want);
    assert!(d <= 1e-5, "max abs diff {d} after {frames} frames");
}

/// A render blends each pixel once, when its last run is in
/// (`blend_last_only`): the same image bit for bit as blending every frame,
/// in core, out of core (stand-ins retaken after the last run) and with a
/// budget that stops pixels early; the frames before show nothing new.
#[test]
fn blending_only_the_last_frame_gives_the_same_image() {
    let f = fixture();
    for (pool, n, budget) in [
        (64u64 << 20, 16u32, 1usize << 20),
        (f.bytes / 3, 8, 1 << 20),
        (64 << 20, 16, 3 * 200),
    ] {
        let mut every = Accumulation::new(f.params.width, f.params.height, n, budget);
        let mut s = session(&f.store, pool);
        accumulate(&mut s, &f, &mut every, Lod::Fixed(0));
        let mut last = Accumulation::new(f.params.width, f.params.height, n, budget);
        last.blend_last_only();
        let mut s = session(&f.store, pool);
        // Frames before the last blend nothing, also those whose samples
        // were served (the first, from cold, has none).
        let mut served = 0;
        while budget > 1000 && last.frames() + 1 < n && (served == 0 || last.frames() < 3) {
            std::thread::sleep(std::time::Duration::from_millis(2));
            s.begin_frame();
            let (st, reqs) = last.frame(s.vm(), &f.scene, &f.params, Lod::Fixed(0));
            s.finish_frame(reqs.iter());
            served += st.frame.exact;
            let what = format!("pool {pool}, frame {}", last.frames());
            assert_eq!(last.image().coverage(0.01), 0.0, "{what} blended");
            assert!(!last.complete(), "{what}");
        }
        assert!(served > 0 || budget < 1000, "pool {pool}: nothing served");
        accumulate(&mut s, &f, &mut last, Lod::Fixed(0));
        assert_eq!(last.frames(), every.frames());
        assert_eq!(
            last.image().rgba,
            every.image().rgba,
            "pool {pool}, {n} frames, budget {budget}"
        );
        assert!(every.image().coverage(0.01) > 0.2, "image nearly empty");
    }
}

/// Frames lowered after the first to fit a memory budget
/// (`fit_memory`, what `render --progressive` does with the samples' share
/// of --memory): the memory held stays within it, and the image is that of
/// an accumulation asked for the lowered number from the start, bit for
/// bit. The expected memory of the first frame's room is an upper bound of
/// what it held.
#[test]
fn frames_lowered_to_fit_memory_stay_within_it() {
    use brickyard_render::savr::first_frame_memory;
    let f = fixture();
    let (w, h) = (f.params.width, f.params.height);
    let bound = first_frame_memory(&f.scene, &f.params, 0..h, 0);
    let mut s = session(&f.store, 64 << 20);
    let mut acc = Accumulation::new(w, h, 16, 1 << 20);
    acc.blend_last_only();
    s.begin_frame();
    let (_, reqs) = acc.frame(s.vm(), &f.scene, &f.params, Lod::Fixed(0));
    s.finish_frame(reqs.iter());
    let first = acc.memory() as u64;
    assert!(first <= bound, "first frame {first} > its bound {bound}");
    let all = acc.expected_memory(16);
    let five = acc.expected_memory(5);
    assert!(five < all && acc.expected_memory(4) < five);
    // Room for five frames: five are drawn.
    assert_eq!(acc.fit_memory(five), Some((5, all)));
    assert_eq!(acc.fit_memory(five), None, "already within");
    accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
    assert!(acc.complete());
    assert_eq!(acc.target(), 5);
    let held = acc.memory() as u64;
    assert!(held <= five, "held {held} > {five} expected");
    let mut s = session(&f.store, 64 << 20);
    let mut want = Accumulation::new(w, h, 5, 1 << 20);
    accumulate(&mut s, &f, &mut want, Lod::Fixed(0));
    assert_eq!(acc.image().rgba, want.image().rgba);
    assert!(want.image().coverage(0.01) > 0.2, "image nearly empty");
    // Less than one more frame's room: the frames drawn stay.
    let mut one = Accumulation::new(w, h, 16, 1 << 20);
    let mut s = session(&f.store, 64 << 20);
    s.begin_frame();
    let (_, reqs) = one.frame(s.vm(), &f.scene, &f.params, Lod::Fixed(0));
    s.finish_frame(reqs.iter());
    assert_eq!(one.fit_memory(0).map(|(t, _)| t), Some(1));
    accumulate(&mut s, &f, &mut one, Lod::Fixed(0));
    assert!(one.complete() && one.drawn() >= 1 && one.target() == 1);
}

/// A per-pixel budget of 600 samples stops pixels short of the 16 frames
/// asked for (at ⌊600 / steps of the ray⌋) and the accumulation is
/// complete there, within the memory bound.
#[test]
fn a_full_store_stops_the_pixel_at_the_rate_reached() {
    let f = fixture();
    let mut s = session(&f.store, 64 << 20);
    // The longest ray of this view is well under 200 steps.
    let mut acc = Accumulation::new(f.params.width, f.params.height, 16, 3 * 200);
    accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
    assert!(acc.frames() >= 3 && acc.frames() < 16, "{}", acc.frames());
    assert!(acc.complete());
    assert!(acc.memory() < (f.params.width * f.params.height) as usize * (3 * 200 * 5 + 400));
}

/// A re-blend under a new transfer function, without the volume, equals a
/// fresh accumulation under it; one that sees further than the runs were
/// taken reports the pixels short, and the next frame completes them.
#[test]
fn a_reblend_equals_a_fresh_accumulation() {
    let mut f = fixture();
    let mut s = session(&f.store, 64 << 20);
    let mut acc = Accumulation::new(f.params.width, f.params.height, 8, 1 << 20);
    accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
    for (scale, cmap) in [(3.0f32, "hot"), (0.2, "linear")] {
        let mut tf = TransferFunction::preset(cmap, [0.0, 255.0]).unwrap();
        scale_opacity(&mut tf, 0.25 * scale);
        let short = acc.reblend(&tf).unwrap();
        f.params.tf = tf.clone();
        if scale < 1.0 {
            assert!(short > 0, "a fainter function sees further");
            assert!(!acc.complete());
            accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
        } else {
            assert_eq!(short, 0, "a denser function stops earlier");
            assert!(acc.complete());
        }
        let mut fresh = Accumulation::new(f.params.width, f.params.height, 8, 1 << 20);
        accumulate(&mut s, &f, &mut fresh, Lod::Fixed(0));
        let d = acc.image().max_abs_diff(fresh.image());
        assert!(d <= 1e-6, "{cmap}: re-blend vs fresh: {d}");
        let want = single_pass(&f.levels[0], &f, &tf, 0, 8);
        assert!(acc.image().max_abs_diff(&want) <= 1e-5);
    }
}

/// Sort-last accumulation (data-parallel ranks): three regions of a k-d
/// split, each keeping only its samples of the whole ray's grid and
/// blending all of them, composited per pixel in the order the ray enters
/// them, equal the whole view's accumulation without early termination,
/// which equals the single pass without it. Image-parallel ranks: the
/// accumulations of bands of rows equal the whole image's rows bit for
/// bit.
#[test]
fn regions_and_bands_equal_the_whole_accumulation() {
    let mut f = fixture();
    let (w, h) = (f.params.width, f.params.height);
    let e = f.scene.extent;
    let (cx, cy) = (0.45 * e[0], 0.6 * e[1]);
    let regions = [
        [[0.0, 0.0, 0.0], [cx, e[1], e[2]]],
        [[cx, 0.0, 0.0], [e[0], cy, e[2]]],
        [[cx, cy, 0.0], [e[0], e[1], e[2]]],
    ];
    for (n, lod) in [(8u32, Lod::Fixed(0)), (4, Lod::Auto { bias: 0.0 })] {
        f.params.early_termination = false;
        f.params.clip = None;
        let mut s = session(&f.store, 64 << 20);
        let mut whole = Accumulation::new(w, h, n, 1 << 20);
        accumulate(&mut s, &f, &mut whole, lod);
        if let Lod::Fixed(level) = lod {
            let want = single_pass_to(&f.levels[level], &f, &f.params.tf, level, n, false);
            let d = whole.image().max_abs_diff(&want);
            assert!(
                d <= 1e-5,
                "whole without early termination vs single pass: {d}"
            );
            let stopped = single_pass(&f.levels[level], &f, &f.params.tf, level, n);
            assert!(
                whole.image().max_abs_diff(&stopped) > 1e-3,
                "early termination must matter in this view"
            );
        }
        let parts: Vec<Image> = regions
            .iter()
            .map(|r| {
                f.params.clip = Some(Box::new(*r));
                let mut acc = Accumulation::new(w, h, n, 1 << 20);
                accumulate(&mut s, &f, &mut acc, lod);
                assert!(
                    acc.image().coverage(0.01) > 0.05,
                    "region {r:?} drew nothing"
                );
                acc.image().clone()
            })
            .collect();
        f.params.clip = None;
        let rg = brickyard_core::views::ViewRays::new(&f.params.camera, None, w, h);
        let mut img = Image::new(w, h);
        for j in 0..h {
            for i in 0..w {
                let ray = rg.pixel_ray(i, j);
                let inv = ray.dir.map(|d| 1.0 / d);
                let mut order: Vec<(f64, usize)> = regions
                    .iter()
                    .enumerate()
                    .filter_map(|(k, r)| Some((intersect_box_inv(&ray, inv, r[0], r[1])?.0, k)))
                    .collect();
                order.sort_by(|a, b| a.0.total_cmp(&b.0));
                let px = (j * w + i) as usize;
                let mut acc = [0.0f32; 4];
                for (_, k) in order {
                    let c = parts[k].rgba[px];
                    let t = 1.0 - acc[3];
                    for ch in 0..4 {
                        acc[ch] += t * c[ch];
                    }
                }
                img.rgba[px] = acc;
            }
        }
        let d = img.max_abs_diff(whole.image());
        assert!(
            d <= 1e-5,
            "{n} frames, {lod:?}: regions composited vs whole: {d}"
        );
        assert!(whole.image().coverage(0.01) > 0.2, "image nearly empty");
        // Bands of rows, with early termination as one process draws.
        f.params.early_termination = true;
        let mut whole = Accumulation::new(w, h, n, 1 << 20);
        accumulate(&mut s, &f, &mut whole, lod);
        for rows in [0..7, 7..19, 19..h] {
            let mut band = Accumulation::rows(w, h, rows.clone(), n, 1 << 20);
            accumulate(&mut s, &f, &mut band, lod);
            assert_eq!(band.kept_rows(), rows);
            let (a, b) = (
                rows.start as usize * w as usize,
                rows.end as usize * w as usize,
            );
            assert_eq!(band.image().rgba, whole.image().rgba[a..b], "rows {rows:?}");
        }
    }
}

/// Mean SSIM of the luminance of two images over black (premultiplied
/// RGB), on 8×8 windows every 4 pixels, uniform weights, `C1 = 0.01²`,
/// `C2 = 0.03²`.
fn ssim(a: &Image, b: &Image) -> f64 {
    let lum = |c: [f32; 4]| 0.299 * c[0] as f64 + 0.587 * c[1] as f64 + 0.114 * c[2] as f64;
    let (w, h) = (a.width as usize, a.height as usize);
    let (c1, c2) = (1e-4, 9e-4);
    let (mut sum, mut n) = (0.0, 0);
    for y0 in (0..h.saturating_sub(7)).step_by(4) {
        for x0 in (0..w.saturating_sub(7)).step_by(4) {
            let (mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for y in y0..y0 + 8 {
                for x in x0..x0 + 8 {
                    let (p, q) = (lum(a.rgba[y * w + x]), lum(b.rgba[y * w + x]));
                    sa += p;
                    sb += q;
                    saa += p * p;
                    sbb += q * q;
                    sab += p * q;
                }
            }
            let m = 64.0;
            let (ma, mb) = (sa / m, sb / m);
            let (va, vb) = (saa / m - ma * ma, sbb / m - mb * mb);
            let cov = sab / m - ma * mb;
            sum += ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                / ((ma * ma + mb * mb + c1) * (va + vb + c2));
            n += 1;
        }
    }
    sum / n as f64
}

#[test]
fn ssim_of_an_image_with_itself_is_one_and_drops_with_noise() {
    let f = fixture();
    let img = render(&f.levels[0], &f.params);
    assert!((ssim(&img, &img) - 1.0).abs() < 1e-12);
    let mut noisy = img.clone();
    for (i, p) in noisy.rgba.iter_mut().enumerate() {
        p[0] = (p[0] + if i % 3 == 0 { 0.2 } else { -0.1 }).clamp(0.0, 1.0);
    }
    assert!(ssim(&img, &noisy) < 0.9, "{}", ssim(&img, &noisy));
}

/// Convergence figures (run by hand, `--ignored --nocapture`): a generated
/// 128³ Mandelbulb with a narrow, dense opacity band (thin shells a coarse
/// step undersamples), and the MR brain of the shared data with a narrow
/// band over its tissue values (iso-surface-like shells).
#[test]
#[ignore]
fn convergence_figures() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("mb.ome.zarr");
    let o = ConvertOptions {
        brick: [32; 3],
        shard: [64; 3],
        ..Default::default()
    };
    let src = Procedural::new(Kind::Mandelbulb, [128, 128, 128], DType::U8);
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let mut tf = TransferFunction::preset("viridis", [0.0, 255.0]).unwrap();
    tf.opacity = vec![[0.0, 0.0], [0.3, 0.0], [0.33, 0.9], [0.36, 0.0], [1.0, 0.0]];
    println!("## generated 128³ Mandelbulb");
    convergence(&store, tf);
    let nrrd = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/mr-brain-i16.nrrd");
    let src = brickyard_store::import::open_input(&nrrd, &Default::default()).unwrap();
    let store = dir.path().join("mr.ome.zarr");
    convert(
        src.as_ref(),
        &store,
        &o,
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    let mut tf = TransferFunction::preset("soft", [150.0, 1100.0]).unwrap();
    tf.opacity = vec![[0.0, 0.0], [0.45, 0.0], [0.5, 0.8], [0.55, 0.0], [1.0, 0.0]];
    println!("## MR brain (shared data, 256×256×25 int16, 0.78×0.78×6.5 mm)");
    convergence(&store, tf);
}

/// Frames → PSNR and SSIM against the oracle at 32 samples per voxel, the
/// plain single pass at the same rate beside them, frame times, memory and
/// re-blend times, for a 256² view of level 0 of `store`.
fn convergence(store: &Path, tf: TransferFunction) {
    use brickyard_render::cpu::render_frame;
    use std::time::Instant;
    let vol = Volume::from_store(store, 0, 0).unwrap();
    let extent = world_extent(vol.dims, vol.spacing);
    let mut scene = Scene::new(extent, vec![vol.dims]);
    scene.ranges = None;
    let cam = Camera::fit(
        extent,
        30.0,
        20.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut p = RenderParams::new(256, 256, cam, tf, RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(0));
    let t = Instant::now();
    let mut pr = p.clone();
    pr.samples_per_voxel = 32.0;
    let reference = render(&vol, &pr);
    println!(
        "reference (32 samples per voxel, oracle): {:.1} s",
        t.elapsed().as_secs_f64()
    );
    let cfg = VmConfig {
        brick: [32; 3],
        apron: 1,
        pt_block: [4; 3],
        max_dir_entries: 64,
        pool_bytes: 64 << 20,
        pt_cache_blocks: 256,
        request_cap: 4096,
        upload_bytes_per_frame: 64 << 20,
    };
    let mut s = Session::open(store, cfg, 64 << 20, 2).unwrap();
    // Load the working set (nothing is timed before it is resident).
    for _ in 0..50 {
        s.begin_frame();
        let (_, st, reqs) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
        s.finish_frame(reqs.iter());
        if st.completeness() == 1.0 {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let mut plain_ms = f64::INFINITY;
    for _ in 0..3 {
        let t = Instant::now();
        let _ = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
        plain_ms = plain_ms.min(t.elapsed().as_secs_f64() * 1e3);
    }
    println!("plain DVR frame (1 sample per voxel): {plain_ms:.1} ms");
    println!("| frames | accumulated PSNR dB | SSIM | frame ms | plain single pass at the same rate: PSNR dB | SSIM |");
    println!("|---:|---:|---:|---:|---:|---:|");
    let mut acc = Accumulation::new(p.width, p.height, 32, 1 << 20);
    let mut total = 0.0;
    for n in 1..=32u32 {
        s.begin_frame();
        let t = Instant::now();
        let (st, reqs) = acc.frame(s.vm(), &scene, &p, Lod::Fixed(0));
        let ms = t.elapsed().as_secs_f64() * 1e3;
        total += ms;
        s.finish_frame(reqs.iter());
        assert_eq!(st.stand_ins, 0);
        if n.is_power_of_two() {
            let mut pn = p.clone();
            pn.samples_per_voxel = n as f64;
            let plain = render(&vol, &pn);
            println!(
                "| {n} | {:.2} | {:.4} | {ms:.0} | {:.2} | {:.4} |",
                acc.image().psnr(&reference),
                ssim(acc.image(), &reference),
                plain.psnr(&reference),
                ssim(&plain, &reference)
            );
        }
        if n == 16 {
            // Re-blends against a fresh accumulation of 16 frames: new
            // colours; the band moved and widened.
            let mut colours = p.tf.clone();
            colours.colormap = TransferFunction::preset("hot", [0.0, 1.0])
                .unwrap()
                .colormap;
            let mut moved = p.tf.clone();
            moved.opacity = vec![[0.0, 0.0], [0.25, 0.0], [0.3, 0.9], [0.36, 0.0], [1.0, 0.0]];
            println!(
                "16 frames: {total:.0} ms in all, {:.1} MiB kept",
                acc.memory() as f64 / (1 << 20) as f64
            );
            for (what, tf2) in [("colours", colours), ("opacity band", moved)] {
                let t = Instant::now();
                let short = acc.reblend(&tf2).unwrap();
                let reblend_ms = t.elapsed().as_secs_f64() * 1e3;
                println!("re-blend, new {what}: {reblend_ms:.1} ms ({short} pixels short of kept samples)");
            }
            acc.reblend(&p.tf);
        }
    }
}

/// Shaded accumulation: each kept sample keeps the cosine of its normal
/// with the ray, so 8 frames equal the shaded single pass at 8× the rate,
/// out of core too (a normal from a stand-in is retaken); a re-blend with
/// other shading parameters equals a fresh accumulation under them; an
/// accumulation begun unshaded cannot be re-blended shaded.
#[test]
fn shaded_accumulation_equals_the_shaded_single_pass() {
    let mut f = fixture();
    f.params.tf.shading = Some(Shading::default());
    // Out of core: a pool of 29 slots for the 48 bricks of level 0. (A
    // shaded sample needs its brick and its neighbours' at once; with 9
    // slots, as the unshaded out-of-core test has, the retakes starve.)
    for pool in [64 << 20, f.bytes] {
        let mut s = session(&f.store, pool);
        if pool == f.bytes {
            assert!(s.vm().pool_slots() < 48, "{}", s.vm().pool_slots());
        }
        let mut acc = Accumulation::new(f.params.width, f.params.height, 8, 1 << 20);
        accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
        let want = single_pass(&f.levels[0], &f, &f.params.tf, 0, 8);
        let d = acc.image().max_abs_diff(&want);
        assert!(d <= 1e-5, "pool {pool}: max abs diff {d}");
        let mut plain = f.params.tf.clone();
        plain.shading = None;
        let unshaded = single_pass(&f.levels[0], &f, &plain, 0, 8);
        assert!(want.max_abs_diff(&unshaded) > 0.02, "shading did nothing");
    }
    let mut s = session(&f.store, 64 << 20);
    let mut acc = Accumulation::new(f.params.width, f.params.height, 8, 1 << 20);
    accumulate(&mut s, &f, &mut acc, Lod::Fixed(0));
    let mut glossy = f.params.tf.clone();
    glossy.shading = Some(Shading {
        ambient: 0.1,
        diffuse: 0.5,
        specular: 0.9,
        shininess: 4.0,
    });
    assert_eq!(acc.reblend(&glossy), Some(0));
    let want = single_pass(&f.levels[0], &f, &glossy, 0, 8);
    let d = acc.image().max_abs_diff(&want);
    assert!(d <= 1e-5, "re-blend with new shading: max abs diff {d}");
    // Begun unshaded: no normals kept.
    let mut unshaded = f.params.clone();
    unshaded.tf.shading = None;
    let mut acc = Accumulation::new(f.params.width, f.params.height, 2, 1 << 20);
    s.begin_frame();
    let (_, reqs) = acc.frame(s.vm(), &f.scene, &unshaded, Lod::Fixed(0));
    s.finish_frame(reqs.iter());
    assert_eq!(acc.reblend(&glossy), None);
}
