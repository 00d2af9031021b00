//! Raw binary volumes: dims, dtype, endianness and spacing come from the
//! caller (command-line flags) or from a JSON sidecar next to the file.
//!
//! Layout on disk: `header_bytes` skipped, then channel-major
//! (`c, z, y, x`, x fastest) voxels.

use crate::error::{IoContext, Result, StoreError};
use crate::import::swap_bytes_in_place;
use crate::source::{check_region, SourceMeta, VolumeSource};
use brickyard_core::DType;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{self, Read};
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// Description of a raw file. Dims and spacing are in `x, y, z` order, as
/// people write them; brickyard converts to `[z, y, x]` internally.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawOptions {
    /// `[x, y, z]` in voxels.
    pub dims: [u64; 3],
    pub dtype: DType,
    /// `"little"` (default) or `"big"`.
    #[serde(default = "default_endian")]
    pub endian: String,
    /// `[x, y, z]` voxel spacing.
    #[serde(default)]
    pub spacing: Option<[f64; 3]>,
    /// `[x, y, z]` position of the centre of the first voxel.
    #[serde(default)]
    pub origin: Option<[f64; 3]>,
    #[serde(default)]
    pub unit: Option<String>,
    #[serde(default = "one")]
    pub channels: usize,
    #[serde(default)]
    pub header_bytes: u64,
}

/// Largest sidecar file read.
pub const MAX_SIDECAR_BYTES: u64 = 1 << 20;

fn default_endian() -> String {
    "little".into()
}
fn one() -> usize {
    1
}

impl RawOptions {
    /// `dims` (`[x, y, z]`) of `dtype`, little-endian, one channel, no
    /// header, no geometry.
    pub fn new(dims: [u64; 3], dtype: DType) -> RawOptions {
        RawOptions {
            dims,
            dtype,
            endian: default_endian(),
            spacing: None,
            origin: None,
            unit: None,
            channels: 1,
            header_bytes: 0,
        }
    }

    /// The sidecar path of a raw file: `FILE.json`.
    pub fn sidecar_path(raw: &Path) -> PathBuf {
        let mut s = raw.as_os_str().to_owned();
        s.push(".json");
        PathBuf::from(s)
    }

    /// Read a sidecar file (at most [`MAX_SIDECAR_BYTES`] of it).
    pub fn read_sidecar(path: &Path) -> Result<RawOptions> {
        let mut bytes = Vec::new();
        File::open(path)
            .at(path)?
            .take(MAX_SIDECAR_BYTES + 1)
            .read_to_end(&mut bytes)
            .at(path)?;
        if bytes.len() as u64 > MAX_SIDECAR_BYTES {
            return Err(StoreError::invalid(
                path,
                "sidecar",
                format!("larger than {MAX_SIDECAR_BYTES} bytes; expected a short JSON description"),
            ));
        }
        Self::parse_sidecar(path, &bytes)
    }

    /// Parse the bytes of a sidecar file; `path` names it in errors.
    pub fn parse_sidecar(path: &Path, bytes: &[u8]) -> Result<RawOptions> {
        let r: RawOptions = serde_json::from_slice(bytes).map_err(|e| {
            StoreError::invalid(
                path,
                "sidecar",
                format!(
                    "{e}; expected {{\"dims\":[x,y,z],\"dtype\":\"u16\",\"endian\":\"little\",\
                     \"spacing\":[x,y,z],\"channels\":1,\"header_bytes\":0}}"
                ),
            )
        })?;
        r.check_geometry(path)?;
        Ok(r)
    }

    /// The sidecar's spacing, origin and unit are the user's own statement:
    /// refused as the same values given as flags are (not silently
    /// replaced or dropped); `path` names the sidecar.
    pub fn check_geometry(&self, path: &Path) -> Result<()> {
        if let Some(sp) = self.spacing {
            if sp.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(StoreError::invalid(
                    path,
                    "spacing",
                    format!("expected positive numbers, found {sp:?} (x, y, z)"),
                ));
            }
        }
        if let Some(o) = self.origin {
            if o.iter().any(|v| !v.is_finite()) {
                return Err(StoreError::invalid(
                    path,
                    "origin",
                    format!("expected finite numbers, found {o:?} (x, y, z)"),
                ));
            }
        }
        if let Some(u) = &self.unit {
            crate::omezarr::known_unit(u).map_err(|why| StoreError::invalid(path, "unit", why))?;
        }
        Ok(())
    }

    /// Write a sidecar file.
    pub fn write_sidecar(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self).expect("serializable");
        std::fs::write(path, text + "\n").at(path)
    }
}

