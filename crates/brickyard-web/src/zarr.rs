//! OME-Zarr metadata as the browser reads it: the multiscale group
//! (OME-Zarr 0.4 on Zarr v2, 0.5 on Zarr v3), each level's array (shape,
//! data type, chunk grid, chunk keys, codecs, sharding) and the channel
//! defaults. Only what reading voxels needs; errors name the document and
//! the field.

use brickyard_core::{DType, Dims3};
use serde_json::Value;

/// A metadata problem: the document, the field, what was expected.
#[derive(Debug, Clone, PartialEq)]
pub struct MetaError {
    pub doc: String,
    pub field: String,
    pub expected: String,
}

impl std::fmt::Display for MetaError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}: {}", self.doc, self.field, self.expected)
    }
}

impl std::error::Error for MetaError {}

fn err(doc: &str, field: &str, expected: impl Into<String>) -> MetaError {
    MetaError {
        doc: doc.to_string(),
        field: field.to_string(),
        expected: expected.into(),
    }
}

/// One codec of a chain, as far as decoding needs it.
#[derive(Debug, Clone, PartialEq)]
pub enum Codec {
    /// Zarr v3 `bytes`: the array's values in this byte order.
    Bytes {
        big_endian: bool,
    },
    Blosc,
    Zstd,
    Gzip,
    /// `crc32c`: four checksum bytes at the end.
    Crc32c,
    /// Zarr v3 `sharding_indexed`: inner chunks of `chunk` voxels with
    /// their own codecs, and an index (offset, length per inner chunk)
    /// at the end or the start.
    Sharding {
        chunk: Vec<u64>,
        codecs: Vec<Codec>,
        index_codecs: Vec<Codec>,
        index_at_end: bool,
    },
}

/// How chunk keys are spelled.
#[derive(Debug, Clone, PartialEq)]
pub enum KeyEncoding {
    /// Zarr v3 `default`: `c/1/2/3` (or with `.`).
    Default(char),
    /// Zarr v2 (and v3's `v2` encoding): `1.2.3` (or with `/`).
    V2(char),
}

/// One array of the pyramid.
#[derive(Debug, Clone, PartialEq)]
pub struct ArrayMeta {
    /// Path of the array below the store's root (`"0"`).
    pub path: String,
    pub shape: Vec<u64>,
    /// Chunks (shards, when sharded) of the chunk grid.
    pub chunk: Vec<u64>,
    pub dtype: DType,
    /// Stored values are big-endian (Zarr v2 `>` types; v3 `bytes` says it
    /// inside the codecs).
    pub big_endian: bool,
    /// The fill value as the data type's bytes (native order).
    pub fill: Vec<u8>,
    pub keys: KeyEncoding,
    /// The codec chain, array side first (decoding runs it backwards).
    pub codecs: Vec<Codec>,
}

impl ArrayMeta {
    /// The key of chunk `idx` (one index per array axis).
    pub fn chunk_key(&self, idx: &[u64]) -> String {
        let join = |sep: char| {
            idx.iter()
                .map(|i| i.to_string())
                .collect::<Vec<_>>()
                .join(&sep.to_string())
        };
        let p = match self.keys {
            KeyEncoding::Default(_) if idx.is_empty() => "c".to_string(),
            KeyEncoding::Default(sep) => format!("c{sep}{}", join(sep)),
            KeyEncoding::V2(_) if idx.is_empty() => "0".to_string(),
            KeyEncoding::V2(sep) => join(sep),
        };
        format!("{}/{p}", self.path)
    }

    /// The sharding codec, if the chunks are shards.
    pub fn sharding(&self) -> Option<Sharding<'_>> {
        self.codecs.iter().find_map(|c| match c {
            Codec::Sharding {
                chunk,
                codecs,
                index_codecs,
                index_at_end,
            } => Some((
                chunk.as_slice(),
                codecs.as_slice(),
                index_codecs.as_slice(),
                *index_at_end,
            )),
            _ => None,
        })
    }
}

