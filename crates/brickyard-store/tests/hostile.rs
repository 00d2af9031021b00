//! Hostile and damaged inputs: every importer refuses headers that claim
//! more than their file could hold, overflowing or negative sizes, offsets
//! past the end of a file, absurd counts and unbounded gzip streams with a
//! clear error (naming the file and the offending field) before any large
//! allocation, instead of panicking, aborting or reading without end. The
//! inputs found by fuzzing (docs/FUZZING.md) are replayed here too.
//!
//! Over 800 lines: tests only, one case per importer and field, sharing the file helpers.

mod common;

use brickyard_core::DType;
use brickyard_store::builder::{convert, ConvertOptions, NoProgress};
use brickyard_store::error::StoreError;
use brickyard_store::import::raw::{self, RawOptions};
use brickyard_store::import::zarr::{self, ZarrSource};
use brickyard_store::import::{nifti, nrrd, tiff};
use brickyard_store::shard::{self, IndexLayout, IndexLocation};
use brickyard_store::{Compression, VolumeSource};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

/// The error of `r`, which must be one.
fn err<T>(r: brickyard_store::Result<T>) -> StoreError {
    match r {
        Ok(_) => panic!("expected an error, got a value"),
        Err(e) => e,
    }
}

/// Check that `e` is an `Invalid` (or `Unsupported`) error on the file
/// named `file`, about `field`, whose message holds every one of `words`.
fn assert_refused(e: &StoreError, file: &str, field: &str, words: &[&str]) {
    let (path, f, msg) = match e {
        StoreError::Invalid { path, field, msg } | StoreError::Unsupported { path, field, msg } => {
            (path, field, msg)
        }
        other => panic!("expected an invalid-input error about {field}, got {other:?}"),
    };
    assert!(
        path.to_string_lossy().ends_with(file),
        "error names {} instead of {file}: {e}",
        path.display()
    );
    assert_eq!(f, field, "{e}");
    for w in words {
        assert!(msg.contains(w), "{w:?} missing from: {e}");
    }
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    if let Some(d) = p.parent() {
        std::fs::create_dir_all(d).unwrap();
    }
    std::fs::write(&p, bytes).unwrap();
    p
}

fn gzip(b: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(b).unwrap();
    e.finish().unwrap()
}

