//! The `brickyard` command line.

#[macro_use]
extern crate brickyard_run;
mod bench;
mod dist;
mod gpubench;
mod netbench;
mod octbench;
mod process;
mod progress;
mod remote;
mod serve;
mod view;
mod viewbench;
mod vmbench;
mod vmcmd;
// The render run (backend, frame loop, memory split, windows, derived
// channels) lives in brickyard-run, shared with the Python bindings.
pub use brickyard_run::{backend, derive, frames, memory, render, window};

use anyhow::{bail, Context, Result};
use brickyard_core::{DType, Dims3};
use brickyard_store::builder::partial_path;
use brickyard_store::generate::{parse_size, Kind, Procedural};
use brickyard_store::import::raw::RawOptions;
use brickyard_store::import::stack::ChannelStack;
use brickyard_store::import::{open_input, Format, ImportOptions};
use brickyard_store::info::{format_info, human_bytes, inspect};
use brickyard_store::{convert, Compression, ConvertOptions, VolumeSource};
use clap::{Args, Parser, Subcommand};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// brickyard: interactive visualization and on-demand processing of volumes
/// larger than memory.
#[derive(Parser)]
#[command(name = "brickyard", version, about, long_about = None)]
struct Cli {
    /// Threads for decoding, rendering and processing (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    /// s3:// stores: an S3-compatible endpoint (http(s)://host:port),
    /// addressed path style; default AWS_ENDPOINT_URL_S3 or
    /// AWS_ENDPOINT_URL, else Amazon's regional endpoint. Credentials come
    /// from AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY and AWS_SESSION_TOKEN,
    /// else from the profile AWS_PROFILE (default) of ~/.aws/credentials.
    #[arg(long, global = true, value_name = "URL", help_heading = "s3:// stores")]
    s3_endpoint: Option<String>,
    /// s3:// stores: the region (default AWS_REGION, AWS_DEFAULT_REGION,
    /// the profile's region in ~/.aws/config, else us-east-1).
    #[arg(
        long,
        global = true,
        value_name = "REGION",
        help_heading = "s3:// stores"
    )]
    s3_region: Option<String>,
    /// s3:// stores: unsigned requests (public buckets), whatever
    /// credentials the environment holds (as AWS_NO_SIGN_REQUEST=true).
    #[arg(long, global = true, help_heading = "s3:// stores")]
    s3_anonymous: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Convert a volume (raw, TIFF, NRRD, NIfTI, Zarr/OME-Zarr) into a
    /// multi-resolution OME-Zarr 0.5 pyramid.
    Convert(ConvertCmd),
    /// Run a processing pipeline (e.g. "gauss(1.5)|threshold(0.3)|label(26)")
    /// over a store and write the result into it at every level: labels and
    /// masks under STORE/labels/NAME, other results under STORE/derived/NAME.
    Process(process::ProcessCmd),
    /// Describe a store: levels, shapes, chunks, codecs, sizes, brick statistics.
    Info {
        path: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
        /// Also read and decode every chunk of every level and of the
        /// statistics, and list the damaged ones. Exit status: 1 where a
        /// problem is listed (with or without --check: an unreadable
        /// level, a damaged chunk, leftovers of an interrupted job), 2 for
        /// a store whose writing did not finish, else 0.
        #[arg(long)]
        check: bool,
    },
    /// Generate a procedural volume (raw + JSON sidecar, or an OME-Zarr
    /// pyramid when OUTPUT ends in .zarr).
    Generate {
        /// mandelbulb or marschner-lobb
        kind: String,
        output: PathBuf,
        /// N (a cube) or XxYxZ.
        #[arg(long, default_value = "256")]
        size: String,
        /// Voxel type: u8, u16, u32, i16, f32, ...
        #[arg(long, default_value = "u8")]
        dtype: String,
        #[command(flatten)]
        pyramid: PyramidArgs,
    },
    /// The main job on a built-in dataset: generate a procedural volume and
    /// convert it into a pyramid under a small memory budget.
    Demo {
        /// Output folder.
        #[arg(long, default_value = "brickyard-demo")]
        out: PathBuf,
        /// Volume size (N or XxYxZ).
        #[arg(long, default_value = "384")]
        size: String,
    },
    /// Render a store (DVR, MIP or slice) to PNG through the virtual memory.
    /// Exit status 0: every view complete; 3: images written, but not every
    /// view is complete: bricks could not be loaded (a damaged store, a
    /// lost server) and coarser data stands in for them, or a view stopped
    /// before it was complete (--max-frames); 1: an error (no image where
    /// a view has no data at any level).
    // (`--azimuth -30`, `--fov -10`: a negative number is the flag's
    // value, checked by its own rule, not taken for a flag.)
    #[command(allow_negative_numbers = true)]
    Render(Box<render::RenderCmd>),
    /// Open an interactive viewer (no STORE: the demo dataset, generated on
    /// first use).
    View(view::ViewCmd),
    /// Run a benchmark scenario and print its figures (one JSON line; a
    /// table for `octree`).
    Bench(bench::BenchCmd),
    /// Serve store directories read-only over HTTP (GET/HEAD with ranges,
    /// ETag, CORS); loopback unless a bearer token is set.
    Serve(serve::ServeCmd),
    /// Virtual memory for voxels: `footprint` prints the management memory
    /// of a configuration beside the paper's accounting.
    #[command(subcommand)]
    Vm(VmCmd),
}

#[derive(Subcommand)]
enum VmCmd {
    /// Management memory of a virtual-memory configuration.
    Footprint(vmcmd::FootprintCmd),
}

/// An edge in voxels from 2 to `most` (`--brick`, `--shard`).
fn edge(t: &str, most: u64) -> Result<u64, String> {
    t.trim()
        .parse::<u64>()
        .ok()
        .filter(|v| (2..=most).contains(v))
        .ok_or_else(|| format!("expected a number of voxels from 2 to {most}, found {t:?}"))
}

