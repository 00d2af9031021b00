//! The extension module `brickyard._native`: a store read through the
//! loader and host cache, renders as `brickyard render` draws them, and
//! conversions through the pyramid builder, pipelines as `brickyard process`
//! runs them. The Python package `brickyard`
//! (`python/brickyard/__init__.py`) turns its bytes into NumPy arrays and its
//! arguments into the CLI's; the GIL is released while work runs.

mod read;
mod source;

use brickyard_cache::host_cache::HostCache;
use brickyard_cache::loader::Loader;
use brickyard_store::builder::Progress;
use brickyard_store::import::{open_input, ImportOptions};
use brickyard_store::info::inspect;
use brickyard_store::{Compression, ConvertOptions, VolumeSource};
use pyo3::exceptions::{PyFileNotFoundError, PyKeyboardInterrupt, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyByteArray;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// A long call stopped by Ctrl-C (a signal seen between two pieces of
/// work): the same marker as a processing job's.
pub use brickyard_run::process::Interrupted;

/// An error as a Python exception, with the CLI's message: a missing file
/// is a `FileNotFoundError`, other I/O failures `OSError`, an interrupted
/// call `KeyboardInterrupt`, everything else (bad arguments, bad stores) a
/// `ValueError`.
fn to_py(e: anyhow::Error) -> PyErr {
    let msg = format!("{e:#}");
    for cause in e.chain() {
        if cause.downcast_ref::<Interrupted>().is_some() {
            return PyKeyboardInterrupt::new_err(msg);
        }
        let io =
            cause.downcast_ref::<std::io::Error>().or_else(|| {
                match cause.downcast_ref::<brickyard_store::StoreError>() {
                    Some(brickyard_store::StoreError::Io { error, .. }) => Some(error),
                    _ => None,
                }
            });
        if let Some(io) = io {
            return match io.kind() {
                std::io::ErrorKind::NotFound => PyFileNotFoundError::new_err(msg),
                _ => PyOSError::new_err(msg),
            };
        }
    }
    PyValueError::new_err(msg)
}

/// A path that is not there, said as the CLI says it (an unknown URL
/// scheme, an interrupted conversion or processing job named).
fn missing(path: &Path) -> PyErr {
    PyFileNotFoundError::new_err(brickyard_store::StoreError::not_found(path).to_string())
}

/// Whether Ctrl-C was pressed (asks the interpreter, taking the GIL for a
/// moment): long loops call this between pieces of work.
fn interrupted() -> bool {
    Python::attach(|py| py.check_signals().is_err())
}

/// Run `job` on a thread of its own, without the GIL, while this thread
/// watches for Ctrl-C every few milliseconds and sets `cancel` when it
/// comes: the job's own threads are not where Python runs signal
/// handlers, and they may go long between progress reports (a slab of
/// bricks at zstd:19, a median filter's block).
fn watched<R: Send>(
    py: Python<'_>,
    cancel: &AtomicBool,
    what: &str,
    job: impl FnOnce() -> anyhow::Result<R> + Send,
) -> anyhow::Result<R> {
    py.detach(|| {
        std::thread::scope(|s| {
            let job = s.spawn(job);
            while !job.is_finished() {
                std::thread::sleep(std::time::Duration::from_millis(2));
                if interrupted() {
                    cancel.store(true, Ordering::SeqCst);
                }
            }
            job.join()
                .unwrap_or_else(|_| Err(anyhow::anyhow!("{what}: the job panicked")))
        })
    })
}

/// An OME-Zarr store opened for reading: every level through one loader
/// and one byte-bounded host cache.
#[pyclass(module = "brickyard._native", frozen)]
struct NativeStore {
    path: PathBuf,
    loader: Loader,
    /// One read at a time: a read takes what the loader hands out and its
    /// failures, so two at once took each other's bricks (and one then
    /// failed, "never arrived"). Each read keeps the loader's threads busy.
    reads: std::sync::Mutex<()>,
    scales: Vec<Option<Vec<f64>>>,
    translations: Vec<Option<Vec<f64>>>,
    axes: Vec<String>,
    units: Vec<Option<String>>,
    /// One name per channel: the OME `omero` block's labels, else
    /// "channel i" (as the viewer and `info` name them).
    channel_names: Vec<String>,
    /// The root `zarr.json` (or `.zgroup`/`.zarray`) as it was opened (a
    /// local store): a store replaced since (written again with
    /// `overwrite`) is refused, not read half from what this handle
    /// cached and half from the new files.
    identity: Option<brickyard_store::storage::StoreIdentity>,
}

impl NativeStore {
    /// An error when the store was replaced or removed since it was
    /// opened.
    fn check_same(&self) -> PyResult<()> {
        match &self.identity {
            Some(id) => id
                .check()
                .map_err(|m| PyOSError::new_err(format!("{}: {m}", self.path.display()))),
            None => Ok(()),
        }
    }
}

#[pymethods]
impl NativeStore {
    /// An OSError when the store was replaced or removed since it was
    /// opened (what reads refuse).
    fn check(&self) -> PyResult<()> {
        self.check_same()
    }

    #[new]
    #[pyo3(signature = (path, cache_bytes, chunk_bytes, brick, threads))]
    fn new(
        py: Python<'_>,
        path: PathBuf,
        cache_bytes: u64,
        chunk_bytes: u64,
        brick: u64,
        threads: usize,
    ) -> PyResult<Self> {
        // A URL (http:// or https://) is read through the store layer's
        // HTTP client; a missing one is reported by `inspect`.
        if !path.exists() && !brickyard_store::storage::is_remote(&path) {
            return Err(missing(&path));
        }
        // (As `render --brick`: bricks of one voxel read a level a voxel
        // at a time, for minutes.)
        if !(2..=512).contains(&brick) {
            return Err(PyValueError::new_err(format!(
                "brick: expected an edge between 2 and 512 voxels, got {brick}"
            )));
        }
        // Opened on a thread of its own while this one watches for Ctrl-C:
        // a server that takes the connection and never answers holds the
        // open for a minute (its retries). When a signal's handler raises,
        // that exception is raised here at once and the thread is left to
        // end by itself (what it opened is dropped then).
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::Builder::new()
            .name("brickyard-open".into())
            .spawn(move || {
                let _ = tx.send(open_store(path, cache_bytes, chunk_bytes, brick, threads));
            })
            .map_err(|e| PyOSError::new_err(format!("open: cannot start a thread: {e}")))?;
        py.detach(move || loop {
            match rx.recv_timeout(std::time::Duration::from_millis(20)) {
                Ok(r) => return r.map_err(to_py),
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
                    Python::attach(|py| py.check_signals())?
                }
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                    return Err(PyValueError::new_err(
                        "open: the thread opening the store panicked",
                    ))
                }
            }
        })
    }

    #[getter]
    fn path(&self) -> PathBuf {
        self.path.clone()
    }

    /// Level shapes `[z, y, x]`, level 0 first.
    #[getter]
    fn shapes(&self) -> Vec<[u64; 3]> {
        self.loader.geometry().levels.clone()
    }

    #[getter]
    fn channels(&self) -> usize {
        self.loader.geometry().channels
    }

    /// The voxel type as NumPy names it (`uint8`, `float32`, ...).
    #[getter]
    fn dtype(&self) -> &'static str {
        numpy_name(self.loader.geometry().dtype)
    }

    /// Per level, the OME `scale` of every axis (`None` when absent).
    #[getter]
    fn scales(&self) -> Vec<Option<Vec<f64>>> {
        self.scales.clone()
    }

    #[getter]
    fn translations(&self) -> Vec<Option<Vec<f64>>> {
        self.translations.clone()
    }

    #[getter]
    fn axes(&self) -> Vec<String> {
        self.axes.clone()
    }

    #[getter]
    fn units(&self) -> Vec<Option<String>> {
        self.units.clone()
    }

    #[getter]
    fn channel_names(&self) -> Vec<String> {
        self.channel_names.clone()
    }

    /// Host cache: (bytes held, budget, hits, misses).
    fn cache_stats(&self) -> (u64, u64, u64, u64) {
        let c = self.loader.cache();
        (c.bytes(), c.budget(), c.hits(), c.misses())
    }

    /// Bytes of voxel data read from the store so far.
    fn bytes_read(&self) -> u64 {
        self.loader.bytes_read()
    }

    /// The box `lo..hi` (`[z, y, x]`, half open) of one level and channel,
    /// C order, native-endian voxels.
    fn read<'py>(
        &self,
        py: Python<'py>,
        level: usize,
        channel: usize,
        lo: [u64; 3],
        hi: [u64; 3],
    ) -> PyResult<Bound<'py, PyByteArray>> {
        // Checked first (a bad box allocates nothing), then read with the
        // GIL released straight into the bytearray returned (no one else
        // holds it yet).
        let n = read::region_len(&self.loader, level, channel, lo, hi).map_err(to_py)?;
        self.check_same()?;
        PyByteArray::new_with(py, n, |buf| {
            py.detach(|| {
                let _one = self.reads.lock().unwrap_or_else(|e| e.into_inner());
                read::read_region_into(&self.loader, level, channel, lo, hi, &interrupted, buf)
            })
            .map_err(to_py)
        })
    }
}

