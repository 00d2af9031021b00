//! `brickyard process STORE PIPELINE --out NAME`: run a pipeline over a
//! level of a store and write the result back into the store, at every
//! level, as a new multiscale image.
//!
//! Where results go: label and mask results (pipelines ending in `label`,
//! `threshold` or `window`) under `STORE/labels/NAME`, as the OME-Zarr 0.5
//! labels spec says (`labels/zarr.json` lists them; the image carries
//! `image-label` metadata); other results under `STORE/derived/NAME`.
//!
//! Crash safety: the result is written aside (`.NAME.new.partial`, then
//! `.NAME.new`), published by renaming it to `NAME`, and only then listed in
//! `labels/zarr.json` (written to a temporary file and renamed). Nothing
//! that exists is modified before the result is complete; a killed job
//! leaves only hidden `.NAME.*` directories, which the next run removes.
//!
//! `--backend gpu` computes the filter stages with the WGSL kernels of
//! `brickyard_process::gpu` (f32; float results within the tolerance stated
//! there, masks equal for equal values); labelling stays on the CPU.
//!
//! The job itself is `brickyard_run::process` (the Python bindings run it
//! too); this file holds the options, the progress bars and the report.

use crate::{install_ctrl_c, parse_bytes, peak_rss, progress, CANCEL};
use anyhow::{Context, Result};
use brickyard_run::process::{Caller, Phases, ProcessArgs};
use brickyard_store::info::human_bytes;
use brickyard_store::Progress;
use clap::Args;
use serde_json::json;
use std::path::PathBuf;

#[derive(Args)]
pub struct ProcessCmd {
    /// The OME-Zarr image to process (a store written by `convert`).
    pub store: PathBuf,
    /// The pipeline, e.g. "gauss(1.5)|threshold(3000)|label(26)". Stages:
    /// gauss(σ), gradmag(σ), sobel, median(r) (radius 0 to 7 voxels, on
    /// the CPU), threshold(t) (1 where the value is above t, in the
    /// image's own values: see `brickyard info`), window(lo,hi),
    /// label(6|26); σ in voxels, or with a unit (1.5um); three values are
    /// x,y,z. Gradients (gradmag, sobel) are per voxel, not per unit of
    /// the spacing.
    pub pipeline: String,
    /// Name of the result: STORE/labels/NAME for labels and masks,
    /// STORE/derived/NAME otherwise.
    #[arg(long)]
    pub out: String,
    /// Memory budget (e.g. 1GiB, 512MiB).
    #[arg(long, default_value = "1GiB")]
    pub memory: String,
    /// Level of the store to process (0 = full resolution).
    #[arg(long, default_value_t = 0)]
    pub level: usize,
    /// Channel of the store to process.
    #[arg(long, default_value_t = 0)]
    pub channel: usize,
    /// Labelling: also write the per-label statistics to FILE (.csv or
    /// .json). They are always stored in the label image as
    /// `_brickyard/labels.csv` and `_brickyard/labels.json`.
    #[arg(long)]
    pub stats: Option<PathBuf>,
    /// Replace an existing result of the same name.
    #[arg(long)]
    pub overwrite: bool,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Who computes the filter stages: cpu (f64), gpu (f32 WGSL kernels on
    /// the device; results within the tolerance `brickyard_process::gpu`
    /// states, masks equal) or auto (a hardware GPU when there is one, else
    /// the CPU). Labelling runs on the CPU.
    #[arg(long, default_value = "cpu")]
    pub backend: String,
}

/// How the command line names things in messages.
const CLI: Caller = Caller {
    flag: "--",
    convert: "`brickyard convert`",
    remote: "view the result live with `render --derive` / `view --derive`, or copy the \
             store first (`brickyard convert URL local.zarr`)",
    overwrite: "pass --overwrite",
    again: "command",
};

/// A bar per phase, cleared when the phase ends.
struct Bars {
    labelling: progress::Bar,
    writing: progress::Bar,
}

impl Phases for Bars {
    fn labelling(&self) -> &dyn Progress {
        &self.labelling
    }
    fn writing(&self) -> &dyn Progress {
        &self.writing
    }
    fn done(&self, labelling: bool) {
        if labelling {
            self.labelling.finish()
        } else {
            self.writing.finish()
        }
    }
}

pub fn run(c: ProcessCmd) -> Result<()> {
    let quiet = c.quiet || c.json;
    let job = ProcessArgs {
        store: c.store,
        pipeline: c.pipeline,
        out: c.out,
        memory: parse_bytes(&c.memory).context("--memory")?,
        level: c.level,
        channel: c.channel,
        stats: c.stats,
        overwrite: c.overwrite,
        backend: c.backend,
        quiet,
    };
    install_ctrl_c();
    let bars = Bars {
        labelling: progress::Bar::counting(quiet, "labelling (pass 1, voxels)"),
        writing: progress::Bar::new(quiet, "writing"),
    };
    let r = brickyard_run::process::run(&job, &CLI, &bars, &CANCEL)?;
    let rss = peak_rss();
    if c.json {
        outln!(
            "{}",
            json!({
                "output": r.output,
                "pipeline": r.pipeline,
                "labels": r.labels,
                "levels": r.levels,
                "dtype": r.dtype.short_name(),
                "seconds": r.seconds,
                "bytes_written": r.bytes_written,
                "peak_rss_bytes": rss,
                "device": r.device,
                "notes": r.notes,
            })
        );
    } else {
        outln!("{}, peak RSS {}", r.headline(), human_bytes(rss));
        for n in &r.notes {
            eprintln!("note: {n}");
        }
    }
    Ok(())
}
