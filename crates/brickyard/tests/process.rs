//! `brickyard process` as a user meets it: labels written into the store
//! equal an in-core flood fill; jobs killed at random points leave the
//! store as it was and readable, and a rerun completes.

use brickyard_core::{as_bytes_mut, Dims3};
use brickyard_store::import::zarr;
use brickyard_store::VolumeSource;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[track_caller]
fn ok(o: Output) -> Output {
    assert!(
        o.status.success(),
        "failed: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

fn read_level0<T: brickyard_core::Sample>(path: &Path) -> (Vec<T>, Dims3) {
    let src = zarr::open(path, 0).unwrap();
    let d = src.meta().dims;
    let mut v = vec![T::default(); d.iter().product::<u64>() as usize];
    src.read_region(0, 0..d[0], 0..d[1], 0..d[2], as_bytes_mut(&mut v))
        .unwrap();
    (v, d)
}

/// Flood fill in raster order (the reference numbering).
fn flood(mask: &[bool], d: Dims3, conn: u8) -> Vec<u32> {
    let (nz, ny, nx) = (d[0] as i64, d[1] as i64, d[2] as i64);
    let mut lab = vec![0u32; mask.len()];
    let mut n = 0;
    let mut st = vec![];
    for s0 in 0..mask.len() {
        if !mask[s0] || lab[s0] != 0 {
            continue;
        }
        n += 1;
        lab[s0] = n;
        st.push(s0);
        while let Some(i) = st.pop() {
            let (z, y, x) = (i as i64 / (ny * nx), i as i64 / nx % ny, i as i64 % nx);
            for dz in -1i64..=1 {
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let k = dz.abs() + dy.abs() + dx.abs();
                        if k == 0 || (conn == 6 && k > 1) {
                            continue;
                        }
                        let (a, b, c) = (z + dz, y + dy, x + dx);
                        if a < 0 || b < 0 || c < 0 || a >= nz || b >= ny || c >= nx {
                            continue;
                        }
                        let j = ((a * ny + b) * nx + c) as usize;
                        if mask[j] && lab[j] == 0 {
                            lab[j] = n;
                            st.push(j);
                        }
                    }
                }
            }
        }
    }
    lab
}

/// Every file of the store outside `labels/`, with its bytes.
fn snapshot(store: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut m = BTreeMap::new();
    let mut todo = vec![store.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            let rel = p
                .strip_prefix(store)
                .unwrap()
                .to_string_lossy()
                .into_owned();
            if rel.starts_with("labels") {
                continue;
            }
            if p.is_dir() {
                todo.push(p);
            } else {
                m.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    m
}

/// The peak RSS a job's report line gives, in MiB.
fn peak_rss_mib(o: &Output) -> f64 {
    let out = String::from_utf8_lossy(&o.stdout);
    out.split("peak RSS ")
        .nth(1)
        .and_then(|t| t.split(" MiB").next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no peak RSS in {out:?}"))
}

fn make_store(dir: &Path, size: &str) -> std::path::PathBuf {
    let store = dir.join("v.zarr");
    ok(run(&[
        "generate",
        "marschner-lobb",
        s(&store),
        "--size",
        size,
        "--dtype",
        "u16",
        "--brick",
        "16",
        "--shard",
        "32",
        "--quiet",
    ]));
    store
}

#[test]
fn labels_equal_an_in_core_flood_fill_and_follow_the_labels_spec() {
    let d = tempfile::tempdir().unwrap();
    // Random bytes; about 8 % of voxels above the threshold: many
    // components with either connectivity, some across many bricks.
    let dims: Dims3 = [41, 29, 37];
    let mut r = 0x2545f4914f6cdd1du64;
    let v: Vec<u8> = (0..dims.iter().product::<u64>())
        .map(|_| {
            r ^= r << 13;
            r ^= r >> 7;
            r ^= r << 17;
            (r >> 56) as u8
        })
        .collect();
    let raw = d.path().join("v.raw");
    std::fs::write(&raw, &v).unwrap();
    let store = d.path().join("v.zarr");
    ok(run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "37x29x41",
        "--dtype",
        "u8",
        "--brick",
        "8",
        "--shard",
        "16",
        "--quiet",
    ]));
    let t = 235u8;
    let stats = d.path().join("cells.json");
    for conn in [6u8, 26] {
        let pipe = format!("threshold({t})|label({conn})");
        ok(run(&[
            "process",
            s(&store),
            &pipe,
            "--out",
            "cells",
            "--stats",
            s(&stats),
            "--overwrite",
            "--quiet",
        ]));
        let (got, gd) = read_level0::<u32>(&store.join("labels/cells"));
        assert_eq!(gd, dims);
        let mask: Vec<bool> = v.iter().map(|&x| x > t).collect();
        let want = flood(&mask, dims, conn);
        let n = *want.iter().max().unwrap();
        assert!(n > 2, "the test volume should have several components");
        assert!(got == want, "labels differ from the flood fill ({conn})");
        let j: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
        assert_eq!(j["count"], n);
        assert_eq!(j["labels"].as_array().unwrap().len(), n as usize);
    }
    let lj: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(store.join("labels/zarr.json")).unwrap())
            .unwrap();
    assert_eq!(
        lj["attributes"]["ome"]["labels"],
        serde_json::json!(["cells"])
    );
    let ij: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(store.join("labels/cells/zarr.json")).unwrap(),
    )
    .unwrap();
    assert!(ij["attributes"]["ome"]["image-label"].is_object());
    // Coarser levels hold the most frequent label, and say so.
    assert_eq!(ij["attributes"]["ome"]["multiscales"][0]["type"], "mode");
    assert_eq!(ij["attributes"]["brickyard"]["labels"], true);
    assert!(store.join("labels/cells/_brickyard/labels.csv").exists());
    // A second label image is added to the list, the first kept.
    ok(run(&[
        "process",
        s(&store),
        "window(100,200)|label(6)",
        "--out",
        "band",
        "--quiet",
    ]));
    let lj: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(store.join("labels/zarr.json")).unwrap())
            .unwrap();
    assert_eq!(
        lj["attributes"]["ome"]["labels"],
        serde_json::json!(["cells", "band"])
    );
    // `info` lists them.
    let o = ok(run(&["info", s(&store)]));
    let text = String::from_utf8_lossy(&o.stdout);
    for l in [
        "image inside: labels/band (uint32, ",
        "image inside: labels/cells (uint32, ",
    ] {
        assert!(text.contains(l), "{l:?} not in {text}");
    }
    // With the number of labels the statistics hold, as their JSON says.
    let lj: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(store.join("labels/cells/_brickyard/labels.json")).unwrap(),
    )
    .unwrap();
    let n = lj["count"].as_u64().unwrap();
    let want = format!(", {n} labels with statistics (_brickyard/labels.csv))");
    let line = text.lines().find(|l| l.contains("labels/cells")).unwrap();
    assert!(line.ends_with(&want), "{line:?} does not end with {want:?}");
}

#[test]
fn killed_jobs_leave_the_store_as_it_was_and_a_rerun_completes() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "120x110x100");
    let before = snapshot(&store);
    let pipe = "gauss(2)|threshold(30000)|label(26)";
    let args = |extra: &[&str]| {
        let mut a = vec!["process", s(&store), pipe, "--out", "cells", "--quiet"];
        a.extend_from_slice(extra);
        a.into_iter().map(String::from).collect::<Vec<_>>()
    };
    // An uninterrupted run: its duration and result.
    let t0 = Instant::now();
    ok(bin().args(args(&[])).output().unwrap());
    let dur = t0.elapsed();
    let (want, _) = read_level0::<u32>(&store.join("labels/cells"));
    std::fs::remove_dir_all(store.join("labels")).unwrap();
    assert_eq!(snapshot(&store), before);
    let mut leftovers_seen = 0;
    // Kill points spread over the job (pseudo-random, fixed seed).
    let mut r = 0x9e3779b97f4a7c15u64;
    // The last round kills the job as soon as its partial output appears,
    // so that at least one kill lands while the pyramid is being written.
    for k in 0..6 {
        r ^= r << 13;
        r ^= r >> 7;
        r ^= r << 17;
        let f = 0.05 + 0.9 * ((r >> 11) as f64 / (1u64 << 53) as f64);
        let mut child = bin().args(args(&[])).spawn().unwrap();
        if k == 5 {
            let partial = store.join("labels/.cells.new.partial/0");
            let t = Instant::now();
            while !partial.exists() && t.elapsed() < Duration::from_secs(60) {
                std::thread::sleep(Duration::from_millis(2));
            }
            assert!(partial.exists(), "the job never wrote its partial output");
        } else {
            std::thread::sleep(Duration::from_secs_f64(dur.as_secs_f64() * f));
        }
        let _ = child.kill(); // SIGKILL
        let st = child.wait().unwrap();
        // The store opens, the image is unchanged byte for byte.
        assert_eq!(snapshot(&store), before, "kill {k}: the store changed");
        zarr::open(&store, 0).unwrap();
        let labels = store.join("labels");
        let published = labels.join("cells").exists();
        if published {
            // Killed after publishing: the result is complete.
            let (got, _) = read_level0::<u32>(&labels.join("cells"));
            assert!(got == want, "kill {k}: published labels differ");
        }
        let hidden = labels.exists()
            && std::fs::read_dir(&labels)
                .unwrap()
                .any(|e| e.unwrap().file_name().to_string_lossy().starts_with('.'));
        let extra: &[&str] = if published { &["--overwrite"] } else { &[] };
        let o = ok(bin().args(args(extra)).output().unwrap());
        let err = String::from_utf8_lossy(&o.stderr);
        if hidden {
            leftovers_seen += 1;
            assert!(
                err.contains("interrupted run") || err.contains("a process that is gone"),
                "kill {k}: the rerun should say what it cleaned up: {err:?}"
            );
        }
        let (got, _) = read_level0::<u32>(&labels.join("cells"));
        assert!(
            got == want,
            "kill {k} ({st:?} after {f:.2} of the job): rerun differs"
        );
        assert!(!std::fs::read_dir(&labels).unwrap().any(|e| e
            .unwrap()
            .file_name()
            .to_string_lossy()
            .starts_with('.')));
        std::fs::remove_dir_all(&labels).unwrap();
    }
    eprintln!("kills that left hidden leftovers: {leftovers_seen} of 6");
    assert!(leftovers_seen >= 1);
}

