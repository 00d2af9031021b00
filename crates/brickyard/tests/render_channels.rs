//! `render`'s channel options and the flags that another makes moot, as
//! a user meets them: a window given with one DVR channel is its
//! transfer function's window, `--tf` with several channels is said to
//! be unused (it was ignored silently), a store with more active channels than a mode draws
//! still renders, a slice plane that misses the volume is refused (it
//! drew a blank image called complete).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(args)
        .output()
        .unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn err(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[track_caller]
fn ok(o: &Output) {
    assert!(o.status.success(), "{}", err(o));
}

#[track_caller]
fn fails_with(o: &Output, words: &[&str]) {
    let e = err(o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    for w in words {
        assert!(e.contains(w), "{w:?} not in: {e}");
    }
}

/// A `channels`-channel u8 store of 20³ voxels (channel c's voxel at
/// (x, y, z): a ramp that differs per channel).
fn store(dir: &Path, name: &str, channels: usize) -> PathBuf {
    let n = 20usize;
    let raw = dir.join(format!("{name}.raw"));
    let mut v = Vec::with_capacity(channels * n * n * n);
    for c in 0..channels {
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    v.push(((x * 7 + y * 3 + z * 5 + c * 11) % 200) as u8);
                }
            }
        }
    }
    std::fs::write(&raw, v).unwrap();
    let out = dir.join(format!("{name}.ome.zarr"));
    let channels = channels.to_string();
    ok(&run(&[
        "convert",
        "--quiet",
        "--dims",
        "20x20x20",
        "--dtype",
        "u8",
        "--channels",
        &channels,
        "--brick",
        "8",
        "--shard",
        "16",
        s(&raw),
        s(&out),
    ]));
    out
}

fn render(store: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut a = vec![
        "render",
        s(store),
        "--backend",
        "cpu",
        "--size",
        "48",
        "--quiet",
        "--out",
        s(out),
    ];
    a.extend_from_slice(extra);
    run(&a)
}

#[test]
fn one_dvr_channel_takes_the_window_given_with_it() {
    let d = tempfile::tempdir().unwrap();
    let st = store(d.path(), "three", 3);
    let p = |n: &str| d.path().join(n);
    // The window with the channel is the transfer function's window: the
    // same image as --window gives (it was the default window's).
    ok(&render(&st, &p("a.png"), &["--channel", "1:red:0,100"]));
    ok(&render(
        &st,
        &p("b.png"),
        &["--channel", "1", "--window", "0,100"],
    ));
    ok(&render(&st, &p("c.png"), &["--channel", "1"]));
    let (a, b, c) = (
        std::fs::read(p("a.png")).unwrap(),
        std::fs::read(p("b.png")).unwrap(),
        std::fs::read(p("c.png")).unwrap(),
    );
    assert_eq!(
        a, b,
        "--channel 1:red:0,100 is not --channel 1 --window 0,100"
    );
    assert_ne!(a, c, "the window given made no difference");
    // The colour, not used by one channel through --tf, is said.
    let o = render(&st, &p("d.png"), &["--channel", "1:red"]);
    ok(&o);
    let o2 = run(&[
        "render",
        s(&st),
        "--backend",
        "cpu",
        "--size",
        "16",
        "--out",
        s(&p("e.png")),
        "--channel",
        "1:red",
    ]);
    ok(&o2);
    assert!(
        err(&o2).contains("colour in --channel 1:red is not used"),
        "{}",
        err(&o2)
    );
    // Given twice: refused.
    fails_with(
        &render(
            &st,
            &p("f.png"),
            &["--channel", "1:red:0,100", "--window", "0,50"],
        ),
        &["channel", "--window", "once"],
    );
    assert!(!p("f.png").exists());
}

#[test]
fn tf_with_several_channels_is_said_unused_and_per_channel_flags_name_what_to_give() {
    let d = tempfile::tempdir().unwrap();
    let st = store(d.path(), "three", 3);
    let one = store(d.path(), "one", 1);
    let out = d.path().join("x.png");
    for mode in ["dvr", "mip", "slice"] {
        // Said, not silently dropped (not refused: the viewer's saved
        // views give --tf with several channels).
        let o = run(&[
            "render",
            s(&st),
            "--backend",
            "cpu",
            "--size",
            "16",
            "--mode",
            mode,
            "--tf",
            "hot",
            "--out",
            s(&out),
        ]);
        ok(&o);
        assert!(
            err(&o).contains("note: --tf is not used: 3 channels"),
            "{mode}: {}",
            err(&o)
        );
    }
    std::fs::remove_file(&out).unwrap();
    // One channel shown: --tf applies.
    ok(&render(&st, &out, &["--channel", "2", "--tf", "hot"]));
    std::fs::remove_file(&out).unwrap();
    fails_with(
        &render(&one, &out, &["--channel-tf", "0=hot"]),
        &["channel-tf", "one channel", "--tf"],
    );
    fails_with(
        &render(&one, &out, &["--channel-levels", "0=0-1"]),
        &["channel-levels", "one channel", "--level"],
    );
    assert!(!out.exists());
}

#[test]
fn a_store_with_more_active_channels_than_a_mode_draws_still_renders() {
    let d = tempfile::tempdir().unwrap();
    let st = store(d.path(), "many", 70);
    let out = d.path().join("m.png");
    for (mode, most) in [("dvr", "64"), ("mip", "16")] {
        let o = run(&[
            "render",
            s(&st),
            "--backend",
            "cpu",
            "--size",
            "16",
            "--mode",
            mode,
            "--out",
            s(&out),
        ]);
        ok(&o);
        let e = err(&o);
        assert!(
            e.contains("70 active channels") && e.contains(&format!("at most {most}")),
            "{e}"
        );
    }
}

#[test]
fn flags_that_another_makes_moot_and_planes_that_miss_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let st = store(d.path(), "one", 1);
    let out = d.path().join("x.png");
    fails_with(
        &render(&st, &out, &["--ortho", "--fov", "20"]),
        &["fov", "--ortho"],
    );
    fails_with(
        &render(&st, &out, &["--level", "0", "--lod-bias", "2"]),
        &["lod-bias", "--level 0"],
    );
    fails_with(
        &render(&st, &out, &["--gpu-update", "host"]),
        &["gpu-update", "--backend cpu"],
    );
    fails_with(
        &render(&st, &out, &["--loader-threads", "0"]),
        &["loader-threads"],
    );
    fails_with(
        &render(
            &st,
            &out,
            &["--mode", "slice", "--slice-origin", "0,0,1000000"],
        ),
        &["slice-origin", "misses the volume"],
    );
    fails_with(
        &render(
            &st,
            &out,
            &[
                "--mode",
                "slice",
                "--slice-origin",
                "-5,10,10",
                "--slice-normal",
                "1,0,0",
            ],
        ),
        &["slice-origin", "misses the volume"],
    );
    assert!(!out.exists());
    // A plane through a face still draws.
    ok(&render(
        &st,
        &out,
        &["--mode", "slice", "--slice-origin", "10,10,0"],
    ));
}
