//! Loader and host cache against real stores written by the converter and
//! read back, as oracle, whole level by whole level through `ZarrSource`.
//!
//! Over 800 lines: tests only, sharing their store fixtures.

use brickyard_cache::brick::{BrickContent, BrickGeometry, BrickKey, LoadedBrick};
use brickyard_cache::host_cache::{entry_cost, HostCache};
use brickyard_cache::loader::Loader;
use brickyard_core::{dispatch_dtype, DType, Dims3, Sample};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::error::Result as SResult;
use brickyard_store::import::zarr;
use brickyard_store::source::{SourceMeta, VolumeSource};
use std::collections::{HashMap, HashSet};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(120);

fn lcg(s: &mut u64) -> u64 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    *s >> 33
}

/// An in-memory volume, channel-major, x fastest, native endian.
struct MemSource {
    meta: SourceMeta,
    data: Vec<u8>,
}

impl VolumeSource for MemSource {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }
    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> SResult<()> {
        let es = self.meta.dtype.size() as u64;
        let [dz, dy, dx] = self.meta.dims;
        let base = c as u64 * dz * dy * dx;
        let row = ((x.end - x.start) * es) as usize;
        let mut o = 0;
        for zz in z {
            for yy in y.clone() {
                let s = ((base + (zz * dy + yy) * dx + x.start) * es) as usize;
                out[o..o + row].copy_from_slice(&self.data[s..s + row]);
                o += row;
            }
        }
        Ok(())
    }
}

/// A volume whose voxel (c, z, y, x) is `f(c, z, y, x)` converted to `dtype`.
fn mem_source(
    dims: Dims3,
    channels: usize,
    dtype: DType,
    f: impl Fn(usize, u64, u64, u64) -> f64,
) -> MemSource {
    let mut data = Vec::new();
    for c in 0..channels {
        for z in 0..dims[0] {
            for y in 0..dims[1] {
                for x in 0..dims[2] {
                    data.extend(brickyard_cache::brick::value_bytes(dtype, f(c, z, y, x)));
                }
            }
        }
    }
    MemSource {
        meta: SourceMeta::new("mem", dims, channels, dtype),
        data,
    }
}

/// Zero slab (z < d/4), constant slab (z < d/2, value 37 + c), noise.
fn slabs(dims: Dims3, seed: u64) -> impl Fn(usize, u64, u64, u64) -> f64 {
    move |c, z, y, x| {
        if z < dims[0] / 4 {
            0.0
        } else if z < dims[0] / 2 {
            37.0 + c as f64
        } else {
            let mut s = seed ^ (((c as u64 * 1000 + z) * 1000 + y) * 1000 + x);
            lcg(&mut s);
            (lcg(&mut s) % 200) as f64 + 1.0
        }
    }
}

fn convert_to(dir: &Path, name: &str, src: &MemSource, brick: u64, shard: u64) -> PathBuf {
    let out = dir.join(name);
    let opts = ConvertOptions {
        brick: [brick; 3],
        shard: [shard; 3],
        ..Default::default()
    };
    convert(src, &out, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
    out
}

/// Every level, every channel, read whole through `ZarrSource`, as f64.
struct Levels {
    dims: Vec<Dims3>,
    /// `[level][channel]` voxels.
    data: Vec<Vec<Vec<f64>>>,
    dtype: DType,
}

fn read_levels(store: &Path, nlevels: usize) -> Levels {
    let mut dims = vec![];
    let mut data = vec![];
    let mut dtype = DType::U8;
    for l in 0..nlevels {
        let src = zarr::open(store, l).unwrap();
        let m = src.meta();
        dtype = m.dtype;
        let [dz, dy, dx] = m.dims;
        let es = m.dtype.size();
        let mut chans = vec![];
        for c in 0..m.channels {
            let mut b = vec![0u8; (dz * dy * dx) as usize * es];
            src.read_region(c, 0..dz, 0..dy, 0..dx, &mut b).unwrap();
            let v: Vec<f64> = dispatch_dtype!(m.dtype, T => {
                b.chunks_exact(es).map(|e| <T as Sample>::from_le(e).to_f64()).collect()
            });
            chans.push(v);
        }
        dims.push(m.dims);
        data.push(chans);
    }
    Levels { dims, data, dtype }
}

/// Values of a padded brick as a dense f64 array.
fn brick_values(b: &LoadedBrick, g: &BrickGeometry) -> Vec<f64> {
    let n = g.voxels_per_brick() as usize;
    let bytes = b.content.to_dense(n, g.dtype);
    let es = g.dtype.size();
    dispatch_dtype!(g.dtype, T => {
        bytes.chunks_exact(es).map(|e| <T as Sample>::from_le(e).to_f64()).collect()
    })
}

/// The padded brick cut from the whole level with clamp-to-edge, and the
/// (min, max) of the brick proper.
fn crop(levels: &Levels, g: &BrickGeometry, key: &BrickKey) -> (Vec<f64>, f64, f64) {
    let d = levels.dims[key.level as usize];
    let v = &levels.data[key.level as usize][key.channel as usize];
    let po = g.padded_origin_of(key);
    let p = g.padded();
    let o = g.origin_of(key);
    let mut out = vec![];
    let (mut mn, mut mx) = (f64::INFINITY, f64::NEG_INFINITY);
    for k in 0..p[0] as i64 {
        for j in 0..p[1] as i64 {
            for i in 0..p[2] as i64 {
                let q = [po[0] + k, po[1] + j, po[2] + i];
                let c = [0, 1, 2].map(|a| q[a].clamp(0, d[a] as i64 - 1) as u64);
                let val = v[((c[0] * d[1] + c[1]) * d[2] + c[2]) as usize];
                out.push(val);
                let inside = (0..3).all(|a| {
                    q[a] >= o[a] as i64 && q[a] < (o[a] + g.brick[a]) as i64 && (q[a] as u64) < d[a]
                });
                if inside {
                    mn = mn.min(val);
                    mx = mx.max(val);
                }
            }
        }
    }
    (out, mn, mx)
}

fn all_keys(g: &BrickGeometry) -> Vec<BrickKey> {
    let mut keys = vec![];
    for l in 0..g.levels.len() {
        for c in 0..g.channels {
            keys.extend(g.keys(l, c));
        }
    }
    keys
}

/// Request everything, wait, and return what arrived by key.
fn load_all(loader: &Loader, keys: &[BrickKey]) -> HashMap<BrickKey, Arc<LoadedBrick>> {
    let req: Vec<(BrickKey, u32)> = keys.iter().map(|&k| (k, 1)).collect();
    loader.request(&req);
    assert!(loader.wait_idle(WAIT), "loader did not finish");
    let mut got = HashMap::new();
    for b in loader.poll() {
        assert!(got.insert(b.key, b).is_none(), "brick delivered twice");
    }
    got
}

/// Load every brick and compare; returns how many came back uniform.
fn check_all_bricks(store: &Path, brick: Dims3, apron: u64, expect_stats: bool) -> u64 {
    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(store, brick, apron, 2, cache.clone()).unwrap();
    let g = loader.geometry().clone();
    assert_eq!(loader.has_stats(0), expect_stats);
    let levels = read_levels(store, g.levels.len());
    assert_eq!(levels.dims, g.levels);
    assert_eq!(levels.dtype, g.dtype);
    let keys = all_keys(&g);
    let got = load_all(&loader, &keys);
    assert!(loader.take_failures().is_empty());
    assert_eq!(got.len(), keys.len());
    let mut uniform = 0;
    let mut read = 0;
    for k in &keys {
        let b = &got[k];
        let (want, mn, mx) = crop(&levels, &g, k);
        let have = brick_values(b, &g);
        assert_eq!(have, want, "brick {k:?} (brick {brick:?}, apron {apron})");
        assert_eq!((b.min, b.max), (mn, mx), "min/max of {k:?}");
        // Uniform exactly when the padded brick is.
        assert_eq!(b.is_uniform(), want.iter().all(|&v| v == want[0]), "{k:?}");
        if let BrickContent::Data(d) = &b.content {
            assert_eq!(d.len() as u64, g.bytes_per_brick());
            assert!(b.bytes_read > 0);
        } else {
            uniform += 1;
        }
        read += b.bytes_read;
        assert!(cache.contains(k));
    }
    let st = loader.stats();
    assert_eq!(st.bricks_loaded, keys.len() as u64);
    assert_eq!(st.bytes_read, read);
    assert_eq!(st.bricks_empty + st.bricks_constant, uniform);
    // A second request is answered from the cache without reading.
    let again = load_all(&loader, &keys);
    assert_eq!(again.len(), keys.len());
    assert_eq!(loader.bricks_from_cache(), keys.len() as u64);
    assert_eq!(loader.bytes_read(), read);
    for k in &keys {
        assert!(Arc::ptr_eq(&again[k], &got[k]));
    }
    uniform
}

#[test]
fn every_brick_equals_a_clamped_crop_of_its_level() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [37, 45, 51];
    let src = mem_source(dims, 1, DType::U16, slabs(dims, 1));
    let store = convert_to(dir.path(), "a.ome.zarr", &src, 16, 32);
    for apron in [1, 2] {
        for brick in [[8; 3], [12; 3], [20; 3], [12, 8, 20]] {
            let uniform = check_all_bricks(&store, brick, apron, true);
            // Zero below z = 9, constant below z = 18.
            if brick == [8; 3] && apron == 1 {
                assert!(uniform > 0, "the volume has uniform bricks");
            }
        }
    }
}