#[test]
fn a_second_job_on_the_same_name_is_refused_while_the_first_runs() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "120x110x100");
    let args = [
        "process",
        s(&store),
        "gauss(3)|threshold(30000)|label(26)",
        "--out",
        "cells",
        "--quiet",
    ];
    let mut first = bin().args(args).spawn().unwrap();
    let lock = store.join("labels/.cells.lock");
    let t = Instant::now();
    while !lock.exists() && t.elapsed() < Duration::from_secs(60) {
        std::thread::sleep(Duration::from_millis(1));
    }
    assert!(lock.exists(), "the job took no lock");
    // While it runs: refused, and the first job's work is left alone.
    let o = run(&args);
    let first_done = first.try_wait().unwrap().is_some();
    if !first_done {
        assert!(!o.status.success(), "a second job ran beside the first");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(
            e.contains("another process")
                && e.contains("is writing cells")
                && !e.contains("panicked"),
            "{e}"
        );
    }
    assert!(first.wait().unwrap().success(), "the first job failed");
    assert!(!lock.exists(), "the lock outlived its job");
    let (v, _) = read_level0::<u32>(&store.join("labels/cells"));
    assert!(v.iter().any(|&l| l > 0));
    // A lock left by a killed job is taken over.
    std::fs::write(&lock, "4000000000\n").unwrap();
    let o = ok(run(&[
        "process",
        s(&store),
        "threshold(30000)",
        "--out",
        "cells",
        "--overwrite",
        "--quiet",
    ]));
    assert!(String::from_utf8_lossy(&o.stderr).contains("the lock of a process that is gone"));
    assert!(!lock.exists());
}

/// `--overwrite` replaces results only: a folder or file of the user's at
/// the result's place, and results made from the old result, stay as they
/// are, with an error naming them; a job writing the name as the other
/// kind (a label image beside a derived result) is refused while it runs.
#[test]
fn overwrite_replaces_results_only_and_one_name_is_one_kind() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "40");
    let process = |pipeline: &str, out: &str| {
        run(&[
            "process",
            s(&store),
            pipeline,
            "--out",
            out,
            "--overwrite",
            "--quiet",
        ])
    };
    let refused = |o: &Output, want: &str| {
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{e}");
        assert!(e.contains(want) && !e.contains("panicked"), "{e}");
    };
    // A folder of the user's.
    ok(process("gauss(1)", "g"));
    let mine = store.join("derived/mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("notes.txt"), "precious").unwrap();
    refused(
        &process("gauss(1)", "mine"),
        "derived/mine: exists and is not a result (a folder with no zarr.json in it)",
    );
    assert_eq!(std::fs::read(mine.join("notes.txt")).unwrap(), b"precious");
    // A file of the user's: not moved aside, the store untouched.
    let file = store.join("derived/notes");
    std::fs::write(&file, "mine").unwrap();
    let before = snapshot(&store);
    refused(&process("gauss(1)", "notes"), "is not a result (a file)");
    assert_eq!(snapshot(&store), before);
    // A result made from the result.
    ok(run(&[
        "process",
        s(&store.join("derived/g")),
        "gauss(1)",
        "--out",
        "gg",
        "--quiet",
    ]));
    refused(
        &process("gauss(2)", "g"),
        "--overwrite would delete what the job does not make again: derived/gg",
    );
    assert!(store.join("derived/g/derived/gg/zarr.json").is_file());
    // A live job writing `cells` as a label image (its lock, naming this
    // process): a derived `cells` is refused, and goes once it is gone.
    std::fs::create_dir_all(store.join("labels")).unwrap();
    let lock = store.join("labels/.cells.lock");
    std::fs::write(&lock, format!("{}\n", std::process::id())).unwrap();
    refused(&process("gauss(1)", "cells"), "another process (pid");
    assert!(!store.join("derived/cells").exists());
    std::fs::remove_file(&lock).unwrap();
    ok(process("gauss(1)", "cells"));
    refused(
        &process("threshold(30000)", "cells"),
        "a result of this name is there already",
    );
}

/// Jobs that publish different label images into the same store at the
/// same time each add their name to the labels group's list: none is lost
/// (the list was read at the start and written at the end, so the last
/// job to finish kept only its own name).
#[test]
fn concurrent_jobs_keep_every_label_image_listed() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "24");
    let names = ["r1", "r2", "r3", "r4"];
    let jobs: Vec<_> = names
        .iter()
        .enumerate()
        .map(|(i, n)| {
            bin()
                .args([
                    "process",
                    s(&store),
                    &format!("threshold({})", 10000 * (i + 1)),
                    "--out",
                    n,
                    "--quiet",
                ])
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for j in jobs {
        let o = j.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(store.join("labels/zarr.json")).unwrap())
            .unwrap();
    let mut listed: Vec<&str> = j["attributes"]["ome"]["labels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    listed.sort();
    assert_eq!(listed, names);
    for n in names {
        assert!(store.join("labels").join(n).join("zarr.json").is_file());
    }
    // No lock or temporary file stays.
    let hidden: Vec<_> = std::fs::read_dir(store.join("labels"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(hidden.is_empty(), "{hidden:?}");
}

/// A σ far wider than the volume folds its kernel onto the volume without
/// making the unfolded one first (eight million taps per axis at σ = 1e6:
/// 260 MiB for a job given 100 MiB).
#[test]
fn a_huge_sigma_stays_within_the_memory_budget() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "24");
    let o = ok(run(&[
        "process",
        s(&store),
        "gauss(1e6)",
        "--out",
        "wide",
        "--memory",
        "64MiB",
    ]));
    let peak = peak_rss_mib(&o);
    assert!(peak <= 64.0, "peak RSS {peak} MiB over a 64 MiB budget");
}

/// The device back end's driver is in --memory, as for render: a budget
/// that cannot hold it is refused (naming it and --backend cpu), and one
/// that can is kept (`--backend gpu` ran past 200 MiB by the driver's
/// share, 333 MiB). On lavapipe here: its share is a software adapter's.
#[test]
fn the_device_back_ends_driver_is_in_the_budget() {
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "48");
    let job = |memory: &str| {
        run(&[
            "process",
            s(&store),
            "gauss(1)",
            "--out",
            "g",
            "--backend",
            "gpu",
            "--memory",
            memory,
            "--overwrite",
        ])
    };
    let o = job("200MiB");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("for its driver") && err.contains("--backend cpu"),
        "{err}"
    );
    assert!(!store.join("derived/g").exists());
    let o = ok(job("800MiB"));
    let peak = peak_rss_mib(&o);
    assert!(peak <= 800.0, "peak RSS {peak} MiB over an 800 MiB budget");
}

