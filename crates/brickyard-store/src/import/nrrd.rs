//! NRRD importer: attached (`.nrrd`) and detached (`.nhdr`) headers, `raw` and
//! `gzip` encodings, read region by region with bounded memory.
//!
//! The header is parsed by hand following the NRRD0001..NRRD0005 format
//! (<https://teem.sourceforge.net/nrrd/format.html>):
//!
//! * fields `type`, `dimension`, `sizes`, `endian`, `encoding`, `byte skip`,
//!   `line skip`, `data file` (single file, `LIST [subdim]` and the printf form
//!   `fmt min max step [subdim]`), `space`, `space dimension`,
//!   `space directions`, `space origin`, `spacings`, `kinds`, `space units`,
//!   `units`; other standard fields (`content`, `centers`, `axis mins` ...),
//!   comments (`#`) and `key:=value` pairs are ignored. Field names are matched
//!   ignoring case, spaces and underscores, so `datafile` and `byteskip` work.
//! * NRRD lists axes fastest first (x, y, z); brickyard uses `[z, y, x]`.
//!   A 3-D file is one channel; a 2-D file is a single z slice. The first
//!   (fastest) axis becomes the channel axis when its kind is not a domain
//!   kind (`list`, `vector`, `RGB-color`, ...) or its space direction is
//!   `none`; the last (slowest) axis does when its kind says so explicitly.
//!   With that, 4-D files (and 3-D files holding a 2-D image with channels)
//!   are read; anything else is [`StoreError::Unsupported`].
//! * Spacing comes from the norms of `space directions` (so a flipped axis
//!   still has a positive spacing) or from `spacings`; a 2-D image gets a z
//!   spacing of 1. brickyard keeps only a scale and a translation, so
//!   rotations and flips in `space directions` are dropped: the origin of an
//!   axis is the `space origin` component along which that axis mostly points.
//!   The unit comes from `space units` (or `units`); a `space` that is
//!   anatomical or `scanner-xyz`, given without units, means millimetres.
//!
//! Data access streams: `raw` data is read with positioned reads of just the
//! rows a region needs. `gzip` data cannot be seeked, so each source keeps a
//! decoder cursor and decompresses forwards, only as far as the last byte a
//! request needs; a request that lies before the cursor restarts the stream
//! from the beginning of its file. **For gzip input, read regions in
//! increasing z order** (as the pyramid builder does) or each backwards step
//! costs a fresh decompression from the start. Channels stored one after the
//! other get a cursor each; for interleaved channels the last decompressed
//! span is kept (at most twice the bytes of the region times the channel
//! count) so that reading the other channels of the same region is free.

use crate::error::{IoContext, Result, StoreError};
use crate::import::{swap_bytes_in_place, MAX_DEFLATE_RATIO};
use crate::source::{check_region, SourceMeta, VolumeSource};
use brickyard_core::{DType, Dims3};
use flate2::read::MultiGzDecoder;
use std::fs::File;
use std::io::{BufRead, BufReader, ErrorKind, Read, Seek, SeekFrom};
use std::ops::Range;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};

/// Largest header accepted (a `LIST` of data files can make it long).
const MAX_HEADER_BYTES: u64 = 16 << 20;
/// Longest header line accepted.
const MAX_LINE_BYTES: u64 = 1 << 20;
/// Most data files a `LIST` or printf-style `data file` may name.
const MAX_DATA_FILES: u64 = 1 << 20;
/// Size of the scratch buffer used to de-interleave channels.
const CHUNK_BYTES: usize = 4 << 20;
/// Most gzip decoder cursors kept (one per channel for planar channels).
const MAX_GZ_CURSORS: usize = 256;
/// Buffer between a gzip file and its decoder.
const GZ_BUF_BYTES: usize = 64 << 10;

/// Open a NRRD file (`.nrrd` with attached data, or a detached `.nhdr`
/// header) and check that its data is present.
///
/// The header is parsed completely and validated; raw data files are checked
/// to be large enough, gzip data files to start with a gzip stream. Voxels
/// are read later, on demand, through [`VolumeSource::read_region`].
pub fn open(path: &Path) -> Result<NrrdSource> {
    let file = File::open(path).at(path)?;
    let header = read_header(path, &file)?;
    let plan = interpret(path, &header)?;
    NrrdSource::new(path, file, header.end, plan)
}

/// Parse and check a NRRD header held in memory (the start of a `.nrrd` file
/// or a whole `.nhdr`): everything [`open`] decides from the header alone,
/// without touching any data. `path` names the file in errors and anchors
/// relative data file names.
pub fn parse_header(path: &Path, bytes: &[u8]) -> Result<SourceMeta> {
    let header = read_header(path, bytes)?;
    Ok(interpret(path, &header)?.meta)
}

/// A NRRD volume opened for streaming reads; see the [module docs](self).
///
/// `read_region` may be called from several threads. For `gzip` data the
/// decoder state is shared behind a mutex, so such calls are serialised and
/// are cheapest in increasing z order.
pub struct NrrdSource {
    meta: SourceMeta,
    layout: Layout,
    encoding: Encoding,
    big_endian: bool,
    files: Vec<DataFile>,
    /// Payload bytes held by each data file (all files hold the same amount).
    per_file: u64,
    /// gzip only: decompressed bytes to skip at the start of each file.
    gz_skip: u64,
    /// Whether the data is in the header's own file.
    attached: bool,
    /// The data file kept open when there is a single raw one.
    raw_file: Option<File>,
    /// gzip decoder cursors: one per channel when channels are stored one
    /// after the other, else a single one.
    gz: Vec<Mutex<GzState>>,
    /// Number of gzip streams opened (tests check that reads stream forwards).
    #[cfg(test)]
    gz_opens: std::sync::atomic::AtomicUsize,
}

impl std::fmt::Debug for NrrdSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NrrdSource")
            .field("meta", &self.meta)
            .field("encoding", &self.encoding)
            .field("big_endian", &self.big_endian)
            .field("data_files", &self.files.len())
            .finish_non_exhaustive()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Raw,
    Gzip,
}

/// Where the voxels of one channel lie in the payload, in elements.
#[derive(Debug, Clone, Copy)]
struct Layout {
    /// Strides of z, y and x (z stride is 0 for a 2-D image).
    stride: [u64; 3],
    /// Offset between channels when they are stored one after the other.
    channel_stride: u64,
    /// Channels interleaved voxel by voxel (channel axis fastest).
    interleaved: bool,
}

/// One data file and where its payload starts.
#[derive(Debug)]
struct DataFile {
    path: PathBuf,
    /// Raw: byte offset of the payload. Gzip: byte offset of the gzip stream.
    start: u64,
}

#[derive(Default)]
struct GzState {
    cursor: Option<GzCursor>,
    /// A decompressed span `(payload offset, bytes)` kept so that the other
    /// channels of interleaved data can be read without decompressing again.
    cache: Option<(u64, Vec<u8>)>,
}

struct GzCursor {
    file: usize,
    /// Decompressed bytes consumed from this file's stream (byte skip included).
    pos: u64,
    dec: MultiGzDecoder<BufReader<File>>,
}

// ---------------------------------------------------------------------------
// Header reading

/// The raw lines of a header.
struct Header {
    /// `(canonical name, name as written, value)` of each known field.
    fields: Vec<(&'static str, String, String)>,
    /// File names following `data file: LIST`.
    list: Vec<String>,
    /// Offset just past the blank line that ends the header, if there is one.
    end: Option<u64>,
}

impl Header {
    /// `(name as written, value)` of a field.
    fn get(&self, key: &str) -> Option<(&str, &str)> {
        self.fields
            .iter()
            .find(|f| f.0 == key)
            .map(|f| (f.1.as_str(), f.2.as_str()))
    }
}

/// The spec name of a field, from a name matched ignoring case, spaces and
/// underscores. `None` for an unknown field.
fn canonical_field(name: &str) -> Option<&'static str> {
    let n: String = name
        .chars()
        .filter(|c| !matches!(c, ' ' | '_' | '\t'))
        .collect::<String>()
        .to_ascii_lowercase();
    Some(match n.as_str() {
        "type" => "type",
        "dimension" => "dimension",
        "sizes" => "sizes",
        "endian" => "endian",
        "encoding" => "encoding",
        "byteskip" => "byte skip",
        "lineskip" => "line skip",
        "datafile" => "data file",
        "space" => "space",
        "spacedimension" => "space dimension",
        "spacedirections" => "space directions",
        "spaceorigin" => "space origin",
        "spacings" => "spacings",
        "kinds" => "kinds",
        "spaceunits" => "space units",
        "units" => "units",
        "content" => "content",
        "thicknesses" => "thicknesses",
        "axismins" => "axis mins",
        "axismaxs" => "axis maxs",
        "centers" | "centerings" => "centers",
        "labels" => "labels",
        "min" => "min",
        "max" => "max",
        "oldmin" => "old min",
        "oldmax" => "old max",
        "sampleunits" => "sample units",
        "measurementframe" => "measurement frame",
        "blocksize" => "block size",
        "number" => "number",
        _ => return None,
    })
}

/// Read one line (with its `\n`) of at most `MAX_LINE_BYTES`; returns the
/// number of bytes read, 0 at end of file.
fn read_line(r: &mut impl BufRead, buf: &mut Vec<u8>) -> std::io::Result<u64> {
    buf.clear();
    let n = r.take(MAX_LINE_BYTES + 1).read_until(b'\n', buf)?;
    Ok(n as u64)
}

fn trim_eol(line: &[u8]) -> &[u8] {
    let line = line.strip_suffix(b"\n").unwrap_or(line);
    line.strip_suffix(b"\r").unwrap_or(line)
}

