//! `brickyard vm footprint`: the management memory of a virtual-memory
//! configuration, line by line, beside the paper's accounting of the same
//! configuration (thesis Tables 6.2–6.4, paper Table 2).

use anyhow::{bail, Context, Result};
use brickyard_core::vm::{Footprint, VirtualLayout};
use brickyard_core::{plan_levels, DType, Dims3};
use brickyard_store::generate::parse_size;
use brickyard_store::import::zarr;
use brickyard_store::info::human_bytes;
use brickyard_store::VolumeSource;
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub struct FootprintCmd {
    /// A store (its levels are used); or give --dims.
    store: Option<PathBuf>,
    /// Volume size XxYxZ (levels halve every axis down to one brick).
    #[arg(long)]
    dims: Option<String>,
    /// Voxel type (for --dims): u8, u16, u32 (RGBA), f32 ...
    #[arg(long, default_value = "u8")]
    dtype: String,
    /// Brick edge in voxels, without the apron.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(2..=1024))]
    brick: u64,
    /// Voxels each brick repeats of its neighbours on every side.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(0..=64))]
    apron: u64,
    /// Page-table block edge.
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u64).range(2..=1024))]
    pt_block: u64,
    /// Intermediate page-table levels (default: automatic from --max-dir).
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=16))]
    pt_levels: Option<u64>,
    /// Largest directory (entries) before a page-table level is added.
    #[arg(long, default_value_t = 32768, value_parser = clap::value_parser!(u64).range(1..))]
    max_dir: u64,
    /// Brick pool size (e.g. 3GB, 4GiB).
    #[arg(long, default_value = "4GB")]
    pool: String,
    /// Blocks per page-table cache.
    #[arg(long, default_value_t = 500)]
    pt_cache_blocks: u64,
    /// Requests the capped request list holds a frame.
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    request_cap: u64,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
}

pub fn footprint(c: FootprintCmd) -> Result<()> {
    let (levels, dtype): (Vec<Dims3>, DType) = match (&c.store, &c.dims) {
        (Some(p), None) => {
            let mut v = vec![];
            let mut dt = DType::U8;
            for l in 0.. {
                match zarr::open(p, l) {
                    Ok(s) => {
                        v.push(s.meta().dims);
                        dt = s.meta().dtype;
                    }
                    Err(e) if l == 0 => return Err(e.into()),
                    Err(_) => break,
                }
            }
            (v, dt)
        }
        (None, Some(d)) => {
            let dims = parse_size(d).map_err(|e| anyhow::anyhow!("dims: {e}"))?;
            let dt =
                DType::parse(&c.dtype).with_context(|| format!("dtype: unknown {:?}", c.dtype))?;
            // Sums over the bricks stay within 64 bits below 2^60 bytes.
            let bytes = dims
                .iter()
                .try_fold(dt.size() as u64, |a, &n| a.checked_mul(n));
            if bytes.is_none_or(|b| b > 1 << 60) {
                bail!(
                    "dims: {}x{}x{} voxels of {} are more than 1 EiB; expected a volume of at most 2^60 bytes",
                    dims[0],
                    dims[1],
                    dims[2],
                    c.dtype
                );
            }
            let plan = plan_levels(dims, [1.0; 3], [0.0; 3], [c.brick; 3]);
            (plan.levels.iter().map(|l| l.dims).collect(), dt)
        }
        _ => bail!("give either a store or --dims"),
    };
    let brick = [c.brick; 3];
    let layout = match c.pt_levels {
        Some(n) => VirtualLayout::new(levels.clone(), brick, vec![[c.pt_block; 3]; n as usize]),
        None => VirtualLayout::auto(levels.clone(), brick, [c.pt_block; 3], c.max_dir),
    };
    let pool = crate::parse_bytes(&c.pool)?;
    if c.apron > c.brick {
        bail!(
            "apron: {} voxels on each side of a brick of {}: expected at most the brick's edge",
            c.apron,
            c.brick
        );
    }
    let padded = (c.brick + 2 * c.apron).pow(3) * dtype.size() as u64;
    let slots = pool / padded;
    if slots == 0 {
        bail!(
            "pool: {} holds no brick of {} (padded, {} voxels a side); expected at least one",
            human_bytes(pool),
            human_bytes(padded),
            c.brick + 2 * c.apron
        );
    }
    let pt_caches = vec![c.pt_cache_blocks; layout.pt_levels()];
    let ours = Footprint::of(&layout, slots, &pt_caches, padded, c.request_cap);
    let paper = Footprint::paper_equivalent(
        &layout,
        pool,
        c.brick.pow(3) * dtype.size() as u64,
        &pt_caches,
    );
    if c.json {
        outln!(
            "{}",
            serde_json::json!({"levels": levels.len(), "pt_levels": layout.pt_levels(), "dir_entries": layout.dir_entries(),
                "bricks": layout.brick_count(), "pool_slots": slots, "ours": ours, "paper": paper})
        );
        return Ok(());
    }
    outln!(
        "{} levels, {} bricks of {}³ ({} with apron {}), {} page-table level(s) of {}³ blocks, directory {} entries ({:?})",
        levels.len(),
        layout.brick_count(),
        c.brick,
        human_bytes(padded),
        c.apron,
        layout.pt_levels(),
        c.pt_block,
        layout.dir_entries(),
        layout.dir_dims
    );
    outln!("pool {} = {} slots\n", human_bytes(pool), slots);
    outln!("{:<40} {:>14}", "brickyard", "bytes");
    for (k, v) in &ours.lines {
        outln!("{k:<40} {:>14}  {}", v, human_bytes(*v));
    }
    let mgmt = ours.total() - ours.get("pool").unwrap_or(0) - ours.sum_prefix("pt cache");
    outln!(
        "{:<40} {:>14}  {}\n",
        "management (no pool, no PT data)",
        mgmt,
        human_bytes(mgmt)
    );
    outln!(
        "{:<40} {:>14}",
        "paper's accounting (thesis Tables 6.2-6.4)",
        "bytes"
    );
    for (k, v) in &paper.lines {
        outln!("{k:<40} {:>14}  {}", v, human_bytes(*v));
    }
    outln!(
        "{:<40} {:>14}  {}",
        "total",
        paper.total(),
        human_bytes(paper.total())
    );
    Ok(())
}