/// Open a store for [`NativeStore::new`] (without the GIL).
fn open_store(
    path: PathBuf,
    cache_bytes: u64,
    chunk_bytes: u64,
    brick: u64,
    threads: usize,
) -> anyhow::Result<NativeStore> {
    // (A URL with no store behind it: `inspect` says not found.)
    let info = inspect(&path)?;
    if let Some(why) = info.incomplete {
        anyhow::bail!("{}: the store is incomplete: {why}", path.display());
    }
    let identity = brickyard_store::storage::StoreIdentity::of(&path);
    let cache = Arc::new(HostCache::new(cache_bytes));
    let loader =
        Loader::open_with_chunk_cache(&path, [brick; 3], 0, threads.max(1), cache, chunk_bytes)?;
    let omero = brickyard_store::omezarr::read_omero(&path)
        .ok()
        .flatten()
        .unwrap_or_default();
    let channel_names = (0..loader.geometry().channels)
        .map(|i| {
            omero
                .get(i)
                .map_or_else(|| format!("channel {i}"), |c| c.label.clone())
        })
        .collect();
    Ok(NativeStore {
        identity,
        channel_names,
        scales: info.levels.iter().map(|l| l.scale.clone()).collect(),
        translations: info.levels.iter().map(|l| l.translation.clone()).collect(),
        axes: info.axes.clone(),
        units: info.units.clone(),
        path,
        loader,
        reads: std::sync::Mutex::new(()),
    })
}