fn read_header(path: &Path, src: impl Read) -> Result<Header> {
    let mut r = BufReader::new(src);
    let mut line = Vec::new();
    let mut pos = read_line(&mut r, &mut line).at(path)?;

    // Magic.
    let first = trim_eol(&line).trim_ascii_end();
    let shown = String::from_utf8_lossy(&first[..first.len().min(24)]).into_owned();
    match first.strip_prefix(b"NRRD000") {
        Some([v @ b'1'..=b'5']) => {
            tracing::debug!("{}: NRRD000{}", path.display(), *v as char);
        }
        Some([b'6'..=b'9']) => {
            return Err(StoreError::unsupported(
                path,
                "magic",
                format!("{shown:?} is newer than NRRD0005, the latest version this reader knows"),
            ))
        }
        _ => {
            return Err(StoreError::invalid(
                path,
                "magic",
                format!("expected \"NRRD0001\"..\"NRRD0005\" on the first line, found {shown:?}"),
            ))
        }
    }

    let mut header = Header {
        fields: Vec::new(),
        list: Vec::new(),
        end: None,
    };
    let mut in_list = false;
    let mut lineno = 1usize;
    loop {
        if pos > MAX_HEADER_BYTES {
            return Err(StoreError::invalid(
                path,
                "header",
                format!("no blank line ends the header within its first {MAX_HEADER_BYTES} bytes"),
            ));
        }
        let n = read_line(&mut r, &mut line).at(path)?;
        if n == 0 {
            break; // end of file: a detached header may end without a blank line
        }
        lineno += 1;
        pos += n;
        if !line.ends_with(b"\n") && n > MAX_LINE_BYTES {
            return Err(StoreError::invalid(
                path,
                "header",
                format!("line {lineno} is longer than {MAX_LINE_BYTES} bytes"),
            ));
        }
        let raw = trim_eol(&line);
        if raw.is_empty() {
            header.end = Some(pos);
            break;
        }
        let Ok(text) = std::str::from_utf8(raw) else {
            return Err(StoreError::invalid(
                path,
                "header",
                format!(
                    "line {lineno} is not text (is the blank line that must end the header \
                     missing before the data?)"
                ),
            ));
        };
        if in_list {
            header.list.push(text.trim().to_string());
            continue;
        }
        if text.starts_with('#') {
            continue;
        }
        let kv = text.find(":=");
        let colon = text
            .find(": ")
            .or_else(|| text.ends_with(':').then(|| text.len() - 1))
            .or_else(|| text.find(':').filter(|&i| kv != Some(i)));
        let colon = match colon {
            Some(c) if kv.is_none_or(|k| c < k) => c,
            _ if kv.is_some() => continue, // key:=value
            _ => {
                return Err(StoreError::invalid(
                    path,
                    "header",
                    format!(
                        "line {lineno}: expected \"field: value\" or \"key:=value\", found {:?}",
                        truncate(text, 80)
                    ),
                ))
            }
        };
        let name = text[..colon].trim();
        let value = text[colon + 1..].trim();
        let Some(canon) = canonical_field(name) else {
            tracing::debug!("{}: ignoring unknown NRRD field {name:?}", path.display());
            continue;
        };
        if header.fields.iter().any(|f| f.0 == canon) {
            return Err(StoreError::invalid(
                path,
                name,
                format!("given twice (line {lineno})"),
            ));
        }
        if canon == "data file" && value.split_whitespace().next() == Some("LIST") {
            in_list = true;
        }
        header
            .fields
            .push((canon, name.to_string(), value.to_string()));
    }
    Ok(header)
}

fn truncate(s: &str, n: usize) -> String {
    if s.chars().count() > n {
        let t: String = s.chars().take(n).collect();
        format!("{t}...")
    } else {
        s.to_string()
    }
}

// ---------------------------------------------------------------------------
// Header interpretation

/// Everything decided from the header alone.
struct Plan {
    meta: SourceMeta,
    layout: Layout,
    encoding: Encoding,
    big_endian: bool,
    byte_skip: i64,
    line_skip: u64,
    /// Data file paths (empty when the data is attached).
    data_files: Vec<PathBuf>,
    /// Bytes of the whole payload.
    total_bytes: u64,
}

/// Result of mapping a NRRD type name.
enum TypeName {
    Ok(DType),
    Wide,
    Block,
    Unknown,
}

/// Every type spelling of the NRRD format (matched ignoring case and repeated
/// spaces). `char` is accepted as signed like most C compilers do.
fn nrrd_type(s: &str) -> TypeName {
    let t = s.split_whitespace().collect::<Vec<_>>().join(" ");
    let t = t.to_ascii_lowercase();
    TypeName::Ok(match t.as_str() {
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => DType::U8,
        "signed char" | "char" | "int8" | "int8_t" => DType::I8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            DType::I16
        }
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => DType::U16,
        "int" | "signed int" | "int32" | "int32_t" => DType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => DType::U32,
        "float" => DType::F32,
        "double" => DType::F64,
        "longlong"
        | "long long"
        | "long long int"
        | "signed long long"
        | "signed long long int"
        | "int64"
        | "int64_t"
        | "ulonglong"
        | "unsigned long long"
        | "unsigned long long int"
        | "uint64"
        | "uint64_t" => return TypeName::Wide,
        "block" => return TypeName::Block,
        _ => return TypeName::Unknown,
    })
}

const DOMAIN_KINDS: &[&str] = &["domain", "space", "time"];
const OTHER_KINDS: &[&str] = &["???", "none"];
const CHANNEL_KINDS: &[&str] = &[
    "list",
    "point",
    "vector",
    "covariant-vector",
    "normal",
    "stub",
    "scalar",
    "complex",
    "2-vector",
    "3-color",
    "rgb-color",
    "hsv-color",
    "xyz-color",
    "4-color",
    "rgba-color",
    "3-vector",
    "3-gradient",
    "3-normal",
    "4-vector",
    "quaternion",
    "2d-symmetric-matrix",
    "2d-masked-symmetric-matrix",
    "2d-matrix",
    "2d-masked-matrix",
    "3d-symmetric-matrix",
    "3d-masked-symmetric-matrix",
    "3d-matrix",
    "3d-masked-matrix",
];

/// Space names and their dimension; `true` for the anatomical/scanner spaces
/// whose coordinates are conventionally millimetres.
fn space_info(s: &str) -> Option<(usize, bool)> {
    Some(match s.to_ascii_lowercase().as_str() {
        "right-anterior-superior"
        | "ras"
        | "left-anterior-superior"
        | "las"
        | "left-posterior-superior"
        | "lps"
        | "scanner-xyz" => (3, true),
        "right-anterior-superior-time"
        | "rast"
        | "left-anterior-superior-time"
        | "last"
        | "left-posterior-superior-time"
        | "lpst"
        | "scanner-xyz-time" => (4, true),
        "3d-right-handed" | "3d-left-handed" => (3, false),
        "3d-right-handed-time" | "3d-left-handed-time" => (4, false),
        _ => return None,
    })
}

/// OME-NGFF unit name of a NRRD unit string.
fn unit_name(s: &str) -> Option<&'static str> {
    Some(match s.trim() {
        "m" | "meter" | "meters" | "metre" | "metres" => "meter",
        "cm" | "centimeter" | "centimeters" | "centimetre" => "centimeter",
        "mm" | "millimeter" | "millimeters" | "millimetre" | "millimetres" => "millimeter",
        "um" | "µm" | "μm" | "micron" | "microns" | "micrometer" | "micrometers" | "micrometre" => {
            "micrometer"
        }
        "nm" | "nanometer" | "nanometers" | "nanometre" => "nanometer",
        "pm" | "picometer" => "picometer",
        "angstrom" | "Å" => "angstrom",
        _ => return None,
    })
}

/// Parse `(a,b,c) none (d,e,f)`; `None` on a syntax error.
fn parse_vectors(s: &str) -> Option<Vec<Option<Vec<f64>>>> {
    let mut out = Vec::new();
    let mut rest = s.trim();
    while !rest.is_empty() {
        if rest
            .get(..4)
            .is_some_and(|w| w.eq_ignore_ascii_case("none"))
        {
            out.push(None);
            rest = rest[4..].trim_start();
            continue;
        }
        let r = rest.strip_prefix('(')?;
        let end = r.find(')')?;
        let v = r[..end]
            .split(',')
            .map(|t| t.trim().parse::<f64>().ok())
            .collect::<Option<Vec<f64>>>()?;
        out.push(Some(v));
        rest = r[end + 1..].trim_start();
    }
    Some(out)
}

/// Parse `"mm" "mm" ""`; `None` on a syntax error.
fn parse_quoted(s: &str) -> Option<Vec<String>> {
    let mut out = Vec::new();
    let mut chars = s.trim().chars().peekable();
    loop {
        while chars.next_if(|c| c.is_whitespace()).is_some() {}
        match chars.next() {
            None => return Some(out),
            Some('"') => {}
            Some(_) => return None,
        }
        let mut word = String::new();
        loop {
            match chars.next()? {
                '"' => break,
                '\\' => word.push(chars.next()?),
                c => word.push(c),
            }
        }
        out.push(word);
    }
}

/// A printf-style file name with one integer conversion (`%d`, `%03i`, ...).
struct NameFormat {
    prefix: String,
    suffix: String,
    left: bool,
    plus: bool,
    space: bool,
    zero: bool,
    width: usize,
    precision: Option<usize>,
}

impl NameFormat {
    fn parse(f: &str) -> std::result::Result<NameFormat, String> {
        let mut prefix = String::new();
        let mut chars = f.chars().peekable();
        while let Some(c) = chars.next() {
            if c != '%' {
                prefix.push(c);
                continue;
            }
            if chars.next_if_eq(&'%').is_some() {
                prefix.push('%');
                continue;
            }
            let mut fmt = NameFormat {
                prefix,
                suffix: String::new(),
                left: false,
                plus: false,
                space: false,
                zero: false,
                width: 0,
                precision: None,
            };
            while let Some(flag) = chars.next_if(|c| matches!(c, '-' | '+' | ' ' | '0' | '#')) {
                match flag {
                    '-' => fmt.left = true,
                    '+' => fmt.plus = true,
                    ' ' => fmt.space = true,
                    '0' => fmt.zero = true,
                    _ => {}
                }
            }
            let digits = |chars: &mut std::iter::Peekable<std::str::Chars>| {
                let mut n = 0usize;
                while let Some(d) = chars.next_if(|c| c.is_ascii_digit()) {
                    n = n
                        .saturating_mul(10)
                        .saturating_add(d as usize - '0' as usize);
                }
                n.min(64)
            };
            fmt.width = digits(&mut chars);
            if chars.next_if_eq(&'.').is_some() {
                fmt.precision = Some(digits(&mut chars));
            }
            while chars
                .next_if(|c| matches!(c, 'h' | 'l' | 'j' | 'z' | 't'))
                .is_some()
            {}
            match chars.next() {
                Some('d' | 'i' | 'u') => {}
                other => {
                    return Err(format!(
                        "the format {f:?} must have one integer conversion (%d, %i or %u), \
                         found {}",
                        other.map_or("the end".to_string(), |c| format!("%{c}"))
                    ))
                }
            }
            while let Some(c) = chars.next() {
                if c == '%' {
                    if chars.next_if_eq(&'%').is_some() {
                        fmt.suffix.push('%');
                        continue;
                    }
                    return Err(format!("the format {f:?} has more than one % conversion"));
                }
                fmt.suffix.push(c);
            }
            return Ok(fmt);
        }
        Err(format!(
            "the format {f:?} has no integer conversion such as %03d"
        ))
    }

    fn render(&self, v: i64) -> String {
        let mut digits = v.unsigned_abs().to_string();
        if let Some(p) = self.precision {
            if digits.len() < p {
                digits = "0".repeat(p - digits.len()) + &digits;
            }
        }
        let sign = if v < 0 {
            "-"
        } else if self.plus {
            "+"
        } else if self.space {
            " "
        } else {
            ""
        };
        let len = sign.len() + digits.len();
        let pad = self.width.saturating_sub(len);
        let body = if self.left {
            format!("{sign}{digits}{}", " ".repeat(pad))
        } else if self.zero && self.precision.is_none() {
            format!("{sign}{}{digits}", "0".repeat(pad))
        } else {
            format!("{}{sign}{digits}", " ".repeat(pad))
        };
        format!("{}{body}{}", self.prefix, self.suffix)
    }
}

