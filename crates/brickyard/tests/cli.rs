//! The command line as a user meets it: bad inputs give clear errors and a
//! non-zero exit, memory stays under the budget for volumes larger than it,
//! unfinished stores are reported as such.

use std::path::Path;
use std::process::{Command, Output};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[track_caller]
fn fails_with(o: &Output, needles: &[&str]) {
    assert!(
        !o.status.success(),
        "expected failure, got success: {}",
        String::from_utf8_lossy(&o.stdout)
    );
    let e = stderr(o);
    assert!(!e.contains("panicked"), "panic: {e}");
    for n in needles {
        assert!(e.contains(n), "error {e:?} should mention {n:?}");
    }
}

#[test]
fn bad_inputs_give_clear_errors() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("o.ome.zarr");
    // Missing path.
    fails_with(
        &run(&["convert", s(&d.path().join("nope.tif")), s(&out)]),
        &["nope.tif"],
    );
    // A missing store, whatever reads it: named, in words.
    let gone = d.path().join("gone.ome.zarr");
    let png = d.path().join("x.png");
    for args in [
        vec!["info", s(&gone)],
        vec!["render", s(&gone), "--out", s(&png)],
        vec!["process", s(&gone), "gauss(1)", "--out", "g"],
    ] {
        let o = run(&args);
        fails_with(&o, &["gone.ome.zarr", "no such file or directory"]);
        assert!(!stderr(&o).contains("entity not found"), "{}", stderr(&o));
    }
    // Benchmark options outside their ranges: refused before any work.
    for (args, want) in [
        (["bench", "views", "--views", "17"], "2 to 16 views"),
        (["bench", "views", "--views", "1"], "2 to 16 views"),
        (["bench", "render", "--zoom", "0"], "zoom"),
        (["bench", "render", "--repeat", "0"], "repeat"),
    ] {
        fails_with(&run(&args), &[want]);
    }
    // Dims that do not match the file size.
    let raw = d.path().join("v.raw");
    std::fs::write(&raw, vec![0u8; 1000]).unwrap();
    fails_with(
        &run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "10x10x11",
            "--dtype",
            "u8",
        ]),
        &["v.raw", "dims", "1000"],
    );
    // Unsupported dtype.
    fails_with(
        &run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "10x10x10",
            "--dtype",
            "c64",
        ]),
        &["dtype", "c64"],
    );
    // Raw without description.
    fails_with(&run(&["convert", s(&raw), s(&out)]), &["v.raw", "--dims"]);
    // Corrupt gzip NIfTI.
    let nii = d.path().join("bad.nii.gz");
    std::fs::write(&nii, [0x1f, 0x8b, 8, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9]).unwrap();
    fails_with(&run(&["convert", s(&nii), s(&out)]), &["bad.nii.gz"]);
    // Truncated TIFF.
    let src =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/nuclei-confocal-u16.tif");
    let bytes = std::fs::read(&src).expect("shared/data/nuclei-confocal-u16.tif is missing");
    let tif = d.path().join("cut.tif");
    std::fs::write(&tif, &bytes[..bytes.len() / 2]).unwrap();
    fails_with(&run(&["convert", s(&tif), s(&out)]), &["cut.tif"]);
    assert!(!out.exists(), "no output after failures");
    // Existing output without --overwrite is refused and left alone.
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("precious"), b"keep").unwrap();
    std::fs::write(&raw, vec![7u8; 1000]).unwrap();
    fails_with(
        &run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "10x10x10",
            "--dtype",
            "u8",
        ]),
        &["--overwrite"],
    );
    assert_eq!(std::fs::read(out.join("precious")).unwrap(), b"keep");
    // Bad option values.
    fails_with(
        &run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "10x10x10",
            "--dtype",
            "u8",
            "--brick",
            "7",
        ]),
        &["brick"],
    );
    fails_with(
        &run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "10x10x10",
            "--dtype",
            "u8",
            "--memory",
            "lots",
        ]),
        &["memory"],
    );
    // A negative edge is a value out of range, not a flag.
    fails_with(
        &run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "10x10x10",
            "--dtype",
            "u8",
            "--brick",
            "-64",
        ]),
        &[
            "--brick",
            "expected a number of voxels from 2 to 1024, found \"-64\"",
        ],
    );
    // info on something that is not a store.
    fails_with(&run(&["info", s(&raw)]), &["v.raw"]);
}

#[test]
fn memory_stays_under_budget_for_a_larger_volume() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("big.raw");
    // 448 x 448 x 256 u16 = 98 MiB, converted under a 72 MiB budget.
    let g = run(&[
        "generate",
        "marschner-lobb",
        s(&raw),
        "--size",
        "448x448x256",
        "--dtype",
        "u16",
        "--quiet",
    ]);
    assert!(g.status.success(), "{}", stderr(&g));
    let out = d.path().join("big.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&out),
        "--memory",
        "72MiB",
        "--json",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let rss = r["peak_rss_bytes"].as_u64().unwrap();
    let input = r["bytes_in"].as_u64().unwrap();
    assert!(
        input > 72 << 20,
        "the volume must be larger than the budget"
    );
    assert!(
        rss > 0 && rss <= 72 << 20,
        "peak RSS {rss} over the 72 MiB budget; passes {}",
        r["passes"]
    );
    let i = run(&["info", s(&out)]);
    assert!(i.status.success());
    let text = String::from_utf8_lossy(&i.stdout);
    assert!(
        text.contains("complete (brickyard)") && text.contains("level 3"),
        "{text}"
    );
}

#[test]
fn info_reports_an_unfinished_store() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("x.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&out),
        "--size",
        "40",
        "--quiet",
        "--brick",
        "8",
        "--shard",
        "16",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(run(&["info", s(&out)]).status.success());
    // What a crash leaves: the partial folder, whose root says incomplete.
    let partial = d.path().join("x.ome.zarr.partial");
    std::fs::rename(&out, &partial).unwrap();
    let root = partial.join("zarr.json");
    let text = std::fs::read_to_string(&root)
        .unwrap()
        .replace("\"complete\": true", "\"complete\": false");
    std::fs::write(&root, text).unwrap();
    let i = run(&["info", s(&partial)]);
    assert_eq!(i.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&i.stdout).contains("INCOMPLETE"));
}

#[test]
fn sigint_leaves_no_store() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("int.ome.zarr");
    let mut child = bin()
        .args([
            "generate",
            "mandelbulb",
            s(&out),
            "--size",
            "512",
            "--quiet",
        ])
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    unsafe {
        libc_kill(child.id() as i32, 2);
    }
    let st = child.wait().unwrap();
    assert!(!st.success());
    assert!(
        !out.exists(),
        "an interrupted conversion must not leave the output"
    );
    assert!(
        !d.path().join("int.ome.zarr.partial").exists(),
        "nor a partial store"
    );
    // A raw file being generated: stopped as cleanly (it used to end by
    // the signal, leaving its partial file and lock behind).
    let raw = d.path().join("int.raw");
    let child = bin()
        .args(["generate", "mandelbulb", s(&raw), "--size", "1024"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    unsafe {
        libc_kill(child.id() as i32, 2);
    }
    let o = child.wait_with_output().unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("interrupted"), "{}", stderr(&o));
    let left: Vec<_> = std::fs::read_dir(d.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

extern "C" {
    #[link_name = "kill"]
    fn libc_kill(pid: i32, sig: i32) -> i32;
}

/// A 48³ Mandelbulb store (16³ bricks, 32³ shards) `name` in `dir`.
fn mandelbulb_48(dir: &Path, name: &str) -> std::path::PathBuf {
    let store = dir.join(name);
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "48",
        "--quiet",
        "--brick",
        "16",
        "--shard",
        "32",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    store
}

/// `info` on the `labels/` group `process` writes lists the label images
/// in it: no level of its own to fail on, no "infx" ratio of nothing.
#[test]
fn info_on_a_labels_group_lists_its_images() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "g.ome.zarr");
    let o = run(&[
        "process",
        s(&store),
        "threshold(100)",
        "--out",
        "mask",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = run(&["info", s(&store.join("labels"))]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("image inside: mask (3 levels)"), "{out}");
    for bad in ["infx", "problem", "shape"] {
        assert!(!out.contains(bad), "{bad}: {out}");
    }
    // --check has no array of the group's own to read: it says where to look.
    fails_with(
        &run(&["info", "--check", s(&store.join("labels"))]),
        &["group", "check the images in it"],
    );
    // A volume file where a store is read: what to do with it.
    let file = d.path().join("scan.nii.gz");
    std::fs::write(&file, b"not a store").unwrap();
    for cmd in ["info", "render"] {
        fails_with(
            &run(&[cmd, s(&file)]),
            &["not a Zarr store", "convert it first", "brickyard convert"],
        );
    }
}

/// `--labels` on float voxels is refused before anything is written: a
/// label image holds integers.
#[test]
fn labels_of_float_voxels_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("f.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "16",
        "--dtype",
        "f32",
        "--labels",
        "--quiet",
    ]);
    fails_with(&o, &["labels", "integers", "f32"]);
    assert!(!store.exists());
}

#[test]
fn render_writes_pngs_and_rejects_bad_options() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "r.ome.zarr");
    for mode in ["dvr", "mip", "slice"] {
        let png = d.path().join(format!("{mode}.png"));
        let cam = d.path().join(format!("{mode}.json"));
        let o = run(&[
            "render",
            s(&store),
            "--mode",
            mode,
            "--size",
            "48x40",
            "--out",
            s(&png),
            "--pool",
            "1MiB",
            "--brick",
            "8",
            "--save-camera",
            s(&cam),
        ]);
        assert!(o.status.success(), "{mode}: {}", stderr(&o));
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(out.contains("100.00% complete"), "{mode}: {out}");
        let bytes = std::fs::read(&png).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        has_content(&png_pixels(&png), mode);
        // The saved camera renders the same view again.
        let png2 = d.path().join(format!("{mode}-again.png"));
        let o = run(&[
            "render",
            s(&store),
            "--mode",
            mode,
            "--size",
            "48x40",
            "--out",
            s(&png2),
            "--camera",
            s(&cam),
            "--brick",
            "8",
        ]);
        assert!(o.status.success(), "{mode}: {}", stderr(&o));
        assert_eq!(
            std::fs::read(&png2).unwrap(),
            bytes,
            "{mode}: same camera, same image"
        );
    }
    fails_with(
        &run(&["render", s(&store), "--mode", "xray"]),
        &["mode", "xray"],
    );
    fails_with(&run(&["render", s(&store), "--size", "0x10"]), &["size"]);
    fails_with(&run(&["render", s(&store), "--tf", "nonsense"]), &["tf"]);
    fails_with(
        &run(&["render", s(&d.path().join("missing.zarr"))]),
        &["missing.zarr"],
    );
    // A pool too small for the coarsest level names the flag that sets it.
    let png = d.path().join("small.png");
    fails_with(
        &run(&[
            "render",
            s(&store),
            "--out",
            s(&png),
            "--brick",
            "8",
            "--pool",
            "4KiB",
        ]),
        &["pool", "coarsest level", "--pool"],
    );
    // Numbers past any machine are refused, never wrapped around or
    // allocated (a pool of 2^64 − 1 bytes summed to a small budget; a
    // parallax of 1e30 indexed out of bounds; 100000 loader threads
    // aborted the process; a field of view of 1e-30° blamed the eye).
    let out = d.path().join("huge.png");
    let r = |extra: &[&str]| {
        run(&[
            &["render", s(&store), "--out", s(&out), "--size", "64x40"],
            extra,
        ]
        .concat())
    };
    // (A size at or past 2^64 bytes is refused when read; below it, as
    // more than the machine has.)
    fails_with(&r(&["--pool", "18446744073709551615"]), &["pool", "16 EiB"]);
    fails_with(&r(&["--pool", "99999999999999999999"]), &["pool", "16 EiB"]);
    fails_with(&r(&["--pool", "9000000000000000000"]), &["pool", "RAM"]);
    fails_with(
        &r(&["--memory", "1.9"]),
        &["memory", "whole number of bytes"],
    );
    // (2 views shift a slice by half the parallax, 4 views by three times
    // it; at most 4096 pixels.)
    for p in ["1e30", "-1e30", "1e9", "8193"] {
        fails_with(
            &r(&[
                "--mode",
                "slice",
                "--views",
                "2",
                &format!("--parallax={p}"),
            ]),
            &["parallax", "at most 8192 pixels with 2 views"],
        );
    }
    fails_with(
        &r(&["--mode", "slice", "--views", "4", "--parallax=1366"]),
        &["parallax", "at most 1365.33 pixels with 4 views"],
    );
    let o = r(&["--mode", "slice", "--views", "2", "--parallax=-128"]);
    assert!(o.status.success(), "{}", stderr(&o));
    // 16 narrow views of DVR (whose parallax, 1 by default, says nothing).
    let o = r(&["--views", "16", "--size", "16"]);
    assert!(o.status.success(), "{}", stderr(&o));
    for t in ["0", "257", "100000"] {
        fails_with(
            &r(&["--loader-threads", t]),
            &["loader-threads", "1 to 256"],
        );
    }
    fails_with(&r(&["--fov", "1e-30"]), &["fov", "too narrow"]);
    // A view's saved arguments (which hold its --size) and then a larger
    // size: the last one given.
    let o = r(&["--size", "80x40"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&out).unwrap()));
    let info = dec.read_info().unwrap();
    assert_eq!((info.info().width, info.info().height), (80, 40));
}

/// The viewer refuses an upload budget below one brick before it opens a
/// window (with it, no brick ever reached the pool and the views waited
/// for ever), and a pool too small for the coarsest level, as `render`
/// does.
#[test]
fn view_rejects_budgets_that_cannot_work_before_its_window() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "u.ome.zarr");
    // Without a display: had the flag passed, the error would be the
    // window's. (The pool's used to be said in the opened window.)
    for (flag, value, needles) in [
        (
            "--upload",
            "0",
            &["upload", "less than one padded brick"][..],
        ),
        ("--pool", "1KiB", &["pool", "coarsest level", "at least"]),
    ] {
        let out = bin()
            .args(["view", s(&store), flag, value, "--backend", "cpu"])
            .env_remove("DISPLAY")
            .env_remove("WAYLAND_DISPLAY")
            .output()
            .unwrap();
        fails_with(&out, needles);
    }
}

