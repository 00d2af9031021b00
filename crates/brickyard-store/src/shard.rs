//! Streaming writer of `sharding_indexed` shard files.
//!
//! A shard file is the concatenation of its encoded inner chunks (bricks) in
//! any order, followed by the index: for each inner chunk in C order a pair
//! of little-endian u64 `(offset, nbytes)` (`(u64::MAX, u64::MAX)` for an
//! absent chunk, read as the fill value), then the CRC32C of the index.
//! Bricks are appended as soon as they are encoded and the index is written
//! when the last brick of the shard has been seen, so a shard never has to be
//! held in memory.

use crate::error::{IoContext, Result};
use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

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
