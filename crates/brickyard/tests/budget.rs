//! `render` as a user with a small machine meets it: pools from far below
//! to above the view's working set complete in a few frames, on the CPU and
//! on the device, at the detail the pool holds (and say so), with no part of
//! the volume missing; the process stays within `--memory`; damaged chunks
//! are drawn from coarser data and reported, and the run ends.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    run_env(&[], args)
}

/// [`run`] with environment variables set.
fn run_env(env: &[(&str, &str)], args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(args)
        .envs(env.iter().copied())
        .output()
        .unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn ok(o: &Output) -> String {
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    // Status 3: the image written, bricks drawn from coarser data (the
    // summary's `failed_bricks` then lists them; checked by `render`).
    assert!(
        o.status.success() || o.status.code() == Some(3),
        "failed: {}\n{out}",
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

/// A 128³ u8 Mandelbulb: 64³ store bricks in 64³ shards (levels 128, 64).
fn store(dir: &Path) -> PathBuf {
    let store = dir.join("m.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "128",
        "--dtype",
        "u8",
        "--quiet",
        "--brick",
        "32",
        "--shard",
        "64",
    ]));
    store
}

/// The summary line of `render --json`.
fn summary(out: &str) -> serde_json::Value {
    out.lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|v| v["summary"] == true)
        .unwrap_or_else(|| panic!("no summary in {out}"))
}

fn png_rgba(p: &Path) -> Vec<u8> {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    buf
}

/// Pixels lit (any channel above 8) in `full` but black in `img`.
fn holes(full: &[u8], img: &[u8]) -> usize {
    full.chunks(4)
        .zip(img.chunks(4))
        .filter(|(a, b)| a[..3].iter().any(|&v| v > 8) && b[..3].iter().all(|&v| v == 0))
        .count()
}

fn lit(img: &[u8]) -> usize {
    img.chunks(4)
        .filter(|p| p[..3].iter().any(|&v| v > 8))
        .count()
}

fn render(store: &Path, out: &Path, backend: &str, extra: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "render",
        s(store),
        "--size",
        "160",
        "--brick",
        "16",
        "--window",
        "0,255",
        "--backend",
        backend,
        "--json",
        "--out",
        s(out),
    ];
    args.extend_from_slice(extra);
    let o = run(&args);
    let v = summary(&ok(&o));
    // Status 3 exactly when bricks failed.
    let failed = v["failed_bricks"].as_array().is_some_and(|f| !f.is_empty());
    assert_eq!(o.status.code(), Some(if failed { 3 } else { 0 }), "{v}");
    v
}

/// The back ends to compare: the device too where there is an adapter
/// (lavapipe here; none with BRICKYARD_SKIP_GPU=1).
fn backends() -> &'static [&'static str] {
    match brickyard_gpu::context::test_gpu() {
        Some(_) => &["cpu", "gpu"],
        None => &["cpu"],
    }
}