#[derive(Args, Clone)]
struct PyramidArgs {
    /// Brick (inner chunk) edge in voxels (even, 2 to 1024) [default: 64].
    // (`--brick -64` gets the range's message, not taken for flags.)
    #[arg(long, allow_hyphen_values = true, value_parser = |t: &str| edge(t, 1024))]
    brick: Option<u64>,
    /// Shard edge in voxels (a multiple of the brick, at most 16384)
    /// [default: 512 rounded up to a multiple of the brick].
    #[arg(long, allow_hyphen_values = true, value_parser = |t: &str| edge(t, 16384))]
    shard: Option<u64>,
    /// lz4 (blosc), zstd, zstd:LEVEL or none [default: lz4].
    #[arg(long)]
    compression: Option<String>,
    /// The volume holds labels: coarser levels take the mode, not the mean.
    #[arg(long)]
    labels: bool,
    /// Memory budget (e.g. 1GiB, 512MiB).
    #[arg(long, default_value = "1GiB")]
    memory: String,
    /// Replace an existing output.
    #[arg(long)]
    overwrite: bool,
    /// Voxel spacing X,Y,Z (overrides the file's).
    // (`--spacing -1,1,1` is refused by its own rule, saying why, not
    // taken for a flag.)
    #[arg(long, allow_hyphen_values = true)]
    spacing: Option<String>,
    /// Position X,Y,Z of the first voxel's centre (overrides the file's).
    #[arg(long, allow_hyphen_values = true)]
    origin: Option<String>,
    /// Unit of spacing and origin (micrometer, millimeter, ...).
    #[arg(long)]
    unit: Option<String>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Under mpirun: end a pass before a level that leaves fewer than N
    /// columns of whole shards (a later pass reads that level back), so
    /// that N ranks can share the finer levels (e.g. 64; 1, the default:
    /// the fewest passes). The store depends on it: a single process given
    /// the same --columns writes the same bytes.
    #[arg(long, value_name = "N")]
    columns: Option<u64>,
}

#[derive(Args)]
struct ConvertCmd {
    /// INPUT... OUTPUT: one input, or several inputs of one grid (same
    /// shape, voxel type, spacing and origin) stored as the channels of
    /// one volume, in order, named after the files.
    // (Taken in any number of runs, options between them: `convert IN
    // --spacing 1,1,4 OUT`; at least two are checked when run.)
    #[arg(required = true, num_args = 1.., action = clap::ArgAction::Append, value_name = "INPUT... OUTPUT")]
    paths: Vec<PathBuf>,
    /// Channel names, comma-separated (one per channel; default: the input
    /// files' names), stored in the OME-Zarr `omero` metadata.
    #[arg(long)]
    channel_names: Option<String>,
    /// Raw input: size XxYxZ.
    #[arg(long)]
    dims: Option<String>,
    /// Raw input: voxel type (u8, i8, u16, i16, u32, i32, f32, f64).
    #[arg(long)]
    dtype: Option<String>,
    /// Raw input: little (default) or big.
    #[arg(long)]
    endian: Option<String>,
    /// Raw input: number of channels (stored one after the other; default 1).
    #[arg(long)]
    channels: Option<usize>,
    /// Raw input: bytes to skip at the start of the file (default 0).
    #[arg(long)]
    header_bytes: Option<u64>,
    /// OME-Zarr input: level to convert (default 0).
    #[arg(long)]
    level: Option<usize>,
    /// Keep the numbers as stored: do not apply the rescale the file asks
    /// for (NIfTI scl_slope/scl_inter).
    #[arg(long)]
    raw_values: bool,
    #[command(flatten)]
    pyramid: PyramidArgs,
}

pub(crate) static CANCEL: AtomicBool = AtomicBool::new(false);

extern "C" fn on_sigint(_: libc::c_int) {
    CANCEL.store(true, Ordering::SeqCst);
}

pub(crate) fn install_ctrl_c() {
    // SAFETY: the handler only stores to an atomic.
    unsafe {
        libc::signal(libc::SIGINT, on_sigint as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_sigint as *const () as libc::sighandler_t);
        // A closed terminal (SIGHUP) stops work the same way: cleaned up,
        // nothing half-written left behind. Unless started ignoring it
        // (nohup): then it goes on.
        let hup = libc::signal(libc::SIGHUP, on_sigint as *const () as libc::sighandler_t);
        if hup == libc::SIG_IGN {
            libc::signal(libc::SIGHUP, libc::SIG_IGN);
        }
    }
}

pub use brickyard_run::memory::parse_bytes;

fn parse_triple(s: &str, what: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = s
        .split([',', 'x'])
        .map(|p| p.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("{what}: expected X,Y,Z numbers, found {s:?}"))?;
    if v.len() != 3 {
        bail!("{what}: expected three numbers X,Y,Z, found {s:?}");
    }
    Ok([v[0], v[1], v[2]])
}

/// Peak resident set size of this process in bytes (Linux).
pub fn peak_rss() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<u64>().ok())
            })
        })
        .map(|kb| kb * 1024)
        .unwrap_or(0)
}

/// A `--compression` value (`convert`, `bench`).
pub(crate) fn parse_compression(s: &str) -> Result<Compression> {
    Compression::parse(s).with_context(|| {
        format!(
            "compression: expected {}, found {s:?}",
            Compression::EXPECTED
        )
    })
}

/// The brick when `--brick` is not given.
const DEFAULT_BRICK: u64 = 64;

fn convert_options(p: &PyramidArgs) -> Result<ConvertOptions> {
    let compression = parse_compression(p.compression.as_deref().unwrap_or("lz4"))?;
    let brick = p.brick.unwrap_or(DEFAULT_BRICK);
    if brick < 2 || !brick.is_multiple_of(2) {
        bail!("brick: expected an even number of voxels >= 2, found {brick}");
    }
    let shard = p
        .shard
        .unwrap_or_else(|| brickyard_store::builder::default_shard(brick));
    if shard < brick || !shard.is_multiple_of(brick) {
        bail!("shard: expected a multiple of the brick ({brick}), found {shard}");
    }
    let xyz = |o: Option<[f64; 3]>| o.map(|v| [v[2], v[1], v[0]]);
    let spacing = xyz(p
        .spacing
        .as_deref()
        .map(|s| parse_triple(s, "spacing"))
        .transpose()?);
    if let Some(s) = spacing {
        if s.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            bail!(
                "spacing: expected positive numbers, found {:?}",
                p.spacing.as_deref().unwrap_or("")
            );
        }
    }
    Ok(ConvertOptions {
        brick: [brick; 3],
        shard: [shard; 3],
        compression,
        labels: p.labels,
        memory: parse_bytes(&p.memory).context("--memory")?,
        overwrite: p.overwrite,
        spacing,
        // (Checked with the spacings the input gives, by the builder.)
        origin: xyz(p
            .origin
            .as_deref()
            .map(|s| parse_triple(s, "origin"))
            .transpose()?),
        unit: p.unit.clone(),
        columns: match p.columns {
            Some(0) => bail!(
                "columns: expected at least 1 column of whole shards (the ranks under mpirun \
                 share the columns), found 0"
            ),
            c => c.unwrap_or(1),
        },
    })
}

