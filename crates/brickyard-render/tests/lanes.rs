//! Two switches of the CPU DVR that must not change the image, against
//! their twins on random scenes:
//!
//! - the per-sample work in four lanes (`Scene::lanes`, the default)
//!   against the scalar twin (`lanes = false`): random volumes (u8, u16,
//!   f32; random sizes, smooth fields plus noise, some NaN in f32),
//!   transfer functions (random points, steps, clear stretches, random
//!   colour maps and presets), cameras (perspective and orthographic, any
//!   direction), sampling rates and engine bricks. Every complete frame
//!   equals the twin's within 1e-6 (the lanes do the scalar operations, so
//!   in fact bit for bit);
//! - entry depths (`Scene::entry_depths`, the default) against the walk
//!   from the volume's face, on sparse random volumes with cameras outside
//!   and inside them, and on lone bright voxels seen through levels that
//!   turn coarser along the rays;
//! - the ray loop's copy compiled for x86-64-v3 (`Scene::x86_v3`, the
//!   default where the processor has it) against the baseline build, bit
//!   for bit, with lanes and scalar.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection};
use brickyard_core::transfer::{ColorMap, Preset};
use brickyard_core::{DType, TransferFunction};
use brickyard_render::cpu::{render_frame, Lod, Scene};
use brickyard_render::image::Image;
use brickyard_render::reference::{RenderMode, RenderParams, Volume};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::import::raw::{self, RawOptions};
use std::path::Path;
use std::sync::atomic::AtomicBool;

struct Rng(u64);

impl Rng {
    /// Uniform in `[0, 1)`.
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
    fn int(&mut self, lo: u64, hi: u64) -> u64 {
        lo + (self.next() * (hi - lo + 1) as f64) as u64
    }
}

/// A random volume of `dims` (`[x, y, z]`) in `dtype` as a store in `dir`;
/// returns the store and the data's range.
fn random_store(
    dir: &Path,
    rng: &mut Rng,
    dims: [u64; 3],
    dtype: DType,
) -> (std::path::PathBuf, [f32; 2]) {
    // A few random blobs and waves plus noise, scaled to the type's range.
    let blobs: Vec<[f64; 5]> = (0..4)
        .map(|_| {
            [
                rng.next(),
                rng.next(),
                rng.next(),
                rng.range(0.1, 0.4),
                rng.range(0.3, 1.0),
            ]
        })
        .collect();
    let freq = [
        rng.range(2.0, 12.0),
        rng.range(2.0, 12.0),
        rng.range(2.0, 12.0),
    ];
    let noise = rng.range(0.0, 0.2);
    let field = move |p: [f64; 3], rng: &mut Rng| {
        let mut v =
            0.15 * ((p[0] * freq[0]).sin() * (p[1] * freq[1]).cos() + (p[2] * freq[2]).sin());
        for b in &blobs {
            let d2 = (p[0] - b[0]).powi(2) + (p[1] - b[1]).powi(2) + (p[2] - b[2]).powi(2);
            v += b[4] * (-d2 / (b[3] * b[3])).exp();
        }
        v + noise * (rng.next() - 0.5)
    };
    store_of(dir, rng, dims, dtype, field)
}