/// Negative numbers are values, as the help's "negative = finer" says, not
/// flags: `--lod-bias -1` used to stop at "unexpected argument '-1'".
#[test]
fn render_takes_negative_numbers_as_values() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "n.ome.zarr");
    let png = d.path().join("n.png");
    for (extra, says) in [
        (vec!["--lod-bias", "-1"], "LOD bias -1.0"),
        (
            vec!["--mode", "slice", "--views", "2", "--parallax", "-2"],
            "complete",
        ),
    ] {
        let _ = std::fs::remove_file(&png);
        let mut args = vec!["render", s(&store), "--size", "16", "--out", s(&png)];
        args.extend(extra.iter().copied());
        let out = run(&args);
        assert!(out.status.success(), "{extra:?}: {}", stderr(&out));
        let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), stderr(&out));
        assert!(said.contains(says), "{extra:?}: {said}");
        assert!(png.exists(), "{extra:?}: no image");
    }
}

/// Flags a user may get wrong name themselves and stop before any work:
/// non-finite LOD biases, an upload budget below one brick, an empty
/// window, an image in a folder that does not exist.
#[test]
fn render_rejects_flags_that_cannot_work() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "f.ome.zarr");
    let png = d.path().join("f.png");
    let base = ["render", s(&store), "--size", "16", "--out", s(&png)];
    for (extra, needles) in [
        (vec!["--lod-bias", "inf"], vec!["lod-bias", "inf"]),
        (vec!["--lod-bias", "NaN"], vec!["lod-bias", "NaN"]),
        (
            vec!["--upload", "0"],
            vec!["upload", "less than one padded brick"],
        ),
        (vec!["--window", "5,5"], vec!["window", "LO < HI"]),
        // No request a frame: nothing could ever load (it used to end
        // "complete" at 0 %).
        (vec!["--requests", "0"], vec!["requests", "at least 1"]),
        (vec!["--max-frames", "0"], vec!["max-frames", "at least 1"]),
        (vec!["--pool", "0"], vec!["pool", "above 0"]),
        (vec!["--azimuth", "inf"], vec!["azimuth", "finite"]),
        (vec!["--elevation", "NaN"], vec!["elevation", "finite"]),
        (vec!["--fov", "0"], vec!["fov", "between 0 and 180"]),
        // A pool too small for one brick: the least that works, not 0 MiB.
        (
            vec!["--pool", "1KiB"],
            vec!["pool", "holds 0 bricks", "at least 0."],
        ),
        (vec!["--turntable", "0"], vec!["turntable", "1 to 3600"]),
        (
            vec!["--turntable", "100000"],
            vec!["turntable", "1 to 3600"],
        ),
        // (A negative count got the parser's "not in 0..=4294967295".)
        (
            vec!["--turntable", "-2"],
            vec!["turntable", "1 to 3600", "found -2"],
        ),
        // A negative number is the flag's value (not taken for a flag).
        (vec!["--fov", "-10"], vec!["fov", "found -10"]),
        // A channel's window as --window's: not reversed, not NaN.
        (vec!["--channel", "0:red:5,1"], vec!["channel", "LO < HI"]),
        (vec!["--channel", "0:red:NaN,1"], vec!["channel", "finite"]),
        // A slice outside the volume would draw nothing.
        (
            vec!["--mode", "slice", "--slice-z", "1.5"],
            vec!["slice-z", "from 0 to 1", "1.5"],
        ),
        (
            vec!["--mode", "slice", "--slice-z", "NaN"],
            vec!["slice-z", "from 0 to 1"],
        ),
        // A negative value is the flag's value (it was read as a flag "-0").
        (
            vec!["--mode", "slice", "--slice-z", "-0.1"],
            vec!["slice-z", "from 0 to 1", "-0.1"],
        ),
        // Checked before the memory split is printed, naming the flag.
        (
            vec!["--samples-per-voxel", "0"],
            vec!["samples-per-voxel", "above 0"],
        ),
        (
            vec!["--samples-per-voxel", "NaN"],
            vec!["samples-per-voxel", "above 0"],
        ),
        (
            vec!["--samples-per-voxel", "1e9"],
            vec!["samples-per-voxel", "at most 64"],
        ),
        // (A huge delay used to hang the render.)
        (
            vec!["--read-delay-ms", "999999999999"],
            vec!["read-delay-ms", "at most 60000"],
        ),
        // Flags of one mode given to another would change nothing: they
        // used to be taken silently.
        (
            vec!["--mode", "mip", "--slice-z", "0.3"],
            vec!["slice-z", "--mode slice only", "--mode mip"],
        ),
        (
            vec!["--slice-origin", "1,2,3"],
            vec!["slice-origin", "--mode slice only", "--mode dvr"],
        ),
        (
            vec!["--mode", "dvr", "--slice-normal", "0,1,0"],
            vec!["slice-normal", "--mode slice only"],
        ),
        (
            vec!["--mode", "slice", "--azimuth", "40"],
            vec!["azimuth", "dvr and mip only", "--slice-normal"],
        ),
        (
            vec!["--mode", "slice", "--ortho"],
            vec!["ortho", "dvr and mip only"],
        ),
        (
            vec!["--mode", "slice", "--fov", "20"],
            vec!["fov", "dvr and mip only"],
        ),
        (
            vec!["--mode", "slice", "--samples-per-voxel", "2"],
            vec!["samples-per-voxel", "dvr and mip only"],
        ),
        (
            vec!["--mode", "slice", "--no-early-termination"],
            vec!["no-early-termination", "dvr only"],
        ),
        (
            vec!["--mode", "slice", "--views", "4", "--eye-separation", "2"],
            vec!["eye-separation:", "slices take --views N"],
        ),
        (
            vec!["--multiplex", "tiles"],
            vec!["multiplex", "only with --views N"],
        ),
        (
            vec!["--mode", "slice", "--parallax", "2"],
            vec!["parallax", "only with --views N (a super-slice)"],
        ),
        (
            vec!["--mode", "slice", "--turntable", "4"],
            vec!["turntable", "dvr and mip only", "face on"],
        ),
        (
            vec!["--traversal", "octree", "--no-early-termination"],
            vec![
                "no-early-termination",
                "octree traversal ends rays",
                "page-table",
            ],
        ),
        (
            vec!["--debug", "steps", "--progressive", "4"],
            vec!["debug", "a debug image counts the work of one frame's rays"],
        ),
        (
            vec![
                "--mode",
                "slice",
                "--slice-z",
                "0.3",
                "--slice-origin",
                "1,1,1",
            ],
            vec!["slice-z", "not --slice-z and --slice-origin"],
        ),
        // The camera of --camera has its angles and projection.
        (
            vec!["--camera", "view.camera.json", "--elevation", "10"],
            vec!["elevation", "--camera view.camera.json"],
        ),
        (
            vec!["--mode", "sideways"],
            vec!["mode", "dvr, mip or slice", "sideways"],
        ),
    ] {
        let args: Vec<&str> = base.iter().copied().chain(extra).collect();
        let o = run(&args);
        fails_with(&o, &needles);
        assert!(!stderr(&o).contains("at least 0.0 MiB"), "{}", stderr(&o));
        // (No back end was asked for: none is blamed.)
        assert!(!stderr(&o).contains("--backend"), "{}", stderr(&o));
        assert!(!png.exists(), "{args:?} wrote an image");
    }
    // The camera's file is not the image's (it was overwritten by it).
    for (cam, extra, flag) in [
        (png.clone(), None, "--out"),
        (png.with_extension("f32"), Some("--raw-f32"), "--raw-f32"),
    ] {
        let mut args = vec!["render", s(&store), "--size", "16", "--out", s(&png)];
        args.extend(extra);
        args.extend(["--save-camera", s(&cam)]);
        fails_with(
            &run(&args),
            &["save-camera", &format!("is the image's own file ({flag})")],
        );
        assert!(!cam.exists());
    }
    let jpg = d.path().join("x.jpg");
    fails_with(
        &run(&["render", s(&store), "--size", "16", "--out", s(&jpg)]),
        &["x.jpg", "PNG", ".png"],
    );
    assert!(!jpg.exists());
    fails_with(
        &run(&["--threads", "100000", "info", s(&store)]),
        &["threads", "1024"],
    );
    let deep = d.path().join("no/such/folder/x.png");
    fails_with(
        &run(&["render", s(&store), "--size", "16", "--out", s(&deep)]),
        &["no/such/folder", "not an existing folder"],
    );
    // An output that is a folder fails before the render, not after it.
    let folder = d.path().join("folder.png");
    std::fs::create_dir(&folder).unwrap();
    let o = run(&["render", s(&store), "--size", "16", "--out", s(&folder)]);
    fails_with(&o, &["folder.png", "is a folder"]);
    assert!(
        !String::from_utf8_lossy(&o.stdout).contains("frame"),
        "rendered first"
    );
}

/// Without the `mpi` feature, several processes under an MPI launcher
/// would each run the whole command alone (two renders into one file):
/// refused, as is `--distribute`, saying how to build one that shares.
#[cfg(not(feature = "mpi"))]
#[test]
fn a_build_without_mpi_refuses_to_run_as_several_ranks() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "m.ome.zarr");
    let png = d.path().join("m.png");
    let args = ["render", s(&store), "--size", "16", "--out", s(&png)];
    for var in ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE"] {
        let o = bin().args(args).env(var, "2").output().unwrap();
        fails_with(&o, &["one of 2 MPI processes", "without MPI", "--features"]);
        assert!(!png.exists());
    }
    // One process under the launcher is the command alone.
    let o = bin()
        .args(args)
        .env("OMPI_COMM_WORLD_SIZE", "1")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let mut a = args.to_vec();
    a.extend(["--distribute", "data"]);
    fails_with(&run(&a), &["--distribute", "without MPI"]);
    // A wrong value is said as such, built with MPI or not.
    let mut a = args.to_vec();
    a.extend(["--distribute", "foo"]);
    fails_with(
        &run(&a),
        &["distribute: expected image or data, found \"foo\""],
    );
}

/// `--max-frames N` bounds the frames a view draws, its request passes
/// (a quarter of the pixels, from 128² up) included, and the report counts
/// the frames drawn: `--max-frames 1` draws the image alone, once.
#[test]
fn max_frames_bounds_the_frames_drawn_and_reported() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "m.ome.zarr");
    let png = d.path().join("m.png");
    let render = |extra: &[&str]| {
        let mut a = vec![
            "render",
            s(&store),
            "--size",
            "128",
            "--backend",
            "cpu",
            "--out",
            s(&png),
        ];
        a.extend_from_slice(extra);
        let o = run(&a);
        // (3: a view stopped before it was complete.)
        assert!(
            matches!(o.status.code(), Some(0 | 3)),
            "{extra:?}: {}",
            stderr(&o)
        );
        (
            String::from_utf8_lossy(&o.stdout).into_owned(),
            o.status.code(),
        )
    };
    // (frame lines with their pass, the summary's frame count and how
    // the view ended; the exit status agrees)
    let frames = |extra: &[&str]| {
        let mut a = vec!["--json"];
        a.extend_from_slice(extra);
        let (out, code) = render(&a);
        let mut passes = Vec::new();
        let mut summary = None;
        // (JSON lines only: `wrote …` goes to standard error.)
        for l in out.lines() {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            if v["summary"] == true {
                summary = Some((v["frames"].as_u64().unwrap(), v["stop"].clone()));
            } else if v.get("frame").is_some() {
                passes.push(v["pass"].as_str().unwrap().to_string());
            }
        }
        let (n, stop) = summary.expect("a summary line");
        let want = if stop == "complete" { 0 } else { 3 };
        assert_eq!(code, Some(want), "{extra:?}: stop {stop}");
        (passes, n, stop)
    };
    // Unbounded, the view starts with request passes: the bound has
    // something to cut. How it ended is a JSON string (not Rust's
    // `Some(Complete)`).
    let (all, n, stop) = frames(&[]);
    assert_eq!(all.len() as u64, n, "{all:?}");
    assert!(all[0] == "requests" && all.len() >= 2, "{all:?}");
    assert_eq!(stop, "complete");
    let (_, _, stop) = frames(&["--max-frames", "1"]);
    assert_eq!(stop, "max_frames");
    for max in 1..=3usize {
        let m = max.to_string();
        let (drawn, n, _) = frames(&["--max-frames", &m]);
        assert_eq!(drawn.len() as u64, n, "--max-frames {max}: {drawn:?}");
        assert!(
            !drawn.is_empty() && drawn.len() <= max,
            "--max-frames {max}: {drawn:?}"
        );
        assert_eq!(
            drawn.last().map(String::as_str),
            Some("image"),
            "--max-frames {max}: the last frame is the image"
        );
    }
    let (out, code) = render(&["--max-frames", "1"]);
    assert!(out.contains("; 1 frames,"), "{out}");
    assert_eq!(code, Some(3), "{out}");
    has_content(&png_pixels(&png), "--max-frames 1");
    // A view stopped by --max-frames whose accumulation then loads the
    // rest ends complete (it ended with status 3), its image the one
    // drawn without the bound.
    let (out, code) = render(&["--progressive", "3"]);
    assert_eq!(code, Some(0), "{out}");
    let whole = std::fs::read(&png).unwrap();
    let (out, code) = render(&["--progressive", "3", "--max-frames", "1"]);
    assert!(out.contains("complete after all"), "{out}");
    assert_eq!(code, Some(0), "{out}");
    assert_eq!(std::fs::read(&png).unwrap(), whole);
    has_content(&png_pixels(&png), "--progressive 3 --max-frames 1");
}

