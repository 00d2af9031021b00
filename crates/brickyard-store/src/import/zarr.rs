//! Zarr and OME-Zarr input: Zarr v2 and v3 arrays (any chunking, sharded or
//! not, any codec `zarrs` decodes) and OME-Zarr 0.4 / 0.5 multiscale images.
//!
//! Over 800 lines: with its tests: 0.84k lines of code, 0.1k of tests.

use super::chunks::{copy_into, Body, ChunkCache, Decoded, Idx, ShardReader};
use crate::brick_stats::LevelStats;
use crate::error::{Result, StoreError};
use crate::omezarr::{read_json, read_multiscale, Multiscale, STATS_DIR};
use crate::shard::{self, IndexLayout};
use crate::source::{check_box, check_region, Absence, SourceMeta, VolumeSource};
use crate::storage::{self, StoreAt};
use brickyard_core::{as_bytes, dispatch_dtype, DType, Dims3};
use serde_json::Value;
use std::collections::HashSet;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use zarrs::array::codec::api::CodecOptions;
use zarrs::array::{
    Array, ArrayShardedExt, ArrayShardedReadableExt, ArrayShardedReadableExtCache, ArraySubset,
};

/// Most shard decoders kept by one source.
pub const SHARD_CACHE_MAX: usize = 256;

/// Largest chunk (inner chunk of a sharded array) decoded in one piece:
/// metadata asking for more is refused when the array is opened.
pub const MAX_CHUNK_BYTES: u64 = 1 << 30;

/// Most channels read from one array: every channel costs per-channel
/// state downstream, and an array's channel axis, unlike a file's, need
/// not be backed by any data.
pub const MAX_CHANNELS: u64 = 1 << 16;

/// Chunks decoded so far by the direct reads of sharded arrays (every
/// array of this process): benchmarks compare it with the chunks a read
/// covers to count decodes per chunk.
pub fn chunks_decoded() -> u64 {
    super::chunks::CHUNKS_DECODED.load(std::sync::atomic::Ordering::Relaxed)
}

pub use super::chunks::take_fill_read;

/// Shards whose index was checked, remembered per source (the set is
/// cleared when it grows past this, so it stays small).
const CHECKED_SHARDS_MAX: usize = 1 << 16;

/// Source keys in shared decoded-chunk caches.
static NEXT_SOURCE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// A cache of decoded chunks that several [`ZarrSource`]s read through
/// ([`ZarrSource::share_chunk_cache`]): `bytes` in all, shells of evicted
/// chunks `width` deep kept (0: none). The sources should share the voxel
/// type.
#[derive(Clone)]
pub struct SharedChunkCache(Arc<ChunkCache>);

impl SharedChunkCache {
    pub fn new(bytes: u64, width: u64, dtype: DType) -> SharedChunkCache {
        SharedChunkCache(Arc::new(ChunkCache::new(bytes, width, dtype.size())))
    }

    /// Bytes held now.
    pub fn bytes(&self) -> u64 {
        self.0.bytes()
    }
}

/// A 3D (optionally multi-channel) view of one Zarr array.
pub struct ZarrSource {
    meta: SourceMeta,
    array: Array<StoreAt>,
    /// Array axis index of z, y, x (`None` for an absent axis of size 1).
    zyx: [Option<usize>; 3],
    /// Array axis index of the channel axis.
    caxis: Option<usize>,
    chunk: Vec<u64>,
    /// Decoders of recently used shards (their indexes), so that reading a
    /// brick does not re-read the shard index. Cleared when it grows past
    /// [`SHARD_CACHE_MAX`] shards, to keep memory bounded.
    shards: ArrayShardedReadableExtCache,
    /// Optional cache of decoded read-granularity chunks (see
    /// [`ZarrSource::enable_chunk_cache`]), possibly shared with other
    /// sources, and this source's key in it (prefixed to chunk indices).
    chunk_cache: Option<(Arc<ChunkCache>, u64)>,
    /// The read granularity: inner chunks of a sharded array, chunks
    /// otherwise (array axis order).
    grain: Vec<u64>,
    /// Direct reads of the inner chunks of a sharded array whose index
    /// layout is known (otherwise the Zarr library reads them).
    direct: Option<ShardReader>,
    /// The fill value, one element.
    fill: Vec<u8>,
    /// Shard index checking, for sharded arrays whose index layout is known.
    shard_check: Option<ShardCheck>,
    /// The multiscale metadata, when the path was an OME-Zarr image.
    pub multiscale: Option<Multiscale>,
    /// The array's directory (chunk keys are relative to it).
    dir: std::path::PathBuf,
    /// The image's group and level, when opened through it.
    group: Option<(PathBuf, usize)>,
    /// Reads checked against the store's per-brick statistics
    /// ([`ZarrSource::check_against_stats`]).
    stats_check: Option<LevelStats>,
    /// A 64-bit integer array, read as 32-bit (`meta.dtype`): see [`Wide`].
    wide: Option<Wide>,
}

/// 64-bit integer arrays (label images from segmentation tools are often
/// uint64), which brickyard stores as their 32-bit counterpart: every value
/// read is checked to fit, and a read that meets one that does not fails,
/// naming the value and the voxel, so that no value is ever changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Wide {
    U64,
    I64,
}

impl Wide {
    fn name(self) -> &'static str {
        match self {
            Wide::U64 => "uint64",
            Wide::I64 => "int64",
        }
    }

    /// The 32-bit type's Zarr name.
    fn narrow_name(self) -> &'static str {
        match self {
            Wide::U64 => "uint32",
            Wide::I64 => "int32",
        }
    }

    fn narrow(self) -> DType {
        match self {
            Wide::U64 => DType::U32,
            Wide::I64 => DType::I32,
        }
    }
}

/// The voxel type of a Zarr array from its `data_type` (v3) or `dtype`
/// (v2, a NumPy type string whose number counts bytes: `<u8` is uint64):
/// the type brickyard stores, and whether it is a 64-bit integer read
/// narrowed ([`Wide`]).
pub(crate) fn zarr_dtype(name: &str, v2: bool) -> Option<(DType, Option<Wide>)> {
    let t = name.trim().to_ascii_lowercase();
    let t = if v2 {
        let t = t.trim_start_matches(['<', '>', '|', '=']);
        match t {
            "u1" | "b1" => "uint8",
            "i1" => "int8",
            "u2" => "uint16",
            "i2" => "int16",
            "u4" => "uint32",
            "i4" => "int32",
            "u8" => "uint64",
            "i8" => "int64",
            "f4" => "float32",
            "f8" => "float64",
            _ => return None,
        }
    } else {
        t.as_str()
    };
    let wide = match t {
        "uint64" => Some(Wide::U64),
        "int64" => Some(Wide::I64),
        _ => None,
    };
    let dtype = match (wide, t) {
        (Some(w), _) => w.narrow(),
        (None, "uint8" | "bool") => DType::U8,
        (None, "int8") => DType::I8,
        (None, "uint16") => DType::U16,
        (None, "int16") => DType::I16,
        (None, "uint32") => DType::U32,
        (None, "int32") => DType::I32,
        (None, "float32") => DType::F32,
        (None, "float64") => DType::F64,
        _ => return None,
    };
    Some((dtype, wide))
}

