//! Saving what the window shows: a view's image as PNG, the whole window
//! as a screenshot, and a view as the `brickyard render` arguments (camera
//! and transfer-function JSON) that draw it again.

use super::{Vec3, ViewerApp};
use crate::view::script::VIEWS;
use anyhow::{bail, Context, Result};
use brickyard_render::cpu::Lod;
use brickyard_render::params::Traversal;
use brickyard_render::reference::RenderMode;
use brickyard_render::views::Layout;
use eframe::egui;
use std::path::Path;

impl ViewerApp {
    /// The `brickyard render` arguments that draw view `v` as it is now.
    pub(super) fn render_args(&self, v: usize, prefix: &Path) -> Result<Vec<String>> {
        let spec = self.spec(v);
        let p = &spec.params;
        let cam_path = prefix.with_extension("camera.json");
        let tf_path = prefix.with_extension("tf.json");
        std::fs::write(&cam_path, p.camera.to_json())
            .with_context(|| format!("{}: cannot write", cam_path.display()))?;
        std::fs::write(&tf_path, p.tf.to_json())
            .with_context(|| format!("{}: cannot write", tf_path.display()))?;
        let count = p.views.map_or(1, |v| v.count);
        let mut a: Vec<String> = vec![
            "--size".into(),
            format!("{}x{}", p.width / count, p.height),
            "--camera".into(),
            cam_path.display().to_string(),
            "--tf".into(),
            // A label image's slice: its labels' colours.
            match p.labels {
                true => "labels".into(),
                false => tf_path.display().to_string(),
            },
        ];
        // (Rays take samples in dvr and mip; a slice one per pixel.)
        if !matches!(p.mode, RenderMode::Slice { .. }) {
            a.extend([
                "--samples-per-voxel".into(),
                format!("{}", p.samples_per_voxel),
            ]);
        }
        // Sample accumulation where the view's latest frame was one (of
        // the version shown): what was drawn, not what could have been.
        let vs = &self.views[v];
        let accumulated = vs
            .last
            .as_ref()
            .filter(|o| o.version == vs.version)
            .and_then(|o| o.accumulated)
            .filter(|&(k, n)| k > 0 && n > 0);
        match &p.mode {
            RenderMode::Dvr if p.channels.is_empty() && !p.labels && accumulated.is_some() => {
                let (_, n) = accumulated.expect("matched");
                a.extend([
                    "--mode".into(),
                    "dvr".into(),
                    "--progressive".into(),
                    n.to_string(),
                ])
            }
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
        if let (Some(views), Some(layout)) = (&p.views, &spec.layout) {
            let voxels = views.spacing / self.voxel0();
            match layout {
                Layout::SideBySide => a.extend(["--stereo".into(), "sbs".into()]),
                Layout::Anaglyph => a.extend(["--stereo".into(), "anaglyph".into()]),
                _ => a.extend(["--views".into(), views.count.to_string()]),
            }
            if matches!(p.mode, RenderMode::Slice { .. }) {
                a.extend([
                    "--parallax".into(),
                    format!("{}", views.parallax),
                    "--spacing".into(),
                    format!("{voxels}"),
                ]);
            } else {
                a.extend(["--eye-separation".into(), format!("{}", views.separation)]);
            }
        }
        if let (Traversal::Octree, Some(depth)) = (p.traversal, self.setup.octree) {
            a.extend([
                "--traversal".into(),
                "octree".into(),
                "--octree-depth".into(),
                depth.to_string(),
            ]);
        }
        if let (Some(l), Some(_)) = (&self.labels, self.label_spec(&spec)) {
            a.extend([
                "--labels".into(),
                l.name.clone(),
                "--label-opacity".into(),
                format!("{}", l.opacity),
            ]);
        }
        // The labels drawn, of the label image shown or laid over it.
        let select = match p.labels {
            true => p.label_select.clone(),
            false => self.label_spec(&spec).and_then(|s| s.params.label_select),
        };
        if let Some(sel) = select {
            let flag = if sel.hide {
                "--hide-labels"
            } else {
                "--only-labels"
            };
            a.extend([flag.into(), sel.ids_text()]);
        }
        match spec.lod {
            Lod::Fixed(l) => a.extend(["--level".into(), l.to_string()]),
            Lod::Auto { bias } => a.extend(["--lod-bias".into(), format!("{bias}")]),
        }
        if let Some((pipeline, channel)) = self.derived_args() {
            // The derived channel, computed from one stored channel.
            a.extend([
                "--derive".into(),
                pipeline,
                "--channel".into(),
                channel.to_string(),
            ]);
        } else if p.mode == RenderMode::Dvr && p.channels.is_empty() {
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
            if p.mode == RenderMode::Dvr {
                for s in &p.channels {
                    if let Some([lo, hi]) = s.levels {
                        a.extend([
                            "--channel-levels".into(),
                            format!("{}={lo}-{hi}", s.channel),
                        ]);
                    }
                }
            }
        }
        Ok(a)
    }

    pub(super) fn save_view(&self, v: usize, prefix: &Path) -> Result<()> {
        let a = self.render_args(v, prefix)?;
        let args_path = prefix.with_extension("args");
        std::fs::write(&args_path, a.join("\n") + "\n")
            .with_context(|| format!("{}: cannot write", args_path.display()))?;
        Ok(())
    }

    pub(super) fn screenshot(&self, v: usize, path: &Path) -> Result<()> {
        let Some(img) = self.shown_image(v) else {
            bail!("screenshot {}: no frame yet", VIEWS[v]);
        };
        img.write_png(path, [0.0, 0.0, 0.0, 1.0])
            .map_err(|e| anyhow::anyhow!("{e}"))
    }

    /// Writes the window screenshot a script asked for, once egui has it.
    pub(super) fn take_window_shot(&mut self, ctx: &egui::Context) {
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
