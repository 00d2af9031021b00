//! OME-Zarr metadata: writing OME-Zarr 0.5 (Zarr v3) and reading the
//! `multiscales` of OME-Zarr 0.4 (Zarr v2 or v3) and 0.5.

use crate::codec::Compression;
use crate::error::{IoContext, Result, StoreError};
use crate::source::ChannelDisplay;
use brickyard_core::{DType, LevelPlan};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// Name of the brickyard attribute block in the root group.
pub const ATTR: &str = "brickyard";
/// Where the per-brick statistics live, relative to the root.
pub const STATS_DIR: &str = "_brickyard/stats";

pub use brickyard_core::grid::{known_unit, normalize_unit, unit_in_meters, SPACE_UNITS};

/// Zarr v3 array metadata of one sharded pyramid level.
pub fn level_array_json(
    shape: &[u64],
    shard: &[u64],
    inner: &[u64],
    dtype: DType,
    compression: Compression,
    dim_names: &[&str],
) -> Value {
    let fill = if dtype.is_float() {
        json!(0.0)
    } else {
        json!(0)
    };
    json!({
        "zarr_format": 3,
        "node_type": "array",
        "shape": shape,
        "data_type": dtype.zarr_name(),
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": shard}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": fill,
        "codecs": [{
            "name": "sharding_indexed",
            "configuration": {
                "chunk_shape": inner,
                "codecs": compression.codecs_json(dtype),
                "index_codecs": [
                    {"name": "bytes", "configuration": {"endian": "little"}},
                    {"name": "crc32c"}
                ],
                "index_location": "end"
            }
        }],
        "dimension_names": dim_names,
        "attributes": {}
    })
}

/// Zarr v3 metadata of a plain chunked array (used for statistics).
pub fn plain_array_json(
    shape: &[u64],
    chunk: &[u64],
    dtype: DType,
    compression: Compression,
) -> Value {
    json!({
        "zarr_format": 3,
        "node_type": "array",
        "shape": shape,
        "data_type": dtype.zarr_name(),
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunk}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": if dtype.is_float() { json!("NaN") } else { json!(0) },
        "codecs": compression.codecs_json(dtype),
        "attributes": {}
    })
}

/// The `multiscales` block of OME-Zarr 0.5 for the given levels.
pub fn multiscales_json(
    levels: &[LevelPlan],
    channels: usize,
    unit: Option<&str>,
    name: &str,
    labels: bool,
) -> Value {
    let mut axes = vec![];
    if channels > 1 {
        axes.push(json!({"name": "c", "type": "channel"}));
    }
    for a in ["z", "y", "x"] {
        let mut ax = json!({"name": a, "type": "space"});
        if let Some(u) = unit {
            ax["unit"] = json!(u);
        }
        axes.push(ax);
    }
    let datasets: Vec<Value> = levels
        .iter()
        .enumerate()
        .map(|(i, l)| {
            let mut scale: Vec<f64> = l.scale.to_vec();
            let mut tr: Vec<f64> = l.translation.to_vec();
            if channels > 1 {
                scale.insert(0, 1.0);
                tr.insert(0, 0.0);
            }
            let mut t = vec![json!({"type": "scale", "scale": scale})];
            if tr.iter().any(|&v| v != 0.0) {
                t.push(json!({"type": "translation", "translation": tr}));
            }
            json!({"path": i.to_string(), "coordinateTransformations": t})
        })
        .collect();
    json!([{
        "name": name,
        "axes": axes,
        "datasets": datasets,
        // How coarser levels were made: box means, or the most frequent
        // value for labels.
        "type": if labels { "mode" } else { "mean" }
    }])
}

/// Write a JSON document atomically (temporary file + rename).
pub fn write_json(path: &Path, v: &Value) -> Result<()> {
    if let Some(p) = path.parent() {
        std::fs::create_dir_all(p).at(p)?;
    }
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(v).unwrap() + "\n")
        .and_then(|_| std::fs::rename(&tmp, path))
        .inspect_err(|_| {
            // (A full disk leaves it empty or cut short.)
            let _ = std::fs::remove_file(&tmp);
        })
        .at(path)
}

