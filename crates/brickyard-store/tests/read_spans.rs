//! `storage::read_spans_with` (the chunk reads: one buffer a thread keeps,
//! each span handed over as a slice) gives the file's bytes for spans at
//! any offset and of any length, in any order, and the errors
//! `storage::read_spans` gives.

use brickyard_store::storage::{self, Span};
use std::path::Path;

fn lcg(s: &mut u64) -> u64 {
    *s = s
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    *s >> 33
}

type Read = brickyard_store::error::Result<Option<Vec<Vec<u8>>>>;

fn read_with(p: &Path, spans: &[Span]) -> Read {
    let mut out = vec![Vec::new(); spans.len()];
    let found = storage::read_spans_with(p, spans, |i, b| {
        out[i] = b.to_vec();
        Ok(())
    })?;
    Ok(found.then_some(out))
}

#[test]
fn spans_read_with_one_buffer_are_the_files_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let len = 300_001usize;
    let mut s = 7u64;
    let data: Vec<u8> = (0..len).map(|_| lcg(&mut s) as u8).collect();
    let p = dir.path().join("a.bin");
    std::fs::write(&p, &data).unwrap();
    // Large spans before small ones (the buffer is reused, not cleared),
    // empty ones, the whole file, suffixes, the last byte.
    let mut spans = vec![
        Span::All,
        Span::Range(0..1),
        Span::Range(4095..4097),
        Span::Range(len as u64 - 1..len as u64),
        Span::Range(len as u64..len as u64),
        Span::From(299_000),
        Span::Suffix(5000),
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
    assert_eq!(read_with(&p, &spans).unwrap().unwrap(), want);
    assert_eq!(storage::read_spans(&p, &spans).unwrap().unwrap(), want);
    // A span larger than the buffer a thread keeps (1 MiB), then small ones.
    let big: Vec<u8> = (0..5_000_000u32).map(|i| (i % 253) as u8).collect();
    let q = dir.path().join("big.bin");
    std::fs::write(&q, &big).unwrap();
    let got = read_with(&q, &[Span::All, Span::Range(10..20), Span::Suffix(3)])
        .unwrap()
        .unwrap();
    assert!(got[0] == big && got[1] == big[10..20] && got[2] == big[big.len() - 3..]);

    // A read within the handler (the thread's buffer in use) reads too.
    let mut inner = vec![];
    storage::read_spans_with(&p, &[Span::Range(0..100)], |_, outer| {
        storage::read_spans_with(&p, &[Span::Range(50..150)], |_, b| {
            inner = [outer, b].concat();
            Ok(())
        })
        .map(|_| ())
    })
    .unwrap();
    assert_eq!(inner, [&data[..100], &data[50..150]].concat());

    // No file (absent), a folder (damage: an error) and a span past the
    // end: as `read_spans`.
    assert!(read_with(&dir.path().join("none.bin"), &spans)
        .unwrap()
        .is_none());
    let e = read_with(dir.path(), &spans).unwrap_err().to_string();
    assert!(e.contains("a folder stands where"), "{e}");
    assert_eq!(
        e,
        storage::read_spans(dir.path(), &spans)
            .unwrap_err()
            .to_string()
    );
    let past = [Span::Range(len as u64 - 10..len as u64 + 1)];
    let e = read_with(&p, &past).unwrap_err().to_string();
    assert!(e.contains("a.bin") && e.contains("300001"), "{e}");
    assert_eq!(e, storage::read_spans(&p, &past).unwrap_err().to_string());
    // An error of the caller's stops the reads and comes back.
    let mut seen = 0;
    let e = storage::read_spans_with(&p, &spans, |i, _| {
        seen += 1;
        if i == 2 {
            Err(brickyard_store::error::StoreError::invalid(
                &p,
                "test",
                "stop here",
            ))
        } else {
            Ok(())
        }
    })
    .unwrap_err();
    assert!(e.to_string().contains("stop here"), "{e}");
    assert_eq!(seen, 3);
}
