//! NIfTI-1 and NIfTI-2 importer: `.nii`, `.nii.gz` and `.hdr`/`.img` pairs
//! (either half of a pair may be gzip-compressed).
//!
//! Over 800 lines: 1.2k lines of importer (two headers, gzip, pairs, the
//! geometry of sform and qform), 1.3k of tests.
//!
//! The header is parsed by hand rather than with the `nifti` crate: that
//! crate (0.18) knows NIfTI-1 only and reads whole volumes into memory,
//! while this importer must stream regions of volumes larger than memory.
//! Both header layouts are fixed structs (348 bytes for NIfTI-1, 540 for
//! NIfTI-2); the byte order is detected from `sizeof_hdr`.
//!
//! Axes: NIfTI stores x fastest, then y, z (and t), which is brickyard's
//! `[z, y, x]` C order, so `dims = [dim[3], dim[2], dim[1]]`. A fourth
//! dimension becomes channels (channel `c` is the `c`-th 3-D volume); more
//! dimensions are unsupported.
//!
//! Orientation: when the sform (else the qform) only scales each axis, an
//! axis it steps backwards along (a negative diagonal entry of the sform,
//! `qfac` −1 or a 180° quaternion) is read reversed (`import::flip::Flip`)
//! and its origin moved to the file's last voxel along it, so that OME-Zarr's
//! positive scale and translation put every voxel where the file does.
//! Rotations, shears and permuted axes are not applied (noted). Reversing
//! z of gzip data reads the slices back to front, so each slab read
//! decompresses the stream again from its start: such files convert
//! correctly but more slowly.
//!
//! Values: `scl_slope`/`scl_inter` are applied (`value = slope · stored +
//! inter`) unless raw values are asked for ([`open_with`]); a slope of 0 or
//! not finite means no scaling and `(1, 0)` is the identity, as nibabel reads
//! them. The type of the values is chosen by [`scale::choose_dtype`]: the
//! integer type is kept (or widened) when the rescale is exact and the values
//! fit, else the values are float. Deciding that may need the range of the
//! stored numbers: then [`open_with`] reads the voxels once, streaming, to
//! find it (only for integer data with an integer slope and intercept whose
//! rescaled type range overflows the stored type and where the stored
//! numbers could change the answer, such as int16 CT with intercept −1024;
//! not for uint8 with intercept −1024, which is int16 whatever they are).
//!
//! Memory stays bounded: an uncompressed file is read with positioned reads
//! at `vox_offset`; a gzip-compressed one is decompressed sequentially by a
//! few cursors kept between requests (a cursor restarts from the beginning of
//! the file only when a request lies behind every cursor), so reading slices
//! in z order decompresses the file once. Truncated gzip data is detected
//! when a read reaches it, not at [`open`].

use crate::error::{IoContext, Result, StoreError};
use crate::import::flip::{self, Flip};
use crate::import::scale::{self, num, Choice, ValueScaling};
use crate::import::{swap_bytes_in_place, MAX_DEFLATE_RATIO};
use crate::source::{check_region, SourceMeta, VolumeSource};
use brickyard_core::{as_bytes_mut, dispatch_dtype, DType, Dims3, Sample};
use flate2::read::MultiGzDecoder;
use std::fs::File;
use std::io::{self, BufReader, Read};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

const NIFTI1_HDR: usize = 348;
const NIFTI2_HDR: usize = 540;
const GZ_MAGIC: [u8; 2] = [0x1f, 0x8b];
/// `NIFTI_INTENT_LABEL`: the voxels are label indices.
const INTENT_LABEL: i32 = 1002;
/// Most gzip cursors kept open at once (one per channel up to this).
const MAX_GZ_CURSORS: usize = 8;
/// Scratch buffer used to skip forward in a gzip stream.
const SKIP_CHUNK: usize = 64 * 1024;
/// Companion file extensions of a `.hdr`/`.img` pair, in search order.
const HDR_EXTS: [&str; 5] = [".hdr", ".HDR", ".hdr.gz", ".HDR.gz", ".HDR.GZ"];
const IMG_EXTS: [&str; 5] = [".img", ".IMG", ".img.gz", ".IMG.gz", ".IMG.GZ"];

/// A NIfTI volume opened for region reads. See the [module docs](self).
pub struct NiftiSource {
    meta: SourceMeta,
    /// `(scl_slope, scl_inter)` when the header asks for a linear rescale
    /// other than the identity (`slope` finite, non-zero and not `(1, 0)`),
    /// applied or not: `meta().scaling` says which.
    pub scale: Option<(f64, f64)>,
    /// Type of the numbers in the file (`meta.dtype` is that of the values
    /// returned, which differs when a rescale changes the type).
    stored: DType,
    version: u8,
    /// File holding the voxels (the `.img` of a pair).
    data_path: PathBuf,
    /// Byte offset of the first voxel in the (decompressed) data file.
    data_offset: u64,
    /// The data is big-endian and must be swapped.
    swap: bool,
    /// Axes the sform/qform runs against the world's: read reversed.
    flip: Flip,
    data: Data,
}

enum Data {
    /// Uncompressed: positioned reads.
    Raw(File),
    /// Gzip-compressed: sequential decompression by pooled cursors.
    Gz(Mutex<GzPool>),
}

impl std::fmt::Debug for NiftiSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NiftiSource")
            .field("meta", &self.meta)
            .field("scale", &self.scale)
            .field("stored", &self.stored)
            .field("version", &self.version)
            .field("data_path", &self.data_path)
            .field("data_offset", &self.data_offset)
            .field("gzip", &matches!(self.data, Data::Gz(_)))
            .field("flip", &self.flip.axes)
            .finish()
    }
}

impl NiftiSource {
    /// NIfTI format version of the header: 1 or 2.
    pub fn version(&self) -> u8 {
        self.version
    }

    /// Whether the voxel data is gzip-compressed.
    pub fn is_gzip(&self) -> bool {
        matches!(self.data, Data::Gz(_))
    }

    /// Error for voxel data that ends before the volume does.
    fn gz_too_small(&self, len: u64, most: u64) -> StoreError {
        let [z, y, x] = self.meta.dims;
        let need = self.stored_channel_bytes() * self.meta.channels as u64;
        StoreError::invalid(
            &self.data_path,
            "data",
            format!(
                "gzip-compressed file of {len} bytes holds at most {most} bytes of voxel data \
                 (deflate inflates at most {MAX_DEFLATE_RATIO}-fold), dims {x}×{y}×{z} × {} need \
                 {need}",
                self.stored
            ),
        )
    }

    /// Error for voxel data that ends before the volume does.
    fn data_short(&self, held: u64) -> StoreError {
        let [z, y, x] = self.meta.dims;
        let mut shape = format!("{x}×{y}×{z}");
        if self.meta.channels > 1 {
            shape += &format!("×{}", self.meta.channels);
        }
        let need = self.stored_channel_bytes() * self.meta.channels as u64;
        let holds = match self.data {
            Data::Raw(_) => format!("file holds {held} bytes of voxel data"),
            Data::Gz(_) => format!(
                "the gzip stream is cut short (a truncated file?): its voxel data ends after \
                 {held} bytes"
            ),
        };
        StoreError::invalid(
            &self.data_path,
            "data",
            format!("{holds}, dims {shape} × {} need {need}", self.stored),
        )
    }

    /// Bytes of one channel in the file.
    fn stored_channel_bytes(&self) -> u64 {
        self.meta.dims.iter().product::<u64>() * self.stored.size() as u64
    }

    /// Read the stored numbers of a region (native-endian, unscaled) into
    /// `out`, which holds `stored.size()` bytes per voxel.
    fn read_stored(
        &self,
        c: usize,
        z: &Range<u64>,
        y: &Range<u64>,
        x: &Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        let size = self.stored.size() as u64;
        let base = self.data_offset + c as u64 * self.stored_channel_bytes();
        let runs = contiguous_runs(base, self.meta.dims, size, z, y, x);
        match &self.data {
            Data::Raw(file) => {
                for (off, range) in &runs {
                    read_exact_at(file, &mut out[range.clone()], *off).at(&self.data_path)?;
                }
            }
            Data::Gz(pool) => self.read_gz(pool, &runs, out)?,
        }
        if self.swap {
            swap_bytes_in_place(out, size as usize);
        }
        Ok(())
    }

    /// `[min, max]` of the stored numbers of every channel (integer types
    /// only), read slice by slice in file order with bounded memory.
    fn stored_range(&self) -> Result<[f64; 2]> {
        const BUDGET: u64 = 8 << 20;
        let [nz, ny, nx] = self.meta.dims;
        let row = nx * self.stored.size() as u64;
        let rows = (BUDGET / row.max(1)).clamp(1, ny);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        dispatch_dtype!(self.stored, T => {
            let mut buf: Vec<T> = Vec::new();
            for c in 0..self.meta.channels {
                for z in 0..nz {
                    for y0 in (0..ny).step_by(rows as usize) {
                        let y1 = (y0 + rows).min(ny);
                        buf.resize(((y1 - y0) * nx) as usize, T::default());
                        self.read_stored(c, &(z..z + 1), &(y0..y1), &(0..nx), as_bytes_mut(&mut buf))?;
                        let (a, b) = T::min_max(&buf);
                        lo = lo.min(a.to_f64());
                        hi = hi.max(b.to_f64());
                    }
                }
            }
        });
        Ok([lo, hi])
    }

    /// Map an error from the gzip stream: truncation is a `data` error,
    /// undecodable bytes a `gzip` error.
    fn gz_error(&self, e: io::Error, pos: u64) -> StoreError {
        match e.kind() {
            io::ErrorKind::UnexpectedEof => self.data_short(pos.saturating_sub(self.data_offset)),
            io::ErrorKind::InvalidInput | io::ErrorKind::InvalidData => StoreError::invalid(
                &self.data_path,
                "gzip",
                format!("corrupt compressed data after {pos} decompressed bytes: {e}"),
            ),
            _ => StoreError::io(&self.data_path, e),
        }
    }

    fn read_gz(
        &self,
        pool: &Mutex<GzPool>,
        runs: &[(u64, Range<usize>)],
        out: &mut [u8],
    ) -> Result<()> {
        let Some(first) = runs.first() else {
            return Ok(());
        };
        let mut pool = pool.lock().unwrap_or_else(PoisonError::into_inner);
        let mut cur = pool.take(&self.data_path, first.0)?;
        for (off, range) in runs {
            let pos = cur.pos;
            match cur.skip_to(*off, &mut pool.scratch) {
                Ok(true) => {}
                Ok(false) => return Err(self.data_short(cur.pos.saturating_sub(self.data_offset))),
                Err(e) => return Err(self.gz_error(e, pos)),
            }
            let dst = &mut out[range.clone()];
            match cur.read_fully(dst) {
                Ok(n) if n == dst.len() => {}
                Ok(_) => return Err(self.data_short(cur.pos.saturating_sub(self.data_offset))),
                Err(e) => return Err(self.gz_error(e, cur.pos)),
            }
        }
        // The last voxel read: decompress to the end of the stream, where
        // gzip checks its CRC and length (a flipped bit in the data is
        // caught only there).
        let end = self.data_offset + self.stored_channel_bytes() * self.meta.channels as u64;
        if cur.pos == end {
            let pos = cur.pos;
            cur.drain(&mut pool.scratch)
                .map_err(|e| self.gz_error(e, pos))?;
        }
        pool.put(cur);
        Ok(())
    }
}

impl VolumeSource for NiftiSource {
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
        if out.is_empty() {
            return Ok(());
        }
        let size = self.meta.dtype.size();
        self.flip.read(z, y, x, out, size, |z, y, x, out| {
            self.read_values(c, &z, &y, &x, out)
        })
    }
}