/// Read every voxel of every channel (for small volumes).
fn read_all(src: &dyn VolumeSource) -> brickyard_store::Result<()> {
    let m = src.meta().clone();
    let [z, y, x] = m.dims;
    for c in 0..m.channels {
        let mut out = vec![0u8; m.channel_bytes() as usize];
        src.read_region(c, 0..z, 0..y, 0..x, &mut out)?;
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// NRRD

fn nrrd_header(sizes: &str, encoding: &str, extra: &str) -> String {
    format!("NRRD0004\ntype: uchar\ndimension: 3\nsizes: {sizes}\nencoding: {encoding}\n{extra}\n")
}

/// Raw data: 10^12 voxels claimed by a file of a few bytes.
#[test]
fn nrrd_raw_more_voxels_than_the_file_holds() {
    let dir = tempfile::tempdir().unwrap();
    let hdr = nrrd_header("10000 10000 10000", "raw", "");
    let p = write(
        dir.path(),
        "huge.nrrd",
        &[hdr.as_bytes(), &[0u8; 64]].concat(),
    );
    let e = err(nrrd::open(&p));
    assert_refused(
        &e,
        "huge.nrrd",
        "data",
        &["holds 64 bytes", "1000000000000"],
    );
}

/// Gzip data: deflate inflates at most 1032-fold, so a small stream cannot
/// hold 10^12 voxels; refused at open, not after decompressing it all.
#[test]
fn nrrd_gzip_more_voxels_than_the_stream_can_inflate_to() {
    let dir = tempfile::tempdir().unwrap();
    let hdr = nrrd_header("10000 10000 10000", "gzip", "");
    let data = gzip(&[0u8; 100_000]);
    let p = write(dir.path(), "bomb.nrrd", &[hdr.as_bytes(), &data].concat());
    let e = err(nrrd::open(&p));
    assert_refused(
        &e,
        "bomb.nrrd",
        "data",
        &["gzip stream of", "inflates to at most", "1000000000000"],
    );
    // A stream that can hold the volume still opens.
    let hdr = nrrd_header("100 100 10", "gzip", "");
    let p = write(dir.path(), "ok.nrrd", &[hdr.as_bytes(), &data].concat());
    read_all(&nrrd::open(&p).unwrap()).unwrap();
}

#[test]
fn nrrd_overflowing_and_negative_sizes() {
    let dir = tempfile::tempdir().unwrap();
    let hdr = nrrd_header("4294967296 4294967296 4294967296", "raw", "");
    let p = write(dir.path(), "overflow.nrrd", hdr.as_bytes());
    let e = err(nrrd::open(&p));
    assert_refused(&e, "overflow.nrrd", "sizes", &["too large to address"]);
    let e = err(nrrd::parse_header(&p, hdr.as_bytes()));
    assert_refused(&e, "overflow.nrrd", "sizes", &["too large to address"]);

    let hdr = nrrd_header("-5 4 3", "raw", "");
    let p = write(dir.path(), "negative.nrrd", hdr.as_bytes());
    let e = err(nrrd::open(&p));
    assert_refused(&e, "negative.nrrd", "sizes", &["positive integers", "-5"]);
}

#[test]
fn nrrd_byte_skip_past_the_end_of_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let hdr = nrrd_header("4 4 4", "raw", "byte skip: 1000000\n");
    let p = write(
        dir.path(),
        "skip.nrrd",
        &[hdr.as_bytes(), &[0u8; 64]].concat(),
    );
    let e = err(nrrd::open(&p));
    assert_refused(
        &e,
        "skip.nrrd",
        "data",
        &["holds 64 bytes", "1000000 (byte skip)"],
    );
    // The same skip over gzip data: more than the stream can inflate to.
    let hdr = nrrd_header("4 4 4", "gzip", "byte skip: 1000000000\n");
    let data = gzip(&[0u8; 64]);
    let p = write(
        dir.path(),
        "skip-gz.nrrd",
        &[hdr.as_bytes(), &data].concat(),
    );
    let e = err(nrrd::open(&p));
    assert_refused(&e, "skip-gz.nrrd", "data", &["1000000000 (byte skip)"]);
}

/// The header parser reads at most one bounded line at a time and a bounded
/// header: a "line" of 2 MiB is refused instead of being read.
#[test]
fn nrrd_header_reading_is_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let mut hdr = b"NRRD0004\n# ".to_vec();
    hdr.extend(std::iter::repeat_n(b'a', 2 << 20));
    hdr.extend_from_slice(&nrrd_header("2 2 2", "raw", "").as_bytes()[9..]);
    hdr.extend_from_slice(&[0u8; 8]);
    let p = write(dir.path(), "long.nrrd", &hdr);
    let e = err(nrrd::open(&p));
    assert_refused(&e, "long.nrrd", "header", &["line 2 is longer than"]);
}

// ---------------------------------------------------------------------------
// NIfTI

/// A NIfTI-1 header (uint8 voxels) with the given `dim[1..]` and
/// `vox_offset`, plus the 4 extension bytes.
fn nifti1(dims: &[i16], vox_offset: f32) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    let mut d = [1i16; 8];
    d[0] = dims.len() as i16;
    d[1..=dims.len()].copy_from_slice(dims);
    for (i, v) in d.iter().enumerate() {
        h[40 + 2 * i..42 + 2 * i].copy_from_slice(&v.to_le_bytes());
    }
    h[70..72].copy_from_slice(&2i16.to_le_bytes()); // DT_UINT8
    h[72..74].copy_from_slice(&8i16.to_le_bytes());
    for i in 0..8 {
        h[76 + 4 * i..80 + 4 * i].copy_from_slice(&1f32.to_le_bytes());
    }
    h[108..112].copy_from_slice(&vox_offset.to_le_bytes());
    h[344..348].copy_from_slice(b"n+1\0");
    h
}

