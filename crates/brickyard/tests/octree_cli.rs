//! `render --traversal octree|page-table`, `--octree-depth`, `--debug` and
//! `bench octree` as a user meets them: the octree draws the page tables'
//! image (one and two channels, two depths), debug images count what they
//! say, unsupported values and combinations fail naming the flag; the
//! benchmark measures both traversals.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(args)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[track_caller]
fn ok(o: &Output, what: &str) -> String {
    assert!(o.status.success(), "{what}: {}", stderr(o));
    String::from_utf8_lossy(&o.stdout).into_owned()
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

/// A 48³ Mandelbulb store of 16³ bricks.
fn mandelbulb(dir: &Path) -> PathBuf {
    let store = dir.join("m.ome.zarr");
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
    ok(&o, "generate");
    store
}

/// A two-channel store: a Mandelbulb and a Marschner–Lobb of 40×48×56,
/// converted from raw files as the channels of one volume.
fn two_channels(dir: &Path) -> PathBuf {
    let mut raws = vec![];
    for kind in ["mandelbulb", "marschner-lobb"] {
        let raw = dir.join(format!("{kind}.raw"));
        ok(
            &run(&["generate", kind, s(&raw), "--size", "56x48x40", "--quiet"]),
            kind,
        );
        raws.push(raw);
    }
    let store = dir.join("two.ome.zarr");
    ok(
        &run(&[
            "convert",
            s(&raws[0]),
            s(&raws[1]),
            s(&store),
            "--brick",
            "16",
            "--shard",
            "32",
            "--quiet",
        ]),
        "convert",
    );
    store
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

/// Pixels (of RGBA8) with some colour over black.
fn lit(pixels: &[u8]) -> usize {
    pixels
        .chunks(4)
        .filter(|c| c[0].max(c[1]).max(c[2]) > 8)
        .count()
}

/// `render STORE --size 64x56 --backend cpu --json ARGS --out DIR/NAME`
/// (`--backend cpu` unless ARGS choose one), which must end complete: the
/// pixels and the octree nodes its frames visited and the largest count of
/// a debug image (`None` without one).
fn render(store: &Path, dir: &Path, name: &str, args: &[&str]) -> (Vec<u8>, u64, Option<f64>) {
    let png = dir.join(name);
    let mut a = vec![
        "render",
        s(store),
        "--size",
        "64x56",
        "--brick",
        "8",
        "--json",
        "--out",
        s(&png),
    ];
    if !args.contains(&"--backend") {
        a.extend(["--backend", "cpu"]);
    }
    a.extend_from_slice(args);
    let out = ok(&run(&a), name);
    assert!(out.contains(r#""stop":"complete""#), "{name}: {out}");
    let lines: Vec<serde_json::Value> = out
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    let nodes = lines
        .iter()
        .filter(|v| v["frame"].is_u64())
        .filter_map(|v| v["octree_nodes"].as_u64())
        .sum();
    let largest = lines.iter().find_map(|v| v["largest"].as_f64());
    (png_pixels(&png), nodes, largest)
}

/// Largest difference of two RGBA8 images, in 1/255.
fn max_diff(a: &[u8], b: &[u8]) -> u8 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap()
}

#[test]
fn octree_draws_the_page_tables_image() {
    let d = tempfile::tempdir().unwrap();
    let one = mandelbulb(d.path());
    let two = two_channels(d.path());
    let two_ch = ["--channel", "0:green", "--channel", "1:magenta"];
    for (store, extra, what) in [
        (&one, &[][..], "one channel"),
        (&one, &["--level", "1"][..], "one channel, level 1"),
        (&two, &two_ch[..], "two channels"),
    ] {
        let (pt, pt_nodes, _) = render(store, d.path(), "pt.png", extra);
        assert_eq!(pt_nodes, 0, "{what}: page tables visit no octree nodes");
        let n = pt.len() / 4;
        assert!(
            lit(&pt) * 10 >= n,
            "{what}: only {} of {n} pixels lit",
            lit(&pt)
        );
        for depth in ["4", "2"] {
            let mut a = vec!["--traversal", "octree", "--octree-depth", depth];
            a.extend_from_slice(extra);
            let (oc, nodes, _) = render(store, d.path(), "oc.png", &a);
            assert!(nodes > 0, "{what}, depth {depth}: no octree node visited");
            let diff = max_diff(&pt, &oc);
            assert!(
                diff <= 1,
                "{what}, depth {depth}: pixels differ by {diff}/255"
            );
            // The same on the device (Vulkan: lavapipe here), its updates
            // decided on the host.
            a.extend(["--backend", "gpu"]);
            let (dev, dev_nodes, _) = render(store, d.path(), "dev.png", &a);
            assert!(
                dev_nodes > 0,
                "{what}, depth {depth}: the device visited no node"
            );
            let diff = max_diff(&oc, &dev);
            assert!(
                diff <= 1,
                "{what}, depth {depth}: device and CPU octree differ by {diff}/255"
            );
        }
        // Explicit page tables are the default.
        let mut a = vec!["--traversal", "page-table"];
        a.extend_from_slice(extra);
        let (pt2, _, _) = render(store, d.path(), "pt2.png", &a);
        assert_eq!(pt, pt2, "{what}");
    }
}

#[test]
fn debug_images_count_nodes_only_through_the_octree() {
    let d = tempfile::tempdir().unwrap();
    let store = two_channels(d.path());
    let opaque = |px: &[u8]| px.chunks(4).all(|c| c[3] == 255);
    let (nodes, visited, largest) = render(
        &store,
        d.path(),
        "nodes.png",
        &["--traversal", "octree", "--debug", "nodes"],
    );
    assert!(visited > 0);
    assert!(largest.is_some_and(|m| m >= 1.0), "{largest:?}");
    let n = nodes.len() / 4;
    // Rays through the volume visit nodes, rays beside it none (black);
    // the largest count is white.
    assert!(opaque(&nodes));
    assert!(
        lit(&nodes) * 4 >= n && lit(&nodes) < n,
        "nodes: {} of {n} lit",
        lit(&nodes)
    );
    assert!(
        nodes.chunks(4).any(|c| c[..3] == [255; 3]),
        "no white pixel"
    );
    // Page tables visit no nodes: all black, yet their bricks and steps
    // images show the volume.
    let (pt_nodes, _, largest) = render(&store, d.path(), "pt-nodes.png", &["--debug", "nodes"]);
    assert_eq!(largest, Some(0.0));
    assert!(opaque(&pt_nodes));
    assert_eq!(lit(&pt_nodes), 0, "page-table nodes image not black");
    assert!(pt_nodes.chunks(4).all(|c| c[..3] == [0; 3]));
    for what in ["bricks", "steps"] {
        let (pt, _, _) = render(&store, d.path(), "pt.png", &["--debug", what]);
        let (oc, _, _) = render(
            &store,
            d.path(),
            "oc.png",
            &["--traversal", "octree", "--debug", what],
        );
        for (img, t) in [(&pt, "page-table"), (&oc, "octree")] {
            assert!(
                lit(img) * 4 >= n && lit(img) < n,
                "{what} through {t}: {} of {n} lit",
                lit(img)
            );
        }
    }
}

#[test]
fn bad_values_and_combinations_name_the_flag() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb(d.path());
    let out = d.path().join("x.png");
    let r = |args: &[&str]| {
        let mut a = vec!["render", s(&store), "--size", "16", "--out", s(&out)];
        a.extend_from_slice(args);
        run(&a)
    };
    let oc = ["--traversal", "octree"];
    fails_with(
        &r(&[&oc[..], &["--octree-depth", "0"]].concat()),
        &["octree-depth", "1 to 7", "0"],
    );
    fails_with(
        &r(&[&oc[..], &["--octree-depth", "9"]].concat()),
        &["octree-depth", "9"],
    );
    fails_with(&r(&["--octree-depth", "x"]), &["--octree-depth"]);
    fails_with(&r(&["--octree-depth", "3"]), &["octree-depth", "octree"]);
    fails_with(&r(&["--traversal", "foo"]), &["traversal", "foo"]);
    fails_with(&r(&["--debug", "foo"]), &["debug", "foo"]);
    for mode in ["mip", "slice"] {
        fails_with(
            &r(&[&oc[..], &["--mode", mode]].concat()),
            &["traversal", "dvr", mode],
        );
        fails_with(&r(&["--debug", "nodes", "--mode", mode]), &["debug", "dvr"]);
    }
    fails_with(
        &r(&[&oc[..], &["--gpu-update", "device"]].concat()),
        &["gpu-update", "host", "octree"],
    );
    // Level ranges per channel: several channels in DVR, levels the store
    // has.
    let two = two_channels(d.path());
    let r2 = |args: &[&str]| {
        let mut a = vec!["render", s(&two), "--size", "16", "--out", s(&out)];
        a.extend_from_slice(args);
        run(&a)
    };
    let both = ["--channel", "0:green", "--channel", "1:magenta"];
    for (bad, words) in [
        ("1=x", &["channel-levels", "C=LO-HI", "1=x"][..]),
        ("1=2-1", &["channel-levels", "LO <= HI"][..]),
        ("1=0-9", &["channel-levels", "levels"][..]),
        ("5=0", &["channel-levels", "channel 5", "not shown"][..]),
    ] {
        fails_with(
            &r2(&[&both[..], &["--channel-levels", bad]].concat()),
            words,
        );
    }
    fails_with(
        &r2(&["--channel", "1", "--channel-levels", "1=1"]),
        &["channel-levels", "several channels"],
    );
    fails_with(
        &r2(&[&both[..], &["--mode", "mip", "--channel-levels", "1=1"]].concat()),
        &["channel-levels", "dvr"],
    );
    ok(
        &r2(&[
            &both[..],
            &["--channel-levels", "1=1-1", "--backend", "cpu"],
        ]
        .concat()),
        "a channel at level 1",
    );
    // The deepest octree on the device: where its tables (two channels,
    // at least two levels: 146 MiB or more) pass the device's limit per
    // binding (lavapipe: 128 MiB), it is drawn through a shallower one,
    // and the run says so (it was refused after the device was set up).
    // Without an adapter: refused, never a panic.
    let o = r2(&[
        &both[..],
        &oc[..],
        &["--octree-depth", "7", "--backend", "gpu"],
    ]
    .concat());
    let e = stderr(&o);
    assert!(!e.contains("panicked"), "{e}");
    if let Some(g) = brickyard_gpu::context::test_gpu() {
        assert!(o.status.success(), "{e}");
        let least = brickyard_render::octree::Octree::device_table_bytes(7, 2, 2);
        if least > g.max_storage_binding() {
            assert!(
                e.contains("note: octree-depth 7: its tables would take")
                    && e.contains("drawing through depth 6"),
                "{e}"
            );
        }
    } else {
        assert!(!o.status.success());
    }
    fails_with(
        &r(&["--debug", "steps", "--backend", "gpu"]),
        &["debug", "CPU"],
    );
    fails_with(
        &r(&[&oc[..], &["--progressive", "4"]].concat()),
        &["traversal", "progressive"],
    );
    // Shading in the transfer function.
    let tf = d.path().join("shaded.json");
    std::fs::write(
        &tf,
        r#"{"preset": "soft", "window": [0, 255], "shading": true}"#,
    )
    .unwrap();
    ok(
        &r(&["--tf", s(&tf), "--backend", "cpu"]),
        "shaded page tables",
    );
    fails_with(
        &r(&[&oc[..], &["--tf", s(&tf)]].concat()),
        &["traversal", "shading"],
    );
    // --backend auto takes the CPU for a debug image, and says so.
    let o = r(&["--debug", "steps"]);
    ok(&o, "debug, auto");
    assert!(
        stderr(&o).contains("--backend auto takes the CPU"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn bench_octree_measures_both_traversals() {
    let d = tempfile::tempdir().unwrap();
    let o = run(&[
        "bench",
        "octree",
        "--size",
        "32",
        "--image",
        "40",
        "--channels",
        "1,3",
        "--backend",
        "both",
        "--dir",
        s(d.path()),
    ]);
    let out = ok(&o, "bench octree");
    let rows: Vec<Vec<&str>> = out
        .lines()
        .map(|l| l.split_whitespace().collect::<Vec<_>>())
        .filter(|w| w.len() >= 13 && (w[2] == "page-table" || w[2] == "octree"))
        .collect();
    let names: Vec<(&str, &str, &str)> = rows.iter().map(|w| (w[0], w[1], w[2])).collect();
    assert_eq!(
        names,
        [
            ("1", "cpu", "page-table"),
            ("1", "cpu", "octree"),
            ("1", "gpu", "page-table"),
            ("1", "gpu", "octree"),
            ("3", "cpu", "page-table"),
            ("3", "cpu", "octree"),
            ("3", "gpu", "page-table"),
            ("3", "gpu", "octree"),
        ],
        "{out}"
    );
    for w in &rows {
        let num = |i: usize| w[i].parse::<f64>().unwrap();
        // Frame time, samples per ray, images equal.
        assert!(num(3) > 0.0 && num(5) > 0.0, "{w:?}");
        assert!(num(w.len() - 1) <= 1e-4, "images differ: {w:?}");
        // Nodes per ray: none through page tables, some through the octree.
        assert_eq!(num(7) > 0.0, w[2] == "octree", "{w:?}");
    }
    // The same samples per ray on both back ends through the page tables
    // for one channel. For several, the CPU's runs leave out a channel
    // whose resident cell it hides, where the device samples it (and adds
    // nothing): the CPU takes fewer, and more than half. Through the
    // octree the CPU's runs cross the cells every channel hides, but
    // sample the channels a node hides, where the device samples step by
    // step and leaves those out: within a factor of two either way (the
    // descent itself is compared with the device's in the renderer's
    // tests, runs off).
    let ratio = |cpu: &str, dev: &str| cpu.parse::<f64>().unwrap() / dev.parse::<f64>().unwrap();
    for pair in rows.chunks(4) {
        let (cpu, dev) = (pair[0][5], pair[2][5]);
        if pair[0][0] == "1" {
            assert_eq!(cpu, dev, "{out}");
        } else {
            let r = ratio(cpu, dev);
            assert!(r <= 1.0 && r > 0.5, "{out}");
        }
        let r = ratio(pair[1][5], pair[3][5]);
        assert!(r > 0.5 && r < 2.0, "{out}");
    }
    fails_with(
        &run(&["bench", "octree", "--channels", "0", "--dir", s(d.path())]),
        &["channels"],
    );
}

/// An octree deeper than `--memory` holds: depth 7 over three levels took
/// 600 MiB with `--memory 128MiB` and said so only after. The depth is
/// lowered to what fits, said before drawing, the run stays within the
/// budget, and the image is the one the deeper octree draws.
#[test]
fn an_octree_deeper_than_the_budget_holds_is_lowered() {
    let d = tempfile::tempdir().unwrap();
    let store = mandelbulb(d.path());
    let (deep, _, _) = render(
        &store,
        d.path(),
        "deep.png",
        &[
            "--traversal",
            "octree",
            "--octree-depth",
            "6",
            "--memory",
            "4GiB",
        ],
    );
    let png = d.path().join("small.png");
    let o = run(&[
        "render",
        s(&store),
        "--size",
        "64x56",
        "--brick",
        "8",
        "--backend",
        "cpu",
        "--json",
        "--traversal",
        "octree",
        "--octree-depth",
        "6",
        "--memory",
        "96MiB",
        "--out",
        s(&png),
    ]);
    let out = ok(&o, "small");
    let err = stderr(&o);
    assert!(
        err.contains("octree-depth 6 would take about") && err.contains("drawing through depth"),
        "{err}"
    );
    let v = out
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|v| v["peak_rss_bytes"].is_u64())
        .unwrap_or_else(|| panic!("no summary: {out}"));
    let (peak, budget) = (
        v["peak_rss_bytes"].as_u64().unwrap(),
        v["memory_budget_bytes"].as_u64().unwrap(),
    );
    assert!(peak <= budget, "{peak} > {budget}");
    let small = png_pixels(&png);
    assert!(lit(&small) > 0, "an empty image");
    assert_eq!(max_diff(&deep, &small), 0);
}
