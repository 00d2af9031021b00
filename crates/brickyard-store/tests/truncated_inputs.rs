//! Raw and NRRD inputs that are not regular files, or that shrink after
//! they were opened (checked), fail with an error naming the file, the
//! byte where it ends and what was expected: never "failed to fill whole
//! buffer", never a wait on a pipe.

use brickyard_core::DType;
use brickyard_store::import::{nrrd, raw};
use brickyard_store::source::VolumeSource;
use std::path::Path;
use std::sync::mpsc;
use std::time::Duration;

/// Cut `path` to `len` bytes.
fn shrink(path: &Path, len: u64) {
    std::fs::OpenOptions::new()
        .write(true)
        .open(path)
        .unwrap()
        .set_len(len)
        .unwrap();
}

/// Read the whole 4×4×4 u8 volume of `s`, expecting an error.
fn read_all_fails(s: &dyn VolumeSource) -> String {
    let mut out = vec![0u8; 64];
    let e = s
        .read_region(0, 0..4, 0..4, 0..4, &mut out)
        .expect_err("reading a shrunk file must fail")
        .to_string();
    assert!(!e.contains("fill whole buffer"), "{e}");
    e
}

fn assert_ends_early(e: &str, name: &str, at: u64, need: u64) {
    for want in [
        name.to_string(),
        "data".into(),
        "ends early".into(),
        format!("byte {at}"),
        format!("{need} expected"),
        "changed while being read".into(),
        "truncated".into(),
    ] {
        assert!(e.contains(&want), "expected {want:?} in: {e}");
    }
}

#[test]
fn raw_shrunk_while_reading() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("v.raw");
    std::fs::write(&p, [7u8; 64]).unwrap();
    let s = raw::open(&p, &raw::RawOptions::new([4, 4, 4], DType::U8)).unwrap();
    shrink(&p, 20);
    // Slice 0 reads whole, slice 1 finds 4 of its 16 bytes.
    let e = read_all_fails(&s);
    assert_ends_early(&e, "v.raw", 20, 64);
    // Rows read one by one (part of each row): the row of z 1, y 1 starts
    // at byte 21, past the end.
    let mut out = vec![0u8; 2 * 4 * 2];
    let e = s
        .read_region(0, 0..2, 0..4, 1..3, &mut out)
        .unwrap_err()
        .to_string();
    assert_ends_early(&e, "v.raw", 21, 64);
}

#[test]
fn raw_input_must_be_a_regular_file() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("pipe.raw");
    let st = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(st.success());
    // Opening a FIFO for reading waits for a writer: open in a thread so
    // that a wait fails the test instead of hanging it.
    let (tx, rx) = mpsc::channel();
    let f = fifo.clone();
    std::thread::spawn(move || {
        let r = raw::open(&f, &raw::RawOptions::new([4, 4, 4], DType::U8)).map(|_| ());
        let _ = tx.send(r.map_err(|e| e.to_string()));
    });
    let e = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("opening a FIFO as raw input waited for a writer instead of failing")
        .expect_err("a FIFO is not raw input");
    assert!(
        e.contains("pipe.raw") && e.contains("regular file") && e.contains("FIFO"),
        "{e}"
    );
    for (path, kind) in [("/dev/null", "character device"), ("/tmp", "folder")] {
        let e = raw::open(Path::new(path), &raw::RawOptions::new([4, 4, 4], DType::U8))
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(path) && e.contains("regular file") && e.contains(kind),
            "{e}"
        );
    }
}

const HEADER: &str = "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\n";

#[test]
fn nrrd_attached_shrunk_while_reading() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("v.nrrd");
    let mut bytes = format!("{HEADER}\n").into_bytes();
    let h = bytes.len() as u64;
    bytes.extend([3u8; 64]);
    std::fs::write(&p, &bytes).unwrap();
    let s = nrrd::open(&p).unwrap();
    shrink(&p, h + 20);
    let e = read_all_fails(&s);
    assert_ends_early(&e, "v.nrrd", h + 20, h + 64);
}

#[test]
fn nrrd_detached_shrunk_while_reading() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("v.nhdr");
    std::fs::write(&p, format!("{HEADER}data file: d.raw\n\n")).unwrap();
    let d = dir.path().join("d.raw");
    std::fs::write(&d, [3u8; 64]).unwrap();
    let s = nrrd::open(&p).unwrap();
    shrink(&d, 20);
    let e = read_all_fails(&s);
    assert_ends_early(&e, "d.raw", 20, 64);
    assert!(e.contains("v.nhdr"), "the header is named too: {e}");
}
