//! The browser's streaming session: the virtual memory fed by asynchronous
//! brick loads, frame by frame, as the native session does with its loader
//! threads. A frame never waits: it draws what is resident (coarser bricks
//! stand in for missing ones), sends its capped request list, and takes in
//! what arrived since the last one.

use crate::source::{LocalFuture, WebSource};
use brickyard_cache::brick::{BrickKey, LoadedBrick, PoolTooSmall};
use brickyard_cache::vm::{FrameReport, InsertReport, VirtualMemory, VmConfig};
use brickyard_render::budget::{Decision, FrameSignals, LodBudget};
use brickyard_render::cpu::{render_tiles, FrameStats, Lod, Scene, Tiles};
use brickyard_render::octree::{Octree, DEFAULT_DEPTH};
use brickyard_render::params::Traversal;
use brickyard_render::{readout, Image, RenderParams};
use std::cell::RefCell;
use std::collections::{HashSet, VecDeque};
use std::rc::Rc;
use std::sync::{Arc, RwLock};

/// Runs a task to its end beside the caller (the page's event loop, or a
/// test's executor).
pub type Spawn = Rc<dyn Fn(LocalFuture<()>)>;

#[derive(Default)]
struct LoadState {
    /// Wanted bricks not yet started, most wanted first.
    queue: VecDeque<BrickKey>,
    in_flight: HashSet<BrickKey>,
    arrived: Vec<Arc<LoadedBrick>>,
    failed: Vec<(BrickKey, String)>,
    loaded: u64,
}

/// Brick loads in flight, at most `max` at a time.
#[derive(Clone)]
pub struct Loads {
    pub src: Rc<WebSource>,
    st: Rc<RefCell<LoadState>>,
    spawn: Spawn,
    max: usize,
}

impl Loads {
    pub fn new(src: Rc<WebSource>, spawn: Spawn, max: usize) -> Loads {
        Loads {
            src,
            st: Rc::default(),
            spawn,
            max: max.max(1),
        }
    }

    /// Want these bricks (most wanted first) and no others: queued ones no
    /// longer wanted are dropped, loads in flight finish.
    pub fn request(&self, wanted: &[BrickKey]) {
        {
            let mut st = self.st.borrow_mut();
            let busy = st.in_flight.clone();
            st.queue = wanted
                .iter()
                .filter(|k| !busy.contains(k))
                .copied()
                .collect();
        }
        self.pump();
    }

    fn pump(&self) {
        loop {
            let key = {
                let mut st = self.st.borrow_mut();
                if st.in_flight.len() >= self.max {
                    return;
                }
                let Some(k) = st.queue.pop_front() else {
                    return;
                };
                st.in_flight.insert(k);
                k
            };
            let me = self.clone();
            (self.spawn)(Box::pin(async move {
                let r = me.src.load(key).await;
                {
                    let mut st = me.st.borrow_mut();
                    st.in_flight.remove(&key);
                    match r {
                        Ok(b) => {
                            st.loaded += 1;
                            st.arrived.push(Arc::new(b));
                        }
                        Err(e) => st.failed.push((key, e)),
                    }
                }
                me.pump();
            }));
        }
    }

    /// Bricks that arrived, and loads that failed, since the last call.
    pub fn take(&self) -> (Vec<Arc<LoadedBrick>>, Vec<(BrickKey, String)>) {
        let mut st = self.st.borrow_mut();
        (
            std::mem::take(&mut st.arrived),
            std::mem::take(&mut st.failed),
        )
    }

    /// Loads queued and in flight.
    pub fn pending(&self) -> (usize, usize) {
        let st = self.st.borrow();
        (st.queue.len(), st.in_flight.len())
    }

    pub fn loaded(&self) -> u64 {
        self.st.borrow().loaded
    }

    /// Bricks arrived (or failed) and not yet taken.
    pub fn arrived(&self) -> usize {
        let st = self.st.borrow();
        st.arrived.len() + st.failed.len()
    }
}

