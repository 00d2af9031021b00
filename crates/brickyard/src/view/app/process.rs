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
    let window = crate::window::window_of_levels_in(stored.levels.len(), 0, d.read_limit(), |l| {
        d.open_level(l)
    })?
    .map(|(lo, hi)| [lo as f32, hi as f32])
    .filter(|w| w[1] > w[0])
    .unwrap_or([0.0, 1.0]);
    Ok(Dataset {
        channels: 1,
        dtype: d.dtype,
        range: window,
        histogram: vec![0.0; stored.histogram.len()],
        labels: false,
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
        let _ = self.tx.send(Msg::Reopen(Box::new(setup)));
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
        ui.horizontal(|ui| {
            ui.add(
                egui::TextEdit::singleline(&mut self.job_name)
                    .hint_text("name")
                    .desired_width(90.0),
            );
            let running = self.job.is_some();
            if ui
                .add_enabled(!running, egui::Button::new("Apply to whole volume"))
                .clicked()
            {
                let name = self.job_name.clone();
                if let Err(e) = self.apply(&name) {
                    self.message = format!("{e:#}");
                }
            }
            if running && ui.button("Stop").clicked() {
                if let Some(mut j) = self.job.take() {
                    j.stop();
                    self.message = format!("{} stopped; the store is as it was", j.pipeline);
                }
            }
        });
        if let Some(j) = &self.job {
            ui.label(format!(
                "writing {} as {} ({:.0} s)…",
                j.pipeline,
                j.name,
                j.seconds()
            ));
        }
    }

    /// Write the pipeline shown (or typed) into the store as NAME, at every
    /// level, in the background.
    pub(super) fn apply(&mut self, name: &str) -> Result<()> {
        if self.job.is_some() {
            anyhow::bail!("apply: a job is running; wait for it or stop it");
        }
        let (pipeline, channel) = match &self.derived {
            Some((p, c, _)) => (p.clone(), *c),
            None if !self.derive_text.trim().is_empty() => {
                (self.derive_text.clone(), self.dvr_channel)
            }
            None => anyhow::bail!("apply: type a pipeline first"),
        };
        if name.trim().is_empty() {
            anyhow::bail!("apply: give the result a name");
        }
        let memory = job_memory(self.setup.memory_budget);
        self.job = Some(Job::start(
            &self.stored.store,
            &pipeline,
            name,
            channel,
            memory,
        )?);
        self.message = format!("writing {pipeline} as {name} in the background");
        Ok(())
    }

    /// Take the job's end, if it ended.
    pub(super) fn poll_job(&mut self) -> Option<JobEnd> {
        let end = self.job.as_mut()?.poll()?;
        self.job = None;
        self.message = match &end {
            JobEnd::Done(m) | JobEnd::Failed(m) => m.clone(),
        };
        eprintln!("view: {}", self.message);
        self.last_job = Some(end.clone());
        Some(end)
    }
}

/// A job's refusal for its memory ("give --memory NMiB or more") in the
/// viewer's terms: the job's budget is a quarter of the viewer's (see
/// [`job_memory`]), which is what a user can change.
fn for_the_viewer(err: &str) -> Option<String> {
    let rest = err.split("give --memory ").nth(1)?;
    let mib: u64 = rest.split("MiB").next()?.trim().parse().ok()?;
    Some(format!(
        "; a job started from the viewer gets a quarter of the viewer's --memory \
         (at least 256 MiB): start the viewer with --memory {}MiB or more",
        mib.saturating_mul(4)
    ))
}

/// The memory budget of a job started from the viewer: a quarter of the
/// viewer's, at least 256 MiB.
pub fn job_memory(viewer_budget: u64) -> u64 {
    (viewer_budget / 4).max(256 << 20)
}

/// A whole-volume processing job started from the viewer: `brickyard
/// process` in a child process at a lower CPU priority (nice 10) and with
/// its own memory budget, so that it never takes the view's cores first
/// or its memory. It publishes its result only when complete, as the
/// command does; closing the viewer stops it and leaves the store as it
/// was.
pub struct Job {
    child: std::process::Child,
    pub name: String,
    pub pipeline: String,
    started: std::time::Instant,
    stderr_path: std::path::PathBuf,
}

/// How a job ended.
#[derive(Debug, Clone, PartialEq)]
pub enum JobEnd {
    Done(String),
    Failed(String),
}

impl Job {
    /// Start `brickyard process STORE PIPELINE --out NAME` over `channel`.
    pub fn start(
        store: &std::path::Path,
        pipeline: &str,
        name: &str,
        channel: usize,
        memory: u64,
    ) -> Result<Job> {
        let exe = std::env::current_exe()?;
        let stderr_path = std::env::temp_dir().join(format!(
            "brickyard-view-job-{}-{name}.log",
            std::process::id()
        ));
        let err = std::fs::File::create(&stderr_path)?;
        let child = std::process::Command::new(exe)
            .args(["process", &store.to_string_lossy(), pipeline, "--out", name])
            .args(["--channel", &channel.to_string()])
            .args(["--memory", &format!("{}MiB", (memory >> 20).max(64))])
            .args(["--overwrite", "--quiet"])
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(err)
            .spawn()?;
        // Below the view: the scheduler serves the viewer's threads first.
        // SAFETY: setpriority on a child's pid has no memory effects.
        unsafe {
            libc::setpriority(libc::PRIO_PROCESS, child.id() as libc::id_t, 10);
        }
        Ok(Job {
            child,
            name: name.to_string(),
            pipeline: pipeline.to_string(),
            started: std::time::Instant::now(),
            stderr_path,
        })
    }

    /// `None` while it runs.
    pub fn poll(&mut self) -> Option<JobEnd> {
        let status = self.child.try_wait().ok()??;
        let err = std::fs::read_to_string(&self.stderr_path).unwrap_or_default();
        let _ = std::fs::remove_file(&self.stderr_path);
        let secs = self.started.elapsed().as_secs_f64();
        Some(if status.success() {
            JobEnd::Done(format!(
                "{} written to the store as {} in {secs:.1} s",
                self.pipeline, self.name
            ))
        } else {
            let last = err
                .lines()
                .rev()
                .find(|l| !l.trim().is_empty())
                .unwrap_or("");
            let advice = for_the_viewer(last).unwrap_or_default();
            JobEnd::Failed(format!(
                "{} failed ({status}): {last}{advice}",
                self.pipeline
            ))
        })
    }

    pub fn seconds(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// Stop the job: its result is not published.
    pub fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_file(&self.stderr_path);
    }
}

#[cfg(test)]
mod tests {
    use super::{for_the_viewer, job_memory};

    /// A job's memory refusal names the viewer's --memory that gives the
    /// job what it asked for; other errors get no advice.
    #[test]
    fn a_memory_refusal_names_the_viewers_memory() {
        let err = "error: --memory: 256.0 MiB is too small for \"gauss(40)\" on level 0 of \
                   /data/x.ome.zarr: give --memory 292MiB or more (the filters hold …)";
        let advice = for_the_viewer(err).unwrap();
        assert!(advice.contains("--memory 1168MiB"), "{advice}");
        // That viewer budget gives the job the memory it asked for.
        assert!(job_memory(1168 << 20) >= 292 << 20);
        assert_eq!(for_the_viewer("error: no such channel 3"), None);
        assert_eq!(for_the_viewer("give --memory lots"), None);
    }
}
