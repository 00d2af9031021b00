//! TIFF importer: a multi-page TIFF or BigTIFF (one page per z slice), a
//! directory of 2-D TIFF slices, or a glob of slice files.
//!
//! Over 800 lines: 1.8k lines of importer (every TIFF layout, reads in place and
//! YCbCr included), 1.2k of tests.
//!
//! Samples may be 8/16/32-bit unsigned or signed integers or 16/32/64-bit
//! floats (16-bit floats are stored as f32, exactly); several samples per
//! pixel (RGB, multiband) become channels, in both chunky and
//! planar-separate layouts. Compression is whatever the `tiff` crate
//! decodes (LZW, Deflate, PackBits, JPEG, CCITT G4, Zstandard).
//!
//! Memory follows the region asked for, not the page size: uncompressed
//! strips and tiles (no predictor) are not decoded at all, a request reads
//! just the bytes of its rows and columns from the file (as the raw
//! importer does); compressed ones are decoded one strip or tile at a time,
//! only those that cover the request, and a small LRU cache bounded in
//! bytes ([`DEFAULT_CACHE_BYTES`], whatever the page size) avoids decoding
//! the same data again when a page is read in several sub-regions. The
//! converter's memory plan counts no memory for a source beyond its fixed
//! allowance, so this stays a small constant; a compressed strip or tile is
//! still decoded whole, so a file of huge compressed strips (one strip per
//! page) needs that much more ([`TiffSource::largest_decode_bytes`]). And
//! when a small budget makes the converter read a page in columns narrower
//! than its strips, each compressed strip is decoded once per column: the
//! price of staying within the budget (a whole band of strips would not
//! fit it).
//!
//! The IFD offsets of a multi-page file are collected once by [`open`],
//! which also checks that all pages agree in size and sample type; reading
//! a page then parses only its own IFD, so random access does not walk the
//! IFD chain.
//!
//! Reduced-resolution pages (`NewSubfileType` bit 0, i.e. thumbnails and
//! pyramid levels) are skipped.
//!
//! Header fields that change what values or positions mean:
//!
//! * `SampleFormat` and `BitsPerSample` give the voxel type; `Predictor`
//!   (horizontal differencing, floating point) and the byte order are undone
//!   by the decoder.
//! * `PhotometricInterpretation` MinIsWhite (0): the decoder returns
//!   `max − stored` for unsigned integers (`max` of the type) and
//!   `1 − stored` for floats, so that higher values are brighter; the
//!   conversion report says so. Signed or multi-sample MinIsWhite images are
//!   refused.
//! * `PhotometricInterpretation` YCbCr (6), tifffile's default for JPEG
//!   colour images and common from slide scanners: the decoder hands back
//!   the stored Y, Cb, Cr samples (its JPEG path does no colour conversion,
//!   only chroma upsampling), so they are converted to R, G, B with the
//!   JFIF (BT.601 full range) equations, as libjpeg does, and the report
//!   says so. 8-bit chunky YCbCr only. JPEG-compressed YCbCr may have any
//!   `YCbCrSubSampling` (the JPEG decoder upsamples; `YCbCrCoefficients`
//!   and `ReferenceBlackWhite` are ignored, as libtiff's and tifffile's
//!   readers do); other compressions only `YCbCrSubSampling` 1,1 (the
//!   decoder reads no subsampled data), with the default coefficients and
//!   full-range reference values; anything else is refused.
//! * An ImageJ file (a multi-page file whose `ImageDescription` starts with
//!   `ImageJ=`): `channels=C` makes C channels of interleaved pages (ImageJ
//!   stores channel fastest, then slice, then frame); the spacing is
//!   `1/XResolution`, `1/YResolution` and `spacing=` (z), in `unit=`, when
//!   a unit other than `pixel` is given. Several frames of a single slice
//!   are read as z; several frames of several slices (a time series of
//!   volumes) are refused.
//! * Otherwise TIFF stores no reliable voxel spacing (`XResolution` of a
//!   plain TIFF is about printing), so `spacing` is `None`; OME-TIFF XML
//!   metadata is not read (pages are z in file order), which the report
//!   notes.

use crate::error::{IoContext, Result, StoreError};
use crate::import::MAX_DEFLATE_RATIO;
use crate::omezarr::normalize_unit;
use crate::source::{check_region, SourceMeta, VolumeSource};
use brickyard_core::DType;
use std::cmp::Ordering;
use std::collections::HashMap;
use std::fs::File;
use std::io::{self, BufReader, Read, Seek, SeekFrom};
use std::ops::Range;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};
use std::sync::{Arc, Mutex, PoisonError};
use tiff::decoder::{ChunkType, Decoder, Limits};
use tiff::tags::{ByteOrder, Tag};
use tiff::{ColorType, TiffError, TiffFormatError, TiffUnsupportedError};

/// Bytes of decoded strips/tiles kept by default, whatever the page size:
/// the converter's memory plan has no share for a source beyond its fixed
/// allowance, so this must stay small.
pub const DEFAULT_CACHE_BYTES: usize = 8 << 20;

/// Most bytes of an uncompressed strip or tile read in one piece when a
/// request needs most of each of its rows (rows needing little of theirs
/// are read one by one).
const RAW_BLOCK_BYTES: u64 = 1 << 20;

/// Largest strip or tile decoded in one piece (a guard against absurd sizes
/// in corrupt files).
const MAX_CHUNK_BYTES: u64 = 16 << 30;

/// A TIFF stack opened for region reads. See the [module docs](self).
pub struct TiffSource {
    meta: SourceMeta,
    stack: Stack,
    pages: Vec<PageGeom>,
    format: PageFormat,
    /// Channels stored as interleaved pages (ImageJ `channels=`): page
    /// `z · page_channels + c` holds channel `c` of slice `z`. 1 otherwise.
    page_channels: usize,
    cache: Mutex<ChunkCache>,
    /// Bytes of strips and tiles decoded, or read without decoding, so far
    /// (for tests and benchmarks: what a request costs).
    decoded: AtomicU64,
}

/// Where the pages come from.
enum Stack {
    /// One multi-page file, shared by all reads (positioned reads).
    File {
        path: PathBuf,
        file: Arc<File>,
        len: u64,
        /// The first two bytes of the file (`II` or `MM`).
        byte_order: [u8; 2],
        bigtiff: bool,
    },
    /// One 2-D file per slice.
    Files(Vec<PathBuf>),
}

/// Where a page's IFD is and how its data is cut into strips or tiles.
#[derive(Debug, Clone, Copy)]
struct PageGeom {
    /// IFD index in the file (for messages).
    index: usize,
    /// IFD offset (multi-page files only).
    ifd: u64,
    /// Strip (full width × rows per strip) or tile size.
    chunk_w: u32,
    chunk_h: u32,
    /// Uncompressed, no predictor, values as stored: regions are read from
    /// the file without decoding whole strips or tiles.
    raw: bool,
}

/// What all pages must agree on.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PageFormat {
    width: u32,
    height: u32,
    bits: u8,
    sample_format: u16,
    dtype: DType,
    channels: usize,
    planar: bool,
    /// `PhotometricInterpretation` 0: the decoder inverts the values.
    min_is_white: bool,
    /// `PhotometricInterpretation` 6: decoded chunks hold Y, Cb, Cr, which
    /// are converted to R, G, B.
    ycbcr: bool,
}

impl PageFormat {
    /// Bytes of one stored sample (2 for 16-bit floats, which `dtype`
    /// holds as f32).
    fn stored_size(&self) -> usize {
        usize::from(self.bits / 8)
    }

    /// 16-bit float samples: decoded, then widened to f32.
    fn half(&self) -> bool {
        self.sample_format == 3 && self.bits == 16
    }
}

impl std::fmt::Debug for TiffSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TiffSource")
            .field("meta", &self.meta)
            .field("pages", &self.pages.len())
            .field("format", &self.format)
            .finish()
    }
}

/// Open a multi-page TIFF/BigTIFF file, or a directory of 2-D TIFF slices
/// (files ending in `.tif` or `.tiff`, any case, in natural order so that
/// `img2.tif` comes before `img10.tif`; hidden files are ignored).
pub fn open(path: &Path) -> Result<TiffSource> {
    if path.is_dir() {
        let mut files: Vec<PathBuf> = list_dir(path)?
            .into_iter()
            .filter(|(name, _)| {
                let lower = name.to_ascii_lowercase();
                !name.starts_with('.') && (lower.ends_with(".tif") || lower.ends_with(".tiff"))
            })
            .map(|(_, p)| p)
            .collect();
        if files.is_empty() {
            return Err(StoreError::invalid(
                path,
                "page count",
                "the directory holds no .tif or .tiff files",
            ));
        }
        sort_natural(&mut files);
        open_files(path, files)
    } else {
        open_multipage(path)
    }
}

/// Open the files matching a glob such as `/data/slice_*.tif` as a stack of
/// 2-D slices in natural order. `*` (any run of characters) and `?` (one
/// character) are allowed in the file-name part only.
pub fn open_glob(pattern: &str) -> Result<TiffSource> {
    let p = Path::new(pattern);
    let name = p
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| StoreError::invalid(pattern, "glob", "the pattern has no file-name part"))?;
    let dir = match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if dir.to_string_lossy().contains(['*', '?', '[']) {
        return Err(StoreError::unsupported(
            pattern,
            "glob",
            "wildcards are supported in the file name only, not in directory names",
        ));
    }
    let mut files: Vec<PathBuf> = list_dir(&dir)?
        .into_iter()
        .filter(|(n, _)| (!n.starts_with('.') || name.starts_with('.')) && wildcard_match(name, n))
        .map(|(_, p)| p)
        .collect();
    if files.is_empty() {
        return Err(StoreError::invalid(
            pattern,
            "page count",
            "no file matches the pattern",
        ));
    }
    sort_natural(&mut files);
    open_files(Path::new(pattern), files)
}

impl TiffSource {
    /// Keep up to `bytes` of decoded strips/tiles in the cache (0 disables
    /// caching; a strip or tile larger than that is never kept). The
    /// default is [`DEFAULT_CACHE_BYTES`].
    pub fn with_cache_bytes(self, bytes: usize) -> Self {
        self.set_cache_bytes(bytes);
        self
    }

    /// Change the cache size; see [`TiffSource::with_cache_bytes`].
    pub fn set_cache_bytes(&self, bytes: usize) {
        let mut cache = self.lock_cache();
        cache.budget = bytes;
        cache.shrink_to(bytes);
    }

    /// Bytes of strips and tiles decoded, or read from the file without
    /// decoding, since the source was opened: what the reads so far cost.
    pub fn bytes_decoded(&self) -> u64 {
        self.decoded.load(AtomicOrdering::Relaxed)
    }

    /// The most bytes the cache of decoded strips/tiles has held.
    pub fn cache_peak_bytes(&self) -> usize {
        self.lock_cache().peak
    }

    /// Decoded bytes of the largest strip or tile that a read decodes whole
    /// (0 when every page is read without decoding): the memory a read
    /// needs beyond its output and the cache, per reading thread.
    pub fn largest_decode_bytes(&self) -> u64 {
        let f = &self.format;
        let mut px = (if f.planar { 1 } else { f.channels } * f.dtype.size()) as u64;
        if f.half() {
            // The decoded f16 samples beside their f32 copy.
            px += px / 2;
        }
        self.pages
            .iter()
            .filter(|g| !g.raw)
            .map(|g| (g.chunk_w as u64).saturating_mul(g.chunk_h.min(f.height) as u64) * px)
            .max()
            .unwrap_or(0)
    }

    /// The files of a slice stack, in z order (`None` for a multi-page file).
    pub fn slice_files(&self) -> Option<&[PathBuf]> {
        match &self.stack {
            Stack::Files(files) => Some(files),
            Stack::File { .. } => None,
        }
    }

    /// The file holding page `z`, and how messages name the page.
    fn page_origin(&self, z: usize) -> (&Path, String) {
        match &self.stack {
            Stack::File { path, .. } => (path, format!("page {}", self.pages[z].index)),
            Stack::Files(files) => (&files[z], format!("slice {z}")),
        }
    }

    /// A decoder positioned on page `z`.
    fn page_decoder(&self, z: usize) -> Result<Decoder<BufReader<PageReader>>> {
        let (path, label) = self.page_origin(z);
        let reader = match &self.stack {
            Stack::File {
                file,
                len,
                byte_order,
                bigtiff,
                ..
            } => PageReader::at_ifd(file.clone(), *len, *byte_order, *bigtiff, self.pages[z].ifd),
            Stack::Files(files) => {
                let file = File::open(&files[z]).at(&files[z])?;
                let len = file.metadata().at(&files[z])?.len();
                PageReader::new(Arc::new(file), len)
            }
        };
        let len = reader.len;
        Decoder::new(BufReader::new(reader))
            .map(|d| d.with_limits(limits(len)))
            .map_err(|e| tiff_error(path, &label, "IFD", e))
    }