/// What one frame did.
#[derive(Debug, Clone, Default)]
pub struct FrameOut {
    pub stats: FrameStats,
    pub frame: FrameReport,
    pub insert: InsertReport,
    /// Every sample was served at its own level (or only failed bricks
    /// are missing) and nothing is left to load.
    pub complete: bool,
    pub queued: usize,
    pub in_flight: usize,
    pub failed: usize,
    /// The LOD bias drawn with (above the user's when the pool is too
    /// small for the view).
    pub bias: f64,
    /// Tiles drawn by this call, and tiles of its frame still to draw
    /// (a frame drawn in parts: [`WebSession::frame_cpu_part`]).
    pub tiles_drawn: usize,
    pub tiles_left: usize,
}

/// A frame on the CPU drawn in parts, one per call, so that no call holds
/// the page's thread for long: its tiles still to draw, and what the parts
/// drawn so far gathered. The virtual memory's frame spans the parts (no
/// brick enters or leaves it between them), so the image is the one a
/// single call would draw.
#[derive(Default)]
struct Pass {
    /// Tile indices still to draw, in the order they are drawn.
    left: Vec<usize>,
    stats: FrameStats,
    reqs: Vec<brickyard_cache::vm::Requests>,
    failed: usize,
}

/// Virtual memory + loads + the scene it draws.
pub struct WebSession {
    pub vm: VirtualMemory,
    pub loads: Loads,
    pub scene: Scene,
    waiting: VecDeque<Arc<LoadedBrick>>,
    /// Every load failure so far, oldest first.
    pub failures: Vec<(BrickKey, String)>,
    /// The coarsest levels' bricks still to arrive before they are pinned.
    pin: Option<HashSet<BrickKey>>,
    pinned: Vec<Arc<LoadedBrick>>,
    budget: Option<LodBudget>,
    /// The view and level of detail of the last frame, for its settled
    /// tiles.
    drawn: Option<(RenderParams, Lod)>,
    image: Image,
    tiles: Tiles,
    /// A frame drawn in parts, begun and not finished.
    pass: Option<Pass>,
    /// The depth of the residency octree frames through it attach
    /// ([`View::octree_depth`](crate::view::View)).
    pub octree_depth: u32,
    /// When failed bricks were last let go to be asked for again (ms;
    /// `None`: not yet timed), and when the store was last checked for a
    /// change, with a check under way.
    retried_at: Option<f64>,
    checked_at: f64,
    checking: Rc<std::cell::Cell<bool>>,
    /// A probe of a server found unreachable is under way; one found it
    /// back (the next [`retry_failed`](Self::retry_failed) lets the failed
    /// bricks go).
    probing: Rc<std::cell::Cell<bool>>,
    back: Rc<std::cell::Cell<bool>>,
}

/// How often bricks that failed to load are asked for again (ms): the
/// native viewer's `RETRY_FAILED_AFTER` (20 s), so that a server back up
/// (or a file repaired) fills the view without a reload.
pub const RETRY_FAILED_AFTER_MS: f64 = 20_000.0;

/// How often, while bricks are being loaded or failing, the store's root
/// document is checked for a change on the server (ms).
pub const CHECK_STORE_EVERY_MS: f64 = 2_000.0;

impl WebSession {
    /// Channel `c` at world point `w` from what is resident: the value and
    /// the level that served it, the finest there is from `level` on
    /// (`None`: nothing resident there). Asks for no brick.
    pub fn value_at(&self, w: [f64; 3], c: usize, level: usize) -> Option<(f32, u8)> {
        let p = brickyard_core::camera::world_to_normalized(w, self.scene.extent);
        let mut req = brickyard_cache::vm::Requests::with_capacity(1);
        let l = self.vm.sample(level, c, p, false, &mut req);
        l.level.map(|lv| (l.value, lv))
    }

    /// The level of detail of this session's last frame (the budget's bias
    /// included), or `lod` before there is one.
    pub fn drawn_lod(&self, lod: Lod) -> Lod {
        self.drawn.as_ref().map_or(lod, |(_, l)| *l)
    }

