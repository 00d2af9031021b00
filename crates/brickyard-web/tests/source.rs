//! The web client's data path against the native one, natively: every
//! brick read over `Fetch` (here from files, byte ranges and all) equals
//! the native loader's, and a streamed view equals `brickyard render`.

#![cfg(not(target_arch = "wasm32"))]

use brickyard_cache::brick::{BrickContent, BrickKey, LoadedBrick};
use brickyard_cache::host_cache::HostCache;
use brickyard_cache::loader::Loader;
use brickyard_cache::vm::VmConfig;
use brickyard_render::Image;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::codec::Compression;
use brickyard_store::import::{open_input, ImportOptions};
use brickyard_web::session::{Spawn, WebSession};
use brickyard_web::source::{FileFetch, WebSource, UNREACHABLE};
use brickyard_web::view::ViewState;
use futures_executor::LocalPool;
use futures_util_spawn::spawn_local;
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

mod futures_util_spawn {
    pub fn spawn_local(
        s: &futures_executor::LocalSpawner,
        f: std::pin::Pin<Box<dyn std::future::Future<Output = ()>>>,
    ) {
        use futures_task::LocalSpawn;
        s.spawn_local_obj(f.into()).expect("spawn");
    }
}

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(name)
}

fn convert_file(
    dir: &Path,
    input: &str,
    compression: Compression,
    brick: u64,
    shard: u64,
) -> PathBuf {
    let src = open_input(&data(input), &ImportOptions::default()).expect("input");
    let out = dir.join(format!("{input}.ome.zarr"));
    let opts = ConvertOptions {
        brick: [brick; 3],
        shard: [shard; 3],
        compression,
        ..Default::default()
    };
    convert(&*src, &out, &opts, &NoProgress, &AtomicBool::new(false)).expect("convert");
    out
}

fn open_web(store: &Path, brick: u64) -> WebSource {
    futures_executor::block_on(WebSource::open(
        Rc::new(FileFetch(store.into())),
        brick,
        1,
        1 << 20,
    ))
    .expect("open")
}

fn same(a: &LoadedBrick, b: &LoadedBrick) -> bool {
    a.content == b.content
        && (a.min.to_bits() == b.min.to_bits() || (a.min.is_nan() && b.min.is_nan()))
        && (a.max.to_bits() == b.max.to_bits() || (a.max.is_nan() && b.max.is_nan()))
}

/// Every brick of every level and channel, web against native.
fn check_store(store: &Path, brick: u64) -> (usize, usize) {
    let web = open_web(store, brick);
    let native =
        Loader::open(store, [brick; 3], 1, 1, Arc::new(HostCache::new(1 << 26))).expect("loader");
    assert_eq!(&web.geometry, native.geometry());
    let g = web.geometry.clone();
    let (mut data, mut uniform) = (0, 0);
    for l in 0..g.levels.len() {
        for c in 0..g.channels {
            for key in g.keys(l, c) {
                let w = futures_executor::block_on(web.load(key))
                    .unwrap_or_else(|e| panic!("{key:?}: {e}"));
                let n = native.load_now(&key).expect("native");
                assert!(same(&w, &n), "{}: {key:?} differs", store.display());
                match w.content {
                    BrickContent::Data(_) => data += 1,
                    _ => uniform += 1,
                }
            }
        }
    }
    (data, uniform)
}

#[test]
fn bricks_equal_the_native_loaders_on_real_volumes() {
    let dir = tempfile::tempdir().unwrap();
    // u8 (blosc LZ4), u16 (blosc LZ4 with byte shuffle), f32 (zstd), with
    // engine bricks that cut across store chunks and shards.
    for (input, comp, brick, shard, b) in [
        ("mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128, 32),
        ("nuclei-confocal-u16.tif", Compression::Lz4, 32, 64, 24),
        ("tomo-cryoet-f32.tif", Compression::Zstd(3), 32, 64, 40),
    ] {
        let store = convert_file(dir.path(), input, comp, brick, shard);
        let (d, u) = check_store(&store, b);
        eprintln!("{input}: {d} data bricks and {u} uniform ones equal");
        assert!(d > 10, "{input}: a check of {d} data bricks is too small");
    }
}

/// The value ranges of every engine brick, as bits (NaN: unknown).
fn range_bits(r: &brickyard_cache::ranges::BrickRanges) -> Vec<Option<Vec<[u32; 2]>>> {
    r.levels
        .iter()
        .map(|l| {
            l.as_ref()
                .map(|l| l.range.iter().map(|x| x.map(f32::to_bits)).collect())
        })
        .collect()
}

#[test]
fn brick_statistics_read_over_fetch_equal_the_native_loaders() {
    let dir = tempfile::tempdir().unwrap();
    for (input, brick) in [
        ("mni152-t1-u8.nii.gz", 32),
        ("nuclei-confocal-u16.tif", 16),
        ("tomo-cryoet-f32.tif", 32),
    ] {
        let store = convert_file(dir.path(), input, Compression::Lz4, 64, 128);
        let web = open_web(&store, brick);
        let native = Loader::open(&store, [brick; 3], 1, 1, Arc::new(HostCache::new(1 << 26)))
            .expect("loader");
        let (w, problems) = futures_executor::block_on(web.brick_ranges(1 << 24));
        assert!(problems.is_empty(), "{problems:?}");
        let n = native.brick_ranges(1 << 24);
        let (wb, nb) = (range_bits(&w), range_bits(&n));
        assert!(
            wb.iter().all(Option::is_some),
            "{input}: a level without statistics"
        );
        assert_eq!(
            wb, nb,
            "{input}: the page's brick ranges differ from the native loader's"
        );
        // Not a vacuous check: some bricks have known, finite ranges.
        let known = wb[0]
            .as_ref()
            .unwrap()
            .iter()
            .filter(|r| f32::from_bits(r[0]).is_finite())
            .count();
        assert!(known > 0, "{input}: no brick of level 0 has a known range");
        // A level of more bricks than allowed is left out, as natively.
        let (few, _) = futures_executor::block_on(web.brick_ranges(1));
        assert_eq!(range_bits(&few), range_bits(&native.brick_ranges(1)));
    }
    // A damaged chunk of the statistics: reported by name, its bricks
    // unknown, the other levels as before.
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    let web = open_web(&store, 32);
    let (before, _) = futures_executor::block_on(web.brick_ranges(1 << 24));
    let chunk = store.join("_brickyard/stats/0/c/0/0/0/0/0");
    assert!(chunk.is_file(), "{}", chunk.display());
    std::fs::write(&chunk, b"not zstd").unwrap();
    let (after, problems) = futures_executor::block_on(web.brick_ranges(1 << 24));
    assert!(
        problems.len() == 1 && problems[0].contains("stats/0/c/0/0/0/0/0"),
        "{problems:?}"
    );
    let (a, b) = (range_bits(&after), range_bits(&before));
    assert!(a[0]
        .as_ref()
        .unwrap()
        .iter()
        .all(|r| f32::from_bits(r[0]).is_nan()));
    assert_eq!(a[1..], b[1..]);
}

#[test]
fn damaged_chunks_fail_their_bricks_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    let shard = store.join("0/c/0/0/0");
    let b = std::fs::read(&shard).unwrap();
    // A shard cut short: its index (read from the end) fails its checksum.
    std::fs::write(&shard, &b[..b.len() / 2]).unwrap();
    let web = open_web(&store, 32);
    let g = web.geometry.clone();
    let mut failed = 0;
    for key in g.keys(0, 0) {
        if let Err(e) = futures_executor::block_on(web.load(key)) {
            assert!(e.contains("0/c/0/0/0"), "{e}");
            failed += 1;
        }
    }
    assert!(failed > 0, "a damaged shard must fail some bricks");
    // A chunk cut short inside an intact shard fails too.
    let shard1 = store.join("1/c/0/0/0");
    let mut b = std::fs::read(&shard1).unwrap();
    let n = b.len();
    // The first inner chunk's length in the index (at the end) made longer
    // than the file.
    let idx = n - 4 - 16 * 8;
    let len = u64::from_le_bytes(b[idx + 8..idx + 16].try_into().unwrap());
    if len != u64::MAX {
        b[idx + 8..idx + 16].copy_from_slice(&(n as u64 * 2).to_le_bytes());
        let crc = crc32c_of(&b[idx..n - 4]);
        b[n - 4..].copy_from_slice(&crc.to_le_bytes());
        std::fs::write(&shard1, &b).unwrap();
        let web = open_web(&store, 32);
        let e = futures_executor::block_on(web.load(BrickKey::new(1, 0, [0, 0, 0]))).unwrap_err();
        assert!(e.contains("1/c/0/0/0"), "{e}");
    }
    // A store that is not there: a clear error.
    let e = futures_executor::block_on(WebSource::open(
        Rc::new(FileFetch(dir.path().join("nothing"))),
        32,
        1,
        1 << 20,
    ))
    .err()
    .unwrap();
    assert!(e.contains("zarr.json: not found"), "{e}");
}

