//! The viewer's render thread: it owns the session (virtual memory, loader,
//! host cache) and the back end, and draws the views the window asks for,
//! one frame at a time, round robin over the views that are not complete.
//! The window never waits for it: it sends view specifications and takes
//! finished frames when they come. A complete view is not drawn again until
//! its specification changes; when every view is complete the thread
//! sleeps until a message arrives.

use crate::backend::{Accumulating, Backend, GpuUpdate};
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_render::budget::{Decision, LodBudget};
use brickyard_render::cpu::{Lod, Scene, Tiles};
use brickyard_render::reference::RenderParams;
use brickyard_render::Image;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::time::{Duration, Instant};

/// What one view shows.
#[derive(Debug, Clone, PartialEq)]
pub struct Spec {
    pub params: RenderParams,
    pub lod: Lod,
    /// The channel a DVR shows.
    pub channel: usize,
    /// How several views (`params.views`) are laid out on screen.
    pub layout: Option<brickyard_render::views::Layout>,
}

/// How the worker opens its session and back end.
#[derive(Debug, Clone)]
pub struct Setup {
    pub store: PathBuf,
    pub cfg: VmConfig,
    pub host_bytes: u64,
    /// The loader's decoded-chunk caches, all levels.
    pub chunk_bytes: u64,
    /// The whole viewer's budget (reported beside the peak).
    pub memory_budget: u64,
    pub loader_threads: usize,
    pub backend: String,
    pub gpu_update: GpuUpdate,
    /// Channels shown at once (more than one: the CPU back end).
    pub channels: usize,
    pub read_delay: Duration,
    /// A live derived channel shown instead of the stored ones.
    pub derive: Option<std::sync::Arc<crate::derive::Derived>>,
    /// Frames a still DVR view accumulates (0: none), and the bytes its
    /// kept samples may take.
    pub accumulate: u32,
    pub accum_bytes: u64,
    /// `--traversal octree`: the residency octree's depth (`None`: page
    /// tables). The octree is attached to each session's virtual memory
    /// and kept after every frame; the 3D view's unshaded DVR goes
    /// through it.
    pub octree: Option<u32>,
    /// Bytes the memory budget set aside for the views' images (by the
    /// window's size), and whether that budget was given (`--memory`):
    /// the sizes scripts set are held to it.
    pub image_bytes: u64,
    pub memory_given: bool,
}

pub enum Msg {
    /// View `i` now shows `spec` (`None`: hidden), version `v`.
    View(usize, u64, Option<Box<Spec>>),
    /// New budgets or a derived channel: the session and back end are
    /// made again.
    Reopen(Box<Setup>),
    Quit,
}

/// One drawn frame of one view.
pub struct Out {
    pub view: usize,
    pub version: u64,
    pub image: Image,
    pub completeness: f64,
    pub render_ms: f64,
    pub cache_ms: f64,
    pub up: u64,
    pub down: u64,
    pub resident_bricks: usize,
    pub pool_slots: usize,
    pub pending: usize,
    pub bytes_read: u64,
    pub host_bytes: u64,
    pub host_budget: u64,
    pub backend: String,
    /// The LOD bias this view's pool budget added (0: full detail).
    pub lod_extra: f64,
    /// The level of detail the frame was drawn with (the budget's bias
    /// included): the readout reads the levels it drew.
    pub lod: Lod,
    /// Bricks that could not be loaded (drawn from coarser data).
    pub failed: usize,
    /// Load failures new since the last frame sent: "brick: error".
    pub new_failures: Vec<String>,
    /// Nothing more will come for this view until it changes: complete,
    /// or what is missing are bricks that failed to load.
    pub settled: bool,
    /// Sample accumulation: frames drawn and asked for (`Some((0, N))`
    /// on the plain frame after which it begins).
    pub accumulated: Option<(u32, u32)>,
    /// The fewest frames any pixel holds: fewer than drawn where the
    /// memory for kept samples stopped long rays short.
    pub accumulated_fewest: u32,
    /// The image is a re-blend of kept samples (a transfer-function edit;
    /// no volume access).
    pub reblended: bool,
    /// Milliseconds since this version of the view arrived (for its first
    /// frame: the time to answer the change).
    pub since_change_ms: f64,
    /// Residency-octree nodes the frame's rays visited (0: drawn through
    /// the page tables).
    pub octree_nodes: u64,
    /// A preview: the view drawn smaller (a fraction of its width and
    /// height, [`PREVIEW_FOR`](crate::frames::PREVIEW_FOR)) while most of what it needs is still
    /// loading; shown scaled up, never complete.
    pub preview: bool,
}