fn numpy_name(d: brickyard_core::DType) -> &'static str {
    use brickyard_core::DType::*;
    match d {
        U8 => "uint8",
        I8 => "int8",
        U16 => "uint16",
        I16 => "int16",
        U32 => "uint32",
        I32 => "int32",
        F32 => "float32",
        F64 => "float64",
    }
}

/// What [`render`] returns: views, width, height, pixels, notes.
type Rendered<'py> = (usize, u32, u32, Bound<'py, PyByteArray>, Vec<String>);

/// Render exactly as `brickyard render ARGS…` does (the same options, the
/// same code); `args` is the whole command line, starting `brickyard
/// render STORE`. Returns `(views, width, height, pixels, notes)`: every view (a
/// turntable's, in order; else one) one after the other, each RGBA8 over
/// black as the PNG holds it, or the premultiplied RGBA f32 image when
/// `float`. With `write`, each view is also written where and as the CLI
/// writes it (`--out`, or for a turntable `STEM-0000.png`,
/// `STEM-0001.png`, ... beside it). `notes` holds each view's closing
/// line, as the CLI prints it (how the view ended).
#[pyfunction]
#[pyo3(signature = (args, float = false, write = false, threads = None))]
fn render<'py>(
    py: Python<'py>,
    args: Vec<String>,
    float: bool,
    write: bool,
    threads: Option<usize>,
) -> PyResult<Rendered<'py>> {
    let mut cmd = brickyard_run::render::RenderCmd::try_parse_from(&args)
        .map_err(|e| PyValueError::new_err(e.to_string().trim().to_string()))?;
    if !write {
        cmd = cmd.in_memory();
    }
    // Ctrl-C stops the render within a band of tiles of its frame.
    let cancel = std::sync::Arc::new(AtomicBool::new(false));
    cmd = cmd.with_stop(cancel.clone());
    if let Some(store) = args.get(2).map(PathBuf::from) {
        if !store.exists() && !brickyard_store::storage::is_remote(&store) {
            return Err(missing(&store));
        }
    }
    let raw = cmd.raw_f32;
    // `threads`: the render's own pool of that many (as the CLI's --threads).
    let pool = match threads {
        Some(n) => Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| PyOSError::new_err(format!("threads: {e}")))?,
        ),
        None => None,
    };
    let r = watched(py, &cancel, "render", || -> anyhow::Result<_> {
        let (views, notes) = match &pool {
            Some(p) => p.install(|| brickyard_run::render::views_noted(cmd))?,
            None => brickyard_run::render::views_noted(cmd)?,
        };
        if write {
            for (path, img) in &views {
                // A file that cannot be written is an `OSError`.
                brickyard_run::render::write_view(path, img, raw)
                    .map_err(|e| anyhow::Error::new(std::io::Error::other(format!("{e:#}"))))?;
            }
        }
        Ok((
            views.into_iter().map(|(_, img)| img).collect::<Vec<_>>(),
            notes,
        ))
    });
    // (Ctrl-C taken by the watch: raised even where the render had ended.)
    if cancel.load(Ordering::SeqCst) {
        return Err(PyKeyboardInterrupt::new_err("render: interrupted"));
    }
    let (images, notes) = r.map_err(to_py)?;
    let (w, h) = match images.first() {
        Some(img) => (img.width, img.height),
        None => return Err(PyValueError::new_err("render: no view was drawn")),
    };
    let mut bytes = Vec::new();
    for img in &images {
        if float {
            bytes.extend(
                img.rgba
                    .iter()
                    .flat_map(|p| p.iter().flat_map(|v| v.to_ne_bytes())),
            );
        } else {
            bytes.extend(img.to_rgba8([0.0, 0.0, 0.0, 1.0]));
        }
    }
    Ok((images.len(), w, h, PyByteArray::new(py, &bytes), notes))
}