/// Stream a view to complete through the web session on one thread.
fn stream(store: &Path, state: &ViewState, window: [f64; 2], pool: u64) -> (Image, u32) {
    let (img, frames, _) = stream_view(store, pool, |s, src| {
        let (meta, n, labels) = (
            src.meta.channels.clone(),
            src.geometry.channels,
            src.meta.labels,
        );
        state.params(&s.scene, window, &meta, n, labels).unwrap()
    });
    (img, frames)
}

/// Stream the view `view` makes of the session to complete; returns the
/// image, the frames it took and the view.
fn stream_view(
    store: &Path,
    pool: u64,
    view: impl FnOnce(&WebSession, &WebSource) -> brickyard_web::view::View,
) -> (Image, u32, brickyard_web::view::View) {
    let (img, frames, v, _) = stream_session(store, pool, view);
    (img, frames, v)
}

/// [`stream_view`], with the session kept.
fn stream_session(
    store: &Path,
    pool: u64,
    view: impl FnOnce(&WebSession, &WebSource) -> brickyard_web::view::View,
) -> (Image, u32, brickyard_web::view::View, WebSession) {
    let (mut s, mut exec, src) = session(store, pool);
    let v = view(&s, &src);
    let (image, frames) = frames_until_complete(&mut s, &mut exec, &v);
    (image, frames, v, s)
}

/// Frames of `v` until one is complete: its image and the frames it took.
fn frames_until_complete(
    s: &mut WebSession,
    exec: &mut LocalPool,
    v: &brickyard_web::view::View,
) -> (Image, u32) {
    s.scene.channel = v.channel;
    s.octree_depth = v.octree_depth;
    for frame in 0..500 {
        exec.run_until_stalled();
        let out = s.frame_cpu(&v.params, v.lod);
        if out.complete {
            eprintln!(
                "complete at LOD bias {} after {} frames, {} bricks loaded",
                out.bias,
                frame,
                s.loads.loaded()
            );
            return (s.image().clone(), frame);
        }
    }
    panic!("the view did not complete in 500 frames");
}

/// The largest difference of any component of any pixel.
fn max_diff(a: &Image, b: &Image) -> f32 {
    a.rgba
        .iter()
        .zip(&b.rgba)
        .flat_map(|(a, b)| (0..4).map(move |i| (a[i] - b[i]).abs()))
        .fold(0f32, f32::max)
}

fn render_cli(store: &Path, args: &[&str]) -> Image {
    let mut a: Vec<String> = ["brickyard", "render", store.to_str().unwrap()]
        .map(String::from)
        .to_vec();
    a.extend(args.iter().map(|s| s.to_string()));
    a.extend(["--backend", "cpu", "--brick", "32"].map(String::from));
    let c = brickyard_run::render::RenderCmd::try_parse_from(&a).expect("args");
    brickyard_run::render::images(c).expect("render").remove(0)
}

#[test]
fn a_streamed_view_equals_brickyard_render() {
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    for q in [
        "size=400x300&az=40&el=25&tf=soft&window=0,255",
        "mode=mip&size=300x300&az=-70&el=10&tf=hot&window=20,200",
        "mode=slice&size=320x320&slice=0.4&window=0,255&tf=linear",
    ] {
        let st = ViewState::from_query(q).unwrap();
        let (web, frames) = stream(&store, &st, [0.0, 255.0], 64 << 20);
        let [lo, hi] = st.window.unwrap();
        let mut args = vec![
            "--mode".to_string(),
            st.mode.clone(),
            "--size".into(),
            format!("{}x{}", st.width, st.height),
            "--tf".into(),
            st.tf.clone().unwrap(),
            "--window".into(),
            format!("{lo},{hi}"),
        ];
        // (The CLI takes the flags of the mode drawn only.)
        if st.mode == "slice" {
            args.extend(["--slice-z".into(), st.slice_z.to_string()]);
        } else {
            args.extend([
                format!("--azimuth={}", st.azimuth),
                format!("--elevation={}", st.elevation),
            ]);
        }
        let cli = render_cli(&store, &args.iter().map(String::as_str).collect::<Vec<_>>());
        let lit = cli.rgba.iter().filter(|p| p[3] > 0.05).count();
        assert!(
            lit > cli.rgba.len() / 10,
            "{q}: the reference image is nearly blank ({lit} lit pixels)"
        );
        let d = max_diff(&web, &cli);
        eprintln!("{q}: complete after {frames} frames, max difference {d:e}");
        assert!(
            d <= 1e-5,
            "{q}: the streamed view differs from brickyard render by {d}"
        );
    }
}

#[test]
fn a_view_through_the_residency_octree_streams_as_brickyard_render_draws_it() {
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    let q = "size=240x200&az=-50&el=30&window=0,255";
    let mut images = vec![];
    for (traversal, depth) in [("page-table", None), ("octree", None), ("octree", Some(2))] {
        let mut query = format!("{q}&traversal={traversal}");
        if let Some(d) = depth {
            query += &format!("&octree_depth={d}");
        }
        let st = ViewState::from_query(&query).unwrap();
        let (img, frames, v, mut s) = stream_session(&store, 64 << 20, |s, src| {
            st.params(&s.scene, [0.0, 255.0], &src.meta.channels, 1, false)
                .unwrap()
        });
        assert_eq!(s.scene.octree.is_some(), traversal == "octree");
        if let Some(o) = &s.scene.octree {
            // The octree followed the session: what it holds is what the
            // virtual memory maps, and a redraw of the whole view walks it.
            let want = depth.unwrap_or(brickyard_render::octree::DEFAULT_DEPTH);
            assert_eq!(o.read().unwrap().depth, want);
            let fresh = brickyard_render::octree::Octree::of_vm(
                want,
                &s.scene.levels,
                &s.vm,
                s.scene.ranges.as_deref(),
            )
            .unwrap();
            let o = o.read().unwrap();
            assert_eq!(o.mask, fresh.mask, "the octree's masks fell behind");
            let bits = |r: &[[f32; 2]]| -> Vec<[u32; 2]> {
                r.iter().map(|x| x.map(f32::to_bits)).collect()
            };
            assert_eq!(bits(&o.range), bits(&fresh.range), "ranges kept vs fresh");
            drop(o);
            let nudged = ViewState::from_query(&format!("{q}&zoom=1.0001&traversal=octree"))
                .unwrap()
                .params(&s.scene, [0.0, 255.0], &[], 1, false)
                .unwrap();
            let out = s.frame_cpu(&nudged.params, nudged.lod);
            assert!(out.stats.octree_nodes > 0, "{:?}", out.stats);
        }
        let depth_flag = depth.map(|d| format!("--octree-depth={d}"));
        let mut args = vec![
            "--size",
            "240x200",
            "--azimuth=-50",
            "--elevation=30",
            "--window",
            "0,255",
            "--traversal",
            traversal,
        ];
        args.extend(depth_flag.as_deref());
        let cli = render_cli(&store, &args);
        let lit = cli.rgba.iter().filter(|p| p[3] > 0.05).count();
        assert!(lit > cli.rgba.len() / 10, "the reference is nearly blank");
        let d = max_diff(&img, &cli);
        eprintln!(
            "{traversal}: complete after {frames} frames, max difference {d:e}; {:?}",
            v.lod
        );
        assert!(
            d <= 1e-5,
            "{traversal}: differs from brickyard render by {d}"
        );
        images.push(img);
    }
    for img in &images[1..] {
        let d = max_diff(&images[0], img);
        eprintln!("octree vs page tables: max difference {d:e}");
        assert!(d <= 1e-5, "octree vs page tables: {d}");
    }
}

