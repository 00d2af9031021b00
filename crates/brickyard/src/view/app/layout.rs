//! What each view shows and where it sits: plane normals, render sizes,
//! the slice views' cameras, the render specification sent for each view,
//! and the window's arrangement (controls on the left, the 3D view, the
//! four slice views in a column).

use super::{Vec3, ViewerApp, N_VIEWS};
use crate::view::worker::{Msg, Spec};
use brickyard_core::camera::{add, dot, length, normalize, scale, sub, Camera, Projection};
use brickyard_core::views::Views;
use brickyard_core::TransferFunction;
use brickyard_render::cpu::Lod;
use brickyard_render::params::Traversal;
use brickyard_render::reference::{ChannelStyle, RenderMode, RenderParams};
use brickyard_render::views::Layout;
use eframe::egui;
use std::time::Duration;

/// What slices use: the transfer function's window and colours at opacity 1.
fn tf_opaque(tf: &TransferFunction) -> TransferFunction {
    TransferFunction {
        window: tf.window,
        opacity: vec![[0.0, 1.0]],
        colormap: tf.colormap.clone(),
        shading: None,
    }
}

impl ViewerApp {
    pub(super) fn oblique_normal(&self) -> Vec3 {
        let (sa, ca) = self.oblique[0].to_radians().sin_cos();
        let (se, ce) = self.oblique[1].to_radians().sin_cos();
        [ce * sa, -ce * ca, se]
    }

    pub(super) fn plane_normal(&self, v: usize) -> Vec3 {
        match v {
            1 => [0.0, 0.0, 1.0],
            2 => [0.0, 1.0, 0.0],
            3 => [1.0, 0.0, 0.0],
            _ => self.oblique_normal(),
        }
    }

    pub(super) fn render_size(&self, v: usize) -> [u32; 2] {
        let vs = &self.views[v];
        if let Some(f) = vs.forced {
            return f;
        }
        // While the 3D view moves, fewer pixels where full-size frames
        // would not keep up (the page draws by the same rule).
        if v == 0 && self.interacting.elapsed() < Duration::from_millis(200) {
            let k = brickyard_render::budget::moving_scale(self.full_ms, self.moving_last);
            return brickyard_render::budget::scaled_size(vs.size, k);
        }
        vs.size
    }

    /// The home camera for a 3D view of `size` pixels: the whole volume
    /// in both its height and width ([`Camera::fit_image`]). The current
    /// camera follows while it is still the home one (not moved, not
    /// given).
    pub(super) fn fit_home(&mut self, size: [u32; 2]) {
        let home = Camera::fit_image(
            self.ds.extent,
            30.0,
            20.0,
            Projection::Perspective { fov_y_deg: 35.0 },
            size[0],
            size[1],
        );
        if home != self.home {
            if self.cam == self.home {
                self.cam = home;
            }
            self.home = home;
        }
    }

