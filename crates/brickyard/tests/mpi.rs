//! `mpirun -n N brickyard …` (feature `mpi`): distributed conversion is
//! byte for byte the single-process one, image- and data-parallel renders
//! equal the single-process image, and a rank that fails gives a clear
//! error and no store that looks complete.
//!
//! These run only with the `mpi` feature. Without `mpirun` on the PATH
//! they say so and pass, unless `BRICKYARD_REQUIRE_MPI=1` (CI), where a
//! missing `mpirun` fails them.
#![cfg(feature = "mpi")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_brickyard")
}

/// Whether `mpirun` can be used; a failure when CI asks for MPI.
fn have_mpirun() -> bool {
    let ok = Command::new("mpirun")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var("BRICKYARD_REQUIRE_MPI").as_deref() != Ok("1"),
            "BRICKYARD_REQUIRE_MPI=1 but mpirun cannot be run (install openmpi-bin)"
        );
        eprintln!(
            "mpirun not found: skipping the MPI test (set BRICKYARD_REQUIRE_MPI=1 to fail instead)"
        );
    }
    ok
}

/// `brickyard generate mandelbulb OUT ARGS --quiet`, which must succeed.
fn generate(out: &Path, args: &[&str]) {
    let mut a = vec!["generate", "mandelbulb", s(out)];
    a.extend_from_slice(args);
    a.push("--quiet");
    ok(&run(&a), "generate");
}

/// One `mpirun` at a time: concurrent launchers race for their session
/// directory, and the ranks of one already fill the cores.
static MPIRUN: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// `mpirun --oversubscribe -n N brickyard ARGS` (as root too).
fn mpirun(n: usize, args: &[&str], env: &[(&str, &str)]) -> Output {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let mut c = Command::new("mpirun");
    c.args(["--oversubscribe", "-n", &n.to_string(), bin()])
        .args(args)
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("OMPI_MCA_rmaps_base_oversubscribe", "1")
        // Containers often forbid the cross-memory attach OpenMPI's shared
        // memory transport tries first: copy through the segment instead.
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none");
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

fn run(args: &[&str]) -> Output {
    Command::new(bin()).args(args).output().unwrap()
}

#[track_caller]
fn ok(o: &Output, what: &str) {
    assert!(
        o.status.success(),
        "{what} failed: {}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn shared_data(name: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(name);
    assert!(
        path.exists(),
        "{} is missing: this test needs the shared data folder",
        path.display()
    );
    path
}

/// Every file under `dir`, by relative path, with its bytes.
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

#[track_caller]
fn same_store(a: &Path, b: &Path) {
    let (fa, fb) = (files(a), files(b));
    assert_eq!(
        fa.keys().collect::<Vec<_>>(),
        fb.keys().collect::<Vec<_>>(),
        "{} and {} hold different files",
        a.display(),
        b.display()
    );
    for (k, v) in &fa {
        assert!(
            v == &fb[k],
            "{}: differs between {} and {}",
            k.display(),
            a.display(),
            b.display()
        );
    }
    assert!(fa.len() > 20, "{} files only", fa.len());
}

/// Conversion on 2, 3 and 4 ranks writes the single-process store, byte
/// for byte, for a generated and a real volume; several shard columns per
/// level so that every rank writes shards.
#[test]
fn distributed_conversion_is_byte_identical() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("m.raw");
    generate(&raw, &["--size", "150x130x70", "--dtype", "u16"]);
    let nii = shared_data("mni152-t1-u8.nii.gz");
    for (name, input) in [("gen", raw.as_path()), ("mni", nii.as_path())] {
        let single = dir.path().join(format!("{name}-1.ome.zarr"));
        // --columns 4: passes that 4 ranks can share (the single process
        // plans the same passes).
        let args = [
            "--brick",
            "16",
            "--shard",
            "32",
            "--quiet",
            "--columns",
            "4",
        ];
        let mut a = vec!["convert", s(input), s(&single), "--json"];
        a.extend(args);
        let o = run(&a);
        ok(&o, "single-process convert");
        let one: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        for n in [2usize, 3, 4] {
            let out = dir.path().join(format!("{name}-{n}.ome.zarr"));
            let mut a = vec!["convert", s(input), s(&out), "--json"];
            a.extend(args);
            let o = mpirun(n, &a, &[]);
            ok(&o, &format!("convert on {n} ranks"));
            let stdout = String::from_utf8_lossy(&o.stdout);
            // One report, from rank 0, saying how many ranks shared it.
            assert_eq!(stdout.lines().count(), 1, "{stdout}");
            let j: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
            assert_eq!(j["ranks"], n, "{stdout}");
            // The report is the whole conversion's: counts summed over ranks.
            for k in [
                "bytes_in",
                "bytes_written",
                "bricks",
                "bricks_empty",
                "bricks_constant",
            ] {
                assert_eq!(j[k], one[k], "{k} on {n} ranks");
            }
            same_store(&single, &out);
        }
        // Without --columns: the fewest passes, whose first has one column
        // here; the ranks still write the single-process store, and the
        // report says that the other ranks had nothing to do.
        let plain = dir.path().join(format!("{name}-plain-1.ome.zarr"));
        ok(
            &run(&[
                "convert",
                s(input),
                s(&plain),
                "--brick",
                "16",
                "--shard",
                "32",
                "--quiet",
            ]),
            "single-process convert",
        );
        let out = dir.path().join(format!("{name}-plain-2.ome.zarr"));
        let o = mpirun(
            2,
            &[
                "convert",
                s(input),
                s(&out),
                "--brick",
                "16",
                "--shard",
                "32",
                "--quiet",
                "--json",
            ],
            &[],
        );
        ok(&o, "convert on 2 ranks without --columns");
        let stdout = String::from_utf8_lossy(&o.stdout);
        assert!(
            stdout.contains("1 of 2 ranks had nothing to do"),
            "{stdout}"
        );
        same_store(&plain, &out);
    }
}

/// A rank failing in the middle of a conversion: every rank stops, the
/// exit status is non-zero, the error names the rank and the cause, and
/// nothing at the output looks like a complete store.
#[test]
fn a_failing_rank_leaves_no_complete_store() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("m.raw");
    generate(&raw, &["--size", "150x130x70", "--dtype", "u16"]);
    // An error reported by rank 1 after the first pass (meeting 3): rank 0
    // removes the partial output.
    let out = dir.path().join("e.ome.zarr");
    let o = mpirun(
        3,
        &[
            "convert",
            s(&raw),
            s(&out),
            "--brick",
            "16",
            "--shard",
            "32",
            "--quiet",
        ],
        &[("BRICKYARD_MPI_FAIL", "1:3:error")],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("rank 1: injected failure at meeting point 3"),
        "{err}"
    );
    assert!(!out.exists());
    assert!(!dir.path().join("e.ome.zarr.partial").exists());
    // Rank 2 dies outright mid-job: mpirun ends the job; what is left is
    // the partial output, which says it is incomplete.
    let out = dir.path().join("x.ome.zarr");
    let o = mpirun(
        3,
        &[
            "convert",
            s(&raw),
            s(&out),
            "--brick",
            "16",
            "--shard",
            "32",
            "--quiet",
        ],
        &[("BRICKYARD_MPI_FAIL", "2:3:exit")],
    );
    assert!(!o.status.success());
    assert!(!out.exists());
    let partial = dir.path().join("x.ome.zarr.partial");
    if partial.exists() {
        let root: serde_json::Value =
            serde_json::from_slice(&std::fs::read(partial.join("zarr.json")).unwrap()).unwrap();
        assert_eq!(root["attributes"]["brickyard"]["complete"], false);
        let info = run(&["info", s(&partial)]);
        assert_eq!(info.status.code(), Some(2), "info must call it incomplete");
    }
}

