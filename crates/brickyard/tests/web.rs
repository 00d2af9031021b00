//! The web client end to end: `brickyard serve --web` serves the page and
//! a real volume, headless Chromium opens a link to a DVR view, and the
//! canvas must equal `brickyard render` of the same view within 2/255;
//! the link the page writes, opened without WebGPU, reopens the same view,
//! and the page says WebGPU is missing and still draws it; a bad view in
//! the link is an error that names its key. Also `serve --web` without a
//! built client: a clear error. Needs the bundle (`scripts/build-web.sh`, run by
//! `scripts/test.sh`), Node.js with the pinned playwright-core, and
//! Debian's chromium; `BRICKYARD_SKIP_BROWSER=1` opts out explicitly.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_brickyard"))
}

fn ok(o: &Output) -> String {
    assert!(
        o.status.success(),
        "failed: {}\n{}",
        String::from_utf8_lossy(&o.stderr),
        String::from_utf8_lossy(&o.stdout)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The built web client (`scripts/build-web.sh`): beside the binary's
/// directory, as `serve --web` looks for it.
fn dist() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_brickyard"))
        .parent()
        .unwrap()
        .parent()
        .unwrap()
        .join("web")
}

struct Served(Child, u16, String);

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn serve_web(store: &Path) -> Served {
    let mut child = bin()
        .args(["serve", "--web", "--quiet", "--port", "0"])
        .arg(store)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(child.stderr.take().unwrap());
    let (mut first, mut second) = (String::new(), String::new());
    err.read_line(&mut first).unwrap();
    err.read_line(&mut second).unwrap();
    let port: u16 = first
        .split("127.0.0.1:")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no address in {first:?}"));
    std::thread::spawn(move || {
        let mut l = String::new();
        while err.read_line(&mut l).unwrap_or(0) > 0 {
            l.clear();
        }
    });
    Served(child, port, second)
}

fn needs_browser() -> Option<()> {
    let have = Command::new("chromium")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success())
        && Command::new("node")
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
        && repo()
            .join("crates/brickyard-web/browser/node_modules/playwright-core")
            .is_dir()
        && dist().join("brickyard_web_bg.wasm").is_file();
    if have {
        return Some(());
    }
    if std::env::var("BRICKYARD_SKIP_BROWSER").as_deref() == Ok("1") {
        eprintln!("skipped: BRICKYARD_SKIP_BROWSER=1");
        return None;
    }
    panic!(
        "this test needs chromium, node, the web client built and its test driver installed \
         (bash scripts/build-web.sh); BRICKYARD_SKIP_BROWSER=1 opts out"
    );
}

/// The headless-browser check (`browser/e2e.mjs`) of the page at `url`,
/// its files in `out`; returns its report (JSON text).
fn e2e(url: &str, out: &Path) -> String {
    std::fs::create_dir_all(out).unwrap();
    browser_driver(
        "e2e",
        &["chromium".as_ref(), url.as_ref(), out.as_os_str()],
        &out.join("report.json"),
    )
}

/// `node browser/SCRIPT.mjs ARGS…` run to its end (a test driver in
/// headless Chromium), which writes its report `report` (JSON): the
/// report's text, the driver's failure with it when it failed.
fn browser_driver(script: &str, args: &[&std::ffi::OsStr], report: &Path) -> String {
    let o = Command::new("node")
        .arg(repo().join(format!("crates/brickyard-web/browser/{script}.mjs")))
        .args(args)
        .output()
        .unwrap();
    let text = std::fs::read_to_string(report).unwrap_or_default();
    assert!(
        o.status.success(),
        "the browser check failed:\n{}\n{text}",
        String::from_utf8_lossy(&o.stderr)
    );
    text
}

/// `../shared/data/FILE` converted into `dir/NAME`.
fn converted(dir: &Path, file: &str, name: &str) -> PathBuf {
    let store = dir.join(name);
    ok(&bin()
        .arg("convert")
        .arg(repo().join("../shared/data").join(file))
        .arg(&store)
        .arg("--quiet")
        .output()
        .unwrap());
    store
}

/// The MNI152 T1 converted into `dir/mni.ome.zarr`.
fn mni_t1(dir: &Path) -> PathBuf {
    converted(dir, "mni152-t1-u8.nii.gz", "mni.ome.zarr")
}