#[test]
fn multichannel_and_signed_bricks_equal_crops() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [40, 26, 30];
    let f = slabs(dims, 2);
    let src = mem_source(dims, 2, DType::I16, move |c, z, y, x| f(c, z, y, x) - 50.0);
    let store = convert_to(dir.path(), "m.ome.zarr", &src, 8, 16);
    for (brick, apron) in [([8; 3], 1), ([6, 10, 4], 2), ([32; 3], 1)] {
        let uniform = check_all_bricks(&store, brick, apron, true);
        assert_eq!(uniform > 0, brick != [32; 3], "{brick:?}");
    }
}

#[test]
fn stores_without_statistics_load_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [37, 45, 51];
    let src = mem_source(dims, 1, DType::F32, slabs(dims, 3));
    let store = convert_to(dir.path(), "f.ome.zarr", &src, 16, 32);
    std::fs::remove_dir_all(store.join("_brickyard")).unwrap();
    // Uniform padded bricks are still recognized, after reading them.
    assert!(check_all_bricks(&store, [8; 3], 1, false) > 0);
    check_all_bricks(&store, [20; 3], 2, false);
}

/// Expected kind of each brick, from the level's voxels: `Some(true)` when
/// the statistics prove it uniform (no read), `Some(false)` when it is
/// uniform but only reading shows it, `None` for data.
fn expected_kind(
    levels: &Levels,
    g: &BrickGeometry,
    store_brick: Dims3,
    key: &BrickKey,
) -> Option<bool> {
    let d = levels.dims[key.level as usize];
    let v = &levels.data[key.level as usize][key.channel as usize];
    let po = g.padded_origin_of(key);
    let p = g.padded();
    let lo = [0, 1, 2].map(|a| po[a].max(0) as u64);
    let hi = [0, 1, 2].map(|a| ((po[a] + p[a] as i64) as u64).min(d[a]));
    let uniform = |lo: Dims3, hi: Dims3| -> bool {
        let first = v[((lo[0] * d[1] + lo[1]) * d[2] + lo[2]) as usize];
        (lo[0]..hi[0]).all(|z| {
            (lo[1]..hi[1])
                .all(|y| (lo[2]..hi[2]).all(|x| v[((z * d[1] + y) * d[2] + x) as usize] == first))
        })
    };
    let slo = [0, 1, 2].map(|a| lo[a] / store_brick[a] * store_brick[a]);
    let shi = [0, 1, 2].map(|a| (hi[a].div_ceil(store_brick[a]) * store_brick[a]).min(d[a]));
    if uniform(slo, shi) {
        Some(true)
    } else if uniform(lo, hi) {
        Some(false)
    } else {
        None
    }
}

#[test]
fn uniform_regions_need_no_reads() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [64, 40, 44];
    // Zero below z = 24, 9 up to z = 48, noise above.
    let src = mem_source(dims, 1, DType::U8, |_, z, y, x| {
        if z < 24 {
            0.0
        } else if z < 48 {
            9.0
        } else {
            let mut s = (z * 1000 + y) * 1000 + x;
            lcg(&mut s);
            (lcg(&mut s) % 250) as f64 + 1.0
        }
    });
    let store = convert_to(dir.path(), "u.ome.zarr", &src, 8, 16);

    // Engine brick = store brick, apron 1: brick z-index 0 and 1 are empty,
    // 4 is constant, 2, 3, 5 (touching another region through the apron)
    // and above are data.
    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(&store, [8; 3], 1, 2, cache).unwrap();
    let g = loader.geometry().clone();
    let got = load_all(&loader, &g.keys(0, 0).collect::<Vec<_>>());
    for (k, b) in &got {
        match k.brick[0] {
            0 | 1 => {
                assert_eq!(b.content, BrickContent::Empty, "{k:?}");
                assert_eq!(b.bytes_read, 0);
                assert_eq!((b.min, b.max), (0.0, 0.0));
            }
            4 => {
                assert_eq!(b.content, BrickContent::Constant(9.0), "{k:?}");
                assert_eq!(b.bytes_read, 0);
                assert_eq!((b.min, b.max), (9.0, 9.0));
            }
            _ => {
                assert!(matches!(b.content, BrickContent::Data(_)), "{k:?}");
                assert!(b.bytes_read > 0);
            }
        }
    }
    let st = loader.stats();
    let per_layer = (5 * 6) as u64;
    assert_eq!(st.bricks_empty, 2 * per_layer);
    assert_eq!(st.bricks_constant, per_layer);
    assert_eq!(
        st.bytes_read,
        got.values().map(|b| b.bytes_read).sum::<u64>()
    );
    // Interior data bricks read exactly their padded size.
    let inner = BrickKey::new(0, 0, [6, 2, 2]);
    assert_eq!(got[&inner].bytes_read, g.bytes_per_brick());
    drop(loader);

    // Other engine bricks, every level: the kind follows from the voxels.
    for (brick, apron) in [([12; 3], 2), ([4; 3], 1), ([6, 16, 10], 1)] {
        let cache = Arc::new(HostCache::new(1 << 30));
        let loader = Loader::open(&store, brick, apron, 2, cache).unwrap();
        let g = loader.geometry().clone();
        let levels = read_levels(&store, g.levels.len());
        let got = load_all(&loader, &all_keys(&g));
        let mut counts = [0; 3];
        for (k, b) in &got {
            match expected_kind(&levels, &g, [8; 3], k) {
                Some(true) => {
                    assert!(b.is_uniform(), "{k:?} {brick:?}");
                    assert_eq!(b.bytes_read, 0, "{k:?} {brick:?}");
                    counts[0] += 1;
                }
                Some(false) => {
                    assert!(b.is_uniform(), "{k:?} {brick:?}");
                    assert!(b.bytes_read > 0, "{k:?} {brick:?}");
                    counts[1] += 1;
                }
                None => {
                    assert!(!b.is_uniform(), "{k:?} {brick:?}");
                    counts[2] += 1;
                }
            }
            let (want, _, _) = crop(&levels, &g, k);
            assert_eq!(brick_values(b, &g), want);
        }
        assert!(counts[0] > 0 && counts[2] > 0, "{brick:?}: {counts:?}");
    }
}

fn test_brick(i: u64, data: usize) -> Arc<LoadedBrick> {
    Arc::new(LoadedBrick {
        key: BrickKey::new((i % 3) as u8, 0, [i as u32, 0, 0]),
        content: match data {
            0 => BrickContent::Empty,
            1 => BrickContent::Constant(5.0),
            n => BrickContent::Data(vec![7u8; n].into()),
        },
        min: 0.0,
        max: 0.0,
        bytes_read: 0,
    })
}