/// A NIfTI-2 header (uint8 voxels) with the given `dim[1..]`.
fn nifti2(dims: &[i64]) -> Vec<u8> {
    let mut h = vec![0u8; 544];
    h[0..4].copy_from_slice(&540i32.to_le_bytes());
    h[4..12].copy_from_slice(b"n+2\0\r\n\x1a\n");
    h[12..14].copy_from_slice(&2i16.to_le_bytes());
    h[14..16].copy_from_slice(&8i16.to_le_bytes());
    let mut d = [1i64; 8];
    d[0] = dims.len() as i64;
    d[1..=dims.len()].copy_from_slice(dims);
    for (i, v) in d.iter().enumerate() {
        h[16 + 8 * i..24 + 8 * i].copy_from_slice(&v.to_le_bytes());
    }
    h[168..176].copy_from_slice(&544i64.to_le_bytes());
    h
}

#[test]
fn nifti_more_voxels_than_the_file_holds() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "huge.nii",
        &nifti1(&[10000, 10000, 10000], 352.0),
    );
    let e = err(nifti::open(&p));
    assert_refused(&e, "huge.nii", "data", &["holds 0 bytes", "1000000000000"]);
}

/// Gzip-compressed: a small file cannot inflate to 10^12 voxels.
#[test]
fn nifti_gz_more_voxels_than_the_file_can_inflate_to() {
    let dir = tempfile::tempdir().unwrap();
    let mut file = nifti1(&[10000, 10000, 10000], 352.0);
    file.extend(vec![0u8; 1 << 20]);
    let p = write(dir.path(), "bomb.nii.gz", &gzip(&file));
    let e = err(nifti::open(&p));
    assert_refused(
        &e,
        "bomb.nii.gz",
        "data",
        &["gzip-compressed file of", "holds at most", "1000000000000"],
    );
    // A file that can hold its volume still opens.
    let mut file = nifti1(&[64, 64, 64], 352.0);
    file.extend(vec![0u8; 64 * 64 * 64]);
    let p = write(dir.path(), "ok.nii.gz", &gzip(&file));
    read_all(&nifti::open(&p).unwrap()).unwrap();
}

#[test]
fn nifti_negative_and_overflowing_dims() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(dir.path(), "negative.nii", &nifti1(&[4, -4, 4], 352.0));
    let e = err(nifti::open(&p));
    assert_refused(&e, "negative.nii", "dim", &["dim[2] = -4"]);

    let big = 1i64 << 40;
    let p = write(dir.path(), "overflow.nii", &nifti2(&[big, big, big]));
    let e = err(nifti::open(&p));
    assert_refused(&e, "overflow.nii", "dim", &["do not fit in a 64-bit size"]);
}

#[test]
fn nifti_vox_offset_past_the_end_of_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let mut file = nifti1(&[4, 4, 4], 1.0e9);
    file.extend([0u8; 64]);
    let p = write(dir.path(), "offset.nii", &file);
    let e = err(nifti::open(&p));
    assert_refused(&e, "offset.nii", "data", &["holds 0 bytes", "need 64"]);

    let mut file = nifti1(&[4, 4, 4], -352.0);
    file.extend([0u8; 64]);
    let p = write(dir.path(), "negative-offset.nii", &file);
    let e = err(nifti::open(&p));
    assert_refused(
        &e,
        "negative-offset.nii",
        "vox_offset",
        &["not a valid byte offset"],
    );
}

/// Opening a `.nii.gz` decompresses the header only: a stream that goes on
/// for 64 MiB of zeros and then turns corrupt does not keep `open` busy (or
/// fail it); the corruption is found by the read that reaches it.
#[test]
fn nifti_gz_header_reading_is_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let mut file = nifti1(&[4, 4, 4], 352.0);
    file.extend(vec![0u8; 64 << 20]);
    let mut gz = gzip(&file);
    let n = gz.len();
    // Corrupt the deflate data well past the header, and the trailer.
    for b in &mut gz[n / 2..] {
        *b ^= 0x5a;
    }
    let p = write(dir.path(), "bomb.nii.gz", &gz);
    let src = nifti::open(&p).unwrap();
    assert_eq!(src.meta().dims, [4, 4, 4]);
}