#[test]
fn bad_process_inputs_give_clear_errors() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "20");
    // A statistics file in a folder that is not there: refused before any
    // work (it is written last).
    let stats = d.path().join("no/such/s.csv");
    // A statistics file inside the store (its own metadata once) or over a
    // file that exists: refused, the file untouched.
    let meta = store.join("zarr.json");
    let kept = std::fs::read(&meta).unwrap();
    let precious = d.path().join("precious.csv");
    std::fs::write(&precious, "precious").unwrap();
    for (args, want) in [
        (
            vec!["threshold(1)|label(6)", "--out", "x", "--stats", s(&meta)],
            "inside the store",
        ),
        (
            vec![
                "threshold(1)|label(6)",
                "--out",
                "x",
                "--stats",
                s(&store.join("labels.json")),
            ],
            "inside the store",
        ),
        (
            vec![
                "threshold(1)|label(6)",
                "--out",
                "x",
                "--stats",
                s(&precious),
            ],
            "exists; pass --overwrite",
        ),
        (vec!["sobel", "--out", "a\nb"], "control characters"),
        (
            vec!["threshold(1)|label(6)", "--out", "x", "--stats", s(&stats)],
            "no/such does not exist",
        ),
        (vec!["gauss(1)|treshold(3)", "--out", "x"], "treshold"),
        (
            vec!["gauss(1)|label(8)", "--out", "x"],
            "connectivity 6 or 26",
        ),
        (vec!["sobel", "--out", "a/b"], "--out"),
        // The group's metadata, not a result name (this once replaced
        // derived/zarr.json by a folder).
        (
            vec!["sobel", "--out", "zarr.json", "--overwrite"],
            "group's metadata",
        ),
        (
            vec!["threshold(1)", "--out", "ZARR.JSON"],
            "group's metadata",
        ),
        (vec!["sobel", "--out", "x", "--level", "7"], "level 7"),
        (vec!["sobel", "--out", "x", "--channel", "2"], "channel"),
        (
            vec!["label", "--out", "x", "--stats", "s.txt"],
            ".csv or .json",
        ),
        (vec!["sobel", "--out", "x", "--memory", "lots"], "memory"),
    ] {
        let mut a = vec!["process", s(&store)];
        a.extend(args.iter().copied());
        let o = run(&a);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{a:?} succeeded");
        assert!(!e.contains("panicked"), "{a:?}: {e}");
        assert!(e.contains(want), "{a:?}: {e:?} should mention {want:?}");
    }
    assert_eq!(std::fs::read(&meta).unwrap(), kept);
    assert_eq!(std::fs::read_to_string(&precious).unwrap(), "precious");
    let o = run(&[
        "process",
        s(&d.path().join("none.zarr")),
        "sobel",
        "--out",
        "x",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("none.zarr"));
    // Nothing was written by the failures.
    assert!(!store.join("labels").exists() && !store.join("derived").exists());
    // A labels group whose list is not a list of names: named, refused,
    // left as it was.
    std::fs::create_dir_all(store.join("labels")).unwrap();
    let bad = r#"{"zarr_format": 3, "node_type": "group", "attributes": {"ome": {"labels": 5}}}"#;
    std::fs::write(store.join("labels/zarr.json"), bad).unwrap();
    let o = run(&["process", s(&store), "threshold(1)", "--out", "m"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && !e.contains("panicked"), "{e}");
    assert!(
        e.contains("labels/zarr.json") && e.contains("attributes.ome.labels"),
        "{e}"
    );
    assert_eq!(
        std::fs::read_to_string(store.join("labels/zarr.json")).unwrap(),
        bad
    );
    assert_eq!(std::fs::read_dir(store.join("labels")).unwrap().count(), 1);
    // An OME-Zarr 0.4 store (Zarr v2), which `render` reads: its readers
    // would not find results written as v3 groups, so it is refused,
    // pointing to `convert`, and left as it was.
    let v2 = d.path().join("v2.ome.zarr");
    std::fs::create_dir_all(v2.join("0")).unwrap();
    std::fs::write(v2.join(".zgroup"), r#"{"zarr_format": 2}"#).unwrap();
    let ms = r#"{"multiscales": [{"version": "0.4", "axes": [{"name": "z", "type": "space"},
        {"name": "y", "type": "space"}, {"name": "x", "type": "space"}], "datasets": [{"path": "0",
        "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1]}]}]}]}"#;
    std::fs::write(v2.join(".zattrs"), ms).unwrap();
    let arr = r#"{"zarr_format": 2, "shape": [4, 4, 4], "chunks": [4, 4, 4], "dtype": "|u1",
        "compressor": null, "fill_value": 0, "order": "C", "filters": null}"#;
    std::fs::write(v2.join("0/.zarray"), arr).unwrap();
    std::fs::write(v2.join("0/0.0.0"), (0..64u8).collect::<Vec<u8>>()).unwrap();
    let before = snapshot(&v2);
    ok(run(&[
        "render",
        s(&v2),
        "--mode",
        "slice",
        "--size",
        "8",
        "--out",
        s(&d.path().join("v2.png")),
    ]));
    let o = run(&["process", s(&v2), "threshold(10)|label(6)", "--out", "m"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && !e.contains("panicked"), "{e}");
    assert!(
        e.contains("Zarr v2") && e.contains("brickyard convert"),
        "{e}"
    );
    assert_eq!(snapshot(&v2), before);
    assert!(!v2.join("labels").exists() && !v2.join("derived").exists());
}

#[test]
fn the_chosen_channel_is_processed_and_measured() {
    // Two channels, stored one after the other: channel 0 noise, channel 1
    // a few boxes of distinct values on zero.
    let d = tempfile::tempdir().unwrap();
    let dims: Dims3 = [12, 14, 16];
    let n = dims.iter().product::<u64>() as usize;
    let mut r = 0x853c49e6748fea9bu64;
    let mut c0 = vec![0u16; n];
    for v in &mut c0 {
        r ^= r << 13;
        r ^= r >> 7;
        r ^= r << 17;
        *v = (r >> 48) as u16;
    }
    let mut c1 = vec![0u16; n];
    let boxes = [
        ([1, 2, 3], [4, 5, 6], 500u16),
        ([6, 8, 9], [11, 13, 15], 900),
    ];
    for (lo, hi, val) in boxes {
        for z in lo[0]..hi[0] {
            for y in lo[1]..hi[1] {
                for x in lo[2]..hi[2] {
                    c1[(z * 14 + y) * 16 + x] = val;
                }
            }
        }
    }
    let mut bytes = vec![];
    for v in c0.iter().chain(&c1) {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    let raw = d.path().join("two.raw");
    std::fs::write(&raw, bytes).unwrap();
    let store = d.path().join("two.zarr");
    ok(run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "16x14x12",
        "--dtype",
        "u16",
        "--channels",
        "2",
        "--brick",
        "8",
        "--shard",
        "16",
        "--quiet",
    ]));
    let stats = d.path().join("boxes.csv");
    ok(run(&[
        "process",
        s(&store),
        "threshold(0)|label(6)",
        "--out",
        "boxes",
        "--channel",
        "1",
        "--stats",
        s(&stats),
        "--quiet",
    ]));
    let (got, gd) = read_level0::<u32>(&store.join("labels/boxes"));
    assert_eq!(gd, dims);
    let want = flood(&c1.iter().map(|&v| v > 0).collect::<Vec<_>>(), dims, 6);
    assert!(got == want);
    let csv = std::fs::read_to_string(&stats).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), 2);
    for (row, (lo, hi, val)) in rows.iter().zip(boxes) {
        let vox: u64 = (0..3).map(|a| (hi[a] - lo[a]) as u64).product();
        assert_eq!(row[1], vox.to_string());
        assert_eq!(
            &row[2..8],
            &[lo[0], lo[1], lo[2], hi[0] - 1, hi[1] - 1, hi[2] - 1].map(|v| v.to_string())[..]
        );
        // The mean is over channel 1 (the processed one), not channel 0.
        assert_eq!(row[11].parse::<f64>().unwrap(), val as f64);
    }
    // A derived image of channel 1 (a median of radius 1: the boxes'
    // middles keep their values, the zeros around them stay zero; channel
    // 0's noise would not), its one channel named as the result (not
    // "channel 0").
    ok(run(&[
        "process",
        s(&store),
        "median(1)",
        "--out",
        "bright",
        "--channel",
        "1",
        "--quiet",
    ]));
    let (got, _) = read_level0::<f32>(&store.join("derived/bright"));
    let at = |z: usize, y: usize, x: usize| got[(z * 14 + y) * 16 + x];
    assert_eq!(
        (at(8, 10, 12), at(2, 3, 4), at(0, 0, 0), at(11, 0, 15)),
        (900.0, 500.0, 0.0, 0.0)
    );
    let info =
        String::from_utf8(ok(run(&["info", s(&store.join("derived/bright"))])).stdout).unwrap();
    assert!(info.contains("channel 0 \"bright\""), "{info}");
}

