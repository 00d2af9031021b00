//! DVR through the residency octree: complete frames equal the page-table
//! traversal and the in-core reference for 1, 3 and 16 channels, the
//! octree kept from the virtual
//! memory's events frame by frame; nodes are really skipped; debug images.

use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::camera::{world_extent, Camera, Projection, Vec3};
use brickyard_core::{DType, Dims3, TransferFunction};
use brickyard_render::cpu::{render_frame, FrameStats, Lod, Scene};
use brickyard_render::image::Image;
use brickyard_render::octree::Octree;
use brickyard_render::params::{DebugCounts, Traversal};
use brickyard_render::reference::{
    render_channels, ChannelStyle, RenderMode, RenderParams, Volume,
};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, RwLock};

const TOLERANCE: f32 = 1e-4;
const DIMS: Dims3 = [40, 48, 64];

/// An `n`-channel u8 store: channel `c` holds the Mandelbulb's values
/// (Marschner–Lobb for odd `c`) in the `c`-th of `n` overlapping bands,
/// rescaled to 60–255, 0 elsewhere (the fixture of `multichannel.rs`).
fn banded_store(dir: &Path, n: usize) -> (PathBuf, Vec3, Vec<Dims3>) {
    let dims = DIMS;
    let raw = dir.join(format!("banded{n}.raw"));
    let kinds: Vec<Vec<f64>> = [Kind::Mandelbulb, Kind::MarschnerLobb]
        .into_iter()
        .take(n.min(2))
        .map(|k| {
            let g = Procedural::new(k, dims, DType::U8);
            let mut v = vec![];
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
    let mut bytes = vec![];
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

fn dvr_params(extent: Vec3, n: usize) -> RenderParams {
    let cam = Camera::fit(
        extent,
        35.0,
        25.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let tf = TransferFunction::preset("soft", [0.0, 255.0]).unwrap();
    let mut p = RenderParams::new(56, 48, cam, tf, RenderMode::Dvr);
    p.channels = (0..n)
        .map(|c| {
            let h = c as f32 / n as f32 * 6.0;
            let col = [
                ((h - 3.0).abs() - 1.0).clamp(0.0, 1.0),
                (2.0 - (h - 2.0).abs()).clamp(0.0, 1.0),
                (2.0 - (h - 4.0).abs()).clamp(0.0, 1.0),
            ];
            ChannelStyle::new(c, col, [0.0, 255.0])
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

/// CPU frames until complete, the octree (if any) synced after each;
/// the image and the last frame's figures.
fn converge(s: &mut Session, scene: &Scene, p: &RenderParams, lod: Lod) -> (Image, FrameStats) {
    for _ in 0..600 {
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), scene, p, lod);
        s.finish_frame(reqs.iter());
        if let Some(o) = &scene.octree {
            o.write().unwrap().sync(s.vm_mut());
        }
        if st.completeness() == 1.0 && st.samples > 0 {
            return (img, st);
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!("the view never completed ({} channels)", p.channels.len());
}

fn not_blank(img: &Image, what: &str) {
    let a: f64 = img.rgba.iter().map(|px| px[3] as f64).sum();
    assert!(
        a > 0.05 * img.rgba.len() as f64,
        "{what}: image nearly empty (alpha sum {a})"
    );
}

fn reference(store: &Path, p: &RenderParams, level: usize) -> Image {
    let vols: Vec<Volume> = p
        .channels
        .iter()
        .map(|c| Volume::from_store(store, level, c.channel).unwrap())
        .collect();
    render_channels(&vols, p)
}

/// A session with the store's ranges and an octree of `depth` attached.
fn open(store: &Path, scene: &mut Scene, pool: u64, depth: u32) -> Session {
    let mut s = Session::open(store, cfg(pool), 8 << 20, 2).unwrap();
    let ranges = Arc::new(s.loader().brick_ranges(1 << 20));
    scene.ranges = Some(ranges.clone());
    let levels = scene.levels.clone();
    let o = Octree::attach(depth, &levels, s.vm_mut(), Some(&ranges)).unwrap();
    scene.octree = Some(Arc::new(RwLock::new(o)));
    s
}

#[test]
fn octree_frames_equal_page_table_frames_and_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    for n in [1usize, 3, 16] {
        let (store, extent, levels) = banded_store(dir.path(), n);
        let mut p = dvr_params(extent, n);
        if n == 1 {
            // One channel through the one-channel path (no channel list).
            p.tf = p.channels[0].dvr_tf();
            p.channels.clear();
        }
        let want = if n == 1 {
            brickyard_render::render(&Volume::from_store(&store, 0, 0).unwrap(), &p)
        } else {
            reference(&store, &p, 0)
        };
        not_blank(&want, &format!("{n} channels, reference"));
        let vol_bytes = n as u64 * DIMS.iter().product::<u64>();
        // A pool twice the volume, octrees of depth 4 and 3.
        for (pool, depth) in [(2 * vol_bytes, 4), (2 * vol_bytes, 3)] {
            let mut scene = Scene::new(extent, levels.clone());
            let mut s = open(&store, &mut scene, pool, depth);
            p.traversal = Traversal::PageTable;
            let (pt, pst) = converge(&mut s, &scene, &p, Lod::Fixed(0));
            p.traversal = Traversal::Octree;
            let (oc, ost) = converge(&mut s, &scene, &p, Lod::Fixed(0));
            let (d_pt, d_oc, d_both) = (
                pt.max_abs_diff(&want),
                oc.max_abs_diff(&want),
                oc.max_abs_diff(&pt),
            );
            eprintln!(
                "{n} channels, pool {pool}, depth {depth}: octree vs reference {d_oc}, vs page table {d_both} \
                 (page table vs reference {d_pt}); samples {} vs {}, nodes {} visited, {} skipped",
                ost.samples, pst.samples, ost.octree_nodes, ost.skipped_nodes
            );
            assert!(d_pt <= TOLERANCE && d_oc <= TOLERANCE && d_both <= TOLERANCE);
            assert!(ost.octree_nodes > 0 && ost.samples > 0);
            // Fresh from the virtual memory, the octree is what was kept.
            let o = scene.octree.as_ref().unwrap().read().unwrap();
            let fresh = Octree::of_vm(depth, &levels, s.vm(), scene.ranges.as_deref()).unwrap();
            assert_eq!(o.mask, fresh.mask);
            let bits = |r: &[[f32; 2]]| -> Vec<[u32; 2]> {
                r.iter().map(|x| x.map(f32::to_bits)).collect()
            };
            assert_eq!(bits(&o.range), bits(&fresh.range), "ranges kept vs fresh");
        }
    }
}

#[test]
fn an_octree_built_on_the_fly_and_automatic_lod_agree_with_page_tables() {
    // No octree in the scene (the frame builds one); automatic level of
    // detail; transfer functions that hide all but the top values, so
    // that nodes whose statistics stay below them are skipped: the
    // octree's frames equal the page table's.
    let dir = tempfile::tempdir().unwrap();
    let (store, extent, levels) = banded_store(dir.path(), 3);
    let mut p = dvr_params(extent, 3);
    for c in &mut p.channels {
        c.tf = Some(
            TransferFunction::from_json(
                r#"{"window": [0, 255], "opacity": [[0, 0], [0.94, 0], [1, 0.9]], "colormap": "grayscale"}"#,
            )
            .unwrap(),
        );
    }
    let mut scene = Scene::new(extent, levels);
    let mut s = Session::open(&store, cfg(1 << 24), 8 << 20, 2).unwrap();
    scene.ranges = Some(Arc::new(s.loader().brick_ranges(1 << 20)));
    for lod in [Lod::Fixed(0), Lod::Auto { bias: 0.0 }] {
        p.traversal = Traversal::PageTable;
        let (pt, _) = converge(&mut s, &scene, &p, lod);
        let shown = pt.rgba.iter().filter(|px| px[3] > 0.05).count();
        assert!(
            lod != Lod::Fixed(0) || shown > 20,
            "{shown} pixels show anything"
        );
        p.traversal = Traversal::Octree;
        let (oc, st) = converge(&mut s, &scene, &p, lod);
        let d = oc.max_abs_diff(&pt);
        eprintln!(
            "{lod:?}: octree vs page table {d}, {} nodes visited, {} skipped; {shown} pixels show",
            st.octree_nodes, st.skipped_nodes
        );
        assert!(d <= TOLERANCE, "{d}");
        if lod == Lod::Fixed(0) {
            assert!(st.skipped_nodes > 0, "no node skipped");
            let want = reference(&store, &p, 0);
            let dr = oc.max_abs_diff(&want);
            assert!(dr <= TOLERANCE, "octree vs reference {dr}");
        }
    }
}

#[test]
fn ranges_from_resident_voxels_let_the_octree_skip_where_statistics_did_not() {
    // The banded volume has empty (0) regions smaller than a brick: with
    // node ranges from the store's statistics the default transfer
    // function hides no node of one channel; with ranges from the
    // resident voxels nodes are skipped, and complete frames still equal
    // the page tables and the in-core reference. Three channels: channel
    // 0 holds 60 (not 0) where the Mandelbulb is empty, so transfer
    // functions hiding values below 30% of the window; more nodes skipped
    // than with the statistics.
    let dir = tempfile::tempdir().unwrap();
    for n in [1usize, 3] {
        let (store, extent, levels) = banded_store(dir.path(), n);
        let mut p = dvr_params(extent, n);
        if n == 1 {
            p.tf = p.channels[0].dvr_tf();
            p.channels.clear();
        } else {
            for c in &mut p.channels {
                c.tf = Some(
                    TransferFunction::from_json(
                        r#"{"window": [0, 255], "opacity": [[0, 0], [0.3, 0], [1, 0.8]], "colormap": "grayscale"}"#,
                    )
                    .unwrap(),
                );
            }
        }
        let vol_bytes = n as u64 * DIMS.iter().product::<u64>();
        for lod in [Lod::Fixed(0), Lod::Auto { bias: 0.0 }] {
            let mut scene = Scene::new(extent, levels.clone());
            let mut s = open(&store, &mut scene, 2 * vol_bytes, 4);
            p.traversal = Traversal::PageTable;
            let (pt, _) = converge(&mut s, &scene, &p, lod);
            p.traversal = Traversal::Octree;
            let (oc, ost) = converge(&mut s, &scene, &p, lod);
            // The same octree with the statistics' ranges, one frame more
            // (everything it needs is resident).
            let mut stats_tree = scene.octree.as_ref().unwrap().read().unwrap().clone();
            assert!(stats_tree.read_bricks() > 0);
            stats_tree.range = Octree::new(4, &levels, [16; 3], n, scene.ranges.as_deref())
                .unwrap()
                .range;
            let mut stats_scene = Scene::new(extent, levels.clone());
            stats_scene.ranges = scene.ranges.clone();
            stats_scene.octree = Some(Arc::new(RwLock::new(stats_tree)));
            s.begin_frame();
            let (os, sst, reqs) = render_frame(s.vm(), &stats_scene, &p, lod);
            s.finish_frame(reqs.iter());
            assert_eq!(sst.completeness(), 1.0);
            let d_oc = oc.max_abs_diff(&pt);
            let d_os = os.max_abs_diff(&pt);
            eprintln!(
                "{n} channels, {lod:?}: skipped nodes {} (statistics: {}), visited {} ({}), \
                 samples {} ({}); octree vs page table {d_oc} ({d_os})",
                ost.skipped_nodes,
                sst.skipped_nodes,
                ost.octree_nodes,
                sst.octree_nodes,
                ost.samples,
                sst.samples,
            );
            if n == 1 {
                assert_eq!(sst.skipped_nodes, 0, "statistics skipped");
            }
            assert!(
                ost.skipped_nodes > sst.skipped_nodes,
                "no more nodes skipped"
            );
            assert!(ost.samples < sst.samples, "no sample saved");
            assert!(d_oc <= TOLERANCE && d_os <= TOLERANCE, "{d_oc} {d_os}");
            if lod == Lod::Fixed(0) {
                let want = if n == 1 {
                    brickyard_render::render(&Volume::from_store(&store, 0, 0).unwrap(), &p)
                } else {
                    reference(&store, &p, 0)
                };
                not_blank(&want, "reference");
                let dr = oc.max_abs_diff(&want);
                assert!(dr <= TOLERANCE, "octree vs reference {dr}");
            }
        }
    }
}

#[test]
fn debug_images_count_nodes_bricks_and_steps() {
    let dir = tempfile::tempdir().unwrap();
    let (store, extent, levels) = banded_store(dir.path(), 3);
    let mut p = dvr_params(extent, 3);
    let mut scene = Scene::new(extent, levels);
    let mut s = open(&store, &mut scene, 1 << 24, 4);
    p.traversal = Traversal::Octree;
    converge(&mut s, &scene, &p, Lod::Fixed(0));
    for d in [DebugCounts::Nodes, DebugCounts::Bricks, DebugCounts::Steps] {
        p.debug = Some(d);
        s.begin_frame();
        let (img, st, reqs) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
        s.finish_frame(reqs.iter());
        // Opaque everywhere; black where rays miss the volume (corners),
        // coloured where they cross it; some pixel at the top (white).
        assert!(img.rgba.iter().all(|px| px[3] == 1.0), "{d:?}");
        let black = img.rgba.iter().filter(|px| px[..3] == [0.0; 3]).count();
        let white = img.rgba.iter().filter(|px| px[..3] == [1.0; 3]).count();
        assert!(
            black > 0 && black < img.rgba.len() * 3 / 4,
            "{d:?}: {black} black"
        );
        assert!(white > 0, "{d:?}: no pixel at the largest count");
        assert!(st.octree_nodes > 0);
    }
    // Page tables visit no nodes: all black.
    p.traversal = Traversal::PageTable;
    p.debug = Some(DebugCounts::Nodes);
    let (img, _, _) = render_frame(s.vm(), &scene, &p, Lod::Fixed(0));
    assert!(img.rgba.iter().all(|px| px[..3] == [0.0; 3]));
}

/// Small deterministic generator (xorshift).
struct Rng(u64);
impl Rng {
    fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0 % n
    }
}

#[test]
fn device_octree_passes_equal_the_cpu_model_over_random_sequences() {
    use brickyard_cache::brick::BrickKey;
    use brickyard_cache::ranges::{BrickRanges, LevelRanges};
    use brickyard_render::octree::device::DeviceOctree;
    use brickyard_render::octree::Event;
    let Some(gpu) = brickyard_gpu::context::test_gpu() else {
        return;
    };
    // Odd sizes (bricks and nodes do not line up), a level without
    // statistics, a few unknown brick ranges.
    let dims: Vec<Dims3> = vec![[37, 50, 61], [19, 25, 31], [10, 13, 16], [5, 7, 8]];
    let brick = [8u64; 3];
    let channels = 3;
    let mut rng = Rng(0x5eed);
    let ranges = BrickRanges {
        levels: dims
            .iter()
            .enumerate()
            .map(|(l, d)| {
                (l != 2).then(|| {
                    let nb = d.map(|x| x.div_ceil(8));
                    let n = nb.iter().product::<u64>() as usize * channels;
                    LevelRanges {
                        bricks: nb,
                        channels,
                        range: (0..n)
                            .map(|i| {
                                if l == 1 && i % 53 == 7 {
                                    [f32::NAN; 2]
                                } else {
                                    let a = rng.below(200) as f32;
                                    [a, a + rng.below(50) as f32]
                                }
                            })
                            .collect(),
                    }
                })
            })
            .collect(),
    };
    let same_ranges = |a: &[[f32; 2]], b: &[[f32; 2]]| {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(x, y)| (x[0].is_nan() && y[0].is_nan()) || (x[0] == y[0] && x[1] == y[1]))
    };
    let mut frames = 0;
    for depth in [1, 2, 3, 4] {
        let mut o = Octree::new(depth, &dims, brick, channels, Some(&ranges)).unwrap();
        let mut dev = DeviceOctree::new(&gpu, &o, Some(&ranges)).unwrap();
        let (_, _, r) = dev.read(&gpu).unwrap();
        assert!(same_ranges(&r, &o.range), "depth {depth}: ranges");
        let known = o.range.iter().filter(|r| !r[0].is_nan()).count();
        assert!(known > o.range.len() / 4, "depth {depth}: {known} known");
        let mut mapped: Vec<BrickKey> = vec![];
        for frame in 0..25 {
            let mut events = vec![];
            for _ in 0..rng.below(40) {
                let l = rng.below(dims.len() as u64) as usize;
                let nb = o.bricks(l);
                let key = BrickKey::new(
                    l as u8,
                    rng.below(channels as u64) as u16,
                    [0, 1, 2].map(|a| rng.below(nb[a]) as u32),
                );
                events.push(Event { key, mapped: true });
            }
            for _ in 0..rng.below(20).min(mapped.len() as u64) {
                let key = mapped[rng.below(mapped.len() as u64) as usize];
                events.push(Event { key, mapped: false });
            }
            let eff = o.effective(&events);
            for e in &eff {
                if e.mapped {
                    mapped.push(e.key);
                } else {
                    mapped.retain(|k| *k != e.key);
                }
            }
            o.pass(&eff);
            dev.update(&gpu, &eff);
            let (m, c, _) = dev.read(&gpu).unwrap();
            assert_eq!(c, o.count, "depth {depth}, frame {frame}: counters");
            assert_eq!(m, o.mask, "depth {depth}, frame {frame}: masks");
            frames += 1;
        }
        assert!(o.mask.iter().any(|&m| m != 0) && o.mapped_count() > 20);
        // The device's ranges are the statistics-only ones, which the CPU
        // model keeps when no voxels are read (`pass` alone, or `new`).
        let (_, _, r) = dev.read(&gpu).unwrap();
        let stats_only = Octree::new(depth, &dims, brick, channels, Some(&ranges)).unwrap();
        assert!(
            same_ranges(&r, &stats_only.range),
            "depth {depth}: ranges after"
        );
        assert!(same_ranges(&r, &o.range), "depth {depth}: ranges after");
    }
    assert_eq!(frames, 100);
}

/// Device frames with the host deciding updates (the octree follows the
/// host's virtual memory, synced after each frame as on the CPU), until
/// complete: the image and the last frame's figures.
fn converge_device(
    gpu: &brickyard_gpu::context::Gpu,
    s: &mut Session,
    scene: &Scene,
    p: &RenderParams,
    lod: Lod,
) -> (Image, FrameStats) {
    use brickyard_gpu::vm::DeviceVm;
    use brickyard_render::gpu::GpuRenderer;
    let mut renderer = GpuRenderer::new(gpu);
    let (mut dvm, _) = DeviceVm::new(gpu, s.vm_mut()).unwrap();
    for _ in 0..600 {
        s.begin_frame();
        let f = renderer.render(gpu, &dvm, s.vm(), scene, p, lod).unwrap();
        if let (Some(o), Traversal::Octree) = (&scene.octree, p.traversal) {
            // The masks the frame read: the device twin's, kept by its own
            // update passes from the events, equal to the host's.
            let (masks, _, _) = renderer.device_octree().unwrap().read(gpu).unwrap();
            assert_eq!(masks, o.read().unwrap().mask, "device and host masks");
        }
        s.finish_frame([&f.requests]);
        if let Some(o) = &scene.octree {
            o.write().unwrap().sync(s.vm_mut());
        }
        dvm.sync(gpu, s.vm_mut());
        if f.stats.completeness() == 1.0 && f.stats.samples > 0 {
            return (f.image, f.stats);
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    panic!(
        "the device's view never completed ({} channels)",
        p.channels.len()
    );
}

#[test]
fn device_octree_frames_equal_the_cpu_octree_page_tables_and_the_reference() {
    // The traversal of `octree/dvr.wgsl` against its CPU twin, the
    // device's page-table traversal and the in-core reference, for 1, 3
    // and 16 channels; then transfer functions that hide all but the top
    // values, where nodes are crossed unsampled on the device too.
    let Some(gpu) = brickyard_gpu::context::test_gpu() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let mut stores = std::collections::HashMap::new();
    for (n, sparse) in [(1usize, false), (3, false), (16, false), (3, true)] {
        let (store, extent, levels) = stores
            .entry(n)
            .or_insert_with(|| banded_store(dir.path(), n))
            .clone();
        let mut p = dvr_params(extent, n);
        if n == 1 {
            p.tf = p.channels[0].dvr_tf();
            p.channels.clear();
        }
        if sparse {
            for c in &mut p.channels {
                c.tf = Some(
                    TransferFunction::from_json(
                        r#"{"window": [0, 255], "opacity": [[0, 0], [0.94, 0], [1, 0.9]], "colormap": "grayscale"}"#,
                    )
                    .unwrap(),
                );
            }
        }
        let want = if n == 1 {
            brickyard_render::render(&Volume::from_store(&store, 0, 0).unwrap(), &p)
        } else {
            reference(&store, &p, 0)
        };
        if !sparse {
            not_blank(&want, &format!("{n} channels, reference"));
        } else {
            let shown = want.rgba.iter().filter(|px| px[3] > 0.05).count();
            assert!(shown > 20, "{shown} pixels show anything");
        }
        let pool = 2 * n as u64 * DIMS.iter().product::<u64>();
        let mut cpu_scene = Scene::new(extent, levels.clone());
        let mut cs = open(&store, &mut cpu_scene, pool, 4);
        p.traversal = Traversal::Octree;
        let (cpu, run_st) = converge(&mut cs, &cpu_scene, &p, Lod::Fixed(0));
        // The descent the device takes: no runs through resident bricks,
        // rays from the volume's face. The same image.
        let mut walk_scene = cpu_scene.clone();
        walk_scene.octree_runs = false;
        walk_scene.entry_depths = false;
        let (walked, cst) = converge(&mut cs, &walk_scene, &p, Lod::Fixed(0));
        let d_runs = walked.max_abs_diff(&cpu);
        assert!(
            d_runs <= 1e-5,
            "{n} channels: runs and entry depths change the image by {d_runs}"
        );
        // And they save descents: far fewer nodes visited.
        assert!(
            2 * run_st.octree_nodes < cst.octree_nodes,
            "{n} channels: {} nodes with runs, {} without",
            run_st.octree_nodes,
            cst.octree_nodes
        );
        let mut pt_scene = Scene::new(extent, levels.clone());
        let mut ps = open(&store, &mut pt_scene, pool, 4);
        p.traversal = Traversal::PageTable;
        let (pt, _) = converge_device(&gpu, &mut ps, &pt_scene, &p, Lod::Fixed(0));
        let mut scene = Scene::new(extent, levels.clone());
        let mut s = open(&store, &mut scene, pool, 4);
        p.traversal = Traversal::Octree;
        let (dev, dst) = converge_device(&gpu, &mut s, &scene, &p, Lod::Fixed(0));
        let (d_cpu, d_pt, d_ref) = (
            dev.max_abs_diff(&cpu),
            dev.max_abs_diff(&pt),
            dev.max_abs_diff(&want),
        );
        eprintln!(
            "{n} channels (sparse: {sparse}): device octree vs CPU octree {d_cpu}, vs device page tables {d_pt}, \
             vs reference {d_ref}; nodes visited {} (CPU {}), crossed unsampled {} (CPU {}), samples {} (CPU {})",
            dst.octree_nodes, cst.octree_nodes, dst.skipped_nodes, cst.skipped_nodes, dst.samples, cst.samples
        );
        // The device's page tables and octree: the same samples. Against
        // the CPU: the device's f32 positions, which the steep transfer
        // functions of the sparse case (opacity 0 to 0.9 over 6% of the
        // window) turn into up to 2e-4 for both device traversals alike.
        let cpu_tol = if sparse { 1e-3 } else { TOLERANCE };
        assert!(
            d_pt <= TOLERANCE && d_cpu <= cpu_tol && d_ref <= cpu_tol,
            "{d_cpu} {d_pt} {d_ref}"
        );
        assert!(dst.octree_nodes > 0, "no node visited");
        if sparse {
            assert!(dst.skipped_nodes > 0, "no node crossed unsampled");
        }
        // The same descent on both sides: node counts within 1% (rays may
        // round differently at a node's face).
        let rel =
            (dst.octree_nodes as f64 - cst.octree_nodes as f64).abs() / cst.octree_nodes as f64;
        assert!(
            rel < 0.01,
            "nodes visited: device {} vs CPU {}",
            dst.octree_nodes,
            cst.octree_nodes
        );
    }
}

#[test]
fn per_channel_level_ranges_read_each_channel_at_its_level() {
    // Three channels at a fixed level 0; channel 1 drawn at level 1 only,
    // channel 2 at levels 1–2 (so at 1): CPU and device, page tables and
    // octree, equal the reference that reads those levels; no level-0
    // brick of channels 1 and 2 is ever mapped.
    let dir = tempfile::tempdir().unwrap();
    let (store, extent, levels) = banded_store(dir.path(), 3);
    assert!(levels.len() >= 3);
    let mut p = dvr_params(extent, 3);
    p.reference_step = Some(extent[0] / DIMS[2] as f64);
    p.channels[1].levels = Some([1, 1]);
    p.channels[2].levels = Some([1, 2]);
    let vols: Vec<Volume> = [(0, 0), (1, 1), (2, 1)]
        .iter()
        .map(|&(c, l)| Volume::from_store(&store, l, c).unwrap())
        .collect();
    let want = render_channels(&vols, &p);
    not_blank(&want, "reference");
    let all_fine = reference(&store, &p, 0);
    assert!(
        want.max_abs_diff(&all_fine) > 0.02,
        "the level ranges changed nothing"
    );
    let gpu = brickyard_gpu::context::test_gpu();
    let pool = 6 * DIMS.iter().product::<u64>();
    for traversal in [Traversal::PageTable, Traversal::Octree] {
        p.traversal = traversal;
        let mut scene = Scene::new(extent, levels.clone());
        let mut s = open(&store, &mut scene, pool, 4);
        let (cpu, _) = converge(&mut s, &scene, &p, Lod::Fixed(0));
        let d = cpu.max_abs_diff(&want);
        eprintln!("{traversal:?}, CPU: vs reference {d}");
        assert!(d <= TOLERANCE, "{traversal:?}, CPU: {d}");
        let o = scene.octree.as_ref().unwrap().read().unwrap();
        let root = o.node(0, [0, 0, 0]);
        assert_eq!(
            o.mask_of(root, 1) & 1,
            0,
            "a level-0 brick of channel 1 mapped"
        );
        assert_eq!(
            o.mask_of(root, 2) & 1,
            0,
            "a level-0 brick of channel 2 mapped"
        );
        assert_ne!(o.mask_of(root, 0) & 1, 0);
        drop(o);
        if let Some(gpu) = &gpu {
            let mut scene = Scene::new(extent, levels.clone());
            let mut s = open(&store, &mut scene, pool, 4);
            let (dev, _) = converge_device(gpu, &mut s, &scene, &p, Lod::Fixed(0));
            let (dr, dc) = (dev.max_abs_diff(&want), dev.max_abs_diff(&cpu));
            eprintln!("{traversal:?}, device: vs reference {dr}, vs CPU {dc}");
            assert!(
                dr <= TOLERANCE && dc <= TOLERANCE,
                "{traversal:?}, device: {dr} {dc}"
            );
            let o = scene.octree.as_ref().unwrap().read().unwrap();
            assert_eq!(o.mask_of(o.node(0, [0, 0, 0]), 1) & 1, 0);
        }
    }
}

#[test]
fn kept_tables_follow_transfer_functions_and_the_octree() {
    // The traversal's per-frame tables are kept in the octree between
    // frames: a frame after a transfer-function change, after evictions
    // (a small pool) and back again must equal the page tables' frame of
    // the same parameters, never a frame of stale tables.
    let dir = tempfile::tempdir().unwrap();
    let (store, extent, levels) = banded_store(dir.path(), 3);
    let mut p = dvr_params(extent, 3);
    let top = TransferFunction::from_json(
        r#"{"window": [0, 255], "opacity": [[0, 0], [0.94, 0], [1, 0.9]], "colormap": "grayscale"}"#,
    )
    .unwrap();
    let soft = p.channels[0].dvr_tf();
    let mut scene = Scene::new(extent, levels.clone());
    let mut s = open(&store, &mut scene, 2 * 3 * DIMS.iter().product::<u64>(), 4);
    let mut images = vec![];
    // The hiding transfer function first: its tables kept for the soft one
    // would hide what it shows.
    for (i, tf) in [&top, &soft, &top, &soft].into_iter().enumerate() {
        for c in &mut p.channels {
            c.tf = Some(tf.clone());
        }
        p.traversal = Traversal::Octree;
        let (oc, st) = converge(&mut s, &scene, &p, Lod::Fixed(0));
        p.traversal = Traversal::PageTable;
        let (pt, _) = converge(&mut s, &scene, &p, Lod::Fixed(0));
        let d = oc.max_abs_diff(&pt);
        eprintln!(
            "step {i}: octree vs page tables {d}, {} nodes skipped",
            st.skipped_nodes
        );
        assert!(d <= TOLERANCE, "step {i}: {d}");
        // The hiding one's own tables: nodes crossed unsampled.
        assert_eq!(
            st.skipped_nodes > 0,
            i % 2 == 0,
            "step {i}: {} skipped",
            st.skipped_nodes
        );
        images.push(oc);
    }
    assert!(
        images[0].max_abs_diff(&images[1]) > 0.05,
        "the transfer functions look alike"
    );
    assert!(images[0].max_abs_diff(&images[2]) <= TOLERANCE);
    // A generation bump (an octree change) with the same parameters: the
    // tables are made again and still agree.
    let gen = scene.octree.as_ref().unwrap().read().unwrap().generation();
    let mut small = Scene::new(extent, levels);
    small.ranges = scene.ranges.clone();
    let mut s2 = open(&store, &mut small, 3 * DIMS.iter().product::<u64>() / 4, 4);
    p.traversal = Traversal::Octree;
    for _ in 0..40 {
        s2.begin_frame();
        let (_, _, reqs) = render_frame(s2.vm(), &small, &p, Lod::Fixed(0));
        s2.finish_frame(reqs.iter());
        small
            .octree
            .as_ref()
            .unwrap()
            .write()
            .unwrap()
            .sync(s2.vm_mut());
        // Whatever is resident now: the kept tables equal fresh ones.
        let o = small.octree.as_ref().unwrap().read().unwrap();
        let fresh = o.clone(); // a clone starts with no kept tables
        drop(o);
        let mut fs = Scene::new(extent, small.levels.clone());
        fs.ranges = small.ranges.clone();
        fs.octree = Some(Arc::new(RwLock::new(fresh)));
        let (a, sa, _) = render_frame(s2.vm(), &small, &p, Lod::Fixed(0));
        let (b, sb, _) = render_frame(s2.vm(), &fs, &p, Lod::Fixed(0));
        assert_eq!(a.rgba, b.rgba, "kept tables differ from fresh ones");
        // The same nodes crossed unsampled: tables of an older octree
        // (ranges from fewer voxels) would skip fewer.
        assert_eq!(
            (sa.skipped_nodes, sa.octree_nodes),
            (sb.skipped_nodes, sb.octree_nodes),
            "kept tables differ from fresh ones"
        );
    }
    assert!(gen > 0);
    assert!(
        small.octree.as_ref().unwrap().read().unwrap().generation() > 0,
        "the small pool's octree never changed"
    );
}