/// The builder's progress, handed to a Python callable `progress(kind,
/// n)` (`kind` "start" with the total bytes, "inc" with bytes done); a
/// Ctrl-C seen here cancels the conversion, and so does an exception the
/// callback raises (kept in `error`, raised when the job has stopped).
struct PyProgress<'a> {
    callback: Option<Py<PyAny>>,
    cancel: &'a AtomicBool,
    /// Named phases of one call (`process`): "start" becomes "start:PHASE".
    phase: Option<&'static str>,
    /// The first exception the callback raised (other than Ctrl-C's).
    error: &'a std::sync::Mutex<Option<PyErr>>,
}

/// The exception a `progress` callback raised, if any, to raise for the
/// job it cancelled (`failed`: the callback's own, not a
/// KeyboardInterrupt). Raised after the job's last piece, the job is
/// done: the exception is shown, not lost.
fn callback_error(
    py: Python<'_>,
    error: &std::sync::Mutex<Option<PyErr>>,
    failed: bool,
) -> PyResult<()> {
    match error.lock().unwrap_or_else(|e| e.into_inner()).take() {
        Some(e) if failed => Err(e),
        Some(e) => {
            e.print(py);
            Ok(())
        }
        None => Ok(()),
    }
}

impl PyProgress<'_> {
    fn call(&self, kind: &str, n: u64) {
        let kind = match (kind, self.phase) {
            ("start", Some(p)) => format!("start:{p}"),
            _ => kind.to_string(),
        };
        Python::attach(|py| {
            if py.check_signals().is_err() {
                self.cancel.store(true, Ordering::Relaxed);
                return;
            }
            if let Some(cb) = &self.callback {
                if let Err(e) = cb.call1(py, (kind.as_str(), n)) {
                    // Ctrl-C that arrived while the callback ran is the
                    // user's: it cancels the job (raised again as the
                    // job's KeyboardInterrupt). Any other exception of the
                    // callback cancels it too (a notebook's or GUI's way
                    // to stop a job), and is the one the job raises.
                    if !e.is_instance_of::<PyKeyboardInterrupt>(py) {
                        let mut slot = self.error.lock().unwrap_or_else(|e| e.into_inner());
                        slot.get_or_insert(e);
                    }
                    self.cancel.store(true, Ordering::Relaxed);
                }
            }
        })
    }
}