#[test]
fn host_cache_matches_a_naive_lru_model() {
    for budget in [0, 300, 5_000, 40_000] {
        let cache = HostCache::new(budget);
        // Most recently used first: (key, cost).
        let mut model: Vec<(BrickKey, u64)> = vec![];
        let mut s = budget + 11;
        for step in 0..20_000 {
            let i = lcg(&mut s) % 48;
            if lcg(&mut s) % 5 < 3 {
                let size = match lcg(&mut s) % 4 {
                    0 => 0,
                    1 => 1,
                    _ => (lcg(&mut s) % 4000) as usize,
                };
                let b = test_brick(i, size);
                let cost = entry_cost(&b);
                let key = b.key;
                let ok = cache.insert(b);
                model.retain(|e| e.0 != key);
                if cost <= budget {
                    while model.iter().map(|e| e.1).sum::<u64>() + cost > budget {
                        model.pop();
                    }
                    model.insert(0, (key, cost));
                }
                assert_eq!(ok, cost <= budget);
            } else {
                let key = test_brick(i, 0).key;
                let got = cache.get(&key);
                let pos = model.iter().position(|e| e.0 == key);
                assert_eq!(got.is_some(), pos.is_some(), "step {step}");
                if let Some(p) = pos {
                    let e = model.remove(p);
                    model.insert(0, e);
                    assert_eq!(got.unwrap().key, key);
                }
            }
            assert!(cache.bytes() <= budget);
            assert_eq!(cache.bytes(), model.iter().map(|e| e.1).sum::<u64>());
            assert_eq!(
                cache.keys_by_recency(),
                model.iter().map(|e| e.0).collect::<Vec<_>>(),
                "step {step}"
            );
        }
        assert_eq!(cache.len(), model.len());
        assert_eq!(cache.budget(), budget);
    }
}

#[test]
fn host_cache_budget_holds_under_concurrency() {
    let budget = 50_000;
    let cache = Arc::new(HostCache::new(budget));
    std::thread::scope(|sc| {
        for t in 0..4u64 {
            let cache = cache.clone();
            sc.spawn(move || {
                let mut s = t + 1;
                for _ in 0..20_000 {
                    let i = lcg(&mut s) % 200;
                    if lcg(&mut s).is_multiple_of(2) {
                        cache.insert(test_brick(i, (lcg(&mut s) % 3000) as usize));
                    } else if let Some(b) = cache.get(&test_brick(i, 0).key) {
                        assert_eq!(b.key, test_brick(i, 0).key);
                    }
                    assert!(cache.bytes() <= budget);
                }
            });
        }
    });
    assert!(cache.bytes() <= budget);
    assert!(cache.hits() > 0 && cache.misses() > 0 && cache.evictions() > 0);
    let n = cache.keys_by_recency().len();
    assert_eq!(n, cache.len());
}

fn noise_store(dir: &Path) -> PathBuf {
    let dims = [40, 36, 44];
    let src = mem_source(dims, 1, DType::U16, |_, z, y, x| {
        let mut s = (z * 1000 + y) * 1000 + x + 5;
        lcg(&mut s);
        (lcg(&mut s) % 60000) as f64
    });
    convert_to(dir, "n.ome.zarr", &src, 8, 16)
}

/// Keys of every level with pseudo-random priorities (many ties).
fn prioritized(g: &BrickGeometry, seed: u64) -> Vec<(BrickKey, u32)> {
    let mut s = seed;
    let mut v: Vec<(BrickKey, u32)> = all_keys(g)
        .into_iter()
        .map(|k| (k, (lcg(&mut s) % 5) as u32))
        .collect();
    // Shuffle the request order.
    for i in (1..v.len()).rev() {
        let j = (lcg(&mut s) % (i as u64 + 1)) as usize;
        v.swap(i, j);
    }
    v
}

/// The service order: priority, then coarser level, then request order.
fn service_order(req: &[(BrickKey, u32)]) -> Vec<BrickKey> {
    let mut v: Vec<(usize, &(BrickKey, u32))> = req.iter().enumerate().collect();
    v.sort_by_key(|(i, (k, p))| (std::cmp::Reverse(*p), std::cmp::Reverse(k.level), *i));
    v.into_iter().map(|(_, (k, _))| *k).collect()
}