/// The premultiplied RGBA floats `render --raw-f32` wrote beside `png`.
fn floats(png: &Path) -> Vec<f32> {
    std::fs::read(png.with_extension("f32"))
        .unwrap()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

#[track_caller]
fn close(a: &Path, b: &Path, tol: f32, what: &str) {
    let (x, y) = (floats(a), floats(b));
    assert_eq!(x.len(), y.len(), "{what}: image sizes");
    let d = x
        .iter()
        .zip(&y)
        .map(|(p, q)| (p - q).abs())
        .fold(0.0f32, f32::max);
    assert!(d <= tol, "{what}: max abs diff {d} > {tol}");
    // Something was drawn (not two empty images).
    let lit = x.chunks_exact(4).filter(|p| p[3] > 0.05).count();
    assert!(lit > x.len() / 4 / 20, "{what}: {lit} pixels drawn");
}

/// Two stores: a generated Mandelbulb and the MNI152 T1 scan.
fn stores(dir: &Path) -> Vec<PathBuf> {
    let gen = dir.join("gen.ome.zarr");
    generate(
        &gen,
        &[
            "--size",
            "112x96x80",
            "--dtype",
            "u16",
            "--brick",
            "32",
            "--shard",
            "64",
        ],
    );
    let mni = dir.join("mni.ome.zarr");
    let nii = shared_data("mni152-t1-u8.nii.gz");
    ok(
        &run(&[
            "convert",
            s(&nii),
            s(&mni),
            "--brick",
            "32",
            "--shard",
            "64",
            "--quiet",
        ]),
        "convert",
    );
    vec![gen, mni]
}

/// Image-parallel renders on 1 to 4 ranks equal the single-process image
/// within 1e-5, DVR and MIP, for both stores.
#[test]
fn image_parallel_equals_one_process() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    for store in stores(dir.path()) {
        let name = store.file_stem().unwrap().to_string_lossy().into_owned();
        for mode in ["dvr", "mip"] {
            let view = [
                "--size",
                "150x110",
                "--mode",
                mode,
                "--azimuth",
                "40",
                "--quiet",
                "--raw-f32",
            ];
            let one = dir.path().join(format!("{name}-{mode}-1p.png"));
            let mut a = vec!["render", s(&store), "--backend", "cpu", "--out", s(&one)];
            a.extend(view);
            ok(&run(&a), "single-process render");
            for n in 1..=4usize {
                let out = dir.path().join(format!("{name}-{mode}-i{n}.png"));
                let mut a = vec![
                    "render",
                    s(&store),
                    "--distribute",
                    "image",
                    "--out",
                    s(&out),
                ];
                a.extend(view);
                let o = mpirun(n, &a, &[]);
                ok(&o, &format!("{name} {mode} on {n} ranks"));
                // Rank 0 alone reports.
                let stdout = String::from_utf8_lossy(&o.stdout);
                assert_eq!(stdout.matches("wrote ").count(), 1, "{stdout}");
                close(
                    &one,
                    &out,
                    1e-5,
                    &format!("{name} {mode} image-parallel on {n} ranks"),
                );
            }
        }
    }
}

/// Data-parallel (sort-last) renders on 2 to 4 ranks (binary swap on 2
/// and 4, direct send on 3) equal the single-process image within 1e-5:
/// DVR against the image without early ray termination (every sample
/// composited, as the regions do), MIP against the plain one. One rank
/// draws the plain image.
#[test]
fn data_parallel_equals_one_process() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    for store in stores(dir.path()) {
        let name = store.file_stem().unwrap().to_string_lossy().into_owned();
        for mode in ["dvr", "mip"] {
            let view = [
                "--size",
                "150x110",
                "--mode",
                mode,
                "--azimuth=-70",
                "--elevation",
                "35",
                "--quiet",
                "--raw-f32",
            ];
            let plain = dir.path().join(format!("{name}-{mode}-plain.png"));
            let mut a = vec!["render", s(&store), "--backend", "cpu", "--out", s(&plain)];
            a.extend(view);
            ok(&run(&a), "single-process render");
            let all = dir.path().join(format!("{name}-{mode}-all.png"));
            let mut a = vec![
                "render",
                s(&store),
                "--backend",
                "cpu",
                "--no-early-termination",
                "--out",
                s(&all),
            ];
            a.extend(view);
            ok(&run(&a), "single-process render without early termination");
            if mode == "mip" {
                close(&plain, &all, 0.0, "MIP does not terminate early");
            }
            for n in 1..=4usize {
                let out = dir.path().join(format!("{name}-{mode}-d{n}.png"));
                let mut a = vec![
                    "render",
                    s(&store),
                    "--distribute",
                    "data",
                    "--out",
                    s(&out),
                ];
                a.extend(view);
                let o = mpirun(n, &a, &[]);
                ok(&o, &format!("{name} {mode} data-parallel on {n} ranks"));
                let stdout = String::from_utf8_lossy(&o.stdout);
                if n > 1 {
                    let how = if n == 3 { "direct send" } else { "binary swap" };
                    assert!(
                        stdout.contains(&format!("composited {n} ranks ({how})")),
                        "{stdout}"
                    );
                }
                let want = if n == 1 { &plain } else { &all };
                close(
                    want,
                    &out,
                    1e-5,
                    &format!("{name} {mode} data-parallel on {n} ranks"),
                );
            }
        }
    }
}