    /// The level this session's frames draw where a pixel spans
    /// `footprint` ([`drawn_lod`](Self::drawn_lod) of `lod`).
    pub fn level_drawn(&self, footprint: f64, lod: Lod) -> usize {
        self.drawn_lod(lod)
            .level_for(footprint, self.scene.voxel(0), self.scene.levels.len())
    }

    /// A session over `src` with a pool of `cfg.pool_bytes`; starts
    /// loading the coarsest level (and finer ones while they stay within
    /// an eighth of the pool), which stays resident for good once in.
    /// A pool too small for that is refused
    /// ([`view::pool_too_small`](crate::view::pool_too_small) says it in
    /// the page's words).
    pub fn new(
        src: Rc<WebSource>,
        cfg: VmConfig,
        spawn: Spawn,
        max_loads: usize,
    ) -> Result<WebSession, PoolTooSmall> {
        let g = src.geometry.clone();
        let vm = VirtualMemory::new(&g.levels, g.channels, g.dtype, cfg);
        let slots = vm.pool_slots();
        let slot_bytes = vm.slot_bytes() as u64;
        let levels = g.pinned_levels(slots, slot_bytes, 512)?;
        let mut keys = vec![];
        for &l in &levels {
            for c in 0..g.channels {
                keys.extend(g.keys(l, c));
            }
        }
        let ms = &src.meta;
        let extent = brickyard_core::camera::world_extent(g.levels[0], ms.spacing);
        let scene = Scene::new(extent, g.levels.clone());
        let loads = Loads::new(src, spawn, max_loads);
        loads.request(&keys);
        Ok(WebSession {
            vm,
            loads,
            scene,
            waiting: VecDeque::new(),
            failures: vec![],
            pin: Some(keys.into_iter().collect()),
            pinned: vec![],
            budget: None,
            drawn: None,
            image: Image::new(0, 0),
            tiles: Tiles::all(0, 0),
            pass: None,
            octree_depth: DEFAULT_DEPTH,
            retried_at: None,
            checked_at: f64::NEG_INFINITY,
            checking: Rc::default(),
            probing: Rc::default(),
            back: Rc::default(),
        })
    }

    /// Bricks that failed and are not asked for now (drawn from coarser
    /// data) until [`retry_failed`](Self::retry_failed) lets them go.
    pub fn failing(&self) -> usize {
        self.vm.failed_count()
    }

    /// At `now_ms`: every [`RETRY_FAILED_AFTER_MS`] while bricks are
    /// failing, forget which failed so that the next frames ask for them
    /// again, as the native viewer does (`Session::retry_failed`); the
    /// failures stay in [`failures`](Self::failures). Not once the store
    /// changed on the server (nothing more is read of it). Returns whether
    /// it let them go (the view is then drawn again).
    ///
    /// While the server is unreachable ([`WebSource::unreachable`]) nothing
    /// is let go: every [`RETRY_FAILED_AFTER_MS`] one request
    /// ([`WebSource::probe`]) asks whether it is back, and the first call
    /// after an answer lets the failed bricks go (and the view, drawn
    /// again, asks for what it had not asked for). A server still gone
    /// costs that one request, not a view reset and a request per brick.
    pub fn retry_failed(&mut self, now_ms: f64) -> bool {
        let at = *self.retried_at.get_or_insert(now_ms);
        let src = self.loads.src.clone();
        if src.changed() {
            return false;
        }
        if src.unreachable() {
            if now_ms - at >= RETRY_FAILED_AFTER_MS && !self.probing.get() {
                self.retried_at = Some(now_ms);
                self.probing.set(true);
                let (probing, back) = (self.probing.clone(), self.back.clone());
                (self.loads.spawn)(Box::pin(async move {
                    if src.probe().await {
                        back.set(true);
                    }
                    probing.set(false);
                }));
            }
            return false;
        }
        if self.back.take() {
            self.retried_at = Some(now_ms);
            self.vm.clear_failed();
            return true;
        }
        if self.vm.failed_count() == 0 || now_ms - at < RETRY_FAILED_AFTER_MS {
            return false;
        }
        self.retried_at = Some(now_ms);
        self.vm.clear_failed();
        true
    }