/// Read a JSON document (a file or a URL, see [`crate::storage`]).
pub fn read_json(path: &Path) -> Result<Value> {
    let bytes = crate::storage::read(path)?.ok_or_else(|| StoreError::not_found(path))?;
    parse_json(path, &bytes)
}

/// Parse a JSON document held in memory; `path` names it in errors.
pub fn parse_json(path: &Path, bytes: &[u8]) -> Result<Value> {
    serde_json::from_slice(bytes)
        .map_err(|e| StoreError::invalid(path, "json", format!("not valid JSON: {e}")))
}

/// One axis of a multiscale image.
#[derive(Debug, Clone, PartialEq)]
pub struct Axis {
    pub name: String,
    pub kind: Option<String>,
    pub unit: Option<String>,
}

/// One dataset (level) of a multiscale image.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    pub path: String,
    pub scale: Option<Vec<f64>>,
    pub translation: Option<Vec<f64>>,
}

/// The parsed `multiscales[0]` of an OME-Zarr image.
#[derive(Debug, Clone, PartialEq)]
pub struct Multiscale {
    /// `"0.4"`, `"0.5"`, ...
    pub version: String,
    pub axes: Vec<Axis>,
    pub datasets: Vec<Dataset>,
    /// Zarr format of the group (2 or 3).
    pub zarr_format: u8,
    /// The root's `brickyard` attribute block, if any.
    pub brickyard: Option<Value>,
    /// A label image: its OME attributes hold `image-label` (as a store's
    /// `labels/NAME` does), or its multiscales say coarser levels took the
    /// most frequent value (`"type": "mode"`, as `convert --labels` writes).
    pub label_image: bool,
    /// The `omero` block as the group gives it (read with
    /// [`omero_given`]), and the file it comes from.
    pub omero: Option<Value>,
    pub meta_path: PathBuf,
}

/// The `scale` and `translation` of an object's `coordinateTransformations`
/// (given inline; `identity` and transformations stored in a `path` add
/// nothing).
fn scale_translation(o: &Value) -> (Option<Vec<f64>>, Option<Vec<f64>>) {
    let mut scale = None;
    let mut translation = None;
    if let Some(ts) = o.get("coordinateTransformations").and_then(Value::as_array) {
        for t in ts {
            let vals = |k: &str| {
                t.get(k)
                    .and_then(Value::as_array)
                    // (A value that is not a number is NaN: refused below,
                    // not dropped, which shifted the others to other axes.)
                    .map(|a| {
                        a.iter()
                            .map(|v| v.as_f64().unwrap_or(f64::NAN))
                            .collect::<Vec<_>>()
                    })
            };
            match t.get("type").and_then(Value::as_str) {
                Some("scale") => scale = vals("scale"),
                Some("translation") => translation = vals("translation"),
                _ => {}
            }
        }
    }
    (scale, translation)
}

/// Read the group attributes of a Zarr v2 or v3 group directory.
/// Returns `(zarr_format, attributes)` or `None` if `dir` is not a group.
pub fn read_group_attributes(dir: &Path) -> Result<Option<(u8, Value)>> {
    let v3 = dir.join("zarr.json");
    if crate::storage::exists(&v3) {
        let j = read_json(&v3)?;
        if j.get("node_type").and_then(Value::as_str) != Some("group") {
            return Ok(None);
        }
        return Ok(Some((3, j.get("attributes").cloned().unwrap_or(json!({})))));
    }
    if crate::storage::exists(&dir.join(".zgroup")) {
        let attrs = dir.join(".zattrs");
        let a = if crate::storage::exists(&attrs) {
            read_json(&attrs)?
        } else {
            json!({})
        };
        return Ok(Some((2, a)));
    }
    Ok(None)
}