/// A volume of `dims` (`[x, y, z]`) in `dtype` whose voxel at `p` (in
/// `[0, 1)³`) is `field(p)` in `[0, 1]` scaled to the type's range, as a
/// store in `dir` (random spacing, 16³ chunks); returns the store and the
/// data's range.
fn store_of(
    dir: &Path,
    rng: &mut Rng,
    dims: [u64; 3],
    dtype: DType,
    mut field: impl FnMut([f64; 3], &mut Rng) -> f64,
) -> (std::path::PathBuf, [f32; 2]) {
    let (max, bytes): (f64, usize) = match dtype {
        DType::U8 => (255.0, 1),
        DType::U16 => (65535.0, 2),
        _ => (1.0, 4),
    };
    let mut data = Vec::with_capacity((dims[0] * dims[1] * dims[2]) as usize * bytes);
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let p = [
                    x as f64 / dims[0] as f64,
                    y as f64 / dims[1] as f64,
                    z as f64 / dims[2] as f64,
                ];
                let v = field(p, rng).clamp(0.0, 1.0) * max;
                match dtype {
                    DType::U8 => data.push(v.round() as u8),
                    DType::U16 => data.extend_from_slice(&(v.round() as u16).to_le_bytes()),
                    _ => {
                        let f = if rng.next() < 0.001 {
                            f32::NAN
                        } else {
                            v as f32 * 3.0 - 1.0
                        };
                        data.extend_from_slice(&f.to_le_bytes());
                    }
                }
            }
        }
    }
    let path = dir.join(format!("v-{}.raw", rng.0 % 1_000_000));
    let spacing = [1.0, rng.range(0.7, 1.4), rng.range(0.7, 1.4)];
    let store = raw_store(&path, &data, (dims, dtype, 1), Some(spacing));
    let range = match dtype {
        DType::U8 | DType::U16 => [0.0, max as f32],
        _ => [-1.0, 2.0],
    };
    (store, range)
}

/// `data` (`channels` channels of `dims` voxels, `[x, y, z]`, in `dtype`,
/// channel-major) written to `path` and converted beside it to a store of
/// 16³ chunks in 32³ shards, which is returned.
fn raw_store(
    path: &Path,
    data: &[u8],
    (dims, dtype, channels): ([u64; 3], DType, usize),
    spacing: Option<[f64; 3]>,
) -> std::path::PathBuf {
    std::fs::write(path, data).unwrap();
    let opts = RawOptions {
        dims,
        dtype,
        endian: "little".into(),
        spacing,
        origin: None,
        unit: None,
        channels,
        header_bytes: 0,
    };
    let src = raw::open(path, &opts).unwrap();
    let store = path.with_extension("ome.zarr");
    let o = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    store
}

/// A random transfer function over about the data's range `r`.
fn random_tf(rng: &mut Rng, r: [f32; 2]) -> TransferFunction {
    let w = (r[1] - r[0]) as f64;
    let w0 = r[0] as f64 + w * rng.range(-0.1, 0.4);
    let w1 = w0 + w * rng.range(0.2, 1.0);
    let n = rng.int(1, 7) as usize;
    let mut xs: Vec<f32> = (0..n).map(|_| rng.next() as f32).collect();
    xs.sort_by(f32::total_cmp);
    if n > 2 && rng.next() < 0.3 {
        // A step: two points at the same x.
        xs[1] = xs[2];
    }
    let opacity: Vec<[f32; 2]> = xs
        .iter()
        .map(|&x| {
            let a = if rng.next() < 0.3 {
                0.0
            } else {
                rng.range(0.0, 0.9) as f32
            };
            [x, a]
        })
        .collect();
    let colormap = if rng.next() < 0.5 {
        let p = [
            Preset::Grayscale,
            Preset::Hot,
            Preset::Viridis,
            Preset::Coolwarm,
            Preset::Bone,
        ];
        ColorMap::Preset(p[rng.int(0, 4) as usize])
    } else {
        let m = rng.int(1, 5) as usize;
        let mut xs: Vec<f32> = (0..m).map(|_| rng.next() as f32).collect();
        xs.sort_by(f32::total_cmp);
        ColorMap::Points(
            xs.iter()
                .map(|&x| [x, rng.next() as f32, rng.next() as f32, rng.next() as f32])
                .collect(),
        )
    };
    TransferFunction::new([w0 as f32, w1 as f32], opacity, colormap).unwrap()
}