pub enum Reply {
    Frame(Box<Out>),
    Error(String),
    /// Something the status line should say about view `usize` that
    /// fails nothing (an accumulation given up or drawn coarser).
    Note(usize, String),
}

struct View {
    version: u64,
    /// When this version arrived.
    arrived: Instant,
    spec: Option<Spec>,
    complete: bool,
    /// Coarsens the view when its working set does not fit the pool.
    budget: LodBudget,
    /// The CPU's last frame of this view and its unsettled tiles: the
    /// next frame at the same level of detail draws only those.
    keep: Option<(Lod, Image, Tiles)>,
    /// The samples a still DVR view accumulates.
    acc: Option<Acc>,
    /// Pool slots its last frame needed: used at their own level, and
    /// asked for.
    need: usize,
    /// This version of the view does not accumulate samples (its
    /// accumulation could not be begun, or failed): its plain frame is
    /// its last.
    no_acc: bool,
    /// Its next frame is drawn first as a preview ([`preview`](crate::frames::preview)),
    /// and sent as one while that preview is incomplete.
    preview: bool,
}

impl View {
    /// Shown, not complete, and drawn in plain frames (not accumulating):
    /// its bricks are wanted in the pool beside the other such views'.
    fn drawing(&self) -> bool {
        self.spec.is_some() && !self.complete && self.acc.is_none()
    }
}

/// A view's sample accumulation: what it was begun for (the view but its
/// transfer function), the passes drawn, and whether a transfer-function
/// edit waits to be re-blended.
struct Acc {
    key: (RenderParams, Lod, usize),
    acc: Accumulating,
    /// Frames drawn whole.
    passes: u32,
    reblend: bool,
    /// The CPU draws a frame in parts of `part` rows (about
    /// [`PART_MS`] each), from row `next_row` on, so that input is answered
    /// between them.
    next_row: u32,
    part: u32,
    /// When a part of it was last sent to the window.
    sent_at: Instant,
}

/// The time an accumulation part should take.
const PART_MS: f64 = 20.0;

/// The least time between accumulation parts sent to the window (a pass's
/// last part is always sent): each sent image is converted for display on
/// a core the renderer shares, and a part every 20 ms showed no more than
/// one every 100 ms does.
const SEND_MS: f64 = 100.0;

/// What an accumulation is valid for: the view without its transfer
/// function.
fn acc_key(spec: &Spec, lod: Lod) -> (RenderParams, Lod, usize) {
    let mut p = spec.params.clone();
    p.tf = brickyard_core::TransferFunction::preset("linear", [0.0, 1.0]).expect("a preset");
    (p, lod, spec.channel)
}

/// Samples a pixel of a `p`-sized view keeps for `n` frames within
/// `bytes` (`savr::sample_bytes` a sample, about 160 bytes of bookkeeping
/// a pixel), and at most `n` whole rays of the scene.
fn acc_budget(scene: &Scene, p: &RenderParams, n: u32, bytes: u64) -> usize {
    use brickyard_render::savr::{longest_run, sample_bytes};
    let per = sample_bytes(p.tf.shading.is_some());
    let pixels = (p.width as u64 * p.height as u64).max(1);
    let fit = (bytes / pixels).saturating_sub(160) / per;
    fit.min(n as u64 * longest_run(scene, p, 0)) as usize
}