/// `render STORE --backend cpu --out OUT VIEW… EXTRA…` in one process,
/// which must succeed; returns `out`.
fn one_process(store: &Path, out: &Path, view: &[&str], extra: &[&str]) -> PathBuf {
    let mut a = vec!["render", s(store), "--backend", "cpu", "--out", s(out)];
    a.extend(view);
    a.extend(extra);
    ok(
        &run(&a),
        &format!("single-process render {}", out.display()),
    );
    out.to_path_buf()
}

/// The largest difference between the floats of two renders.
fn max_diff(a: &Path, b: &Path) -> f32 {
    floats(a)
        .iter()
        .zip(floats(b))
        .map(|(p, q)| (p - q).abs())
        .fold(0.0f32, f32::max)
}

/// The most steps a ray takes through level 0 of `store` at one sample
/// per voxel: the diagonal of its grid, in voxels (rounded up).
fn ray_steps(store: &Path) -> u64 {
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(store.join("0/zarr.json")).unwrap()).unwrap();
    let shape: Vec<f64> = meta["shape"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    // (The spatial axes: the last three.)
    let d2: f64 = shape[shape.len() - 3..].iter().map(|v| v * v).sum();
    d2.sqrt().ceil() as u64
}

/// A data-parallel accumulation (`b`) against the single-process one
/// without early termination (`a`), for rays of at most `samples` samples.
///
/// The ranks composite the same samples in the same order, but where a
/// ray is nearly opaque f32 arithmetic does not follow: the opacity `A`
/// of the front-to-back sum `A += (1 − A)·α` stops growing a few units in
/// the last place below 1 once an increment `(1 − A)·α` is under half a
/// unit (2⁻²⁵), while the colour lanes, smaller and so finer-grained, keep
/// taking `(1 − A)·α·c` from every later sample. Past the stall a sample
/// adds up to 2⁻²⁵ that the exact sum would not have, and rounding the
/// colour sum up to half a unit (2⁻²⁵ below 1), so an accumulation is
/// within `samples · 2⁻²⁴` of the exact one; each (the whole ray's, each
/// region's, which starts from 0) stalls at its own sample, so the two
/// images differ by up to `samples · 2⁻²³` in such pixels. Measured:
/// 4.65e-5 (256², colin27 at 0.5 mm, `--progressive 8`, 2 and 4 ranks),
/// where the single-process pixel had stalled at an opacity of 1 − 5.4e-7
/// and the composited one reached 1. Elsewhere (opacity below 0.99) the
/// images agree within 1e-5 (measured there: 3.6e-7).
#[track_caller]
fn close_accumulated(a: &Path, b: &Path, samples: u64, what: &str) {
    let (x, y) = (floats(a), floats(b));
    assert_eq!(x.len(), y.len(), "{what}: image sizes");
    let stalled = samples as f32 * 2f32.powi(-23);
    let (mut d_clear, mut d_opaque) = (0.0f32, 0.0f32);
    for (p, q) in x.chunks_exact(4).zip(y.chunks_exact(4)) {
        let d = (0..4).map(|c| (p[c] - q[c]).abs()).fold(0.0, f32::max);
        match p[3] >= 0.99 {
            true => d_opaque = d_opaque.max(d),
            false => d_clear = d_clear.max(d),
        }
    }
    assert!(d_clear <= 1e-5, "{what}: max abs diff {d_clear} > 1e-5");
    assert!(
        d_opaque <= stalled.max(1e-5),
        "{what}: max abs diff {d_opaque} in opaque pixels > {stalled}"
    );
    let lit = x.chunks_exact(4).filter(|p| p[3] > 0.05).count();
    assert!(lit > x.len() / 4 / 20, "{what}: {lit} pixels drawn");
}

