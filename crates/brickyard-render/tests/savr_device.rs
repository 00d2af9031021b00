//! Sample accumulation on the device (`savr.wgsl`) against its CPU twin
//! and the single pass at the rate reached: in core after 1, 8 and 16
//! frames, out of core with a pool far smaller than the volume (no stand-in
//! survives a complete image), shaded, with a per-pixel budget that stops
//! pixels short, and re-blended under a new transfer function. Positions
//! are f32 on the device: within 1e-4 of the host (the device tolerance of
//! `tests/gpu.rs`). Runs on lavapipe in CI.

mod accumulation;

use accumulation::{fixture, scale_opacity, session, Fixture};
use brickyard_cache::session::Session;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::{DType, Shading, TransferFunction};
use brickyard_gpu::context::{test_gpu, Gpu};
use brickyard_gpu::vm::DeviceVm;
use brickyard_render::cpu::{Lod, Scene};
use brickyard_render::gpu::GpuRenderer;
use brickyard_render::image::Image;
use brickyard_render::reference::{RenderMode, RenderParams, Volume};
use brickyard_render::savr::device::DeviceAccumulation;
use brickyard_render::savr::Accumulation;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::source::{SourceMeta, VolumeSource};
use std::sync::atomic::AtomicBool;

const TOLERANCE: f32 = 1e-4;

/// Whether the device's image `a` is the host's `b` within [`TOLERANCE`],
/// but for pixels (at most 1 in 200, each within 0.01) where a sample lies
/// within f32 rounding of the ray's exit: in on one back end, out on the
/// other (a sample at offset 0 meets the exit whenever the ray's length is
/// a multiple of the step). Prints the figures.
fn twins(what: &str, a: &Image, b: &Image) {
    let n = a.rgba.len();
    let (mut off, mut worst) = (0usize, 0.0f32);
    for (p, q) in a.rgba.iter().zip(&b.rgba) {
        let d = (0..4).map(|c| (p[c] - q[c]).abs()).fold(0.0, f32::max);
        off += (d > TOLERANCE) as usize;
        worst = worst.max(d);
    }
    eprintln!("{what}: device vs CPU max {worst}, {off} of {n} pixels beyond {TOLERANCE}");
    assert!(
        off * 200 <= n && worst <= 0.01,
        "{what}: device vs CPU max {worst}, {off} of {n} pixels beyond {TOLERANCE}"
    );
}