/// Whether an accumulation keeping `kept` samples a pixel can draw `p`
/// at `lod`: every ray's first run must fit (the rule of the device's
/// accumulation, which the CPU's twin keeps). `Ok(None)`: at `lod`;
/// `Ok(Some(note))`: at a coarser level of detail (as `render
/// --progressive` does, and says); `Err(note)`: not even at the coarsest
/// level, so the view does not accumulate.
fn acc_fits(
    scene: &Scene,
    p: &RenderParams,
    lod: Lod,
    kept: usize,
    on_device: bool,
) -> Result<Option<String>, String> {
    use brickyard_render::savr::{lod_within, longest_run};
    match lod_within(scene, p, lod, kept as u64) {
        Some(fit) if fit == lod => Ok(None),
        Some(fit) => Ok(Some(format!(
            "accumulating at {}: a pixel keeps {kept} samples, fewer than one run of the longest ray takes at the level of detail asked for (a smaller view keeps more detail)",
            match fit {
                Lod::Fixed(l) => format!("level {l}"),
                Lod::Auto { bias } => format!("a level-of-detail bias of {bias:+.2}"),
            }
        ))),
        None => Err(format!(
            "no accumulation: a pixel keeps {kept} samples{}, fewer than one run of the longest ray takes even at the coarsest level ({}); a smaller view, or {}, accumulates",
            match on_device {
                true => " (what the device's largest buffer holds over the view)",
                false => "",
            },
            longest_run(scene, p, scene.levels.len().saturating_sub(1)),
            match on_device {
                true => "--backend cpu",
                false => "a larger --memory",
            }
        )),
    }
}

fn open(setup: &Setup, scene: &mut Scene) -> anyhow::Result<(Session, Backend)> {
    let mut s = match &setup.derive {
        Some(d) => d.session(
            setup.cfg.clone(),
            setup.host_bytes,
            setup.chunk_bytes,
            setup.loader_threads,
        )?,
        None => Session::open_with_budget(
            &setup.store,
            setup.cfg.clone(),
            setup.host_bytes,
            setup.chunk_bytes,
            setup.loader_threads,
        )?,
    };
    s.loader().set_read_delay(setup.read_delay);
    // A frame waits a little for the bricks it asked for (the window keeps
    // drawing meanwhile).
    s.set_batch(Some(crate::frames::STREAM_LOAD_WAIT));
    // The coarsest levels stay resident, so no part of a view is ever
    // empty (before the back end mirrors the pool).
    s.pin_coarsest(512, Duration::from_secs(120))
        .map_err(|e| anyhow::anyhow!("pool: {e}"))?;
    // The window's histogram already read the statistics (same bricks);
    // a derived channel has none (nothing is known to be empty), and
    // leaving it reads them again.
    let unknown = |r: &brickyard_cache::ranges::BrickRanges| r.levels.iter().all(Option::is_none);
    if setup.derive.is_some() || scene.ranges.as_deref().is_none_or(unknown) {
        scene.ranges = Some(std::sync::Arc::new(s.loader().brick_ranges(1 << 24)));
    }
    let b = Backend::choose(&setup.backend, setup.gpu_update, &mut s, setup.channels)?;
    // The residency octree of this session's virtual memory.
    scene.octree = None;
    if let Some(depth) = setup.octree {
        // (A depth whose tables pass the device's limit for one buffer is
        // lowered, as `render` does.)
        let depth = match b.max_storage_binding() {
            Some(limit) => {
                let fit = crate::render::fit_octree_to_device(
                    depth,
                    scene.levels.len(),
                    setup.channels,
                    limit,
                );
                if let Some(n) = &fit.note {
                    eprintln!("{n}");
                }
                fit.depth
            }
            None => depth,
        };
        crate::backend::attach_octree(scene, &mut s, depth)?;
    }
    Ok((s, b))
}

/// Run the worker until [`Msg::Quit`] or the window goes away. `wake` is
/// called after each frame sent (the window repaints).
/// How often bricks that failed to load are tried again while viewing.
const RETRY_FAILED_AFTER: Duration = Duration::from_secs(20);