/// A sharding codec's inner chunk shape, inner codecs, index codecs and
/// whether the index is at the end.
pub type Sharding<'a> = (&'a [u64], &'a [Codec], &'a [Codec], bool);

/// A channel's defaults from `omero`.
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelMeta {
    pub label: String,
    pub color: [f32; 3],
    pub window: Option<[f64; 2]>,
    pub active: bool,
}

/// The multiscale image: its levels (finest first), axes and spacing.
#[derive(Debug, Clone, PartialEq)]
pub struct Multiscale {
    /// `2` or `3`.
    pub zarr_format: u8,
    pub levels: Vec<ArrayMeta>,
    /// Axis names in array order.
    pub axes: Vec<String>,
    /// Array axes of z, y, x (z absent for 2D images).
    pub space: [Option<usize>; 3],
    /// The channel axis, if any.
    pub channel_axis: Option<usize>,
    /// Level 0's voxel size `[z, y, x]`.
    pub spacing: [f64; 3],
    /// The centre of level 0's voxel 0 `[z, y, x]` (its translations).
    pub origin: [f64; 3],
    /// The unit of the first space axis that names one.
    pub unit: Option<String>,
    pub channels: Vec<ChannelMeta>,
    /// Why the store is incomplete, if its brickyard attributes say so (the
    /// rule the native readers share).
    pub incomplete: Option<&'static str>,
    /// brickyard's per-brick statistics group, if any.
    pub stats: Option<String>,
    /// brickyard's statistics brick edge `[z, y, x]`.
    pub stats_brick: Option<Dims3>,
    /// A label image: `image-label` in its attributes (a store's
    /// `labels/NAME`) or coarser levels by the mode (`"type": "mode"`).
    pub labels: bool,
}

impl Multiscale {
    /// Voxels `[z, y, x]` of level `l`.
    pub fn dims(&self, l: usize) -> Dims3 {
        let s = &self.levels[l].shape;
        self.space.map(|a| a.map_or(1, |a| s[a]))
    }

    /// Level 0's grid in world space.
    pub fn grid(&self) -> brickyard_core::grid::Grid<'_> {
        brickyard_core::grid::Grid {
            dims: self.dims(0),
            spacing: self.spacing,
            origin: self.origin,
            unit: self.unit.as_deref(),
        }
    }

    /// Number of channels.
    pub fn n_channels(&self) -> usize {
        self.channel_axis
            .map_or(1, |a| self.levels[0].shape[a] as usize)
    }
}

fn parse_json(doc: &str, text: &[u8]) -> Result<Value, MetaError> {
    serde_json::from_slice(text).map_err(|e| err(doc, "(document)", format!("valid JSON ({e})")))
}

fn u64s(doc: &str, field: &str, v: Option<&Value>) -> Result<Vec<u64>, MetaError> {
    let a = v
        .and_then(Value::as_array)
        .ok_or_else(|| err(doc, field, "an array of non-negative integers"))?;
    a.iter()
        .map(|x| {
            x.as_u64()
                .ok_or_else(|| err(doc, field, format!("non-negative integers, found {x}")))
        })
        .collect()
}

/// The data type of a Zarr v3 name or a v2 type string (`<u2`), and
/// whether it is stored big-endian.
fn dtype_of(doc: &str, field: &str, s: &str) -> Result<(DType, bool), MetaError> {
    let (big, core) = match s.as_bytes().first() {
        Some(b'>') => (true, &s[1..]),
        Some(b'<') | Some(b'|') => (false, &s[1..]),
        _ => (false, s),
    };
    let t = match core {
        "uint8" | "u1" => DType::U8,
        "int8" | "i1" => DType::I8,
        "uint16" | "u2" => DType::U16,
        "int16" | "i2" => DType::I16,
        "uint32" | "u4" => DType::U32,
        "int32" | "i4" => DType::I32,
        "float32" | "f4" => DType::F32,
        "float64" | "f8" => DType::F64,
        _ => {
            return Err(err(
                doc,
                field,
                format!(
                "one of uint8, int8, uint16, int16, uint32, int32, float32, float64, found {s:?}"
            ),
            ))
        }
    };
    Ok((t, big))
}