impl NiftiSource {
    /// Read a region of the file as stored (not reversed), rescaled when
    /// the rescale is applied.
    fn read_values(
        &self,
        c: usize,
        z: &Range<u64>,
        y: &Range<u64>,
        x: &Range<u64>,
        out: &mut [u8],
    ) -> Result<()> {
        match self.meta.scaling.as_ref().filter(|s| s.applied) {
            None => self.read_stored(c, z, y, x, out),
            Some(s) if s.stored.size() == s.dtype.size() => {
                self.read_stored(c, z, y, x, out)?;
                s.apply_in_place(out);
                Ok(())
            }
            Some(s) => {
                let n = out.len() / s.dtype.size();
                let mut stored = vec![0u8; n * s.stored.size()];
                self.read_stored(c, z, y, x, &mut stored)?;
                s.apply(&stored, out);
                Ok(())
            }
        }
    }
}

/// Open a NIfTI-1 or NIfTI-2 file: `.nii`, `.nii.gz`, or either file of a
/// `.hdr`/`.img` pair, with `scl_slope`/`scl_inter` applied. See
/// [`open_with`].
pub fn open(path: &Path) -> Result<NiftiSource> {
    open_with(path, false)
}

/// Open a NIfTI-1 or NIfTI-2 file: `.nii`, `.nii.gz`, or either file of a
/// `.hdr`/`.img` pair. Only the header is read here, unless choosing the
/// type of rescaled values needs the range of the stored numbers (see the
/// [module docs](self)).
///
/// Supported voxel types: uint8, int8, uint16, int16, uint32, int32,
/// float32, float64. Spacing comes from `pixdim[1..=3]` or a diagonal
/// sform (unit from `xyzt_units`), the origin from the sform translation if
/// `sform_code > 0`, else from the qform offsets if `qform_code > 0`; axes
/// that a diagonal sform or qform steps backwards along are read reversed
/// (see `geometry`), rotations and shears are not applied. With
/// `raw_values` the stored numbers are returned as they are, without
/// `scl_slope`/`scl_inter`.
pub fn open_with(path: &Path, raw_values: bool) -> Result<NiftiSource> {
    let (hdr_path, img_path) = locate(path)?;
    let (head, hdr_gz) = read_head(&hdr_path)?;
    let h = parse_header(&head, &hdr_path)?;

    let data_path = if h.pair {
        match img_path {
            Some(p) => p,
            None => companion(&hdr_path, &IMG_EXTS).ok_or_else(|| {
                StoreError::invalid(
                    &hdr_path,
                    "magic",
                    format!(
                        "\"ni{}\" means the voxels are in a separate .img file, but none was \
                         found next to the header",
                        h.version
                    ),
                )
            })?,
        }
    } else {
        hdr_path.clone()
    };

    // Dimensions and channels.
    let hp = &hdr_path;
    let ndim = h.dim[0];
    if !(1..=7).contains(&ndim) {
        return Err(StoreError::invalid(
            hp,
            "dim",
            format!("dim[0] = {ndim}; expected 1 to 7"),
        ));
    }
    let mut d = [1u64; 8];
    for (i, (&n, di)) in h.dim.iter().zip(&mut d).enumerate().skip(1) {
        if i > ndim as usize {
            break;
        }
        if n < 1 {
            return Err(StoreError::invalid(
                hp,
                "dim",
                format!("dim[{i}] = {n}; every used dimension must be at least 1"),
            ));
        }
        *di = n as u64;
    }
    if let Some(i) = (5..=7).find(|&i| d[i] > 1) {
        return Err(StoreError::unsupported(
            hp,
            "dim",
            format!(
                "{ndim}-D data with dim[{i}] = {}; only 3-D volumes and 4-D volumes \
                 (the 4th dimension read as channels) are supported",
                d[i]
            ),
        ));
    }
    let dims: Dims3 = [d[3], d[2], d[1]];
    let channels = usize::try_from(d[4])
        .map_err(|_| StoreError::invalid(hp, "dim", format!("dim[4] = {} is too large", d[4])))?;

    let dtype = dtype_from_code(h.datatype).map_err(|name| {
        StoreError::unsupported(
            hp,
            "datatype",
            format!(
                "datatype {} ({name}); supported are uint8, int8, uint16, int16, uint32, int32, \
                 float32 and float64",
                h.datatype
            ),
        )
    })?;
    // (Noted below, once the notes exist.)
    let bitpix_note = (h.bitpix != 8 * dtype.size() as i32).then(|| {
        format!(
            "bitpix {} disagrees with datatype {} ({dtype}, {} bits): read as {dtype}, as \
             datatype says",
            h.bitpix,
            h.datatype,
            8 * dtype.size()
        )
    });
    let total = dims
        .iter()
        .chain([&d[4]])
        .try_fold(dtype.size() as u64, |acc, &n| acc.checked_mul(n))
        .filter(|&t| t <= i64::MAX as u64)
        .ok_or_else(|| {
            StoreError::invalid(
                hp,
                "dim",
                format!(
                    "{}×{}×{}×{} voxels of {dtype} do not fit in a 64-bit size",
                    d[1], d[2], d[3], d[4]
                ),
            )
        })?;

    // Where the voxels start.
    let vo = h.vox_offset;
    if !vo.is_finite() || vo < 0.0 || vo.fract() != 0.0 || vo >= 2f64.powi(62) {
        return Err(StoreError::invalid(
            hp,
            "vox_offset",
            format!("{vo} is not a valid byte offset"),
        ));
    }
    let data_offset = vo as u64;
    let hdr_size = if h.version == 1 {
        NIFTI1_HDR
    } else {
        NIFTI2_HDR
    };
    if !h.pair && data_offset < hdr_size as u64 {
        return Err(StoreError::invalid(
            hp,
            "vox_offset",
            format!(
                "{data_offset} lies inside the {hdr_size}-byte header of a single-file NIfTI-{}",
                h.version
            ),
        ));
    }

    // Physical metadata.
    let mut meta = SourceMeta::new(path, dims, channels, dtype);
    meta.notes.extend(bitpix_note);
    let geo = geometry(&h, dims);
    meta.spacing = Some(geo.spacing);
    meta.origin = geo.origin;
    meta.notes.extend(geo.notes);
    meta.unit = match h.xyzt_units & 0x07 {
        1 => Some("meter".to_string()),
        2 => Some("millimeter".to_string()),
        3 => Some("micrometer".to_string()),
        // Unknown, with a qform or sform placing the voxels in scanner or
        // template space: those coordinates are millimetres.
        _ if h.sform_code > 0 || h.qform_code > 0 => {
            meta.notes.push(
                "xyzt_units gives no spatial unit: millimetres assumed, as for the scanner or \
                 template coordinates of the qform/sform"
                    .to_string(),
            );
            Some("millimeter".to_string())
        }
        _ => None,
    };
    meta.labels = h.intent_code == INTENT_LABEL;
    if meta.labels {
        meta.notes.push(
            "intent_code 1002 (label): the voxels are labels, coarser levels take the mode"
                .to_string(),
        );
    }
    if channels > 1 {
        meta.notes.push(format!(
            "dim[4] = {channels}: the volumes are read as channels"
        ));
    }
    let scale = scale::effective(h.scl_slope, h.scl_inter);
    if let Some((slope, inter)) = scale {
        if !inter.is_finite() && !raw_values {
            return Err(StoreError::invalid(
                hp,
                "scl_inter",
                format!(
                    "{inter} with scl_slope {slope}: the values cannot be rescaled (convert \
                     with raw values to keep the stored numbers)"
                ),
            ));
        }
    }

    // The voxel data.
    let (file, gz) = if data_path == hdr_path {
        (File::open(&data_path).at(&data_path)?, hdr_gz)
    } else {
        let mut f = File::open(&data_path).at(&data_path)?;
        let magic = read_up_to(&mut f, 2).at(&data_path)?;
        (f, magic == GZ_MAGIC)
    };
    let data = if gz {
        drop(file);
        Data::Gz(Mutex::new(GzPool {
            cursors: Vec::new(),
            max: channels.clamp(2, MAX_GZ_CURSORS),
            tick: 0,
            scratch: vec![0; SKIP_CHUNK],
        }))
    } else {
        Data::Raw(file)
    };
    let mut src = NiftiSource {
        meta,
        scale,
        stored: dtype,
        version: h.version,
        data_path,
        data_offset,
        swap: h.big_endian,
        flip: Flip::new(geo.flip, dims),
        data,
    };
    // The size of compressed data is only known once it is decompressed:
    // a short gzip stream is reported by the read that reaches its end.
    if let Data::Raw(file) = &src.data {
        let len = file.metadata().at(&src.data_path)?.len();
        let held = len.saturating_sub(data_offset);
        if held < total {
            return Err(src.data_short(held));
        }
    } else {
        // But deflate inflates at most MAX_DEFLATE_RATIO-fold, which bounds
        // what a gzip file can hold without decompressing it.
        let len = std::fs::metadata(&src.data_path).at(&src.data_path)?.len();
        let most = len.saturating_mul(MAX_DEFLATE_RATIO);
        if total.saturating_add(data_offset) > most {
            return Err(src.gz_too_small(len, most.saturating_sub(data_offset)));
        }
    }
    if let Some((slope, inter)) = scale {
        let (out, scanned) = if raw_values {
            (dtype, None)
        } else {
            match scale::choose_dtype(dtype, slope, inter, None) {
                Choice::Type(t) => (t, None),
                Choice::NeedsRange => {
                    let r = src.stored_range()?;
                    match scale::choose_dtype(dtype, slope, inter, Some(r)) {
                        Choice::Type(t) => (t, Some(r)),
                        Choice::NeedsRange => unreachable!("a known range always decides"),
                    }
                }
            }
        };
        let s = ValueScaling {
            fields: ["scl_slope", "scl_inter"],
            slope,
            inter,
            stored: dtype,
            dtype: out,
            applied: !raw_values,
            scanned,
        };
        src.meta.notes.push(s.describe());
        src.meta.dtype = out;
        src.meta.scaling = Some(s);
    }
    Ok(src)
}

/// Where the voxels lie, from `pixdim`, the sform and the qform.
struct Geometry {
    /// `[z, y, x]`.
    spacing: [f64; 3],
    /// `[z, y, x]`: the world position of the voxel that is index 0 once
    /// the reversed axes are reversed.
    origin: Option<[f64; 3]>,
    /// Axes read reversed, `[z, y, x]`.
    flip: [bool; 3],
    notes: Vec<String>,
}