fn pools_complete_at_the_detail_that_fits(backend: &str) {
    let d = tempfile::tempdir().unwrap();
    let store = store(d.path());
    let full_png = d.path().join("full.png");
    let full = render(&store, &full_png, backend, &["--pool", "64MiB"]);
    assert_eq!(full["stop"], "complete", "{full}");
    assert_eq!(full["lod_bias"], 0.0, "{full}");
    let full_px = png_rgba(&full_png);
    assert!(lit(&full_px) > full_px.len() / 4 / 10, "too little content");
    let mut biases = vec![];
    // 16³ bricks of u8 take about 6 KiB each: 160 KiB hold 25 (the
    // coarsest level pins 8 of 64³ at level 1... 16³ bricks: 64 bricks at
    // level 1 would not fit; level 2 is the one pinned).
    for pool in ["2MiB", "600KiB", "256KiB", "160KiB"] {
        let png = d.path().join(format!("{pool}.png"));
        let v = render(&store, &png, backend, &["--pool", pool]);
        assert_eq!(v["stop"], "complete", "{pool}: {v}");
        let frames = v["frames"].as_u64().unwrap();
        assert!(frames <= 30, "{pool}: {frames} frames");
        let bias = v["lod_bias"].as_f64().unwrap();
        let px = png_rgba(&png);
        // A hole would be a brick's whole footprint; coarser data may only
        // thin out features finer than its voxels at silhouettes.
        let lost = holes(&full_px, &px);
        assert!(
            lost * 50 <= lit(&full_px),
            "{pool} (bias {bias}): {lost} pixels lost"
        );
        if bias > 0.0 {
            assert!(
                v["needed_bytes_at_full_detail"].as_u64().unwrap()
                    > v["pool_bytes"].as_u64().unwrap(),
                "{v}"
            );
        }
        // The same view with a large pool at the bias reached is the
        // same image: the small pool cost detail, nothing else.
        let again = d.path().join(format!("{pool}-again.png"));
        let b = format!("{bias}");
        let w = render(
            &store,
            &again,
            backend,
            &["--pool", "64MiB", "--lod-bias", &b],
        );
        assert_eq!(w["lod_bias"].as_f64().unwrap(), bias, "{w}");
        let worst = px
            .iter()
            .zip(&png_rgba(&again))
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap();
        assert!(
            worst <= 1,
            "{pool}: differs from the large pool at bias {bias} by {worst}/255"
        );
        biases.push(bias);
    }
    assert!(
        biases[3] > 0.0,
        "the smallest pool must coarsen: {biases:?}"
    );
    // Too small even for the coarsest level: refused, with the minimum.
    let o = run(&[
        "render",
        s(&store),
        "--brick",
        "16",
        "--backend",
        backend,
        "--pool",
        "20KiB",
        "--out",
        s(&d.path().join("x.png")),
    ]);
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("pool") && e.contains("at least"), "{e}");
}

#[test]
fn pools_from_tiny_to_large_complete_on_the_cpu() {
    pools_complete_at_the_detail_that_fits("cpu");
}

#[test]
fn pools_from_tiny_to_large_complete_on_the_device() {
    if brickyard_gpu::context::test_gpu().is_none() {
        eprintln!("skipped on purpose: BRICKYARD_SKIP_GPU=1 and no adapter");
        return;
    }
    pools_complete_at_the_detail_that_fits("gpu");
}

/// A close perspective camera and pools from below to an eighth of the
/// view's working set (2.4 MiB): the CPU and the device settle at the same bias, and
/// it is the finest that fits (asked half a level finer, the same pool
/// makes the render coarsen again). Coarsening decides from frames still
/// waiting for data, which ask for more than the view needs (the back ends
/// differed by up to 1.5 levels); a complete render tries half a level
/// finer before it ends. The CPU also marked the finer bricks its rays
/// passed through clear space beyond their level's end as in use, which
/// held the pool against the bricks the view needed.
#[test]
fn back_ends_settle_at_the_same_finest_bias_that_fits() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "192",
        "--dtype",
        "u8",
        "--quiet",
        "--brick",
        "16",
        "--shard",
        "64",
    ]));
    let cam = d.path().join("near.json");
    std::fs::write(
        &cam,
        r#"{"projection":{"type":"perspective","fov_y_deg":70},"eye":[96,-30,150],"target":[96,96,96],"up":[0,0,1]}"#,
    )
    .unwrap();
    let backends = backends();
    let png = d.path().join("x.png");
    let mut raised = 0;
    for pool in ["2MiB", "1MiB", "600KiB", "300KiB"] {
        let mut biases = vec![];
        for &backend in backends {
            let args = ["--camera", s(&cam), "--pool", pool];
            let v = render(&store, &png, backend, &args);
            assert_eq!(v["stop"], "complete", "{pool} {backend}: {v}");
            let bias = v["lod_bias"].as_f64().unwrap();
            raised += (bias > 0.0) as usize;
            if bias > 0.0 {
                let finer = format!("{}", bias - 0.5);
                let mut args = args.to_vec();
                args.extend(["--lod-bias", &finer]);
                let w = render(&store, &png, backend, &args);
                assert!(
                    w["lod_bias"].as_f64().unwrap() > bias - 0.5,
                    "{pool} {backend}: settled at {bias}, but {finer} fits: {w}"
                );
            }
            biases.push(bias);
        }
        assert!(
            biases.windows(2).all(|b| b[0] == b[1]),
            "{pool}: {backends:?} at {biases:?}"
        );
    }
    assert_eq!(
        raised,
        4 * backends.len(),
        "every pool is below the working set"
    );
}

