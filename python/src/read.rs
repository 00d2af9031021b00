//! Any box of a store read through the loader and its host cache: the
//! engine bricks that cover the box are asked for in batches no larger than
//! half the host cache, and each is copied into the output as it arrives,
//! so memory stays at the output plus the cache, whatever the store's size.

use crate::Interrupted;
use anyhow::{bail, Result};
use brickyard_cache::brick::{value_bytes, BrickContent, BrickKey};
use brickyard_cache::loader::Loader;
use std::collections::HashSet;
use std::time::Duration;

/// The bytes of the box `lo..hi` of `level` and `channel`, after checking
/// that the box is inside the level and the level and channel exist.
pub fn region_len(
    loader: &Loader,
    level: usize,
    channel: usize,
    lo: [u64; 3],
    hi: [u64; 3],
) -> Result<usize> {
    let g = loader.geometry();
    if level >= g.levels.len() {
        bail!(
            "level: {level} asked for but the store has {} level(s)",
            g.levels.len()
        );
    }
    if channel >= g.channels {
        bail!(
            "channel: {channel} asked for but the store has {} channel(s)",
            g.channels
        );
    }
    let dims = g.levels[level];
    for a in 0..3 {
        if lo[a] >= hi[a] || hi[a] > dims[a] {
            bail!(
                "region: {lo:?}..{hi:?} is empty or outside level {level} of shape {dims:?} ([z, y, x])"
            );
        }
    }
    Ok((0..3).map(|a| hi[a] - lo[a]).product::<u64>() as usize * g.dtype.size())
}

/// The box `lo..hi` (`[z, y, x]`, half open) of `level` and `channel`
/// into `out` (of [`region_len`] bytes) as a dense C-order buffer; the
/// caller chooses where the voxels go (the bindings: straight into the
/// Python bytearray they return). `interrupted` is asked between batches.
pub fn read_region_into(
    loader: &Loader,
    level: usize,
    channel: usize,
    lo: [u64; 3],
    hi: [u64; 3],
    interrupted: &dyn Fn() -> bool,
    out: &mut [u8],
) -> Result<()> {
    let n = region_len(loader, level, channel, lo, hi)?;
    if out.len() != n {
        bail!(
            "region: {lo:?}..{hi:?} needs {n} bytes, the buffer has {}",
            out.len()
        );
    }
    let g = loader.geometry().clone();
    let es = g.dtype.size();
    let b = g.brick;
    let first = [0, 1, 2].map(|a| lo[a] / b[a]);
    let last = [0, 1, 2].map(|a| (hi[a] - 1) / b[a]);
    let mut keys = vec![];
    for z in first[0]..=last[0] {
        for y in first[1]..=last[1] {
            for x in first[2]..=last[2] {
                keys.push(BrickKey::new(
                    level as u8,
                    channel as u16,
                    [z as u32, y as u32, x as u32],
                ));
            }
        }
    }
    // Bricks handed out but not yet copied are held once each: a batch
    // takes at most half the host cache (at least one brick).
    let batch = (loader.cache().budget() / 2 / g.bytes_per_brick().max(1)).max(1) as usize;
    loader.retry_failed();
    let result = (|| -> Result<()> {
        for chunk in keys.chunks(batch) {
            if interrupted() {
                return Err(Interrupted.into());
            }
            let mut want: HashSet<BrickKey> = chunk.iter().copied().collect();
            let req: Vec<(BrickKey, u32)> = chunk.iter().map(|k| (*k, 1)).collect();
            loader.request(&req);
            let mut idle_rounds = 0;
            while !want.is_empty() {
                let got = loader.poll();
                let progressed = !got.is_empty();
                for brick in got {
                    if want.remove(&brick.key) {
                        copy_brick(&g, &brick.key, &brick.content, lo, hi, es, out);
                    }
                }
                if let Some(f) = loader
                    .take_failures()
                    .into_iter()
                    .find(|f| want.contains(&f.key))
                {
                    // The store could not be read: an OSError in Python,
                    // as at `open`; what it holds is wrong: a ValueError.
                    if f.io {
                        return Err(std::io::Error::other(f.message).into());
                    }
                    bail!("{}", f.message);
                }
                if want.is_empty() {
                    break;
                }
                let idle = loader.wait_idle(Duration::from_millis(20));
                if idle && !progressed {
                    idle_rounds += 1;
                    if idle_rounds > 100 {
                        bail!(
                            "{} brick(s) of level {level} never arrived from the loader",
                            want.len()
                        );
                    }
                    if idle_rounds % 10 == 0 {
                        // Asked again in case a request was dropped.
                        let again: Vec<(BrickKey, u32)> = want.iter().map(|k| (*k, 1)).collect();
                        loader.request(&again);
                    }
                } else {
                    idle_rounds = 0;
                }
                if interrupted() {
                    return Err(Interrupted.into());
                }
            }
        }
        Ok(())
    })();
    if result.is_err() {
        loader.cancel_except(&[]);
        loader.poll();
    }
    result
}

/// Copy the part of one brick (no apron) that lies in `lo..hi`.
fn copy_brick(
    g: &brickyard_cache::brick::BrickGeometry,
    key: &BrickKey,
    content: &BrickContent,
    lo: [u64; 3],
    hi: [u64; 3],
    es: usize,
    out: &mut [u8],
) {
    let o = g.origin_of(key);
    let pad = g.padded();
    let shape = [0, 1, 2].map(|a| hi[a] - lo[a]);
    let s = [0, 1, 2].map(|a| o[a].max(lo[a]));
    let e = [0, 1, 2].map(|a| (o[a] + g.brick[a]).min(hi[a]));
    let run = (e[2] - s[2]) as usize * es;
    let uniform = match content {
        BrickContent::Data(_) => None,
        _ => Some(value_bytes(g.dtype, content.uniform_value().unwrap_or(0.0)).repeat(run / es)),
    };
    for z in s[0]..e[0] {
        for y in s[1]..e[1] {
            let dst =
                (((z - lo[0]) * shape[1] + (y - lo[1])) * shape[2] + (s[2] - lo[2])) as usize * es;
            match (&uniform, content) {
                (Some(v), _) => out[dst..dst + run].copy_from_slice(v),
                (None, BrickContent::Data(d)) => {
                    let src = ((((z - o[0]) * pad[1]) + (y - o[1])) * pad[2] + (s[2] - o[2]))
                        as usize
                        * es;
                    out[dst..dst + run].copy_from_slice(&d[src..src + run]);
                }
                (None, _) => unreachable!(),
            }
        }
    }
}