fn png_rgba(p: &Path) -> Vec<u8> {
    let d = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = d.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    buf
}

/// Mean and largest absolute difference of two RGBA images (0..255).
fn image_diff(a: &[u8], b: &[u8]) -> (f64, u8) {
    assert_eq!(a.len(), b.len());
    let sum: u64 = a.iter().zip(b).map(|(x, y)| x.abs_diff(*y) as u64).sum();
    let max = a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
    (sum as f64 / a.len() as f64, max)
}

#[test]
fn a_live_derived_channel_equals_the_written_result_and_stands_in_at_coarse_levels() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "48");
    let render = |src: &Path, derive: Option<&str>, level: &str, window: &str, out: &str| {
        let out = d.path().join(out);
        let mut a = vec![
            "render",
            s(src),
            "--mode",
            "slice",
            "--slice-z",
            "0.37",
            "--level",
            level,
            "--window",
            window,
            "--tf",
            "linear",
            "--size",
            "96",
            "--quiet",
            "--out",
            s(&out),
        ];
        if let Some(p) = derive {
            a.extend(["--derive", p]);
        }
        ok(run(&a));
        png_rgba(&out)
    };
    for (pipe, name, window) in [
        ("gauss(1)|sobel", "gs", "0,110000"),
        ("gradmag(2)", "gm", "0,2400"),
    ] {
        ok(run(&["process", s(&store), pipe, "--out", name, "--quiet"]));
        let written = store.join("derived").join(name);
        // Level 0: the live channel is the pipeline itself.
        let a = render(&written, None, "0", window, &format!("{name}-w0.png"));
        let b = render(&store, Some(pipe), "0", window, &format!("{name}-l0.png"));
        let lit = a.chunks(4).filter(|p| p[0] > 8).count() as f64 / (a.len() / 4) as f64;
        let shades = a
            .chunks(4)
            .map(|p| p[0])
            .collect::<std::collections::BTreeSet<_>>()
            .len();
        assert!(
            lit > 0.2 && shades > 50,
            "{pipe}: a flat image ({lit} lit, {shades} shades)"
        );
        let (mean, max) = image_diff(&a, &b);
        assert!(
            max <= 1,
            "{pipe} level 0: live differs from written by up to {max}/255"
        );
        // Level 1: the written level is the finer result downsampled, the
        // live one the pipeline on level 1 with σ and gradients scaled.
        let a1 = render(&written, None, "1", window, &format!("{name}-w1.png"));
        let b1 = render(&store, Some(pipe), "1", window, &format!("{name}-l1.png"));
        let (mean1, max1) = image_diff(&a1, &b1);
        eprintln!("{pipe}: level 0 mean {mean:.3} max {max}; level 1 mean {mean1:.2} max {max1}");
        // Sobel's stencil is not scaled with the level: a looser stand-in.
        let bound = if pipe.ends_with("sobel") { 12.0 } else { 6.0 };
        assert!(mean1 < bound, "{pipe} level 1: mean difference {mean1}/255");
    }
}