fn is_array_dir(p: &Path) -> bool {
    if storage::exists(&p.join(".zarray")) {
        return true;
    }
    match read_json(&p.join("zarr.json")) {
        Ok(j) => j.get("node_type").and_then(Value::as_str) == Some("array"),
        Err(_) => false,
    }
}

/// Whether `p` looks like a Zarr node (group or array).
pub fn is_zarr(p: &Path) -> bool {
    (storage::is_remote(p) || p.is_dir())
        && (storage::exists(&p.join("zarr.json"))
            || storage::exists(&p.join(".zarray"))
            || storage::exists(&p.join(".zgroup")))
}

/// Open level `level` of an OME-Zarr image, or a bare Zarr array.
pub fn open(path: &Path, level: usize) -> Result<ZarrSource> {
    if storage::is_remote(path) {
        if !is_zarr(path) {
            return Err(StoreError::invalid(
                path,
                "zarr.json",
                "no Zarr group or array at this URL (neither zarr.json, .zarray nor .zgroup \
                 could be read)",
            ));
        }
    } else if !path.exists() {
        return Err(StoreError::not_found(path));
    }
    if is_array_dir(path) {
        return open_array(path, None, None);
    }
    let ms = read_multiscale(path)?.ok_or_else(|| {
        StoreError::invalid(
            path,
            "multiscales",
            "this Zarr group holds no OME multiscale image (and is not an array)",
        )
    })?;
    // An interrupted conversion's store (or its folder while it is
    // written): its missing chunks would read as the fill value.
    if let Some(why) =
        brickyard_core::pyramid::incomplete_reason(&path.to_string_lossy(), ms.brickyard.as_ref())
    {
        return Err(StoreError::invalid(
            path,
            "attributes.brickyard.complete",
            format!(
                "the store is incomplete: {why}; its missing chunks would read as zeros; \
                 convert the volume again"
            ),
        ));
    }
    let ds = ms.datasets.get(level).ok_or_else(|| {
        StoreError::invalid(
            path,
            "multiscales.datasets",
            format!(
                "level {level} asked for but the image has {} levels",
                ms.datasets.len()
            ),
        )
    })?;
    let apath = path.join(&ds.path);
    if !is_array_dir(&apath) {
        // A metadata file that is there but unreadable (damaged, cut
        // short) is named with its own fault, not as a missing array.
        let meta = apath.join("zarr.json");
        if storage::exists(&meta) {
            let j = read_json(&meta)?;
            return Err(StoreError::invalid(
                &meta,
                "node_type",
                format!(
                    "expected \"array\" (level {level} of the image), found {}",
                    j.get("node_type").unwrap_or(&Value::Null)
                ),
            ));
        }
        return Err(StoreError::invalid(
            &apath,
            "datasets.path",
            "no Zarr array at this path",
        ));
    }
    let ds0 = ms.datasets[0].clone();
    let mut src = open_array(&apath, Some((ms, level)), Some(ds0.path))?;
    src.group = Some((path.to_path_buf(), level));
    Ok(src)
}

/// Shard index checking of one sharded array.
struct ShardCheck {
    layout: IndexLayout,
    /// The array's directory (shard keys are relative to it).
    dir: PathBuf,
    /// Shards (by grid index) whose index was found sound.
    checked: Mutex<HashSet<Vec<u64>>>,
}

/// The metadata file of the array at `apath` and its chunk shape key.
fn metadata_file(apath: &Path) -> (PathBuf, &'static str) {
    if storage::exists(&apath.join("zarr.json")) {
        (
            apath.join("zarr.json"),
            "chunk_grid.configuration.chunk_shape",
        )
    } else {
        (apath.join(".zarray"), "chunks")
    }
}

/// Check the shape and chunk shape of an array's metadata before the Zarr
/// library sees them: lists of positive integers of one length (an empty
/// array has nothing to convert or show). The library's own errors about
/// these are less clear, and it accepts empty arrays.
fn precheck_metadata(apath: &Path) -> Result<()> {
    let (file, chunk_key) = metadata_file(apath);
    let j = read_json(&file)?;
    let ints = |v: Option<&Value>| -> Option<Vec<u64>> {
        v?.as_array()?.iter().map(Value::as_u64).collect()
    };
    let shape = ints(j.get("shape")).ok_or_else(|| {
        StoreError::invalid(
            &file,
            "shape",
            "expected a list of positive integers (one size per axis)",
        )
    })?;
    if shape.contains(&0) {
        return Err(StoreError::invalid(
            &file,
            "shape",
            format!("{shape:?} holds no voxels; every axis needs a size of at least 1"),
        ));
    }
    let chunk_json = if chunk_key == "chunks" {
        j.get("chunks")
    } else {
        match j.get("chunk_grid").and_then(|g| g.get("name")) {
            Some(Value::String(n)) if n == "regular" => j
                .get("chunk_grid")
                .and_then(|g| g.get("configuration"))
                .and_then(|c| c.get("chunk_shape")),
            // Other grids: the library checks them.
            _ => return Ok(()),
        }
    };
    let chunk = ints(chunk_json).filter(|c| c.len() == shape.len() && !c.contains(&0));
    if chunk.is_none() {
        return Err(StoreError::invalid(
            &file,
            chunk_key,
            format!(
                "expected {} positive integers (one per axis of the shape {shape:?}), found {}",
                shape.len(),
                chunk_json.map_or("nothing".to_string(), |v| {
                    let s = v.to_string();
                    if s.len() > 80 {
                        format!("{}...", s.chars().take(80).collect::<String>())
                    } else {
                        s
                    }
                })
            ),
        ));
    }
    Ok(())
}

/// Check an opened array's sizes: the array addressable in bytes, one
/// decoded (inner) chunk at most [`MAX_CHUNK_BYTES`], and the shard index
/// layout. Returns the shard check to use when reading.
fn check_sizes(
    apath: &Path,
    array: &Array<StoreAt>,
    mj: &Value,
    dtype: &str,
    size: u64,
) -> Result<Option<ShardCheck>> {
    let (file, chunk_key) = metadata_file(apath);
    let shape = array.shape();
    shape
        .iter()
        .try_fold(size, |a, &s| a.checked_mul(s))
        .filter(|&b| b <= i64::MAX as u64)
        .ok_or_else(|| {
            StoreError::invalid(
                &file,
                "shape",
                format!("{shape:?} of {dtype} makes an array of more than 2^63 bytes"),
            )
        })?;
    let n = shape.len();
    let chunk: Vec<u64> = array
        .chunk_shape(&vec![0; n])
        .map_err(|e| StoreError::zarr(apath, e))?
        .iter()
        .map(|c| c.get())
        .collect();
    let sharding = mj.get("codecs").and_then(Value::as_array).and_then(|c| {
        c.iter()
            .position(|c| c.get("name").and_then(Value::as_str) == Some("sharding_indexed"))
            .map(|i| (i, &c[i]))
    });
    let (grain, grain_key): (Vec<u64>, &str) = match (array.is_sharded(), sharding) {
        (true, Some(_)) => match array.effective_subchunk_shape() {
            Some(s) => (
                s.iter().map(|c| c.get()).collect(),
                "sharding_indexed.chunk_shape",
            ),
            None => (chunk.clone(), chunk_key),
        },
        _ => (chunk.clone(), chunk_key),
    };
    let grain_bytes = grain
        .iter()
        .try_fold(size, |a, &c| a.checked_mul(c))
        .unwrap_or(u64::MAX);
    if grain_bytes > MAX_CHUNK_BYTES {
        return Err(StoreError::invalid(
            &file,
            grain_key,
            format!(
                "chunks of {grain:?} {dtype} hold {grain_bytes} bytes; at most {MAX_CHUNK_BYTES} \
                 are decoded in one piece"
            ),
        ));
    }
    let Some((pos, codec)) = sharding.filter(|_| array.is_sharded()) else {
        return Ok(None);
    };
    if pos != 0 {
        // Array-to-array codecs before sharding change the shard's shape;
        // leave such (rare) arrays to the library.
        return Ok(None);
    }
    let empty = Value::Null;
    let config = codec.get("configuration").unwrap_or(&empty);
    Ok(
        IndexLayout::from_codec(&file, config, &chunk)?.map(|layout| ShardCheck {
            layout,
            dir: apath.to_path_buf(),
            checked: Mutex::new(HashSet::new()),
        }),
    )
}

