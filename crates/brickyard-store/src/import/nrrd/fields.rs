//! NRRD field semantics: from a parsed header to a plan (voxel type, axes
//! and channels, spacing, origin and unit, encoding and endianness, skips,
//! data files), with the notes on fields deliberately not applied.

use super::header::{parse_quoted, parse_vectors, truncate, Header, NameFormat};
use super::{Encoding, Layout};
use crate::error::{Result, StoreError};
use crate::import::flip;
use crate::source::SourceMeta;
use brickyard_core::{DType, Dims3};
use std::path::{Path, PathBuf};

/// Most data files a `LIST` or printf-style `data file` may name.
const MAX_DATA_FILES: u64 = 1 << 20;

/// Everything decided from the header alone.
pub(super) struct Plan {
    pub(super) meta: SourceMeta,
    pub(super) layout: Layout,
    pub(super) encoding: Encoding,
    pub(super) big_endian: bool,
    pub(super) byte_skip: i64,
    pub(super) line_skip: u64,
    /// Data file paths (empty when the data is attached).
    pub(super) data_files: Vec<PathBuf>,
    /// Bytes of the whole payload.
    pub(super) total_bytes: u64,
    /// Axes read reversed, `[z, y, x]`: their space direction points
    /// along the negative of their own world axis.
    pub(super) flip: [bool; 3],
}

/// Result of mapping a NRRD type name.
pub(super) enum TypeName {
    Ok(DType),
    Wide,
    Block,
    Unknown,
}

/// Every type spelling of the NRRD format (matched ignoring case and repeated
/// spaces). `char` is accepted as signed like most C compilers do.
pub(super) fn nrrd_type(s: &str) -> TypeName {
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
pub(super) fn unit_name(s: &str) -> Option<&'static str> {
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

pub(super) fn interpret(path: &Path, h: &Header) -> Result<Plan> {
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
        if sp.iter().any(|s| s.is_infinite()) {
            return Err(inv(
                f,
                format!("spatial axes need a finite spacing (nan: unknown), found {v:?}"),
            ));
        }
        // (Unknown on a spatial axis: not applied, and said so by the
        // header's notes.)
        if sp.iter().all(|s| s.is_finite()) {
            spacing_xyz = Some(sp);
        }
    }

    // Steps (x, y[, z]) when every spatial axis steps along its own world
    // axis only (x along the first component, ...), forwards or backwards:
    // the backward ones are read reversed.
    let steps: Option<Vec<f64>> = dirs.as_ref().and_then(|d| {
        spatial
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let v = d[i].as_deref()?;
                let own = *v.get(k)?;
                let alone = v.iter().enumerate().all(|(j, &c)| j == k || c == 0.0);
                (own != 0.0 && alone).then_some(own)
            })
            .collect()
    });
    let mut flip = [false; 3];

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
    // The note on reversed axes, and the origin moved to the voxel that
    // becomes index 0.
    let mut flip_note = None;
    if let Some(st) = &steps {
        const NAMES: [&str; 3] = ["x", "y", "z"];
        let mut said = Vec::new();
        for (k, &step) in st.iter().enumerate() {
            let a = 2 - k;
            if step < 0.0 && dims[a] > 1 {
                flip[a] = true;
                let t = origin.as_mut().map(|o: &mut [f64; 3]| {
                    o[a] = flip::first_voxel(o[a], dims[a], step);
                    o[a]
                });
                said.push((NAMES[k], flip::short(step), t));
            }
        }
        if !said.is_empty() {
            let v = h.get("space directions").map_or("", |x| x.1);
            flip_note = Some(format!(
                "space directions {}: {}",
                truncate(v, 80),
                flip::describe(&said)
            ));
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
    if let Some(n) = flip_note {
        meta.notes.insert(0, n);
    }
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
        flip,
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
        // Kept: axis k of the image points along ±component k only (a
        // backward axis is read reversed, and noted by the caller).
        let kept = spatial.iter().enumerate().all(|(k, &i)| {
            d[i].as_deref().is_some_and(|v| {
                v.iter()
                    .enumerate()
                    .all(|(j, &c)| if j == k { c != 0.0 } else { c == 0.0 })
            })
        });
        if !kept {
            let v = h.get("space directions").map_or("", |x| x.1);
            notes.push(format!(
                "space directions {} rotate or permute the axes: not applied (spacing = vector \
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
    if let (None, Some((_, v))) = (dirs, h.get("spacings")) {
        let unknown = v
            .split_whitespace()
            .enumerate()
            .any(|(i, t)| spatial.contains(&i) && t.parse::<f64>().is_ok_and(f64::is_nan));
        if unknown {
            notes.push(format!(
                "spacings {} unknown (nan) on a spatial axis: not applied (1 on every axis)",
                truncate(v, 80)
            ));
        }
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
pub(super) fn data_files(
    path: &Path,
    h: &Header,
    dim: usize,
    sizes: &[u64],
) -> Result<Vec<PathBuf>> {
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
