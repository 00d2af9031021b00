//! End to end: a converted store streamed through loader, host cache and
//! virtual memory with budgets far smaller than the volume. Every sample
//! equals clamp-to-edge sampling of the level that served it (read whole
//! from the store), and a still view completes.

use brickyard_cache::brick::BrickKey;
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_core::{dispatch_dtype, DType, Dims3, Sample};
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::import::zarr;
use brickyard_store::VolumeSource;
use std::sync::atomic::AtomicBool;

struct Level {
    dims: Dims3,
    data: Vec<f64>,
}

fn read_levels(store: &std::path::Path) -> Vec<Level> {
    let mut out = vec![];
    for l in 0.. {
        let Ok(s) = zarr::open(store, l) else { break };
        let d = s.meta().dims;
        let es = s.meta().dtype.size();
        let mut b = vec![0u8; (d[0] * d[1] * d[2]) as usize * es];
        s.read_region(0, 0..d[0], 0..d[1], 0..d[2], &mut b).unwrap();
        let data = dispatch_dtype!(s.meta().dtype, T => {
            b.chunks_exact(es).map(|e| <T as Sample>::from_le(e).to_f64()).collect()
        });
        out.push(Level { dims: d, data });
    }
    out
}

fn reference(lv: &Level, p: [f64; 3]) -> f64 {
    let d = lv.dims;
    let at = |v: [i64; 3]| {
        let c = [0, 1, 2].map(|a| v[a].clamp(0, d[a] as i64 - 1) as u64);
        lv.data[((c[0] * d[1] + c[1]) * d[2] + c[2]) as usize]
    };
    let q = [0, 1, 2].map(|a| (p[a] * d[a] as f64 - 0.5).clamp(0.0, (d[a] - 1) as f64));
    let b = q.map(|x| x.floor());
    let f = [0, 1, 2].map(|a| q[a] - b[a]);
    let mut acc = 0.0;
    for dz in 0..2 {
        for dy in 0..2 {
            for dx in 0..2 {
                let w = (if dz == 1 { f[0] } else { 1.0 - f[0] })
                    * (if dy == 1 { f[1] } else { 1.0 - f[1] })
                    * (if dx == 1 { f[2] } else { 1.0 - f[2] });
                acc += w * at([b[0] as i64 + dz, b[1] as i64 + dy, b[2] as i64 + dx]);
            }
        }
    }
    acc
}