/// The nuclei stack converted into `dir` with `labels/cells` from
/// `process`; and the TIFF it came from.
fn nuclei_with_cells(dir: &Path) -> (PathBuf, PathBuf) {
    let store = converted(dir, "nuclei-confocal-u16.tif", "nuclei.ome.zarr");
    let input = repo().join("../shared/data/nuclei-confocal-u16.tif");
    ok(&bin()
        .arg("process")
        .arg(&store)
        .args([
            "gauss(1)|threshold(12000)|label(26)",
            "--out",
            "cells",
            "--quiet",
        ])
        .output()
        .unwrap());
    (store, input)
}

/// The largest difference between two RGBA buffers' bytes.
fn max_abs_diff(a: &[u8], b: &[u8]) -> u8 {
    a.iter().zip(b).map(|(a, b)| a.abs_diff(*b)).max().unwrap()
}

/// Pixels of an RGBA buffer brighter than 20 in some colour.
fn lit_pixels(rgba: &[u8]) -> usize {
    rgba.chunks_exact(4)
        .filter(|p| p[0].max(p[1]).max(p[2]) > 20)
        .count()
}

fn read_png(p: &Path) -> (u32, u32, Vec<u8>) {
    let d = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = d.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// `brickyard render` of `store` at `w`×`h` from azimuth `az` and
/// elevation `el` with the page's `tf=soft&window=0,255` (its bricks, on
/// the CPU) into `png`; the image read back.
fn render_soft(
    store: &Path,
    w: u32,
    h: u32,
    az: &str,
    el: &str,
    png: &Path,
) -> (u32, u32, Vec<u8>) {
    ok(&bin()
        .arg("render")
        .arg(store)
        .args([
            "--size",
            &format!("{w}x{h}"),
            "--azimuth",
            az,
            "--elevation",
            el,
        ])
        .args([
            "--tf",
            "soft",
            "--window",
            "0,255",
            "--brick",
            "32",
            "--backend",
            "cpu",
        ])
        .args(["--quiet", "-o"])
        .arg(png)
        .output()
        .unwrap());
    read_png(png)
}

#[test]
fn the_web_client_draws_what_render_draws_in_a_headless_browser() {
    if needs_browser().is_none() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let store = mni_t1(d.path());
    let srv = serve_web(&store);
    assert!(srv.2.contains("/web/#store=../mni.ome.zarr/"), "{}", srv.2);
    // backend=gpu: WebGPU also on a software adapter (SwiftShader here),
    // which the default (auto) leaves for the CPU.
    let view = "az=40&el=25&size=320x240&tf=soft&window=0,255";
    let url = format!(
        "http://127.0.0.1:{}/web/#store=..%2Fmni.ome.zarr%2F&backend=gpu&{view}",
        srv.1
    );
    let out = d.path().join("out");
    let report = e2e(&url, &out);
    eprintln!("{report}");
    let r: serde_json::Value = serde_json::from_str(&report).unwrap();
    // The same view by the command line.
    let (w, h, cli) = render_soft(&store, 320, 240, "40", "25", &d.path().join("cli.png"));
    assert_eq!(
        (r["width"].as_u64(), r["height"].as_u64()),
        (Some(w as u64), Some(h as u64))
    );
    let lit = lit_pixels(&cli);
    assert!(
        lit as u32 > w * h / 10,
        "the reference is nearly black ({lit} lit pixels)"
    );
    // The page drew through WebGPU where the browser has it (the first
    // page), and on the CPU in WebAssembly without it (the fallback page).
    let first = r["device"]
        .as_str()
        .map_or("the CPU (no WebGPU adapter)".to_string(), |d| {
            format!("WebGPU ({d})")
        });
    for (file, what) in [
        ("canvas.rgba", first),
        ("canvas-cpu.rgba", "the CPU (WebGPU hidden)".to_string()),
    ] {
        let canvas = std::fs::read(out.join(file)).unwrap();
        assert_eq!(canvas.len(), cli.len());
        let max = max_abs_diff(&canvas, &cli);
        eprintln!(
            "canvas drawn on {what} vs render: max difference {max}/255; {lit} lit pixels of {}",
            w * h
        );
        assert!(
            max <= 2,
            "the canvas drawn on {what} differs from brickyard render by {max}/255"
        );
    }
    if std::env::var("BRICKYARD_REQUIRE_GPU").as_deref() == Ok("1") {
        assert!(
            r["device"].is_string(),
            "CI requires the WebGPU path to be checked, but the page drew on the CPU: {report}"
        );
    }
    // The link, opened without WebGPU, reopens the same view: the page
    // says WebGPU is missing and draws the same pixels (compared above as
    // canvas-cpu.rgba, and by the page against its first canvas here).
    assert_eq!(r["reload_url"], r["url"]);
    assert!(r["url"].as_str().unwrap().contains("az=40"), "{report}");
    assert_eq!(r["fallback_webgpu"], false, "{report}");
    assert!(
        r["fallback_notice"]
            .as_str()
            .unwrap()
            .contains("WebGPU is not available"),
        "{report}"
    );
    assert!(r["fallback_max_diff"].as_u64().unwrap() <= 2, "{report}");
    assert!(
        r["bad_query_error"].as_str().unwrap().starts_with("mode:"),
        "{report}"
    );
    // The histogram shows the complete view's voxels.
    assert!(
        r["hist_bar_pixels"].as_u64().unwrap_or(0) > 100,
        "an empty histogram: {report}"
    );
}

/// A view turned with the mouse, as a user does: while it moves, frames
/// whose full-size redraw is slow are drawn smaller (the viewer's rule,
/// `budget::moving_scale`) and scaled onto the canvas, which keeps its
/// size and shows the volume; the moving view does not count as complete;
/// at rest the page draws it at full size again, equal to `render` of the
/// view it ended at.
#[test]
fn a_moving_view_is_drawn_smaller_and_at_rest_as_render_draws_it() {
    if needs_browser().is_none() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let store = mni_t1(d.path());
    let srv = serve_web(&store);
    // On the CPU (WebAssembly, one thread), large enough that a full
    // redraw takes longer than a moving frame may.
    let (w, h) = (960u32, 720u32);
    let url = format!(
        "http://127.0.0.1:{}/web/#store=..%2Fmni.ome.zarr%2F&backend=cpu&az=40&el=25&size={w}x{h}&tf=soft&window=0,255",
        srv.1
    );
    let out = d.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    let report = browser_driver(
        "moving",
        &["chromium".as_ref(), out.as_os_str(), url.as_ref()],
        &out.join("moving.json"),
    );
    let r: serde_json::Value = serde_json::from_str(&report).unwrap();
    // The first frame of the drag is drawn at full size and measured (the
    // page's first frame, which also sets up, is not); the later ones at
    // the rule's fraction of it. Every frame the page drew during the drag
    // is checked against the rule, with what the page knew when it drew
    // it (the last full-size redraw's time, the last moving frame's size):
    // whether a frame counts as moving depends on how soon it follows a
    // pointer move, which a busy machine stretches, so only the moving
    // ones are held to it.
    assert_eq!(r["before"]["scale"], 1.0, "{report}");
    assert_eq!(r["before"]["moving"], false, "{report}");
    let log = r["drag_log"].as_array().unwrap();
    let (mut full_ms, mut last, mut frames) = (
        r["before"]["full_ms"].as_f64().unwrap(),
        1.0,
        r["before"]["frames"].as_u64().unwrap(),
    );
    let (mut moving, mut smaller) = (0, Vec::new());
    for s in log {
        let n = s["frames"].as_u64().unwrap();
        if n != frames {
            assert_eq!(n, frames + 1, "a frame is missing from the log: {report}");
            if s["moving"] == true {
                moving += 1;
                let k = brickyard_render::budget::moving_scale(full_ms, last);
                let scale = s["scale"].as_f64().unwrap();
                assert!(
                    (scale - k).abs() < 1e-9,
                    "a moving frame at {scale} of the size, the rule says {k} \
                     (last full-size redraw {full_ms} ms, last moving frame {last}): {s}"
                );
                if scale < 1.0 {
                    assert!(full_ms > 40.0, "{s}");
                    assert_eq!(
                        s["complete"], false,
                        "a smaller frame counted as complete: {s}"
                    );
                    smaller.push((full_ms, scale));
                }
                last = scale;
            } else {
                assert_eq!(s["scale"], 1.0, "a frame at rest drawn smaller: {s}");
            }
            frames = n;
        }
        full_ms = s["full_ms"].as_f64().unwrap();
    }
    assert!(
        moving >= 3 && smaller.len() >= 2,
        "{moving} frames of the drag were drawn as moving, {} of them smaller: {report}",
        smaller.len()
    );
    eprintln!(
        "full-size redraw {:.1} ms: moving frames at {:.3} of the size ({} of {moving} moving frames)",
        smaller[0].0,
        smaller[0].1,
        smaller.len()
    );
    // Mid-drag the canvas keeps its size and shows the volume.
    let mid = &r["mid_canvas"];
    assert_eq!(
        (mid["width"].as_u64(), mid["height"].as_u64()),
        (Some(w as u64), Some(h as u64)),
        "{report}"
    );
    assert!(
        mid["lit"].as_u64().unwrap() > (w * h / 20) as u64,
        "the canvas mid-drag is nearly black: {report}"
    );
    // The status line says so while the view is drawn smaller (any of the
    // texts it showed during the drag: between two pointer moves a frame
    // of an unmoved camera is drawn at full size).
    assert!(
        r["drag_text"]
            .as_array()
            .unwrap()
            .iter()
            .any(|t| t.as_str().unwrap().contains("while moving")),
        "{report}"
    );
    // At rest: full size, complete, the view it ended at as render draws it,
    // redrawn in parts (slower than a part may take: the page's thread is
    // let go between them).
    assert_eq!(r["end"]["scale"], 1.0, "{report}");
    let (full_ms, parts) = (
        r["end"]["full_ms"].as_f64().unwrap(),
        r["end"]["full_parts"].as_u64().unwrap(),
    );
    assert!(
        full_ms > 80.0 && parts >= 2,
        "the redraw at rest ({full_ms} ms) was not drawn in parts: {report}"
    );
    eprintln!(
        "at rest: redrawn in {full_ms:.1} ms in {parts} parts; the page's tasks over 50 ms meanwhile: {}",
        r["rest_long_tasks"]
    );
    let end_url = r["url"].as_str().unwrap();
    let key = |k: &str| {
        end_url
            .split(['#', '&'])
            .find_map(|p| p.strip_prefix(&format!("{k}=")))
            .unwrap_or_else(|| panic!("no {k}= in {end_url}"))
            .to_string()
    };
    let (az, el) = (key("az"), key("el"));
    assert_ne!(az, "40", "the drag did not turn the view: {end_url}");
    let (cw, ch, cli) = render_soft(&store, w, h, &az, &el, &d.path().join("cli.png"));
    assert_eq!((cw, ch), (w, h));
    assert!(
        lit_pixels(&cli) as u32 > w * h / 20,
        "the reference is nearly black"
    );
    let end = std::fs::read(out.join("end.rgba")).unwrap();
    let max = max_abs_diff(&end, &cli);
    eprintln!("the view at rest (az {az}, el {el}) vs render: max difference {max}/255");
    assert!(
        max <= 2,
        "the view at rest differs from render by {max}/255"
    );
}

/// Pages drawn in headless Chromium (`browser/canvas.mjs`), each `(name,
/// url)`; their canvases as `out/NAME.rgba`; returns the report.
fn canvases(out: &Path, pages: &[(&str, String)]) -> serde_json::Value {
    std::fs::create_dir_all(out).unwrap();
    let specs: Vec<String> = pages.iter().map(|(n, u)| format!("{n}={u}")).collect();
    let mut args: Vec<&std::ffi::OsStr> = vec!["chromium".as_ref(), out.as_os_str()];
    args.extend(specs.iter().map(std::ffi::OsStr::new));
    let report = browser_driver("canvas", &args, &out.join("canvas.json"));
    serde_json::from_str(&report).unwrap()
}

#[test]
fn the_web_client_draws_several_channels_through_webgpu_and_the_octree_as_render_does() {
    if needs_browser().is_none() {
        return;
    }
    // The three-channel MNI152 (T1, grey and white matter), its channels
    // composited per sample in the `omero` colours and windows.
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("mni3.ome.zarr");
    let data = repo().join("../shared/data");
    ok(&bin()
        .arg("convert")
        .args(["t1", "gm", "wm"].map(|c| data.join(format!("mni152-{c}-u8.nii.gz"))))
        .arg(&store)
        .args(["--channel-names", "t1,gm,wm", "--quiet"])
        .output()
        .unwrap());
    let srv = serve_web(&store);
    let base = format!(
        "http://127.0.0.1:{}/web/#store=..%2Fmni3.ome.zarr%2F",
        srv.1
    );
    let view = "az=40&el=25&size=160x120";
    let out = d.path().join("out");
    let r = canvases(
        &out,
        &[
            ("gpu", format!("{base}&backend=gpu&{view}")),
            ("auto", format!("{base}&{view}")),
            // The residency octree, through WebGPU and on the CPU.
            (
                "gpu-octree",
                format!("{base}&backend=gpu&{view}&traversal=octree&octree_depth=3"),
            ),
            (
                "cpu-octree",
                format!("{base}&backend=cpu&{view}&traversal=octree&octree_depth=3"),
            ),
        ],
    );
    let cli_render = |traversal: &str, more: &[&str]| {
        let png = d.path().join(format!("cli-{traversal}.png"));
        ok(&bin()
            .arg("render")
            .arg(&store)
            .args(more)
            .args([
                "--size",
                "160x120",
                "--azimuth",
                "40",
                "--elevation",
                "25",
                "--brick",
                "32",
                "--traversal",
                traversal,
                "--backend",
                "cpu",
                "--quiet",
                "-o",
            ])
            .arg(&png)
            .output()
            .unwrap());
        read_png(&png)
    };
    let (w, h, cli) = cli_render("page-table", &[]);
    let (_, _, cli_octree) = cli_render("octree", &["--octree-depth", "3"]);
    let lit = lit_pixels(&cli);
    assert!(
        lit as u32 > w * h / 10,
        "the reference is nearly black ({lit} lit pixels)"
    );
    // Each channel shows: neither grey (T1 alone) nor one hue.
    let hue = |k: usize| {
        cli.chunks_exact(4)
            .filter(|p| p[k] > p[(k + 1) % 3] + 30)
            .count()
    };
    assert!(
        hue(1) > 50 && (hue(0) > 50 || hue(2) > 50),
        "one channel only?"
    );
    for name in ["gpu", "auto", "gpu-octree", "cpu-octree"] {
        let canvas = std::fs::read(out.join(format!("{name}.rgba"))).unwrap();
        let cli = if name.ends_with("octree") {
            // The page wrote the traversal into its link and its control.
            assert!(
                r[name]["url"]
                    .as_str()
                    .unwrap()
                    .contains("traversal=octree&octree_depth=3"),
                "{r}"
            );
            assert_eq!(r[name]["traversal"], "octree", "{r}");
            &cli_octree
        } else {
            &cli
        };
        assert_eq!(canvas.len(), cli.len());
        let max = max_abs_diff(&canvas, cli);
        eprintln!(
            "{name} page, drawn on {}: max difference {max}/255",
            r[name]["device"]
        );
        assert!(
            max <= 2,
            "the {name} page differs from brickyard render by {max}/255: {r}"
        );
    }
    let gpu = r["gpu"]["device"].as_str();
    if std::env::var("BRICKYARD_REQUIRE_GPU").as_deref() == Ok("1") {
        assert!(
            gpu.is_some(),
            "CI requires the WebGPU path to be checked: {r}"
        );
    }
    // The frames compared were the device's, not a CPU fallback's.
    assert_eq!(r["gpu"]["status"]["on_device"], gpu.is_some(), "{r}");
    assert_eq!(r["gpu-octree"]["status"]["on_device"], gpu.is_some(), "{r}");
    assert_eq!(r["cpu-octree"]["status"]["on_device"], false, "{r}");
    // The default leaves a software adapter (isFallbackAdapter: "Cpu") for
    // the CPU in WebAssembly, and says why; a hardware one it uses.
    // The adapter named for people, not wgpu's debug fields.
    if let Some(g) = gpu {
        let notice = r["gpu"]["notice"].as_str().unwrap();
        assert!(
            !g.contains("Cpu") && !g.contains("driver") && !notice.contains("( ("),
            "{g}: {notice}"
        );
    }
    match gpu {
        Some(g) if g.contains("software") => {
            assert!(r["auto"]["device"].is_null(), "{r}");
            assert_eq!(r["auto"]["status"]["on_device"], false, "{r}");
            let notice = r["auto"]["notice"].as_str().unwrap();
            assert!(
                notice.contains("software") && notice.contains("backend=gpu"),
                "{notice}"
            );
        }
        Some(g) => assert_eq!(r["auto"]["device"].as_str(), Some(g), "{r}"),
        None => assert!(r["auto"]["device"].is_null(), "{r}"),
    }
}

#[test]
fn serve_web_without_a_built_client_says_how_to_build_it() {
    let d = tempfile::tempdir().unwrap();
    let o = bin()
        .args(["serve", "--web", "--port", "0", "--web-dist"])
        .arg(d.path())
        .arg(d.path())
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("--web") && e.contains("build-web.sh"), "{e}");
}