/// The fill value's native bytes.
fn fill_of(doc: &str, v: Option<&Value>, t: DType) -> Result<Vec<u8>, MetaError> {
    let f = match v {
        None | Some(Value::Null) => 0.0,
        Some(Value::Number(n)) => n.as_f64().unwrap_or(0.0),
        Some(Value::String(s)) => match s.as_str() {
            "NaN" => f64::NAN,
            "Infinity" => f64::INFINITY,
            "-Infinity" => f64::NEG_INFINITY,
            _ => return Err(err(doc, "fill_value", format!("a number, found {s:?}"))),
        },
        Some(x) => return Err(err(doc, "fill_value", format!("a number, found {x}"))),
    };
    Ok(brickyard_cache::brick::value_bytes(t, f))
}

fn v3_codecs(doc: &str, field: &str, v: Option<&Value>) -> Result<Vec<Codec>, MetaError> {
    let list = v
        .and_then(Value::as_array)
        .ok_or_else(|| err(doc, field, "a list of codecs"))?;
    let mut out = vec![];
    for c in list {
        let name = c.get("name").and_then(Value::as_str).unwrap_or("");
        let conf = c.get("configuration");
        out.push(match name {
            "bytes" => Codec::Bytes {
                big_endian: conf.and_then(|c| c.get("endian")).and_then(Value::as_str)
                    == Some("big"),
            },
            "blosc" => Codec::Blosc,
            "zstd" => Codec::Zstd,
            "gzip" => Codec::Gzip,
            "crc32c" => Codec::Crc32c,
            "transpose" => {
                let order = conf.and_then(|c| c.get("order"));
                let identity = order.and_then(Value::as_array).is_some_and(|o| {
                    o.iter()
                        .enumerate()
                        .all(|(i, x)| x.as_u64() == Some(i as u64))
                });
                if !identity {
                    return Err(err(
                        doc,
                        field,
                        "no transpose codec other than the identity (not supported in the browser)",
                    ));
                }
                continue;
            }
            "sharding_indexed" => {
                let conf =
                    conf.ok_or_else(|| err(doc, field, "sharding_indexed with a configuration"))?;
                Codec::Sharding {
                    chunk: u64s(doc, "sharding_indexed.chunk_shape", conf.get("chunk_shape"))?,
                    codecs: v3_codecs(doc, "sharding_indexed.codecs", conf.get("codecs"))?,
                    index_codecs: v3_codecs(
                        doc,
                        "sharding_indexed.index_codecs",
                        conf.get("index_codecs"),
                    )?,
                    index_at_end: conf.get("index_location").and_then(Value::as_str)
                        != Some("start"),
                }
            }
            other => {
                return Err(err(
                    doc,
                    field,
                    format!(
                    "codecs bytes, blosc, zstd, gzip, crc32c, sharding_indexed, found {other:?}"
                ),
                ))
            }
        });
    }
    Ok(out)
}