/// `render --stream` with a pool smaller than the view: on the device,
/// bricks that arrived and waited for a slot were not asked for again, the
/// frames asked for nothing, and the render ran until it was killed (for
/// every mode). It ends, complete at a coarser bias, on both back ends.
#[test]
fn streamed_views_with_small_pools_end() {
    let d = tempfile::tempdir().unwrap();
    let store = store(d.path());
    let png = d.path().join("s.png");
    for &backend in backends() {
        for mode in ["dvr", "mip", "slice"] {
            for pool in ["600KiB", "256KiB"] {
                let args = [
                    "--stream",
                    "--mode",
                    mode,
                    "--pool",
                    pool,
                    "--max-frames",
                    "200",
                ];
                let v = render(&store, &png, backend, &args);
                assert_eq!(v["stop"], "complete", "{backend} {mode} {pool}: {v}");
                assert!(
                    v["frames"].as_u64().unwrap() < 60,
                    "{backend} {mode} {pool}: {v}"
                );
            }
        }
    }
}

#[test]
fn the_process_stays_within_its_memory_budget() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("big.ome.zarr");
    // 256³ u16 = 32 MiB of voxels.
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "256",
        "--dtype",
        "u16",
        "--quiet",
    ]));
    for (memory, pool) in [("96MiB", None), ("160MiB", Some("2MiB")), ("256MiB", None)] {
        let mut extra = vec!["--memory", memory];
        if let Some(p) = pool {
            extra.extend(["--pool", p]);
        }
        let v = render(&store, &d.path().join("m.png"), "cpu", &extra);
        assert_eq!(v["stop"], "complete", "{memory}: {v}");
        let peak = v["peak_rss_bytes"].as_u64().unwrap();
        let budget = v["memory_budget_bytes"].as_u64().unwrap();
        // The budget, plus a constant for what is not split (the
        // allocator's slack).
        assert!(
            peak <= budget + (16 << 20),
            "{memory}: peak {} MiB over the budget {} MiB",
            peak >> 20,
            budget >> 20
        );
    }
    // A split that cannot fit is refused.
    let o = run(&[
        "render",
        s(&store),
        "--memory",
        "64MiB",
        "--pool",
        "60MiB",
        "--out",
        s(&d.path().join("x.png")),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("does not hold"));
}

