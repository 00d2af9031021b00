//! The device back end against the CPU through the command line, where the
//! device once drew differently: `render --progressive` at a size whose
//! sample store is larger than one storage binding of the device (it was
//! then accumulated at a coarser level than the plain frame), and values
//! exactly on a hard step of the transfer function (the device's f32 ray
//! positions gave samples at voxel centres fractions of about 1e-5, which
//! moved such values off the step).

use std::path::Path;
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

#[track_caller]
fn ok(o: &Output, what: &str) -> String {
    assert!(
        o.status.success(),
        "{what}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The `.f32` image `--raw-f32` writes beside `png`.
fn raw(png: &Path) -> Vec<f32> {
    let b = std::fs::read(png.with_extension("f32")).unwrap();
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

/// Largest difference and the count of values beyond `tol`.
fn diff(a: &[f32], b: &[f32], tol: f32) -> (f32, usize) {
    assert_eq!(a.len(), b.len());
    let mut worst = 0.0f32;
    let mut off = 0;
    for (x, y) in a.iter().zip(b) {
        let d = (x - y).abs();
        worst = worst.max(d);
        off += (d > tol) as usize;
    }
    (worst, off)
}

/// A u8 store of `n³` voxels from `f(z, y, x)` (spacing 1).
fn store(dir: &Path, n: u32, f: impl Fn(u32, u32, u32) -> u8) -> std::path::PathBuf {
    let raw = dir.join("v.raw");
    let mut v = Vec::with_capacity((n * n * n) as usize);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                v.push(f(z, y, x));
            }
        }
    }
    std::fs::write(&raw, v).unwrap();
    let out = dir.join("v.zarr");
    let dims = format!("{n}x{n}x{n}");
    let o = run(&[
        "convert",
        s(&raw),
        s(&out),
        "--dims",
        &dims,
        "--dtype",
        "u8",
        "--brick",
        "16",
        "--quiet",
    ]);
    ok(&o, "convert");
    out
}

/// An orthographic camera along +z whose pixel centres are voxel centres
/// (one voxel a pixel) of an `n³` volume of spacing 1.
fn axial_camera(dir: &Path, n: u32) -> std::path::PathBuf {
    let c = n as f64 / 2.0;
    let cam = dir.join("cam.json");
    std::fs::write(
        &cam,
        format!(
            r#"{{"projection":{{"type":"orthographic","height":{n}.0}},"eye":[{c},{c},-100.0],"target":[{c},{c},{c}],"up":[0.0,-1.0,0.0]}}"#
        ),
    )
    .unwrap();
    cam
}

#[test]
fn values_on_a_hard_step_are_classified_alike_on_both_back_ends() {
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    let d = tempfile::tempdir().unwrap();
    let n = 48;
    // Values below, exactly on and above the step at 65 (window [0, 130]:
    // x = 0.5), mixed so that each voxel on the step has neighbours below
    // (and every brick's range is wide: 0 to 130).
    let h = |z: u32, y: u32, x: u32| {
        (z.wrapping_mul(73) ^ y.wrapping_mul(151) ^ x.wrapping_mul(31)) % 7
    };
    let st = store(d.path(), n, |z, y, x| match h(z, y, x) {
        0 => 0,
        1..=3 => 60,
        4 | 5 => 65,
        _ => 130,
    });
    let cam = axial_camera(d.path(), n);
    let tf = d.path().join("tf.json");
    std::fs::write(
        &tf,
        r#"{"window":[0,130],"opacity":[[0,0],[0.5,0],[0.5,1],[1,1]],"colormap":[[0,0,0,0],[1,1,1,1]],"shading":false}"#,
    )
    .unwrap();
    let size = format!("{n}x{n}");
    for traversal in ["page-table", "octree"] {
        let mut imgs = vec![];
        for backend in ["cpu", "gpu"] {
            let png = d.path().join(format!("{traversal}-{backend}.png"));
            let o = run(&[
                "render",
                s(&st),
                "--size",
                &size,
                "--camera",
                s(&cam),
                "--level",
                "0",
                "--tf",
                s(&tf),
                "--raw-f32",
                "--traversal",
                traversal,
                "--backend",
                backend,
                "--out",
                s(&png),
            ]);
            ok(&o, &format!("{traversal} {backend}"));
            imgs.push(raw(&png));
        }
        // Every ray meets a voxel on the step or above: opaque pixels.
        assert!(
            imgs[0].chunks(4).all(|p| p[3] > 0.99),
            "{traversal}: not opaque"
        );
        // The first voxel at or above the step is 65 in many pixels.
        let on = imgs[0]
            .chunks(4)
            .filter(|p| (p[0] - 0.5).abs() < 1e-6)
            .count();
        assert!(
            on * 4 > imgs[0].len() / 4,
            "{traversal}: {on} pixels on the step"
        );
        let (worst, off) = diff(&imgs[0], &imgs[1], 1e-5);
        assert!(
            off == 0,
            "{traversal}: device vs CPU max {worst}, {off} values beyond 1e-5"
        );
    }
}