fn interpret(path: &Path, h: &Header) -> Result<Plan> {
    let inv = |field: &str, msg: String| StoreError::invalid(path, field, msg);
    let unsup = |field: &str, msg: String| StoreError::unsupported(path, field, msg);
    let required = |key: &'static str| {
        h.get(key)
            .ok_or_else(|| inv(key, "missing: this field is required".to_string()))
    };

    // dimension
    let (f, v) = required("dimension")?;
    let dim: usize = match v.parse::<usize>() {
        Ok(d) if d >= 1 => d,
        _ => return Err(inv(f, format!("expected a positive integer, found {v:?}"))),
    };
    if dim == 1 || dim > 4 {
        return Err(unsup(
            f,
            format!(
                "{dim}-D data; brickyard reads 2-D and 3-D images, optionally with one channel \
                 axis (dimension 3 or 4)"
            ),
        ));
    }

    // type
    let (f, v) = required("type")?;
    let dtype = match nrrd_type(v) {
        TypeName::Ok(d) => d,
        TypeName::Wide => {
            return Err(unsup(
                f,
                format!("{v:?}: 64-bit integers have no brickyard data type; convert to int32 or double first"),
            ))
        }
        TypeName::Block => {
            return Err(unsup(f, format!("{v:?}: opaque blocks are not voxel data")))
        }
        TypeName::Unknown => {
            return Err(inv(
                f,
                format!(
                    "expected a NRRD type (uchar, signed char, short, ushort, int, uint, float, \
                     double, int8 ... uint32, ...), found {v:?}"
                ),
            ))
        }
    };
    let size = dtype.size() as u64;
    let type_name = v;

    // sizes
    let (f, v) = required("sizes")?;
    let sizes: Vec<u64> = v
        .split_whitespace()
        .map(|t| t.parse::<u64>().ok().filter(|&s| s > 0))
        .collect::<Option<Vec<u64>>>()
        .filter(|s| s.len() == dim)
        .ok_or_else(|| inv(f, format!("expected {dim} positive integers, found {v:?}")))?;
    let elems = sizes
        .iter()
        .try_fold(1u64, |a, &s| a.checked_mul(s))
        .filter(|e| e.checked_mul(size).is_some_and(|b| b < i64::MAX as u64))
        .ok_or_else(|| inv(f, format!("{v:?} makes a volume too large to address")))?;
    let total_bytes = elems * size;

    // encoding
    let (f, v) = required("encoding")?;
    let encoding = match v.to_ascii_lowercase().as_str() {
        "raw" => Encoding::Raw,
        "gzip" | "gz" => Encoding::Gzip,
        "bzip2" | "bz2" => {
            return Err(unsup(
                f,
                format!("{v:?}: bzip2 data is not supported; re-save it as raw or gzip (e.g. `unu save -e gzip`)"),
            ))
        }
        "ascii" | "text" | "txt" | "hex" | "zrl" => {
            return Err(unsup(
                f,
                format!("{v:?}: only raw and gzip data can be streamed; re-save it as raw or gzip (e.g. `unu save -e raw`)"),
            ))
        }
        _ => {
            return Err(inv(
                f,
                format!("expected raw, gzip, bzip2, ascii or hex, found {v:?}"),
            ))
        }
    };

    // endian
    let big_endian = match h.get("endian") {
        Some((f, v)) => match v.to_ascii_lowercase().as_str() {
            "little" => false,
            "big" => true,
            _ => {
                return Err(inv(
                    f,
                    format!("expected \"little\" or \"big\", found {v:?}"),
                ))
            }
        },
        None if size > 1 => {
            return Err(inv(
                "endian",
                format!("missing: required for the {size}-byte type {type_name:?}"),
            ))
        }
        None => false,
    };

    // byte skip, line skip
    let byte_skip = match h.get("byte skip") {
        Some((f, v)) => match v.parse::<i64>() {
            Ok(b) if b >= -1 => b,
            _ => {
                return Err(inv(
                    f,
                    format!("expected a non-negative integer or -1, found {v:?}"),
                ))
            }
        },
        None => 0,
    };
    if byte_skip == -1 && encoding != Encoding::Raw {
        let f = h.get("byte skip").map_or("byte skip", |x| x.0);
        return Err(inv(
            f,
            "-1 (data at the end of the file) works only with raw encoding, not gzip".to_string(),
        ));
    }
    let line_skip = match h.get("line skip") {
        Some((f, v)) => v
            .parse::<u64>()
            .map_err(|_| inv(f, format!("expected a non-negative integer, found {v:?}")))?,
        None => 0,
    };

    // data file(s)
    let data_files = data_files(path, h, dim, &sizes)?;

    // kinds
    let kinds: Option<Vec<String>> = match h.get("kinds") {
        Some((f, v)) => {
            let k: Vec<String> = v
                .split_whitespace()
                .map(|s| s.to_ascii_lowercase())
                .collect();
            if k.len() != dim {
                return Err(inv(
                    f,
                    format!("expected {dim} kinds, found {} in {v:?}", k.len()),
                ));
            }
            if let Some(bad) = k.iter().find(|k| {
                !DOMAIN_KINDS.contains(&k.as_str())
                    && !OTHER_KINDS.contains(&k.as_str())
                    && !CHANNEL_KINDS.contains(&k.as_str())
            }) {
                return Err(inv(
                    f,
                    format!("unknown kind {bad:?} (expected domain, space, time, list, vector, RGB-color, ...)"),
                ));
            }
            Some(k)
        }
        None => None,
    };

    // space, space dimension
    let mut space_dim: Option<usize> = None;
    let mut medical = false;
    if let Some((f, v)) = h.get("space") {
        match space_info(v) {
            Some((d, m)) => {
                space_dim = Some(d);
                medical = m;
            }
            None => {
                return Err(inv(
                    f,
                    format!(
                        "unknown space {v:?} (expected e.g. left-posterior-superior, \
                         right-anterior-superior, scanner-xyz, 3D-right-handed)"
                    ),
                ))
            }
        }
    }
    if let Some((f, v)) = h.get("space dimension") {
        let d = v
            .parse::<usize>()
            .ok()
            .filter(|&d| d > 0)
            .ok_or_else(|| inv(f, format!("expected a positive integer, found {v:?}")))?;
        if space_dim.is_some_and(|s| s != d) {
            return Err(inv(f, format!("{d} disagrees with the space field")));
        }
        space_dim = Some(d);
    }

    // space directions
    let dirs: Option<Vec<Option<Vec<f64>>>> = match h.get("space directions") {
        Some((f, v)) => {
            let expect = format!(
                "expected {dim} entries, each a vector \"(x,y,z)\" or \"none\", found {:?}",
                truncate(v, 120)
            );
            let d = parse_vectors(v)
                .filter(|d| d.len() == dim)
                .ok_or_else(|| inv(f, expect))?;
            let lens: Vec<usize> = d.iter().flatten().map(|v| v.len()).collect();
            let sd = space_dim.or(lens.first().copied());
            if let Some(sd) = sd {
                if lens.iter().any(|&l| l != sd) {
                    return Err(inv(
                        f,
                        format!("every vector must have {sd} components (the space dimension), found {:?}", truncate(v, 120)),
                    ));
                }
                space_dim = Some(sd);
            }
            if d.iter().flatten().flatten().any(|c| !c.is_finite()) {
                return Err(inv(
                    f,
                    format!(
                        "vectors must hold finite numbers, found {:?}",
                        truncate(v, 120)
                    ),
                ));
            }
            Some(d)
        }
        None => None,
    };

    // Axes: which one (if any) holds channels.
    let kind_is =
        |i: usize, set: &[&str]| kinds.as_ref().is_some_and(|k| set.contains(&k[i].as_str()));
    let dir_none = |i: usize| dirs.as_ref().is_some_and(|d| d[i].is_none());
    let first_chan =
        dim >= 3 && (kind_is(0, CHANNEL_KINDS) || (dir_none(0) && !kind_is(0, DOMAIN_KINDS)));
    let last_chan = !first_chan && dim >= 3 && kind_is(dim - 1, CHANNEL_KINDS);
    let chan_axis = if first_chan {
        Some(0)
    } else if last_chan {
        Some(dim - 1)
    } else {
        None
    };
    let spatial: Vec<usize> = (0..dim).filter(|&i| Some(i) != chan_axis).collect();
    if spatial.len() > 3 {
        return Err(unsup(
            "dimension",
            format!(
                "4-D data without a channel axis (kinds: {}); brickyard reads 4-D NRRD only \
                 when the first or last axis holds channels (kind list, vector, RGB-color, ...)",
                h.get("kinds").map_or("not given", |k| k.1)
            ),
        ));
    }
    if spatial.len() < 2 {
        return Err(unsup(
            "dimension",
            "2-D data whose first axis holds channels is a 1-D signal, not an image".to_string(),
        ));
    }
    for &i in &spatial {
        if kind_is(i, CHANNEL_KINDS) {
            let k = kinds.as_ref().map_or("", |k| k[i].as_str());
            return Err(unsup(
                "kinds",
                format!(
                    "axis {i} has kind {k:?}, but brickyard needs it as a spatial axis (one \
                     channel axis is read, the first or last axis of 3-D or 4-D data)"
                ),
            ));
        }
        if dir_none(i) {
            return Err(unsup(
                "space directions",
                format!(
                    "axis {i} has no direction (none) but is needed as a spatial axis; if it \
                     holds channels, set its kind (e.g. list) and make it the first or last axis"
                ),
            ));
        }
    }
    let channels = chan_axis.map_or(1, |a| sizes[a]);
    let mut strides = vec![1u64; dim];
    for i in 1..dim {
        strides[i] = strides[i - 1] * sizes[i - 1];
    }
    let (dims, stride): (Dims3, [u64; 3]) = if spatial.len() == 3 {
        (
            [sizes[spatial[2]], sizes[spatial[1]], sizes[spatial[0]]],
            [
                strides[spatial[2]],
                strides[spatial[1]],
                strides[spatial[0]],
            ],
        )
    } else {
        (
            [1, sizes[spatial[1]], sizes[spatial[0]]],
            [0, strides[spatial[1]], strides[spatial[0]]],
        )
    };
    let layout = Layout {
        stride,
        channel_stride: chan_axis.map_or(0, |a| strides[a]),
        interleaved: chan_axis == Some(0) && channels > 1,
    };

    // Spacing, per spatial axis in NRRD order (x, y[, z]).
    let mut spacing_xyz: Option<Vec<f64>> = None;
    if let Some(d) = &dirs {
        let mut s = Vec::new();
        for &i in &spatial {
            let v = d[i].as_deref().unwrap_or(&[]);
            let n = v.iter().map(|c| c * c).sum::<f64>().sqrt();
            if n <= 0.0 {
                let f = h
                    .get("space directions")
                    .map_or("space directions", |x| x.0);
                return Err(inv(
                    f,
                    format!("axis {i} has a zero-length direction vector"),
                ));
            }
            s.push(n);
        }
        spacing_xyz = Some(s);
        if h.get("spacings").is_some() {
            tracing::debug!(
                "{}: both space directions and spacings given; using space directions",
                path.display()
            );
        }
    } else if let Some((f, v)) = h.get("spacings") {
        let s: Vec<f64> = v
            .split_whitespace()
            .map(|t| t.parse::<f64>().ok())
            .collect::<Option<Vec<f64>>>()
            .filter(|s| s.len() == dim)
            .ok_or_else(|| {
                inv(
                    f,
                    format!("expected {dim} numbers (nan for non-spatial axes), found {v:?}"),
                )
            })?;
        let sp: Vec<f64> = spatial.iter().map(|&i| s[i].abs()).collect();
        if sp.contains(&0.0) {
            return Err(inv(
                f,
                format!("spatial axes need a non-zero spacing, found {v:?}"),
            ));
        }
        if sp.iter().all(|s| s.is_finite()) {
            spacing_xyz = Some(sp);
        } else {
            tracing::debug!("{}: spacings {v:?} not all known; ignored", path.display());
        }
    }

    // Origin.
    let mut origin = None;
    if let Some((f, v)) = h.get("space origin") {
        let o = if v.trim().eq_ignore_ascii_case("none") {
            None
        } else {
            let o = parse_vectors(v)
                .and_then(|mut o| match o.len() {
                    1 => o.pop().flatten(),
                    _ => None,
                })
                .ok_or_else(|| inv(f, format!("expected one vector \"(x,y,z)\", found {v:?}")))?;
            if let Some(sd) = space_dim {
                if o.len() != sd {
                    return Err(inv(
                        f,
                        format!("expected {sd} components (the space dimension), found {v:?}"),
                    ));
                }
            }
            Some(o).filter(|o| o.iter().all(|c| c.is_finite()))
        };
        if let Some(o) = o {
            origin = Some(origin_zyx(&o, &spatial, dirs.as_deref()));
        }
    }

    // Unit.
    let mut unit: Option<String> = None;
    let mut unit_given = false;
    let mut pick_unit = |field: &str, names: Vec<String>| {
        let names: Vec<String> = names
            .into_iter()
            .filter(|n| !n.is_empty() && n != "???")
            .collect();
        if names.is_empty() {
            return;
        }
        unit_given = true;
        let mapped: Vec<Option<&str>> = names.iter().map(|n| unit_name(n)).collect();
        match mapped[0] {
            Some(u) if mapped.iter().all(|m| *m == Some(u)) => unit = Some(u.to_string()),
            _ => tracing::warn!(
                "{}: {field} {names:?}: not one known length unit; no unit recorded",
                path.display()
            ),
        }
    };
    if let Some((f, v)) = h.get("space units") {
        let u = parse_quoted(v)
            .filter(|u| space_dim.is_none_or(|sd| u.len() == sd))
            .ok_or_else(|| {
                inv(
                    f,
                    format!(
                        "expected {} quoted unit names such as \"mm\", found {v:?}",
                        space_dim.map_or("the".to_string(), |d| d.to_string())
                    ),
                )
            })?;
        // The spatial components (a 4-D "-time" space lists time last).
        pick_unit(f, u.into_iter().take(3).collect());
    } else if let Some((f, v)) = h.get("units") {
        let u = parse_quoted(v).filter(|u| u.len() == dim).ok_or_else(|| {
            inv(
                f,
                format!("expected {dim} quoted unit names such as \"mm\", found {v:?}"),
            )
        })?;
        pick_unit(f, spatial.iter().map(|&i| u[i].clone()).collect());
    }
    if !unit_given && medical {
        unit = Some("millimeter".to_string());
    }

    let mut meta = SourceMeta::new(path, dims, channels as usize, dtype);
    meta.notes = header_notes(h, &spatial, dirs.as_deref(), origin.is_some());
    meta.spacing = spacing_xyz.map(|s| {
        if s.len() == 3 {
            [s[2], s[1], s[0]]
        } else {
            [1.0, s[1], s[0]]
        }
    });
    meta.origin = origin;
    meta.unit = unit;
    if let Some(a) = chan_axis {
        let names: &[&str] = match kinds.as_ref().map(|k| k[a].as_str()) {
            Some("rgb-color") => &["red", "green", "blue"],
            Some("rgba-color") => &["red", "green", "blue", "alpha"],
            _ => &[],
        };
        if names.len() as u64 == channels {
            meta.channel_names = names.iter().map(|s| s.to_string()).collect();
        }
    }

    Ok(Plan {
        meta,
        layout,
        encoding,
        big_endian: big_endian && size > 1,
        byte_skip,
        line_skip,
        data_files,
        total_bytes,
    })
}