/// Budgets just below and above the least a view takes: each one is drawn
/// complete or refused with a total that holds it (drawn complete when
/// given), and where the pool's share is a little short of the coarsest
/// level the host cache's share lends it the rest. A 256³ u32 label image
/// (its coarsest level 8 bricks of 2.4 MiB at 32³); the split is computed,
/// not measured, so the same budgets fall the same way on every machine.
#[test]
fn a_budget_that_is_refused_names_one_that_holds_the_view() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("l.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "256",
        "--dtype",
        "u32",
        "--labels",
        "--quiet",
    ]));
    let out = d.path().join("l.png");
    let draw = |memory: u64| {
        let m = format!("{memory}MiB");
        run(&[
            "render",
            s(&store),
            "--mode",
            "dvr",
            "--size",
            "128",
            "--backend",
            "cpu",
            "--json",
            "--memory",
            &m,
            "--out",
            s(&out),
        ])
    };
    let (mut refused, mut lent, mut drawn) = (0, 0, 0);
    for memory in 50..=58u64 {
        let o = draw(memory);
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        if o.status.success() {
            let v = summary(&String::from_utf8_lossy(&o.stdout));
            assert_eq!(v["stop"], "complete", "{memory} MiB: {v}");
            if err.contains("note: the pool takes") {
                lent += 1;
            } else {
                drawn += 1;
            }
            continue;
        }
        assert_eq!(o.status.code(), Some(1), "{memory} MiB: {err}");
        refused += 1;
        let holds: u64 = err
            .split("raise --memory (")
            .nth(1)
            .and_then(|t| t.split("MiB holds it)").next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{memory} MiB: no total named: {err}"));
        assert!(holds > memory, "{memory} MiB: {err}");
        let o = draw(holds);
        assert!(
            o.status.success(),
            "{memory} MiB was refused naming {holds} MiB, which failed too: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    assert!(
        refused > 0 && lent > 0 && drawn > 0,
        "refused {refused}, lent {lent}, drawn {drawn}: the budgets no longer span the least"
    );
}

/// The device back end's driver lives in the process too: `--memory` sets
/// it aside (on a software adapter the device's copy of the pool besides),
/// refuses a budget that cannot hold it, and `auto` takes the CPU rather
/// than go over (lavapipe took 168 MiB beyond the CPU back end, uncounted:
/// 208 MiB peak for a 64 MiB budget; with its shader cache empty, 401 MiB).
#[test]
fn device_back_ends_stay_within_the_memory_budget() {
    if brickyard_gpu::context::test_gpu().is_none() {
        eprintln!("skipped on purpose: BRICKYARD_SKIP_GPU=1 and no adapter");
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let store = store(d.path());
    let png = d.path().join("g.png");
    let o = run(&[
        "render",
        s(&store),
        "--backend",
        "gpu",
        "--memory",
        "96MiB",
        "--out",
        s(&png),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && !e.contains("panicked"), "{e}");
    assert!(
        e.contains("--backend gpu") && e.contains("driver") && e.contains("--backend cpu"),
        "{e}"
    );
    for (backend, memory) in [("auto", "96MiB"), ("gpu", "768MiB"), ("auto", "512MiB")] {
        // (The driver's compiler at its largest: no shader cache, as on a
        // fresh machine.)
        let o = run_env(
            &[("MESA_SHADER_CACHE_DISABLE", "true")],
            &[
                "render",
                s(&store),
                "--size",
                "160",
                "--window",
                "0,255",
                "--backend",
                backend,
                "--memory",
                memory,
                "--json",
                "--out",
                s(&png),
            ],
        );
        let v = summary(&ok(&o));
        assert_eq!(v["stop"], "complete", "{backend} {memory}: {v}");
        if memory == "96MiB" {
            let e = String::from_utf8_lossy(&o.stderr);
            assert!(e.contains("auto takes the CPU"), "{e}");
        }
        let peak = v["peak_rss_bytes"].as_u64().unwrap();
        let budget = v["memory_budget_bytes"].as_u64().unwrap();
        assert!(
            peak <= budget + (16 << 20),
            "{backend} {memory}: peak {} MiB over the budget {} MiB",
            peak >> 20,
            budget >> 20
        );
    }
}

/// Shard files of level `l` of a store, sorted.
fn shards(store: &Path, l: usize) -> Vec<PathBuf> {
    fn walk(p: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(p).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.file_name().unwrap() != "zarr.json" {
                out.push(p);
            }
        }
    }
    let mut v = vec![];
    walk(&store.join(l.to_string()).join("c"), &mut v);
    v.sort();
    v
}

/// One shard truncated (its index gone), one with its chunks' bytes
/// scrambled (bad compressed streams), one removed.
fn damage(shards: &[PathBuf]) {
    let t = std::fs::read(&shards[0]).unwrap();
    std::fs::write(&shards[0], &t[..t.len() / 3]).unwrap();
    let mut c = std::fs::read(&shards[1]).unwrap();
    let n = c.len();
    for b in &mut c[16..n.saturating_sub(600)] {
        *b = b.wrapping_mul(31).wrapping_add(7);
    }
    std::fs::write(&shards[1], &c).unwrap();
    std::fs::remove_file(&shards[2]).unwrap();
}

#[test]
fn damaged_chunks_are_drawn_coarser_and_reported() {
    let d = tempfile::tempdir().unwrap();
    let store = store(d.path());
    let clean_png = d.path().join("clean.png");
    render(&store, &clean_png, "cpu", &[]);
    let clean = png_rgba(&clean_png);
    let l0 = shards(&store, 0);
    assert!(l0.len() >= 4, "{l0:?}");
    damage(&l0);
    let png = d.path().join("damaged.png");
    let v = render(&store, &png, "cpu", &[]);
    let stop = v["stop"].as_str().unwrap();
    assert!(stop == "complete_but_failed" || stop == "complete", "{v}");
    let failed = v["failed_bricks"].as_array().unwrap();
    assert!(!failed.is_empty(), "{v}");
    // Each brick's key as JSON (not Rust's `BrickKey { … }`).
    for f in failed {
        let k = &f["key"];
        assert!(
            k["level"].is_u64()
                && k["channel"].is_u64()
                && k["brick"].as_array().unwrap().len() == 3,
            "{f}"
        );
        // The voxels it covers: the brick's 16³ from its index.
        let b = k["brick"].as_array().unwrap();
        let lo: Vec<u64> = b.iter().map(|i| i.as_u64().unwrap() * 16).collect();
        assert_eq!(f["voxels"][0], serde_json::json!(lo), "{f}");
    }
    assert!(
        failed
            .iter()
            .any(|f| f["error"].as_str().unwrap().contains("c/")),
        "errors should name the chunk's file: {v}"
    );
    let frames = v["frames"].as_u64().unwrap();
    assert!(frames <= 30, "{frames} frames");
    // Regions of failed bricks are drawn from coarser data: nothing lit in
    // the clean image is black now.
    let lost = holes(&clean, &png_rgba(&png));
    assert!(lost * 200 <= lit(&clean), "{lost} pixels lost");
    // The text report lists them too, and exits 0.
    let text_render = || {
        run(&[
            "render",
            s(&store),
            "--size",
            "160",
            "--brick",
            "16",
            "--backend",
            "cpu",
            "--out",
            s(&png),
        ])
    };
    let o = text_render();
    let out = ok(&o);
    assert!(out.contains("could not load level 0"), "{out}");
    // Also by the level's voxels (the engine's 16³ bricks are not the
    // store's chunks).
    assert!(out.contains(" (voxels z "), "{out}");
    // Damaged brick statistics change nothing in the image (their bricks
    // are loaded instead of skipped) but are reported, not passed over.
    let stats = store.join("_brickyard/stats/0/c/0/0/0/0/0");
    let mut b = std::fs::read(&stats).unwrap();
    let n = b.len();
    for x in &mut b[n / 4..n / 2] {
        *x ^= 0xa5;
    }
    std::fs::write(&stats, &b).unwrap();
    let o = text_render();
    ok(&o);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("warning: brick statistics") && e.contains("_brickyard/stats/0"),
        "{e}"
    );
}

/// A label image's surfaces over a damaged level 0 are drawn from its
/// coarser levels, as an image's are, on both back ends: the missing
/// neighbours of a surface voxel only shade it, they are no hole (the CPU
/// counted them as samples no level could serve, and the render ended
/// with an error and no image).
#[test]
fn a_damaged_label_image_is_drawn_coarser_and_reported() {
    let d = tempfile::tempdir().unwrap();
    let store = store(d.path());
    ok(&run(&[
        "process",
        s(&store),
        "threshold(40)|label(6)",
        "--out",
        "blobs",
        "--quiet",
    ]));
    let labels = store.join("labels/blobs");
    // (`render`'s arguments but --window: label colours take none.)
    let draw = |png: &Path, backend: &str| {
        let o = run(&[
            "render",
            s(&labels),
            "--size",
            "160",
            "--brick",
            "16",
            "--backend",
            backend,
            "--json",
            "--out",
            s(png),
        ]);
        let v = summary(&ok(&o));
        let failed = v["failed_bricks"].as_array().is_some_and(|f| !f.is_empty());
        assert_eq!(o.status.code(), Some(if failed { 3 } else { 0 }), "{v}");
        v
    };
    let backends = backends();
    let mut clean = vec![];
    for &backend in backends {
        let png = d.path().join(format!("clean-{backend}.png"));
        let v = draw(&png, backend);
        assert_eq!(v["stop"], "complete", "{v}");
        clean.push(png_rgba(&png));
        assert!(
            lit(clean.last().unwrap()) > 160 * 160 / 10,
            "too little shows"
        );
    }
    // Level 0 is one shard: its index cut off, every brick of it fails.
    let l0 = shards(&labels, 0);
    assert_eq!(l0.len(), 1, "{l0:?}");
    let t = std::fs::read(&l0[0]).unwrap();
    std::fs::write(&l0[0], &t[..t.len() / 3]).unwrap();
    for (i, &backend) in backends.iter().enumerate() {
        let png = d.path().join(format!("damaged-{backend}.png"));
        let v = draw(&png, backend);
        assert_eq!(v["stop"], "complete_but_failed", "{backend}: {v}");
        assert!(!v["failed_bricks"].as_array().unwrap().is_empty(), "{v}");
        // Level 0 lost whole: the image is level 1's, up to a few
        // silhouette pixels (the walk steps at level 0's rate through
        // level 1's voxels), and close to full detail's.
        let png1 = d.path().join(format!("l1-{backend}.png"));
        ok(&run(&[
            "render",
            s(&labels),
            "--size",
            "160",
            "--brick",
            "16",
            "--backend",
            backend,
            "--level",
            "1",
            "--out",
            s(&png1),
        ]));
        let (img, l1) = (png_rgba(&png), png_rgba(&png1));
        let (lost, gained) = (holes(&l1, &img), holes(&img, &l1));
        eprintln!(
            "{backend}: against level 1: {lost} lost, {gained} gained of {}",
            lit(&l1)
        );
        assert!(
            (lost + gained) * 50 <= lit(&l1),
            "{backend}: {lost} lost, {gained} gained"
        );
        let lost = holes(&clean[i], &img);
        assert!(lost * 20 <= lit(&clean[i]), "{backend}: {lost} pixels lost");
    }
}

#[test]
fn a_store_damaged_during_a_render_is_drawn_coarser_and_reported() {
    // A slow render (a few bricks a frame, each read delayed) of a store
    // whose level-0 shards are truncated, scrambled and removed after its
    // second frame: what was read stays, what was not fails, and the run
    // ends with the failures listed and no part of the volume missing.
    use std::io::BufRead;
    let d = tempfile::tempdir().unwrap();
    let store = store(d.path());
    let clean_png = d.path().join("clean.png");
    render(&store, &clean_png, "cpu", &[]);
    let clean = png_rgba(&clean_png);
    let l0 = shards(&store, 0);
    assert!(l0.len() >= 4, "{l0:?}");
    let png = d.path().join("damaged.png");
    let mut child = Command::new(env!("CARGO_BIN_EXE_brickyard"))
        .args(["render", s(&store), "--size", "160", "--brick", "16"])
        .args(["--window", "0,255", "--backend", "cpu", "--json"])
        .args(["--stream", "--requests", "4", "--loader-threads", "1"])
        .args(["--read-delay-ms", "10", "--out", s(&png)])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    let mut out = String::new();
    let mut frames = 0;
    for l in lines.by_ref() {
        let l = l.unwrap();
        frames += l.contains("\"frame\"") as usize;
        out += &l;
        out.push('\n');
        if frames == 2 {
            break;
        }
    }
    assert_eq!(frames, 2, "the render ended before its second frame: {out}");
    damage(&l0);
    for l in lines {
        out += &l.unwrap();
        out.push('\n');
    }
    let status = child.wait().unwrap();
    // Bricks failed: the image is written, with status 3.
    assert_eq!(status.code(), Some(3), "{out}");
    let v = summary(&out);
    let stop = v["stop"].as_str().unwrap();
    assert!(stop == "complete_but_failed" || stop == "complete", "{v}");
    let failed = v["failed_bricks"].as_array().unwrap();
    assert!(!failed.is_empty(), "no brick failed: {v}");
    assert!(v["frames"].as_u64().unwrap() > 2, "{v}");
    let lost = holes(&clean, &png_rgba(&png));
    assert!(lost * 200 <= lit(&clean), "{lost} pixels lost");
}

#[test]
fn a_camera_inside_the_volume_completes_in_a_small_pool() {
    // A perspective eye inside the volume: pixels near it span less than
    // a level-0 voxel. The level-of-detail bias used to coarsen only
    // samples past where the footprint reached a voxel, so raising it
    // never shrank the near part of the working set: MIP with a pool
    // below it stopped at --max-frames, 87 % complete at bias +7 in a
    // volume of 5 levels. Now the view completes in a few frames, at a
    // bias no larger than the coarsest level needs, without holes.
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("g.ome.zarr");
    ok(&run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "256",
        "--quiet",
        "--brick",
        "16",
        "--shard",
        "64",
    ]));
    let cam = d.path().join("inside.json");
    std::fs::write(
        &cam,
        r#"{"projection":{"type":"perspective","fov_y_deg":35.0},"eye":[212,87,162],"target":[187,118,137],"up":[0,0,1]}"#,
    )
    .unwrap();
    for mode in ["mip", "dvr"] {
        let shot = |pool: &str| {
            let png = d.path().join(format!("{mode}-{pool}.png"));
            let o = run(&[
                "render",
                s(&store),
                "--mode",
                mode,
                "--camera",
                s(&cam),
                "--size",
                "256",
                "--backend",
                "cpu",
                "--pool",
                pool,
                "--max-frames",
                "100",
                "--json",
                "--out",
                s(&png),
            ]);
            let v = summary(&ok(&o));
            assert_eq!(o.status.code(), Some(0), "{mode} {pool}: {v}");
            (v, png_rgba(&png))
        };
        let (full, full_px) = shot("64MiB");
        assert_eq!(full["lod_bias"], 0.0, "{full}");
        assert!(lit(&full_px) > 1000, "{mode}: too little content");
        let (v, px) = shot("128KiB");
        assert_eq!(v["stop"], "complete", "{mode}: {v}");
        let (frames, bias) = (
            v["frames"].as_u64().unwrap(),
            v["lod_bias"].as_f64().unwrap(),
        );
        assert!(frames <= 20 && bias > 0.0 && bias <= 4.0, "{mode}: {v}");
        assert_eq!(holes(&full_px, &px), 0, "{mode}: holes at 128 KiB");
    }
}

#[test]
fn the_default_budget_stays_within_an_address_space_limit() {
    // Under `ulimit -v` the default budget (a quarter of RAM) asked for
    // more than the process could map: an allocation failed and the
    // process aborted. The default now fits the limit, and `auto` takes
    // the CPU without loading a graphics driver.
    let d = tempfile::tempdir().unwrap();
    let store = store(d.path());
    let png = d.path().join("v.png");
    let cmd = format!(
        "ulimit -v 400000 && exec '{}' render '{}' --size 256 --out '{}'",
        env!("CARGO_BIN_EXE_brickyard"),
        s(&store),
        s(&png)
    );
    let o = Command::new("bash").args(["-c", &cmd]).output().unwrap();
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(0), "{out}\n{err}");
    assert!(out.contains("within the address-space limit"), "{out}");
    assert!(err.contains("takes the CPU"), "{err}");
    assert!(lit(&png_rgba(&png)) > 1000, "too little drawn");
}