#[test]
fn brick_statistics_spare_the_loads_of_bricks_the_view_hides() {
    // Only the brightest tissue shows: bricks whose statistics stay below
    // the window are crossed without being asked for. (Statistics per 16³
    // store brick, finer than the engine's 32³ bricks.)
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 16, 64);
    let st = ViewState::from_query("size=240x200&az=20&el=10&window=160,255&tf=hot").unwrap();
    let mut runs = vec![];
    for ranges in [false, true] {
        let src = Rc::new(open_web(&store, 32));
        let mut exec = LocalPool::new();
        let sp = exec.spawner();
        let spawn: Spawn = Rc::new(move |f| spawn_local(&sp, f));
        let cfg = VmConfig {
            brick: [32; 3],
            pool_bytes: 16 << 20,
            ..Default::default()
        };
        let mut s = WebSession::new(src.clone(), cfg, spawn, 6).expect("session");
        if ranges {
            assert!(exec.run_until(s.read_ranges(1 << 21)).is_empty());
        }
        let v = st
            .params(&s.scene, [0.0, 255.0], &src.meta.channels, 1, false)
            .unwrap();
        let (img, frames) = frames_until_complete(&mut s, &mut exec, &v);
        // Level 0 is not pinned: its bricks come in only when asked for.
        let level0 = src
            .geometry
            .keys(0, 0)
            .filter(|k| s.vm.is_resident(*k))
            .count();
        eprintln!(
            "statistics {ranges}: {level0} bricks of level 0 resident, {} loaded in all, \
             {frames} frames",
            s.loads.loaded()
        );
        runs.push((img, level0));
    }
    let cli = render_cli(
        &store,
        &[
            "--size",
            "240x200",
            "--azimuth=20",
            "--elevation=10",
            "--window",
            "160,255",
            "--tf",
            "hot",
        ],
    );
    let lit = cli.rgba.iter().filter(|p| p[3] > 0.05).count();
    assert!(lit > 1000, "the reference is nearly blank ({lit})");
    for (img, _) in &runs {
        let d = max_diff(img, &cli);
        assert!(d <= 1e-5, "differs from brickyard render by {d}");
    }
    assert!(
        runs[1].1 < runs[0].1,
        "with statistics {} bricks of level 0 loaded, without {}",
        runs[1].1,
        runs[0].1
    );
}

#[test]
fn a_pool_smaller_than_the_view_still_completes() {
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    let st = ViewState::from_query("size=200x200&window=0,255").unwrap();
    // Room for the coarse levels and a few dozen bricks: the view ends,
    // complete at the detail the pool holds... or at least ends.
    let (img, frames) = stream_small(&store, &st);
    let lit = img.rgba.iter().filter(|p| p[3] > 0.05).count();
    assert!(lit > 1000, "{lit} lit pixels after {frames} frames");
}

/// A session over `store` (32³ bricks, a pool of `pool` bytes, the brick
/// statistics read as the page reads them) and its executor.
fn session(store: &Path, pool: u64) -> (WebSession, LocalPool, Rc<WebSource>) {
    let src = Rc::new(open_web(store, 32));
    let (s, exec) = session_over(src.clone(), pool);
    (s, exec, src)
}

/// A session over `src` with a pool of `pool` bytes (bricks of 32³, six
/// loads at a time), its brick statistics read without a problem.
fn session_over(src: Rc<WebSource>, pool: u64) -> (WebSession, LocalPool) {
    let mut exec = LocalPool::new();
    let sp = exec.spawner();
    let spawn: Spawn = Rc::new(move |f| spawn_local(&sp, f));
    let cfg = VmConfig {
        brick: [32; 3],
        pool_bytes: pool,
        ..Default::default()
    };
    let mut s = WebSession::new(src, cfg, spawn, 6).expect("session");
    let problems = exec.run_until(s.read_ranges(1 << 21));
    assert!(problems.is_empty(), "{problems:?}");
    (s, exec)
}

#[test]
fn a_frame_drawn_in_parts_equals_one_drawn_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    for (q, pool) in [
        ("size=400x300&az=40&el=25&tf=soft&window=0,255", 64 << 20),
        (
            "mode=mip&size=300x300&az=-70&el=10&tf=hot&window=20,200",
            64 << 20,
        ),
        (
            "traversal=octree&size=320x240&az=120&el=-15&tf=soft&window=0,255",
            64 << 20,
        ),
        // A pool too small for the view: the LOD budget sees whole frames.
        ("size=200x200&window=0,255", 2 << 20),
    ] {
        let st = ViewState::from_query(q).unwrap();
        // Each frame at once, and in parts of at most 13 tiles.
        let mut runs = vec![];
        for max in [None, Some(13)] {
            let (mut s, mut exec, src) = session(&store, pool);
            let v = st
                .params(
                    &s.scene,
                    [0.0, 255.0],
                    &src.meta.channels,
                    src.geometry.channels,
                    src.meta.labels,
                )
                .unwrap();
            s.scene.channel = v.channel;
            s.octree_depth = v.octree_depth;
            let tiles =
                (v.params.width as usize).div_ceil(32) * (v.params.height as usize).div_ceil(16);
            let (mut frames, mut calls) = (0, 0);
            let img = loop {
                assert!(calls < 5000, "{q}: no end");
                exec.run_until_stalled();
                let out = s.frame_cpu_part(&v.params, v.lod, max);
                calls += 1;
                if !s.ready() {
                    continue;
                }
                if let Some(m) = max {
                    assert!(
                        out.tiles_drawn <= m,
                        "{q}: {} tiles in a part",
                        out.tiles_drawn
                    );
                }
                if out.tiles_left > 0 {
                    // A part: nothing ended (the page shows a frame once
                    // no part of it is left).
                    assert!(!out.complete && s.in_parts(), "{q}");
                    continue;
                }
                assert!(!s.in_parts(), "{q}");
                frames += 1;
                if out.complete {
                    break s.image().clone();
                }
            };
            let lit = img.rgba.iter().filter(|p| p[3] > 0.05).count();
            assert!(lit > 1000, "{q}: {lit} lit pixels");
            eprintln!(
                "{q}: {max:?} tiles a part: {frames} frames in {calls} calls ({tiles} tiles)"
            );
            runs.push((img, frames, calls));
        }
        let (whole, parts) = (&runs[0], &runs[1]);
        // The same frames, the same image, bit for bit; more calls.
        assert_eq!(parts.1, whole.1, "{q}: frames");
        assert!(
            parts.2 > whole.2 + 1,
            "{q}: the frames were not drawn in parts"
        );
        assert_eq!(parts.0.rgba, whole.0.rgba, "{q}: the images differ");
    }
}

fn stream_small(store: &Path, st: &ViewState) -> (Image, u32) {
    stream(store, st, [0.0, 255.0], 2 << 20)
}

fn crc32c_of(b: &[u8]) -> u32 {
    // The index codec's checksum (Castagnoli), bit by bit.
    let mut c = !0u32;
    for &x in b {
        c ^= x as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0x82F6_3B78
            } else {
                c >> 1
            };
        }
    }
    !c
}

