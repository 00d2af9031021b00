//! The default view of `render` fits the volume into the image, its width
//! as well as its height (portrait and very wide images, volumes thinner
//! than a pixel), and a slice's camera saved with `--save-camera` brings
//! the same slice back with `--camera`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[track_caller]
fn ok(o: &Output) {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().unwrap()
}

/// A `x × y × z` u8 store `name` in `dir` whose every voxel is lit (100 to
/// 199, varying), so that the volume's box is what an image shows.
fn raw_store(dir: &Path, name: &str, [x, y, z]: [usize; 3]) -> PathBuf {
    let raw = dir.join(format!("{name}.raw"));
    let mut v = Vec::with_capacity(x * y * z);
    for k in 0..z {
        for j in 0..y {
            for i in 0..x {
                v.push((100 + (i + 2 * j + 3 * k) % 100) as u8);
            }
        }
    }
    std::fs::write(&raw, v).unwrap();
    let store = dir.join(format!("{name}.zarr"));
    let dims = format!("{x}x{y}x{z}");
    ok(&run(&[
        "convert",
        "--quiet",
        "--dims",
        &dims,
        "--dtype",
        "u8",
        s(&raw),
        s(&store),
    ]));
    store
}

/// Decoded RGBA8 pixels of a PNG, with its width and height.
fn png_pixels(p: &Path) -> (Vec<u8>, u32, u32) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = dec.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    assert_eq!(buf.len(), (info.width * info.height * 4) as usize);
    (buf, info.width, info.height)
}

/// The lit pixels (any colour above 0) of a render: how many, and the
/// columns and rows they span, `[x0, x1, y0, y1]`.
fn lit(pixels: &[u8], w: u32) -> (usize, Option<[u32; 4]>) {
    let mut n = 0;
    let mut b: Option<[u32; 4]> = None;
    for (k, c) in pixels.chunks_exact(4).enumerate() {
        if c[..3].iter().any(|v| *v > 0) {
            n += 1;
            let (x, y) = (k as u32 % w, k as u32 / w);
            b = Some(match b {
                None => [x, x, y, y],
                Some(b) => [b[0].min(x), b[1].max(x), b[2].min(y), b[3].max(y)],
            });
        }
    }
    (n, b)
}

fn render(store: &Path, out: &Path, args: &[&str]) {
    let mut c = bin();
    c.arg("render").arg(store).args(args).args([
        "--tf",
        "linear",
        "--window",
        "0,255",
        "--backend",
        "cpu",
        "--quiet",
        "-o",
        s(out),
    ]);
    ok(&c.output().unwrap());
}

#[test]
fn default_views_fit_portrait_and_very_wide_images() {
    let d = tempfile::tempdir().unwrap();
    // A box taller than wide seen in a portrait image, and a bar 16 times
    // longer than thick in an image 12 times wider than tall: the width
    // limits both. (The old views were as tall as the volume's largest
    // extent whatever the width: the box ran over the portrait image's
    // sides, the bar filled a twelfth of the wide one.)
    let block = raw_store(d.path(), "block", [48, 64, 40]);
    let bar = raw_store(d.path(), "bar", [256, 16, 16]);
    for (store, size) in [(&block, "60x200"), (&bar, "600x50"), (&block, "200x60")] {
        for mode in ["slice", "dvr", "mip"] {
            let png = d.path().join(format!("{mode}-{size}.png"));
            render(store, &png, &["--mode", mode, "--size", size]);
            let (px, w, h) = png_pixels(&png);
            let (n, b) = lit(&px, w);
            let what = format!("{} --mode {mode} --size {size}", store.display());
            let [x0, x1, y0, y1] = b.unwrap_or_else(|| panic!("{what}: nothing lit"));
            eprintln!("{what}: {n} lit, columns {x0}..={x1} of {w}, rows {y0}..={y1} of {h}");
            // The margin (2.5 % of the limiting side each way, over a
            // pixel in these sizes) keeps the edge columns and rows dark.
            assert!(x0 >= 1 && x1 + 2 <= w && y0 >= 1 && y1 + 2 <= h, "{what}");
            // And the volume fills the limiting side but for the margin: a
            // slice its box's projection (1/1.05); 3D views the box's
            // bounding sphere, which a box fills less (the bar, seen
            // obliquely, a quarter).
            let fill = ((x1 - x0 + 1) as f64 / w as f64).max((y1 - y0 + 1) as f64 / h as f64);
            let least = match (mode, store == &bar) {
                ("slice", _) => 0.9,
                (_, false) => 0.7,
                (_, true) => 0.2,
            };
            assert!(
                fill >= least && fill <= 1.0 / 1.05 + 0.02,
                "{what}: fills {fill}"
            );
        }
    }
}

