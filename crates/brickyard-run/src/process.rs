//! `brickyard process` and `brickyard.process`: a pipeline over a level of
//! a store, written back into it (`STORE/labels/NAME` for labels and masks,
//! `STORE/derived/NAME` otherwise) with crash-safe publishing: one job per
//! name (a lock file holding its pid), the result staged beside the final
//! name and swapped in, leftovers of an interrupted run undone first. The
//! command line and the Python bindings both run this; they differ only in
//! how they name options in messages ([`Caller`]) and how they show
//! progress ([`Phases`]).

use anyhow::{bail, Context, Result};
use brickyard_process::{
    build_within, label_pass1_within, write_stats_csv, write_stats_json, FilterKernels,
    LabelSource, Op, Pipeline,
};
use brickyard_store::builder::Progress;
use brickyard_store::import::zarr::{self, ZarrSource};
use brickyard_store::info::human_bytes;
use brickyard_store::lock::PidLock;
use brickyard_store::omezarr::{read_json, write_json};
use brickyard_store::{convert, Compression, ConvertOptions, StoreError, VolumeSource};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// A job stopped by its cancel flag (Ctrl-C); the store is as it was.
#[derive(Debug)]
pub struct Interrupted;

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("interrupted")
    }
}

impl std::error::Error for Interrupted {}

/// How the caller names things in messages.
pub struct Caller {
    /// Before an option's name: `"--"` on the command line, `""` for
    /// keyword arguments.
    pub flag: &'static str,
    /// How a volume is converted first.
    pub convert: &'static str,
    /// What to do about a remote store.
    pub remote: &'static str,
    /// How an existing result is replaced.
    pub overwrite: &'static str,
    /// What is run again after an interruption ("command", "call").
    pub again: &'static str,
}

/// Progress of a job's phases: `labelling` (pass 1 of a labelling, in
/// voxels) and `writing` (the pyramid, in bytes); `done` once each ends.
pub trait Phases {
    fn labelling(&self) -> &dyn Progress;
    fn writing(&self) -> &dyn Progress;
    fn done(&self, _labelling: bool) {}
}

/// What a job is asked to do (the command line's options).
pub struct ProcessArgs {
    pub store: PathBuf,
    pub pipeline: String,
    pub out: String,
    pub memory: u64,
    pub level: usize,
    pub channel: usize,
    pub stats: Option<PathBuf>,
    pub overwrite: bool,
    pub backend: String,
    /// No line about the device.
    pub quiet: bool,
}

/// What a job did.
pub struct ProcessReport {
    /// Where the result was published.
    pub output: PathBuf,
    /// Labels found (a labelling).
    pub labels: Option<u32>,
    /// The pipeline as parsed.
    pub pipeline: String,
    pub levels: usize,
    pub dtype: brickyard_core::DType,
    pub bytes_written: u64,
    /// The device the filter stages ran on (`None`: the CPU).
    pub device: Option<String>,
    pub seconds: f64,
    /// What the user should know of the result: label ids filtered as
    /// intensities, a mask that came out empty or full, a label image of a
    /// coarser level off the image's grid.
    pub notes: Vec<String>,
}

impl ProcessReport {
    /// `wrote OUTPUT (DTYPE, N levels[, M labels]) in S s`.
    pub fn headline(&self) -> String {
        format!(
            "wrote {} ({}, {} levels{}) in {:.2} s",
            self.output.display(),
            self.dtype,
            self.levels,
            self.labels
                .map(|n| format!(", {n} labels"))
                .unwrap_or_default(),
            self.seconds,
        )
    }

    /// The [`headline`](Self::headline) and `; note: …` for each note.
    pub fn summary(&self) -> String {
        format!(
            "{}{}",
            self.headline(),
            self.notes
                .iter()
                .map(|n| format!("; note: {n}"))
                .collect::<String>()
        )
    }
}

/// The pipeline parsed, with the CLI's message on an error.
pub fn parse(text: &str) -> Result<Pipeline> {
    Pipeline::parse(text).map_err(|e| anyhow::anyhow!("{e}"))
}

/// The filter kernels on the device `backend` names (`None`: the CPU).
fn device(backend: &str, flag: &str) -> Result<Option<Arc<FilterKernels>>> {
    use brickyard_gpu::{AdapterChoice, Gpu};
    let open = || crate::backend::quietly(|| Gpu::new(AdapterChoice::Best));
    let gpu = match backend {
        "cpu" => return Ok(None),
        "gpu" => open().with_context(|| format!("{flag}backend gpu"))?,
        "auto" => match open() {
            Ok(g) if g.info.device_type != wgpu::DeviceType::Cpu => g,
            _ => return Ok(None),
        },
        b => bail!("{flag}backend: expected cpu, gpu or auto, found {b:?}"),
    };
    Ok(Some(FilterKernels::new(Arc::new(gpu))))
}