/// An OME-Zarr 0.4 (Zarr v2) image written here by hand: `c, z, y, x`
/// axes, gzip chunks of 5×7×6 in big- or little-endian u16, `.` or `/`
/// keys, some chunks absent (the fill value). Every brick must equal a
/// clamped crop of the array computed here.
#[test]
fn zarr_v2_stores_read_as_the_array_they_hold() {
    use std::io::Write;
    let dims = [2u64, 19, 23, 17]; // c z y x
    let chunk = [1u64, 5, 7, 6];
    let val = |c: u64, z: u64, y: u64, x: u64| -> u16 {
        ((c * 7919 + z * 131 + y * 17 + x * 3) % 60000) as u16 + 1
    };
    for (big, sep, fill) in [(false, ".", 0u16), (true, "/", 9)] {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        std::fs::write(root.join(".zgroup"), r#"{"zarr_format":2}"#).unwrap();
        std::fs::write(
            root.join(".zattrs"),
            r#"{"multiscales":[{"version":"0.4","axes":[{"name":"c","type":"channel"},{"name":"z","type":"space"},{"name":"y","type":"space"},{"name":"x","type":"space"}],
               "datasets":[{"path":"0","coordinateTransformations":[{"type":"scale","scale":[1,2.0,0.5,0.5]}]}]}]}"#,
        )
        .unwrap();
        std::fs::create_dir_all(root.join("0")).unwrap();
        std::fs::write(
            root.join("0/.zarray"),
            format!(
                r#"{{"zarr_format":2,"shape":{dims:?},"chunks":{chunk:?},"dtype":"{}u2","compressor":{{"id":"gzip","level":1}},"fill_value":{fill},"order":"C","filters":null,"dimension_separator":"{sep}"}}"#,
                if big { ">" } else { "<" }
            ),
        )
        .unwrap();
        let n: Vec<u64> = (0..4).map(|d| dims[d].div_ceil(chunk[d])).collect();
        let mut absent = std::collections::HashSet::new();
        for c in 0..n[0] {
            for z in 0..n[1] {
                for y in 0..n[2] {
                    for x in 0..n[3] {
                        let idx = [c, z, y, x];
                        if (c + z + y + x) % 5 == 3 {
                            absent.insert(idx);
                            continue;
                        }
                        let mut raw = vec![];
                        for i in 0..chunk[1] {
                            for j in 0..chunk[2] {
                                for k in 0..chunk[3] {
                                    let (zz, yy, xx) =
                                        (z * chunk[1] + i, y * chunk[2] + j, x * chunk[3] + k);
                                    let v = if zz < dims[1] && yy < dims[2] && xx < dims[3] {
                                        val(c, zz, yy, xx)
                                    } else {
                                        0
                                    };
                                    raw.extend(if big {
                                        v.to_be_bytes()
                                    } else {
                                        v.to_le_bytes()
                                    });
                                }
                            }
                        }
                        let mut e =
                            flate2::write::GzEncoder::new(vec![], flate2::Compression::fast());
                        e.write_all(&raw).unwrap();
                        let key = format!("{c}{sep}{z}{sep}{y}{sep}{x}");
                        let path = root.join("0").join(&key);
                        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
                        std::fs::write(path, e.finish().unwrap()).unwrap();
                    }
                }
            }
        }
        let web = open_web(root, 8);
        assert_eq!(web.geometry.levels, vec![[19, 23, 17]]);
        assert_eq!(web.geometry.channels, 2);
        assert_eq!(web.meta.spacing, [2.0, 0.5, 0.5]);
        let truth = |c: u64, z: u64, y: u64, x: u64| -> u16 {
            let idx = [c, z / chunk[1], y / chunk[2], x / chunk[3]];
            if absent.contains(&idx) {
                fill
            } else {
                val(c, z, y, x)
            }
        };
        let g = web.geometry.clone();
        let p = g.padded();
        for c in 0..2 {
            for key in g.keys(0, c) {
                let b = futures_executor::block_on(web.load(key)).unwrap();
                let dense = b.content.to_dense(g.voxels_per_brick() as usize, g.dtype);
                let po = g.padded_origin_of(&key);
                for i in 0..p[0] as i64 {
                    for j in 0..p[1] as i64 {
                        for k in 0..p[2] as i64 {
                            let cl = |v: i64, n: u64| v.clamp(0, n as i64 - 1) as u64;
                            let want = truth(
                                c as u64,
                                cl(po[0] + i, dims[1]),
                                cl(po[1] + j, dims[2]),
                                cl(po[2] + k, dims[3]),
                            );
                            let o = (((i * p[1] as i64 + j) * p[2] as i64 + k) * 2) as usize;
                            let got = u16::from_ne_bytes([dense[o], dense[o + 1]]);
                            assert_eq!(got, want, "{key:?} voxel ({i},{j},{k}), big-endian {big}");
                        }
                    }
                }
            }
        }
    }
}

