//! Signals: SIGHUP (the terminal closed) stops work like SIGINT and
//! SIGTERM (cleaned up, nothing half-written left), except under `nohup`
//! (SIGHUP ignored when started), where the work goes on.

use std::io::Read;
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// Generous: a slow, shared 2-core machine.
const DEADLINE: Duration = Duration::from_secs(300);

/// `generate mandelbulb` of a `size`³ store `out`, one worker thread (a
/// few seconds of work at least, most of it after the partial store is
/// made).
fn generate(out: &Path, size: u32) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_brickyard"));
    c.args(["generate", "mandelbulb"])
        .arg(out)
        .args(["--size", &size.to_string(), "--threads", "1", "--quiet"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    c
}

/// The names in `dir`.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Wait for `child` to exit, killing it past the deadline; its status and
/// stderr.
fn finish(mut child: Child) -> (ExitStatus, String) {
    let t0 = Instant::now();
    let st = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if t0.elapsed() > DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            panic!("still running {DEADLINE:?} after the signal");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    (st, err)
}

/// Start `cmd` and send it `sig` as soon as `partial` exists.
fn signal_once_started(mut cmd: Command, partial: &Path, sig: i32) -> Child {
    let mut child = cmd.spawn().unwrap();
    let t0 = Instant::now();
    while !partial.exists() {
        if let Some(st) = child.try_wait().unwrap() {
            let mut err = String::new();
            let _ = child.stderr.take().unwrap().read_to_string(&mut err);
            panic!("ended ({st}) before {} appeared: {err}", partial.display());
        }
        if t0.elapsed() > DEADLINE {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{} did not appear in {DEADLINE:?}", partial.display());
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    // SAFETY: plain kill(2) on our own child (not yet reaped).
    assert_eq!(unsafe { libc::kill(child.id() as i32, sig) }, 0);
    child
}

#[test]
fn sighup_stops_work_and_leaves_nothing() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("hup.ome.zarr");
    let partial = d.path().join("hup.ome.zarr.partial");
    // 640³ on one thread: a minute or so of work if the signal is missed.
    let mut cmd = generate(&out, 640);
    // As started from a terminal: SIGHUP at its default (a test run under
    // `nohup` hands its children SIGHUP ignored, which they keep).
    // SAFETY: signal(2) is async-signal-safe.
    unsafe {
        cmd.pre_exec(|| {
            libc::signal(libc::SIGHUP, libc::SIG_DFL);
            Ok(())
        });
    }
    let child = signal_once_started(cmd, &partial, libc::SIGHUP);
    let (st, err) = finish(child);
    assert!(!st.success(), "a hung-up run must fail: {st} {err}");
    assert_eq!(
        st.code(),
        Some(1),
        "stopped and cleaned up, not killed by the signal ({st}): {err}"
    );
    assert!(err.contains("interrupted"), "{err}");
    assert!(!out.exists(), "no output store after SIGHUP");
    let left = names(d.path());
    assert!(
        left.is_empty(),
        "SIGHUP left behind (a .partial or .lock): {left:?}"
    );
}

#[test]
fn sighup_ignored_under_nohup() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("nohup.ome.zarr");
    let partial = d.path().join("nohup.ome.zarr.partial");
    let mut cmd = generate(&out, 256);
    // SAFETY: signal(2) is async-signal-safe; this is what `nohup` does.
    unsafe {
        cmd.pre_exec(|| {
            libc::signal(libc::SIGHUP, libc::SIG_IGN);
            Ok(())
        });
    }
    let child = signal_once_started(cmd, &partial, libc::SIGHUP);
    let (st, err) = finish(child);
    assert!(st.success(), "under nohup SIGHUP is ignored: {st} {err}");
    assert_eq!(names(d.path()), ["nohup.ome.zarr"]);
}

#[test]
fn sigint_stops_a_slow_filter_within_its_region() {
    // median(3) of 256³ computes for about half a minute on two cores,
    // mostly within one region the writer asked for: the stages stop
    // between their blocks, not at the region's end.
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.ome.zarr");
    let o = generate(&store, 256).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let before = names(&store);
    let mut child = Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(["process"])
        .arg(&store)
        .args(["median(3)", "--out", "med", "--quiet"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(2500));
    assert!(
        child.try_wait().unwrap().is_none(),
        "ended before the signal: the test would prove nothing"
    );
    let t0 = Instant::now();
    // SAFETY: plain kill(2) on our own child (not yet reaped).
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
    let (st, err) = finish(child);
    let late = t0.elapsed();
    assert_eq!(st.code(), Some(1), "{st}: {err}");
    assert!(err.contains("interrupted"), "{err}");
    // (Before: 5.2 s here, 28 s for a 64 × 512² volume; now about 0.5 s.)
    assert!(
        late < Duration::from_secs(3),
        "stopped {late:?} after SIGINT"
    );
    assert_eq!(names(&store), before, "the store is as it was");
}

#[test]
fn sigint_during_a_label_conversion_leaves_the_image_as_it_was() {
    // Labels written into an image that has no `labels` group yet: the
    // group is made for them, and an interrupted conversion takes it back
    // (it left an empty `labels` folder behind).
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("bulb.raw");
    let o = generate(&raw, 256).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let img = d.path().join("img.ome.zarr");
    let o = Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .arg("convert")
        .args([&raw, &img])
        .arg("--quiet")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let before = names(&img);
    let labels = img.join("labels/L");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_brickyard"));
    cmd.arg("convert")
        .args([&raw, &labels])
        .args(["--labels", "--threads", "1", "--compression", "zstd:19"])
        .args(["--quiet"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let child = signal_once_started(cmd, &img.join("labels/L.partial"), libc::SIGINT);
    let (st, err) = finish(child);
    assert_eq!(st.code(), Some(1), "{st}: {err}");
    assert!(err.contains("interrupted"), "{err}");
    assert_eq!(names(&img), before, "the image changed: {err}");
}