/// Progressive DVR (sample accumulation) shared by ranks: image-parallel
/// bands each accumulate their rows, equal to the single-process
/// accumulation within 1e-5 on 1 to 4 ranks; data-parallel regions each
/// keep and blend their own samples of every ray, composited in
/// visibility order, equal to the single-process accumulation without
/// early termination on 2 to 4 ranks within 1e-5, and in nearly opaque
/// pixels within the bound of f32 rounding of [`close_accumulated`]
/// (frames × steps of the longest ray × 2⁻²³). The accumulated image
/// is not the plain one (the sampling rate shows). Ranks on devices are
/// refused with a clear error.
#[test]
fn progressive_accumulation_equals_one_process() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    for store in stores(dir.path()) {
        let name = store.file_stem().unwrap().to_string_lossy().into_owned();
        let view = [
            "--size",
            "120x90",
            "--azimuth=-70",
            "--elevation",
            "35",
            "--quiet",
            "--raw-f32",
        ];
        let single = |extra: &[&str], tag: &str| {
            one_process(
                &store,
                &dir.path().join(format!("{name}-{tag}.png")),
                &view,
                extra,
            )
        };
        let plain = single(&[], "plain");
        let acc = single(&["--progressive", "4"], "acc");
        let all = single(&["--progressive", "4", "--no-early-termination"], "acc-all");
        let d = max_diff(&plain, &acc);
        assert!(
            d > 1e-3,
            "{name}: accumulation equals the plain frame ({d})"
        );
        for (how, ns, want) in [("image", 1..=4usize, &acc), ("data", 2..=4, &all)] {
            for n in ns {
                let out = dir.path().join(format!("{name}-{how}-p{n}.png"));
                let mut a = vec![
                    "render",
                    s(&store),
                    "--distribute",
                    how,
                    "--progressive",
                    "4",
                    "--out",
                    s(&out),
                ];
                a.extend(view);
                let o = mpirun(n, &a, &[]);
                ok(
                    &o,
                    &format!("{name} progressive {how}-parallel on {n} ranks"),
                );
                let what = format!("{name} progressive {how}-parallel on {n} ranks");
                match how {
                    // Each band's rows are the whole accumulation's.
                    "image" => close(want, &out, 1e-5, &what),
                    _ => close_accumulated(want, &out, 4 * ray_steps(&store), &what),
                }
            }
        }
        let o = mpirun(
            2,
            &[
                "render",
                s(&store),
                "--distribute",
                "data",
                "--progressive",
                "4",
                "--backend",
                "gpu",
                "--quiet",
                "--out",
                s(&dir.path().join("refused.png")),
            ],
            &[],
        );
        assert!(!o.status.success());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("--progressive accumulates on the CPU"),
            "{err}"
        );
    }
}

/// Data-parallel DVR of several channels (the three-channel MNI152: T1,
/// grey and white matter, each through its own transfer function, mixed
/// per sample) on 2 to 4 ranks equals the single-process image without
/// early termination within 1e-5, which differs from the one with it.
/// Device ranks are refused for several channels.
#[test]
fn several_channels_data_parallel_equal_one_process() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("mni3.ome.zarr");
    let files = ["mni152-t1-u8", "mni152-gm-u8", "mni152-wm-u8"]
        .map(|n| shared_data(&format!("{n}.nii.gz")));
    let mut a = vec!["convert"];
    a.extend(files.iter().map(|f| s(f)));
    a.extend([s(&store), "--brick", "32", "--shard", "64", "--quiet"]);
    ok(&run(&a), "convert three channels");
    let view = [
        "--size",
        "150x110",
        "--azimuth=-70",
        "--elevation",
        "35",
        "--quiet",
        "--raw-f32",
    ];
    let single = |extra: &[&str], tag: &str| {
        one_process(&store, &dir.path().join(format!("{tag}.png")), &view, extra)
    };
    let stopped = single(&[], "stopped");
    let all = single(&["--no-early-termination"], "all");
    let d = max_diff(&stopped, &all);
    assert!(d > 1e-3, "early termination must show in this view ({d})");
    for n in 2..=4usize {
        let out = dir.path().join(format!("d{n}.png"));
        let mut a = vec![
            "render",
            s(&store),
            "--distribute",
            "data",
            "--out",
            s(&out),
        ];
        a.extend(view);
        let o = mpirun(n, &a, &[]);
        ok(&o, &format!("three channels data-parallel on {n} ranks"));
        close(
            &all,
            &out,
            1e-5,
            &format!("three channels data-parallel on {n} ranks"),
        );
    }
    let o = mpirun(
        2,
        &[
            "render",
            s(&store),
            "--distribute",
            "data",
            "--backend",
            "gpu",
            "--quiet",
            "--out",
            s(&dir.path().join("refused.png")),
        ],
        &[],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("several channels draw on the CPU"), "{err}");
}

/// A rank failing during a render: every rank stops with a failure
/// status, rank 0 says which rank failed and why, no image is written;
/// a bad --distribute is a clear error.
#[test]
fn a_failing_rank_stops_the_render() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("g.ome.zarr");
    generate(&store, &["--size", "64", "--brick", "32", "--shard", "64"]);
    for split in ["image", "data"] {
        let out = dir.path().join(format!("{split}.png"));
        let o = mpirun(
            3,
            &[
                "render",
                s(&store),
                "--distribute",
                split,
                "--size",
                "64x64",
                "--out",
                s(&out),
                "--quiet",
            ],
            &[("BRICKYARD_MPI_FAIL", "2:1:error")],
        );
        assert!(!o.status.success(), "{split}: expected a failure");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("rank 2: injected failure at meeting point 1"),
            "{split}: {err}"
        );
        assert!(!out.exists(), "{split}: an image was written");
    }
    let o = mpirun(
        2,
        &[
            "render",
            s(&store),
            "--distribute",
            "pixels",
            "--out",
            s(&dir.path().join("x.png")),
        ],
        &[],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("distribute: expected image or data, found \"pixels\""),
        "{err}"
    ); // A MIP of channels mixed by colour draws whole rays: not by regions.
    let o = mpirun(
        2,
        &[
            "render",
            s(&store),
            "--distribute",
            "data",
            "--mode",
            "mip",
            "--channel",
            "0:white",
            "--out",
            s(&dir.path().join("x.png")),
        ],
        &[],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("distribute data: MIP of the first channel through --tf (no --channel)"),
        "{err}"
    );
}