/// A Zarr v3 array's `zarr.json`.
pub fn parse_v3_array(path: &str, text: &[u8]) -> Result<ArrayMeta, MetaError> {
    let doc = format!("{path}/zarr.json");
    let v = parse_json(&doc, text)?;
    if v.get("node_type").and_then(Value::as_str) != Some("array") {
        return Err(err(&doc, "node_type", "\"array\""));
    }
    let shape = u64s(&doc, "shape", v.get("shape"))?;
    let grid = v.get("chunk_grid");
    if grid.and_then(|g| g.get("name")).and_then(Value::as_str) != Some("regular") {
        return Err(err(&doc, "chunk_grid.name", "\"regular\""));
    }
    let chunk = u64s(
        &doc,
        "chunk_grid.configuration.chunk_shape",
        grid.and_then(|g| g.get("configuration"))
            .and_then(|c| c.get("chunk_shape")),
    )?;
    let dt = v
        .get("data_type")
        .and_then(Value::as_str)
        .ok_or_else(|| err(&doc, "data_type", "a data type name"))?;
    let (dtype, _) = dtype_of(&doc, "data_type", dt)?;
    let kenc = v.get("chunk_key_encoding");
    let sep = kenc
        .and_then(|k| k.get("configuration"))
        .and_then(|c| c.get("separator"))
        .and_then(Value::as_str);
    let keys = match kenc.and_then(|k| k.get("name")).and_then(Value::as_str) {
        None | Some("default") => KeyEncoding::Default(if sep == Some(".") { '.' } else { '/' }),
        Some("v2") => KeyEncoding::V2(if sep == Some("/") { '/' } else { '.' }),
        Some(o) => {
            return Err(err(
                &doc,
                "chunk_key_encoding.name",
                format!("default or v2, found {o:?}"),
            ))
        }
    };
    let codecs = v3_codecs(&doc, "codecs", v.get("codecs"))?;
    if shape.len() != chunk.len() || chunk.contains(&0) {
        return Err(err(
            &doc,
            "chunk_grid",
            "one positive chunk edge per axis of shape",
        ));
    }
    Ok(ArrayMeta {
        path: path.to_string(),
        shape,
        chunk,
        dtype,
        big_endian: false,
        fill: fill_of(&doc, v.get("fill_value"), dtype)?,
        keys,
        codecs,
    })
}

/// A Zarr v2 array's `.zarray`.
pub fn parse_v2_array(path: &str, text: &[u8]) -> Result<ArrayMeta, MetaError> {
    let doc = format!("{path}/.zarray");
    let v = parse_json(&doc, text)?;
    let shape = u64s(&doc, "shape", v.get("shape"))?;
    let chunk = u64s(&doc, "chunks", v.get("chunks"))?;
    if shape.len() != chunk.len() || chunk.contains(&0) {
        return Err(err(
            &doc,
            "chunks",
            "one positive chunk edge per axis of shape",
        ));
    }
    let dt = v
        .get("dtype")
        .and_then(Value::as_str)
        .ok_or_else(|| err(&doc, "dtype", "a type string such as \"<u2\""))?;
    let (dtype, big_endian) = dtype_of(&doc, "dtype", dt)?;
    if v.get("order").and_then(Value::as_str) == Some("F") {
        return Err(err(
            &doc,
            "order",
            "\"C\" (Fortran order is not supported in the browser)",
        ));
    }
    if v.get("filters")
        .is_some_and(|f| !f.is_null() && f.as_array().is_none_or(|a| !a.is_empty()))
    {
        return Err(err(
            &doc,
            "filters",
            "none (filters are not supported in the browser)",
        ));
    }
    let codecs = match v.get("compressor") {
        None | Some(Value::Null) => vec![],
        Some(c) => match c.get("id").and_then(Value::as_str) {
            Some("blosc") => vec![Codec::Blosc],
            Some("zstd") => vec![Codec::Zstd],
            Some("gzip") | Some("zlib") => vec![Codec::Gzip],
            o => {
                return Err(err(
                    &doc,
                    "compressor.id",
                    format!("blosc, zstd, gzip or none, found {o:?}"),
                ))
            }
        },
    };
    let sep = if v.get("dimension_separator").and_then(Value::as_str) == Some("/") {
        '/'
    } else {
        '.'
    };
    Ok(ArrayMeta {
        path: path.to_string(),
        shape,
        chunk,
        dtype,
        big_endian,
        fill: fill_of(&doc, v.get("fill_value"), dtype)?,
        keys: KeyEncoding::V2(sep),
        codecs,
    })
}