    /// Where the strips or tiles of page `z` (an uncompressed one) lie.
    fn raw_page(&self, z: usize) -> Result<RawPage> {
        let (path, label) = self.page_origin(z);
        guard(path, &label, || {
            let mut dec = self.page_decoder(z)?;
            let file = dec.inner().get_ref().file.clone();
            let (offsets_tag, counts_tag) = match dec.get_chunk_type() {
                ChunkType::Strip => (Tag::StripOffsets, Tag::StripByteCounts),
                ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts),
            };
            let offsets = dec
                .get_tag_u64_vec(offsets_tag)
                .map_err(|e| tiff_error(path, &label, &format!("{offsets_tag:?}"), e))?;
            let counts = dec
                .get_tag_u64_vec(counts_tag)
                .map_err(|e| tiff_error(path, &label, &format!("{counts_tag:?}"), e))?;
            let big = matches!(dec.byte_order(), ByteOrder::BigEndian);
            Ok(RawPage {
                file,
                offsets,
                counts,
                swap: big != cfg!(target_endian = "big"),
            })
        })
    }

    /// Copy rows `ys` × columns `xs` (image coordinates) of uncompressed
    /// strip or tile `idx` of page `z`, whose first pixel is at row `cy0`,
    /// column `cx0` and whose rows hold `cw` pixels of `spp` samples, into
    /// `out` (a slab of `nx` columns starting at image row `y0`, column
    /// `x0`), reading only the bytes needed (`sample`: the sample to pick).
    #[allow(clippy::too_many_arguments)]
    fn read_raw(
        &self,
        z: usize,
        page: &RawPage,
        idx: u32,
        [cy0, cx0, cw]: [u64; 3],
        (ys, xs): (Range<u64>, Range<u64>),
        (spp, sample): (usize, usize),
        (out, nx, y0, x0): (&mut [u8], usize, u64, u64),
        scratch: &mut Vec<u8>,
    ) -> Result<()> {
        let (path, label) = self.page_origin(z);
        let ss = self.format.dtype.size();
        let px = (spp * ss) as u64;
        let stride = cw * px;
        let n = (xs.end - xs.start) as usize;
        let len = n as u64 * px;
        let (Some(&offset), Some(&count)) = (
            page.offsets.get(idx as usize),
            page.counts.get(idx as usize),
        ) else {
            return Err(StoreError::invalid(
                path,
                "strip data",
                format!("{label}: strip/tile {idx} is missing from the offsets"),
            ));
        };
        // Bytes into the strip/tile of the first needed sample and past the
        // last one.
        let first = (ys.start - cy0) * stride + (xs.start - cx0) * px;
        let end = (ys.end - 1 - cy0) * stride + (xs.start - cx0) * px + len;
        if end > count {
            return Err(StoreError::invalid(
                path,
                "strip data",
                format!(
                    "{label}: strip/tile {idx} holds {count} bytes but the image needs {end} of \
                     them"
                ),
            ));
        }
        let read = |buf: &mut [u8], at: u64| {
            read_exact_at(&page.file, buf, offset + at).map_err(|e| {
                if e.kind() == io::ErrorKind::UnexpectedEof {
                    StoreError::invalid(
                        path,
                        "strip data",
                        format!("{label}: the file ends early (truncated?): {e}"),
                    )
                } else {
                    StoreError::io(path, e)
                }
            })
        };
        // Rows that need most of their bytes are read several at a time.
        let rows = ys.end - ys.start;
        let per_read = if 2 * len >= stride {
            (RAW_BLOCK_BYTES / stride.max(1)).max(1)
        } else {
            1
        };
        let mut r = 0;
        while r < rows {
            let k = per_read.min(rows - r);
            let at = first + r * stride;
            let span = ((k - 1) * stride + len) as usize;
            let direct = spp == 1 && k == 1;
            if !direct {
                scratch.resize(span, 0);
                read(&mut scratch[..span], at)?;
            }
            for i in 0..k {
                let yy = ys.start + r + i;
                let d = ((yy - y0) as usize * nx + (xs.start - x0) as usize) * ss;
                let dst = &mut out[d..d + n * ss];
                if direct {
                    read(dst, at)?;
                } else {
                    let s0 = (i * stride) as usize;
                    let src = &scratch[s0..s0 + len as usize];
                    if spp == 1 {
                        dst.copy_from_slice(src);
                    } else {
                        let pxs = px as usize;
                        for (d, s) in dst.chunks_exact_mut(ss).zip(src.chunks_exact(pxs)) {
                            d.copy_from_slice(&s[sample * ss..(sample + 1) * ss]);
                        }
                    }
                }
                if page.swap && ss > 1 {
                    for e in dst.chunks_exact_mut(ss) {
                        e.reverse();
                    }
                }
            }
            self.decoded.fetch_add(span as u64, AtomicOrdering::Relaxed);
            r += k;
        }
        Ok(())
    }

    /// Strip or tile `idx` of page `z`, from the cache or decoded (opening
    /// the page's decoder in `dec` on first use).
    fn chunk(
        &self,
        z: usize,
        idx: u32,
        dec: &mut Option<Decoder<BufReader<PageReader>>>,
    ) -> Result<Arc<Chunk>> {
        let key = (z, idx);
        if let Some(c) = self.lock_cache().get(key) {
            return Ok(c);
        }
        let (path, label) = self.page_origin(z);
        let f = self.format;
        let samples = if f.planar { 1 } else { f.channels };
        let mut chunk = guard(path, &label, || {
            let d = match dec {
                Some(d) => d,
                None => dec.insert(self.page_decoder(z)?),
            };
            decode_chunk(d, idx, samples * f.stored_size())
                .map_err(|e| tiff_error(path, &label, "strip data", e))
        })?;
        self.decoded
            .fetch_add(chunk.data.len() as u64, AtomicOrdering::Relaxed);
        if f.half() {
            chunk.data = widen_f16(&chunk.data);
        }
        if f.ycbcr {
            ycbcr_to_rgb(&mut chunk.data);
        }
        let chunk = Arc::new(chunk);
        self.lock_cache().insert(key, chunk.clone());
        Ok(chunk)
    }

    fn lock_cache(&self) -> std::sync::MutexGuard<'_, ChunkCache> {
        self.cache.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl VolumeSource for TiffSource {
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
        let f = self.format;
        let ss = f.dtype.size();
        // Samples per pixel inside a decoded chunk, the sample to pick, and
        // the plane (planar-separate images keep each channel in its own
        // strips/tiles).
        let (spp, sample, plane) = if self.page_channels > 1 {
            (1, 0, 0)
        } else if f.planar {
            (1, 0, c as u64)
        } else {
            (f.channels, c, 0)
        };
        let nx = (x.end - x.start) as usize;
        let slab = nx * (y.end - y.start) as usize * ss;
        for (k, zz) in z.clone().enumerate() {
            let zi = zz as usize * self.page_channels + if self.page_channels > 1 { c } else { 0 };
            let geom = self.pages[zi];
            let out_z = &mut out[k * slab..(k + 1) * slab];
            let (cw, ch) = (geom.chunk_w as u64, geom.chunk_h as u64);
            let across = (f.width as u64).div_ceil(cw);
            let down = (f.height as u64).div_ceil(ch);
            let mut dec = None;
            let mut raw = None;
            let mut scratch = Vec::new();
            for row in y.start / ch..=(y.end - 1) / ch {
                for col in x.start / cw..=(x.end - 1) / cw {
                    let idx = (plane * down + row) * across + col;
                    let idx = u32::try_from(idx).map_err(|_| {
                        let (path, label) = self.page_origin(zi);
                        StoreError::invalid(
                            path,
                            "strip data",
                            format!("{label}: too many strips or tiles"),
                        )
                    })?;
                    let (cy0, cx0) = (row * ch, col * cw);
                    let ys = y.start.max(cy0)..y.end.min(cy0 + ch);
                    let xs = x.start.max(cx0)..x.end.min(cx0 + cw);
                    if geom.raw {
                        let page = match &raw {
                            Some(p) => p,
                            None => raw.insert(self.raw_page(zi)?),
                        };
                        self.read_raw(
                            zi,
                            page,
                            idx,
                            [cy0, cx0, cw],
                            (ys, xs),
                            (spp, sample),
                            (&mut *out_z, nx, y.start, x.start),
                            &mut scratch,
                        )?;
                        continue;
                    }
                    let chunk = self.chunk(zi, idx, &mut dec)?;
                    if ys.end > cy0 + chunk.height as u64 || xs.end > cx0 + chunk.width as u64 {
                        let (path, label) = self.page_origin(zi);
                        return Err(StoreError::invalid(
                            path,
                            "strip data",
                            format!(
                                "{label}: strip/tile {idx} holds fewer pixels than the image needs"
                            ),
                        ));
                    }
                    let n = (xs.end - xs.start) as usize;
                    for yy in ys {
                        let src = (((yy - cy0) * chunk.width as u64 + xs.start - cx0) as usize)
                            * spp
                            * ss;
                        let dst =
                            ((yy - y.start) as usize * nx + (xs.start - x.start) as usize) * ss;
                        let dst = &mut out_z[dst..dst + n * ss];
                        if spp == 1 {
                            dst.copy_from_slice(&chunk.data[src..src + n * ss]);
                        } else {
                            let px = spp * ss;
                            let row_data = &chunk.data[src..src + n * px];
                            for (d, s) in dst.chunks_exact_mut(ss).zip(row_data.chunks_exact(px)) {
                                d.copy_from_slice(&s[sample * ss..(sample + 1) * ss]);
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }
}

/// Open one multi-page file: walk its IFD chain once, checking every page.
fn open_multipage(path: &Path) -> Result<TiffSource> {
    let file = File::open(path).at(path)?;
    let len = file.metadata().at(path)?.len();
    let file = Arc::new(file);
    let mut head = [0u8; 4];
    let n = PageReader::new(file.clone(), len)
        .read(&mut head)
        .at(path)?;
    let byte_order = [head[0], head[1]];
    let version = match &byte_order {
        b"MM" => u16::from_be_bytes([head[2], head[3]]),
        _ => u16::from_le_bytes([head[2], head[3]]),
    };
    if n < 4 || !(byte_order == *b"II" || byte_order == *b"MM") || !(version == 42 || version == 43)
    {
        return Err(StoreError::invalid(
            path,
            "header",
            "not a TIFF file (no II*/MM* signature)",
        ));
    }
    let bigtiff = version == 43;

    let (pages, format, tags) = guard(path, "page 0", || {
        let mut dec = Decoder::new(BufReader::new(PageReader::new(file.clone(), len)))
            .map(|d| d.with_limits(limits(len)))
            .map_err(|e| tiff_error(path, "page 0", "header", e))?;
        let mut pages = Vec::new();
        let mut first: Option<(PageFormat, String)> = None;
        let mut tags = PageTags::default();
        let mut index = 0usize;
        // Bytes all pages need, and the largest decoding ratio among them.
        let (mut need, mut ratio) = (0u64, 1u64);
        loop {
            let label = format!("page {index}");
            let ifd = dec.ifd_pointer().map(|p| p.0).unwrap_or(0);
            if !is_reduced(&mut dec, path, &label)? {
                let (fmt, chunk, raw) = page_info(&mut dec, path, &label)?;
                let (n, r) = check_chunk_extents(&mut dec, path, &label, len, &fmt)?;
                need = need.saturating_add(n);
                ratio = ratio.max(r);
                // Pages may share strips, so check the whole file too.
                if need > len.saturating_mul(ratio) {
                    return Err(StoreError::invalid(
                        path,
                        "page count",
                        format!(
                            "{} pages of {}×{} pixels × {} sample(s) of {} need {need} bytes, \
                             but the file holds only {len} bytes{}",
                            pages.len() + 1,
                            fmt.width,
                            fmt.height,
                            fmt.channels,
                            fmt.dtype,
                            if ratio > 1 {
                                format!(", which decode at most {ratio}-fold")
                            } else {
                                String::new()
                            }
                        ),
                    ));
                }
                match &first {
                    None => {
                        first = Some((fmt, label));
                        tags = PageTags::read(&mut dec);
                    }
                    Some((f0, l0)) => same_format(f0, l0, &fmt, &label, path)?,
                }
                pages.push(PageGeom {
                    index,
                    ifd,
                    chunk_w: chunk.0,
                    chunk_h: chunk.1,
                    raw,
                });
            }
            if !dec.more_images() {
                break;
            }
            index += 1;
            dec.next_image()
                .map_err(|e| tiff_error(path, &format!("page {index}"), "IFD", e))?;
        }
        match first {
            Some((format, _)) => Ok((pages, format, tags)),
            None => Err(StoreError::invalid(
                path,
                "page count",
                "the file holds only reduced-resolution pages",
            )),
        }
    })?;
    TiffSource::new(
        path,
        Stack::File {
            path: path.to_path_buf(),
            file,
            len,
            byte_order,
            bigtiff,
        },
        pages,
        format,
        tags,
    )
}

/// Open a stack of 2-D files (already sorted), checking every file.
fn open_files(stack_path: &Path, files: Vec<PathBuf>) -> Result<TiffSource> {
    let mut pages = Vec::with_capacity(files.len());
    let mut first: Option<(PageFormat, String)> = None;
    for (z, path) in files.iter().enumerate() {
        let label = format!("slice {z}");
        let file = File::open(path).at(path)?;
        let len = file.metadata().at(path)?.len();
        let geom = guard(path, &label, || {
            let mut dec = Decoder::new(BufReader::new(PageReader::new(Arc::new(file), len)))
                .map(|d| d.with_limits(limits(len)))
                .map_err(|e| tiff_error(path, &label, "header", e))?;
            // Skip leading reduced-resolution pages; any further
            // full-resolution page makes the file a stack of its own.
            let mut index = 0;
            while is_reduced(&mut dec, path, &label)? && dec.more_images() {
                index += 1;
                dec.next_image()
                    .map_err(|e| tiff_error(path, &format!("{label} page {index}"), "IFD", e))?;
            }
            let (fmt, chunk, raw) = page_info(&mut dec, path, &label)?;
            check_chunk_extents(&mut dec, path, &label, len, &fmt)?;
            let mut extra = 0;
            while dec.more_images() {
                let l = format!("{label} page {}", index + 1);
                dec.next_image()
                    .map_err(|e| tiff_error(path, &l, "IFD", e))?;
                index += 1;
                if !is_reduced(&mut dec, path, &l)? {
                    extra += 1;
                }
            }
            if extra > 0 {
                return Err(StoreError::invalid(
                    path,
                    "page count",
                    format!(
                        "{label} holds {} pages; a slice stack needs one 2-D image per file \
                         (open a multi-page file on its own)",
                        extra + 1
                    ),
                ));
            }
            match &first {
                None => first = Some((fmt, format!("{label} ({})", path.display()))),
                Some((f0, l0)) => same_format(f0, l0, &fmt, &label, path)?,
            }
            Ok(PageGeom {
                index: z,
                ifd: 0,
                chunk_w: chunk.0,
                chunk_h: chunk.1,
                raw,
            })
        })?;
        pages.push(geom);
    }
    let Some((format, _)) = first else {
        return Err(StoreError::invalid(stack_path, "page count", "no slices"));
    };
    // Each slice file is a plain 2-D image: no stack metadata.
    TiffSource::new(
        stack_path,
        Stack::Files(files),
        pages,
        format,
        PageTags::default(),
    )
}

impl TiffSource {
    fn new(
        path: &Path,
        stack: Stack,
        pages: Vec<PageGeom>,
        format: PageFormat,
        tags: PageTags,
    ) -> Result<Self> {
        let mut notes = Vec::new();
        let mut page_channels = 1usize;
        let mut spacing = None;
        let mut unit = None;
        let n = pages.len();
        if let Some(ij) = tags.imagej() {
            let (c, z, t) = (ij.channels, ij.slices, ij.frames);
            if c.saturating_mul(z).saturating_mul(t) != n {
                notes.push(format!(
                    "ImageJ description (channels={c}, slices={z}, frames={t}) does not match \
                     the {n} pages: its layout and spacing are not applied, pages are z"
                ));
            } else {
                if t > 1 && z > 1 {
                    return Err(StoreError::unsupported(
                        path,
                        "ImageDescription",
                        format!(
                            "an ImageJ time series of {t} frames of {z} slices; brickyard \
                             converts one 3-D (multi-channel) volume"
                        ),
                    ));
                }
                if c > 1 {
                    if format.channels > 1 {
                        return Err(StoreError::unsupported(
                            path,
                            "ImageDescription",
                            format!(
                                "ImageJ channels={c} of pages with {} samples each",
                                format.channels
                            ),
                        ));
                    }
                    page_channels = c;
                    notes.push(format!(
                        "ImageJ channels={c}: interleaved pages read as {c} channels"
                    ));
                }
                if t > 1 {
                    notes.push(format!("ImageJ frames={t} (one slice each) read as z"));
                }
                if let (Some(u), Some(xr), Some(yr)) = (&ij.unit, tags.xres, tags.yres) {
                    let dz = if t > 1 {
                        1.0
                    } else {
                        ij.spacing.unwrap_or(1.0)
                    };
                    spacing = Some([dz, 1.0 / yr, 1.0 / xr]);
                    unit = normalize_unit(u);
                    notes.push(format!(
                        "ImageJ calibration: spacing {}, {}, {dz} {u} (1/XResolution, \
                         1/YResolution, spacing=)",
                        1.0 / xr,
                        1.0 / yr
                    ));
                }
            }
        } else if tags.ome_xml {
            notes.push(
                "OME-TIFF XML metadata not read: pages are z in file order, no spacing".into(),
            );
        }
        if format.min_is_white {
            notes.push(if format.dtype.is_float() {
                "PhotometricInterpretation MinIsWhite: values are 1 − stored, higher is brighter"
                    .to_string()
            } else {
                format!(
                    "PhotometricInterpretation MinIsWhite: values are {} − stored, higher is \
                     brighter",
                    (1u64 << (8 * format.dtype.size())) - 1
                )
            });
        }
        if format.half() {
            notes.push("16-bit float samples stored as float32 (exactly)".to_string());
        }
        if format.ycbcr {
            notes.push(
                "PhotometricInterpretation YCbCr: the stored Y, Cb, Cr samples were converted to \
                 R, G, B (JFIF / BT.601 full range, as libjpeg does)"
                    .to_string(),
            );
        }
        let dims = [
            (n / page_channels) as u64,
            format.height as u64,
            format.width as u64,
        ];
        let channels = if page_channels > 1 {
            page_channels
        } else {
            format.channels
        };
        let mut meta = SourceMeta::new(path, dims, channels, format.dtype);
        meta.spacing = spacing;
        meta.unit = unit;
        meta.notes = notes;
        let mut src = TiffSource {
            meta,
            stack,
            pages,
            format,
            page_channels,
            cache: Mutex::new(ChunkCache::default()),
            decoded: AtomicU64::new(0),
        };
        src.set_cache_bytes(DEFAULT_CACHE_BYTES);
        // What a read decodes whole, beside its encoded bytes, for the
        // converter's memory plan (the cache is within its fixed share).
        src.meta.read_bytes = src.largest_decode_bytes().saturating_mul(2);
        Ok(src)
    }
}

/// Tags of the first page that describe the whole stack.
#[derive(Debug, Default)]
struct PageTags {
    description: Option<String>,
    /// Pixels per unit (`XResolution`, `YResolution`), when positive.
    xres: Option<f64>,
    yres: Option<f64>,
    /// The description is OME-XML.
    ome_xml: bool,
}

/// What an ImageJ `ImageDescription` says about the stack.
#[derive(Debug, PartialEq)]
struct ImageJ {
    channels: usize,
    slices: usize,
    frames: usize,
    /// `spacing=`: the z step.
    spacing: Option<f64>,
    /// `unit=`, absent for `pixel` (uncalibrated).
    unit: Option<String>,
}

impl PageTags {
    /// Read the tags of the decoder's current page; unreadable tags are
    /// treated as absent (they only add metadata).
    fn read<R: Read + Seek>(dec: &mut Decoder<R>) -> PageTags {
        let res = |dec: &mut Decoder<R>, tag| -> Option<f64> {
            let v = match dec.find_tag(tag).ok()?? {
                tiff::decoder::ifd::Value::Rational(n, d) => n as f64 / d as f64,
                _ => return None,
            };
            (v.is_finite() && v > 0.0).then_some(v)
        };
        let description = dec
            .find_tag(Tag::ImageDescription)
            .ok()
            .flatten()
            .and_then(|v| v.into_string().ok());
        let ome_xml = description
            .as_deref()
            .is_some_and(|d| d.trim_start().starts_with("<?xml") && d.contains("<OME"));
        PageTags {
            xres: res(dec, Tag::XResolution),
            yres: res(dec, Tag::YResolution),
            description,
            ome_xml,
        }
    }

    /// The ImageJ metadata, if the description is ImageJ's.
    fn imagej(&self) -> Option<ImageJ> {
        parse_imagej(self.description.as_deref()?)
    }
}

/// Parse an ImageJ `ImageDescription` (`ImageJ=1.54f\nimages=6\nchannels=2
/// \n...`); `None` if it is not one.
fn parse_imagej(d: &str) -> Option<ImageJ> {
    if !d.starts_with("ImageJ=") {
        return None;
    }
    let mut kv = HashMap::new();
    for line in d.lines() {
        if let Some((k, v)) = line.split_once('=') {
            kv.insert(k.trim(), v.trim());
        }
    }
    let count = |k: &str| {
        kv.get(k)
            .and_then(|v| v.parse::<usize>().ok())
            .filter(|&n| n > 0)
    };
    let images = count("images");
    let channels = count("channels").unwrap_or(1);
    let frames = count("frames").unwrap_or(1);
    let slices =
        count("slices").unwrap_or_else(|| images.map_or(1, |i| (i / (channels * frames)).max(1)));
    let spacing = kv
        .get("spacing")
        .and_then(|v| v.parse::<f64>().ok())
        .map(f64::abs)
        .filter(|v| v.is_finite() && *v > 0.0);
    let unit = kv
        .get("unit")
        .map(|u| u.replace("\\u00B5", "µ").replace("\\u00b5", "µ"))
        .filter(|u| !u.is_empty() && !u.eq_ignore_ascii_case("pixel") && u != "pixels");
    Some(ImageJ {
        channels,
        slices,
        frames,
        spacing,
        unit,
    })
}

/// Decoder limits for a file of `file_len` bytes. Pixel data is read into
/// buffers sized here (see [`MAX_CHUNK_BYTES`]) one strip or tile at a time,
/// so only tag values are limited: the decoder sizes them from the counts
/// in the IFD before reading them, so a count is allowed only as large as
/// the file could hold (one byte per value at least), never an absurd one.
fn limits(file_len: u64) -> Limits {
    let value = std::mem::size_of::<tiff::decoder::ifd::Value>() as u64;
    let tag_bytes = file_len.max(64).saturating_mul(value);
    let mut l = Limits::unlimited();
    l.decoding_buffer_size = usize::try_from(tag_bytes).unwrap_or(usize::MAX);
    l.ifd_value_size = l.decoding_buffer_size;
    l
}

/// Most bytes one byte of a strip or tile can decode to, per TIFF
/// compression (`None`: not bounded): PackBits repeats a byte at most 128
/// times for 2 bytes; an LZW code of 9 bits at least yields at most 4096
/// bytes; deflate, see [`MAX_DEFLATE_RATIO`]; a JPEG block of 64 samples
/// (of up to 4 components, up to 16 bits) costs one bit at least.
fn max_ratio(compression: u16) -> Option<u64> {
    match compression {
        1 => Some(1),
        32773 => Some(64),
        5 => Some(4096 * 8 / 9 + 1),
        8 | 32946 => Some(MAX_DEFLATE_RATIO),
        7 => Some(64 * 4 * 2 * 8),
        _ => None,
    }
}

/// Run `f`, turning a panic inside the `tiff` crate into an error.
fn guard<T>(path: &Path, label: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|_| {
        Err(StoreError::invalid(
            path,
            "TIFF data",
            format!("{label}: the TIFF decoder failed on malformed data"),
        ))
    })
}

/// Whether the current page is a reduced-resolution image (thumbnail,
/// pyramid level): `NewSubfileType` bit 0.
fn is_reduced<R: Read + Seek>(dec: &mut Decoder<R>, path: &Path, label: &str) -> Result<bool> {
    let t = dec
        .find_tag_unsigned::<u32>(Tag::NewSubfileType)
        .map_err(|e| tiff_error(path, label, "NewSubfileType", e))?;
    Ok(t.is_some_and(|t| t & 1 == 1))
}

/// Size, sample type and channels of the current page, its strip or tile
/// size, and whether its regions can be read without decoding (see
/// [`PageGeom::raw`]).
fn page_info<R: Read + Seek>(
    dec: &mut Decoder<R>,
    path: &Path,
    label: &str,
) -> Result<(PageFormat, (u32, u32), bool)> {
    let err = |field: &'static str| move |e: TiffError| tiff_error(path, label, field, e);
    let (width, height) = dec.dimensions().map_err(err("ImageWidth"))?;
    let color = dec.colortype().map_err(err("PhotometricInterpretation"))?;
    if let ColorType::Palette(_) = color {
        return Err(StoreError::unsupported(
            path,
            "PhotometricInterpretation",
            format!("{label}: palette (indexed colour) images"),
        ));
    }
    let compression = dec
        .find_tag_unsigned::<u16>(Tag::Compression)
        .map_err(err("Compression"))?
        .unwrap_or(1);
    if let Some(name) = unsupported_compression(compression) {
        return Err(StoreError::unsupported(
            path,
            "Compression",
            format!("{label}: compression {compression} ({name})"),
        ));
    }
    let bits = color.bit_depth();
    let photometric = dec
        .find_tag_unsigned::<u16>(Tag::PhotometricInterpretation)
        .map_err(err("PhotometricInterpretation"))?;
    let min_is_white = photometric == Some(0);
    let spp = dec
        .find_tag_unsigned::<u16>(Tag::SamplesPerPixel)
        .map_err(err("SamplesPerPixel"))?
        .unwrap_or(1);
    let sample_format = dec
        .find_tag_unsigned_vec::<u16>(Tag::SampleFormat)
        .map_err(err("SampleFormat"))?
        .and_then(|v| v.first().copied())
        .unwrap_or(1);
    let planar = match dec
        .find_tag_unsigned::<u16>(Tag::PlanarConfiguration)
        .map_err(err("PlanarConfiguration"))?
        .unwrap_or(1)
    {
        1 => false,
        2 => true,
        v => {
            return Err(StoreError::invalid(
                path,
                "PlanarConfiguration",
                format!("{label}: {v} is neither 1 (chunky) nor 2 (planar)"),
            ))
        }
    };
    let dtype = match (sample_format, bits) {
        (1, 8) => DType::U8,
        (1, 16) => DType::U16,
        (1, 32) => DType::U32,
        (2, 8) => DType::I8,
        (2, 16) => DType::I16,
        (2, 32) => DType::I32,
        // 16-bit floats are widened to f32 (every f16 value is exact in f32).
        (3, 16) | (3, 32) => DType::F32,
        (3, 64) => DType::F64,
        (1..=3, b) if !matches!(b, 8 | 16 | 32 | 64) => {
            return Err(StoreError::unsupported(
                path,
                "BitsPerSample",
                format!(
                    "{label}: {b}-bit samples; supported are 8, 16 and 32 bits (64 for floats)"
                ),
            ))
        }
        (sf, b) => {
            let kind = match sf {
                1 => "unsigned integer",
                2 => "signed integer",
                3 => "floating point",
                4 => "undefined",
                5 => "complex integer",
                6 => "complex floating point",
                _ => "unknown",
            };
            return Err(StoreError::unsupported(
                path,
                "SampleFormat",
                format!(
                    "{label}: {b}-bit {kind} samples (SampleFormat {sf}); supported are \
                     8/16/32-bit integers and 16/32/64-bit floats"
                ),
            ));
        }
    };
    let channels = if planar {
        spp as usize
    } else {
        color.num_samples() as usize
    };
    if min_is_white && (channels > 1 || sample_format == 2) {
        return Err(StoreError::unsupported(
            path,
            "PhotometricInterpretation",
            format!(
                "{label}: MinIsWhite (0) with {}; brickyard inverts MinIsWhite only for \
                 single-sample unsigned integer or float images",
                if channels > 1 {
                    format!("{channels} samples per pixel")
                } else {
                    "signed samples".to_string()
                }
            ),
        ));
    }
    let ycbcr = photometric == Some(6);
    if ycbcr {
        check_ycbcr(dec, path, label, compression, bits, planar)?;
    }
    let predictor = dec
        .find_tag_unsigned::<u16>(Tag::Predictor)
        .map_err(err("Predictor"))?
        .unwrap_or(1);
    let half = sample_format == 3 && bits == 16;
    let raw = compression == 1 && predictor == 1 && !min_is_white && !ycbcr && !half;
    let chunk = dec.chunk_dimensions();
    if chunk.0 == 0 || chunk.1 == 0 {
        return Err(StoreError::invalid(
            path,
            "RowsPerStrip",
            format!("{label}: strips or tiles of size {}×{}", chunk.0, chunk.1),
        ));
    }
    let format = PageFormat {
        width,
        height,
        bits,
        sample_format,
        dtype,
        channels,
        planar,
        min_is_white,
        ycbcr,
    };
    Ok((format, chunk, raw))
}

/// Refuse YCbCr pages that are not converted right (see the [module
/// docs](self)): other than 8-bit chunky; not JPEG-compressed and
/// subsampled (the decoder reads no subsampled data), or with other than
/// the default coefficients or full-range reference values.
fn check_ycbcr<R: Read + Seek>(
    dec: &mut Decoder<R>,
    path: &Path,
    label: &str,
    compression: u16,
    bits: u8,
    planar: bool,
) -> Result<()> {
    if bits != 8 || planar {
        return Err(StoreError::unsupported(
            path,
            "PhotometricInterpretation",
            format!(
                "{label}: YCbCr (6) with {}; brickyard converts YCbCr to RGB for 8-bit samples \
                 stored chunky (PlanarConfiguration 1) only",
                if planar {
                    "planar-separate samples".to_string()
                } else {
                    format!("{bits}-bit samples")
                }
            ),
        ));
    }
    if compression == 7 {
        // The JPEG decoder upsamples the chroma; like libtiff's and
        // tifffile's readers, the JFIF conversion ignores the coefficient
        // and reference tags.
        return Ok(());
    }
    let err = |field: &'static str| move |e: TiffError| tiff_error(path, label, field, e);
    let sub = dec
        .find_tag_unsigned_vec::<u16>(Tag::ChromaSubsampling)
        .map_err(err("YCbCrSubSampling"))?
        .unwrap_or_else(|| vec![2, 2]);
    if sub != [1, 1] {
        return Err(StoreError::unsupported(
            path,
            "YCbCrSubSampling",
            format!(
                "{label}: YCbCr (PhotometricInterpretation 6) subsampled {} with compression \
                 {compression}; brickyard reads subsampled YCbCr only JPEG-compressed \
                 (compression 7), other YCbCr only with YCbCrSubSampling 1,1 (the default, when \
                 the tag is absent, is 2,2)",
                sub.iter()
                    .map(|v| v.to_string())
                    .collect::<Vec<_>>()
                    .join(",")
            ),
        ));
    }
    let numbers = |dec: &mut Decoder<R>, code: u16, field: &'static str| {
        dec.find_tag(Tag::from_u16_exhaustive(code))
            .map_err(err(field))
            .map(|v| v.map(tag_numbers))
    };
    for (code, field, want) in [
        (529, "YCbCrCoefficients", &[0.299, 0.587, 0.114][..]),
        (
            532,
            "ReferenceBlackWhite",
            &[0.0, 255.0, 128.0, 255.0, 128.0, 255.0][..],
        ),
    ] {
        let Some(got) = numbers(dec, code, field)? else {
            continue;
        };
        let same = got.len() == want.len()
            && got
                .iter()
                .zip(want)
                .all(|(g, w)| (g - w).abs() <= 1e-3 * w.max(1.0));
        if !same {
            return Err(StoreError::unsupported(
                path,
                field,
                format!(
                    "{label}: {field} {got:?} with YCbCr not JPEG-compressed; brickyard \
                     converts such YCbCr with the default {want:?} only"
                ),
            ));
        }
    }
    Ok(())
}

/// The numbers of a tag value (rationals as their quotient); values that
/// are not numbers become NaN.
fn tag_numbers(v: tiff::decoder::ifd::Value) -> Vec<f64> {
    use tiff::decoder::ifd::Value;
    match v {
        Value::List(l) => l.into_iter().flat_map(tag_numbers).collect(),
        Value::Rational(n, d) => vec![n as f64 / d as f64],
        Value::SRational(n, d) => vec![n as f64 / d as f64],
        Value::Byte(v) => vec![v as f64],
        Value::Short(v) => vec![v as f64],
        Value::Unsigned(v) => vec![v as f64],
        Value::UnsignedBig(v) => vec![v as f64],
        Value::Float(v) => vec![v as f64],
        Value::Double(v) => vec![v],
        _ => vec![f64::NAN],
    }
}

/// Convert 8-bit Y, Cb, Cr triples to R, G, B in place, with the JFIF
/// (BT.601 full range) equations libjpeg uses, rounded and clamped:
/// R = Y + 1.402 (Cr − 128), G = Y − 0.344136 (Cb − 128) − 0.714136 (Cr −
/// 128), B = Y + 1.772 (Cb − 128).
fn ycbcr_to_rgb(data: &mut [u8]) {
    for px in data.chunks_exact_mut(3) {
        let y = px[0] as f32;
        let cb = px[1] as f32 - 128.0;
        let cr = px[2] as f32 - 128.0;
        let to_u8 = |v: f32| v.round().clamp(0.0, 255.0) as u8;
        px[0] = to_u8(y + 1.402 * cr);
        px[1] = to_u8(y - 0.344136 * cb - 0.714136 * cr);
        px[2] = to_u8(y + 1.772 * cb);
    }
}

/// Native-endian f16 samples as native-endian f32 ones (exact: f32 holds
/// every f16 value, infinities and NaNs included).
fn widen_f16(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(data.len() * 2);
    for b in data.chunks_exact(2) {
        let v = half::f16::from_bits(u16::from_ne_bytes([b[0], b[1]])).to_f32();
        out.extend_from_slice(&v.to_ne_bytes());
    }
    out
}

/// The name of a compression the `tiff` crate cannot decode, if it is one.
fn unsupported_compression(code: u16) -> Option<&'static str> {
    match code {
        // None, CCITT G4, LZW, JPEG, Adobe Deflate, PackBits, Deflate,
        // Zstandard.
        1 | 4 | 5 | 7 | 8 | 32773 | 32946 | 50000 => None,
        2 => Some("CCITT RLE"),
        3 => Some("CCITT G3 fax"),
        6 => Some("old-style JPEG"),
        34712 => Some("JPEG 2000"),
        34887 => Some("LERC"),
        34925 => Some("LZMA"),
        50001 => Some("WebP"),
        _ => Some("unknown"),
    }
}

/// Check that every strip or tile of the current page lies inside the file
/// and that together they can hold the page: as many bytes as its pixels
/// need when uncompressed, at least that divided by the compression's
/// [`max_ratio`] otherwise. Returns the bytes the page needs and the
/// compression's largest ratio (`u64::MAX` when unbounded).
fn check_chunk_extents<R: Read + Seek>(
    dec: &mut Decoder<R>,
    path: &Path,
    label: &str,
    file_len: u64,
    fmt: &PageFormat,
) -> Result<(u64, u64)> {
    let (offsets_tag, counts_tag, what) = match dec.get_chunk_type() {
        ChunkType::Strip => (Tag::StripOffsets, Tag::StripByteCounts, "strip"),
        ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts, "tile"),
    };
    let offsets = dec
        .get_tag_u64_vec(offsets_tag)
        .map_err(|e| tiff_error(path, label, &format!("{offsets_tag:?}"), e))?;
    let counts = dec
        .get_tag_u64_vec(counts_tag)
        .map_err(|e| tiff_error(path, label, &format!("{counts_tag:?}"), e))?;
    for (k, (&o, &n)) in offsets.iter().zip(&counts).enumerate() {
        match o.checked_add(n) {
            Some(end) if end <= file_len => {}
            end => {
                return Err(StoreError::invalid(
                    path,
                    format!("{counts_tag:?}"),
                    format!(
                        "{label}: {what} {k} ends at byte {} but the file holds only {file_len} \
                         bytes (truncated file?)",
                        end.map_or_else(|| "2^64+".to_string(), |e| e.to_string())
                    ),
                ))
            }
        }
    }
    let need = (fmt.width as u64)
        .saturating_mul(fmt.height as u64)
        .saturating_mul(fmt.channels as u64)
        .saturating_mul(fmt.stored_size() as u64);
    let compression = dec
        .find_tag_unsigned::<u16>(Tag::Compression)
        .map_err(|e| tiff_error(path, label, "Compression", e))?
        .unwrap_or(1);
    let ratio = max_ratio(compression).unwrap_or(u64::MAX);
    let held: u64 = counts
        .iter()
        .take(offsets.len())
        .fold(0, |a, &n| a.saturating_add(n));
    let most = held.saturating_mul(ratio);
    if need > most {
        let how = if ratio == 1 {
            "uncompressed".to_string()
        } else {
            format!("compression {compression} decodes at most {ratio}-fold, to {most} bytes")
        };
        return Err(StoreError::invalid(
            path,
            format!("{counts_tag:?}"),
            format!(
                "{label}: the {what}s hold {held} bytes ({how}) but {}×{} pixels × {} \
                 sample(s) of {} need {need}",
                fmt.width, fmt.height, fmt.channels, fmt.dtype
            ),
        ));
    }
    Ok((need, ratio))
}

/// Check that a page agrees with the first one.
fn same_format(
    f0: &PageFormat,
    label0: &str,
    f: &PageFormat,
    label: &str,
    path: &Path,
) -> Result<()> {
    let (field, what, want) = if (f.width, f.height) != (f0.width, f0.height) {
        let field = if f.width != f0.width {
            "ImageWidth"
        } else {
            "ImageLength"
        };
        (
            field,
            format!("{}×{}", f.width, f.height),
            format!("{}×{}", f0.width, f0.height),
        )
    } else if f.bits != f0.bits {
        ("BitsPerSample", f.bits.to_string(), f0.bits.to_string())
    } else if f.sample_format != f0.sample_format {
        (
            "SampleFormat",
            f.sample_format.to_string(),
            f0.sample_format.to_string(),
        )
    } else if f.channels != f0.channels {
        (
            "SamplesPerPixel",
            f.channels.to_string(),
            f0.channels.to_string(),
        )
    } else if f.planar != f0.planar {
        (
            "PlanarConfiguration",
            (f.planar as u8 + 1).to_string(),
            (f0.planar as u8 + 1).to_string(),
        )
    } else if f.ycbcr != f0.ycbcr {
        let name = |y: bool| if y { "6 (YCbCr)" } else { "not YCbCr" };
        (
            "PhotometricInterpretation",
            name(f.ycbcr).to_string(),
            name(f0.ycbcr).to_string(),
        )
    } else if f.min_is_white != f0.min_is_white {
        let name = |w: bool| {
            if w {
                "0 (MinIsWhite)"
            } else {
                "not MinIsWhite"
            }
        };
        (
            "PhotometricInterpretation",
            name(f.min_is_white).to_string(),
            name(f0.min_is_white).to_string(),
        )
    } else {
        return Ok(());
    };
    Err(StoreError::invalid(
        path,
        field,
        format!("{label} has {what} but {label0} has {want}; all pages must agree"),
    ))
}

/// Turn a `tiff` crate error into a store error naming the file, page and
/// (where the error tells it) the offending tag.
fn tiff_error(path: &Path, label: &str, field: &str, e: TiffError) -> StoreError {
    let field = match &e {
        TiffError::FormatError(f) => match f {
            TiffFormatError::RequiredTagNotFound(t)
            | TiffFormatError::InvalidTagValueType(t)
            | TiffFormatError::InvalidCountForTag(t, _) => format!("{t:?}"),
            TiffFormatError::InvalidDimensions(..) => "ImageWidth".into(),
            TiffFormatError::TiffSignatureNotFound | TiffFormatError::TiffSignatureInvalid => {
                "header".into()
            }
            TiffFormatError::ImageFileDirectoryNotFound | TiffFormatError::CycleInOffsets => {
                "IFD".into()
            }
            TiffFormatError::UnknownPlanarConfiguration(_) => "PlanarConfiguration".into(),
            TiffFormatError::UnknownPredictor(_) => "Predictor".into(),
            TiffFormatError::SamplesPerPixelIsZero => "SamplesPerPixel".into(),
            _ => field.into(),
        },
        TiffError::UnsupportedError(u) => match u {
            TiffUnsupportedError::InconsistentBitsPerSample(_) => "BitsPerSample".into(),
            TiffUnsupportedError::UnsupportedSampleFormat(_) => "SampleFormat".into(),
            TiffUnsupportedError::UnknownCompressionMethod
            | TiffUnsupportedError::UnsupportedCompressionMethod(_) => "Compression".into(),
            TiffUnsupportedError::UnknownInterpretation
            | TiffUnsupportedError::InterpretationWithBits(..) => {
                "PhotometricInterpretation".into()
            }
            _ => field.into(),
        },
        _ => field.into(),
    };
    match e {
        TiffError::IoError(io) if io.kind() == io::ErrorKind::UnexpectedEof => StoreError::invalid(
            path,
            field,
            format!("{label}: the file ends early (truncated?): {io}"),
        ),
        // Decompressors report damaged data as I/O errors of these kinds.
        TiffError::IoError(io)
            if field == "strip data"
                && matches!(
                    io.kind(),
                    io::ErrorKind::InvalidData | io::ErrorKind::InvalidInput | io::ErrorKind::Other
                ) =>
        {
            StoreError::invalid(
                path,
                field,
                format!("{label}: a strip or tile does not decode (damaged data?): {io}"),
            )
        }
        TiffError::IoError(io) => StoreError::io(path, io),
        TiffError::LimitsExceeded if field == "strip data" => StoreError::unsupported(
            path,
            field,
            format!("{label}: a strip or tile is too large to decode in one piece"),
        ),
        // Only tag values are limited otherwise (see `limits`).
        TiffError::LimitsExceeded => StoreError::invalid(
            path,
            field,
            format!("{label}: a tag claims more values than the file could hold (damaged IFD?)"),
        ),
        TiffError::UnsupportedError(_) => {
            StoreError::unsupported(path, field, format!("{label}: {e}"))
        }
        _ => StoreError::invalid(path, field, format!("{label}: {e}")),
    }
}

/// The strips or tiles of an uncompressed page, for reads without decoding:
/// the file holding them, where each starts and how many bytes it holds,
/// and whether samples need their bytes swapped (file byte order not
/// native).
struct RawPage {
    file: Arc<File>,
    offsets: Vec<u64>,
    counts: Vec<u64>,
    swap: bool,
}

/// One decoded strip or tile: `width × height` pixels of native-endian
/// samples (all samples of a pixel together for chunky images).
struct Chunk {
    data: Vec<u8>,
    width: u32,
    height: u32,
}

/// Decode strip or tile `idx` of the decoder's current page.
fn decode_chunk<R: Read + Seek>(
    dec: &mut Decoder<R>,
    idx: u32,
    pixel_bytes: usize,
) -> std::result::Result<Chunk, TiffError> {
    let (width, height) = dec.chunk_data_dimensions(idx);
    let n = (width as u64)
        .checked_mul(height as u64)
        .and_then(|n| n.checked_mul(pixel_bytes as u64))
        .filter(|&n| n <= MAX_CHUNK_BYTES)
        .and_then(|n| usize::try_from(n).ok())
        .ok_or(TiffError::LimitsExceeded)?;
    let mut data = vec![0u8; n];
    dec.read_chunk_bytes(idx, &mut data)?;
    Ok(Chunk {
        data,
        width,
        height,
    })
}

/// LRU cache of decoded chunks, keyed by (page, chunk index), bounded in
/// bytes.
#[derive(Default)]
struct ChunkCache {
    map: HashMap<(usize, u32), (Arc<Chunk>, u64)>,
    bytes: usize,
    budget: usize,
    /// The most bytes held at once.
    peak: usize,
    tick: u64,
}

impl ChunkCache {
    fn get(&mut self, key: (usize, u32)) -> Option<Arc<Chunk>> {
        self.tick += 1;
        let tick = self.tick;
        self.map.get_mut(&key).map(|(c, used)| {
            *used = tick;
            c.clone()
        })
    }

    fn insert(&mut self, key: (usize, u32), chunk: Arc<Chunk>) {
        let n = chunk.data.len();
        if n > self.budget || self.map.contains_key(&key) {
            return;
        }
        self.shrink_to(self.budget - n);
        self.tick += 1;
        self.bytes += n;
        self.peak = self.peak.max(self.bytes);
        self.map.insert(key, (chunk, self.tick));
    }

    /// Evict least recently used chunks until at most `bytes` are held.
    fn shrink_to(&mut self, bytes: usize) {
        while self.bytes > bytes {
            let Some(key) = self
                .map
                .iter()
                .min_by_key(|(_, (_, used))| *used)
                .map(|(k, _)| *k)
            else {
                break;
            };
            if let Some((c, _)) = self.map.remove(&key) {
                self.bytes -= c.data.len();
            }
        }
    }
}

/// A `Read + Seek` view of a shared file using positioned reads, so that
/// several decoders can read one file at once. Optionally it shows a
/// rewritten TIFF header whose first-IFD pointer is a given page's IFD:
/// a decoder opened on it starts directly at that page.
struct PageReader {
    file: Arc<File>,
    len: u64,
    pos: u64,
    header: [u8; 16],
    header_len: usize,
}

impl PageReader {
    /// The file as it is.
    fn new(file: Arc<File>, len: u64) -> Self {
        PageReader {
            file,
            len,
            pos: 0,
            header: [0; 16],
            header_len: 0,
        }
    }

    /// The file with its header pointing at the IFD at offset `ifd`.
    fn at_ifd(file: Arc<File>, len: u64, byte_order: [u8; 2], bigtiff: bool, ifd: u64) -> Self {
        let be = byte_order == *b"MM";
        let u16b = |v: u16| if be { v.to_be_bytes() } else { v.to_le_bytes() };
        let mut header = [0u8; 16];
        header[..2].copy_from_slice(&byte_order);
        let header_len = if bigtiff {
            header[2..4].copy_from_slice(&u16b(43));
            header[4..6].copy_from_slice(&u16b(8));
            header[6..8].copy_from_slice(&u16b(0));
            let p = if be {
                ifd.to_be_bytes()
            } else {
                ifd.to_le_bytes()
            };
            header[8..16].copy_from_slice(&p);
            16
        } else {
            header[2..4].copy_from_slice(&u16b(42));
            // Classic TIFF offsets are 32-bit, so `ifd` fits.
            let ifd = ifd as u32;
            let p = if be {
                ifd.to_be_bytes()
            } else {
                ifd.to_le_bytes()
            };
            header[4..8].copy_from_slice(&p);
            8
        };
        PageReader {
            file,
            len,
            pos: 0,
            header,
            header_len,
        }
    }
}

impl Read for PageReader {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.pos < self.header_len as u64 {
            let h = &self.header[self.pos as usize..self.header_len];
            let n = h.len().min(buf.len());
            buf[..n].copy_from_slice(&h[..n]);
            self.pos += n as u64;
            return Ok(n);
        }
        let n = read_at(&self.file, buf, self.pos)?;
        self.pos += n as u64;
        Ok(n)
    }
}