/// The description of the raw input `input`: its sidecar (`FILE.json`),
/// if any, with the flags given laid over it (each flag that changes a
/// sidecar's field is said); `None`: neither (opening it says what to
/// give).
fn raw_options(
    input: &Path,
    (dims, dtype): (Option<Dims3>, Option<DType>),
    c: &ConvertCmd,
) -> Result<Option<RawOptions>> {
    let side = RawOptions::sidecar_path(input);
    let sidecar = match side.exists() {
        true => Some(RawOptions::read_sidecar(&side)?),
        false => None,
    };
    let had = sidecar.is_some();
    if !had && dims.is_some() != dtype.is_some() {
        bail!(
            "{}: raw input needs both --dims and --dtype (or a sidecar {} describing it), \
             found only {}",
            input.display(),
            side.display(),
            if dims.is_some() { "--dims" } else { "--dtype" }
        );
    }
    let Some(mut r) = sidecar.or_else(|| match (dims, dtype) {
        (Some(dims), Some(dtype)) => Some(RawOptions::new(dims, dtype)),
        _ => None,
    }) else {
        return Ok(None);
    };
    let mut changed = vec![];
    let mut set = |name: &str, differs: bool| {
        if had && differs {
            changed.push(name.to_string());
        }
    };
    if let Some(dims) = dims {
        set("dims", r.dims != dims);
        r.dims = dims;
    }
    if let Some(dtype) = dtype {
        set("dtype", r.dtype != dtype);
        r.dtype = dtype;
    }
    if let Some(e) = &c.endian {
        set("endian", &r.endian != e);
        r.endian = e.clone();
    }
    if let Some(n) = c.channels {
        set("channels", r.channels != n);
        r.channels = n;
    }
    if let Some(h) = c.header_bytes {
        set("header_bytes", r.header_bytes != h);
        r.header_bytes = h;
    }
    if !changed.is_empty() {
        eprintln!(
            "note: {}: the flags replace its {} (the sidecar's spacing, origin and unit are kept)",
            side.display(),
            changed.join(", ")
        );
    }
    Ok(Some(r))
}

/// A label image converted from a file: published in its image's labels
/// group, if in one, and its statistics table written (as `process` writes
/// for the labels it makes): one more pass over its voxels, with the mean
/// intensity of the image it is published under.
/// Too many labels for half the memory budget, or values that are not
/// labels, leave it without one, which is said; an interruption too.
fn label_table(output: &Path, group: Option<&Path>, p: &PyramidArgs) -> Result<()> {
    let memory = parse_bytes(&p.memory).context("--memory")?;
    let bar = progress::Bar::new(p.quiet || p.json, "label statistics");
    let r = brickyard_run::labels::finish_label_image(output, group, memory / 2, &bar, &CANCEL);
    bar.finish();
    match r {
        Ok(notes) => {
            if let Some(how) = notes.off_grid {
                eprintln!("note: {}: {how}", output.display());
            }
            if let Some(why) = notes.no_table {
                eprintln!(
                    "note: {}: no table of label statistics ({why}); the label image is complete",
                    output.display()
                );
            }
            Ok(())
        }
        Err(e) if CANCEL.load(Ordering::SeqCst) => Err(e.context(format!(
            "{}: the label image is complete, its table of label statistics not written",
            output.display()
        ))),
        Err(e) => Err(e.context(format!("{}: label statistics", output.display()))),
    }
}

/// Convert with a progress bar and print the report; under `mpirun` the
/// ranks share the conversion (rank 0 reports).
fn run_convert(
    src: &dyn VolumeSource,
    output: &Path,
    p: &PyramidArgs,
    cluster: Option<&dist::Cluster>,
) -> Result<()> {
    let opts = convert_options(p)?;
    install_ctrl_c();
    let (rank, size) = dist::rank_size(cluster);
    let bar = progress::Bar::new(p.quiet || p.json || rank > 0, "converting");
    let r = match cluster {
        #[cfg(feature = "mpi")]
        Some(c) if size > 1 => {
            let _watch = InterruptWatch::start(output, rank);
            let r = brickyard_store::builder::convert_team(src, output, &opts, &bar, &CANCEL, c);
            // A failure the ranks met over has stopped every rank's writing:
            // rank 0 removes what is left of this run's partial output (the
            // builder does after most meetings, not after the first).
            if rank == 0 && matches!(r, Err(brickyard_store::StoreError::Team(_))) {
                remove_unlocked_partial(output);
            }
            r
        }
        _ => convert(src, output, &opts, &bar, &CANCEL),
    };
    bar.finish();
    let r = match r {
        Ok(r) => r,
        Err(e) => {
            if CANCEL.load(Ordering::SeqCst) {
                let _ = std::fs::remove_dir_all(partial_path(output));
            }
            return Err(e.into());
        }
    };
    let rss = peak_rss();
    if rank > 0 {
        return Ok(());
    }
    if p.json {
        let mut j = serde_json::to_value(&r)?;
        j["peak_rss_bytes"] = rss.into();
        if size > 1 {
            j["ranks"] = size.into();
        }
        j["input_mb_s"] = (r.bytes_in as f64 / 1e6 / r.seconds).into();
        outln!("{}", serde_json::to_string(&j)?);
    } else {
        outln!(
            "wrote {}{} ({} levels, {} bricks: {} empty, {} constant incl. empty) in {:.2} s: {} in, {} out, {:.0} MB/s, peak RSS {}",
            output.display(),
            if size > 1 { format!(" on {size} ranks") } else { String::new() },
            r.levels.len(),
            r.bricks,
            r.bricks_empty,
            r.bricks_constant,
            r.seconds,
            human_bytes(r.bytes_in),
            human_bytes(r.bytes_written),
            r.bytes_in as f64 / 1e6 / r.seconds,
            human_bytes(rss)
        );
        for n in &r.notes {
            outln!("  {n}");
        }
    }
    Ok(())
}

