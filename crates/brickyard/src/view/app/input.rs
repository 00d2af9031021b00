//! Input: mouse, keys and script commands, all through the same handlers
//! (orbit, pan, zoom, cursor moves, transfer-function and channel edits),
//! and the script runner that checks what the views show.

use super::{ChannelUi, Vec3, ViewerApp, N_VIEWS};
use crate::view::script::{Cmd, VIEWS};
use crate::view::worker::Out;
use anyhow::{bail, Context, Result};
use brickyard_core::camera::{add, dot, length, normalize, scale, sub, Camera, Projection};
use brickyard_core::transfer::{ColorMap, Preset};
use brickyard_core::TransferFunction;
use brickyard_render::cpu::Lod;
use eframe::egui;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// The 3D camera's least and greatest distance to its target, in
/// diagonals of the volume (see [`ViewerApp::zoom_range`]).
const ZOOM_NEAREST: f64 = 1e-3;
const ZOOM_FARTHEST: f64 = 1e3;

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
    // ---- interactions (mouse, keys and scripts share these) -------------

    pub(super) fn orbit(&mut self, dx: f64, dy: f64) {
        let (d, az, el) = orbit_of(&self.cam);
        let el = (el + dy * 0.4).clamp(-89.0, 89.0);
        self.cam = Camera::orbit(self.cam.target, d, az - dx * 0.4, el, self.cam.projection);
        self.interacting = Instant::now();
    }

    pub(super) fn pixel_world(&self, cam: &Camera, h: u32) -> f64 {
        match cam.projection {
            Projection::Perspective { fov_y_deg } => {
                2.0 * length(sub(cam.eye, cam.target)) * (fov_y_deg * 0.5).to_radians().tan()
                    / h as f64
            }
            Projection::Orthographic { height } => height / h as f64,
        }
    }

    pub(super) fn pan(&mut self, dx: f64, dy: f64) {
        let s = self.pixel_world(&self.cam, self.render_size(0)[1].max(1));
        let b = self.cam.basis();
        let shift = add(scale(b.right, -dx * s), scale(b.up, dy * s));
        self.cam.eye = add(self.cam.eye, shift);
        self.cam.target = add(self.cam.target, shift);
        self.interacting = Instant::now();
    }

    /// The 3D camera's distance to its target (perspective) or the
    /// height it sees (orthographic) stays within this range, relative to
    /// the volume's diagonal (as the slice views' zoom stays within
    /// 0.05–200): closer, one frame's rays took practically for ever.
    pub(super) fn zoom_range(&self) -> [f64; 2] {
        let diagonal = length(self.ds.extent).max(1e-9);
        [ZOOM_NEAREST * diagonal, ZOOM_FARTHEST * diagonal]
    }

    pub(super) fn zoom(&mut self, steps: f64) {
        if !steps.is_finite() {
            return;
        }
        let k = 0.85f64.powf(steps);
        let [near, far] = self.zoom_range();
        match &mut self.cam.projection {
            Projection::Orthographic { height } => *height = (*height * k).clamp(near, far),
            Projection::Perspective { .. } => {
                let v = sub(self.cam.eye, self.cam.target);
                let d = length(v);
                if d > 0.0 && d.is_finite() {
                    let to = (d * k).clamp(near, far);
                    self.cam.eye = add(self.cam.target, scale(v, to / d));
                }
            }
        }
        self.interacting = Instant::now();
    }

    /// Fails unless `(x, y)` is a render pixel of view `v` (`what`: the
    /// command).
    pub(super) fn check_pixel(&self, what: &str, v: usize, x: f64, y: f64) -> Result<()> {
        let [w, h] = self.render_size(v);
        if !(x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64) {
            bail!(
                "{what} {}: pixel ({x}, {y}) is outside the view ({w}×{h} pixels)",
                VIEWS[v]
            );
        }
        Ok(())
    }

    /// Fails unless view `v` drawn at `w × h` (the others as they are)
    /// keeps the views' images within what the memory budget set aside
    /// for them at the start (the window's pixels, by `--window-size`),
    /// as the start refuses a window too large for `--memory`. Without
    /// `--memory`, within the machine's memory.
    pub(super) fn check_view_size(&self, v: usize, w: u32, h: u32) -> Result<()> {
        let pixels: u64 = (0..N_VIEWS)
            .map(|k| {
                let [a, b] = match k == v {
                    true => [w, h],
                    false => self.views[k].forced.unwrap_or(self.views[k].size),
                };
                a as u64 * b as u64
            })
            .sum();
        let need = crate::view::image_bytes(pixels, self.labels.is_some());
        let have = self.setup.image_bytes;
        if need <= have {
            return Ok(());
        }
        let human = brickyard_store::info::human_bytes;
        let more = need - have;
        let within = match self.setup.memory_given {
            true => self.setup.memory_budget,
            false => crate::memory::physical_ram(),
        };
        let total = self.setup.memory_budget.saturating_add(more);
        if !self.setup.memory_given && total <= within {
            return Ok(());
        }
        bail!(
            "size {} {w} {h}: the views' images would need {} ({pixels} pixels in all), {} more than the {} set aside for them{}; a smaller size{}",
            VIEWS[v],
            human(need),
            human(more),
            human(have),
            match self.setup.memory_given {
                true => format!(
                    " within --memory {} (by the window's size)",
                    human(self.setup.memory_budget)
                ),
                false => format!(", and the viewer would need {} of this machine's {}", human(total), human(within)),
            },
            match self.setup.memory_given {
                true => ", or a larger --memory",
                false => "",
            }
        );
    }

    pub(super) fn key(&mut self, k: &str) {
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
    pub(super) fn slice_point(&self, v: usize, px: f64, py: f64) -> Vec3 {
        let size = self.render_size(v);
        let cam = self.slice_camera(v, size);
        let ray = cam.ray(px, py, size[0], size[1]);
        let n = normalize(self.plane_normal(v));
        let t = dot(n, sub(self.cursor, ray.origin)) / dot(n, ray.dir);
        let p = ray.at(t);
        let e = self.ds.extent;
        [0, 1, 2].map(|a| p[a].clamp(0.0, e[a]))
    }

    /// [`Self::slice_point`], and the level the labels drawn at that pixel
    /// come from (the label image laid over, or the label image shown
    /// itself): the level the view's frame read there, by its footprint
    /// and its level of detail, so the readout and picks read what the
    /// view draws, also where it draws a coarser level.
    pub(super) fn slice_pixel(&self, v: usize, px: f64, py: f64) -> (Vec3, usize) {
        let size = self.render_size(v);
        let cam = self.slice_camera(v, size);
        let ray = cam.ray(px, py, size[0], size[1]);
        let n = normalize(self.plane_normal(v));
        let t = dot(n, sub(self.cursor, ray.origin)) / dot(n, ray.dir);
        let fp = cam.pixel_footprint(t, size[1]);
        let (voxel0, levels) = match &self.labels {
            Some(l) => (l.voxel0, l.levels),
            None => (self.voxel0(), self.ds.levels.len()),
        };
        let lod = self.drawn_lod(v, self.labels.as_ref().map(|l| l.views[v].last.as_deref()));
        (
            self.slice_point(v, px, py),
            lod.level_for(fp, voxel0, levels),
        )
    }

    /// The level of detail view `v`'s latest frame was drawn with (of the
    /// labels laid over it when `layer` is given: their latest frame), or,
    /// before there is one, what the controls ask for.
    pub(super) fn drawn_lod(&self, v: usize, layer: Option<Option<&Out>>) -> Lod {
        let last = match layer {
            Some(l) => l,
            None => self.views[v].last.as_deref(),
        };
        last.map_or(self.asked_lod(), |o| o.lod)
    }

    /// Where the cursor is in slice view `v`, in render pixels.
    pub(super) fn cursor_pixel(&self, v: usize) -> Option<[f64; 2]> {
        let size = self.render_size(v);
        self.slice_camera(v, size)
            .project(self.cursor, size[0], size[1])
    }

    pub(super) fn slice_drag(&mut self, v: usize, button: &str, dx: f64, dy: f64) {
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

    pub(super) fn drag(&mut self, v: usize, button: &str, dx: f64, dy: f64) {
        if v == 0 {
            match button {
                "left" => self.orbit(dx, dy),
                _ => self.pan(dx, dy),
            }
        } else {
            self.slice_drag(v, button, dx, dy);
        }
    }

    pub(super) fn scroll(&mut self, v: usize, steps: f64) {
        if v == 0 {
            self.zoom(steps);
        } else {
            let vs = &mut self.views[v];
            vs.zoom = (vs.zoom * 1.15f64.powf(steps)).clamp(0.05, 200.0);
        }
    }

    pub(super) fn set_tf_preset(&mut self, name: &str) -> Result<()> {
        self.tf =
            TransferFunction::preset(name, self.tf.window).map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(())
    }

    pub(super) fn set_colormap(&mut self, name: &str) -> Result<()> {
        let p = Preset::parse(name).with_context(|| format!("unknown colour map {name:?}"))?;
        self.tf.colormap = ColorMap::Preset(p);
        Ok(())
    }

    pub(super) fn set_window(&mut self, lo: f32, hi: f32) -> Result<()> {
        if !(lo.is_finite() && hi.is_finite() && hi > lo) {
            bail!("window: expected LO < HI, found {lo} {hi}");
        }
        self.tf.window = [lo, hi];
        for c in &mut self.channels {
            c.window = [lo, hi];
        }
        Ok(())
    }

    pub(super) fn add_point(&mut self, x: f32, a: f32) {
        let x = x.clamp(0.0, 1.0);
        let a = a.clamp(0.0, 1.0);
        let i = self.tf.opacity.partition_point(|p| p[0] <= x);
        self.tf.opacity.insert(i, [x, a]);
    }

    pub(super) fn channel_ui(&mut self, c: usize) -> Result<&mut ChannelUi> {
        let n = self.channels.len();
        self.channels
            .get_mut(c)
            .with_context(|| format!("channel {c}: the store has {n} channel(s)"))
    }

    /// Keys pressed this frame (when no text field has focus).
    pub(super) fn keys(&mut self, ctx: &egui::Context) {
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
    }

    // ---- scripts ---------------------------------------------------------

    pub(super) fn fail(&mut self, ctx: &egui::Context, e: &str) {
        eprintln!("view: script: {e}");
        self.exit.store(1, Ordering::SeqCst);
        self.script.clear();
        ctx.send_viewport_cmd(egui::ViewportCommand::Close);
    }

    /// A script command answered by the readout's thread (`pick`,
    /// `goto-label`): `start` asks, then it waits until the answer is taken
    /// (`pick` and `goto` cleared); done when the message then starts with
    /// `ok`, else an error with the message.
    fn await_answer(
        &mut self,
        what: &str,
        ok: &str,
        start: impl FnOnce(&mut Self) -> Result<()>,
    ) -> Result<bool> {
        let Some(since) = self.waiting else {
            self.waiting = Some(Instant::now());
            self.message.clear();
            start(self).with_context(|| what.to_string())?;
            return Ok(false);
        };
        if self.pick.is_some() || self.goto.is_some() || self.pick3d || self.seek.is_some() {
            if since.elapsed() > Duration::from_secs(60) {
                bail!("{what}: no answer in 60 s");
            }
            return Ok(false);
        }
        self.waiting = None;
        if !self.message.starts_with(ok) {
            // (The message may already name the command.)
            let m = self.message.trim_start_matches(&format!("{what}: "));
            bail!("{what}: {m}");
        }
        Ok(true)
    }

    /// Run script commands until one has to wait.
    pub(super) fn run_script(&mut self, ctx: &egui::Context) {
        while self.pc < self.script.len() {
            if self.window_shot.is_some() {
                return;
            }
            let step = self.script[self.pc].clone();
            let cmd = step.cmd;
            let r: Result<bool> = (|| {
                Ok(match &cmd {
                    Cmd::Size(v, w, h) => {
                        self.check_view_size(*v, *w, *h)?;
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
                    Cmd::Click(0, x, y) => {
                        // As a double-click: the cursor to the point shown.
                        let (x, y) = (*x as f64, *y as f64);
                        if self.waiting.is_none() {
                            self.check_pixel("click", 0, x, y)?;
                        }
                        if self.probe.is_none() {
                            bail!("click 3d: the viewer has no voxel readout");
                        }
                        self.await_answer("click 3d", "cursor at", |a| {
                            a.seek = Some(((x, y), None));
                            Ok(())
                        })?
                    }
                    Cmd::Click(v, x, y) => {
                        self.check_pixel("click", *v, *x as f64, *y as f64)?;
                        self.cursor = self.slice_point(*v, *x as f64, *y as f64);
                        true
                    }
                    Cmd::Key(k) => {
                        self.key(k);
                        true
                    }
                    Cmd::Hover(h) => {
                        if let Some((v, x, y)) = *h {
                            self.check_pixel("hover", v, x, y)?;
                        }
                        self.script_hover = *h;
                        true
                    }
                    Cmd::Pick(v, x, y) => {
                        if self.probe.is_none() {
                            bail!("pick: the viewer has no voxel readout");
                        }
                        let (v, x, y) = (*v, *x, *y);
                        if self.waiting.is_none() {
                            self.check_pixel("pick", v, x, y)?;
                        }
                        let at = self.slice_pixel(v.max(1), x, y);
                        self.await_answer("pick", "labels picked", |a| match v {
                            0 => a.pick_3d(x, y).map_err(|e| anyhow::anyhow!("{e}")),
                            _ => {
                                a.pick = Some(at);
                                Ok(())
                            }
                        })?
                    }
                    Cmd::GotoLabel(id) => {
                        let id = *id;
                        self.await_answer("goto-label", &format!("label {id}: at"), |a| {
                            a.goto_label(id).map_err(|e| anyhow::anyhow!("{e}"))
                        })?
                    }
                    Cmd::LargestLabels(n, order) => {
                        let Some(p) = &mut self.probe else {
                            bail!("largest-labels: the viewer has no voxel readout");
                        };
                        if p.stats_dims.is_none() {
                            bail!("largest-labels: no label image is shown");
                        }
                        let since = match self.waiting {
                            Some(t) => t,
                            None => {
                                self.table_order = *order;
                                p.largest(*n, *order);
                                self.largest_asked = true;
                                *self.waiting.insert(Instant::now())
                            }
                        };
                        match &p.largest {
                            None if since.elapsed() > Duration::from_secs(120) => {
                                bail!("largest-labels: no answer in 120 s")
                            }
                            None => false,
                            Some(Err(e)) => bail!("largest-labels: {e}"),
                            Some(Ok(rows)) => {
                                let means: Vec<Option<f64>> =
                                    rows.iter().map(|(_, r)| r.mean).collect();
                                let rows: Vec<[u64; 2]> =
                                    rows.iter().map(|(id, r)| [*id, r.voxels]).collect();
                                self.waiting = None;
                                let t = self.started.elapsed().as_secs_f64();
                                self.log_line(
                                    serde_json::json!({ "t": t, "largest": rows, "means": means }),
                                );
                                true
                            }
                        }
                    }
                    Cmd::LabelSelect(t) => {
                        if self.labels.is_none() && !self.ds.labels {
                            bail!("label-select: no label image is shown");
                        }
                        self.set_picked(t)?;
                        true
                    }
                    Cmd::LabelMode(m) => {
                        if self.labels.is_none() && !self.ds.labels {
                            bail!("label-mode: no label image is shown");
                        }
                        self.label_mode = *m;
                        true
                    }
                    Cmd::WaitProbe(secs) => {
                        let since = *self.waiting.get_or_insert_with(Instant::now);
                        // The question for the point read now goes out first.
                        self.probe();
                        let Some(p) = &self.probe else {
                            bail!("wait-probe: the viewer has no voxel readout");
                        };
                        if p.answered() {
                            self.waiting = None;
                            true
                        } else if since.elapsed().as_secs_f64() > *secs {
                            bail!("wait-probe: no answer in {secs} s");
                        } else {
                            false
                        }
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
                    Cmd::ChannelLevels(c, range) => {
                        let n = self.ds.levels.len();
                        if let Some([lo, hi]) = range {
                            if lo > hi || *hi >= n {
                                bail!("channel-levels: expected LO <= HI within 0-{}, found {lo} {hi}", n - 1);
                            }
                        }
                        self.channel_ui(*c)?.levels = *range;
                        true
                    }
                    Cmd::Apply(name) => {
                        self.apply(name)?;
                        true
                    }
                    Cmd::WaitJob(secs) => {
                        let since = *self.waiting.get_or_insert_with(Instant::now);
                        if self.job.is_none() {
                            self.waiting = None;
                            match &self.last_job {
                                Some(super::process::JobEnd::Failed(m)) => bail!("wait-job: {m}"),
                                Some(_) => true,
                                None => bail!("wait-job: no job was started"),
                            }
                        } else if since.elapsed().as_secs_f64() > *secs {
                            bail!("wait-job: still running after {secs} s");
                        } else {
                            false
                        }
                    }
                    Cmd::Derive(p) => {
                        self.set_derive(p.as_deref())?;
                        true
                    }
                    Cmd::DvrChannel(c) => {
                        self.channel_ui(*c)?;
                        self.dvr_channel = *c;
                        true
                    }
                    Cmd::Labels(on) => {
                        let Some(l) = &mut self.labels else {
                            bail!("labels: the viewer was started without --labels NAME");
                        };
                        l.shown = *on;
                        self.labels_changed(ctx);
                        true
                    }
                    Cmd::LabelOpacity(a) => {
                        let Some(l) = &mut self.labels else {
                            bail!("label-opacity: the viewer was started without --labels NAME");
                        };
                        l.opacity = *a;
                        self.labels_changed(ctx);
                        true
                    }
                    Cmd::DvrChannels(on) => {
                        self.dvr_channels = *on;
                        true
                    }
                    Cmd::Stereo(layout, n) => {
                        self.stereo = layout.clone();
                        if layout == "tiles" {
                            self.n_views = *n;
                        }
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
                    Cmd::Sleep(ms) => {
                        let since = *self.waiting.get_or_insert_with(Instant::now);
                        if since.elapsed().as_secs_f64() * 1e3 >= *ms {
                            self.waiting = None;
                            true
                        } else {
                            false
                        }
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
                Ok(true) => {
                    // The log marks where each command took effect, between
                    // the frames before and after it.
                    self.log_line(serde_json::json!({
                        "t": self.started.elapsed().as_secs_f64(),
                        "script_line": step.line,
                        "command": format!("{cmd:?}"),
                    }));
                    self.pc += 1
                }
                Ok(false) => return,
                Err(e) => {
                    self.fail(ctx, &format!("{}: {e:#}", step.at));
                    return;
                }
            }
        }
    }
}