impl Seek for PageReader {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        let pos = match to {
            SeekFrom::Start(p) => Some(p),
            SeekFrom::End(d) => self.len.checked_add_signed(d),
            SeekFrom::Current(d) => self.pos.checked_add_signed(d),
        };
        self.pos = pos.ok_or_else(|| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                "seek before the start of the file",
            )
        })?;
        Ok(self.pos)
    }
}

/// Fill `buf` from `file` at byte `offset` (`UnexpectedEof` if the file
/// ends first).
fn read_exact_at(file: &File, mut buf: &mut [u8], mut offset: u64) -> io::Result<()> {
    while !buf.is_empty() {
        match read_at(file, buf, offset)? {
            0 => {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    format!("no data at byte {offset}"),
                ))
            }
            n => {
                buf = &mut buf[n..];
                offset += n as u64;
            }
        }
    }
    Ok(())
}

/// Read from `file` at byte `offset` (a short count only at end of file).
#[cfg(unix)]
fn read_at(file: &File, buf: &mut [u8], offset: u64) -> io::Result<usize> {
    loop {
        match std::os::unix::fs::FileExt::read_at(file, buf, offset) {
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            r => return r,
        }
    }
}

/// Read from `file` at byte `offset` (a short count only at end of file).
#[cfg(windows)]
fn read_at(file: &File, buf: &mut [u8], offset: u64) -> io::Result<usize> {
    loop {
        match std::os::windows::fs::FileExt::seek_read(file, buf, offset) {
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            r => return r,
        }
    }
}