/// A u8 volume 128×48×48 whose low 88 columns (x) are empty, the rest a
/// smooth pattern, converted with bricks of 16: most of the volume's
/// bricks hold nothing.
fn skewed_store(dir: &Path) -> PathBuf {
    let (nx, ny, nz) = (128usize, 48usize, 48usize);
    let mut bytes = vec![0u8; nx * ny * nz];
    for z in 0..nz {
        for y in 0..ny {
            for x in 88..nx {
                let v = ((x as f64 * 0.31).sin()
                    + (y as f64 * 0.43).sin()
                    + (z as f64 * 0.57).sin()
                    + 3.0)
                    / 6.0
                    * 255.0;
                bytes[(z * ny + y) * nx + x] = v as u8;
            }
        }
    }
    let raw = dir.join("skew.raw");
    std::fs::write(&raw, &bytes).unwrap();
    let store = dir.join("skew.ome.zarr");
    ok(
        &run(&[
            "convert",
            s(&raw),
            s(&store),
            "--dims",
            "128x48x48",
            "--dtype",
            "u8",
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

/// The bricks drawn in each rank's region, as rank 0 reports them.
fn data_bricks(stdout: &str) -> Vec<u64> {
    let line = stdout
        .lines()
        .find(|l| l.starts_with("regions of "))
        .unwrap_or_else(|| panic!("no regions line: {stdout}"));
    let list = &line[line.rfind('[').unwrap() + 1..line.rfind(']').unwrap()];
    list.split(", ").map(|x| x.parse().unwrap()).collect()
}

/// Data-parallel regions weighted by the store's statistics share out the
/// bricks drawn (DVR: shown by the transfer function; MIP: holding data)
/// more evenly than regions of equal brick counts, on a volume mostly
/// empty, and the images still equal the single-process one within 1e-5
/// (DVR without early termination, MIP), by either split. Where the
/// transfer function shows the empty space, every brick is drawn and the
/// weighted split is the uniform one.
#[test]
fn data_weights_balance_a_volume_with_empty_space() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = skewed_store(dir.path());
    for mode in ["dvr", "mip"] {
        let view = [
            "--size",
            "160x120",
            "--mode",
            mode,
            "--brick",
            "16",
            "--azimuth=-70",
            "--elevation",
            "35",
            "--quiet",
            "--raw-f32",
        ];
        let all = dir.path().join(format!("{mode}-all.png"));
        let mut a = vec![
            "render",
            s(&store),
            "--backend",
            "cpu",
            "--no-early-termination",
            "--out",
            s(&all),
        ];
        a.extend(view);
        ok(&run(&a), "single-process render");
        for n in [2usize, 3] {
            let mut spread = vec![];
            for weights in ["data", "uniform"] {
                let out = dir.path().join(format!("{mode}-{weights}-{n}.png"));
                let mut a = vec![
                    "render",
                    s(&store),
                    "--distribute",
                    "data",
                    "--region-weights",
                    weights,
                    "--out",
                    s(&out),
                ];
                a.extend(view);
                let o = mpirun(n, &a, &[]);
                ok(&o, &format!("{mode} {weights} on {n} ranks"));
                let stdout = String::from_utf8_lossy(&o.stdout);
                let counts = data_bricks(&stdout);
                assert_eq!(counts.len(), n, "{stdout}");
                spread.push(counts);
                close(
                    &all,
                    &out,
                    1e-5,
                    &format!("{mode} data-parallel, {weights} weights, on {n} ranks"),
                );
            }
            let (by_data, uniform) = (&spread[0], &spread[1]);
            // The same bricks in all, shared out differently.
            assert_eq!(
                by_data.iter().sum::<u64>(),
                uniform.iter().sum::<u64>(),
                "{spread:?}"
            );
            let most = |c: &Vec<u64>| *c.iter().max().unwrap();
            let total: u64 = by_data.iter().sum();
            eprintln!("{mode} on {n} ranks: bricks drawn, split by statistics {by_data:?}, uniform {uniform:?}");
            assert!(
                most(by_data) < most(uniform),
                "{mode} on {n} ranks: the weighted split is not better balanced: {spread:?}"
            );
            // Within a brick slab of an even share.
            assert!(
                most(by_data) as f64 <= total as f64 / n as f64 * 1.5,
                "{mode} on {n} ranks: {by_data:?}"
            );
        }
    }
    // A transfer function that shows every value (empty bricks too): DVR
    // draws every brick, so the weights are those of the uniform split.
    let mut counts = vec![];
    for weights in ["data", "uniform"] {
        let o = mpirun(
            2,
            &[
                "render",
                s(&store),
                "--distribute",
                "data",
                "--region-weights",
                weights,
                "--tf",
                "opaque",
                "--brick",
                "16",
                "--size",
                "64x48",
                "--quiet",
                "--out",
                s(&dir.path().join(format!("opaque-{weights}.png"))),
            ],
            &[],
        );
        ok(&o, "opaque DVR on 2 ranks");
        let stdout = String::from_utf8_lossy(&o.stdout);
        assert!(stdout.contains("ranks drew their parts in "), "{stdout}");
        counts.push(data_bricks(&stdout));
    }
    assert_eq!(counts[0], vec![36, 36], "{counts:?}");
    assert_eq!(counts[0], counts[1]);
}

/// Several devices in one node: with --backend gpu each rank opens a
/// device of its own (on lavapipe, several logical devices of one
/// adapter); image-parallel renders equal the single-process device image
/// within 1e-5 and data-parallel ones the single-process device image
/// without early termination within 1e-5 (the same f32 arithmetic on the
/// same device kind, only the compositing's order differs), DVR and MIP.
/// A --backend gpu where no adapter matches is a clear error.
#[test]
fn device_ranks_equal_one_process() {
    if !have_mpirun() {
        return;
    }
    if brickyard_gpu::context::test_gpu().is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = skewed_store(dir.path());
    for mode in ["dvr", "mip"] {
        let view = [
            "--size",
            "128x96",
            "--mode",
            mode,
            "--brick",
            "16",
            "--azimuth=-70",
            "--elevation",
            "35",
            "--memory",
            "768M",
            "--quiet",
            "--raw-f32",
            "--backend",
            "gpu",
        ];
        let plain = dir.path().join(format!("{mode}-plain.png"));
        let mut a = vec!["render", s(&store), "--out", s(&plain)];
        a.extend(view);
        ok(&run(&a), "single-process device render");
        let all = dir.path().join(format!("{mode}-all.png"));
        let mut a = vec![
            "render",
            s(&store),
            "--no-early-termination",
            "--out",
            s(&all),
        ];
        a.extend(view);
        ok(
            &run(&a),
            "single-process device render without early termination",
        );
        if mode == "dvr" {
            // Early termination matters in this view (on the device too).
            let (x, y) = (floats(&plain), floats(&all));
            let d = x
                .iter()
                .zip(&y)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0, f32::max);
            assert!(d > 1e-4, "early termination changed nothing: {d}");
        }
        for split in ["image", "data"] {
            let out = dir.path().join(format!("{mode}-{split}-2.png"));
            let mut a = vec!["render", s(&store), "--distribute", split, "--out", s(&out)];
            a.extend(view);
            let o = mpirun(2, &a, &[]);
            ok(&o, &format!("{mode} {split} on 2 ranks, each on a device"));
            let stdout = String::from_utf8_lossy(&o.stdout);
            assert!(stdout.contains("rendering on GPU"), "{stdout}");
            let want = if split == "image" { &plain } else { &all };
            close(
                want,
                &out,
                1e-5,
                &format!("{mode} {split}-parallel on 2 ranks, each on a device"),
            );
        }
    }
    let o = mpirun(
        2,
        &[
            "render",
            s(&store),
            "--distribute",
            "data",
            "--backend",
            "gpu",
            "--out",
            s(&dir.path().join("x.png")),
        ],
        &[("WGPU_ADAPTER_NAME", "no such adapter anywhere")],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--backend gpu") && err.contains("no GPU adapter found"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(!dir.path().join("x.png").exists());
}

/// An MPMD job, `mpirun -n 1 brickyard A : -n 1 brickyard B : …`, ended
/// by `timeout` after `secs` seconds: its output, and whether it ran past
/// that bound (a hang).
fn mpirun_mpmd(parts: &[Vec<&str>], env: &[(&str, &str)], secs: u32) -> (Output, bool) {
    let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
    let mut c = Command::new("timeout");
    c.args(["-k", "10", &secs.to_string(), "mpirun", "--oversubscribe"]);
    for (i, p) in parts.iter().enumerate() {
        if i > 0 {
            c.arg(":");
        }
        c.args(["-n", "1", bin()]).args(p);
    }
    c.env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("OMPI_MCA_rmaps_base_oversubscribe", "1")
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none");
    for (k, v) in env {
        c.env(k, v);
    }
    let o = c.output().unwrap();
    let hung = matches!(o.status.code(), Some(124) | Some(137) | None);
    (o, hung)
}

/// `n` ranks of one command, bounded as [`mpirun_mpmd`].
fn mpirun_bounded(n: usize, args: &[&str], env: &[(&str, &str)], secs: u32) -> (Output, bool) {
    mpirun_mpmd(&vec![args.to_vec(); n], env, secs)
}

/// A failure on one rank that the others do not hear of (not at a meeting
/// point: before the ranks meet, or a panic) ends the whole job within a
/// bound, with a failure status, naming the rank; a conversion so ended
/// leaves nothing that looks complete, and the next run takes over its
/// stale lock. When every rank fails alike before they meet, rank 0 says
/// it once and the job ends cleanly (no MPI_Abort).
#[test]
fn a_rank_failing_alone_ends_the_job() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("m.raw");
    generate(&raw, &["--size", "64x48x40", "--dtype", "u8"]);
    let out = dir.path().join("h.ome.zarr");
    let conv = [
        "convert",
        s(&raw),
        s(&out),
        "--brick",
        "16",
        "--shard",
        "32",
        "--quiet",
    ];
    for how in ["error", "panic"] {
        let t = std::time::Instant::now();
        let (o, hung) = mpirun_bounded(
            3,
            &conv,
            &[("BRICKYARD_MPI_FAIL", &format!("1:0:{how}"))],
            120,
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!hung, "convert, rank 1 {how}: the job hung\n{err}");
        assert!(!o.status.success(), "convert, rank 1 {how}: {err}");
        let want = match how {
            "error" => "rank 1: injected failure at the start",
            _ => "rank 1: panicked: injected panic at the start",
        };
        assert!(err.contains(want), "{err}");
        assert!(t.elapsed().as_secs() < 60, "{:?}", t.elapsed());
        assert!(!out.exists(), "a store that looks complete");
        let partial = dir.path().join("h.ome.zarr.partial");
        if partial.join("zarr.json").exists() {
            assert_eq!(run(&["info", s(&partial)]).status.code(), Some(2));
        }
    }
    // The next run takes over what the aborted one left.
    ok(&mpirun(2, &conv, &[]), "convert after an aborted one");
    assert!(out.join("zarr.json").exists());
    // A render: rank 2 panics before the ranks meet.
    for split in ["image", "data"] {
        let png = dir.path().join(format!("{split}.png"));
        let (o, hung) = mpirun_bounded(
            3,
            &[
                "render",
                s(&out),
                "--distribute",
                split,
                "--size",
                "48x40",
                "--out",
                s(&png),
                "--quiet",
            ],
            &[("BRICKYARD_MPI_FAIL", "2:0:panic")],
            120,
        );
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!hung, "render {split}: the job hung\n{err}");
        assert!(!o.status.success(), "{split}: {err}");
        assert!(
            err.contains("rank 2: panicked: injected panic"),
            "{split}: {err}"
        );
        assert!(!png.exists(), "{split}: an image was written");
    }
    // A hang seen once: one rank names an input that is not there.
    let elsewhere = dir.path().join("elsewhere/m.raw");
    let out2 = dir.path().join("h2.ome.zarr");
    let a = |input: &Path| -> Vec<String> {
        [
            "convert",
            s(input),
            s(&out2),
            "--brick",
            "16",
            "--shard",
            "32",
            "--quiet",
        ]
        .iter()
        .map(|x| x.to_string())
        .collect()
    };
    let (a0, a1) = (a(&raw), a(&elsewhere));
    let (o, hung) = mpirun_mpmd(
        &[
            a0.iter().map(|x| x.as_str()).collect(),
            a1.iter().map(|x| x.as_str()).collect(),
        ],
        &[],
        120,
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!hung, "the job hung\n{err}");
    assert!(!o.status.success(), "{err}");
    assert_eq!(
        err.matches("not given the same command").count(),
        1,
        "{err}"
    );
    assert!(
        err.contains("rank 0 ran `convert") && err.contains("rank 1 ran `convert"),
        "{err}"
    );
    assert!(!out2.exists() && !dir.path().join("h2.ome.zarr.partial").exists());
    // Every rank fails alike before the ranks meet: said once, cleanly.
    let (o, hung) = mpirun_bounded(
        3,
        &[
            "render",
            s(&out),
            "--distribute",
            "data",
            "--size",
            "0x0",
            "--out",
            s(&dir.path().join("z.png")),
        ],
        &[],
        120,
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!hung && !o.status.success(), "{err}");
    assert_eq!(err.matches("error:").count(), 1, "{err}");
    assert!(!err.contains("rank "), "{err}");
    assert!(!err.contains("MPI_ABORT"), "{err}");
}

/// Ranks given different arguments (an MPMD job) stop before they draw or
/// write anything: an error every rank agrees on, said once, naming the
/// ranks; a command that shares no work is refused under mpirun.
#[test]
fn ranks_must_run_the_same_command() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("g.ome.zarr");
    generate(&store, &["--size", "64", "--brick", "32", "--shard", "64"]);
    let png = dir.path().join("x.png");
    let r = |size: &'static str, split: &'static str| -> Vec<String> {
        [
            "render",
            s(&store),
            "--distribute",
            split,
            "--size",
            size,
            "--out",
            s(&png),
            "--quiet",
        ]
        .iter()
        .map(|x| x.to_string())
        .collect()
    };
    for (a, b, c) in [
        (r("64", "data"), r("64", "data"), r("32", "data")),
        (r("64", "image"), r("64", "data"), r("64", "image")),
    ] {
        let parts: Vec<Vec<&str>> = [&a, &b, &c]
            .iter()
            .map(|v| v.iter().map(|x| x.as_str()).collect())
            .collect();
        let (o, hung) = mpirun_mpmd(&parts, &[], 120);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!hung, "the job hung\n{err}");
        assert!(!o.status.success(), "{err}");
        assert_eq!(
            err.matches("not given the same command").count(),
            1,
            "{err}"
        );
        assert!(
            err.contains("ranks 0, 1 ran `render") || err.contains("ranks 0, 2 ran `render"),
            "{err}"
        );
        assert!(!png.exists());
    }
    // convert against render: no hang either.
    let parts = vec![
        vec!["info", s(&store)],
        vec!["render", s(&store), "--out", s(&png)],
    ];
    let (o, hung) = mpirun_mpmd(&parts, &[], 120);
    assert!(!hung && !o.status.success());
    for args in [
        vec!["info", s(&store)],
        vec![
            "generate",
            "mandelbulb",
            s(&dir.path().join("m.raw")),
            "--size",
            "16",
        ],
    ] {
        let (o, hung) = mpirun_bounded(2, &args, &[], 120);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!hung && !o.status.success(), "{args:?}: {err}");
        assert_eq!(
            err.matches("shares no work among MPI ranks").count(),
            1,
            "{err}"
        );
    }
}