    /// Whether the server was found unreachable: nothing is asked of it
    /// (but a probe every [`RETRY_FAILED_AFTER_MS`]), and the view is drawn
    /// from what it has.
    pub fn unreachable(&self) -> bool {
        self.loads.src.unreachable()
    }

    /// At `now_ms`: while bricks are being loaded or failing, every
    /// [`CHECK_STORE_EVERY_MS`], ask the server whether the store changed
    /// since it was opened ([`WebSource::check_changed`], one check at a
    /// time, beside the loads): a store reconverted in place is then no
    /// longer read, rather than old and new data mixed.
    pub fn check_store(&mut self, now_ms: f64) {
        let (q, f) = self.loads.pending();
        let busy = q + f > 0 || self.vm.failed_count() > 0 || !self.ready();
        if !busy
            || self.unreachable()
            || self.checking.get()
            || now_ms - self.checked_at < CHECK_STORE_EVERY_MS
            || self.loads.src.changed()
        {
            return;
        }
        self.checked_at = now_ms;
        self.checking.set(true);
        let (src, checking) = (self.loads.src.clone(), self.checking.clone());
        (self.loads.spawn)(Box::pin(async move {
            src.check_changed().await;
            checking.set(false);
        }));
    }

    /// Bricks that arrived and wait to be drawn with.
    pub fn news(&self) -> usize {
        self.loads.arrived() + self.waiting.len()
    }

    /// Whether the coarsest levels are in (every sample finds data).
    pub fn ready(&self) -> bool {
        self.pin.is_none()
    }

    fn collect(&mut self) -> usize {
        let (arrived, failed) = self.loads.take();
        for (k, _) in &failed {
            self.vm.mark_failed(*k);
        }
        let n = failed.len();
        if let Some(pin) = &mut self.pin {
            for b in &arrived {
                pin.remove(&b.key);
            }
            for (k, _) in &failed {
                pin.remove(k);
            }
            self.pinned.extend(arrived);
            if pin.is_empty() {
                let mut rest = &self.pinned[..];
                while !rest.is_empty() {
                    let r = self.vm.insert(rest);
                    if r.processed == 0 {
                        break;
                    }
                    rest = &rest[r.processed..];
                }
                for b in std::mem::take(&mut self.pinned) {
                    self.vm.pin(b.key);
                }
                self.pin = None;
            }
        } else {
            self.waiting.extend(arrived);
        }
        self.failures.extend(failed);
        n
    }

    /// Draw a frame of the view `p` at `lod` (the user's level of detail)
    /// on the CPU into [`image`](Self::image), then end it: requests out,
    /// arrivals in. The same view as the last frame redraws only the tiles
    /// not settled then; a pool too small for the view raises its LOD bias
    /// (detail is lost, never completeness), and lowers it again when room
    /// is back.
    pub fn frame_cpu(&mut self, p: &RenderParams, lod: Lod) -> FrameOut {
        self.frame_cpu_part(p, lod, None)
    }