impl Progress for PyProgress<'_> {
    fn start(&self, total_bytes: u64) {
        self.call("start", total_bytes)
    }
    fn inc(&self, bytes: u64) {
        self.call("inc", bytes)
    }
}

/// A processing job's two phases, reported to the Python callback.
struct PyPhases<'a> {
    labelling: PyProgress<'a>,
    writing: PyProgress<'a>,
}

impl brickyard_run::process::Phases for PyPhases<'_> {
    fn labelling(&self) -> &dyn Progress {
        &self.labelling
    }
    fn writing(&self) -> &dyn Progress {
        &self.writing
    }
}

/// How `brickyard.process` names things in messages.
const PYTHON: brickyard_run::process::Caller = brickyard_run::process::Caller {
    flag: "",
    convert: "`brickyard.convert`",
    remote: "copy the store first (`brickyard.convert(URL, \"local.zarr\")`)",
    overwrite: "pass overwrite=True",
    again: "call",
};

/// Conversion options as Python gives them.
#[derive(FromPyObject)]
#[pyo3(from_item_all)]
struct PyConvertOptions {
    brick: [u64; 3],
    /// `None`: `convert`'s default for the brick.
    shard: Option<[u64; 3]>,
    compression: String,
    labels: bool,
    memory: u64,
    overwrite: bool,
    spacing: Option<[f64; 3]>,
    origin: Option<[f64; 3]>,
    unit: Option<String>,
    /// One name per channel (checked here against the source's channels;
    /// empty and repeated names refused by the Python side).
    channel_names: Option<Vec<String>>,
}

/// `names`, where given, for a source of `channels` channels: one each.
fn check_name_count(names: &Option<Vec<String>>, channels: usize) -> PyResult<()> {
    match names {
        Some(n) if n.len() != channels => Err(PyValueError::new_err(format!(
            "channel_names: {} name(s) given for {channels} channel(s); expected one per channel",
            n.len()
        ))),
        _ => Ok(()),
    }
}

impl PyConvertOptions {
    fn to_options(&self) -> PyResult<ConvertOptions> {
        // The command line's parser (zstd levels checked, `zstd:abc`
        // refused rather than taken as level 3).
        let compression = Compression::parse(&self.compression).ok_or_else(|| {
            PyValueError::new_err(format!(
                "compression: expected {}, found {:?}",
                Compression::EXPECTED,
                self.compression
            ))
        })?;
        let positive = |what: &str, v: [u64; 3]| match v.contains(&0) {
            true => Err(PyValueError::new_err(format!(
                "{what}: every edge must be positive, got {v:?}"
            ))),
            false => Ok(v),
        };
        let brick = positive("brick", self.brick)?;
        let shard = match self.shard {
            Some(s) => positive("shard", s)?,
            None => brick.map(brickyard_store::builder::default_shard),
        };
        Ok(ConvertOptions {
            brick,
            shard,
            compression,
            labels: self.labels,
            memory: self.memory,
            overwrite: self.overwrite,
            spacing: self.spacing,
            origin: self.origin,
            unit: self.unit.clone(),
            columns: 1,
        })
    }
}

