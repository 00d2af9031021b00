//! Read-ahead hints (`VolumeSource::prefetch`): a hinted region's stored
//! chunks come into the page cache without a read by the caller, only the
//! chunks the decoded-chunk cache lacks are hinted, and chunks absent from
//! their shard's index (fill value) are not.
#![cfg(target_os = "linux")]

use brickyard_core::DType;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::generate::{Kind, Procedural};
use brickyard_store::shard::{read_index, IndexLayout};
use brickyard_store::{Compression, VolumeSource};
use std::fs::File;
use std::ops::Range;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

const N: u64 = 128;
const CHUNK: u64 = 32;
const SHARD: u64 = 64;

/// Pages of `ranges` of `file` in the page cache, and all its pages.
fn resident(file: &Path, ranges: &[Range<u64>]) -> (usize, usize) {
    let f = File::open(file).unwrap();
    let len = f.metadata().unwrap().len() as usize;
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) } as usize;
    // SAFETY: a read-only shared mapping of a file we keep open; only
    // mincore looks at it.
    let map = unsafe {
        libc::mmap(
            std::ptr::null_mut(),
            len,
            libc::PROT_READ,
            libc::MAP_SHARED,
            f.as_raw_fd(),
            0,
        )
    };
    assert_ne!(map, libc::MAP_FAILED, "mmap {}", file.display());
    let pages = len.div_ceil(page);
    let mut v = vec![0u8; pages];
    let rc = unsafe { libc::mincore(map, len, v.as_mut_ptr()) };
    unsafe { libc::munmap(map, len) };
    assert_eq!(rc, 0, "mincore {}", file.display());
    let mut want = vec![false; pages];
    for r in ranges {
        let pages = (r.start as usize / page)..(r.end as usize).div_ceil(page);
        want[pages].fill(true);
    }
    let n = (0..pages).filter(|&p| want[p] && v[p] & 1 == 1).count();
    (n, want.iter().filter(|w| **w).count())
}

/// Drop `file` from the page cache (written back first).
fn drop_cached(file: &Path) {
    let f = File::options().read(true).write(true).open(file).unwrap();
    f.sync_all().unwrap();
    let rc = unsafe { libc::posix_fadvise(f.as_raw_fd(), 0, 0, libc::POSIX_FADV_DONTNEED) };
    assert_eq!(rc, 0);
}

/// The shard file of chunk `c` (`[z, y, x]` chunk indices) and the byte
/// range of the chunk in it (`None`: not stored, the fill value).
fn chunk_range(level: &Path, c: [u64; 3]) -> (PathBuf, Option<Range<u64>>) {
    let per = SHARD / CHUNK;
    let s = c.map(|i| i / per);
    let file = level.join(format!("c/{}/{}/{}", s[0], s[1], s[2]));
    let index = read_index(&file, &IndexLayout::brickyard(per.pow(3)))
        .unwrap()
        .unwrap_or_default();
    let e = ((c[0] % per) * per + c[1] % per) * per + c[2] % per;
    let r = index
        .get(e as usize)
        .filter(|e| **e != [u64::MAX, u64::MAX])
        .map(|e| e[0]..e[0] + e[1]);
    (file, r)
}

#[test]
fn hinted_chunks_come_into_memory_and_held_or_absent_chunks_are_not_hinted() {
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let out = dir.path().join("m.ome.zarr");
    let g = Procedural::new(Kind::Mandelbulb, [N; 3], DType::U8);
    let o = ConvertOptions {
        brick: [CHUNK; 3],
        shard: [SHARD; 3],
        compression: Compression::None,
        ..Default::default()
    };
    convert(&g, &out, &o, &NoProgress, &AtomicBool::new(false)).unwrap();
    let level = out.join("0");

    // A region across two shards along x: chunks z 0..=1, y 1, x 1..=2.
    let region = [20..60, 40..60, 40..90];
    let mut stored: Vec<(PathBuf, Range<u64>)> = vec![];
    for z in 0..=1 {
        for y in 1..=1 {
            for x in 1..=2 {
                if let (f, Some(r)) = chunk_range(&level, [z, y, x]) {
                    stored.push((f, r));
                }
            }
        }
    }
    assert!(
        stored.len() >= 2,
        "the region should hold stored chunks: {stored:?}"
    );
    let mut files: Vec<PathBuf> = stored.iter().map(|(f, _)| f.clone()).collect();
    files.sort();
    files.dedup();
    assert_eq!(files.len(), 2, "the region should cross two shards");
    let ranges_of = |f: &Path| -> Vec<Range<u64>> {
        stored
            .iter()
            .filter(|(g, _)| g == f)
            .map(|(_, r)| r.clone())
            .collect()
    };

    let mut src = brickyard_store::import::zarr::open(&out, 0).unwrap();
    src.enable_chunk_cache(16 << 20);

    for f in &files {
        drop_cached(f);
    }
    let observable = files.iter().all(|f| resident(f, &ranges_of(f)).0 == 0);
    let hinted = src.prefetch(0, region.clone());
    // Hinted once: a second hint of the same chunks before their load is
    // not made.
    assert_eq!(src.prefetch(0, region.clone()), 0);
    // One range per run of neighbouring chunks in a shard: at least one
    // per shard, at most one per chunk.
    assert!(
        (files.len()..=stored.len()).contains(&hinted),
        "{hinted} ranges hinted for {} stored chunks in {} shards",
        stored.len(),
        files.len()
    );
    if observable {
        // The kernel reads the hinted ranges in the background.
        let t = Instant::now();
        loop {
            let counts: Vec<(usize, usize)> =
                files.iter().map(|f| resident(f, &ranges_of(f))).collect();
            if counts.iter().all(|(n, all)| n == all) {
                println!(
                    "hinted chunks resident after {:.1} ms: {counts:?}",
                    t.elapsed().as_secs_f64() * 1e3
                );
                break;
            }
            assert!(
                t.elapsed() < Duration::from_secs(20),
                "hinted chunks still not in memory after 20 s: {counts:?} (pages resident, pages wanted)"
            );
            std::thread::sleep(Duration::from_millis(2));
        }
    } else {
        // tmpfs and the like keep every page in memory: the ranges are
        // still checked above, the page cache cannot tell more.
        println!("this file system keeps the store in memory: page residency not observable");
    }

    // Read the region: the same bytes as a plain reader's.
    let n = region.iter().map(|r| r.end - r.start).product::<u64>() as usize;
    let (mut a, mut b) = (vec![0u8; n], vec![0u8; n]);
    let [z, y, x] = region.clone();
    src.read_region(0, z.clone(), y.clone(), x.clone(), &mut a)
        .unwrap();
    brickyard_store::import::zarr::open(&out, 0)
        .unwrap()
        .read_region(0, z, y, x, &mut b)
        .unwrap();
    assert_eq!(a, b);
    assert!(a.iter().any(|&v| v != 0), "the region holds data");

    // Now its chunks are decoded and held: nothing left to hint.
    assert_eq!(src.prefetch(0, region), 0);

    // A corner whose chunk holds only the fill value is not stored: no hint.
    let (_, corner) = chunk_range(&level, [0, 0, 0]);
    assert_eq!(
        corner, None,
        "the Mandelbulb's corner chunk should be empty"
    );
    assert_eq!(src.prefetch(0, [0..CHUNK, 0..CHUNK, 0..CHUNK]), 0);
}