/// Report lines for the fields that change what values or positions mean
/// but are deliberately not applied.
fn header_notes(
    h: &Header,
    spatial: &[usize],
    dirs: Option<&[Option<Vec<f64>>]>,
    has_origin: bool,
) -> Vec<String> {
    let mut notes = Vec::new();
    if let Some(d) = dirs {
        // Plain: axis k of the image points along +component k only.
        let plain = spatial.iter().enumerate().all(|(k, &i)| {
            d[i].as_deref().is_some_and(|v| {
                v.iter()
                    .enumerate()
                    .all(|(j, &c)| if j == k { c > 0.0 } else { c == 0.0 })
            })
        });
        if !plain {
            let v = h.get("space directions").map_or("", |x| x.1);
            notes.push(format!(
                "space directions {} flip or rotate the axes: not applied (spacing = vector \
                 lengths, origin = space origin)",
                truncate(v, 80)
            ));
        }
    }
    let old = (h.get("old min"), h.get("old max"));
    if old.0.is_some() || old.1.is_some() {
        let v = |f: Option<(&str, &str)>| f.map_or("?", |x| x.1).to_string();
        notes.push(format!(
            "old min/old max ({}..{}, the range before quantization) not applied: values are \
             the stored numbers",
            v(old.0),
            v(old.1)
        ));
    }
    if !has_origin && h.get("axis mins").is_some() {
        notes.push("axis mins not applied: no origin recorded".to_string());
    }
    notes
}

/// Origin `[z, y, x]` from a `space origin`: each axis takes the component
/// its direction mostly points along (the plain component order when there
/// are no directions or two axes point the same way). A missing z axis (2-D
/// image) takes the one world component left over, else 0.
fn origin_zyx(o: &[f64], spatial: &[usize], dirs: Option<&[Option<Vec<f64>>]>) -> [f64; 3] {
    let mut comp: Vec<usize> = (0..spatial.len()).collect();
    if let Some(d) = dirs {
        let dominant: Vec<usize> = spatial
            .iter()
            .map(|&i| {
                let v = d[i].as_deref().unwrap_or(&[]);
                (0..v.len())
                    .max_by(|&a, &b| v[a].abs().total_cmp(&v[b].abs()))
                    .unwrap_or(0)
            })
            .collect();
        let distinct = dominant
            .iter()
            .enumerate()
            .all(|(k, c)| !dominant[..k].contains(c));
        if distinct {
            comp = dominant;
        }
    }
    let at = |c: usize| o.get(c).copied().unwrap_or(0.0);
    if spatial.len() == 3 {
        [at(comp[2]), at(comp[1]), at(comp[0])]
    } else {
        let left: Vec<usize> = (0..o.len()).filter(|c| !comp.contains(c)).collect();
        let z = if left.len() == 1 { at(left[0]) } else { 0.0 };
        [z, at(comp[1]), at(comp[0])]
    }
}

/// The data file paths named by the header (empty for attached data),
/// checked against `sizes`.
fn data_files(path: &Path, h: &Header, dim: usize, sizes: &[u64]) -> Result<Vec<PathBuf>> {
    let Some((f, v)) = h.get("data file") else {
        return Ok(Vec::new());
    };
    let inv = |msg: String| StoreError::invalid(path, f, msg);
    let dir = path.parent().unwrap_or(Path::new(""));
    let toks: Vec<&str> = v.split_whitespace().collect();
    let parse_subdim = |t: Option<&&str>| -> Result<usize> {
        match t {
            None => Ok(dim - 1),
            Some(t) => t
                .parse::<usize>()
                .ok()
                .filter(|&s| (1..=dim).contains(&s))
                .ok_or_else(|| {
                    inv(format!(
                        "expected a sub-dimension between 1 and {dim}, found {t:?}"
                    ))
                }),
        }
    };
    let (names, subdim): (Vec<String>, usize) = if toks.first() == Some(&"LIST") {
        if toks.len() > 2 {
            return Err(inv(format!(
                "expected \"LIST\" or \"LIST <subdim>\", found {v:?}"
            )));
        }
        let subdim = parse_subdim(toks.get(1))?;
        if h.list.is_empty() {
            return Err(inv(
                "LIST must be followed by one data file name per line".to_string()
            ));
        }
        (h.list.clone(), subdim)
    } else if (4..=5).contains(&toks.len())
        && toks[0].contains('%')
        && toks[1..4].iter().all(|t| t.parse::<i64>().is_ok())
    {
        let fmt = NameFormat::parse(toks[0]).map_err(inv)?;
        let n: Vec<i64> = toks[1..4].iter().filter_map(|t| t.parse().ok()).collect();
        let (min, max, step) = (n[0], n[1], n[2]);
        if step == 0 {
            return Err(inv(format!("the step must not be 0, found {v:?}")));
        }
        let count = if (step > 0 && min <= max) || (step < 0 && min >= max) {
            (max.abs_diff(min) / step.unsigned_abs()).saturating_add(1)
        } else {
            return Err(inv(format!(
                "{min} to {max} in steps of {step} names no file, found {v:?}"
            )));
        };
        if count > MAX_DATA_FILES {
            return Err(inv(format!("{count} data files are too many")));
        }
        let subdim = parse_subdim(toks.get(4))?;
        let mut names = Vec::with_capacity(count as usize);
        let mut n = min;
        for _ in 0..count {
            names.push(fmt.render(n));
            n = n.saturating_add(step);
        }
        (names, subdim)
    } else if v.is_empty() {
        return Err(inv("expected a file name, found nothing".to_string()));
    } else {
        (vec![v.to_string()], dim)
    };
    let pieces: u64 = sizes[subdim..].iter().product();
    if names.len() as u64 != pieces {
        return Err(inv(format!(
            "{} data file(s) listed, but sizes with {subdim}-D pieces per file need {pieces}",
            names.len()
        )));
    }
    Ok(names.iter().map(|n| dir.join(n)).collect())
}

// ---------------------------------------------------------------------------
// Locating the data

impl NrrdSource {
    fn new(path: &Path, file: File, header_end: Option<u64>, plan: Plan) -> Result<NrrdSource> {
        let attached = plan.data_files.is_empty();
        let (paths, first_start) = if attached {
            let Some(end) = header_end else {
                return Err(StoreError::invalid(
                    path,
                    "data",
                    "the file ends inside the header: no blank line and no data follow it, \
                     and there is no data file field",
                ));
            };
            (vec![path.to_path_buf()], end)
        } else {
            (plan.data_files.clone(), 0)
        };
        let per_file = plan.total_bytes / paths.len() as u64;
        let mut files = Vec::with_capacity(paths.len());
        let mut raw_file = None;
        let single = paths.len() == 1;
        for p in paths {
            let f = if attached {
                file.try_clone().at(path)?
            } else {
                File::open(&p).map_err(|e| data_file_error(path, &p, e))?
            };
            let start = locate(path, &p, &f, first_start, &plan, per_file, attached)?;
            if single && plan.encoding == Encoding::Raw {
                raw_file = Some(f);
            }
            files.push(DataFile { path: p, start });
        }
        let gz_slots = match plan.encoding {
            Encoding::Raw => 0,
            Encoding::Gzip if !plan.layout.interleaved => plan.meta.channels.min(MAX_GZ_CURSORS),
            Encoding::Gzip => 1,
        };
        Ok(NrrdSource {
            meta: plan.meta,
            layout: plan.layout,
            encoding: plan.encoding,
            big_endian: plan.big_endian,
            files,
            per_file,
            gz_skip: plan.byte_skip.max(0) as u64,
            attached,
            raw_file,
            gz: (0..gz_slots).map(|_| Mutex::default()).collect(),
            #[cfg(test)]
            gz_opens: Default::default(),
        })
    }