// ---------------------------------------------------------------------------
// TIFF

/// One IFD entry: tag, type (3 SHORT, 4 LONG), count, value or offset.
type Entry = (u16, u16, u32, u32);

/// A classic little-endian TIFF: `data` at offset 8, then one IFD per page
/// (entries sorted by tag), chained in order.
fn tiff_file(data: &[u8], pages: &[Vec<Entry>]) -> Vec<u8> {
    let mut out = b"II\x2a\0".to_vec();
    out.extend(0u32.to_le_bytes());
    out.extend_from_slice(data);
    if out.len() % 2 == 1 {
        out.push(0);
    }
    let mut prev = 4;
    for entries in pages {
        let mut e = entries.clone();
        e.sort();
        let at = out.len();
        out[prev..prev + 4].copy_from_slice(&(at as u32).to_le_bytes());
        out.extend((e.len() as u16).to_le_bytes());
        for (tag, typ, count, value) in e {
            out.extend(tag.to_le_bytes());
            out.extend(typ.to_le_bytes());
            out.extend(count.to_le_bytes());
            out.extend(value.to_le_bytes());
        }
        prev = out.len();
        out.extend(0u32.to_le_bytes());
    }
    out
}

/// The entries of a `w`×`h` 8-bit grey page in one strip at `offset` of
/// `count` bytes.
fn tiff_page(w: u32, h: u32, compression: u32, offset: u32, count: u32) -> Vec<Entry> {
    vec![
        (256, 4, 1, w),
        (257, 4, 1, h),
        (258, 3, 1, 8),
        (259, 3, 1, compression),
        (262, 3, 1, 1),
        (273, 4, 1, offset),
        (277, 3, 1, 1),
        (278, 4, 1, h),
        (279, 4, 1, count),
    ]
}

/// A page claiming 10^12 pixels whose single strip holds 64 bytes.
#[test]
fn tiff_more_pixels_than_the_strips_hold() {
    let dir = tempfile::tempdir().unwrap();
    let data = [0u8; 64];
    let f = tiff_file(&data, &[tiff_page(1_000_000, 1_000_000, 1, 8, 64)]);
    let p = write(dir.path(), "huge.tif", &f);
    let e = err(tiff::open(&p));
    assert_refused(
        &e,
        "huge.tif",
        "StripByteCounts",
        &["page 0", "hold 64 bytes (uncompressed)", "1000000000000"],
    );
    // Deflate: 64 bytes decode to at most 1032 times as much.
    let z = {
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
        e.write_all(&[0u8; 1 << 16]).unwrap();
        e.finish().unwrap()
    };
    let f = tiff_file(&z, &[tiff_page(1_000_000, 1_000_000, 8, 8, z.len() as u32)]);
    let p = write(dir.path(), "huge-deflate.tif", &f);
    let e = err(tiff::open(&p));
    assert_refused(
        &e,
        "huge-deflate.tif",
        "StripByteCounts",
        &["decodes at most 1032-fold", "1000000000000"],
    );
    // The same strip for the page it holds still opens and reads.
    let f = tiff_file(&z, &[tiff_page(256, 256, 8, 8, z.len() as u32)]);
    let p = write(dir.path(), "ok-deflate.tif", &f);
    read_all(&tiff::open(&p).unwrap()).unwrap();
}

/// Many pages sharing one strip: each page looks fine on its own, the file
/// as a whole cannot hold them.
#[test]
fn tiff_pages_sharing_one_strip() {
    let dir = tempfile::tempdir().unwrap();
    let data = [7u8; 100 * 100];
    let pages = vec![tiff_page(100, 100, 1, 8, 100 * 100); 1000];
    let p = write(dir.path(), "shared.tif", &tiff_file(&data, &pages));
    let e = err(tiff::open(&p));
    assert_refused(
        &e,
        "shared.tif",
        "page count",
        &["pages of 100×100", "file holds only"],
    );
}