fn main() {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_env("BRICKYARD_LOG"))
        .with_writer(std::io::stderr)
        .init();
    if let Some(t) = cli.threads {
        if !(1..=1024).contains(&t) {
            eprintln!("error: threads: expected 1 to 1024 worker threads, found {t}");
            std::process::exit(2);
        }
        let _ = rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global();
    }
    match brickyard_store::storage::http::HttpConfig::from_env() {
        Ok(c) => brickyard_store::storage::http::configure(c),
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
    // s3:// settings: the flags over the environment's variables.
    let s3 = brickyard_store::storage::s3::S3Config::from_vars(|k| {
        let flag = match k {
            "AWS_ENDPOINT_URL_S3" => cli.s3_endpoint.as_ref(),
            "AWS_REGION" => cli.s3_region.as_ref(),
            _ => None,
        };
        match (flag, k) {
            (Some(v), _) => Some(v.clone()),
            (None, "AWS_NO_SIGN_REQUEST") if cli.s3_anonymous => Some("true".into()),
            _ => std::env::var(k).ok(),
        }
    });
    match s3 {
        Ok(c) => brickyard_store::storage::s3::configure(c),
        Err(e) => {
            let e = e
                .replacen(
                    "AWS_ENDPOINT_URL_S3:",
                    "--s3-endpoint (or AWS_ENDPOINT_URL_S3):",
                    1,
                )
                .replacen("AWS_REGION:", "--s3-region (or AWS_REGION):", 1);
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    }
    // Under an MPI launcher (feature `mpi`): the ranks sharing the work.
    #[cfg(feature = "mpi")]
    let cluster = match brickyard_dist::Cluster::from_launcher() {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(1);
        }
    };
    #[cfg(not(feature = "mpi"))]
    let cluster: Option<dist::Cluster> = {
        if let Err(e) = dist::refuse_launcher(&cli.cmd) {
            eprintln!("error: {e:#}");
            std::process::exit(1);
        }
        None
    };
    let (rank, size) = dist::rank_size(cluster.as_ref());
    let result = match cluster.as_ref() {
        #[cfg(feature = "mpi")]
        Some(c) if size > 1 => run_ranks(cli.cmd, c),
        _ => run(cli.cmd, cluster.as_ref()),
    };
    let code = match result {
        Ok(()) => EXIT_STATUS.load(std::sync::atomic::Ordering::SeqCst),
        Err(e) => {
            // What every rank agreed on is said once, by rank 0; a rank's
            // own failure by that rank.
            if size == 1 {
                eprintln!("error: {e:#}");
            } else if rank == 0 || !dist::agreed(&e) {
                eprintln!(
                    "error: {}{e:#}",
                    if dist::agreed(&e) {
                        String::new()
                    } else {
                        format!("rank {rank}: ")
                    }
                );
            }
            1
        }
    };
    // What went to standard output must have arrived (a full disk under
    // `> file` would leave a truncated file behind a status of 0).
    let code = match brickyard_run::out_error() {
        Some(e) => {
            eprintln!("error: standard output: {e}: what was printed is incomplete");
            1
        }
        None => code,
    };
    // MPI_Finalize before leaving (process::exit runs no destructors).
    #[cfg(feature = "mpi")]
    drop(cluster);
    std::process::exit(code);
}

/// A command under `mpirun` with several ranks. Every rank must be given
/// the same command and see the same inputs (checked first, an error every
/// rank agrees on); commands that share no work are refused. A rank's own
/// failure or panic (not one the ranks agreed on at a meeting point) must
/// not end in `MPI_Finalize`, which would wait for ranks that wait for this
/// one: [`brickyard_dist::Cluster::fail_alone`] ends the job, or, when
/// every rank failed alike, lets rank 0 say it once.
#[cfg(feature = "mpi")]
fn run_ranks(cmd: Cmd, c: &dist::Cluster) -> Result<()> {
    use brickyard_dist::{cluster::input_identity, Agreed};
    let args: Vec<String> = std::env::args_os()
        .skip(1)
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    let inputs: Vec<PathBuf> = match &cmd {
        Cmd::Convert(cv) => cv.paths.split_last().map_or(vec![], |(_, i)| i.to_vec()),
        Cmd::Render(r) => vec![r.store().to_path_buf()],
        _ => vec![],
    };
    let seen: Vec<(String, String)> = inputs
        .iter()
        .map(|p| (p.display().to_string(), input_identity(p)))
        .collect();
    c.check_same_command(&args, &seen).map_err(Agreed)?;
    let alone = match &cmd {
        Cmd::Convert(_) | Cmd::Render(_) => None,
        Cmd::Generate { output, .. }
            if [".zarr", ".zarr/"]
                .iter()
                .any(|e| output.to_string_lossy().ends_with(e)) =>
        {
            None
        }
        Cmd::Generate { .. } => Some("generate (of a raw file)"),
        Cmd::Process(_) => Some("process"),
        Cmd::Info { .. } => Some("info"),
        Cmd::Demo { .. } => Some("demo"),
        Cmd::View(_) => Some("view"),
        Cmd::Bench(_) => Some("bench"),
        Cmd::Serve(_) => Some("serve"),
        Cmd::Vm(_) => Some("vm"),
    };
    if let Some(name) = alone {
        // The same on every rank (the same command): said once by rank 0.
        return Err(Agreed(format!(
            "{name} runs in one process and shares no work among MPI ranks: each of the {} \
             ranks would run it whole (racing for its output). Run it without mpirun, or with \
             mpirun -n 1; convert, generate (of a store) and render share their work",
            dist::rank_size(Some(c)).1
        ))
        .into());
    }
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        c.fail_at_start()?;
        run(cmd, Some(c))
    }));
    let msg = match r {
        Ok(Ok(())) => return Ok(()),
        Ok(Err(e)) if dist::agreed(&e) => return Err(e),
        Ok(Err(e)) => format!("{e:#}"),
        Err(p) => {
            let what = p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "(no message)".into());
            format!("panicked: {what}")
        }
    };
    // Returns only when every rank failed so: then rank 0 says it, once.
    Err(Agreed(c.fail_alone(&msg)).into())
}

/// `OUTPUT.partial` removed, unless another live process holds the lock
/// of `output` (then the partial output is its own).
#[cfg(feature = "mpi")]
fn remove_unlocked_partial(output: &Path) {
    let name = output
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let lock = output.with_file_name(format!("{name}.lock"));
    let what = format!("writing {}", output.display());
    if let Ok(_held) = brickyard_store::lock::PidLock::take(&lock, &what) {
        let _ = std::fs::remove_dir_all(partial_path(output));
    }
}

