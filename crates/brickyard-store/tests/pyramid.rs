//! End-to-end tests of the pyramid builder: every level read back with the
//! `zarrs` reader (not ours) and compared with an independent, naive
//! reference downsample of the level above.

mod common;

use brickyard_core::{DType, Dims3};
use brickyard_store::builder::{convert, partial_path, ConvertOptions, NoProgress};
use brickyard_store::error::StoreError;
use common::*;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use zarrs::array::{Array, ArraySubset};
use zarrs::filesystem::FilesystemStore;

fn opts(brick: u64, shard: u64) -> ConvertOptions {
    ConvertOptions {
        brick: [brick; 3],
        shard: [shard; 3],
        ..Default::default()
    }
}

#[test]
fn awkward_shapes_round_trip_and_levels_match_reference() {
    let cases: &[(Dims3, usize, DType, u64, u64)] = &[
        ([37, 45, 51], 1, DType::U8, 8, 16), // not a multiple of the brick
        ([5, 6, 7], 1, DType::U16, 8, 8),    // smaller than one brick
        ([1, 40, 33], 1, DType::I16, 8, 16), // one voxel thick
        ([20, 3, 1], 1, DType::F32, 4, 8),   // thin in two axes
        ([19, 23, 17], 3, DType::U16, 8, 16), // several channels
        ([17, 18, 21], 1, DType::U32, 4, 8),
        ([18, 17, 16], 1, DType::I32, 4, 16),
        ([15, 16, 17], 1, DType::F64, 4, 8),
        ([16, 16, 16], 1, DType::I8, 4, 8),
    ];
    for (i, &(dims, c, dt, brick, shard)) in cases.iter().enumerate() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("o.ome.zarr");
        let src = make_source(dims, c, dt, 100 + i as u64);
        let r = convert(
            &src,
            &out,
            &opts(brick, shard),
            &NoProgress,
            &AtomicBool::new(false),
        )
        .unwrap();
        assert!(!r.levels.is_empty());
        check_store(&src, &out, false);
        assert!(!partial_path(&out).exists());
    }
}

/// A source that says it holds labels gets the mode without `labels` set.
#[test]
fn labels_from_the_source_use_the_mode() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("l.ome.zarr");
    let mut src = make_source([13, 18, 20], 1, DType::U16, 9);
    for b in src.data.iter_mut() {
        *b %= 3;
    }
    src.meta.labels = true;
    let o = opts(4, 8);
    assert!(!o.labels);
    convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    check_store(&src, &out, true);
    let root: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("zarr.json")).unwrap()).unwrap();
    assert_eq!(root["attributes"]["brickyard"]["labels"], true);
}

#[test]
fn labels_use_the_mode() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("l.ome.zarr");
    let mut src = make_source([21, 26, 30], 1, DType::U8, 7);
    // Few distinct labels so that ties and majorities both happen.
    for b in src.data.iter_mut() {
        *b %= 3;
    }
    let mut o = opts(4, 8);
    o.labels = true;
    convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    check_store(&src, &out, true);
}

#[test]
fn small_budget_uses_tiles_and_passes_and_stays_exact() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t.ome.zarr");
    let src = make_source([70, 150, 260], 1, DType::U16, 3);
    // The volume is 5.5 MB; allow ~300 KB of slabs beyond the fixed overhead.
    let mut o = opts(8, 32);
    let threads = rayon::current_num_threads() as u64;
    o.memory = (48 << 20) + threads * 8 * 8 * 8 * 2 * 3 + 200_000 + (300 << 10);
    let r = convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    assert!(
        r.passes.len() > 1,
        "expected several passes: {:?}",
        r.passes
    );
    assert!(
        r.passes[0].tile[0] < 150 || r.passes[0].tile[1] < 260,
        "expected tiles: {:?}",
        r.passes
    );
    assert!(r.planned_bytes <= o.memory);
    check_store(&src, &out, false);
}