#[test]
fn streamed_samples_are_exact_and_a_still_view_completes() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("v.ome.zarr");
    let src = Procedural::new(Kind::MarschnerLobb, [40, 56, 72], DType::U16);
    let opts = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
    let levels = read_levels(&store);
    let volume_bytes = 40 * 56 * 72 * 2;
    // Pool: 24 bricks of 10³ u16 = 48 KB against a 322 KB volume.
    let cfg = VmConfig {
        brick: [8; 3],
        apron: 1,
        pt_block: [2; 3],
        max_dir_entries: 64,
        pool_bytes: 24 * 1000 * 2,
        pt_cache_blocks: 24,
        request_cap: 16,
        upload_bytes_per_frame: 6 * 2000,
    };
    assert!(cfg.pool_bytes * 4 < volume_bytes);
    let mut s = Session::open(&store, cfg, 64 << 10, 2).unwrap();
    assert!(
        s.vm().layout().nmax() >= 3,
        "expect intermediate page tables"
    );
    let mut rng = 7u64;
    let mut next = || {
        rng = rng
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (rng >> 11) as f64 / (1u64 << 53) as f64
    };
    // A still view on level 1 and a coarser overview: fits in the pool.
    let view: Vec<(usize, [f64; 3])> = (0..40)
        .map(|i| {
            (
                if i % 4 == 0 { 2 } else { 1 },
                [0.3 + 0.2 * next(), 0.3 + 0.2 * next(), 0.3 + 0.2 * next()],
            )
        })
        .collect();
    let mut completed = None;
    for frame in 0..2000 {
        s.begin_frame();
        let mut req = s.vm().requests();
        let mut exact = 0;
        for &(l, p) in &view {
            let r = s.vm().sample(l, 0, p, true, &mut req);
            if let Some(lv) = r.level {
                let want = reference(&levels[lv as usize], p);
                assert!(
                    (r.value as f64 - want).abs() < 1e-2 * want.abs().max(1.0),
                    "frame {frame} level {lv}: {} vs {want}",
                    r.value
                );
                exact += (lv as usize == l) as usize;
            }
        }
        let st = s.finish_frame([&req]);
        assert!(
            st.insert.bytes_uploaded <= 6 * 2000,
            "upload budget exceeded"
        );
        assert!(st.frame.requests.len() <= 16);
        if exact == view.len() {
            completed = Some(frame);
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    assert!(completed.is_some(), "the view never completed");
    assert!(
        s.loader().cache().bytes() <= 64 << 10,
        "host cache over budget"
    );
    s.vm().check_invariants().unwrap();
    // Then a moving view over every level: values stay exact, bricks keep coming.
    let (mut inserted, mut checked) = (0, 0);
    for frame in 0..300 {
        s.begin_frame();
        let mut req = s.vm().requests();
        for _ in 0..30 {
            let l = (next() * levels.len() as f64) as usize;
            let p = [next(), next(), next()];
            let r = s.vm().sample(l.min(levels.len() - 1), 0, p, true, &mut req);
            if let Some(lv) = r.level {
                let want = reference(&levels[lv as usize], p);
                assert!(
                    (r.value as f64 - want).abs() < 1e-2 * want.abs().max(1.0),
                    "moving frame {frame}"
                );
                checked += 1;
            }
        }
        let st = s.finish_frame([&req]);
        inserted += st.insert.inserted;
        s.vm().check_invariants().unwrap();
    }
    assert!(inserted > 0);
    // Most samples were served (and so compared), not only a few.
    assert!(
        checked > 300 * 30 / 2,
        "{checked} of {} samples served",
        300 * 30
    );
}

/// A session over a 64³ store of 8³ bricks (512 at level 0: eight caps of
/// `cap`), with a pool that holds them all.
fn eight_caps_session(cap: usize) -> (tempfile::TempDir, Session) {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("v.ome.zarr");
    let src = Procedural::new(Kind::Mandelbulb, [64; 3], DType::U8);
    let opts = ConvertOptions {
        brick: [16; 3],
        shard: [32; 3],
        ..Default::default()
    };
    convert(&src, &store, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
    let cfg = VmConfig {
        brick: [8; 3],
        apron: 1,
        pool_bytes: 1024 * (10 * 10 * 10 + 64 * 8),
        request_cap: cap,
        upload_bytes_per_frame: 64 << 20,
        ..Default::default()
    };
    let s = Session::open(&store, cfg, 64 << 20, 2).unwrap();
    (dir, s)
}

/// Bricks that arrived while a frame was drawn are inserted at its end and
/// not asked for again: each frame's capped request list goes to bricks
/// not here yet. A view of eight caps' worth of bricks then fills in about
/// eight frames, where asking again for the bricks just arrived took two
/// frames a cap (every other frame loaded nothing).
#[test]
fn bricks_that_arrived_are_not_asked_for_again() {
    let cap = 64;
    let (_dir, mut s) = eight_caps_session(cap);
    // The view: every brick of level 0 (8³ = 512, eight caps), most
    // wanted first in a fixed order.
    let keys: Vec<BrickKey> = (0..512u32)
        .map(|i| BrickKey::new(0, 0, [i / 64, i / 8 % 8, i % 8]))
        .collect();
    let mut frames = 0;
    // Every brick an earlier frame asked for.
    let mut asked = std::collections::HashSet::new();
    while keys.iter().any(|k| !s.vm().is_resident(*k)) {
        frames += 1;
        assert!(frames <= 40, "the view did not fill in 40 frames");
        s.begin_frame();
        let mut req = s.vm().requests();
        for (i, k) in keys.iter().enumerate() {
            if !s.vm().is_resident(*k) {
                req.add(*k, 1000 - i as u32);
            }
        }
        // Whatever was asked for before has arrived by the frame's end
        // (a frame drawn slower than the loader loads).
        assert!(s.loader().wait_idle(std::time::Duration::from_secs(20)));
        let st = s.finish_frame([&req]);
        // The cap goes to bricks not asked for yet, as many as remain.
        assert_eq!(st.frame.requests.len(), cap.min(keys.len() - asked.len()));
        // No request for a brick an earlier frame asked for: all of those
        // had arrived when this frame's list was made. (A brick asked for
        // now may arrive before the frame's end and be inserted already.)
        for k in &st.frame.requests {
            assert!(
                asked.insert(*k),
                "frame {frames}: asked again for {k:?}, which had arrived"
            );
        }
    }
    assert!(frames <= 512 / cap + 2, "{frames} frames");
    s.vm().check_invariants().unwrap();
}

/// The same for a device that decides its updates (`Session::exchange`):
/// the device's list, longer than the cap, still names the bricks that
/// arrived since it was drawn; the cap goes to bricks not asked for yet.
#[test]
fn a_device_list_leaves_out_the_bricks_that_arrived() {
    let cap = 64;
    let (_dir, mut s) = eight_caps_session(cap);
    let keys: Vec<BrickKey> = (0..512u32)
        .map(|i| BrickKey::new(0, 0, [i / 64, i / 8 % 8, i % 8]))
        .collect();
    // What the device holds: bricks handed over at the end of a frame.
    let mut on_device = std::collections::HashSet::new();
    let mut asked = std::collections::HashSet::new();
    let mut frames = 0;
    while on_device.len() < keys.len() {
        frames += 1;
        assert!(frames <= 40, "the view did not fill in 40 frames");
        // The device's list: twice the cap of the bricks it lacks, most
        // wanted first, drawn before the last requests arrived.
        let list: Vec<BrickKey> = keys
            .iter()
            .filter(|k| !on_device.contains(*k))
            .take(2 * cap)
            .copied()
            .collect();
        assert!(s.loader().wait_idle(std::time::Duration::from_secs(20)));
        let (_, _, sent) = s.exchange(&list);
        assert_eq!(sent.len(), cap.min(keys.len() - asked.len()));
        for k in &sent {
            assert!(
                asked.insert(*k),
                "frame {frames}: asked again for {k:?}, which had arrived"
            );
        }
        // Every brick here is handed to the device.
        for b in s.waiting() {
            on_device.insert(b.key);
        }
        let all = vec![true; s.waiting().len()];
        s.hand_over(&all);
    }
    assert!(frames <= 512 / cap + 2, "{frames} frames");
}

/// Bricks that failed (their shard gone for a while) are asked for again
/// after [`Session::retry_failed`], and load once the shard is back; until
/// then they stay out of the request lists.
#[test]
fn failed_bricks_load_after_a_retry_once_they_can_be_read() {
    let (dir, mut s) = eight_caps_session(512);
    let shard = dir.path().join("v.ome.zarr/0/c/0/0/0");
    assert!(shard.is_file());
    let aside = dir.path().join("aside");
    std::fs::rename(&shard, &aside).unwrap();
    // The bricks of that shard with data, by the statistics: level-0
    // bricks of 8³ in the store's 32³ shard at the origin.
    let keys: Vec<BrickKey> = (0..64u32)
        .map(|i| BrickKey::new(0, 0, [i / 16, i / 4 % 4, i % 4]))
        .collect();
    let frame = |s: &mut Session| {
        s.begin_frame();
        let mut req = s.vm().requests();
        for k in &keys {
            if !s.vm().is_resident(*k) {
                req.add(*k, 1);
            }
        }
        assert!(s.loader().wait_idle(std::time::Duration::from_secs(20)));
        s.finish_frame([&req])
    };
    for _ in 0..4 {
        frame(&mut s);
    }
    let failed = s.vm().failed_count();
    assert!(failed > 0, "no brick of the missing shard failed");
    assert!(keys.iter().any(|k| s.vm().is_failed(*k)));
    // Failed bricks are not asked for again.
    let st = frame(&mut s);
    assert!(st.frame.requests.iter().all(|k| !s.vm().is_failed(*k)));
    // The shard is back: after a retry every brick of the view arrives.
    std::fs::rename(&aside, &shard).unwrap();
    s.retry_failed();
    assert_eq!(s.vm().failed_count(), 0);
    for _ in 0..6 {
        frame(&mut s);
    }
    assert!(
        keys.iter().all(|k| s.vm().is_resident(*k)),
        "bricks still missing after the retry"
    );
    assert_eq!(s.vm().failed_count(), 0);
    assert_eq!(s.failures().len(), failed, "the first failures stay listed");
}