#[test]
fn one_thread_serves_by_priority_then_coarser_level() {
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(&store, [8; 3], 1, 1, cache).unwrap();
    let req = prioritized(loader.geometry(), 9);
    assert!(req.len() > 100);
    loader.set_paused(true);
    loader.request(&req);
    // Duplicates in one call and across calls are queued once.
    loader.request(&req[..10]);
    assert_eq!(loader.pending(), req.len());
    assert!(!loader.wait_idle(Duration::from_millis(50)));
    loader.set_paused(false);
    assert!(loader.wait_idle(WAIT));
    let got: Vec<BrickKey> = loader.poll().iter().map(|b| b.key).collect();
    assert_eq!(got, service_order(&req));
    assert!(loader.poll().is_empty());

    // Without pausing: a request made in one call is served in order too
    // (the worker takes the best entry each time).
    let dir2 = tempfile::tempdir().unwrap();
    let store2 = noise_store(dir2.path());
    let loader = Loader::open(&store2, [12; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    let req = prioritized(loader.geometry(), 10);
    loader.request(&req);
    assert!(loader.wait_idle(WAIT));
    let got: Vec<BrickKey> = loader.poll().iter().map(|b| b.key).collect();
    assert_eq!(got, service_order(&req));
}

#[test]
fn threads_taking_runs_along_x_stop_at_a_pause_and_lose_nothing() {
    // Three threads take runs of neighbours along x; a pause stops them
    // after the brick each is loading (the rest of a run goes back to the
    // queue), and on resuming every brick arrives once.
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let loader = Loader::open(&store, [4; 3], 1, 3, Arc::new(HostCache::new(1 << 30))).unwrap();
    let keys: Vec<BrickKey> = loader.geometry().keys(0, 0).collect();
    assert!(keys.len() > 200, "{}", keys.len());
    loader.set_read_delay(Duration::from_millis(2));
    loader.request(&keys.iter().map(|&k| (k, 1)).collect::<Vec<_>>());
    std::thread::sleep(Duration::from_millis(30));
    loader.set_paused(true);
    let at_pause = loader.bricks_loaded();
    // The loads in progress (one per thread) finish; nothing starts after
    // them, not even the rest of a thread's run.
    let t = std::time::Instant::now();
    while loader.in_flight() > 0 && t.elapsed() < WAIT {
        std::thread::sleep(Duration::from_millis(1));
    }
    assert_eq!(loader.in_flight(), 0);
    let loaded = loader.bricks_loaded();
    assert!(
        loaded <= at_pause + 3,
        "{at_pause} loaded at the pause, {loaded} after it"
    );
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(loader.bricks_loaded(), loaded);
    assert!(loaded > 0 && (loaded as usize) < keys.len(), "{loaded}");
    assert_eq!(loader.pending() + loaded as usize, keys.len());
    loader.set_read_delay(Duration::ZERO);
    loader.set_paused(false);
    assert!(loader.wait_idle(WAIT));
    let mut got: Vec<BrickKey> = loader.poll().iter().map(|b| b.key).collect();
    got.sort();
    let mut want = keys.clone();
    want.sort();
    assert_eq!(got, want, "every brick once");
}

/// The loader hints the store's bytes of the bricks it claims and of the
/// next ones queued (only once it serves them: none while paused), and the
/// bricks are the same with the hints off.
#[test]
#[cfg(target_os = "linux")]
fn read_ahead_hints_the_bricks_queued_next_and_can_be_turned_off() {
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let mut runs = vec![];
    for ahead in [None, Some(0), Some(3)] {
        let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
        if let Some(n) = ahead {
            loader.set_read_ahead(n);
        }
        let keys: Vec<BrickKey> = loader.geometry().keys(0, 0).collect();
        loader.set_paused(true);
        loader.request(&keys.iter().map(|&k| (k, 1)).collect::<Vec<_>>());
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(loader.stats().ranges_hinted, 0, "hints while paused");
        loader.set_paused(false);
        assert!(loader.wait_idle(WAIT));
        assert!(loader.take_failures().is_empty());
        let mut got: Vec<(BrickKey, Vec<u8>)> = loader
            .poll()
            .iter()
            .map(|b| match &b.content {
                BrickContent::Data(d) => (b.key, d.to_vec()),
                _ => (b.key, vec![]),
            })
            .collect();
        got.sort_by_key(|(k, _)| *k);
        assert_eq!(got.len(), keys.len());
        let hinted = loader.stats().ranges_hinted;
        // The noise store (8³ chunks in 16³ shards) stores every chunk: each
        // is hinted once (neighbouring chunks of a shard in one range), so
        // at least one range per shard and at most one per chunk.
        let d = loader.geometry().levels[0];
        let count = |edge: u64| d.iter().map(|n| n.div_ceil(edge)).product::<u64>();
        match ahead {
            None | Some(3) => assert!(
                (count(16)..=count(8)).contains(&hinted),
                "{ahead:?}: {hinted} ranges for {} shards and {} chunks",
                count(16),
                count(8)
            ),
            _ => assert_eq!(hinted, 0),
        }
        runs.push(got);
    }
    assert!(
        runs[0] == runs[1] && runs[1] == runs[2],
        "bricks differ with read-ahead"
    );
}

#[test]
fn raising_a_priority_moves_the_request_forward() {
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    let keys: Vec<BrickKey> = loader.geometry().keys(0, 0).take(20).collect();
    loader.set_paused(true);
    loader.request(&keys.iter().map(|&k| (k, 1)).collect::<Vec<_>>());
    loader.request(&[(keys[19], 9), (keys[7], 5)]);
    assert_eq!(loader.pending(), 20);
    loader.set_paused(false);
    assert!(loader.wait_idle(WAIT));
    let got: Vec<BrickKey> = loader.poll().iter().map(|b| b.key).collect();
    let mut want = vec![keys[19], keys[7]];
    want.extend(keys.iter().filter(|k| **k != keys[19] && **k != keys[7]));
    assert_eq!(got, want);
}

#[test]
fn cancelled_requests_never_arrive() {
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(&store, [8; 3], 1, 1, cache.clone()).unwrap();
    let req = prioritized(loader.geometry(), 21);
    loader.set_paused(true);
    loader.request(&req);
    let wanted: Vec<BrickKey> = req.iter().step_by(3).map(|e| e.0).collect();
    let dropped = loader.cancel_except(&wanted);
    assert_eq!(dropped, req.len() - wanted.len());
    assert_eq!(loader.pending(), wanted.len());
    loader.set_paused(false);
    assert!(loader.wait_idle(WAIT));
    let got: Vec<BrickKey> = loader.poll().iter().map(|b| b.key).collect();
    let want_order: Vec<BrickKey> = service_order(&req)
        .into_iter()
        .filter(|k| wanted.contains(k))
        .collect();
    assert_eq!(got, want_order);
    assert_eq!(loader.bricks_loaded(), wanted.len() as u64);
    assert_eq!(cache.len(), wanted.len());

    // Racing a running worker: what arrives is a prefix of the service
    // order (started before the cancel) followed by wanted keys only.
    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(&store, [4; 3], 1, 1, cache).unwrap();
    let req = prioritized(loader.geometry(), 22);
    let order = service_order(&req);
    loader.request(&req);
    let wanted: HashSet<BrickKey> = req.iter().step_by(2).map(|e| e.0).collect();
    let dropped = loader.cancel_except(&wanted.iter().copied().collect::<Vec<_>>());
    assert!(loader.wait_idle(WAIT));
    let got: Vec<BrickKey> = loader.poll().iter().map(|b| b.key).collect();
    assert_eq!(got.len() + dropped, req.len());
    let last_unwanted = got.iter().rposition(|k| !wanted.contains(k));
    let prefix = last_unwanted.map_or(0, |i| i + 1);
    assert_eq!(got[..prefix], order[..prefix]);
    let rest: Vec<BrickKey> = order[prefix..]
        .iter()
        .filter(|k| wanted.contains(k))
        .copied()
        .collect();
    assert_eq!(got[prefix..], rest[..]);
}

#[test]
fn cached_bricks_are_delivered_without_loading() {
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(&store, [8; 3], 1, 2, cache.clone()).unwrap();
    let keys: Vec<BrickKey> = loader.geometry().keys(1, 0).collect();
    let first = load_all(&loader, &keys);
    let read = loader.bytes_read();
    // Requesting again, twice before polling: each delivered once.
    let req: Vec<(BrickKey, u32)> = keys.iter().map(|&k| (k, 3)).collect();
    loader.request(&req);
    loader.request(&req);
    assert_eq!(loader.pending(), 0);
    let again = loader.poll();
    assert_eq!(again.len(), keys.len());
    for b in &again {
        assert!(Arc::ptr_eq(b, &first[&b.key]));
    }
    assert_eq!(loader.bytes_read(), read);
    assert_eq!(loader.bricks_from_cache(), keys.len() as u64);
    assert_eq!(loader.bricks_loaded(), keys.len() as u64);

    // A cache too small for one data brick: bricks still arrive by poll.
    let tiny = Arc::new(HostCache::new(100));
    let loader = Loader::open(&store, [8; 3], 1, 2, tiny.clone()).unwrap();
    let got = load_all(&loader, &keys);
    assert_eq!(got.len(), keys.len());
    assert_eq!(tiny.len(), 0);
}

fn shard_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            shard_files(&p, out);
        } else if p.file_name().unwrap() != "zarr.json" {
            out.push(p);
        }
    }
}

#[test]
fn broken_stores_report_failures_without_hanging() {
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let mut shards = vec![];
    shard_files(&store.join("0"), &mut shards);
    shards.sort();
    assert!(shards.len() >= 4);
    // One shard truncated, one with garbage of the same length (bad CRC).
    std::fs::write(&shards[0], b"garbage").unwrap();
    let len = std::fs::metadata(&shards[1]).unwrap().len() as usize;
    std::fs::write(&shards[1], vec![0xA5u8; len]).unwrap();

    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(&store, [8; 3], 1, 2, cache).unwrap();
    let keys: Vec<BrickKey> = loader.geometry().keys(0, 0).collect();
    let got = load_all(&loader, &keys);
    let failures = loader.take_failures();
    assert!(!failures.is_empty());
    assert_eq!(got.len() + failures.len(), keys.len());
    for f in &failures {
        assert!(!got.contains_key(&f.key));
        assert!(!f.message.is_empty());
    }
    assert_eq!(loader.failed_keys().len(), failures.len());
    assert_eq!(loader.stats().bricks_failed, failures.len() as u64);
    // Failed keys are not retried on a new request...
    loader.request(&failures.iter().map(|f| (f.key, 1)).collect::<Vec<_>>());
    assert_eq!(loader.pending(), 0);
    assert!(loader.wait_idle(WAIT));
    assert!(loader.take_failures().is_empty());
    // ... until asked to.
    loader.retry_failed();
    loader.request(&failures.iter().map(|f| (f.key, 1)).collect::<Vec<_>>());
    assert!(loader.wait_idle(WAIT));
    assert_eq!(loader.take_failures().len(), failures.len());
    // The workers are still alive.
    let ok: Vec<BrickKey> = loader.geometry().keys(1, 0).collect();
    assert_eq!(load_all(&loader, &ok).len(), ok.len());

    // A key outside the volume is a failure, not a panic.
    let bad = BrickKey::new(0, 0, [999, 0, 0]);
    loader.request(&[(bad, 1)]);
    assert_eq!(loader.take_failures()[0].key, bad);
    assert!(loader.load_now(&bad).is_err());

    // Stores that cannot be opened.
    assert!(Loader::open(
        &dir.path().join("missing"),
        [8; 3],
        1,
        1,
        Arc::new(HostCache::new(0))
    )
    .is_err());
    std::fs::remove_file(store.join("1/zarr.json")).unwrap();
    assert!(Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(0))).is_err());
    assert!(Loader::open(&store, [0, 8, 8], 1, 1, Arc::new(HostCache::new(0))).is_err());
}

