//! The viewer's window: a 3D view (DVR, MIP, or the oblique plane seen in
//! perspective) and four slice views (xy, xz, yz through the cursor, and
//! an oblique plane), the controls, the transfer-function editor and a
//! live status line. Drawing happens on the render thread (`worker`);
//! the window only sends what each view should show and shows the frames
//! that come back, so it never waits for data.

use super::script::{Cmd, VIEWS};
use super::worker::{Msg, Out, Reply, Setup, Spec};
use anyhow::{bail, Context, Result};
use brickyard_core::camera::{add, dot, length, normalize, scale, sub, Camera, Projection};
use brickyard_core::transfer::{ColorMap, Preset};
use brickyard_core::{DType, Dims3, TransferFunction};
use brickyard_render::cpu::Lod;
use brickyard_render::reference::{ChannelStyle, RenderMode, RenderParams};
use brickyard_store::info::human_bytes;
use eframe::egui;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicI32, Ordering};
use std::sync::mpsc::{Receiver, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

type Vec3 = [f64; 3];

/// What the window knows of the dataset.
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
    channels: Vec<ChannelUi>,
    cursor: Vec3,
    oblique: [f64; 2],
    lod_bias: f64,
    level: Option<usize>,
    quality: f64,
    views: Vec<ViewState>,
    pool_mib: f64,
    host_mib: f64,
    script: Vec<Cmd>,
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
    /// Milliseconds of the last full-size frame of the 3D view.
    full_ms: f64,
    counter: u32,
    camera_path: String,
    /// Load failures reported so far, and the latest (the status line).
    failures_seen: usize,
    last_failure: Option<String>,
}

fn tf_opaque(tf: &TransferFunction) -> TransferFunction {
    TransferFunction {
        window: tf.window,
        opacity: vec![[0.0, 1.0]],
        colormap: tf.colormap.clone(),
    }
}