#[test]
fn tiff_strip_past_the_end_of_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let data = [0u8; 64];
    let p = write(
        dir.path(),
        "offset.tif",
        &tiff_file(&data, &[tiff_page(8, 8, 1, 1 << 30, 64)]),
    );
    let e = err(tiff::open(&p));
    assert_refused(
        &e,
        "offset.tif",
        "StripByteCounts",
        &["page 0", "strip 0 ends at byte"],
    );
    let p = write(
        dir.path(),
        "overflow.tif",
        &tiff_file(&data, &[tiff_page(8, 8, 1, u32::MAX, u32::MAX)]),
    );
    let e = err(tiff::open(&p));
    assert_refused(
        &e,
        "overflow.tif",
        "StripByteCounts",
        &["strip 0 ends at byte"],
    );
}

/// A second page whose strip offsets claim 2^32 - 1 values: the decoder
/// must refuse the count instead of allocating for it (which aborts).
#[test]
fn tiff_absurd_strip_count() {
    let dir = tempfile::tempdir().unwrap();
    let data = [1u8; 64];
    let mut second = tiff_page(8, 8, 1, 8, 64);
    second[5] = (273, 4, u32::MAX, 8);
    second[8] = (279, 4, u32::MAX, 8);
    let p = write(
        dir.path(),
        "strips.tif",
        &tiff_file(&data, &[tiff_page(8, 8, 1, 8, 64), second]),
    );
    let e = err(tiff::open(&p));
    assert_refused(
        &e,
        "strips.tif",
        "IFD",
        &["page 1", "more values than the file could hold"],
    );
}

// ---------------------------------------------------------------------------
// Raw with a JSON sidecar

fn sidecar(dir: &Path, name: &str, json: &str) -> brickyard_store::Result<RawOptions> {
    let p = write(dir, name, json.as_bytes());
    RawOptions::read_sidecar(&p)
}

#[test]
fn raw_more_voxels_than_the_file_holds() {
    let dir = tempfile::tempdir().unwrap();
    let o = sidecar(
        dir.path(),
        "v.raw.json",
        r#"{"dims":[10000,10000,10000],"dtype":"u8"}"#,
    )
    .unwrap();
    let p = write(dir.path(), "v.raw", &[0u8; 64]);
    let e = err(raw::open(&p, &o));
    assert_refused(&e, "v.raw", "dims", &["holds 64 bytes", "1000000000000"]);
}

#[test]
fn raw_overflowing_and_negative_dims() {
    let dir = tempfile::tempdir().unwrap();
    let o = sidecar(
        dir.path(),
        "o.raw.json",
        r#"{"dims":[4294967296,4294967296,4294967296],"dtype":"u16"}"#,
    )
    .unwrap();
    let p = write(dir.path(), "o.raw", &[0u8; 64]);
    let e = err(raw::open(&p, &o));
    assert_refused(&e, "o.raw", "dims", &["overflows 64 bits"]);
    let o = sidecar(
        dir.path(),
        "c.raw.json",
        r#"{"dims":[2,2,2],"dtype":"u8","channels":4611686018427387904}"#,
    )
    .unwrap();
    let e = err(raw::open(&p, &o));
    assert_refused(&e, "o.raw", "dims", &["overflows 64 bits"]);

    let e = err(sidecar(
        dir.path(),
        "n.raw.json",
        r#"{"dims":[-4,4,4],"dtype":"u8"}"#,
    ));
    assert_refused(&e, "n.raw.json", "sidecar", &["-4", "expected"]);
}

#[test]
fn raw_header_bytes_past_the_end_of_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let o = sidecar(
        dir.path(),
        "h.raw.json",
        r#"{"dims":[4,4,4],"dtype":"u8","header_bytes":18446744073709551615}"#,
    )
    .unwrap();
    let p = write(dir.path(), "h.raw", &[0u8; 64]);
    let e = err(raw::open(&p, &o));
    assert_refused(&e, "h.raw", "dims", &["overflows 64 bits"]);
    let o = sidecar(
        dir.path(),
        "h2.raw.json",
        r#"{"dims":[4,4,4],"dtype":"u8","header_bytes":4096}"#,
    )
    .unwrap();
    let e = err(raw::open(&p, &o));
    assert_refused(
        &e,
        "h.raw",
        "dims",
        &["holds 64 bytes", "4096 header bytes"],
    );
}