/// A store of three channels (MNI152 T1, grey and white matter): its
/// active channels composited in DVR by default, and two added up in a
/// MIP, each in its `omero` colour and window, equal `brickyard render`
/// with the same (default) channels.
#[test]
fn several_channels_equal_brickyard_render() {
    let dir = tempfile::tempdir().unwrap();
    let inputs: Vec<std::path::PathBuf> = [
        "mni152-t1-u8.nii.gz",
        "mni152-gm-u8.nii.gz",
        "mni152-wm-u8.nii.gz",
    ]
    .iter()
    .map(|f| data(f))
    .collect();
    let sources = inputs
        .iter()
        .map(|p| open_input(p, &ImportOptions::default()).expect("input"))
        .collect();
    let src: Box<dyn brickyard_store::source::VolumeSource> =
        Box::new(brickyard_store::import::stack::ChannelStack::new(sources).expect("stack"));
    let store = dir.path().join("mni3.ome.zarr");
    convert(
        &*src,
        &store,
        &ConvertOptions::default(),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .expect("convert");
    for (q, args) in [
        ("size=200x160&az=40&el=25", vec![]),
        (
            "size=200x160&az=40&el=25&traversal=octree",
            vec!["--traversal", "octree"],
        ),
        (
            "mode=mip&size=160x160&channels=1,2",
            vec!["--mode", "mip", "--channel", "1", "--channel", "2"],
        ),
    ] {
        let st = ViewState::from_query(q).unwrap();
        let (web, frames) = stream(&store, &st, [0.0, 255.0], 64 << 20);
        let mut a: Vec<String> = vec![
            "--size".into(),
            format!("{}x{}", st.width, st.height),
            "--azimuth=40".into(),
            "--elevation=25".into(),
        ];
        if st.mode == "mip" {
            a = vec!["--size".into(), format!("{}x{}", st.width, st.height)];
        }
        a.extend(args.iter().map(|s| s.to_string()));
        let a: Vec<&str> = a.iter().map(|s| s.as_str()).collect();
        let cli = render_cli(&store, &a);
        let lit = cli.rgba.iter().filter(|p| p[3] > 0.05).count();
        assert!(
            lit > cli.rgba.len() / 10,
            "{q}: the reference is nearly blank"
        );
        let d = max_diff(&web, &cli);
        eprintln!("{q}: complete after {frames} frames, max difference {d:e}");
        assert!(d <= 1e-5, "{q}: differs from brickyard render by {d}");
    }
}

#[test]
fn a_label_image_streams_in_its_labels_colours_as_brickyard_render_draws_it() {
    let dir = tempfile::tempdir().unwrap();
    let src = open_input(&data("nuclei-labels-u32.tif"), &ImportOptions::default()).expect("input");
    let store = dir.path().join("labels.ome.zarr");
    let opts = ConvertOptions {
        brick: [32; 3],
        shard: [64; 3],
        labels: true,
        spacing: Some([2.0, 0.5, 0.5]),
        ..Default::default()
    };
    convert(&*src, &store, &opts, &NoProgress, &AtomicBool::new(false)).expect("convert");
    assert!(
        open_web(&store, 32).meta.labels,
        "the store reads as a label image"
    );
    // No tf: a label image's slice takes its labels' colours, in the page
    // as in `brickyard render`.
    let q = "mode=slice&size=160x160&slice=0.5";
    let st = ViewState::from_query(q).unwrap();
    let (web, _) = stream(&store, &st, [0.0, 20.0], 64 << 20);
    let cli = render_cli(
        &store,
        &["--mode", "slice", "--size", "160x160", "--slice-z", "0.5"],
    );
    let d = web.max_abs_diff(&cli);
    assert!(d <= 1e-6, "web and CLI differ by {d}");
    let colours: std::collections::HashSet<[u32; 4]> =
        web.rgba.iter().map(|p| p.map(f32::to_bits)).collect();
    assert!(
        (6..=21).contains(&colours.len()),
        "{} colours: not the labels' (20 labels and the background)",
        colours.len()
    );
    // Its surfaces in 3D, as `brickyard render` draws them.
    let st = ViewState::from_query("mode=dvr&size=120x100&az=35&el=40").unwrap();
    let (web, _) = stream(&store, &st, [0.0, 20.0], 64 << 20);
    let cli = render_cli(
        &store,
        &["--size", "120x100", "--azimuth", "35", "--elevation", "40"],
    );
    let d = web.max_abs_diff(&cli);
    assert!(d <= 1e-6, "3D: web and CLI differ by {d}");
    assert!(web.coverage(0.01) > 0.1, "3D: nearly empty");
    // Asked for in a MIP: refused, naming the key.
    let st = ViewState::from_query("mode=mip&tf=labels").unwrap();
    let s = open_web(&store, 32);
    let scene = brickyard_render::cpu::Scene::new([1.0; 3], vec![[1, 1, 1]]);
    let e = st
        .params(&scene, [0.0, 1.0], &s.meta.channels, 1, true)
        .unwrap_err();
    assert!(e.starts_with("tf: labels"), "{e}");
}

struct Quiet;

impl brickyard_run::process::Phases for Quiet {
    fn labelling(&self) -> &dyn brickyard_store::Progress {
        &NoProgress
    }
    fn writing(&self) -> &dyn brickyard_store::Progress {
        &NoProgress
    }
}

/// The nuclei stack converted into `dir`, with `labels/cells` from
/// `process`.
#[test]
fn the_readout_names_the_point_a_3d_view_shows() {
    let dir = tempfile::tempdir().unwrap();
    let store = nuclei_with_cells(dir.path());
    let (w, h) = (200u32, 160u32);
    let grid: Vec<(f64, f64)> = (0..10)
        .flat_map(|j| (0..12).map(move |i| (8.5 + i as f64 * 16.0, 6.5 + j as f64 * 15.0)))
        .collect();
    // References read apart: the stack's and the labels' level 0 whole.
    let (tif, d) = read_whole(
        &*open_input(&data("nuclei-confocal-u16.tif"), &ImportOptions::default()).unwrap(),
    );
    // (Every level of the labels.)
    let lab: Vec<(Vec<u8>, [u64; 3])> = (0..)
        .map_while(|l| brickyard_store::import::zarr::open(&store.join("labels/cells"), l).ok())
        .map(|src| read_whole(&src))
        .collect();
    assert!(lab.len() >= 2, "{} levels", lab.len());
    let at = |v: &serde_json::Value| {
        let q: Vec<u64> = (0..3).map(|k| v[k].as_u64().unwrap()).collect();
        ((q[0] * d[1] + q[1]) * d[2] + q[2]) as usize
    };
    // Every answer's point lies on its pixel's ray, and what it reads at
    // level 0 is the file's voxel there.
    let on_ray = |v: &brickyard_web::view::View, p: &serde_json::Value, (x, y): (f64, f64)| {
        let q: Vec<f64> = (0..3).map(|k| p["world"][k].as_f64().unwrap()).collect();
        let px = v.params.camera.project([q[0], q[1], q[2]], w, h).unwrap();
        assert!(
            (px[0] - x).abs() < 1e-3 && (px[1] - y).abs() < 1e-3,
            "({x}, {y}) shows a point at {px:?}: {p}"
        );
    };
    // MIP of the stack, complete: its greatest samples.
    let st =
        ViewState::from_query(&format!("mode=mip&size={w}x{h}&tf=linear&window=0,40000")).unwrap();
    let (_, _, v, image) = stream_session(&store, 64 << 20, |s, src| {
        st.params(&s.scene, [0.0, 40000.0], &src.meta.channels, 1, false)
            .unwrap()
    });
    let (mut hits, mut checked) = (0, 0);
    for &(x, y) in &grid {
        let Some(p) = brickyard_web::session::probe(&v, &image, None, x, y) else {
            continue;
        };
        hits += 1;
        on_ray(&v, &p, (x, y));
        assert_eq!(p["seen"]["how"], "the MIP's maximum", "{p}");
        assert!(p.get("labels").is_none(), "{p}");
        if p["values"][0]["level"] == 0 {
            let want = u16::from_ne_bytes([
                tif[2 * at(&p["voxel_zyx"])],
                tif[2 * at(&p["voxel_zyx"]) + 1],
            ]);
            assert_eq!(p["values"][0]["value"].as_f64(), Some(want as f64), "{p}");
            checked += 1;
            if p["seen"]["level"] == 0 {
                assert_eq!(p["seen"]["value"], p["values"][0]["value"], "{p}");
            }
        }
    }
    eprintln!(
        "MIP: {hits} of {} pixels show a point, {checked} read at level 0",
        grid.len()
    );
    assert!(
        hits >= 20 && checked * 2 >= hits,
        "{hits} of {}, {checked}",
        grid.len()
    );
    // The label image itself in DVR: its surfaces, the first label drawn,
    // is the label read out (and picked by a click).
    let st = ViewState::from_query(&format!("mode=dvr&size={w}x{h}&tf=labels")).unwrap();
    let (_, _, v, labels) = stream_session(&store.join("labels/cells"), 64 << 20, |s, src| {
        st.params(&s.scene, [0.0, 60.0], &src.meta.channels, 1, false)
            .unwrap()
    });
    assert!(v.params.labels, "a label image's DVR draws its labels");
    let (mut found, mut checked) = (0, 0);
    for &(x, y) in &grid {
        let Some(p) = brickyard_web::session::probe(&v, &labels, None, x, y) else {
            continue;
        };
        found += 1;
        on_ray(&v, &p, (x, y));
        assert_eq!(p["seen"]["how"], "the first label drawn", "{p}");
        let id = p["labels"]["label"].as_f64().unwrap();
        assert!(id >= 1.0, "{p}");
        assert_eq!(p["seen"]["value"].as_f64(), Some(id), "{p}");
        // The label image's level that served it, read whole, at the point.
        let l = p["labels"]["level"].as_u64().unwrap() as usize;
        let (b, dl) = &lab[l];
        let q: Vec<f64> = (0..3).map(|k| p["world"][k].as_f64().unwrap()).collect();
        let e = labels.scene.extent;
        let v =
            [0, 1, 2].map(|a| ((q[2 - a] / e[2 - a] * dl[a] as f64).floor() as u64).min(dl[a] - 1));
        let i = ((v[0] * dl[1] + v[1]) * dl[2] + v[2]) as usize;
        let want = u32::from_ne_bytes(b[4 * i..4 * i + 4].try_into().unwrap());
        assert_eq!(id, want as f64, "level {l}: {p}");
        checked += (l == 0) as usize;
    }
    eprintln!(
        "labels: {found} of {} pixels show a label, {checked} read at level 0",
        grid.len()
    );
    assert!(
        found > 10 && checked >= 3,
        "{found} of {}, {checked}",
        grid.len()
    );
}

#[test]
fn a_label_selection_crosses_the_bricks_its_labels_do_not_reach() {
    let dir = tempfile::tempdir().unwrap();
    let labels = nuclei_with_cells(dir.path()).join("labels/cells");
    // Every label's box, from the statistics, and the label of most voxels.
    let table = futures_executor::block_on(open_web(&labels, 32).label_boxes(32 << 20))
        .unwrap()
        .expect("statistics");
    let csv = std::fs::read_to_string(labels.join("_brickyard/labels.csv")).unwrap();
    let (id, _) = csv
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<u64> = l.split(',').take(2).map(|x| x.parse().unwrap()).collect();
            (f[0], f[1])
        })
        .max_by_key(|r| r.1)
        .unwrap();
    assert_eq!(table.len(), csv.lines().count() - 1);
    let st = ViewState::from_query(&format!("mode=dvr&size=512x400&tf=labels&only_labels={id}"))
        .unwrap();
    let (plain, _, v0, s0) = stream_session(&labels, 64 << 20, |s, src| {
        st.params(&s.scene, [0.0, 60.0], &src.meta.channels, 1, true)
            .unwrap()
    });
    let (boxed, _, v1, s1) = stream_session(&labels, 64 << 20, |s, src| {
        st.params(&s.scene, [0.0, 60.0], &src.meta.channels, 1, true)
            .unwrap()
            .with_label_boxes(&table, src.geometry.levels[0])
    });
    assert!(v0.params.label_select.as_ref().unwrap().boxes.is_none());
    let b = v1
        .params
        .label_select
        .as_ref()
        .unwrap()
        .boxes
        .as_ref()
        .unwrap();
    assert_eq!(b.boxes, vec![table[&id]]);
    // The same image, the label in it, from fewer bricks.
    let lit = plain
        .rgba
        .iter()
        .filter(|p| p[..3].iter().any(|&c| c > 0.05))
        .count();
    assert!(lit > 100, "{lit} pixels show label {id}");
    assert_eq!(plain.rgba, boxed.rgba, "the boxes changed the image");
    let (n0, n1) = (s0.loads.loaded(), s1.loads.loaded());
    eprintln!("label {id}: {n1} bricks loaded with its box, {n0} without");
    assert!(n1 < n0, "{n1} bricks loaded with the box, {n0} without");
}

/// A source's channel 0 read whole, and its size.
fn read_whole(src: &dyn brickyard_store::VolumeSource) -> (Vec<u8>, [u64; 3]) {
    let d = src.meta().dims;
    let mut b = vec![0u8; d.iter().product::<u64>() as usize * src.meta().dtype.size()];
    src.read_region(0, 0..d[0], 0..d[1], 0..d[2], &mut b)
        .unwrap();
    (b, d)
}

fn nuclei_with_cells(dir: &Path) -> PathBuf {
    let store = convert_file(dir, "nuclei-confocal-u16.tif", Compression::Lz4, 32, 64);
    let args = brickyard_run::process::ProcessArgs {
        store: store.clone(),
        pipeline: "gauss(1)|threshold(12000)|label(26)".into(),
        out: "cells".into(),
        memory: 256 << 20,
        level: 0,
        channel: 0,
        stats: None,
        overwrite: false,
        backend: "cpu".into(),
        quiet: true,
    };
    let caller = brickyard_run::process::Caller {
        flag: "--",
        convert: "",
        remote: "",
        overwrite: "",
        again: "command",
    };
    brickyard_run::process::run(&args, &caller, &Quiet, &AtomicBool::new(false)).expect("process");
    store
}

