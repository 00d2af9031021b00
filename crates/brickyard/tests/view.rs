//! The viewer in a real window (under Xvfb when no display is set), driven
//! by a script of input events: every view it saves, once complete, equals
//! `brickyard render` of the same camera and transfer function, and frames
//! kept coming while bricks were still loading. Needs Xvfb (`xvfb-run`);
//! `BRICKYARD_SKIP_VIEW=1` opts out explicitly.

use std::path::Path;
use std::process::{Command, Output};

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_brickyard")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn png_pixels(p: &Path) -> (u32, u32, Vec<u8>) {
    let d = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(p).unwrap()));
    let mut r = d.read_info().unwrap();
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let info = r.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// Render the view the viewer saved as `dir/NAME.args` with `brickyard
/// render` and check it equals the viewer's `dir/NAME.png` within 1/255;
/// returns the viewer's pixels (RGBA).
fn equals_render(store: &Path, dir: &Path, name: &str) -> Vec<u8> {
    let p = |n: String| dir.join(n);
    let args = std::fs::read_to_string(p(format!("{name}.args"))).unwrap();
    let reference = p(format!("{name}-render.png"));
    let o = Command::new(bin())
        .args(["render", s(store)])
        .args(args.lines())
        .args(["--out", s(&reference), "--pool", "4MiB", "--brick", "8"])
        .args(["--backend", "cpu", "--quiet"])
        .output()
        .unwrap();
    assert!(o.status.success(), "render {name}: {}", stderr(&o));
    let (w, h, a) = png_pixels(&p(format!("{name}.png")));
    let (w2, h2, b) = png_pixels(&reference);
    assert_eq!((w, h), (w2, h2), "{name}: sizes");
    let worst = a.iter().zip(&b).map(|(x, y)| x.abs_diff(*y)).max().unwrap();
    assert!(
        worst <= 1,
        "{name}: the viewer's image and render's differ by {worst}"
    );
    a
}

/// A command with a display: the current one, or a virtual one.
fn with_display(args: &[&str]) -> Option<Command> {
    if std::env::var_os("DISPLAY").is_some() {
        let mut c = Command::new(bin());
        c.args(args);
        return Some(c);
    }
    let have_xvfb = Command::new("xvfb-run").arg("--help").output().is_ok();
    if !have_xvfb {
        if std::env::var("BRICKYARD_SKIP_VIEW").as_deref() == Ok("1") {
            eprintln!("viewer test skipped: BRICKYARD_SKIP_VIEW=1 and no display");
            return None;
        }
        panic!("the viewer test needs a display or xvfb-run (apt-get install xvfb); BRICKYARD_SKIP_VIEW=1 opts out");
    }
    let mut c = Command::new("xvfb-run");
    c.args(["-a", "-s", "-screen 0 1600x1000x24", bin()])
        .args(args);
    Some(c)
}

#[test]
fn viewer_views_equal_render_and_stream_while_loading() {
    viewer_case("cpu");
}

#[test]
fn viewer_on_the_device_equals_render() {
    // The same script with the viewer drawing on the GPU back end (lavapipe
    // in CI), against `render` on the CPU.
    if brickyard_gpu::context::test_gpu().is_none() {
        return; // BRICKYARD_SKIP_GPU=1
    }
    viewer_case("gpu");
}