/// A conversion shared by ranks, stopped by SIGTERM or SIGINT (`mpirun`,
/// itself interrupted, sends every rank SIGTERM, and SIGKILL a second
/// later: Open MPI's `odls_base_sigkill_timeout`). The ranks stop at their
/// next slab of input and meet over it, and rank 0 removes `OUT.partial`
/// (and, as the lock is dropped, `OUT.lock`), as a single process does.
/// A rank still busy with a slab (a slow codec) would have SIGKILL come
/// first and leave both behind; so where the meeting has not ended the
/// conversion [`InterruptWatch::ROOT`] after the signal, rank 0 removes
/// the partial output and its lock itself, and keeps removing what the
/// others still write until it ends; at [`InterruptWatch::OTHERS`] the
/// other ranks end (status 130), which stops their writing and makes
/// `mpirun` end rank 0.
#[cfg(feature = "mpi")]
struct InterruptWatch {
    done: std::sync::Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

#[cfg(feature = "mpi")]
impl InterruptWatch {
    const ROOT: std::time::Duration = std::time::Duration::from_millis(400);
    const OTHERS: std::time::Duration = std::time::Duration::from_millis(600);
    /// Rank 0's end, if nothing has ended it before.
    const ROOT_END: std::time::Duration = std::time::Duration::from_millis(950);

