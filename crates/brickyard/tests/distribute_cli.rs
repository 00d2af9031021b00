//! The render flags of shared renders, on one process (no MPI needed):
//! `--distribute` is checked and, alone, draws what a plain render draws;
//! `--raw-f32` writes the image's floats; `--no-early-termination` changes
//! a DVR (every sample composited) and not a MIP.

use std::path::Path;
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(args)
        .output()
        .unwrap()
}

#[track_caller]
fn ok(o: &Output) {
    assert!(
        o.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn floats(png: &Path) -> Vec<f32> {
    std::fs::read(png.with_extension("f32"))
        .unwrap()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn distribute_flags_on_one_process() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("g.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "64",
        "--brick",
        "32",
        "--shard",
        "64",
        "--quiet",
    ]));
    let render = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut a = vec![
            "render",
            s(&store),
            "--size",
            "96x80",
            "--backend",
            "cpu",
            "--quiet",
            "--raw-f32",
            "--out",
            s(&out),
        ];
        a.extend(extra);
        ok(&run(&a));
        out
    };
    let plain = render("plain.png", &[]);
    let f = floats(&plain);
    assert_eq!(f.len(), 96 * 80 * 4);
    assert!(f.chunks_exact(4).filter(|p| p[3] > 0.05).count() > 200);
    for split in ["image", "data"] {
        let one = render(&format!("{split}.png"), &["--distribute", split]);
        assert_eq!(max_diff(&f, &floats(&one)), 0.0, "{split} on one process");
    }
    let all = render("all.png", &["--no-early-termination"]);
    let d = max_diff(&f, &floats(&all));
    assert!(d > 1e-4, "without early termination the DVR differs ({d})");
    let mip = render("mip.png", &["--mode", "mip"]);
    let mip_all = render("mip-all.png", &["--mode", "mip", "--no-early-termination"]);
    assert_eq!(max_diff(&floats(&mip), &floats(&mip_all)), 0.0);
    let o = run(&[
        "render",
        s(&store),
        "--distribute",
        "pixels",
        "--out",
        s(&dir.path().join("x.png")),
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("distribute: expected image or data, found \"pixels\""),
        "{err}"
    );
    let o = run(&[
        "render",
        s(&store),
        "--region-weights",
        "bricks",
        "--out",
        s(&dir.path().join("x.png")),
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("region-weights: expected view, data or uniform, found \"bricks\""),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}

/// An MPI build run without mpirun: `--distribute` has no ranks to share
/// with, and says so (a build without MPI refuses the flag).
#[cfg(feature = "mpi")]
#[test]
fn distribute_alone_says_it_shares_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("g.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "32",
        "--brick",
        "16",
        "--shard",
        "32",
        "--quiet",
    ]));
    let o = run(&[
        "render",
        s(&store),
        "--distribute",
        "data",
        "--size",
        "32x32",
        "--quiet",
        "--out",
        s(&dir.path().join("x.png")),
    ]);
    ok(&o);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("note: --distribute data shares a render among the processes mpirun starts"),
        "{err}"
    );
}

/// `--region-weights` balances the regions of `--distribute data` only:
/// given with another split, or without one, it is refused, saying what
/// was given and what it needs; `--columns 0` (no column for the ranks
/// to share) is refused by `convert` and `generate`.
#[test]
fn flags_without_their_split_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("g.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "32",
        "--brick",
        "16",
        "--shard",
        "32",
        "--quiet",
    ]));
    let out = dir.path().join("x.png");
    let render = |extra: &[&str]| {
        let mut a = vec![
            "render",
            s(&store),
            "--size",
            "32x32",
            "--backend",
            "cpu",
            "--quiet",
            "--out",
            s(&out),
        ];
        a.extend(extra);
        run(&a)
    };
    for (extra, said) in [
        (
            &["--region-weights", "data"][..],
            "found --region-weights data without --distribute",
        ),
        (
            &["--region-weights=view"][..],
            "found --region-weights view without --distribute",
        ),
        (
            &["--region-weights", "uniform", "--distribute", "image"][..],
            "found --region-weights uniform with --distribute image",
        ),
    ] {
        let o = render(extra);
        assert_eq!(o.status.code(), Some(1), "{extra:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("region-weights: only with --distribute data"),
            "{extra:?}: {err}"
        );
        assert!(err.contains(said), "{extra:?}: {err}");
        assert!(!out.exists(), "{extra:?}: an image was written");
    }
    // With the split it balances: drawn (alone, a note says it shares nothing).
    ok(&render(&[
        "--distribute",
        "data",
        "--region-weights",
        "uniform",
    ]));
    assert!(out.exists());

    let raw = dir.path().join("m.raw");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&raw),
        "--size",
        "16",
        "--quiet",
    ]));
    for args in [
        vec!["convert", s(&raw), "c.ome.zarr"],
        vec!["generate", "mandelbulb", "c.ome.zarr", "--size", "16"],
    ] {
        let mut a = args.clone();
        a.extend(["--columns", "0", "--quiet"]);
        let o = Command::new(env!("CARGO_BIN_EXE_brickyard"))
            .args(&a)
            .current_dir(dir.path())
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1), "{a:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("columns: expected at least 1 column") && err.contains("found 0"),
            "{a:?}: {err}"
        );
        assert!(!dir.path().join("c.ome.zarr").exists());
        assert!(!dir.path().join("c.ome.zarr.partial").exists());
    }
}

/// Standard error that is not a terminal (a log, a pipe under mpirun)
/// gets plain progress lines (what, done of total, rate, time left), the
/// first after the interval of `BRICKYARD_PROGRESS_SECONDS` (10 s unless
/// set) and a last one when the work is done; `--quiet` and `--json`
/// write none, and work shorter than the interval writes none.
#[test]
fn progress_lines_in_a_log() {
    let dir = tempfile::tempdir().unwrap();
    let convert = |name: &str, extra: &[&str], every: Option<&str>| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_brickyard"));
        c.args(["generate", "mandelbulb"])
            .arg(dir.path().join(name))
            .args(["--size", "48", "--brick", "16", "--shard", "16"])
            .args(extra)
            .env_remove("BRICKYARD_PROGRESS_SECONDS");
        if let Some(e) = every {
            c.env("BRICKYARD_PROGRESS_SECONDS", e);
        }
        let o = c.output().unwrap();
        ok(&o);
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let err = convert("a.ome.zarr", &[], Some("0"));
    let lines: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("converting: "))
        .collect();
    assert!(lines.len() >= 2, "{err}");
    assert!(
        lines[0].contains(" of 108.00 KiB (") && lines[0].contains("/s, ETA "),
        "{err}"
    );
    assert!(
        lines
            .last()
            .unwrap()
            .starts_with("converting: done, 108.00 KiB in "),
        "{err}"
    );
    // No terminal's bar drawing in a log.
    assert!(!err.contains('\r') && !err.contains('\u{1b}'), "{err:?}");
    for (name, extra) in [("q.ome.zarr", "--quiet"), ("j.ome.zarr", "--json")] {
        let err = convert(name, &[extra], Some("0"));
        assert!(!err.contains("converting"), "{extra}: {err}");
    }
    // Shorter than the default interval: nothing.
    let err = convert("d.ome.zarr", &[], None);
    assert!(!err.contains("converting"), "{err}");
}