pub fn run(setup: Setup, mut scene: Scene, rx: Receiver<Msg>, tx: Sender<Reply>, wake: impl Fn()) {
    let (mut s, mut backend) = match open(&setup, &mut scene) {
        Ok(x) => x,
        Err(e) => {
            let _ = tx.send(Reply::Error(format!("{e:#}")));
            wake();
            return;
        }
    };
    backend.set_read_image(true);
    let mut setup_accumulate = (setup.accumulate, setup.accum_bytes);
    let mut views: Vec<View> = vec![];
    let mut next = 0;
    let mut idle_since = Instant::now();
    // Failures of the session already sent to the window.
    let mut reported = 0;
    let mut last_retry = Instant::now();
    // Frames left in which the views drawing in turn are known to take
    // each other's bricks.
    let mut contended = 0;
    loop {
        // Bricks that failed (a server gone for a while, a file being
        // replaced) are asked for again now and then: the view picks them
        // up once they can be read. Views that accumulate samples were
        // complete without them.
        if s.vm().failed_count() > 0 && last_retry.elapsed() >= RETRY_FAILED_AFTER {
            last_retry = Instant::now();
            s.retry_failed();
            for v in views
                .iter_mut()
                .filter(|v| v.spec.is_some() && v.acc.is_none())
            {
                v.complete = false;
            }
        }
        // Take every message; wait for one only when nothing is left to do.
        let busy = views.iter().any(|v| v.spec.is_some() && !v.complete);
        let first = if busy {
            match rx.try_recv() {
                Ok(m) => Some(m),
                Err(TryRecvError::Empty) => None,
                Err(TryRecvError::Disconnected) => return,
            }
        } else {
            match rx.recv_timeout(Duration::from_millis(250)) {
                Ok(m) => Some(m),
                Err(RecvTimeoutError::Timeout) => continue,
                Err(RecvTimeoutError::Disconnected) => return,
            }
        };
        for m in first
            .into_iter()
            .chain(std::iter::from_fn(|| rx.try_recv().ok()))
        {
            match m {
                Msg::Quit => return,
                Msg::View(i, version, spec) => {
                    let spec = spec.map(|s| *s);
                    while views.len() <= i {
                        views.push(View {
                            version: 0,
                            arrived: Instant::now(),
                            spec: None,
                            complete: true,
                            budget: LodBudget::new(0.0, scene.levels.len(), true),
                            keep: None,
                            acc: None,
                            need: 0,
                            no_acc: false,
                            preview: false,
                        });
                    }
                    let v = &mut views[i];
                    v.version = version;
                    v.arrived = Instant::now();
                    v.complete = spec.is_none();
                    if let Some(sp) = &spec {
                        let base = match sp.lod {
                            Lod::Auto { bias } => bias,
                            Lod::Fixed(_) => 0.0,
                        };
                        if base != v.budget.base {
                            // The user moved the bias: start from it.
                            v.budget = LodBudget::new(base, scene.levels.len(), true);
                        }
                    }
                    // A transfer-function edit of an accumulated view
                    // re-blends its samples; anything else starts over.
                    let same = match (&v.acc, &spec, &v.spec) {
                        (Some(a), Some(sp), Some(old)) => {
                            a.key == acc_key(sp, a.key.1)
                                && old.lod == sp.lod
                                && (sp.params.tf.shading.is_none()
                                    || old.params.tf.shading.is_some())
                        }
                        _ => false,
                    };
                    if same {
                        if let Some(a) = &mut v.acc {
                            a.reblend = true;
                        }
                    } else {
                        v.acc = None;
                        v.no_acc = false;
                        v.budget.view_changed();
                        v.keep = None;
                        v.preview = true;
                    }
                    v.spec = spec;
                }
                Msg::Reopen(setup) => match open(&setup, &mut scene) {
                    Ok((s2, b2)) => {
                        setup_accumulate = (setup.accumulate, setup.accum_bytes);
                        s = s2;
                        backend = b2;
                        reported = 0;
                        backend.set_read_image(true);
                        for v in &mut views {
                            v.complete = v.spec.is_none();
                            v.keep = None;
                            v.acc = None;
                            v.preview = true;
                        }
                    }
                    Err(e) => {
                        let _ = tx.send(Reply::Error(format!("reopen: {e:#}")));
                        wake();
                    }
                },
            }
        }
        let n = views.len();
        let Some(i) = (0..n).map(|k| (next + k) % n.max(1)).find(|&k| {
            views
                .get(k)
                .is_some_and(|v| v.spec.is_some() && !v.complete)
        }) else {
            continue;
        };
        next = i + 1;
        let v = &views[i];
        let spec = v.spec.clone().expect("chosen above");
        let mut sc = scene.clone();
        sc.channel = spec.channel;
        // A brick evicted that a view still drawing used at its own level
        // in its latest frame is one the views take from each other.
        let drawing = views.iter().filter(|v| v.drawing()).count();
        s.vm_mut().set_in_use_frames(drawing as u32);
        let lod = views[i].budget.apply(spec.lod, sc.levels.len());
        if views[i].acc.is_some() {
            match accumulate(&mut views[i], &mut backend, &mut s, &sc, &spec) {
                Ok((None, _)) => {}
                Ok((Some(out), done)) => {
                    views[i].complete = done;
                    let out = Out {
                        view: i,
                        version: views[i].version,
                        backend: backend.describe(),
                        since_change_ms: views[i].arrived.elapsed().as_secs_f64() * 1e3,
                        ..status(&s, out)
                    };
                    if tx.send(Reply::Frame(Box::new(out))).is_err() {
                        return;
                    }
                    wake();
                }
                Err(e) => {
                    // The view keeps its plain frame: drawn once more and
                    // settled, without accumulating (interactively and in
                    // scripts alike; the status line says why).
                    let note = format!("accumulation stopped: {e:#}");
                    let _ = tx.send(Reply::Note(i, note));
                    wake();
                    views[i].acc = None;
                    views[i].no_acc = true;
                    views[i].complete = false;
                    views[i].keep = None;
                }
            }
            continue;
        }
        // A view just changed is first drawn as a preview: sent while it
        // is incomplete (most of the view still loading), dropped for the
        // full frame once it is complete (the view was warm), nothing
        // more is coming, or after PREVIEW_FOR.
        let preview = match views[i].preview {
            true => crate::frames::preview(&backend, &spec.params, lod),
            false => None,
        };
        if let Some((pp, pl)) = preview {
            let f = match backend.frame(&mut s, &sc, &pp, pl) {
                Ok(f) => f,
                Err(e) => {
                    let _ = tx.send(Reply::Error(format!("{e:#}")));
                    wake();
                    views[i].complete = true;
                    continue;
                }
            };
            let completeness = f.stats.completeness();
            if crate::frames::preview_over(&s, &f, views[i].arrived) {
                views[i].preview = false;
            }
            if completeness < 1.0 {
                let idle = f.session.insert.inserted == 0 && f.session.insert.flagged == 0;
                let out = Out {
                    preview: true,
                    ..frame_out(i, &views[i], &s, &backend, f, lod)
                };
                if tx.send(Reply::Frame(Box::new(out))).is_err() {
                    return;
                }
                wake();
                if views[i].preview {
                    if idle {
                        std::thread::sleep(Duration::from_millis(4));
                    }
                    continue;
                }
            }
        }
        let drawn = match views[i].keep.take() {
            Some((kl, img, tiles)) if kl == lod => {
                backend.frame_again(&mut s, &sc, &spec.params, lod, img, tiles)
            }
            _ => backend.frame(&mut s, &sc, &spec.params, lod),
        };
        let mut f = match drawn {
            Ok(f) => f,
            Err(e) => {
                let _ = tx.send(Reply::Error(format!("{e:#}")));
                wake();
                views[i].complete = true;
                continue;
            }
        };
        let completeness = f.stats.completeness();
        // The pool is shared by the views still drawing: when they take
        // each other's bricks, the one that needs the most coarsens until
        // they fit.
        let (others, largest) = views
            .iter()
            .enumerate()
            .filter(|(k, v)| *k != i && v.drawing())
            .fold((0, 0), |(sum, most), (_, v)| {
                (sum + v.need, most.max(v.need))
            });
        let sig = crate::frames::signals(&s, &f);
        views[i].need = sig.need();
        // Contention seen lasts a round of the views drawing.
        if sig.evicted_in_use > 0 {
            contended = drawing;
        }
        let sig = sig.shared_with(others, largest, contended > 0);
        contended = contended.saturating_sub(1);
        let changed = matches!(views[i].budget.update(&sig), Decision::Changed { .. });
        // Complete, or nothing left to ask for but bricks that failed.
        let mut done = !changed && (completeness >= 1.0 || (sig.requests == 0 && !sig.progress));
        // A complete DVR view of one channel goes on accumulating samples.
        let mut accumulated = None;
        if done
            && completeness >= 1.0
            && setup_accumulate.0 > 0
            && spec.params.mode == brickyard_render::reference::RenderMode::Dvr
            && spec.params.channels.is_empty()
            // (A label image's surfaces are whole in every frame.)
            && !spec.params.labels
            && !views[i].no_acc
        {
            let n = setup_accumulate.0;
            let budget = acc_budget(&sc, &spec.params, n, setup_accumulate.1);
            if budget > 0 {
                let acc = Accumulating::new(&backend, &spec.params, n, budget);
                let on_device = !matches!(backend, crate::backend::Backend::Cpu);
                match acc_fits(&sc, &spec.params, lod, acc.budget(), on_device) {
                    Ok(note) => {
                        if let Some(note) = note {
                            let _ = tx.send(Reply::Note(i, note));
                        }
                        views[i].acc = Some(Acc {
                            key: acc_key(&spec, lod),
                            acc,
                            passes: 0,
                            reblend: false,
                            next_row: 0,
                            part: 8,
                            sent_at: Instant::now(),
                        });
                        accumulated = Some((0, n));
                        done = false;
                    }
                    Err(note) => {
                        // Not even the coarsest level's rays fit what a
                        // pixel keeps: the plain frame stands.
                        views[i].no_acc = true;
                        let _ = tx.send(Reply::Note(i, note));
                    }
                }
            }
        }
        views[i].complete = done;
        // Not done: the next frame of this view draws only what changed.
        if let Some(t) = f.tiles.take().filter(|_| !done) {
            views[i].keep = Some((lod, f.image.clone(), t));
        }
        let new_failures: Vec<String> = s.failures()[reported.min(s.failures().len())..]
            .iter()
            .map(|f| format!("{}: {}", f.place(s.loader().geometry()), f.message))
            .collect();
        reported = s.failures().len();
        let idle = f.session.insert.inserted == 0 && f.session.insert.flagged == 0;
        let out = Out {
            new_failures,
            settled: done,
            accumulated,
            ..frame_out(i, &views[i], &s, &backend, f, lod)
        };
        if tx.send(Reply::Frame(Box::new(out))).is_err() {
            return;
        }
        wake();
        // Waiting for I/O: frames keep coming, but not as a busy loop.
        if !done && idle {
            if idle_since.elapsed() > Duration::from_millis(2) {
                std::thread::sleep(Duration::from_millis(4));
            }
        } else {
            idle_since = Instant::now();
        }
    }
}