/// Spacing, origin and reversed axes of the transform that places the
/// voxels: the sform if `sform_code > 0` (and its translation is finite),
/// else the qform if `qform_code > 0`, else none (spacing from `pixdim`
/// only).
///
/// When that transform only scales each axis, possibly by a negative
/// number (a diagonal sform; a qform whose quaternion is a rotation by 0
/// or 180° about x, y or z, with `qfac` flipping z), its axes are kept:
/// an axis whose step is negative is read reversed and its origin moves to
/// the file's last voxel along it, so that world positions are the file's.
/// The spacing is then the sform's diagonal (pixdim is only noted where it
/// disagrees) or, for a qform, `|pixdim|`. Other transforms (rotations,
/// shears, permuted axes) are not applied: spacing from `pixdim`, origin =
/// the translation, noted.
///
/// An invalid `pixdim` entry (zero, negative zero, NaN, infinite) of an
/// axis longer than one voxel takes the length of the sform's column when
/// there is an sform, else 1, for that axis only, noted.
fn geometry(h: &Header, dims: Dims3) -> Geometry {
    const NAMES: [&str; 3] = ["x", "y", "z"];
    let n = [dims[2], dims[1], dims[0]];
    let mut notes = Vec::new();
    let sform = h.sform_code > 0 && h.srow_offset.iter().all(|v| v.is_finite());
    let qform = !sform && h.qform_code > 0 && h.qoffset.iter().all(|v| v.is_finite());
    let sdiag = if sform {
        diagonal(&h.srow_linear)
    } else {
        None
    };

    // Spacing, x, y, z.
    let mut sp = [1.0; 3];
    for (a, s) in sp.iter_mut().enumerate() {
        let i = a + 1;
        let raw = h.pixdim[i];
        let pix = Some(raw.abs()).filter(|p| p.is_finite() && *p > 0.0);
        *s = match (sdiag, pix) {
            (Some(d), pix) => {
                let from_s = d[a].abs();
                match pix {
                    Some(p) if (p - from_s).abs() > 1e-4 * from_s => notes.push(format!(
                        "pixdim[{i}] = {} disagrees with the sform's {}: {} spacing {} from \
                         the sform",
                        num(raw),
                        num(from_s),
                        NAMES[a],
                        num(from_s)
                    )),
                    None if n[a] > 1 => notes.push(format!(
                        "pixdim[{i}] = {} is not a valid spacing: {} spacing {} from the sform",
                        num(raw),
                        NAMES[a],
                        num(from_s)
                    )),
                    _ => {}
                }
                from_s
            }
            (None, Some(p)) => p,
            (None, None) if n[a] == 1 => 1.0,
            (None, None) => {
                let col = (0..3)
                    .map(|r| h.srow_linear[r][a].powi(2))
                    .sum::<f64>()
                    .sqrt();
                if h.sform_code > 0 && col.is_finite() && col > 0.0 {
                    notes.push(format!(
                        "pixdim[{i}] = {} is not a valid spacing: {} spacing {} from the sform \
                         (the length of its column {i})",
                        num(raw),
                        NAMES[a],
                        flip::short(col)
                    ));
                    col
                } else {
                    notes.push(format!(
                        "pixdim[{i}] = {} is not a valid spacing and no sform gives one: {} \
                         spacing 1",
                        num(raw),
                        NAMES[a]
                    ));
                    1.0
                }
            }
        };
    }

    // The step of each axis along its own world axis, when the transform
    // only scales the axes; the translation.
    let qfac = if h.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
    let (steps, offset, what) = if sform {
        let rows: Vec<String> = h
            .srow_linear
            .iter()
            .map(|r| format!("[{} {} {}]", num(r[0]), num(r[1]), num(r[2])))
            .collect();
        let what = format!("sform (code {}) {}", h.sform_code, rows.join(" "));
        (sdiag, Some(h.srow_offset), what)
    } else if qform {
        let [b, c, d] = h.quatern;
        let what = format!(
            "qform (code {}) quaternion ({}, {}, {}){}",
            h.qform_code,
            num(b),
            num(c),
            num(d),
            if qfac < 0.0 { " with qfac -1" } else { "" }
        );
        let steps = quaternion_signs(h.quatern).map(|s| {
            let mut st = [0, 1, 2].map(|a| s[a] * sp[a]);
            st[2] *= qfac;
            st
        });
        (steps, Some(h.qoffset), what)
    } else {
        (None, None, String::new())
    };

    let mut flip = [false; 3];
    let mut origin = offset;
    match (steps, offset) {
        (Some(st), Some(mut o)) => {
            let mut said = Vec::new();
            for a in 0..3 {
                if st[a] < 0.0 && n[a] > 1 {
                    flip[2 - a] = true;
                    o[a] = flip::first_voxel(o[a], n[a], st[a]);
                    said.push((NAMES[a], num(st[a]), Some(o[a])));
                }
            }
            origin = Some(o);
            if !said.is_empty() {
                notes.push(format!("{what}: {}", flip::describe(&said)));
            }
        }
        (None, Some(_)) => notes.push(if sform {
            format!(
                "{what} rotates, shears or permutes the axes: not applied (spacing = pixdim, \
                 origin = sform translation)"
            )
        } else {
            format!("{what} rotates the axes: not applied (spacing = pixdim, origin = qoffset)")
        }),
        _ => {}
    }
    Geometry {
        spacing: [sp[2], sp[1], sp[0]],
        origin: origin.map(|[x, y, z]| [z, y, x]),
        flip,
        notes,
    }
}

/// The diagonal of `m` when `m` only scales each axis (off-diagonal
/// entries zero, up to float32 rounding: at most 1e-6 of the largest
/// entry), with no zero or non-finite entry.
fn diagonal(m: &[[f64; 3]; 3]) -> Option<[f64; 3]> {
    let big = m.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    if !big.is_finite() || big == 0.0 {
        return None;
    }
    let d = [m[0][0], m[1][1], m[2][2]];
    let off_zero = (0..3).all(|r| (0..3).all(|c| r == c || m[r][c].abs() <= 1e-6 * big));
    (off_zero && d.iter().all(|v| *v != 0.0)).then_some(d)
}

/// The signs (±1 for x, y, z) of the rotation of a NIfTI quaternion
/// `(b, c, d)` when it is a rotation by 0 or 180° about one axis (a
/// diagonal matrix), as `nifti_quatern_to_mat44` computes it.
fn quaternion_signs([b, c, d]: [f64; 3]) -> Option<[f64; 3]> {
    if ![b, c, d].iter().all(|v| v.is_finite()) {
        return None;
    }
    let aa = 1.0 - (b * b + c * c + d * d);
    let (a, b, c, d) = if aa < 1e-7 {
        // The standard's rule: a = 0 and (b, c, d) normalised.
        let s = (b * b + c * c + d * d).sqrt();
        (0.0, b / s, c / s, d / s)
    } else {
        (aa.sqrt(), b, c, d)
    };
    let r = [
        [
            a * a + b * b - c * c - d * d,
            2.0 * (b * c - a * d),
            2.0 * (b * d + a * c),
        ],
        [
            2.0 * (b * c + a * d),
            a * a + c * c - b * b - d * d,
            2.0 * (c * d - a * b),
        ],
        [
            2.0 * (b * d - a * c),
            2.0 * (c * d + a * b),
            a * a + d * d - c * c - b * b,
        ],
    ];
    diagonal(&r).map(|d| d.map(f64::signum))
}

/// The brickyard type of a NIfTI datatype code, or the name of the code.
fn dtype_from_code(code: i32) -> std::result::Result<DType, &'static str> {
    Ok(match code {
        2 => DType::U8,
        4 => DType::I16,
        8 => DType::I32,
        16 => DType::F32,
        64 => DType::F64,
        256 => DType::I8,
        512 => DType::U16,
        768 => DType::U32,
        0 => return Err("DT_UNKNOWN"),
        1 => return Err("binary"),
        32 => return Err("complex64"),
        128 => return Err("RGB24"),
        1024 => return Err("int64"),
        1280 => return Err("uint64"),
        1536 => return Err("float128"),
        1792 => return Err("complex128"),
        2048 => return Err("complex256"),
        2304 => return Err("RGBA32"),
        _ => return Err("unknown code"),
    })
}

/// The header file and, if `path` is the `.img` of a pair, the data file.
fn locate(path: &Path) -> Result<(PathBuf, Option<PathBuf>)> {
    let lower = path.to_string_lossy().to_ascii_lowercase();
    if lower.ends_with(".img") || lower.ends_with(".img.gz") {
        let hdr = companion(path, &HDR_EXTS).ok_or_else(|| {
            StoreError::io(
                path,
                io::Error::new(
                    io::ErrorKind::NotFound,
                    "no .hdr header file next to this .img file",
                ),
            )
        })?;
        Ok((hdr, Some(path.to_path_buf())))
    } else {
        Ok((path.to_path_buf(), None))
    }
}

/// The existing file with `path`'s stem (without `.hdr`/`.img`, `.nii`,
/// optionally followed by `.gz`) and one of `exts`.
fn companion(path: &Path, exts: &[&str]) -> Option<PathBuf> {
    let s = path.to_str()?;
    let lower = s.to_ascii_lowercase();
    let stem_len = [".hdr.gz", ".img.gz", ".nii.gz", ".hdr", ".img", ".nii"]
        .iter()
        .find(|e| lower.ends_with(*e))
        .map_or(s.len(), |e| s.len() - e.len());
    let stem = &s[..stem_len];
    exts.iter()
        .map(|e| PathBuf::from(format!("{stem}{e}")))
        .find(|p| p.is_file())
}

/// Read the first bytes of a header file (decompressing it if it is
/// gzip-compressed). Returns them and whether the file is compressed.
fn read_head(path: &Path) -> Result<(Vec<u8>, bool)> {
    let mut f = File::open(path).at(path)?;
    let head = read_up_to(&mut f, NIFTI2_HDR).at(path)?;
    if !head.starts_with(&GZ_MAGIC) {
        if path.to_string_lossy().to_ascii_lowercase().ends_with(".gz") {
            tracing::warn!(
                "{}: named .gz but not gzip-compressed; reading it as uncompressed",
                path.display()
            );
        }
        return Ok((head, false));
    }
    let f = File::open(path).at(path)?;
    let mut gz = MultiGzDecoder::new(BufReader::new(f));
    match read_up_to(&mut gz, NIFTI2_HDR) {
        Ok(head) => Ok((head, true)),
        Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => Err(StoreError::invalid(
            path,
            "gzip",
            format!("compressed stream ends inside the header (truncated file?): {e}"),
        )),
        Err(e)
            if matches!(
                e.kind(),
                io::ErrorKind::InvalidInput | io::ErrorKind::InvalidData
            ) =>
        {
            Err(StoreError::invalid(
                path,
                "gzip",
                format!("cannot decompress the header: {e}"),
            ))
        }
        Err(e) => Err(StoreError::io(path, e)),
    }
}

/// Read up to `n` bytes (fewer only at end of stream).
fn read_up_to(r: &mut impl Read, n: usize) -> io::Result<Vec<u8>> {
    let mut buf = Vec::with_capacity(n);
    r.take(n as u64).read_to_end(&mut buf)?;
    Ok(buf)
}

/// The header fields brickyard uses, widened to common types.
#[derive(Debug, Clone)]
struct Header {
    version: u8,
    big_endian: bool,
    /// Magic `ni1`/`ni2`: the voxels are in a separate `.img` file.
    pair: bool,
    dim: [i64; 8],
    datatype: i32,
    bitpix: i32,
    pixdim: [f64; 8],
    vox_offset: f64,
    scl_slope: f64,
    scl_inter: f64,
    xyzt_units: i32,
    intent_code: i32,
    qform_code: i32,
    sform_code: i32,
    /// `qoffset_x`, `qoffset_y`, `qoffset_z`.
    qoffset: [f64; 3],
    /// `srow_x[3]`, `srow_y[3]`, `srow_z[3]`.
    srow_offset: [f64; 3],
    /// The 3×3 linear part of the sform: row r is `srow_{x,y,z}[0..3]`.
    srow_linear: [[f64; 3]; 3],
    /// `quatern_b`, `quatern_c`, `quatern_d`.
    quatern: [f64; 3],
}

/// Endian-aware field access into a header buffer of checked length.
struct Fields<'a> {
    b: &'a [u8],
    be: bool,
}

macro_rules! field_getter {
    ($name:ident, $t:ty) => {
        fn $name(&self, off: usize) -> $t {
            const N: usize = std::mem::size_of::<$t>();
            let mut a = [0u8; N];
            a.copy_from_slice(&self.b[off..off + N]);
            if self.be {
                <$t>::from_be_bytes(a)
            } else {
                <$t>::from_le_bytes(a)
            }
        }
    };
}

impl Fields<'_> {
    field_getter!(i16, i16);
    field_getter!(i32, i32);
    field_getter!(i64, i64);
    field_getter!(f32, f32);
    field_getter!(f64, f64);
}