/// A sidecar is read up to a bound: a (valid) 2 MiB one is refused rather
/// than read whole.
#[test]
fn raw_sidecar_reading_is_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let json = format!(
        "{}{{\"dims\":[4,4,4],\"dtype\":\"u8\"}}",
        " ".repeat(2 << 20)
    );
    let e = err(sidecar(dir.path(), "big.raw.json", &json));
    assert_refused(&e, "big.raw.json", "sidecar", &["larger than"]);
}

// ---------------------------------------------------------------------------
// Zarr metadata

/// A Zarr v3 array directory with the given `zarr.json`.
fn zarr_array(dir: &Path, name: &str, json: serde_json::Value) -> PathBuf {
    let a = dir.join(name);
    write(&a, "zarr.json", json.to_string().as_bytes());
    a
}

fn v3(shape: serde_json::Value, chunk: serde_json::Value, dtype: &str) -> serde_json::Value {
    serde_json::json!({
        "zarr_format": 3,
        "node_type": "array",
        "shape": shape,
        "data_type": dtype,
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunk}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": 0,
        "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}]
    })
}

#[test]
fn zarr_huge_and_negative_shapes() {
    let dir = tempfile::tempdir().unwrap();
    let big = 1u64 << 40;
    let a = zarr_array(
        dir.path(),
        "huge",
        v3(
            serde_json::json!([big, big, big]),
            serde_json::json!([64, 64, 64]),
            "uint16",
        ),
    );
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(&e, "huge/zarr.json", "shape", &["more than 2^63 bytes"]);

    let a = zarr_array(
        dir.path(),
        "negative",
        v3(
            serde_json::json!([-4, 4, 4]),
            serde_json::json!([4, 4, 4]),
            "uint8",
        ),
    );
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(&e, "negative/zarr.json", "shape", &["positive integers"]);

    // A channel axis of 2^32 channels (no data needed: all fill value).
    let mut j = v3(
        serde_json::json!([1u64 << 32, 4, 4, 4]),
        serde_json::json!([1, 4, 4, 4]),
        "uint8",
    );
    j["dimension_names"] = serde_json::json!(["c", "z", "y", "x"]);
    let a = zarr_array(dir.path(), "channels", j);
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(
        &e,
        "channels/zarr.json",
        "shape",
        &["4294967296 channels", "at most 65536"],
    );
}

#[test]
fn zarr_zero_and_huge_chunks() {
    let dir = tempfile::tempdir().unwrap();
    let a = zarr_array(
        dir.path(),
        "zero",
        v3(
            serde_json::json!([8, 8, 8]),
            serde_json::json!([4, 0, 4]),
            "uint8",
        ),
    );
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(
        &e,
        "zero/zarr.json",
        "chunk_grid.configuration.chunk_shape",
        &["3 positive integers", "[4,0,4]"],
    );
    // Zarr v2: `chunks`.
    let a = dir.path().join("zero-v2");
    write(
        &a,
        ".zarray",
        br#"{"zarr_format":2,"shape":[8,8,8],"chunks":[0,8,8],"dtype":"|u1","compressor":null,"fill_value":0,"order":"C","filters":null}"#,
    );
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(&e, "zero-v2/.zarray", "chunks", &["3 positive integers"]);

    // One 64 GiB chunk for a tiny array.
    let a = zarr_array(
        dir.path(),
        "bigchunk",
        v3(
            serde_json::json!([2, 2, 2]),
            serde_json::json!([4096, 4096, 4096]),
            "uint8",
        ),
    );
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(
        &e,
        "bigchunk/zarr.json",
        "chunk_grid.configuration.chunk_shape",
        &["68719476736 bytes", "at most"],
    );
}