#[test]
fn label_images_laid_over_slices_stream_as_brickyard_render_lays_them() {
    let dir = tempfile::tempdir().unwrap();
    let store = nuclei_with_cells(dir.path());
    let view = "mode=slice&size=180x160&slice=0.45&tf=linear&window=0,40000";
    let cli_base = [
        "--mode",
        "slice",
        "--size",
        "180x160",
        "--slice-z",
        "0.45",
        "--tf",
        "linear",
        "--window",
        "0,40000",
        "--labels",
        "cells",
    ];
    let plain = render_cli(&store, &cli_base[..10]);
    for (extra, flags) in [
        ("", vec![]),
        (
            "&label_opacity=0.8&only_labels=2,4-6",
            vec!["--label-opacity", "0.8", "--only-labels", "2,4-6"],
        ),
        ("&hide_labels=3", vec!["--hide-labels", "3"]),
    ] {
        let q = format!("{view}&labels=cells{extra}");
        let st = ViewState::from_query(&q).unwrap();
        assert_eq!(ViewState::from_query(&st.to_query()).unwrap(), st, "{q}");
        // The image's slice, then the labels' under the same view, laid
        // over it as the page does.
        let (mut web, _, v) = stream_view(&store, 64 << 20, |s, src| {
            st.params(&s.scene, [0.0, 40000.0], &src.meta.channels, 1, false)
                .unwrap()
        });
        let lv = st.label_view(&v).expect("a label view");
        let (labels, _, _) = stream_view(&store.join("labels/cells"), 16 << 20, |_, src| {
            assert!(src.meta.labels, "labels/cells reads as a label image");
            lv.clone()
        });
        web.lay_labels_over(&labels, st.label_opacity as f32)
            .unwrap();
        let mut a: Vec<&str> = cli_base.to_vec();
        a.extend(flags.iter().copied());
        let cli = render_cli(&store, &a);
        let d = web.max_abs_diff(&cli);
        // The labels are there: pixels the plain slice does not have.
        let changed = web
            .rgba
            .iter()
            .zip(&plain.rgba)
            .filter(|(p, q)| (0..3).any(|i| (p[i] - q[i]).abs() > 0.05))
            .count();
        eprintln!("{q}: {changed} pixels coloured by labels, {d:e} from render");
        assert!(d <= 1e-6, "{q}: web and CLI differ by {d}");
        assert!(changed > 200, "{q}: {changed} pixels show labels");
    }
    // Refused, naming the key: labels over a 3D view, a bad name.
    let e = ViewState::from_query("labels=cells")
        .unwrap()
        .params(
            &brickyard_render::cpu::Scene::new([1.0; 3], vec![[1, 1, 1]]),
            [0.0, 1.0],
            &[],
            1,
            false,
        )
        .unwrap_err();
    assert!(e.starts_with("labels:") && e.contains("mode=slice"), "{e}");
    for q in [
        "labels=../x",
        "labels=",
        "label_opacity=0",
        "only_labels=0",
        "only_labels=1&hide_labels=2",
    ] {
        let e = ViewState::from_query(q).unwrap_err();
        let key = q.split('=').next().unwrap();
        assert!(
            e.starts_with(key) || e.starts_with("hide_labels"),
            "{q}: {e}"
        );
    }
}

#[test]
fn the_readout_reads_the_voxel_and_label_under_a_pixel_of_a_slice() {
    let dir = tempfile::tempdir().unwrap();
    let store = nuclei_with_cells(dir.path());
    let st = ViewState::from_query(
        "mode=slice&size=480x440&slice=0.45&tf=linear&window=0,40000&labels=cells",
    )
    .unwrap();
    let (_, _, v, image) = stream_session(&store, 64 << 20, |s, src| {
        st.params(&s.scene, [0.0, 40000.0], &src.meta.channels, 1, false)
            .unwrap()
    });
    let lv = st.label_view(&v).unwrap();
    // (The label session streams the label view in a pool of its own,
    // kept to stream it again at another level of detail below.)
    let lsrc = Rc::new(open_web(&store.join("labels/cells"), 32));
    let mut lexec = LocalPool::new();
    let sp = lexec.spawner();
    let cfg = VmConfig {
        brick: [32; 3],
        pool_bytes: 32 << 20,
        ..Default::default()
    };
    let spawn: Spawn = Rc::new(move |f| spawn_local(&sp, f));
    let mut labels = WebSession::new(lsrc, cfg, spawn, 6).expect("label session");
    frames_until_complete(&mut labels, &mut lexec, &lv);
    // References read apart: the TIFF through its importer, the labels'
    // level 0 whole.
    let (tif, d) = read_whole(
        &*open_input(&data("nuclei-confocal-u16.tif"), &ImportOptions::default()).unwrap(),
    );
    let (lab, _) =
        read_whole(&brickyard_store::import::zarr::open(&store.join("labels/cells"), 0).unwrap());
    let at = |v: [u64; 3]| ((v[0] * d[1] + v[1]) * d[2] + v[2]) as usize;
    let (mut hits, mut in_labels) = (0, 0);
    for j in 0..12 {
        for i in 0..12 {
            let (x, y) = (20.0 + i as f64 * 38.3, 15.0 + j as f64 * 35.9);
            let Some(p) = brickyard_web::session::probe(&v, &image, Some(&labels), x, y) else {
                continue;
            };
            hits += 1;
            let q: Vec<u64> = p["voxel_zyx"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap())
                .collect();
            let q = [q[0], q[1], q[2]];
            // The view is complete at level 0: the readout reads it there.
            assert_eq!(p["values"][0]["level"], 0, "{p}");
            let want = u16::from_ne_bytes([tif[2 * at(q)], tif[2 * at(q) + 1]]) as f64;
            assert_eq!(p["values"][0]["value"].as_f64(), Some(want), "{x} {y}: {p}");
            let l = u32::from_ne_bytes(lab[4 * at(q)..4 * at(q) + 4].try_into().unwrap()) as f64;
            assert_eq!(p["labels"]["label"].as_f64(), Some(l), "{x} {y}: {p}");
            in_labels += (l != 0.0) as usize;
        }
    }
    eprintln!("{hits} pixels read out, {in_labels} inside labels");
    assert!(
        hits > 100 && in_labels >= 5,
        "{hits} pixels, {in_labels} in labels"
    );
    // The labels drawn at level 2 (a LOD bias of 2: unbiased, this view
    // would draw level -0.8, that is level 0, which the bias shifts by
    // 2), their level 0 still resident: the label read out is the one
    // drawn, level 2's.
    let mut lv2 = lv.clone();
    lv2.lod = brickyard_render::cpu::Lod::Auto { bias: 2.0 };
    frames_until_complete(&mut labels, &mut lexec, &lv2);
    let (lab2, d2) =
        read_whole(&brickyard_store::import::zarr::open(&store.join("labels/cells"), 2).unwrap());
    let extent = image.scene.extent;
    let (mut differ, mut n) = (0, 0);
    for j in 0..12 {
        for i in 0..12 {
            let (x, y) = (20.0 + i as f64 * 38.3, 15.0 + j as f64 * 35.9);
            let Some(p) = brickyard_web::session::probe(&v, &image, Some(&labels), x, y) else {
                continue;
            };
            n += 1;
            assert_eq!(p["labels"]["level"], 2, "{x} {y}: {p}");
            let w: Vec<f64> = (0..3).map(|k| p["world"][k].as_f64().unwrap()).collect();
            let q2 = [0, 1, 2].map(|a| {
                let f = w[2 - a] / extent[2 - a];
                ((f * d2[a] as f64).floor() as u64).min(d2[a] - 1)
            });
            let i2 = ((q2[0] * d2[1] + q2[1]) * d2[2] + q2[2]) as usize;
            let l2 = u32::from_ne_bytes(lab2[4 * i2..4 * i2 + 4].try_into().unwrap()) as f64;
            assert_eq!(p["labels"]["label"].as_f64(), Some(l2), "{x} {y}: {p}");
            let q: Vec<u64> = (0..3)
                .map(|k| p["voxel_zyx"][k].as_u64().unwrap())
                .collect();
            let l0 = u32::from_ne_bytes(
                lab[4 * at([q[0], q[1], q[2]])..4 * at([q[0], q[1], q[2]]) + 4]
                    .try_into()
                    .unwrap(),
            ) as f64;
            differ += (l0 != l2) as usize;
        }
    }
    eprintln!("at level 2: {differ} of {n} pixels show another label than level 0 has there");
    assert!(n > 100 && differ > 0, "{differ} of {n}");
    // Off the volume, and not a slice: nothing.
    assert!(brickyard_web::session::probe(&v, &image, None, -50.0, 5.0).is_none());
    // A MIP of the same camera: the point it shows there, named so (the
    // 3D readout is tested below).
    let mut mip = v.clone();
    mip.params.mode = brickyard_render::RenderMode::Mip;
    let p = brickyard_web::session::probe(&mip, &image, None, 240.0, 220.0).expect("a MIP point");
    assert_eq!(p["seen"]["how"], "the MIP's maximum", "{p}");
}