fn open_array(
    apath: &Path,
    ms: Option<(Multiscale, usize)>,
    _p0: Option<String>,
) -> Result<ZarrSource> {
    precheck_metadata(apath)?;
    let store = Arc::new(StoreAt::new(apath));
    let array = Array::open(store, "/").map_err(|e| StoreError::zarr(apath, e))?;
    let mj = serde_json::to_value(array.metadata()).map_err(|e| StoreError::zarr(apath, e))?;
    let v2 = mj.get("data_type").is_none() && mj.get("dtype").is_some();
    let dt_name = mj
        .get("data_type")
        .or_else(|| mj.get("dtype"))
        .and_then(Value::as_str)
        .unwrap_or("?")
        .to_string();
    let (dtype, wide) = zarr_dtype(&dt_name, v2).ok_or_else(|| {
        StoreError::unsupported(
            apath,
            if v2 { "dtype" } else { "data_type" },
            format!(
                "{dt_name:?}; expected one of uint8, int8, uint16, int16, uint32, int32, \
                 uint64 or int64 (read as 32-bit when every value fits), float32, float64"
            ),
        )
    })?;
    // The size of a stored element.
    let esize = if wide.is_some() { 8 } else { dtype.size() };
    let shape = array.shape().to_vec();
    let n = shape.len();
    if !(2..=5).contains(&n) {
        return Err(StoreError::unsupported(
            apath,
            "shape",
            format!("{n} dimensions; expected 2 to 5"),
        ));
    }
    let shard_check = check_sizes(apath, &array, &mj, &dt_name, esize as u64)?;
    // Axis names: from the multiscale, else from dimension_names, else positional.
    let mut names: Vec<Option<String>> = vec![None; n];
    let mut kinds: Vec<Option<String>> = vec![None; n];
    let mut units: Vec<Option<String>> = vec![None; n];
    if let Some((m, _)) = &ms {
        if m.axes.len() == n {
            for (i, a) in m.axes.iter().enumerate() {
                names[i] = Some(a.name.to_ascii_lowercase());
                kinds[i] = a.kind.clone();
                units[i] = a.unit.clone();
            }
        } else if !m.axes.is_empty() {
            return Err(StoreError::invalid(
                apath,
                "multiscales.axes",
                format!("{} axes for an array of {n} dimensions", m.axes.len()),
            ));
        }
    }
    if names.iter().all(Option::is_none) {
        if let Some(dn) = mj.get("dimension_names").and_then(Value::as_array) {
            for (i, v) in dn.iter().enumerate().take(n) {
                names[i] = v.as_str().map(|s| s.to_ascii_lowercase());
            }
        }
    }
    let find = |nm: &str| names.iter().position(|x| x.as_deref() == Some(nm));
    let mut zyx = [find("z"), find("y"), find("x")];
    if zyx[1].is_none() || zyx[2].is_none() {
        // Positional: the last axes are (z,) y, x.
        zyx = if n == 2 {
            [None, Some(0), Some(1)]
        } else {
            [Some(n - 3), Some(n - 2), Some(n - 1)]
        };
    }
    let used: Vec<usize> = zyx.iter().flatten().copied().collect();
    let mut caxis = None;
    for i in 0..n {
        if used.contains(&i) {
            continue;
        }
        let is_c = names[i].as_deref() == Some("c") || kinds[i].as_deref() == Some("channel");
        let is_t = names[i].as_deref() == Some("t") || kinds[i].as_deref() == Some("time");
        if shape[i] == 1 && !is_c {
            continue;
        }
        if is_t {
            return Err(StoreError::unsupported(
                apath,
                "axes",
                format!(
                    "time axis with {} points; brickyard converts one 3D (multi-channel) volume",
                    shape[i]
                ),
            ));
        }
        if caxis.is_some() {
            return Err(StoreError::unsupported(
                apath,
                "axes",
                "more than one non-spatial axis longer than 1",
            ));
        }
        caxis = Some(i);
    }
    let dim = |a: Option<usize>| a.map(|i| shape[i]).unwrap_or(1);
    let dims: Dims3 = [dim(zyx[0]), dim(zyx[1]), dim(zyx[2])];
    let channels = caxis.map(|i| shape[i]).unwrap_or(1);
    if channels > MAX_CHANNELS {
        return Err(StoreError::invalid(
            metadata_file(apath).0,
            "shape",
            format!(
                "{channels} channels (axis {} of {shape:?}); at most {MAX_CHANNELS} are supported",
                caxis.unwrap_or(0)
            ),
        ));
    }
    let channels = channels as usize;
    let mut meta = SourceMeta::new(apath, dims, channels, dtype);
    if let Some((m, level)) = &ms {
        let ds = &m.datasets[*level];
        let pick = |v: &Option<Vec<f64>>| -> Option<[f64; 3]> {
            let v = v.as_ref()?;
            if v.len() != n {
                return None;
            }
            Some([
                zyx[0].map(|i| v[i]).unwrap_or(1.0),
                zyx[1].map(|i| v[i])?,
                zyx[2].map(|i| v[i])?,
            ])
        };
        meta.spacing = pick(&ds.scale);
        meta.origin = pick(&ds.translation);
        meta.unit = zyx.iter().flatten().find_map(|&i| units[i].clone());
        meta.path = apath
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_else(|| PathBuf::from(apath));
        if let Some(b) = &m.brickyard {
            meta.labels = b.get("labels").and_then(Value::as_bool).unwrap_or(false);
        }
        // The channels' names, colours, windows and active flags from
        // `omero`, so a copy keeps them (the name of a single channel
        // is not taken, as before).
        match crate::omezarr::omero_given(&m.meta_path, m.omero.as_ref()) {
            Ok(Some(om)) if om.len() == channels => {
                let (names, display): (Vec<_>, Vec<_>) = om.into_iter().unzip();
                if channels > 1 {
                    meta.channel_names = names;
                }
                if display.iter().any(|d| !d.is_empty()) {
                    meta.channel_display = display;
                }
            }
            Ok(Some(om)) => meta.notes.push(format!(
                "omero: {} channel(s) described for {channels}: their names, colours and \
                 windows are not kept",
                om.len()
            )),
            Ok(None) => {}
            Err(e) => meta.notes.push(format!(
                "omero: not kept ({e}); the channels take the default names, colours and windows"
            )),
        }
    }
    let chunk: Vec<u64> = array
        .chunk_shape(&vec![0; n])
        .map_err(|e| StoreError::zarr(apath, e))?
        .iter()
        .map(|c| c.get())
        .collect();
    let shards = ArrayShardedReadableExtCache::new(&array);
    let fill = array.fill_value().as_ne_bytes().to_vec();
    let direct = shard_check
        .as_ref()
        .filter(|_| wide.is_none())
        .and_then(|sc| {
            let config = mj
                .get("codecs")?
                .as_array()?
                .first()?
                .get("configuration")?;
            ShardReader::new(
                sc.layout,
                &chunk,
                config,
                array.data_type(),
                array.fill_value(),
                dtype.size(),
            )
        });
    let grain: Vec<u64> = match &direct {
        Some(d) => d.inner().to_vec(),
        None if array.is_sharded() => array
            .effective_subchunk_shape()
            .map(|c| c.iter().map(|v| v.get()).collect())
            .unwrap_or_else(|| chunk.clone()),
        None => chunk.clone(),
    };
    // A chunk decoded whole, beside its encoded bytes.
    meta.read_bytes = grain
        .iter()
        .fold(esize as u64, |a, &c| a.saturating_mul(c))
        .saturating_mul(2);
    if let Some(w) = wide {
        meta.notes.push(format!(
            "{} values stored as {} (brickyard's widest integers): every value is checked to \
             fit, and the conversion stops at the first that does not",
            w.name(),
            w.narrow_name()
        ));
    }
    Ok(ZarrSource {
        chunk_cache: None,
        grain,
        direct,
        fill,
        shard_check,
        shards,
        meta,
        array,
        zyx,
        caxis,
        chunk,
        multiscale: ms.map(|(m, _)| m),
        dir: apath.to_path_buf(),
        group: None,
        stats_check: None,
        wide,
    })
}