/// Orbit parameters of a camera: (distance, azimuth, elevation) around its
/// target (see [`Camera::orbit`]).
fn orbit_of(c: &Camera) -> (f64, f64, f64) {
    let v = sub(c.eye, c.target);
    let d = length(v).max(1e-9);
    let el = (v[2] / d).clamp(-1.0, 1.0).asin().to_degrees();
    let az = v[0].atan2(-v[1]).to_degrees();
    (d, az, el)
}

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
        script: Vec<Cmd>,
        log: Option<std::fs::File>,
        exit: Arc<AtomicI32>,
    ) -> ViewerApp {
        let home = Camera::fit(
            ds.extent,
            30.0,
            20.0,
            Projection::Perspective { fov_y_deg: 35.0 },
        );
        let channels = (0..ds.channels)
            .map(|c| ChannelUi {
                visible: c < 3,
                color: CHANNEL_COLORS[c % CHANNEL_COLORS.len()],
                window: ds.range,
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
            counter: 0,
            camera_path: String::new(),
            failures_seen: 0,
            last_failure: None,
        }
    }

    // ---- what each view shows ------------------------------------------

    fn oblique_normal(&self) -> Vec3 {
        let (sa, ca) = self.oblique[0].to_radians().sin_cos();
        let (se, ce) = self.oblique[1].to_radians().sin_cos();
        [ce * sa, -ce * ca, se]
    }

    fn plane_normal(&self, v: usize) -> Vec3 {
        match v {
            1 => [0.0, 0.0, 1.0],
            2 => [0.0, 1.0, 0.0],
            3 => [1.0, 0.0, 0.0],
            _ => self.oblique_normal(),
        }
    }

    fn render_size(&self, v: usize) -> [u32; 2] {
        let vs = &self.views[v];
        if let Some(f) = vs.forced {
            return f;
        }
        // While the 3D view moves, fewer pixels, so that frames keep up:
        // aim at about 40 ms a frame from what full-size frames took.
        if v == 0 && self.interacting.elapsed() < Duration::from_millis(200) {
            let k = (40.0 / self.full_ms.max(1.0)).sqrt().clamp(0.25, 0.5);
            return vs.size.map(|s| ((s as f64 * k) as u32).max(8));
        }
        vs.size
    }

    fn slice_camera(&self, v: usize, size: [u32; 2]) -> Camera {
        let n = self.plane_normal(v);
        let vs = &self.views[v];
        let e = self.ds.extent;
        let height = e.iter().cloned().fold(0.0, f64::max) * 1.05 / vs.zoom;
        let base = Camera::facing_plane(self.cursor, n, height);
        let b = base.basis();
        let _ = size;
        let shift = add(scale(b.right, vs.pan[0]), scale(b.up, vs.pan[1]));
        // Centre the view on the volume's centre projected into the plane,
        // then pan.
        let c = scale(e, 0.5);
        let c_in_plane = sub(c, scale(n, dot(sub(c, self.cursor), normalize(n))));
        let centre = add(c_in_plane, shift);
        Camera {
            eye: add(centre, sub(base.eye, base.target)),
            target: centre,
            ..base
        }
    }

    fn styles(&self) -> Vec<ChannelStyle> {
        if self.ds.channels <= 1 {
            return vec![];
        }
        self.channels
            .iter()
            .enumerate()
            .filter(|(_, c)| c.visible)
            .map(|(i, c)| ChannelStyle {
                channel: i,
                color: c.color.map(|x| x as f32 / 255.0),
                window: c.window,
            })
            .collect()
    }

    fn spec(&self, v: usize) -> Spec {
        let [w, h] = self.render_size(v);
        let lod = match self.level {
            Some(l) => Lod::Fixed(l),
            None => Lod::Auto {
                bias: self.lod_bias,
            },
        };
        let (camera, tf, mode) = if v == 0 {
            let mode = match self.mode.as_str() {
                "mip" => RenderMode::Mip,
                "slice" => RenderMode::Slice {
                    origin: self.cursor,
                    normal: self.oblique_normal(),
                },
                _ => RenderMode::Dvr,
            };
            let tf = if self.mode == "slice" {
                tf_opaque(&self.tf)
            } else {
                self.tf.clone()
            };
            (self.cam, tf, mode)
        } else {
            let mode = RenderMode::Slice {
                origin: self.cursor,
                normal: self.plane_normal(v),
            };
            (self.slice_camera(v, [w, h]), tf_opaque(&self.tf), mode)
        };
        let mut params = RenderParams::new(w, h, camera, tf, mode.clone());
        params.samples_per_voxel = self.quality;
        params.reference_step = Some(self.voxel0());
        if mode != RenderMode::Dvr {
            params.channels = self.styles();
        }
        Spec {
            params,
            lod,
            channel: self.dvr_channel,
        }
    }

    fn voxel0(&self) -> f64 {
        let d = self.ds.levels[0];
        let e = self.ds.extent;
        // As `Scene::voxel(0)`: the smallest voxel edge of level 0.
        [0, 1, 2]
            .map(|a| e[a] / d[2 - a] as f64)
            .into_iter()
            .fold(f64::INFINITY, f64::min)
    }

    fn send_specs(&mut self) {
        for v in 0..N_VIEWS {
            let spec = self.spec(v);
            if self.views[v].sent.as_ref() != Some(&spec) {
                self.views[v].version += 1;
                self.views[v].sent = Some(spec.clone());
                let _ = self
                    .tx
                    .send(Msg::View(v, self.views[v].version, Some(spec)));
            }
        }
    }

    // ---- frames from the worker ----------------------------------------

    fn take_frames(&mut self, ctx: &egui::Context) {
        while let Ok(r) = self.rx.try_recv() {
            match r {
                Reply::Error(e) => {
                    self.message = format!("error: {e}");
                    if !self.script.is_empty() {
                        eprintln!("view: {e}");
                        self.fail(ctx, &e);
                    }
                }
                Reply::Frame(out) => self.show_frame(ctx, out),
            }
        }
    }

    fn show_frame(&mut self, ctx: &egui::Context, out: Box<Out>) {
        let v = out.view;
        if let Some(log) = &mut self.log {
            let _ = writeln!(
                log,
                "{}",
                serde_json::json!({
                    "t": self.started.elapsed().as_secs_f64(),
                    "view": VIEWS[v], "version": out.version,
                    "current": out.version == self.views[v].version,
                    "completeness": out.completeness, "render_ms": out.render_ms,
                    "cache_ms": out.cache_ms, "resident_bricks": out.resident_bricks,
                    "pending": out.pending, "bytes_read": out.bytes_read,
                    "up": out.up, "down": out.down,
                    "lod_extra": out.lod_extra, "failed_bricks": out.failed,
                    "settled": out.settled, "new_failures": out.new_failures,
                    "peak_rss_bytes": crate::memory::peak_rss(),
                    "memory_budget_bytes": self.setup.memory_budget,
                })
            );
        }
        // Unreadable bricks: reported on stderr (the first ones; a store
        // removed under the view fails every brick it still needed) and in
        // the status line; the view goes on with coarser data.
        const SHOWN: usize = 20;
        for f in &out.new_failures {
            self.failures_seen += 1;
            if self.failures_seen <= SHOWN {
                eprintln!("view: cannot load {f} (drawn from coarser data)");
            } else if self.failures_seen == SHOWN + 1 {
                eprintln!("view: more bricks cannot be loaded; the status line counts them");
            }
            self.last_failure = Some(f.clone());
        }
        if v == 0 && [out.image.width, out.image.height] == self.views[0].size {
            self.full_ms = out.render_ms;
        }
        self.read_history.push((Instant::now(), out.bytes_read));
        let cut = Instant::now() - Duration::from_secs(2);
        self.read_history.retain(|(t, _)| *t >= cut);
        let vs = &mut self.views[v];
        vs.frames += 1;
        if out.completeness < 1.0 {
            vs.streaming += 1;
        }
        let img = &out.image;
        let rgba = img.to_rgba8([0.0, 0.0, 0.0, 1.0]);
        let ci = egui::ColorImage::from_rgba_unmultiplied(
            [img.width as usize, img.height as usize],
            &rgba,
        );
        match &mut vs.texture {
            Some(t) => t.set(ci, egui::TextureOptions::LINEAR),
            None => {
                vs.texture =
                    Some(ctx.load_texture(format!("view-{v}"), ci, egui::TextureOptions::LINEAR))
            }
        }
        vs.last = Some(out);
    }

    fn complete(&self, v: usize) -> bool {
        let vs = &self.views[v];
        vs.last
            .as_ref()
            .is_some_and(|o| o.version == vs.version && (o.completeness >= 1.0 || o.settled))
    }

    // ---- interactions (mouse, keys and scripts share these) -------------

    fn orbit(&mut self, dx: f64, dy: f64) {
        let (d, az, el) = orbit_of(&self.cam);
        let el = (el + dy * 0.4).clamp(-89.0, 89.0);
        self.cam = Camera::orbit(self.cam.target, d, az - dx * 0.4, el, self.cam.projection);
        self.interacting = Instant::now();
    }

    fn pixel_world(&self, cam: &Camera, h: u32) -> f64 {
        match cam.projection {
            Projection::Perspective { fov_y_deg } => {
                2.0 * length(sub(cam.eye, cam.target)) * (fov_y_deg * 0.5).to_radians().tan()
                    / h as f64
            }
            Projection::Orthographic { height } => height / h as f64,
        }
    }

    fn pan(&mut self, dx: f64, dy: f64) {
        let s = self.pixel_world(&self.cam, self.render_size(0)[1].max(1));
        let b = self.cam.basis();
        let shift = add(scale(b.right, -dx * s), scale(b.up, dy * s));
        self.cam.eye = add(self.cam.eye, shift);
        self.cam.target = add(self.cam.target, shift);
        self.interacting = Instant::now();
    }

    fn zoom(&mut self, steps: f64) {
        let k = 0.85f64.powf(steps);
        match &mut self.cam.projection {
            Projection::Orthographic { height } => *height *= k,
            Projection::Perspective { .. } => {
                let v = sub(self.cam.eye, self.cam.target);
                self.cam.eye = add(self.cam.target, scale(v, k));
            }
        }
        self.interacting = Instant::now();
    }

    fn key(&mut self, k: &str) {
        match k {
            "left" => self.orbit(-12.5, 0.0),
            "right" => self.orbit(12.5, 0.0),
            "up" => self.orbit(0.0, 12.5),
            "down" => self.orbit(0.0, -12.5),
            "plus" => self.zoom(1.0),
            "minus" => self.zoom(-1.0),
            "r" => {
                self.cam = self.home;
                for vs in &mut self.views {
                    vs.zoom = 1.0;
                    vs.pan = [0.0; 2];
                }
            }
            _ => {}
        }
    }

    /// The world point under render pixel `(px, py)` of slice view `v`, in
    /// its plane (clamped into the volume).
    fn slice_point(&self, v: usize, px: f64, py: f64) -> Vec3 {
        let size = self.render_size(v);
        let cam = self.slice_camera(v, size);
        let ray = cam.ray(px, py, size[0], size[1]);
        let n = normalize(self.plane_normal(v));
        let t = dot(n, sub(self.cursor, ray.origin)) / dot(n, ray.dir);
        let p = ray.at(t);
        let e = self.ds.extent;
        [0, 1, 2].map(|a| p[a].clamp(0.0, e[a]))
    }

    /// Where the cursor is in slice view `v`, in render pixels.
    fn cursor_pixel(&self, v: usize) -> Option<[f64; 2]> {
        let size = self.render_size(v);
        self.slice_camera(v, size)
            .project(self.cursor, size[0], size[1])
    }

    fn slice_drag(&mut self, v: usize, button: &str, dx: f64, dy: f64) {
        if button == "left" {
            if let Some([x, y]) = self.cursor_pixel(v) {
                self.cursor = self.slice_point(v, x + dx, y + dy);
            }
        } else {
            let size = self.render_size(v);
            let cam = self.slice_camera(v, size);
            let s = self.pixel_world(&cam, size[1].max(1));
            let vs = &mut self.views[v];
            vs.pan[0] -= dx * s;
            vs.pan[1] += dy * s;
        }
    }

    fn drag(&mut self, v: usize, button: &str, dx: f64, dy: f64) {
        if v == 0 {
            match button {
                "left" => self.orbit(dx, dy),
                _ => self.pan(dx, dy),
            }
        } else {
            self.slice_drag(v, button, dx, dy);
        }
    }

    fn scroll(&mut self, v: usize, steps: f64) {
        if v == 0 {
            self.zoom(steps);
        } else {
            let vs = &mut self.views[v];
            vs.zoom = (vs.zoom * 1.15f64.powf(steps)).clamp(0.05, 200.0);
        }
    }

    fn set_tf_preset(&mut self, name: &str) -> Result<()> {
        self.tf =
            TransferFunction::preset(name, self.tf.window).map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(())
    }

    fn set_colormap(&mut self, name: &str) -> Result<()> {
        let p = Preset::parse(name).with_context(|| format!("unknown colour map {name:?}"))?;
        self.tf.colormap = ColorMap::Preset(p);
        Ok(())
    }

    fn set_window(&mut self, lo: f32, hi: f32) -> Result<()> {
        if !(lo.is_finite() && hi.is_finite() && hi > lo) {
            bail!("window: expected LO < HI, found {lo} {hi}");
        }
        self.tf.window = [lo, hi];
        for c in &mut self.channels {
            c.window = [lo, hi];
        }
        Ok(())
    }

    fn add_point(&mut self, x: f32, a: f32) {
        let x = x.clamp(0.0, 1.0);
        let a = a.clamp(0.0, 1.0);
        let i = self.tf.opacity.partition_point(|p| p[0] <= x);
        self.tf.opacity.insert(i, [x, a]);
    }

    fn channel_ui(&mut self, c: usize) -> Result<&mut ChannelUi> {
        let n = self.channels.len();
        self.channels
            .get_mut(c)
            .with_context(|| format!("channel {c}: the store has {n} channel(s)"))
    }

    // ---- saving ----------------------------------------------------------

    /// The `brickyard render` arguments that draw view `v` as it is now.
    fn render_args(&self, v: usize, prefix: &Path) -> Result<Vec<String>> {
        let spec = self.spec(v);
        let p = &spec.params;
        let cam_path = prefix.with_extension("camera.json");
        let tf_path = prefix.with_extension("tf.json");
        std::fs::write(&cam_path, p.camera.to_json())
            .with_context(|| format!("{}: cannot write", cam_path.display()))?;
        std::fs::write(&tf_path, p.tf.to_json())
            .with_context(|| format!("{}: cannot write", tf_path.display()))?;
        let mut a: Vec<String> = vec![
            "--size".into(),
            format!("{}x{}", p.width, p.height),
            "--camera".into(),
            cam_path.display().to_string(),
            "--tf".into(),
            tf_path.display().to_string(),
            "--samples-per-voxel".into(),
            format!("{}", p.samples_per_voxel),
        ];
        match &p.mode {
            RenderMode::Dvr => a.extend(["--mode".into(), "dvr".into()]),
            RenderMode::Mip => a.extend(["--mode".into(), "mip".into()]),
            RenderMode::Slice { origin, normal } => {
                let f = |v: &Vec3| format!("{},{},{}", v[0], v[1], v[2]);
                a.extend([
                    "--mode".into(),
                    "slice".into(),
                    "--slice-origin".into(),
                    f(origin),
                    "--slice-normal".into(),
                    f(normal),
                ]);
            }
        }
        match spec.lod {
            Lod::Fixed(l) => a.extend(["--level".into(), l.to_string()]),
            Lod::Auto { bias } => a.extend(["--lod-bias".into(), format!("{bias}")]),
        }
        if p.mode == RenderMode::Dvr {
            if self.ds.channels > 1 {
                a.extend(["--channel".into(), spec.channel.to_string()]);
            }
        } else {
            for s in &p.channels {
                let c = s.color.map(|x| (x * 255.0).round() as u8);
                a.extend([
                    "--channel".into(),
                    format!(
                        "{}:{:02x}{:02x}{:02x}:{},{}",
                        s.channel, c[0], c[1], c[2], s.window[0], s.window[1]
                    ),
                ]);
            }
        }
        Ok(a)
    }

    fn save_view(&self, v: usize, prefix: &Path) -> Result<()> {
        let a = self.render_args(v, prefix)?;
        let args_path = prefix.with_extension("args");
        std::fs::write(&args_path, a.join("\n") + "\n")
            .with_context(|| format!("{}: cannot write", args_path.display()))?;
        Ok(())
    }

    fn screenshot(&self, v: usize, path: &Path) -> Result<()> {
        let vs = &self.views[v];
        let Some(o) = &vs.last else {
            bail!("screenshot {}: no frame yet", VIEWS[v]);
        };
        o.image
            .write_png(path, [0.0, 0.0, 0.0, 1.0])
            .map_err(|e| anyhow::anyhow!("{e}"))
    }

    // ---- scripts ---------------------------------------------------------

    fn fail(&mut self, ctx: &egui::Context, e: &str) {
        eprintln!("view: script: {e}");
        self.exit.store(1, Ordering::SeqCst);
        self.script.clear();
        ctx.send_viewport_cmd(egui::ViewportCommand::Close);
    }

    /// Run script commands until one has to wait.
    fn run_script(&mut self, ctx: &egui::Context) {
        while self.pc < self.script.len() {
            if self.window_shot.is_some() {
                return;
            }
            let cmd = self.script[self.pc].clone();
            let r: Result<bool> = (|| {
                Ok(match &cmd {
                    Cmd::Size(v, w, h) => {
                        self.views[*v].forced = Some([*w, *h]);
                        true
                    }
                    Cmd::Mode(m) => {
                        self.mode = m.clone();
                        true
                    }
                    Cmd::Drag(v, b, dx, dy) => {
                        self.drag(*v, b, *dx as f64, *dy as f64);
                        true
                    }
                    Cmd::Scroll(v, s) => {
                        self.scroll(*v, *s as f64);
                        true
                    }
                    Cmd::Click(v, x, y) => {
                        if *v > 0 {
                            self.cursor = self.slice_point(*v, *x as f64, *y as f64);
                        }
                        true
                    }
                    Cmd::Key(k) => {
                        self.key(k);
                        true
                    }
                    Cmd::Tf(p) => {
                        self.set_tf_preset(p)?;
                        true
                    }
                    Cmd::Colormap(c) => {
                        self.set_colormap(c)?;
                        true
                    }
                    Cmd::Window(lo, hi) => {
                        self.set_window(*lo, *hi)?;
                        true
                    }
                    Cmd::Point(x, a) => {
                        self.add_point(*x, *a);
                        true
                    }
                    Cmd::Cursor(f) => {
                        let e = self.ds.extent;
                        self.cursor = [0, 1, 2].map(|a| f[a].clamp(0.0, 1.0) * e[a]);
                        true
                    }
                    Cmd::Channel(c, on) => {
                        self.channel_ui(*c)?.visible = *on;
                        true
                    }
                    Cmd::ChannelColor(c, rgb) => {
                        self.channel_ui(*c)?.color = *rgb;
                        true
                    }
                    Cmd::ChannelWindow(c, lo, hi) => {
                        if !(lo.is_finite() && hi.is_finite() && hi > lo) {
                            bail!("channel-window: expected LO < HI, found {lo} {hi}");
                        }
                        self.channel_ui(*c)?.window = [*lo, *hi];
                        true
                    }
                    Cmd::DvrChannel(c) => {
                        self.channel_ui(*c)?;
                        self.dvr_channel = *c;
                        true
                    }
                    Cmd::Oblique(az, el) => {
                        self.oblique = [*az, *el];
                        true
                    }
                    Cmd::LodBias(b) => {
                        self.lod_bias = *b;
                        true
                    }
                    Cmd::Level(l) => {
                        if let Some(l) = l {
                            if *l >= self.ds.levels.len() {
                                bail!("level: the store has {} levels", self.ds.levels.len());
                            }
                        }
                        self.level = *l;
                        true
                    }
                    Cmd::Quality(q) => {
                        if !(*q > 0.0 && *q <= 16.0) {
                            bail!("quality: expected samples per voxel in (0, 16], found {q}");
                        }
                        self.quality = *q;
                        true
                    }
                    Cmd::WaitComplete(secs) => {
                        self.send_specs();
                        let since = *self.waiting.get_or_insert_with(Instant::now);
                        // Not while a reduced-resolution frame stands in
                        // for the full one.
                        let settled = self.interacting.elapsed() >= Duration::from_millis(200);
                        if settled && (0..N_VIEWS).all(|v| self.complete(v)) {
                            self.waiting = None;
                            true
                        } else if since.elapsed().as_secs_f64() > *secs {
                            bail!("wait-complete: the views did not complete in {secs} s");
                        } else {
                            false
                        }
                    }
                    Cmd::Screenshot(v, p) => {
                        if !self.complete(*v) {
                            bail!(
                                "screenshot {}: the view is not complete (wait-complete first)",
                                VIEWS[*v]
                            );
                        }
                        self.screenshot(*v, p)?;
                        true
                    }
                    Cmd::SaveView(v, p) => {
                        self.save_view(*v, p)?;
                        true
                    }
                    Cmd::WindowShot(p) => {
                        self.window_shot = Some(p.clone());
                        let slot = self.shot.clone();
                        let c2 = ctx.clone();
                        ctx.request_screenshot(move |img| {
                            *slot.lock().unwrap_or_else(|e| e.into_inner()) = Some(img);
                            c2.request_repaint();
                        });
                        true
                    }
                    Cmd::ExpectStreaming(v, n) => {
                        let got = self.views[*v].streaming;
                        if got < *n {
                            bail!(
                                "expect-streaming {}: {got} frame(s) showed partial data, expected at least {n}",
                                VIEWS[*v]
                            );
                        }
                        self.views[*v].streaming = 0;
                        true
                    }
                    Cmd::Touch(p) => {
                        std::fs::write(p, b"").with_context(|| format!("touch {}", p.display()))?;
                        true
                    }
                    Cmd::WaitFile(p, secs) => {
                        let since = *self.waiting.get_or_insert_with(Instant::now);
                        if p.exists() {
                            self.waiting = None;
                            true
                        } else if since.elapsed().as_secs_f64() > *secs {
                            bail!("wait-file: {} did not appear in {secs} s", p.display());
                        } else {
                            false
                        }
                    }
                    Cmd::Quit => {
                        ctx.send_viewport_cmd(egui::ViewportCommand::Close);
                        self.pc = self.script.len();
                        return Ok(false);
                    }
                })
            })();
            match r {
                Ok(true) => self.pc += 1,
                Ok(false) => return,
                Err(e) => {
                    self.fail(ctx, &format!("{e:#}"));
                    return;
                }
            }
        }
    }

    fn take_window_shot(&mut self, ctx: &egui::Context) {
        let Some(path) = self.window_shot.clone() else {
            return;
        };
        let shot = self.shot.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(img) = shot {
            self.window_shot = None;
            let r = write_png(&path, img.size, img.as_raw());
            if let Err(e) = r {
                self.fail(ctx, &format!("window-shot: {e:#}"));
            }
        }
    }

    // ---- drawing -----------------------------------------------------------

    fn controls(&mut self, ui: &mut egui::Ui) {
        ui.heading("brickyard");
        ui.label(self.ds.store.display().to_string());
        let lv = self.ds.levels[0];
        ui.label(format!(
            "{}×{}×{} {} · {} level(s) · {} channel(s)",
            lv[2],
            lv[1],
            lv[0],
            self.ds.dtype.short_name(),
            self.ds.levels.len(),
            self.ds.channels
        ));
        ui.separator();
        ui.horizontal(|ui| {
            ui.label("3D view:");
            for m in ["dvr", "mip", "slice"] {
                ui.selectable_value(&mut self.mode, m.to_string(), m.to_uppercase());
            }
        });
        if self.ds.channels > 1 {
            egui::ComboBox::from_label("DVR channel")
                .selected_text(self.dvr_channel.to_string())
                .show_ui(ui, |ui| {
                    for c in 0..self.ds.channels {
                        ui.selectable_value(&mut self.dvr_channel, c, c.to_string());
                    }
                });
            ui.label("Channels (MIP and slices, added up):");
            for (i, c) in self.channels.iter_mut().enumerate() {
                ui.horizontal(|ui| {
                    ui.checkbox(&mut c.visible, format!("{i}"));
                    let mut rgb = c.color.map(|x| x as f32 / 255.0);
                    if ui.color_edit_button_rgb(&mut rgb).changed() {
                        c.color = rgb.map(|x| (x * 255.0).round() as u8);
                    }
                    ui.add(egui::DragValue::new(&mut c.window[0]).speed(1.0));
                    ui.add(egui::DragValue::new(&mut c.window[1]).speed(1.0));
                });
            }
        }
        ui.separator();
        ui.label("Transfer function (drag points; double-click adds, right-click removes):");
        self.tf_editor(ui);
        ui.horizontal(|ui| {
            egui::ComboBox::from_label("preset")
                .selected_text("choose")
                .show_ui(ui, |ui| {
                    for p in TransferFunction::PRESETS {
                        if ui.button(p).clicked() {
                            let _ = self.set_tf_preset(p);
                        }
                    }
                });
            egui::ComboBox::from_label("colours")
                .selected_text(match &self.tf.colormap {
                    ColorMap::Preset(p) => p.name(),
                    ColorMap::Points(_) => "custom",
                })
                .show_ui(ui, |ui| {
                    for p in Preset::ALL {
                        if ui.button(p.name()).clicked() {
                            self.tf.colormap = ColorMap::Preset(p);
                        }
                    }
                });
        });
        let [lo, hi] = self.tf.window;
        let (mut level, mut width) = ((lo + hi) * 0.5, hi - lo);
        let span = (self.ds.range[1] - self.ds.range[0]).abs().max(1e-6);
        ui.horizontal(|ui| {
            ui.label("window");
            let a = ui.add(
                egui::DragValue::new(&mut level)
                    .speed(span / 200.0)
                    .prefix("level "),
            );
            let b = ui.add(
                egui::DragValue::new(&mut width)
                    .speed(span / 200.0)
                    .prefix("width ")
                    .range(span * 1e-4..=f32::MAX),
            );
            if a.changed() || b.changed() {
                let w = TransferFunction::window_level(level, width);
                let _ = self.set_window(w[0], w[1]);
            }
        });
        ui.separator();
        ui.add(
            egui::Slider::new(&mut self.quality, 0.25..=4.0)
                .text("samples per voxel")
                .logarithmic(true),
        );
        ui.add(egui::Slider::new(&mut self.lod_bias, -2.0..=3.0).text("LOD bias"));
        egui::ComboBox::from_label("level")
            .selected_text(self.level.map_or("auto".to_string(), |l| l.to_string()))
            .show_ui(ui, |ui| {
                ui.selectable_value(&mut self.level, None, "auto");
                for l in 0..self.ds.levels.len() {
                    ui.selectable_value(&mut self.level, Some(l), l.to_string());
                }
            });
        ui.add(egui::Slider::new(&mut self.oblique[0], -180.0..=180.0).text("oblique azimuth"));
        ui.add(egui::Slider::new(&mut self.oblique[1], -90.0..=90.0).text("oblique elevation"));
        ui.separator();
        ui.label("Budgets (MiB):");
        ui.horizontal(|ui| {
            ui.add(
                egui::DragValue::new(&mut self.pool_mib)
                    .range(4.0..=1e6)
                    .prefix("pool "),
            );
            ui.add(
                egui::DragValue::new(&mut self.host_mib)
                    .range(4.0..=1e7)
                    .prefix("host "),
            );
            if ui.button("Apply").clicked() {
                let mut s = self.setup.clone();
                s.cfg.pool_bytes = (self.pool_mib * (1 << 20) as f64) as u64;
                s.host_bytes = (self.host_mib * (1 << 20) as f64) as u64;
                // The budget moves with the shares the user set.
                s.memory_budget = (s.memory_budget + s.cfg.pool_bytes + s.host_bytes)
                    .saturating_sub(self.setup.cfg.pool_bytes + self.setup.host_bytes);
                self.setup = s.clone();
                let _ = self.tx.send(Msg::Reopen(s));
                for vs in &mut self.views {
                    vs.sent = None;
                }
            }
        });
        ui.separator();
        ui.horizontal(|ui| {
            if ui.button("Screenshot").clicked() {
                self.counter += 1;
                let p = PathBuf::from(format!("brickyard-view-{:03}.png", self.counter));
                self.message = match self.screenshot(0, &p) {
                    Ok(()) => format!("wrote {}", p.display()),
                    Err(e) => format!("{e:#}"),
                };
            }
            if ui.button("Save view").clicked() {
                self.counter += 1;
                let p = PathBuf::from(format!("brickyard-view-{:03}", self.counter));
                self.message = match self.save_view(0, &p) {
                    Ok(()) => format!(
                        "wrote {0}.camera.json, {0}.tf.json; render it with `brickyard render {1} $(cat {0}.args)`",
                        p.display(),
                        self.ds.store.display()
                    ),
                    Err(e) => format!("{e:#}"),
                };
            }
            if ui.button("Reset camera").clicked() {
                self.key("r");
            }
        });
        ui.horizontal(|ui| {
            ui.add(
                egui::TextEdit::singleline(&mut self.camera_path)
                    .hint_text("camera.json")
                    .desired_width(150.0),
            );
            if ui.button("Load camera").clicked() {
                self.message = match std::fs::read_to_string(&self.camera_path)
                    .map_err(|e| e.to_string())
                    .and_then(|t| Camera::from_json(&t).map_err(|e| e.to_string()))
                {
                    Ok(c) => {
                        self.cam = c;
                        format!("loaded {}", self.camera_path)
                    }
                    Err(e) => format!("{}: {e}", self.camera_path),
                };
            }
        });
        if !self.message.is_empty() {
            ui.label(&self.message);
        }
    }

    fn tf_editor(&mut self, ui: &mut egui::Ui) {
        let (rect, resp) = ui.allocate_exact_size(
            egui::vec2(ui.available_width().min(300.0), 120.0),
            egui::Sense::click_and_drag(),
        );
        let p = ui.painter_at(rect);
        p.rect_filled(rect, 2.0, egui::Color32::from_gray(24));
        // Histogram of the bricks' value ranges, over the window, log scale.
        let [lo, hi] = self.tf.window;
        let [r0, r1] = self.ds.range;
        let h = &self.ds.histogram;
        if !h.is_empty() && r1 > r0 {
            let max = h.iter().cloned().fold(0.0f32, f32::max).max(1e-9);
            let n = h.len();
            for (i, &c) in h.iter().enumerate() {
                let v0 = r0 + (r1 - r0) * i as f32 / n as f32;
                let v1 = r0 + (r1 - r0) * (i + 1) as f32 / n as f32;
                let x0 = (v0 - lo) / (hi - lo);
                let x1 = (v1 - lo) / (hi - lo);
                if x1 < 0.0 || x0 > 1.0 || c <= 0.0 {
                    continue;
                }
                let t = (1.0 + c).ln() / (1.0 + max).ln();
                let a = rect.left() + x0.max(0.0) * rect.width();
                let b = rect.left() + x1.min(1.0) * rect.width();
                p.rect_filled(
                    egui::Rect::from_min_max(
                        egui::pos2(a, rect.bottom() - t * rect.height()),
                        egui::pos2(b.max(a + 1.0), rect.bottom()),
                    ),
                    0.0,
                    egui::Color32::from_gray(70),
                );
            }
        }
        // Colour map along the bottom.
        for i in 0..64 {
            let x = i as f32 / 63.0;
            let c = self.tf.colormap.color(x);
            let col = egui::Color32::from_rgb(
                (c[0] * 255.0) as u8,
                (c[1] * 255.0) as u8,
                (c[2] * 255.0) as u8,
            );
            let a = rect.left() + rect.width() * i as f32 / 64.0;
            p.rect_filled(
                egui::Rect::from_min_max(
                    egui::pos2(a, rect.bottom() - 6.0),
                    egui::pos2(a + rect.width() / 64.0 + 1.0, rect.bottom()),
                ),
                0.0,
                col,
            );
        }
        let to_screen = |q: [f32; 2]| {
            egui::pos2(
                rect.left() + q[0] * rect.width(),
                rect.bottom() - 6.0 - q[1] * (rect.height() - 8.0),
            )
        };
        let from_screen = |s: egui::Pos2| {
            [
                ((s.x - rect.left()) / rect.width()).clamp(0.0, 1.0),
                ((rect.bottom() - 6.0 - s.y) / (rect.height() - 8.0)).clamp(0.0, 1.0),
            ]
        };
        let mut pts: Vec<egui::Pos2> = self.tf.opacity.iter().map(|q| to_screen(*q)).collect();
        if let (Some(f), Some(l)) = (pts.first().copied(), pts.last().copied()) {
            pts.insert(0, egui::pos2(rect.left(), f.y));
            pts.push(egui::pos2(rect.right(), l.y));
        }
        p.add(egui::Shape::line(
            pts,
            egui::Stroke::new(1.5, egui::Color32::WHITE),
        ));
        let nearest = |pos: egui::Pos2, tf: &TransferFunction| {
            tf.opacity
                .iter()
                .enumerate()
                .map(|(i, q)| (i, to_screen(*q).distance(pos)))
                .filter(|(_, d)| *d < 10.0)
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(i, _)| i)
        };
        for q in &self.tf.opacity {
            p.circle_filled(to_screen(*q), 4.0, egui::Color32::YELLOW);
        }
        if let Some(pos) = resp.interact_pointer_pos() {
            if resp.drag_started() {
                self.drag_point = nearest(pos, &self.tf);
            }
            if resp.dragged() {
                if let Some(i) = self.drag_point {
                    let q = from_screen(pos);
                    let lo_x = if i > 0 {
                        self.tf.opacity[i - 1][0]
                    } else {
                        0.0
                    };
                    let hi_x = self.tf.opacity.get(i + 1).map_or(1.0, |n| n[0]);
                    self.tf.opacity[i] = [q[0].clamp(lo_x, hi_x), q[1]];
                }
            }
            if resp.double_clicked() && nearest(pos, &self.tf).is_none() {
                let q = from_screen(pos);
                self.add_point(q[0], q[1]);
            }
            if resp.secondary_clicked() && self.tf.opacity.len() > 1 {
                if let Some(i) = nearest(pos, &self.tf) {
                    self.tf.opacity.remove(i);
                }
            }
        }
        if resp.drag_stopped() {
            self.drag_point = None;
        }
    }

    fn view_panel(&mut self, ui: &mut egui::Ui, v: usize, size: egui::Vec2) {
        let (rect, resp) = ui.allocate_exact_size(size, egui::Sense::click_and_drag());
        let ppp = ui.ctx().pixels_per_point();
        let px = [(rect.width() * ppp) as u32, (rect.height() * ppp) as u32]
            .map(|s| (s / 8 * 8).max(16));
        self.views[v].size = px;
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 0.0, egui::Color32::BLACK);
        // The image keeps its aspect (a size fixed by a script may differ
        // from the panel's).
        let rs = self.render_size(v);
        let aspect = rs[0] as f32 / rs[1].max(1) as f32;
        let (w, h) = if rect.width() / rect.height() > aspect {
            (rect.height() * aspect, rect.height())
        } else {
            (rect.width(), rect.width() / aspect)
        };
        let img = egui::Rect::from_center_size(rect.center(), egui::vec2(w, h));
        if let Some(t) = &self.views[v].texture {
            painter.image(
                t.id(),
                img,
                egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0)),
                egui::Color32::WHITE,
            );
        }
        // Input: the same handlers as scripts, in render pixels.
        let k = rs[0] as f32 / img.width();
        let rect = img;
        if resp.dragged_by(egui::PointerButton::Primary) {
            let d = resp.drag_delta() * k;
            if v == 0 {
                self.orbit(d.x as f64, d.y as f64);
            } else if let Some(pos) = resp.interact_pointer_pos() {
                let q = (pos - rect.min) * k;
                self.cursor = self.slice_point(v, q.x as f64, q.y as f64);
            }
        } else if resp.clicked() && v > 0 {
            if let Some(pos) = resp.interact_pointer_pos() {
                let q = (pos - rect.min) * k;
                self.cursor = self.slice_point(v, q.x as f64, q.y as f64);
            }
        }
        if resp.dragged_by(egui::PointerButton::Secondary)
            || resp.dragged_by(egui::PointerButton::Middle)
        {
            let d = resp.drag_delta() * k;
            self.drag(v, "right", d.x as f64, d.y as f64);
        }
        if resp.hovered() {
            let s = ui.input(|i| i.smooth_scroll_delta.y);
            if s != 0.0 {
                self.scroll(v, s as f64 / 50.0);
            }
        }
        // Cursor lines in slice views.
        if v > 0 {
            if let Some([x, y]) = self.cursor_pixel(v) {
                let p = rect.min + egui::vec2(x as f32 / k, y as f32 / k);
                let st =
                    egui::Stroke::new(1.0, egui::Color32::from_rgba_unmultiplied(255, 220, 0, 160));
                painter.line_segment(
                    [egui::pos2(rect.left(), p.y), egui::pos2(rect.right(), p.y)],
                    st,
                );
                painter.line_segment(
                    [egui::pos2(p.x, rect.top()), egui::pos2(p.x, rect.bottom())],
                    st,
                );
            }
        }
        let label = match v {
            0 => format!("3D · {}", self.mode.to_uppercase()),
            _ => VIEWS[v].to_uppercase(),
        };
        let c = self.views[v].last.as_ref().map_or(0.0, |o| o.completeness);
        painter.text(
            painter.clip_rect().left_top() + egui::vec2(6.0, 4.0),
            egui::Align2::LEFT_TOP,
            format!("{label} · {:.0}%", 100.0 * c),
            egui::FontId::monospace(12.0),
            egui::Color32::from_gray(220),
        );
        if v == 0 {
            let full = painter.clip_rect();
            painter.text(
                full.left_bottom() + egui::vec2(6.0, -4.0),
                egui::Align2::LEFT_BOTTOM,
                self.status(),
                egui::FontId::monospace(12.0),
                egui::Color32::from_gray(220),
            );
        }
    }

    fn status(&self) -> String {
        let Some(o) = self.views[0].last.as_ref() else {
            return "waiting for the first frame".into();
        };
        let rate = match (self.read_history.first(), self.read_history.last()) {
            (Some(a), Some(b)) if b.0 > a.0 => (b.1 - a.1) as f64 / (b.0 - a.0).as_secs_f64(),
            _ => 0.0,
        };
        let mut detail = String::new();
        if o.lod_extra > 0.0 {
            detail += &format!(
                " · coarser by {:.1} level(s): the pool is too small for full detail",
                o.lod_extra
            );
        }
        if o.failed > 0 {
            detail += &format!(" · {} brick(s) unreadable, drawn coarser", o.failed);
            if let Some(f) = &self.last_failure {
                let f: String = f.chars().take(160).collect();
                detail += &format!("\nlast: {f}");
            }
        }
        let peak = crate::memory::peak_rss().map_or(String::new(), |p| {
            format!(
                " · peak memory {} of {}",
                human_bytes(p),
                human_bytes(self.setup.memory_budget)
            )
        });
        format!(
            "{:.1} ms/frame · {:.1}% complete{detail}\n{} bricks resident of {} slots · {} pending\nhost cache {} of {} · {:.1} MiB/s read{peak}\n{}",
            o.render_ms,
            100.0 * o.completeness,
            o.resident_bricks,
            o.pool_slots,
            o.pending,
            human_bytes(o.host_bytes),
            human_bytes(o.host_budget),
            rate / (1 << 20) as f64,
            o.backend
        )
    }
}

