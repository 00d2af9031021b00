//! Streaming writer of `sharding_indexed` shard files.
//!
//! A shard file is the concatenation of its encoded inner chunks (bricks) in
//! any order, followed by the index: for each inner chunk in C order a pair
//! of little-endian u64 `(offset, nbytes)` (`(u64::MAX, u64::MAX)` for an
//! absent chunk, read as the fill value), then the CRC32C of the index.
//! Bricks are appended as soon as they are encoded and the index is written
//! when the last brick of the shard has been seen, so a shard never has to be
//! held in memory.
//!
//! Reading side: [`check_index`] and [`read_index`] decode a shard's index
//! and check every entry against the length of the shard file, so that a
//! damaged or hostile index is a clear error before any reader sizes a
//! buffer from it.

use crate::error::{IoContext, Result, StoreError};
use serde_json::Value;
use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// Most inner chunks one shard may hold (16 bytes of index each): a larger
/// count in an array's metadata is refused before any index is read.
pub const MAX_INDEX_ENTRIES: u64 = 1 << 24;

/// Where a shard's index lies in the shard file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IndexLocation {
    Start,
    End,
}

/// How a shard index is laid out: the `sharding_indexed` codec's
/// `index_location` and `index_codecs` (`bytes`, optionally `crc32c`), and
/// the number of inner chunks of a shard.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IndexLayout {
    /// Inner chunks per shard (entries of the index).
    pub entries: u64,
    pub location: IndexLocation,
    pub big_endian: bool,
    /// Whether a CRC32C of the entries follows them.
    pub crc32c: bool,
}

impl IndexLayout {
    /// The layout brickyard writes: index at the end, little-endian, CRC32C.
    pub fn brickyard(entries: u64) -> IndexLayout {
        IndexLayout {
            entries,
            location: IndexLocation::End,
            big_endian: false,
            crc32c: true,
        }
    }

    /// Bytes of the encoded index (at most [`MAX_INDEX_ENTRIES`] entries).
    pub fn index_bytes(&self) -> u64 {
        self.entries.min(MAX_INDEX_ENTRIES) * 16 + if self.crc32c { 4 } else { 0 }
    }

    /// The layout of a `sharding_indexed` codec's `configuration` for shards
    /// of `shard_shape`, in `path`'s metadata. `Ok(None)` when the index uses
    /// codecs this reader does not check (the Zarr library still reads it).
    /// Errors name the offending key: inner chunk sizes of 0, a shard shape
    /// that is not a multiple of the inner chunk, or more than
    /// [`MAX_INDEX_ENTRIES`] inner chunks per shard.
    pub fn from_codec(
        path: &Path,
        config: &Value,
        shard_shape: &[u64],
    ) -> Result<Option<IndexLayout>> {
        let inv = |field: &str, msg: String| StoreError::invalid(path, field, msg);
        let inner: Vec<u64> = config
            .get("chunk_shape")
            .and_then(Value::as_array)
            .and_then(|a| a.iter().map(Value::as_u64).collect::<Option<Vec<u64>>>())
            .ok_or_else(|| {
                inv(
                    "sharding_indexed.chunk_shape",
                    format!(
                        "expected a list of {} positive integers, found {}",
                        shard_shape.len(),
                        short_json(config.get("chunk_shape"))
                    ),
                )
            })?;
        if inner.len() != shard_shape.len() || inner.contains(&0) {
            return Err(inv(
                "sharding_indexed.chunk_shape",
                format!(
                    "expected {} positive integers (one per axis of the shard {shard_shape:?}), \
                     found {inner:?}",
                    shard_shape.len()
                ),
            ));
        }
        let mut entries = 1u64;
        for (&s, &i) in shard_shape.iter().zip(&inner) {
            if s % i != 0 {
                return Err(inv(
                    "sharding_indexed.chunk_shape",
                    format!(
                        "the shard {shard_shape:?} is not a multiple of the inner chunk {inner:?}"
                    ),
                ));
            }
            entries = entries.saturating_mul(s / i);
        }
        if entries > MAX_INDEX_ENTRIES {
            return Err(inv(
                "sharding_indexed.chunk_shape",
                format!(
                    "shards of {shard_shape:?} in inner chunks of {inner:?} hold {entries} inner \
                     chunks; at most {MAX_INDEX_ENTRIES} are supported"
                ),
            ));
        }
        let location = match config.get("index_location").and_then(Value::as_str) {
            None | Some("end") => IndexLocation::End,
            Some("start") => IndexLocation::Start,
            Some(other) => {
                return Err(inv(
                    "sharding_indexed.index_location",
                    format!("expected \"start\" or \"end\", found {other:?}"),
                ))
            }
        };
        let codecs = config.get("index_codecs").and_then(Value::as_array);
        let names: Vec<&str> = codecs
            .map(|c| {
                c.iter()
                    .map(|c| c.get("name").and_then(Value::as_str).unwrap_or("?"))
                    .collect()
            })
            .unwrap_or_default();
        let (big_endian, crc32c) = match names.as_slice() {
            ["bytes"] | ["bytes", "crc32c"] => {
                let endian = codecs.unwrap()[0]
                    .get("configuration")
                    .and_then(|c| c.get("endian"))
                    .and_then(Value::as_str);
                (endian == Some("big"), names.len() == 2)
            }
            _ => return Ok(None),
        };
        Ok(Some(IndexLayout {
            entries,
            location,
            big_endian,
            crc32c,
        }))
    }
}