impl ZarrSource {
    /// Check every read against the per-brick statistics a brickyard store
    /// keeps (`_brickyard/stats/<level>`): a store brick that reads as all
    /// zeros (the fill value) where the statistics say it holds data, and
    /// whose chunk is absent from the store (its file missing, or its
    /// shard's index without it), fails the read with the file named,
    /// instead of passing for empty. A Zarr reader cannot tell such a
    /// lost chunk from one that was never written; the statistics can.
    /// Returns whether the store has such statistics (other stores are
    /// read as before). Readers that do not check for themselves
    /// (conversion, processing) turn it on; the loader checks its bricks
    /// itself.
    pub fn check_against_stats(&mut self) -> bool {
        let (Some((root, level)), Some(ms)) = (&self.group, &self.multiscale) else {
            return false;
        };
        let Some(b) = &ms.brickyard else {
            return false;
        };
        let brick: Option<Dims3> = b
            .get("brick")
            .and_then(|v| serde_json::from_value(v.clone()).ok())
            .filter(|b: &Dims3| b.iter().all(|&v| v > 0));
        let dir = b.get("stats").and_then(Value::as_str).unwrap_or(STATS_DIR);
        let fill_zero = self.fill.iter().all(|&x| x == 0);
        self.stats_check = brick.filter(|_| fill_zero).and_then(|sb| {
            LevelStats::open(
                &root.join(dir).join(level.to_string()),
                sb,
                self.meta.dims,
                self.meta.channels,
            )
        });
        self.stats_check.is_some()
    }

    /// [`check_against_stats`](Self::check_against_stats) of a read of
    /// `region` of channel `c` into a box of `dims` voxels at `at` of
    /// `buf`.
    fn verify(
        &self,
        c: usize,
        region: &[Range<u64>; 3],
        buf: &[u8],
        dims: Dims3,
        at: Dims3,
    ) -> Result<()> {
        let Some(st) = &self.stats_check else {
            return Ok(());
        };
        if region.iter().any(|r| r.is_empty()) {
            return Ok(());
        }
        let lo = region.clone().map(|r| r.start);
        let hi = region.clone().map(|r| r.end);
        let r = crate::brick_stats::ReadBox {
            lo,
            hi,
            buf,
            dims,
            at,
            es: self.meta.dtype.size() as u64,
        };
        st.check_lost_read(self, c as u64, &r)?;
        st.check_range_read(self, c as u64, &r, self.meta.dtype)
    }

    /// Keep up to `bytes` of decoded chunks, so that reads of overlapping
    /// regions (bricks with aprons) decode each chunk once; reads then go
    /// chunk by chunk through that cache, straight into the caller's
    /// buffer. Off by default.
    pub fn enable_chunk_cache(&mut self, bytes: u64) {
        self.enable_chunk_cache_with_shells(bytes, 0);
    }

    /// [`ZarrSource::enable_chunk_cache`], keeping of each evicted chunk
    /// its faces `width` voxels deep (within the same budget): what the
    /// aprons of neighbouring bricks `width` deep read, for a tenth of the
    /// chunk's bytes (64³ chunks, width 1).
    pub fn enable_chunk_cache_with_shells(&mut self, bytes: u64, width: u64) {
        let cc = SharedChunkCache::new(bytes, width, self.meta.dtype);
        self.share_chunk_cache(&cc);
    }

    /// Read through `cache`, a decoded-chunk cache shared with other
    /// sources (the levels of one image): one budget and one
    /// least-recently-used order for all of them, so that the level being
    /// read gets the room the others do not use.
    pub fn share_chunk_cache(&mut self, cache: &SharedChunkCache) {
        if self.wide.is_some() {
            // Read through the library and narrowed, region by region.
            return;
        }
        let id = NEXT_SOURCE.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        self.chunk_cache = Some((cache.0.clone(), id));
    }

    /// Bytes held by the decoded-chunk cache now (0 without one), for all
    /// the sources sharing it: never more than its budget.
    pub fn chunk_cache_bytes(&self) -> u64 {
        self.chunk_cache.as_ref().map_or(0, |(c, _)| c.bytes())
    }

    /// Forget what is kept of the file (shard or chunk) at grid index
    /// `grid`: its index and its decoded chunks, so that the next read
    /// reads it again (a missing file may be back by then).
    fn forget_file(&self, grid: &[u64]) {
        if let Some(d) = &self.direct {
            d.forget_index(grid);
        }
        let Some((cc, id)) = &self.chunk_cache else {
            return;
        };
        // The inner chunks (grain) of the file, in every combination.
        let n = grid.len();
        let per: Vec<u64> = (0..n)
            .map(|a| (self.chunk[a] / self.grain[a].max(1)).max(1))
            .collect();
        let total: u64 = per.iter().product();
        let keys: Vec<Idx> = (0..total)
            .map(|mut k| {
                let mut key: Idx = smallvec::smallvec![0; n];
                for a in (0..n).rev() {
                    key[a] = grid[a] * per[a] + k % per[a];
                    k /= per[a];
                }
                key
            })
            .collect();
        cc.forget(*id, &keys);
    }