/// A session on `store` (`dims` voxels, `[x, y, z]`) with engine bricks of
/// `brick`, and its scene: with the brick ranges seven times in ten.
fn open_scene(
    store: &Path,
    dims: [u64; 3],
    brick: u64,
    rng: &mut Rng,
) -> (Session, Scene, [f64; 3]) {
    let cfg = VmConfig {
        brick: [brick; 3],
        apron: 1,
        pool_bytes: 64 << 20,
        ..Default::default()
    };
    let s = Session::open(store, cfg, 16 << 20, 2).unwrap();
    let pyramid: Vec<Volume> = (0..)
        .map_while(|l| Volume::from_store(store, l, 0).ok())
        .collect();
    let extent = world_extent(dims, pyramid[0].spacing);
    let mut scene = Scene::new(extent, pyramid.iter().map(|v| v.dims).collect());
    if rng.next() < 0.7 {
        scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 20)));
    }
    (s, scene, extent)
}

/// A camera fitted to `extent` from a random direction.
fn orbit(rng: &mut Rng, extent: [f64; 3], proj: Projection) -> Camera {
    Camera::fit(
        extent,
        rng.range(-180.0, 180.0),
        rng.range(-80.0, 80.0),
        proj,
    )
}

/// A 64×48 DVR through `cam` and `tf` at a random sampling rate, and its
/// level of detail: level 0 with probability `fixed`, else automatic with
/// a bias from −1 to `bias_hi`.
fn random_view(
    rng: &mut Rng,
    cam: Camera,
    tf: TransferFunction,
    fixed: f64,
    bias_hi: f64,
) -> (RenderParams, Lod) {
    let mut p = RenderParams::new(64, 48, cam, tf, RenderMode::Dvr);
    p.samples_per_voxel = [1.0, 0.5, 2.0, 1.7][rng.int(0, 3) as usize];
    let lod = if rng.next() < fixed {
        Lod::Fixed(0)
    } else {
        Lod::Auto {
            bias: rng.range(-1.0, bias_hi),
        }
    };
    (p, lod)
}

/// Pixels of `a` and `b` whose bits differ.
fn bits_differ(a: &Image, b: &Image) -> usize {
    a.rgba
        .iter()
        .zip(&b.rgba)
        .filter(|(a, b)| a.map(f32::to_bits) != b.map(f32::to_bits))
        .count()
}