/// `file_notes`: the conversion's notes on its input (no voxel spacing,
/// ...) are added to the report, as for a file (an array without spacing
/// is the rule, not worth a warning).
fn run_convert(
    py: Python<'_>,
    src: &dyn VolumeSource,
    dst: &Path,
    opts: &ConvertOptions,
    progress: Option<Py<PyAny>>,
    file_notes: bool,
) -> PyResult<String> {
    let cancel = AtomicBool::new(false);
    let error = std::sync::Mutex::new(None);
    let p = PyProgress {
        callback: progress,
        cancel: &cancel,
        phase: None,
        error: &error,
    };
    // Labels into an image's `labels/NAME`, as the command line writes
    // them: refused without `labels`; without geometry of their own, on
    // the image's grid, they take the image's.
    let group = brickyard_run::labels::label_target(dst, opts.labels).map_err(to_py)?;
    // A label image that cannot be one (several channels, float voxels):
    // refused before its labels group is made.
    brickyard_store::builder::check_labels(dst, src.meta(), opts.labels)
        .map_err(|e| to_py(e.into()))?;
    let mut opts = opts.clone();
    let mut made = None;
    if let Some(g) = &group {
        if opts.spacing.is_none() && opts.origin.is_none() && opts.unit.is_none() {
            let inherit =
                brickyard_run::labels::inherited_geometry(g, src.meta()).map_err(to_py)?;
            if let Some((spacing, origin, unit)) = inherit {
                (opts.spacing, opts.origin, opts.unit) = (spacing, origin, unit);
            }
        }
        made = Some(brickyard_run::labels::LabelGroup::make(g).map_err(to_py)?);
    }
    let opts = &opts;
    let r = watched(py, &cancel, "convert", || {
        Ok(brickyard_store::convert(src, dst, opts, &p, &cancel)?)
    });
    if r.is_err() {
        if let Some(m) = made {
            m.undo();
        }
    }
    callback_error(py, &error, r.is_err())?;
    if cancel.load(Ordering::Relaxed) {
        // (Ctrl-C after the last piece: the store was written whole.)
        let done = if r.is_ok() {
            " after it had finished: the store is complete"
        } else {
            ""
        };
        return Err(PyKeyboardInterrupt::new_err(format!(
            "{}: conversion interrupted{done}",
            dst.display()
        )));
    }
    let report = r.map_err(to_py)?;
    // A label image: published in its image's group, and its statistics
    // table written from its voxels.
    let table = match opts.labels {
        true => {
            let notes = py
                .detach(|| {
                    brickyard_run::labels::finish_label_image(
                        dst,
                        group.as_deref(),
                        opts.memory / 2,
                        &brickyard_store::NoProgress,
                        &cancel,
                    )
                })
                .map_err(to_py)?;
            let mut t = String::new();
            if let Some(why) = notes.no_table {
                t += &format!("; note: no table of label statistics ({why})");
            }
            if let Some(how) = notes.off_grid {
                t += &format!("; note: a label image off its image's grid: {how}");
            }
            Some(t)
        }
        false => None,
    };
    // The conversion's notes (no spacing in the input, ...), which the
    // bindings raise as warnings.
    let table = table.unwrap_or_default()
        + &report
            .notes
            .iter()
            .filter(|_| file_notes)
            .map(|n| format!("; note: {n}"))
            .collect::<String>();
    Ok(format!(
        "{} levels, {} bricks ({} empty, {} constant incl. empty), {} bytes written in {:.2} s{}",
        report.levels.len(),
        report.bricks,
        report.bricks_empty,
        report.bricks_constant,
        report.bytes_written,
        report.seconds,
        table
    ))
}