/// A sharded array whose shards would list 2^36 inner chunks each.
#[test]
fn zarr_absurd_shard_index() {
    let dir = tempfile::tempdir().unwrap();
    let mut j = v3(
        serde_json::json!([8, 8, 8]),
        serde_json::json!([4096, 4096, 4096]),
        "uint8",
    );
    j["codecs"] = serde_json::json!([{
        "name": "sharding_indexed",
        "configuration": {
            "chunk_shape": [1, 1, 1],
            "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
            "index_codecs": [{"name": "bytes", "configuration": {"endian": "little"}}, {"name": "crc32c"}],
            "index_location": "end"
        }
    }]);
    let a = zarr_array(dir.path(), "index", j);
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(
        &e,
        "index/zarr.json",
        "sharding_indexed.chunk_shape",
        &["68719476736 inner chunks", "at most 16777216"],
    );
}

// ---------------------------------------------------------------------------
// Shard index

/// Convert a small volume to a store and return (tempdir, store, the
/// level-0 shard file holding the first brick).
fn small_store() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let src = common::make_source([16, 16, 16], 1, DType::U16, 3);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s.ome.zarr");
    let opts = ConvertOptions {
        brick: [8; 3],
        shard: [16; 3],
        compression: Compression::None,
        ..Default::default()
    };
    convert(&src, &out, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
    let shard = out.join("0/c/0/0/0");
    assert!(shard.exists());
    (dir, out, shard)
}

/// Rewrite entry `k` of a brickyard shard's index (8 entries, CRC after
/// them) and fix the CRC, so that only the entry is wrong.
fn set_entry(shard: &Path, k: usize, off: u64, n: u64) {
    let mut b = std::fs::read(shard).unwrap();
    let ib = b.len() - (8 * 16 + 4);
    b[ib + 16 * k..ib + 16 * k + 8].copy_from_slice(&off.to_le_bytes());
    b[ib + 16 * k + 8..ib + 16 * k + 16].copy_from_slice(&n.to_le_bytes());
    let crc = crc32c::crc32c(&b[ib..ib + 8 * 16]);
    let l = b.len();
    b[l - 4..].copy_from_slice(&crc.to_le_bytes());
    std::fs::write(shard, b).unwrap();
}

fn read_level0(store: &Path) -> brickyard_store::Result<()> {
    let src = zarr::open(store, 0)?;
    read_all(&src)
}

#[test]
fn shard_entry_past_the_end_of_the_shard() {
    let (_d, store, shard) = small_store();
    read_level0(&store).unwrap();
    for (off, n) in [
        (0, 1u64 << 40),
        (1 << 40, 16),
        (u64::MAX - 8, 16),
        (0, u64::MAX),
    ] {
        set_entry(&shard, 0, off, n);
        let e = err(read_level0(&store));
        assert_refused(
            &e,
            "0/c/0/0/0",
            "shard index",
            &["entry 0", "must lie in bytes 0.."],
        );
    }
    // An entry inside the index itself is refused too.
    let len = std::fs::metadata(&shard).unwrap().len();
    set_entry(&shard, 0, len - 100, 64);
    let e = err(read_level0(&store));
    assert_refused(&e, "0/c/0/0/0", "shard index", &["entry 0"]);
}

#[test]
fn shard_bad_crc_and_truncated_shard() {
    let (_d, store, shard) = small_store();
    let mut b = std::fs::read(&shard).unwrap();
    let l = b.len();
    b[l - 1] ^= 0xff;
    std::fs::write(&shard, &b).unwrap();
    let e = err(read_level0(&store));
    assert_refused(
        &e,
        "0/c/0/0/0",
        "shard index",
        &["CRC32C", "does not match"],
    );

    std::fs::write(&shard, &b[..100]).unwrap();
    let e = err(read_level0(&store));
    assert_refused(
        &e,
        "0/c/0/0/0",
        "shard index",
        &["holds 100 bytes", "132 bytes"],
    );
}