fn check_name(name: &str, flag: &str) -> Result<()> {
    if name.is_empty()
        || name.starts_with('.')
        || name.contains(['/', '\\'])
        || name.ends_with(".partial")
    {
        bail!("{flag}out: expected a plain name (no '/', not starting with '.'), found {name:?}");
    }
    // (A line break would split `info`'s report; 255 bytes is what file
    // systems take, less the staging names' additions.)
    if name.chars().any(char::is_control) || name.len() > 200 {
        bail!(
            "{flag}out: expected a name of at most 200 bytes without control characters, found {name:?}"
        );
    }
    // The group's own metadata lives beside the results.
    if name.eq_ignore_ascii_case("zarr.json") {
        bail!("{flag}out: {name:?} is the name of the group's metadata; choose another name");
    }
    Ok(())
}

/// Names of the directories a run of `name` uses in `dir`.
struct Paths {
    dir: PathBuf,
    name: String,
    fin: PathBuf,
    staged: PathBuf,
    partial: PathBuf,
    old: PathBuf,
    lock: PathBuf,
}

impl Paths {
    fn new(dir: PathBuf, name: &str) -> Paths {
        Paths {
            fin: dir.join(name),
            staged: dir.join(format!(".{name}.new")),
            partial: dir.join(format!(".{name}.new.partial")),
            old: dir.join(format!(".{name}.old")),
            lock: dir.join(format!(".{name}.lock")),
            dir,
            name: name.to_string(),
        }
    }

    /// Undo what an interrupted run left: a replaced result that was not
    /// yet swapped back comes back; unpublished results go.
    fn recover(&self) -> Result<()> {
        if self.old.exists() {
            if !self.old.is_dir() {
                // (Not a result: an earlier version moved a file of the
                // user's here when asked to overwrite it.)
                bail!(
                    "{}: not a result (a file): move it back to {} or remove it yourself",
                    self.old.display(),
                    self.fin.display()
                );
            }
            if self.fin.exists() {
                note(&format!(
                    "removing {} (left by an interrupted run)",
                    self.old.display()
                ));
                std::fs::remove_dir_all(&self.old)
                    .with_context(|| format!("{}: cannot remove", self.old.display()))?;
            } else {
                note(&format!(
                    "restoring {} from {} (an interrupted run was replacing it)",
                    self.fin.display(),
                    self.old.display()
                ));
                std::fs::rename(&self.old, &self.fin)
                    .with_context(|| format!("{}: cannot restore", self.fin.display()))?;
            }
        }
        for p in [&self.partial, &self.staged] {
            if p.exists() {
                note(&format!(
                    "removing {} (left by an interrupted run; the job starts again from the beginning)",
                    p.display()
                ));
                match std::fs::remove_dir_all(p) {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                        return Err(e).with_context(|| format!("{}: cannot remove", p.display()))
                    }
                    _ => {}
                }
            }
        }
        Ok(())
    }
}

fn note(s: &str) {
    eprintln!("note: {s}");
}

/// The `labels` group's list of label images.
fn labels_list(dir: &Path) -> Result<(Value, Vec<String>)> {
    let f = dir.join("zarr.json");
    if !f.exists() {
        return Ok((
            json!({"zarr_format": 3, "node_type": "group",
                   "attributes": {"ome": {"version": "0.5", "labels": []}}}),
            vec![],
        ));
    }
    let j = read_json(&f)?;
    if j.get("node_type").and_then(Value::as_str) != Some("group") {
        bail!(
            "{}: node_type: expected \"group\" (the labels group)",
            f.display()
        );
    }
    let list = match j.pointer("/attributes/ome/labels") {
        None => vec![],
        Some(Value::Array(a)) => a
            .iter()
            .map(|v| {
                v.as_str().map(str::to_string).with_context(|| {
                    format!(
                        "{}: attributes.ome.labels: expected names, found {v}",
                        f.display()
                    )
                })
            })
            .collect::<Result<_>>()?,
        Some(v) => bail!(
            "{}: attributes.ome.labels: expected a list of names, found {v}",
            f.display()
        ),
    };
    Ok((j, list))
}

/// Change the `labels` group's list in `dir` with `edit` (which says
/// whether it changed it): read anew and written under the group's lock,
/// so that jobs publishing other names at the same time keep each other's
/// entries.
fn edit_labels(dir: &Path, edit: impl FnOnce(&mut Vec<String>) -> bool) -> Result<()> {
    let _lock = PidLock::wait(
        &dir.join(".zarr.json.lock"),
        "updating the list of label images",
        std::time::Duration::from_secs(60),
    )?;
    let (mut j, mut list) = labels_list(dir)?;
    if edit(&mut list) {
        j["attributes"]["ome"]["version"] = json!("0.5");
        j["attributes"]["ome"]["labels"] = json!(list);
        write_json(&dir.join("zarr.json"), &j)?;
    }
    Ok(())
}

/// Add `name` to the `labels` group's list in `dir`.
fn add_label(dir: &Path, name: &str) -> Result<()> {
    edit_labels(dir, |list| {
        let new = !list.iter().any(|n| n == name);
        if new {
            list.push(name.to_string());
        }
        new
    })
}

/// Take `name` off the `labels` group's list in `dir` (a result that could
/// not be put in place after it was named).
fn remove_label(dir: &Path, name: &str) -> Result<()> {
    edit_labels(dir, |list| {
        let had = list.iter().any(|n| n == name);
        list.retain(|n| n != name);
        had
    })
}