#[test]
fn a_volume_thinner_than_a_pixel_is_drawn() {
    let d = tempfile::tempdir().unwrap();
    // 4096 × 4 × 4 voxels: in 1024 × 64 one pixel is 4.2 voxels, the
    // volume 0.95 pixel tall, centred between two rows of pixel centres.
    let raw = d.path().join("thin.raw");
    let row: Vec<u8> = (0..4096).map(|i| (i % 256) as u8).collect();
    std::fs::write(&raw, row.repeat(16)).unwrap();
    let store = d.path().join("thin.zarr");
    ok(&run(&[
        "convert",
        "--quiet",
        "--dims",
        "4096x4x4",
        "--dtype",
        "u8",
        s(&raw),
        s(&store),
    ]));
    for size in ["1024x64", "1024x1", "1024x2"] {
        let png = d.path().join(format!("thin-{size}.png"));
        render(&store, &png, &["--mode", "slice", "--size", size]);
        let (px, w, _) = png_pixels(&png);
        let (n, b) = lit(&px, w);
        let [x0, x1, y0, y1] = b.unwrap_or_else(|| panic!("{size}: nothing lit"));
        eprintln!("thin slice {size}: {n} lit, columns {x0}..={x1}, rows {y0}..={y1}");
        // One row: the volume's middle, across 1/1.05 of the width (less
        // the 16 columns of value 0).
        assert_eq!(y0, y1, "{size}");
        assert!(
            n >= 950 && x0 >= 20 && x1 < 1004,
            "{size}: {n} lit, {x0}..={x1}"
        );
    }
}

#[test]
fn a_saved_slice_camera_brings_back_the_same_slice() {
    let d = tempfile::tempdir().unwrap();
    let store = raw_store(d.path(), "block", [48, 64, 40]);
    let p = |n: &str| d.path().join(n);
    let (a, cam) = (p("a.png"), p("rt.json"));
    let plane = ["--slice-z", "0.2", "--slice-normal", "1,0.3,0.2"];
    let slice = ["--mode", "slice", "--size", "80x64"];
    render(
        &store,
        &a,
        &[&slice[..], &plane[..], &["--save-camera", s(&cam)]].concat(),
    );
    let saved: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cam).unwrap()).unwrap();
    assert_eq!(saved["slice_normal"], serde_json::json!([1.0, 0.3, 0.2]));
    // The plane's point in world units, as --slice-origin takes it: the
    // middle of x and y, z at the centre of layer 8 of 40.
    assert_eq!(saved["slice_origin"], serde_json::json!([24.0, 32.0, 8.5]));
    // The camera alone draws the same slice, byte for byte.
    let b = p("b.png");
    render(&store, &b, &[&slice[..], &["--camera", s(&cam)]].concat());
    let bytes = |f: &Path| std::fs::read(f).unwrap();
    assert!(bytes(&a) == bytes(&b), "--camera drew another image");
    assert!(lit(&png_pixels(&a).0, 80).0 > 1000);
    // Options given with it win: the same plane given again draws the
    // same image; the default plane draws what a camera file without a
    // plane (as older ones) draws.
    let c = p("c.png");
    render(
        &store,
        &c,
        &[&slice[..], &plane[..], &["--camera", s(&cam)]].concat(),
    );
    assert!(bytes(&c) == bytes(&a));
    let mut old = saved.clone();
    let o = old.as_object_mut().unwrap();
    o.remove("slice_origin").unwrap();
    o.remove("slice_normal").unwrap();
    let old_cam = p("old.json");
    std::fs::write(&old_cam, old.to_string()).unwrap();
    let (e, f) = (p("e.png"), p("f.png"));
    let axial = ["--slice-z", "0.5", "--slice-normal", "0,0,1"];
    render(
        &store,
        &e,
        &[&slice[..], &axial[..], &["--camera", s(&cam)]].concat(),
    );
    render(
        &store,
        &f,
        &[&slice[..], &["--camera", s(&old_cam)]].concat(),
    );
    assert!(
        bytes(&e) == bytes(&f),
        "--slice-* with --camera: not the options' plane"
    );
    assert!(bytes(&e) != bytes(&a));
    // Only the normal given: the file's point with that normal, as
    // --slice-origin and --slice-normal would draw it.
    let (g, h) = (p("g.png"), p("h.png"));
    let normal = ["--slice-normal", "0,1,0.5"];
    render(
        &store,
        &g,
        &[&slice[..], &normal[..], &["--camera", s(&cam)]].concat(),
    );
    let origin = ["--slice-origin", "24,32,8.5"];
    render(
        &store,
        &h,
        &[
            &slice[..],
            &normal[..],
            &origin[..],
            &["--camera", s(&old_cam)],
        ]
        .concat(),
    );
    assert!(bytes(&g) == bytes(&h));
    assert!(bytes(&g) != bytes(&a));
    // A 3D view's camera file has no plane.
    let cam3 = p("dvr.json");
    render(
        &store,
        &p("dvr.png"),
        &["--mode", "dvr", "--size", "32", "--save-camera", s(&cam3)],
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cam3).unwrap()).unwrap();
    assert!(
        v.get("slice_origin").is_none() && v.get("slice_normal").is_none(),
        "{v}"
    );
}