#[test]
fn shard_index_parser() {
    let p = Path::new("shard");
    let layout = IndexLayout::brickyard(2);
    // Two chunks of 3 bytes, then the index.
    let mut b = vec![1u8, 2, 3, 4, 5, 6];
    for (o, n) in [(0u64, 3u64), (3, 3)] {
        b.extend(o.to_le_bytes());
        b.extend(n.to_le_bytes());
    }
    let crc = crc32c::crc32c(&b[6..]);
    b.extend(crc.to_le_bytes());
    assert_eq!(
        shard::parse_index(p, &b, &layout).unwrap(),
        vec![[0, 3], [3, 3]]
    );
    // Index at the start: offsets count from the start of the file.
    let start = IndexLayout {
        location: IndexLocation::Start,
        crc32c: false,
        ..layout
    };
    let mut s = Vec::new();
    for (o, n) in [(32u64, 3u64), (u64::MAX, u64::MAX)] {
        s.extend(o.to_le_bytes());
        s.extend(n.to_le_bytes());
    }
    s.extend([9, 9, 9]);
    assert_eq!(
        shard::parse_index(p, &s, &start).unwrap(),
        vec![[32, 3], [u64::MAX, u64::MAX]]
    );
    s[0] = 0; // offset 0: inside the index
    let e = err(shard::parse_index(p, &s, &start));
    assert_refused(&e, "shard", "shard index", &["entry 0", "bytes 32..35"]);
    let e = err(shard::parse_index(p, &b[..10], &layout));
    assert_refused(&e, "shard", "shard index", &["holds 10 bytes"]);
}

// ---------------------------------------------------------------------------
// Inputs found by fuzzing (tests/fuzz/, named after their fuzz target)

fn fuzz_input(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fuzz")
        .join(name)
}

/// `tiff_header`: the second IFD's ImageWidth claims 1334545665 values; the
/// `tiff` decoder reserved 40 GiB for them before reading any (an abort).
#[test]
fn fuzz_tiff_tag_count() {
    let p = fuzz_input("tiff_header-tag-count.tif");
    let e = err(tiff::open(&p));
    assert_refused(
        &e,
        "tiff_header-tag-count.tif",
        "IFD",
        &["page 1", "more values than the file could hold"],
    );
}

/// Lay out an input of the `zarr_array` fuzz target as that target does:
/// the metadata up to the first NUL byte, then the first chunk.
fn zarr_array_input(dir: &Path, name: &str) -> PathBuf {
    let data = std::fs::read(fuzz_input(name)).unwrap();
    let i = data.iter().position(|&b| b == 0).unwrap();
    let (meta, chunk) = (&data[..i], &data[i + 1..]);
    let j: serde_json::Value = serde_json::from_slice(meta).unwrap();
    let n = j["shape"].as_array().unwrap().len();
    let a = dir.join(name);
    if j["zarr_format"] == 2 {
        write(&a, ".zarray", meta);
        write(&a, &vec!["0"; n].join("."), chunk);
    } else {
        write(&a, "zarr.json", meta);
        write(&a, &format!("c/{}", vec!["0"; n].join("/")), chunk);
    }
    a
}

/// `zarr_array`: a Zarr v2 array of shape [3, 4, 0] opened as an empty
/// volume (which the fuzz target then read out of bounds).
#[test]
fn fuzz_zarr_empty_shape() {
    let dir = tempfile::tempdir().unwrap();
    let a = zarr_array_input(dir.path(), "zarr_array-empty-shape");
    let e = err(ZarrSource::open_level_array(&a));
    assert_refused(
        &e,
        "zarr_array-empty-shape/.zarray",
        "shape",
        &["[3, 4, 0] holds no voxels"],
    );
}

/// `zarr_array` (a seed with one index entry set by hand): a shard index
/// without CRC whose entry claims 2^40 bytes; `zarrs` allocated them
/// before reading the gzip-compressed inner chunk (an abort).
#[test]
fn fuzz_zarr_shard_entry() {
    let dir = tempfile::tempdir().unwrap();
    let a = zarr_array_input(dir.path(), "zarr_array-shard-entry");
    let src = ZarrSource::open_level_array(&a).unwrap();
    let mut out = vec![0u8; 2];
    let e = err(src.read_region(0, 0..1, 0..1, 0..1, &mut out));
    assert_refused(
        &e,
        "c/0/0/0",
        "shard index",
        &["entry 0", "1099511627776 bytes"],
    );
}
