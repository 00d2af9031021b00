//! The window's panels: the controls (mode, channels, transfer function,
//! window, quality, level of detail, budgets, saving), the transfer-function
//! editor over the histogram, each view's image with its mouse input and
//! cursor lines, and the status line.

use super::ViewerApp;
use crate::view::probe::SortBy;
use crate::view::script::VIEWS;
use crate::view::worker::Msg;
use brickyard_core::camera::Camera;
use brickyard_core::transfer::{ColorMap, Preset};
use brickyard_core::TransferFunction;
use brickyard_render::params::Traversal;
use brickyard_store::info::human_bytes;
use eframe::egui;
use std::path::PathBuf;

/// Rows of the largest-labels table.
pub(super) const LARGEST: usize = 50;

impl ViewerApp {
    /// `--labels NAME`: shown or not, and how opaque.
    fn label_controls(&mut self, ui: &mut egui::Ui) {
        let Some(l) = &mut self.labels else {
            return;
        };
        let mut changed = false;
        ui.horizontal(|ui| {
            changed |= ui
                .checkbox(&mut l.shown, format!("labels/{}", l.name))
                .on_hover_text("The label image over the slice views, each label in its colour")
                .changed();
            changed |= ui
                .add(egui::Slider::new(&mut l.opacity, 0.05..=1.0).text("opacity"))
                .changed();
        });
        if changed {
            self.labels_changed(&ui.ctx().clone());
        }
    }