    fn start(output: &Path, rank: usize) -> InterruptWatch {
        use std::time::{Duration, Instant};
        let done = std::sync::Arc::new(AtomicBool::new(false));
        let (d, output) = (done.clone(), output.to_path_buf());
        let thread = std::thread::spawn(move || {
            let tick = Duration::from_millis(10);
            // Until `until` after the signal, or the conversion's end (true).
            let wait_until = |t: Instant, until: Duration| loop {
                if d.load(Ordering::SeqCst) {
                    return true;
                }
                if t.elapsed() >= until {
                    return false;
                }
                std::thread::sleep(tick);
            };
            while !CANCEL.load(Ordering::SeqCst) {
                if d.load(Ordering::SeqCst) {
                    return;
                }
                std::thread::sleep(tick);
            }
            let t = Instant::now();
            if rank != 0 {
                if wait_until(t, Self::OTHERS) {
                    return;
                }
                // SAFETY: ends the process at once, as the signal's
                // default action would have.
                unsafe { libc::_exit(130) }
            }
            if wait_until(t, Self::ROOT) {
                return;
            }
            let partial = partial_path(&output);
            let name = output
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let lock = output.with_file_name(format!("{name}.lock"));
            let _ = std::fs::remove_dir_all(&partial);
            if std::fs::read_to_string(&lock)
                .is_ok_and(|s| s.trim() == std::process::id().to_string())
            {
                let _ = std::fs::remove_file(&lock);
            }
            eprintln!(
                "error: interrupted: {} not written (its partial output removed)",
                output.display()
            );
            while t.elapsed() < Self::ROOT_END {
                if partial.exists() {
                    let _ = std::fs::remove_dir_all(&partial);
                }
                std::thread::sleep(Duration::from_millis(2));
            }
            // SAFETY: as above.
            unsafe { libc::_exit(130) }
        });
        InterruptWatch {
            done,
            thread: Some(thread),
        }
    }
}

#[cfg(feature = "mpi")]
impl Drop for InterruptWatch {
    fn drop(&mut self) {
        self.done.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The exit status of a command that ended without an error (0 unless it
/// says otherwise).
static EXIT_STATUS: std::sync::atomic::AtomicI32 = std::sync::atomic::AtomicI32::new(0);

/// `render`'s lines, one per view: views drawn in part from coarser data
/// because bricks could not be loaded end the command with status 3, so
/// that a script can tell such an image from a complete one.
fn degraded(lines: Vec<String>) {
    let n = lines
        .iter()
        .filter(|l| l.contains(render::DEGRADED))
        .count();
    let stopped = lines.iter().filter(|l| l.contains(render::STOPPED)).count();
    if n > 0 {
        eprintln!(
            "note: {n} view(s) drawn in part from coarser data, bricks could not be loaded: exit status 3"
        );
    }
    if stopped > 0 {
        eprintln!("note: {stopped} view(s) stopped before they were complete: exit status 3");
    }
    if n + stopped > 0 {
        EXIT_STATUS.store(3, std::sync::atomic::Ordering::SeqCst);
    }
}

fn run(cmd: Cmd, cluster: Option<&dist::Cluster>) -> Result<()> {
    match cmd {
        Cmd::Convert(c) => {
            // Either alone replaces that field of a sidecar; without one,
            // both are needed (refused once the input is known to be raw:
            // other inputs are told that the flag is not for them).
            let dims = match &c.dims {
                None => None,
                Some(d) => {
                    let zyx = parse_size(d).map_err(|e| anyhow::anyhow!("dims: {e}"))?;
                    Some([zyx[2], zyx[1], zyx[0]])
                }
            };
            let dtype = match &c.dtype {
                None => None,
                Some(t) => Some(DType::parse(t).with_context(|| {
                    format!(
                        "dtype: expected one of u8, i8, u16, i16, u32, i32, f32, f64, found {t:?}"
                    )
                })?),
            };
            let dims_dtype = (dims, dtype);
            if c.paths.len() < 2 {
                bail!(
                    "convert: expected INPUT... OUTPUT, found one path ({}): name the store to write",
                    c.paths[0].display()
                );
            }
            let (output, inputs) = c.paths.split_last().expect("two paths at least");
            // Each input's options: the flags that describe raw data, the
            // level of a Zarr input and the NIfTI rescale are refused for
            // inputs they do not apply to (not silently ignored).
            let options = |input: &Path| -> Result<ImportOptions> {
                let fmt = brickyard_store::import::detect(input)?;
                let raw_flags = [
                    (c.dims.is_some(), "--dims"),
                    (c.dtype.is_some(), "--dtype"),
                    (c.endian.is_some(), "--endian"),
                    (c.channels.is_some(), "--channels"),
                    (c.header_bytes.is_some(), "--header-bytes"),
                ];
                let kind = fmt.describe();
                if let (false, Some((_, flag))) =
                    (fmt == Format::Raw, raw_flags.iter().find(|f| f.0))
                {
                    bail!(
                        "{}: {flag} describes raw data, and this input is read as {kind} (its \
                         header describes it): leave {flag} out",
                        input.display()
                    );
                }
                // (open_input refuses these too, for every caller; here
                // they are named as the flags they were given as.)
                if c.level.is_some_and(|l| l > 0) && fmt != Format::Zarr {
                    bail!(
                        "{}: --level picks a level of a Zarr/OME-Zarr input, and this input is \
                         read as {kind}",
                        input.display()
                    );
                }
                if c.raw_values && fmt != Format::Nifti {
                    bail!(
                        "{}: --raw-values keeps a NIfTI file's numbers without its \
                         scl_slope/scl_inter, and this input is read as {kind}",
                        input.display()
                    );
                }
                Ok(ImportOptions {
                    raw: (fmt == Format::Raw)
                        .then(|| raw_options(input, dims_dtype, &c))
                        .transpose()?
                        .flatten(),
                    zarr_level: c.level.unwrap_or(0),
                    raw_values: c.raw_values,
                })
            };
            // (Checked before any input is opened.)
            let names: Option<Vec<String>> = c
                .channel_names
                .as_ref()
                .map(|n| n.split(',').map(|s| s.trim().to_string()).collect());
            if let (Some(n), Some(names)) = (&c.channel_names, &names) {
                check_channel_names(n, names)?;
            }
            let src: Box<dyn VolumeSource> = if inputs.len() == 1 && names.is_none() {
                open_input(&inputs[0], &options(&inputs[0])?)?
            } else {
                let sources = inputs
                    .iter()
                    .map(|p| Ok(open_input(p, &options(p)?)?))
                    .collect::<Result<Vec<_>>>()?;
                // --labels given: the inputs are labels, whatever their
                // headers say.
                let mut stack = match c.pyramid.labels {
                    true => ChannelStack::of_labels(sources)?,
                    false => ChannelStack::new(sources)?,
                };
                if let Some(names) = &names {
                    stack = stack.with_names(names)?;
                }
                Box::new(stack)
            };
            // Labels written into an image's `labels` group: the group is
            // made when missing, and once written the label image is
            // marked as the image's and listed, as `process` publishes.
            let group = brickyard_run::labels::label_target(output, c.pyramid.labels)?;
            // A label image that cannot be one (several channels, float
            // voxels) is refused before anything is written.
            brickyard_store::builder::check_labels(output, src.meta(), c.pyramid.labels)?;
            let mut pyramid = c.pyramid.clone();
            let mut made = None;
            if let Some(g) = &group {
                // Flags given win over the image's geometry.
                let given = [&pyramid.spacing, &pyramid.origin, &pyramid.unit];
                let inherit = match given.iter().all(|g| g.is_none()) {
                    true => brickyard_run::labels::inherited_geometry(g, src.meta())?,
                    false => None,
                };
                if let Some((spacing, origin, unit)) = inherit {
                    let xyz = |v: [f64; 3]| format!("{},{},{}", v[2], v[1], v[0]);
                    pyramid.spacing = spacing.map(xyz);
                    pyramid.origin = origin.map(xyz);
                    pyramid.unit = unit;
                    if let Some(sp) = &pyramid.spacing {
                        eprintln!(
                            "note: {} gives no spacing: the image's ({sp}{}) taken, on the same grid",
                            inputs[0].display(),
                            pyramid.unit.as_deref().map(|u| format!(" {u}")).unwrap_or_default()
                        );
                    }
                }
                made = Some(brickyard_run::labels::LabelGroup::make(g)?);
            }
            if let Err(e) = run_convert(src.as_ref(), output, &pyramid, cluster) {
                if let Some(m) = made {
                    m.undo();
                }
                return Err(e);
            }
            if dist::rank_size(cluster).0 != 0 {
                return Ok(());
            }
            if c.pyramid.labels {
                label_table(output, group.as_deref(), &pyramid)?;
            }
            Ok(())
        }
        Cmd::Process(p) => process::run(p),
        Cmd::Info { path, json, check } => {
            let i = inspect(&path)?;
            let checked = if check {
                let bar = progress::Bar::counting(false, "checking chunks");
                let r = brickyard_store::info::check::check(&path, &bar)?;
                bar.finish();
                Some(r)
            } else {
                None
            };
            if json {
                let mut v = serde_json::to_value(&i)?;
                if let Some(r) = &checked {
                    v["check"] = serde_json::to_value(r)?;
                }
                outln!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                out!("{}", format_info(&i));
                if let Some(r) = &checked {
                    out!("{}", brickyard_store::info::check::format_check(r));
                }
            }
            let status = if i.complete == Some(false) {
                2
            } else if checked.as_ref().is_some_and(|r| !r.ok()) || !i.problems.is_empty() {
                1
            } else {
                0
            };
            EXIT_STATUS.store(status, std::sync::atomic::Ordering::SeqCst);
            Ok(())
        }
        Cmd::Generate {
            kind,
            output,
            size,
            dtype,
            pyramid,
        } => {
            let k = Kind::parse(&kind).with_context(|| {
                format!("kind: expected mandelbulb or marschner-lobb, found {kind:?}")
            })?;
            let dims = parse_size(&size).map_err(|e| anyhow::anyhow!("size: {e}"))?;
            let dt = DType::parse(&dtype)
                .with_context(|| format!("dtype: unknown voxel type {dtype:?}"))?;
            let src = Procedural::new(k, dims, dt).with_spacing([1.0; 3]);
            let s = output.to_string_lossy();
            if s.ends_with(".zarr") || s.ends_with(".zarr/") {
                run_convert(&src, &output, &pyramid, cluster).map_err(|e| {
                    too_large(e, dims, dt, &pyramid.memory, "--size or a larger --memory")
                })
            } else {
                // The raw file and its sidecar: neither is replaced unasked.
                let sidecar = RawOptions::sidecar_path(&output);
                for p in [&output, &sidecar] {
                    if p.exists() && !pyramid.overwrite {
                        bail!("{}: exists; pass --overwrite to replace it", p.display());
                    }
                    if p.is_dir() {
                        bail!("{}: is a folder; expected a file to write", p.display());
                    }
                }
                // The flags that shape a store do nothing for a raw file:
                // refused, not ignored.
                let store_only = [
                    (pyramid.brick.is_some(), "--brick"),
                    (pyramid.shard.is_some(), "--shard"),
                    (pyramid.compression.is_some(), "--compression"),
                    (pyramid.labels, "--labels"),
                    (pyramid.columns.is_some(), "--columns"),
                ];
                if let Some((_, flag)) = store_only.iter().find(|f| f.0) {
                    bail!(
                        "{}: {flag} shapes an OME-Zarr store, and this output is a raw file \
                         (its name does not end in .zarr): leave {flag} out, or name a .zarr output",
                        output.display()
                    );
                }
                // Spacing, origin and unit go into the sidecar, checked as
                // convert checks them.
                let geometry = convert_options(&pyramid)?;
                let xyz = |v: [f64; 3]| [v[2], v[1], v[0]];
                let unit = match &pyramid.unit {
                    None => None,
                    Some(u) => Some(
                        brickyard_store::omezarr::known_unit(u)
                            .map_err(|why| anyhow::anyhow!("unit: {why}"))?,
                    ),
                };
                // Within --memory (a quarter of it for the slab, at most
                // 64 MiB), and stopped cleanly by Ctrl-C.
                let memory = geometry.memory;
                install_ctrl_c();
                let bar = progress::Bar::new(pyramid.quiet, "generating");
                brickyard_store::generate::write_raw_described(
                    &src,
                    &output,
                    &bar,
                    (memory / 4).clamp(1, 64 << 20),
                    &CANCEL,
                    Some(geometry.spacing.map_or([1.0; 3], xyz)),
                    geometry.origin.map(xyz),
                    unit,
                )?;
                bar.finish();
                outln!(
                    "wrote {} ({}x{}x{} {dt}) and {}",
                    output.display(),
                    dims[2],
                    dims[1],
                    dims[0],
                    RawOptions::sidecar_path(&output).display()
                );
                Ok(())
            }
        }
        Cmd::Demo { out, size } => demo(&out, &size),
        Cmd::Render(r) => match cluster {
            // Under mpirun: the ranks share the render (rank 0 writes).
            #[cfg(feature = "mpi")]
            Some(c) if dist::rank_size(Some(c)).1 > 1 => {
                let split = match r.distribute.as_deref() {
                    None | Some("image") => brickyard_run::share::Split::Image,
                    Some("data") => brickyard_run::share::Split::Data,
                    Some(d) => bail!("distribute: expected image or data, found {d:?}"),
                };
                use brickyard_dist::share::{RenderShare, BANDS_PER_RANK, DEVICE_BANDS_PER_RANK};
                // On devices each band is a whole frame: one band a rank.
                let per_rank = match r.backend() {
                    "gpu" => DEVICE_BANDS_PER_RANK,
                    _ => BANDS_PER_RANK,
                };
                let mut share = RenderShare::new(c, split).bands_per_rank(per_rank);
                render::run_shared(*r, Some(&mut share)).map(degraded)
            }
            _ => {
                // An MPI build run alone: --distribute has no ranks to share with.
                #[cfg(feature = "mpi")]
                if let Some(d) = r
                    .distribute
                    .as_deref()
                    .filter(|d| ["image", "data"].contains(d))
                {
                    eprintln!(
                        "note: --distribute {d} shares a render among the processes mpirun \
                         starts; this process runs alone and draws the whole image"
                    );
                }
                render::run(*r).map(degraded)
            }
        },
        Cmd::View(v) => {
            let code = view::run(v, || demo_store(Path::new("brickyard-demo"), "384"))?;
            EXIT_STATUS.store(code, std::sync::atomic::Ordering::SeqCst);
            Ok(())
        }
        Cmd::Bench(b) => bench::run(b),
        Cmd::Serve(s) => serve::run(s),
        Cmd::Vm(VmCmd::Footprint(f)) => vmcmd::footprint(f),
    }
}

/// The demo store in `out`, converted now if it is missing or incomplete.
fn demo_store(out: &Path, size: &str) -> Result<PathBuf> {
    let store = out.join("mandelbulb.ome.zarr");
    if inspect(&store).is_ok_and(|i| i.complete != Some(false)) {
        return Ok(store);
    }
    convert_demo(out, size)?;
    Ok(store)
}

/// A conversion of a generated `dims` volume of `dtype` that failed for
/// want of memory: the volume's size is the problem, said so (with the
/// builder's figures), and `fix` the way out.
fn too_large(
    e: anyhow::Error,
    dims: Dims3,
    dtype: DType,
    memory: &str,
    fix: &str,
) -> anyhow::Error {
    let Some(brickyard_store::error::StoreError::Invalid { field, .. }) =
        e.downcast_ref::<brickyard_store::error::StoreError>()
    else {
        return e;
    };
    if field != "memory" {
        return e;
    }
    let mut bytes = dims.iter().map(|&d| d as f64).product::<f64>() * dtype.size() as f64;
    let mut unit = 0;
    let units = ["B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB", "ZiB", "YiB"];
    while bytes >= 1024.0 && unit + 1 < units.len() {
        bytes /= 1024.0;
        unit += 1;
    }
    anyhow::anyhow!(
        "size: a {}x{}x{} {dtype} volume ({bytes:.1} {}) is too large to convert within a memory \
         budget of {memory}: choose a smaller {fix} ({e})",
        dims[2],
        dims[1],
        dims[0],
        units[unit]
    )
}

fn convert_demo(out: &Path, size: &str) -> Result<PathBuf> {
    let dims = parse_size(size).map_err(|e| anyhow::anyhow!("size: {e}"))?;
    // The demo folder itself is made, never the folders above it; made
    // here and left empty by a failure, it is removed.
    brickyard_store::builder::check_parent(out)?;
    let made = !out.exists();
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let r = convert_demo_in(out, dims);
    if r.is_err() && made {
        // (Only an empty folder: remove_dir removes nothing else.)
        let _ = std::fs::remove_dir(out);
    }
    r
}

fn convert_demo_in(out: &Path, dims: Dims3) -> Result<PathBuf> {
    let store = out.join("mandelbulb.ome.zarr");
    let src = Procedural::new(Kind::Mandelbulb, dims, DType::U16).with_spacing([1.0; 3]);
    outln!(
        "demo: converting a {}x{}x{} u16 Mandelbulb into {}",
        dims[2],
        dims[1],
        dims[0],
        store.display()
    );
    let args = PyramidArgs {
        brick: Some(64),
        shard: Some(256),
        compression: Some("lz4".into()),
        labels: false,
        memory: "256MiB".into(),
        overwrite: true,
        spacing: None,
        origin: None,
        unit: Some("micrometer".into()),
        json: false,
        quiet: false,
        columns: None,
    };
    run_convert(&src, &store, &args, None)
        .map_err(|e| too_large(e, dims, DType::U16, &args.memory, "--size"))?;
    Ok(store)
}

fn demo(out: &Path, size: &str) -> Result<()> {
    let store = convert_demo(out, size)?;
    out!("{}", format_info(&inspect(&store)?));
    stream_demo(&store)?;
    render_demo(&store, out)?;
    outln!(
        "demo: done; inspect it with `brickyard info {}`",
        store.display()
    );
    Ok(())
}

/// `--channel-names`: one name per channel, none empty, none twice.
fn check_channel_names(given: &str, names: &[String]) -> Result<()> {
    for (i, n) in names.iter().enumerate() {
        if n.is_empty() {
            bail!(
                "channel-names: name {} of {given:?} is empty; expected one name per channel, comma-separated",
                i + 1
            );
        }
        if let Some(j) = names[..i].iter().position(|m| m == n) {
            bail!(
                "channel-names: {n:?} given twice (names {} and {} of {given:?}); each channel needs a name of its own",
                j + 1,
                i + 1
            );
        }
    }
    Ok(())
}

/// Render the demo store to PNGs at 1024²: a DVR turntable (4 views), a
/// MIP, a slice, and one DVR through a pool far smaller than the view's
/// working set (drawn as fine as that pool allows, and saying so); then a
/// summary of what was shown and measured.
fn render_demo(store: &Path, out: &Path) -> Result<()> {
    let base = ["--size", "1024x1024", "--brick", "32"];
    let jobs: Vec<(Vec<&str>, &str, &str)> = vec![
        (
            vec!["--mode", "dvr", "--turntable", "4", "--tf", "hot"],
            "dvr.png",
            "DVR turntable, 4 views",
        ),
        (
            vec!["--mode", "mip", "--tf", "hot"],
            "mip.png",
            "maximum intensity projection",
        ),
        (
            vec!["--mode", "slice", "--slice-z", "0.45", "--tf", "viridis"],
            "slice.png",
            "slice through the middle",
        ),
        (
            vec![
                "--mode",
                "dvr",
                "--tf",
                "hot",
                "--pool",
                "8MiB",
                "--azimuth",
                "120",
            ],
            "dvr-8mib-pool.png",
            "DVR through an 8 MiB pool (a tenth of the view's working set)",
        ),
    ];
    let mut summary = vec![];
    for (args, name, what) in jobs {
        let path = out.join(name);
        outln!("demo: rendering {what} ({})", args.join(" "));
        let mut all: Vec<String> = vec![
            "brickyard".into(),
            "render".into(),
            store.to_string_lossy().into_owned(),
        ];
        all.extend(base.iter().map(|s| s.to_string()));
        all.extend(args.iter().map(|s| s.to_string()));
        all.extend(["--out".to_string(), path.to_string_lossy().into_owned()]);
        let cmd = render::RenderCmd::try_parse_from(&all).map_err(|e| anyhow::anyhow!("{e}"))?;
        let t = std::time::Instant::now();
        let lines = render::run_quiet(cmd)?;
        summary.push(format!(
            "  {what} ({:.1} s):\n{}",
            t.elapsed().as_secs_f64(),
            lines
                .iter()
                .map(|l| format!("    {l}"))
                .collect::<Vec<_>>()
                .join("\n")
        ));
    }
    outln!("demo: summary");
    for s in &summary {
        outln!("{s}");
    }
    if let Some(p) = memory::peak_rss() {
        outln!("demo: peak memory {}", human_bytes(p));
    }
    Ok(())
}

/// Stream a 1920×1080 slice through the middle of the store, at full
/// resolution, through the virtual memory with a pool far smaller than the
/// volume, printing each frame's completeness until the view is complete.
fn stream_demo(store: &Path) -> Result<()> {
    use brickyard_cache::session::Session;
    use brickyard_cache::vm::{Requests, VmConfig};
    use rayon::prelude::*;
    let cfg = VmConfig {
        brick: [32; 3],
        pool_bytes: 24 << 20,
        pt_cache_blocks: 64,
        request_cap: 64,
        upload_bytes_per_frame: 4 << 20,
        max_dir_entries: 512,
        ..Default::default()
    };
    let mut s = Session::open(store, cfg, 32 << 20, 2)?;
    let (w, h) = (1920usize, 1080usize);
    outln!(
        "demo: streaming a {w}x{h} slice at level 0 through a {} pool ({} slots, {} page-table level(s))",
        human_bytes(s.vm().pool_bytes() as u64),
        s.vm().pool_slots(),
        s.vm().layout().pt_levels()
    );
    let t0 = std::time::Instant::now();
    for frame in 1..=10_000 {
        let ft = std::time::Instant::now();
        s.begin_frame();
        let vm = s.vm();
        let parts: Vec<(usize, Requests)> = (0..h)
            .into_par_iter()
            .chunks(64)
            .map(|rows| {
                let mut req = vm.requests();
                let mut exact = 0;
                for y in rows {
                    for x in 0..w {
                        let p = [
                            0.5,
                            (y as f64 + 0.5) / h as f64,
                            (x as f64 + 0.5) / w as f64,
                        ];
                        exact += (vm.sample(0, 0, p, true, &mut req).level == Some(0)) as usize;
                    }
                }
                (exact, req)
            })
            .collect();
        let exact: usize = parts.iter().map(|p| p.0).sum();
        let st = s.finish_frame(parts.iter().map(|p| &p.1));
        outln!(
            "  frame {frame:3}: {:5.1}% complete, {:3} requests, {:3} bricks in ({} uploaded), {} resident, {:.0} ms",
            100.0 * exact as f64 / (w * h) as f64,
            st.frame.requests.len(),
            st.insert.inserted + st.insert.flagged,
            human_bytes(st.insert.bytes_uploaded),
            st.frame.resident_bricks,
            ft.elapsed().as_secs_f64() * 1e3
        );
        if exact == w * h {
            outln!(
                "demo: view complete after {frame} frames, {:.2} s",
                t0.elapsed().as_secs_f64()
            );
            return Ok(());
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    bail!("the demo view did not complete")
}