#[test]
fn progressive_on_the_device_keeps_the_detail_of_the_cpu() {
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    let d = tempfile::tempdir().unwrap();
    let n = 32;
    let st = store(d.path(), n, |z, y, x| {
        (40 + ((z * 7 + y * 13 + x * 29) % 200)) as u8
    });
    let cam = axial_camera(d.path(), n);
    // Opaque from the first sample: a ray's run ends at once, so the
    // samples taken stay few while each pixel's store must still hold the
    // longest ray's run (about 59 samples). At 512² those did not fit one
    // 128 MiB storage binding (lavapipe's): the device fell back to level 1.
    let tf = d.path().join("tf.json");
    std::fs::write(
        &tf,
        r#"{"window":[0,255],"opacity":[[0,1],[1,1]],"shading":false}"#,
    )
    .unwrap();
    let mut imgs = vec![];
    for backend in ["cpu", "gpu"] {
        let png = d.path().join(format!("{backend}.png"));
        let o = run(&[
            "render",
            s(&st),
            "--size",
            "512x512",
            "--camera",
            s(&cam),
            "--tf",
            s(&tf),
            "--level",
            "0",
            "--progressive",
            "2",
            "--raw-f32",
            "--backend",
            backend,
            "--out",
            s(&png),
        ]);
        let out = ok(&o, backend);
        assert!(
            !out.contains("accumulating at"),
            "{backend}: a coarser level: {out}"
        );
        imgs.push(raw(&png));
    }
    let (worst, off) = diff(&imgs[0], &imgs[1], 1e-4);
    assert!(
        worst < 1e-3 && off * 1000 <= imgs[0].len(),
        "device vs CPU max {worst}, {off} values beyond 1e-4"
    );
}

#[test]
fn a_blend_longer_than_the_devices_loop_limit_is_named_as_such() {
    // 256 frames of 4 samples a voxel along rays through a nearly clear
    // 160³ volume: one pixel's blend takes over 200 000 samples, more
    // than a software device runs in one invocation (65 535 loop
    // iterations). With every brick resident the render once ended with
    // "the pool cannot hold the view's bricks".
    let Some(gpu) = brickyard_gpu::context::test_gpu() else {
        return; // BRICKYARD_SKIP_GPU=1
    };
    let software = gpu.info.device_type == wgpu::DeviceType::Cpu;
    drop(gpu);
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.zarr");
    let o = run(&[
        "generate",
        "mandelbulb",
        s(&store),
        "--size",
        "160",
        "--quiet",
    ]);
    ok(&o, "generate");
    let view = [
        "--mode",
        "dvr",
        "--size",
        "4x4",
        "--tf",
        "linear",
        "--window",
        "0,100000",
        "--progressive",
        "256",
        "--samples-per-voxel",
        "4",
        "--quiet",
    ];
    let png = d.path().join("a.png");
    let o = run(&[
        &["render", s(&store)][..],
        &view,
        &["--backend", "gpu", "-o", s(&png)],
    ]
    .concat());
    let err = String::from_utf8_lossy(&o.stderr);
    if o.status.success() && !software {
        // A hardware device may run such loops whole, and draw it.
        assert!(png.exists(), "{err}");
        return;
    }
    assert!(!o.status.success() && !png.exists(), "{err}");
    assert!(
        err.contains("stayed short of their blend") && err.contains("--backend cpu"),
        "{err}"
    );
    assert!(!err.contains("pool cannot hold"), "{err}");
    // The CPU draws it, as the message says.
    let o = run(&[
        &["render", s(&store)][..],
        &view,
        &["--backend", "cpu", "-o", s(&png)],
    ]
    .concat());
    ok(&o, "render on the CPU");
}

/// Where the device's fixed sample store holds fewer runs of the longest
/// rays than the frames asked for, those pixels stop at fewer frames (the
/// room rule), and `render` says how many: "accumulated 32 frames" alone
/// claimed more than such pixels hold. The CPU's store grows: no such note.
#[test]
fn frames_the_devices_store_cannot_hold_are_said() {
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    let d = tempfile::tempdir().unwrap();
    let st = d.path().join("m.zarr");
    ok(
        &run(&["generate", "mandelbulb", s(&st), "--size", "32", "--quiet"]),
        "generate",
    );
    let view = |backend: &'static str| {
        [
            "render",
            s(&st),
            "--size",
            "256",
            "--tf",
            "linear",
            "--progressive",
            "32",
            "--memory",
            "1GiB",
            "--backend",
            backend,
        ]
    };
    let png = d.path().join("g.png");
    let out = ok(&run(&[&view("gpu")[..], &["-o", s(&png)]].concat()), "gpu");
    let line = out
        .lines()
        .find(|l| l.starts_with("accumulated 32 frames"))
        .unwrap_or_else(|| panic!("no accumulated line: {out}"));
    // "... diagonal (L samples a run) keeps K of them in the B samples ..."
    let num_after = |key: &str| -> u64 {
        let at = line.find(key).unwrap_or_else(|| panic!("{key}: {line}")) + key.len();
        line[at..]
            .split(|c: char| !c.is_ascii_digit())
            .next()
            .unwrap()
            .parse()
            .unwrap_or_else(|_| panic!("{key}: {line}"))
    };
    let (runs, fewest, kept) = (
        num_after("diagonal ("),
        num_after(" keeps "),
        num_after(" in the "),
    );
    // A 32³ volume's diagonal at one sample a voxel, and the room rule.
    assert_eq!(runs, (32f64 * 3f64.sqrt()).ceil() as u64 + 2, "{line}");
    assert_eq!(fewest, kept / runs, "{line}");
    assert!((1..32).contains(&fewest), "{line}");
    assert!(png.exists());
    let out = ok(&run(&[&view("cpu")[..], &["-o", s(&png)]].concat()), "cpu");
    assert!(
        out.contains("accumulated 32 frames") && !out.contains("diagonal"),
        "{out}"
    );
}