/// The label images a store's `labels` group lists (none without the
/// group).
pub fn label_names(store: &Path) -> Result<Vec<String>> {
    let Some((_, attrs)) = read_group_attributes(&store.join("labels"))? else {
        return Ok(vec![]);
    };
    let ome = attrs.get("ome").unwrap_or(&attrs);
    Ok(ome
        .get("labels")
        .and_then(Value::as_array)
        .map(|a| {
            a.iter()
                .filter_map(Value::as_str)
                .map(str::to_string)
                .collect()
        })
        .unwrap_or_default())
}

/// Parse the OME multiscales of the group at `dir`, if it has any.
pub fn read_multiscale(dir: &Path) -> Result<Option<Multiscale>> {
    let Some((zarr_format, attrs)) = read_group_attributes(dir)? else {
        return Ok(None);
    };
    let meta_path: PathBuf = if zarr_format == 3 {
        dir.join("zarr.json")
    } else {
        dir.join(".zattrs")
    };
    parse_multiscale(&meta_path, zarr_format, &attrs)
}

/// Parse the OME multiscales in the attributes `attrs` of a Zarr v2 or v3
/// group (`meta_path` names the file they come from in errors); `Ok(None)`
/// when there are none.
pub fn parse_multiscale(
    meta_path: &Path,
    zarr_format: u8,
    attrs: &Value,
) -> Result<Option<Multiscale>> {
    let brickyard = attrs.get(ATTR).cloned();
    // 0.5 puts everything under "ome"; 0.4 at the top level.
    let (ome, version_default) = match attrs.get("ome") {
        Some(o) => (o.clone(), "0.5"),
        None => (attrs.clone(), "0.4"),
    };
    let Some(ms) = ome.get("multiscales") else {
        return Ok(None);
    };
    let ms0 = ms.as_array().and_then(|a| a.first()).ok_or_else(|| {
        StoreError::invalid(meta_path, "multiscales", "expected a non-empty list")
    })?;
    let version = ome
        .get("version")
        .or_else(|| ms0.get("version"))
        .and_then(Value::as_str)
        .unwrap_or(version_default)
        .to_string();
    let axes = match ms0.get("axes").and_then(Value::as_array) {
        Some(a) => a
            .iter()
            .map(|ax| match ax {
                Value::String(s) => Ok(Axis {
                    name: s.clone(),
                    kind: None,
                    unit: None,
                }),
                Value::Object(o) => Ok(Axis {
                    name: o
                        .get("name")
                        .and_then(Value::as_str)
                        .ok_or_else(|| {
                            StoreError::invalid(
                                meta_path,
                                "multiscales.axes",
                                "axis without a name",
                            )
                        })?
                        .to_string(),
                    kind: o.get("type").and_then(Value::as_str).map(str::to_string),
                    unit: o.get("unit").and_then(Value::as_str).map(str::to_string),
                }),
                _ => Err(StoreError::invalid(
                    meta_path,
                    "multiscales.axes",
                    "expected objects or names",
                )),
            })
            .collect::<Result<Vec<_>>>()?,
        // 0.1-0.3 had no axes: assume the last three are z, y, x.
        None => vec![],
    };
    let datasets = ms0
        .get("datasets")
        .and_then(Value::as_array)
        .filter(|d| !d.is_empty())
        .ok_or_else(|| {
            StoreError::invalid(
                meta_path,
                "multiscales.datasets",
                "expected a non-empty list",
            )
        })?
        .iter()
        .map(|d| {
            let path = d
                .get("path")
                .and_then(Value::as_str)
                .ok_or_else(|| {
                    StoreError::invalid(meta_path, "multiscales.datasets.path", "missing")
                })?
                .to_string();
            // A level lies inside the image's group: a path out of it (up,
            // absolute, empty) would read another store's (or any) files.
            if !brickyard_core::pyramid::level_path_inside(&path) {
                return Err(StoreError::invalid(
                    meta_path,
                    "multiscales.datasets.path",
                    format!(
                        "expected a path inside the image's group (such as \"0\" or \"s1/a\"), \
                         found {path:?}"
                    ),
                ));
            }
            let (scale, translation) = scale_translation(d);
            Ok(Dataset {
                path,
                scale,
                translation,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    // Transformations of the whole multiscale apply after each dataset's:
    // world = gs · (s · i + t) + gt. Fold them into the datasets.
    let (gs, gt) = scale_translation(ms0);
    let datasets = datasets
        .into_iter()
        .map(|mut d| {
            let n = d
                .scale
                .as_ref()
                .or(d.translation.as_ref())
                .map(Vec::len)
                .or(gs.as_ref().map(Vec::len))
                .or(gt.as_ref().map(Vec::len))
                .unwrap_or(0);
            for (what, g) in [("scale", &gs), ("translation", &gt)] {
                if let Some(g) = g {
                    if g.len() != n {
                        return Err(StoreError::invalid(
                            meta_path,
                            "multiscales.coordinateTransformations",
                            format!(
                                "{what} has {} values but the datasets' transformations have {n}",
                                g.len()
                            ),
                        ));
                    }
                }
            }
            if let Some(g) = &gs {
                let s = d.scale.get_or_insert_with(|| vec![1.0; n]);
                s.iter_mut().zip(g).for_each(|(v, g)| *v *= g);
                if let Some(t) = &mut d.translation {
                    t.iter_mut().zip(g).for_each(|(v, g)| *v *= g);
                }
            }
            if let Some(g) = &gt {
                let t = d.translation.get_or_insert_with(|| vec![0.0; n]);
                t.iter_mut().zip(g).for_each(|(v, g)| *v += g);
            }
            Ok(d)
        })
        .collect::<Result<Vec<_>>>()?;
    // A voxel's size is positive and a position finite: a scale of 0 or
    // -0.2 was taken as 1 by `convert` (silently), and failed `render`
    // naming one of its own parameters.
    for (i, d) in datasets.iter().enumerate() {
        let bad = |v: &Option<Vec<f64>>, ok: fn(f64) -> bool| {
            v.as_ref().filter(|v| !v.iter().all(|&x| ok(x))).cloned()
        };
        if let Some(v) = bad(&d.scale, |x| x.is_finite() && x > 0.0) {
            return Err(StoreError::invalid(
                meta_path,
                format!("multiscales.datasets[{i}] (path {:?}) scale", d.path),
                format!("expected positive numbers (a voxel's size along each axis), found {v:?}"),
            ));
        }
        if let Some(v) = bad(&d.translation, f64::is_finite) {
            return Err(StoreError::invalid(
                meta_path,
                format!("multiscales.datasets[{i}] (path {:?}) translation", d.path),
                format!("expected finite numbers, found {v:?}"),
            ));
        }
    }
    let label_image =
        ome.get("image-label").is_some() || ms0.get("type").and_then(Value::as_str) == Some("mode");
    Ok(Some(Multiscale {
        version,
        axes,
        datasets,
        zarr_format,
        brickyard,
        label_image,
        omero: ome.get("omero").or_else(|| attrs.get("omero")).cloned(),
        meta_path: meta_path.to_path_buf(),
    }))
}

/// Colours (RRGGBB) given to channels in the `omero` metadata, in order:
/// one channel is white; several cycle through these.
pub const CHANNEL_COLORS: [&str; 8] = [
    "00FF00", "FF00FF", "00FFFF", "FF0000", "0000FF", "FFFF00", "FF8000", "8080FF",
];

/// How a channel is shown by default (`omero` metadata).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OmeroChannel {
    pub label: String,
    /// Linear RGB colour, 0–255.
    pub color: [u8; 3],
    /// Data values `[start, end]` shown from black to full colour.
    pub window: Option<[f64; 2]>,
    pub active: bool,
}

/// The OME-Zarr `omero` block for channels named `labels` whose data
/// ranges are `ranges` (`(min, max)`, NaN: unknown): each with its colour,
/// its window and whether it is active, as `display` says where it has an
/// entry for the channel (a source's `omero`), else the defaults: white
/// for one channel, [`CHANNEL_COLORS`] in turn for several, a window over
/// the data range, active. A window's `min`/`max` span the data range and
/// the window.
pub fn omero_json(labels: &[String], ranges: &[(f64, f64)], display: &[ChannelDisplay]) -> Value {
    let n = labels.len();
    let hex = |c: [u8; 3]| format!("{:02X}{:02X}{:02X}", c[0], c[1], c[2]);
    let channels: Vec<Value> = labels
        .iter()
        .zip(ranges)
        .enumerate()
        .map(|(i, (label, &(lo, hi)))| {
            let given = display.get(i).cloned().unwrap_or_default();
            let color = match given.color {
                Some(c) => hex(c),
                None if n == 1 => "FFFFFF".to_string(),
                None => CHANNEL_COLORS[i % CHANNEL_COLORS.len()].to_string(),
            };
            let mut c = json!({
                "label": label,
                "color": color,
                "active": given.active.unwrap_or(true),
                "coefficient": 1,
                "family": "linear",
                "inverted": false,
            });
            let finite = lo.is_finite() && hi.is_finite();
            let range = finite.then_some((lo, if hi > lo { hi } else { lo + 1.0 }));
            match (given.window, range) {
                (Some([a, b]), Some((lo, hi))) => {
                    c["window"] = json!({"min": lo.min(a), "max": hi.max(b), "start": a, "end": b});
                }
                (Some([a, b]), None) => {
                    c["window"] = json!({"min": a, "max": b, "start": a, "end": b});
                }
                (None, Some((lo, hi))) => {
                    c["window"] = json!({"min": lo, "max": hi, "start": lo, "end": hi});
                }
                (None, None) => {}
            }
            c
        })
        .collect();
    json!({"channels": channels, "rdefs": {"model": "color"}})
}

/// The channels of the `omero` block of the group at `dir` (OME-Zarr 0.5:
/// under `ome`; 0.4: at the top of the attributes); `Ok(None)` when there
/// is none. A malformed entry is an error naming the field.
pub fn read_omero(dir: &Path) -> Result<Option<Vec<OmeroChannel>>> {
    Ok(read_omero_given(dir)?.map(|chs| {
        chs.into_iter()
            .map(|(label, d)| OmeroChannel {
                label,
                color: d.color.unwrap_or([255, 255, 255]),
                window: d.window,
                active: d.active.unwrap_or(true),
            })
            .collect()
    }))
}

/// [`read_omero`] as given: each channel's label (`channel i` where it has
/// none) and the fields it gives (a field left out is `None`), for a copy
/// that keeps what the store says and no more.
pub fn read_omero_given(dir: &Path) -> Result<Option<Vec<(String, ChannelDisplay)>>> {
    let Some((zarr_format, attrs)) = read_group_attributes(dir)? else {
        return Ok(None);
    };
    let meta_path = if zarr_format == 3 {
        dir.join("zarr.json")
    } else {
        dir.join(".zattrs")
    };
    omero_given(
        &meta_path,
        attrs
            .get("ome")
            .and_then(|o| o.get("omero"))
            .or_else(|| attrs.get("omero")),
    )
}

/// [`read_omero_given`] of an `omero` block already read (from
/// [`Multiscale::omero`]); `meta_path` names its file in errors.
pub fn omero_given(
    meta_path: &Path,
    omero: Option<&Value>,
) -> Result<Option<Vec<(String, ChannelDisplay)>>> {
    let Some(o) = omero else {
        return Ok(None);
    };
    let Some(chs) = o.get("channels").and_then(Value::as_array) else {
        return Err(StoreError::invalid(
            meta_path,
            "omero.channels",
            "expected an array of channels",
        ));
    };
    let mut out = vec![];
    for (i, c) in chs.iter().enumerate() {
        let field = |f: &str| format!("omero.channels[{i}].{f}");
        let label = c
            .get("label")
            .and_then(Value::as_str)
            .map_or_else(|| format!("channel {i}"), str::to_string);
        let color = match c.get("color") {
            None => None,
            Some(v) => {
                let s = v.as_str().unwrap_or("");
                let ok = s.len() == 6 && s.chars().all(|ch| ch.is_ascii_hexdigit());
                if !ok {
                    return Err(StoreError::invalid(
                        meta_path,
                        field("color"),
                        format!("expected six hex digits RRGGBB, found {v}"),
                    ));
                }
                let b = |k: usize| u8::from_str_radix(&s[2 * k..2 * k + 2], 16).unwrap();
                Some([b(0), b(1), b(2)])
            }
        };
        let window = match c.get("window") {
            None => None,
            Some(w) => {
                let num = |k: &str| w.get(k).and_then(Value::as_f64);
                match (num("start"), num("end")) {
                    (Some(a), Some(b)) if a.is_finite() && b.is_finite() && a < b => Some([a, b]),
                    _ => {
                        return Err(StoreError::invalid(
                            meta_path,
                            field("window"),
                            format!("expected numbers start < end, found {w}"),
                        ))
                    }
                }
            }
        };
        let active = c.get("active").and_then(Value::as_bool);
        out.push((
            label,
            ChannelDisplay {
                color,
                window,
                active,
            },
        ));
    }
    Ok(Some(out))
}

#[cfg(test)]
mod omero_tests {
    use super::*;

    #[test]
    fn omero_keeps_what_a_source_gives_and_defaults_the_rest() {
        let labels = ["DAPI".to_string(), "GFP".to_string(), "RFP".to_string()];
        let ranges = [(0.0, 999.0), (0.0, 999.0), (f64::NAN, f64::NAN)];
        let display = [
            ChannelDisplay {
                color: Some([0, 0, 255]),
                window: Some([100.0, 500.0]),
                active: Some(true),
            },
            ChannelDisplay {
                color: None,
                window: Some([200.0, 1200.0]),
                active: Some(false),
            },
            ChannelDisplay::default(),
        ];
        let o = omero_json(&labels, &ranges, &display);
        let c = &o["channels"];
        assert_eq!(c[0]["color"], "0000FF");
        assert_eq!(c[0]["active"], true);
        assert_eq!(
            c[0]["window"],
            json!({"min": 0.0, "max": 999.0, "start": 100.0, "end": 500.0})
        );
        // A colour not given: the default for its place; a window beyond
        // the data: min/max take it in.
        assert_eq!(c[1]["color"], CHANNEL_COLORS[1]);
        assert_eq!(c[1]["active"], false);
        assert_eq!(
            c[1]["window"],
            json!({"min": 0.0, "max": 1200.0, "start": 200.0, "end": 1200.0})
        );
        assert_eq!(c[2]["color"], CHANNEL_COLORS[2]);
        assert_eq!(c[2]["active"], true);
        assert!(c[2].get("window").is_none());
        // Nothing given: as before.
        assert_eq!(
            omero_json(&labels, &ranges, &[]),
            omero_json(&labels, &ranges, &vec![ChannelDisplay::default(); 3])
        );
        // Read back as given.
        let d = tempfile::tempdir().unwrap();
        let root = json!({"zarr_format": 3, "node_type": "group",
                          "attributes": {"ome": {"version": "0.5", "omero": o}}});
        std::fs::write(d.path().join("zarr.json"), root.to_string()).unwrap();
        let got = read_omero_given(d.path()).unwrap().unwrap();
        assert_eq!(got[0].1, display[0]);
        assert_eq!(got[1].1.window, display[1].window);
        assert_eq!(got[1].1.active, Some(false));
        assert_eq!(got[1].0, "GFP");
    }
}