#[test]
fn a_deleted_shard_where_statistics_say_data_is_a_failure_naming_the_file() {
    // A Zarr reader sees a missing shard as all fill value; the store's
    // statistics say the brick holds data, so the loader reports the
    // missing file instead of handing out an empty brick.
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let mut shards = vec![];
    shard_files(&store.join("0"), &mut shards);
    shards.sort();
    std::fs::remove_file(&shards[0]).unwrap();
    let loader = Loader::open(&store, [8; 3], 0, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    let k = BrickKey::new(0, 0, [0, 0, 0]);
    let e = loader.load_now(&k).unwrap_err().to_string();
    assert!(e.contains(shards[0].to_str().unwrap()), "{e}");
    assert!(e.contains("missing") && e.contains("store brick"), "{e}");
    // Gone with its statistics (a store replaced by one of fewer levels,
    // read through a server): the message said the statistics held
    // "[NaN, NaN]"; it says they are missing too.
    let mut stats = vec![];
    shard_files(&store.join("_brickyard/stats/0"), &mut stats);
    assert!(!stats.is_empty());
    for f in &stats {
        std::fs::remove_file(f).unwrap();
    }
    let loader = Loader::open(&store, [8; 3], 0, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    let e = loader.load_now(&k).unwrap_err().to_string();
    assert!(e.contains(shards[0].to_str().unwrap()), "{e}");
    assert!(
        e.contains("its brick statistics are missing too") && !e.contains("NaN"),
        "{e}"
    );
}

#[test]
fn a_deleted_shard_beside_shards_that_were_read_is_a_failure() {
    // Engine bricks of 32³ over shards of 16³: brick [0, 0, 0] reads eight
    // shards (and an apron from the next ones). With one of them gone the
    // brick comes out partly zeros, not empty; the statistics still say
    // the lost store bricks held data, so the loader names the file
    // instead of handing out a brick with a hole. A deleted shard that
    // only the apron reads fails the brick proper's read no more: the
    // brick is read without its apron, which repeats its edge (its edge
    // blended with zeros before the statistics were looked at; then the
    // brick failed).
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let levels = read_levels(&store, 1);
    let mut shards = vec![];
    shard_files(&store.join("0"), &mut shards);
    let shard = |s: &str| {
        shards
            .iter()
            .find(|p| p.to_str().unwrap().ends_with(s))
            .unwrap()
            .clone()
    };
    let k = BrickKey::new(0, 0, [0, 0, 0]);
    for (gone, apron) in [(shard("/1/0/1"), 0), (shard("/0/2/0"), 1)] {
        let bytes = std::fs::read(&gone).unwrap();
        std::fs::remove_file(&gone).unwrap();
        let loader =
            Loader::open(&store, [32; 3], apron, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
        if apron == 1 {
            let b = loader.load_now(&k).unwrap();
            let g = loader.geometry().clone();
            let (want, have) = (crop(&levels, &g, &k).0, brick_values(&b, &g));
            let p = g.padded();
            let at = |j: [u64; 3]| ((j[0] * p[1] + j[1]) * p[2] + j[2]) as usize;
            for z in 0..p[0] {
                for y in 0..p[1] {
                    for x in 0..p[2] {
                        let own = [z, y, x].map(|v| v.clamp(1, 32));
                        assert_eq!(have[at([z, y, x])], want[at(own)], "{z} {y} {x}");
                    }
                }
            }
            std::fs::write(&gone, bytes).unwrap();
            continue;
        }
        let e = loader.load_now(&k).unwrap_err().to_string();
        assert!(e.contains(gone.to_str().unwrap()), "{e}");
        assert!(e.contains("missing") && e.contains("store brick"), "{e}");
        // With the shard back the brick loads.
        std::fs::write(&gone, bytes).unwrap();
        let loader =
            Loader::open(&store, [32; 3], apron, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
        assert!(matches!(
            loader.load_now(&k).unwrap().content,
            BrickContent::Data(_)
        ));
    }
}

/// A noise store in `dir` with its first level-0 shard moved away: the
/// store, that shard's path and its bytes (to put back).
fn noise_store_less_a_shard(dir: &Path) -> (PathBuf, PathBuf, Vec<u8>) {
    let store = noise_store(dir);
    let mut shards = vec![];
    shard_files(&store.join("0"), &mut shards);
    shards.sort();
    let shard = shards.swap_remove(0);
    let bytes = std::fs::read(&shard).unwrap();
    std::fs::remove_file(&shard).unwrap();
    (store, shard, bytes)
}

#[test]
fn a_deleted_shard_that_comes_back_is_read_by_the_same_loader() {
    // The loader keeps shard indexes and decoded chunks: what it read while
    // the shard was missing (no index, fill-value chunks) must not outlive
    // the failure, or the brick would load as zeros once the shard is back
    // (a viewer retrying failed bricks drew it black and "complete").
    let dir = tempfile::tempdir().unwrap();
    let (store, shard, bytes) = noise_store_less_a_shard(dir.path());
    let k = BrickKey::new(0, 0, [0, 0, 0]);
    std::fs::write(&shard, &bytes).unwrap();
    let want = match Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30)))
        .unwrap()
        .load_now(&k)
        .unwrap()
        .content
    {
        BrickContent::Data(d) => d,
        _ => panic!("brick [0, 0, 0] holds data"),
    };
    std::fs::remove_file(&shard).unwrap();
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    for _ in 0..2 {
        let e = loader.load_now(&k).unwrap_err().to_string();
        assert!(e.contains("missing"), "{e}");
    }
    std::fs::write(&shard, &bytes).unwrap();
    match loader.load_now(&k).unwrap().content {
        BrickContent::Data(d) => assert!(d == want, "the brick differs from the stored one"),
        _ => panic!("the brick came back empty"),
    }
}

#[test]
fn a_shard_index_kept_from_before_the_shard_came_back_is_read_again() {
    // A read-ahead hint reads (and keeps) the index of a shard that is
    // missing at the time; once the shard is back, the read that used the
    // kept "no shard" comes out as the fill value. The lost-chunk rule
    // tells, the reader forgets what it kept, and the read again gets the
    // data (the loader does it at once: a viewer's retry took two rounds).
    let dir = tempfile::tempdir().unwrap();
    let (store, shard, bytes) = noise_store_less_a_shard(dir.path());
    let mut src = zarr::open(&store, 0).unwrap();
    src.enable_chunk_cache(16 << 20);
    assert!(src.check_against_stats());
    src.prefetch(0, [0..8, 0..8, 0..8]);
    std::fs::write(&shard, &bytes).unwrap();
    let mut out = vec![0u8; 8 * 8 * 8 * 2];
    let e = src
        .read_region(0, 0..8, 0..8, 0..8, &mut out)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("missing when the brick was read and is there now")
            && e.contains(brickyard_store::source::READ_AGAIN),
        "{e}"
    );
    src.read_region(0, 0..8, 0..8, 0..8, &mut out).unwrap();
    let fresh = zarr::open(&store, 0).unwrap();
    let mut want = vec![0u8; out.len()];
    fresh.read_region(0, 0..8, 0..8, 0..8, &mut want).unwrap();
    assert!(out == want, "the read again differs from the store");
}

#[test]
fn bricks_of_a_shard_that_came_back_load_at_the_first_retry() {
    // Loads and read-ahead hints while a shard is missing leave its kept
    // index saying "no shard"; once it is back, the first retry of the
    // failed bricks loads them all (a load that meets the stale index is
    // done again at once).
    let dir = tempfile::tempdir().unwrap();
    let (store, shard, bytes) = noise_store_less_a_shard(dir.path());
    let loader = Loader::open(&store, [8; 3], 1, 2, Arc::new(HostCache::new(1 << 30))).unwrap();
    loader.set_read_ahead(64);
    let level0: Vec<(BrickKey, u32)> = all_keys(loader.geometry())
        .into_iter()
        .filter(|k| k.level == 0)
        .map(|k| (k, 1))
        .collect();
    loader.request(&level0);
    assert!(loader.wait_idle(Duration::from_secs(60)));
    assert!(!loader.take_failures().is_empty(), "no brick failed");
    std::fs::write(&shard, &bytes).unwrap();
    for round in 0..3 {
        loader.retry_failed();
        assert!(loader.wait_idle(Duration::from_secs(60)));
        let f = loader.take_failures();
        assert!(
            f.is_empty(),
            "round {round}: {} failed: {}",
            f.len(),
            f[0].message
        );
    }
}