/// Parse a NIfTI-1 or NIfTI-2 header from the first bytes of a file.
fn parse_header(b: &[u8], path: &Path) -> Result<Header> {
    if b.len() < 4 {
        return Err(StoreError::invalid(
            path,
            "sizeof_hdr",
            format!(
                "file holds only {} bytes, too few for a NIfTI header",
                b.len()
            ),
        ));
    }
    let raw = [b[0], b[1], b[2], b[3]];
    let (le, be) = (i32::from_le_bytes(raw), i32::from_be_bytes(raw));
    let (version, big_endian, size) = match (le, be) {
        (348, _) => (1u8, false, NIFTI1_HDR),
        (540, _) => (2, false, NIFTI2_HDR),
        (_, 348) => (1, true, NIFTI1_HDR),
        (_, 540) => (2, true, NIFTI2_HDR),
        _ => {
            return Err(StoreError::invalid(
                path,
                "sizeof_hdr",
                format!(
                    "is {le} (byte-swapped {be}); expected 348 (NIfTI-1) or 540 (NIfTI-2) — \
                     not a NIfTI file?"
                ),
            ))
        }
    };
    if b.len() < size {
        return Err(StoreError::invalid(
            path,
            "sizeof_hdr",
            format!(
                "NIfTI-{version} header needs {size} bytes but the file holds only {}",
                b.len()
            ),
        ));
    }
    let magic = if version == 1 { &b[344..348] } else { &b[4..8] };
    let pair = match (magic[0], magic[1], magic[2], magic[3]) {
        (b'n', b'+', v, 0) if v == b'0' + version => false,
        (b'n', b'i', v, 0) if v == b'0' + version => true,
        (0, 0, 0, 0) if version == 1 => {
            return Err(StoreError::unsupported(
                path,
                "magic",
                "no NIfTI magic: an ANALYZE 7.5 header, which is not supported",
            ))
        }
        _ => {
            return Err(StoreError::invalid(
                path,
                "magic",
                format!(
                    "{:?} is not \"n+{version}\" or \"ni{version}\"",
                    String::from_utf8_lossy(magic)
                ),
            ))
        }
    };
    let f = Fields {
        b: &b[..size],
        be: big_endian,
    };
    let h = if version == 1 {
        Header {
            version,
            big_endian,
            pair,
            dim: std::array::from_fn(|i| f.i16(40 + 2 * i) as i64),
            datatype: f.i16(70) as i32,
            bitpix: f.i16(72) as i32,
            pixdim: std::array::from_fn(|i| f.f32(76 + 4 * i) as f64),
            vox_offset: f.f32(108) as f64,
            scl_slope: f.f32(112) as f64,
            scl_inter: f.f32(116) as f64,
            xyzt_units: b[123] as i32,
            intent_code: f.i16(68) as i32,
            qform_code: f.i16(252) as i32,
            sform_code: f.i16(254) as i32,
            qoffset: std::array::from_fn(|i| f.f32(268 + 4 * i) as f64),
            srow_offset: std::array::from_fn(|i| f.f32(292 + 16 * i) as f64),
            srow_linear: std::array::from_fn(|r| {
                std::array::from_fn(|c| f.f32(280 + 16 * r + 4 * c) as f64)
            }),
            quatern: std::array::from_fn(|i| f.f32(256 + 4 * i) as f64),
        }
    } else {
        Header {
            version,
            big_endian,
            pair,
            dim: std::array::from_fn(|i| f.i64(16 + 8 * i)),
            datatype: f.i16(12) as i32,
            bitpix: f.i16(14) as i32,
            pixdim: std::array::from_fn(|i| f.f64(104 + 8 * i)),
            vox_offset: f.i64(168) as f64,
            scl_slope: f.f64(176),
            scl_inter: f.f64(184),
            xyzt_units: f.i32(500),
            intent_code: f.i32(504),
            qform_code: f.i32(344),
            sform_code: f.i32(348),
            qoffset: std::array::from_fn(|i| f.f64(376 + 8 * i)),
            srow_offset: std::array::from_fn(|i| f.f64(424 + 32 * i)),
            srow_linear: std::array::from_fn(|r| {
                std::array::from_fn(|c| f.f64(400 + 32 * r + 8 * c))
            }),
            quatern: std::array::from_fn(|i| f.f64(352 + 8 * i)),
        }
    };
    Ok(h)
}

/// The byte runs of a region of one channel, in file order: `(file offset,
/// range in the output buffer)`. Rows adjacent in the file are merged.
fn contiguous_runs(
    base: u64,
    dims: Dims3,
    size: u64,
    z: &Range<u64>,
    y: &Range<u64>,
    x: &Range<u64>,
) -> Vec<(u64, Range<usize>)> {
    let row = ((x.end - x.start) * size) as usize;
    let mut runs: Vec<(u64, Range<usize>)> = Vec::new();
    let mut out_pos = 0usize;
    for zz in z.clone() {
        for yy in y.clone() {
            let off = base + ((zz * dims[1] + yy) * dims[2] + x.start) * size;
            match runs.last_mut() {
                Some((o, r)) if *o + r.len() as u64 == off => r.end += row,
                _ => runs.push((off, out_pos..out_pos + row)),
            }
            out_pos += row;
        }
    }
    runs
}

/// Fill `buf` from `file` at byte `offset`.
#[cfg(unix)]
fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
}

