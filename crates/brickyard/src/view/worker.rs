//! The viewer's render thread: it owns the session (virtual memory, loader,
//! host cache) and the back end, and draws the views the window asks for,
//! one frame at a time, round robin over the views that are not complete.
//! The window never waits for it: it sends view specifications and takes
//! finished frames when they come. A complete view is not drawn again until
//! its specification changes; when every view is complete the thread
//! sleeps until a message arrives.

use crate::backend::{Backend, GpuUpdate};
use brickyard_cache::session::Session;
use brickyard_cache::vm::VmConfig;
use brickyard_render::budget::{Decision, LodBudget};
use brickyard_render::cpu::{Lod, Scene, Tiles};
use brickyard_render::reference::RenderParams;
use brickyard_render::Image;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::time::{Duration, Instant};

/// What one view shows.
#[derive(Debug, Clone, PartialEq)]
pub struct Spec {
    pub params: RenderParams,
    pub lod: Lod,
    /// The channel a DVR shows.
    pub channel: usize,
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
}

pub enum Msg {
    /// View `i` now shows `spec` (`None`: hidden), version `v`.
    View(usize, u64, Option<Spec>),
    /// New budgets or a derived channel: the session and back end are
    /// made again.
    Reopen(Setup),
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
    /// Bricks that could not be loaded (drawn from coarser data).
    pub failed: usize,
    /// Load failures new since the last frame sent: "brick: error".
    pub new_failures: Vec<String>,
    /// Nothing more will come for this view until it changes: complete,
    /// or what is missing are bricks that failed to load.
    pub settled: bool,
}

pub enum Reply {
    Frame(Box<Out>),
    Error(String),
}

struct View {
    version: u64,
    spec: Option<Spec>,
    complete: bool,
    /// Coarsens the view when its working set does not fit the pool.
    budget: LodBudget,
    /// The CPU's last frame of this view and its unsettled tiles: the
    /// next frame at the same level of detail draws only those.
    keep: Option<(Lod, Image, Tiles)>,
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
    Ok((s, b))
}

/// Run the worker until [`Msg::Quit`] or the window goes away. `wake` is
/// called after each frame sent (the window repaints).
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
    let mut views: Vec<View> = vec![];
    let mut next = 0;
    let mut idle_since = Instant::now();
    // Failures of the session already sent to the window.
    let mut reported = 0;
    loop {
        // Take every message; wait for one only when nothing is left to do.
        let busy = views.iter().any(|v| v.spec.is_some() && !v.complete);
        let first = if busy {
            rx.try_recv().ok()
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
                    while views.len() <= i {
                        views.push(View {
                            version: 0,
                            spec: None,
                            complete: true,
                            budget: LodBudget::new(0.0, scene.levels.len(), true),
                            keep: None,
                        });
                    }
                    let v = &mut views[i];
                    v.version = version;
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
                    v.budget.view_changed();
                    v.spec = spec;
                    v.keep = None;
                }
                Msg::Reopen(setup) => match open(&setup, &mut scene) {
                    Ok((s2, b2)) => {
                        s = s2;
                        backend = b2;
                        reported = 0;
                        backend.set_read_image(true);
                        for v in &mut views {
                            v.complete = v.spec.is_none();
                            v.keep = None;
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
        let lod = views[i].budget.apply(spec.lod, sc.levels.len());
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
        let sig = crate::frames::signals(&s, &f);
        let changed = matches!(views[i].budget.update(&sig), Decision::Changed { .. });
        // Complete, or nothing left to ask for but bricks that failed.
        let done = !changed && (completeness >= 1.0 || (sig.requests == 0 && !sig.progress));
        views[i].complete = done;
        // Not done: the next frame of this view draws only what changed.
        if let Some(t) = f.tiles.take().filter(|_| !done) {
            views[i].keep = Some((lod, f.image.clone(), t));
        }
        let new_failures: Vec<String> = s.failures()[reported.min(s.failures().len())..]
            .iter()
            .map(|f| {
                let k = f.key;
                format!(
                    "level {} channel {} brick {:?}: {}",
                    k.level, k.channel, k.brick, f.message
                )
            })
            .collect();
        reported = s.failures().len();
        let loader = s.loader();
        let out = Out {
            view: i,
            version: views[i].version,
            image: f.image,
            completeness,
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
            lod_extra: views[i].budget.extra(),
            failed: s.vm().failed_count(),
            new_failures,
            settled: done,
        };
        if tx.send(Reply::Frame(Box::new(out))).is_err() {
            return;
        }
        wake();
        // Waiting for I/O: frames keep coming, but not as a busy loop.
        if !done && f.session.insert.inserted == 0 && f.session.insert.flagged == 0 {
            if idle_since.elapsed() > Duration::from_millis(2) {
                std::thread::sleep(Duration::from_millis(4));
            }
        } else {
            idle_since = Instant::now();
        }
    }
}