#[test]
fn slice_at_takes_the_stores_physical_coordinates() {
    // 40 × 32 × 24 voxels, spacing 2, 1, 0.5 and voxel 0's centre at
    // (-30, 10, 5) millimeters: layer k of z lies at 5 + 0.5·k.
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n);
    // (The raw file of a lit volume, converted again with a geometry.)
    raw_store(d.path(), "placed", [40, 32, 24]);
    let store = p("placed-mm.zarr");
    ok(&run(&[
        "convert",
        "--quiet",
        "--dims",
        "40x32x24",
        "--dtype",
        "u8",
        "--spacing",
        "2,1,0.5",
        "--origin",
        "-30,10,5",
        "--unit",
        "mm",
        s(&p("placed.raw")),
        s(&store),
    ]));
    let slice = ["--mode", "slice", "--size", "80x64"];
    let bytes = |f: &Path| std::fs::read(f).unwrap();
    // z = 8.5 mm is layer 7 of 24: the slice --slice-z draws at that
    // layer (any x and y name the same plane).
    let (a, b) = (p("at.png"), p("z.png"));
    render(
        &store,
        &a,
        &[&slice[..], &["--slice-at", "-100,0,8.5"]].concat(),
    );
    render(
        &store,
        &b,
        &[&slice[..], &["--slice-z", &format!("{}", 7.5 / 24.0)]].concat(),
    );
    assert!(lit(&png_pixels(&a).0, 80).0 > 1000, "a blank slice");
    assert!(bytes(&a) == bytes(&b), "--slice-at 8.5 mm is not layer 7");
    // Across x: x = -4 mm is column 13, at 27 in the renderer's world
    // (corner at 0, (13 + ½)·2), as --slice-origin takes it.
    let (c, e) = (p("at-x.png"), p("origin-x.png"));
    let across = ["--slice-normal", "1,0,0"];
    render(
        &store,
        &c,
        &[&slice[..], &across[..], &["--slice-at", "-4,12,6"]].concat(),
    );
    render(
        &store,
        &e,
        &[&slice[..], &across[..], &["--slice-origin", "27,0,0"]].concat(),
    );
    assert!(lit(&png_pixels(&c).0, 80).0 > 1000, "a blank slice");
    assert!(bytes(&c) == bytes(&e), "--slice-at -4 mm is not column 13");
    // A plane beyond the volume names its span in the same coordinates:
    // z from 5 - 0.25 to 5 + 23.75 mm.
    let o = bin()
        .arg("render")
        .arg(&store)
        .args([
            "--mode",
            "slice",
            "--slice-at",
            "0,0,40",
            "-o",
            s(&p("no.png")),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("slice-at:")
            && err.contains("spans [-31.0, 9.5, 4.75] to [49.0, 41.5, 16.75]")
            && err.contains("millimeter"),
        "{err}"
    );
    assert!(!p("no.png").exists());
    // Two ways of placing the plane at once are refused.
    let o = bin()
        .arg("render")
        .arg(&store)
        .args(["--mode", "slice", "--slice-at", "0,0,8", "--slice-z", "0.5"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("--slice-z and --slice-at"), "{err}");
}

#[test]
fn coarser_levels_lie_where_the_store_places_them() {
    // A ramp along x (value = x index, 61 voxels: no power of two), float
    // so that the levels' box means are exact. Level L's voxel j is the
    // mean of its two level-(L−1) voxels (the last one alone) and is
    // centred at 2^L·(j + ½) level-0 voxels, as the store's scale and
    // translation say: a slice drawn at level L is that level's voxels
    // interpolated at those places. (They were spread over the level-0
    // extent instead: 8 voxels over 61 at level 3, off by up to 2.9.)
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n);
    let (nx, ny, nz) = (61usize, 8usize, 8usize);
    let mut bytes = Vec::with_capacity(nx * ny * nz * 4);
    for _ in 0..ny * nz {
        for i in 0..nx {
            bytes.extend_from_slice(&(i as f32).to_le_bytes());
        }
    }
    std::fs::write(p("ramp.raw"), bytes).unwrap();
    let store = p("ramp.zarr");
    ok(&run(&[
        "convert",
        "--quiet",
        "--dims",
        "61x8x8",
        "--dtype",
        "f32",
        "--brick",
        "4",
        s(&p("ramp.raw")),
        s(&store),
    ]));
    // The levels along x, by the builder's rule.
    let mut levels = vec![(0..nx).map(|i| i as f64).collect::<Vec<f64>>()];
    while levels.last().unwrap().len() > 4 {
        let prev = levels.last().unwrap();
        let next = prev
            .chunks(2)
            .map(|c| c.iter().sum::<f64>() / c.len() as f64)
            .collect();
        levels.push(next);
    }
    assert_eq!(levels.len(), 5, "61 → 31 → 16 → 8 → 4");
    // Two pixels a voxel across x, looking down z at the middle layer.
    let (w, h) = (2 * nx, 2 * ny);
    std::fs::write(
        p("cam.json"),
        r#"{"projection":{"type":"orthographic","height":8.0},"eye":[30.5,4.0,-100.0],"target":[30.5,4.0,4.0],"up":[0.0,-1.0,0.0]}"#,
    )
    .unwrap();
    let backends: &[&str] = match brickyard_gpu::context::test_gpu() {
        Some(_) => &["cpu", "gpu"],
        None => &["cpu"], // BRICKYARD_SKIP_GPU=1
    };
    for &backend in backends {
        for (l, lv) in levels.iter().enumerate().skip(1) {
            let out = p(&format!("l{l}-{backend}.png"));
            let o = bin()
                .arg("render")
                .arg(&store)
                .args([
                    "--mode",
                    "slice",
                    "--slice-z",
                    "0.5",
                    "--level",
                    &l.to_string(),
                ])
                .args(["--camera", s(&p("cam.json")), "--size", &format!("{w}x{h}")])
                .args(["--tf", "linear", "--window", "0,61", "--raw-f32", "--quiet"])
                .args(["--backend", backend, "-o", s(&out)])
                .output()
                .unwrap();
            ok(&o);
            let raw = std::fs::read(out.with_extension("f32")).unwrap();
            let px: Vec<f32> = raw
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                .collect();
            assert_eq!(px.len(), w * h * 4);
            let r = (1u64 << l) as f64;
            let (mut worst, mut interior) = (0.0f64, 0.0f64);
            for i in 0..w {
                let x = (i as f64 + 0.5) * 0.5;
                let q = (x / r - 0.5).clamp(0.0, (lv.len() - 1) as f64);
                let j = q.floor() as usize;
                let f = q - j as f64;
                let want = lv[j] * (1.0 - f) + lv[(j + 1).min(lv.len() - 1)] * f;
                let got = px[(h / 2 * w + i) * 4] as f64 * 61.0;
                worst = worst.max((got - want).abs());
                // Box means of a ramp interpolated between their centres
                // are the ramp itself, away from the partial last box.
                if x > r && x < 56.0 - r {
                    interior = interior.max((got - (x - 0.5)).abs());
                }
            }
            assert!(worst < 2e-3, "{backend} level {l}: off by {worst}");
            assert!(
                interior < 2e-3,
                "{backend} level {l}: the ramp off by {interior}"
            );
        }
    }
}