    /// [`frame_cpu`](Self::frame_cpu), drawing at most `max_tiles` of the
    /// frame's tiles per call (`None`: all): a call that leaves tiles to
    /// draw ends nothing (no requests out, no arrivals in, never complete;
    /// [`FrameOut::tiles_left`] says how many), and the next call of the
    /// same view goes on with them; the call that draws the last ends the
    /// frame with the figures of all its parts. A changed view drops a
    /// frame begun. Each part takes tiles spread over the whole frame, so
    /// that parts cost alike.
    pub fn frame_cpu_part(
        &mut self,
        p: &RenderParams,
        lod: Lod,
        max_tiles: Option<usize>,
    ) -> FrameOut {
        let (drawn, failed) = match self.prepare(p, lod) {
            Ok(x) => x,
            Err(out) => return *out,
        };
        let mut pass = match self.pass.take() {
            Some(pass) => pass,
            None => {
                self.vm.begin_frame();
                Pass {
                    left: (0..self.tiles.redo.len())
                        .filter(|&i| self.tiles.redo[i])
                        .collect(),
                    ..Pass::default()
                }
            }
        };
        pass.failed += failed;
        // This part's tiles: every k-th of those left, k so that at most
        // `max_tiles` are taken.
        let n = pass.left.len();
        let step = max_tiles.map_or(1, |m| n.div_ceil(m.max(1)).max(1));
        let mut now = vec![false; self.tiles.redo.len()];
        let mut rest = Vec::with_capacity(n);
        for (j, i) in pass.left.drain(..).enumerate() {
            if j % step == 0 {
                now[i] = true;
            } else {
                rest.push(i);
            }
        }
        pass.left = rest;
        let drawn_now = n - pass.left.len();
        // Draw those tiles only; the others keep their marks.
        let marks = std::mem::replace(&mut self.tiles.redo, now.clone());
        let (stats, reqs) = render_tiles(
            &self.vm,
            &self.scene,
            p,
            drawn,
            &mut self.image,
            &mut self.tiles,
        );
        for (i, m) in marks.into_iter().enumerate() {
            if !now[i] {
                self.tiles.redo[i] = m;
            }
        }
        pass.stats.add(&stats);
        pass.reqs.extend(reqs);
        if !pass.left.is_empty() {
            let tiles_left = pass.left.len();
            self.pass = Some(pass);
            let (queued, in_flight) = self.loads.pending();
            return FrameOut {
                stats,
                queued,
                in_flight,
                failed,
                bias: self.budget.as_ref().map_or(0.0, |b| b.bias),
                tiles_drawn: drawn_now,
                tiles_left,
                ..Default::default()
            };
        }
        let mut out = self.finish(pass.stats, pass.reqs.iter(), pass.failed);
        out.tiles_drawn = drawn_now;
        out
    }

    /// A frame is being drawn in parts ([`frame_cpu_part`](Self::frame_cpu_part)).
    pub fn in_parts(&self) -> bool {
        self.pass.is_some()
    }

    /// Start a frame of `p` at the user's `lod`: arrivals taken in, the
    /// LOD budget applied. `Ok((level of detail to draw, failures taken))`,
    /// or the frame's figures when the coarsest levels are not in yet.
    /// Between this and [`finish`](Self::finish) a renderer draws from
    /// [`vm`](Self::vm) (begun with `begin_frame`).
    pub fn prepare(&mut self, p: &RenderParams, lod: Lod) -> Result<(Lod, usize), Box<FrameOut>> {
        let failed = self.collect();
        let nl = self.scene.levels.len();
        let base = match lod {
            Lod::Auto { bias } => bias,
            Lod::Fixed(_) => 0.0,
        };
        if self.budget.as_ref().is_none_or(|b| b.base != base) {
            self.budget = Some(LodBudget::new(base, nl, true));
        }
        let budget = self.budget.as_mut().expect("set above");
        let drawn = budget.apply(lod, nl);
        let same = self
            .drawn
            .as_ref()
            .is_some_and(|(q, l)| q == p && *l == drawn);
        if !same {
            if self.drawn.as_ref().is_some_and(|(q, _)| q != p) {
                budget.view_changed();
            }
            self.image = Image::new(p.width, p.height);
            self.tiles = Tiles::all(p.width, p.height);
            self.drawn = Some((p.clone(), drawn));
            self.pass = None;
        }
        if !self.ready() {
            let (q, f) = self.loads.pending();
            return Err(Box::new(FrameOut {
                queued: q,
                in_flight: f,
                failed,
                bias: base,
                ..Default::default()
            }));
        }
        let depth = self.octree_depth;
        if p.traversal == Traversal::Octree
            && self
                .scene
                .octree
                .as_ref()
                .is_none_or(|o| o.read().expect("octree lock").depth != depth)
        {
            self.attach_octree();
        }
        Ok((drawn, failed))
    }