    /// Which labels a label image draws: all, only those picked, or all
    /// but them; the list picked (Ctrl+click in a slice view adds or
    /// removes the label under the pointer).
    fn selection_controls(&mut self, ui: &mut egui::Ui) {
        if self.labels.is_none() && !self.ds.labels {
            return;
        }
        ui.horizontal(|ui| {
            ui.label("draw");
            for (m, name) in [(0u8, "all"), (1, "only picked"), (2, "all but picked")] {
                ui.selectable_value(&mut self.label_mode, m, name);
            }
        });
        ui.horizontal(|ui| {
            let edit = ui
                .add(egui::TextEdit::singleline(&mut self.picked_text).desired_width(150.0))
                .on_hover_text("Labels picked, e.g. 3,17,40-45; Ctrl+click a label in a slice view adds or removes it");
            let enter = edit.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter));
            if ui.button("Set").clicked() || enter {
                self.message = match self.set_picked(&self.picked_text.clone()) {
                    Ok(()) => String::new(),
                    Err(e) => format!("{e:#}"),
                };
            }
            if ui.button("Clear").clicked() {
                self.set_picked_ids(vec![]);
            }
            // The cursor to the centroid of the label typed first (or the
            // last picked).
            let first = self.picked_text.split([',', '-']).next().and_then(|t| t.trim().parse::<u64>().ok());
            if let Some(id) = first.or(self.picked.last().map(|&i| i as u64)) {
                if ui
                    .button(format!("Go to {id}"))
                    .on_hover_text("Move the cursor to the label's centroid (by the label statistics)")
                    .clicked()
                {
                    if let Err(e) = self.goto_label(id) {
                        self.message = e;
                    }
                }
            }
        });
    }

    /// The label table, from the label statistics: the first labels by
    /// size, mean or label (of at least so many voxels), each with its size
    /// and mean, a button to pick it and one to go to it.
    fn largest_labels(&mut self, ui: &mut egui::Ui) {
        let Some(p) = &mut self.probe else {
            return;
        };
        if p.stats_dims.is_none() {
            return;
        }
        let order = &mut self.table_order;
        let open = egui::CollapsingHeader::new("Labels").show(ui, |ui| {
            let mut pick = None;
            let mut goto = None;
            let was = *order;
            ui.horizontal(|ui| {
                egui::ComboBox::from_id_salt("table-by")
                    .selected_text(order.by.name())
                    .show_ui(ui, |ui| {
                        for b in SortBy::ALL {
                            ui.selectable_value(&mut order.by, b, b.name());
                        }
                    });
                ui.checkbox(&mut order.descending, "most first");
                ui.label("at least");
                ui.add(egui::DragValue::new(&mut order.min_voxels).suffix(" vx"));
            });
            if *order != was {
                p.largest(LARGEST, *order);
            }
            match &p.largest {
                None => {
                    ui.label("reading the label statistics…");
                }
                Some(Err(e)) => {
                    ui.label(e.as_str());
                }
                Some(Ok(rows)) => {
                    egui::ScrollArea::vertical()
                        .max_height(160.0)
                        .show(ui, |ui| {
                            for (id, r) in rows {
                                ui.horizontal(|ui| {
                                    let mean =
                                        r.mean.map_or(String::new(), |m| format!(" mean {m:.4}"));
                                    ui.monospace(format!("{id:>7} {:>10} vx{mean}", r.voxels));
                                    if ui.small_button("pick").clicked() {
                                        pick = Some(*id);
                                    }
                                    if ui.small_button("go to").clicked() {
                                        goto = Some(*id);
                                    }
                                });
                            }
                        });
                }
            }
            (pick, goto)
        });
        if open.body_returned.is_some() && p.largest.is_none() && !self.largest_asked {
            p.largest(LARGEST, self.table_order);
            self.largest_asked = true;
        }
        if let Some((pick, goto)) = open.body_returned {
            if let Some(id) = pick {
                self.toggle_picked(id as i32);
            }
            if let Some(id) = goto {
                if let Err(e) = self.goto_label(id) {
                    self.message = e;
                }
            }
        }
    }

    /// The labels picked, from text as `render --only-labels` takes it
    /// (empty or `none`: none).
    pub(super) fn set_picked(&mut self, text: &str) -> anyhow::Result<()> {
        let ids = match text.trim() {
            "" | "none" => vec![],
            t => brickyard_render::params::LabelSelect::parse_ids(t)
                .map_err(|e| anyhow::anyhow!("labels picked: {e}"))?,
        };
        self.set_picked_ids(ids);
        Ok(())
    }

    /// The labels were turned on or off or their opacity changed: the
    /// views show it at once (the specs follow with the next frame).
    pub(super) fn labels_changed(&mut self, ctx: &egui::Context) {
        for v in 0..super::N_VIEWS {
            self.refresh_texture(ctx, v);
        }
    }

    pub(super) fn controls(&mut self, ui: &mut egui::Ui) {
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
        ui.horizontal(|ui| {
            ui.label("Views:");
            for (v, label) in [
                ("off", "one"),
                ("sbs", "stereo side by side"),
                ("anaglyph", "anaglyph"),
                ("tiles", "N views"),
            ] {
                ui.selectable_value(&mut self.stereo, v.to_string(), label);
            }
            if self.stereo == "tiles" {
                ui.add(
                    egui::DragValue::new(&mut self.n_views)
                        .range(2..=brickyard_core::views::MAX_VIEWS),
                );
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
            ui.checkbox(
                &mut self.dvr_channels,
                "DVR: composite the visible channels (each in its colour and window)",
            );
            ui.label("Channels (MIP and slices add them up):");
            let nl = self.ds.levels.len();
            for (i, c) in self.channels.iter_mut().enumerate() {
                ui.horizontal(|ui| {
                    ui.checkbox(&mut c.visible, format!("{i}"));
                    let mut rgb = c.color.map(|x| x as f32 / 255.0);
                    if ui.color_edit_button_rgb(&mut rgb).changed() {
                        c.color = rgb.map(|x| (x * 255.0).round() as u8);
                    }
                    ui.add(egui::DragValue::new(&mut c.window[0]).speed(1.0));
                    ui.add(egui::DragValue::new(&mut c.window[1]).speed(1.0));
                    // DVR: the levels this channel is drawn at.
                    let mut limited = c.levels.is_some();
                    if ui
                        .checkbox(&mut limited, "levels")
                        .on_hover_text("DVR of several channels: draw this channel only at these pyramid levels (finest, coarsest)")
                        .changed()
                    {
                        c.levels = limited.then_some([0, nl - 1]);
                    }
                    if let Some([lo, hi]) = &mut c.levels {
                        ui.add(egui::DragValue::new(lo).range(0..=nl - 1));
                        ui.add(egui::DragValue::new(hi).range(0..=nl - 1));
                        *hi = (*hi).max(*lo);
                    }
                });
            }
        }
        self.label_controls(ui);
        self.selection_controls(ui);
        self.largest_labels(ui);
        ui.separator();
        self.processing_panel(ui);
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
                let _ = self.tx.send(Msg::Reopen(Box::new(s)));
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

    pub(super) fn tf_editor(&mut self, ui: &mut egui::Ui) {
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

    pub(super) fn view_panel(&mut self, ui: &mut egui::Ui, v: usize, size: egui::Vec2) {
        let (rect, resp) = ui.allocate_exact_size(size, egui::Sense::click_and_drag());
        let ppp = ui.ctx().pixels_per_point();
        let px = [(rect.width() * ppp) as u32, (rect.height() * ppp) as u32]
            .map(|s| (s / 8 * 8).max(16));
        self.views[v].size = px;
        if v == 0 {
            self.fit_home(self.views[0].forced.unwrap_or(px));
        }
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
        if v == 0 && resp.double_clicked() {
            // A double-click in 3D moves the cursor to the point shown.
            if let Some(pos) = resp.interact_pointer_pos() {
                let q = (pos - rect.min) * k;
                self.seek = Some(((q.x as f64, q.y as f64), None));
            }
        } else if v == 0 && resp.clicked() && ui.input(|i| i.modifiers.command) {
            // Ctrl+click in 3D picks the label shown there.
            if let Some(pos) = resp.interact_pointer_pos() {
                let q = (pos - rect.min) * k;
                if let Err(e) = self.pick_3d(q.x as f64, q.y as f64) {
                    self.message = e;
                }
            }
        }
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
                let at = self.slice_pixel(v, q.x as f64, q.y as f64);
                // Ctrl+click picks the label there; a click moves the
                // cursor.
                if ui.input(|i| i.modifiers.command) {
                    self.pick = Some(at);
                } else {
                    self.cursor = at.0;
                }
            }
        }
        if resp.dragged_by(egui::PointerButton::Secondary)
            || resp.dragged_by(egui::PointerButton::Middle)
        {
            let d = resp.drag_delta() * k;
            self.drag(v, "right", d.x as f64, d.y as f64);
        }
        // The voxel readout follows the pointer over a slice view, and over
        // the 3D view (the point it shows there).
        if let Some(pos) = resp.hover_pos().filter(|p| rect.contains(*p)) {
            let q = (pos - rect.min) * k;
            match v {
                0 => self.hover_3d = Some((q.x as f64, q.y as f64)),
                _ => self.hover = Some(self.slice_pixel(v, q.x as f64, q.y as f64)),
            }
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
            // With --traversal octree: which traversal draws the 3D view
            // (the slice views always walk the page tables).
            0 => match (self.setup.octree, self.views[0].sent.as_ref()) {
                (Some(d), Some(sp)) if sp.params.traversal == Traversal::Octree => {
                    format!("3D · {} · octree, depth {d}", self.mode.to_uppercase())
                }
                (Some(_), _) => format!("3D · {} · page tables", self.mode.to_uppercase()),
                (None, _) => format!("3D · {}", self.mode.to_uppercase()),
            },
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

    pub(super) fn status(&self) -> String {
        let Some(o) = self.views[0].last.as_ref() else {
            return "waiting for the first frame".into();
        };
        let rate = match (self.read_history.first(), self.read_history.last()) {
            (Some(a), Some(b)) if b.0 > a.0 => (b.1 - a.1) as f64 / (b.0 - a.0).as_secs_f64(),
            _ => 0.0,
        };
        let mut detail = String::new();
        match o.accumulated {
            Some((_, n)) if o.settled => {
                detail += &format!(" · accumulated {n} frames");
                if o.accumulated_fewest < n {
                    detail += &format!(
                        " ({} in the longest rays: their memory for samples is full)",
                        o.accumulated_fewest
                    );
                }
            }
            Some((k, n)) => detail += &format!(" · accumulating {k}/{n}"),
            None => {}
        }
        if o.reblended {
            detail += " (re-blended)";
        }
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
        // The label image's session (`--labels`), while shown.
        let labels = match self.labels.as_ref().filter(|l| l.shown) {
            Some(l) => {
                let [resident, slots, pending, failed] = l.figures;
                let unreadable = match failed {
                    0 => String::new(),
                    n => format!(" · {n} unreadable"),
                };
                format!(
                    "\nlabels/{}: {resident} bricks resident of {slots} slots · {pending} pending{unreadable}",
                    l.name
                )
            }
            None => String::new(),
        };
        let mut probe = self
            .probe_line()
            .map_or(String::new(), |p| format!("\n{p}"));
        if let Some(sel) = self.label_selection() {
            let what = if sel.hide {
                "all labels but"
            } else {
                "only labels"
            };
            let mut ids = sel.ids_text();
            if ids.len() > 80 {
                let cut = ids[..80].rfind(',').unwrap_or(0);
                ids = format!("{}… ({} labels)", &ids[..cut], sel.ids.len());
            }
            probe += &format!("\ndrawing {what} {ids}");
        }
        format!(
            "{:.1} ms/frame · {:.1}% complete{detail}\n{} bricks resident of {} slots · {} pending{labels}\nhost cache {} of {} · {:.1} MiB/s read{peak}\n{}{probe}",
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