#[test]
fn the_web_client_lays_label_images_over_slices_as_render_does() {
    if needs_browser().is_none() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let (store, _) = nuclei_with_cells(d.path());
    let srv = serve_web(&store);
    let view = "mode=slice&size=200x180&slice=0.45&tf=linear&window=0,40000&labels=cells&label_opacity=0.7&only_labels=2,4-6";
    let url = format!(
        "http://127.0.0.1:{}/web/#store=..%2Fnuclei.ome.zarr%2F&backend=gpu&{view}",
        srv.1
    );
    let out = d.path().join("out");
    let report = e2e(&url, &out);
    let r: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert_eq!(r["status"]["labels"]["complete"], true, "{report}");
    assert!(
        r["url"].as_str().unwrap().contains("only_labels=2,4-6"),
        "{report}"
    );
    // The image's slice with the labels over it, and the image alone, by
    // the command line.
    let render = |name: &str, labels: bool| {
        let png = d.path().join(name);
        let mut c = bin();
        c.arg("render").arg(&store).args([
            "--mode",
            "slice",
            "--size",
            "200x180",
            "--slice-z",
            "0.45",
            "--tf",
            "linear",
            "--window",
            "0,40000",
            "--brick",
            "32",
            "--backend",
            "cpu",
            "--quiet",
        ]);
        if labels {
            c.args([
                "--labels",
                "cells",
                "--label-opacity",
                "0.7",
                "--only-labels",
                "2,4-6",
            ]);
        }
        ok(&c.arg("-o").arg(&png).output().unwrap());
        read_png(&png).2
    };
    let (cli, plain) = (render("cli.png", true), render("plain.png", false));
    let coloured = cli
        .chunks_exact(4)
        .zip(plain.chunks_exact(4))
        .filter(|(a, b)| (0..3).any(|i| a[i].abs_diff(b[i]) > 12))
        .count();
    assert!(coloured > 500, "the labels change {coloured} pixels");
    for file in ["canvas.rgba", "canvas-cpu.rgba"] {
        let canvas = std::fs::read(out.join(file)).unwrap();
        assert_eq!(canvas.len(), cli.len());
        let max = max_abs_diff(&canvas, &cli);
        eprintln!("{file}: max difference {max}/255 from render --labels; labels change {coloured} pixels");
        assert!(max <= 2, "{file} differs from render --labels by {max}/255");
    }
}

