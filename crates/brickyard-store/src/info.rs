//! `brickyard info`: what a store holds — levels, shapes, chunking, codecs,
//! size on disk against raw size, brick statistics — for brickyard's own
//! stores and foreign (OME-)Zarr alike; `check` reads and decodes every
//! chunk.

pub mod check;

use crate::error::{Result, StoreError};
use crate::import::zarr::is_zarr;
use crate::omezarr::{read_json, read_multiscale, STATS_DIR};
use crate::storage::{self, StoreAt};
use brickyard_core::DType;
use serde::Serialize;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::Array;

/// Summary of one level.
#[derive(Debug, Clone, Serialize)]
pub struct LevelInfo {
    pub path: String,
    pub shape: Vec<u64>,
    pub dtype: String,
    /// Chunk (or shard) shape of the array.
    pub chunk: Vec<u64>,
    /// Inner chunk shape when the array is sharded.
    pub inner_chunk: Option<Vec<u64>>,
    pub codecs: Vec<String>,
    pub scale: Option<Vec<f64>>,
    pub translation: Option<Vec<f64>>,
    pub bytes_on_disk: u64,
    pub bytes_raw: u64,
    pub stats: Option<BrickSummary>,
}

/// Counts from the per-brick statistics of one level.
#[derive(Debug, Clone, Serialize, Default)]
pub struct BrickSummary {
    pub bricks: u64,
    /// Constant bricks whose value is the fill value 0 (never stored).
    pub empty: u64,
    /// Constant bricks (min == max), including empty ones.
    pub constant: u64,
    /// Bricks of NaN only (counted in `bricks`; they have no range).
    pub nan: u64,
    pub min: f64,
    pub max: f64,
}

/// One channel as the store's `omero` metadata describes it (fields it
/// leaves out take the readers' defaults: white, active).
#[derive(Debug, Clone, Serialize)]
pub struct ChannelInfo {
    pub index: usize,
    pub label: String,
    /// `RRGGBB`.
    pub color: String,
    /// `[start, end]`: the values shown from black to full colour.
    pub window: Option<[f64; 2]>,
    pub active: bool,
}

/// Summary of a store.
#[derive(Debug, Clone, Serialize)]
pub struct StoreInfo {
    pub path: PathBuf,
    pub zarr_format: u8,
    pub ome_version: Option<String>,
    /// `Some(false)` when the store is an unfinished brickyard conversion.
    pub complete: Option<bool>,
    /// Why it is incomplete, where it is
    /// ([`incomplete_reason`](brickyard_core::pyramid::incomplete_reason)).
    #[serde(skip)]
    pub incomplete: Option<&'static str>,
    pub axes: Vec<String>,
    pub units: Vec<Option<String>>,
    pub labels: bool,
    /// A label image ([`Multiscale::label_image`](crate::omezarr::Multiscale::label_image)).
    pub label_image: bool,
    /// What the importer did with the source's header fields (brickyard
    /// stores: the root attribute `brickyard.source_notes`).
    pub source_notes: Vec<String>,
    pub levels: Vec<LevelInfo>,
    /// The channels as the store's OME `omero` metadata describes them
    /// (empty where it has none).
    pub channels: Vec<ChannelInfo>,
    /// Images written into the store by processing (`labels/NAME`,
    /// `derived/NAME`): path inside the store and a one-line summary.
    pub inner_images: Vec<(String, String)>,
    pub problems: Vec<String>,
    /// The path is one level (an array) of an OME-Zarr image in the folder
    /// above: which one, and that `info` of that folder describes it whole.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub level_of: Option<String>,
}

fn dir_size(p: &Path) -> u64 {
    let mut n = 0;
    if let Ok(rd) = std::fs::read_dir(p) {
        for e in rd.flatten() {
            match e.file_type() {
                Ok(t) if t.is_dir() => n += dir_size(&e.path()),
                Ok(_) => n += e.metadata().map(|m| m.len()).unwrap_or(0),
                Err(_) => {}
            }
        }
    }
    n
}