/// What an accumulation pass sends (the rest of [`Out`] is filled in by
/// the caller).
struct AccOut {
    image: Image,
    completeness: f64,
    render_ms: f64,
    accumulated: (u32, u32),
    fewest: u32,
    reblended: bool,
    settled: bool,
    lod: Lod,
}

/// One pass of view `v`'s accumulation: a re-blend when its transfer
/// function changed, else an accumulation frame (on the CPU, the next
/// part of one). Returns what to send (`None`: a part within a pass, less
/// than [`SEND_MS`] after the last one sent) and whether the view is done
/// (the accumulation complete, or given up after as many passes as
/// `render --progressive` allows).
fn accumulate(
    v: &mut View,
    backend: &mut Backend,
    s: &mut Session,
    scene: &Scene,
    spec: &Spec,
) -> anyhow::Result<(Option<AccOut>, bool)> {
    let a = v.acc.as_mut().expect("an accumulating view");
    let lod = a.key.1;
    let t = Instant::now();
    if std::mem::take(&mut a.reblend) {
        if let Some(short) = a.acc.reblend(backend, s, scene, &spec.params)? {
            let done = short == 0 && a.acc.complete();
            a.sent_at = Instant::now();
            let out = AccOut {
                image: a.acc.image().clone(),
                completeness: 1.0,
                render_ms: t.elapsed().as_secs_f64() * 1e3,
                accumulated: (a.acc.drawn(), a.acc.target()),
                fewest: a.acc.frames(),
                reblended: true,
                settled: done,
                lod,
            };
            return Ok((Some(out), done));
        }
        // Shading asked of samples kept without normals: start over.
        a.acc = Accumulating::new(backend, &spec.params, a.acc.target(), a.acc.budget());
        a.passes = 0;
        a.next_row = 0;
    }
    let h = spec.params.height;
    let rows = match a.acc.in_parts() {
        true => a.next_row..(a.next_row + a.part).min(h),
        false => 0..h,
    };
    let f = a
        .acc
        .frame_rows(backend, s, scene, &spec.params, lod, rows.clone())?;
    // The next part: sized to take about PART_MS.
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let n = (rows.end - rows.start) as f64;
    // (At most twice as many rows as the last part: rows outside the
    // volume cost nothing and say little about those inside.)
    let want = (n * PART_MS / ms.max(0.1)).min(2.0 * n) as u32;
    a.part = want.clamp(1, h.max(1));
    a.next_row = if rows.end >= h { 0 } else { rows.end };
    if rows.end >= h {
        a.passes += 1;
    }
    let done = (rows.end >= h && a.acc.complete()) || a.passes >= 4 * a.acc.target() + 64;
    if rows.end < h && !done && a.sent_at.elapsed().as_secs_f64() * 1e3 < SEND_MS {
        return Ok((None, false));
    }
    a.sent_at = Instant::now();
    let out = AccOut {
        image: a.acc.image().clone(),
        completeness: if f.samples == 0 {
            1.0
        } else {
            f.exact as f64 / f.samples as f64
        },
        render_ms: t.elapsed().as_secs_f64() * 1e3,
        accumulated: (a.acc.drawn(), a.acc.target()),
        fewest: a.acc.frames(),
        reblended: false,
        settled: done,
        lod,
    };
    Ok((Some(out), done))
}