#[test]
fn bad_derive_pipelines_give_clear_errors() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "24");
    let out = d.path().join("x.png");
    for (pipe, want) in [
        ("threshold(5)|label(6)", "brickyard process"),
        ("gauss(", "pipeline"),
        ("blur(2)", "blur"),
        ("gauss(1um)", "spacing"),
    ] {
        let o = run(&[
            "render",
            s(&store),
            "--derive",
            pipe,
            "--out",
            s(&out),
            "--quiet",
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{pipe}: accepted");
        assert!(e.contains(want) && !e.contains("panicked"), "{pipe}: {e}");
    }
    let o = run(&[
        "render",
        s(&store),
        "--derive",
        "sobel",
        "--channel",
        "3",
        "--out",
        s(&out),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("channel"));
    assert!(!out.exists(), "no image after a refused run");
}

fn read_level<T: brickyard_core::Sample>(path: &Path, level: usize) -> Vec<T> {
    let src = zarr::open(path, level).unwrap();
    let d = src.meta().dims;
    let mut v = vec![T::default(); d.iter().product::<u64>() as usize];
    src.read_region(0, 0..d[0], 0..d[1], 0..d[2], as_bytes_mut(&mut v))
        .unwrap();
    v
}

/// `process --backend gpu` writes what `--backend cpu` writes: float
/// results within the tolerance `brickyard_process::gpu` states (at every
/// level: coarser levels are means), masks equal except where the value
/// before the threshold lies within that tolerance of it.
#[test]
fn the_device_backend_writes_what_the_cpu_writes() {
    use brickyard_process::Filter;
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "45x38x41");
    let (input, _) = read_level0::<u16>(&store);
    let m = *input.iter().max().unwrap() as f64;
    let process = |pipe: &str, name: &str, backend: &str| -> String {
        let o = ok(run(&[
            "process",
            s(&store),
            pipe,
            "--out",
            name,
            "--backend",
            backend,
            "--json",
        ]));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let g = Filter::Gauss([1.5; 3]);
    let cases = [
        ("gauss(1.5)|sobel", "s", {
            let s = Filter::Sobel;
            s.gain() * g.device_tolerance(m) + s.device_tolerance(m)
        }),
        (
            "gradmag(1)",
            "gm",
            Filter::GradMag([1.0; 3]).device_tolerance(m),
        ),
        ("gauss(2)", "g", Filter::Gauss([2.0; 3]).device_tolerance(m)),
    ];
    for (pipe, name, tol) in cases {
        let cpu = process(pipe, &format!("{name}-cpu"), "cpu");
        assert!(cpu.contains("\"device\":null"), "{cpu}");
        let gpu = process(pipe, &format!("{name}-gpu"), "gpu");
        assert!(!gpu.contains("\"device\":null"), "{gpu}");
        for level in 0..2 {
            let want = read_level::<f32>(&store.join(format!("derived/{name}-cpu")), level);
            let got = read_level::<f32>(&store.join(format!("derived/{name}-gpu")), level);
            assert_eq!(got.len(), want.len());
            let worst = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs() as f64)
                .fold(0.0, f64::max);
            let big = want.iter().fold(0.0f64, |a, v| a.max(v.abs() as f64));
            assert!(
                worst <= tol,
                "{pipe}, level {level}: device and CPU differ by {worst} (tolerance {tol})"
            );
            assert!(
                big > 100.0 * tol,
                "{pipe}: largest value {big}, tolerance {tol}"
            );
        }
    }
    // A threshold near the middle of the smoothed values.
    let smooth = read_level::<f32>(&store.join("derived/g-cpu"), 0);
    let mut sorted = smooth.clone();
    sorted.sort_by(f32::total_cmp);
    let t = (sorted[sorted.len() / 2] as f64).round() + 0.5;
    let pipe = format!("gauss(2)|threshold({t})");
    process(&pipe, "t-cpu", "cpu");
    process(&pipe, "t-gpu", "gpu");
    let want = read_level::<u8>(&store.join("labels/t-cpu"), 0);
    let got = read_level::<u8>(&store.join("labels/t-gpu"), 0);
    let tol = Filter::Gauss([2.0; 3]).device_tolerance(m);
    for i in 0..want.len() {
        assert!(
            got[i] == want[i] || (smooth[i] as f64 - t).abs() <= tol,
            "voxel {i}: masks differ at {} (threshold {t}, tolerance {tol})",
            smooth[i]
        );
    }
    let ones = want.iter().filter(|&&v| v == 1).count();
    assert!(
        ones > want.len() / 4 && ones < want.len() * 3 / 4,
        "{ones} set"
    );
    // A bad back end is refused before anything is written.
    let o = run(&[
        "process",
        s(&store),
        "gauss(1)",
        "--out",
        "x",
        "--backend",
        "tpu",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("expected cpu, gpu or auto"));
    assert!(!store.join("derived/x").exists());
}

/// scipy's `gaussian_filter(v, σ, mode="nearest", truncate=4)` written out
/// here: one 1D pass per axis over the whole kernel, clamped indices.
fn gauss_nearest_ref(v: &[f64], d: Dims3, sigma: f64) -> Vec<f64> {
    let r = (4.0 * sigma + 0.5) as i64;
    let phi: Vec<f64> = (-r..=r)
        .map(|m| (-((m * m) as f64) / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f64 = phi.iter().sum();
    let w: Vec<f64> = phi.iter().map(|p| p / sum).collect();
    let d = d.map(|v| v as i64);
    let mut cur = v.to_vec();
    for axis in 0..3 {
        let mut next = vec![0.0; cur.len()];
        for z in 0..d[0] {
            for y in 0..d[1] {
                for x in 0..d[2] {
                    let p = [z, y, x];
                    let mut s = 0.0;
                    for (k, wk) in w.iter().enumerate() {
                        let mut q = p;
                        q[axis] = (p[axis] + k as i64 - r).clamp(0, d[axis] - 1);
                        s += wk * cur[((q[0] * d[1] + q[1]) * d[2] + q[2]) as usize];
                    }
                    next[((z * d[1] + y) * d[2] + x) as usize] = s;
                }
            }
        }
        cur = next;
    }
    cur
}

/// A --memory too small is refused with the least --memory that works:
/// with it the job runs, with 1 MiB less it is refused again, and every
/// smaller budget asks for the same. (The message used to quote the
/// filters' own minimum, half of the --memory they need since they get at
/// most half of it; at budgets where the filters fit but the pyramid
/// writer did not, the writer's refusal named the result's temporary
/// folder, `.small.new`.)
#[test]
fn a_refusal_for_memory_asks_for_the_least_that_works() {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("b.ome.zarr");
    ok(run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "128",
        "--quiet",
    ]));
    for (pipe, out) in [
        ("gauss(2)", "small"),
        ("threshold(50)|label(26)", "small-labels"),
        ("sobel", "small"),
    ] {
        let job = |memory: u64| {
            run(&[
                "process",
                s(&store),
                pipe,
                "--out",
                out,
                "--memory",
                &format!("{memory}MiB"),
                "--quiet",
                "--overwrite",
            ])
        };
        // The --memory a refusal asks for.
        let refused = |memory: u64| -> u64 {
            let o = job(memory);
            let e = String::from_utf8_lossy(&o.stderr).into_owned();
            assert_eq!(o.status.code(), Some(1), "{pipe} in {memory} MiB: {e}");
            assert!(!e.contains("panicked"), "{e}");
            assert!(
                !e.contains(".new") && !e.contains(".partial"),
                "{pipe} in {memory} MiB: a temporary path: {e}"
            );
            assert!(
                e.contains(&format!("--memory: {memory}.0 MiB is too small")),
                "{e}"
            );
            e.split("give --memory ")
                .nth(1)
                .and_then(|t| t.split("MiB or more").next())
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("{pipe} in {memory} MiB: no --memory asked for: {e}"))
        };
        let need = refused(1);
        // Below a MiB too: the same figure at once (it said "expected at
        // least 1 MiB", and the figure only on a second try).
        let o = run(&[
            "process",
            s(&store),
            pipe,
            "--out",
            out,
            "--memory",
            "1KiB",
            "--quiet",
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(
            e.contains("1.0 KiB is too small")
                && e.contains(&format!("give --memory {need}MiB or more")),
            "{pipe}: {e}"
        );
        for m in [need / 2, need / 2 + 1, need * 3 / 4, need - 1] {
            assert_eq!(refused(m), need, "{pipe} in {m} MiB");
        }
        ok(job(need));
        ok(job(need + need / 3));
    }
}

#[test]
fn a_sigma_wider_than_the_volume_is_computed_and_an_impossible_one_refused() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "20");
    // σ 40: a kernel of radius 160, eight times the volume.
    ok(run(&[
        "process",
        s(&store),
        "gauss(40)",
        "--out",
        "wide",
        "--memory",
        "256MiB",
        "--quiet",
    ]));
    let (got, dims) = read_level0::<f32>(&store.join("derived/wide"));
    let (v, vd) = read_level0::<u16>(&store);
    assert_eq!(dims, vd);
    let v: Vec<f64> = v.iter().map(|&x| x as f64).collect();
    let want = gauss_nearest_ref(&v, vd, 40.0);
    let scale = want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(
            (*g as f64 - w).abs() <= 1e-6 * scale,
            "voxel {i}: {g} vs {w}"
        );
    }
    // σ whose kernel cannot be summed, and a budget that cannot hold one
    // block with its halo: errors naming the stage, nothing written.
    for (pipe, memory, want) in [
        ("gauss(1e9)", "256MiB", "1048576"),
        ("gauss(1)|gradmag(1e7)", "256MiB", "gradmag(10000000)"),
        ("gauss(8)", "2MiB", "memory"),
    ] {
        let o = run(&[
            "process",
            s(&store),
            pipe,
            "--out",
            "big",
            "--memory",
            memory,
            "--quiet",
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{pipe}: {e}");
        assert!(!e.contains("panicked"), "{pipe}: {e}");
        assert!(e.contains(want), "{pipe}: {e:?} should mention {want:?}");
        let left: Vec<_> = std::fs::read_dir(store.join("derived"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains("big"))
            .collect();
        assert!(left.is_empty(), "{pipe}: left {left:?}");
    }
    // The live derived channel refuses the same σ.
    let o = run(&[
        "render",
        s(&store),
        "--backend",
        "cpu",
        "--size",
        "32",
        "--derive",
        "gauss(1e9)",
        "--out",
        s(&d.path().join("x.png")),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && !e.contains("panicked"), "{e}");
    assert!(e.contains("1048576"), "{e}");
}

/// `render --derive` holds its filters to a quarter of --memory, for the
/// loader threads' brick reads at once: a Gaussian whose block with its
/// halo (the whole 128³ volume per brick read here) does not fit is
/// refused before any work, naming the stage and --memory; one loader
/// thread, or more memory, fits.
#[test]
fn a_live_derived_channel_is_held_to_its_share_of_memory() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "128");
    let png = d.path().join("x.png");
    let render = |extra: &[&str]| {
        let mut a = vec![
            "render",
            s(&store),
            "--backend",
            "cpu",
            "--size",
            "32",
            "--level",
            "3",
            "--window",
            "0,40000",
            "--max-frames",
            "1",
            "--derive",
            "gauss(40)",
            "--out",
            s(&png),
        ];
        a.extend_from_slice(extra);
        run(&a)
    };
    // About 38 MiB a read: two reads at once exceed 64 MiB.
    let o = render(&["--memory", "256MiB"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(!e.contains("panicked"), "{e}");
    for want in ["gauss(40)", "--memory", "loader"] {
        assert!(e.contains(want), "{e:?} should mention {want:?}");
    }
    assert!(!png.exists(), "an image after a refused run");
    // The least --memory it names runs; a MiB less is refused.
    let least = e
        .split("--memory ")
        .find_map(|t| t.strip_prefix(|c: char| c.is_ascii_digit()).map(|_| t))
        .and_then(|t| t.split("MiB runs it").next())
        .and_then(|n| n.parse::<u64>().ok())
        .unwrap_or_else(|| panic!("no least --memory in {e:?}"));
    assert!(least > 256, "{e}");
    let below = format!("{}MiB", least - 1);
    let o = render(&["--memory", &below]);
    assert_eq!(o.status.code(), Some(1), "{below}");
    assert!(!png.exists(), "an image at {below}");
    let least = format!("{least}MiB");
    for extra in [
        &["--memory", "256MiB", "--loader-threads", "1"][..],
        &["--memory", &least][..],
        &["--memory", "1GiB"][..],
    ] {
        ok(render(extra));
        assert!(png.exists(), "{extra:?}: no image");
        std::fs::remove_file(&png).unwrap();
    }
}

#[test]
fn an_interrupted_conversion_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "20");
    // What a crash leaves: the partial folder, whose root says incomplete.
    let partial = d.path().join("v.zarr.partial");
    std::fs::rename(&store, &partial).unwrap();
    let root = partial.join("zarr.json");
    let text = std::fs::read_to_string(&root).unwrap();
    assert!(text.contains("\"complete\": true"), "{text}");
    std::fs::write(
        &root,
        text.replace("\"complete\": true", "\"complete\": false"),
    )
    .unwrap();
    let before = snapshot(&partial);
    let converted = d.path().join("again.ome.zarr");
    for args in [
        vec!["process", s(&partial), "threshold(10)", "--out", "m"],
        // (A conversion from it would write its lost chunks as zeros into
        // a store marked complete.)
        vec!["convert", s(&partial), s(&converted)],
        vec![
            "render",
            s(&partial),
            "--backend",
            "cpu",
            "--size",
            "32",
            "--derive",
            "gauss(1)",
            "--out",
            s(&d.path().join("x.png")),
        ],
    ] {
        let o = run(&args);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {e}");
        assert!(e.contains("the store is incomplete: "), "{args:?}: {e}");
    }
    assert_eq!(snapshot(&partial), before, "the store was changed");
    assert!(!partial.join("labels").exists(), "labels were written");
    assert!(!converted.exists(), "a store was converted from it");
}

/// `args` exits with status 1 and its stderr holds each of `words`.
#[track_caller]
fn fails_naming(args: &[&str], words: &[&str]) {
    let o = run(args);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{args:?}: {e}");
    for w in words {
        assert!(e.contains(w), "{args:?}: {e} should mention {w:?}");
    }
}

/// `convert --overwrite` of a store with a job at work inside it (its
/// lock held by a live process) is refused, naming the lock, and leaves the
/// store as it was (it used to replace the store from under the job); a
/// lock whose process is gone does not hold it up. `info` lists such a
/// lock, a replaced store left beside as STORE.old, and, for a STORE that
/// is missing, the STORE.partial of an interrupted conversion.
#[test]
fn a_store_with_a_job_at_work_inside_is_not_replaced_and_leftovers_are_listed() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "24");
    let other = d.path().join("w.zarr");
    ok(run(&[
        "generate",
        "mandelbulb",
        s(&other),
        "--size",
        "16",
        "--quiet",
    ]));
    std::fs::create_dir_all(store.join("labels")).unwrap();
    let lock = store.join("labels/.cells.lock");
    // A live job: this test's own process holds the lock.
    std::fs::write(&lock, format!("{}\n", std::process::id())).unwrap();
    // The job's staging folder: at work, not a leftover.
    std::fs::create_dir_all(store.join("labels/.cells.new.partial")).unwrap();
    let info = || {
        let o = run(&["info", s(&store)]);
        String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr)
    };
    let text = info();
    assert!(!text.contains(".cells.new.partial"), "{text}");
    let before = snapshot(&store);
    let replace = ["convert", s(&other), s(&store), "--overwrite", "--quiet"];
    fails_naming(&replace, &[".cells.lock", "job is writing inside it"]);
    assert_eq!(snapshot(&store), before, "the store changed");
    // The lock of a job that is gone: listed by `info` with its folder,
    // no obstacle.
    std::fs::write(&lock, "4194305\n").unwrap();
    let text = info();
    assert!(
        text.contains("labels/.cells.lock") && text.contains("interrupted"),
        "{text}"
    );
    assert!(text.contains("labels/.cells.new.partial"), "{text}");
    // A conversion into the store killed: its partial output and lock
    // beside it.
    let partial = d.path().join("v.zarr.partial");
    let store_lock = d.path().join("v.zarr.lock");
    std::fs::create_dir_all(&partial).unwrap();
    std::fs::write(&store_lock, "4194305\n").unwrap();
    let text = info();
    assert!(
        text.contains("v.zarr.partial") && text.contains("v.zarr.lock"),
        "{text}"
    );
    std::fs::remove_dir_all(&partial).unwrap();
    std::fs::remove_file(&store_lock).unwrap();
    ok(run(&replace));
    assert!(!lock.exists());
    // A replaced store left beside it.
    let old = d.path().join("v.zarr.old");
    let o8 = d.path().join("o.zarr");
    ok(run(&[
        "generate",
        "mandelbulb",
        s(&o8),
        "--size",
        "8",
        "--quiet",
    ]));
    std::fs::rename(&o8, &old).unwrap();
    let o = run(&["info", s(&store)]);
    let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    assert!(
        text.contains("v.zarr.old") && text.contains("replaced"),
        "{text}"
    );
    // Only the partial output of an interrupted conversion.
    std::fs::remove_dir_all(&old).unwrap();
    std::fs::rename(&store, d.path().join("v.zarr.partial")).unwrap();
    fails_naming(
        &["info", s(&store)],
        &["v.zarr.partial", "interrupted conversion"],
    );
}