    /// Name a data file in messages: nothing when attached.
    fn where_(&self, k: usize) -> String {
        if self.attached {
            String::new()
        } else {
            format!(" in data file {}", self.files[k].path.display())
        }
    }
}

/// An I/O error on a detached data file, naming the data file and the header.
fn data_file_error(header: &Path, data: &Path, e: std::io::Error) -> StoreError {
    let source = std::io::Error::new(
        e.kind(),
        format!("{e} (data file named in {})", header.display()),
    );
    StoreError::io(data, source)
}

/// Where the payload (raw) or gzip stream starts in one data file, after
/// `line skip` and (raw) `byte skip`; checks the file is large enough (raw)
/// or starts like a gzip stream.
fn locate(
    header: &Path,
    data: &Path,
    f: &File,
    base: u64,
    plan: &Plan,
    per_file: u64,
    attached: bool,
) -> Result<u64> {
    let io_err = |e| {
        if attached {
            StoreError::io(header, e)
        } else {
            data_file_error(header, data, e)
        }
    };
    let what = if attached {
        "file".to_string()
    } else {
        format!("data file {}", data.display())
    };
    let len = f.metadata().map_err(io_err)?.len();
    let mut start = base;
    if plan.line_skip > 0 && plan.byte_skip != -1 {
        let mut r = BufReader::new(f);
        r.seek(SeekFrom::Start(base)).map_err(io_err)?;
        let mut line = Vec::new();
        for k in 0..plan.line_skip {
            line.clear();
            let n = r.read_until(b'\n', &mut line).map_err(io_err)?;
            if n == 0 || !line.ends_with(b"\n") {
                return Err(StoreError::invalid(
                    header,
                    "line skip",
                    format!(
                        "{what} ends after {k} of the {} lines to skip",
                        plan.line_skip
                    ),
                ));
            }
            start += n as u64;
        }
    }
    let after = if attached { " after the header" } else { "" };
    let per = if plan.data_files.len() > 1 {
        format!(" per file ({} files)", plan.data_files.len())
    } else {
        String::new()
    };
    match plan.encoding {
        Encoding::Raw => {
            let avail = len.saturating_sub(start);
            let skip = plan.byte_skip.max(0) as u64;
            if avail < per_file.saturating_add(skip) {
                let skipped = if skip > 0 {
                    format!(" plus {skip} (byte skip)")
                } else {
                    String::new()
                };
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!(
                        "{what} holds {avail} bytes{after} but sizes × type need {per_file}{per}{skipped}"
                    ),
                ));
            }
            Ok(if plan.byte_skip == -1 {
                len - per_file
            } else {
                start + skip
            })
        }
        Encoding::Gzip => {
            let mut magic = [0u8; 2];
            let got = f.read_at(&mut magic, start).map_err(io_err)?;
            let got = if got == 1 {
                got + f.read_at(&mut magic[1..], start + 1).map_err(io_err)?
            } else {
                got
            };
            let at = if attached || start > 0 {
                format!(" at byte {start}")
            } else {
                String::new()
            };
            if got < 2 {
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!("{what} holds no gzip stream{at}{after}: it is empty or truncated"),
                ));
            }
            if magic != [0x1f, 0x8b] {
                let in_ = if attached {
                    String::new()
                } else {
                    format!(" in {what}")
                };
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!(
                        "gzip stream is corrupt{in_}: expected the gzip signature 1f 8b{at}, \
                         found {:02x} {:02x}",
                        magic[0], magic[1]
                    ),
                ));
            }
            // Deflate inflates at most MAX_DEFLATE_RATIO-fold: a header
            // claiming more than the stream can hold is refused now rather
            // than after decompressing all of it.
            let compressed = len.saturating_sub(start);
            let most = compressed.saturating_mul(MAX_DEFLATE_RATIO);
            let skip = plan.byte_skip.max(0) as u64;
            if per_file.saturating_add(skip) > most {
                let skipped = if skip > 0 {
                    format!(" plus {skip} (byte skip)")
                } else {
                    String::new()
                };
                return Err(StoreError::invalid(
                    header,
                    "data",
                    format!(
                        "{what} holds a gzip stream of {compressed} bytes{at}{after}, which \
                         inflates to at most {most} bytes, but sizes × type need \
                         {per_file}{per}{skipped}"
                    ),
                ));
            }
            Ok(start)
        }
    }
}

// ---------------------------------------------------------------------------
// Reading

impl VolumeSource for NrrdSource {
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
        let rows = Rows::new(self, c, &z, &y, &x);
        match self.encoding {
            Encoding::Raw => {
                let mut handle: Option<(usize, File)> = None;
                rows.copy(out, &mut |off, buf| self.raw_read(off, buf, &mut handle))?;
            }
            Encoding::Gzip => self.gzip_region(&rows, c, out)?,
        }
        if self.big_endian {
            swap_bytes_in_place(out, self.meta.dtype.size());
        }
        Ok(())
    }
}

/// The rows (z, y) of a region and where each lies in the payload.
struct Rows {
    z: Range<u64>,
    y: Range<u64>,
    /// Payload offset of row (z, y) is `base + z * dz + y * dy` bytes.
    base: u64,
    dz: u64,
    dy: u64,
    /// Payload bytes of one row (all channels when interleaved).
    row_len: usize,
    /// Output bytes of one row.
    out_len: usize,
    /// Element size.
    size: usize,
    /// Channels per pixel in the payload (1 unless interleaved).
    px: usize,
    c: usize,
}

impl Rows {
    fn new(s: &NrrdSource, c: usize, z: &Range<u64>, y: &Range<u64>, x: &Range<u64>) -> Rows {
        let size = s.meta.dtype.size();
        let l = &s.layout;
        let px = if l.interleaved { s.meta.channels } else { 1 };
        let chan = if l.interleaved {
            0
        } else {
            c as u64 * l.channel_stride
        };
        let w = (x.end - x.start) as usize;
        let sz = size as u64;
        Rows {
            z: z.clone(),
            y: y.clone(),
            base: (x.start * l.stride[2] + chan) * sz,
            dz: l.stride[0] * sz,
            dy: l.stride[1] * sz,
            row_len: w * px * size,
            out_len: w * size,
            size,
            px,
            c,
        }
    }

    fn offset(&self, z: u64, y: u64) -> u64 {
        self.base + z * self.dz + y * self.dy
    }

    /// Payload byte range spanned by all rows.
    fn span(&self) -> Range<u64> {
        let first = self.offset(self.z.start, self.y.start);
        let last = self.offset(self.z.end - 1, self.y.end - 1) + self.row_len as u64;
        first..last
    }

    /// Fill `out` using `read(payload offset, buf)`, merging rows that are
    /// adjacent in the payload into one read.
    fn copy(
        &self,
        out: &mut [u8],
        read: &mut dyn FnMut(u64, &mut [u8]) -> Result<()>,
    ) -> Result<()> {
        let max_rows = if self.px == 1 {
            usize::MAX
        } else {
            (CHUNK_BYTES / self.row_len).max(1)
        };
        let mut tmp = Vec::new();
        // Pending run: payload offset, first row index, number of rows.
        let mut run: Option<(u64, usize, usize)> = None;
        let mut k = 0usize;
        for zz in self.z.clone() {
            for yy in self.y.clone() {
                let off = self.offset(zz, yy);
                match run {
                    Some((o, f, n)) if n < max_rows && o + (n * self.row_len) as u64 == off => {
                        run = Some((o, f, n + 1));
                    }
                    _ => {
                        if let Some(r) = run {
                            self.flush(r, out, &mut tmp, read)?;
                        }
                        run = Some((off, k, 1));
                    }
                }
                k += 1;
            }
        }
        if let Some(r) = run {
            self.flush(r, out, &mut tmp, read)?;
        }
        Ok(())
    }

    fn flush(
        &self,
        (off, first, n): (u64, usize, usize),
        out: &mut [u8],
        tmp: &mut Vec<u8>,
        read: &mut dyn FnMut(u64, &mut [u8]) -> Result<()>,
    ) -> Result<()> {
        let dst = &mut out[first * self.out_len..(first + n) * self.out_len];
        if self.px == 1 {
            return read(off, dst);
        }
        tmp.resize(n * self.row_len, 0);
        read(off, tmp)?;
        let (s, px, c) = (self.size, self.px, self.c);
        for (o, t) in dst.chunks_exact_mut(s).zip(tmp.chunks_exact(s * px)) {
            o.copy_from_slice(&t[c * s..(c + 1) * s]);
        }
        Ok(())
    }
}

impl NrrdSource {
    /// Read payload bytes `off..off + buf.len()` of raw data.
    fn raw_read(&self, off: u64, buf: &mut [u8], handle: &mut Option<(usize, File)>) -> Result<()> {
        let mut off = off;
        let mut done = 0;
        while done < buf.len() {
            let k = (off / self.per_file) as usize;
            let local = off % self.per_file;
            let n = ((self.per_file - local) as usize).min(buf.len() - done);
            let df = &self.files[k];
            let piece = &mut buf[done..done + n];
            let res = match &self.raw_file {
                Some(f) => f.read_exact_at(piece, df.start + local),
                None => {
                    let h = match handle.take() {
                        Some(h) if h.0 == k => handle.insert(h),
                        _ => {
                            let f = File::open(&df.path)
                                .map_err(|e| data_file_error(&self.meta.path, &df.path, e))?;
                            handle.insert((k, f))
                        }
                    };
                    h.1.read_exact_at(piece, df.start + local)
                }
            };
            res.map_err(|e| {
                if self.attached {
                    StoreError::io(&self.meta.path, e)
                } else {
                    data_file_error(&self.meta.path, &df.path, e)
                }
            })?;
            done += n;
            off += n as u64;
        }
        Ok(())
    }

    fn gzip_region(&self, rows: &Rows, c: usize, out: &mut [u8]) -> Result<()> {
        let slot = c % self.gz.len();
        let mut guard = self.gz[slot].lock().unwrap_or_else(PoisonError::into_inner);
        let GzState { cursor, cache } = &mut *guard;
        let result = self.gzip_region_locked(rows, out, cursor, cache);
        if result.is_err() {
            *cursor = None;
            *cache = None;
        }
        result
    }