    pub(super) fn slice_camera(&self, v: usize, size: [u32; 2]) -> Camera {
        let n = self.plane_normal(v);
        let vs = &self.views[v];
        let e = self.ds.extent;
        // The three planes share one scale (a cube of the volume's longest
        // side fits each view), in the view's height and, for a view
        // taller than wide, its width too.
        let aspect = size[0].max(1) as f64 / size[1].max(1) as f64;
        let height =
            e.iter().cloned().fold(0.0, f64::max) * 1.05 * (1.0 / aspect).max(1.0) / vs.zoom;
        let base = Camera::facing_plane(self.cursor, n, height);
        let b = base.basis();
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

    /// Whether DVR composites the visible channels: asked for, with two
    /// or more visible (one goes through the transfer function, as
    /// `render --channel C` does).
    pub(super) fn dvr_composites(&self) -> bool {
        self.dvr_channels
            && self.ds.channels > 1
            && self.channels.iter().filter(|c| c.visible).count() >= 2
    }

    pub(super) fn styles(&self) -> Vec<ChannelStyle> {
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
                tf: None,
                levels: c.levels,
            })
            .collect()
    }

    /// The level of detail the controls ask for.
    pub(super) fn asked_lod(&self) -> Lod {
        match self.level {
            Some(l) => Lod::Fixed(l),
            None => Lod::Auto {
                bias: self.lod_bias,
            },
        }
    }

    pub(super) fn spec(&self, v: usize) -> Spec {
        let [w, h] = self.render_size(v);
        let lod = self.asked_lod();
        let (camera, tf, mode) = if v == 0 {
            let mode = match self.mode.as_str() {
                "mip" => RenderMode::Mip,
                "slice" => RenderMode::Slice {
                    origin: self.cursor,
                    normal: self.oblique_normal(),
                },
                _ => RenderMode::Dvr,
            };
            // A slice is opaque; a super-slice composites its slices
            // through the transfer function's opacity.
            let tf = if self.mode == "slice" && self.stereo == "off" {
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
        if mode != RenderMode::Dvr || self.dvr_composites() {
            params.channels = self.styles();
        }
        // A label image (one view each): its labels' colours in slices,
        // its labels' surfaces in DVR (through the page tables).
        params.labels = self.ds.labels
            && matches!(mode, RenderMode::Slice { .. } | RenderMode::Dvr)
            && params.channels.is_empty()
            && !(mode == RenderMode::Dvr && self.setup.octree.is_some());
        if params.labels {
            params.label_select = self.label_selection();
        }
        if v == 0 && self.octree_draws(&params) && !params.labels {
            params.traversal = Traversal::Octree;
        }
        let mut layout = None;
        if v == 0 && self.stereo != "off" && (self.mode != "slice" || params.channels.is_empty()) {
            let (count, l) = match self.stereo.as_str() {
                "sbs" => (2, Layout::SideBySide),
                "anaglyph" => (2, Layout::Anaglyph),
                _ => (self.n_views, Layout::Tiles),
            };
            // Each view's size: the panel split between them (side by
            // side: halves; tiles: a grid), an anaglyph's the whole panel.
            let [vw, vh] = match l {
                Layout::SideBySide => [w / 2, h],
                Layout::Tiles => {
                    let cols = (count as f64).sqrt().ceil() as u32;
                    [w / cols, h / count.div_ceil(cols)]
                }
                _ => [w, h],
            };
            let slices = self.mode == "slice";
            let distance = length(sub(camera.target, camera.eye));
            params.width = vw.max(8) * count;
            params.height = vh.max(8);
            params.views = Some(Views {
                count,
                separation: if slices { 0.0 } else { distance / 30.0 },
                parallax: 1.0,
                spacing: self.voxel0(),
                alone: None,
            });
            // (Super-slices composite through the transfer function.)
            params.labels = false;
            params.label_select = None;
            layout = Some(l);
        }
        Spec {
            params,
            lod,
            channel: self.dvr_channel,
            layout,
        }
    }

    /// Whether the 3D view's `params` go through the residency octree
    /// (`--traversal octree`: DVR, unshaded unless it composites
    /// channels); everything else walks the page tables.
    pub(super) fn octree_draws(&self, params: &RenderParams) -> bool {
        self.setup.octree.is_some()
            && params.mode == RenderMode::Dvr
            && !(params.channels.is_empty() && params.tf.shading.is_some())
    }

    pub(super) fn voxel0(&self) -> f64 {
        let d = self.ds.levels[0];
        let e = self.ds.extent;
        // As `Scene::voxel(0)`: the smallest voxel edge of level 0.
        [0, 1, 2]
            .map(|a| e[a] / d[2 - a] as f64)
            .into_iter()
            .fold(f64::INFINITY, f64::min)
    }

    /// What the label image draws under view `v`'s `spec` (`None`: no
    /// labels there): a slice of one view, the image's plane, camera, size
    /// and level of detail, in the labels' colours.
    pub(super) fn label_spec(&self, spec: &Spec) -> Option<Spec> {
        let l = self.labels.as_ref().filter(|l| l.shown)?;
        let p = &spec.params;
        if !matches!(p.mode, RenderMode::Slice { .. }) || p.views.is_some() || p.labels {
            return None;
        }
        // (Its transfer function is fixed: edits of the image's draw no
        // labels again.)
        let params = p.labels_over(self.label_selection());
        let lod = match spec.lod {
            Lod::Fixed(x) => Lod::Fixed(x.min(l.levels - 1)),
            auto => auto,
        };
        Some(Spec {
            params,
            lod,
            channel: 0,
            layout: None,
        })
    }

    pub(super) fn send_specs(&mut self) {
        for v in 0..N_VIEWS {
            let spec = self.spec(v);
            let labels = self.label_spec(&spec);
            if self.views[v].sent.as_ref() != Some(&spec) {
                self.views[v].version += 1;
                self.views[v].sent = Some(spec.clone());
                let _ = self
                    .tx
                    .send(Msg::View(v, self.views[v].version, Some(Box::new(spec))));
            }
            if let Some(l) = &mut self.labels {
                let lv = &mut l.views[v];
                if lv.sent != labels {
                    lv.version += 1;
                    lv.sent = labels.clone();
                    let _ = l.tx.send(Msg::View(v, lv.version, labels.map(Box::new)));
                }
            }
        }
    }

    /// The window: controls in a panel on the left, the 3D view, and the
    /// four slice views in a column beside it.
    pub(super) fn lay_out(&mut self, ui: &mut egui::Ui) {
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
    }
}