fn viewer_case(backend: &str) {
    let d = tempfile::tempdir().unwrap();
    let store = d.path().join("m.ome.zarr");
    let o = Command::new(bin())
        .args([
            "generate",
            "mandelbulb",
            s(&store),
            "--size",
            "48",
            "--quiet",
        ])
        .args(["--brick", "16", "--shard", "32"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let p = |n: &str| d.path().join(n);
    let script = format!(
        "# sizes fixed so that images compare pixel for pixel
size 3d 96 80
size xy 64 64
size xz 64 56
size yz 56 64
size oblique 64 64
wait-complete 300
expect-streaming 3d 2
screenshot 3d {dvr}.png
save-view 3d {dvr}
drag 3d left 40 -15
scroll 3d 1
drag 3d right 6 4
key left
tf hot
window 30 230
point 0.5 0.9
mode mip
wait-complete 300
screenshot 3d {mip}.png
save-view 3d {mip}
cursor 0.4 0.55 0.6
oblique 40 25
drag xy left 5 3
scroll xz 1
drag yz right 6 -4
click oblique 20 30
level 0
wait-complete 300
screenshot xy {xy}.png
save-view xy {xy}
screenshot xz {xz}.png
save-view xz {xz}
screenshot yz {yz}.png
save-view yz {yz}
screenshot oblique {ob}.png
save-view oblique {ob}
level auto
lod-bias 0.5
mode slice
wait-complete 300
screenshot 3d {sl}.png
save-view 3d {sl}
window-shot {win}
quit
",
        dvr = s(&p("dvr")),
        mip = s(&p("mip")),
        xy = s(&p("xy")),
        xz = s(&p("xz")),
        yz = s(&p("yz")),
        ob = s(&p("oblique")),
        sl = s(&p("slice3d")),
        win = s(&p("window.png")),
    );
    std::fs::write(p("s.txt"), script).unwrap();
    let log = p("log.jsonl");
    let Some(mut cmd) = with_display(&[
        "view",
        s(&store),
        "--script",
        s(&p("s.txt")),
        "--log",
        s(&log),
        "--pool",
        "4MiB",
        "--brick",
        "8",
        "--backend",
        backend,
        "--read-delay-ms",
        "15",
        "--window-size",
        "1000x700",
    ]) else {
        return;
    };
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "viewer: {}\n{}",
        stderr(&o),
        String::from_utf8_lossy(&o.stdout)
    );
    // Each saved view against `brickyard render` with its arguments.
    for name in ["dvr", "mip", "xy", "xz", "yz", "oblique", "slice3d"] {
        let a = equals_render(&store, d.path(), name);
        let lit = a
            .chunks(4)
            .filter(|c| c[0] as u32 + c[1] as u32 + c[2] as u32 > 30)
            .count();
        assert!(
            lit > a.len() / 4 / 20,
            "{name}: image nearly black ({lit} lit pixels)"
        );
    }
    // Frames kept coming while bricks loaded: partial frames of the first
    // view, no long gap between them, then a complete one.
    let text = std::fs::read_to_string(&log).unwrap();
    let frames: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .filter(|v: &serde_json::Value| v["view"] == "3d" && v["version"] == 1)
        .collect();
    let first_complete = frames
        .iter()
        .position(|v| v["completeness"].as_f64().unwrap() >= 1.0)
        .expect("the first 3D view completes");
    assert!(
        first_complete >= 2,
        "{first_complete} partial frames before completion"
    );
    let times: Vec<f64> = frames[..=first_complete]
        .iter()
        .map(|v| v["t"].as_f64().unwrap())
        .collect();
    let gap = times.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
    assert!(
        gap < 2.0,
        "a gap of {gap:.2} s between frames while loading"
    );
    let (w, h, px) = png_pixels(&p("window.png"));
    assert!(w >= 600 && h >= 400, "window shot {w}x{h}");
    assert!(px.chunks(4).any(|c| c[0] > 100), "window shot is blank");
}

#[test]
fn viewer_adds_channels_up_as_render_does() {
    let d = tempfile::tempdir().unwrap();
    let p = |n: &str| d.path().join(n);
    // Two channels, one after the other in one raw file.
    let mut bytes = vec![];
    for kind in ["mandelbulb", "marschner-lobb"] {
        let raw = p(&format!("{kind}.raw"));
        let o = Command::new(bin())
            .args(["generate", kind, s(&raw), "--size", "40x36x32", "--quiet"])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        bytes.extend(std::fs::read(&raw).unwrap());
    }
    std::fs::write(p("two.raw"), bytes).unwrap();
    let store = p("two.ome.zarr");
    let o = Command::new(bin())
        .args(["convert", s(&p("two.raw")), s(&store), "--dims", "40x36x32"])
        .args([
            "--dtype",
            "u8",
            "--channels",
            "2",
            "--brick",
            "16",
            "--quiet",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let script = format!(
        "size 3d 80 64
size xy 48 48
size xz 48 40
size yz 40 48
size oblique 48 48
channel-color 0 ff3000
channel-window 0 0 220
channel-color 1 00c0ff
channel-window 1 40 200
mode mip
wait-complete 300
screenshot 3d {mip}.png
save-view 3d {mip}
screenshot xz {xz}.png
save-view xz {xz}
channel 0 off
wait-complete 300
screenshot xy {one}.png
save-view xy {one}
quit
",
        mip = s(&p("mip")),
        xz = s(&p("xz")),
        one = s(&p("one")),
    );
    std::fs::write(p("s.txt"), script).unwrap();
    let Some(mut cmd) = with_display(&[
        "view",
        s(&store),
        "--script",
        s(&p("s.txt")),
        "--pool",
        "4MiB",
        "--brick",
        "8",
        "--backend",
        "cpu",
        "--window-size",
        "900x600",
    ]) else {
        return;
    };
    let o = cmd.output().unwrap();
    assert!(o.status.success(), "viewer: {}", stderr(&o));
    for name in ["mip", "xz", "one"] {
        let args = std::fs::read_to_string(p(&format!("{name}.args"))).unwrap();
        let want_channels = if name == "one" { 1 } else { 2 };
        assert_eq!(
            args.lines().filter(|l| *l == "--channel").count(),
            want_channels,
            "{name}: {args}"
        );
        let a = equals_render(&store, d.path(), name);
        // Both colours show where both channels are visible.
        let red = a.chunks(4).filter(|c| c[0] > 60).count();
        let blue = a.chunks(4).filter(|c| c[2] > 60).count();
        if name == "one" {
            assert!(
                red < a.len() / 400 && blue > 0,
                "{name}: red {red} blue {blue}"
            );
        } else {
            assert!(red > 0 && blue > 0, "{name}: red {red} blue {blue}");
        }
    }
}