/// A raw volume read with positioned reads (no buffering of the whole file).
pub struct RawSource {
    meta: SourceMeta,
    file: File,
    big_endian: bool,
    header: u64,
    /// Bytes the file held when opened (header and voxels).
    len: u64,
}

/// Open a raw file described by `opts`.
pub fn open(path: &Path, opts: &RawOptions) -> Result<RawSource> {
    let big_endian = match opts.endian.to_ascii_lowercase().as_str() {
        "little" | "le" => false,
        "big" | "be" => true,
        other => {
            return Err(StoreError::invalid(
                path,
                "endian",
                format!("expected \"little\" or \"big\", found {other:?}"),
            ))
        }
    };
    if opts.dims.contains(&0) {
        return Err(StoreError::invalid(
            path,
            "dims",
            format!("expected three positive sizes, found {:?}", opts.dims),
        ));
    }
    if opts.channels == 0 {
        return Err(StoreError::invalid(path, "channels", "expected at least 1"));
    }
    // A pipe, socket or device has no length to check against dims (and
    // opening a FIFO would wait for a writer): refuse it before opening.
    let not_regular = |m: &std::fs::Metadata| {
        StoreError::invalid(
            path,
            "input",
            format!(
                "raw input must be a regular file, found {}; copy the data to a file first",
                file_kind(m)
            ),
        )
    };
    let m = std::fs::metadata(path).at(path)?;
    if !m.is_file() {
        return Err(not_regular(&m));
    }
    let file = File::open(path).at(path)?;
    let m = file.metadata().at(path)?;
    if !m.is_file() {
        return Err(not_regular(&m));
    }
    let len = m.len();
    let [x, y, z] = opts.dims;
    let need = x
        .checked_mul(y)
        .and_then(|v| v.checked_mul(z))
        .and_then(|v| v.checked_mul(opts.channels as u64))
        .and_then(|v| v.checked_mul(opts.dtype.size() as u64))
        .and_then(|v| v.checked_add(opts.header_bytes))
        .ok_or_else(|| StoreError::invalid(path, "dims", "volume size overflows 64 bits"))?;
    if len != need {
        return Err(StoreError::invalid(
            path,
            "dims",
            format!(
                "file holds {len} bytes but {x}x{y}x{z} voxels x {} channel(s) of {} \
                 plus {} header bytes need {need}",
                opts.channels, opts.dtype, opts.header_bytes
            ),
        ));
    }
    let mut meta = SourceMeta::new(path, [z, y, x], opts.channels, opts.dtype);
    meta.spacing = opts.spacing.map(|s| [s[2], s[1], s[0]]);
    meta.origin = opts.origin.map(|s| [s[2], s[1], s[0]]);
    meta.unit = opts.unit.clone();
    Ok(RawSource {
        meta,
        file,
        big_endian,
        header: opts.header_bytes,
        len,
    })
}

/// What kind of file `m` describes, for messages.
fn file_kind(m: &std::fs::Metadata) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    let t = m.file_type();
    if t.is_dir() {
        "a folder"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else {
        "not a regular file"
    }
}

