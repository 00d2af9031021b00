//! Tests of the NRRD importer: helpers that write small files; reading in
//! `reading`, header and field checks and damaged files in `header`.

mod header;
mod reading;

use super::fields::*;
use super::header::*;
use super::*;
use crate::source::VolumeSource;
use brickyard_core::{DType, Dims3};
use flate2::read::MultiGzDecoder;
use flate2::write::GzEncoder;
use flate2::Compression;
use std::io::{Read, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};

// -- helpers ------------------------------------------------------------

/// Deterministic test values.
fn values(n: usize) -> Vec<u16> {
    (0..n)
        .map(|i| (i as u16).wrapping_mul(37).wrapping_add(5))
        .collect()
}

fn le(v: &[u16]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn be(v: &[u16]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_be_bytes()).collect()
}

fn gz(data: &[u8]) -> Vec<u8> {
    let mut e = GzEncoder::new(Vec::new(), Compression::fast());
    e.write_all(data).unwrap();
    e.finish().unwrap()
}

fn write(dir: &Path, name: &str, parts: &[&[u8]]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, parts.concat()).unwrap();
    p
}

fn read_box(s: &NrrdSource, c: usize, z: Range<u64>, y: Range<u64>, x: Range<u64>) -> Vec<u8> {
    let n = (z.end - z.start) * (y.end - y.start) * (x.end - x.start);
    let mut out = vec![0u8; n as usize * s.meta().dtype.size()];
    s.read_region(c, z, y, x, &mut out).unwrap();
    out
}

fn read_all(s: &NrrdSource, c: usize) -> Vec<u8> {
    let d = s.meta().dims;
    read_box(s, c, 0..d[0], 0..d[1], 0..d[2])
}

/// Cut a box out of a whole channel held in memory.
fn cut(
    full: &[u8],
    dims: Dims3,
    size: usize,
    z: &Range<u64>,
    y: &Range<u64>,
    x: &Range<u64>,
) -> Vec<u8> {
    let mut out = Vec::new();
    for zz in z.clone() {
        for yy in y.clone() {
            let row = ((zz * dims[1] + yy) * dims[2]) as usize;
            out.extend_from_slice(
                &full[(row + x.start as usize) * size..(row + x.end as usize) * size],
            );
        }
    }
    out
}

/// Small deterministic generator (no extra dev-dependency).
struct Lcg(u64);
impl Lcg {
    fn below(&mut self, n: u64) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) % n
    }
    fn range(&mut self, n: u64) -> Range<u64> {
        let a = self.below(n);
        let b = self.below(n);
        a.min(b)..a.max(b) + 1
    }
}

/// Compare random boxes (in random, so also backwards, order) with `full`.
fn check_boxes(s: &NrrdSource, c: usize, full: &[u8], count: usize, seed: u64) {
    let d = s.meta().dims;
    let size = s.meta().dtype.size();
    let mut g = Lcg(seed);
    for _ in 0..count {
        let (z, y, x) = (g.range(d[0]), g.range(d[1]), g.range(d[2]));
        let got = read_box(s, c, z.clone(), y.clone(), x.clone());
        assert_eq!(
            got,
            cut(full, d, size, &z, &y, &x),
            "box {z:?} {y:?} {x:?} channel {c}"
        );
    }
}

/// Open and read every channel; the error text of the first failure.
fn error_of(path: &Path) -> String {
    let r = open(path).and_then(|s| {
        let d = s.meta().dims;
        for c in 0..s.meta().channels {
            let mut out = vec![0u8; s.meta().channel_bytes() as usize];
            s.read_region(c, 0..d[0], 0..d[1], 0..d[2], &mut out)?;
        }
        Ok(())
    });
    match r {
        Ok(()) => panic!("{} was accepted", path.display()),
        Err(e) => e.to_string(),
    }
}

/// The error must name the file and the field.
fn assert_error(path: &Path, file: &str, field: &str) -> String {
    let e = error_of(path);
    assert!(e.contains(file), "error does not name {file}: {e}");
    assert!(
        e.contains(field),
        "error does not name field {field:?}: {e}"
    );
    e
}

const HDR_U16: &str = "NRRD0004\ntype: unsigned short\ndimension: 3\nsizes: 5 4 3\n";