/// The regular files of a directory as (name, path); names that are not
/// valid UTF-8 are skipped.
fn list_dir(dir: &Path) -> Result<Vec<(String, PathBuf)>> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).at(dir)? {
        let entry = entry.at(dir)?;
        let path = entry.path();
        if !path.is_file() {
            continue;
        }
        if let Some(name) = entry.file_name().to_str() {
            out.push((name.to_string(), path));
        }
    }
    Ok(out)
}

/// Sort paths by file name in natural order.
fn sort_natural(files: &mut [PathBuf]) {
    files.sort_by(|a, b| {
        let name = |p: &PathBuf| p.file_name().map(|n| n.to_string_lossy().into_owned());
        natural_cmp(&name(a).unwrap_or_default(), &name(b).unwrap_or_default())
    });
}

/// Natural order: runs of digits compare as numbers (`img2` < `img10`),
/// other characters case-insensitively; ties are broken by plain order.
fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (mut i, mut j) = (a.char_indices().peekable(), b.char_indices().peekable());
    loop {
        let (x, y) = match (i.peek(), j.peek()) {
            (None, None) => return a.cmp(b),
            (None, Some(_)) => return Ordering::Less,
            (Some(_), None) => return Ordering::Greater,
            (Some(&(_, x)), Some(&(_, y))) => (x, y),
        };
        if x.is_ascii_digit() && y.is_ascii_digit() {
            let digits = |it: &mut std::iter::Peekable<std::str::CharIndices>, s: &str| {
                let start = it.peek().map_or(s.len(), |&(k, _)| k);
                while it.next_if(|&(_, c)| c.is_ascii_digit()).is_some() {}
                let end = it.peek().map_or(s.len(), |&(k, _)| k);
                s[start..end].trim_start_matches('0').to_string()
            };
            let (da, db) = (digits(&mut i, a), digits(&mut j, b));
            let o = da.len().cmp(&db.len()).then_with(|| da.cmp(&db));
            if o != Ordering::Equal {
                return o;
            }
        } else {
            let o = x.to_lowercase().cmp(y.to_lowercase());
            if o != Ordering::Equal {
                return o;
            }
            i.next();
            j.next();
        }
    }
}