/// Standard output closed early (`render … | head -1`): the run still
/// writes its image and exits 0, without a panic.
#[test]
fn a_closed_standard_output_does_not_stop_a_render() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "p.ome.zarr");
    let png = d.path().join("p.png");
    let mut child = bin()
        .args(["render", s(&store), "--size", "24", "--out", s(&png)])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The reading end closed before the first line is written.
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!stderr(&o).contains("panicked"), "{}", stderr(&o));
    has_content(&png_pixels(&png), "render with stdout closed");
}

/// A volume of one value has no data range: it renders with the unit
/// window (as the viewer does) instead of failing on an empty window.
#[test]
fn a_constant_volume_renders() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("c.raw");
    std::fs::write(&raw, vec![7u8; 20 * 20 * 20]).unwrap();
    let store = d.path().join("c.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "20x20x20",
        "--dtype",
        "u8",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    for mode in ["dvr", "slice"] {
        let png = d.path().join(format!("c-{mode}.png"));
        let o = run(&[
            "render",
            s(&store),
            "--mode",
            mode,
            "--size",
            "24",
            "--out",
            s(&png),
        ]);
        assert!(o.status.success(), "{mode}: {}", stderr(&o));
        // Value 7 above the unit window: the volume shows (a quarter of
        // the image or more is lit; the rest is background).
        let px = png_pixels(&png);
        let lit = px
            .chunks(4)
            .filter(|p| p[..3].iter().any(|&c| c > 0))
            .count();
        assert!(
            lit * 4 >= px.len() / 4,
            "{mode}: {lit} of {} pixels lit",
            px.len() / 4
        );
    }
}