/// Bricks that ranks other than 0 could not load are reported by rank 0
/// as one process reports its own, with exit status 3 (level 0 drawn). The volume, longer
/// in x, is split in x between 2 ranks (uniform weights): a damaged shard
/// at either end of x is read by rank 0 in one run and by rank 1 in the
/// other.
#[test]
fn failures_on_every_rank_are_reported() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let clean = dir.path().join("c.ome.zarr");
    generate(
        &clean,
        &["--size", "128x64x64", "--brick", "16", "--shard", "32"],
    );
    for x in [0, 3] {
        let store = dir.path().join(format!("d{x}.ome.zarr"));
        let o = Command::new("cp")
            .args(["-r", s(&clean), s(&store)])
            .output()
            .unwrap();
        ok(&o, "cp");
        // Every level-0 shard at this x, damaged in its middle.
        let mut damaged = 0;
        for z in 0..2 {
            for y in 0..2 {
                let f = store.join(format!("0/c/{z}/{y}/{x}"));
                let Ok(mut b) = std::fs::read(&f) else {
                    continue;
                };
                let mid = b.len() / 3;
                let end = (mid + 2000).min(b.len() - 1);
                b[mid..end].fill(b'Z');
                std::fs::write(&f, b).unwrap();
                damaged += 1;
            }
        }
        assert!(damaged > 0, "no shard at x {x}");
        for split in ["data", "image"] {
            let png = dir.path().join(format!("d{x}-{split}.png"));
            let mut a = vec!["render", s(&store), "--distribute", split];
            // (The regions' weights are the data-parallel split's.)
            if split == "data" {
                a.extend(["--region-weights", "uniform"]);
            }
            a.extend(["--size", "96x64", "--level", "0", "--out", s(&png)]);
            let o = mpirun(2, &a, &[]);
            let (out, err) = (
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr),
            );
            assert_eq!(o.status.code(), Some(3), "x {x}, {split}: {out}\n{err}");
            assert!(
                out.contains("could not load level 0"),
                "x {x}, {split}: {out}"
            );
            assert!(err.contains("exit status 3"), "x {x}, {split}: {err}");
        }
    }
}