/// `memory_needed` is the least budget a conversion takes: with it the
/// conversion runs, a byte less is refused (before anything is written).
#[test]
fn memory_needed_is_the_least_budget_that_converts() {
    for (dims, dtype, brick, shard) in [
        ([70, 150, 260], DType::U16, 8, 32),
        ([40, 33, 90], DType::F32, 16, 32),
        ([9, 200, 20], DType::U8, 4, 8),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("m.ome.zarr");
        let src = make_source(dims, 1, dtype, 7);
        let mut o = opts(brick, shard);
        let need = brickyard_store::builder::memory_needed(&src.meta, &o);
        o.memory = need - 1;
        let e = convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap_err();
        assert!(e.to_string().contains("too small"), "{dims:?}: {e}");
        assert!(!out.exists() && !partial_path(&out).exists());
        o.memory = need;
        let r = convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false))
            .unwrap_or_else(|e| panic!("{dims:?} with {need} bytes: {e}"));
        assert!(r.planned_bytes <= need, "{dims:?}");
        check_store(&src, &out, false);
    }
}

#[test]
fn brick_statistics_are_stored() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s.ome.zarr");
    let src = make_source([32, 20, 24], 1, DType::U8, 5);
    let r = convert(
        &src,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    assert!(r.bricks_empty > 0 && r.bricks_constant > r.bricks_empty);
    let info = brickyard_store::info::inspect(&out).unwrap();
    assert_eq!(info.complete, Some(true));
    let s0 = info.levels[0].stats.clone().unwrap();
    assert_eq!(s0.bricks, 4 * 3 * 3);
    // z < 8 is zero, 8 <= z < 16 is 37: one layer of bricks each.
    assert_eq!(s0.empty, 9);
    assert_eq!(s0.constant, 18);
    // Check every brick's min/max against level 0 read back.
    let fs = Arc::new(FilesystemStore::new(out.join("_brickyard/stats/0")).unwrap());
    let a = Array::open(fs, "/").unwrap();
    let st: Vec<f64> = a
        .retrieve_array_subset::<Vec<f64>>(&ArraySubset::new_with_ranges(&[
            0..1,
            0..4,
            0..3,
            0..3,
            0..2,
        ]))
        .unwrap();
    let (l0, d) = read_level(&out, 0, None, DType::U8);
    for bz in 0..4u64 {
        for by in 0..3u64 {
            for bx in 0..3u64 {
                let (mut mn, mut mx) = (f64::INFINITY, f64::NEG_INFINITY);
                for z in bz * 8..((bz + 1) * 8).min(d[0]) {
                    for y in by * 8..((by + 1) * 8).min(d[1]) {
                        for x in bx * 8..((bx + 1) * 8).min(d[2]) {
                            let v = l0[((z * d[1] + y) * d[2] + x) as usize];
                            mn = mn.min(v);
                            mx = mx.max(v);
                        }
                    }
                }
                let i = (((bz * 3 + by) * 3 + bx) * 2) as usize;
                assert_eq!([st[i], st[i + 1]], [mn, mx], "brick {bz},{by},{bx}");
            }
        }
    }
}