fn write_png(path: &Path, size: [usize; 2], rgba: &[u8]) -> Result<()> {
    let f = std::fs::File::create(path)
        .with_context(|| format!("{}: cannot create", path.display()))?;
    let mut e = png::Encoder::new(std::io::BufWriter::new(f), size[0] as u32, size[1] as u32);
    e.set_color(png::ColorType::Rgba);
    e.set_depth(png::BitDepth::Eight);
    let mut w = e
        .write_header()
        .with_context(|| format!("{}: cannot write", path.display()))?;
    w.write_image_data(rgba)
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

impl eframe::App for ViewerApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let ctx = ui.ctx().clone();
        self.take_frames(&ctx);
        self.take_window_shot(&ctx);
        self.run_script(&ctx);
        // Keys (when no text field has focus).
        if !ctx.egui_wants_keyboard_input() {
            let keys = ctx.input(|i| {
                [
                    (egui::Key::ArrowLeft, "left"),
                    (egui::Key::ArrowRight, "right"),
                    (egui::Key::ArrowUp, "up"),
                    (egui::Key::ArrowDown, "down"),
                    (egui::Key::Plus, "plus"),
                    (egui::Key::Equals, "plus"),
                    (egui::Key::Minus, "minus"),
                    (egui::Key::R, "r"),
                ]
                .into_iter()
                .filter(|(k, _)| i.key_pressed(*k))
                .map(|(_, n)| n)
                .collect::<Vec<_>>()
            });
            for k in keys {
                self.key(k);
            }
        }
        egui::Panel::left("controls")
            .resizable(false)
            .exact_size(310.0)
            .show(ui, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| self.controls(ui));
            });
        egui::CentralPanel::default().show(ui, |ui| {
            let avail = ui.available_size();
            let side = (avail.x * 0.3).max(120.0);
            ui.horizontal(|ui| {
                self.view_panel(ui, 0, egui::vec2(avail.x - side - 8.0, avail.y));
                ui.vertical(|ui| {
                    let h = (avail.y - 12.0) / 4.0;
                    for v in 1..N_VIEWS {
                        self.view_panel(ui, v, egui::vec2(side, h));
                    }
                });
            });
        });
        self.send_specs();
        // Keep polling while frames are due; the worker also wakes the
        // window when one arrives.
        let busy = (0..N_VIEWS).any(|v| !self.complete(v))
            || self.pc < self.script.len()
            || self.interacting.elapsed() < Duration::from_millis(300);
        if busy {
            ctx.request_repaint_after(Duration::from_millis(30));
        }
    }

    fn on_exit(&mut self, _gl: Option<&eframe::glow::Context>) {
        let _ = self.tx.send(Msg::Quit);
    }
}