/// With --json, standard output holds JSON lines only under mpirun too.
#[test]
fn json_output_of_shared_renders_is_json() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("g.ome.zarr");
    generate(&store, &["--size", "64", "--brick", "32", "--shard", "64"]);
    for (n, split) in [(3, "data"), (2, "data"), (2, "image")] {
        let png = dir.path().join(format!("{split}{n}.png"));
        let o = mpirun(
            n,
            &[
                "render",
                s(&store),
                "--distribute",
                split,
                "--size",
                "64x48",
                "--json",
                "--out",
                s(&png),
            ],
            &[],
        );
        ok(&o, &format!("{split} on {n} ranks"));
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(out.lines().count() > 1, "{out}");
        for l in out.lines() {
            assert!(
                serde_json::from_str::<serde_json::Value>(l).is_ok(),
                "{split} on {n} ranks: not JSON: {l:?}"
            );
        }
    }
}

/// An injected failure at the ranks' first meeting of a conversion (rank 0
/// has taken the lock and made `OUT.partial`; here the ranks meet over it):
/// every rank stops, and neither the partial output nor the lock is left;
/// the same command then converts.
#[test]
fn a_failure_at_the_first_meeting_leaves_no_partial_output() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("m.raw");
    generate(&raw, &["--size", "40", "--dtype", "u16"]);
    let out = dir.path().join("f.ome.zarr");
    let args = [
        "convert",
        s(&raw),
        s(&out),
        "--brick",
        "16",
        "--shard",
        "32",
        "--quiet",
    ];
    for fail in ["1:1:error", "0:1:error"] {
        let o = mpirun(2, &args, &[("BRICKYARD_MPI_FAIL", fail)]);
        assert!(!o.status.success(), "{fail}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains("injected failure at meeting point 1"),
            "{fail}: {err}"
        );
        for left in ["f.ome.zarr", "f.ome.zarr.partial", "f.ome.zarr.lock"] {
            assert!(!dir.path().join(left).exists(), "{fail}: {left} left");
        }
    }
    ok(&mpirun(2, &args, &[]), "convert after the failures");
    assert!(out.join("zarr.json").exists());
}

