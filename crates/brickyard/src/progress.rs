//! Progress bar with throughput and ETA.
//!
//! Both come from the average since the start, not from the last few
//! seconds: work whose cost varies along the volume (the Mandelbulb's
//! centre costs many times its empty shell) made indicatif's recent rate,
//! and the ETA from it, swing from 3 to 27 minutes and back within 90 s of
//! a 13-minute run.

use indicatif::{
    BinaryBytes, HumanDuration, ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle,
};

/// Items (or bytes) a second since the start.
fn average_rate(st: &ProgressState) -> Option<f64> {
    let secs = st.elapsed().as_secs_f64();
    (secs >= 0.5 && st.pos() > 0).then(|| st.pos() as f64 / secs)
}

/// The time left at the average rate since the start.
fn average_eta(st: &ProgressState, w: &mut dyn std::fmt::Write) {
    match (average_rate(st), st.len()) {
        (Some(r), Some(len)) => {
            let left = len.saturating_sub(st.pos()) as f64 / r;
            let _ = write!(
                w,
                "{:#}",
                HumanDuration(std::time::Duration::from_secs_f64(left))
            );
        }
        _ => {
            let _ = write!(w, "…");
        }
    }
}

fn style(template: &str) -> ProgressStyle {
    ProgressStyle::with_template(template)
        .unwrap()
        .progress_chars("=> ")
        .with_key("avg_eta", average_eta)
        .with_key(
            "avg_bytes_per_sec",
            |st: &ProgressState, w: &mut dyn std::fmt::Write| {
                let _ = match average_rate(st) {
                    Some(r) => write!(w, "{}/s", BinaryBytes(r as u64)),
                    None => write!(w, "…"),
                };
            },
        )
        .with_key(
            "avg_per_sec",
            |st: &ProgressState, w: &mut dyn std::fmt::Write| {
                let _ = match average_rate(st) {
                    Some(r) => write!(w, "{r:.1}/s"),
                    None => write!(w, "…"),
                };
            },
        )
}

pub struct Bar {
    bar: Option<ProgressBar>,
}

impl Bar {
    pub fn new(quiet: bool, what: &str) -> Bar {
        if quiet {
            return Bar { bar: None };
        }
        // Hidden until its phase starts: a job without that phase (a
        // labelling bar for a pipeline that labels nothing) shows none.
        let bar = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::hidden());
        bar.set_style(style(
            "{msg} [{bar:40}] {binary_bytes}/{binary_total_bytes} {avg_bytes_per_sec} ETA {avg_eta}",
        ));
        bar.set_message(what.to_string());
        Bar { bar: Some(bar) }
    }

    /// A bar that counts items (chunks) rather than bytes.
    pub fn counting(quiet: bool, what: &str) -> Bar {
        if quiet {
            return Bar { bar: None };
        }
        // Hidden until its phase starts: a job without that phase (a
        // labelling bar for a pipeline that labels nothing) shows none.
        let bar = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::hidden());
        bar.set_style(style(
            "{msg} [{bar:40}] {pos}/{len} {avg_per_sec} ETA {avg_eta}",
        ));
        bar.set_message(what.to_string());
        Bar { bar: Some(bar) }
    }

    pub fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish_and_clear();
        }
    }
}

impl brickyard_store::Progress for Bar {
    fn start(&self, total: u64) {
        if let Some(b) = &self.bar {
            // The rate and ETA count from here (not from when the bar was
            // made, before the phases ahead of it).
            b.reset();
            b.set_length(total);
            if b.is_hidden() && total > 0 {
                b.set_draw_target(ProgressDrawTarget::stderr());
            }
        }
    }
    fn inc(&self, n: u64) {
        if let Some(b) = &self.bar {
            b.inc(n);
        }
    }
}