    fn gzip_region_locked(
        &self,
        rows: &Rows,
        out: &mut [u8],
        cursor: &mut Option<GzCursor>,
        cache: &mut Option<(u64, Vec<u8>)>,
    ) -> Result<()> {
        let span = rows.span();
        if let Some((start, data)) = cache.as_ref() {
            if *start <= span.start && span.end <= start + data.len() as u64 {
                return rows.copy(out, &mut |off, buf| {
                    let i = (off - start) as usize;
                    buf.copy_from_slice(&data[i..i + buf.len()]);
                    Ok(())
                });
            }
        }
        *cache = None;
        // Interleaved channels: keep the decompressed span for the other
        // channels, as long as it is not much larger than what they read.
        let span_len = span.end - span.start;
        if self.layout.interleaved && span_len <= 2 * out.len() as u64 * self.meta.channels as u64 {
            let mut data = vec![0u8; span_len as usize];
            self.gz_read(cursor, span.start, &mut data)?;
            let start = span.start;
            rows.copy(out, &mut |off, buf| {
                let i = (off - start) as usize;
                buf.copy_from_slice(&data[i..i + buf.len()]);
                Ok(())
            })?;
            *cache = Some((start, data));
            return Ok(());
        }
        rows.copy(out, &mut |off, buf| self.gz_read(cursor, off, buf))
    }

    /// Read payload bytes `off..off + buf.len()` of gzip data through the
    /// cursor, restarting a file's stream only when `off` lies behind it.
    fn gz_read(&self, cursor: &mut Option<GzCursor>, off: u64, buf: &mut [u8]) -> Result<()> {
        let mut off = off;
        let mut done = 0;
        while done < buf.len() {
            let k = (off / self.per_file) as usize;
            let local = off % self.per_file;
            let n = ((self.per_file - local) as usize).min(buf.len() - done);
            let target = self.gz_skip + local;
            let cur = match cursor.take() {
                Some(cur) if cur.file == k && cur.pos <= target => cursor.insert(cur),
                _ => cursor.insert(self.gz_open(k)?),
            };
            if cur.pos < target {
                let mut scratch = vec![0u8; GZ_BUF_BYTES];
                while cur.pos < target {
                    let m = ((target - cur.pos) as usize).min(scratch.len());
                    self.gz_fill(cur, &mut scratch[..m])?;
                }
            }
            self.gz_fill(cur, &mut buf[done..done + n])?;
            done += n;
            off += n as u64;
        }
        Ok(())
    }

    fn gz_open(&self, k: usize) -> Result<GzCursor> {
        let df = &self.files[k];
        let io_err = |e| {
            if self.attached {
                StoreError::io(&df.path, e)
            } else {
                data_file_error(&self.meta.path, &df.path, e)
            }
        };
        let mut f = File::open(&df.path).map_err(io_err)?;
        #[cfg(test)]
        self.gz_opens
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        f.seek(SeekFrom::Start(df.start)).map_err(io_err)?;
        Ok(GzCursor {
            file: k,
            pos: 0,
            dec: MultiGzDecoder::new(BufReader::with_capacity(GZ_BUF_BYTES, f)),
        })
    }

    /// Decompress exactly `buf.len()` bytes.
    fn gz_fill(&self, cur: &mut GzCursor, buf: &mut [u8]) -> Result<()> {
        let mut done = 0;
        while done < buf.len() {
            match cur.dec.read(&mut buf[done..]) {
                Ok(0) => {
                    let got = cur.pos.saturating_sub(self.gz_skip);
                    let skip = if self.gz_skip > 0 {
                        format!(" (after skipping {} bytes for byte skip)", self.gz_skip)
                    } else {
                        String::new()
                    };
                    return Err(StoreError::invalid(
                        &self.meta.path,
                        "data",
                        format!(
                            "gzip stream{} ends after {got} bytes{skip} but sizes × type need {}{} \
                             (truncated file?)",
                            self.where_(cur.file),
                            self.per_file,
                            if self.files.len() > 1 { " per file" } else { "" },
                        ),
                    ));
                }
                Ok(n) => {
                    done += n;
                    cur.pos += n as u64;
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) if matches!(e.kind(), ErrorKind::InvalidInput | ErrorKind::InvalidData) => {
                    return Err(StoreError::invalid(
                        &self.meta.path,
                        "data",
                        format!("gzip stream is corrupt{}: {e}", self.where_(cur.file)),
                    ));
                }
                Err(e) if e.kind() == ErrorKind::UnexpectedEof => {
                    return Err(StoreError::invalid(
                        &self.meta.path,
                        "data",
                        format!(
                            "gzip stream{} is truncated: {e} (after {} bytes)",
                            self.where_(cur.file),
                            cur.pos.saturating_sub(self.gz_skip)
                        ),
                    ));
                }
                Err(e) => {
                    let df = &self.files[cur.file];
                    return Err(if self.attached {
                        StoreError::io(&df.path, e)
                    } else {
                        data_file_error(&self.meta.path, &df.path, e)
                    });
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use flate2::write::GzEncoder;
    use flate2::Compression;
    use std::io::Write;

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

    // -- the real file ------------------------------------------------------

    #[test]
    fn mr_brain_real_file() {
        let path =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/mr-brain-i16.nrrd");
        assert!(
            path.exists(),
            "the shared data folder is missing: {} not found (the real test volumes live in \
             ../shared/data next to the project root, see its README.md)",
            path.display()
        );
        let s = open(&path).unwrap();
        let m = s.meta();
        assert_eq!(m.dims, [25, 256, 256]);
        assert_eq!(m.channels, 1);
        assert_eq!(m.dtype, DType::I16);
        let sp = m.spacing.unwrap();
        for (a, b) in sp.iter().zip([6.5, 0.78125, 0.78125]) {
            assert!((a - b).abs() < 1e-9, "spacing {sp:?}");
        }
        let o = m.origin.unwrap();
        for (a, b) in o.iter().zip([-78.0, 99.609375, -99.609375]) {
            assert!((a - b).abs() < 1e-9, "origin {o:?}");
        }
        assert_eq!(m.unit.as_deref(), Some("millimeter"));
        assert_eq!(
            m.notes.len(),
            1,
            "the flipped y axis is noted: {:?}",
            m.notes
        );
        assert!(m.notes[0].contains("not applied"));

        // Independent decode: the payload follows the first blank line.
        let bytes = std::fs::read(&path).unwrap();
        let hdr_end = bytes.windows(2).position(|w| w == b"\n\n").unwrap() + 2;
        let mut expected = Vec::new();
        MultiGzDecoder::new(&bytes[hdr_end..])
            .read_to_end(&mut expected)
            .unwrap();
        assert_eq!(expected.len(), 256 * 256 * 25 * 2);
        let voxel = |z: usize, y: usize, x: usize| {
            let i = ((z * 256 + y) * 256 + x) * 2;
            i16::from_le_bytes([expected[i], expected[i + 1]])
        };

        let whole = read_all(&s, 0);
        assert!(
            whole == expected,
            "whole volume differs from an independent decode"
        );
        let got = |z: u64, y: u64, x: u64| {
            let b = read_box(&s, 0, z..z + 1, y..y + 1, x..x + 1);
            i16::from_le_bytes([b[0], b[1]])
        };
        for (z, y, x) in [
            (12, 128, 128),
            (0, 0, 0),
            (24, 255, 255),
            (3, 100, 60),
            (20, 17, 200),
        ] {
            assert_eq!(got(z, y, x), voxel(z as usize, y as usize, x as usize));
        }
        let max = (0..expected.len() / 2)
            .map(|i| i16::from_le_bytes([expected[2 * i], expected[2 * i + 1]]))
            .max()
            .unwrap();
        assert!(max > 100, "the volume looks empty (max {max})");

        // Increasing z-slabs, as the pyramid builder reads.
        for z0 in (0..25).step_by(4) {
            let z = z0..(z0 + 4).min(25);
            let b = read_box(&s, 0, z.clone(), 0..256, 0..256);
            assert!(
                b == cut(&expected, m.dims, 2, &z, &(0..256), &(0..256)),
                "slab {z:?}"
            );
        }
        // Random boxes, out of z order.
        check_boxes(&s, 0, &expected, 12, 7);
        let back = read_box(&s, 0, 2..3, 10..20, 30..40);
        assert_eq!(
            back,
            cut(&expected, m.dims, 2, &(2..3), &(10..20), &(30..40))
        );
    }

    // -- synthetic files: layouts and encodings ------------------------------

    #[test]
    fn raw_little_endian_u16() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(60);
        let hdr = format!("{HDR_U16}endian: little\nencoding: raw\nspacings: 0.5 0.25 2\n\n");
        let p = write(dir.path(), "le.nrrd", &[hdr.as_bytes(), &le(&v)]);
        let s = open(&p).unwrap();
        let m = s.meta();
        assert_eq!((m.dims, m.channels, m.dtype), ([3, 4, 5], 1, DType::U16));
        assert_eq!(m.spacing, Some([2.0, 0.25, 0.5]));
        assert_eq!((m.origin, m.unit.as_deref()), (None, None));
        assert_eq!(read_all(&s, 0), le(&v));
        check_boxes(&s, 0, &le(&v), 30, 1);
    }

    /// Fields that are deliberately not applied are named in the notes; the
    /// stored numbers come back unchanged.
    #[test]
    fn unapplied_fields_are_noted() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(60);
        let plain = format!(
            "{HDR_U16}endian: little\nencoding: raw\nspace: RAS\n\
             space directions: (0.5,0,0) (0,0.25,0) (0,0,2)\nspace origin: (1,2,3)\n\n"
        );
        let p = write(dir.path(), "plain.nrrd", &[plain.as_bytes(), &le(&v)]);
        assert!(open(&p).unwrap().meta().notes.is_empty());

        let hdr = format!(
            "{HDR_U16}endian: little\nencoding: raw\nspace: RAS\n\
             space directions: (0.5,0,0) (0,-0.25,0) (0,0,2)\nold min: -1.5\nold max: 7\n\
             axis mins: 0 0 0\n\n"
        );
        let p = write(dir.path(), "noted.nrrd", &[hdr.as_bytes(), &le(&v)]);
        let s = open(&p).unwrap();
        let n = &s.meta().notes;
        assert_eq!(n.len(), 3, "{n:?}");
        assert!(n[0].starts_with("space directions (0.5,0,0) (0,-0.25,0) (0,0,2) flip"));
        assert!(n[1].contains("(-1.5..7, the range before quantization) not applied"));
        assert!(n[2].starts_with("axis mins not applied"));
        assert_eq!(read_all(&s, 0), le(&v), "values are the stored numbers");
    }

    #[test]
    fn raw_big_endian_u16() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(60);
        let hdr = format!("{HDR_U16}endian: big\nencoding: raw\n\n");
        let p = write(dir.path(), "be.nrrd", &[hdr.as_bytes(), &be(&v)]);
        let s = open(&p).unwrap();
        assert_eq!(read_all(&s, 0), le(&v));
        check_boxes(&s, 0, &le(&v), 30, 2);
    }

    #[test]
    fn detached_raw_with_skips_and_geometry() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(60);
        let hdr = "NRRD0005\n# a comment\ntype: uint16\ndimension: 3\nsizes: 5 4 3\n\
                   endian: little\nencoding: raw\nline skip: 2\nbyte skip: 3\n\
                   space: right-anterior-superior\n\
                   space directions: (0,0.5,0) (-0.25,0,0) (0,0,2)\n\
                   space origin: (1,2,3)\nspace units: \"um\" \"um\" \"um\"\n\
                   some key:=some value\ndata file: vol.raw\n";
        let p = write(dir.path(), "vol.nhdr", &[hdr.as_bytes()]);
        write(
            dir.path(),
            "vol.raw",
            &[b"line one\nline two\nxyz", &le(&v)],
        );
        let s = open(&p).unwrap();
        let m = s.meta();
        assert_eq!(m.dims, [3, 4, 5]);
        assert_eq!(m.spacing, Some([2.0, 0.25, 0.5]));
        // x points along world y, y along world x (negated): origin follows.
        assert_eq!(m.origin, Some([3.0, 1.0, 2.0]));
        assert_eq!(m.unit.as_deref(), Some("micrometer"));
        assert_eq!(read_all(&s, 0), le(&v));
        check_boxes(&s, 0, &le(&v), 20, 3);
    }