/// Convert any input `brickyard convert` reads (OME-Zarr/Zarr, TIFF, NRRD,
/// NIfTI, raw with a JSON sidecar) into a brickyard OME-Zarr pyramid;
/// several inputs of one grid become the channels of one store, in order,
/// as the command line stacks them.
#[pyfunction]
#[pyo3(signature = (srcs, dst, options, zarr_level = 0, progress = None))]
fn convert(
    py: Python<'_>,
    srcs: Vec<PathBuf>,
    dst: PathBuf,
    options: PyConvertOptions,
    zarr_level: usize,
    progress: Option<Py<PyAny>>,
) -> PyResult<String> {
    if srcs.is_empty() {
        return Err(PyValueError::new_err(
            "src: expected an input, or a list of inputs, found none",
        ));
    }
    // (A remote store is there or not as its server says, when opened; a
    // pattern of TIFF slices, `slices/img_*.tif`, names no file itself: the
    // reader says when it matches none.)
    for src in &srcs {
        let pattern = !src.exists()
            && matches!(
                brickyard_store::import::detect(src),
                Ok(brickyard_store::import::Format::TiffGlob)
            );
        if !brickyard_store::storage::is_remote(src) && !src.exists() && !pattern {
            return Err(missing(src));
        }
    }
    let opts = options.to_options()?;
    let mut sources = py
        .detach(|| {
            srcs.iter()
                .map(|src| {
                    open_input(
                        src,
                        &ImportOptions {
                            zarr_level,
                            ..Default::default()
                        },
                    )
                })
                .collect::<brickyard_store::Result<Vec<_>>>()
        })
        .map_err(|e| to_py(e.into()))?;
    let channels: usize = sources.iter().map(|s| s.meta().channels).sum();
    check_name_count(&options.channel_names, channels)?;
    let source: Box<dyn VolumeSource> = if sources.len() == 1 && options.channel_names.is_none() {
        sources.pop().expect("one source")
    } else {
        // Labels given: the inputs are labels, whatever their headers say.
        let stack = match opts.labels {
            true => brickyard_store::import::stack::ChannelStack::of_labels(sources),
            false => brickyard_store::import::stack::ChannelStack::new(sources),
        };
        let stack = match &options.channel_names {
            Some(names) => stack.and_then(|s| s.with_names(names)),
            None => stack,
        };
        Box::new(stack.map_err(|e| to_py(e.into()))?)
    };
    run_convert(py, source.as_ref(), &dst, &opts, progress, true)
}

/// Convert a NumPy array (C-contiguous, native-endian, `[c, z, y, x]` of
/// `dtype`) into a brickyard OME-Zarr pyramid, read where it lies: the
/// array's memory is handed to the builder without a copy, and the array
/// is held until the conversion ends.
#[pyfunction]
#[pyo3(signature = (array, dtype, dst, options, progress = None))]
fn from_array(
    py: Python<'_>,
    array: Bound<'_, PyAny>,
    dtype: &str,
    dst: PathBuf,
    options: PyConvertOptions,
    progress: Option<Py<PyAny>>,
) -> PyResult<String> {
    let opts = options.to_options()?;
    let view = source::ArrayView::of(&array, dtype)?;
    // SAFETY: `array` is borrowed for this whole call, and a NumPy array
    // keeps its memory while it is referenced (it cannot be resized then).
    let data = unsafe { view.bytes() };
    let mut src = source::MemorySource::new(data, view.shape, dtype).map_err(to_py)?;
    check_name_count(&options.channel_names, src.meta().channels)?;
    if let Some(names) = &options.channel_names {
        src.name_channels(names);
    }
    run_convert(py, &src, &dst, &opts, progress, false)
}