/// The `labels` group `output` lies in when it is `IMAGE/labels/NAME` of
/// an OME-Zarr image (its `zarr.json` has `multiscales`): where a label
/// image converted from a file is published as `process` publishes its.
pub fn label_group_of(output: &Path) -> Option<PathBuf> {
    let group = output
        .parent()
        .filter(|p| p.file_name().is_some_and(|n| n == "labels"))?;
    let image = group.parent()?;
    let j = read_json(&image.join("zarr.json")).ok()?;
    j.pointer("/attributes/ome/multiscales")?;
    Some(group.to_path_buf())
}

/// Mark the label image at `output` as its image's (`image-label`, source
/// `../../`) and list it in `group` (`labels/zarr.json`, under the
/// group's lock).
pub fn publish_label_image(group: &Path, output: &Path) -> Result<()> {
    let meta = output.join("zarr.json");
    let mut j = read_json(&meta)?;
    j["attributes"]["ome"]["image-label"] =
        json!({"version": "0.5", "source": {"image": "../../"}});
    write_json(&meta, &j)?;
    let name = output
        .file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("{}: a label image needs a UTF-8 name", output.display()))?;
    add_label(group, name)
}

/// The least `--memory` a job takes whose filters hold `filters` bytes
/// (one block at a time per stage) and whose result's pyramid writer needs
/// `writer`: the filters get at most half of it, the input's chunk cache
/// an eighth, and the writer what is left.
fn least_memory(filters: u64, writer: u64) -> u64 {
    let fits = |m: u64| m / 2 >= filters && m - m / 8 >= writer.saturating_add(filters);
    let start = (1u64 << 20).max(filters.saturating_mul(2));
    brickyard_store::builder::least_budget(start, fits).max(1 << 20)
}

/// What a threshold or window keeps, said where a mask came out empty or
/// full (most likely a threshold in the wrong units).
const MASK_UNITS: &str = "threshold(t) keeps values above t and window(lo,hi) values from lo to \
    hi, in the image's own values (`brickyard info` shows them)";

/// The writing phase's progress: the bytes the writer has read, or,
/// where further on, what the last filter stage has computed since the
/// phase began (`meter`, in voxels of `per_voxel` bytes of the writer's
/// input): the writer reads a slab of whole planes at a time, which a slow
/// filter takes minutes over, and the bar moves meanwhile.
struct Metered<'a> {
    inner: &'a dyn Progress,
    meter: &'a AtomicU64,
    per_voxel: u64,
    s: std::sync::Mutex<MeterState>,
}

#[derive(Default)]
struct MeterState {
    on: bool,
    /// The meter when the phase began (a labelling's first pass counted
    /// before it).
    base: u64,
    total: u64,
    read: u64,
    shown: u64,
}

impl Metered<'_> {
    fn show(&self, s: &mut MeterState) {
        if !s.on {
            return;
        }
        let computed = self.meter.load(Ordering::Relaxed).saturating_sub(s.base) * self.per_voxel;
        let t = s.read.max(computed).min(s.total);
        if t > s.shown {
            self.inner.inc(t - s.shown);
            s.shown = t;
        }
    }

    fn tick(&self) {
        let mut s = self.s.lock().unwrap();
        self.show(&mut s);
    }
}

impl Progress for Metered<'_> {
    fn start(&self, total: u64) {
        let mut s = self.s.lock().unwrap();
        self.inner.start(total);
        *s = MeterState {
            on: true,
            base: self.meter.load(Ordering::Relaxed),
            total,
            read: 0,
            shown: 0,
        };
    }

    fn inc(&self, bytes: u64) {
        let mut s = self.s.lock().unwrap();
        s.read += bytes;
        self.show(&mut s);
    }

    fn message(&self, msg: &str) {
        self.inner.message(msg)
    }
}