#[test]
fn failures_leave_nothing_and_never_damage_existing_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f.ome.zarr");
    // A failing read: no output, no partial store.
    let mut src = make_source([40, 20, 20], 1, DType::U8, 9);
    src.fail_after = Some(2);
    let e = convert(
        &src,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap_err();
    assert!(e.to_string().contains("simulated"), "{e}");
    assert!(!out.exists() && !partial_path(&out).exists());
    // A good store, then a refused and a failing overwrite: it stays intact.
    let good = make_source([40, 20, 20], 1, DType::U8, 9);
    convert(
        &good,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    let e = convert(
        &good,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap_err();
    assert!(e.to_string().contains("--overwrite"), "{e}");
    let mut o = opts(8, 16);
    o.overwrite = true;
    src.reads.store(0, Ordering::SeqCst);
    convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap_err();
    check_store(&good, &out, false);
    // Cancellation.
    let e = convert(
        &good,
        &dir.path().join("c.ome.zarr"),
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(true),
    )
    .unwrap_err();
    assert!(matches!(e, StoreError::Interrupted));
    assert!(!dir.path().join("c.ome.zarr").exists());
    assert!(!partial_path(&dir.path().join("c.ome.zarr")).exists());
}

/// `info` and the reader read a store's `complete` flag by one rule: where
/// its brickyard attributes do not say `complete: true` (false, missing,
/// not a boolean), `info` calls it incomplete and the reader refuses it,
/// naming why; a store without brickyard attributes is read.
#[test]
fn info_and_the_reader_agree_on_what_is_incomplete() {
    use brickyard_store::import::zarr;
    use brickyard_store::info::inspect;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c.ome.zarr");
    let src = make_source([9, 10, 11], 1, DType::U8, 4);
    convert(
        &src,
        &out,
        &opts(8, 8),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    let root = out.join("zarr.json");
    let original: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&root).unwrap()).unwrap();
    assert_eq!(original["attributes"]["brickyard"]["complete"], true);
    let cases: [(Option<serde_json::Value>, bool); 5] = [
        (Some(serde_json::json!(true)), true),
        (Some(serde_json::json!(false)), false),
        (None, false),
        (Some(serde_json::json!("true")), false),
        (Some(serde_json::json!(1)), false),
    ];
    for (flag, complete) in cases {
        let mut j = original.clone();
        let b = j["attributes"]["brickyard"].as_object_mut().unwrap();
        match &flag {
            Some(v) => b.insert("complete".into(), v.clone()),
            None => b.remove("complete"),
        };
        std::fs::write(&root, serde_json::to_vec(&j).unwrap()).unwrap();
        let info = inspect(&out).unwrap();
        assert_eq!(info.complete, Some(complete), "{flag:?}");
        match zarr::open(&out, 0) {
            Ok(_) => assert!(complete, "{flag:?}: an incomplete store was read"),
            Err(e) => {
                assert!(!complete, "{flag:?}: {e}");
                assert!(e.to_string().contains("the store is incomplete"), "{e}");
            }
        }
    }
    // Without brickyard attributes (another writer's store): read, and
    // `info` says nothing of completeness.
    let mut j = original.clone();
    j["attributes"].as_object_mut().unwrap().remove("brickyard");
    std::fs::write(&root, serde_json::to_vec(&j).unwrap()).unwrap();
    assert_eq!(inspect(&out).unwrap().complete, None);
    assert!(zarr::open(&out, 0).is_ok());
}

/// A label image holds one object id per voxel: a conversion of several
/// channels as labels (asked for, or marked so by the source) is refused
/// before anything is written, naming the channels; Python's
/// `from_numpy(..., labels=True)` converts through the same call.
#[test]
fn a_label_image_of_several_channels_is_refused_before_writing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("two.ome.zarr");
    let mut o = opts(8, 8);
    o.labels = true;
    let src = make_source([9, 10, 11], 2, DType::U16, 4);
    let e = convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("a label image has one channel") && e.contains("2 channels"),
        "{e}"
    );
    assert!(!out.exists() && !partial_path(&out).exists());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    // Marked as labels by the source, not asked for: the same.
    let mut src = make_source([9, 10, 11], 3, DType::U16, 4);
    src.meta.labels = true;
    let e = convert(
        &src,
        &out,
        &opts(8, 8),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("3 channels") && e.contains("marks it as labels"),
        "{e}"
    );
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    // One channel: written.
    let src = make_source([9, 10, 11], 1, DType::U16, 4);
    convert(&src, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
}