/// Fill `buf` from `file` at byte `offset`.
#[cfg(windows)]
fn read_exact_at(file: &File, mut buf: &mut [u8], mut offset: u64) -> io::Result<()> {
    use std::os::windows::fs::FileExt;
    while !buf.is_empty() {
        match file.seek_read(buf, offset) {
            Ok(0) => return Err(io::ErrorKind::UnexpectedEof.into()),
            Ok(n) => {
                buf = &mut buf[n..];
                offset += n as u64;
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// A position in the decompressed stream of a gzip file.
struct GzCursor {
    reader: MultiGzDecoder<BufReader<File>>,
    /// Decompressed bytes consumed so far.
    pos: u64,
    last_use: u64,
}

impl GzCursor {
    fn open(path: &Path) -> Result<Self> {
        let f = File::open(path).at(path)?;
        Ok(GzCursor {
            reader: MultiGzDecoder::new(BufReader::with_capacity(SKIP_CHUNK, f)),
            pos: 0,
            last_use: 0,
        })
    }

    /// Decompress and discard up to `target`. `Ok(false)` at end of stream.
    fn skip_to(&mut self, target: u64, scratch: &mut [u8]) -> io::Result<bool> {
        while self.pos < target {
            let n = (target - self.pos).min(scratch.len() as u64) as usize;
            let got = self.read_fully(&mut scratch[..n])?;
            if got < n {
                return Ok(false);
            }
        }
        Ok(true)
    }

    /// Decompress to the end of the stream (the gzip trailer's checks run
    /// there), whatever follows the voxels.
    fn drain(&mut self, scratch: &mut [u8]) -> io::Result<()> {
        while self.read_fully(scratch)? == scratch.len() {}
        Ok(())
    }

    /// Fill `buf`; returns fewer bytes than asked only at end of stream.
    fn read_fully(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let mut done = 0;
        while done < buf.len() {
            match self.reader.read(&mut buf[done..]) {
                Ok(0) => break,
                Ok(n) => {
                    done += n;
                    self.pos += n as u64;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(done)
    }
}

/// The gzip cursors of one source.
struct GzPool {
    cursors: Vec<GzCursor>,
    max: usize,
    tick: u64,
    scratch: Vec<u8>,
}

impl GzPool {
    /// Take the cursor nearest before `target`, opening a new one (and
    /// dropping the least recently used) if every cursor is past it.
    fn take(&mut self, path: &Path, target: u64) -> Result<GzCursor> {
        self.tick += 1;
        let best = (0..self.cursors.len())
            .filter(|&i| self.cursors[i].pos <= target)
            .max_by_key(|&i| self.cursors[i].pos);
        if let Some(i) = best {
            return Ok(self.cursors.swap_remove(i));
        }
        if self.cursors.len() >= self.max {
            if let Some(i) = (0..self.cursors.len()).min_by_key(|&i| self.cursors[i].last_use) {
                self.cursors.swap_remove(i);
            }
        }
        GzCursor::open(path)
    }

    /// Return a cursor after a successful read (a failed one is dropped).
    fn put(&mut self, mut cur: GzCursor) {
        cur.last_use = self.tick;
        self.cursors.push(cur);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::test_util::{read_all, read_stitched};
    use flate2::write::GzEncoder;
    use std::io::Write;

    fn shared(name: &str) -> PathBuf {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../../shared/data")
            .join(name);
        assert!(
            p.is_file(),
            "the shared data folder is missing: {} not found (tests need ../shared/data/ next to \
             the project root)",
            p.display()
        );
        p
    }

    #[test]
    fn colin27_real_file() {
        let path = shared("colin27-t1-0.5mm.nii.gz");
        let src = open(&path).unwrap();
        let m = src.meta();
        assert_eq!(m.dims, [316, 370, 301]);
        assert_eq!(m.channels, 1);
        assert_eq!(m.dtype, DType::U8);
        assert_eq!(m.spacing, Some([0.5, 0.5, 0.5]));
        assert_eq!(m.origin, Some([-69.5, -107.0, -75.0]));
        assert_eq!(
            m.unit.as_deref(),
            Some("millimeter"),
            "xyzt_units 0 with an sform"
        );
        assert_eq!(m.notes.len(), 1, "{:?}", m.notes);
        assert!(m.notes[0].contains("millimetres assumed"));
        assert_eq!(m.scaling, None);
        assert_eq!(src.version(), 1);
        assert!(src.is_gzip());
        assert_eq!(src.scale, None);

        let whole = read_all(&src, 0);
        assert!(whole.iter().all(|&v| v <= 130));
        assert_eq!(whole.iter().copied().max(), Some(130));

        // Independent decode: inflate the whole file, index from vox_offset.
        let mut raw = Vec::new();
        flate2::read::GzDecoder::new(File::open(&path).unwrap())
            .read_to_end(&mut raw)
            .unwrap();
        let vox = f32::from_le_bytes(raw[108..112].try_into().unwrap()) as usize;
        assert_eq!(raw.len() - vox, whole.len());
        assert!(
            whole == raw[vox..],
            "whole read differs from an independent decode"
        );
        let slice = 370 * 301;
        for z in [0u64, 157, 315] {
            let mut s = vec![0u8; slice];
            src.read_region(0, z..z + 1, 0..370, 0..301, &mut s)
                .unwrap();
            let o = vox + z as usize * slice;
            assert!(s == raw[o..o + slice], "slice {z} differs");
        }

        let stitched = read_stitched(&src, 0, [120, 200, 160]);
        assert!(
            stitched == whole,
            "stitched sub-region reads differ from the whole read"
        );
    }

    /// Description of a synthetic NIfTI header.
    #[derive(Clone)]
    struct Synth {
        version: u8,
        be: bool,
        dims: Vec<i64>,
        datatype: i16,
        bitpix: i16,
        pixdim: [f64; 3],
        units: u8,
        vox_offset: u64,
        sform: Option<[f64; 3]>,
        qoffset: Option<[f64; 3]>,
        slope: f64,
        inter: f64,
        intent: i32,
        pair: bool,
    }

    impl Default for Synth {
        fn default() -> Self {
            Synth {
                version: 1,
                be: false,
                dims: vec![5, 4, 3],
                datatype: 4,
                bitpix: 16,
                pixdim: [0.8, 0.9, 2.5],
                units: 2,
                vox_offset: 352,
                sform: None,
                qoffset: None,
                slope: 0.0,
                inter: 0.0,
                intent: 0,
                pair: false,
            }
        }
    }

    struct Put<'a> {
        b: &'a mut Vec<u8>,
        be: bool,
    }

    macro_rules! putter {
        ($name:ident, $t:ty) => {
            fn $name(&mut self, off: usize, v: $t) {
                let a = if self.be {
                    v.to_be_bytes()
                } else {
                    v.to_le_bytes()
                };
                self.b[off..off + a.len()].copy_from_slice(&a);
            }
        };
    }

    impl Put<'_> {
        putter!(i16, i16);
        putter!(i32, i32);
        putter!(i64, i64);
        putter!(f32, f32);
        putter!(f64, f64);
    }

    /// Header bytes, padded with zeros up to `vox_offset` for single files.
    fn header(s: &Synth) -> Vec<u8> {
        let n = if s.version == 1 {
            NIFTI1_HDR
        } else {
            NIFTI2_HDR
        };
        let mut b = vec![0u8; n];
        let mut p = Put {
            b: &mut b,
            be: s.be,
        };
        let mut dim = [1i64; 8];
        dim[0] = s.dims.len() as i64;
        dim[1..=s.dims.len()].copy_from_slice(&s.dims);
        let pix = [
            1.0,
            s.pixdim[0],
            s.pixdim[1],
            s.pixdim[2],
            1.0,
            0.0,
            0.0,
            0.0,
        ];
        let magic: &[u8] = match (s.version, s.pair) {
            (1, false) => b"n+1\0",
            (1, true) => b"ni1\0",
            (_, false) => b"n+2\0\r\n\x1a\n",
            (_, true) => b"ni2\0\r\n\x1a\n",
        };
        if s.version == 1 {
            p.i32(0, 348);
            for (i, d) in dim.iter().enumerate() {
                p.i16(40 + 2 * i, *d as i16);
            }
            p.i16(68, s.intent as i16);
            p.i16(70, s.datatype);
            p.i16(72, s.bitpix);
            for (i, v) in pix.iter().enumerate() {
                p.f32(76 + 4 * i, *v as f32);
            }
            p.f32(108, s.vox_offset as f32);
            p.f32(112, s.slope as f32);
            p.f32(116, s.inter as f32);
            p.b[123] = s.units;
            if let Some(q) = s.qoffset {
                p.i16(252, 1);
                for (i, v) in q.iter().enumerate() {
                    p.f32(268 + 4 * i, *v as f32);
                }
            }
            if let Some(t) = s.sform {
                p.i16(254, 2);
                for (i, v) in t.iter().enumerate() {
                    p.f32(280 + 16 * i + 4 * i, s.pixdim[i] as f32); // diagonal
                    p.f32(292 + 16 * i, *v as f32);
                }
            }
            p.b[344..348].copy_from_slice(magic);
        } else {
            p.i32(0, 540);
            p.b[4..12].copy_from_slice(magic);
            p.i16(12, s.datatype);
            p.i16(14, s.bitpix);
            for (i, d) in dim.iter().enumerate() {
                p.i64(16 + 8 * i, *d);
            }
            for (i, v) in pix.iter().enumerate() {
                p.f64(104 + 8 * i, *v);
            }
            p.i64(168, s.vox_offset as i64);
            p.f64(176, s.slope);
            p.f64(184, s.inter);
            if let Some(q) = s.qoffset {
                p.i32(344, 1);
                for (i, v) in q.iter().enumerate() {
                    p.f64(376 + 8 * i, *v);
                }
            }
            if let Some(t) = s.sform {
                p.i32(348, 2);
                for (i, v) in t.iter().enumerate() {
                    p.f64(400 + 32 * i + 8 * i, s.pixdim[i]);
                    p.f64(424 + 32 * i, *v);
                }
            }
            p.i32(500, s.units as i32);
            p.i32(504, s.intent);
        }
        if !s.pair {
            b.resize(s.vox_offset as usize, 0);
        }
        b
    }

    fn i16_bytes(v: &[i16], be: bool) -> Vec<u8> {
        v.iter()
            .flat_map(|x| if be { x.to_be_bytes() } else { x.to_le_bytes() })
            .collect()
    }

    fn f32_bytes(v: &[f32], be: bool) -> Vec<u8> {
        v.iter()
            .flat_map(|x| if be { x.to_be_bytes() } else { x.to_le_bytes() })
            .collect()
    }

    fn ne_i16(v: &[i16]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_ne_bytes()).collect()
    }

    fn gzip(b: &[u8]) -> Vec<u8> {
        let mut e = GzEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(b).unwrap();
        e.finish().unwrap()
    }

    fn ramp_i16(n: usize) -> Vec<i16> {
        (0..n).map(|i| (i as i32 * 37 - 20000) as i16).collect()
    }

    fn check_i16(be: bool) {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            be,
            sform: Some([10.0, -20.0, 30.5]),
            qoffset: Some([1.0, 2.0, 3.0]),
            ..Default::default()
        };
        let vals = ramp_i16(5 * 4 * 3);
        let mut file = header(&s);
        file.extend(i16_bytes(&vals, be));
        let path = dir.path().join(if be { "be.nii" } else { "le.nii" });
        std::fs::write(&path, &file).unwrap();

        let src = open(&path).unwrap();
        let m = src.meta();
        assert_eq!(m.dims, [3, 4, 5]);
        assert_eq!(m.channels, 1);
        assert_eq!(m.dtype, DType::I16);
        let sp = m.spacing.unwrap();
        assert!(
            (sp[0] - 2.5).abs() < 1e-6 && (sp[1] - 0.9).abs() < 1e-6 && (sp[2] - 0.8).abs() < 1e-6
        );
        assert_eq!(m.unit.as_deref(), Some("millimeter"));
        assert_eq!(m.origin, Some([30.5, -20.0, 10.0]), "sform wins over qform");
        assert!(!src.is_gzip());
        assert_eq!(read_all(&src, 0), ne_i16(&vals));
        assert_eq!(read_stitched(&src, 0, [2, 3, 2]), ne_i16(&vals));

        // One voxel: z=2, y=1, x=3.
        let mut one = [0u8; 2];
        src.read_region(0, 2..3, 1..2, 3..4, &mut one).unwrap();
        assert_eq!(i16::from_ne_bytes(one), vals[(2 * 4 + 1) * 5 + 3]);
    }

    #[test]
    fn nifti1_little_endian_i16() {
        check_i16(false);
    }

    #[test]
    fn nifti1_big_endian_i16() {
        check_i16(true);
    }

    #[test]
    fn nifti2_f32_with_qform_origin_and_scale() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            version: 2,
            dims: vec![6, 5, 4],
            datatype: 16,
            bitpix: 32,
            vox_offset: 544,
            units: 3,
            qoffset: Some([1.5, 2.5, 3.5]),
            slope: 2.0,
            inter: -1.0,
            ..Default::default()
        };
        let vals: Vec<f32> = (0..120).map(|i| i as f32 * 0.25 - 7.0).collect();
        for be in [false, true] {
            let mut file = header(&Synth { be, ..s.clone() });
            file.extend(f32_bytes(&vals, be));
            let path = dir.path().join(format!("n2-{be}.nii"));
            std::fs::write(&path, &file).unwrap();
            let src = open(&path).unwrap();
            assert_eq!(src.version(), 2);
            let m = src.meta();
            assert_eq!(m.dims, [4, 5, 6]);
            assert_eq!(m.dtype, DType::F32);
            assert_eq!(m.unit.as_deref(), Some("micrometer"));
            assert_eq!(m.origin, Some([3.5, 2.5, 1.5]));
            assert_eq!(src.scale, Some((2.0, -1.0)));
            let got = read_all(&src, 0);
            let want: Vec<u8> = vals
                .iter()
                .flat_map(|v| ((*v as f64 * 2.0 - 1.0) as f32).to_ne_bytes())
                .collect();
            assert_eq!(got, want, "values are rescaled: 2 · stored − 1");
            assert_eq!(read_stitched(&src, 0, [3, 2, 4]), want);
            let raw = open_with(&path, true).unwrap();
            let want: Vec<u8> = vals.iter().flat_map(|v| v.to_ne_bytes()).collect();
            assert_eq!(read_all(&raw, 0), want, "raw values: as stored");
        }
    }

    /// Write a one-file NIfTI-1 with `slope`/`inter` over `data` bytes.
    fn scaled_file(dir: &Path, name: &str, s: Synth, data: Vec<u8>) -> PathBuf {
        let mut file = header(&s);
        file.extend(data);
        let p = dir.join(name);
        if name.ends_with(".gz") {
            std::fs::write(&p, gzip(&file)).unwrap();
        } else {
            std::fs::write(&p, &file).unwrap();
        }
        p
    }

    fn from_ne<T: Copy, const N: usize>(b: &[u8], f: fn([u8; N]) -> T) -> Vec<T> {
        b.chunks_exact(N)
            .map(|c| f(c.try_into().unwrap()))
            .collect()
    }

    /// int16 CT: Hounsfield units = stored − 1024. The stored numbers
    /// (0..4095) shifted fit int16, so int16 is kept; with raw values the
    /// stored numbers come back.
    #[test]
    fn ct_int16_intercept_keeps_int16() {
        let dir = tempfile::tempdir().unwrap();
        let dims = vec![9i64, 7, 5];
        let n = 9 * 7 * 5;
        let stored: Vec<i16> = (0..n).map(|i| (i * 97 % 4096) as i16).collect();
        for (be, gz) in [(false, false), (true, false), (false, true)] {
            let s = Synth {
                be,
                dims: dims.clone(),
                slope: 1.0,
                inter: -1024.0,
                ..Default::default()
            };
            let name = format!("ct-{be}.nii{}", if gz { ".gz" } else { "" });
            let p = scaled_file(dir.path(), &name, s, i16_bytes(&stored, be));
            let src = open(&p).unwrap();
            let m = src.meta();
            assert_eq!(m.dtype, DType::I16, "int16 kept");
            let sc = m.scaling.clone().unwrap();
            assert!(sc.applied);
            assert_eq!((sc.slope, sc.inter), (1.0, -1024.0));
            let max = *stored.iter().max().unwrap();
            assert_eq!(sc.scanned, Some([0.0, max as f64]));
            assert_eq!(
                m.notes,
                vec![format!(
                    "values scaled by scl_slope=1, scl_inter=-1024 (int16 kept; stored numbers \
                     span 0..{max})"
                )]
            );
            let want: Vec<i16> = stored.iter().map(|v| v - 1024).collect();
            assert_eq!(from_ne(&read_all(&src, 0), i16::from_ne_bytes), want);
            assert_eq!(
                from_ne(&read_stitched(&src, 0, [2, 3, 4]), i16::from_ne_bytes),
                want
            );

            let raw = open_with(&p, true).unwrap();
            assert_eq!(raw.meta().dtype, DType::I16);
            assert!(!raw.meta().scaling.as_ref().unwrap().applied);
            assert!(raw.meta().notes[0].contains("not applied"));
            assert_eq!(read_all(&raw, 0), ne_i16(&stored));
        }
    }

    /// Stored numbers over the whole int16 range minus 1024 need int32.
    #[test]
    fn int16_full_range_widens_to_int32() {
        let dir = tempfile::tempdir().unwrap();
        let stored: Vec<i16> = vec![i16::MIN, -1, 0, 1, i16::MAX, 5];
        let s = Synth {
            dims: vec![3, 2, 1],
            slope: 1.0,
            inter: -1024.0,
            ..Default::default()
        };
        let p = scaled_file(dir.path(), "wide.nii", s, i16_bytes(&stored, false));
        let src = open(&p).unwrap();
        assert_eq!(src.meta().dtype, DType::I32);
        let want: Vec<i32> = stored.iter().map(|&v| v as i32 - 1024).collect();
        assert_eq!(from_ne(&read_all(&src, 0), i32::from_ne_bytes), want);
    }

    /// uint8 with intercept −1024 becomes int16 (exact); uint8 plus 10
    /// stays uint8 when the stored numbers leave room.
    #[test]
    fn uint8_widened_or_kept() {
        let dir = tempfile::tempdir().unwrap();
        let stored: Vec<u8> = (0..60).map(|i| (i * 3) as u8).collect();
        let u8s = |slope: f64, inter: f64| Synth {
            datatype: 2,
            bitpix: 8,
            slope,
            inter,
            ..Default::default()
        };
        let p = scaled_file(dir.path(), "u8a.nii", u8s(2.0, -1024.0), stored.clone());
        let src = open(&p).unwrap();
        assert_eq!(src.meta().dtype, DType::I16);
        assert_eq!(
            src.meta().scaling.as_ref().unwrap().scanned,
            None,
            "no stored number fits uint8 after −1024: int16 without a scan"
        );
        let want: Vec<i16> = stored.iter().map(|&v| v as i16 * 2 - 1024).collect();
        assert_eq!(from_ne(&read_all(&src, 0), i16::from_ne_bytes), want);
        assert!(
            src.meta().notes[0].contains("(uint8 → int16, exact)"),
            "{:?}",
            src.meta().notes
        );

        let p = scaled_file(dir.path(), "u8b.nii", u8s(1.0, 10.0), stored.clone());
        let src = open(&p).unwrap();
        assert_eq!(src.meta().dtype, DType::U8);
        let want: Vec<u8> = stored.iter().map(|&v| v + 10).collect();
        assert_eq!(read_all(&src, 0), want);
    }

    /// A fractional slope or intercept makes float32 values.
    #[test]
    fn fractional_scale_makes_float32() {
        let dir = tempfile::tempdir().unwrap();
        let stored = ramp_i16(60);
        let s = Synth {
            slope: 0.5,
            inter: 3.25,
            ..Default::default()
        };
        let p = scaled_file(dir.path(), "frac.nii.gz", s, i16_bytes(&stored, false));
        let src = open(&p).unwrap();
        assert_eq!(src.meta().dtype, DType::F32);
        assert_eq!(src.meta().scaling.as_ref().unwrap().scanned, None);
        assert_eq!(
            src.meta().notes,
            vec!["values scaled by scl_slope=0.5, scl_inter=3.25 (int16 → float32)".to_string()]
        );
        let want: Vec<f32> = stored.iter().map(|&v| v as f32 * 0.5 + 3.25).collect();
        assert_eq!(from_ne(&read_all(&src, 0), f32::from_ne_bytes), want);
        assert_eq!(
            from_ne(&read_stitched(&src, 0, [1, 3, 2]), f32::from_ne_bytes),
            want
        );
        let raw = open_with(&p, true).unwrap();
        assert_eq!(raw.meta().dtype, DType::I16);
        assert_eq!(read_all(&raw, 0), ne_i16(&stored));
    }

    /// A slope of 0 (or not finite) means no scaling; so does (1, 0).
    #[test]
    fn slope_zero_nan_and_identity_mean_no_scaling() {
        let dir = tempfile::tempdir().unwrap();
        let stored = ramp_i16(60);
        for (k, (slope, inter)) in [(0.0, -1024.0), (f64::NAN, 5.0), (1.0, 0.0)]
            .into_iter()
            .enumerate()
        {
            let s = Synth {
                slope,
                inter,
                ..Default::default()
            };
            let p = scaled_file(
                dir.path(),
                &format!("n{k}.nii"),
                s,
                i16_bytes(&stored, false),
            );
            let src = open(&p).unwrap();
            assert_eq!(src.scale, None, "slope {slope}, inter {inter}");
            assert_eq!(src.meta().scaling, None);
            assert!(src.meta().notes.is_empty());
            assert_eq!(src.meta().dtype, DType::I16);
            assert_eq!(read_all(&src, 0), ne_i16(&stored));
        }
    }

    /// A valid slope with an intercept that is not finite cannot be applied
    /// (nibabel refuses it too); raw values still read.
    #[test]
    fn non_finite_intercept_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            slope: 2.0,
            inter: f64::NAN,
            ..Default::default()
        };
        let p = scaled_file(
            dir.path(),
            "naninter.nii",
            s,
            i16_bytes(&ramp_i16(60), false),
        );
        assert_err(open(&p), "naninter.nii", "scl_inter");
        assert_eq!(
            read_all(&open_with(&p, true).unwrap(), 0),
            ne_i16(&ramp_i16(60))
        );
    }

    /// 4-D data: the stored range is scanned over every channel.
    #[test]
    fn scan_covers_every_channel() {
        let dir = tempfile::tempdir().unwrap();
        let n = 5 * 4 * 3;
        let mut stored: Vec<i16> = vec![100; n * 2];
        stored[n + 7] = i16::MIN; // only channel 1 overflows int16 after −1024
        let s = Synth {
            dims: vec![5, 4, 3, 2],
            slope: 1.0,
            inter: -1024.0,
            ..Default::default()
        };
        let p = scaled_file(dir.path(), "4d.nii", s, i16_bytes(&stored, false));
        let src = open(&p).unwrap();
        assert_eq!(src.meta().channels, 2);
        assert_eq!(src.meta().dtype, DType::I32);
        let got = from_ne(&read_all(&src, 1), i32::from_ne_bytes);
        assert_eq!(got[7], i16::MIN as i32 - 1024);
        assert_eq!(got[0], 100 - 1024);
    }

    /// A sform or qform that only scales the axes adds no note; one that
    /// rotates or shears them is not applied, and the report says so.
    #[test]
    fn orientation_notes() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            sform: Some([1.0, 2.0, 3.0]),
            ..Default::default()
        };
        let vals = ramp_i16(60);
        let data = i16_bytes(&vals, false);
        let mut file = header(&s);
        file.extend(&data);
        let p = write(dir.path(), "plain.nii", &file);
        assert!(open(&p).unwrap().meta().notes.is_empty());
        file[284..288].copy_from_slice(&0.3f32.to_le_bytes()); // srow_x[1]: a shear
        let p = write(dir.path(), "shear.nii", &file);
        let src = open(&p).unwrap();
        assert_eq!(src.meta().origin, Some([3.0, 2.0, 1.0]));
        assert_eq!(src.meta().spacing.unwrap()[2] as f32, 0.8, "pixdim");
        assert_eq!(src.meta().notes.len(), 1);
        assert!(
            src.meta().notes[0]
                .starts_with("sform (code 2) [0.8 0.3 0] [0 0.9 0] [0 0 2.5] rotates"),
            "{:?}",
            src.meta().notes
        );
        assert!(src.meta().notes[0].contains("not applied"));
        assert_eq!(read_all(&src, 0), ne_i16(&vals), "as stored");

        let s = Synth {
            qoffset: Some([1.0, 2.0, 3.0]),
            ..Default::default()
        };
        let mut file = header(&s);
        file.extend(&data);
        let p = write(dir.path(), "q.nii", &file);
        assert!(open(&p).unwrap().meta().notes.is_empty());
        file[256..260].copy_from_slice(&0.5f32.to_le_bytes()); // quatern_b
        let p = write(dir.path(), "qrot.nii", &file);
        let src = open(&p).unwrap();
        let n = src.meta().notes.clone();
        assert!(
            n[0].starts_with("qform (code 1) quaternion (0.5, 0, 0) rotates"),
            "{n:?}"
        );
        assert_eq!(src.meta().origin, Some([3.0, 2.0, 1.0]));
        assert_eq!(read_all(&src, 0), ne_i16(&vals), "as stored");
    }

    /// The 4×4 affine of a NIfTI-1 header's sform (sform_code > 0) or else
    /// qform, computed here from the header bytes as the standard defines
    /// it (nibabel's `get_best_affine`).
    fn affine_of(b: &[u8]) -> [[f64; 4]; 3] {
        let f = |o: usize| f32::from_le_bytes(b[o..o + 4].try_into().unwrap()) as f64;
        if i16::from_le_bytes([b[254], b[255]]) > 0 {
            return std::array::from_fn(|r| std::array::from_fn(|c| f(280 + 16 * r + 4 * c)));
        }
        let (qb, qc, qd) = (f(256), f(260), f(264));
        let qa = (1.0 - qb * qb - qc * qc - qd * qd).max(0.0).sqrt();
        let rot = [
            [
                qa * qa + qb * qb - qc * qc - qd * qd,
                2.0 * (qb * qc - qa * qd),
                2.0 * (qb * qd + qa * qc),
            ],
            [
                2.0 * (qb * qc + qa * qd),
                qa * qa + qc * qc - qb * qb - qd * qd,
                2.0 * (qc * qd - qa * qb),
            ],
            [
                2.0 * (qb * qd - qa * qc),
                2.0 * (qc * qd + qa * qb),
                qa * qa + qd * qd - qc * qc - qb * qb,
            ],
        ];
        let qfac = if f(76) < 0.0 { -1.0 } else { 1.0 };
        let zoom = [f(80), f(84), f(88) * qfac];
        std::array::from_fn(|r| {
            let mut row = [0.0; 4];
            for c in 0..3 {
                row[c] = rot[r][c] * zoom[c];
            }
            row[3] = f(268 + 4 * r);
            row
        })
    }

    /// World position (x, y, z) of file voxel (i, j, k) by `affine`.
    fn world(a: &[[f64; 4]; 3], ijk: [u64; 3]) -> [f64; 3] {
        std::array::from_fn(|r| (0..3).map(|c| a[r][c] * ijk[c] as f64).sum::<f64>() + a[r][3])
    }

    /// A file whose axes run against the world's is read with them
    /// reversed: the voxel at the reversed index is the file's, and the
    /// store's scale and translation put every voxel where the file's
    /// affine does. `flips` are the reversed axes `[x, y, z]` expected.
    fn check_reversed(file: &[u8], dims: [u64; 3], vals: &[i16], flips: [bool; 3]) {
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "f.nii", file);
        let src = open(&p).unwrap();
        let m = src.meta();
        let [nx, ny, nz] = dims;
        assert_eq!(m.dims, [nz, ny, nx]);
        let names = ["x", "y", "z"];
        for (a, name) in names.iter().enumerate() {
            let said = m
                .notes
                .iter()
                .any(|n| n.contains(&format!("{name} runs against the file's direction")));
            assert_eq!(said, flips[a], "axis {name}: {:?}", m.notes);
        }
        // Values.
        let got = read_all(&src, 0);
        let got: Vec<i16> = from_ne(&got, i16::from_ne_bytes);
        let idx = |i: u64, j: u64, k: u64| ((k * ny + j) * nx + i) as usize;
        let m_ = |a: usize, v: u64| if flips[a] { dims[a] - 1 - v } else { v };
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    assert_eq!(
                        got[idx(i, j, k)],
                        vals[idx(m_(0, i), m_(1, j), m_(2, k))],
                        "store voxel x={i} y={j} z={k}"
                    );
                }
            }
        }
        assert_eq!(read_stitched(&src, 0, [2, 3, 4]), read_all(&src, 0));
        // World positions.
        let aff = affine_of(file);
        let (sp, o) = (m.spacing.unwrap(), m.origin.unwrap());
        for f in [
            [0, 0, 0],
            [nx - 1, ny - 1, nz - 1],
            [1, ny - 1, 0],
            [nx / 2, 1, nz - 1],
        ] {
            let want = world(&aff, f);
            let store = [m_(0, f[0]), m_(1, f[1]), m_(2, f[2])];
            for a in 0..3 {
                let got = o[2 - a] + sp[2 - a] * store[a] as f64;
                assert!(
                    (got - want[a]).abs() < 1e-4,
                    "file voxel {f:?}: {} = {got} in the store, {} in the file",
                    names[a],
                    want[a]
                );
            }
        }
    }

    /// The LAS file of the user trial: a diagonal sform with a negative x
    /// (`A = diag(-1.5, 1.5, 1.5)`, translation (50, -20, -10)).
    #[test]
    fn negative_sform_axis_is_read_reversed() {
        let s = Synth {
            dims: vec![30, 20, 10],
            pixdim: [1.5, 1.5, 1.5],
            sform: Some([50.0, -20.0, -10.0]),
            ..Default::default()
        };
        let vals = ramp_i16(6000);
        let mut file = header(&s);
        file[280..284].copy_from_slice(&(-1.5f32).to_le_bytes()); // srow_x[0]
        file.extend(i16_bytes(&vals, false));
        check_reversed(&file, [30, 20, 10], &vals, [true, false, false]);
        let src = open(&write(tempfile::tempdir().unwrap().path(), "a.nii", &file)).unwrap();
        let m = src.meta();
        assert_eq!(m.origin, Some([-10.0, -20.0, 6.5]), "50 + 29 · -1.5");
        assert_eq!(m.spacing, Some([1.5, 1.5, 1.5]));
        assert_eq!(m.notes.len(), 1, "{:?}", m.notes);
        assert!(
            m.notes[0].starts_with(
                "sform (code 2) [-1.5 0 0] [0 1.5 0] [0 0 1.5]: x runs against the file's \
                 direction -1.5: stored reversed so that it runs along +x (translation 6.5"
            ),
            "{:?}",
            m.notes
        );

        // Every axis backwards, in a NIfTI-2 file.
        let s2 = Synth {
            version: 2,
            vox_offset: 544,
            ..s.clone()
        };
        let mut file = header(&s2);
        for i in 0..3 {
            let o = 400 + 32 * i + 8 * i;
            file[o..o + 8].copy_from_slice(&(-1.5f64).to_le_bytes());
        }
        file.extend(i16_bytes(&vals, false));
        let dir = tempfile::tempdir().unwrap();
        let src = open(&write(dir.path(), "n2.nii", &file)).unwrap();
        assert_eq!(src.meta().origin, Some([-23.5, -48.5, 6.5]));
        let got: Vec<i16> = from_ne(&read_all(&src, 0), i16::from_ne_bytes);
        let rev: Vec<i16> = vals.iter().rev().copied().collect();
        assert_eq!(
            got, rev,
            "all three axes reversed: the whole volume backwards"
        );
    }

    /// The qform: qfac −1 (pixdim[0] < 0) flips z; quaternions of 180°
    /// turns about an axis flip the other two.
    #[test]
    fn qform_flips_are_read_reversed() {
        let s = Synth {
            qoffset: Some([1.0, 2.0, 3.0]),
            ..Default::default()
        };
        let vals = ramp_i16(60);
        let cases: [([f32; 3], f32, [bool; 3]); 4] = [
            ([0.0, 0.0, 0.0], -1.0, [false, false, true]),
            ([0.0, 1.0, 0.0], 1.0, [true, false, true]),
            ([0.0, 1.0, 0.0], -1.0, [true, false, false]),
            ([1.0, 0.0, 0.0], 1.0, [false, true, true]),
        ];
        for (quat, qfac, flips) in cases {
            let mut file = header(&s);
            for (i, q) in quat.iter().enumerate() {
                file[256 + 4 * i..260 + 4 * i].copy_from_slice(&q.to_le_bytes());
            }
            file[76..80].copy_from_slice(&qfac.to_le_bytes());
            file.extend(i16_bytes(&vals, false));
            check_reversed(&file, [5, 4, 3], &vals, flips);
        }
        // qfac −1 alone: z from 3 down by 2.5 per slice, so slice 2 at -2.
        let mut file = header(&s);
        file[76..80].copy_from_slice(&(-1.0f32).to_le_bytes());
        file.extend(i16_bytes(&vals, false));
        let dir = tempfile::tempdir().unwrap();
        let src = open(&write(dir.path(), "q.nii", &file)).unwrap();
        assert_eq!(src.meta().origin.unwrap()[0] as f32, -2.0);
        assert!(
            src.meta().notes[0].starts_with("qform (code 1) quaternion (0, 0, 0) with qfac -1: z"),
            "{:?}",
            src.meta().notes
        );
    }

    /// Reversal keeps channels (4-D), the rescale and gzip: each channel of
    /// a file with y backwards is the same file's forward channel reversed.
    #[test]
    fn reversed_axes_keep_channels_and_rescale() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            dims: vec![5, 4, 3, 2],
            sform: Some([0.0, 10.0, 0.0]),
            slope: 0.5,
            inter: -3.0,
            ..Default::default()
        };
        let vals = ramp_i16(120);
        let mut fwd = header(&s);
        fwd.extend(i16_bytes(&vals, false));
        let mut back = fwd.clone();
        back[300..304].copy_from_slice(&(-0.9f32).to_le_bytes()); // srow_y[1]
        let pf = write(dir.path(), "fwd.nii.gz", &gzip(&fwd));
        let pb = write(dir.path(), "back.nii.gz", &gzip(&back));
        let (f, b) = (open(&pf).unwrap(), open(&pb).unwrap());
        assert_eq!(b.meta().channels, 2);
        assert_eq!(b.meta().dtype, DType::F32, "rescaled");
        assert!(b.meta().scaling.is_some());
        assert_eq!(b.meta().origin.unwrap()[1] as f32, 10.0 - 3.0 * 0.9);
        for c in 0..2 {
            let fv: Vec<f32> = from_ne(&read_all(&f, c), f32::from_ne_bytes);
            let bv: Vec<f32> = from_ne(&read_all(&b, c), f32::from_ne_bytes);
            for k in 0..3 {
                for j in 0..4 {
                    for i in 0..5 {
                        assert_eq!(
                            bv[(k * 4 + j) * 5 + i],
                            fv[(k * 4 + (3 - j)) * 5 + i],
                            "channel {c} voxel {i},{j},{k}"
                        );
                    }
                }
            }
            assert_eq!(read_stitched(&b, c, [2, 3, 2]), read_all(&b, c));
        }
    }

    /// An invalid pixdim entry costs that axis only: its spacing comes
    /// from the sform (the length of its column), else 1, and is noted.
    #[test]
    fn invalid_pixdim_is_replaced_and_noted() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            pixdim: [1.5, 1.5, 1.5],
            sform: Some([1.0, 2.0, 3.0]),
            ..Default::default()
        };
        let data = i16_bytes(&ramp_i16(60), false);
        let mut file = header(&s);
        file.extend(&data);
        file[80..84].copy_from_slice(&0f32.to_le_bytes()); // pixdim[1]
        let src = open(&write(dir.path(), "sform.nii", &file)).unwrap();
        let m = src.meta();
        assert_eq!(m.spacing, Some([1.5, 1.5, 1.5]));
        assert_eq!(m.unit.as_deref(), Some("millimeter"));
        assert_eq!(m.notes.len(), 1, "{:?}", m.notes);
        assert!(
            m.notes[0]
                .starts_with("pixdim[1] = 0 is not a valid spacing: x spacing 1.5 from the sform"),
            "{:?}",
            m.notes
        );

        // A rotated sform: the column's length.
        let mut rot = file.clone();
        let (c, sn) = (0.6f32 * 1.5, 0.8f32 * 1.5);
        for (o, v) in [(280, c), (284, -sn), (296, sn), (300, c)] {
            rot[o..o + 4].copy_from_slice(&v.to_le_bytes());
        }
        rot[84..88].copy_from_slice(&f32::NAN.to_le_bytes()); // pixdim[2]
        let m = open(&write(dir.path(), "rot.nii", &rot))
            .unwrap()
            .meta()
            .clone();
        let sp = m.spacing.unwrap();
        assert!(
            (sp[2] - 1.5).abs() < 1e-6 && (sp[1] - 1.5).abs() < 1e-6 && sp[0] == 1.5,
            "{sp:?}"
        );
        assert!(m.notes.iter().any(|n| n.starts_with("pixdim[1] = 0 is not a valid spacing: x spacing 1.5 from the sform (the length of its column 1)")), "{:?}", m.notes);
        assert!(
            m.notes
                .iter()
                .any(|n| n.starts_with("pixdim[2] = NaN is not a valid spacing")),
            "{:?}",
            m.notes
        );

        // No sform: 1 for that axis, the others kept.
        let s = Synth {
            pixdim: [1.5, 1.5, 1.5],
            qoffset: Some([0.0, 0.0, 0.0]),
            ..Default::default()
        };
        let mut file = header(&s);
        file.extend(&data);
        file[80..84].copy_from_slice(&0f32.to_le_bytes());
        let m = open(&write(dir.path(), "q.nii", &file))
            .unwrap()
            .meta()
            .clone();
        assert_eq!(m.spacing, Some([1.5, 1.5, 1.0]));
        assert_eq!(m.notes.len(), 1, "{:?}", m.notes);
        assert!(
            m.notes[0].starts_with(
                "pixdim[1] = 0 is not a valid spacing and no sform gives one: x spacing 1"
            ),
            "{:?}",
            m.notes
        );
    }

    /// A `bitpix` that disagrees with `datatype` is read as the datatype
    /// says, and noted.
    #[test]
    fn bitpix_disagreement_is_noted() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            bitpix: 32,
            ..Default::default()
        };
        let vals = ramp_i16(60);
        let mut file = header(&s);
        file.extend(i16_bytes(&vals, false));
        let src = open(&write(dir.path(), "b.nii", &file)).unwrap();
        assert_eq!(src.meta().dtype, DType::I16);
        assert_eq!(read_all(&src, 0), ne_i16(&vals));
        assert_eq!(src.meta().notes.len(), 1, "{:?}", src.meta().notes);
        assert!(
            src.meta().notes[0]
                .starts_with("bitpix 32 disagrees with datatype 4 (i16, 16 bits): read as i16"),
            "{:?}",
            src.meta().notes
        );
    }

    /// `--origin`/`--spacing` replace the file's geometry, not the data's
    /// direction: the store keeps the reversed axis, with the overrides.
    #[test]
    fn overrides_keep_the_reversal() {
        use crate::builder::{convert, ConvertOptions, NoProgress};
        use std::sync::atomic::AtomicBool;
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            sform: Some([50.0, -20.0, -10.0]),
            ..Default::default()
        };
        let vals = ramp_i16(60);
        let mut file = header(&s);
        file[280..284].copy_from_slice(&(-0.8f32).to_le_bytes());
        file.extend(i16_bytes(&vals, false));
        let src = open(&write(dir.path(), "o.nii", &file)).unwrap();
        let out = dir.path().join("o.ome.zarr");
        let opts = ConvertOptions {
            brick: [4, 4, 4],
            shard: [8, 8, 8],
            origin: Some([7.0, 8.0, 9.0]),
            spacing: Some([3.0, 2.0, 1.0]),
            ..Default::default()
        };
        convert(&src, &out, &opts, &NoProgress, &AtomicBool::new(false)).unwrap();
        let ms = crate::omezarr::read_multiscale(&out).unwrap().unwrap();
        assert_eq!(ms.datasets[0].translation, Some(vec![7.0, 8.0, 9.0]));
        assert_eq!(ms.datasets[0].scale, Some(vec![3.0, 2.0, 1.0]));
        let store = crate::import::zarr::open(&out, 0).unwrap();
        let got: Vec<i16> = from_ne(&read_all(&store, 0), i16::from_ne_bytes);
        assert_eq!(got[0], vals[4], "store voxel 0 is the file's last x voxel");
        assert_eq!(read_all(&store, 0), read_all(&src, 0));
    }

    /// A 4-D file with 3 volumes: channel c must be the c-th volume.
    fn four_d(gz: bool) {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            dims: vec![7, 6, 5, 3],
            ..Default::default()
        };
        let n = 7 * 6 * 5;
        let vals = ramp_i16(n * 3);
        let mut file = header(&s);
        file.extend(i16_bytes(&vals, false));
        let name = if gz { "4d.nii.gz" } else { "4d.nii" };
        let path = dir.path().join(name);
        std::fs::write(&path, if gz { gzip(&file) } else { file }).unwrap();
        let src = open(&path).unwrap();
        assert_eq!(src.is_gzip(), gz);
        assert_eq!(src.meta().dims, [5, 6, 7]);
        assert_eq!(src.meta().channels, 3);
        // Interleave channels slice by slice, as a pyramid builder would.
        for z in 0..5u64 {
            for c in 0..3 {
                let mut out = vec![0u8; 6 * 7 * 2];
                src.read_region(c, z..z + 1, 0..6, 0..7, &mut out).unwrap();
                let o = c * n + z as usize * 42;
                assert_eq!(out, ne_i16(&vals[o..o + 42]), "c {c} z {z}");
            }
        }
        for c in 0..3 {
            let want = ne_i16(&vals[c * n..(c + 1) * n]);
            assert_eq!(read_all(&src, c), want);
            assert_eq!(read_stitched(&src, c, [2, 4, 3]), want);
        }
    }

    #[test]
    fn four_d_becomes_channels() {
        four_d(false);
    }

    #[test]
    fn four_d_gz_becomes_channels() {
        four_d(true);
    }

    #[test]
    fn gz_big_endian_with_backward_reads() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            be: true,
            dims: vec![33, 20, 17],
            ..Default::default()
        };
        let vals = ramp_i16(33 * 20 * 17);
        let mut file = header(&s);
        file.extend(i16_bytes(&vals, true));
        let path = dir.path().join("vol.nii.gz");
        std::fs::write(&path, gzip(&file)).unwrap();
        let src = open(&path).unwrap();
        assert!(src.is_gzip());
        assert_eq!(read_all(&src, 0), ne_i16(&vals));
        assert_eq!(read_stitched(&src, 0, [5, 7, 11]), ne_i16(&vals));
    }

    #[test]
    fn hdr_img_pair() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            pair: true,
            vox_offset: 0,
            intent: INTENT_LABEL,
            ..Default::default()
        };
        let vals = ramp_i16(60);
        std::fs::write(dir.path().join("pair.hdr"), header(&s)).unwrap();
        std::fs::write(dir.path().join("pair.img"), i16_bytes(&vals, false)).unwrap();
        for name in ["pair.hdr", "pair.img"] {
            let src = open(&dir.path().join(name)).unwrap();
            assert_eq!(src.meta().dims, [3, 4, 5]);
            assert!(src.meta().labels, "intent_code 1002 marks labels");
            assert_eq!(read_all(&src, 0), ne_i16(&vals));
        }
        // A compressed image half.
        std::fs::remove_file(dir.path().join("pair.img")).unwrap();
        std::fs::write(
            dir.path().join("pair.img.gz"),
            gzip(&i16_bytes(&vals, false)),
        )
        .unwrap();
        let src = open(&dir.path().join("pair.hdr")).unwrap();
        assert!(src.is_gzip());
        assert_eq!(read_all(&src, 0), ne_i16(&vals));
    }

    /// Assert that `r` failed and its message names `file` and `field`.
    fn assert_err<T: std::fmt::Debug>(r: Result<T>, file: &str, field: &str) -> String {
        let e = r.expect_err("expected an error");
        let msg = e.to_string();
        assert!(msg.contains(file), "{msg:?} does not name the file {file}");
        assert!(
            msg.contains(&format!(" {field}: ")),
            "{msg:?} does not name the field {field}"
        );
        msg
    }

    fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }

    #[test]
    fn truncated_data() {
        let dir = tempfile::tempdir().unwrap();
        let mut file = header(&Synth::default());
        file.extend(i16_bytes(&ramp_i16(59), false)); // one voxel short
        let p = write(dir.path(), "short.nii", &file);
        let msg = assert_err(open(&p), "short.nii", "data");
        assert!(msg.contains("file holds 118 bytes of voxel data"), "{msg}");
        assert!(msg.contains("need 120"), "{msg}");

        // Truncated inside the header.
        let p = write(dir.path(), "stub.nii", &file[..200]);
        assert_err(open(&p), "stub.nii", "sizeof_hdr");
    }

    #[test]
    fn truncated_gz_fails_on_read() {
        let dir = tempfile::tempdir().unwrap();
        let s = Synth {
            dims: vec![64, 64, 16],
            ..Default::default()
        };
        let mut file = header(&s);
        // Incompressible-ish data so that the cut lands inside the voxels.
        let mut x = 12345u32;
        file.extend((0..64 * 64 * 16 * 2).map(|_| {
            x = x.wrapping_mul(1664525).wrapping_add(1013904223);
            (x >> 24) as u8
        }));
        let gz = gzip(&file);
        let p = write(dir.path(), "cut.nii.gz", &gz[..gz.len() / 2]);
        let src = open(&p).unwrap();
        let mut out = vec![0u8; src.meta().channel_bytes() as usize];
        let r = src.read_region(0, 0..16, 0..64, 0..64, &mut out);
        let msg = r.as_ref().err().map(|e| e.to_string()).unwrap_or_default();
        assert!(msg.contains("the gzip stream is cut short"), "{msg}");
        assert_err(r, "cut.nii.gz", "data");
    }

    #[test]
    fn bad_sizeof_hdr() {
        let dir = tempfile::tempdir().unwrap();
        let mut file = header(&Synth::default());
        file[0..4].copy_from_slice(&349i32.to_le_bytes());
        file.extend(vec![0u8; 120]);
        let p = write(dir.path(), "bad.nii", &file);
        assert_err(open(&p), "bad.nii", "sizeof_hdr");
        let p = write(dir.path(), "text.nii", b"this is not a NIfTI file at all");
        assert_err(open(&p), "text.nii", "sizeof_hdr");
    }

    #[test]
    fn unsupported_datatype() {
        let dir = tempfile::tempdir().unwrap();
        for (code, bitpix) in [(128i16, 24i16), (1024, 64), (32, 64)] {
            let s = Synth {
                datatype: code,
                bitpix,
                ..Default::default()
            };
            let mut file = header(&s);
            file.extend(vec![0u8; 60 * bitpix as usize / 8]);
            let name = format!("dt{code}.nii");
            let p = write(dir.path(), &name, &file);
            let msg = assert_err(open(&p), &name, "datatype");
            assert!(msg.contains(&code.to_string()), "{msg}");
            assert!(matches!(open(&p), Err(StoreError::Unsupported { .. })));
        }
    }

    #[test]
    fn bad_dims_and_offsets() {
        let dir = tempfile::tempdir().unwrap();
        let five_d = Synth {
            dims: vec![2, 2, 2, 1, 3],
            ..Default::default()
        };
        let mut file = header(&five_d);
        file.extend(vec![0u8; 2 * 8 * 3]);
        let p = write(dir.path(), "5d.nii", &file);
        assert_err(open(&p), "5d.nii", "dim");

        let mut file = header(&Synth::default());
        file[40..42].copy_from_slice(&9i16.to_le_bytes()); // dim[0] = 9
        file.extend(vec![0u8; 120]);
        let p = write(dir.path(), "dim0.nii", &file);
        assert_err(open(&p), "dim0.nii", "dim");

        let mut file = header(&Synth::default());
        file[42..44].copy_from_slice(&(-5i16).to_le_bytes()); // dim[1] = -5
        file.extend(vec![0u8; 120]);
        let p = write(dir.path(), "neg.nii", &file);
        assert_err(open(&p), "neg.nii", "dim");

        let mut file = header(&Synth::default());
        file[108..112].copy_from_slice(&100.0f32.to_le_bytes());
        file.extend(vec![0u8; 120]);
        let p = write(dir.path(), "vox.nii", &file);
        assert_err(open(&p), "vox.nii", "vox_offset");

        let mut file = header(&Synth::default());
        file[108..112].copy_from_slice(&f32::NAN.to_le_bytes());
        file.extend(vec![0u8; 120]);
        let p = write(dir.path(), "nan.nii", &file);
        assert_err(open(&p), "nan.nii", "vox_offset");

        let mut file = header(&Synth::default());
        file[344..348].copy_from_slice(b"xyz\0");
        file.extend(vec![0u8; 120]);
        let p = write(dir.path(), "magic.nii", &file);
        assert_err(open(&p), "magic.nii", "magic");
    }

    #[test]
    fn corrupt_gzip() {
        let dir = tempfile::tempdir().unwrap();
        let mut file = header(&Synth::default());
        file.extend(vec![7u8; 120]);
        let mut gz = gzip(&file);
        // Keep the 10-byte gzip header, garble the deflate stream.
        for (i, b) in gz[10..].iter_mut().enumerate() {
            *b = 0xff ^ (i as u8).wrapping_mul(31);
        }
        let p = write(dir.path(), "corrupt.nii.gz", &gz);
        assert_err(open(&p), "corrupt.nii.gz", "gzip");
    }

    /// A gzip stream whose bytes decompress but whose CRC (or length) in
    /// the trailer does not match: an error once the last voxel is read,
    /// not a volume with a flipped voxel.
    #[test]
    fn gzip_checksum_is_checked() {
        let dir = tempfile::tempdir().unwrap();
        let mut file = header(&Synth::default());
        file.extend(i16_bytes(&ramp_i16(60), false));
        let read_all = |p: &Path| {
            open(p).and_then(|src| {
                let mut out = vec![0u8; src.meta().channel_bytes() as usize];
                src.read_region(0, 0..3, 0..4, 0..5, &mut out).map(|_| out)
            })
        };
        let gz = gzip(&file);
        let good = read_all(&write(dir.path(), "good.nii.gz", &gz)).unwrap();
        assert_eq!(good, i16_bytes(&ramp_i16(60), false));
        // The trailer's CRC, then its length, off by one bit.
        for (name, at) in [("crc.nii.gz", gz.len() - 8), ("len.nii.gz", gz.len() - 4)] {
            let mut bad = gz.clone();
            bad[at] ^= 1;
            let msg = assert_err(read_all(&write(dir.path(), name, &bad)), name, "gzip");
            assert!(msg.contains("checksum"), "{msg}");
        }
        // A voxel flipped in a stored (uncompressed) deflate block: it
        // decompresses, and only the CRC tells.
        let mut e = GzEncoder::new(Vec::new(), flate2::Compression::none());
        e.write_all(&file).unwrap();
        let mut stored = e.finish().unwrap();
        let voxel = stored.len() - 8 - 10;
        stored[voxel] ^= 0x40;
        let msg = assert_err(
            read_all(&write(dir.path(), "flip.nii.gz", &stored)),
            "flip.nii.gz",
            "gzip",
        );
        assert!(msg.contains("checksum"), "{msg}");
    }

    #[test]
    fn missing_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("nowhere.nii.gz");
        let e = open(&p).unwrap_err();
        assert!(e.to_string().contains("nowhere.nii.gz"), "{e}");
        assert!(
            matches!(&e, StoreError::Io { error, .. } if error.kind() == io::ErrorKind::NotFound)
        );

        // The .img of a pair without its header.
        let p = write(dir.path(), "lonely.img", &[0u8; 16]);
        let e = open(&p).unwrap_err();
        assert!(e.to_string().contains("lonely.img"), "{e}");
    }
}
