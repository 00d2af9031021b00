//! The viewer's window: its state, the frame loop and the frames that come
//! back from the render thread. A 3D view (DVR, MIP, or the oblique plane
//! seen in perspective) and four slice views (xy, xz, yz through the
//! cursor, and an oblique plane), the controls, the transfer-function
//! editor and a live status line. Drawing happens on the render thread
//! (`worker`); the window only sends what each view should show and shows
//! the frames that come back, so it never waits for data.
//!
//! What each view shows and where it sits on screen is in `layout`; the
//! controls, the editor and the views' panels are in `panels`; mouse, keys
//! and scripts go through `input`; screenshots and saved views are in
//! `save`.

mod input;
mod layout;
mod panels;
mod process;
mod save;

pub use process::derived_dataset;

use super::probe::{Look, Probe};
use super::script::{Step, VIEWS};
use super::worker::{Msg, Out, Reply, Setup, Spec};
use brickyard_core::camera::{scale, Camera, Projection};
use brickyard_core::{DType, Dims3, TransferFunction};
use brickyard_render::Image;
use eframe::egui;
use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::AtomicI32;
use std::sync::mpsc::{Receiver, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

type Vec3 = [f64; 3];

/// What the window knows of the dataset (or of the derived channel shown).
#[derive(Clone)]
pub struct Dataset {
    pub store: PathBuf,
    pub extent: Vec3,
    pub levels: Vec<Dims3>,
    pub dtype: DType,
    pub channels: usize,
    /// The data range (from the store's statistics).
    pub range: [f32; 2],
    /// Brick counts per value bin over `range`, from the bricks' value
    /// ranges (each brick spread evenly over its range).
    pub histogram: Vec<f32>,
    /// A label image (`StoreInfo::label_image`): its slices and 3D view
    /// show each label in its own colour.
    pub labels: bool,
}

const N_VIEWS: usize = 5;
/// Colours given to channels 0, 1, 2, … (RRGGBB, as `render --channel`
/// takes them).
const CHANNEL_COLORS: [[u8; 3]; 6] = [
    [0, 255, 0],
    [255, 0, 255],
    [0, 255, 255],
    [255, 128, 0],
    [255, 255, 255],
    [255, 0, 0],
];

struct ChannelUi {
    visible: bool,
    color: [u8; 3],
    window: [f32; 2],
    /// DVR of several channels: the finest and coarsest level it is drawn
    /// at (`None`: every level).
    levels: Option<[usize; 2]>,
}

#[derive(Default)]
struct ViewState {
    version: u64,
    sent: Option<Spec>,
    texture: Option<egui::TextureHandle>,
    last: Option<Box<Out>>,
    /// Fixed render size (scripts); else the size on screen.
    forced: Option<[u32; 2]>,
    /// Render size from the last layout.
    size: [u32; 2],
    /// Frames shown with partial data since the last check.
    streaming: usize,
    frames: u64,
    zoom: f64,
    pan: [f64; 2],
}

/// A label image laid over the slice views (`view --labels NAME`): its
/// own render thread and session draw each slice view's labels, which the
/// window lays over the image's frame at `opacity`.
pub struct LabelLayer {
    name: String,
    tx: Sender<Msg>,
    rx: Receiver<Reply>,
    opacity: f32,
    shown: bool,
    /// The label image's levels (a fixed level beyond them takes its
    /// coarsest).
    levels: usize,
    /// Its level-0 voxel (smallest edge, world units).
    voxel0: f64,
    views: Vec<LabelView>,
    /// The label session's figures from its latest frame: bricks
    /// resident, pool slots, requests pending, bricks unreadable.
    figures: [usize; 4],
}

/// What the label thread was asked to draw for one view, and its last
/// frame.
#[derive(Default)]
struct LabelView {
    version: u64,
    sent: Option<Spec>,
    last: Option<Box<Out>>,
}

impl LabelLayer {
    pub fn new(
        name: String,
        tx: Sender<Msg>,
        rx: Receiver<Reply>,
        opacity: f32,
        levels: usize,
        voxel0: f64,
    ) -> LabelLayer {
        LabelLayer {
            name,
            tx,
            rx,
            opacity,
            shown: true,
            levels: levels.max(1),
            voxel0,
            views: (0..N_VIEWS).map(|_| LabelView::default()).collect(),
            figures: [0; 4],
        }
    }
}

pub struct ViewerApp {
    ds: Arc<Dataset>,
    setup: Setup,
    tx: Sender<Msg>,
    rx: Receiver<Reply>,
    mode: String,
    cam: Camera,
    home: Camera,
    tf: TransferFunction,
    dvr_channel: usize,
    /// DVR composites the visible channels (each through its colour and
    /// window) instead of showing `dvr_channel` through `tf`.
    dvr_channels: bool,
    /// The 3D view's views: "off", "sbs", "anaglyph" or "tiles" (of
    /// `n_views`).
    stereo: String,
    n_views: u32,
    channels: Vec<ChannelUi>,
    cursor: Vec3,
    oblique: [f64; 2],
    lod_bias: f64,
    level: Option<usize>,
    quality: f64,
    views: Vec<ViewState>,
    pool_mib: f64,
    host_mib: f64,
    script: Vec<Step>,
    pc: usize,
    waiting: Option<Instant>,
    window_shot: Option<PathBuf>,
    shot: Arc<std::sync::Mutex<Option<Arc<egui::ColorImage>>>>,
    log: Option<std::fs::File>,
    message: String,
    exit: Arc<AtomicI32>,
    started: Instant,
    interacting: Instant,
    read_history: Vec<(Instant, u64)>,
    drag_point: Option<usize>,
    /// Milliseconds of the last full-size redraw of the 3D view (the first
    /// frame of a version of the view: later frames draw only the tiles
    /// still missing data), and that version.
    full_ms: f64,
    full_ms_version: Option<u64>,
    /// The fraction of its size the 3D view's last frame while moving was
    /// drawn at (1: full size, or none yet).
    moving_last: f64,
    counter: u32,
    camera_path: String,
    /// Load failures reported so far, and the latest (the status line).
    failures_seen: usize,
    last_failure: Option<String>,
    /// The store's dataset (`ds` is the derived channel's while one is
    /// shown).
    stored: Arc<Dataset>,
    /// The pipeline typed in the processing panel.
    derive_text: String,
    /// The live derived channel shown: pipeline and the store's channel it
    /// is computed from; with the transfer-function window of the stored
    /// data, to go back to.
    derived: Option<Shown>,
    /// The whole-volume job running, its name field, and how the last one
    /// ended.
    job: Option<process::Job>,
    job_name: String,
    last_job: Option<process::JobEnd>,
    /// `--labels NAME`: the label image over the slices.
    labels: Option<LabelLayer>,
    /// The voxel readout (`None`: its readers could not be opened).
    probe: Option<Probe>,
    /// The world point under the pointer in a slice view this frame, and
    /// the level the labels drawn there come from.
    hover: Option<(Vec3, usize)>,
    /// The render pixel under the pointer in the 3D view, this frame.
    hover_3d: Option<(f64, f64)>,
    /// A script's pointer: view and render pixel (`hover`).
    script_hover: Option<(usize, f64, f64)>,
    /// A double-click (script: `click 3d`) in the 3D view waiting for the
    /// point it shows there, to move the cursor to: the render pixel, and
    /// the question's id once asked.
    seek: Option<((f64, f64), Option<u64>)>,
    /// Why the readout cannot follow the pointer over the 3D view.
    seen_note: Option<String>,
    /// Whether the display's pointer is read out (not in a script's
    /// session until it moves after the script).
    display_pointer: bool,
    /// Whether the latest question was about the pointer (else the
    /// cursor).
    probe_pointer: bool,
    /// Labels picked (Ctrl+click, the controls, scripts) and what is drawn
    /// of a label image: every label (0), only those picked (1) or all but
    /// them (2).
    picked: Vec<i32>,
    label_mode: u8,
    /// The controls' text of the labels picked.
    picked_text: String,
    /// A pick waiting for the readout: the world point clicked, and the
    /// level the labels drawn there come from.
    pick: Option<(Vec3, usize)>,
    /// A label whose centroid the cursor is to go to, once its row of the
    /// statistics is found.
    goto: Option<u64>,
    /// The label table was asked for, and its order.
    largest_asked: bool,
    table_order: super::probe::TableOrder,
    /// A pick in the 3D view waiting for the first label along its ray.
    pick3d: bool,
}

/// A live derived channel shown: its pipeline, the store's channel it is
/// computed from, and the transfer-function window of the stored data.
pub type Shown = (String, usize, [f32; 2]);

impl ViewerApp {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ds: Arc<Dataset>,
        setup: Setup,
        tx: Sender<Msg>,
        rx: Receiver<Reply>,
        camera: Option<Camera>,
        tf: TransferFunction,
        mode: String,
        script: Vec<Step>,
        log: Option<std::fs::File>,
        exit: Arc<AtomicI32>,
        derived: Option<(Arc<Dataset>, Shown)>,
        labels: Option<LabelLayer>,
        probe: Option<Probe>,
    ) -> ViewerApp {
        let display_pointer = script.is_empty();
        // Started on a derived channel: `ds` is its dataset, and the
        // store's comes with it.
        let (stored, derived) = match derived {
            Some((st, shown)) => (st, Some(shown)),
            None => (ds.clone(), None),
        };
        let home = Camera::fit(
            ds.extent,
            30.0,
            20.0,
            Projection::Perspective { fov_y_deg: 35.0 },
        );
        // Colours and windows from the store's `omero` metadata where it
        // has them.
        let omero = brickyard_store::omezarr::read_omero(&stored.store)
            .ok()
            .flatten()
            .unwrap_or_default();
        let channels = (0..stored.channels)
            .map(|c| match omero.get(c) {
                Some(o) => ChannelUi {
                    visible: o.active && c < 3,
                    color: o.color,
                    window: o
                        .window
                        .map_or(stored.range, |w| [w[0] as f32, w[1] as f32]),
                    levels: None,
                },
                None => ChannelUi {
                    visible: c < 3,
                    color: CHANNEL_COLORS[c % CHANNEL_COLORS.len()],
                    window: stored.range,
                    levels: None,
                },
            })
            .collect();
        let views = (0..N_VIEWS)
            .map(|_| ViewState {
                zoom: 1.0,
                size: [256, 256],
                ..Default::default()
            })
            .collect();
        ViewerApp {
            derive_text: derived.as_ref().map(|d| d.0.clone()).unwrap_or_default(),
            derived,
            stored,
            job: None,
            job_name: "processed".into(),
            last_job: None,
            cursor: scale(ds.extent, 0.5),
            pool_mib: setup.cfg.pool_bytes as f64 / (1 << 20) as f64,
            host_mib: setup.host_bytes as f64 / (1 << 20) as f64,
            ds,
            setup,
            tx,
            rx,
            mode,
            cam: camera.unwrap_or(home),
            home,
            tf,
            dvr_channel: 0,
            dvr_channels: false,
            stereo: "off".into(),
            n_views: 4,
            channels,
            oblique: [30.0, 30.0],
            lod_bias: 0.0,
            level: None,
            quality: 1.0,
            views,
            script,
            pc: 0,
            waiting: None,
            window_shot: None,
            shot: Default::default(),
            log,
            message: String::new(),
            exit,
            started: Instant::now(),
            interacting: Instant::now() - Duration::from_secs(10),
            read_history: vec![],
            drag_point: None,
            full_ms: 40.0,
            full_ms_version: None,
            moving_last: 1.0,
            counter: 0,
            camera_path: String::new(),
            failures_seen: 0,
            last_failure: None,
            labels,
            probe,
            hover: None,
            script_hover: None,
            hover_3d: None,
            seek: None,
            seen_note: None,
            display_pointer,
            probe_pointer: false,
            picked: vec![],
            label_mode: 0,
            picked_text: String::new(),
            pick: None,
            goto: None,
            largest_asked: false,
            table_order: super::probe::TableOrder::LARGEST,
            pick3d: false,
        }
    }

    // ---- frames from the worker ----------------------------------------

    fn take_frames(&mut self, ctx: &egui::Context) {
        // Every frame that came is taken in (logged, counted), but only
        // each view's latest is turned into its texture: the conversion
        // costs a few milliseconds of a core that the renderer shares.
        let mut shown = [false; N_VIEWS];
        while let Ok(r) = self.rx.try_recv() {
            match r {
                Reply::Error(e) => {
                    self.message = format!("error: {e}");
                    if !self.script.is_empty() {
                        eprintln!("view: {e}");
                        self.fail(ctx, &e);
                    }
                }
                Reply::Note(v, note) => self.note(v, note, ""),
                Reply::Frame(out) => {
                    shown[out.view] = true;
                    self.show_frame(out);
                }
            }
        }
        for v in (0..N_VIEWS).filter(|&v| shown[v]) {
            self.refresh_texture(ctx, v);
        }
        // The labels' frames: each view's latest is laid over the image's.
        let mut got = vec![];
        if let Some(l) = &mut self.labels {
            while let Ok(r) = l.rx.try_recv() {
                got.push(r);
            }
        }
        for r in got {
            match r {
                Reply::Error(e) => {
                    let e = format!("labels: {e}");
                    self.message = format!("error: {e}");
                    if !self.script.is_empty() {
                        eprintln!("view: {e}");
                        self.fail(ctx, &e);
                    }
                }
                Reply::Note(v, note) => self.note(v, note, "labels"),
                Reply::Frame(out) => {
                    let v = out.view;
                    if self.log.is_some() {
                        self.log_line(serde_json::json!({
                            "t": self.started.elapsed().as_secs_f64(),
                            "view": VIEWS[v], "layer": "labels", "version": out.version,
                            "completeness": out.completeness, "render_ms": out.render_ms,
                            "settled": out.settled, "new_failures": out.new_failures,
                        }));
                    }
                    let name = self.labels.as_ref().map_or("", |l| l.name.as_str());
                    let failures: Vec<String> = out
                        .new_failures
                        .iter()
                        .map(|f| format!("labels/{name}: {f}"))
                        .collect();
                    self.report_failures(&failures);
                    if let Some(l) = &mut self.labels {
                        l.figures = [out.resident_bricks, out.pool_slots, out.pending, out.failed];
                        l.views[v].last = Some(out);
                    }
                    self.refresh_texture(ctx, v);
                }
            }
        }
    }

    /// A note from a render thread about view `v` (of `layer`, when not
    /// empty) that fails nothing: said in the status line and logged,
    /// and on stderr when the view gives something up (once per text).
    fn note(&mut self, v: usize, note: String, layer: &str) {
        let text = match layer {
            "" => format!("{}: {note}", VIEWS[v]),
            l => format!("{l}: {}: {note}", VIEWS[v]),
        };
        if self.message == text {
            return;
        }
        if note.starts_with("no accumulation") || note.starts_with("accumulation stopped") {
            eprintln!("view: {text}");
        }
        self.message = text;
        let t = self.started.elapsed().as_secs_f64();
        self.log_line(serde_json::json!({ "t": t, "note": note, "note_view": VIEWS[v] }));
    }

    /// The voxel readout: ask about the point under the pointer (a
    /// script's, else the mouse's over a slice view), else the cursor, and
    /// log the answers that came.
    fn probe(&mut self) {
        // A point in a slice view, or a pixel of the 3D view.
        let pointer = match (self.pick, self.seek, self.script_hover) {
            (Some(w), ..) => Some(Ok(w)),
            (None, Some((px, _)), _) => Some(Err(px)),
            (None, None, Some((0, x, y))) => Some(Err((x, y))),
            (None, None, Some((v, x, y))) => Some(Ok(self.slice_pixel(v, x, y))),
            // (A script's session: its pointer only, not the display's,
            // until that moves after the script.)
            (None, None, None) if !self.display_pointer => None,
            (None, None, None) => self.hover.map(Ok).or(self.hover_3d.map(Err)),
        };
        let seen = match pointer {
            Some(Err((x, y))) => Some(self.seen_question(x, y)),
            _ => None,
        };
        let Some(p) = &mut self.probe else {
            return;
        };
        self.probe_pointer = pointer.is_some();
        self.seen_note = None;
        match (pointer, seen) {
            (Some(Ok((at, level))), _) => p.ask(at, level),
            (_, Some(Ok((ray, drawn, look)))) => {
                let id = p.ask_seen(ray, drawn, look);
                if let Some((_, asked)) = &mut self.seek {
                    asked.get_or_insert(id);
                }
            }
            (_, Some(Err(e))) => {
                // The 3D view draws nothing the readout can follow.
                if self.seek.take().is_some() {
                    self.message = format!("click 3d: {e}");
                }
                self.seen_note = Some(e);
            }
            _ => p.ask(self.cursor, 0),
        }
        let got = p.take();
        let picked = self.pick.is_some() && p.answered();
        for a in got {
            let t = self.started.elapsed().as_secs_f64();
            self.log_line(serde_json::json!({ "t": t, "probe": a.to_json() }));
        }
        if picked {
            self.pick = None;
            self.take_pick();
        }
        self.take_goto();
        self.take_pick3d();
        self.take_seek();
    }

    /// What to ask about render pixel `(x, y)` of the 3D view: its ray,
    /// how the view chose its levels and what it draws; or why the
    /// readout cannot follow it.
    fn seen_question(
        &self,
        x: f64,
        y: f64,
    ) -> Result<(brickyard_core::camera::Ray, super::probe::Drawn, Look), String> {
        if self.stereo != "off" {
            return Err("the 3D view shows several views: no readout".into());
        }
        if self.derived.is_some() {
            return Err("the 3D view shows a derived channel: no readout".into());
        }
        // What the 3D view's frames draw.
        let spec = self.spec(0);
        let look = Look::of(&spec.params, spec.channel)
            .ok_or("the 3D view shows a slice: read it out in the slice views")?;
        let (ray, drawn) = self.ray_3d(x, y);
        Ok((ray, drawn, look))
    }

    /// The ray of render pixel `(x, y)` of the 3D view, and how the view
    /// chose levels along it.
    fn ray_3d(&self, x: f64, y: f64) -> (brickyard_core::camera::Ray, super::probe::Drawn) {
        let [w, h] = self.render_size(0);
        let drawn = super::probe::Drawn {
            camera: self.cam,
            height: h,
            lod: self.drawn_lod(0, None),
        };
        (self.cam.ray(x, y, w, h), drawn)
    }

    /// A double-click in the 3D view was answered: the cursor (and with it
    /// the slices) moves to the point shown there.
    fn take_seek(&mut self) {
        let Some((_, Some(id))) = self.seek else {
            return;
        };
        let Some(a) = self.probe.as_ref().and_then(|p| p.answer.as_ref()) else {
            return;
        };
        if a.id != id {
            return;
        }
        self.message = match (a.seen.map(|s| (s.how, s.hit)), &a.values) {
            (Some((how, true)), Ok(_)) => {
                self.cursor = a.world;
                let [z, y, x] = a.voxel;
                format!("cursor at {how}: voxel x {x} y {y} z {z}")
            }
            (Some((how, false)), _) => format!("click 3d: nothing drawn there ({how})"),
            (_, Err(e)) => format!("click 3d: {e}"),
            (None, _) => "click 3d: no answer about the 3D view".into(),
        };
        self.seek = None;
        let t = self.started.elapsed().as_secs_f64();
        let (m, c) = (self.message.clone(), self.cursor);
        self.log_line(serde_json::json!({ "t": t, "seek": m, "cursor": c }));
    }

    /// Pick the label the 3D view shows at render pixel `(x, y)`: the first
    /// label drawn along the pixel's ray (a label image in DVR mode).
    pub(super) fn pick_3d(&mut self, x: f64, y: f64) -> Result<(), String> {
        if !self.ds.labels || self.mode != "dvr" || self.stereo != "off" {
            return Err(
                "labels are picked in 3D on a label image shown in DVR mode, one view".into(),
            );
        }
        let (ray, drawn) = self.ray_3d(x, y);
        let sel = self.label_selection();
        let Some(p) = &mut self.probe else {
            return Err("the viewer has no voxel readout".into());
        };
        p.ray(ray, sel, drawn);
        self.pick3d = true;
        self.message.clear();
        Ok(())
    }

    fn take_pick3d(&mut self) {
        if !self.pick3d {
            return;
        }
        let Some(hit) = self.probe.as_ref().and_then(|p| p.hit.clone()) else {
            return;
        };
        self.pick3d = false;
        let hit = hit.map(|id| id as i64);
        self.take_picked(hit, "no label along that ray: nothing picked", true);
    }

    /// Move the cursor to label `id`'s centroid (by the label statistics),
    /// once the readout's thread has found its row.
    pub(super) fn goto_label(&mut self, id: u64) -> Result<(), String> {
        let Some(p) = &mut self.probe else {
            return Err("the viewer has no voxel readout".into());
        };
        if p.stats_dims.is_none() {
            return Err("no label image is shown (--labels NAME, or a label image)".into());
        }
        p.find(id);
        self.goto = Some(id);
        self.message.clear();
        Ok(())
    }

    fn take_goto(&mut self) {
        let (Some(id), Some(p)) = (self.goto, &self.probe) else {
            return;
        };
        let (Some((fid, r)), Some(dims)) = (&p.found, p.stats_dims) else {
            return;
        };
        if *fid != id {
            return;
        }
        self.message = match r {
            Ok(Some(row)) => {
                self.cursor = super::probe::centroid_world(row, dims, self.ds.extent);
                let [z, y, x] = row.centroid;
                format!(
                    "label {id}: at its centroid, voxel x {x:.1} y {y:.1} z {z:.1} ({} voxels)",
                    row.voxels
                )
            }
            Ok(None) => format!("label {id}: not in the label statistics"),
            Err(e) => format!("label {id}: {e}"),
        };
        self.goto = None;
        let t = self.started.elapsed().as_secs_f64();
        let (m, c) = (self.message.clone(), self.cursor);
        self.log_line(serde_json::json!({ "t": t, "goto": id, "message": m, "cursor": c }));
    }

    /// The readout answered about the point picked: its label joins the
    /// labels picked, or leaves them.
    fn take_pick(&mut self) {
        let Some(a) = self.probe.as_ref().and_then(|p| p.answer.as_ref()) else {
            return;
        };
        // The label drawn there: of the label image laid over, or of the
        // label image shown itself.
        let id = match &a.label {
            Some(Ok(l)) => Ok(l.label as i64),
            Some(Err(e)) => Err(e.clone()),
            None => Err("no label image is shown".into()),
        };
        self.take_picked(id, "the background is not a label: nothing picked", false);
    }

    /// A pick's label (in a slice, or along a ray in 3D): toggled among the
    /// labels picked (0: `nothing` said), said and logged.
    fn take_picked(&mut self, id: Result<i64, String>, nothing: &str, in_3d: bool) {
        self.message = match id {
            Ok(0) => nothing.into(),
            Ok(id) => {
                self.toggle_picked(id as i32);
                format!("labels picked: {}", self.picked_text)
            }
            Err(e) => format!("pick: {e}"),
        };
        let t = self.started.elapsed().as_secs_f64();
        self.log_line(serde_json::json!({
            "t": t, "picked": self.picked, "label_mode": self.label_mode, "in_3d": in_3d,
        }));
    }

    /// Label `id` joins the labels picked, or leaves them; picking the
    /// first draws only those picked.
    pub(super) fn toggle_picked(&mut self, id: i32) {
        let mut ids = std::mem::take(&mut self.picked);
        match ids.binary_search(&id) {
            Ok(i) => {
                ids.remove(i);
            }
            Err(i) => ids.insert(i, id),
        }
        self.set_picked_ids(ids);
        if self.label_mode == 0 {
            self.label_mode = 1;
        }
    }

    /// The labels picked (any order), and the controls' text of them.
    pub(super) fn set_picked_ids(&mut self, ids: Vec<i32>) {
        let sel = brickyard_render::params::LabelSelect::new(ids, false);
        self.picked_text = sel.ids_text();
        self.picked = sel.ids;
        // Where they lie, from the label statistics, for a label image
        // shown itself in 3D: bricks none of them reaches are crossed.
        if self.ds.labels && !self.picked.is_empty() {
            if let Some(p) = &mut self.probe {
                p.boxes(self.picked.clone());
            }
        }
    }

    /// What the label image draws (`None`: every label).
    pub(super) fn label_selection(&self) -> Option<brickyard_render::params::LabelSelect> {
        (self.label_mode != 0 && !self.picked.is_empty()).then(|| {
            let mut s = brickyard_render::params::LabelSelect::new(
                self.picked.clone(),
                self.label_mode == 2,
            );
            // (With their boxes once the readout's thread has found them.)
            if !s.hide {
                s.boxes = self
                    .probe
                    .as_ref()
                    .and_then(|p| p.boxes.as_ref())
                    .filter(|(ids, _)| *ids == s.ids)
                    .and_then(|(_, b)| b.clone().ok().flatten());
            }
            s
        })
    }

    /// The voxel readout's line of the status bar.
    pub(super) fn probe_line(&self) -> Option<String> {
        if let Some(n) = &self.seen_note {
            return Some(format!("pointer (3D): {n}"));
        }
        let a = self.probe.as_ref()?.answer.as_ref()?;
        let name = self.labels.as_ref().map_or("", |l| l.name.as_str());
        let at = match (a.seen.is_some(), self.probe_pointer) {
            (true, _) => "pointer (3D)",
            (false, true) => "pointer",
            (false, false) => "cursor",
        };
        let stored = if self.derived.is_some() {
            ", stored"
        } else {
            ""
        };
        Some(format!(
            "{at}{stored}: {}",
            a.describe(self.stored.dtype, name)
        ))
    }

    /// One line of the `--log` file (JSON), if there is one.
    pub(super) fn log_line(&mut self, v: serde_json::Value) {
        if let Some(log) = &mut self.log {
            let _ = writeln!(log, "{v}");
        }
    }

    /// Take in a frame of a view (its texture is refreshed by the caller).
    fn show_frame(&mut self, out: Box<Out>) {
        let v = out.view;
        if self.log.is_some() {
            self.log_line(serde_json::json!({
                    "t": self.started.elapsed().as_secs_f64(),
                    "view": VIEWS[v], "version": out.version,
                    "current": out.version == self.views[v].version,
                    "completeness": out.completeness, "render_ms": out.render_ms,
                    "cache_ms": out.cache_ms, "resident_bricks": out.resident_bricks,
                    "pending": out.pending, "bytes_read": out.bytes_read,
                    "up": out.up, "down": out.down,
                    "lod_extra": out.lod_extra, "failed_bricks": out.failed,
                    "settled": out.settled, "new_failures": out.new_failures,
                    "accumulated": out.accumulated, "reblended": out.reblended,
                    "accumulated_fewest": out.accumulated_fewest,
                    "since_change_ms": out.since_change_ms,
                    "octree_nodes": out.octree_nodes, "preview": out.preview,
                    "peak_rss_bytes": crate::memory::peak_rss(),
                    "memory_budget_bytes": self.setup.memory_budget,
            }));
        }
        self.report_failures(&out.new_failures);
        if v == 0
            && [out.image.width, out.image.height] == self.views[0].size
            && !out.reblended
            && out.accumulated.is_none_or(|(k, _)| k == 0)
            && self.full_ms_version != Some(out.version)
        {
            self.full_ms = out.render_ms;
            self.full_ms_version = Some(out.version);
        }
        if v == 0
            && out.version == self.views[0].version
            && !out.preview
            && self.interacting.elapsed() < Duration::from_millis(200)
        {
            self.moving_last = out.image.width as f64 / self.views[0].size[0].max(1) as f64;
        }
        self.read_history.push((Instant::now(), out.bytes_read));
        let cut = Instant::now() - Duration::from_secs(2);
        self.read_history.retain(|(t, _)| *t >= cut);
        let vs = &mut self.views[v];
        vs.frames += 1;
        if out.completeness < 1.0 {
            vs.streaming += 1;
        }
        vs.last = Some(out);
    }

    /// View `v` as shown: its last frame (laid out when it holds several
    /// views), with the labels' last frame of the same size over it while
    /// labels are drawn for it.
    pub(super) fn shown_image(&self, v: usize) -> Option<std::borrow::Cow<'_, Image>> {
        use std::borrow::Cow;
        let vs = &self.views[v];
        let o = vs.last.as_ref()?;
        let mut img = match laid_out(vs.sent.as_ref(), o) {
            Some(i) => Cow::Owned(i),
            None => Cow::Borrowed(&o.image),
        };
        let over = self.labels.as_ref().filter(|l| l.shown).and_then(|l| {
            let lv = &l.views[v];
            lv.sent.as_ref()?;
            let lo = lv.last.as_ref()?;
            ((lo.image.width, lo.image.height) == (img.width, img.height))
                .then_some((&lo.image, l.opacity))
        });
        if let Some((labels, opacity)) = over {
            brickyard_run::labels::overlay(img.to_mut(), labels, opacity).ok()?;
        }
        Some(img)
    }

    /// Upload view `v`'s shown image into its texture.
    pub(super) fn refresh_texture(&mut self, ctx: &egui::Context, v: usize) {
        let Some(img) = self.shown_image(v) else {
            return;
        };
        let rgba = img.to_rgba8([0.0, 0.0, 0.0, 1.0]);
        // Over an opaque background every pixel is opaque, where
        // premultiplied and straight colours agree (and egui skips a
        // conversion per pixel).
        let ci = egui::ColorImage::from_rgba_premultiplied(
            [img.width as usize, img.height as usize],
            &rgba,
        );
        drop(img);
        let vs = &mut self.views[v];
        match &mut vs.texture {
            Some(t) => t.set(ci, egui::TextureOptions::LINEAR),
            None => {
                vs.texture =
                    Some(ctx.load_texture(format!("view-{v}"), ci, egui::TextureOptions::LINEAR))
            }
        }
    }

    /// Unreadable bricks (of the image, or of the labels over it):
    /// reported on stderr (the first ones; a store removed under the view
    /// fails every brick it still needed) and in the status line; the view
    /// goes on with coarser data.
    fn report_failures(&mut self, failures: &[String]) {
        const SHOWN: usize = 20;
        for f in failures {
            self.failures_seen += 1;
            if self.failures_seen <= SHOWN {
                eprintln!("view: cannot load {f} (drawn from coarser data)");
            } else if self.failures_seen == SHOWN + 1 {
                eprintln!("view: more bricks cannot be loaded; the status line counts them");
            }
            self.last_failure = Some(f.clone());
        }
    }

    fn complete(&self, v: usize) -> bool {
        let done = |o: &Out, version: u64| {
            o.version == version
                && !o.preview
                && (o.settled || (o.completeness >= 1.0 && o.accumulated.is_none()))
        };
        let vs = &self.views[v];
        // With labels over it, their frame must be complete too.
        let labels_done = self.labels.as_ref().is_none_or(|l| {
            let lv = &l.views[v];
            lv.sent.is_none() || lv.last.as_ref().is_some_and(|o| done(o, lv.version))
        });
        labels_done && vs.last.as_ref().is_some_and(|o| done(o, vs.version))
    }
}

