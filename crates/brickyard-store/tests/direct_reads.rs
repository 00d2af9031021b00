#![cfg(target_os = "linux")]
//! Reads around the page cache (`storage::set_direct_reads`): the same
//! bytes as reads through it, for spans at any offset and up to the file's
//! end, the same errors, and ranges read ahead by a hint taken from the
//! staging area. Its own test binary: the setting holds for the process.

use brickyard_store::storage::{self, Span};
use std::path::{Path, PathBuf};

fn lcg(s: &mut u64) -> u64 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    *s >> 33
}

/// A file of `len` pseudo-random bytes on the disk the build is on (not a
/// RAM file system, which takes no `O_DIRECT`).
fn file(dir: &Path, name: &str, len: usize, seed: u64) -> (PathBuf, Vec<u8>) {
    let mut s = seed;
    let data: Vec<u8> = (0..len).map(|_| lcg(&mut s) as u8).collect();
    let p = dir.join(name);
    std::fs::write(&p, &data).unwrap();
    (p, data)
}

type Read = brickyard_store::error::Result<Option<Vec<Vec<u8>>>>;

fn read_all(p: &Path, spans: &[Span]) -> Read {
    let mut out = vec![Vec::new(); spans.len()];
    let found = storage::read_spans_with(p, spans, |i, b| {
        out[i] = b.to_vec();
        Ok(())
    })?;
    Ok(found.then_some(out))
}

/// Whether this file system takes reads around the page cache.
fn takes_direct(dir: &Path) -> bool {
    use std::os::unix::fs::OpenOptionsExt;
    let p = dir.join("probe");
    std::fs::write(&p, [0u8; 4096]).unwrap();
    std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_DIRECT)
        .open(&p)
        .is_ok()
}

/// One test: the setting is the process's.
#[test]
fn direct_reads_give_the_files_bytes_and_errors_and_take_what_was_read_ahead() {
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let direct_here = takes_direct(dir.path());
    if !direct_here {
        eprintln!(
            "note: {} takes no O_DIRECT: the reads below go through the page cache",
            dir.path().display()
        );
    }
    let len = 300_001;
    let (p, data) = file(dir.path(), "a.bin", len, 7);
    let mut s = 11u64;
    let mut spans = vec![
        Span::All,
        Span::Range(0..1),
        Span::Range(4095..4097),
        Span::Range(len as u64 - 1..len as u64),
        Span::Range(len as u64..len as u64),
        Span::From(299_000),
        Span::Suffix(5000),
        Span::Range(8192..3 * 4096),
    ];
    for _ in 0..40 {
        let a = lcg(&mut s) % len as u64;
        let b = a + lcg(&mut s) % (len as u64 - a + 1);
        spans.push(Span::Range(a..b));
    }
    let want: Vec<Vec<u8>> = spans
        .iter()
        .map(|sp| {
            let r = sp.within(len as u64).unwrap();
            data[r.start as usize..r.end as usize].to_vec()
        })
        .collect();

    storage::set_direct_reads(false);
    assert_eq!(read_all(&p, &spans).unwrap().unwrap(), want);
    let before = storage::direct_read_counts();
    storage::set_direct_reads(true);
    assert_eq!(read_all(&p, &spans).unwrap().unwrap(), want);
    let after = storage::direct_read_counts();
    if direct_here {
        assert_eq!(
            after.read - before.read,
            spans.len() as u64,
            "every span read around the page cache"
        );
    }
    // No file, and a span past the end: as through the page cache.
    assert!(read_all(&dir.path().join("none.bin"), &spans)
        .unwrap()
        .is_none());
    let e = read_all(&p, &[Span::Range(len as u64 - 10..len as u64 + 1)]).unwrap_err();
    assert!(
        e.to_string().contains("a.bin") && e.to_string().contains("300001"),
        "{e}"
    );

    // Read ahead: hinted ranges come from the staging area, whole, in part
    // or across neighbouring hints; the bytes are the file's.
    let (r, rdata) = file(dir.path(), "c.bin", 1 << 20, 5);
    let hinted = storage::will_need(&r, &[0..65536, 65536..131072, 200_000..300_000]);
    if direct_here {
        assert_eq!(hinted, 3);
        // Room for the background readers to read them.
        std::thread::sleep(std::time::Duration::from_millis(300));
    }
    // Across the first two hints (the second whole), the rest of the
    // first, a part of the third, and a range not hinted.
    let asks = [4096..131072u64, 0..4096, 204_800..290_000, 400_000..500_000];
    let before = storage::direct_read_counts();
    let spans: Vec<Span> = asks.iter().map(|a| Span::Range(a.clone())).collect();
    let got = read_all(&r, &spans).unwrap().unwrap();
    for (a, g) in asks.iter().zip(&got) {
        assert_eq!(
            g[..],
            rdata[a.start as usize..a.end as usize],
            "bytes {a:?}"
        );
    }
    let after = storage::direct_read_counts();
    if direct_here {
        let (read, staged) = (after.read - before.read, after.staged - before.staged);
        assert_eq!(read + staged, 4, "{before:?} -> {after:?}");
        // A hint still queued when its range is asked for is read by the
        // asker; after the pause above, most were read ahead.
        assert!(staged >= 2, "{before:?} -> {after:?}: hinted ranges staged");
    }
    storage::set_direct_reads(false);
}