/// Convert a lazy array into a brickyard OME-Zarr pyramid, region by
/// region: `read(c, z0, z1, y0, y1, x0, x1)` returns the bytes of one box
/// (C order, native-endian `dtype`); `chunk` is the box `[z, y, x]` the
/// array reads best (its chunks), if it has one. An exception raised by
/// `read` stops the conversion and is raised again here.
#[pyfunction]
#[pyo3(signature = (read, name, shape, dtype, chunk, dst, options, progress = None))]
#[allow(clippy::too_many_arguments)]
fn from_lazy(
    py: Python<'_>,
    read: Py<PyAny>,
    name: &str,
    shape: [u64; 4],
    dtype: &str,
    chunk: Option<[u64; 3]>,
    dst: PathBuf,
    options: PyConvertOptions,
    progress: Option<Py<PyAny>>,
) -> PyResult<String> {
    let opts = options.to_options()?;
    let mut src = source::LazySource::new(read, name, shape, dtype, chunk).map_err(to_py)?;
    check_name_count(&options.channel_names, src.meta().channels)?;
    if let Some(names) = &options.channel_names {
        src.name_channels(names);
    }
    let r = run_convert(py, &src, &dst, &opts, progress, false);
    let cause = src.error.lock().unwrap().take();
    match (r, cause) {
        // Ctrl-C inside the array's own code: raised as it came.
        (Err(_), Some(cause)) if cause.is_instance_of::<PyKeyboardInterrupt>(py) => Err(cause),
        // The builder's error names the region; the array's exception is
        // its cause.
        (Err(e), Some(cause)) => {
            e.set_cause(py, Some(cause));
            Err(e)
        }
        (r, _) => r,
    }
}

/// Run a pipeline over a level of a store and publish the result in it,
/// as `brickyard process STORE PIPELINE --out OUT` does. Returns
/// `(output path, number of labels or None, report line)`.
#[pyfunction]
#[pyo3(signature = (store, pipeline, out, memory, level = 0, channel = 0, stats = None,
                    overwrite = false, backend = "cpu".to_string(), progress = None))]
#[allow(clippy::too_many_arguments)]
fn process(
    py: Python<'_>,
    store: PathBuf,
    pipeline: String,
    out: String,
    memory: String,
    level: usize,
    channel: usize,
    stats: Option<PathBuf>,
    overwrite: bool,
    backend: String,
    progress: Option<Py<PyAny>>,
) -> PyResult<(PathBuf, Option<u32>, String)> {
    // The CLI's order: the pipeline text is checked first.
    brickyard_run::process::parse(&pipeline).map_err(to_py)?;
    let memory = brickyard_run::memory::parse_bytes(&memory)
        .map_err(|e| e.context("memory"))
        .map_err(to_py)?;
    let args = brickyard_run::process::ProcessArgs {
        store,
        pipeline,
        out,
        memory,
        level,
        channel,
        stats,
        overwrite,
        backend,
        quiet: progress.is_none(),
    };
    let cancel = AtomicBool::new(false);
    let error = std::sync::Mutex::new(None);
    let phases = PyPhases {
        labelling: PyProgress {
            callback: progress.as_ref().map(|p| p.clone_ref(py)),
            cancel: &cancel,
            phase: Some("labelling (pass 1, voxels)"),
            error: &error,
        },
        writing: PyProgress {
            callback: progress,
            cancel: &cancel,
            phase: Some("writing"),
            error: &error,
        },
    };
    // The job runs beside this thread, which watches for Ctrl-C: the
    // labelling reports progress from worker threads, where Python does
    // not run signal handlers.
    // (Often: a signal sent at the first piece of a short phase must stop
    // it before it ends.)
    let r = watched(py, &cancel, "process", || {
        brickyard_run::process::run(&args, &PYTHON, &phases, &cancel)
    });
    callback_error(py, &error, r.is_err())?;
    let r = r.map_err(to_py)?;
    Ok((r.output.clone(), r.labels, r.summary()))
}

/// A size as the CLI takes it (`512MiB`, `1GiB`, `1e9`, a number of
/// bytes): bytes, or a ValueError saying what is expected.
#[pyfunction]
fn parse_bytes(text: &str) -> PyResult<u64> {
    brickyard_run::memory::parse_bytes(text).map_err(|e| PyValueError::new_err(format!("{e:#}")))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<NativeStore>()?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(parse_bytes, m)?)?;
    m.add_function(wrap_pyfunction!(convert, m)?)?;
    m.add_function(wrap_pyfunction!(from_array, m)?)?;
    m.add_function(wrap_pyfunction!(from_lazy, m)?)?;
    m.add_function(wrap_pyfunction!(process, m)?)?;
    Ok(())
}
