//! `bench remote`: brick reads of one store from disk and over HTTP on
//! loopback (a `brickyard serve` child process), through the same loader:
//! bricks per second and bytes read per second, for 1, 2 and 4 loader
//! threads.

use anyhow::{Context, Result};
use brickyard_cache::brick::BrickKey;
use brickyard_cache::host_cache::HostCache;
use brickyard_cache::loader::Loader;
use brickyard_core::{DType, Dims3};
use serde_json::json;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Instant;

pub fn remote(dir: &Path, dims: Dims3, dtype: DType) -> Result<()> {
    let st = crate::vmbench::store(dir, dims, dtype)?;
    let mut child = Command::new(std::env::current_exe()?)
        .arg("serve")
        .arg(&st)
        .args(["--port", "0", "--quiet"])
        .stderr(Stdio::piped())
        .spawn()
        .context("starting `brickyard serve`")?;
    let mut first = String::new();
    BufReader::new(child.stderr.take().context("no stderr")?).read_line(&mut first)?;
    let port = first
        .split("127.0.0.1:")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .and_then(|p| p.parse::<u16>().ok())
        .with_context(|| format!("serve said {first:?}"))?;
    let name = st
        .file_name()
        .and_then(|n| n.to_str())
        .context("store name")?;
    let url = PathBuf::from(format!("http://127.0.0.1:{port}/{name}"));
    let res = (|| -> Result<()> {
        for (source, path) in [("local", &st), ("http", &url)] {
            for threads in [1usize, 2, 4] {
                let l = Loader::open(
                    path,
                    [64; 3],
                    1,
                    threads,
                    Arc::new(HostCache::new(64 << 20)),
                )?;
                let keys: Vec<(BrickKey, u32)> = l.geometry().keys(0, 0).map(|k| (k, 1)).collect();
                let t = Instant::now();
                l.request(&keys);
                let (got, data) =
                    crate::vmbench::await_bricks(&l, keys.len()).with_context(|| source)?;
                let s = t.elapsed().as_secs_f64();
                outln!(
                    "{}",
                    json!({"scenario": "remote", "source": source, "size": [dims[2], dims[1], dims[0]],
                        "dtype": dtype.short_name(), "threads": threads, "bricks": keys.len(),
                        "data_bricks": data, "loaded": got, "seconds": s,
                        "bricks_per_s": got as f64 / s, "read_mb_s": l.bytes_read() as f64 / 1e6 / s})
                );
            }
        }
        Ok(())
    })();
    let _ = child.kill();
    let _ = child.wait();
    res
}