/// Frames until complete.
fn converge(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> Image {
    for _ in 0..400 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
        s.finish_frame(reqs.iter());
        if st.completeness() == 1.0 {
            return img;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("never complete");
}

/// A random scene of `dtype` and `dims` (`[x, y, z]`) as a store in `dir`:
/// its session, scene, view (perspective or orthographic, from any
/// direction, random transfer function and sampling rate) and LOD.
fn random_scene(
    dir: &Path,
    rng: &mut Rng,
    dtype: DType,
    dims: [u64; 3],
) -> (Session, Scene, RenderParams, Lod) {
    let (store, range) = random_store(dir, rng, dims, dtype);
    let brick = [8, 16][rng.int(0, 1) as usize];
    let (s, scene, extent) = open_scene(&store, dims, brick, rng);
    let tf = random_tf(rng, range);
    let proj = if rng.next() < 0.7 {
        Projection::Perspective {
            fov_y_deg: rng.range(20.0, 60.0),
        }
    } else {
        Projection::Orthographic {
            height: extent.iter().cloned().fold(0.0, f64::max) * rng.range(0.8, 1.6),
        }
    };
    let cam = orbit(rng, extent, proj);
    let (p, lod) = random_view(rng, cam, tf, 0.7, 1.0);
    (s, scene, p, lod)
}

#[test]
fn lanes_equal_the_scalar_twin_on_random_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(0x1a7e_5eed);
    let mut lit_scenes = 0;
    for scene_no in 0..12 {
        let dtype = [DType::U8, DType::U16, DType::F32][scene_no % 3];
        let dims = [0; 3].map(|_| rng.int(20, 56));
        let (mut s, scene, p, lod) = random_scene(dir.path(), &mut rng, dtype, dims);
        let img = converge(&mut s, &scene, &p, lod);
        let mut twin = scene.clone();
        twin.lanes = false;
        s.begin_frame();
        let (want, st, reqs) = render_frame(s.vm(), &twin, &p, lod);
        s.finish_frame(reqs.iter());
        assert_eq!(st.completeness(), 1.0);
        let diff = img.max_abs_diff(&want);
        assert!(
            diff <= 1e-6,
            "scene {scene_no} ({dtype:?}, {dims:?}, {lod:?}): max abs diff {diff}"
        );
        lit_scenes += (img.coverage(0.01) > 0.02) as u32;
    }
    assert!(
        lit_scenes >= 8,
        "only {lit_scenes} of 12 scenes show something"
    );
}

/// The x86-64-v3 copy of the ray loop (`brickyard_render::isa`) gives the
/// baseline build's bits, lanes and scalar, on the random scenes of
/// `lanes_equal_the_scalar_twin_on_random_scenes`. On an x86-64 processor
/// without those instructions both would be the baseline: the test says so
/// rather than compare a build with itself.
#[test]
fn the_x86_64_v3_copy_gives_the_baseline_bits() {
    if cfg!(target_arch = "x86_64") {
        assert!(
            brickyard_render::isa::x86_64_v3(),
            "this processor lacks x86-64-v3 (AVX2, FMA, BMI1/2, LZCNT, MOVBE, F16C): \
             only the baseline ray loop can run here, so there is nothing to compare"
        );
    } else {
        assert!(!brickyard_render::isa::x86_64_v3());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(0x5e30_fa11);
    let mut lit_scenes = 0;
    for scene_no in 0..10 {
        let dtype = [DType::U8, DType::U16, DType::F32][scene_no % 3];
        let dims = [0; 3].map(|_| rng.int(20, 56));
        let (mut s, scene, p, lod) = random_scene(dir.path(), &mut rng, dtype, dims);
        let img = converge(&mut s, &scene, &p, lod);
        for lanes in [true, false] {
            let mut base = scene.clone();
            base.x86_v3 = false;
            base.lanes = lanes;
            let mut v3 = base.clone();
            v3.x86_v3 = true;
            let mut frame = |sc: &Scene| {
                s.begin_frame();
                let (img, st, reqs) = render_frame(s.vm(), sc, &p, lod);
                s.finish_frame(reqs.iter());
                assert_eq!(st.completeness(), 1.0);
                img
            };
            let (want, got) = (frame(&base), frame(&v3));
            let differ = bits_differ(&want, &got);
            assert_eq!(
                differ, 0,
                "scene {scene_no} ({dtype:?}, {dims:?}, lanes {lanes}): {differ} pixels differ"
            );
        }
        lit_scenes += (img.coverage(0.01) > 0.02) as u32;
    }
    assert!(
        lit_scenes >= 7,
        "only {lit_scenes} of 10 scenes show something"
    );
}

/// A sparse random volume: a few small balls whose value falls from the
/// centre, on a faint noisy background.
fn sparse_store(
    dir: &Path,
    rng: &mut Rng,
    dims: [u64; 3],
    dtype: DType,
) -> (std::path::PathBuf, [f32; 2]) {
    let balls: Vec<[f64; 4]> = (0..rng.int(2, 6))
        .map(|_| [rng.next(), rng.next(), rng.next(), rng.range(0.1, 0.3)])
        .collect();
    let field = move |p: [f64; 3], rng: &mut Rng| {
        let mut v = 0.1 * rng.next();
        for b in &balls {
            let d = ((p[0] - b[0]).powi(2) + (p[1] - b[1]).powi(2) + (p[2] - b[2]).powi(2)).sqrt();
            v = v.max(1.0 - d / b[3]);
        }
        v
    };
    store_of(dir, rng, dims, dtype, field)
}

/// Entry depths (`Scene::entry_depths`, the default) change no pixel: on
/// random scenes, cameras outside and inside the volume, fixed and
/// automatic levels, complete frames with and without them are equal
/// within 1e-6 (runs start at other steps, so positions differ by the
/// fixed point's rounding), rays walk fewer steps with them, and a frame
/// with them marks at least the pool slots the walk marks (the bricks rays
/// now pass before their entry are marked by the pre-pass).
#[test]
fn entry_depths_change_no_pixel_on_random_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(0x0e47_12d5);
    let (mut lit_scenes, mut steps_with, mut steps_without) = (0, 0u64, 0u64);
    for scene_no in 0..12 {
        let dtype = [DType::U8, DType::U16, DType::F32][scene_no % 3];
        let dims = [0; 3].map(|_| rng.int(40, 90));
        let (store, range) = sparse_store(dir.path(), &mut rng, dims, dtype);
        let brick = [16, 32][rng.int(0, 1) as usize];
        let (mut s, scene, extent) = open_scene(&store, dims, brick, &mut rng);
        // Only the blobs' cores show: space to skip around them.
        let (lo, width) = (range[0] as f64, (range[1] - range[0]) as f64);
        let w0 = lo + width * rng.range(0.15, 0.5);
        let tf = TransferFunction::new(
            [w0 as f32, (w0 + width * rng.range(0.1, 0.5)) as f32],
            vec![
                [0.0, 0.0],
                [rng.range(0.02, 0.2) as f32, 0.0],
                [rng.range(0.2, 0.6) as f32, rng.range(0.3, 0.9) as f32],
                [1.0, rng.range(0.2, 1.0) as f32],
            ],
            ColorMap::Preset([Preset::Hot, Preset::Viridis][scene_no % 2]),
        )
        .unwrap();
        let proj = if scene_no % 4 == 3 {
            Projection::Orthographic {
                height: extent.iter().cloned().fold(0.0, f64::max) * rng.range(0.8, 1.6),
            }
        } else {
            Projection::Perspective {
                fov_y_deg: rng.range(20.0, 60.0),
            }
        };
        let cam = if scene_no % 4 == 1 {
            // The eye inside the volume: boxes behind it and beside it.
            let eye = [0, 1, 2].map(|a| extent[a] * rng.range(0.2, 0.8));
            let target = [0, 1, 2].map(|a| extent[a] * rng.next());
            Camera::look_at(eye, target, [0.0, 0.0, 1.0], proj)
        } else {
            orbit(&mut rng, extent, proj)
        };
        let (p, lod) = random_view(&mut rng, cam, tf, 0.6, 1.5);
        let img = converge(&mut s, &scene, &p, lod);
        let mut walk = scene.clone();
        walk.entry_depths = false;
        let mut frame = |sc: &Scene| {
            s.begin_frame();
            let (img, st, reqs) = render_frame(s.vm(), sc, &p, lod);
            let slots = s.finish_frame(reqs.iter()).frame.exact_slots;
            assert_eq!(st.completeness(), 1.0);
            (img, st, slots)
        };
        let (want, st_walk, slots_walk) = frame(&walk);
        let (got, st, slots) = frame(&scene);
        let diff = got.max_abs_diff(&want).max(img.max_abs_diff(&want));
        assert!(
            diff <= 1e-6,
            "scene {scene_no} ({dtype:?}, {dims:?}, {lod:?}): max abs diff {diff}"
        );
        assert!(
            slots >= slots_walk,
            "scene {scene_no}: {slots} slots marked, the walk marks {slots_walk}"
        );
        steps_with += st.steps;
        steps_without += st_walk.steps;
        lit_scenes += (img.coverage(0.01) > 0.02) as u32;
    }
    assert!(
        lit_scenes >= 8,
        "only {lit_scenes} of 12 scenes show something"
    );
    assert!(
        steps_with * 2 < steps_without,
        "{steps_with} steps with entry depths, {steps_without} without"
    );
}

/// A ray that meets no entry box at the level rays start at may still
/// show something where the level turns coarser along it: a coarse
/// voxel's average spreads a lone bright voxel over more space than the
/// fine cells that hold it. Frames with entry depths equal the walk's on
/// such volumes (lone bright voxels, a transfer function that shows
/// faint values) under automatic levels that change inside the volume;
/// the rays with no entry are skipped only where no level change follows.
#[test]
fn rays_without_an_entry_still_walk_where_the_level_changes() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(0x5eed_0f1a);
    let (mut differs_from_level_0, mut lit) = (0, 0);
    for scene_no in 0..8 {
        let dims = [64, 64, 64];
        // Each spot the second voxel of an 8³ cell: a neighbouring cell's
        // range (its voxels and the next one) misses it, and the coarse
        // voxels holding it reach past its cell's low faces.
        let spots: Vec<[u64; 3]> = (0..20)
            .map(|_| [0; 3].map(|_| 8 * rng.int(1, 6) + 1))
            .collect();
        let (store, _) = store_of(dir.path(), &mut rng, dims, DType::U8, |p, _| {
            let v = p.map(|c| (c * 64.0).round() as u64);
            spots.contains(&v) as u8 as f64
        });
        let (mut s, mut scene, extent) = open_scene(&store, dims, 16, &mut rng);
        scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 20)));
        let tf = TransferFunction::new(
            [0.0, 255.0],
            vec![[0.0, 0.0], [0.003, 0.0], [0.03, 0.9], [1.0, 1.0]],
            ColorMap::Preset(Preset::Hot),
        )
        .unwrap();
        let proj = Projection::Perspective {
            fov_y_deg: rng.range(25.0, 50.0),
        };
        // The eye inside the volume: level 0 near it, coarser levels
        // (whose voxels spread a spot over several cells) farther on.
        let eye = [0, 1, 2].map(|a| extent[a] * rng.range(0.3, 0.7));
        // Looking at a spot (`[x, y, z]` voxel, world `[x, y, z]`).
        let spot = spots[rng.int(0, 9) as usize];
        let target = [0, 1, 2].map(|a| (spot[a] as f64 + 0.5) / dims[a] as f64 * extent[a]);
        let cam = Camera::look_at(eye, target, [0.0, 0.0, 1.0], proj);
        let p = RenderParams::new(128, 96, cam, tf, RenderMode::Dvr);
        let lod = Lod::Auto {
            bias: [3.5, 4.0, 4.5][scene_no % 3],
        };
        let mut walk = scene.clone();
        walk.entry_depths = false;
        // Level 0 first: its bricks resident, so that the entries are
        // the cells', not whole bricks' that are not resident.
        let level_0 = converge(&mut s, &scene, &p, Lod::Fixed(0));
        let want = converge(&mut s, &walk, &p, lod);
        let got = converge(&mut s, &scene, &p, lod);
        let diff = got.max_abs_diff(&want);
        assert!(
            diff <= 1e-6,
            "scene {scene_no} ({lod:?}): max abs diff {diff}"
        );
        differs_from_level_0 += (level_0.max_abs_diff(&want) > 0.05) as u32;
        lit += (want.coverage(0.01) > 0.005) as u32;
    }
    // The levels do change inside these views, and the spots show.
    assert!(differs_from_level_0 >= 5, "{differs_from_level_0} of 8");
    assert!(lit >= 6, "{lit} of 8");
}