    #[test]
    fn detached_gzip_with_byte_skip_read_backwards() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(20 * 9 * 7);
        let hdr = "NRRD0004\ntype: short\ndimension: 3\nsizes: 7 9 20\nendian: big\n\
                   encoding: gz\nbyte skip: 4\ndatafile: vol.raw.gz\n\n";
        let p = write(dir.path(), "vol.nhdr", &[hdr.as_bytes()]);
        write(
            dir.path(),
            "vol.raw.gz",
            &[&gz(&[b"skip".as_slice(), &be(&v)].concat())],
        );
        let s = open(&p).unwrap();
        assert_eq!((s.meta().dims, s.meta().dtype), ([20, 9, 7], DType::I16));
        let full = le(&v);
        // Backwards in z: every request restarts the stream and must still work.
        for z in (0..20).rev() {
            assert_eq!(
                read_box(&s, 0, z..z + 1, 0..9, 0..7),
                cut(&full, [20, 9, 7], 2, &(z..z + 1), &(0..9), &(0..7))
            );
        }
        check_boxes(&s, 0, &full, 30, 4);
        assert_eq!(read_all(&s, 0), full);
    }

    #[test]
    fn attached_gzip_from_several_threads() {
        let dir = tempfile::tempdir().unwrap();
        let v: Vec<u16> = values(16 * 32 * 33);
        let hdr = "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 33 32 16\nendian: little\nencoding: gzip\n\n";
        let p = write(dir.path(), "t.nrrd", &[hdr.as_bytes(), &gz(&le(&v))]);
        let s = open(&p).unwrap();
        let full = le(&v);
        std::thread::scope(|sc| {
            for t in 0..4u64 {
                let (s, full) = (&s, &full);
                sc.spawn(move || {
                    for z in (t..16).step_by(4) {
                        let b = read_box(s, 0, z..z + 1, 0..32, 0..33);
                        assert_eq!(
                            b,
                            cut(full, [16, 32, 33], 2, &(z..z + 1), &(0..32), &(0..33))
                        );
                    }
                    check_boxes(s, 0, full, 5, 10 + t);
                });
            }
        });
    }

    #[test]
    fn gzip_streams_forward_only_as_far_as_needed() {
        let dir = tempfile::tempdir().unwrap();
        let v: Vec<u16> = values(10 * 8 * 9);
        let hdr = "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 9 8 10\nendian: little\nencoding: gzip\n\n";
        let p = write(dir.path(), "f.nrrd", &[hdr.as_bytes(), &gz(&le(&v))]);
        let s = open(&p).unwrap();
        let opens = || s.gz_opens.load(std::sync::atomic::Ordering::Relaxed);
        let pos = || s.gz[0].lock().unwrap().cursor.as_ref().map(|c| c.pos);
        let slice = 8 * 9 * 2;
        assert_eq!((opens(), pos()), (0, None));
        for z in 0..10 {
            read_box(&s, 0, z..z + 1, 2..5, 0..9);
            assert_eq!(opens(), 1, "increasing z must not restart the stream");
            assert_eq!(
                pos(),
                Some(z * slice + 5 * 9 * 2),
                "decompressed past the request"
            );
        }
        read_box(&s, 0, 3..4, 0..8, 0..9);
        assert_eq!((opens(), pos()), (2, Some(4 * slice)));
    }

    /// `sizes: C 5 4 3`, channels fastest; the payload in NRRD order.
    fn interleaved(channels: usize) -> (Vec<u16>, Vec<Vec<u8>>) {
        let v = values(channels * 60);
        let per_channel = (0..channels)
            .map(|c| {
                le(&v
                    .iter()
                    .skip(c)
                    .step_by(channels)
                    .copied()
                    .collect::<Vec<_>>())
            })
            .collect();
        (v, per_channel)
    }

    #[test]
    fn four_d_interleaved_channels_raw_and_gzip() {
        let dir = tempfile::tempdir().unwrap();
        let (v, chans) = interleaved(2);
        for (name, enc, data) in [
            ("i.nrrd", "raw", le(&v)),
            ("i.nrrd.gz.nrrd", "gzip", gz(&le(&v))),
        ] {
            let hdr = format!(
                "NRRD0004\ntype: uint16\ndimension: 4\nsizes: 2 5 4 3\nkinds: vector domain domain domain\n\
                 endian: little\nencoding: {enc}\nspace directions: none (1,0,0) (0,1,0) (0,0,3)\n\n"
            );
            let p = write(dir.path(), name, &[hdr.as_bytes(), &data]);
            let s = open(&p).unwrap();
            assert_eq!((s.meta().dims, s.meta().channels), ([3, 4, 5], 2), "{enc}");
            assert_eq!(s.meta().spacing, Some([3.0, 1.0, 1.0]));
            for (c, full) in chans.iter().enumerate() {
                assert_eq!(&read_all(&s, c), full, "{enc} channel {c}");
            }
            // Alternate channels on the same boxes (served from the span cache
            // for gzip), then random boxes.
            let mut g = Lcg(5);
            for _ in 0..20 {
                let (z, y, x) = (g.range(3), g.range(4), g.range(5));
                for (c, full) in chans.iter().enumerate() {
                    assert_eq!(
                        read_box(&s, c, z.clone(), y.clone(), x.clone()),
                        cut(full, [3, 4, 5], 2, &z, &y, &x)
                    );
                }
            }
            check_boxes(&s, 1, &chans[1], 20, 6);
        }
    }

    #[test]
    fn four_d_channels_from_space_directions_none() {
        let dir = tempfile::tempdir().unwrap();
        let (v, chans) = interleaved(3);
        let hdr = "NRRD0004\ntype: uint16\ndimension: 4\nsizes: 3 5 4 3\nendian: little\nencoding: raw\n\
                   space: LPS\nspace directions: none (0.5,0,0) (0,0.5,0) (0,0,1)\nspace origin: (10,20,30)\n\n";
        let p = write(dir.path(), "n.nrrd", &[hdr.as_bytes(), &le(&v)]);
        let s = open(&p).unwrap();
        assert_eq!((s.meta().dims, s.meta().channels), ([3, 4, 5], 3));
        assert_eq!(s.meta().origin, Some([30.0, 20.0, 10.0]));
        assert_eq!(s.meta().unit.as_deref(), Some("millimeter"));
        for (c, full) in chans.iter().enumerate() {
            assert_eq!(&read_all(&s, c), full);
            check_boxes(&s, c, full, 10, c as u64);
        }
    }

    #[test]
    fn four_d_planar_channels_gzip() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(3 * 60);
        let hdr =
            "NRRD0004\ntype: uint16\ndimension: 4\nsizes: 5 4 3 3\nkinds: space space space list\n\
                   endian: little\nencoding: gzip\n\n";
        let p = write(dir.path(), "p.nrrd", &[hdr.as_bytes(), &gz(&le(&v))]);
        let s = open(&p).unwrap();
        assert_eq!((s.meta().dims, s.meta().channels), ([3, 4, 5], 3));
        let chans: Vec<Vec<u8>> = (0..3).map(|c| le(&v[c * 60..(c + 1) * 60])).collect();
        // Channel by channel for each z slice, as a per-slab builder reads.
        for z in 0..3 {
            for (c, full) in chans.iter().enumerate() {
                assert_eq!(
                    read_box(&s, c, z..z + 1, 0..4, 0..5),
                    cut(full, [3, 4, 5], 2, &(z..z + 1), &(0..4), &(0..5))
                );
            }
        }
        for (c, full) in chans.iter().enumerate() {
            check_boxes(&s, c, full, 10, 20 + c as u64);
        }
    }

    #[test]
    fn rgb_image_and_two_d_image() {
        let dir = tempfile::tempdir().unwrap();
        let (v, chans) = interleaved(3);
        let hdr =
            "NRRD0004\ntype: uint16\ndimension: 3\nsizes: 3 10 6\nkinds: RGB-color space space\n\
                   endian: little\nencoding: raw\n\n";
        let p = write(dir.path(), "rgb.nrrd", &[hdr.as_bytes(), &le(&v)]);
        let s = open(&p).unwrap();
        assert_eq!((s.meta().dims, s.meta().channels), ([1, 6, 10], 3));
        assert_eq!(s.meta().channel_names, ["red", "green", "blue"]);
        for (c, full) in chans.iter().enumerate() {
            assert_eq!(&read_all(&s, c), full);
            check_boxes(&s, c, full, 10, 30 + c as u64);
        }

        let v = values(24);
        let hdr =
            "NRRD0001\ntype: uchar\ndimension: 2\nsizes: 6 4\nencoding: raw\nspacings: 0.1 0.2\n\n";
        let bytes: Vec<u8> = v.iter().map(|&x| x as u8).collect();
        let p = write(dir.path(), "2d.nrrd", &[hdr.as_bytes(), &bytes]);
        let s = open(&p).unwrap();
        assert_eq!((s.meta().dims, s.meta().dtype), ([1, 4, 6], DType::U8));
        assert_eq!(s.meta().spacing, Some([1.0, 0.2, 0.1]));
        assert_eq!(read_all(&s, 0), bytes);
        check_boxes(&s, 0, &bytes, 10, 40);
    }

    #[test]
    fn byte_skip_minus_one_and_crlf_header() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(60);
        let hdr = format!("{HDR_U16}endian: little\nencoding: raw\nbyte skip: -1\n\n")
            .replace('\n', "\r\n");
        let p = write(
            dir.path(),
            "m1.nrrd",
            &[hdr.as_bytes(), b"junk bytes before the data", &le(&v)],
        );
        let s = open(&p).unwrap();
        assert_eq!(read_all(&s, 0), le(&v));
        check_boxes(&s, 0, &le(&v), 10, 50);
    }

    #[test]
    fn data_file_list_and_printf_forms() {
        let dir = tempfile::tempdir().unwrap();
        let v = values(60);
        let full = le(&v);
        let slice = |z: usize| &full[z * 40..(z + 1) * 40];
        for z in 0..3 {
            write(dir.path(), &format!("slice{z}.raw"), &[slice(z)]);
            write(
                dir.path(),
                &format!("sl{:02}.raw.gz", 4 - 2 * z),
                &[&gz(slice(z))],
            );
        }
        let list = format!("{HDR_U16}endian: little\nencoding: raw\ndata file: LIST\nslice0.raw\nslice1.raw\nslice2.raw\n");
        let p = write(dir.path(), "list.nhdr", &[list.as_bytes()]);
        let s = open(&p).unwrap();
        assert_eq!(read_all(&s, 0), full);
        check_boxes(&s, 0, &full, 20, 60);

        // Descending numbers: sl04 is z = 0.
        let fmt =
            format!("{HDR_U16}endian: little\nencoding: gzip\ndata file: sl%02d.raw.gz 4 0 -2 2\n");
        let p = write(dir.path(), "fmt.nhdr", &[fmt.as_bytes()]);
        let s = open(&p).unwrap();
        assert_eq!(read_all(&s, 0), full);
        check_boxes(&s, 0, &full, 20, 61);
    }

    #[test]
    fn all_type_spellings() {
        let spellings: &[(&str, DType)] = &[
            ("uchar", DType::U8),
            ("unsigned char", DType::U8),
            ("uint8", DType::U8),
            ("uint8_t", DType::U8),
            ("signed char", DType::I8),
            ("int8", DType::I8),
            ("int8_t", DType::I8),
            ("short", DType::I16),
            ("short int", DType::I16),
            ("signed short", DType::I16),
            ("signed short int", DType::I16),
            ("int16", DType::I16),
            ("int16_t", DType::I16),
            ("ushort", DType::U16),
            ("unsigned short", DType::U16),
            ("unsigned short int", DType::U16),
            ("uint16", DType::U16),
            ("uint16_t", DType::U16),
            ("int", DType::I32),
            ("signed int", DType::I32),
            ("int32", DType::I32),
            ("int32_t", DType::I32),
            ("uint", DType::U32),
            ("unsigned int", DType::U32),
            ("uint32", DType::U32),
            ("uint32_t", DType::U32),
            ("float", DType::F32),
            ("double", DType::F64),
        ];
        for &(s, d) in spellings {
            assert!(matches!(nrrd_type(s), TypeName::Ok(t) if t == d), "{s}");
            assert!(
                matches!(nrrd_type(&s.to_uppercase().replace(' ', "  ")), TypeName::Ok(t) if t == d),
                "{s}"
            );
            assert_eq!(DType::parse(s), Some(d), "DType::parse disagrees on {s}");
        }
        for s in [
            "int64",
            "uint64_t",
            "long long",
            "unsigned long long int",
            "ulonglong",
            "longlong",
        ] {
            assert!(matches!(nrrd_type(s), TypeName::Wide), "{s}");
        }
        assert!(matches!(nrrd_type("block"), TypeName::Block));
        for s in ["u2", "<u2", "float32", "complex"] {
            assert!(matches!(nrrd_type(s), TypeName::Unknown), "{s}");
        }
    }

    #[test]
    fn small_parsers() {
        let f = NameFormat::parse("slice%03d.raw").unwrap();
        assert_eq!(f.render(7), "slice007.raw");
        assert_eq!(f.render(-7), "slice-07.raw");
        assert_eq!(NameFormat::parse("%d").unwrap().render(12), "12");
        assert_eq!(NameFormat::parse("a%%%-4i|").unwrap().render(5), "a%5   |");
        assert_eq!(NameFormat::parse("%+.3u").unwrap().render(5), "+005");
        assert!(NameFormat::parse("%s").is_err());
        assert!(NameFormat::parse("%d%d").is_err());
        assert!(NameFormat::parse("plain").is_err());
        let h = Header {
            fields: vec![(
                "data file",
                "data file".into(),
                format!("x%d {} {} {}", i64::MIN, i64::MAX, 1i64 << 62),
            )],
            list: Vec::new(),
            end: None,
        };
        assert!(data_files(Path::new("h.nhdr"), &h, 3, &[1, 1, 4]).is_ok());
        assert_eq!(
            parse_vectors("(1, 2,3) none (4e-1,-5,6)").unwrap(),
            vec![Some(vec![1.0, 2.0, 3.0]), None, Some(vec![0.4, -5.0, 6.0])]
        );
        assert!(parse_vectors("(1,2").is_none());
        assert!(parse_vectors("(1,x,2)").is_none());
        assert_eq!(
            parse_quoted(r#""mm" "" "a\"b""#).unwrap(),
            ["mm", "", "a\"b"]
        );
        assert!(parse_quoted("mm mm").is_none());
        for (u, n) in [
            ("mm", "millimeter"),
            ("um", "micrometer"),
            ("µm", "micrometer"),
            ("nm", "nanometer"),
            ("m", "meter"),
        ] {
            assert_eq!(unit_name(u), Some(n));
        }
    }

    // -- bad inputs ---------------------------------------------------------

    #[test]
    fn bad_inputs_name_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let v = le(&values(60));
        let raw = format!("{HDR_U16}endian: little\nencoding: raw\n\n");

        let p = write(d, "truncated.nrrd", &[raw.as_bytes(), &v[..100]]);
        let e = assert_error(&p, "truncated.nrrd", "data");
        assert!(
            e.contains("holds 100 bytes after the header but sizes × type need 120"),
            "{e}"
        );

        let p = write(
            d,
            "sizes.nrrd",
            &[raw.replace("5 4 3", "5 4").as_bytes(), &v],
        );
        let e = assert_error(&p, "sizes.nrrd", "sizes");
        assert!(
            e.contains("sizes: expected 3 positive integers, found \"5 4\""),
            "{e}"
        );

        let p = write(
            d,
            "type.nrrd",
            &[raw.replace("unsigned short", "quadruple").as_bytes(), &v],
        );
        assert_error(&p, "type.nrrd", "type");
        let p = write(
            d,
            "int64.nrrd",
            &[raw.replace("unsigned short", "int64").as_bytes(), &v],
        );
        assert_error(&p, "int64.nrrd", "type");

        let p = write(
            d,
            "bzip2.nrrd",
            &[raw.replace("raw", "bzip2").as_bytes(), &v],
        );
        let e = assert_error(&p, "bzip2.nrrd", "encoding");
        assert!(e.contains("unsupported"), "{e}");
        let p = write(
            d,
            "ascii.nrrd",
            &[raw.replace("raw", "ascii").as_bytes(), &v],
        );
        assert_error(&p, "ascii.nrrd", "encoding");

        let gzh = raw.replace("raw", "gzip");
        let mut bad = gz(&v);
        let n = bad.len();
        for b in &mut bad[10..n - 8] {
            *b ^= 0x5a;
        }
        let p = write(d, "corrupt.nrrd", &[gzh.as_bytes(), &bad]);
        let e = assert_error(&p, "corrupt.nrrd", "data");
        assert!(
            e.contains("corrupt") || e.contains("truncated") || e.contains("ends after"),
            "{e}"
        );
        let p = write(d, "notgz.nrrd", &[gzh.as_bytes(), &v]);
        let e = assert_error(&p, "notgz.nrrd", "data");
        assert!(e.contains("gzip stream is corrupt"), "{e}");
        let p = write(d, "shortgz.nrrd", &[gzh.as_bytes(), &gz(&v[..50])]);
        let e = assert_error(&p, "shortgz.nrrd", "data");
        assert!(e.contains("ends after 50 bytes"), "{e}");
        let cut_gz = gz(&v);
        let p = write(
            d,
            "cutgz.nrrd",
            &[gzh.as_bytes(), &cut_gz[..cut_gz.len() / 2]],
        );
        assert_error(&p, "cutgz.nrrd", "data");

        let p = write(
            d,
            "missing.nhdr",
            &[format!("{HDR_U16}endian: little\nencoding: raw\ndata file: gone.raw\n").as_bytes()],
        );
        let e = assert_error(&p, "gone.raw", "data file");
        assert!(e.contains("missing.nhdr"), "{e}");

        let p = write(d, "magic.nrrd", &[b"NRRX0004\n", &v]);
        assert_error(&p, "magic.nrrd", "magic");
        let p = write(d, "empty.nrrd", &[]);
        assert_error(&p, "empty.nrrd", "magic");

        let p = write(
            d,
            "dim5.nrrd",
            &[raw.replace("dimension: 3", "dimension: 5").as_bytes()],
        );
        assert_error(&p, "dim5.nrrd", "dimension");
        let t = "NRRD0004\ntype: uchar\ndimension: 4\nsizes: 2 2 2 2\nkinds: space space space time\nencoding: raw\n\n";
        let p = write(d, "time.nrrd", &[t.as_bytes(), &[0u8; 16]]);
        assert_error(&p, "time.nrrd", "dimension");
        let p = write(
            d,
            "endian.nrrd",
            &[raw.replace("endian: little\n", "").as_bytes(), &v],
        );
        assert_error(&p, "endian.nrrd", "endian");
        let p = write(
            d,
            "skip.nrrd",
            &[
                gzh.to_string()
                    .replace("\n\n", "\nbyte skip: -1\n\n")
                    .as_bytes(),
                &gz(&v),
            ],
        );
        assert_error(&p, "skip.nrrd", "byte skip");
        let p = write(
            d,
            "twice.nrrd",
            &[
                raw.replace("encoding", "sizes: 5 4 3\nencoding").as_bytes(),
                &v,
            ],
        );
        assert_error(&p, "twice.nrrd", "sizes");
        let p = write(
            d,
            "noblank.nrrd",
            &[raw.trim_end().as_bytes(), b"\n\xff\xfe\x00\x01"],
        );
        assert_error(&p, "noblank.nrrd", "header");
        let p = write(
            d,
            "dirs.nrrd",
            &[
                raw.replace("\n\n", "\nspace directions: (1,0,0) (0,1,0)\n\n")
                    .as_bytes(),
                &v,
            ],
        );
        assert_error(&p, "dirs.nrrd", "space directions");
        let p = write(
            d,
            "list.nhdr",
            &[
                format!("{HDR_U16}endian: little\nencoding: raw\ndata file: LIST\na.raw\n")
                    .as_bytes(),
            ],
        );
        assert_error(&p, "list.nhdr", "data file");
        let p = write(
            d,
            "lines.nrrd",
            &[
                raw.replace("\n\n", "\nline skip: 3\n\n").as_bytes(),
                b"one line\n",
            ],
        );
        assert_error(&p, "lines.nrrd", "line skip");
    }

    /// Truncated and mutated headers give errors, never panics.
    #[test]
    fn no_panic_on_damaged_files() {
        let dir = tempfile::tempdir().unwrap();
        let v = le(&values(60));
        for enc in ["raw", "gzip"] {
            let hdr = format!(
                "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 5 4 3\nendian: little\nencoding: {enc}\n\
                 space directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (1,2,3)\nkinds: domain domain domain\n\n"
            );
            let data = if enc == "raw" { v.clone() } else { gz(&v) };
            let good = [hdr.as_bytes(), &data].concat();
            let p = dir.path().join("damaged.nrrd");
            let try_it = |bytes: &[u8]| {
                std::fs::write(&p, bytes).unwrap();
                if let Ok(s) = open(&p) {
                    let m = s.meta().clone();
                    if m.channel_bytes() < 1 << 20 {
                        for c in 0..m.channels {
                            let mut out = vec![0u8; m.channel_bytes() as usize];
                            let _ = s.read_region(
                                c,
                                0..m.dims[0],
                                0..m.dims[1],
                                0..m.dims[2],
                                &mut out,
                            );
                        }
                    }
                }
            };
            for n in 0..good.len() {
                try_it(&good[..n]);
            }
            for i in 0..hdr.len() {
                for b in [b'0', b'9', b' ', b'\n', b'-', b'(', 0xff] {
                    let mut m = good.clone();
                    m[i] = b;
                    try_it(&m);
                }
            }
        }
    }
}