#[test]
fn a_store_that_lost_a_shard_fails_process_and_convert_with_the_file_named() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "40");
    // One shard of level 0 lost (the Marschner-Lobb signal has data in
    // every brick).
    let shard = store.join("0/c/0/0/0");
    assert!(shard.is_file());
    std::fs::remove_file(&shard).unwrap();
    let before = snapshot(&store);
    let converted = d.path().join("again.ome.zarr");
    for args in [
        vec![
            "process",
            s(&store),
            "threshold(0.3)|label(6)",
            "--out",
            "m",
        ],
        vec!["process", s(&store), "gauss(1)", "--out", "g"],
        vec!["convert", s(&store), s(&converted)],
    ] {
        fails_naming(
            &args,
            &["0/c/0/0/0", "the file is missing, but the statistics say"],
        );
    }
    assert_eq!(snapshot(&store), before, "the store was changed");
    assert!(!converted.exists(), "a store was converted from it");
    assert!(
        !store.join("labels/m").exists() && !store.join("derived/g").exists(),
        "a result was written"
    );
    // The same store whole converts and processes (the check does not
    // fail sound stores).
    std::fs::create_dir(d.path().join("w")).unwrap();
    let whole = make_store(&d.path().join("w"), "40");
    ok(run(&["convert", s(&whole), s(&converted), "--quiet"]));
    ok(run(&[
        "process",
        s(&whole),
        "threshold(0.3)|label(6)",
        "--out",
        "m",
        "--quiet",
    ]));
}

/// A 32³ f32 store in 8³ chunks and 16³ shards (`compression`) whose first
/// shard file `damage` changes: `process` and `convert` from it fail naming
/// the file and `words`, and leave no result.
fn fails_on_a_damaged_shard(compression: &str, damage: impl Fn(&mut Vec<u8>), words: &[&str]) {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("f.ome.zarr");
    ok(run(&[
        "generate",
        "marschner-lobb",
        s(&store),
        "--size",
        "32",
        "--dtype",
        "f32",
        "--brick",
        "8",
        "--shard",
        "16",
        "--compression",
        compression,
        "--quiet",
    ]));
    let shard = store.join("0/c/0/0/0");
    let mut b = std::fs::read(&shard).unwrap();
    damage(&mut b);
    std::fs::write(&shard, &b).unwrap();
    let converted = d.path().join("again.ome.zarr");
    for args in [
        vec!["process", s(&store), "gauss(1)", "--out", "g"],
        vec!["convert", s(&store), s(&converted)],
    ] {
        fails_naming(&args, &[&["0/c/0/0/0"], words].concat());
    }
    assert!(!converted.exists());
    assert!(!store.join("derived/g").exists());
}

/// A chunk whose bytes changed in place still decodes (no codec here
/// carries a checksum; uncompressed chunks decode whatever they hold) to
/// values its statistics exclude: `process` and `convert` fail naming the
/// file, where they used to compute from them (a user trial's flipped
/// bytes gave 9496 labels instead of 9494, exit 0).
#[test]
fn a_chunk_whose_bytes_changed_fails_process_and_convert() {
    // The first chunk (8³ f32, uncompressed, at the start of the shard):
    // 3.4e38 in a row of it.
    fails_on_a_damaged_shard("none", |b| b[..64].fill(0x7f), &["the statistics say"]);
}

/// A chunk that cannot be decoded (its compressed bytes overwritten) fails
/// `convert` and `process` naming the shard file and the chunk (`convert`
/// named only the store).
#[test]
fn an_undecodable_chunk_is_named_by_convert_and_process() {
    // The shard's chunks, not its index (at the end): garbage.
    fails_on_a_damaged_shard(
        "lz4",
        |b| {
            let n = b.len() - 300;
            b[..n].fill(0x5a)
        },
        &["chunk at [0, 0, 0]", "blosc"],
    );
}

/// The nuclei stack converted (z 4× coarser than x and y) and its nuclei
/// labelled by `process` into `labels/cells`.
fn nuclei_with_labels(dir: &Path) -> std::path::PathBuf {
    let tif =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/nuclei-confocal-u16.tif");
    assert!(
        tif.exists(),
        "{} is missing: this test needs the shared data folder",
        tif.display()
    );
    let store = dir.join("nuclei.ome.zarr");
    ok(run(&[
        "convert",
        s(&tif),
        s(&store),
        "--spacing",
        "0.5,0.5,2",
        "--quiet",
    ]));
    ok(run(&[
        "process",
        s(&store),
        "gauss(1)|threshold(12000)|label(26)",
        "--out",
        "cells",
        "--quiet",
    ]));
    store
}