#[test]
fn a_store_replaced_while_open_fails_its_loads() {
    // The loader caches shard indexes and statistics; a store written
    // again in its place (`convert --overwrite` renames the new one in)
    // has other offsets. Loads after the swap fail, naming the reason,
    // instead of reading the new files at the old offsets.
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(0))).unwrap();
    let k = BrickKey::new(0, 0, [0, 0, 0]);
    loader.load_now(&k).unwrap();
    let other = tempfile::tempdir().unwrap();
    let fresh = noise_store(other.path());
    std::fs::rename(&store, dir.path().join("old")).unwrap();
    std::fs::rename(&fresh, &store).unwrap();
    let e = loader.load_now(&k).unwrap_err().to_string();
    assert!(e.contains("replaced or removed since it was opened"), "{e}");
    // A loader opened on the new store reads it.
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(0))).unwrap();
    loader.load_now(&k).unwrap();
}

#[cfg(unix)]
#[test]
fn a_fifo_in_place_of_a_shard_is_a_failure_not_a_hang() {
    // Opening a FIFO for reading waits for a writer; the loader's threads
    // must not: the file is refused by kind, naming it.
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let shard = first_shard(&store);
    std::fs::remove_file(&shard).unwrap();
    let made = std::process::Command::new("mkfifo")
        .arg(&shard)
        .status()
        .unwrap();
    assert!(made.success());
    let (tx, rx) = std::sync::mpsc::channel();
    let s = store.clone();
    std::thread::spawn(move || {
        let loader = Loader::open(&s, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
        let _ = tx.send(
            loader
                .load_now(&BrickKey::new(0, 0, [0, 0, 0]))
                .map(|_| ())
                .map_err(|e| e.to_string()),
        );
    });
    let got = rx
        .recv_timeout(std::time::Duration::from_secs(60))
        .expect("the load returned");
    let e = got.unwrap_err();
    assert!(e.contains(shard.to_str().unwrap()), "{e}");
    assert!(e.contains("not a regular file"), "{e}");
}

#[test]
fn a_deleted_shard_under_a_constant_brick_next_to_data_is_a_failure() {
    // Store bricks of 8³ in shards of 16³. z 24..32: constant 9 (the brick
    // proper of engine bricks [3, y, x], which the statistics say is
    // uniform); its apron planes z = 23 and z = 32 are zeros inside store
    // bricks that hold noise. With the shard of z 16..32 gone, the whole
    // padded brick reads as zeros: the statistics say 9, so the loader
    // must name the file, not hand out an empty brick (whether it reads
    // the apron alone or the whole brick).
    let dir = tempfile::tempdir().unwrap();
    let dims = [48, 16, 16];
    let src = mem_source(dims, 1, DType::U8, |_, z, y, x| {
        let noise = || {
            let mut s = (z * 1000 + y) * 1000 + x + 11;
            lcg(&mut s);
            (lcg(&mut s) % 250) as f64 + 1.0
        };
        match z {
            16..=22 | 33..=39 => noise(),
            24..=31 => 9.0,
            _ => 0.0,
        }
    });
    let store = convert_to(dir.path(), "c.ome.zarr", &src, 8, 16);
    let k = BrickKey::new(0, 0, [3, 0, 0]);
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    let b = loader.load_now(&k).unwrap();
    assert!(matches!(b.content, BrickContent::Data(_)));
    assert_eq!((b.min, b.max), (9.0, 9.0));
    drop(loader);
    let mut shards = vec![];
    shard_files(&store.join("0"), &mut shards);
    let gone = shards
        .into_iter()
        .find(|p| p.to_str().unwrap().ends_with("/1/0/0"))
        .expect("the shard of z 16..32");
    std::fs::remove_file(&gone).unwrap();
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    let e = loader.load_now(&k).unwrap_err().to_string();
    assert!(e.contains(gone.to_str().unwrap()), "{e}");
    assert!(e.contains("missing") && e.contains("store brick"), "{e}");
}

/// The shard file of level 0 holding store brick `[0, 0, 0]`.
fn first_shard(store: &Path) -> PathBuf {
    let mut shards = vec![];
    shard_files(&store.join("0"), &mut shards);
    shards
        .into_iter()
        .find(|p| p.to_str().unwrap().ends_with("/0/0/0"))
        .expect("a shard at the origin")
}

#[test]
fn a_chunk_dropped_from_its_shard_index_is_a_failure_naming_the_file() {
    // The shard file is there and its index is sound (CRC32C included),
    // but the entry of one inner chunk says "absent": a Zarr reader gives
    // the fill value; the statistics say the brick holds data.
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let shard = first_shard(&store);
    let mut bytes = std::fs::read(&shard).unwrap();
    // 16³ shards of 8³ inner chunks: 8 entries of 16 bytes, then the CRC.
    let ib = 8 * 16 + 4;
    let at = bytes.len() - ib;
    let crc = |b: &[u8]| crc32c::crc32c(&b[at..at + 128]).to_le_bytes();
    assert_eq!(
        crc(&bytes),
        bytes[at + 128..],
        "the index layout assumed here"
    );
    bytes[at..at + 16].fill(0xff);
    let c = crc(&bytes);
    bytes[at + 128..].copy_from_slice(&c);
    std::fs::write(&shard, &bytes).unwrap();

    let loader = Loader::open(&store, [8; 3], 0, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    let e = loader
        .load_now(&BrickKey::new(0, 0, [0, 0, 0]))
        .unwrap_err()
        .to_string();
    assert!(e.contains(shard.to_str().unwrap()), "{e}");
    assert!(e.contains("no entry for its inner chunk"), "{e}");
    // Its neighbours in the same shard still load, with their values.
    let levels = read_levels(&store, 1);
    let g = loader.geometry().clone();
    for k in [[0, 0, 1], [0, 1, 0], [1, 1, 1]] {
        let k = BrickKey::new(0, 0, k);
        let b = loader.load_now(&k).unwrap();
        assert_eq!(brick_values(&b, &g), crop(&levels, &g, &k).0, "{k:?}");
    }
}

#[test]
fn a_chunk_whose_bytes_changed_but_still_decode_is_a_failure() {
    // Uncompressed chunks: bytes overwritten inside one decode without
    // complaint (as any codec without a checksum may), to values (65535)
    // the statistics of that brick (at most 59999) exclude.
    let dir = tempfile::tempdir().unwrap();
    let src = mem_source([40, 36, 44], 1, DType::U16, |_, z, y, x| {
        let mut s = (z * 1000 + y) * 1000 + x + 5;
        lcg(&mut s);
        (lcg(&mut s) % 60000) as f64
    });
    let store = dir.path().join("raw.ome.zarr");
    let opts = ConvertOptions {
        brick: [8; 3],
        shard: [16; 3],
        compression: brickyard_store::Compression::None,
        ..Default::default()
    };
    convert(&src, &store, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
    let shard = first_shard(&store);
    let mut bytes = std::fs::read(&shard).unwrap();
    let at = bytes.len() - (8 * 16 + 4);
    let off = u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
    let len = u64::from_le_bytes(bytes[at + 8..at + 16].try_into().unwrap()) as usize;
    assert!(len > 64, "{len}");
    bytes[off..off + len].fill(0xff);
    std::fs::write(&shard, &bytes).unwrap();
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(0))).unwrap();
    let e = loader
        .load_now(&BrickKey::new(0, 0, [0, 0, 0]))
        .unwrap_err()
        .to_string();
    assert!(e.contains(shard.to_str().unwrap()), "{e}");
    assert!(e.contains("statistics say"), "{e}");
    // Bricks of other chunks load, with their values.
    let levels = read_levels(&store, 1);
    let g = loader.geometry().clone();
    let k = BrickKey::new(0, 0, [1, 1, 1]);
    let b = loader.load_now(&k).unwrap();
    assert_eq!(brick_values(&b, &g), crop(&levels, &g, &k).0);
}

#[test]
fn a_store_damaged_while_open_fails_bricks_and_keeps_serving_the_rest() {
    // Some bricks of each shard are read (the reader now holds their shard
    // indexes), then the store changes under the open loader: one shard
    // scrambled in place (same length), one truncated, one deleted, and a
    // whole coarser level removed. The rest are then asked for: no panic,
    // every brick either equals its crop or is a reported failure, the
    // untouched shards' bricks all arrive, and the loader keeps working.
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let levels = read_levels(&store, 2);
    let loader = Loader::open(&store, [8; 3], 0, 2, Arc::new(HostCache::new(0))).unwrap();
    let g = loader.geometry().clone();
    let keys: Vec<BrickKey> = g.keys(0, 0).collect();
    let (early, late): (Vec<BrickKey>, Vec<BrickKey>) = keys
        .iter()
        .partition(|k| k.brick.iter().sum::<u32>() % 2 == 0);
    let got = load_all(&loader, &early);
    assert_eq!(got.len(), early.len());
    assert!(loader.take_failures().is_empty());

    let mut shards = vec![];
    shard_files(&store.join("0"), &mut shards);
    shards.sort();
    assert!(shards.len() >= 6);
    let len = std::fs::metadata(&shards[0]).unwrap().len() as usize;
    std::fs::write(&shards[0], vec![0x5Au8; len]).unwrap();
    let f = std::fs::OpenOptions::new()
        .write(true)
        .open(&shards[1])
        .unwrap();
    f.set_len(len as u64 / 3).unwrap();
    drop(f);
    std::fs::remove_file(&shards[2]).unwrap();
    std::fs::remove_dir_all(store.join("1")).unwrap();
    let damaged: Vec<&PathBuf> = shards[..3].iter().collect();
    // The shard file of a level-0 brick (16³ shards of 8³ bricks).
    let shard_of = |k: &BrickKey| {
        let s = k.brick.map(|p| p / 2);
        shards
            .iter()
            .find(|p| {
                p.to_str()
                    .unwrap()
                    .ends_with(&format!("/{}/{}/{}", s[0], s[1], s[2]))
            })
            .unwrap()
    };

    let got = load_all(&loader, &late);
    let failures = loader.take_failures();
    assert_eq!(got.len() + failures.len(), late.len());
    for (k, b) in &got {
        assert_eq!(brick_values(b, &g), crop(&levels, &g, k).0, "{k:?}");
    }
    for f in &failures {
        assert!(
            damaged.contains(&shard_of(&f.key)),
            "{:?} failed but its shard was not damaged: {}",
            f.key,
            f.message
        );
    }
    let lost: HashSet<&PathBuf> = failures.iter().map(|f| shard_of(&f.key)).collect();
    assert!(
        lost.len() >= 2,
        "failures in {} of the 3 damaged shards",
        lost.len()
    );
    for k in &late {
        if !damaged.contains(&shard_of(k)) {
            assert!(
                got.contains_key(k),
                "{k:?} of an intact shard did not arrive"
            );
        }
    }
    // The removed level fails brick by brick; level 0 still serves.
    let l1: Vec<BrickKey> = g.keys(1, 0).collect();
    let got1 = load_all(&loader, &l1);
    let f1 = loader.take_failures();
    assert_eq!(got1.len() + f1.len(), l1.len());
    assert!(!f1.is_empty());
    let intact: Vec<BrickKey> = late
        .iter()
        .filter(|k| !damaged.contains(&shard_of(k)))
        .copied()
        .collect();
    assert!(!intact.is_empty());
    loader.retry_failed();
    assert_eq!(load_all(&loader, &intact).len(), intact.len());
}

#[test]
fn a_damaged_chunk_fails_its_own_bricks_not_the_neighbours_whose_apron_reaches_it() {
    // One inner chunk of a shard scrambled (same length; the shard's index
    // intact). Its neighbours' aprons reach into it: they failed too (a
    // brick per chunk here, 1 + 26 neighbours). Now only the chunk's own
    // brick fails; the others arrive with their brick proper as stored
    // and their apron as stored but where it lies in the damaged chunk,
    // which repeats the brick's edge.
    let dir = tempfile::tempdir().unwrap();
    let store = noise_store(dir.path());
    let levels = read_levels(&store, 1);
    // Shard [1, 1, 1] of level 0 (voxels 16..32 on every axis): its 8
    // inner chunks of 8³, the index (offset, length) per chunk at its end.
    let shard = store.join("0/c/1/1/1");
    let mut bytes = std::fs::read(&shard).unwrap();
    let index = bytes.len() - (8 * 16 + 4);
    let entry = |i: usize| {
        let at = index + 16 * i;
        let num = |o: usize| u64::from_le_bytes(bytes[at + o..at + o + 8].try_into().unwrap());
        (num(0) as usize, num(8) as usize)
    };
    // Inner chunk [1, 0, 1] of the shard (C order): level-0 brick [3, 2, 3].
    let (off, len) = entry(5);
    assert!(len > 16 && off + len <= index, "chunk ({off}, {len})");
    bytes[off..off + len].fill(0x5A);
    std::fs::write(&shard, &bytes).unwrap();
    let bad = BrickKey {
        level: 0,
        channel: 0,
        brick: [3, 2, 3],
    };
    let loader = Loader::open(&store, [8; 3], 1, 2, Arc::new(HostCache::new(0))).unwrap();
    let g = loader.geometry().clone();
    let keys: Vec<BrickKey> = g.keys(0, 0).collect();
    let got = load_all(&loader, &keys);
    let failures = loader.take_failures();
    assert_eq!(
        failures.iter().map(|f| f.key).collect::<Vec<_>>(),
        vec![bad],
        "{:?}",
        failures.iter().map(|f| &f.message).collect::<Vec<_>>()
    );
    assert_eq!(got.len(), keys.len() - 1);
    // The damaged chunk's voxels, in level coordinates.
    let in_bad = |q: [i64; 3]| {
        (0..3).all(|a| q[a] >= 8 * bad.brick[a] as i64 && q[a] < 8 * (bad.brick[a] as i64 + 1))
    };
    let (p, d) = (g.padded(), levels.dims[0]);
    let mut neighbours = 0;
    for (k, b) in &got {
        let want = crop(&levels, &g, k).0;
        let have = brick_values(b, &g);
        let po = g.padded_origin_of(k);
        let e = g.extent_of(k);
        let voxels = || {
            (0..p[0] as i64).flat_map(move |z| {
                (0..p[1] as i64).flat_map(move |y| (0..p[2] as i64).map(move |x| [z, y, x]))
            })
        };
        let at = |j: [i64; 3]| ((j[0] * p[1] as i64 + j[1]) * p[2] as i64 + j[2]) as usize;
        let level_voxel = |j: [i64; 3]| [0, 1, 2].map(|a| (po[a] + j[a]).clamp(0, d[a] as i64 - 1));
        if !voxels().any(|j| in_bad(level_voxel(j))) {
            assert_eq!(have, want, "{k:?}");
            continue;
        }
        // A neighbour: its brick proper as stored, its apron the brick's
        // edge repeated (the apron's nearest voxel of the brick proper).
        neighbours += 1;
        for j in voxels() {
            let own = [0, 1, 2].map(|a| j[a].clamp(1, e[a] as i64));
            assert_eq!(
                have[at(j)],
                want[at(own)],
                "{k:?} at {j:?} of its padded brick"
            );
        }
    }
    assert_eq!(neighbours, 26, "the damaged brick's neighbours");
}

#[test]
fn read_delay_slows_reads_only() {
    let dir = tempfile::tempdir().unwrap();
    // Zero below z = 16, noise above.
    let src = mem_source([32, 24, 24], 1, DType::U16, |_, z, y, x| {
        if z < 16 {
            0.0
        } else {
            let mut s = (z * 1000 + y) * 1000 + x + 3;
            lcg(&mut s);
            (lcg(&mut s) % 60000) as f64 + 1.0
        }
    });
    let store = convert_to(dir.path(), "d.ome.zarr", &src, 8, 16);
    let cache = Arc::new(HostCache::new(1 << 30));
    let loader = Loader::open(&store, [8; 3], 1, 1, cache).unwrap();
    assert!(loader.has_stats(0));
    assert_eq!(loader.read_delay(), Duration::ZERO);
    let delay = Duration::from_millis(30);
    loader.set_read_delay(delay);
    assert_eq!(loader.read_delay(), delay);

    // Four data bricks (z index 3: noise, apron included) on one thread:
    // at least four delays.
    let data: Vec<BrickKey> = (0..4)
        .map(|i| BrickKey::new(0, 0, [3, i / 2, i % 2]))
        .collect();
    let t = std::time::Instant::now();
    loader.request(&data.iter().map(|&k| (k, 1)).collect::<Vec<_>>());
    assert!(loader.wait_idle(WAIT));
    let took = t.elapsed();
    let got = loader.poll();
    assert_eq!(got.len(), 4);
    assert!(got.iter().all(|b| b.bytes_read > 0 && !b.is_uniform()));
    assert!(
        took >= Duration::from_millis(100),
        "4 reads with a 30 ms delay took {took:?}"
    );

    // Host-cache hits are answered inside `request`, without a worker.
    loader.request(&data.iter().map(|&k| (k, 1)).collect::<Vec<_>>());
    assert_eq!((loader.pending(), loader.in_flight()), (0, 0));
    assert_eq!(loader.poll().len(), 4);
    assert_eq!(loader.bricks_from_cache(), 4);

    // Bricks the statistics prove empty are not read, hence not delayed:
    // nine of them with a 1 s delay would take 9 s.
    loader.set_read_delay(Duration::from_secs(1));
    let empty: Vec<BrickKey> = (0..9)
        .map(|i| BrickKey::new(0, 0, [0, i / 3, i % 3]))
        .collect();
    let t = std::time::Instant::now();
    loader.request(&empty.iter().map(|&k| (k, 1)).collect::<Vec<_>>());
    assert!(loader.wait_idle(WAIT));
    let took = t.elapsed();
    let got = loader.poll();
    assert_eq!(got.len(), 9);
    assert!(got
        .iter()
        .all(|b| b.content == BrickContent::Empty && b.bytes_read == 0));
    assert!(
        took < Duration::from_secs(4),
        "empty bricks were delayed: {took:?}"
    );

    // `load_now` reads on the calling thread and is delayed there.
    loader.set_read_delay(Duration::from_millis(50));
    let t = std::time::Instant::now();
    let b = loader.load_now(&BrickKey::new(0, 0, [2, 1, 1])).unwrap();
    assert!(b.bytes_read > 0);
    assert!(t.elapsed() >= Duration::from_millis(50));

    // Zero turns it off (one-sided: far below four 1 s delays).
    loader.set_read_delay(Duration::from_secs(1));
    loader.set_read_delay(Duration::ZERO);
    let fresh: Vec<BrickKey> = (0..4)
        .map(|i| BrickKey::new(0, 0, [2, i / 2, i % 2]))
        .collect();
    let t = std::time::Instant::now();
    loader.request(&fresh.iter().map(|&k| (k, 1)).collect::<Vec<_>>());
    assert!(loader.wait_idle(WAIT));
    assert!(
        t.elapsed() < Duration::from_secs(3),
        "delay not turned off: {:?}",
        t.elapsed()
    );
}

/// The padded brick of `key` cut from the level's bytes (read whole by the
/// Zarr library, without the loader's chunk path), clamp to edge.
fn crop_bytes(level: &[u8], d: Dims3, es: usize, g: &BrickGeometry, key: &BrickKey) -> Vec<u8> {
    let po = g.padded_origin_of(key);
    let p = g.padded();
    let mut out = Vec::with_capacity(g.bytes_per_brick() as usize);
    for k in 0..p[0] as i64 {
        for j in 0..p[1] as i64 {
            for i in 0..p[2] as i64 {
                let q = [po[0] + k, po[1] + j, po[2] + i];
                let c = [0, 1, 2].map(|a| q[a].clamp(0, d[a] as i64 - 1) as u64);
                let s = ((c[0] * d[1] + c[1]) * d[2] + c[2]) as usize * es;
                out.extend_from_slice(&level[s..s + es]);
            }
        }
    }
    out
}

/// Bit for bit, level 0: every brick the loader cuts (through its
/// decoded-chunk cache, shells and coalesced shard reads) equals the crop
/// of the level read by the Zarr library, for engine bricks smaller than,
/// equal to, larger than and misaligned with the store's chunks, aprons 1
/// and 2 (the volume's faces included), u8, u16 and f32 (NaN and -0.0
/// among the values), with a decoded-chunk cache far smaller than the
/// level (evictions and shells) and with a large one, on 1 and 3 threads.
#[test]
fn bricks_equal_the_store_bit_for_bit_for_every_ratio_and_dtype() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [45, 38, 53];
    for dtype in [DType::U8, DType::U16, DType::F32] {
        let src = mem_source(dims, 1, dtype, |_, z, y, x| {
            let v = ((z * 131 + y * 71 + x * 29) % 251) as f64;
            match (dtype, (z + y + x) % 97) {
                (DType::F32, 0) => f64::NAN,
                (DType::F32, 1) => -0.0,
                (DType::F32, _) => v * 0.37 - 40.0,
                _ if z < 8 => 0.0,
                _ => v,
            }
        });
        let store = convert_to(dir.path(), &format!("b-{dtype}.ome.zarr"), &src, 16, 32);
        let level = {
            let s = zarr::open(&store, 0).unwrap();
            let mut b = vec![0u8; src.data.len()];
            s.read_region(0, 0..dims[0], 0..dims[1], 0..dims[2], &mut b)
                .unwrap();
            assert_eq!(b, src.data, "the store holds the volume");
            b
        };
        let es = dtype.size();
        for (brick, apron) in [
            ([8; 3], 1),
            ([16; 3], 1),
            ([32; 3], 1),
            ([12, 20, 7], 2),
            ([16; 3], 2),
        ] {
            for (chunk_cache, threads) in [(64 << 10, 3), (64 << 20, 1)] {
                let cache = Arc::new(HostCache::new(1 << 30));
                let loader = Loader::open_with_chunk_cache(
                    &store,
                    brick,
                    apron,
                    threads,
                    cache,
                    chunk_cache,
                )
                .unwrap();
                let g = loader.geometry().clone();
                let keys: Vec<BrickKey> = g.keys(0, 0).collect();
                let got = load_all(&loader, &keys);
                let fails = loader.take_failures();
                assert!(fails.is_empty(), "{fails:?}");
                for k in &keys {
                    let want = crop_bytes(&level, dims, es, &g, k);
                    let have = got[k]
                        .content
                        .to_dense(g.voxels_per_brick() as usize, dtype);
                    assert!(
                        have == want,
                        "{dtype} brick {k:?} (brick {brick:?}, apron {apron}, chunk cache {chunk_cache}, {threads} threads)"
                    );
                }
            }
        }
    }
}