/// Writers make their output, never the folders above it: an output
/// whose parent folder is missing (or is a file) is an error naming both,
/// before anything is created.
#[test]
fn writers_refuse_an_output_whose_folder_is_missing() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("v.raw");
    std::fs::write(&raw, vec![9u8; 16 * 16 * 16]).unwrap();
    let file = d.path().join("afile");
    std::fs::write(&file, "hi").unwrap();
    let deep = d.path().join("deep");
    let missing = deep.join("missing");
    for (out, why) in [
        (missing.join("x.ome.zarr"), "does not exist"),
        (file.join("x.ome.zarr"), "is not a folder"),
    ] {
        let parent = out.parent().unwrap();
        let o = run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "16x16x16",
            "--dtype",
            "u8",
            "--quiet",
        ]);
        fails_with(&o, &[s(&out), "parent folder", s(parent), why]);
    }
    for out in ["g.ome.zarr", "g.raw"] {
        let out = missing.join(out);
        fails_with(
            &run(&["generate", "mandelbulb", s(&out), "--size", "16", "--quiet"]),
            &[s(&out), "parent folder", s(&missing), "does not exist"],
        );
    }
    fails_with(
        &run(&["demo", "--out", s(&missing.join("demo")), "--size", "16"]),
        &["parent folder", s(&missing), "does not exist"],
    );
    assert!(!deep.exists(), "a failed writer created {}", deep.display());
    // A bare name is in the working directory, whose folder exists.
    let o = bin()
        .current_dir(d.path())
        .args([
            "convert",
            s(&raw),
            "here.ome.zarr",
            "--dims",
            "16x16x16",
            "--dtype",
            "u8",
            "--quiet",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let store = d.path().join("here.ome.zarr");
    assert!(store.join("zarr.json").is_file());
    // The render's camera file, like its image, before any work.
    let png = d.path().join("r.png");
    let cam = missing.join("cam.json");
    fails_with(
        &run(&[
            "render",
            s(&store),
            "--size",
            "16",
            "--out",
            s(&png),
            "--save-camera",
            s(&cam),
        ]),
        &["cam.json", "save-camera", "not an existing folder"],
    );
    assert!(!png.exists() && !deep.exists());
}

/// A 16³ u8 ramp (`v.raw` in `dir`; no sidecar: give `--dims 16x16x16
/// --dtype u8`).
fn ramp_raw(dir: &Path) -> std::path::PathBuf {
    let raw = dir.join("v.raw");
    let v: Vec<u8> = (0..16u32 * 16 * 16).map(|i| (i % 251) as u8).collect();
    std::fs::write(&raw, v).unwrap();
    raw
}

/// `convert --overwrite` replaces a store (or an empty folder), never a
/// file, a folder of other things, or what a store holds beside the
/// conversion's own arrays; bad units and zstd levels are named.
#[test]
fn overwrite_replaces_stores_only() {
    let d = tempfile::tempdir().unwrap();
    let raw = ramp_raw(d.path());
    let conv = |out: &Path, extra: &[&str]| {
        let mut a = vec![
            "convert",
            s(&raw),
            s(out),
            "--dims",
            "16x16x16",
            "--dtype",
            "u8",
        ];
        a.extend_from_slice(extra);
        a.push("--quiet");
        run(&a)
    };
    let folder = d.path().join("notes");
    std::fs::create_dir(&folder).unwrap();
    std::fs::write(folder.join("important.txt"), "keep me").unwrap();
    let file = d.path().join("afile");
    std::fs::write(&file, "hi").unwrap();
    for p in [&folder, &file] {
        fails_with(
            &conv(p, &["--overwrite"]),
            &["not a Zarr store", "--overwrite"],
        );
    }
    assert_eq!(
        std::fs::read_to_string(folder.join("important.txt")).unwrap(),
        "keep me"
    );
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "hi");
    assert!(!d.path().join("afile.old").exists());
    // An empty folder and an existing store are replaced.
    let empty = d.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let o = conv(&empty, &["--overwrite"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(empty.join("zarr.json").is_file());
    let o = conv(&empty, &["--overwrite"]);
    assert!(o.status.success(), "a store is replaced: {}", stderr(&o));
    // A store holding what a conversion does not make again (a label
    // image, a processing result, notes): refused, naming them (they were
    // deleted without a word), and left as it was.
    std::fs::create_dir_all(empty.join("labels/truth")).unwrap();
    std::fs::write(empty.join("labels/zarr.json"), "{}").unwrap();
    std::fs::write(empty.join("labels/truth/zarr.json"), "{}").unwrap();
    std::fs::write(empty.join("NOTES.txt"), "keep me").unwrap();
    fails_with(
        &conv(&empty, &["--overwrite"]),
        &["would delete", "NOTES.txt", "labels/truth"],
    );
    assert!(empty.join("labels/truth/zarr.json").is_file());
    assert_eq!(
        std::fs::read_to_string(empty.join("NOTES.txt")).unwrap(),
        "keep me"
    );
    std::fs::remove_dir_all(empty.join("labels")).unwrap();
    std::fs::remove_file(empty.join("NOTES.txt")).unwrap();
    // Never into the input itself, even where the output does not exist yet.
    let inner = empty.join("inner.zarr");
    fails_with(
        &run(&["convert", s(&empty), s(&inner), "--quiet"]),
        &["overlap"],
    );
    assert!(!inner.exists());
    fails_with(
        &conv(&d.path().join("u.zarr"), &["--unit", "bananas"]),
        &["unit", "bananas", "micrometer"],
    );
    fails_with(
        &conv(&d.path().join("z.zarr"), &["--compression", "zstd:99"]),
        &["compression", "zstd:99", "22"],
    );
    assert!(!d.path().join("u.zarr").exists() && !d.path().join("z.zarr").exists());
}

/// What a user can get wrong about where a store goes: `.` as the
/// output, spacings or origins that are no numbers at the coarse levels,
/// a second writer of the same output, a leftover `OUTPUT.old`, a
/// generated raw file's sidecar. Each is refused before any work, with the
/// path and field named, and nothing is left behind.
#[test]
fn outputs_and_geometry_a_store_cannot_have_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let raw = ramp_raw(d.path());
    let conv = |dir: &Path, out: &str, extra: &[&str]| {
        let mut a = vec![
            "convert",
            s(&raw),
            out,
            "--dims",
            "16x16x16",
            "--dtype",
            "u8",
        ];
        a.extend_from_slice(extra);
        a.push("--quiet");
        bin().current_dir(dir).args(&a).output().unwrap()
    };
    let listing = |dir: &Path| {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };
    // `.` and `..` name no new folder (this used to panic after the work).
    let empty = d.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    for out in [".", "..", "./"] {
        fails_with(&conv(&empty, out, &["--overwrite"]), &["names the output"]);
        let o = bin()
            .current_dir(&empty)
            .args([
                "generate",
                "mandelbulb",
                out,
                "--size",
                "8",
                "--overwrite",
                "--quiet",
            ])
            .output()
            .unwrap();
        fails_with(&o, &[]);
    }
    assert!(listing(&empty).is_empty(), "{:?}", listing(&empty));
    assert_eq!(listing(d.path()), ["empty", "v.raw"]);
    // Spacings whose coarse levels overflow (this used to plan levels
    // until memory ran out), origins that are no numbers.
    let out = d.path().join("g.zarr");
    fails_with(
        &conv(
            d.path(),
            s(&out),
            &["--spacing", "1e308,1e308,1e308", "--brick", "4"],
        ),
        &["spacing", "too large", "not a finite number"],
    );
    for o in ["nan,1,1", "1e400,1,1", "1,inf,1"] {
        fails_with(
            &conv(d.path(), s(&out), &["--origin", o]),
            &["origin", "finite"],
        );
    }
    // A negative spacing is the flag's value, refused by its rule (it was
    // taken for an unknown flag).
    fails_with(
        &conv(d.path(), s(&out), &["--spacing", "-1,1,1"]),
        &["spacing", "expected positive numbers", "-1"],
    );
    assert!(!out.exists());
    // A volume no viewer could place a camera around: refused (render
    // refused it only later, blaming a camera the user never gave).
    for sp in ["5e-324,5e-324,5e-324", "1e14,1,1"] {
        fails_with(
            &conv(d.path(), s(&out), &["--spacing", sp, "--brick", "4"]),
            &["spacing", "units across", "choose others"],
        );
    }
    assert!(!out.exists());
    let o = conv(
        d.path(),
        s(&out),
        &["--spacing", "1e-9,1e-9,2e-9", "--brick", "4"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    // A raw volume converted without --spacing says what it assumed; with
    // one, nothing is said.
    let said = |o: &Output| String::from_utf8_lossy(&o.stdout).contains("gives no voxel spacing");
    assert!(!said(&o), "{}", String::from_utf8_lossy(&o.stdout));
    let info = run(&["info", s(&out), "--json"]);
    assert!(info.status.success(), "{}", stderr(&info));
    // A second writer of the same output: the lock names the first one
    // (here the test itself, a live process), and nothing is touched.
    let lock = d.path().join("g.zarr.lock");
    std::fs::write(&lock, format!("{}\n", std::process::id())).unwrap();
    fails_with(
        &conv(d.path(), s(&out), &["--overwrite"]),
        &[
            "g.zarr.lock",
            &format!("pid {}", std::process::id()),
            "writing",
        ],
    );
    assert!(!d.path().join("g.zarr.partial").exists());
    // A lock whose process is gone is taken over, and removed at the end.
    std::fs::write(&lock, "4000000000\n").unwrap();
    let o = conv(d.path(), s(&out), &["--overwrite"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(said(&o), "{}", String::from_utf8_lossy(&o.stdout));
    assert!(
        stderr(&o).contains("process that is gone"),
        "{}",
        stderr(&o)
    );
    assert!(!lock.exists());
    // A leftover `.old` beside the store: refused up front, naming it.
    let old = d.path().join("g.zarr.old");
    std::fs::create_dir(&old).unwrap();
    std::fs::write(old.join("f"), "x").unwrap();
    fails_with(
        &conv(d.path(), s(&out), &["--overwrite"]),
        &["g.zarr.old", "in the way"],
    );
    // What a run killed while it removed the store it replaced left
    // (marked so) is removed by the next run; unmarked folders are not.
    std::fs::remove_dir_all(&old).unwrap();
    std::fs::create_dir_all(old.join("1/c")).unwrap();
    std::fs::write(old.join(".brickyard-replaced"), "").unwrap();
    let o = conv(d.path(), s(&out), &["--overwrite"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!old.exists() && out.join("zarr.json").is_file());
    // ... or instead of it: the store a stopped swap moved aside.
    std::fs::create_dir(&old).unwrap();
    std::fs::remove_dir_all(&old).unwrap();
    std::fs::rename(&out, &old).unwrap();
    fails_with(
        &conv(d.path(), s(&out), &[]),
        &["g.zarr.old", "rename it back"],
    );
    assert!(!out.exists() && old.join("zarr.json").is_file());
    // `generate` keeps an existing sidecar unless told to replace it.
    let side = d.path().join("m.raw.json");
    std::fs::write(&side, "mine").unwrap();
    let gen = |extra: &[&str]| {
        let m = d.path().join("m.raw");
        let mut a = vec!["generate", "mandelbulb", s(&m), "--size", "8", "--quiet"];
        a.extend_from_slice(extra);
        run(&a)
    };
    fails_with(&gen(&[]), &["m.raw.json", "--overwrite"]);
    assert_eq!(std::fs::read_to_string(&side).unwrap(), "mine");
    assert!(!d.path().join("m.raw").exists());
    let o = gen(&["--overwrite"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read_to_string(&side).unwrap().contains("\"dims\""));
}

/// Values that start with a minus sign are values, not flags: windows of
/// signed data, angles, slice planes, origins.
#[test]
fn negative_values_are_taken_as_values() {
    let d = tempfile::tempdir().unwrap();
    let raw = ramp_raw(d.path());
    let store = d.path().join("v.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "16x16x16",
        "--dtype",
        "u8",
        "--origin",
        "-1.5,-2,3",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let png = d.path().join("n.png");
    for extra in [
        &["--window", "-0.05,200"][..],
        &["--azimuth", "-30", "--elevation", "-10"],
        &[
            "--mode",
            "slice",
            "--slice-normal",
            "-1,0,0",
            "--slice-origin",
            "1,-8,8",
        ],
        &["--mode", "mip", "--channel", "0:red:-1,200"],
    ] {
        let mut a = vec![
            "render",
            s(&store),
            "--size",
            "16",
            "--backend",
            "cpu",
            "--out",
            s(&png),
        ];
        a.extend_from_slice(extra);
        let o = run(&a);
        assert!(o.status.success(), "{extra:?}: {}", stderr(&o));
    }
}

/// `BRICKYARD_READ_AHEAD` sets how far the loader hints ahead: the image
/// is the same with hints off, many or the default; a value that is not a
/// number of bricks from 0 to 4096 is an error naming the variable.
#[test]
fn read_ahead_comes_from_the_environment() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "ra.ome.zarr");
    let render = |value: Option<&str>, name: &str| {
        let png = d.path().join(name);
        let mut c = bin();
        c.args(["render", s(&store), "--size", "40x32", "--brick", "8"]);
        c.args(["--out", s(&png)]);
        match value {
            Some(v) => c.env("BRICKYARD_READ_AHEAD", v),
            None => c.env_remove("BRICKYARD_READ_AHEAD"),
        };
        (c.output().unwrap(), png)
    };
    let (o, png) = render(None, "default.png");
    assert!(o.status.success(), "{}", stderr(&o));
    let want = std::fs::read(&png).unwrap();
    has_content(&png_pixels(&png), "default read-ahead");
    for v in ["0", "4096", " 7 ", ""] {
        let (o, png) = render(Some(v), "other.png");
        assert!(o.status.success(), "{v:?}: {}", stderr(&o));
        assert_eq!(std::fs::read(&png).unwrap(), want, "read-ahead {v:?}");
    }
    for v in ["abc", "-1", "4097", "1.5"] {
        let (o, _) = render(Some(v), "bad.png");
        fails_with(&o, &["BRICKYARD_READ_AHEAD", "0 to 4096", v]);
    }
}

/// Decoded RGBA8 pixels of a PNG.
fn png_pixels(p: &Path) -> Vec<u8> {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    buf
}

/// Fails unless RGBA8 `pixels` (drawn over black) show something: at least
/// 5 % of the pixels lit and at least 16 distinct colours among them, so
/// that two blank (or flat) images cannot pass a comparison.
#[track_caller]
fn has_content(pixels: &[u8], what: &str) {
    let lit: Vec<&[u8]> = pixels
        .chunks(4)
        .filter(|c| c[0].max(c[1]).max(c[2]) > 8)
        .collect();
    let colours: std::collections::HashSet<&[u8]> = lit.iter().map(|c| &c[..3]).collect();
    let n = pixels.len() / 4;
    assert!(
        lit.len() * 20 >= n && colours.len() >= 16,
        "{what}: {} of {n} pixels lit, {} distinct colours: blank or flat",
        lit.len(),
        colours.len()
    );
}

#[test]
fn gpu_and_cpu_backends_draw_the_same_pngs() {
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "b.ome.zarr");
    for mode in ["dvr", "mip", "slice"] {
        let mut pixels = vec![];
        for backend in ["cpu", "gpu"] {
            let png = d.path().join(format!("{mode}-{backend}.png"));
            let o = run(&[
                "render",
                s(&store),
                "--mode",
                mode,
                "--size",
                "48x40",
                "--out",
                s(&png),
                "--pool",
                "1MiB",
                "--brick",
                "8",
                "--backend",
                backend,
            ]);
            assert!(o.status.success(), "{mode} {backend}: {}", stderr(&o));
            let out = String::from_utf8_lossy(&o.stdout);
            assert!(out.contains("100.00% complete"), "{mode} {backend}: {out}");
            assert!(
                out.contains(if backend == "gpu" { "GPU:" } else { "CPU (" }),
                "{out}"
            );
            let px = png_pixels(&png);
            has_content(&px, &format!("{mode} {backend}"));
            pixels.push(px);
        }
        assert_eq!(pixels[0].len(), pixels[1].len());
        let worst = pixels[0]
            .iter()
            .zip(&pixels[1])
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap();
        assert!(worst <= 1, "{mode}: 8-bit images differ by {worst}");
    }
    // Channels added up (here the volume twice, as two channels, with
    // different windows and colours) on both back ends.
    let two = d.path().join("two.ome.zarr");
    let o = run(&[
        "convert",
        s(&store),
        s(&store),
        s(&two),
        "--channel-names",
        "a,b",
        "--brick",
        "16",
        "--shard",
        "32",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut pixels = vec![];
    for backend in ["cpu", "gpu"] {
        let png = d.path().join(format!("channels-{backend}.png"));
        let o = run(&[
            "render",
            s(&two),
            "--mode",
            "mip",
            "--channel",
            "0:green:0,200",
            "--channel",
            "1:ff4000:60,255",
            "--size",
            "48x40",
            "--out",
            s(&png),
            "--pool",
            "1MiB",
            "--brick",
            "8",
            "--backend",
            backend,
        ]);
        assert!(o.status.success(), "channels {backend}: {}", stderr(&o));
        let px = png_pixels(&png);
        has_content(&px, &format!("channels {backend}"));
        pixels.push(px);
    }
    let worst = pixels[0]
        .iter()
        .zip(&pixels[1])
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap();
    assert!(worst <= 1, "channels: 8-bit images differ by {worst}");
    fails_with(
        &run(&["render", s(&store), "--backend", "quantum"]),
        &["backend", "quantum"],
    );
}

#[test]
fn a_pool_larger_than_the_device_can_hold_is_an_error_not_a_panic() {
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    let d = tempfile::tempdir().unwrap();
    // A pool never has more slots than the volume has bricks: the volume
    // must be large enough to want a pool of 12 GiB. 2048³ u8 (8 GiB
    // stored, 10.7 GiB of padded 32³ bricks at level 0), of metadata only:
    // every chunk is missing, so every brick is empty.
    let store = d.path().join("big.ome.zarr");
    let plan = brickyard_core::plan_levels([2048; 3], [1.0; 3], [0.0; 3], [256; 3]);
    let omz = brickyard_store::omezarr::multiscales_json(&plan.levels, 1, None, "big", false);
    brickyard_store::omezarr::write_json(
        &store.join("zarr.json"),
        &serde_json::json!({"zarr_format": 3, "node_type": "group",
            "attributes": {"ome": {"version": "0.5", "multiscales": omz}}}),
    )
    .unwrap();
    for (i, l) in plan.levels.iter().enumerate() {
        brickyard_store::omezarr::write_json(
            &store.join(i.to_string()).join("zarr.json"),
            &brickyard_store::omezarr::level_array_json(
                &l.dims,
                &[256; 3],
                &[64; 3],
                brickyard_core::DType::U8,
                brickyard_store::codec::Compression::Lz4,
                &["z", "y", "x"],
            ),
        )
        .unwrap();
    }
    let out = d.path().join("x.png");
    // Beyond the software device's largest allocation (or, on a machine
    // with less RAM, beyond the machine: refused before any device work).
    let o = run(&[
        "render",
        s(&store),
        "--backend",
        "gpu",
        "--pool",
        "12GiB",
        "--host",
        "64MiB",
        "--out",
        s(&out),
    ]);
    fails_with(&o, &["pool"]);
    assert!(!stderr(&o).contains("panicked"), "{}", stderr(&o));
    assert!(!out.exists());
}

/// `--progressive N` accumulates N frames after the view completes (CPU,
/// DVR) and writes an image of N times the sampling rate; it refuses other
/// modes and N = 0; `--stream` is the frame-per-batch loop; a shaded
/// transfer function draws a different image.
#[test]
fn render_progressive_accumulates_frames() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "p.ome.zarr");
    let common = ["--size", "48x40", "--backend", "cpu", "--level", "0"];
    let png = |name: &str| d.path().join(name);
    let plain = png("plain.png");
    let o = run(&[&["render", s(&store), "--out", s(&plain)], &common[..]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let acc = png("acc.png");
    let o = run(&[
        &["render", s(&store), "--out", s(&acc), "--progressive", "4"],
        &common[..],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("accumulate 4/4") && out.contains("accumulated 4 frames"),
        "{out}"
    );
    let px = png_pixels(&acc);
    has_content(&px, "progressive");
    assert_ne!(px, png_pixels(&plain), "4 frames drew the 1-frame image");
    // With --json: a JSON line per frame and one at the end (the text
    // lines were dropped), and the same image.
    let o = run(&[
        &[
            "render",
            s(&store),
            "--out",
            s(&acc),
            "--progressive",
            "4",
            "--json",
        ],
        &common[..],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}")))
        .collect();
    let frames: Vec<u64> = lines
        .iter()
        .filter_map(|v| v["accumulate"].as_u64())
        .collect();
    assert_eq!(frames.last(), Some(&4), "{lines:?}");
    assert!(
        lines
            .iter()
            .any(|v| v["accumulated"] == 4 && v["asked"] == 4),
        "{lines:?}"
    );
    assert_eq!(png_pixels(&acc), px);
    let streamed = png("stream.png");
    let o = run(&[
        &["render", s(&store), "--out", s(&streamed), "--stream"],
        &common[..],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(png_pixels(&streamed), png_pixels(&plain));
    let tf = d.path().join("shaded.json");
    std::fs::write(
        &tf,
        r#"{"preset": "soft", "window": [0, 255], "shading": true}"#,
    )
    .unwrap();
    let shaded = png("shaded.png");
    let o = run(&[
        &["render", s(&store), "--out", s(&shaded), "--tf", s(&tf)],
        &common[..],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let mut soft = common.to_vec();
    soft.extend(["--tf", "soft"]);
    let unshaded = png("unshaded.png");
    let o = run(&[&["render", s(&store), "--out", s(&unshaded)], &soft[..]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert_ne!(png_pixels(&shaded), png_pixels(&unshaded));
    fails_with(
        &run(&[
            "render",
            s(&store),
            "--mode",
            "mip",
            "--backend",
            "cpu",
            "--progressive",
            "4",
        ]),
        &["progressive", "dvr"],
    );
    fails_with(
        &run(&[
            "render",
            s(&store),
            "--backend",
            "cpu",
            "--progressive",
            "0",
        ]),
        &["progressive"],
    );
}

/// `--progressive`'s kept samples are held to their share of --memory:
/// asked for 64 frames of a 256² view (about 560 MiB of samples) within
/// 160 MiB, it draws the frames that fit, says so, and stays within the
/// budget (it took 689 MiB before); where the share cannot hold the first
/// frame even at the coarsest level, the view's one frame is the image.
#[test]
fn progressive_samples_stay_within_their_share_of_memory() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "96",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = d.path().join("p.png");
    let render = |memory: &str, size: &str| {
        run(&[
            "render",
            s(&store),
            "--out",
            s(&out),
            "--backend",
            "cpu",
            "--size",
            size,
            "--progressive",
            "64",
            "--memory",
            memory,
        ])
    };
    let o = render("160MiB", "256");
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout).to_string() + &stderr(&o);
    let drawn: u32 = text
        .split("accumulated ")
        .nth(1)
        .and_then(|t| t.split(" of the 64 frames").next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no lowered frame count: {text}"));
    assert!((2..64).contains(&drawn), "{drawn} frames: {text}");
    assert!(text.contains(&format!("accumulating {drawn} ")), "{text}");
    has_content(&png_pixels(&out), "progressive within a budget");
    // "peak memory 89.9 MiB of a 160.0 MiB budget"
    let peak = text
        .split("peak memory ")
        .nth(1)
        .and_then(|t| t.split(" of a").next())
        .unwrap_or_else(|| panic!("no peak: {text}"));
    let mib: f64 = match peak.split_once(' ') {
        Some((v, "MiB")) => v.parse().unwrap(),
        Some((v, "KiB")) => v.parse::<f64>().unwrap() / 1024.0,
        _ => panic!("peak {peak}"),
    };
    assert!(mib <= 160.0, "peak {peak} over the 160 MiB budget: {text}");
    // A million pixels' headers alone take more than a quarter of 400 MiB:
    // the view as drawn (one frame) is the image, and the run says so (it
    // drew the view, then failed and wrote nothing).
    let _ = std::fs::remove_file(&out);
    let o = render("400MiB", "1024");
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    for w in [
        "progressive",
        "first frame",
        "coarsest level",
        "--memory",
        "1 of the 64 frames",
    ] {
        assert!(err.contains(w), "{w:?} not in {err}");
    }
    has_content(
        &png_pixels(&out),
        "one frame where none could be accumulated",
    );
    // Room for one frame only, and that at a coarser level than the view
    // (192³, 256², level 0, 90 MiB): the view as drawn is the image, not
    // the coarser frame (it was written instead, blurrier, exit 0).
    let big = d.path().join("b.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&big),
        "--size",
        "192",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let at = |out: &Path, extra: &[&str]| {
        let mut a = vec![
            "render",
            s(&big),
            "--out",
            s(out),
            "--backend",
            "cpu",
            "--size",
            "256",
            "--level",
            "0",
            "--memory",
            "90MiB",
        ];
        a.extend_from_slice(extra);
        run(&a)
    };
    let view = d.path().join("view.png");
    let o = at(&out, &["--progressive", "32"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains("one frame's samples fit at level 1, coarser than the view drawn at level 0"),
        "{err}"
    );
    assert!(at(&view, &[]).status.success());
    assert_eq!(png_pixels(&out), png_pixels(&view));
}

/// A budget too small for the pyramid names one that is enough.
#[test]
fn the_memory_a_conversion_asks_for_is_enough() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.ome.zarr");
    let gen = |memory: &str| {
        run(&[
            "generate",
            "mandelbulb",
            s(&store),
            "--size",
            "256",
            "--dtype",
            "u16",
            "--memory",
            memory,
            "--quiet",
        ])
    };
    let o = gen("40MiB");
    fails_with(&o, &["memory", "need at least"]);
    let e = stderr(&o);
    let need = e.split("need at least ").nth(1).unwrap();
    let need: u64 = need.split(' ').next().unwrap().parse().unwrap();
    let o = gen(&format!("{need}MiB"));
    assert!(o.status.success(), "{need} MiB, as asked: {}", stderr(&o));
}

/// A copy of a multi-channel store (`convert STORE COPY`, to rechunk it)
/// keeps the channels' names.
#[test]
fn a_copy_of_a_store_keeps_its_channel_names() {
    let d = tempfile::tempdir().unwrap();
    let (a, b) = (d.path().join("a.raw"), d.path().join("b.raw"));
    std::fs::write(&a, vec![7u8; 8 * 8 * 8]).unwrap();
    std::fs::write(&b, vec![9u8; 8 * 8 * 8]).unwrap();
    let store = d.path().join("two.ome.zarr");
    let flags = ["--dims", "8x8x8", "--dtype", "u8", "--quiet"];
    let mut args = vec!["convert", s(&a), s(&b), s(&store)];
    args.extend(flags);
    args.extend(["--channel-names", "dapi,gfp"]);
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    let copy = d.path().join("copy.ome.zarr");
    let o = run(&["convert", s(&store), s(&copy), "--brick", "4", "--quiet"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let root: serde_json::Value =
        serde_json::from_slice(&std::fs::read(copy.join("zarr.json")).unwrap()).unwrap();
    let labels: Vec<&str> = root["attributes"]["ome"]["omero"]["channels"]
        .as_array()
        .expect("omero channels")
        .iter()
        .map(|c| c["label"].as_str().unwrap())
        .collect();
    assert_eq!(labels, ["dapi", "gfp"], "{root}");
}

/// Each channel is named once by `convert --channel-names` and shown once
/// by `render --channel` (with at most one --channel-tf and one
/// --channel-levels): a second one used to be taken silently (a channel
/// added up twice, a transfer function replaced).
#[test]
fn channels_and_their_names_are_given_once() {
    let d = tempfile::tempdir().unwrap();
    let (a, b) = (d.path().join("a.raw"), d.path().join("b.raw"));
    std::fs::write(
        &a,
        (0..16 * 16 * 16)
            .map(|i| (i % 200) as u8)
            .collect::<Vec<_>>(),
    )
    .unwrap();
    std::fs::write(&b, vec![9u8; 16 * 16 * 16]).unwrap();
    let store = d.path().join("two.ome.zarr");
    let convert = |names: &str| {
        run(&[
            "convert",
            s(&a),
            s(&b),
            s(&store),
            "--dims",
            "16x16x16",
            "--dtype",
            "u8",
            "--brick",
            "8",
            "--quiet",
            "--channel-names",
            names,
        ])
    };
    fails_with(
        &convert("gfp, gfp"),
        &["channel-names", "\"gfp\" given twice", "names 1 and 2"],
    );
    fails_with(&convert("gfp,"), &["channel-names", "name 2", "empty"]);
    assert!(!store.exists());
    let o = convert("dapi,gfp");
    assert!(o.status.success(), "{}", stderr(&o));
    let png = d.path().join("x.png");
    let tf = d.path().join("tf.json");
    std::fs::write(
        &tf,
        r#"{"window": [0, 200], "opacity": [[0, 0], [1, 0.5]]}"#,
    )
    .unwrap();
    let tf_arg = format!("1={}", s(&tf));
    for (extra, needles) in [
        (
            vec![
                "--mode",
                "mip",
                "--channel",
                "0:red",
                "--channel",
                "0:green",
            ],
            vec![
                "channel 0 given twice",
                "--channel 0:red",
                "--channel 0:green",
            ],
        ),
        (
            vec!["--channel", "1", "--channel", "0", "--channel", "1:blue"],
            vec!["channel 1 given twice"],
        ),
        (
            vec![
                "--channel",
                "0",
                "--channel",
                "1",
                "--channel-tf",
                &tf_arg,
                "--channel-tf",
                &tf_arg,
            ],
            vec!["channel-tf", "channel 1 given twice"],
        ),
        (
            vec![
                "--channel",
                "0",
                "--channel",
                "1",
                "--channel-levels",
                "0=0",
                "--channel-levels",
                "0=0-1",
            ],
            vec!["channel-levels", "channel 0 given twice", "0=0-1"],
        ),
    ] {
        let mut args = vec!["render", s(&store), "--size", "16", "--out", s(&png)];
        args.extend(extra);
        fails_with(&run(&args), &needles);
        assert!(!png.exists(), "{args:?} wrote an image");
    }
}

/// `--channel-tf C=PRESET` takes the presets of --tf (over the channel's
/// window): it used to take files only, and read a preset's name as one.
#[test]
fn channel_tf_takes_the_presets_of_tf() {
    let d = tempfile::tempdir().unwrap();
    let (a, b) = (d.path().join("a.raw"), d.path().join("b.raw"));
    let n = 24 * 24 * 24;
    std::fs::write(&a, (0..n).map(|i| (i % 200) as u8).collect::<Vec<_>>()).unwrap();
    std::fs::write(&b, (0..n).map(|i| (i * 7 % 251) as u8).collect::<Vec<_>>()).unwrap();
    let store = d.path().join("two.ome.zarr");
    let o = run(&[
        "convert",
        s(&a),
        s(&b),
        s(&store),
        "--dims",
        "24x24x24",
        "--dtype",
        "u8",
        "--brick",
        "8",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let render = |name: &str, extra: &[&str]| {
        let png = d.path().join(name);
        let mut args = vec![
            "render",
            s(&store),
            "--size",
            "32",
            "--backend",
            "cpu",
            "--quiet",
            "--channel",
            "0",
            "--channel",
            "1:white:0,200",
            "--out",
            s(&png),
        ];
        args.extend_from_slice(extra);
        let o = run(&args);
        (o, png)
    };
    // The preset, and the same transfer function as a file.
    let (o, hot) = render("hot.png", &["--channel-tf", "1=hot"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let tf = d.path().join("hot.json");
    std::fs::write(
        &tf,
        r#"{"window": [0, 200], "colormap": "hot", "opacity": [[0, 0], [0.1, 0], [1, 0.8]]}"#,
    )
    .unwrap();
    let (o, file) = render("file.png", &["--channel-tf", &format!("1={}", s(&tf))]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (o, plain) = render("plain.png", &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (hot, file, plain) = (png_pixels(&hot), png_pixels(&file), png_pixels(&plain));
    has_content(&hot, "--channel-tf 1=hot");
    assert_eq!(hot, file, "the preset differs from its JSON");
    assert_ne!(hot, plain, "--channel-tf 1=hot changed nothing");
    // Neither a preset nor a file: both named, and what is accepted.
    let (o, png) = render("bad.png", &["--channel-tf", "1=hott"]);
    fails_with(
        &o,
        &[
            "channel-tf",
            "\"hott\"",
            "linear, soft, hot, viridis, coolwarm, opaque",
            ".json",
        ],
    );
    assert!(!png.exists());
    let (o, _) = render("bad.png", &["--tf", "hott"]);
    fails_with(&o, &["tf", "\"hott\"", "linear, soft, hot"]);
}

/// The three MNI152 files of `../shared/data` (T1, grey and white
/// matter), or `None` (said on stderr) when the folder is absent.
fn mni_files() -> Option<[std::path::PathBuf; 3]> {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data");
    let f =
        ["mni152-t1-u8", "mni152-gm-u8", "mni152-wm-u8"].map(|n| data.join(format!("{n}.nii.gz")));
    if f.iter().all(|p| p.exists()) {
        Some(f)
    } else {
        eprintln!(
            "{}: the MNI152 files are missing; test skipped",
            data.display()
        );
        None
    }
}

#[test]
fn convert_takes_channels_from_several_files_and_render_shows_them() {
    let Some([t1, gm, wm]) = mni_files() else {
        return;
    };
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("mni.ome.zarr");
    let o = run(&["convert", s(&t1), s(&gm), s(&wm), s(&store)]);
    assert!(o.status.success(), "{}", stderr(&o));
    // The channels are named in the `omero` metadata, with colours and
    // windows over their data.
    let root: serde_json::Value =
        serde_json::from_slice(&std::fs::read(store.join("zarr.json")).unwrap()).unwrap();
    let chs = root["attributes"]["ome"]["omero"]["channels"]
        .as_array()
        .expect("omero channels")
        .clone();
    let labels: Vec<&str> = chs.iter().map(|c| c["label"].as_str().unwrap()).collect();
    assert_eq!(labels, ["mni152-t1-u8", "mni152-gm-u8", "mni152-wm-u8"]);
    let colours: std::collections::HashSet<&str> =
        chs.iter().map(|c| c["color"].as_str().unwrap()).collect();
    assert_eq!(colours.len(), 3, "{chs:?}");
    for c in &chs {
        let (a, b) = (
            c["window"]["start"].as_f64().unwrap(),
            c["window"]["end"].as_f64().unwrap(),
        );
        assert!(a >= 0.0 && b > a && b <= 255.0, "{c}");
    }
    // The axes have a channel axis of 3.
    let arr: serde_json::Value =
        serde_json::from_slice(&std::fs::read(store.join("0/zarr.json")).unwrap()).unwrap();
    assert_eq!(arr["shape"][0], 3);

    // render takes the three channels by default (DVR composites them).
    let render = |extra: &[&str], png: &Path| {
        let mut a = vec![
            "render",
            s(&store),
            "--size",
            "48x40",
            "--backend",
            "cpu",
            "--level",
            "1",
            "--out",
            s(png),
        ];
        a.extend_from_slice(extra);
        let o = run(&a);
        assert!(o.status.success(), "{extra:?}: {}", stderr(&o));
        png_pixels(png)
    };
    let all = render(&[], &d.path().join("all.png"));
    has_content(&all, "three channels");
    let t1_only = render(&["--channel", "0"], &d.path().join("t1.png"));
    has_content(&t1_only, "T1 alone");
    assert_ne!(all, t1_only, "the other channels add nothing");
    // A transfer function of its own for channel 2.
    let tf = d.path().join("wm.json");
    std::fs::write(
        &tf,
        r#"{"window": [100, 255], "opacity": [[0, 0], [1, 0.9]], "colormap": [[0, 1, 0.5, 0], [1, 1, 1, 0]]}"#,
    )
    .unwrap();
    let custom = render(
        &["--channel-tf", &format!("2={}", s(&tf))],
        &d.path().join("custom.png"),
    );
    has_content(&custom, "custom channel 2");
    assert_ne!(custom, all, "--channel-tf changed nothing");
    fails_with(
        &run(&[
            "render",
            s(&store),
            "--channel",
            "0",
            "--channel-tf",
            &format!("5={}", s(&tf)),
        ]),
        &["channel-tf", "5"],
    );

    fails_with(
        &run(&[
            "render",
            s(&store),
            "--backend",
            "cpu",
            "--progressive",
            "4",
        ]),
        &["progressive", "one channel"],
    );
    // Inputs of different grids are refused, naming the file and field.
    let nuclei = t1.with_file_name("nuclei-confocal-u16.tif");
    fails_with(
        &run(&[
            "convert",
            s(&t1),
            s(&nuclei),
            s(&d.path().join("bad.ome.zarr")),
        ]),
        &["nuclei-confocal-u16.tif", "dims"],
    );
    fails_with(
        &run(&[
            "convert",
            s(&t1),
            s(&gm),
            s(&d.path().join("bad.ome.zarr")),
            "--channel-names",
            "a,b,c",
        ]),
        &["channel names", "3 names", "2 channels"],
    );
}

/// A store's metadata edited (by hand, or by another tool) so that its
/// levels point out of it or come in the wrong order is refused with the
/// field named, before anything is read.
#[test]
fn levels_out_of_the_store_or_out_of_order_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "m.ome.zarr");
    let root = store.join("zarr.json");
    let text = std::fs::read_to_string(&root).unwrap();
    let png = d.path().join("x.png");
    let render = |st: &Path| render_cpu(st, &png, &["--size", "32"]);
    ok_status(&render(&store));
    for bad in ["../other.ome.zarr/0", "/etc", "", "0/../../x"] {
        std::fs::write(
            &root,
            text.replacen("\"path\": \"0\"", &format!("\"path\": {bad:?}"), 1),
        )
        .unwrap();
        for args in [
            vec!["info", s(&store)],
            vec!["render", s(&store), "--backend", "cpu", "--out", s(&png)],
            vec!["convert", s(&store), s(&d.path().join("c.ome.zarr"))],
        ] {
            fails_with(
                &run(&args),
                &[
                    "zarr.json",
                    "multiscales.datasets.path",
                    "inside the image's group",
                ],
            );
        }
    }
    // Levels 0 and 1 swapped: the coarser first.
    let swapped = text
        .replacen("\"path\": \"0\"", "\"path\": \"@\"", 1)
        .replacen("\"path\": \"1\"", "\"path\": \"0\"", 1)
        .replacen("\"path\": \"@\"", "\"path\": \"1\"", 1);
    assert_ne!(swapped, text);
    std::fs::write(&root, swapped).unwrap();
    fails_with(
        &render(&store),
        &[
            "multiscales.datasets",
            "level 1 is",
            "each no larger than the one before",
        ],
    );
    std::fs::write(&root, &text).unwrap();
    ok_status(&render(&store));
}

#[track_caller]
fn ok_status(o: &Output) {
    assert!(o.status.success(), "{}", stderr(o));
}

/// A store whose every level is damaged, the coarsest included: no part
/// of a view can be drawn from coarser data, and no image is written (a
/// blank image used to be written, "complete but for N bricks", exit 0).
/// Damage to the finer levels alone still draws from the coarser ones.
#[test]
fn a_view_with_no_data_at_any_level_writes_no_image() {
    let d = tempfile::tempdir().unwrap();
    let damage = |store: &Path, levels: &[&str]| {
        for l in levels {
            for e in walk(&store.join(l).join("c")) {
                std::fs::OpenOptions::new()
                    .write(true)
                    .open(&e)
                    .unwrap()
                    .set_len(10)
                    .unwrap();
            }
        }
    };
    let png = d.path().join("x.png");
    let render = |st: &Path| render_cpu(st, &png, &["--size", "48", "--level", "0"]);
    let all = mandelbulb_48(d.path(), "all.ome.zarr");
    damage(&all, &["0", "1", "2"]);
    fails_with(
        &render(&all),
        &["no data at any level", "no image written", "shard"],
    );
    assert!(!png.exists());
    let fine = mandelbulb_48(d.path(), "fine.ome.zarr");
    damage(&fine, &["0"]);
    let o = render(&fine);
    // Written, drawn from coarser data: status 3, said on stderr.
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(stderr(&o).contains("exit status 3"), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        png.exists() && out.contains("could not be loaded (drawn from coarser data)"),
        "{out}"
    );
    // Accumulated (--progressive): the bricks that fail stay stand-ins for
    // good, and the image is written as such (it failed: "the pool cannot
    // hold the view's bricks", no image).
    std::fs::remove_file(&png).unwrap();
    let o = render_cpu(
        &fine,
        &png,
        &["--size", "48", "--level", "0", "--progressive", "4"],
    );
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(png.exists());
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = vec![];
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// `render STORE --backend cpu --out PNG` with `extra` flags.
fn render_cpu(store: &Path, png: &Path, extra: &[&str]) -> Output {
    let mut a = vec!["render", s(store), "--backend", "cpu", "--out", s(png)];
    a.extend_from_slice(extra);
    run(&a)
}

/// A slice at a fraction of the depth shows the voxel layer holding it,
/// through the layer's centres: the default (0.5) of a volume two layers
/// deep is the upper layer, not their blend (the middle of an even depth
/// is a boundary, where a label image's nearest voxel was a tie that the
/// CPU and the device broke differently).
#[test]
fn a_slice_shows_one_layer_not_a_blend_of_two() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("two.raw");
    let mut v = vec![50u8; 16 * 16];
    v.extend(vec![200u8; 16 * 16]);
    std::fs::write(&raw, v).unwrap();
    let store = d.path().join("two.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "16x16x2",
        "--dtype",
        "u8",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    for (z, want) in [
        (None, 200u8),
        (Some("0.49"), 50),
        (Some("0"), 50),
        (Some("1"), 200),
    ] {
        let png = d.path().join("s.png");
        let mut a = vec![
            "render",
            s(&store),
            "--mode",
            "slice",
            "--size",
            "16",
            "--tf",
            "linear",
            "--window",
            "0,255",
            "--backend",
            "cpu",
            "--out",
            s(&png),
        ];
        if let Some(z) = z {
            a.extend(["--slice-z", z]);
        }
        let o = run(&a);
        assert!(o.status.success(), "{}", stderr(&o));
        let px = png_pixels(&png);
        // The middle pixel (grey: the linear map's colour at the value).
        let m = (8 * 16 + 8) * 4;
        assert!(
            px[m].abs_diff(want) <= 1,
            "--slice-z {z:?}: {} where the layer holds {want}",
            px[m]
        );
    }
}

/// Options may stand between `convert`'s paths (`convert IN --spacing
/// 1,1,4 OUT` was refused: "2 values required"); one path alone is named.
#[test]
fn options_may_stand_between_convert_paths() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("v.raw");
    std::fs::write(&raw, vec![9u8; 8 * 8 * 8]).unwrap();
    let out = d.path().join("v.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        "--dims",
        "8x8x8",
        "--dtype",
        "u8",
        "--spacing",
        "1,1,4",
        s(&out),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let meta = std::fs::read_to_string(out.join("zarr.json")).unwrap();
    assert!(meta.contains("4.0"), "{meta}");
    fails_with(
        &run(&["convert", s(&raw), "--dims", "8x8x8", "--dtype", "u8"]),
        &["INPUT... OUTPUT", "one path"],
    );
}

/// Flags that describe raw data, a Zarr input's level and NIfTI's rescale
/// are refused for inputs they do not apply to, naming the flag; flags laid
/// over a raw file's sidecar replace its fields and keep its geometry; a
/// store under an image's `labels/` needs `--labels`.
#[test]
fn flags_that_do_not_apply_to_an_input_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let raw = ramp_raw(d.path());
    let store = d.path().join("s.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "16x16x16",
        "--dtype",
        "u8",
        "--brick",
        "8",
        "--shard",
        "16",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // The store as input: raw flags, --raw-values refused; --level taken.
    for (flag, val) in [
        ("--endian", Some("big")),
        ("--channels", Some("2")),
        ("--header-bytes", Some("4")),
        ("--raw-values", None),
    ] {
        let out = d.path().join("o.ome.zarr");
        let mut args = vec!["convert", s(&store), s(&out), flag];
        args.extend(val);
        fails_with(&run(&args), &[s(&store), flag, "a Zarr store"]);
        assert!(!out.exists());
    }
    // One of --dims and --dtype alone: an input that is not raw is told the
    // flag is not for it; raw data is asked for both.
    let half = d.path().join("half.ome.zarr");
    fails_with(
        &run(&["convert", s(&store), s(&half), "--dims", "1x2x3"]),
        &["--dims describes raw data", "a Zarr store"],
    );
    fails_with(
        &run(&["convert", s(&raw), s(&half), "--dtype", "u8"]),
        &["needs both --dims and --dtype"],
    );
    // Not inside an array's folder, nor a store's own _brickyard folder.
    for (inside, why) in [
        ("0/x.ome.zarr", "is a Zarr array"),
        ("_brickyard/x", "statistics"),
    ] {
        let out = store.join(inside);
        fails_with(
            &run(&[
                "convert",
                s(&raw),
                s(&out),
                "--dims",
                "16x16x16",
                "--dtype",
                "u8",
            ]),
            &[why],
        );
        assert!(!out.exists());
    }
    let lvl = d.path().join("l1.ome.zarr");
    let o = run(&["convert", s(&store), s(&lvl), "--level", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    // A raw file's sidecar (big-endian u16, with geometry), a flag over it.
    let r16 = d.path().join("w.raw");
    let vals: Vec<u16> = (0..4 * 5 * 6).map(|i| i as u16 * 3 + 1).collect();
    let be: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
    std::fs::write(&r16, &be).unwrap();
    std::fs::write(
        d.path().join("w.raw.json"),
        r#"{"dims":[6,5,4],"dtype":"u16","endian":"big","spacing":[0.5,0.25,3],"origin":[1,2,3],"unit":"micrometer"}"#,
    )
    .unwrap();
    // The same bytes read little-endian: the flag wins, the geometry stays.
    let le = d.path().join("le.ome.zarr");
    let o = run(&["convert", s(&r16), s(&le), "--endian", "little"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("replace its endian"), "{}", stderr(&o));
    let j = std::fs::read_to_string(le.join("zarr.json")).unwrap();
    assert!(j.contains("micrometer") && j.contains("0.25"), "{j}");
    let first = u16::from_le_bytes([be[0], be[1]]);
    let got = brickyard_store::import::zarr::open(&le, 0).unwrap();
    let mut v = [0u8; 2];
    brickyard_store::VolumeSource::read_region(&got, 0, 0..1, 0..1, 0..1, &mut v).unwrap();
    assert_eq!(u16::from_ne_bytes(v), first, "read little-endian as asked");
    // Under an image's labels/: --labels or nothing.
    let lab = store.join("labels").join("seg");
    fails_with(
        &run(&[
            "convert",
            s(&raw),
            s(&lab),
            "--dims",
            "16x16x16",
            "--dtype",
            "u8",
        ]),
        &["give --labels", "labels"],
    );
    assert!(!lab.exists());
    // Labels without geometry on the grid of an image that has one take
    // the image's, so that one lies over the other.
    let sp = d.path().join("sp.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&sp),
        "--dims",
        "16x16x16",
        "--dtype",
        "u8",
        "--spacing",
        "0.5,0.25,2",
        "--unit",
        "micrometer",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let seg = sp.join("labels").join("seg");
    let o = run(&[
        "convert",
        s(&raw),
        s(&seg),
        "--dims",
        "16x16x16",
        "--dtype",
        "u8",
        "--labels",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("the image's (0.5,0.25,2 micrometer) taken"),
        "{}",
        stderr(&o)
    );
    let (a, b) = (
        brickyard_store::import::zarr::open(&sp, 0).unwrap(),
        brickyard_store::import::zarr::open(&seg, 0).unwrap(),
    );
    use brickyard_store::VolumeSource;
    assert_eq!(a.meta().spacing, Some([2.0, 0.25, 0.5]));
    assert_eq!(
        (a.meta().spacing, &a.meta().unit),
        (b.meta().spacing, &b.meta().unit)
    );
}

/// A label image lies over its image only on the same grid: the same
/// voxels, spacing and origin, in the same unit (nanometers against
/// micrometers compared as lengths). Off that grid it is refused by
/// `render --labels`, and its table has no mean intensities.
#[test]
fn labels_over_an_image_need_its_origin_and_unit() {
    let d = tempfile::tempdir().unwrap();
    let raw = ramp_raw(d.path());
    let store = d.path().join("s.ome.zarr");
    let conv = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "convert",
            s(&raw),
            s(out),
            "--dims",
            "16x16x16",
            "--dtype",
            "u8",
            "--spacing",
            "0.26,0.26,0.5",
        ];
        args.extend(extra);
        if !extra.contains(&"--unit") {
            args.extend(["--unit", "micrometer"]);
        }
        let o = run(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        stderr(&o)
    };
    conv(&store, &[]);
    let lab = |name: &str| store.join("labels").join(name);
    let off = "only on the image's grid";
    assert!(!conv(&lab("same"), &["--labels"]).contains(off));
    for (name, flags) in [
        ("shifted", ["--origin", "13,13,0"]),
        ("mm", ["--unit", "millimeter"]),
    ] {
        let e = conv(&lab(name), &["--labels", flags[0], flags[1]]);
        assert!(e.contains(off), "{name}: {e}");
    }
    // The image's grid, in nanometers.
    let o = run(&[
        "convert",
        s(&raw),
        s(&lab("nm")),
        "--dims",
        "16x16x16",
        "--dtype",
        "u8",
        "--spacing",
        "260,260,500",
        "--unit",
        "nanometer",
        "--labels",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let render = |name: &str| {
        let out = d.path().join(format!("{name}.png"));
        let o = run(&[
            "render",
            s(&store),
            "--mode",
            "slice",
            "--size",
            "32x32",
            "--out",
            s(&out),
            "--labels",
            name,
        ]);
        (o, out)
    };
    for ok in ["same", "nm"] {
        let (o, out) = render(ok);
        assert!(o.status.success() && out.exists(), "{ok}: {}", stderr(&o));
    }
    for (bad, why) in [("shifted", "[0.0, 13.0, 13.0]"), ("mm", "millimeter")] {
        let (o, out) = render(bad);
        fails_with(&o, &[bad, "drawn over the grid they were made on", why]);
        assert!(!out.exists());
    }
    // Mean intensities only on the image's grid.
    let means = |name: &str| {
        let csv = std::fs::read_to_string(lab(name).join("_brickyard/labels.csv")).unwrap();
        let rows: Vec<String> = csv.lines().skip(1).map(str::to_string).collect();
        assert!(!rows.is_empty(), "{name}: no rows");
        rows.iter().all(|r| !r.ends_with(','))
    };
    assert!(means("same") && means("nm"));
    assert!(!means("shifted") && !means("mm"));
}

/// An input read in large chunks (a store of 256³ u16 chunks, 32 MiB
/// each, decoded whole) counts them in the plan: a budget that cannot hold
/// them is refused naming them, and the budget asked for holds the whole
/// conversion (its peak RSS included). Bricks blosc cannot take whole are
/// refused before anything is written.
#[test]
fn an_input_of_large_chunks_is_planned_with_them() {
    let d = tempfile::tempdir().unwrap();
    let big = d.path().join("big.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&big),
        "--size",
        "256",
        "--dtype",
        "u16",
        "--brick",
        "256",
        "--shard",
        "256",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let copy = d.path().join("copy.ome.zarr");
    let conv = |memory: &str| {
        run(&[
            "convert",
            s(&big),
            s(&copy),
            "--memory",
            memory,
            "--json",
            "--overwrite",
        ])
    };
    let o = conv("48MiB");
    fails_with(&o, &["memory", "the input's chunks", "need at least"]);
    let e = stderr(&o);
    let need: u64 = e
        .split("need at least ")
        .nth(1)
        .unwrap()
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let o = conv(&format!("{need}MiB"));
    assert!(o.status.success(), "{need} MiB, as asked: {}", stderr(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let peak = j["peak_rss_bytes"].as_u64().unwrap();
    assert!(
        peak <= need << 20,
        "peak {peak} over the {need} MiB asked for"
    );
    let huge = d.path().join("huge.ome.zarr");
    fails_with(
        &run(&[
            "convert",
            s(&big),
            s(&huge),
            "--brick",
            "1024",
            "--shard",
            "1024",
        ]),
        &["brick", "blosc", "2 GiB"],
    );
    assert!(!huge.exists());
}

/// `info` counts the bricks of NaN only that `convert` wrote (they have no
/// range of values), as the conversion report does.
#[test]
fn info_counts_bricks_of_nan_only() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("nan.raw");
    let mut v = vec![f32::NAN; 16 * 16 * 32];
    v[16 * 16 * 16] = 3.0;
    std::fs::write(
        &raw,
        v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>(),
    )
    .unwrap();
    let store = d.path().join("nan.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "16x16x32",
        "--dtype",
        "f32",
        "--brick",
        "16",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = run(&["info", s(&store), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let st = &j["levels"][0]["stats"];
    assert_eq!(
        (st["bricks"].as_u64(), st["nan"].as_u64()),
        (Some(2), Some(1)),
        "{st}"
    );
    assert_eq!(st["max"].as_f64(), Some(3.0), "{st}");
    let o = run(&["info", s(&store)]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("1 of NaN only"));
}

/// NaN voxels are drawn as nothing whether the other values of their brick
/// differ or are all one value: such a brick is recorded as `(v, NaN)`, so
/// that no reader takes it for constant and maps it without loading it
/// (which drew its NaN as `v`). Bricks of 8 voxels; the left half's bricks
/// hold 50 and NaN, the right half's 50, 60 and NaN; every odd column is
/// NaN through the whole depth.
#[test]
fn nan_beside_a_single_value_is_drawn_as_nan() {
    let d = tempfile::tempdir().unwrap();
    let (nx, ny, nz) = (32usize, 32usize, 16usize);
    let mut v = vec![50f32; nx * ny * nz];
    for (i, x) in v.iter_mut().enumerate() {
        let c = i % nx;
        if c % 2 == 1 {
            *x = f32::NAN;
        } else if c >= 16 && c % 3 == 0 {
            *x = 60.0;
        }
    }
    let raw = d.path().join("v.raw");
    std::fs::write(
        &raw,
        v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>(),
    )
    .unwrap();
    let store = d.path().join("v.ome.zarr");
    let o = run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "32x32x16",
        "--dtype",
        "f32",
        "--brick",
        "8",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // Level 0: 4·4·2 bricks, none constant (each holds NaN), none of NaN only.
    let o = run(&["info", s(&store), "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let st = &j["levels"][0]["stats"];
    assert_eq!(
        (
            st["bricks"].as_u64(),
            st["constant"].as_u64(),
            st["nan"].as_u64()
        ),
        (Some(32), Some(0), Some(0)),
        "{st}"
    );
    assert_eq!(
        (st["min"].as_f64(), st["max"].as_f64()),
        (Some(50.0), Some(60.0)),
        "{st}"
    );
    let o = run(&["info", s(&store), "--check"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let cam = d.path().join("cam.json");
    std::fs::write(
        &cam,
        r#"{"projection":{"type":"orthographic","height":32},"eye":[16,16,-50],"target":[16,16,8],"up":[0,-1,0]}"#,
    )
    .unwrap();
    let backends: &[&str] = match brickyard_gpu::context::test_gpu() {
        Some(_) => &["cpu", "gpu"],
        None => &["cpu"], // BRICKYARD_SKIP_GPU=1
    };
    for &backend in backends {
        for mode in ["mip", "slice"] {
            let png = d.path().join(format!("{mode}-{backend}.png"));
            let o = run(&[
                "render",
                s(&store),
                "--size",
                "32",
                "--camera",
                s(&cam),
                "--mode",
                mode,
                "--tf",
                "linear",
                "--window",
                "0,100",
                "--level",
                "0",
                "--backend",
                backend,
                "--raw-f32",
                "--quiet",
                "-o",
                s(&png),
            ]);
            assert!(o.status.success(), "{}", stderr(&o));
            let px: Vec<f32> = std::fs::read(png.with_extension("f32"))
                .unwrap()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                .collect();
            assert_eq!(px.len(), 32 * 32 * 4);
            // Pixel centres lie on voxel centres: column c shows voxel column c.
            for y in [3usize, 16, 28] {
                for c in 0..nx {
                    let got = px[(y * 32 + c) * 4];
                    let want = match c {
                        c if c % 2 == 1 => 0.0,
                        c if c >= 16 && c % 3 == 0 => 0.6,
                        _ => 0.5,
                    };
                    assert!(
                        (got - want).abs() < 1e-4,
                        "{backend} {mode}: row {y} column {c} is {got}, {want} expected"
                    );
                }
            }
        }
    }
}

/// A NIfTI-1 file of u8 voxels `data` (x fastest) of `dims` (x, y, z), with
/// `intent` and the rescale `scl` (slope, intercept).
fn nifti_u8(path: &Path, dims: [u16; 3], data: &[u8], intent: i16, scl: (f32, f32)) {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    let dim = [3, dims[0], dims[1], dims[2], 1, 1, 1, 1];
    for (k, d) in dim.iter().enumerate() {
        h[40 + 2 * k..42 + 2 * k].copy_from_slice(&(*d as i16).to_le_bytes());
    }
    h[68..70].copy_from_slice(&intent.to_le_bytes());
    h[70..72].copy_from_slice(&2i16.to_le_bytes()); // uint8
    h[72..74].copy_from_slice(&8i16.to_le_bytes());
    for k in 0..4 {
        h[76 + 4 * k..80 + 4 * k].copy_from_slice(&1f32.to_le_bytes());
    }
    h[108..112].copy_from_slice(&352f32.to_le_bytes());
    h[112..116].copy_from_slice(&scl.0.to_le_bytes());
    h[116..120].copy_from_slice(&scl.1.to_le_bytes());
    h[123] = 2; // millimetres
    h[344..348].copy_from_slice(b"n+1\0");
    h.extend_from_slice(data);
    std::fs::write(path, h).unwrap();
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), &t).unwrap();
        }
    }
}

fn read_root(store: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(store.join("zarr.json")).unwrap()).unwrap()
}

/// What a killed `convert FILE STORE/labels/NAME --labels` leaves
/// (`labels/NAME.partial`, its root saying complete: false) is no image of
/// the store: `info` lists it as a problem (status 1), saying what left it
/// and how to clean it up, with or without a labels group before; the
/// same convert run again with --overwrite clears it. A finished label
/// image that the group does not name is blamed on the command that wrote
/// it (its metadata tells `convert` from `process`).
#[test]
fn info_lists_an_interrupted_label_conversion_as_a_problem() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "k.ome.zarr");
    let raw = d.path().join("seg.raw");
    std::fs::write(
        &raw,
        (0..48 * 48 * 48).map(|i| (i % 3) as u8).collect::<Vec<_>>(),
    )
    .unwrap();
    let convert_labels = |name: &str, extra: &[&str]| {
        let out = store.join("labels").join(name);
        let mut args = vec![
            "convert",
            s(&raw),
            s(&out),
            "--labels",
            "--dims",
            "48x48x48",
        ];
        args.extend(["--dtype", "u8", "--quiet"]);
        args.extend(extra);
        let o = run(&args);
        assert!(o.status.success(), "{}", stderr(&o));
    };
    convert_labels("seg", &[]);
    // What the kill leaves, made from a finished one.
    let partial = store.join("labels/killed.partial");
    copy_tree(&store.join("labels/seg"), &partial);
    let mut root = read_root(&partial);
    root["attributes"]["brickyard"]["complete"] = false.into();
    std::fs::write(partial.join("zarr.json"), root.to_string()).unwrap();
    let check = |what: &Path, rel: &str| {
        let o = run(&["info", s(what)]);
        let out = String::from_utf8_lossy(&o.stdout).into_owned();
        assert_eq!(o.status.code(), Some(1), "{out}");
        let line = out
            .lines()
            .find(|l| l.contains("problem:") && l.contains("killed.partial"))
            .unwrap_or_else(|| panic!("no problem line for the partial: {out}"));
        for want in [
            rel,
            "interrupted",
            "brickyard convert INPUT STORE/labels/killed --labels",
            "run that convert again",
            "remove the folder",
        ] {
            assert!(line.contains(want), "{want}: {line}");
        }
        // (labels/killed does not exist: the same command takes over the
        // partial output without --overwrite.)
        assert!(!line.contains("--overwrite"), "{line}");
        assert!(!line.contains("process"), "{line}");
        assert!(!out.contains("image inside: labels/killed"), "{out}");
        assert!(!out.contains("image inside: killed"), "{out}");
    };
    // A labels group that names other images.
    check(&store, "labels/killed.partial");
    check(&store.join("labels"), "labels/killed.partial");
    // --check reads no chunk of it (not an image): named once, as above.
    let o = run(&["info", "--check", s(&store)]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1), "{out}");
    let named: Vec<&str> = out.lines().filter(|l| l.contains("killed")).collect();
    assert!(
        named.len() == 1 && named[0].contains("problem: labels/killed.partial: not an image"),
        "{out}"
    );
    // No labels group yet (the first label image was being converted).
    let fresh = d.path().join("fresh.ome.zarr");
    copy_tree(&store, &fresh);
    std::fs::remove_dir_all(fresh.join("labels/seg")).unwrap();
    std::fs::remove_file(fresh.join("labels/zarr.json")).unwrap();
    check(&fresh, "labels/killed.partial");
    // The same convert again, with --overwrite: the partial is gone, the
    // image listed, nothing to report.
    convert_labels("killed", &["--overwrite"]);
    assert!(!partial.exists());
    let o = run(&["info", s(&store)]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(0), "{out}");
    assert!(out.contains("image inside: labels/killed (uint8"), "{out}");
    // Finished but not named by the group: convert's blamed on convert,
    // process's on process.
    let o = run(&[
        "process",
        s(&store),
        "threshold(100)",
        "--out",
        "mask",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let group = store.join("labels/zarr.json");
    let mut j: serde_json::Value = serde_json::from_slice(&std::fs::read(&group).unwrap()).unwrap();
    j["attributes"]["ome"]["labels"] = serde_json::json!(["seg"]);
    std::fs::write(&group, j.to_string()).unwrap();
    let o = run(&["info", s(&store)]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1), "{out}");
    let line = |name: &str| {
        out.lines()
            .find(|l| l.contains(&format!("problem: labels/{name}: not named")))
            .unwrap_or_else(|| panic!("{name}: {out}"))
            .to_string()
    };
    let killed = line("killed");
    assert!(
        killed.contains("brickyard convert INPUT STORE/labels/killed --labels")
            && !killed.contains("process"),
        "{killed}"
    );
    let mask = line("mask");
    assert!(
        mask.contains("brickyard process") && !mask.contains("convert"),
        "{mask}"
    );
}

/// A conversion of a store keeps each channel's colour, window and active
/// flag from its `omero` metadata (not only the names), a stack of inputs
/// each input's, and `info` shows them (text and JSON).
#[test]
fn a_copy_keeps_the_channels_colours_windows_and_active_flags() {
    let d = tempfile::tempdir().unwrap();
    let (a, b) = (d.path().join("a.raw"), d.path().join("b.raw"));
    std::fs::write(
        &a,
        (0..8 * 8 * 8).map(|i| (i % 100) as u8).collect::<Vec<_>>(),
    )
    .unwrap();
    std::fs::write(
        &b,
        (0..8 * 8 * 8).map(|i| (i % 90) as u8).collect::<Vec<_>>(),
    )
    .unwrap();
    let store = d.path().join("two.ome.zarr");
    let raw = ["--dims", "8x8x8", "--dtype", "u8", "--quiet"];
    let mut args = vec![
        "convert",
        s(&a),
        s(&b),
        s(&store),
        "--channel-names",
        "dapi,gfp",
    ];
    args.extend(raw);
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut root = read_root(&store);
    let chs = &mut root["attributes"]["ome"]["omero"]["channels"];
    chs[0]["color"] = "123456".into();
    chs[0]["window"] = serde_json::json!({"min": 0, "max": 255, "start": 10, "end": 50});
    chs[1]["color"] = "ABCDEF".into();
    chs[1]["window"] = serde_json::json!({"min": 0, "max": 255, "start": 20, "end": 80});
    chs[1]["active"] = false.into();
    std::fs::write(store.join("zarr.json"), root.to_string()).unwrap();
    let shown = |store: &Path| -> Vec<(String, String, bool, f64, f64)> {
        read_root(store)["attributes"]["ome"]["omero"]["channels"]
            .as_array()
            .expect("omero channels")
            .iter()
            .map(|c| {
                (
                    c["label"].as_str().unwrap().to_string(),
                    c["color"].as_str().unwrap().to_string(),
                    c["active"].as_bool().unwrap(),
                    c["window"]["start"].as_f64().unwrap(),
                    c["window"]["end"].as_f64().unwrap(),
                )
            })
            .collect()
    };
    let want = vec![
        ("dapi".to_string(), "123456".to_string(), true, 10.0, 50.0),
        ("gfp".to_string(), "ABCDEF".to_string(), false, 20.0, 80.0),
    ];
    assert_eq!(shown(&store), want);
    let copy = d.path().join("copy.ome.zarr");
    let o = run(&["convert", s(&store), s(&copy), "--brick", "4", "--quiet"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(shown(&copy), want);
    // `info` shows them.
    let o = run(&["info", s(&copy)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("channel 0 \"dapi\": colour 123456, window 10..50, active")
            && out.contains("channel 1 \"gfp\": colour ABCDEF, window 20..80, inactive"),
        "{out}"
    );
    let o = run(&["info", s(&copy), "--json"]);
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        j["channels"][1],
        serde_json::json!({"index": 1, "label": "gfp", "color": "ABCDEF",
                           "window": [20.0, 80.0], "active": false}),
        "{j}"
    );
    assert!(
        j["levels"][0]["shape"].is_array() && j["complete"] == true,
        "{j}"
    );
    // A stack: each input's channels as that input shows them (a
    // one-channel store's white), in order.
    let one = d.path().join("one.ome.zarr");
    let mut args = vec!["convert", s(&a), s(&one)];
    args.extend(raw);
    assert!(run(&args).status.success());
    let stack = d.path().join("stack.ome.zarr");
    let o = run(&["convert", s(&copy), s(&one), s(&stack), "--quiet"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let got = shown(&stack);
    assert_eq!(got.len(), 3, "{got:?}");
    // (Named after their input: `copy:dapi`.)
    assert_eq!(got[0].0, "copy:dapi");
    for (g, w) in got.iter().zip(&want) {
        assert_eq!((&g.1, g.2, g.3, g.4), (&w.1, w.2, w.3, w.4), "{got:?}");
    }
    assert_eq!((got[2].1.as_str(), got[2].2), ("FFFFFF", true));
}

/// A label image holds one channel: `convert a b IMAGE/labels/NAME
/// --labels` (two channels) is refused before anything is written, naming
/// the count, instead of writing and listing an image that `render
/// --labels` then refuses; a standalone one likewise.
#[test]
fn a_label_image_of_several_channels_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "m.ome.zarr");
    let raw = d.path().join("seg.raw");
    std::fs::write(&raw, vec![1u8; 48 * 48 * 48]).unwrap();
    let two = store.join("labels/two");
    let flags = ["--labels", "--dims", "48x48x48", "--dtype", "u8", "--quiet"];
    let mut args = vec!["convert", s(&raw), s(&raw), s(&two)];
    args.extend(flags);
    fails_with(
        &run(&args),
        &["a label image has one channel", "2 channels"],
    );
    assert!(!store.join("labels").exists(), "nothing written");
    let alone = d.path().join("alone.ome.zarr");
    let mut args = vec!["convert", s(&raw), s(&raw), s(&alone)];
    args.extend(flags);
    fails_with(
        &run(&args),
        &["a label image has one channel", "2 channels"],
    );
    assert!(!alone.exists() && !d.path().join("alone.ome.zarr.partial").exists());
}

/// Several inputs, one of NIfTI intent "label": without --labels the
/// message names the intent (not a grid); with --labels the files'
/// intents give way (what stops it then is the one-channel rule). Voxel
/// types are named as on the command line, and a rescale that widened a
/// file's numbers is said.
#[test]
fn inputs_that_differ_in_intent_or_voxel_type_are_named_plainly() {
    let d = tempfile::tempdir().unwrap();
    let data: Vec<u8> = (0..8 * 8 * 8).map(|i| (i % 256) as u8).collect();
    let (seg, t1, scl) = (
        d.path().join("seg.nii"),
        d.path().join("t1.nii"),
        d.path().join("scl.nii"),
    );
    nifti_u8(&seg, [8, 8, 8], &data, 1002, (0.0, 0.0));
    nifti_u8(&t1, [8, 8, 8], &data, 0, (0.0, 0.0));
    nifti_u8(&scl, [8, 8, 8], &data, 0, (2.0, -1.0));
    let out = d.path().join("o.ome.zarr");
    let o = run(&["convert", s(&seg), s(&t1), s(&out), "--quiet"]);
    fails_with(
        &o,
        &[
            "seg.nii marks its voxels as labels",
            "NIfTI intent",
            "--labels",
        ],
    );
    assert!(!stderr(&o).contains("grid"), "{}", stderr(&o));
    let o = run(&["convert", s(&seg), s(&t1), s(&out), "--labels", "--quiet"]);
    fails_with(&o, &["a label image has one channel"]);
    assert!(
        !stderr(&o).contains("grid") && !stderr(&o).contains("labels false"),
        "{}",
        stderr(&o)
    );
    let o = run(&["convert", s(&t1), s(&scl), s(&out), "--quiet"]);
    fails_with(
        &o,
        &[
            "this file has i16 (its u8 numbers rescaled by scl_slope=2, scl_inter=-1",
            "--raw-values keeps them u8",
            "t1.nii has u8",
        ],
    );
    assert!(
        !stderr(&o).contains("I16") && !stderr(&o).contains("U8"),
        "{}",
        stderr(&o)
    );
    let o = run(&[
        "convert",
        s(&t1),
        s(&scl),
        s(&out),
        "--raw-values",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
}

/// A raw sidecar's spacing, origin and unit are checked as the flags are:
/// refused naming the sidecar and the field, not silently replaced.
#[test]
fn sidecar_geometry_is_checked() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("sc.raw");
    std::fs::write(&raw, vec![0u8; 32 * 32 * 16]).unwrap();
    let side = d.path().join("sc.raw.json");
    let out = d.path().join("sc.ome.zarr");
    for (j, field) in [
        (
            r#"{"dims":[32,32,16],"dtype":"u8","spacing":[0,1,1]}"#,
            "spacing",
        ),
        (
            r#"{"dims":[32,32,16],"dtype":"u8","spacing":[-2,1,1]}"#,
            "spacing",
        ),
        (
            r#"{"dims":[32,32,16],"dtype":"u8","unit":"furlong"}"#,
            "unit",
        ),
    ] {
        std::fs::write(&side, j).unwrap();
        let o = run(&["convert", s(&raw), s(&out), "--quiet"]);
        fails_with(&o, &["sc.raw.json", field]);
        assert!(!out.exists(), "{j}");
    }
    std::fs::write(
        &side,
        r#"{"dims":[32,32,16],"dtype":"u8","unit":"um","spacing":[0.5,1,1]}"#,
    )
    .unwrap();
    let o = run(&["convert", s(&raw), s(&out), "--quiet"]);
    assert!(o.status.success(), "{}", stderr(&o));
}

/// `--dims` or `--dtype` alone replaces that field of a sidecar; without
/// one, the error names the input and asks for both (or a sidecar).
#[test]
fn dims_or_dtype_alone_with_a_sidecar() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("a.raw");
    std::fs::write(&raw, vec![0u8; 32 * 32 * 16]).unwrap();
    let side = d.path().join("a.raw.json");
    std::fs::write(&side, r#"{"dims":[32,32,16],"dtype":"u8"}"#).unwrap();
    for (i, flags) in [["--dims", "16x32x32"], ["--dtype", "u8"]]
        .iter()
        .enumerate()
    {
        let out = d.path().join(format!("a{i}.ome.zarr"));
        let mut args = vec!["convert", s(&raw), s(&out), "--quiet"];
        args.extend(flags);
        let o = run(&args);
        assert!(o.status.success(), "{flags:?}: {}", stderr(&o));
    }
    // The dims given win: 16x32x32 read as u16 does not match the file.
    let out = d.path().join("b.ome.zarr");
    let o = run(&["convert", s(&raw), s(&out), "--dtype", "u16", "--quiet"]);
    fails_with(&o, &["a.raw", "dims"]);
    std::fs::remove_file(&side).unwrap();
    let o = run(&["convert", s(&raw), s(&out), "--dims", "32x32x16"]);
    fails_with(&o, &["a.raw", "--dims and --dtype", "sidecar"]);
}

/// A generated raw file's sidecar holds the spacing, origin and unit
/// given; flags that shape only a store are refused for a raw output.
#[test]
fn generate_raw_geometry_and_store_flags() {
    let d = tempfile::tempdir().unwrap();
    let g = d.path().join("g.raw");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&g),
        "--size",
        "8",
        "--spacing",
        "0.5,0.5,2",
        "--origin",
        "1,2,3",
        "--unit",
        "micrometer",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("g.raw.json")).unwrap())
            .unwrap();
    assert_eq!(j["spacing"], serde_json::json!([0.5, 0.5, 2.0]), "{j}");
    assert_eq!(j["origin"], serde_json::json!([1.0, 2.0, 3.0]), "{j}");
    assert_eq!(j["unit"], "micrometer", "{j}");
    for flag in [
        &["--brick", "32"][..],
        &["--shard", "128"],
        &["--compression", "zstd"],
        &["--labels"],
        &["--columns", "4"],
    ] {
        let h = d.path().join("h.raw");
        let mut args = vec!["generate", "mandelbulb", s(&h), "--size", "8"];
        args.extend(flag);
        fails_with(&run(&args), &[flag[0], "h.raw"]);
        assert!(!h.exists(), "{flag:?}");
    }
    let h = d.path().join("h.raw");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&h),
        "--size",
        "8",
        "--unit",
        "furlong",
    ]);
    fails_with(&o, &["unit", "furlong"]);
    assert!(!h.exists());
}

/// Without --shard, the default shard is at least the brick, a multiple of it.
#[test]
fn default_shard_follows_the_brick() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("v.raw");
    std::fs::write(&raw, vec![0u8; 32 * 32 * 16]).unwrap();
    for brick in ["1024", "96"] {
        let out = d.path().join(format!("v{brick}.ome.zarr"));
        let o = run(&[
            "convert",
            s(&raw),
            s(&out),
            "--dims",
            "32x32x16",
            "--dtype",
            "u8",
            "--brick",
            brick,
            "--memory",
            "8GiB",
            "--quiet",
        ]);
        assert!(!stderr(&o).contains("shard"), "{brick}: {}", stderr(&o));
    }
}

/// A volume far too large for the budget says that its size is the
/// problem; demo leaves no folder behind when it fails before writing.
#[test]
fn absurd_sizes_blame_the_size() {
    let d = tempfile::tempdir().unwrap();
    let h = d.path().join("h.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&h),
        "--size",
        "100000000",
        "--quiet",
    ]);
    fails_with(&o, &["size", "volume", "too large", "--size"]);
    let dh = d.path().join("dhuge");
    let o = run(&["demo", "--size", "100000", "--out", s(&dh)]);
    fails_with(&o, &["size", "volume", "too large", "--size"]);
    assert!(!dh.exists());
}

/// A high Zstandard level's compressor state (several MiB a thread) is in
/// the conversion's budget: with eight threads at level 19 a 128³ u16
/// volume peaked near 100 MiB under `--memory 64MiB`. Now such a budget
/// is refused, naming --memory, and a budget the plan accepts holds.
#[test]
fn zstd_compressor_state_is_in_the_memory_budget() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("z.raw");
    let g = run(&[
        "generate",
        "mandelbulb",
        s(&raw),
        "--size",
        "128",
        "--dtype",
        "u16",
        "--quiet",
    ]);
    assert!(g.status.success(), "{}", stderr(&g));
    let conv = |memory: &str, name: &str| {
        run(&[
            "convert",
            s(&raw),
            s(&d.path().join(name)),
            "--memory",
            memory,
            "--compression",
            "zstd:19",
            "--threads",
            "8",
            "--json",
            "--quiet",
        ])
    };
    let o = conv("64MiB", "a.ome.zarr");
    assert!(
        !o.status.success(),
        "64 MiB taken for 8 level-19 compressors"
    );
    assert!(stderr(&o).contains("memory"), "{}", stderr(&o));
    assert!(!d.path().join("a.ome.zarr").exists());
    // The least budget the plan takes, named in the message, holds.
    let e = stderr(&o);
    let need: u64 = e
        .split("at least ")
        .nth(1)
        .and_then(|t| t.split(" MiB").next())
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("no least budget in: {e}"));
    let budget = format!("{need}MiB");
    let o = conv(&budget, "b.ome.zarr");
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let rss = r["peak_rss_bytes"].as_u64().unwrap();
    assert!(
        rss > 0 && rss <= need << 20,
        "peak RSS {rss} over the {need} MiB budget"
    );
}

/// What `convert --overwrite` of a label image leaves when stopped while
/// swapping (NAME.old beside the new NAME) is listed as a problem, not as
/// a second label image.
#[test]
fn info_lists_a_replaced_label_image_left_behind_as_a_problem() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "o.ome.zarr");
    let raw = d.path().join("seg.raw");
    std::fs::write(
        &raw,
        (0..48 * 48 * 48).map(|i| (i % 3) as u8).collect::<Vec<_>>(),
    )
    .unwrap();
    let out = store.join("labels/seg");
    let o = run(&[
        "convert",
        s(&raw),
        s(&out),
        "--labels",
        "--dims",
        "48x48x48",
        "--dtype",
        "u8",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    copy_tree(&out, &store.join("labels/seg.old"));
    let o = run(&["info", s(&store)]);
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    assert_eq!(o.status.code(), Some(1), "{text}");
    assert!(
        text.lines().any(|l| l.contains("problem:")
            && l.contains("labels/seg.old")
            && l.contains("remove the folder")),
        "{text}"
    );
    assert!(
        !text
            .lines()
            .any(|l| l.contains("image inside: labels/seg.old")),
        "{text}"
    );
}

/// A level whose `zarr.json` is there but damaged is named with its fault
/// (the file, "not valid JSON"), by `render` and `info`, not as an array
/// missing from its path.
#[test]
fn a_damaged_level_metadata_file_is_named_with_its_fault() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb_48(d.path(), "b.ome.zarr");
    let meta = store.join("0/zarr.json");
    let mut b = std::fs::read(&meta).unwrap();
    b[40..44].copy_from_slice(&[0, 1, 2, 3]);
    std::fs::write(&meta, &b).unwrap();
    let png = d.path().join("x.png");
    let o = run(&["render", s(&store), "--size", "16", "--out", s(&png)]);
    fails_with(&o, &["0/zarr.json", "not valid JSON"]);
    assert!(!stderr(&o).contains("no Zarr array"), "{}", stderr(&o));
    assert!(!png.exists());
}

/// A transfer-function file without `window` takes the window a preset
/// would (`--window` here): the same image as the file with that window
/// written in (it was refused, "window: missing").
#[test]
fn a_transfer_function_without_a_window_takes_the_presets() {
    let d = tempfile::tempdir().unwrap();
    let st = d.path().join("m.zarr");
    let o = run(&["generate", "mandelbulb", s(&st), "--size", "32", "--quiet"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let bare = d.path().join("bare.json");
    let full = d.path().join("full.json");
    std::fs::write(&bare, r#"{"preset": "soft", "shading": true}"#).unwrap();
    std::fs::write(
        &full,
        r#"{"preset": "soft", "shading": true, "window": [10, 200]}"#,
    )
    .unwrap();
    let mut pngs = vec![];
    for (tf, name) in [(&bare, "a.png"), (&full, "b.png")] {
        let png = d.path().join(name);
        let o = run(&[
            "render",
            s(&st),
            "--tf",
            s(tf),
            "--window",
            "10,200",
            "--size",
            "64",
            "--backend",
            "cpu",
            "-o",
            s(&png),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        pngs.push(std::fs::read(&png).unwrap());
    }
    assert_eq!(pngs[0], pngs[1]);
}

/// Engine bricks of 2 or 3 voxels are refused: a render of Colin27 at
/// `--brick 2` took 244 s over 238 frames and then lowered its detail.
#[test]
fn engine_bricks_below_four_voxels_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.ome.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "16",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    for b in ["2", "3"] {
        fails_with(
            &run(&[
                "render",
                s(&store),
                "--brick",
                b,
                "--out",
                s(&d.path().join("x.png")),
            ]),
            &["--brick", "4..=512"],
        );
    }
}

/// `vm footprint` refuses a pool that holds no brick and an apron wider
/// than the brick (it printed "0 slots" and accounted for them), and
/// `bench --dir` does not create the folders above the one it names (it
/// made `/nonexistent/x`).
#[test]
fn footprint_and_bench_refuse_what_cannot_be() {
    for (args, want) in [
        (&["--pool", "0"][..], "holds no brick"),
        (&["--pool", "1KiB"][..], "holds no brick"),
        (&["--brick", "4", "--apron", "5"][..], "apron"),
    ] {
        let mut a = vec!["vm", "footprint", "--dims", "256"];
        a.extend_from_slice(args);
        fails_with(&run(&a), &[want]);
    }
    let o = run(&["vm", "footprint", "--dims", "256"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let d = tempfile::tempdir().unwrap();
    let dir = d.path().join("no/such");
    fails_with(
        &run(&["bench", "convert", "--size", "16", "--dir", s(&dir)]),
        &["dir", "does not exist"],
    );
    assert!(!d.path().join("no").exists());
}