    /// Take in the store's brick statistics ([`WebSource::brick_ranges`],
    /// levels of up to `max_bricks` bricks × channels): frames then cross
    /// the bricks their transfer function hides without asking for them,
    /// as `render` does. Returns what could not be read, for the page to
    /// report.
    pub async fn read_ranges(&mut self, max_bricks: u64) -> Vec<String> {
        let src = self.loads.src.clone();
        let (ranges, problems) = src.brick_ranges(max_bricks).await;
        self.scene.ranges = Some(Arc::new(ranges));
        problems
    }

    /// The residency octree of depth [`octree_depth`](Self::octree_depth)
    /// over the virtual memory as it is now, kept in the scene for DVR
    /// through it (`traversal=octree`): from here on every frame's end
    /// brings it up to date with what was mapped and evicted (as `render
    /// --traversal octree` keeps its own). Attached by the first frame
    /// that asks for it, again when the depth changes, and kept: views
    /// through the page tables ignore it. (`ViewState::params` refused the
    /// views whose octree cannot be made.)
    fn attach_octree(&mut self) {
        let o = Octree::attach(
            self.octree_depth,
            &self.scene.levels,
            &mut self.vm,
            self.scene.ranges.as_deref(),
        )
        .expect("ViewState::params checked that this octree can be made");
        self.scene.octree = Some(Arc::new(RwLock::new(o)));
    }

    /// End a frame drawn after [`prepare`](Self::prepare) with these
    /// figures and requests.
    pub fn finish<'a>(
        &mut self,
        stats: FrameStats,
        reqs: impl IntoIterator<Item = &'a brickyard_cache::vm::Requests>,
        failed: usize,
    ) -> FrameOut {
        let arrived_before = self.waiting.len();
        let mut out = self.end_frame(reqs);
        // (With the server unreachable, nothing asked for can come: the
        // view is drawn from what it has, as if all of it had failed.)
        let down = self.unreachable();
        let failed_in_list = out
            .frame
            .requests
            .iter()
            .filter(|k| down || self.vm.is_failed(**k))
            .count();
        let sig = FrameSignals {
            complete: stats.completeness() >= 1.0,
            requests: out.frame.requests.len() - failed_in_list,
            requested: out.frame.requested.saturating_sub(failed_in_list),
            deferred: out.insert.deferred,
            exact_slots: Some(out.frame.exact_slots),
            free_slots: self.vm.pool_slots() - self.vm.pinned_bricks(),
            progress: out.insert.inserted + out.insert.flagged + arrived_before > 0
                || out.queued + out.in_flight > 0,
            evicted_in_use: out.insert.evicted_in_use,
        };
        let budget = self.budget.as_mut().expect("set by prepare");
        let decision = budget.update(&sig);
        out.bias = budget.bias;
        out.failed = failed;
        // Complete: every sample at its own level, or nothing left to ask
        // for but bricks that failed (drawn from coarser data).
        out.complete = matches!(decision, Decision::Continue)
            && (sig.complete
                || (sig.requests == 0 && !sig.progress && (stats.unserved == 0 || down)));
        out.stats = stats;
        out
    }

    /// The last image drawn.
    pub fn image(&self) -> &Image {
        &self.image
    }

    /// End a frame whose requests are in `reqs`.
    pub fn end_frame<'a>(
        &mut self,
        reqs: impl IntoIterator<Item = &'a brickyard_cache::vm::Requests>,
    ) -> FrameOut {
        let frame = self.vm.end_frame(reqs);
        // (Nothing is asked of a server found unreachable: queued loads
        // are dropped too.)
        let down = self.unreachable();
        let wanted: Vec<BrickKey> = frame
            .requests
            .iter()
            .filter(|k| !down && !self.vm.is_resident(**k) && !self.vm.is_failed(**k))
            .copied()
            .collect();
        self.loads.request(&wanted);
        let batch: Vec<Arc<LoadedBrick>> = self.waiting.iter().cloned().collect();
        let insert = self.vm.insert(&batch);
        self.waiting.drain(..insert.processed);
        if let Some(o) = &self.scene.octree {
            o.write().expect("octree lock").sync(&mut self.vm);
        }
        let keep = self.vm.config().request_cap * 2;
        while self.waiting.len() > keep {
            self.waiting.pop_back();
        }
        let (queued, in_flight) = self.loads.pending();
        FrameOut {
            frame,
            insert,
            queued,
            in_flight,
            ..Default::default()
        }
    }
}