/// CPU accumulation frames until complete.
fn accumulate(s: &mut Session, f: &Fixture, p: &RenderParams, acc: &mut Accumulation, lod: Lod) {
    for _ in 1..=600 {
        s.begin_frame();
        let (_, reqs) = acc.frame(s.vm(), &f.scene, p, lod);
        s.finish_frame(reqs.iter());
        if acc.complete() {
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the CPU accumulation never completed");
}

/// Device accumulation frames (updates decided on the host, mirrored)
/// until complete; the frames drawn and the stand-ins kept after the
/// first.
#[allow(clippy::too_many_arguments)]
fn accumulate_device(
    gpu: &Gpu,
    r: &mut GpuRenderer,
    dvm: &mut DeviceVm,
    s: &mut Session,
    f: &Fixture,
    p: &RenderParams,
    acc: &mut DeviceAccumulation,
    lod: Lod,
) -> (u32, u64) {
    let mut first = None;
    for frame in 1..=600 {
        s.begin_frame();
        let fr = acc
            .frame(gpu, r, dvm, s.vm(), None, &f.scene, p, lod)
            .unwrap();
        first.get_or_insert(acc.last().stand_ins);
        s.finish_frame([&fr.requests]);
        dvm.sync(gpu, s.vm_mut());
        if acc.complete() {
            return (frame, first.unwrap());
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the device accumulation never completed: {:?}", acc.last());
}

#[test]
fn device_accumulation_equals_its_cpu_twin() {
    let Some(gpu) = test_gpu() else { return };
    let f = fixture();
    let mut r = GpuRenderer::new(&gpu);
    // In core, fixed levels, 1, 8 and 16 frames.
    for (n, level) in [(1u32, 0usize), (8, 0), (16, 1)] {
        let mut s = session(&f.store, 64 << 20);
        let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
        let mut dacc = DeviceAccumulation::new(&gpu, 40, 30, n, 1 << 16);
        let (frames, _) = accumulate_device(
            &gpu,
            &mut r,
            &mut dvm,
            &mut s,
            &f,
            &f.params,
            &mut dacc,
            Lod::Fixed(level),
        );
        assert!(frames >= n);
        let mut acc = Accumulation::new(40, 30, n, 1 << 16);
        accumulate(&mut s, &f, &f.params, &mut acc, Lod::Fixed(level));
        twins(
            &format!("{n} frames, level {level}"),
            dacc.image(),
            acc.image(),
        );
        assert!(acc.image().coverage(0.01) > 0.2, "image nearly empty");
        if n > 1 {
            let mut one = Accumulation::new(40, 30, 1, 1 << 16);
            accumulate(&mut s, &f, &f.params, &mut one, Lod::Fixed(level));
            assert!(
                dacc.image().max_abs_diff(one.image()) > 1e-3,
                "the rate changes nothing"
            );
        }
    }
    // Automatic level of detail.
    let mut s = session(&f.store, 64 << 20);
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let lod = Lod::Auto { bias: 0.5 };
    let mut dacc = DeviceAccumulation::new(&gpu, 40, 30, 4, 1 << 16);
    accumulate_device(
        &gpu, &mut r, &mut dvm, &mut s, &f, &f.params, &mut dacc, lod,
    );
    let mut acc = Accumulation::new(40, 30, 4, 1 << 16);
    accumulate(&mut s, &f, &f.params, &mut acc, lod);
    twins("automatic LOD", dacc.image(), acc.image());
}

/// A pool of a third of the volume: the first frames hold stand-ins; the
/// complete image holds none and equals the CPU's in-core accumulation.
/// With shading, the normals' neighbours must be resident too.
#[test]
fn device_accumulation_out_of_core_and_shaded() {
    let Some(gpu) = test_gpu() else { return };
    let f = fixture();
    let mut r = GpuRenderer::new(&gpu);
    let mut shaded = f.params.clone();
    shaded.tf.shading = Some(Shading::default());
    for (p, pool) in [
        (&f.params, f.bytes / 3),
        (&shaded, f.bytes),
        (&shaded, 64 << 20),
    ] {
        let mut s = session(&f.store, pool);
        let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
        let mut dacc = DeviceAccumulation::new(&gpu, 40, 30, 8, 1 << 16);
        let (frames, first) = accumulate_device(
            &gpu,
            &mut r,
            &mut dvm,
            &mut s,
            &f,
            p,
            &mut dacc,
            Lod::Fixed(0),
        );
        assert_eq!(dacc.last().stand_ins, 0);
        if pool < 64 << 20 {
            assert!(
                first > 0 && frames > 8,
                "{first} stand-ins first, {frames} frames"
            );
        }
        let mut cs = session(&f.store, 64 << 20);
        let mut acc = Accumulation::new(40, 30, 8, 1 << 16);
        accumulate(&mut cs, &f, p, &mut acc, Lod::Fixed(0));
        let what = format!("pool {pool}, shading {}", p.tf.shading.is_some());
        twins(&what, dacc.image(), acc.image());
    }
}

/// Blending each pixel only when its last run is in (`blend_last_only`,
/// what `render --progressive` asks for) gives the device's image of
/// blending every frame bit for bit: in core, out of core (stand-ins
/// retaken after the last run) and with a budget that stops pixels early;
/// frame 1 of several blends nothing.
#[test]
fn device_blending_only_the_last_frame_gives_the_same_image() {
    let Some(gpu) = test_gpu() else { return };
    let f = fixture();
    let mut r = GpuRenderer::new(&gpu);
    for (pool, n, budget) in [
        (64u64 << 20, 16u32, 1usize << 16),
        (f.bytes / 3, 8, 1 << 16),
        (64 << 20, 16, 3 * 200),
    ] {
        let mut run = |last_only: bool| {
            let mut s = session(&f.store, pool);
            let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
            let mut dacc = DeviceAccumulation::new(&gpu, 40, 30, n, budget);
            if last_only {
                dacc.blend_last_only();
                // Frames before the last blend nothing, also those whose
                // samples were served (the first, from cold, has none).
                let mut served = 0;
                while budget > 1000 && dacc.drawn() + 1 < n && (served == 0 || dacc.drawn() < 3) {
                    std::thread::sleep(std::time::Duration::from_millis(2));
                    s.begin_frame();
                    let fr = dacc
                        .frame(
                            &gpu,
                            &mut r,
                            &dvm,
                            s.vm(),
                            None,
                            &f.scene,
                            &f.params,
                            Lod::Fixed(0),
                        )
                        .unwrap();
                    s.finish_frame([&fr.requests]);
                    dvm.sync(&gpu, s.vm_mut());
                    served += dacc.last().frame.exact;
                    let what = format!("pool {pool}, frame {}", dacc.drawn());
                    assert_eq!(dacc.image().coverage(0.01), 0.0, "{what} blended");
                    assert!(!dacc.complete(), "{what}");
                }
                assert!(served > 0 || budget < 1000, "pool {pool}: nothing served");
            }
            accumulate_device(
                &gpu,
                &mut r,
                &mut dvm,
                &mut s,
                &f,
                &f.params,
                &mut dacc,
                Lod::Fixed(0),
            );
            (dacc.image().clone(), dacc.drawn())
        };
        let (every, drawn) = run(false);
        let (last, last_drawn) = run(true);
        assert_eq!(last_drawn, drawn, "pool {pool}");
        assert_eq!(
            last.rgba, every.rgba,
            "pool {pool}, {n} frames, budget {budget}"
        );
        assert!(every.coverage(0.01) > 0.2, "image nearly empty");
    }
}

/// A budget of 600 samples stops pixels short of 16 frames, as on the
/// CPU; a re-blend under a fainter and a denser function equals the CPU's
/// re-blend (the fainter one reports short pixels, the next frame
/// completes them).
#[test]
fn device_budget_and_reblend_follow_the_cpu() {
    let Some(gpu) = test_gpu() else { return };
    let f = fixture();
    let mut r = GpuRenderer::new(&gpu);
    let mut s = session(&f.store, 64 << 20);
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut dacc = DeviceAccumulation::new(&gpu, 40, 30, 16, 600);
    accumulate_device(
        &gpu,
        &mut r,
        &mut dvm,
        &mut s,
        &f,
        &f.params,
        &mut dacc,
        Lod::Fixed(0),
    );
    let mut acc = Accumulation::new(40, 30, 16, 600);
    accumulate(&mut s, &f, &f.params, &mut acc, Lod::Fixed(0));
    assert!(acc.frames() >= 3 && acc.frames() < 16, "{}", acc.frames());
    twins("budget 600", dacc.image(), acc.image());
    for (scale, cmap) in [(3.0f32, "hot"), (0.2, "linear")] {
        let mut p = f.params.clone();
        p.tf = TransferFunction::preset(cmap, [0.0, 255.0]).unwrap();
        scale_opacity(&mut p.tf, 0.25 * scale);
        let short = dacc
            .reblend(&gpu, &mut r, &dvm, s.vm(), &f.scene, &p)
            .unwrap()
            .unwrap();
        let cpu_short = acc.reblend(&p.tf).unwrap() as u64;
        assert_eq!(
            short > 0,
            cpu_short > 0,
            "{cmap}: short pixels {short} vs {cpu_short}"
        );
        if short > 0 {
            accumulate_device(
                &gpu,
                &mut r,
                &mut dvm,
                &mut s,
                &f,
                &p,
                &mut dacc,
                Lod::Fixed(0),
            );
            accumulate(&mut s, &f, &p, &mut acc, Lod::Fixed(0));
        }
        twins(
            &format!("{cmap}: re-blend ({short} short)"),
            dacc.image(),
            acc.image(),
        );
        // Not the image before the change.
        let mut fresh = Accumulation::new(40, 30, 16, 600);
        accumulate(&mut s, &f, &p, &mut fresh, Lod::Fixed(0));
        twins(
            &format!("{cmap}: re-blend vs fresh"),
            dacc.image(),
            fresh.image(),
        );
    }
}

/// A store too small for one run of the view's rays at the level asked
/// for: the accumulation samples the finest level whose runs fit, on the
/// device as on the CPU, and completes. Before, the device wrote the runs
/// past each pixel's region into its neighbour's samples, and the view
/// never completed (stand-ins counted but lost).
#[test]
fn a_store_too_small_for_a_ray_samples_a_coarser_level() {
    use brickyard_render::savr::{lod_within, longest_run};
    let Some(gpu) = test_gpu() else { return };
    let f = fixture();
    let p = &f.params;
    let [need0, need1] = [0, 1].map(|l| longest_run(&f.scene, p, l));
    assert!(
        need1 < need0,
        "level 1 takes fewer samples: {need1} vs {need0}"
    );
    // The rule: level 1 where only its runs fit, the level asked for where
    // level 0's fit, nothing where not even the coarsest level's fit.
    let coarsest = f.scene.levels.len() - 1;
    assert!(matches!(
        lod_within(&f.scene, p, Lod::Fixed(0), need1),
        Some(Lod::Fixed(1))
    ));
    assert!(matches!(
        lod_within(&f.scene, p, Lod::Fixed(0), need0),
        Some(Lod::Fixed(0))
    ));
    assert!(lod_within(
        &f.scene,
        p,
        Lod::Fixed(0),
        longest_run(&f.scene, p, coarsest) - 1
    )
    .is_none());
    match lod_within(&f.scene, p, Lod::Auto { bias: -3.0 }, need1) {
        Some(Lod::Auto { bias }) => assert!(bias > -3.0, "bias {bias} not raised"),
        other => panic!("automatic level of detail became {other:?}"),
    }

    let mut r = GpuRenderer::new(&gpu);
    let budget = need1 as usize;
    let mut s = session(&f.store, 64 << 20);
    let (mut dvm, _) = DeviceVm::new(&gpu, s.vm_mut()).unwrap();
    let mut dacc = DeviceAccumulation::new(&gpu, 40, 30, 4, budget);
    assert_eq!(dacc.budget(), budget);
    accumulate_device(
        &gpu,
        &mut r,
        &mut dvm,
        &mut s,
        &f,
        p,
        &mut dacc,
        Lod::Fixed(0),
    );
    // The CPU twin under the same budget, and the CPU asked for level 1
    // under it (the level's runs fit: the level is kept as asked).
    let mut acc = Accumulation::new(40, 30, 4, budget);
    accumulate(&mut s, &f, p, &mut acc, Lod::Fixed(0));
    twins("small store", dacc.image(), acc.image());
    let mut level1 = Accumulation::new(40, 30, 4, budget);
    accumulate(&mut s, &f, p, &mut level1, Lod::Fixed(1));
    twins("small store vs level 1", dacc.image(), level1.image());
    assert!(level1.image().coverage(0.01) > 0.2, "image nearly empty");
    // Level 0 (room to spare) draws another image.
    let mut level0 = Accumulation::new(40, 30, 4, 1 << 16);
    accumulate(&mut s, &f, p, &mut level0, Lod::Fixed(0));
    assert!(
        level0.image().max_abs_diff(level1.image()) > 1e-3,
        "levels 0 and 1 draw the same image: the check says nothing"
    );
}

/// A slab of `SLAB_VALUE` in the first `SLAB` voxels along x, then zeros
/// to the end of a long volume.
struct SlabThenEmpty(SourceMeta);

const SLAB: u64 = 8;
const SLAB_VALUE: u8 = 108;

impl VolumeSource for SlabThenEmpty {
    fn meta(&self) -> &SourceMeta {
        &self.0
    }
    fn read_region(
        &self,
        _c: usize,
        z: std::ops::Range<u64>,
        y: std::ops::Range<u64>,
        x: std::ops::Range<u64>,
        out: &mut [u8],
    ) -> brickyard_store::Result<()> {
        let mut i = 0;
        for _ in z {
            for _ in y.clone() {
                for xx in x.clone() {
                    out[i] = if xx < SLAB { SLAB_VALUE } else { 0 };
                    i += 1;
                }
            }
        }
        Ok(())
    }
}

/// Rays that cross a thin slab whose opacity lies right at the
/// early-termination threshold, then 400 voxels of nothing, in two frames
/// with every brick resident: the second frame's run (offset 0) reaches an
/// opacity of 0.99 alone and stops, the blend of both runs stays just under
/// it, so that run is extended 8 samples at a time to the ray's far end.
/// The device's image equals the CPU's. Before, the device blended every
/// kept sample again from the ray's start after each extension: the
/// invocation's loops ran past the 65535 iterations lavapipe allows an
/// invocation, the driver cut them short, and every pixel came out blank
/// (as one pixel of Colin27 did under `render --progressive 4`, its fourth
/// frame's blend just under 0.99).
#[test]
fn open_runs_extended_to_a_long_rays_end_blend_as_on_the_cpu() {
    let Some(gpu) = test_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("slab.ome.zarr");
    let dims = [16, 16, 400];
    let src = SlabThenEmpty(SourceMeta::new("<slab>", dims, 1, DType::U8));
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
    // Along x through the slab first, tilted a little (no ray parallel to
    // a face), every ray within the 16 × 16 cross-section.
    let cam = Camera {
        projection: Projection::Orthographic { height: 8.0 },
        eye: [-5.0, 8.0, 8.0],
        target: [400.0, 8.2, 8.1],
        up: [0.0, 0.0, 1.0],
    };
    let tf = TransferFunction::preset("linear", [0.0, 255.0]).unwrap();
    let mut p = RenderParams::new(8, 8, cam, tf, RenderMode::Dvr);
    p.reference_step = Some(scene.voxel(0));
    let f = Fixture {
        _dir: dir,
        store,
        levels,
        scene,
        params: p.clone(),
        bytes: dims.iter().product::<u64>(),
    };

    // The CPU twin: the runs stopped on their own are extended by most of
    // the ray's length.
    let lod = Lod::Fixed(0);
    let mut s = session(&f.store, 64 << 20);
    let mut loaded = Accumulation::new(8, 8, 1, 1 << 16);
    accumulate(&mut s, &f, &p, &mut loaded, lod);
    let mut acc = Accumulation::new(8, 8, 2, 1 << 16);
    let mut extended = 0;
    for _ in 1..=600 {
        s.begin_frame();
        let (st, reqs) = acc.frame(s.vm(), &f.scene, &p, lod);
        extended += st.extended;
        s.finish_frame(reqs.iter());
        if acc.complete() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    assert!(acc.complete(), "the CPU accumulation never completed");
    eprintln!("CPU: {extended} samples added to runs that had stopped");
    assert!(
        extended >= 64 * 360,
        "{extended} samples added to stopped runs: the blend does not reach the far end"
    );
    assert!(acc.image().coverage(0.5) == 1.0, "the slab does not show");

    let mut r = GpuRenderer::new(&gpu);
    let mut ds = session(&f.store, 64 << 20);
    let (mut dvm, _) = DeviceVm::new(&gpu, ds.vm_mut()).unwrap();
    let mut loaded = DeviceAccumulation::new(&gpu, 8, 8, 1, 1 << 16);
    accumulate_device(&gpu, &mut r, &mut dvm, &mut ds, &f, &p, &mut loaded, lod);
    let mut dacc = DeviceAccumulation::new(&gpu, 8, 8, 2, 1 << 16);
    accumulate_device(&gpu, &mut r, &mut dvm, &mut ds, &f, &p, &mut dacc, lod);
    twins("open runs to the far end", dacc.image(), acc.image());
}