#[test]
fn the_web_pages_readout_names_the_voxel_and_a_click_picks_its_label() {
    use brickyard_store::VolumeSource;
    if needs_browser().is_none() {
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let (store, input) = nuclei_with_cells(d.path());
    let srv = serve_web(&store);
    // Level 0 everywhere (a slice larger than the volume's 256 × 256): the
    // readout reads the voxels themselves.
    let url = format!(
        "http://127.0.0.1:{}/web/#store=..%2Fnuclei.ome.zarr%2F&backend=gpu&mode=slice&size=560x540&slice=0.45&tf=linear&window=0,40000&labels=cells",
        srv.1
    );
    let run = |url: &str, name: &str| {
        let out = d.path().join(name);
        std::fs::create_dir_all(&out).unwrap();
        let report = browser_driver(
            "readout",
            &["chromium".as_ref(), url.as_ref(), out.as_os_str()],
            &out.join("readout.json"),
        );
        let r: serde_json::Value = serde_json::from_str(&report).unwrap();
        // A click on the label read out picks it; a second unpicks it.
        let id = r["label"].as_u64().unwrap();
        let after = r["hash_after_click"].as_str().unwrap();
        assert!(after.contains(&format!("only_labels={id}")), "{report}");
        let again = r["hash_after_second_click"].as_str().unwrap();
        assert!(!again.contains("only_labels"), "{report}");
        (r, report)
    };
    let (r, report) = run(&url, "slice");
    // Every readout line names the voxel's value and label as the files
    // hold them.
    let read = |src: &dyn VolumeSource| {
        let dm = src.meta().dims;
        let mut b = vec![0u8; dm.iter().product::<u64>() as usize * src.meta().dtype.size()];
        src.read_region(0, 0..dm[0], 0..dm[1], 0..dm[2], &mut b)
            .unwrap();
        (b, dm)
    };
    let (tif, dm) = read(&brickyard_store::import::tiff::open(&input).unwrap());
    let (lab, _) =
        read(&brickyard_store::import::zarr::open(&store.join("labels/cells"), 0).unwrap());
    let mut checked = 0;
    for l in r["lines"].as_array().unwrap() {
        let t = l["text"].as_str().unwrap();
        if t.is_empty() {
            continue;
        }
        // "voxel x X y Y z Z: V · label L"
        let n: Vec<f64> = t
            .split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .filter(|x| !x.is_empty())
            .map(|x| x.parse().unwrap())
            .collect();
        assert_eq!(n.len(), 5, "{t}");
        let (x, y, z) = (n[0] as u64, n[1] as u64, n[2] as u64);
        let i = ((z * dm[1] + y) * dm[2] + x) as usize;
        let v = u16::from_ne_bytes([tif[2 * i], tif[2 * i + 1]]) as f64;
        let id = u32::from_ne_bytes(lab[4 * i..4 * i + 4].try_into().unwrap()) as f64;
        assert_eq!((n[3], n[4]), (v, id), "{t}");
        checked += 1;
    }
    assert!(checked > 10, "{checked} readout lines checked: {report}");
    // The label image itself in 3D: the readout names the first label its
    // surfaces draw along the pointer's ray, and a click picks it.
    let url = format!(
        "http://127.0.0.1:{}/web/#store=..%2Fnuclei.ome.zarr%2Flabels%2Fcells%2F&mode=dvr&size=400x320&tf=labels",
        srv.1
    );
    let (r, report) = run(&url, "3d");
    let lines: Vec<&str> = r["lines"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|l| l["text"].as_str())
        .filter(|t| !t.is_empty())
        .collect();
    assert!(lines.len() >= 5, "{report}");
    for t in &lines {
        assert!(
            t.starts_with("the first label drawn") && t.contains(" · label "),
            "{t}"
        );
    }
}

/// What the page tells its user (`browser/status.mjs`) of each `(name,
/// url)`, waited for up to `wait_ms` each.
fn page_status(out: &Path, wait_ms: u64, pages: &[(&str, String)]) -> serde_json::Value {
    std::fs::create_dir_all(out).unwrap();
    let mut args: Vec<std::ffi::OsString> = vec![
        "chromium".into(),
        out.as_os_str().into(),
        wait_ms.to_string().into(),
    ];
    args.extend(pages.iter().map(|(n, u)| format!("{n}={u}").into()));
    let refs: Vec<&std::ffi::OsStr> = args.iter().map(|a| a.as_os_str()).collect();
    serde_json::from_str(&browser_driver("status", &refs, &out.join("status.json"))).unwrap()
}

#[test]
fn the_page_says_plainly_what_went_wrong() {
    if needs_browser().is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = mni_t1(dir.path());
    // A lost shard: its bricks fail (drawn from coarser data) where the
    // statistics say they hold data, as `render` reports; not read as fill.
    std::fs::remove_file(store.join("0/c/0/0/0")).unwrap();
    // A label image on another grid than the image's.
    let raw = dir.path().join("small.raw");
    std::fs::write(&raw, [1u8; 8 * 8 * 8]).unwrap();
    let o = bin()
        .args([
            "convert", "--labels", "--dims", "8x8x8", "--dtype", "u8", "--quiet",
        ])
        .arg(&raw)
        .arg(store.join("labels").join("small"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let served = serve_web(&store);
    let page = |q: &str| {
        format!(
            "http://127.0.0.1:{}/web/#store=..%2Fmni.ome.zarr%2F&backend=cpu&size=128x128{q}",
            served.1
        )
    };
    // A server not there: what that means, not `{}`.
    let nothing = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let gone = nothing.local_addr().unwrap().port();
    drop(nothing);
    let r = page_status(
        &dir.path().join("out"),
        60_000,
        &[
            ("lost", page("&mode=slice&slice=0.25&zoom=1")),
            (
                "gone",
                format!(
                    "http://127.0.0.1:{}/web/#store=http%3A%2F%2F127.0.0.1%3A{gone}%2Fx.ome.zarr%2F&backend=cpu",
                    served.1
                ),
            ),
            ("slice_in_dvr", page("&slice=0.3")),
            ("twice", page("&channels=0,0")),
            ("grid", page("&mode=slice&labels=small")),
            // Keys the page does not know, or given twice: refused by
            // name, not dropped or the last one taken.
            ("unknown", page("&frobnicate=1")),
            ("typo", page("&windw=0,100")),
            ("repeated", page("&mode=mip&mode=slice")),
            // A bias out of range: refused, not clamped; one in range:
            // said to be asked for, not blamed on the pool.
            ("bias99", page("&bias=99")),
            ("bias2", page("&bias=2")),
        ],
    );
    let e = r["unknown"]["error"].as_str().unwrap_or_default();
    assert!(
        e.starts_with("frobnicate: not a key of the page's URL"),
        "{}",
        r["unknown"]
    );
    let e = r["typo"]["error"].as_str().unwrap_or_default();
    assert!(
        e.starts_with("windw:") && e.contains("did you mean window?"),
        "{}",
        r["typo"]
    );
    let e = r["repeated"]["error"].as_str().unwrap_or_default();
    assert!(
        e.starts_with("mode: given twice (\"mip\" and \"slice\")"),
        "{}",
        r["repeated"]
    );
    let e = r["bias99"]["error"].as_str().unwrap_or_default();
    assert!(
        e.starts_with("bias:") && e.contains("-8 to 8") && e.contains("99"),
        "{}",
        r["bias99"]
    );
    let b2 = &r["bias2"];
    assert!(
        b2["error"].is_null() && b2["status"]["complete"] == true,
        "{b2}"
    );
    let text = b2["text"].as_str().unwrap();
    assert!(
        text.contains("LOD bias +2, as asked for") && !text.contains("pool is too small"),
        "{text}"
    );
    let lost = &r["lost"];
    assert!(lost["error"].is_null(), "{lost}");
    let text = lost["text"].as_str().unwrap();
    assert!(lost["status"]["failed"].as_u64().unwrap() > 0, "{lost}");
    assert!(
        text.contains("failing bricks")
            && text.contains("0/c/0/0/0")
            && text.contains("statistics")
            && text.contains("level 0, channel 0, brick (z")
            && !text.contains("BrickKey"),
        "{text}"
    );
    // Once complete, no rate of a read that is over.
    if lost["status"]["complete"] == true {
        assert!(!text.contains("MiB/s"), "{text}");
    }
    let e = r["gone"]["error"].as_str().unwrap();
    assert!(
        e.contains("could not reach the server") && !e.contains("{}"),
        "{e}"
    );
    let e = r["slice_in_dvr"]["error"].as_str().unwrap();
    assert!(e.starts_with("slice:") && e.contains("mode=slice"), "{e}");
    let e = r["twice"]["error"].as_str().unwrap();
    assert!(e.contains("channel 0 given twice"), "{e}");
    // Refused as `render --labels` refuses it, not drawn nowhere.
    let e = r["grid"]["error"].as_str().unwrap();
    assert!(
        e.contains("labels/small") && e.contains("drawn over the grid"),
        "{e}"
    );
    drop(served);

    // A token refused is not a token missing.
    let mut secured = bin()
        .args([
            "serve", "--web", "--quiet", "--port", "0", "--token", "s3cret",
        ])
        .arg(&store)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = BufReader::new(secured.stderr.take().unwrap());
    let mut first = String::new();
    err.read_line(&mut first).unwrap();
    let port: u16 = first
        .split("127.0.0.1:")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .and_then(|p| p.parse().ok())
        .unwrap_or_else(|| panic!("no address in {first:?}"));
    let url =
        |t: &str| format!("http://127.0.0.1:{port}/web/#store=..%2Fmni.ome.zarr%2F&backend=cpu{t}");
    let r = page_status(
        &dir.path().join("out2"),
        30_000,
        &[("wrong", url("&token=wrong")), ("none", url(""))],
    );
    let _ = secured.kill();
    let _ = secured.wait();
    let e = r["wrong"]["error"].as_str().unwrap();
    assert!(e.contains("401") && e.contains("refused the token"), "{e}");
    let e = r["none"]["error"].as_str().unwrap();
    assert!(e.contains("401") && e.contains("needs a token"), "{e}");
}