/// The readout under pixel position `(x, y)` of `view`: the world point,
/// the image's level-0 voxel there, each channel's value with the level
/// that served it (from what is resident: the finest level there is), and
/// the label drawn there (its value rounded) where labels are drawn: of
/// `labels` laid over a slice, or of the image when it is a label image,
/// read at the level the frames draw there (or the finest resident coarser
/// one, as they draw it). A slice's point is where the pixel's ray meets
/// the plane; a 3D view's, the point it shows along the ray
/// ([`readout::seen_point`]: the MIP's maximum, the DVR's half-opacity
/// point, the first label drawn), named under `"seen"`. `None` off the
/// volume, where nothing is drawn along the ray, and for several views.
pub fn probe(
    view: &crate::view::View,
    image: &WebSession,
    labels: Option<&WebSession>,
    x: f64,
    y: f64,
) -> Option<serde_json::Value> {
    let p = &view.params;
    let extent = image.scene.extent;
    // A label image shown itself is its own labels.
    let labels = labels.or(p.labels.then_some(image));
    let (w, label_level, seen) = match view.slice_point(extent, x, y) {
        Some((w, footprint)) => {
            let level = labels.map(|s| s.level_drawn(footprint, view.lod));
            (w, level, None)
        }
        None => {
            // (Slices off the volume, several views: nothing.)
            let look = readout::Look::of(p, view.channel)?;
            let drawn = readout::Drawn {
                camera: p.camera,
                height: p.height,
                lod: image.drawn_lod(view.lod),
            };
            let ray = p.camera.ray(x, y, p.width, p.height);
            let found = readout::seen_point::<()>(
                &ray,
                extent,
                &image.scene.levels,
                &drawn,
                &look,
                |l, w, c| Ok(image.value_at(w, c, l).map(|(v, _)| v as f64)),
            );
            let (w, level, value) = found.ok()??;
            let served = image
                .value_at(w, look.first_channel(), level)
                .map(|(_, l)| l);
            let seen = serde_json::json!({
                "how": look.name(), "value": value, "level": served.unwrap_or(level as u8),
            });
            (w, labels.map(|_| level), Some(seen))
        }
    };
    let voxel = brickyard_core::camera::world_to_voxel(w, extent, image.vm.layout().levels[0]);
    let values: Vec<serde_json::Value> = (0..image.vm.channels())
        .map(|c| match image.value_at(w, c, 0) {
            Some((v, l)) => serde_json::json!({ "value": v, "level": l }),
            None => serde_json::Value::Null,
        })
        .collect();
    // The label drawn there.
    let label = labels
        .zip(label_level)
        .map(|(s, level)| match s.value_at(w, 0, level) {
            Some((v, l)) => serde_json::json!({ "label": (v as f64 + 0.5).floor(), "level": l }),
            None => serde_json::Value::Null,
        });
    let mut j = serde_json::json!({ "world": w, "voxel_zyx": voxel, "values": values });
    // (No `labels` key without labels drawn; null where none is loaded.)
    if let Some(l) = label {
        j["labels"] = l;
    }
    if let Some(s) = seen {
        j["seen"] = s;
    }
    Some(j)
}