/// A brick whose values besides NaN are all one value is recorded as
/// `(v, NaN)`, not as constant; bricks of NaN alone as `(NaN, NaN)`; a
/// brick of zeros and NaN is stored (it is not empty). `info --check`
/// accepts what convert wrote, and names statistics that record such a
/// brick as constant (as stores written before the rule do).
#[test]
fn a_brick_of_one_value_beside_nan_is_not_recorded_constant() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("n.ome.zarr");
    let d = 16usize;
    let mut v = vec![0f32; d * d * d];
    for z in 0..d {
        for y in 0..d {
            for x in 0..d {
                v[(z * d + y) * d + x] = match (z / 8, y / 8, x / 8) {
                    (0, 0, 0) if (z, y, x) == (3, 4, 5) => f32::NAN,
                    (0, 0, 0) => 5.0,
                    (0, 0, 1) if (z, y, x) == (1, 2, 9) => 0.0,
                    (0, 0, 1) => f32::NAN,
                    (0, 1, 0) => 7.0,
                    (0, 1, 1) => f32::NAN,
                    _ => 0.0,
                };
            }
        }
    }
    let mut meta = brickyard_store::SourceMeta::new("nan", [16; 3], 1, DType::F32);
    meta.spacing = Some([1.0; 3]);
    let src = MemSource {
        meta,
        data: brickyard_core::as_bytes(&v).to_vec(),
        fail_after: None,
        reads: Default::default(),
    };
    let r = convert(
        &src,
        &out,
        &opts(8, 16),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    // Bricks 0,1,0 (7) and the four of z ≥ 8 that are 0, of which those
    // four are empty.
    assert_eq!((r.bricks_constant, r.bricks_empty), (5, 4), "{r:?}");
    let stats = |out: &std::path::Path| -> (Array<FilesystemStore>, Vec<f64>) {
        let fs = Arc::new(FilesystemStore::new(out.join("_brickyard/stats/0")).unwrap());
        let a = Array::open(fs, "/").unwrap();
        let all = ArraySubset::new_with_ranges(&[0..1, 0..2, 0..2, 0..2, 0..2]);
        let st = a.retrieve_array_subset::<Vec<f64>>(&all).unwrap();
        (a, st)
    };
    let (a, st) = stats(&out);
    let pair = |i: usize| (st[2 * i], st[2 * i + 1]);
    assert!(pair(0).0 == 5.0 && pair(0).1.is_nan(), "{:?}", pair(0));
    assert!(pair(1).0 == 0.0 && pair(1).1.is_nan(), "{:?}", pair(1));
    assert_eq!(pair(2), (7.0, 7.0));
    assert!(pair(3).0.is_nan() && pair(3).1.is_nan(), "{:?}", pair(3));
    assert_eq!(pair(4), (0.0, 0.0));
    // The brick of zeros and NaN was written: level 0 reads back its NaN.
    let (l0, _) = read_level(&out, 0, None, DType::F32);
    assert!(l0[(2 * d + 3) * d + 9].is_nan() && l0[(d + 2) * d + 9] == 0.0);
    let info = brickyard_store::info::inspect(&out).unwrap();
    let s0 = info.levels[0].stats.clone().unwrap();
    assert_eq!((s0.constant, s0.empty, s0.nan), (5, 4, 1), "{s0:?}");
    assert_eq!((s0.min, s0.max), (0.0, 7.0), "{s0:?}");
    let c = brickyard_store::info::check::check(&out, &NoProgress).unwrap();
    assert!(c.ok(), "{c:?}");
    // Statistics of the old kind: brick 0 recorded as constant 5.
    let b0 = ArraySubset::new_with_ranges(&[0..1, 0..1, 0..1, 0..1, 0..2]);
    a.store_array_subset(&b0, &[5.0f64, 5.0]).unwrap();
    let c = brickyard_store::info::check::check(&out, &NoProgress).unwrap();
    assert_eq!(c.problems.len(), 1, "{c:?}");
    let msg = c.problems[0].to_string();
    assert!(msg.contains("NaN voxels are drawn as 5"), "{msg}");
}