fn codec_names(list: &Value) -> Vec<String> {
    list.as_array()
        .map(|a| {
            a.iter()
                .map(|c| {
                    let name = c.get("name").and_then(Value::as_str).unwrap_or("?");
                    let conf = c.get("configuration");
                    match (name, conf) {
                        ("blosc", Some(cf)) => format!(
                            "blosc({}, {})",
                            cf.get("cname").and_then(Value::as_str).unwrap_or("?"),
                            cf.get("shuffle").and_then(Value::as_str).unwrap_or("?")
                        ),
                        ("zstd", Some(cf)) => format!(
                            "zstd({})",
                            cf.get("level").and_then(Value::as_i64).unwrap_or(0)
                        ),
                        ("bytes", Some(cf)) => format!(
                            "bytes({})",
                            cf.get("endian").and_then(Value::as_str).unwrap_or("?")
                        ),
                        _ => name.to_string(),
                    }
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Shape, data type, chunk shape, inner chunk shape, codec names.
type ArraySummary = (Vec<u64>, String, Vec<u64>, Option<Vec<u64>>, Vec<String>);

fn array_info(dir: &Path) -> Result<ArraySummary> {
    let v3 = dir.join("zarr.json");
    if storage::exists(&v3) {
        let j = read_json(&v3)?;
        let shape: Vec<u64> = serde_json::from_value(j["shape"].clone())
            .map_err(|_| StoreError::invalid(&v3, "shape", "expected a list of integers"))?;
        let dtype = j["data_type"].as_str().unwrap_or("?").to_string();
        let chunk: Vec<u64> =
            serde_json::from_value(j["chunk_grid"]["configuration"]["chunk_shape"].clone())
                .unwrap_or_default();
        let codecs = &j["codecs"];
        if let Some(sh) = codecs
            .as_array()
            .and_then(|a| a.iter().find(|c| c["name"] == "sharding_indexed"))
        {
            let inner: Vec<u64> =
                serde_json::from_value(sh["configuration"]["chunk_shape"].clone())
                    .unwrap_or_default();
            let mut names = vec!["sharding_indexed".to_string()];
            names.extend(
                codec_names(&sh["configuration"]["codecs"])
                    .into_iter()
                    .map(|n| format!("inner:{n}")),
            );
            return Ok((shape, dtype, chunk, Some(inner), names));
        }
        return Ok((shape, dtype, chunk, None, codec_names(codecs)));
    }
    let v2 = dir.join(".zarray");
    if !storage::exists(&v2) {
        return Err(StoreError::io(
            dir,
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "no array here (neither zarr.json nor, for Zarr v2, .zarray)",
            ),
        ));
    }
    let j = read_json(&v2)?;
    let shape: Vec<u64> = serde_json::from_value(j["shape"].clone())
        .map_err(|_| StoreError::invalid(&v2, "shape", "expected a list of integers"))?;
    let chunk: Vec<u64> = serde_json::from_value(j["chunks"].clone()).unwrap_or_default();
    let dtype = j["dtype"].as_str().unwrap_or("?").to_string();
    let mut names = vec![];
    if let Some(f) = j["filters"].as_array() {
        names.extend(
            f.iter()
                .map(|f| f["id"].as_str().unwrap_or("?").to_string()),
        );
    }
    match &j["compressor"] {
        Value::Null => {}
        c => names.push(match c["id"].as_str() {
            Some("blosc") => format!(
                "blosc({}, shuffle={})",
                c["cname"].as_str().unwrap_or("?"),
                c["shuffle"]
            ),
            Some(id) => id.to_string(),
            None => "?".into(),
        }),
    }
    Ok((shape, dtype, chunk, None, names))
}

/// Summarize the statistics array of one level, chunk by chunk: `Ok(None)`
/// where none is stored, an error where it is and cannot be read (a
/// remote store whose server does not answer was said to have none).
fn brick_summary(root: &Path, level: usize) -> std::result::Result<Option<BrickSummary>, String> {
    let dir = root.join(STATS_DIR).join(level.to_string());
    if !storage::exists(&dir.join("zarr.json")) {
        return Ok(None);
    }
    let store = Arc::new(StoreAt::new(&dir));
    let a = Array::open(store, "/").map_err(|e| e.to_string())?;
    let grid = a.chunk_grid_shape().to_vec();
    let mut s = BrickSummary {
        min: f64::INFINITY,
        max: f64::NEG_INFINITY,
        ..Default::default()
    };
    let n: u64 = grid.iter().product();
    for i in 0..n {
        let mut idx = vec![0u64; grid.len()];
        let mut r = i;
        for d in (0..grid.len()).rev() {
            idx[d] = r % grid[d];
            r /= grid[d];
        }
        let v: Vec<f64> = a
            .retrieve_chunk::<Vec<f64>>(&idx)
            .map_err(|e| format!("chunk {idx:?}: {e}"))?;
        // Clip to the array: retrieve_chunk returns the full chunk.
        let shape = a.chunk_shape(&idx).map_err(|e| e.to_string())?;
        let cs: Vec<u64> = shape.iter().map(|c| c.get()).collect();
        let ashape = a.shape();
        let ne = v.len() / 2;
        for e in 0..ne {
            // Position of element e inside the chunk (last axis is the pair).
            let mut rem = e as u64;
            let mut inside = true;
            for d in (0..4).rev() {
                let p = rem % cs[d];
                rem /= cs[d];
                if idx[d] * cs[d] + p >= ashape[d] {
                    inside = false;
                }
            }
            if !inside {
                continue;
            }
            let (mn, mx) = (v[2 * e], v[2 * e + 1]);
            s.bricks += 1;
            // (A brick of one value beside NaN is `(v, NaN)`: not constant.)
            let constant = mn == mx;
            let Some((mn, mx)) = brickyard_core::brick_stats::finite_range(mn, mx) else {
                s.nan += 1;
                continue;
            };
            if constant {
                s.constant += 1;
                if mn == 0.0 {
                    s.empty += 1;
                }
            }
            s.min = s.min.min(mn);
            s.max = s.max.max(mx);
        }
    }
    Ok(Some(s))
}

/// Inspect a store.
///
/// A remote store (a URL) is inspected the same way, except that its size
/// cannot be listed (`bytes_on_disk` is 0, shown as unknown) and of the
/// images written by processing only the label images named in
/// `labels/zarr.json` are found.
pub fn inspect(path: &Path) -> Result<StoreInfo> {
    if !path.exists() && !storage::is_remote(path) {
        // (What an interrupted conversion or job left is said.)
        return Err(StoreError::not_found(path));
    }
    if !is_zarr(path) {
        // A URL: only a 404 makes it no store (other failures count as
        // present and are reported by the reads that follow).
        if storage::is_remote(path) {
            return Err(StoreError::io(
                path,
                std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    "not found (HTTP 404 for zarr.json, .zgroup and .zarray)",
                ),
            ));
        }
        // A volume file given where a store is read: say what to do.
        let hint = if path.is_file() {
            "; a file, not a store: convert it first with `brickyard convert FILE STORE`"
        } else {
            ""
        };
        return Err(StoreError::invalid(
            path,
            "zarr.json",
            format!("not a Zarr store (no zarr.json, .zgroup or .zarray){hint}"),
        ));
    }
    let mut problems = vec![];
    if !storage::is_remote(path) {
        // A conversion replacing this store (`--overwrite`) writes
        // STORE.partial under STORE.lock: one at work now, or one
        // stopped (its lock's process gone, or no lock).
        let (partial, lock) = (
            crate::builder::partial_path(path),
            crate::builder::lock_path(path),
        );
        let running = lock.is_file() && !crate::lock::is_stale(&lock);
        if partial.is_dir() && !running {
            problems.push(format!(
                "{}: what an interrupted conversion into this store wrote (it would have \
                 replaced it): run that convert --overwrite again (it starts over), or remove \
                 the folder",
                partial.display()
            ));
        }
        if lock.is_file() && !running {
            problems.push(format!(
                "{}: the lock of an interrupted conversion (the next one removes it), or \
                 remove the file",
                lock.display()
            ));
        }
        let old = crate::builder::old_path(path);
        if old.is_dir() {
            problems.push(format!(
                "{}: the store this one replaced, left beside it by a conversion stopped while \
                 swapping them (it takes the space of a whole store): remove it",
                old.display()
            ));
        }
    }
    let ms = read_multiscale(path)?;
    let mut info = StoreInfo {
        path: path.to_path_buf(),
        zarr_format: 3,
        ome_version: None,
        complete: None,
        incomplete: None,
        axes: vec![],
        units: vec![],
        labels: false,
        label_image: false,
        source_notes: vec![],
        levels: vec![],
        channels: vec![],
        inner_images: vec![],
        problems: vec![],
        level_of: None,
    };
    if ms.is_none() {
        info.level_of = level_of(path);
    }
    type Ds = (String, Option<Vec<f64>>, Option<Vec<f64>>);
    let datasets: Vec<Ds> = match &ms {
        Some(m) => {
            info.zarr_format = m.zarr_format;
            info.ome_version = Some(m.version.clone());
            info.label_image = m.label_image;
            info.axes = m.axes.iter().map(|a| a.name.clone()).collect();
            info.units = m.axes.iter().map(|a| a.unit.clone()).collect();
            if let Some(b) = &m.brickyard {
                info.labels = b.get("labels").and_then(Value::as_bool).unwrap_or(false);
                info.source_notes = b
                    .get("source_notes")
                    .and_then(Value::as_array)
                    .map(|a| {
                        a.iter()
                            .filter_map(Value::as_str)
                            .map(str::to_string)
                            .collect()
                    })
                    .unwrap_or_default();
            }
            m.datasets
                .iter()
                .map(|d| (d.path.clone(), d.scale.clone(), d.translation.clone()))
                .collect()
        }
        None => {
            info.zarr_format = if storage::exists(&path.join("zarr.json")) {
                3
            } else {
                2
            };
            if is_plain_group(path) {
                // A plain group (such as a store's `labels/`): the images
                // in it, no levels of its own.
                info.inner_images = child_images(path, &mut problems);
                if info.inner_images.is_empty() && !storage::is_remote(path) {
                    problems.push("a Zarr group with no multiscale image in it".into());
                }
                info.problems = problems;
                return Ok(info);
            }
            // A bare array.
            vec![(String::new(), None, None)]
        }
    };
    // The one rule shared with the readers and `serve`; a store without
    // brickyard attributes (another writer's) says nothing either way.
    let by = ms.as_ref().and_then(|m| m.brickyard.as_ref());
    info.incomplete = brickyard_core::pyramid::incomplete_reason(&path.to_string_lossy(), by);
    if info.incomplete.is_some() {
        info.complete = Some(false);
    } else if by.is_some() {
        info.complete = Some(true);
    }
    let mut first_dtype: Option<String> = None;
    for (k, (p, scale, translation)) in datasets.into_iter().enumerate() {
        let dir = if p.is_empty() {
            path.to_path_buf()
        } else {
            path.join(&p)
        };
        // What every reader does first: the array opened as Zarr has it
        // (codecs known, a fill value of the type, inner chunks that
        // divide the shard). The metadata read by hand below passed a
        // level that no reader could open.
        if let Err(e) = Array::open(Arc::new(StoreAt::new(&dir)), "/") {
            problems.push(format!("level {k}: cannot be read: {e}"));
        }
        match array_info(&dir) {
            Ok((shape, dtype, chunk, inner, codecs)) => {
                match &first_dtype {
                    None => first_dtype = Some(dtype.clone()),
                    Some(d0) if *d0 != dtype => problems.push(format!(
                        "level {k}: its voxels are {dtype}, level 0's {d0}: the readers take a pyramid of one type"
                    )),
                    Some(_) => {}
                }
                if let Some(inner) = inner.as_ref().filter(|i| {
                    i.len() != chunk.len()
                        || i.iter().zip(&chunk).any(|(i, c)| *i == 0 || c % i != 0)
                }) {
                    problems.push(format!(
                        "level {k}: inner chunks {inner:?} do not divide its shards {chunk:?}: no reader can place them"
                    ));
                }
                let es = DType::parse(&dtype).map(|d| d.size() as u64).unwrap_or(0);
                let bytes_raw = shape.iter().product::<u64>() * es;
                let mut bytes_on_disk = dir_size(&dir);
                if p.is_empty() {
                    bytes_on_disk = dir_size(path);
                }
                info.levels.push(LevelInfo {
                    path: p,
                    shape,
                    dtype,
                    chunk,
                    inner_chunk: inner,
                    codecs,
                    scale,
                    translation,
                    bytes_on_disk,
                    bytes_raw,
                    stats: match brick_summary(path, k) {
                        Ok(st) => st,
                        Err(e) => {
                            problems.push(format!(
                                "level {k}: its brick statistics ({STATS_DIR}/{k}) cannot be read: {e}"
                            ));
                            None
                        }
                    },
                });
            }
            Err(e) => problems.push(format!("level {k}: {e}")),
        }
    }
    // Statistics kept for some levels and not others: those without them
    // were lost (the writer keeps them for every level), and there a
    // missing shard reads as empty (the statistics say where data is).
    if info.levels.iter().any(|l| l.stats.is_some()) {
        for (k, l) in info.levels.iter().enumerate() {
            let said = format!("level {k}: its brick statistics");
            if l.stats.is_none() && !problems.iter().any(|p| p.starts_with(&said)) {
                problems.push(format!(
                    "level {k}: its brick statistics ({}/{k}) are missing or unreadable: a missing chunk or shard of it cannot be told from an empty one",
                    STATS_DIR
                ));
            }
        }
    }
    if let Some(why) = info.incomplete {
        problems.push(format!(
            "INCOMPLETE: the conversion that wrote this store did not finish: {why}"
        ));
    }
    if ms.is_some() {
        match crate::omezarr::read_omero(path) {
            Ok(Some(chs)) => {
                info.channels = chs
                    .into_iter()
                    .enumerate()
                    .map(|(index, c)| ChannelInfo {
                        index,
                        label: c.label,
                        color: format!("{:02X}{:02X}{:02X}", c.color[0], c.color[1], c.color[2]),
                        window: c.window,
                        active: c.active,
                    })
                    .collect()
            }
            Ok(None) => {}
            Err(e) => problems.push(format!("channels: {e}")),
        }
    }
    info.inner_images = inner_images(path, &mut problems);
    info.problems = problems;
    Ok(info)
}

/// Whether the Zarr node at `path` is a group, not an array: a v3
/// `zarr.json` of `node_type` group, or a v2 `.zgroup` without `.zarray`.
pub(crate) fn is_plain_group(path: &Path) -> bool {
    let v3 = path.join("zarr.json");
    if storage::exists(&v3) {
        read_json(&v3).is_ok_and(|j| j.get("node_type").and_then(Value::as_str) == Some("group"))
    } else {
        storage::exists(&path.join(".zgroup")) && !storage::exists(&path.join(".zarray"))
    }
}

/// The multiscale images directly inside a local group folder; the
/// leftovers of interrupted conversions among them as problems.
fn child_images(path: &Path, problems: &mut Vec<String>) -> Vec<(String, String)> {
    let Ok(rd) = std::fs::read_dir(path) else {
        return vec![];
    };
    let mut names: Vec<String> = rd
        .flatten()
        .filter(|e| e.path().is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    let group = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    names
        .into_iter()
        .filter_map(|name| {
            let dir = path.join(&name);
            let ms = read_multiscale(&dir);
            let by = ms.as_ref().ok().and_then(Option::as_ref);
            if let Some(p) = unfinished(&group, &name, &dir, by) {
                problems.push(p);
                return None;
            }
            let ms = ms.ok()??;
            Some((name, format!("{} levels", ms.datasets.len())))
        })
        .collect()
}

/// Which command wrote the image `name` of a store's `group` (`labels`,
/// `derived`) whose root multiscale is `ms`, and how to write it again:
/// `process` marks its results (`brickyard.process`); a brickyard store
/// without that mark is a conversion's (`convert`, or Python's
/// `convert`/`from_numpy`). `None`: another writer's, or not known.
fn writer_of(
    group: &str,
    name: &str,
    ms: Option<&crate::omezarr::Multiscale>,
) -> Option<(String, String)> {
    let b = ms?.brickyard.as_ref()?;
    Some(match b.get("process") {
        Some(_) => (
            "`brickyard process` job".to_string(),
            "the same `brickyard process` command with --overwrite".to_string(),
        ),
        None => (
            format!("conversion ({})", convert_command(group, name)),
            "the same convert with --overwrite".to_string(),
        ),
    })
}

/// Who may have written the image `name` of `group` where its metadata
/// does not say, and what to run again.
fn either_writer(group: &str, name: &str) -> (String, String) {
    (
        format!(
            "conversion ({}) or `brickyard process` job",
            convert_command(group, name)
        ),
        "the command that wrote it, run again with --overwrite,".to_string(),
    )
}

/// The conversion that writes `group/name` (`labels`: with --labels).
fn convert_command(group: &str, name: &str) -> String {
    let labels = match group {
        "labels" => " --labels",
        _ => "",
    };
    format!("`brickyard convert INPUT STORE/{group}/{name}{labels}`")
}

/// The problem with the image `name` in a store's `group` (at `dir`, its
/// root multiscale `ms` where read) when it is not finished, by the one
/// rule for completeness
/// ([`incomplete_reason`](brickyard_core::pyramid::incomplete_reason)):
/// what left it, and how to clean it up.
fn unfinished(
    group: &str,
    name: &str,
    dir: &Path,
    ms: Option<&crate::omezarr::Multiscale>,
) -> Option<String> {
    let by = ms.and_then(|m| m.brickyard.as_ref());
    let why = brickyard_core::pyramid::incomplete_reason(&dir.to_string_lossy(), by)?;
    let rel = format!("{group}/{name}");
    Some(match name.strip_suffix(".partial") {
        // `convert` writes NAME.partial beside NAME (`process` writes
        // hidden folders, .NAME.new.partial): a conversion's.
        Some(target) => format!(
            "{rel}: not an image but {why}, by {}: run that convert again{} (it starts over), \
             or remove the folder",
            convert_command(group, target),
            match dir.with_file_name(target).exists() {
                true => " with --overwrite",
                false => "",
            }
        ),
        None => {
            let (who, again) =
                writer_of(group, name, ms).unwrap_or_else(|| either_writer(group, name));
            format!(
                "{rel}: incomplete ({why}): an interrupted {who}; {again} writes it again, or \
                 remove the folder"
            )
        }
    })
}

/// The names `labels/zarr.json` lists (OME 0.5 `ome.labels`, or 0.4
/// `labels`); `None` where there is no such list.
fn named_labels(path: &Path) -> Option<Vec<String>> {
    let j = read_json(&path.join("labels/zarr.json")).ok()?;
    let a = j
        .pointer("/attributes/ome/labels")
        .or_else(|| j.pointer("/attributes/labels"))?
        .as_array()?;
    Some(
        a.iter()
            .filter_map(Value::as_str)
            .map(str::to_string)
            .collect(),
    )
}

/// The images under `labels/` and `derived/` (what `brickyard process`
/// writes), and the leftovers of interrupted jobs as problems.
fn inner_images(path: &Path, problems: &mut Vec<String>) -> Vec<(String, String)> {
    let mut out = vec![];
    for group in ["labels", "derived"] {
        // The label images the labels group names (`None`: no list).
        let listed = (group == "labels").then(|| named_labels(path)).flatten();
        let mut names: Vec<String> = if storage::is_remote(path) {
            // Not listable: the label images the labels group names.
            match &listed {
                Some(l) => l.clone(),
                None => continue,
            }
        } else {
            group_folders(path, group)
        };
        names.sort();
        // The group's jobs by their locks (`.NAME.lock`): at work now (their
        // names), or gone (killed), as are the temporaries of their
        // attempts: taken over by the next job there.
        let mut working: Vec<String> = vec![];
        let mut left: Vec<String> = vec![];
        if let Ok(rd) = std::fs::read_dir(path.join(group)) {
            for e in rd.flatten().filter(|e| e.path().is_file()) {
                let n = e.file_name().to_string_lossy().into_owned();
                if !n.starts_with('.') {
                    continue;
                }
                match n.strip_suffix(".lock") {
                    Some(job) if crate::lock::live_holder(&e.path()).is_some() => {
                        working.push(job.to_string())
                    }
                    _ if (n.ends_with(".lock") || n.ends_with(".tmp"))
                        && crate::lock::is_stale(&e.path()) =>
                    {
                        left.push(n)
                    }
                    _ => {}
                }
            }
        }
        left.sort();
        for n in left {
            problems.push(format!(
                "{group}/{n}: the lock of an interrupted processing job (the next job there \
                 removes it), or remove the file"
            ));
        }
        // Label images the labels group does not name: a job that stopped
        // between putting the image in place and naming it (a full disk).
        for name in names {
            let rel = format!("{group}/{name}");
            // (A running job's hidden folders: `.NAME.new.partial` and
            // the like, under its lock `.NAME.lock`.)
            if working.iter().any(|w| name.starts_with(&format!("{w}."))) {
                continue;
            }
            if name.starts_with('.') {
                problems.push(format!(
                    "{rel}: left by an interrupted processing job (the same `brickyard process` \
                     command removes it and starts again)"
                ));
                continue;
            }
            // `convert --overwrite` moves the image it replaces to NAME.old
            // and removes it once the new one is in place: one left behind
            // was stopped in between.
            if let Some(target) = name.strip_suffix(".old") {
                if path.join(group).join(target).exists() {
                    problems.push(format!(
                        "{rel}: not an image but the one {group}/{target} replaced, left by a \
                         conversion stopped while swapping them: remove the folder"
                    ));
                    continue;
                }
            }
            let dir = path.join(group).join(&name);
            let ms = read_multiscale(&dir);
            let root = ms.as_ref().ok().and_then(Option::as_ref);
            // A conversion or job that did not finish: not an image of the
            // store, whether its group names it or not.
            if let Some(p) = unfinished(group, &name, &dir, root) {
                problems.push(p);
                continue;
            }
            if listed.as_ref().is_some_and(|l| !l.contains(&name)) {
                let (who, again) =
                    writer_of(group, &name, root).unwrap_or_else(|| either_writer(group, &name));
                problems.push(format!(
                    "{rel}: not named in labels/zarr.json (a {who} that stopped while \
                     publishing it?): {again} writes it again, or remove the folder"
                ));
            }
            // (A first level's metadata that cannot be read is named
            // with its fault, not as "not a multiscale image".)
            let summary = ms.and_then(|ms| {
                let Some(ms) = ms else { return Ok(None) };
                let Some(first) = ms.datasets.first() else {
                    return Ok(None);
                };
                let meta = read_json(&dir.join(&first.path).join("zarr.json"))?;
                let Some(dtype) = meta.get("data_type").and_then(|d| d.as_str()) else {
                    return Ok(None);
                };
                let count = label_count(&dir).map_or(String::new(), |n| {
                    format!(", {n} labels with statistics (_brickyard/labels.csv)")
                });
                Ok(Some(format!(
                    "{dtype}, {} levels{count}",
                    ms.datasets.len()
                )))
            });
            match summary {
                Ok(Some(s)) => out.push((rel, s)),
                Ok(None) => problems.push(format!("{rel}: not a multiscale image")),
                Err(e) => problems.push(format!("{rel}: {e}")),
            }
        }
    }
    out
}

/// The number of labels a label image's statistics hold (`process`
/// writes `"count"` at the head of `_brickyard/labels.json`; only the
/// first KiB is read).
fn label_count(dir: &Path) -> Option<u64> {
    let p = dir.join("_brickyard").join("labels.json");
    let len = storage::size(&p).ok()??;
    let head = storage::read_spans(&p, &[storage::Span::Range(0..len.min(1024))]).ok()??;
    let text = String::from_utf8_lossy(&head[0]).into_owned();
    let rest = &text[text.find("\"count\":")? + 8..];
    let digits: String = rest
        .trim_start()
        .chars()
        .take_while(char::is_ascii_digit)
        .collect();
    digits.parse().ok()
}

/// The folders in a local store's group `group` (`labels`, `derived`),
/// by name, hidden ones (leftovers of interrupted jobs) included.
fn group_folders(path: &Path, group: &str) -> Vec<String> {
    let Ok(rd) = std::fs::read_dir(path.join(group)) else {
        return vec![];
    };
    let mut names: Vec<String> = rd
        .flatten()
        .filter(|e| e.path().is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// Where `path` is one level of an OME-Zarr image (a dataset of the
/// multiscales in the folder above it), which level of which image, in
/// words.
fn level_of(path: &Path) -> Option<String> {
    if storage::is_remote(path) {
        return None;
    }
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty())?;
    let name = path.file_name()?.to_str()?;
    let ms = read_multiscale(parent).ok().flatten()?;
    let i = ms.datasets.iter().position(|d| d.path == name)?;
    Some(format!(
        "level {i} of {} levels of the image {}: `brickyard info {}` describes the whole \
         image, and other commands take it, not the level",
        ms.datasets.len(),
        parent.display(),
        parent.display()
    ))
}

/// Human-readable byte count.
pub fn human_bytes(n: u64) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB", "PiB"];
    let mut v = n as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < units.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{n} B")
    } else {
        format!("{v:.1} {}", units[u])
    }
}

/// Print a store summary as text.
pub fn format_info(i: &StoreInfo) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "{}", i.path.display());
    let status = match i.complete {
        Some(true) => "complete (brickyard)",
        Some(false) => "INCOMPLETE",
        None if i.level_of.is_some() => "one level of an OME-Zarr image",
        None => "foreign store",
    };
    let _ = writeln!(
        s,
        "  format: Zarr v{}, OME-Zarr {}, {status}{}",
        i.zarr_format,
        i.ome_version.as_deref().unwrap_or("-"),
        if i.labels { ", labels" } else { "" }
    );
    if let Some(l) = &i.level_of {
        let _ = writeln!(s, "  {l}");
    }
    if !i.axes.is_empty() {
        let ax: Vec<String> = i
            .axes
            .iter()
            .zip(&i.units)
            .map(|(a, u)| match u {
                Some(u) => format!("{a} ({u})"),
                None => a.clone(),
            })
            .collect();
        let _ = writeln!(s, "  axes: {}", ax.join(", "));
    }
    for c in &i.channels {
        let window = match c.window {
            Some([a, b]) => format!("window {a}..{b}"),
            None => "no window (the data range)".to_string(),
        };
        let _ = writeln!(
            s,
            "  channel {} {:?}: colour {}, {window}, {}",
            c.index,
            c.label,
            c.color,
            if c.active { "active" } else { "inactive" }
        );
    }
    for n in &i.source_notes {
        let _ = writeln!(s, "  source: {n}");
    }
    let (mut disk, mut raw) = (0, 0);
    for (k, l) in i.levels.iter().enumerate() {
        disk += l.bytes_on_disk;
        raw += l.bytes_raw;
        let _ = writeln!(
            s,
            "  level {k} [{}]: shape {:?} {}  chunk {:?}{}  codecs [{}]",
            l.path,
            l.shape,
            l.dtype,
            l.chunk,
            l.inner_chunk
                .as_ref()
                .map(|c| format!(" inner {c:?}"))
                .unwrap_or_default(),
            l.codecs.join(", ")
        );
        if let Some(sc) = &l.scale {
            let _ = writeln!(
                s,
                "           scale {:?}{}",
                sc,
                l.translation
                    .as_ref()
                    .map(|t| format!(" translation {t:?}"))
                    .unwrap_or_default()
            );
        }
        if storage::is_remote(&i.path) {
            let _ = writeln!(
                s,
                "           {} raw (size stored: unknown, a remote store is not listed)",
                human_bytes(l.bytes_raw)
            );
        } else {
            let ratio = if l.bytes_on_disk > 0 {
                l.bytes_raw as f64 / l.bytes_on_disk as f64
            } else {
                f64::INFINITY
            };
            let _ = writeln!(
                s,
                "           {} on disk, {} raw ({ratio:.2}x)",
                human_bytes(l.bytes_on_disk),
                human_bytes(l.bytes_raw)
            );
        }
        if let Some(b) = &l.stats {
            // (Bricks of NaN only have no range.)
            let nan = match b.nan {
                0 => String::new(),
                n => format!(", {n} of NaN only"),
            };
            let values = if b.min <= b.max {
                format!("values {}..{}", b.min, b.max)
            } else {
                "no values but NaN".to_string()
            };
            let _ = writeln!(
                s,
                "           bricks: {} ({} empty, {} constant incl. empty{nan}), {values}",
                b.bricks, b.empty, b.constant
            );
        }
    }
    let ratio = if disk > 0 {
        raw as f64 / disk as f64
    } else {
        f64::INFINITY
    };
    if i.levels.is_empty() {
        // A group: nothing of its own to count.
    } else if storage::is_remote(&i.path) {
        let _ = writeln!(s, "  total: {} raw", human_bytes(raw));
    } else {
        let _ = writeln!(
            s,
            "  total: {} on disk, {} raw ({ratio:.2}x)",
            human_bytes(disk),
            human_bytes(raw)
        );
    }
    if !i.levels.is_empty() && i.levels.iter().all(|l| l.stats.is_none()) {
        let _ = writeln!(s, "  brick statistics: none stored");
    }
    for (rel, summary) in &i.inner_images {
        let _ = writeln!(s, "  image inside: {rel} ({summary})");
    }
    for p in &i.problems {
        let _ = writeln!(s, "  problem: {p}");
    }
    s
}
