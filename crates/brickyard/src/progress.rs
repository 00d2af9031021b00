//! Progress of long work on standard error: a bar with throughput and ETA
//! on a terminal, plain lines in a log.
//!
//! Both come from the average since the start, not from the last few
//! seconds: work whose cost varies along the volume (the Mandelbulb's
//! centre costs many times its empty shell) made indicatif's recent rate,
//! and the ETA from it, swing from 3 to 27 minutes and back within 90 s of
//! a 13-minute run.
//!
//! When standard error is not a terminal (a pipe under `mpirun`, a batch
//! system's log, `2>log`), indicatif draws nothing; a line
//! (`converting: 1.2 GiB of 4.0 GiB (30%), 85.1 MiB/s, ETA 33s`) is
//! written instead, the first after [`LINE_EVERY`] of work and then at
//! most once every [`LINE_EVERY`] (`BRICKYARD_PROGRESS_SECONDS` sets
//! another interval), and a last one when the work is done, if any was
//! written. Short work writes none. Under an MPI launcher only rank 0
//! writes them (the ranks' shares would interleave).

use indicatif::{
    BinaryBytes, HumanDuration, ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle,
};
use std::io::IsTerminal;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// How often a progress line is written where standard error is not a
/// terminal.
pub const LINE_EVERY: Duration = Duration::from_secs(10);

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
            let _ = write!(w, "{:#}", HumanDuration(Duration::from_secs_f64(left)));
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

/// The rank an MPI launcher gave this process (Open MPI, MPICH's PMI,
/// PMIx); `None` when not under one.
fn launcher_rank() -> Option<u64> {
    ["OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK"]
        .iter()
        .find_map(|v| std::env::var(v).ok()?.trim().parse().ok())
}

/// The interval of progress lines: `BRICKYARD_PROGRESS_SECONDS`, else
/// [`LINE_EVERY`].
fn line_every() -> Duration {
    std::env::var("BRICKYARD_PROGRESS_SECONDS")
        .ok()
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|s| s.is_finite() && *s >= 0.0)
        .map_or(LINE_EVERY, Duration::from_secs_f64)
}

/// Progress said in lines, for a standard error that is not a terminal.
struct Lines {
    what: String,
    bytes: bool,
    every: Duration,
    total: AtomicU64,
    pos: AtomicU64,
    /// When the phase started and when a line was last written.
    times: Mutex<Option<(Instant, Instant)>>,
    written: AtomicBool,
}

impl Lines {
    fn amount(&self, n: u64) -> String {
        match self.bytes {
            true => BinaryBytes(n).to_string(),
            false => n.to_string(),
        }
    }

    /// `what: done of total (percent), rate, ETA left`.
    fn line(&self, pos: u64, total: u64, secs: f64) -> String {
        let mut s = format!(
            "{}: {} of {}",
            self.what,
            self.amount(pos),
            self.amount(total)
        );
        if total > 0 {
            s += &format!(" ({:.0}%)", 100.0 * pos as f64 / total as f64);
        }
        let rate = (secs > 0.0 && pos > 0).then(|| pos as f64 / secs);
        match rate {
            Some(r) if self.bytes => s += &format!(", {}/s", BinaryBytes(r as u64)),
            Some(r) => s += &format!(", {r:.1}/s"),
            None => {}
        }
        match rate {
            Some(r) if total >= pos => {
                let left = (total - pos) as f64 / r;
                s += &format!(", ETA {:#}", HumanDuration(Duration::from_secs_f64(left)));
            }
            _ => s += ", ETA unknown",
        }
        s
    }

    fn start(&self, total: u64) {
        self.total.store(total, Ordering::Relaxed);
        self.pos.store(0, Ordering::Relaxed);
        let now = Instant::now();
        *self.times.lock().unwrap_or_else(|e| e.into_inner()) = Some((now, now));
    }

    fn inc(&self, n: u64) {
        let pos = self.pos.fetch_add(n, Ordering::Relaxed) + n;
        // Another thread writing a line: this one need not.
        let Ok(mut t) = self.times.try_lock() else {
            return;
        };
        let Some((t0, last)) = t.as_mut() else {
            return;
        };
        let now = Instant::now();
        if now.duration_since(*last) < self.every {
            return;
        }
        *last = now;
        let secs = now.duration_since(*t0).as_secs_f64();
        let line = self.line(pos, self.total.load(Ordering::Relaxed), secs);
        drop(t);
        eprintln!("{line}");
        self.written.store(true, Ordering::Relaxed);
    }