    /// Read and decode the read-granularity chunks `keys` (chunk grid
    /// indices over the grain, array axis order).
    fn load_chunks(&self, keys: &[Vec<u64>]) -> Result<Vec<Decoded>> {
        if let Some(d) = &self.direct {
            return d.load(&self.array, &self.dir, keys);
        }
        // (The Zarr library gives absent chunks as the fill value without
        // saying so.)
        super::chunks::note_fill();
        let n = self.grain.len();
        let shape = self.array.shape();
        keys.iter()
            .map(|idx| {
                // The chunk's region, clipped to the array.
                let creg: Vec<Range<u64>> = (0..n)
                    .map(|a| idx[a] * self.grain[a]..((idx[a] + 1) * self.grain[a]).min(shape[a]))
                    .collect();
                let sub = ArraySubset::new_with_ranges(&creg);
                self.check_shards(&sub)?;
                let err = |e: zarrs::array::ArrayError| {
                    // Name the file that holds the chunk (its shard).
                    let outer: Vec<u64> = (0..n)
                        .map(|a| creg[a].start / self.chunk[a].max(1))
                        .collect();
                    let file = self.dir.join(self.array.chunk_key(&outer).as_str());
                    StoreError::zarr(file, format!("chunk at {:?}: {e}", sub.start()))
                };
                let data = dispatch_dtype!(self.meta.dtype, T => {
                    let v: Vec<T> = if self.shards.array_is_sharded() {
                        self.array.retrieve_array_subset_sharded_opt::<Vec<T>>(
                            &self.shards,
                            &sub,
                            &CodecOptions::default(),
                        )
                    } else {
                        self.array.retrieve_array_subset::<Vec<T>>(&sub)
                    }
                    .map_err(err)?;
                    as_bytes(&v).to_vec()
                });
                Ok(Decoded {
                    origin: creg.iter().map(|r| r.start).collect(),
                    dims: creg.iter().map(|r| r.end - r.start).collect(),
                    body: Body::Data(data),
                })
            })
            .collect()
    }

    /// Read `ranges` (array axis order) through the chunk cache into `out`:
    /// array position `p` goes to element `base + Σ (p[a] − start[a]) ·
    /// stride[a]`.
    fn read_cached(
        &self,
        (cc, id): (&ChunkCache, u64),
        ranges: &[Range<u64>],
        out: &mut [u8],
        base: usize,
        stride: &[usize],
    ) -> Result<()> {
        if self.shards.len() > SHARD_CACHE_MAX {
            self.shards.clear();
        }
        let (keys, need) = self.chunks_of(ranges);
        let chunks = cc.get_or_load(id, &keys, &need, |ks| self.load_chunks(ks))?;
        for c in &chunks {
            copy_into(c, ranges, &self.fill, out, base, stride);
        }
        Ok(())
    }

    /// A read of `ranges` (array axis order) that failed with `e`: in a
    /// local store, the first of its chunks whose own decoding fails, named
    /// by its file and position as [`Self::load_chunks`] names it (the
    /// region's error named only the store: `convert` of a damaged store
    /// said so); otherwise, and where no chunk fails alone, `e`. Remote
    /// failures are mostly the network's: said as they are, not read again
    /// chunk by chunk.
    fn failed_read(&self, ranges: &[Range<u64>], e: zarrs::array::ArrayError) -> StoreError {
        let whole = StoreError::zarr(&self.meta.path, e);
        if storage::is_remote(&self.dir) {
            return whole;
        }
        let (keys, _) = self.chunks_of(ranges);
        keys.iter()
            .find_map(|k| self.load_chunks(&[k.to_vec()]).err())
            .unwrap_or(whole)
    }

    /// The chunks (indices over the grain) that the box `ranges` (array
    /// axis order) touches, in C order, and the part of each inside it
    /// (`lo`, `hi`).
    fn chunks_of(&self, ranges: &[Range<u64>]) -> (Vec<Idx>, Vec<(Idx, Idx)>) {
        let n = ranges.len();
        let first: Idx = (0..n).map(|a| ranges[a].start / self.grain[a]).collect();
        let last: Idx = (0..n)
            .map(|a| (ranges[a].end - 1) / self.grain[a])
            .collect();
        let mut keys: Vec<Idx> = vec![];
        let mut need: Vec<(Idx, Idx)> = vec![];
        let mut idx = first.clone();
        'all: loop {
            keys.push(idx.clone());
            need.push((
                (0..n)
                    .map(|a| ranges[a].start.max(idx[a] * self.grain[a]))
                    .collect(),
                (0..n)
                    .map(|a| ranges[a].end.min((idx[a] + 1) * self.grain[a]))
                    .collect(),
            ));
            let mut a = n;
            loop {
                if a == 0 {
                    break 'all;
                }
                a -= 1;
                idx[a] += 1;
                if idx[a] <= last[a] {
                    break;
                }
                idx[a] = first[a];
            }
        }
        (keys, need)
    }

    /// The array-order ranges of the region `rs` (`[z, y, x]`) of channel
    /// `c`.
    fn array_ranges(&self, c: usize, rs: [Range<u64>; 3]) -> Vec<Range<u64>> {
        let mut ranges: Vec<Range<u64>> = vec![0..1; self.array.shape().len()];
        for (a, r) in rs.into_iter().enumerate() {
            if let Some(i) = self.zyx[a] {
                ranges[i] = r;
            }
        }
        if let Some(i) = self.caxis {
            ranges[i] = c as u64..c as u64 + 1;
        }
        ranges
    }

    /// Read the region `rs` (`[z, y, x]`) of channel `c` through the chunk
    /// cache into a box of `dims` voxels (z, y, x order) held by `out`, its
    /// first voxel at `at`.
    fn read_box(
        &self,
        cc: (&ChunkCache, u64),
        c: usize,
        rs: [Range<u64>; 3],
        out: &mut [u8],
        dims: Dims3,
        at: Dims3,
    ) -> Result<()> {
        let ranges = self.array_ranges(c, rs);
        // Each array axis's stride in the box (the channel axis: none).
        let bstride = [(dims[1] * dims[2]) as usize, dims[2] as usize, 1];
        let mut stride = vec![0usize; ranges.len()];
        for (a, i) in self.zyx.iter().enumerate() {
            if let Some(i) = i {
                stride[*i] = bstride[a];
            }
        }
        let base = ((at[0] * dims[1] + at[1]) * dims[2] + at[2]) as usize;
        self.read_cached(cc, &ranges, out, base, &stride)
    }

    /// Check the index of every shard that `subset` (array axis order)
    /// touches and that was not checked before (see [`shard::read_index`]),
    /// so that a damaged index is a clear error before the Zarr library
    /// sizes a read from it.
    /// Read the 64-bit integers of `ranges` (array axes) into `dst` as
    /// 32-bit ones (array axis order), failing at the first value that
    /// does not fit. In two pieces along the first axis longer than one,
    /// so that the 64-bit copy is no larger than `dst`.
    fn read_wide(&self, w: Wide, ranges: &[Range<u64>], dst: &mut [u8]) -> Result<()> {
        let path = &self.meta.path;
        let split = ranges.iter().position(|r| r.end - r.start >= 2);
        let pieces: Vec<Vec<Range<u64>>> = match split {
            None => vec![ranges.to_vec()],
            Some(a) => {
                let mid = ranges[a].start + (ranges[a].end - ranges[a].start) / 2;
                let mut lo = ranges.to_vec();
                let mut hi = ranges.to_vec();
                lo[a].end = mid;
                hi[a].start = mid;
                vec![lo, hi]
            }
        };
        let mut at = 0;
        for piece in pieces {
            let subset = ArraySubset::new_with_ranges(&piece);
            let sizes: Vec<u64> = piece.iter().map(|r| r.end - r.start).collect();
            // The array index of element `k` of the piece.
            let index_of = |mut k: u64| -> Vec<u64> {
                let mut idx = vec![0; sizes.len()];
                for a in (0..sizes.len()).rev() {
                    idx[a] = piece[a].start + k % sizes[a];
                    k /= sizes[a];
                }
                idx
            };
            let fail = |k: usize, v: &dyn std::fmt::Display| {
                StoreError::unsupported(
                    path,
                    "data_type",
                    format!(
                        "{}: the value {v} at array index {:?} does not fit in {}, the widest \
                         integer type brickyard stores (relabel the image so that its values \
                         fit)",
                        w.name(),
                        index_of(k as u64),
                        w.narrow_name()
                    ),
                )
            };
            macro_rules! narrow {
                ($wide:ty, $narrow:ty) => {{
                    if self.shards.len() > SHARD_CACHE_MAX {
                        self.shards.clear();
                    }
                    let v: Vec<$wide> = if self.shards.array_is_sharded() {
                        self.check_shards(&subset)?;
                        self.array.retrieve_array_subset_sharded_opt::<Vec<$wide>>(
                            &self.shards,
                            &subset,
                            &CodecOptions::default(),
                        )
                    } else {
                        self.array.retrieve_array_subset::<Vec<$wide>>(&subset)
                    }
                    .map_err(|e| self.failed_read(&piece, e))?;
                    let part = &mut dst[at..at + v.len() * 4];
                    for (k, (x, o)) in v.iter().zip(part.chunks_exact_mut(4)).enumerate() {
                        let y = <$narrow>::try_from(*x).map_err(|_| fail(k, x))?;
                        o.copy_from_slice(&y.to_ne_bytes());
                    }
                    at += v.len() * 4;
                }};
            }
            match w {
                Wide::U64 => narrow!(u64, u32),
                Wide::I64 => narrow!(i64, i32),
            }
        }
        debug_assert_eq!(at, dst.len());
        Ok(())
    }

    fn check_shards(&self, subset: &ArraySubset) -> Result<()> {
        let Some(sc) = &self.shard_check else {
            return Ok(());
        };
        let shards = self
            .array
            .chunks_in_array_subset(subset)
            .map_err(|e| StoreError::zarr(&sc.dir, e))?;
        let Some(shards) = shards else {
            return Ok(());
        };
        for idx in &shards.indices() {
            if sc
                .checked
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .contains(&idx[..])
            {
                continue;
            }
            let path = sc.dir.join(self.array.chunk_key(&idx).as_str());
            shard::read_index(&path, &sc.layout)?;
            let mut checked = sc
                .checked
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            if checked.len() >= CHECKED_SHARDS_MAX {
                checked.clear();
            }
            checked.insert(idx.to_vec());
        }
        Ok(())
    }

    /// Open one Zarr array directory directly (no multiscale metadata).
    pub fn open_level_array(path: &Path) -> Result<ZarrSource> {
        open_array(path, None, None)
    }

    /// The underlying array's shape.
    pub fn array_shape(&self) -> &[u64] {
        self.array.shape()
    }
}