/// MIP: the switches and shortcuts that must not change a pixel, on random
/// scenes (dense and sparse volumes of u8, u16 and f32, random transfer
/// functions whose windows often end below the data's maximum, any camera,
/// fixed and automatic levels, ranges or none):
///
/// - a ray ends once its maximum saturates the window: the complete frame
///   equals, bit for bit, the transfer function's colours of the raw maxima
///   (`RenderParams::mip_values`, where no ray ends early), with fewer
///   samples over the scenes;
/// - blocks of bricks that cannot raise a ray's maximum are crossed in one
///   landing: the frame equals the one without the store's ranges (no brick
///   crossed at all) within 1e-6;
/// - the runs' samples in lanes, and the x86-64-v3 copy, give the scalar
///   baseline's bits.
#[test]
fn mip_shortcuts_change_no_pixel_on_random_scenes() {
    use brickyard_render::optics::mip_color;
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(0x31b0_57a7);
    let (mut lit, mut saturated, mut cut) = (0, 0, 0);
    let (mut samples_stop, mut samples_raw) = (0u64, 0u64);
    for scene_no in 0..12 {
        let dtype = [DType::U8, DType::U16, DType::F32][scene_no % 3];
        let dims = [0; 3].map(|_| rng.int(24, 64));
        let (store, range) = if scene_no % 2 == 0 {
            random_store(dir.path(), &mut rng, dims, dtype)
        } else {
            sparse_store(dir.path(), &mut rng, dims, dtype)
        };
        let brick = [8, 16][rng.int(0, 1) as usize];
        let (mut s, scene, extent) = open_scene(&store, dims, brick, &mut rng);
        let tf = random_tf(&mut rng, range);
        let proj = if rng.next() < 0.7 {
            Projection::Perspective {
                fov_y_deg: rng.range(20.0, 60.0),
            }
        } else {
            Projection::Orthographic {
                height: extent.iter().cloned().fold(0.0, f64::max) * rng.range(0.8, 1.6),
            }
        };
        let cam = orbit(&mut rng, extent, proj);
        let (mut p, lod) = random_view(&mut rng, cam, tf.clone(), 0.6, 1.0);
        p.mode = RenderMode::Mip;
        let img = converge(&mut s, &scene, &p, lod);
        let mut frame = |sc: &Scene, p: &RenderParams| {
            s.begin_frame();
            let (img, st, reqs) = render_frame(s.vm(), sc, p, lod);
            s.finish_frame(reqs.iter());
            assert_eq!(st.completeness(), 1.0, "scene {scene_no}");
            (img, st)
        };
        let what = format!("scene {scene_no} ({dtype:?}, {dims:?}, {lod:?})");
        let (got, st) = frame(&scene, &p);
        // The raw maxima, coloured here.
        let mut raw_p = p.clone();
        raw_p.mip_values = true;
        let (raw, st_raw) = frame(&scene, &raw_p);
        let mut differ = 0;
        for (i, (px, r)) in got.rgba.iter().zip(&raw.rgba).enumerate() {
            let want = if r[3] == 0.0 {
                [0.0; 4]
            } else {
                mip_color(&tf, true, r[0])
            };
            if px.map(f32::to_bits) != want.map(f32::to_bits) {
                differ += 1;
                if differ < 4 {
                    eprintln!("{what}: pixel {i}: {px:?}, the raw maximum's colour {want:?}");
                }
            }
            saturated += (r[0] >= tf.window[1]) as u32;
        }
        assert_eq!(
            differ, 0,
            "{what}: {differ} pixels differ from the raw maxima's colours"
        );
        assert!(st.samples <= st_raw.samples, "{what}");
        samples_stop += st.samples;
        cut += ((st.samples as f64) < 0.9 * st_raw.samples as f64) as u32;
        samples_raw += st_raw.samples;
        // Without ranges: no brick crossed, no block.
        let mut bare = scene.clone();
        bare.ranges = None;
        let (want, _) = frame(&bare, &p);
        let d = got.max_abs_diff(&want).max(img.max_abs_diff(&want));
        assert!(
            d <= 1e-6,
            "{what}: max abs diff {d} to the frame without ranges"
        );
        // Lanes and the x86-64-v3 copy: the scalar baseline's bits.
        let mut base = scene.clone();
        base.lanes = false;
        base.x86_v3 = false;
        let (want, _) = frame(&base, &p);
        let differ = bits_differ(&want, &got);
        assert_eq!(
            differ, 0,
            "{what}: {differ} pixels differ from the scalar baseline"
        );
        lit += (img.coverage(0.5) > 0.05) as u32;
    }
    assert!(lit >= 8, "only {lit} of 12 scenes show something");
    assert!(
        saturated > 1000,
        "only {saturated} pixels saturate: nothing ends early"
    );
    // Behind a saturated maximum most cells and bricks are crossed anyway
    // (their maxima cannot raise it); ending the ray saves the rest.
    assert!(
        (samples_stop as f64) < 0.97 * samples_raw as f64 && cut >= 3,
        "{samples_stop} samples with rays ending at saturation, {samples_raw} without; \
         {cut} scenes with a tenth fewer"
    );
}