/// Files served as a server with `ETag`s does (`brickyard serve`: size and
/// modification time) and `If-Match` (412): for a store reconverted in
/// place while it is open.
struct TaggedFetch(PathBuf);

impl brickyard_web::source::Fetch for TaggedFetch {
    fn get(
        &self,
        path: &str,
        range: brickyard_web::source::Range,
    ) -> brickyard_web::source::LocalFuture<Result<Option<Vec<u8>>, String>> {
        FileFetch(self.0.clone()).get(path, range)
    }

    fn get_tagged(
        &self,
        path: &str,
        range: brickyard_web::source::Range,
        if_match: Option<&str>,
    ) -> brickyard_web::source::LocalFuture<Result<brickyard_web::source::Got, String>> {
        let tag = std::fs::metadata(self.0.join(path)).ok().map(|m| {
            let t = m.modified().unwrap().duration_since(std::time::UNIX_EPOCH);
            format!("\"{:x}-{:x}\"", m.len(), t.unwrap().as_nanos())
        });
        if let (Some(want), Some(have)) = (if_match, &tag) {
            if want != have {
                let e = format!("{path}: HTTP 412: {}", brickyard_web::source::STORE_CHANGED);
                return Box::pin(async move { Err(e) });
            }
        }
        let f = FileFetch(self.0.clone()).get(path, range);
        Box::pin(async move {
            Ok(brickyard_web::source::Got {
                bytes: f.await?,
                etag: tag,
                whole: false,
            })
        })
    }
}