impl ZarrSource {
    /// Array coordinates of voxel `v` (`[z, y, x]`) of channel `c`.
    fn array_coords(&self, c: usize, v: Dims3) -> Vec<u64> {
        let mut at = vec![0u64; self.array.shape().len()];
        for (axis, p) in self.zyx.iter().zip(v) {
            if let Some(i) = axis {
                at[*i] = p;
            }
        }
        if let Some(i) = self.caxis {
            at[i] = c as u64;
        }
        at
    }
}

impl VolumeSource for ZarrSource {
    fn chunk_file(&self, c: usize, v: Dims3) -> Option<PathBuf> {
        let grid: Vec<u64> = self
            .array_coords(c, v)
            .iter()
            .zip(&self.chunk)
            .map(|(&p, &n)| p / n.max(1))
            .collect();
        Some(self.dir.join(self.array.chunk_key(&grid).as_str()))
    }

    fn chunk_absent(&self, c: usize, v: Dims3) -> Option<(PathBuf, Absence)> {
        let at = self.array_coords(c, v);
        let grid: Vec<u64> = at
            .iter()
            .zip(&self.chunk)
            .map(|(&p, &n)| p / n.max(1))
            .collect();
        let file = self.dir.join(self.array.chunk_key(&grid).as_str());
        let missing = || {
            (!storage::exists(&file)).then(|| {
                self.forget_file(&grid);
                (file.clone(), Absence::FileMissing)
            })
        };
        // A shard whose index has no entry for the inner chunk (index in C
        // order over the shard's grid of inner chunks).
        // The inner chunks are the grain (taken once when the store was
        // opened: the library derives it from the codec's configuration
        // through JSON on every call).
        let Some(sc) = self.shard_check.as_ref() else {
            return missing();
        };
        let inner = &self.grain;
        let mut entry = 0u64;
        let mut pos = vec![];
        for i in 0..at.len() {
            let per = (self.chunk[i] / inner[i].max(1)).max(1);
            let k = (at[i] % self.chunk[i].max(1)) / inner[i].max(1);
            entry = entry * per + k;
            pos.push(k);
        }
        let absent = |ix: &Option<Arc<Vec<[u64; 2]>>>| {
            ix.as_ref()
                .is_none_or(|ix| ix.get(entry as usize) == Some(&[u64::MAX, u64::MAX]))
        };
        let no_entry = || {
            Absence::NoEntry(format!(
                "the shard's index has no entry for its inner chunk {pos:?}"
            ))
        };
        match &self.direct {
            Some(d) => {
                // The index the reads used, kept by the direct reader (a
                // lookup per brick checked, not a read of the shard's index
                // each time), unless it left the chunk out: then the shard
                // may have changed since (a file that was missing is back),
                // and the file says.
                // (Most such bricks were read from a chunk of zeros, which
                // this says without a look at the file: a HEAD request per
                // brick on a remote store.)
                let used = d.index(&file, &grid).ok()?;
                if !absent(&used) {
                    return None;
                }
                if let Some(m) = missing() {
                    return Some(m);
                }
                self.forget_file(&grid);
                let now = shard::read_index(&file, &sc.layout).ok()?.map(Arc::new);
                Some(match (absent(&now), used.is_none()) {
                    (true, _) => (file, no_entry()),
                    (false, true) => (
                        file,
                        Absence::ChangedSince(
                            "the shard file was missing when the brick was read and is there now"
                                .into(),
                        ),
                    ),
                    (false, false) => (
                        file,
                        Absence::ChangedSince(
                            "the shard's index had no entry for the brick's inner chunk when it \
                             was read and has one now"
                                .into(),
                        ),
                    ),
                })
            }
            None => {
                if let Some(m) = missing() {
                    return Some(m);
                }
                let now = shard::read_index(&file, &sc.layout).ok()?.map(Arc::new);
                absent(&now).then(|| {
                    self.forget_file(&grid);
                    (file, no_entry())
                })
            }
        }
    }

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
        if let Some((cc, id)) = &self.chunk_cache {
            let cc = (&**cc, *id);
            let dims = [z.end - z.start, y.end - y.start, x.end - x.start];
            let region = [z, y, x];
            self.read_box(cc, c, region.clone(), out, dims, [0; 3])?;
            return self.verify(c, &region, out, dims, [0; 3]);
        }
        let n = self.array.shape().len();
        let mut ranges: Vec<Range<u64>> = vec![0..1; n];
        let rs = [z, y, x];
        for (a, r) in rs.iter().enumerate() {
            if let Some(i) = self.zyx[a] {
                ranges[i] = r.clone();
            }
        }
        if let Some(i) = self.caxis {
            ranges[i] = c as u64..c as u64 + 1;
        }
        let subset = ArraySubset::new_with_ranges(&ranges);
        // Strides of the retrieved subset (C order over array axes).
        let sizes: Vec<u64> = ranges.iter().map(|r| r.end - r.start).collect();
        let mut strides = vec![1u64; n];
        for i in (0..n.saturating_sub(1)).rev() {
            strides[i] = strides[i + 1] * sizes[i + 1];
        }
        let order: Vec<usize> = self.zyx.iter().flatten().copied().collect();
        let natural = order.windows(2).all(|w| w[0] < w[1]);
        super::chunks::note_fill();
        // Copy `src`, elements of `es` bytes in array axis order, into
        // `out` in z, y, x order.
        let place = |src: &[u8], es: usize, out: &mut [u8]| {
            if natural {
                out.copy_from_slice(src);
                return;
            }
            let st = |a: usize| self.zyx[a].map(|i| strides[i]).unwrap_or(0);
            let (sz, sy, sx) = (st(0), st(1), st(2));
            let (nz, ny, nx) = (
                rs[0].end - rs[0].start,
                rs[1].end - rs[1].start,
                rs[2].end - rs[2].start,
            );
            let mut o = 0;
            for k in 0..nz {
                for j in 0..ny {
                    for i in 0..nx {
                        let s = ((k * sz + j * sy + i * sx) as usize) * es;
                        out[o..o + es].copy_from_slice(&src[s..s + es]);
                        o += es;
                    }
                }
            }
        };
        if let Some(w) = self.wide {
            if natural {
                self.read_wide(w, &ranges, out)?;
            } else {
                let mut tmp = vec![0u8; out.len()];
                self.read_wide(w, &ranges, &mut tmp)?;
                place(&tmp, 4, out);
            }
        } else {
            dispatch_dtype!(self.meta.dtype, T => {
                if self.shards.len() > SHARD_CACHE_MAX {
                    self.shards.clear();
                }
                let v: Vec<T> = if self.shards.array_is_sharded() {
                    self.check_shards(&subset)?;
                    self.array
                        .retrieve_array_subset_sharded_opt::<Vec<T>>(&self.shards, &subset, &CodecOptions::default())
                        .map_err(|e| self.failed_read(&ranges, e))?
                } else {
                    self.array.retrieve_array_subset::<Vec<T>>(&subset).map_err(|e| self.failed_read(&ranges, e))?
                };
                place(as_bytes(&v), std::mem::size_of::<T>(), out);
            });
        }
        let dims = rs.clone().map(|r| r.end - r.start);
        self.verify(c, &rs, out, dims, [0; 3])
    }

    fn read_region_into(
        &self,
        c: usize,
        region: [Range<u64>; 3],
        out: &mut [u8],
        dims: Dims3,
        at: Dims3,
    ) -> Result<()> {
        match &self.chunk_cache {
            Some((cc, id)) => {
                let cc = (&**cc, *id);
                check_box(&self.meta, c, &region, out, dims, at);
                self.read_box(cc, c, region.clone(), out, dims, at)?;
                self.verify(c, &region, out, dims, at)
            }
            None => crate::source::read_region_into_by_copy(self, c, region, out, dims, at),
        }
    }

    /// Hints the stored bytes of the region's chunks that the decoded-chunk
    /// cache does not hold and that were not hinted since their last load,
    /// for sharded arrays read directly.
    fn prefetch(&self, c: usize, region: [Range<u64>; 3]) -> usize {
        let (Some(direct), Some((cc, id))) = (&self.direct, &self.chunk_cache) else {
            return 0;
        };
        // Remote stores take no hint: reading their shard indexes here
        // would only move requests ahead of the load that needs them.
        if storage::is_remote(&self.dir) || region.iter().any(|r| r.is_empty()) {
            return 0;
        }
        let (keys, need) = self.chunks_of(&self.array_ranges(c, region));
        let missing: Vec<Vec<u64>> = cc
            .to_hint(*id, &keys, &need)
            .into_iter()
            .map(|i| keys[i].to_vec())
            .collect();
        if missing.is_empty() {
            return 0;
        }
        direct
            .prefetch(&self.array, &self.dir, &missing)
            .unwrap_or(0)
    }

    fn preferred_read(&self) -> Dims3 {
        let cz = self.zyx[0].map(|i| self.chunk[i]).unwrap_or(1);
        [cz, self.meta.dims[1], self.meta.dims[2]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::test_util::read_all;
    use serde_json::json;

    /// A Zarr v3 uint16 array `4×4×4` in chunks of `2×4×4` with fill value
    /// 7, of which only the first chunk is written (values 0..32).
    fn write_array(dir: &Path) {
        std::fs::create_dir_all(dir.join("c/0/0")).unwrap();
        let meta = json!({
            "zarr_format": 3,
            "node_type": "array",
            "shape": [4, 4, 4],
            "data_type": "uint16",
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [2, 4, 4]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": 7,
            "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
            "dimension_names": ["z", "y", "x"],
        });
        std::fs::write(dir.join("zarr.json"), meta.to_string()).unwrap();
        let chunk: Vec<u8> = (0..32u16).flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(dir.join("c/0/0/0"), chunk).unwrap();
    }

    /// 64-bit integer arrays are read as 32-bit ones when every value
    /// fits: a Zarr v2 `<u8` (uint64, not uint8) and a v3 int64 with its
    /// axes in x, y, z order; a value that does not fit fails the read,
    /// naming it and its index.
    #[test]
    fn wide_integers_narrowed_when_they_fit() {
        let dir = tempfile::tempdir().unwrap();
        // v2, uint64, 3×4×5 in chunks of 2×4×5, values v·1000003 + 5.
        let v2 = dir.path().join("v2");
        std::fs::create_dir_all(&v2).unwrap();
        let meta = json!({
            "zarr_format": 2, "shape": [3, 4, 5], "chunks": [2, 4, 5], "dtype": "<u8",
            "compressor": null, "fill_value": 0, "order": "C", "filters": null,
        });
        std::fs::write(v2.join(".zarray"), meta.to_string()).unwrap();
        let val = |i: u64| i * 1_000_003 + 5;
        for c in 0..2u64 {
            let chunk: Vec<u8> = (0..40)
                .flat_map(|k| val(c * 40 + k).to_le_bytes())
                .collect();
            std::fs::write(v2.join(format!("{c}.0.0")), chunk).unwrap();
        }
        let src = open(&v2, 0).unwrap();
        assert_eq!((src.meta().dtype, src.meta().dims), (DType::U32, [3, 4, 5]));
        assert!(src.meta().notes.iter().any(|n| n.contains("uint64")));
        let got: Vec<u32> = read_all(&src, 0)
            .chunks_exact(4)
            .map(|b| u32::from_ne_bytes(b.try_into().unwrap()))
            .collect();
        let want: Vec<u32> = (0..60).map(|i| val(i) as u32).collect();
        assert_eq!(got, want);

        // v3, int64, axes x, y, z (shape 5, 4, 3): read transposed.
        let v3 = dir.path().join("v3");
        std::fs::create_dir_all(v3.join("c/0/0")).unwrap();
        let meta = json!({
            "zarr_format": 3, "node_type": "array", "shape": [5, 4, 3], "data_type": "int64",
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [5, 4, 3]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": 0,
            "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
            "dimension_names": ["x", "y", "z"],
        });
        std::fs::write(v3.join("zarr.json"), meta.to_string()).unwrap();
        let at = |x: i64, y: i64, z: i64| -(x * 100 + y * 10 + z) * 4_000_001;
        let chunk: Vec<u8> = (0..5)
            .flat_map(|x| (0..4).flat_map(move |y| (0..3).map(move |z| at(x, y, z))))
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(v3.join("c/0/0/0"), &chunk).unwrap();
        let src = open(&v3, 0).unwrap();
        assert_eq!((src.meta().dtype, src.meta().dims), (DType::I32, [3, 4, 5]));
        let got: Vec<i32> = read_all(&src, 0)
            .chunks_exact(4)
            .map(|b| i32::from_ne_bytes(b.try_into().unwrap()))
            .collect();
        let want: Vec<i32> = (0..3)
            .flat_map(|z| (0..4).flat_map(move |y| (0..5).map(move |x| at(x, y, z) as i32)))
            .collect();
        assert_eq!(got, want);

        // One value below i32::MIN: the read fails, naming it and where.
        let mut bad = chunk;
        let k = ((2 * 4 + 1) * 3 + 2) * 8; // x 2, y 1, z 2
        bad[k..k + 8].copy_from_slice(&(-(1i64 << 31) - 1).to_le_bytes());
        std::fs::write(v3.join("c/0/0/0"), &bad).unwrap();
        let src = open(&v3, 0).unwrap();
        let e = src
            .read_region(0, 0..3, 0..4, 0..5, &mut vec![0u8; 240])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("-2147483649") && e.contains("[2, 1, 2]") && e.contains("int32"),
            "{e}"
        );
    }

    /// Chunks that were never written read as the array's fill value.
    #[test]
    fn missing_chunks_read_as_fill_value() {
        let dir = tempfile::tempdir().unwrap();
        write_array(dir.path());
        let src = open(dir.path(), 0).unwrap();
        assert_eq!(src.meta().dims, [4, 4, 4]);
        let got: Vec<u16> = read_all(&src, 0)
            .chunks_exact(2)
            .map(|b| u16::from_ne_bytes([b[0], b[1]]))
            .collect();
        let want: Vec<u16> = (0..32).chain(std::iter::repeat_n(7, 32)).collect();
        assert_eq!(got, want);
    }

    /// The multiscale's own coordinateTransformations apply after each
    /// dataset's: world = gs · (s · i + t) + gt.
    #[test]
    fn multiscale_transformations_compose_with_the_datasets() {
        let dir = tempfile::tempdir().unwrap();
        write_array(&dir.path().join("0"));
        let axes: Vec<Value> = ["z", "y", "x"]
            .iter()
            .map(|n| json!({"name": n, "type": "space", "unit": "micrometer"}))
            .collect();
        let group = json!({
            "zarr_format": 3,
            "node_type": "group",
            "attributes": {"ome": {"version": "0.5", "multiscales": [{
                "axes": axes,
                "datasets": [{"path": "0", "coordinateTransformations": [
                    {"type": "scale", "scale": [2.0, 1.0, 1.0]},
                    {"type": "translation", "translation": [1.0, 0.0, 0.0]}
                ]}],
                "coordinateTransformations": [
                    {"type": "scale", "scale": [0.5, 0.25, 0.25]},
                    {"type": "translation", "translation": [10.0, 20.0, 30.0]}
                ]
            }]}}
        });
        std::fs::write(dir.path().join("zarr.json"), group.to_string()).unwrap();
        let src = open(dir.path(), 0).unwrap();
        assert_eq!(src.meta().spacing, Some([1.0, 0.25, 0.25]));
        assert_eq!(src.meta().origin, Some([10.5, 20.0, 30.0]));
        assert_eq!(src.meta().unit.as_deref(), Some("micrometer"));

        // Only a global scale: dataset translations are scaled too.
        let mut g = group.clone();
        g["attributes"]["ome"]["multiscales"][0]["coordinateTransformations"] =
            json!([{"type": "scale", "scale": [3.0, 1.0, 1.0]}]);
        std::fs::write(dir.path().join("zarr.json"), g.to_string()).unwrap();
        let src = open(dir.path(), 0).unwrap();
        assert_eq!(src.meta().spacing, Some([6.0, 1.0, 1.0]));
        assert_eq!(src.meta().origin, Some([3.0, 0.0, 0.0]));

        // A voxel size of 0, below 0 or not a number, a position not
        // finite: refused, naming the dataset (a scale of -0.2 was taken
        // as 1 by convert).
        for (what, t) in [
            ("scale", json!({"type": "scale", "scale": [1.0, 0.2, -0.2]})),
            ("scale", json!({"type": "scale", "scale": [0.0, 1.0, 1.0]})),
            ("scale", json!({"type": "scale", "scale": [1.0, "a", 1.0]})),
            (
                "translation",
                json!({"type": "translation", "translation": [1.0, null, 0.0]}),
            ),
        ] {
            let mut g = group.clone();
            g["attributes"]["ome"]["multiscales"][0]["datasets"][0]["coordinateTransformations"] =
                json!([{"type": "scale", "scale": [1.0, 1.0, 1.0]}, t]);
            if what == "scale" {
                g["attributes"]["ome"]["multiscales"][0]["datasets"][0]
                    ["coordinateTransformations"] = json!([t]);
            }
            std::fs::write(dir.path().join("zarr.json"), g.to_string()).unwrap();
            let Err(e) = open(dir.path(), 0) else {
                panic!("{t} was accepted");
            };
            let e = e.to_string();
            assert!(
                e.contains(&format!("datasets[0] (path \"0\") {what}")),
                "{e}"
            );
        }

        // A global transformation of the wrong length is an error.
        let mut g = group;
        g["attributes"]["ome"]["multiscales"][0]["coordinateTransformations"] =
            json!([{"type": "scale", "scale": [3.0, 1.0]}]);
        std::fs::write(dir.path().join("zarr.json"), g.to_string()).unwrap();
        let Err(e) = open(dir.path(), 0) else {
            panic!("a global scale of the wrong length was accepted");
        };
        let e = e.to_string();
        assert!(e.contains("multiscales.coordinateTransformations"), "{e}");
    }
}