/// What frame `f` of view `i` (`v`) sends: its image and figures, with no
/// new failures, not settled, not accumulated, not a preview (the callers
/// say otherwise).
fn frame_out(
    i: usize,
    v: &View,
    s: &Session,
    backend: &Backend,
    f: crate::backend::Frame,
    lod: Lod,
) -> Out {
    let loader = s.loader();
    Out {
        view: i,
        version: v.version,
        completeness: f.stats.completeness(),
        render_ms: f.render_ms,
        cache_ms: f.cache_ms,
        up: f.up,
        down: f.down,
        resident_bricks: f.session.frame.resident_bricks,
        pool_slots: s.vm().pool_slots(),
        pending: f.session.pending + f.session.in_flight + f.session.waiting_upload,
        bytes_read: loader.bytes_read(),
        host_bytes: loader.cache().bytes(),
        host_budget: loader.cache().budget(),
        backend: backend.describe(),
        lod_extra: v.budget.extra(),
        lod,
        failed: s.vm().failed_count(),
        new_failures: vec![],
        settled: false,
        accumulated: None,
        accumulated_fewest: 0,
        reblended: false,
        since_change_ms: v.arrived.elapsed().as_secs_f64() * 1e3,
        octree_nodes: f.stats.octree_nodes,
        preview: false,
        image: f.image,
    }
}

/// An [`Out`] of an accumulation pass, with the session's figures.
fn status(s: &Session, a: AccOut) -> Out {
    let loader = s.loader();
    Out {
        view: 0,
        version: 0,
        image: a.image,
        completeness: a.completeness,
        render_ms: a.render_ms,
        cache_ms: 0.0,
        up: 0,
        down: 0,
        resident_bricks: s.vm().resident_bricks(),
        pool_slots: s.vm().pool_slots(),
        pending: 0,
        bytes_read: loader.bytes_read(),
        host_bytes: loader.cache().bytes(),
        host_budget: loader.cache().budget(),
        backend: String::new(),
        lod_extra: 0.0,
        lod: a.lod,
        failed: s.vm().failed_count(),
        new_failures: vec![],
        settled: a.settled,
        accumulated: Some(a.accumulated),
        accumulated_fewest: a.fewest,
        reblended: a.reblended,
        since_change_ms: 0.0,
        octree_nodes: 0,
        preview: false,
    }
}