fn short_json(v: Option<&Value>) -> String {
    let s = v.map_or("nothing".to_string(), Value::to_string);
    if s.chars().count() > 80 {
        format!("{}...", s.chars().take(80).collect::<String>())
    } else {
        s
    }
}

/// Decode the encoded `index` of a shard file of `shard_len` bytes and check
/// it: the CRC32C (when the layout has one), and that every present inner
/// chunk lies inside the shard's data (not in the index, not past the end).
/// Returns `(offset, nbytes)` per inner chunk, `(u64::MAX, u64::MAX)` for an
/// absent one. Errors name the shard file and the entry.
pub fn check_index(
    path: &Path,
    index: &[u8],
    shard_len: u64,
    layout: &IndexLayout,
) -> Result<Vec<[u64; 2]>> {
    let inv = |msg: String| StoreError::invalid(path, "shard index", msg);
    if layout.entries > MAX_INDEX_ENTRIES {
        return Err(inv(format!(
            "{} inner chunks per shard; at most {MAX_INDEX_ENTRIES} are supported",
            layout.entries
        )));
    }
    let ib = layout.index_bytes();
    if shard_len < ib {
        return Err(inv(format!(
            "the shard file holds {shard_len} bytes, fewer than its index of {} entries \
             needs ({ib} bytes; truncated file?)",
            layout.entries
        )));
    }
    if index.len() as u64 != ib {
        return Err(inv(format!(
            "expected {ib} index bytes, found {}",
            index.len()
        )));
    }
    let body = &index[..layout.entries as usize * 16];
    if layout.crc32c {
        let stored = u32::from_le_bytes(index[body.len()..].try_into().unwrap());
        let crc = crc32c::crc32c(body);
        if stored != crc {
            return Err(inv(format!(
                "CRC32C {crc:#010x} of the index does not match the stored {stored:#010x} \
                 (damaged shard?)"
            )));
        }
    }
    let data = match layout.location {
        IndexLocation::End => 0..shard_len - ib,
        IndexLocation::Start => ib..shard_len,
    };
    let word = |b: &[u8]| {
        let a: [u8; 8] = b.try_into().unwrap();
        if layout.big_endian {
            u64::from_be_bytes(a)
        } else {
            u64::from_le_bytes(a)
        }
    };
    let mut out = Vec::with_capacity(layout.entries as usize);
    for (k, e) in body.chunks_exact(16).enumerate() {
        let (off, n) = (word(&e[..8]), word(&e[8..]));
        if off == u64::MAX && n == u64::MAX {
            out.push([off, n]);
            continue;
        }
        match off.checked_add(n) {
            Some(end) if off >= data.start && end <= data.end => out.push([off, n]),
            end => {
                return Err(inv(format!(
                    "entry {k} (offset {off}, {n} bytes) ends at byte {} but the inner chunks \
                     must lie in bytes {}..{} of the {shard_len}-byte shard file",
                    end.map_or_else(|| "2^64+".to_string(), |e| e.to_string()),
                    data.start,
                    data.end
                )))
            }
        }
    }
    Ok(out)
}

/// Check the index of a shard held in memory (the whole shard file).
pub fn parse_index(path: &Path, shard: &[u8], layout: &IndexLayout) -> Result<Vec<[u64; 2]>> {
    let len = shard.len() as u64;
    let ib = layout.index_bytes().min(len) as usize;
    let index = match layout.location {
        IndexLocation::End => &shard[shard.len() - ib..],
        IndexLocation::Start => &shard[..ib],
    };
    check_index(path, index, len, layout)
}

/// Read and check the index of the shard file at `path` (see
/// [`check_index`]); `Ok(None)` when there is no such file (a shard that
/// holds only the fill value).
///
/// The read goes through [`crate::storage`] (a file or a URL); remote
/// indexes at the end of their shard are read as a suffix, which the
/// HTTP client caches with the shard's length (no HEAD request).
pub fn read_index(path: &Path, layout: &IndexLayout) -> Result<Option<Vec<[u64; 2]>>> {
    use crate::storage;
    let ib = layout.index_bytes();
    // The index (when there is one to read) and the shard's length.
    let (index, len) = match layout.location {
        _ if layout.entries > MAX_INDEX_ENTRIES => match storage::size(path)? {
            Some(len) => (vec![], len),
            None => return Ok(None),
        },
        // One read gives both (a suffix read also tells the value's length).
        IndexLocation::End => match storage::read_suffix(path, ib)? {
            Some(x) => x,
            None => return Ok(None),
        },
        IndexLocation::Start => {
            let Some(len) = storage::size(path)? else {
                return Ok(None);
            };
            if len < ib {
                (vec![], len)
            } else {
                match storage::read_spans(path, &[storage::Span::Range(0..ib)])? {
                    Some(mut parts) => (parts.swap_remove(0), len),
                    None => return Ok(None),
                }
            }
        }
    };
    let index = if len < ib { &[][..] } else { &index[..] };
    check_index(path, index, len, layout).map(Some)
}