#[test]
fn labels_are_drawn_in_their_colours_alone_and_over_the_image() {
    use brickyard_render::optics::label_color;
    let d = tempfile::tempdir().unwrap();
    let store = nuclei_with_labels(d.path());
    let cells = store.join("labels").join("cells");
    let render = |src: &Path, extra: &[&str], out: &str| {
        let out = d.path().join(out);
        let mut a = vec![
            "render",
            s(src),
            "--mode",
            "slice",
            "--slice-z",
            "0.45",
            "--level",
            "0",
            "--size",
            "128",
            "--quiet",
            "--out",
            s(&out),
        ];
        a.extend(extra);
        ok(run(&a));
        png_rgba(&out)
    };
    // The label image alone: its slices take label colours without being
    // asked (the group says `image-label`). Every pixel is black (label 0)
    // or, within rounding, the colour of a label the image holds.
    let ids: std::collections::BTreeSet<u32> = read_level0::<u32>(&cells).0.into_iter().collect();
    assert!(ids.len() > 20, "{} labels", ids.len());
    let colours: Vec<[u8; 3]> = ids
        .iter()
        .filter(|&&i| i != 0)
        .map(|&i| {
            let c = label_color(Some(i as f32));
            [0, 1, 2].map(|k| (c[k] * 255.0).round() as u8)
        })
        .collect();
    let lab = render(&cells, &[], "labels.png");
    let mut shown = std::collections::BTreeSet::new();
    for p in lab.chunks(4) {
        assert_eq!(p[3], 255);
        if p[..3] == [0, 0, 0] {
            continue;
        }
        let k = colours
            .iter()
            .position(|c| (0..3).all(|i| c[i].abs_diff(p[i]) <= 1))
            .unwrap_or_else(|| panic!("{p:?} is the colour of no label"));
        shown.insert(k);
    }
    let lit = lab.chunks(4).filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(
        shown.len() >= 10 && lit > 128 * 128 / 10,
        "{} labels, {lit} pixels",
        shown.len()
    );
    // `--tf labels` is the same; a grey ramp through the ids is not.
    assert_eq!(render(&cells, &["--tf", "labels"], "labels-tf.png"), lab);
    assert_ne!(
        render(&cells, &["--tf", "linear"], "labels-linear.png"),
        lab
    );
    // In 3D (the default mode, dvr) the labels' surfaces: each lit pixel a
    // label's colour shaded (by a quarter to all of it).
    let d3 = |extra: &[&str], out: &str| {
        let out = d.path().join(out);
        let mut a = vec![
            "render",
            s(&cells),
            "--size",
            "96",
            "--quiet",
            "--out",
            s(&out),
        ];
        a.extend(extra);
        ok(run(&a));
        png_rgba(&out)
    };
    let surf = d3(&[], "surfaces.png");
    assert_eq!(d3(&["--tf", "labels"], "surfaces-tf.png"), surf);
    let mut lit = 0;
    for p in surf.chunks(4).filter(|p| p[..3] != [0, 0, 0]) {
        lit += 1;
        let fits = colours.iter().any(|c| {
            let k = p[..3].iter().copied().max().unwrap() as f32
                / c.iter().copied().max().unwrap() as f32;
            (0.24..=1.01).contains(&k)
                && (0..3).all(|i| (c[i] as f32 * k - p[i] as f32).abs() <= 2.0)
        });
        assert!(fits, "{p:?} is no label's colour, shaded");
    }
    assert!(lit > 96 * 96 / 10, "{lit} pixels of label surfaces");
    // Over the image: at opacity 1 the labels replace the image where they
    // are and leave it alone elsewhere; at 0.5 they meet halfway.
    let grey = ["--tf", "linear", "--window", "0,40000"];
    let plain = render(&store, &grey, "plain.png");
    let lit_plain = plain.chunks(4).filter(|p| p[0] > 8).count();
    assert!(
        lit_plain > 128 * 128 / 4,
        "{lit_plain} pixels of the image lit"
    );
    let mut args = grey.to_vec();
    args.extend(["--labels", "cells", "--label-opacity", "1"]);
    let full = render(&store, &args, "over-1.png");
    args.pop();
    args.push("0.5");
    let half = render(&store, &args, "over-half.png");
    let default = render(&store, &args[..args.len() - 2], "over-default.png");
    assert_eq!(default, half, "the default opacity is 0.5");
    for (i, ((p, l), (f, h))) in plain
        .chunks(4)
        .zip(lab.chunks(4))
        .zip(full.chunks(4).zip(half.chunks(4)))
        .enumerate()
    {
        let labelled = l[..3] != [0, 0, 0];
        assert_eq!(f, if labelled { l } else { p }, "pixel {i} at opacity 1");
        for k in 0..3 {
            let want = if labelled {
                (p[k] as f32 + l[k] as f32) / 2.0
            } else {
                p[k] as f32
            };
            assert!(
                (h[k] as f32 - want).abs() <= 1.0,
                "pixel {i} at 0.5: {h:?}, {p:?} under {l:?}"
            );
        }
    }
}