/// A MIP of two channels walks both through one frame: each channel's
/// rays end where its own window saturates and cross blocks of bricks by
/// its own maxima. Channel 0 is dark but for a few balls (its blocks
/// mostly zero), channel 1 a field that is bright everywhere; windows end
/// below the data's top. Complete frames equal the in-core reference of
/// the channels added up, and the frame whose rays walk on (`mip_values`).
#[test]
fn mip_of_channels_ends_and_crosses_by_each_channels_own_window_and_maxima() {
    use brickyard_render::reference::{render_channels, ChannelStyle};
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng(0xc4a2_e1b5);
    let dims = [48u64, 40, 56];
    let n = (dims[0] * dims[1] * dims[2]) as usize;
    for scene_no in 0..6 {
        let (sparse, _) = sparse_store(dir.path(), &mut rng, dims, DType::U8);
        // Two channels, channel-major: the balls (their faint background
        // zero), then planes across x every 16 voxels, brighter further
        // on, over a grey background (its bricks between the planes
        // cannot raise a ray's maximum; channel 0's blocks there could).
        let mut bytes: Vec<u8> = Volume::from_store(&sparse, 0, 0)
            .unwrap()
            .data
            .iter()
            .map(|&x| if x < 40.0 { 0 } else { x as u8 })
            .collect();
        let phase = rng.int(0, 15);
        for _z in 0..dims[2] {
            for _y in 0..dims[1] {
                for x in 0..dims[0] {
                    bytes.push(if (x + phase).is_multiple_of(16) {
                        (120 + 2 * x) as u8
                    } else {
                        50
                    });
                }
            }
        }
        assert_eq!(bytes.len(), 2 * n);
        let raw_path = dir.path().join(format!("two-{scene_no}.raw"));
        let store = raw_store(&raw_path, &bytes, (dims, DType::U8, 2), None);
        let cfg = VmConfig {
            brick: [8; 3],
            apron: 1,
            pool_bytes: 64 << 20,
            ..Default::default()
        };
        let mut s = Session::open(&store, cfg, 16 << 20, 2).unwrap();
        let vols: Vec<Volume> = (0..2)
            .map(|c| Volume::from_store(&store, 0, c).unwrap())
            .collect();
        let extent = vols[0].extent();
        let levels = (0..)
            .map_while(|l| Volume::from_store(&store, l, 0).ok())
            .map(|v| v.dims)
            .collect();
        let mut scene = Scene::new(extent, levels);
        scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 20)));
        let cam = orbit(
            &mut rng,
            extent,
            Projection::Perspective { fov_y_deg: 40.0 },
        );
        // The transfer function is not used with channels: its window is
        // below both channels' tops.
        let tf = TransferFunction::preset("linear", [0.0, 60.0]).unwrap();
        let mut p = RenderParams::new(64, 48, cam, tf, RenderMode::Mip);
        p.channels = vec![
            ChannelStyle::new(0, [1.0, 0.3, 0.0], [0.0, rng.range(150.0, 255.0) as f32]),
            // Half the scenes: channel 1 never saturates, its rays cross
            // the most blocks.
            ChannelStyle::new(
                1,
                [0.0, 0.6, 1.0],
                [20.0, [255.0, rng.range(90.0, 200.0) as f32][scene_no % 2]],
            ),
        ];
        let img = converge(&mut s, &scene, &p, Lod::Fixed(0));
        let want = render_channels(&vols, &p);
        let d = img.max_abs_diff(&want);
        assert!(
            d <= 1e-5,
            "scene {scene_no}: max abs diff {d} to the reference"
        );
        let mut walk_on = p.clone();
        walk_on.mip_values = true;
        let walked = converge(&mut s, &scene, &walk_on, Lod::Fixed(0));
        let differ = bits_differ(&walked, &img);
        assert_eq!(
            differ, 0,
            "scene {scene_no}: {differ} pixels differ from walking on"
        );
        // Both channels show.
        let sum = |c: usize| img.rgba.iter().map(|px| px[c] as f64).sum::<f64>();
        assert!(
            sum(0) > 5.0 && sum(2) > 5.0,
            "scene {scene_no}: a channel is missing"
        );
    }
}