struct OpenShard {
    path: PathBuf,
    file: Option<File>,
    offset: u64,
    index: Vec<[u64; 2]>,
    seen: u64,
    expected: u64,
}

impl OpenShard {
    fn finish(&mut self) -> Result<()> {
        if self.file.is_none() {
            // Every brick was empty: no file at all, readers use the fill value.
            return Ok(());
        }
        let mut buf = Vec::with_capacity(self.index.len() * 16 + 4);
        for e in &self.index {
            buf.extend_from_slice(&e[0].to_le_bytes());
            buf.extend_from_slice(&e[1].to_le_bytes());
        }
        let crc = crc32c::crc32c(&buf);
        buf.extend_from_slice(&crc.to_le_bytes());
        let f = self.file.as_mut().unwrap();
        f.write_all(&buf).at(&self.path)?;
        self.file = None;
        Ok(())
    }
}

/// Writes the shards of one array. Thread-safe: bricks of different shards
/// are written in parallel.
pub struct ShardSetWriter {
    dir: PathBuf,
    /// Inner chunks per shard along each axis of the array.
    per_shard: Vec<u64>,
    shards: Mutex<HashMap<Vec<u64>, Arc<Mutex<OpenShard>>>>,
    /// Bytes written so far.
    pub bytes: std::sync::atomic::AtomicU64,
}

impl ShardSetWriter {
    /// `dir` is the array's directory; chunk keys are `c/i/j/k` below it.
    pub fn new(dir: &Path, per_shard: Vec<u64>) -> ShardSetWriter {
        ShardSetWriter {
            dir: dir.to_path_buf(),
            per_shard,
            shards: Mutex::new(HashMap::new()),
            bytes: Default::default(),
        }
    }

    fn shard_of(&self, brick: &[u64]) -> (Vec<u64>, usize) {
        let key: Vec<u64> = brick
            .iter()
            .zip(&self.per_shard)
            .map(|(b, p)| b / p)
            .collect();
        let mut idx = 0u64;
        for (b, p) in brick.iter().zip(&self.per_shard) {
            idx = idx * p + b % p;
        }
        (key, idx as usize)
    }

    /// Record one brick. `data` is `None` for a brick that is all fill value.
    /// `expected` is the number of bricks of this shard that exist in the
    /// array (edge shards hold fewer); when all have been recorded the shard
    /// is finished.
    pub fn put(&self, brick: &[u64], data: Option<&[u8]>, expected: u64) -> Result<()> {
        let (key, idx) = self.shard_of(brick);
        let shard = {
            let mut map = self.shards.lock().unwrap();
            map.entry(key.clone())
                .or_insert_with(|| {
                    let mut path = self.dir.join("c");
                    for k in &key {
                        path.push(k.to_string());
                    }
                    let n: u64 = self.per_shard.iter().product();
                    Arc::new(Mutex::new(OpenShard {
                        path,
                        file: None,
                        offset: 0,
                        index: vec![[u64::MAX; 2]; n as usize],
                        seen: 0,
                        expected,
                    }))
                })
                .clone()
        };
        let mut s = shard.lock().unwrap();
        if let Some(d) = data {
            if s.file.is_none() {
                std::fs::create_dir_all(s.path.parent().unwrap()).at(&s.path)?;
                let f = OpenOptions::new()
                    .create(true)
                    .write(true)
                    .truncate(true)
                    .open(&s.path)
                    .at(&s.path)?;
                s.file = Some(f);
            }
            let path = s.path.clone();
            s.file.as_mut().unwrap().write_all(d).at(&path)?;
            s.index[idx] = [s.offset, d.len() as u64];
            s.offset += d.len() as u64;
            self.bytes
                .fetch_add(d.len() as u64, std::sync::atomic::Ordering::Relaxed);
        }
        s.seen += 1;
        if s.seen == s.expected {
            s.finish()?;
            drop(s);
            self.shards.lock().unwrap().remove(&key);
        }
        Ok(())
    }

    /// Finish all shards still open (there are none when every brick was put).
    pub fn finish(&self) -> Result<()> {
        let map = std::mem::take(&mut *self.shards.lock().unwrap());
        for (_, s) in map {
            s.lock().unwrap().finish()?;
        }
        Ok(())
    }
}