#[test]
fn bad_label_overlays_give_clear_errors() {
    let d = tempfile::tempdir().unwrap();
    let store = nuclei_with_labels(d.path());
    let fails = |extra: &[&str], want: &[&str]| {
        let mut a = vec!["render", s(&store), "--mode", "slice", "--quiet", "--out"];
        let out = d.path().join("x.png");
        a.push(s(&out));
        a.extend(extra);
        let o = run(&a);
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert!(!o.status.success(), "{extra:?} succeeded");
        for w in want {
            assert!(err.contains(w), "{extra:?}: {err:?} lacks {w:?}");
        }
        assert!(!out.exists(), "{extra:?} wrote an image");
    };
    fails(
        &["--labels", "nuclei"],
        &["no label image \"nuclei\"", "it has cells"],
    );
    fails(&["--labels", "../cells"], &["expected the name"]);
    fails(
        &["--labels", "cells", "--label-opacity", "0"],
        &["label-opacity", "above 0"],
    );
    fails(
        &["--labels", "cells", "--label-opacity", "1.5"],
        &["label-opacity", "at most 1"],
    );
    fails(&["--label-opacity", "0.3"], &["applies with --labels"]);
    fails(
        &["--labels", "cells", "--only-labels", "4294967295"],
        &["only-labels", "labels from -16777216 to 16777216 (2^24)"],
    );
    // A selection of the labels is refused before the image under them
    // is drawn (it used to be checked once the image was done).
    let out = d.path().join("x.png");
    let o = run(&[
        "render",
        s(&store),
        "--mode",
        "slice",
        "--out",
        s(&out),
        "--labels",
        "cells",
        "--only-labels",
        "5-3",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && !out.exists());
    assert!(
        err.contains("only-labels: the range \"5-3\" runs backwards") && !err.contains("view 0"),
        "{err}"
    );
    fails(
        &["--labels", "cells", "--tf", "labels"],
        &["--tf labels draws a label image alone"],
    );
    fails(
        &["--labels", "cells", "--turntable", "4"],
        &["one view at a time"],
    );
    // Labels named that the image does not hold are said to be missing
    // (a selection of only those drew nothing, silently).
    let drawn = d.path().join("some.png");
    let o = run(&[
        "render",
        s(&store),
        "--mode",
        "slice",
        "--size",
        "32",
        "--out",
        s(&drawn),
        "--labels",
        "cells",
        "--only-labels",
        "1,2000000",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("1 of the 2 label(s) named is not in"), "{err}");
    // Only those: nothing would be drawn, an error (it wrote an image of
    // no label and exited 0).
    let none = d.path().join("none.png");
    for ids in ["2000000", "2000000-2000002"] {
        let o = run(&[
            "render",
            s(&store),
            "--mode",
            "slice",
            "--size",
            "32",
            "--out",
            s(&none),
            "--labels",
            "cells",
            "--only-labels",
            ids,
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && !none.exists(), "{ids}: {err}");
        assert!(
            err.contains("only-labels: ") && err.contains("nothing would be drawn"),
            "{ids}: {err}"
        );
    }
    // Label colours are for slices and 3D views, drawn whole each frame.
    let cells = store.join("labels/cells");
    for (extra, want) in [
        (
            &["--mode", "mip"][..],
            "--mode mip draws a label image's values",
        ),
        (&["--progressive", "8"][..], "no --progressive"),
        (&["--traversal", "octree"][..], "through the page tables"),
    ] {
        let mut a = vec!["render", s(&cells), "--tf", "labels", "--out"];
        let out = d.path().join("y.png");
        a.push(s(&out));
        a.extend(extra);
        let o = run(&a);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains(want),
            "{extra:?}: {err}"
        );
        assert!(!out.exists());
    }
    // A label image on another grid: the nuclei labels of the shared data
    // converted with a spacing of 1 in every axis (the TIFF has none: on
    // the image's grid it would take the image's), listed.
    let tif =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/nuclei-labels-u32.tif");
    // `convert --labels` into the store's labels group lists the image and
    // marks it as the store's (it used to be written unlisted).
    let other = store.join("labels").join("truth");
    ok(run(&[
        "convert",
        s(&tif),
        s(&other),
        "--labels",
        "--quiet",
        "--spacing",
        "1,1,1",
    ]));
    let list = store.join("labels").join("zarr.json");
    let j: serde_json::Value = serde_json::from_slice(&std::fs::read(&list).unwrap()).unwrap();
    let names = j["attributes"]["ome"]["labels"].as_array().unwrap();
    assert_eq!(
        names.iter().filter(|n| *n == "truth").count(),
        1,
        "{names:?}"
    );
    let m: serde_json::Value =
        serde_json::from_slice(&std::fs::read(other.join("zarr.json")).unwrap()).unwrap();
    assert_eq!(
        m["attributes"]["ome"]["image-label"]["source"]["image"],
        "../../"
    );
    fails(
        &["--labels", "truth"],
        &[
            "labels/truth",
            "[2.0, 0.5, 0.5]",
            "label images are drawn over the grid",
        ],
    );
    // With the image's spacing it is drawn.
    ok(run(&[
        "convert",
        s(&tif),
        s(&other),
        "--labels",
        "--spacing",
        "0.5,0.5,2",
        "--overwrite",
        "--quiet",
    ]));
    let out = d.path().join("truth.png");
    ok(run(&[
        "render",
        s(&store),
        "--mode",
        "slice",
        "--labels",
        "truth",
        "--quiet",
        "--out",
        s(&out),
    ]));
}

/// Labelling a noisy mask (a component per few voxels) within a small
/// `--memory`: the bookkeeping of its pieces would exceed the budget, so
/// the job stops with an error that says so and how much it would take,
/// instead of growing past it (a user trial's 128 MiB job peaked at
/// 2.6 GiB); the same job with room enough labels the volume.
#[test]
fn labelling_a_noisy_mask_keeps_to_the_memory_budget_or_says_why_not() {
    let d = tempfile::tempdir().unwrap();
    let raw = d.path().join("noise.raw");
    let n = 160usize;
    let mut seed = 7u64;
    let v: Vec<u8> = (0..n * n * n)
        .map(|_| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 56) as u8
        })
        .collect();
    std::fs::write(&raw, v).unwrap();
    let store = d.path().join("noise.ome.zarr");
    ok(run(&[
        "convert",
        s(&raw),
        s(&store),
        "--dims",
        "160x160x160",
        "--dtype",
        "u8",
        "--quiet",
    ]));
    let o = run(&[
        "process",
        s(&store),
        "threshold(200)|label(6)",
        "--out",
        "n",
        "--memory",
        "96MiB",
        "--quiet",
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(
        e.contains("pieces of components") && e.contains("memory budget"),
        "{e}"
    );
    // A threshold above every value: no labels, and a note saying why.
    let o = run(&[
        "process",
        s(&store),
        "threshold(255)|label(6)",
        "--out",
        "none",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("no voxel is in the mask"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(!store.join("labels/n").exists());
    // A mask alone, empty: the same note (a mask with voxels in it gets
    // none).
    for (pipe, empty) in [("threshold(255)", true), ("threshold(0)", false)] {
        let o = run(&[
            "process",
            s(&store),
            pipe,
            "--out",
            "m",
            "--overwrite",
            "--quiet",
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{pipe}: {e}");
        assert_eq!(e.contains("no voxel is in the mask"), empty, "{pipe}: {e}");
    }
    let o = run(&[
        "process",
        s(&store),
        "threshold(200)|label(6)",
        "--out",
        "n",
        "--memory",
        "1GiB",
        "--quiet",
    ]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains(" labels)"), "{out}");
}

/// A statistics file whose folder takes no new file (read-only even to
/// root: /sys, /proc) is refused before any work, naming it, and leaves
/// nothing in the store (it was found only after the whole computation,
/// leaving `labels/.NAME.new` behind).
#[test]
fn a_statistics_folder_that_takes_no_file_is_refused_before_any_work() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "20");
    let before = snapshot(&store);
    let mut tried = 0;
    for dir in ["/sys", "/proc", "/proc/self"] {
        if !Path::new(dir).is_dir() {
            continue;
        }
        tried += 1;
        let stats = format!("{dir}/cells.csv");
        let o = run(&[
            "process",
            s(&store),
            "threshold(1)|label(6)",
            "--out",
            "cells",
            "--stats",
            &stats,
            "--quiet",
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{stats}: {e}");
        assert!(!e.contains("panicked"), "{e}");
        for want in ["--stats", &stats, "cannot create a file in its folder"] {
            assert!(e.contains(want), "{e} should mention {want:?}");
        }
        // Before any work: no note about the mask, nothing written.
        assert!(!e.contains("mask"), "the work was done first: {e}");
        assert_eq!(snapshot(&store), before, "{stats}: the store changed");
        assert!(!store.join("labels").exists(), "{stats}");
    }
    assert!(tried > 0, "no /sys or /proc to test with");
}

/// A label image made from a coarser level lies off the image's grid, so
/// `render --labels` cannot lay it over the image: the report says so at
/// once (it said nothing, and the overlay failed later).
#[test]
fn labels_of_a_coarser_level_are_said_to_lie_off_the_image_grid() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "48");
    let o = run(&[
        "process",
        s(&store),
        "threshold(100)|label(6)",
        "--level",
        "1",
        "--out",
        "coarse",
    ]);
    let all = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "{all}");
    assert!(all.contains("lies on level 1's grid"), "{all}");
    let o = run(&[
        "process",
        s(&store),
        "threshold(100)|label(6)",
        "--out",
        "fine",
    ]);
    let all = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "{all}");
    assert!(!all.contains("grid"), "{all}");
}

/// One name, one result: a label image named as a derived result already
/// there (or the other way round) is refused, with or without
/// --overwrite; both had been written, and `info` listed two results of
/// one name.
#[test]
fn a_result_name_is_taken_once_over_labels_and_derived() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "24");
    ok(run(&[
        "process",
        s(&store),
        "gauss(1)",
        "--out",
        "r",
        "--quiet",
    ]));
    for extra in [&[][..], &["--overwrite"][..]] {
        let mut a = vec![
            "process",
            s(&store),
            "threshold(0.1)",
            "--out",
            "r",
            "--quiet",
        ];
        a.extend_from_slice(extra);
        fails_naming(&a, &["derived/r", "a result of this name", "--out"]);
    }
    assert!(!store.join("labels/r").exists());
    ok(run(&[
        "process",
        s(&store),
        "threshold(0.1)",
        "--out",
        "m",
        "--quiet",
    ]));
    fails_naming(
        &["process", s(&store), "sobel", "--out", "m", "--quiet"],
        &["labels/m", "a label image"],
    );
    assert!(!store.join("derived/m").exists());
}

/// The default window of a live derived channel is read within the
/// filters' share: it read slabs of whole planes through the filters, and
/// a render of a 128³ store with `--memory 80MiB` peaked at 91 MiB.
#[test]
fn a_derived_channels_default_window_stays_within_the_budget() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "128");
    let png = d.path().join("x.png");
    let o = run(&[
        "render",
        s(&store),
        "--backend",
        "cpu",
        "--derive",
        "gauss(2)|sobel",
        "--memory",
        "80MiB",
        "--json",
        "--out",
        s(&png),
    ]);
    let out = String::from_utf8_lossy(&ok(o).stdout).into_owned();
    let v = out
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|v| v["peak_rss_bytes"].is_u64())
        .unwrap_or_else(|| panic!("no summary: {out}"));
    let (peak, budget) = (
        v["peak_rss_bytes"].as_u64().unwrap(),
        v["memory_budget_bytes"].as_u64().unwrap(),
    );
    assert!(peak <= budget, "peak {peak} over {budget}");
}

/// A result asked for while its job is at work, or after the job was
/// killed, is not there: the error says which (it said only "no such file
/// or directory"), for render and info alike.
#[test]
fn a_result_whose_job_was_stopped_or_is_at_work_is_named_so() {
    let d = tempfile::tempdir().unwrap();
    let store = make_store(d.path(), "20");
    let derived = store.join("derived");
    std::fs::create_dir_all(derived.join(".h.new.partial")).unwrap();
    let h = derived.join("h");
    let png = d.path().join("h.png");
    for args in [vec!["render", s(&h), "-o", s(&png)], vec!["info", s(&h)]] {
        let o = run(&args);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {e}");
        assert!(
            e.contains("no such file or directory")
                && e.contains("stopped before it ended")
                && e.contains(".h.new.partial")
                && e.contains("run the same `brickyard process` command again"),
            "{args:?}: {e}"
        );
    }
    // A live job's lock (this test's own process): at work.
    std::fs::write(derived.join(".h.lock"), format!("{}\n", std::process::id())).unwrap();
    let o = run(&["render", s(&h), "-o", s(&png)]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains(&format!(
            "a processing job is writing it now (process {})",
            std::process::id()
        )),
        "{e}"
    );
    // A name nothing was ever written to: the plain message.
    let o = run(&["render", s(&derived.join("other")), "-o", s(&png)]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("no such file or directory") && !e.contains("processing job"),
        "{e}"
    );
    assert!(!png.exists());
}