impl eframe::App for ViewerApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let ctx = ui.ctx().clone();
        self.take_frames(&ctx);
        self.poll_job();
        self.take_window_shot(&ctx);
        self.run_script(&ctx);
        self.keys(&ctx);
        self.hover = None;
        self.hover_3d = None;
        if !self.display_pointer && self.pc >= self.script.len() {
            self.display_pointer = ctx.input(|i| i.pointer.is_moving());
        }
        self.lay_out(ui);
        self.probe();
        self.send_specs();
        // Keep polling while frames are due; the worker also wakes the
        // window when one arrives.
        let busy = (0..N_VIEWS).any(|v| !self.complete(v))
            || self.pc < self.script.len()
            || self.job.is_some()
            || self.interacting.elapsed() < Duration::from_millis(300);
        if busy {
            ctx.request_repaint_after(Duration::from_millis(30));
        }
    }

    fn on_exit(&mut self, _gl: Option<&eframe::glow::Context>) {
        let _ = self.tx.send(Msg::Quit);
        if let Some(l) = &self.labels {
            let _ = l.tx.send(Msg::Quit);
        }
        if let Some(mut j) = self.job.take() {
            j.stop();
            eprintln!(
                "view: stopped writing {} as {}; the store is as it was",
                j.pipeline, j.name
            );
        }
    }
}

/// A frame of several views laid out for the screen as the view's spec
/// says (`None`: one view, or a frame of another size, from an older
/// spec, shown as it is).
pub(super) fn laid_out(
    sent: Option<&crate::view::worker::Spec>,
    out: &crate::view::worker::Out,
) -> Option<brickyard_render::Image> {
    let sp = sent?;
    let (views, layout) = (sp.params.views?, sp.layout.as_ref()?);
    let img = &out.image;
    if [img.width, img.height] != [sp.params.width, sp.params.height] {
        return None;
    }
    brickyard_render::views::compose(img, views.count, layout, [0.0, 0.0, 0.0, 1.0]).ok()
}