/// Fill as much of `buf` as `file` holds from byte `offset`: the count is
/// short only where the file ends first.
pub(crate) fn read_full_at(file: &File, buf: &mut [u8], offset: u64) -> io::Result<usize> {
    let mut done = 0;
    while done < buf.len() {
        match file.read_at(&mut buf[done..], offset + done as u64) {
            Ok(0) => break,
            Ok(n) => done += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(done)
}

/// The message for a file, checked large enough when opened, that ends at
/// byte `at` where the data needs `need` bytes.
pub(crate) fn ends_early(at: u64, need: u64) -> String {
    format!(
        "the file ends early: no data at byte {at} of the {need} expected (they were there \
         when it was opened): it changed while being read, or is truncated"
    )
}

impl RawSource {
    /// Fill `buf` from byte `off`; a file that ends first is an error
    /// naming it and the byte where it ends.
    fn read_at(&self, buf: &mut [u8], off: u64) -> Result<()> {
        let got = read_full_at(&self.file, buf, off).at(&self.meta.path)?;
        if got < buf.len() {
            return Err(StoreError::invalid(
                &self.meta.path,
                "data",
                ends_early(off + got as u64, self.len),
            ));
        }
        Ok(())
    }
}

impl VolumeSource for RawSource {
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
    ) -> Result<()> {
        check_region(&self.meta, c, &z, &y, &x, out);
        let es = self.meta.dtype.size() as u64;
        let [_, dy, dx] = self.meta.dims;
        let base = self.header + c as u64 * self.meta.channel_bytes();
        let row = (x.end - x.start) * es;
        let full_rows = x.start == 0 && x.end == dx;
        let mut o = 0usize;
        for zz in z.clone() {
            if full_rows {
                // One contiguous read per slice.
                let n = ((y.end - y.start) * row) as usize;
                let off = base + ((zz * dy + y.start) * dx) * es;
                self.read_at(&mut out[o..o + n], off)?;
                o += n;
            } else {
                for yy in y.clone() {
                    let off = base + ((zz * dy + yy) * dx + x.start) * es;
                    let n = row as usize;
                    self.read_at(&mut out[o..o + n], off)?;
                    o += n;
                }
            }
        }
        if self.big_endian {
            swap_bytes_in_place(out, es as usize);
        }
        Ok(())
    }

    fn preferred_read(&self) -> brickyard_core::Dims3 {
        let d = self.meta.dims;
        [1, d[1], d[2]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_regions_and_swaps() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("v.raw");
        let dims = [5u64, 4, 3]; // x y z
        let n = 5 * 4 * 3;
        let vals: Vec<u16> = (0..n as u16 * 2).map(|v| v * 7 + 1).collect();
        let mut bytes = vec![0u8; 3];
        for v in &vals {
            bytes.extend_from_slice(&v.to_be_bytes());
        }
        std::fs::write(&p, &bytes).unwrap();
        let opts = RawOptions {
            dims,
            dtype: DType::U16,
            endian: "big".into(),
            spacing: Some([1.0, 2.0, 3.0]),
            origin: None,
            unit: None,
            channels: 2,
            header_bytes: 3,
        };
        let s = open(&p, &opts).unwrap();
        assert_eq!(s.meta().dims, [3, 4, 5]);
        assert_eq!(s.meta().spacing, Some([3.0, 2.0, 1.0]));
        let mut out = vec![0u8; 2 * 2 * 2 * 2];
        s.read_region(1, 1..3, 2..4, 3..5, &mut out).unwrap();
        let got: Vec<u16> = out
            .chunks(2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
            .collect();
        let mut want = vec![];
        for z in 1..3 {
            for y in 2..4 {
                for x in 3..5 {
                    want.push(vals[n + (z * 4 + y) * 5 + x]);
                }
            }
        }
        assert_eq!(got, want);
    }

    #[test]
    fn size_mismatch_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.raw");
        std::fs::write(&p, vec![0u8; 100]).unwrap();
        let opts = RawOptions::new([10, 10, 2], DType::U8);
        let e = open(&p, &opts).err().unwrap().to_string();
        assert!(
            e.contains("bad.raw") && e.contains("dims") && e.contains("200"),
            "{e}"
        );
        let e = open(&dir.path().join("missing.raw"), &opts)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("missing.raw"), "{e}");
        let side = dir.path().join("s.json");
        std::fs::write(&side, "{\"dims\":[1,2],\"dtype\":\"u8\"}").unwrap();
        let e = RawOptions::read_sidecar(&side).err().unwrap().to_string();
        assert!(e.contains("s.json") && e.contains("sidecar"), "{e}");
    }
}
