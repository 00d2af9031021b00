//! The processing panel: a live derived channel (a pipeline computed brick
//! by brick as the views ask for it, shown instead of the stored data).

use super::{Dataset, ViewerApp};
use crate::derive::Derived;
use crate::view::worker::Msg;
use anyhow::Result;
use eframe::egui;
use std::sync::Arc;

/// The dataset the window shows for derived channel `d` of `stored`: one
/// channel of the pipeline's type, its value range the default window of
/// the derived values (as `render --derive` takes it). The histogram is
/// empty: the store's statistics describe the stored values.
pub fn derived_dataset(stored: &Dataset, d: &Derived) -> Result<Dataset> {
    let window = crate::window::window_of_levels(stored.levels.len(), 0, |l| d.open_level(l))?
        .map(|(lo, hi)| [lo as f32, hi as f32])
        .filter(|w| w[1] > w[0])
        .unwrap_or([0.0, 1.0]);
    Ok(Dataset {
        channels: 1,
        dtype: d.open_level(0)?.meta().dtype,
        range: window,
        histogram: vec![0.0; stored.histogram.len()],
        ..stored.clone()
    })
}

impl ViewerApp {
    /// Show the live derived channel of `pipeline` over the channel the
    /// DVR shows (`None`: the stored data again). The session is opened
    /// again over the derived volume; the transfer function keeps its
    /// shape and takes the derived values' window.
    pub(super) fn set_derive(&mut self, pipeline: Option<&str>) -> Result<()> {
        let mut setup = self.setup.clone();
        match pipeline {
            None => {
                let Some((_, channel, window)) = self.derived.take() else {
                    return Ok(());
                };
                self.ds = self.stored.clone();
                self.dvr_channel = channel;
                self.tf.window = window;
                setup.derive = None;
                setup.channels = self.stored.channels;
                self.message = "showing the stored data".into();
            }
            Some(text) => {
                let channel = match &self.derived {
                    Some((_, c, _)) => *c,
                    None => self.dvr_channel,
                };
                let d = Derived::new(&self.stored.store, text, channel)?;
                let ds = derived_dataset(&self.stored, &d)?;
                let stored_window = match &self.derived {
                    Some((_, _, w)) => *w,
                    None => self.tf.window,
                };
                self.tf.window = ds.range;
                self.ds = Arc::new(ds);
                self.derived = Some((d.pipeline.text(), channel, stored_window));
                self.dvr_channel = 0;
                self.message = format!(
                    "showing {} of channel {channel}, computed as the views ask for it",
                    d.pipeline.text()
                );
                setup.derive = Some(Arc::new(d));
                setup.channels = 1;
            }
        }
        self.setup = setup.clone();
        let _ = self.tx.send(Msg::Reopen(setup));
        for vs in &mut self.views {
            vs.sent = None;
            vs.last = None;
        }
        Ok(())
    }

    /// The store's channel and pipeline of the derived channel shown.
    pub(super) fn derived_args(&self) -> Option<(String, usize)> {
        self.derived.as_ref().map(|(p, c, _)| (p.clone(), *c))
    }

    pub(super) fn processing_panel(&mut self, ui: &mut egui::Ui) {
        ui.label("Processing (a live derived channel, e.g. gauss(1.5)|sobel):");
        ui.horizontal(|ui| {
            ui.add(
                egui::TextEdit::singleline(&mut self.derive_text)
                    .hint_text("gauss(1.5)|sobel")
                    .desired_width(150.0),
            );
            if ui.button("Show").clicked() {
                let t = self.derive_text.clone();
                if let Err(e) = self.set_derive(Some(&t)) {
                    self.message = format!("{e:#}");
                }
            }
            if self.derived.is_some() && ui.button("Stored data").clicked() {
                let _ = self.set_derive(None);
            }
        });
        if let Some((p, c, _)) = &self.derived {
            ui.label(format!("showing {p} of channel {c}"));
        }
    }
}