    /// A last line when lines were written and the work is done.
    fn finish(&self) {
        let t = self.times.lock().unwrap_or_else(|e| e.into_inner()).take();
        let (pos, total) = (
            self.pos.load(Ordering::Relaxed),
            self.total.load(Ordering::Relaxed),
        );
        if let Some((t0, _)) = t {
            if self.written.load(Ordering::Relaxed) && pos >= total {
                let secs = t0.elapsed().as_secs_f64();
                eprintln!(
                    "{}: done, {} in {:#}",
                    self.what,
                    self.amount(pos),
                    HumanDuration(Duration::from_secs_f64(secs))
                );
            }
        }
    }
}

enum Shown {
    /// `--quiet`, `--json`, or a rank other than 0.
    Nothing,
    Bar(ProgressBar),
    Lines(Lines),
}

pub struct Bar {
    shown: Shown,
}

impl Bar {
    /// A bar that counts bytes.
    pub fn new(quiet: bool, what: &str) -> Bar {
        Bar::make(quiet, what, true)
    }

    /// A bar that counts items (chunks) rather than bytes.
    pub fn counting(quiet: bool, what: &str) -> Bar {
        Bar::make(quiet, what, false)
    }

    fn make(quiet: bool, what: &str, bytes: bool) -> Bar {
        let shown = if quiet || launcher_rank().is_some_and(|r| r > 0) {
            Shown::Nothing
        } else if !std::io::stderr().is_terminal() {
            Shown::Lines(Lines {
                what: what.to_string(),
                bytes,
                every: line_every(),
                total: AtomicU64::new(0),
                pos: AtomicU64::new(0),
                times: Mutex::new(None),
                written: AtomicBool::new(false),
            })
        } else {
            // Hidden until its phase starts: a job without that phase (a
            // labelling bar for a pipeline that labels nothing) shows none.
            let bar = ProgressBar::with_draw_target(Some(0), ProgressDrawTarget::hidden());
            bar.set_style(style(match bytes {
                true => "{msg} [{bar:40}] {binary_bytes}/{binary_total_bytes} {avg_bytes_per_sec} ETA {avg_eta}",
                false => "{msg} [{bar:40}] {pos}/{len} {avg_per_sec} ETA {avg_eta}",
            }));
            bar.set_message(what.to_string());
            Shown::Bar(bar)
        };
        Bar { shown }
    }

    pub fn finish(&self) {
        match &self.shown {
            Shown::Bar(b) => b.finish_and_clear(),
            Shown::Lines(l) => l.finish(),
            Shown::Nothing => {}
        }
    }
}

impl brickyard_store::Progress for Bar {
    fn start(&self, total: u64) {
        match &self.shown {
            Shown::Bar(b) => {
                // The rate and ETA count from here (not from when the bar
                // was made, before the phases ahead of it).
                b.reset();
                b.set_length(total);
                if b.is_hidden() && total > 0 {
                    b.set_draw_target(ProgressDrawTarget::stderr());
                }
            }
            Shown::Lines(l) => l.start(total),
            Shown::Nothing => {}
        }
    }
    fn inc(&self, n: u64) {
        match &self.shown {
            Shown::Bar(b) => b.inc(n),
            Shown::Lines(l) => l.inc(n),
            Shown::Nothing => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lines(bytes: bool) -> Lines {
        Lines {
            what: "converting".into(),
            bytes,
            every: LINE_EVERY,
            total: AtomicU64::new(0),
            pos: AtomicU64::new(0),
            times: Mutex::new(None),
            written: AtomicBool::new(false),
        }
    }

    #[test]
    fn a_progress_line_says_what_how_far_how_fast_and_how_long() {
        let l = lines(true);
        let s = l.line(1 << 30, 4 << 30, 8.0);
        assert_eq!(
            s,
            "converting: 1.00 GiB of 4.00 GiB (25%), 128.00 MiB/s, ETA 24s"
        );
        let c = lines(false);
        let s = c.line(250, 1000, 10.0);
        assert_eq!(s, "converting: 250 of 1000 (25%), 25.0/s, ETA 30s");
        assert_eq!(
            c.line(0, 1000, 0.0),
            "converting: 0 of 1000 (0%), ETA unknown"
        );
    }
}