/// Run the pipeline and publish its result; `cancel` stops the job between
/// pieces of work, leaving the store as it was (the error is then
/// [`Interrupted`] with what to do in its context).
pub fn run(
    c: &ProcessArgs,
    caller: &Caller,
    phases: &dyn Phases,
    cancel: &AtomicBool,
) -> Result<ProcessReport> {
    // The filter stages stop between their blocks (a region of a slow
    // filter takes many seconds: median(3) of a 64 × 512² volume took 28 s
    // in one region): `cancel` is mirrored into the flag they hold while
    // the job runs.
    let stop = Arc::new(AtomicBool::new(false));
    let done = AtomicBool::new(false);
    std::thread::scope(|s| {
        s.spawn(|| {
            while !done.load(Ordering::SeqCst) {
                if cancel.load(Ordering::SeqCst) {
                    stop.store(true, Ordering::SeqCst);
                    break;
                }
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
        });
        let r = run_job(c, caller, phases, cancel, &stop);
        done.store(true, Ordering::SeqCst);
        r
    })
}

fn run_job(
    c: &ProcessArgs,
    caller: &Caller,
    phases: &dyn Phases,
    cancel: &AtomicBool,
    stop: &Arc<AtomicBool>,
) -> Result<ProcessReport> {
    let f = caller.flag;
    let t0 = Instant::now();
    let pipe = parse(&c.pipeline)?;
    check_name(&c.out, f)?;
    let memory = c.memory;
    // (A budget too small for the job is refused below, with the least
    // that runs it: saying "at least 1 MiB" first only took a second try.)
    if memory == 0 {
        bail!("{f}memory: expected a size above 0 (e.g. 1GiB)");
    }
    if c.stats.is_some() && !matches!(pipe.ops.last(), Some(Op::Label(_))) {
        bail!("{f}stats: only a pipeline that ends in label(...) has per-label statistics");
    }
    let stats_fmt = match &c.stats {
        None => None,
        Some(p) => match p.extension().and_then(|e| e.to_str()) {
            Some("csv") => Some(false),
            Some("json") => Some(true),
            _ => bail!(
                "{f}stats: expected a file name ending in .csv or .json, found {}",
                p.display()
            ),
        },
    };
    // The statistics file is written last: a folder that is not there
    // fails now, before any work.
    if let Some(p) = &c.stats {
        brickyard_store::builder::check_parent(p).map_err(|e| anyhow::anyhow!("{f}stats: {e}"))?;
        // Never into the store (its metadata, a chunk): it holds the
        // statistics already. Never over a file unasked.
        let inside = |p: &std::path::Path| {
            let parent = p
                .parent()
                .filter(|d| !d.as_os_str().is_empty())
                .unwrap_or(std::path::Path::new("."));
            match (parent.canonicalize(), c.store.canonicalize()) {
                (Ok(d), Ok(s)) => d.starts_with(s),
                _ => false,
            }
        };
        if !brickyard_store::storage::is_remote(&c.store) && inside(p) {
            bail!(
                "{f}stats: {} lies inside the store {}; the statistics are stored in the label \
                 image already (_brickyard/labels.csv and labels.json): name a file outside it",
                p.display(),
                c.store.display()
            );
        }
        if p.is_dir() {
            bail!("{f}stats: {} is a folder", p.display());
        }
        if p.exists() && !c.overwrite {
            bail!(
                "{f}stats: {} exists; {} to replace it",
                p.display(),
                caller.overwrite
            );
        }
        // Its folder must take a new file (read-only, a file system that
        // takes none): found now, not after the whole computation.
        if let Err((dir, e)) = crate::can_create_beside(p) {
            bail!(
                "{f}stats: {}: cannot create a file in its folder {} ({e}); expected a folder \
                 where files can be written",
                p.display(),
                dir.display()
            );
        }
    }
    let store = &c.store;
    if brickyard_store::storage::is_remote(store) {
        bail!(
            "{}: a remote store is read-only, and `process` writes its result into the store; {}",
            store.display(),
            caller.remote
        );
    }
    if !store.exists() {
        return Err(brickyard_store::StoreError::not_found(store).into());
    }
    if !zarr::is_zarr(store) {
        bail!(
            "{}: not a Zarr store (no zarr.json); convert the volume first with {}",
            store.display(),
            caller.convert
        );
    }
    // Results are OME-Zarr 0.5 groups (Zarr v3): inside a Zarr v2 store
    // (OME-Zarr 0.4) its readers would not find them.
    if !store.join("zarr.json").exists()
        && (store.join(".zgroup").exists() || store.join(".zattrs").exists())
    {
        bail!(
            "{}: a Zarr v2 store (OME-Zarr 0.4, .zgroup/.zattrs); `process` writes its results \
             into the store as OME-Zarr 0.5 (Zarr v3) groups, which readers of a v2 store do \
             not find: convert it first with {} and process the copy",
            store.display(),
            caller.convert
        );
    }
    // An interrupted conversion's store is refused, as `render` does.
    if let Some(why) = brickyard_store::info::inspect(store)?.incomplete {
        bail!(
            "{}: the store is incomplete: {why}; convert the volume again with {}",
            store.display(),
            caller.convert
        );
    }
    let mut src = zarr::open(store, c.level)?;
    // Lost chunks (a shard removed) fail the run instead of reading as
    // zeros.
    src.check_against_stats();
    let ms = src.multiscale.clone().with_context(|| {
        format!(
            "{}: expected an OME-Zarr multiscale image (a store written by `brickyard convert`), found a bare array",
            store.display()
        )
    })?;
    // A label image's values are names: filters that mix them are said
    // in the report (the job runs: a user may mean it).
    let ids_note = match ms.label_image {
        true => pipe.label_ids_note(&store.display().to_string()),
        false => None,
    };
    let brick: [u64; 3] = ms
        .brickyard
        .as_ref()
        .and_then(|b| b.get("brick"))
        .and_then(|b| serde_json::from_value(b.clone()).ok())
        .filter(|b: &[u64; 3]| b.iter().all(|&v| v >= 2 && v % 2 == 0))
        .unwrap_or([64; 3]);
    // The device back end's driver (on a software adapter also its
    // memory) is in --memory, as for render: the job takes the rest. It
    // went past --memory by the driver's share (333 MiB at 200 MiB).
    let kernels = device(&c.backend, f)?;
    let device_bytes = kernels.as_ref().map_or(0, |k| match k.gpu.is_software() {
        true => crate::memory::SOFTWARE_DEVICE_BYTES,
        false => crate::memory::DEVICE_BYTES,
    });
    let (kernels, device_bytes) = match (kernels, memory >= device_bytes + (1 << 20)) {
        (k, true) => (k, device_bytes),
        // The CPU: a budget too small is refused below, with a figure.
        (None, false) => (None, 0),
        (Some(_), false) if c.backend == "auto" => {
            if !c.quiet {
                crate::outln!(
                    "note: {f}memory {} leaves no room for the device's driver (about {}): {f}backend auto takes the CPU",
                    human_bytes(memory),
                    human_bytes(device_bytes)
                );
            }
            (None, 0)
        }
        (_, false) => bail!(
            "{f}memory: {} does not hold the device back end's {} for its driver: give more, or {f}backend cpu (which does without)",
            human_bytes(memory),
            human_bytes(device_bytes)
        ),
    };
    let memory = memory - device_bytes;
    src.enable_chunk_cache(memory / 8);
    let meta = src.meta().clone();
    if c.channel >= meta.channels {
        bail!(
            "{f}channel: {} asked for but {} has {} channel(s)",
            c.channel,
            store.display(),
            meta.channels
        );
    }
    let input: Arc<ZarrSource> = Arc::new(src);
    let on = kernels.as_ref().map(|k| k.gpu.describe());
    let is_label = pipe.is_label_output();
    let mut opts = ConvertOptions {
        brick,
        shard: brick.map(brickyard_store::builder::default_shard),
        compression: Compression::Lz4,
        labels: is_label,
        memory: 0,
        overwrite: false,
        spacing: meta.spacing,
        origin: meta.origin,
        unit: meta.unit.clone(),
        columns: 1,
    };
    // --memory: an eighth for the input's chunk cache; the filter stages'
    // blocks (with their halos) a quarter, or half when one block at a
    // time needs more, but never what the pyramid writer needs; the
    // writer the rest. Checked before anything is written.
    let threads = rayon::current_num_threads();
    // The voxels the last filter stage has computed: the writing phase's
    // progress between the writer's reads (a region of a slow filter takes
    // minutes).
    let meter = Arc::new(AtomicU64::new(0));
    let build = |share: u64| {
        build_within(
            &pipe,
            input.clone(),
            c.channel,
            brick,
            kernels.as_ref(),
            share,
            threads,
            brickyard_process::Hooks {
                stop: Some(stop.clone()),
                meter: Some(meter.clone()),
            },
        )
    };
    // (A σ that cannot be computed fails here, whatever the budget.)
    let (filters_least, result) =
        brickyard_process::plan_result(&pipe, input.clone(), c.channel, brick)
            .map_err(|e| anyhow::anyhow!("pipeline {:?}: {e}", c.pipeline))?;
    let writer_least = brickyard_store::builder::memory_needed(&result, &opts);
    let least = least_memory(filters_least, writer_least);
    if memory < least {
        let sigma = pipe
            .ops
            .iter()
            .any(|o| matches!(o, Op::Gauss(_) | Op::GradMag(_)));
        // How the caller gives a size: `--memory 56MiB`, `memory="56MiB"`.
        let least_mib = (least + device_bytes).div_ceil(1 << 20);
        let give = match f {
            "" => format!("memory=\"{least_mib}MiB\""),
            _ => format!("{f}memory {least_mib}MiB"),
        };
        bail!(
            "{f}memory: {} is too small for {:?} on level {} of {}: give {give} or \
             more (the filters hold {} at once, one block with its halo per stage, and take \
             at most half of {f}memory; writing the result's pyramid takes {}, and reading the \
             input an eighth of {f}memory){}{}",
            human_bytes(c.memory),
            pipe.text(),
            c.level,
            store.display(),
            human_bytes(filters_least),
            human_bytes(writer_least),
            if sigma {
                "; a smaller σ needs less"
            } else {
                ""
            },
            match device_bytes {
                0 => String::new(),
                d => format!(
                    "; the device back end takes {} of it for its driver ({f}backend cpu does without)",
                    human_bytes(d)
                ),
            }
        );
    }
    let left = memory - memory / 8 - writer_least;
    let (built, filter_memory) = build((memory / 4).min(left))
        .or_else(|_| build((memory / 2).min(left)))
        .map_err(|e| anyhow::anyhow!("pipeline {:?}: {e}", c.pipeline))?;
    opts.memory = memory - memory / 8 - filter_memory.bytes;
    let dir = store.join(if is_label { "labels" } else { "derived" });
    // One name, one result: the same name under the other folder would
    // make `info`, `render --labels NAME` and `--derived NAME` ambiguous.
    let other = store
        .join(if is_label { "derived" } else { "labels" })
        .join(&c.out);
    let paths = Paths::new(dir, &c.out);
    if paths.dir.exists() && !paths.dir.is_dir() {
        bail!(
            "{}: a file, where results are written into a folder of this name; move the file \
             out of the store",
            paths.dir.display()
        );
    }
    let made_dir = !paths.dir.exists();
    std::fs::create_dir_all(&paths.dir)
        .with_context(|| format!("{}: cannot create", paths.dir.display()))?;
    let _lock = match PidLock::take(&paths.lock, &format!("writing {}", c.out)) {
        Ok(l) => l,
        Err(e) => {
            if made_dir {
                let _ = std::fs::remove_dir(&paths.dir);
            }
            return Err(e.into());
        }
    };
    let leave = |e: anyhow::Error| -> anyhow::Error {
        if made_dir {
            let _ = std::fs::remove_file(&paths.lock);
            let _ = std::fs::remove_dir(&paths.dir);
        }
        e
    };
    // A job writing this name as the other kind (a label image beside a
    // derived result, or the other way round) would publish the second
    // of one name: refused while it is at work; before publishing, the
    // first published holds the name (two started at once: the second
    // to end is refused).
    let other_kind = |what: &str, at_work: bool| -> Option<anyhow::Error> {
        let lock = other.with_file_name(format!(".{}.lock", c.out));
        if other.exists() {
            return Some(anyhow::anyhow!(
                "{}: a result of this name is there already ({}); give another {}out",
                other.display(),
                what,
                caller.flag
            ));
        }
        if !at_work {
            return None;
        }
        brickyard_store::lock::live_holder(&lock).map(|pid| {
            anyhow::anyhow!(
                "{}: another process (pid {pid}) is writing a result of this name ({}); give \
                 another {}out, or wait for it to end",
                other.display(),
                what,
                caller.flag
            )
        })
    };
    let other_what = if is_label {
        "not a label image: derived"
    } else {
        "a label image"
    };
    if let Some(e) = other_kind(other_what, true) {
        return Err(leave(e));
    }
    paths.recover().map_err(leave)?;
    if paths.fin.exists() && !c.overwrite {
        return Err(leave(anyhow::anyhow!(
            "{}: exists; {} to replace it",
            paths.fin.display(),
            caller.overwrite
        )));
    }
    // --overwrite replaces a result, never what is not one (a folder of
    // the user's, a file), nor what a result holds that the job does not
    // make again (results made from it).
    if paths.fin.exists() {
        if !brickyard_store::builder::replaceable(&paths.fin) {
            return Err(leave(anyhow::anyhow!(
                "{}: exists and is not a result ({}): {}overwrite replaces results only; \
                 remove it yourself or give another {}out",
                paths.fin.display(),
                if paths.fin.is_dir() {
                    "a folder with no zarr.json in it"
                } else {
                    "a file"
                },
                caller.flag,
                caller.flag
            )));
        }
        let lost = brickyard_store::builder::not_remade(&paths.fin);
        if !lost.is_empty() {
            return Err(leave(anyhow::anyhow!(
                "{}: {}overwrite would delete what the job does not make again: {}; move it \
                 out first, or give another {}out",
                paths.fin.display(),
                caller.flag,
                lost.join(", "),
                caller.flag
            )));
        }
    }
    // A damaged list of label images is refused before any work (it is
    // read again, under its lock, when the result is added to it).
    if is_label {
        labels_list(&paths.dir).map_err(leave)?;
    }
    if let (Some(d), false) = (&on, c.quiet) {
        eprintln!("filter stages on the GPU: {d}");
    }
    let cleanup = |e: anyhow::Error| -> anyhow::Error {
        let _ = std::fs::remove_dir_all(&paths.partial);
        let _ = std::fs::remove_dir_all(&paths.staged);
        if made_dir {
            let _ = std::fs::remove_file(&paths.lock);
            let _ = std::fs::remove_dir(&paths.dir);
        }
        if cancel.load(Ordering::SeqCst) {
            anyhow::Error::new(Interrupted).context(format!(
                "{} is as it was (nothing was published); run the same {} again to start over",
                store.display(),
                caller.again
            ))
        } else {
            e
        }
    };
    let mut labeling = None;
    // What the report says of a mask that came out empty or full (most
    // likely a threshold in the wrong units).
    let mask_note = std::sync::Mutex::new(None::<String>);
    let say = |n: String| {
        *mask_note
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some(n)
    };
    let report = (|| -> Result<brickyard_store::ConvertReport> {
        let out_src: Arc<dyn VolumeSource> = match built.label {
            Some(conn) => {
                let inten: &dyn VolumeSource = input.as_ref();
                // The writer's share is idle during the labelling pass:
                // its bookkeeping may use it.
                let lab = label_pass1_within(
                    built.source.as_ref(),
                    built.channel,
                    conn,
                    brick,
                    Some((inten, c.channel)),
                    phases.labelling(),
                    cancel,
                    opts.memory,
                );
                phases.done(true);
                let lab = lab?;
                if cancel.load(Ordering::SeqCst) {
                    return Err(StoreError::Interrupted.into());
                }
                // What the labelling keeps stays beside the writer: its
                // share shrinks by that much.
                let kept = lab.bytes();
                if opts.memory.saturating_sub(kept) < writer_least {
                    // The writer's share grows by at least 5/8 of what is
                    // added to --memory (the input's eighth and the
                    // filters' quarter take the rest): that much more.
                    let short = writer_least + kept - opts.memory;
                    let mib = (c.memory + short * 8 / 5).div_ceil(1 << 20);
                    let give = match f {
                        "" => format!("memory=\"{mib}MiB\""),
                        _ => format!("{f}memory {mib}MiB"),
                    };
                    bail!(
                        "{f}memory: {} labels ({} of statistics and maps, kept while the result \
                         is written) leave the writer less than the {} it needs within {}: give \
                         {give} or more",
                        lab.count(),
                        human_bytes(kept),
                        human_bytes(writer_least),
                        human_bytes(c.memory)
                    );
                }
                opts.memory -= kept;
                // A threshold in the wrong units leaves nothing, or
                // everything, in the foreground: say so (the job is not
                // wrong, but hardly what was meant).
                let voxels: u64 = lab.dims.iter().product();
                if lab.count() == 0 {
                    say(format!(
                        "no voxel is in the mask, so there are no labels: {MASK_UNITS}"
                    ));
                } else if lab.count() == 1 && lab.stats[0].voxels == voxels {
                    say(format!(
                        "every voxel is in the mask, one label covers the volume: {MASK_UNITS}"
                    ));
                }
                let lab = Arc::new(lab);
                labeling = Some(lab.clone());
                Arc::new(LabelSource::new(built.source.clone(), built.channel, lab))
            }
            None => built.source.clone(),
        };
        let writing = Metered {
            inner: phases.writing(),
            meter: &meter,
            per_voxel: out_src.meta().dtype.size() as u64,
            s: Default::default(),
        };
        // The meter is shown every 100 ms until the writer ends (the
        // sender dropped).
        let (ended, ticks) = std::sync::mpsc::channel::<()>();
        let r = std::thread::scope(|sc| {
            let shown = &writing;
            sc.spawn(move || {
                use std::sync::mpsc::RecvTimeoutError::Timeout;
                while let Err(Timeout) = ticks.recv_timeout(std::time::Duration::from_millis(100)) {
                    shown.tick();
                }
            });
            let r = convert(out_src.as_ref(), &paths.staged, &opts, &writing, cancel);
            drop(ended);
            r
        });
        phases.done(false);
        let r = r?;
        if cancel.load(Ordering::SeqCst) {
            return Err(StoreError::Interrupted.into());
        }
        // A mask (no labelling) that came out empty: most likely a
        // threshold in the wrong units, as the labelling's note says.
        if is_label && labeling.is_none() && r.bricks_empty == r.bricks {
            say(format!(
                "no voxel is in the mask ({}): {MASK_UNITS}",
                pipe.text()
            ));
        }
        Ok(r)
    })()
    .map_err(cleanup)?;

    // Describe the result, store the statistics, then publish.
    let root = paths.staged.join("zarr.json");
    let mut j = read_json(&root).map_err(|e| cleanup(e.into()))?;
    let attrs = j["attributes"].as_object_mut().context("attributes")?;
    let origin = json!({
        "pipeline": pipe.text(),
        "input": store.to_string_lossy(),
        "level": c.level,
        "channel": c.channel,
        "boundary_mode": "nearest",
        "truncate": brickyard_process::filter::TRUNCATE,
    });
    if let Some(b) = attrs.get_mut(brickyard_store::omezarr::ATTR) {
        b["process"] = origin;
        b["source"] = json!(store.to_string_lossy());
    }
    if is_label {
        attrs["ome"]["image-label"] = json!({"version": "0.5", "source": {"image": "../../"}});
    } else if let Some(ch) = attrs
        .get_mut("ome")
        .and_then(|o| o.get_mut("omero"))
        .and_then(|o| o.get_mut("channels"))
        .and_then(|c| c.get_mut(0))
    {
        // The result's one channel is named as the result (it was
        // "channel 0", whichever channel it came from).
        ch["label"] = json!(paths.name);
    }
    write_json(&root, &j).map_err(|e| cleanup(e.into()))?;
    if let Some(lab) = &labeling {
        let extra = [
            (
                "pipeline",
                brickyard_process::label::json_string(&pipe.text()),
            ),
            ("level", c.level.to_string()),
            ("intensity_channel", c.channel.to_string()),
        ];
        let dirs = paths.staged.join("_brickyard");
        // Streamed to the files (millions of labels: hundreds of MB).
        let to = |p: std::path::PathBuf,
                  f: &dyn Fn(&mut dyn std::io::Write) -> std::io::Result<()>| {
            let mut w = std::io::BufWriter::new(std::fs::File::create(p)?);
            f(&mut w)?;
            std::io::Write::flush(&mut w)
        };
        to(dirs.join("labels.csv"), &|w| write_stats_csv(w, &lab.stats))
            .and_then(|_| {
                to(dirs.join("labels.json"), &|w| {
                    write_stats_json(w, lab, &extra)
                })
            })
            .with_context(|| format!("{}: cannot write statistics", dirs.display()))
            .map_err(cleanup)?;
        if cancel.load(Ordering::SeqCst) {
            return Err(cleanup(StoreError::Interrupted.into()));
        }
        if let (Some(p), Some(is_json)) = (&c.stats, stats_fmt) {
            // Whole or not at all (written beside it, then renamed), as
            // the images `render` writes.
            let write: &dyn Fn(&mut dyn std::io::Write) -> std::io::Result<()> = if is_json {
                &|w| write_stats_json(w, lab, &extra)
            } else {
                &|w| write_stats_csv(w, &lab.stats)
            };
            brickyard_render::image::write_whole(p, write)
                .with_context(|| format!("{}: cannot write", p.display()))?;
        }
    }
    // The last moment a Ctrl-C leaves the store as it was.
    if cancel.load(Ordering::SeqCst) {
        return Err(cleanup(StoreError::Interrupted.into()));
    }
    // (The other kind of result may have come meanwhile: see above.)
    if let Some(e) = other_kind(other_what, false) {
        return Err(cleanup(e));
    }
    // The group names the result before it is put in place: a write that
    // fails here (a full disk) leaves the store as it was, and a result in
    // place is always named (one put in place first and then left unnamed
    // was listed by `info` but unknown to `render --labels`).
    let named_before =
        is_label && labels_list(&paths.dir).is_ok_and(|(_, l)| l.contains(&paths.name));
    if is_label {
        add_label(&paths.dir, &paths.name).map_err(cleanup)?;
    } else {
        let g = paths.dir.join("zarr.json");
        if !g.exists() {
            write_json(
                &g,
                &json!({"zarr_format": 3, "node_type": "group", "attributes": {}}),
            )
            .map_err(|e| cleanup(e.into()))?;
        }
    }
    // A failure to put it in place takes back the name it had not before.
    let unname = |e: anyhow::Error| -> anyhow::Error {
        if is_label && !named_before && !paths.fin.exists() {
            let _ = remove_label(&paths.dir, &paths.name);
        }
        e
    };
    if paths.fin.exists() {
        std::fs::rename(&paths.fin, &paths.old)
            .with_context(|| format!("{}: cannot move aside", paths.fin.display()))
            .map_err(cleanup)?;
        if let Err(e) = std::fs::rename(&paths.staged, &paths.fin) {
            // The old result back in its place.
            let _ = std::fs::rename(&paths.old, &paths.fin);
            return Err(cleanup(
                anyhow::Error::new(e).context(format!("{}: cannot publish", paths.fin.display())),
            ));
        }
        std::fs::remove_dir_all(&paths.old)
            .with_context(|| format!("{}: cannot remove", paths.old.display()))?;
    } else {
        std::fs::rename(&paths.staged, &paths.fin)
            .with_context(|| format!("{}: cannot publish", paths.fin.display()))
            .map_err(|e| unname(cleanup(e)))?;
    }
    Ok(ProcessReport {
        output: paths.fin.clone(),
        labels: labeling.as_ref().map(|l| l.count()),
        pipeline: pipe.text(),
        levels: report.levels.len(),
        dtype: report.dtype,
        bytes_written: report.bytes_written,
        device: on,
        seconds: t0.elapsed().as_secs_f64(),
        // Label images are drawn over their image (render --labels) on
        // its grid only; one made from a coarser level is drawn alone.
        notes: [
            ids_note,
            mask_note
                .into_inner()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
            (is_label && c.level > 0).then(|| {
                format!(
                    "it lies on level {}'s grid, not the image's: render --labels draws label \
                     images over the image on its own grid only; draw it alone with brickyard \
                     render {}",
                    c.level,
                    paths.fin.display()
                )
            }),
        ]
        .into_iter()
        .flatten()
        .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    /// A progress that records each step it is given.
    #[derive(Default)]
    struct Steps(Mutex<Vec<u64>>);
    impl Progress for Steps {
        fn start(&self, total: u64) {
            self.0.lock().unwrap().push(total + 1_000_000);
        }
        fn inc(&self, b: u64) {
            self.0.lock().unwrap().push(b);
        }
    }

    /// The writing bar moves with the filter's meter between the writer's
    /// reads, never backwards, never past its total, and ends at the
    /// writer's count; what the meter counted before the phase (a
    /// labelling's first pass) is not shown.
    #[test]
    fn the_writing_bar_moves_with_the_filters_meter() {
        let meter = AtomicU64::new(500);
        let steps = Steps::default();
        let m = Metered {
            inner: &steps,
            meter: &meter,
            per_voxel: 4,
            s: Default::default(),
        };
        m.tick(); // before the phase: nothing
        m.start(4000);
        m.tick(); // nothing computed since the start
        meter.fetch_add(100, Ordering::Relaxed); // 400 bytes computed
        m.tick();
        m.inc(256); // the writer read less than was computed: no step
        m.inc(256); // now more: the excess
        meter.fetch_add(2000, Ordering::Relaxed); // past the total: capped
        m.tick();
        m.tick();
        m.inc(4000 - 512); // the writer's count ends at the total
        let s = steps.0.lock().unwrap().clone();
        assert_eq!(s, vec![1_004_000, 400, 112, 3488]);
        assert_eq!(s[1..].iter().sum::<u64>(), 4000);
    }
}
