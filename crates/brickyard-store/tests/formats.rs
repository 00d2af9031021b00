//! Every input format converts with level 0 bit-exact and every level equal
//! to the naive reference, on the real volumes in `shared/data/` and on
//! generated files; spacing and origin reach the OME metadata.

mod common;

use brickyard_core::DType;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::import::raw::RawOptions;
use brickyard_store::import::{detect, open_input, Format, ImportOptions};
use brickyard_store::omezarr::read_multiscale;
use brickyard_store::VolumeSource;
use common::*;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

fn shared(name: &str) -> PathBuf {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(name);
    assert!(
        p.exists(),
        "{} is missing: these tests need the project's shared data folder (../shared/data beside the repository)",
        p.display()
    );
    p
}

fn opts() -> ConvertOptions {
    ConvertOptions {
        brick: [16; 3],
        shard: [64; 3],
        ..Default::default()
    }
}

fn convert_and_check(
    input: &Path,
    expect: Format,
) -> (tempfile::TempDir, PathBuf, Box<dyn VolumeSource>) {
    assert_eq!(detect(input).unwrap(), expect, "{}", input.display());
    let src = open_input(input, &ImportOptions::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o.ome.zarr");
    convert(
        src.as_ref(),
        &out,
        &opts(),
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    check_store(src.as_ref(), &out, false);
    (dir, out, src)
}

#[test]
fn nifti_colin27() {
    let (_d, out, src) = convert_and_check(&shared("colin27-t1-0.5mm.nii.gz"), Format::Nifti);
    assert_eq!(src.meta().dims, [316, 370, 301]);
    let ms = read_multiscale(&out).unwrap().unwrap();
    assert_eq!(ms.datasets[0].scale.as_deref(), Some(&[0.5, 0.5, 0.5][..]));
}

#[test]
fn nrrd_mr_brain_keeps_spacing_and_origin() {
    let (_d, out, src) = convert_and_check(&shared("mr-brain-i16.nrrd"), Format::Nrrd);
    assert_eq!(src.meta().dtype, DType::I16);
    let ms = read_multiscale(&out).unwrap().unwrap();
    let s0 = ms.datasets[0].scale.clone().unwrap();
    assert!(
        (s0[0] - 6.5).abs() < 0.01 && (s0[1] - 0.78).abs() < 0.01 && (s0[2] - 0.78).abs() < 0.01,
        "{s0:?}"
    );
    let t0 = ms.datasets[0]
        .translation
        .clone()
        .expect("origin carried as translation");
    assert!(t0.iter().any(|&v| v != 0.0));
    // The thick axis is not halved until x and y catch up.
    let s1 = ms.datasets[1].scale.clone().unwrap();
    assert_eq!(s1[0], s0[0]);
    assert!((s1[1] / s0[1] - 2.0).abs() < 1e-9);
    assert_eq!(ms.axes[0].unit.as_deref(), Some("millimeter"));
}

#[test]
fn tiff_nuclei() {
    let (_d, out, src) = convert_and_check(&shared("nuclei-confocal-u16.tif"), Format::Tiff);
    assert_eq!(src.meta().dims, [60, 256, 256]);
    assert_eq!(src.meta().dtype, DType::U16);
    assert!(read_multiscale(&out).unwrap().unwrap().datasets.len() >= 3);
}

#[test]
fn raw_with_sidecar_and_zarr_reconversion() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("ml.raw");
    let g = Procedural::new(Kind::MarschnerLobb, [33, 40, 47], DType::F32);
    brickyard_store::generate::write_raw(&g, &raw, &NoProgress).unwrap();
    let ro = RawOptions::read_sidecar(&RawOptions::sidecar_path(&raw)).unwrap();
    assert_eq!(ro.dims, [47, 40, 33]);
    let (_d, out, _src) = convert_and_check(&raw, Format::Raw);
    // Re-pyramid our own output with other chunking: same values.
    let again = open_input(&out, &ImportOptions::default()).unwrap();
    assert_eq!(again.meta().dims, [33, 40, 47]);
    let dir2 = tempfile::tempdir().unwrap();
    let out2 = dir2.path().join("again.ome.zarr");
    let o = ConvertOptions {
        brick: [8; 3],
        shard: [8; 3],
        ..Default::default()
    };
    convert(
        again.as_ref(),
        &out2,
        &o,
        &NoProgress,
        &AtomicBool::new(false),
    )
    .unwrap();
    check_store(&g, &out2, false);
    // A coarser level of an OME-Zarr can be the input too.
    let l1 = open_input(
        &out,
        &ImportOptions {
            zarr_level: 1,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(l1.meta().dims, [17, 20, 24]);
}

#[test]
fn chunk_cached_reads_equal_plain_reads() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c.ome.zarr");
    let g = Procedural::new(Kind::Mandelbulb, [29, 37, 41], DType::I16);
    let o = ConvertOptions {
        brick: [8; 3],
        shard: [16; 3],
        ..Default::default()
    };
    convert(&g, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    for (budget, shells) in [(0u64, 0), (3000, 0), (3000, 1), (5000, 2), (1 << 20, 1)] {
        let plain = brickyard_store::import::zarr::open(&out, 0).unwrap();
        let mut cached = brickyard_store::import::zarr::open(&out, 0).unwrap();
        cached.enable_chunk_cache_with_shells(budget, shells);
        let mut s = 99u64;
        for _ in 0..60 {
            let mut r = |n: u64| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (s >> 33) % n
            };
            let z0 = r(29);
            let z1 = z0 + 1 + r(29 - z0);
            let y0 = r(37);
            let y1 = y0 + 1 + r(37 - y0);
            let x0 = r(41);
            let x1 = x0 + 1 + r(41 - x0);
            let n = ((z1 - z0) * (y1 - y0) * (x1 - x0) * 2) as usize;
            let (mut a, mut b) = (vec![0u8; n], vec![0u8; n]);
            plain
                .read_region(0, z0..z1, y0..y1, x0..x1, &mut a)
                .unwrap();
            cached
                .read_region(0, z0..z1, y0..y1, x0..x1, &mut b)
                .unwrap();
            assert_eq!(
                a, b,
                "budget {budget} shells {shells} region {z0}..{z1} {y0}..{y1} {x0}..{x1}"
            );
            assert!(cached.chunk_cache_bytes() <= budget);
        }
    }
}

/// Reads into a larger box (the loader's padded bricks) land at their
/// offset, leave the rest of the box alone, and equal plain reads, with
/// several threads sharing one small decoded-chunk cache.
#[test]
fn box_reads_through_a_shared_chunk_cache_equal_plain_reads() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c.ome.zarr");
    let g = Procedural::new(Kind::Mandelbulb, [33, 40, 47], DType::U16);
    let o = ConvertOptions {
        brick: [8; 3],
        shard: [16; 3],
        ..Default::default()
    };
    convert(&g, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let plain = brickyard_store::import::zarr::open(&out, 0).unwrap();
    let mut cached = brickyard_store::import::zarr::open(&out, 0).unwrap();
    let budget = 4 * 8 * 8 * 8 * 2;
    cached.enable_chunk_cache_with_shells(budget, 1);
    std::thread::scope(|s| {
        for t in 0..3u64 {
            let (plain, cached) = (&plain, &cached);
            s.spawn(move || {
                let mut seed = 7 + t;
                let mut r = |n: u64| {
                    seed = seed
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    (seed >> 33) % n
                };
                for _ in 0..40 {
                    let lo = [r(33), r(40), r(47)];
                    let hi = [
                        lo[0] + 1 + r(33 - lo[0]),
                        lo[1] + 1 + r(40 - lo[1]),
                        lo[2] + 1 + r(47 - lo[2]),
                    ];
                    let n: Vec<u64> = (0..3).map(|a| hi[a] - lo[a]).collect();
                    let at = [r(3), r(3), r(3)];
                    let dims = [
                        n[0] + at[0] + r(3),
                        n[1] + at[1] + r(3),
                        n[2] + at[2] + r(3),
                    ];
                    let mut want = vec![0u8; (n[0] * n[1] * n[2] * 2) as usize];
                    plain
                        .read_region(0, lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2], &mut want)
                        .unwrap();
                    let mut b = vec![0xABu8; (dims[0] * dims[1] * dims[2] * 2) as usize];
                    cached
                        .read_region_into(
                            0,
                            [lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2]],
                            &mut b,
                            dims,
                            at,
                        )
                        .unwrap();
                    let mut k = 0;
                    for z in 0..dims[0] {
                        for y in 0..dims[1] {
                            for x in 0..dims[2] {
                                let i = (((z * dims[1] + y) * dims[2] + x) * 2) as usize;
                                let inside = (z >= at[0] && z < at[0] + n[0])
                                    && (y >= at[1] && y < at[1] + n[1])
                                    && (x >= at[2] && x < at[2] + n[2]);
                                if inside {
                                    assert_eq!(
                                        b[i..i + 2],
                                        want[k..k + 2],
                                        "{lo:?}..{hi:?} at {at:?}"
                                    );
                                    k += 2;
                                } else {
                                    assert_eq!(b[i..i + 2], [0xAB, 0xAB], "outside the region");
                                }
                            }
                        }
                    }
                    assert!(cached.chunk_cache_bytes() <= budget);
                }
            });
        }
    });
}

/// A path with `[...]` that names no file is a pattern of slices; `{...}`
/// is not a pattern (the error says so); a file whose name holds brackets
/// is read as itself.
#[test]
fn brackets_are_classes_unless_a_file_is_named_so() {
    let d = tempfile::tempdir().unwrap();
    assert_eq!(
        detect(&d.path().join("img_[0-2].tif")).unwrap(),
        Format::TiffGlob
    );
    let e = detect(&d.path().join("img_{a,b}.tif"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("glob"), "{e}");
    let named = d.path().join("scan[1].nii");
    std::fs::write(&named, [0u8; 4]).unwrap();
    assert_eq!(detect(&named).unwrap(), Format::Nifti);
}
