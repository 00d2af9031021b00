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