/// The `multiscales` block of a root group's attributes (`zarr.json`'s
/// `attributes.ome`, or `.zattrs` itself) with the Zarr format: the level
/// paths, axes and spacing, the channels and brickyard's own block.
/// Returns the level paths to read next.
pub fn parse_root(zarr_format: u8, text: &[u8]) -> Result<(Multiscale, Vec<String>), MetaError> {
    let doc = if zarr_format == 3 {
        "zarr.json"
    } else {
        ".zattrs"
    };
    let v = parse_json(doc, text)?;
    let attrs = if zarr_format == 3 {
        v.get("attributes").cloned().unwrap_or(Value::Null)
    } else {
        v
    };
    let ome = attrs.get("ome").unwrap_or(&attrs);
    let ms = ome
        .get("multiscales")
        .and_then(Value::as_array)
        .and_then(|a| a.first())
        .ok_or_else(|| {
            err(
                doc,
                "multiscales",
                "an OME-Zarr multiscales list (is this an OME-Zarr image?)",
            )
        })?;
    let unit = ms
        .get("axes")
        .and_then(Value::as_array)
        .and_then(|a| {
            a.iter()
                .filter(|x| x.get("type").and_then(Value::as_str) == Some("space"))
                .find_map(|x| x.get("unit").and_then(Value::as_str))
        })
        .map(str::to_string);
    let axes: Vec<(String, String)> = match ms.get("axes").and_then(Value::as_array) {
        Some(a) => a
            .iter()
            .map(|x| match x {
                Value::String(s) => (s.clone(), String::new()),
                o => (
                    o.get("name")
                        .and_then(Value::as_str)
                        .unwrap_or("")
                        .to_string(),
                    o.get("type")
                        .and_then(Value::as_str)
                        .unwrap_or("")
                        .to_string(),
                ),
            })
            .collect(),
        // OME-Zarr 0.3 and earlier: 5D t, c, z, y, x.
        None => ["t", "c", "z", "y", "x"]
            .map(|s| (s.to_string(), String::new()))
            .to_vec(),
    };
    let find = |n: &str| axes.iter().position(|(a, _)| a == n);
    let space = [find("z"), find("y"), find("x")];
    if space[1].is_none() || space[2].is_none() {
        return Err(err(
            doc,
            "multiscales.axes",
            format!(
                "axes named y and x, found {:?}",
                axes.iter().map(|a| &a.0).collect::<Vec<_>>()
            ),
        ));
    }
    let channel_axis = find("c").or_else(|| axes.iter().position(|(_, t)| t == "channel"));
    let datasets = ms
        .get("datasets")
        .and_then(Value::as_array)
        .filter(|d| !d.is_empty())
        .ok_or_else(|| err(doc, "multiscales.datasets", "a non-empty list of levels"))?;
    let mut paths = vec![];
    for (i, d) in datasets.iter().enumerate() {
        let field = format!("multiscales.datasets[{i}].path");
        let p = d
            .get("path")
            .and_then(Value::as_str)
            .ok_or_else(|| err(doc, &field, "a path"))?;
        // A level lies inside the image's group, as the native reader has it.
        if !brickyard_core::pyramid::level_path_inside(p) {
            return Err(err(
                doc,
                &field,
                format!("a path inside the image's group (such as \"0\"), found {p:?}"),
            ));
        }
        paths.push(p.to_string());
    }
    let transform_of = |o: &Value, kind: &str| -> Option<Vec<f64>> {
        o.get("coordinateTransformations")?
            .as_array()?
            .iter()
            .find(|t| t.get("type").and_then(Value::as_str) == Some(kind))?
            .get(kind)?
            .as_array()
            .map(|a| a.iter().map(|x| x.as_f64().unwrap_or(f64::NAN)).collect())
    };
    let scale_of = |o: &Value| transform_of(o, "scale");
    let s0 = scale_of(&datasets[0]).unwrap_or_else(|| vec![1.0; axes.len()]);
    let top = scale_of(ms).unwrap_or_else(|| vec![1.0; axes.len()]);
    // world = top scale · (scale · i + translation) + top translation.
    let t0 = transform_of(&datasets[0], "translation").unwrap_or_default();
    let tt = transform_of(ms, "translation").unwrap_or_default();
    let origin = space.map(|a| {
        a.map_or(0.0, |a| {
            let get =
                |v: &Vec<f64>, d: f64| v.get(a).copied().filter(|x| x.is_finite()).unwrap_or(d);
            get(&top, 1.0) * get(&t0, 0.0) + get(&tt, 0.0)
        })
    });
    let spacing = space.map(|a| {
        a.map_or(1.0, |a| {
            let s = s0.get(a).copied().unwrap_or(1.0) * top.get(a).copied().unwrap_or(1.0);
            if s.is_finite() && s > 0.0 {
                s
            } else {
                1.0
            }
        })
    });
    let channels = ome
        .get("omero")
        .and_then(|o| o.get("channels"))
        .and_then(Value::as_array)
        .map(|cs| {
            cs.iter()
                .enumerate()
                .map(|(i, c)| {
                    let hex = c.get("color").and_then(Value::as_str).unwrap_or("FFFFFF");
                    let byte = |k: usize| {
                        hex.get(k..k + 2)
                            .and_then(|h| u8::from_str_radix(h, 16).ok())
                            .unwrap_or(255) as f32
                            / 255.0
                    };
                    let w = c.get("window");
                    let wv = |k: &str| w.and_then(|w| w.get(k)).and_then(Value::as_f64);
                    ChannelMeta {
                        label: c
                            .get("label")
                            .and_then(Value::as_str)
                            .map_or_else(|| format!("channel {i}"), str::to_string),
                        color: [byte(0), byte(2), byte(4)],
                        window: match (wv("start"), wv("end")) {
                            (Some(a), Some(b)) if b > a => Some([a, b]),
                            _ => None,
                        },
                        active: c.get("active").and_then(Value::as_bool).unwrap_or(true),
                    }
                })
                .collect()
        })
        .unwrap_or_default();
    let by = attrs.get("brickyard");
    let labels =
        ome.get("image-label").is_some() || ms.get("type").and_then(Value::as_str) == Some("mode");
    let ms = Multiscale {
        zarr_format,
        levels: vec![],
        axes: axes.into_iter().map(|a| a.0).collect(),
        space,
        channel_axis,
        spacing,
        origin,
        unit,
        channels,
        incomplete: brickyard_core::pyramid::incomplete_reason("", by),
        stats: by
            .and_then(|b| b.get("stats"))
            .and_then(Value::as_str)
            .map(str::to_string),
        stats_brick: by
            .and_then(|b| b.get("brick"))
            .and_then(Value::as_array)
            .and_then(|a| {
                let v: Vec<u64> = a.iter().filter_map(Value::as_u64).collect();
                (v.len() == 3).then(|| [v[0], v[1], v[2]])
            }),
        labels,
    };
    Ok((ms, paths))
}