/// Whether `name` matches `pattern`, where `*` matches any run of
/// characters and `?` any single character.
fn wildcard_match(pattern: &str, name: &str) -> bool {
    let p: Vec<char> = pattern.chars().collect();
    let n: Vec<char> = name.chars().collect();
    let (mut i, mut j) = (0, 0);
    // Position of the last `*` and the name position it is tried at.
    let mut star: Option<(usize, usize)> = None;
    while j < n.len() {
        // One pattern element at `i` that takes `n[j]`: where the pattern
        // goes on.
        let one = match p.get(i) {
            Some('*') | None => None,
            Some('?') => Some(i + 1),
            Some('[') => match class_at(&p, i) {
                Some((takes, next)) => takes(n[j]).then_some(next),
                None => (n[j] == '[').then_some(i + 1),
            },
            Some(&c) => (c == n[j]).then_some(i + 1),
        };
        if p.get(i) == Some(&'*') {
            star = Some((i, j));
            i += 1;
        } else if let Some(next) = one {
            i = next;
            j += 1;
        } else if let Some((si, sj)) = star {
            i = si + 1;
            j = sj + 1;
            star = Some((si, sj + 1));
        } else {
            return false;
        }
    }
    p[i..].iter().all(|&c| c == '*')
}

/// The character class `[...]` at `p[i]` (`[!...]` or `[^...]` negated,
/// `a-z` ranges, a `]` first taken as itself): what it takes, and where
/// the pattern goes on; `None` without a closing `]`.
#[allow(clippy::type_complexity)]
fn class_at(p: &[char], i: usize) -> Option<(Box<dyn Fn(char) -> bool>, usize)> {
    let mut k = i + 1;
    let negated = matches!(p.get(k), Some('!') | Some('^'));
    if negated {
        k += 1;
    }
    let first = k;
    let mut ranges: Vec<(char, char)> = vec![];
    while k < p.len() && (p[k] != ']' || k == first) {
        if k + 2 < p.len() && p[k + 1] == '-' && p[k + 2] != ']' {
            ranges.push((p[k], p[k + 2]));
            k += 3;
        } else {
            ranges.push((p[k], p[k]));
            k += 1;
        }
    }
    if k >= p.len() {
        return None;
    }
    let takes = move |c: char| ranges.iter().any(|&(a, b)| a <= c && c <= b) != negated;
    Some((Box::new(takes), k + 1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::test_util::{read_all, read_stitched};
    use std::io::BufWriter;
    use tiff::decoder::DecodingResult;
    use tiff::encoder::{colortype, compression::DeflateLevel, Compression, TiffEncoder};
    use tiff::encoder::{TiffKind, TiffKindBig, TiffKindStandard, TiffValue};

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

    fn bytes<T: Copy>(v: &[T]) -> Vec<u8> {
        let n = std::mem::size_of_val(v);
        // SAFETY: test helper over plain numeric types.
        unsafe { std::slice::from_raw_parts(v.as_ptr() as *const u8, n) }.to_vec()
    }

    #[test]
    fn nuclei_real_file() {
        let path = shared("nuclei-confocal-u16.tif");
        let src = open(&path).unwrap();
        let m = src.meta();
        assert_eq!(m.dims, [60, 256, 256]);
        assert_eq!(m.channels, 1);
        assert_eq!(m.dtype, DType::U16);
        assert_eq!(m.spacing, None);
        assert!(src.slice_files().is_none());

        let whole = read_all(&src, 0);
        let stitched = read_stitched(&src, 0, [25, 100, 90]);
        assert!(
            stitched == whole,
            "stitched sub-region reads differ from the whole read"
        );

        // Independent decode with the tiff crate's plain decoder API.
        let mut dec = Decoder::new(File::open(&path).unwrap()).unwrap();
        let page = 256 * 256 * 2;
        for k in [0usize, 31, 59] {
            dec.seek_to_image(k).unwrap();
            let DecodingResult::U16(v) = dec.read_image().unwrap() else {
                panic!("page {k} is not u16");
            };
            assert!(
                bytes(&v) == whole[k * page..(k + 1) * page],
                "page {k} differs from an independent decode"
            );
        }
        // Not a constant image.
        let first: Vec<u16> = whole[..page]
            .chunks_exact(2)
            .map(|b| u16::from_ne_bytes([b[0], b[1]]))
            .collect();
        assert!(first.iter().max() > first.iter().min());
    }

    /// Write `pages` as a multi-page TIFF (or BigTIFF, depending on `K`).
    fn write_pages<C, K>(
        path: &Path,
        w: u32,
        h: u32,
        pages: &[Vec<C::Inner>],
        comp: Compression,
        rows: Option<u32>,
    ) where
        C: colortype::ColorType,
        K: TiffKind,
        [C::Inner]: TiffValue,
    {
        let f = BufWriter::new(File::create(path).unwrap());
        let mut enc = TiffEncoder::<_, K>::new_generic(f)
            .unwrap()
            .with_compression(comp);
        for p in pages {
            let mut img = enc.new_image::<C>(w, h).unwrap();
            if let Some(r) = rows {
                img.rows_per_strip(r).unwrap();
            }
            img.write_data(p).unwrap();
        }
    }

    #[test]
    fn multipage_u8_lzw_strips() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h, n) = (37u32, 29u32, 5usize);
        let pages: Vec<Vec<u8>> = (0..n)
            .map(|z| {
                (0..w * h)
                    .map(|i| (i as usize * 7 + z * 31) as u8)
                    .collect()
            })
            .collect();
        let path = dir.path().join("u8.tif");
        write_pages::<colortype::Gray8, TiffKindStandard>(
            &path,
            w,
            h,
            &pages,
            Compression::Lzw,
            Some(3),
        );
        let want: Vec<u8> = pages.concat();
        for cache in [0, 2000, DEFAULT_CACHE_BYTES] {
            let src = open(&path).unwrap().with_cache_bytes(cache);
            assert_eq!(src.meta().dims, [5, 29, 37]);
            assert_eq!(src.meta().dtype, DType::U8);
            assert_eq!(read_all(&src, 0), want);
            assert_eq!(read_stitched(&src, 0, [2, 4, 10]), want, "cache {cache}");
            assert_eq!(read_stitched(&src, 0, [1, 29, 37]), want);
        }
    }

    #[test]
    fn multipage_f32_deflate() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (20u32, 11u32);
        let pages: Vec<Vec<f32>> = (0..4)
            .map(|z| {
                (0..w * h)
                    .map(|i| i as f32 * 0.5 - z as f32 * 100.25)
                    .collect()
            })
            .collect();
        let path = dir.path().join("f32.tiff");
        let comp = Compression::Deflate(DeflateLevel::Fast);
        write_pages::<colortype::Gray32Float, TiffKindStandard>(&path, w, h, &pages, comp, Some(4));
        let src = open(&path).unwrap();
        assert_eq!(src.meta().dims, [4, 11, 20]);
        assert_eq!(src.meta().dtype, DType::F32);
        let want = bytes(&pages.concat());
        assert_eq!(read_all(&src, 0), want);
        assert_eq!(read_stitched(&src, 0, [3, 5, 7]), want);
    }

    #[test]
    fn bigtiff_multipage() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (16u32, 9u32);
        let pages: Vec<Vec<u16>> = (0..7)
            .map(|z| (0..w * h).map(|i| (i * 300 + z * 7) as u16).collect())
            .collect();
        let path = dir.path().join("big.tif");
        write_pages::<colortype::Gray16, TiffKindBig>(
            &path,
            w,
            h,
            &pages,
            Compression::Packbits,
            None,
        );
        assert_eq!(
            &std::fs::read(&path).unwrap()[2..4],
            &[43, 0],
            "a BigTIFF file"
        );
        let src = open(&path).unwrap();
        assert_eq!(src.meta().dims, [7, 9, 16]);
        assert_eq!(src.meta().dtype, DType::U16);
        let want = bytes(&pages.concat());
        assert_eq!(read_all(&src, 0), want);
        assert_eq!(read_stitched(&src, 0, [2, 2, 5]), want);
    }

    /// Set tag `tag` (a SHORT held in the entry) of every IFD of a classic
    /// little-endian TIFF to `value`.
    fn patch_short_tag(bytes: &mut [u8], tag: u16, value: u16) {
        let u16at = |b: &[u8], o: usize| u16::from_le_bytes([b[o], b[o + 1]]);
        let u32at = |b: &[u8], o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
        assert_eq!(&bytes[..4], b"II*\0");
        let mut ifd = u32at(bytes, 4) as usize;
        let mut found = 0;
        while ifd != 0 {
            let n = u16at(bytes, ifd) as usize;
            for e in 0..n {
                let o = ifd + 2 + 12 * e;
                if u16at(bytes, o) == tag {
                    assert_eq!(u16at(bytes, o + 2), 3, "a SHORT");
                    bytes[o + 8..o + 10].copy_from_slice(&value.to_le_bytes());
                    found += 1;
                }
            }
            ifd = u32at(bytes, ifd + 2 + 12 * n) as usize;
        }
        assert!(found > 0, "tag {tag} not found");
    }

    /// The horizontal-differencing predictor is undone: the values read are
    /// the values written. (The encoder writes no floating-point predictor;
    /// the decoder undoes that one the same way.)
    #[test]
    fn predictor_is_undone() {
        use tiff::tags::Predictor;
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (23u32, 6u32);
        let pages: Vec<Vec<u16>> = (0..3)
            .map(|z| (0..w * h).map(|i| (i * 977 + z * 13) as u16).collect())
            .collect();
        let path = dir.path().join("pred.tif");
        {
            let f = BufWriter::new(File::create(&path).unwrap());
            let mut enc = TiffEncoder::new(f)
                .unwrap()
                .with_compression(Compression::Lzw)
                .with_predictor(Predictor::Horizontal);
            for p in &pages {
                enc.write_image::<colortype::Gray16>(w, h, p).unwrap();
            }
        }
        let src = open(&path).unwrap();
        assert_eq!(read_all(&src, 0), bytes(&pages.concat()));
        assert_eq!(read_stitched(&src, 0, [2, 4, 5]), bytes(&pages.concat()));
    }

    /// MinIsWhite: unsigned values are inverted (`max − stored`) and the
    /// report says so; signed MinIsWhite is refused.
    #[test]
    fn min_is_white() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (9u32, 4u32);
        let pages: Vec<Vec<u16>> = (0..2)
            .map(|z| (0..w * h).map(|i| (i * 1000 + z) as u16).collect())
            .collect();
        let path = dir.path().join("white.tif");
        write_pages::<colortype::Gray16, TiffKindStandard>(
            &path,
            w,
            h,
            &pages,
            Compression::Uncompressed,
            None,
        );
        let mut b = std::fs::read(&path).unwrap();
        patch_short_tag(&mut b, 262, 0);
        std::fs::write(&path, &b).unwrap();
        let src = open(&path).unwrap();
        assert_eq!(src.meta().dtype, DType::U16);
        let want: Vec<u16> = pages.concat().iter().map(|v| u16::MAX - v).collect();
        assert_eq!(read_all(&src, 0), bytes(&want));
        assert_eq!(
            src.meta().notes,
            vec![
                "PhotometricInterpretation MinIsWhite: values are 65535 − stored, higher is \
                 brighter"
                    .to_string()
            ]
        );

        let ipages: Vec<Vec<i16>> = vec![(0..(w * h) as i16).collect()];
        let path = dir.path().join("iwhite.tif");
        write_pages::<colortype::GrayI16, TiffKindStandard>(
            &path,
            w,
            h,
            &ipages,
            Compression::Uncompressed,
            None,
        );
        let mut b = std::fs::read(&path).unwrap();
        patch_short_tag(&mut b, 262, 0);
        std::fs::write(&path, &b).unwrap();
        let r = open(&path);
        assert!(
            matches!(&r, Err(StoreError::Unsupported { field, .. }) if field == "PhotometricInterpretation"),
            "{r:?}"
        );
    }

    /// Write an ImageJ-style stack: `description` and resolution on the
    /// first page.
    fn write_imagej(path: &Path, w: u32, h: u32, pages: &[Vec<u16>], desc: &str, res: Option<u32>) {
        let f = BufWriter::new(File::create(path).unwrap());
        let mut enc = TiffEncoder::new(f).unwrap();
        for (k, p) in pages.iter().enumerate() {
            let mut img = enc.new_image::<colortype::Gray16>(w, h).unwrap();
            if k == 0 {
                img.encoder()
                    .write_tag(Tag::ImageDescription, desc)
                    .unwrap();
                if let Some(r) = res {
                    img.resolution(
                        tiff::tags::ResolutionUnit::None,
                        tiff::encoder::Rational { n: r, d: 1 },
                    );
                }
            }
            img.write_data(p).unwrap();
        }
    }

    /// ImageJ hyperstack: channels interleaved page by page, spacing from
    /// the resolution and `spacing=`, unit from `unit=`.
    #[test]
    fn imagej_channels_and_calibration() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (7u32, 5u32);
        // Page k = z · 2 + c holds value 100·c + z everywhere.
        let pages: Vec<Vec<u16>> = (0..6)
            .map(|k| vec![(100 * (k % 2) + k / 2) as u16; (w * h) as usize])
            .collect();
        let path = dir.path().join("ij.tif");
        let desc = "ImageJ=1.54f\nimages=6\nchannels=2\nslices=3\nhyperstack=true\n\
                    mode=composite\nunit=micron\nspacing=2.5\nloop=false\n";
        write_imagej(&path, w, h, &pages, desc, Some(4));
        let src = open(&path).unwrap();
        let m = src.meta();
        assert_eq!(m.dims, [3, 5, 7]);
        assert_eq!(m.channels, 2);
        assert_eq!(m.spacing, Some([2.5, 0.25, 0.25]));
        assert_eq!(m.unit.as_deref(), Some("micrometer"));
        assert!(m.notes[0].contains("channels=2"), "{:?}", m.notes);
        for c in 0..2 {
            let want: Vec<u16> = (0..3)
                .flat_map(|z| vec![(100 * c + z) as u16; (w * h) as usize])
                .collect();
            assert_eq!(read_all(&src, c), bytes(&want), "channel {c}");
            assert_eq!(read_stitched(&src, c, [2, 2, 3]), bytes(&want));
        }

        // Without a unit (uncalibrated): no spacing.
        let path = dir.path().join("ij-nounit.tif");
        write_imagej(
            &path,
            w,
            h,
            &pages[..3],
            "ImageJ=1.54f\nimages=3\nslices=3\n",
            Some(4),
        );
        let src = open(&path).unwrap();
        assert_eq!(src.meta().spacing, None);
        assert_eq!(src.meta().channels, 1);
        assert_eq!(src.meta().dims[0], 3);

        // A time series of volumes is refused.
        let path = dir.path().join("ij-t.tif");
        let desc = "ImageJ=1.54f\nimages=6\nslices=3\nframes=2\n";
        write_imagej(&path, w, h, &pages, desc, None);
        assert!(matches!(
            open(&path),
            Err(StoreError::Unsupported { field, .. }) if field == "ImageDescription"
        ));

        // A description that does not match the pages is not applied.
        let path = dir.path().join("ij-bad.tif");
        write_imagej(
            &path,
            w,
            h,
            &pages,
            "ImageJ=1.54f\nimages=8\nchannels=2\nslices=4\n",
            None,
        );
        let src = open(&path).unwrap();
        assert_eq!(src.meta().dims[0], 6);
        assert_eq!(src.meta().channels, 1);
        assert!(src.meta().notes[0].contains("not applied"));
    }

    #[test]
    fn imagej_description_parser() {
        let ij = parse_imagej("ImageJ=1.11a\nimages=12\nchannels=3\nunit=\\u00B5m\nspacing=-0.5\n")
            .unwrap();
        assert_eq!(
            ij,
            ImageJ {
                channels: 3,
                slices: 4,
                frames: 1,
                spacing: Some(0.5),
                unit: Some("µm".into()),
            }
        );
        assert_eq!(normalize_unit("µm").as_deref(), Some("micrometer"));
        assert_eq!(parse_imagej("ImageJ=1.5\nunit=pixel\n").unwrap().unit, None);
        assert_eq!(parse_imagej("{\"shape\": [60, 256, 256]}"), None);
    }

    #[test]
    fn all_sample_types() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (5u32, 3u32);
        let p = dir.path();
        fn check(path: &Path, dtype: DType, want: Vec<u8>) {
            let src = open(path).unwrap();
            assert_eq!(src.meta().dtype, dtype);
            assert_eq!(read_all(&src, 0), want);
        }
        let i8s: Vec<Vec<i8>> = vec![(0..15).map(|i| i * 9 - 64).collect(); 2];
        write_pages::<colortype::GrayI8, TiffKindStandard>(
            &p.join("i8.tif"),
            w,
            h,
            &i8s,
            Compression::Uncompressed,
            None,
        );
        check(&p.join("i8.tif"), DType::I8, bytes(&i8s.concat()));
        let i16s: Vec<Vec<i16>> = vec![(0..15).map(|i| i * 999 - 7000).collect(); 2];
        write_pages::<colortype::GrayI16, TiffKindStandard>(
            &p.join("i16.tif"),
            w,
            h,
            &i16s,
            Compression::Lzw,
            None,
        );
        check(&p.join("i16.tif"), DType::I16, bytes(&i16s.concat()));
        let u32s: Vec<Vec<u32>> = vec![(0..15).map(|i| i * 300_000_000).collect(); 2];
        write_pages::<colortype::Gray32, TiffKindStandard>(
            &p.join("u32.tif"),
            w,
            h,
            &u32s,
            Compression::Uncompressed,
            None,
        );
        check(&p.join("u32.tif"), DType::U32, bytes(&u32s.concat()));
        let i32s: Vec<Vec<i32>> = vec![(0..15).map(|i| i * 100_000_000 - 700_000_000).collect(); 2];
        write_pages::<colortype::GrayI32, TiffKindStandard>(
            &p.join("i32.tif"),
            w,
            h,
            &i32s,
            Compression::Uncompressed,
            None,
        );
        check(&p.join("i32.tif"), DType::I32, bytes(&i32s.concat()));
        let f64s: Vec<Vec<f64>> = vec![(0..15).map(|i| i as f64 / 3.0 - 1e10).collect(); 2];
        write_pages::<colortype::Gray64Float, TiffKindStandard>(
            &p.join("f64.tif"),
            w,
            h,
            &f64s,
            Compression::Uncompressed,
            None,
        );
        check(&p.join("f64.tif"), DType::F64, bytes(&f64s.concat()));

        // 64-bit integers are not supported.
        let u64s: Vec<Vec<u64>> = vec![vec![1; 15]];
        write_pages::<colortype::Gray64, TiffKindStandard>(
            &p.join("u64.tif"),
            w,
            h,
            &u64s,
            Compression::Uncompressed,
            None,
        );
        assert_err(open(&p.join("u64.tif")), "u64.tif", "SampleFormat");
    }

    #[test]
    fn rgb_becomes_three_channels() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (13u32, 6u32);
        let pages: Vec<Vec<u8>> = (0..3)
            .map(|z| (0..w * h * 3).map(|i| (i * 5 + z * 40) as u8).collect())
            .collect();
        let path = dir.path().join("rgb.tif");
        write_pages::<colortype::RGB8, TiffKindStandard>(
            &path,
            w,
            h,
            &pages,
            Compression::Lzw,
            Some(2),
        );
        let src = open(&path).unwrap();
        assert_eq!(src.meta().channels, 3);
        assert_eq!(src.meta().dims, [3, 6, 13]);
        for c in 0..3 {
            let want: Vec<u8> = pages
                .iter()
                .flat_map(|p| p.iter().skip(c).step_by(3).copied())
                .collect();
            assert_eq!(read_all(&src, c), want, "channel {c}");
            assert_eq!(read_stitched(&src, c, [2, 4, 5]), want, "channel {c}");
        }
    }

    /// A minimal hand-written uncompressed TIFF: one IFD per page followed
    /// by its values and strips (or tiles, padded at the edges), in either
    /// byte order and either planar configuration. `pages` hold
    /// native-endian samples in image order (planes one after the other
    /// when `planar`).
    struct Hand {
        w: u32,
        h: u32,
        spp: u16,
        bits: u16,
        sample_format: u16,
        planar: bool,
        rows_per_strip: u32,
        /// Tiles of this width and height instead of strips.
        tile: Option<(u32, u32)>,
        be: bool,
        /// Strips or tiles compressed with Zstandard (compression 50000).
        zstd: bool,
        pages: Vec<Vec<u8>>,
    }

    impl Hand {
        /// The strips or tiles of `page`, plane by plane, in file byte order.
        fn chunks(&self, page: &[u8]) -> Vec<Vec<u8>> {
            let ss = (self.bits / 8) as usize;
            let (planes, spp) = if self.planar {
                (self.spp as usize, 1)
            } else {
                (1, self.spp as usize)
            };
            let px = ss * spp;
            let (w, h) = (self.w as usize, self.h as usize);
            let (cw, ch) = match self.tile {
                Some((tw, th)) => (tw as usize, th as usize),
                None => (w, self.rows_per_strip as usize),
            };
            let mut out = Vec::new();
            for p in 0..planes {
                let plane = &page[p * w * h * px..(p + 1) * w * h * px];
                for cy in 0..h.div_ceil(ch) {
                    for cx in 0..w.div_ceil(cw) {
                        // Strips end with the image, tiles are whole.
                        let rows = if self.tile.is_some() {
                            ch
                        } else {
                            ch.min(h - cy * ch)
                        };
                        let mut c = vec![0u8; rows * cw * px];
                        for r in 0..rows.min(h - cy * ch) {
                            let n = cw.min(w - cx * cw) * px;
                            let src = ((cy * ch + r) * w + cx * cw) * px;
                            c[r * cw * px..r * cw * px + n].copy_from_slice(&plane[src..src + n]);
                        }
                        if self.be {
                            for e in c.chunks_exact_mut(ss) {
                                e.reverse();
                            }
                        }
                        if self.zstd {
                            c = zstd::encode_all(&c[..], 3).unwrap();
                        }
                        out.push(c);
                    }
                }
            }
            out
        }

        fn build(&self) -> Vec<u8> {
            let be = self.be;
            let u16b = |v: u16| if be { v.to_be_bytes() } else { v.to_le_bytes() };
            let u32b = |v: u32| if be { v.to_be_bytes() } else { v.to_le_bytes() };
            let mut out = Vec::new();
            out.extend(if be { *b"MM" } else { *b"II" });
            out.extend(u16b(42));
            out.extend(u32b(8));
            for (pi, page) in self.pages.iter().enumerate() {
                let chunks = self.chunks(page);
                let sizes: Vec<u32> = chunks.iter().map(|c| c.len() as u32).collect();
                let n = sizes.len() as u32;
                let shorts = |v: &[u16]| v.iter().flat_map(|&x| u16b(x)).collect::<Vec<u8>>();
                let longs = |v: &[u32]| v.iter().flat_map(|&x| u32b(x)).collect::<Vec<u8>>();
                let photometric = if self.spp == 3 { 2 } else { 1 };
                let (offsets_tag, counts_tag) = if self.tile.is_some() {
                    (324, 325)
                } else {
                    (273, 279)
                };
                // (tag, type, count, value bytes), in tag order; offsets
                // are patched below.
                let mut entries: Vec<(u16, u16, u32, Vec<u8>)> = vec![
                    (256, 4, 1, longs(&[self.w])),
                    (257, 4, 1, longs(&[self.h])),
                    (
                        258,
                        3,
                        self.spp as u32,
                        shorts(&vec![self.bits; self.spp as usize]),
                    ),
                    (259, 3, 1, shorts(&[if self.zstd { 50000 } else { 1 }])),
                    (262, 3, 1, shorts(&[photometric])),
                    (277, 3, 1, shorts(&[self.spp])),
                    (284, 3, 1, shorts(&[if self.planar { 2 } else { 1 }])),
                    (
                        339,
                        3,
                        self.spp as u32,
                        shorts(&vec![self.sample_format; self.spp as usize]),
                    ),
                    (offsets_tag, 4, n, longs(&vec![0; n as usize])),
                    (counts_tag, 4, n, longs(&sizes)),
                ];
                match self.tile {
                    Some((tw, th)) => {
                        entries.push((322, 4, 1, longs(&[tw])));
                        entries.push((323, 4, 1, longs(&[th])));
                    }
                    None => entries.push((278, 4, 1, longs(&[self.rows_per_strip]))),
                }
                entries.sort_by_key(|e| e.0);
                let ifd = out.len();
                let extra_start = ifd + 2 + 12 * entries.len() + 4;
                let extra_len: usize = entries
                    .iter()
                    .map(|e| if e.3.len() > 4 { e.3.len() } else { 0 })
                    .sum();
                let data_start = extra_start + extra_len;
                let mut offsets = Vec::new();
                let mut o = data_start as u32;
                for s in &sizes {
                    offsets.push(o);
                    o += s;
                }
                let k = entries.iter().position(|e| e.0 == offsets_tag).unwrap();
                entries[k].3 = longs(&offsets);
                out.extend(u16b(entries.len() as u16));
                let mut extra: Vec<u8> = Vec::new();
                for (tag, ty, count, val) in &entries {
                    out.extend(u16b(*tag));
                    out.extend(u16b(*ty));
                    out.extend(u32b(*count));
                    if val.len() > 4 {
                        out.extend(u32b((extra_start + extra.len()) as u32));
                        extra.extend(val);
                    } else {
                        let mut v = val.clone();
                        v.resize(4, 0);
                        out.extend(v);
                    }
                }
                let data_end = o as usize;
                let next = if pi + 1 < self.pages.len() {
                    data_end as u32
                } else {
                    0
                };
                out.extend(u32b(next));
                out.extend(extra);
                assert_eq!(out.len(), data_start);
                for c in chunks {
                    out.extend(c);
                }
            }
            out
        }
    }

    #[test]
    fn planar_separate_big_endian_channels() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (9u32, 7u32);
        // Page z, channel c, pixel i -> value.
        let val = |z: usize, c: usize, i: usize| (z * 1000 + c * 100 + i) as u16;
        let pages: Vec<Vec<u8>> = (0..4)
            .map(|z| {
                let v: Vec<u16> = (0..3)
                    .flat_map(|c| (0..63).map(move |i| val(z, c, i)))
                    .collect();
                bytes(&v)
            })
            .collect();
        for be in [false, true] {
            let hand = Hand {
                w,
                h,
                spp: 3,
                bits: 16,
                sample_format: 1,
                planar: true,
                rows_per_strip: 2,
                tile: None,
                be,
                zstd: false,
                pages: pages.clone(),
            };
            let path = dir.path().join(format!("planar-{be}.tif"));
            std::fs::write(&path, hand.build()).unwrap();
            let src = open(&path).unwrap();
            assert_eq!(src.meta().dims, [4, 7, 9]);
            assert_eq!(src.meta().channels, 3);
            for c in 0..3 {
                let want: Vec<u16> = (0..4)
                    .flat_map(|z| (0..63).map(move |i| val(z, c, i)))
                    .collect();
                assert_eq!(read_all(&src, c), bytes(&want), "be {be} channel {c}");
                assert_eq!(read_stitched(&src, c, [3, 3, 4]), bytes(&want));
            }
        }
    }

    /// Zstandard-compressed strips and tiles (tifffile's `compression='zstd'`)
    /// and 16-bit float samples, which are read as f32: every f16 value,
    /// subnormals, infinities and NaN included, in both byte orders,
    /// compressed or not, chunky or planar.
    #[test]
    fn zstd_and_float16() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (11u32, 9u32);
        let special = [
            0x0000u16, 0x8000, 0x0001, 0x03ff, 0x3c00, 0xbc00, 0x7bff, 0xfbff, 0x7c00, 0xfc00,
            0x7e00,
        ];
        // Page z, channel c, pixel i -> f16 bits.
        let bits = |z: usize, c: usize, i: usize| -> u16 {
            if i < special.len() && z == 0 {
                special[i]
            } else {
                half::f16::from_f32((z * 1000 + c * 100 + i) as f32 * 0.37 - 40.0).to_bits()
            }
        };
        let n = (w * h) as usize;
        for (zstd, be, planar, tile) in [
            (true, false, false, None),
            (true, true, true, Some((16, 16))),
            (false, true, false, Some((16, 16))),
            (false, false, true, None),
        ] {
            let pages: Vec<Vec<u8>> = (0..3)
                .map(|z| {
                    let v: Vec<u16> = if planar {
                        (0..2)
                            .flat_map(|c| (0..n).map(move |i| bits(z, c, i)))
                            .collect()
                    } else {
                        (0..n)
                            .flat_map(|i| (0..2).map(move |c| bits(z, c, i)))
                            .collect()
                    };
                    bytes(&v)
                })
                .collect();
            let hand = Hand {
                w,
                h,
                spp: 2,
                bits: 16,
                sample_format: 3,
                planar,
                rows_per_strip: 4,
                tile,
                be,
                zstd,
                pages,
            };
            let path = dir.path().join(format!("f16-{zstd}-{be}-{planar}.tif"));
            std::fs::write(&path, hand.build()).unwrap();
            let src = open(&path).unwrap();
            let meta = src.meta();
            assert_eq!((meta.dims, meta.channels), ([3, 9, 11], 2));
            assert_eq!(meta.dtype, DType::F32);
            assert!(meta.notes.iter().any(|n| n.contains("16-bit float")));
            for c in 0..2 {
                let want: Vec<f32> = (0..3)
                    .flat_map(|z| (0..n).map(move |i| half::f16::from_bits(bits(z, c, i)).to_f32()))
                    .collect();
                for got in [read_all(&src, c), read_stitched(&src, c, [2, 4, 5])] {
                    let got: Vec<f32> = got
                        .chunks_exact(4)
                        .map(|b| f32::from_ne_bytes(b.try_into().unwrap()))
                        .collect();
                    assert_eq!(got.len(), want.len());
                    for (k, (g, e)) in got.iter().zip(&want).enumerate() {
                        assert!(
                            g.to_bits() == e.to_bits(),
                            "zstd {zstd} be {be} planar {planar} channel {c} voxel {k}: {g} != {e}"
                        );
                    }
                }
            }
        }
    }

    /// A Zstandard strip that does not decode is an error naming the page.
    #[test]
    fn zstd_damaged_strip() {
        let dir = tempfile::tempdir().unwrap();
        let hand = Hand {
            w: 64,
            h: 8,
            spp: 1,
            bits: 16,
            sample_format: 1,
            planar: false,
            rows_per_strip: 8,
            tile: None,
            be: false,
            zstd: true,
            pages: vec![bytes(&(0..512u16).collect::<Vec<_>>())],
        };
        let mut file = hand.build();
        // The strip follows the IFD: scramble its frame's last bytes.
        let k = file.len();
        for b in &mut file[k - 8..] {
            *b ^= 0x5a;
        }
        let path = dir.path().join("bad-zstd.tif");
        std::fs::write(&path, &file).unwrap();
        let src = open(&path).unwrap();
        let mut out = vec![0u8; 64 * 8 * 2];
        let e = src
            .read_region(0, 0..1, 0..8, 0..64, &mut out)
            .unwrap_err()
            .to_string();
        assert!(e.contains("bad-zstd.tif") && e.contains("page 0"), "{e}");
    }

    /// Write 2-D u8 slices `names[k]` holding the value `values[k]`.
    fn write_slices(dir: &Path, names: &[String], values: &[u8], w: u32, h: u32) {
        for (name, &v) in names.iter().zip(values) {
            let data = vec![vec![v; (w * h) as usize]];
            write_pages::<colortype::Gray8, TiffKindStandard>(
                &dir.join(name),
                w,
                h,
                &data,
                Compression::Uncompressed,
                None,
            );
        }
    }

    #[test]
    fn directory_in_natural_order() {
        let dir = tempfile::tempdir().unwrap();
        let names: Vec<String> = (1..=12)
            .map(|i| format!("s{i}.{}", if i % 3 == 0 { "TIFF" } else { "tif" }))
            .collect();
        let values: Vec<u8> = (1..=12).collect();
        write_slices(dir.path(), &names, &values, 6, 4);
        std::fs::write(dir.path().join("notes.txt"), "not an image").unwrap();
        std::fs::write(dir.path().join("._s1.tif"), "AppleDouble junk").unwrap();
        let src = open(dir.path()).unwrap();
        assert_eq!(src.meta().dims, [12, 4, 6]);
        let files = src.slice_files().unwrap();
        assert!(files[1].ends_with("s2.tif") && files[9].ends_with("s10.tif"));
        let all = read_all(&src, 0);
        for z in 0..12 {
            assert!(
                all[z * 24..(z + 1) * 24].iter().all(|&v| v == z as u8 + 1),
                "slice {z}"
            );
        }
        assert_eq!(read_stitched(&src, 0, [5, 3, 4]), all);
    }

    #[test]
    fn glob_selects_and_orders_slices() {
        let dir = tempfile::tempdir().unwrap();
        let names: Vec<String> = (1..=12).map(|i| format!("s{i}.tif")).collect();
        let values: Vec<u8> = (1..=12).map(|i| i * 10).collect();
        write_slices(dir.path(), &names, &values, 3, 2);
        write_slices(dir.path(), &["other.tif".to_string()], &[99], 5, 5);
        let pattern = format!("{}/s*.tif", dir.path().display());
        let src = open_glob(&pattern).unwrap();
        assert_eq!(src.meta().dims, [12, 2, 3]);
        let all = read_all(&src, 0);
        for z in 0..12 {
            assert_eq!(all[z * 6], (z as u8 + 1) * 10, "slice {z}");
        }
        let src = open_glob(&format!("{}/s?.tif", dir.path().display())).unwrap();
        assert_eq!(src.meta().dims[0], 9);
        let e = open_glob(&format!("{}/nothing*.tif", dir.path().display()));
        assert_err(e, "nothing*.tif", "page count");
        let e = open_glob(&format!("{}/*/s1.tif", dir.path().display()));
        assert_err(e, "s1.tif", "glob");
    }

    #[test]
    fn wildcards_and_natural_order() {
        assert!(wildcard_match("slice_*.tif", "slice_001.tif"));
        assert!(wildcard_match("slice_*.tif", "slice_.tif"));
        assert!(!wildcard_match("slice_*.tif", "slice_1.tiff"));
        assert!(wildcard_match("*.tif*", "a.tiff"));
        assert!(wildcard_match("s?.tif", "s1.tif"));
        assert!(!wildcard_match("s?.tif", "s10.tif"));
        assert!(wildcard_match("a*b*c", "aXbYbZc"));
        assert!(!wildcard_match("a*b*c", "aXbYbZ"));
        assert!(wildcard_match("*", ""));
        assert!(wildcard_match("ä*ö", "äxyö"));
        // Classes: ranges, lists, negation, a literal `[` without `]`.
        assert!(wildcard_match("img_[0-2].tif", "img_1.tif"));
        assert!(!wildcard_match("img_[0-2].tif", "img_3.tif"));
        assert!(wildcard_match("img_[02468].tif", "img_8.tif"));
        assert!(!wildcard_match("img_[!0-2].tif", "img_0.tif"));
        assert!(wildcard_match("img_[^0-2].tif", "img_7.tif"));
        assert!(wildcard_match("*_[a-c]*.tif", "x_b9.tif"));
        assert!(wildcard_match("a[]]b", "a]b"));
        assert!(wildcard_match("a[b", "a[b"));
        assert!(!wildcard_match("a[b", "ab"));
        let mut v = vec![
            "img10.tif",
            "img2.tif",
            "img1.tif",
            "IMG3.tif",
            "img02.tif",
            "a.tif",
        ];
        v.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(
            v,
            [
                "a.tif",
                "img1.tif",
                "img02.tif",
                "img2.tif",
                "IMG3.tif",
                "img10.tif"
            ]
        );
        assert_eq!(
            natural_cmp("x99999999999999999999999", "x100000000000000000000000"),
            Ordering::Less
        );
    }

    /// Assert that `r` failed naming `file` and `field`.
    fn assert_err<T: std::fmt::Debug>(r: Result<T>, file: &str, field: &str) -> String {
        let msg = r.expect_err("expected an error").to_string();
        assert!(msg.contains(file), "{msg:?} does not name the file {file}");
        assert!(
            msg.contains(&format!(" {field}: ")),
            "{msg:?} does not name the field {field}"
        );
        msg
    }

    #[test]
    fn pages_of_different_sizes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mixed.tif");
        let f = BufWriter::new(File::create(&path).unwrap());
        let mut enc = TiffEncoder::new(f).unwrap();
        enc.write_image::<colortype::Gray8>(4, 4, &[0; 16]).unwrap();
        enc.write_image::<colortype::Gray8>(5, 4, &[0; 20]).unwrap();
        drop(enc);
        let msg = assert_err(open(&path), "mixed.tif", "ImageWidth");
        assert!(msg.contains("page 1"), "{msg}");

        let path = dir.path().join("types.tif");
        let f = BufWriter::new(File::create(&path).unwrap());
        let mut enc = TiffEncoder::new(f).unwrap();
        enc.write_image::<colortype::Gray8>(4, 4, &[0; 16]).unwrap();
        enc.write_image::<colortype::Gray8>(4, 4, &[0; 16]).unwrap();
        enc.write_image::<colortype::Gray16>(4, 4, &[0; 16])
            .unwrap();
        drop(enc);
        let msg = assert_err(open(&path), "types.tif", "BitsPerSample");
        assert!(msg.contains("page 2"), "{msg}");

        // In a directory the error names the odd slice file.
        let sub = dir.path().join("stack");
        std::fs::create_dir(&sub).unwrap();
        write_slices(&sub, &["a1.tif".into(), "a2.tif".into()], &[1, 2], 4, 4);
        write_slices(&sub, &["a3.tif".into()], &[3], 4, 5);
        let msg = assert_err(open(&sub), "a3.tif", "ImageLength");
        assert!(msg.contains("slice 2"), "{msg}");
    }

    #[test]
    fn empty_directory() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("readme.txt"), "no images").unwrap();
        let name = dir
            .path()
            .file_name()
            .unwrap()
            .to_str()
            .unwrap()
            .to_string();
        assert_err(open(dir.path()), &name, "page count");
    }

    #[test]
    fn not_a_tiff() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fake.tif");
        std::fs::write(&path, "definitely not a TIFF file").unwrap();
        assert_err(open(&path), "fake.tif", "header");
        std::fs::write(&path, "").unwrap();
        assert_err(open(&path), "fake.tif", "header");
        // In a directory stack, the bad file is named.
        let sub = dir.path().join("d");
        std::fs::create_dir(&sub).unwrap();
        write_slices(&sub, &["x1.tif".into()], &[1], 2, 2);
        std::fs::write(sub.join("x2.tif"), "garbage").unwrap();
        assert_err(open(&sub), "x2.tif", "header");
    }

    #[test]
    fn truncated_files() {
        let dir = tempfile::tempdir().unwrap();
        // Strip data cut off (the IFD comes first and survives).
        let hand = Hand {
            w: 10,
            h: 10,
            spp: 1,
            bits: 8,
            sample_format: 1,
            planar: false,
            rows_per_strip: 4,
            tile: None,
            be: false,
            zstd: false,
            pages: vec![vec![7; 100]],
        };
        let file = hand.build();
        let path = dir.path().join("cut.tif");
        std::fs::write(&path, &file[..file.len() - 30]).unwrap();
        let msg = assert_err(open(&path), "cut.tif", "StripByteCounts");
        assert!(msg.contains("page 0"), "{msg}");

        // An encoder-written file (IFDs after the data) cut in half: the
        // chain breaks at some IFD.
        let pages: Vec<Vec<u8>> = vec![vec![1; 400]; 6];
        let path = dir.path().join("half.tif");
        write_pages::<colortype::Gray8, TiffKindStandard>(
            &path,
            20,
            20,
            &pages,
            Compression::Uncompressed,
            None,
        );
        let file = std::fs::read(&path).unwrap();
        std::fs::write(&path, &file[..file.len() / 2]).unwrap();
        let e = open(&path).unwrap_err().to_string();
        assert!(e.contains("half.tif"), "{e}");
        assert!(
            [" IFD: ", " header: ", " StripByteCounts: "]
                .iter()
                .any(|f| e.contains(f)),
            "{e}"
        );
    }

    #[test]
    fn missing_file() {
        let dir = tempfile::tempdir().unwrap();
        let e = open(&dir.path().join("gone.tif")).unwrap_err();
        assert!(e.to_string().contains("gone.tif"), "{e}");
        assert!(
            matches!(&e, StoreError::Io { error, .. } if error.kind() == io::ErrorKind::NotFound)
        );
    }

    /// The JFIF equations against values worked out by hand.
    #[test]
    fn ycbcr_to_rgb_hand_computed() {
        let mut px = vec![
            128, 128, 128, // grey stays grey
            100, 150,
            200, // R 100 + 1.402·72 = 200.94; G 100 − 0.344136·22 − 0.714136·72 = 41.01; B 100 + 1.772·22 = 138.98
            76, 85,
            255, // JFIF of pure red: R 76 + 1.402·127 = 254.05; G 76 + 0.344136·43 − 0.714136·127 = 0.10; B 76 − 1.772·43 = −0.20
            255, 128, 255, // R 433.05 clamped; G 255 − 90.70 = 164.30
            10, 0, 128, // G 10 + 0.344136·128 = 54.05; B 10 − 226.82 clamped
        ];
        ycbcr_to_rgb(&mut px);
        assert_eq!(
            px,
            [128, 128, 128, 201, 41, 139, 254, 0, 0, 255, 164, 255, 10, 54, 0]
        );
    }

    /// A JPEG-compressed YCbCr TIFF as tifffile writes it (chroma
    /// subsampled 2×2, see tests/data/README.md) reads as the RGB colours
    /// written, within JPEG's error, and the report says it was converted.
    #[test]
    fn ycbcr_jpeg_reads_as_rgb() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/ycbcr_jpeg.tif");
        let src = open(&path).unwrap();
        let m = src.meta();
        assert_eq!(m.dims, [2, 48, 64]);
        assert_eq!((m.channels, m.dtype), (3, DType::U8));
        assert!(
            m.notes
                .iter()
                .any(|n| n.contains("YCbCr") && n.contains("R, G, B")),
            "{:?}",
            m.notes
        );
        // The colours written (tests/data/README.md).
        let want = |z: usize, y: usize, x: usize| -> [i32; 3] {
            let v = if z == 0 {
                [200, 50, 3 * x as i32]
            } else {
                [4 * y as i32 + 20, 230 - 3 * x as i32, 90]
            };
            v.map(|c| c.clamp(0, 255))
        };
        let mut worst = 0;
        for c in 0..3 {
            let got = read_all(&src, c);
            assert_eq!(read_stitched(&src, c, [1, 7, 9]), got, "channel {c}");
            for z in 0..2 {
                for y in 0..48 {
                    for x in 0..64 {
                        let g = got[(z * 48 + y) * 64 + x] as i32;
                        let d = (g - want(z, y, x)[c]).abs();
                        worst = worst.max(d);
                        assert!(
                            d <= 4,
                            "channel {c} at z {z} y {y} x {x}: {g}, written {}",
                            want(z, y, x)[c]
                        );
                    }
                }
            }
        }
        // (The stored Y, Cb, Cr differ from R, G, B by up to 150.)
        assert!(worst <= 4, "{worst}");
    }

    /// Set the 4 value bytes of tag `tag` in every IFD of a classic
    /// little-endian TIFF (a value held in the entry).
    fn patch_tag_value(bytes: &mut [u8], tag: u16, value: [u8; 4]) {
        let u16at = |b: &[u8], o: usize| u16::from_le_bytes([b[o], b[o + 1]]);
        let u32at = |b: &[u8], o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
        let mut ifd = u32at(bytes, 4) as usize;
        let mut found = 0;
        while ifd != 0 {
            let n = u16at(bytes, ifd) as usize;
            for e in 0..n {
                let o = ifd + 2 + 12 * e;
                if u16at(bytes, o) == tag {
                    bytes[o + 8..o + 12].copy_from_slice(&value);
                    found += 1;
                }
            }
            ifd = u32at(bytes, ifd + 2 + 12 * n) as usize;
        }
        assert!(found > 0, "tag {tag} not found");
    }

    /// YCbCr that is not JPEG-compressed: converted when not subsampled
    /// (the decoder reads it as stored), refused when subsampled (which
    /// the decoder cannot read), naming the file and the field.
    #[test]
    fn ycbcr_uncompressed_and_subsampled() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (11u32, 5u32);
        let pages: Vec<Vec<u8>> = (0..2)
            .map(|z| (0..w * h * 3).map(|i| (i * 37 + z * 101) as u8).collect())
            .collect();
        let path = dir.path().join("ycc.tif");
        write_pages::<colortype::YCbCr8, TiffKindStandard>(
            &path,
            w,
            h,
            &pages,
            Compression::Lzw,
            Some(2),
        );
        let src = open(&path).unwrap();
        assert_eq!(src.meta().channels, 3);
        assert!(src.meta().notes.iter().any(|n| n.contains("YCbCr")));
        let mut rgb = pages.concat();
        ycbcr_to_rgb(&mut rgb);
        for c in 0..3 {
            let want: Vec<u8> = rgb.iter().skip(c).step_by(3).copied().collect();
            assert_eq!(read_all(&src, c), want, "channel {c}");
        }

        let mut b = std::fs::read(&path).unwrap();
        patch_tag_value(&mut b, 530, [2, 0, 2, 0]);
        let path = dir.path().join("ycc-sub.tif");
        std::fs::write(&path, &b).unwrap();
        let msg = assert_err(open(&path), "ycc-sub.tif", "YCbCrSubSampling");
        assert!(msg.contains("JPEG") && msg.contains("2,2"), "{msg}");
    }

    /// Pseudo-random u16 values of a `w`-wide page.
    fn noise(z: usize, w: u32, h: u32) -> Vec<u16> {
        (0..(w * h) as usize)
            .map(|i| {
                let v = (i as u64 * 2654435761 + z as u64 * 40503) ^ (i as u64 >> 7);
                (v % 65521) as u16
            })
            .collect()
    }

    /// `[z, y, x]` box of the u16 pages (native-endian bytes).
    fn crop(pages: &[Vec<u16>], w: u32, [z, y, x]: [Range<usize>; 3]) -> Vec<u8> {
        let mut v = Vec::new();
        for p in &pages[z] {
            for r in y.clone() {
                let o = r * w as usize;
                v.extend_from_slice(&p[o + x.start..o + x.end]);
            }
        }
        bytes(&v)
    }

    /// A region of wide pages costs the strips it touches (compressed) or
    /// just its own bytes (uncompressed), not whole pages, and its values
    /// are the values written, bit for bit.
    #[test]
    fn wide_pages_read_only_what_a_region_needs() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h, rows) = (3000u32, 40u32, 4u32);
        let pages: Vec<Vec<u16>> = (0..3).map(|z| noise(z, w, h)).collect();
        let page_bytes = (w * h * 2) as u64;
        let strip_bytes = (w * rows * 2) as u64;
        let region = [1..3, 5..11, 1000..1064];
        let want = crop(&pages, w, region.clone());
        for comp in ["none", "lzw", "deflate"] {
            let path = dir.path().join(format!("wide-{comp}.tif"));
            let c = match comp {
                "none" => Compression::Uncompressed,
                "lzw" => Compression::Lzw,
                _ => Compression::Deflate(DeflateLevel::Fast),
            };
            write_pages::<colortype::Gray16, TiffKindStandard>(&path, w, h, &pages, c, Some(rows));
            let src = open(&path).unwrap();
            let mut out = vec![0u8; want.len()];
            let [z, y, x] = region.clone().map(|r| r.start as u64..r.end as u64);
            src.read_region(0, z, y, x, &mut out).unwrap();
            assert!(
                out == want,
                "{comp}: the region differs from the data written"
            );
            let cost = src.bytes_decoded();
            if comp == "none" {
                // 2 pages × 6 rows × 64 samples, read where they lie.
                assert_eq!(cost, want.len() as u64, "{comp}");
            } else {
                // Rows 5..11 lie in strips 1 and 2 of each of 2 pages.
                assert_eq!(cost, 2 * 2 * strip_bytes, "{comp}");
            }
            assert!(
                cost < page_bytes / 2,
                "{comp}: {cost} bytes for a small region"
            );
            // And everything, in narrow blocks and whole.
            let all = bytes(&pages.concat());
            assert!(read_stitched(&src, 0, [2, 7, 700]) == all, "{comp}");
            assert!(read_all(&src, 0) == all, "{comp}");
        }
    }

    /// The cache of decoded strips stays within its byte budget however
    /// large the pages (it used to hold 4 pages' worth).
    #[test]
    fn chunk_cache_bounded_in_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (2048u32, 640u32);
        let pages: Vec<Vec<u16>> = (0..4).map(|z| noise(z, w, h)).collect();
        let path = dir.path().join("wide-lzw.tif");
        write_pages::<colortype::Gray16, TiffKindStandard>(
            &path,
            w,
            h,
            &pages,
            Compression::Lzw,
            Some(16),
        );
        let all = bytes(&pages.concat());
        // Pages of 2.5 MiB: 4 of them are 10 MiB.
        let src = open(&path).unwrap();
        assert!(read_stitched(&src, 0, [4, 64, 512]) == all);
        let peak = src.cache_peak_bytes();
        assert!(peak <= DEFAULT_CACHE_BYTES, "{peak}");
        assert!(peak > 0);
        assert_eq!(src.largest_decode_bytes(), (w * 16 * 2) as u64);
        let src = open(&path).unwrap().with_cache_bytes(100_000);
        assert!(read_stitched(&src, 0, [1, 40, 300]) == all);
        let peak = src.cache_peak_bytes();
        assert!(peak <= 100_000 && peak > 0, "{peak}");
    }

    /// Uncompressed tiles and strips read without decoding: planar and
    /// chunky, both byte orders, edge tiles padded, any region.
    #[test]
    fn uncompressed_tiles_and_strips_read_in_place() {
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (45u32, 29u32);
        for (planar, spp, tile, be) in [
            (false, 1, Some((16, 16)), false),
            (false, 3, Some((16, 32)), true),
            (true, 2, Some((32, 16)), true),
            (false, 3, None, true),
            (true, 3, None, false),
        ] {
            let n = (w * h) as usize * spp as usize;
            // Native u16 samples in image order (planes one after the other
            // when planar); value = page·10000 + sample index.
            let pages: Vec<Vec<u16>> = (0..3)
                .map(|z| (0..n).map(|i| (z * 10000 + i) as u16).collect())
                .collect();
            let hand = Hand {
                w,
                h,
                spp,
                bits: 16,
                sample_format: 1,
                planar,
                rows_per_strip: 3,
                tile,
                be,
                zstd: false,
                pages: pages.iter().map(|p| bytes(p)).collect(),
            };
            let path = dir.path().join("t.tif");
            std::fs::write(&path, hand.build()).unwrap();
            let src = open(&path).unwrap();
            assert!(src.pages.iter().all(|g| g.raw));
            assert_eq!(src.meta().channels, spp as usize);
            for c in 0..spp as usize {
                let want: Vec<u16> = pages
                    .iter()
                    .flat_map(|p| {
                        (0..(w * h) as usize).map(move |i| {
                            if planar {
                                p[c * (w * h) as usize + i]
                            } else {
                                p[i * spp as usize + c]
                            }
                        })
                    })
                    .collect();
                let what = format!("planar {planar} spp {spp} tile {tile:?} be {be} c {c}");
                assert_eq!(read_all(&src, c), bytes(&want), "{what}");
                assert_eq!(read_stitched(&src, c, [2, 5, 7]), bytes(&want), "{what}");
            }
            assert_eq!(src.cache_peak_bytes(), 0);
            assert_eq!(src.largest_decode_bytes(), 0);
        }
    }
}