#[test]
fn a_brick_hinted_while_its_shard_was_missing_loads_once_the_shard_is_back() {
    // The read-ahead hint for brick b reads (and keeps) its shard's index
    // while the shard is missing; the shard comes back before b's load,
    // which meets the kept "no shard" and is done again at once, with the
    // file's index: no failure, and b equals the stored brick.
    let dir = tempfile::tempdir().unwrap();
    let (store, shard, bytes) = noise_store_less_a_shard(dir.path());
    let loader = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30))).unwrap();
    loader.set_read_ahead(8);
    // a's load sleeps after its read: the shard comes back meanwhile,
    // after b's hint (issued before a's load) and before b's load.
    loader.set_read_delay(Duration::from_millis(1500));
    let (a, b) = (
        BrickKey::new(0, 0, [4, 4, 4]),
        BrickKey::new(0, 0, [0, 0, 0]),
    );
    loader.set_paused(true);
    loader.request(&[(a, 2), (b, 1)]);
    loader.set_paused(false);
    std::thread::sleep(Duration::from_millis(300));
    std::fs::write(&shard, &bytes).unwrap();
    assert!(loader.wait_idle(Duration::from_secs(60)));
    let f = loader.take_failures();
    assert!(f.is_empty(), "{}", f[0].message);
    let got = loader.poll();
    let got = got
        .iter()
        .find(|l| l.key == b)
        .expect("brick b was not loaded");
    let want = Loader::open(&store, [8; 3], 1, 1, Arc::new(HostCache::new(1 << 30)))
        .unwrap()
        .load_now(&b)
        .unwrap();
    match (&got.content, want.content) {
        (BrickContent::Data(g), BrickContent::Data(w)) => {
            assert!(*g == w, "brick b differs from the stored one")
        }
        _ => panic!("brick b came back without data"),
    }
}