/// `kill -INT` of `mpirun` during a shared conversion (mpirun sends every
/// rank SIGTERM, and SIGKILL a second later): within a few seconds the job
/// has ended with a failure status, leaving neither `OUT.partial` nor
/// `OUT.lock` nor `OUT`; the same command then converts.
#[test]
fn interrupting_mpirun_leaves_no_partial_output() {
    use std::time::{Duration, Instant};
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("m.raw");
    // (At 160³ the whole job took 1.4 s from its partial output on: a busy
    // CI machine once delivered round 1's interrupt after it had ended.)
    generate(&raw, &["--size", "224", "--dtype", "u16"]);
    let out = dir.path().join("i.ome.zarr");
    let partial = dir.path().join("i.ome.zarr.partial");
    let lock = dir.path().join("i.ome.zarr.lock");
    // Slow enough to be interrupted: one thread a rank, the slowest codec.
    let args = [
        "--threads",
        "1",
        "convert",
        s(&raw),
        s(&out),
        "--shard",
        "64",
        "--columns",
        "4",
        "--compression",
        "zstd:19",
        "--quiet",
    ];
    // Each round is tried until its interrupt lands while the job runs (a
    // job that ended first, converted whole, proves nothing: tried again,
    // three times at most, so that one that ignores SIGINT still fails).
    let mut tries = 0;
    let mut round = 0;
    while round < 2 {
        tries += 1;
        assert!(
            tries <= 6,
            "the interrupts kept arriving after the job ended"
        );
        let _one = MPIRUN.lock().unwrap_or_else(|e| e.into_inner());
        let mut child = Command::new("mpirun")
            .args(["--oversubscribe", "-n", "2", bin()])
            .args(args)
            .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
            .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
            .env("OMPI_MCA_rmaps_base_oversubscribe", "1")
            .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let t0 = Instant::now();
        while !partial.exists() {
            assert!(
                child.try_wait().unwrap().is_none(),
                "the conversion ended before its partial output appeared"
            );
            assert!(t0.elapsed() < Duration::from_secs(120), "no partial output");
            std::thread::sleep(Duration::from_millis(5));
        }
        // Into the first pass (round 1: at once, round 2: a moment later).
        std::thread::sleep(Duration::from_millis(300 * round));
        // SAFETY: kill(2) of our own child, not yet reaped.
        unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
        let t = Instant::now();
        let status = loop {
            if let Some(st) = child.try_wait().unwrap() {
                break st;
            }
            if t.elapsed() > Duration::from_secs(30) {
                let _ = child.kill();
                panic!("mpirun still running 30 s after SIGINT");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let mut err = String::new();
        use std::io::Read;
        let _ = child.stderr.take().unwrap().read_to_string(&mut err);
        if status.success() && out.exists() && tries < 3 + round {
            eprintln!("round {round}: the job ended before its interrupt; again");
            std::fs::remove_dir_all(&out).unwrap();
            continue;
        }
        assert!(!status.success(), "round {round}: {err}");
        assert!(!out.exists(), "round {round}: {err}");
        // Gone within a few seconds (the ranks end by then: SIGKILL).
        let t = Instant::now();
        while (partial.exists() || lock.exists()) && t.elapsed() < Duration::from_secs(5) {
            std::thread::sleep(Duration::from_millis(50));
        }
        assert!(
            !partial.exists(),
            "round {round}: partial output left: {err}"
        );
        assert!(!lock.exists(), "round {round}: lock left: {err}");
        round += 1;
    }
    // The next run converts, alone and shared.
    let small = dir.path().join("s.raw");
    generate(&small, &["--size", "40"]);
    let o = mpirun(
        2,
        &[
            "convert",
            s(&small),
            s(&out),
            "--brick",
            "16",
            "--shard",
            "32",
            "--quiet",
        ],
        &[],
    );
    ok(&o, "convert after the interruptions");
    assert!(out.join("zarr.json").exists());
}

/// Progress lines (standard error not a terminal, as under mpirun) come
/// from rank 0 only: one closing line for the whole job.
#[test]
fn progress_lines_come_from_rank_0_only() {
    if !have_mpirun() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("m.raw");
    generate(&raw, &["--size", "64", "--dtype", "u16"]);
    let out = dir.path().join("p.ome.zarr");
    let o = mpirun(
        2,
        &[
            "convert",
            s(&raw),
            s(&out),
            "--brick",
            "16",
            "--shard",
            "32",
            "--columns",
            "2",
        ],
        &[("BRICKYARD_PROGRESS_SECONDS", "0")],
    );
    ok(&o, "convert on 2 ranks");
    let err = String::from_utf8_lossy(&o.stderr);
    let done: Vec<&str> = err
        .lines()
        .filter(|l| l.starts_with("converting: done"))
        .collect();
    assert_eq!(done.len(), 1, "{err}");
    assert!(
        err.lines()
            .any(|l| l.starts_with("converting: ") && l.contains("ETA")),
        "{err}"
    );
}
