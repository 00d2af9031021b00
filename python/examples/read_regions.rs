//! The reads of `brickyard.Store.read` without Python: the same loader, host
//! cache and `read_region_into` the extension module uses (`src/read.rs`, compiled
//! in here), timed per region. `scripts/bench-python-read.py --native`
//! compares it with the same reads through the bindings (their overhead).
//!
//! Build (the flags maturin uses, so that the bindings' build is reused):
//!
//! ```text
//! PYO3_BUILD_EXTENSION_MODULE=1 PYO3_PYTHON=$PWD/.venv/bin/python \
//!   cargo build --release --manifest-path python/Cargo.toml \
//!   --features pyo3/extension-module --example read_regions
//! ```
//!
//! Usage: `read_regions STORE REGIONS CACHE_BYTES CHUNK_BYTES BRICK THREADS PASSES`,
//! REGIONS a file of lines `z0 y0 x0 z1 y1 x1` (level 0, channel 0). Prints
//! one line per read: pass, index, milliseconds, a checksum of the voxels.

#[path = "../src/read.rs"]
mod read;

use brickyard_cache::host_cache::HostCache;
use brickyard_cache::loader::Loader;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

/// `read.rs` reports Ctrl-C with this (never here: nothing interrupts).
#[derive(Debug)]
pub struct Interrupted;

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("interrupted")
    }
}

impl std::error::Error for Interrupted {}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    if a.len() != 8 {
        anyhow::bail!(
            "usage: read_regions STORE REGIONS CACHE_BYTES CHUNK_BYTES BRICK THREADS PASSES"
        );
    }
    let store = PathBuf::from(&a[1]);
    let text = std::fs::read_to_string(&a[2]).map_err(|e| anyhow::anyhow!("{}: {e}", a[2]))?;
    let regions: Vec<[u64; 6]> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<u64> = l
                .split_whitespace()
                .map(|x| x.parse())
                .collect::<Result<_, _>>()
                .map_err(|e| anyhow::anyhow!("{}: {l:?}: {e}", a[2]))?;
            v.try_into()
                .map_err(|_| anyhow::anyhow!("{}: {l:?}: expected 6 numbers", a[2]))
        })
        .collect::<anyhow::Result<_>>()?;
    let num = |i: usize| -> anyhow::Result<u64> {
        a[i].parse()
            .map_err(|e| anyhow::anyhow!("argument {i} ({:?}): {e}", a[i]))
    };
    let (cache, chunk, brick, threads, passes) = (num(3)?, num(4)?, num(5)?, num(6)?, num(7)?);
    let loader = Loader::open_with_chunk_cache(
        &store,
        [brick; 3],
        0,
        threads.max(1) as usize,
        Arc::new(HostCache::new(cache)),
        chunk,
    )?;
    for pass in 0..passes {
        for (i, r) in regions.iter().enumerate() {
            let t = Instant::now();
            // As the bindings do: check, allocate, read into it.
            let (lo, hi) = ([r[0], r[1], r[2]], [r[3], r[4], r[5]]);
            let mut out = vec![0u8; read::region_len(&loader, 0, 0, lo, hi)?];
            read::read_region_into(&loader, 0, 0, lo, hi, &|| false, &mut out)?;
            let ms = t.elapsed().as_secs_f64() * 1e3;
            let sum: u64 = out.iter().map(|&b| b as u64).sum();
            println!("{pass} {i} {ms:.6} {sum}");
        }
    }
    Ok(())
}