/// Check that the levels fit together: the same axes and data type, and
/// one channel count.
pub fn check_levels(ms: &Multiscale) -> Result<(), MetaError> {
    let l0 = &ms.levels[0];
    for l in &ms.levels {
        let doc = format!(
            "{}/{}",
            l.path,
            if ms.zarr_format == 3 {
                "zarr.json"
            } else {
                ".zarray"
            }
        );
        if l.shape.len() != ms.axes.len() {
            return Err(err(
                &doc,
                "shape",
                format!(
                    "{} axes as the multiscales lists ({:?})",
                    ms.axes.len(),
                    ms.axes
                ),
            ));
        }
        if l.dtype != l0.dtype {
            return Err(err(&doc, "data type", format!("{:?} as level 0", l0.dtype)));
        }
        if let Some(c) = ms.channel_axis {
            if l.shape[c] != l0.shape[c] {
                return Err(err(
                    &doc,
                    "shape",
                    "the same number of channels at every level",
                ));
            }
        }
        if l.shape.contains(&0) {
            return Err(err(&doc, "shape", "no empty axis"));
        }
    }
    // From the finest down: none larger than the one before.
    for w in ms.levels.windows(2) {
        if w[1].shape.iter().zip(&w[0].shape).any(|(a, b)| a > b) {
            return Err(err(
                &format!(
                    "{}/{}",
                    w[1].path,
                    if ms.zarr_format == 3 {
                        "zarr.json"
                    } else {
                        ".zarray"
                    }
                ),
                "shape",
                format!(
                    "no axis larger than the level before ({:?} of {}), found {:?}",
                    w[0].shape, w[0].path, w[1].shape
                ),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunk_keys_follow_the_encoding() {
        let mut a = ArrayMeta {
            path: "0".into(),
            shape: vec![10, 10],
            chunk: vec![5, 5],
            dtype: DType::U8,
            big_endian: false,
            fill: vec![0],
            keys: KeyEncoding::Default('/'),
            codecs: vec![],
        };
        assert_eq!(a.chunk_key(&[1, 2]), "0/c/1/2");
        a.keys = KeyEncoding::V2('.');
        assert_eq!(a.chunk_key(&[1, 2]), "0/1.2");
        a.keys = KeyEncoding::V2('/');
        assert_eq!(a.chunk_key(&[1, 2]), "0/1/2");
    }

    #[test]
    fn bad_fields_are_named() {
        let e = parse_v3_array("1", br#"{"node_type":"array","shape":[4,4],"data_type":"complex64","chunk_grid":{"name":"regular","configuration":{"chunk_shape":[2,2]}},"codecs":[]}"#).unwrap_err();
        assert_eq!(
            (e.doc.as_str(), e.field.as_str()),
            ("1/zarr.json", "data_type")
        );
        let e = parse_v2_array(
            "0",
            br#"{"shape":[4],"chunks":[2],"dtype":"<u2","compressor":{"id":"lzma"}}"#,
        )
        .unwrap_err();
        assert_eq!(e.field, "compressor.id");
        let e = parse_root(
            3,
            br#"{"zarr_format":3,"node_type":"group","attributes":{}}"#,
        )
        .unwrap_err();
        assert_eq!(e.field, "multiscales");
        // Levels out of the image's group.
        for bad in ["../x/0", "/etc", "", "0/./1"] {
            let doc = format!(
                r#"{{"zarr_format":3,"node_type":"group","attributes":{{"ome":{{"version":"0.5","multiscales":[{{"axes":[{{"name":"z"}},{{"name":"y"}},{{"name":"x"}}],"datasets":[{{"path":{bad:?}}}]}}]}}}}}}"#
            );
            let e = parse_root(3, doc.as_bytes()).unwrap_err();
            assert_eq!(e.field, "multiscales.datasets[0].path", "{bad:?}: {e:?}");
        }
    }

    /// Level 0's world grid: world = top scale · (scale · i + translation) +
    /// top translation, in the unit of the space axes, as the native reader
    /// has it (labels are drawn over an image only on its grid).
    #[test]
    fn origin_and_unit() {
        let doc = br#"{"zarr_format":3,"node_type":"group","attributes":{"ome":{"version":"0.5","multiscales":[{
            "axes":[{"name":"c","type":"channel"},{"name":"z","type":"space","unit":"micrometer"},{"name":"y","type":"space","unit":"micrometer"},{"name":"x","type":"space","unit":"micrometer"}],
            "datasets":[{"path":"0","coordinateTransformations":[{"type":"scale","scale":[1,2,1,1]},{"type":"translation","translation":[0,1,0,0]}]}],
            "coordinateTransformations":[{"type":"scale","scale":[1,0.5,0.25,0.25]},{"type":"translation","translation":[0,10,20,30]}]}]}}}"#;
        let (ms, _) = parse_root(3, doc).unwrap();
        assert_eq!(ms.spacing, [1.0, 0.25, 0.25]);
        assert_eq!(ms.origin, [10.5, 20.0, 30.0]);
        assert_eq!(ms.unit.as_deref(), Some("micrometer"));
    }
}