#[test]
fn a_store_reconverted_while_open_is_not_mixed_with_the_old_one() {
    use brickyard_web::source::STORE_CHANGED;
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a");
    let b = dir.path().join("b");
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    let store = convert_file(&a, "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    let other = convert_file(&b, "mni152-t1-u8.nii.gz", Compression::None, 64, 128);
    let open = || {
        futures_executor::block_on(WebSource::open(
            Rc::new(TaggedFetch(store.clone())),
            32,
            1,
            1 << 20,
        ))
        .expect("open")
    };
    let web = open();
    let later = open();
    assert!(!futures_executor::block_on(later.check_changed()));
    // Shard 0/c/0/0/0's index is read with its first brick.
    let keys: Vec<BrickKey> = web
        .geometry
        .keys(0, 0)
        .filter(|k| k.brick.iter().all(|&v| v < 4))
        .collect();
    futures_executor::block_on(web.load(keys[0])).expect("before");
    // The store converted again in place (other bytes, other sizes).
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::remove_dir_all(&store).unwrap();
    std::fs::rename(&other, &store).unwrap();
    // A later brick of that shard: its chunk asked for with the index's
    // version (If-Match) is refused, and the source reads nothing more.
    let e = futures_executor::block_on(web.load(*keys.last().unwrap())).unwrap_err();
    assert!(e.contains(STORE_CHANGED), "{e}");
    assert!(web.changed());
    for k in &keys[1..4] {
        let e = futures_executor::block_on(web.load(*k)).unwrap_err();
        assert_eq!(e, STORE_CHANGED);
    }
    // The root document's check sees it too (a source that read no shard).
    assert!(futures_executor::block_on(later.check_changed()));
    assert!(later.changed());
    assert!(futures_executor::block_on(later.load(keys[0]))
        .unwrap_err()
        .contains(STORE_CHANGED));
    // Without ETags (a plain file server): nothing is checked.
    let plain = open_web(&store, 32);
    assert!(!futures_executor::block_on(plain.check_changed()));
}

#[test]
fn a_lost_shard_fails_the_bricks_its_statistics_say_hold_data() {
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    let shard = std::fs::read(store.join("0/c/0/0/0")).unwrap();
    std::fs::remove_file(store.join("0/c/0/0/0")).unwrap();
    // Without statistics read, as Zarr reads it: the fill value.
    let web = open_web(&store, 32);
    let g = web.geometry.clone();
    let keys: Vec<BrickKey> = g
        .keys(0, 0)
        .filter(|k| k.brick.iter().all(|&v| v < 4))
        .collect();
    for k in &keys {
        futures_executor::block_on(web.load(*k)).expect("fill");
    }
    // With them (as the page reads them): bricks holding data there fail,
    // naming the shard, as the native loader's `check_lost`.
    let (_, problems) = futures_executor::block_on(web.brick_ranges(1 << 21));
    assert!(problems.is_empty(), "{problems:?}");
    let mut failed = 0;
    for k in &keys {
        if let Err(e) = futures_executor::block_on(web.load(*k)) {
            assert!(
                e.contains("0/c/0/0/0") && e.contains("not found") && e.contains("statistics"),
                "{e}"
            );
            failed += 1;
        }
    }
    assert!(failed > 0, "a lost shard of data must fail its bricks");
    // The native loader agrees: the brick fails there too.
    let native =
        Loader::open(&store, [32; 3], 1, 1, Arc::new(HostCache::new(1 << 26))).expect("loader");
    for k in &keys {
        let w = futures_executor::block_on(web.load(*k)).is_err();
        assert_eq!(w, native.load_now(k).is_err(), "{k:?}");
    }
    // The shard back (a repaired file): the same source reads it, equal to
    // a fresh one's bricks (it kept the shard's absence, and failed them
    // for as long as it kept it).
    std::fs::write(store.join("0/c/0/0/0"), &shard).unwrap();
    let fresh = open_web(&store, 32);
    futures_executor::block_on(fresh.brick_ranges(1 << 21));
    for k in &keys {
        let again = futures_executor::block_on(web.load(*k)).expect("the shard is back");
        let want = futures_executor::block_on(fresh.load(*k)).unwrap();
        assert!(again.content == want.content, "{k:?} differs");
    }
}

/// A `Fetch` over files that a switch takes down (a server gone: every
/// request fails as the page's `fetch()` does then), counting the
/// requests sent while it is down.
struct DownFetch(
    FileFetch,
    Rc<std::cell::Cell<bool>>,
    Rc<std::cell::Cell<u64>>,
);

impl brickyard_web::source::Fetch for DownFetch {
    fn get(
        &self,
        path: &str,
        range: brickyard_web::source::Range,
    ) -> brickyard_web::source::LocalFuture<Result<Option<Vec<u8>>, String>> {
        if self.1.get() {
            self.2.set(self.2.get() + 1);
            let e = format!("http://127.0.0.1:1/{path}: {UNREACHABLE}");
            return Box::pin(async move { Err(e) });
        }
        self.0.get(path, range)
    }
}

/// A view (`query`) of the MNI152 T1 over a [`DownFetch`] (its switch
/// and counter), a pool of 64 MiB, the statistics read and the coarsest
/// levels in; and the reference image of the view.
struct DownView {
    s: WebSession,
    exec: LocalPool,
    down: Rc<std::cell::Cell<bool>>,
    sent: Rc<std::cell::Cell<u64>>,
    v: brickyard_web::view::View,
    reference: Image,
}

fn down_view(dir: &Path, query: &str) -> DownView {
    let store = convert_file(dir, "mni152-t1-u8.nii.gz", Compression::Lz4, 64, 128);
    let st = ViewState::from_query(query).unwrap();
    let (reference, _) = stream(&store, &st, [0.0, 255.0], 64 << 20);
    let down = Rc::new(std::cell::Cell::new(false));
    let sent = Rc::new(std::cell::Cell::new(0));
    let src = Rc::new(
        futures_executor::block_on(WebSource::open(
            Rc::new(DownFetch(FileFetch(store), down.clone(), sent.clone())),
            32,
            1,
            1 << 20,
        ))
        .unwrap(),
    );
    let (mut s, mut exec) = session_over(src.clone(), 64 << 20);
    let v = st
        .params(&s.scene, [0.0, 255.0], &src.meta.channels, 1, false)
        .unwrap();
    while !s.ready() {
        exec.run_until_stalled();
        s.frame_cpu(&v.params, v.lod);
    }
    DownView {
        s,
        exec,
        down,
        sent,
        v,
        reference,
    }
}

#[test]
fn a_server_gone_is_not_asked_for_each_brick_and_the_view_ends_from_what_it_has() {
    use brickyard_web::session::RETRY_FAILED_AFTER_MS;
    let dir = tempfile::tempdir().unwrap();
    // A view of many level-0 bricks (more than a frame's request list).
    let DownView {
        mut s,
        mut exec,
        down,
        sent,
        v,
        reference,
    } = down_view(dir.path(), "size=400x400&window=0,255&zoom=1.3");
    // The coarsest levels in and a few frames' bricks, then the server
    // goes.
    for _ in 0..2 {
        exec.run_until_stalled();
        s.frame_cpu(&v.params, v.lod);
    }
    down.set(true);
    let mut frames = 0;
    loop {
        exec.run_until_stalled();
        let out = s.frame_cpu(&v.params, v.lod);
        frames += 1;
        if out.complete {
            break;
        }
        assert!(
            frames < 20,
            "the view did not end in 20 frames with the server gone"
        );
    }
    // Found unreachable by the first request that got no answer: the
    // loads begun meanwhile (at most the 6 at a time) were its only
    // requests, and the view ended from what it had, without asking
    // for its other bricks one by one.
    assert!(s.unreachable());
    assert!(
        sent.get() <= 6,
        "{} requests to a server found unreachable (one per brick?)",
        sent.get()
    );
    assert!(s.image().rgba.iter().filter(|p| p[3] > 0.05).count() > 1000);
    assert!(max_diff(s.image(), &reference) > 0.0);
    let complete = s.image().clone();
    // Still gone at the retry: one request (the probe), nothing let go,
    // and the view stays as it was (no reset, nothing asked for).
    let t0 = 1000.0;
    assert!(!s.retry_failed(t0));
    let before = sent.get();
    assert!(!s.retry_failed(t0 + RETRY_FAILED_AFTER_MS));
    exec.run_until_stalled();
    assert_eq!(sent.get(), before + 1, "the probe is one request");
    assert!(!s.retry_failed(t0 + RETRY_FAILED_AFTER_MS + 1.0));
    exec.run_until_stalled();
    let out = s.frame_cpu(&v.params, v.lod);
    exec.run_until_stalled();
    assert!(out.complete && s.loads.pending() == (0, 0));
    assert_eq!(sent.get(), before + 1, "nothing asked for between probes");
    assert_eq!(max_diff(s.image(), &complete), 0.0);
    // Back: the next probe (20 s on) finds it, the bricks are let go, and
    // the view completes as it would have.
    down.set(false);
    assert!(!s.retry_failed(t0 + 2.0 * RETRY_FAILED_AFTER_MS - 1.0));
    assert!(!s.retry_failed(t0 + 2.0 * RETRY_FAILED_AFTER_MS));
    exec.run_until_stalled();
    assert!(!s.unreachable());
    assert!(s.retry_failed(t0 + 2.0 * RETRY_FAILED_AFTER_MS + 10.0));
    let (image, _) = frames_until_complete(&mut s, &mut exec, &v);
    assert_eq!(s.failing(), 0);
    assert_eq!(max_diff(&image, &reference), 0.0);
}

#[test]
fn failed_bricks_are_asked_for_again_after_a_while() {
    use brickyard_web::session::RETRY_FAILED_AFTER_MS;
    let dir = tempfile::tempdir().unwrap();
    let DownView {
        mut s,
        mut exec,
        down,
        v,
        reference,
        ..
    } = down_view(dir.path(), "mode=mip&size=96x96");
    // The coarsest levels in, then the server goes.
    down.set(true);
    let (partial, _) = frames_until_complete(&mut s, &mut exec, &v);
    assert!(s.failing() > 0, "bricks must fail while the server is down");
    assert!(max_diff(&partial, &reference) > 0.0);
    // Back up: not asked for again before the time is up; then one
    // request finds the server back, and they are.
    down.set(false);
    assert!(!s.retry_failed(1000.0));
    assert!(!s.retry_failed(1000.0 + RETRY_FAILED_AFTER_MS - 1.0));
    assert!(!s.retry_failed(1000.0 + RETRY_FAILED_AFTER_MS));
    exec.run_until_stalled();
    assert!(s.retry_failed(1000.0 + RETRY_FAILED_AFTER_MS + 1.0));
    let (image, _) = frames_until_complete(&mut s, &mut exec, &v);
    assert_eq!(s.failing(), 0);
    assert_eq!(max_diff(&image, &reference), 0.0);
}

/// Files served as a server that ignores `Range` does (`python3 -m
/// http.server`): every read answers the whole object (HTTP 200), a turn
/// of the executor later (so reads overlap); counting the downloads of
/// each level's chunks and shards (`L/c/…`) and the bytes downloaded (of
/// those, and in all).
struct WholeFetch(
    FileFetch,
    Rc<std::cell::RefCell<std::collections::HashMap<String, u64>>>,
    Rc<std::cell::Cell<[u64; 2]>>,
);

impl brickyard_web::source::Fetch for WholeFetch {
    fn get(
        &self,
        path: &str,
        range: brickyard_web::source::Range,
    ) -> brickyard_web::source::LocalFuture<Result<Option<Vec<u8>>, String>> {
        let f = self.get_tagged(path, range, None);
        Box::pin(async move {
            let g = f.await?;
            Ok(g.bytes.map(|b| {
                brickyard_web::source::cut(&b, range)
                    .expect("in the object")
                    .to_vec()
            }))
        })
    }

    fn get_tagged(
        &self,
        path: &str,
        range: brickyard_web::source::Range,
        _if_match: Option<&str>,
    ) -> brickyard_web::source::LocalFuture<Result<brickyard_web::source::Got, String>> {
        let f = self.0.get(path, brickyard_web::source::Range::All);
        let (counts, bytes, path) = (self.1.clone(), self.2.clone(), path.to_string());
        Box::pin(async move {
            let mut yielded = false;
            futures_util::future::poll_fn(|cx| {
                if yielded {
                    std::task::Poll::Ready(())
                } else {
                    yielded = true;
                    cx.waker().wake_by_ref();
                    std::task::Poll::Pending
                }
            })
            .await;
            let b = f.await?;
            if let Some(b) = &b {
                let [mut ranged, mut all] = bytes.get();
                if path.as_bytes()[0].is_ascii_digit() && path.contains("/c/") {
                    *counts.borrow_mut().entry(path).or_insert(0) += 1;
                    ranged += b.len() as u64;
                }
                all += b.len() as u64;
                bytes.set([ranged, all]);
            }
            Ok(brickyard_web::source::Got {
                bytes: b,
                etag: None,
                whole: range != brickyard_web::source::Range::All,
            })
        })
    }
}

#[test]
fn a_server_that_ignores_ranges_sends_each_shard_once_and_the_bytes_are_counted() {
    let dir = tempfile::tempdir().unwrap();
    let store = convert_file(dir.path(), "mni152-t1-u8.nii.gz", Compression::Lz4, 32, 64);
    let st = ViewState::from_query("size=400x400&window=0,255&zoom=1.3").unwrap();
    let (reference, _) = stream(&store, &st, [0.0, 255.0], 64 << 20);
    // The page's chunk budget (32 MiB): each shard downloaded once. One
    // smaller than any shard (memory kept bounded, the shards downloaded
    // again): the same image.
    for (budget, most) in [(32usize << 20, 1), (1 << 12, u64::MAX)] {
        let counts = Rc::new(std::cell::RefCell::new(std::collections::HashMap::new()));
        let bytes = Rc::new(std::cell::Cell::new([0, 0]));
        let src = Rc::new(
            futures_executor::block_on(WebSource::open(
                Rc::new(WholeFetch(
                    FileFetch(store.clone()),
                    counts.clone(),
                    bytes.clone(),
                )),
                32,
                1,
                budget,
            ))
            .unwrap(),
        );
        let (mut s, mut exec) = session_over(src.clone(), 64 << 20);
        let v = st
            .params(&s.scene, [0.0, 255.0], &src.meta.channels, 1, false)
            .unwrap();
        let (image, _) = frames_until_complete(&mut s, &mut exec, &v);
        assert_eq!(max_diff(&image, &reference), 0.0);
        // The read figure is what came down: at least the levels' whole
        // shards, at most everything (the documents and statistics read
        // outside the source's counters are not in it).
        let counted = src.stats.borrow().bytes;
        let [ranged, all] = bytes.get();
        assert!(
            counted >= ranged && counted <= all,
            "read {counted} bytes counted, {ranged} downloaded of shards, {all} in all"
        );
        assert!(src.ranges_ignored());
        let shards: Vec<(String, u64)> = counts
            .borrow()
            .iter()
            .map(|(p, n)| (p.clone(), *n))
            .collect();
        assert!(!shards.is_empty());
        let worst = shards.iter().map(|s| s.1).max().unwrap();
        eprintln!(
            "budget {budget}: {} shards, at most {worst} downloads of one, {} bytes, {:?}",
            shards.len(),
            ranged,
            src.stats.borrow()
        );
        assert!(
            worst <= most,
            "a shard downloaded whole {worst} times: {shards:?}"
        );
    }
}
