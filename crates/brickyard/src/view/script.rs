//! `brickyard view --script FILE`: input events and checks, one per line,
//! run in order by the window (each through the same handler a mouse or
//! key event uses). `#` starts a comment. Commands:
//!
//! | command | effect |
//! |---|---|
//! | `size VIEW W H` | draw view VIEW (`3d`, `xy`, `xz`, `yz`, `oblique`) at W×H pixels, whatever its place on screen |
//! | `mode dvr\|mip\|slice` | the 3D view's mode |
//! | `drag VIEW BUTTON DX DY` | a drag by (DX, DY) pixels with `left`, `right` or `middle` (3D: orbit, pan; slices: cursor, pan) |
//! | `scroll VIEW STEPS` | the mouse wheel (zoom; positive: in) |
//! | `click VIEW X Y` | a click at pixel (X, Y) of the view: slices move the cursor there; `3d`, as a double-click, moves it to the point the pixel shows (the MIP's maximum, where the DVR's opacity reaches 1/2, or the first label drawn; waits for the readout) |
//! | `hover VIEW X Y` / `hover off` | the pointer at pixel (X, Y) of VIEW (the voxel readout reads the voxel there; in `3d`, at the point the pixel shows), or gone (it reads the voxel at the cursor) |
//! | `pick VIEW X Y` | Ctrl+click at pixel (X, Y) of VIEW: the label there (in `3d`, of a label image in DVR mode: the first label drawn along the pixel's ray) joins the labels picked, or leaves them (waits for the readout) |
//! | `label-select IDS\|none` / `label-mode all\|only\|hide` | the labels picked (`3,17,40-45`); which labels a label image draws: all, only those picked, all but them |
//! | `largest-labels N` | read the N labels of most voxels from the label statistics (the controls' table; logged as `"largest"`) |
//! | `labels-table N voxels\|mean\|label asc\|desc [MIN]` | the table's first N rows sorted so, of labels of at least MIN voxels (logged as `"largest"`, with `"means"`) |
//! | `goto-label ID` | the cursor to the label's centroid, by the label statistics (waits for them) |
//! | `wait-probe [SECONDS]` | wait until the voxel readout answered for the voxel it reads now (default 60 s) |
//! | `key NAME` | a key: `left`, `right`, `up`, `down` (orbit), `plus`, `minus` (zoom), `r` (reset) |
//! | `tf PRESET` | a transfer-function preset |
//! | `colormap NAME` | a colour map |
//! | `window LO HI` | the data window |
//! | `point X ALPHA` | add an opacity point (x in [0, 1] of the window) |
//! | `cursor X Y Z` | the cursor, as fractions of the volume |
//! | `channel C on\|off` / `channel-color C RRGGBB` / `channel-window C LO HI` | a channel's visibility, colour and window (MIP and slices add the visible ones up) |
//! | `dvr-channel C` | the channel a DVR shows |
//! | `dvr-channels on\|off` | DVR composites the visible channels (each in its colour and window) or shows the DVR channel |
//! | `stereo off\|sbs\|anaglyph` / `views N` | the 3D view as a stereo pair (side by side, red–cyan) or N views tiled (slice mode: a super-slice) |
//! | `apply NAME` | write the derived channel shown into the store as NAME, at every level, in the background (the panel's "Apply to whole volume") |
//! | `wait-job [SECONDS]` | wait until the job ends (default 600 s); fail if it failed |
//! | `derive PIPELINE` / `derive off` | show the live derived channel of PIPELINE (as the processing panel does) over the DVR channel; `off`: the stored data |
//! | `labels on\|off` / `label-opacity A` | the label image of `--labels NAME` over the slices, and how opaque it is |
//! | `oblique AZIMUTH ELEVATION` | the oblique plane's normal, in degrees |
//! | `lod-bias B` / `level L\|auto` / `quality S` | level of detail; samples per voxel |
//! | `wait-complete [SECONDS]` | wait until every view is complete (default 120 s) |
//! | `screenshot VIEW FILE.png` | write the view's last complete image |
//! | `save-view VIEW PREFIX` | write PREFIX.camera.json, PREFIX.tf.json and PREFIX.args (the `brickyard render` arguments for the same image) |
//! | `window-shot FILE.png` | a screenshot of the whole window |
//! | `touch FILE` | create FILE (empty), e.g. to tell a process driving the test where the script is |
//! | `wait-file FILE [SECONDS]` | wait until FILE exists (default 120 s) |
//! | `expect-streaming VIEW N` | fail unless at least N frames of VIEW showed partial data since the last check |
//! | `sleep MS` | let MS milliseconds pass (the views go on drawing) |
//! | `quit` | close the window (exit 0) |

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, PartialEq)]
pub enum Cmd {
    Size(usize, u32, u32),
    Mode(String),
    Drag(usize, String, f32, f32),
    Scroll(usize, f32),
    Click(usize, f32, f32),
    /// `hover VIEW X Y` (`None`: `hover off`).
    Hover(Option<(usize, f64, f64)>),
    Pick(usize, f64, f64),
    LabelSelect(String),
    LabelMode(u8),
    GotoLabel(u64),
    /// The label table: its first N rows in an order.
    LargestLabels(usize, crate::view::probe::TableOrder),
    WaitProbe(f64),
    Key(String),
    Tf(String),
    Colormap(String),
    Window(f32, f32),
    Point(f32, f32),
    Cursor([f64; 3]),
    Channel(usize, bool),
    ChannelColor(usize, [u8; 3]),
    ChannelWindow(usize, f32, f32),
    /// `channel-levels C LO HI` (`C all`: every level).
    ChannelLevels(usize, Option<[usize; 2]>),
    DvrChannel(usize),
    DvrChannels(bool),
    /// The 3D view's views: 1 (off), 2 with a stereo layout, or N tiled.
    Stereo(String, u32),
    Derive(Option<String>),
    Apply(String),
    WaitJob(f64),
    Oblique(f64, f64),
    Labels(bool),
    LabelOpacity(f32),
    LodBias(f64),
    Level(Option<usize>),
    Quality(f64),
    WaitComplete(f64),
    Screenshot(usize, PathBuf),
    SaveView(usize, PathBuf),
    WindowShot(PathBuf),
    ExpectStreaming(usize, usize),
    Touch(PathBuf),
    WaitFile(PathBuf, f64),
    Sleep(f64),
    Quit,
}

/// View names, in the order of the window's views.
pub const VIEWS: [&str; 5] = ["3d", "xy", "xz", "yz", "oblique"];

fn view(s: &str) -> Result<usize> {
    VIEWS
        .iter()
        .position(|v| *v == s)
        .with_context(|| format!("expected a view ({}), found {s:?}", VIEWS.join(", ")))
}

/// A number a script may write: integers, and finite reals (`nan` and
/// `inf`, or a real too large for its type, are refused).
trait Num: std::str::FromStr {
    fn finite(&self) -> bool {
        true
    }
}
impl Num for f32 {
    fn finite(&self) -> bool {
        self.is_finite()
    }
}
impl Num for f64 {
    fn finite(&self) -> bool {
        self.is_finite()
    }
}
impl Num for u32 {}
impl Num for u64 {}
impl Num for usize {}

fn num<T: Num>(s: &str) -> Result<T> {
    let x = s
        .parse::<T>()
        .ok()
        .with_context(|| format!("expected a number, found {s:?}"))?;
    if !x.finite() {
        bail!("expected a finite number, found {s:?}");
    }
    Ok(x)
}

/// A number of seconds or milliseconds to wait: finite, not negative.
fn duration(what: &str, s: &str) -> Result<f64> {
    let x: f64 = num(s).with_context(|| what.to_string())?;
    if x < 0.0 {
        bail!("{what}: expected a time of 0 or more, found {s:?}");
    }
    Ok(x)
}

/// A pixel of a view (`X Y`, not negative; the view's size is checked
/// when the command runs).
fn pixel(what: &str, x: &str, y: &str) -> Result<(f64, f64)> {
    let (px, py): (f64, f64) = (num(x)?, num(y)?);
    if px < 0.0 || py < 0.0 {
        bail!("{what}: expected a pixel of the view (X and Y of 0 or more), found {x} {y}");
    }
    Ok((px, py))
}

/// The largest view edge a script may ask for (as `--window-size` and
/// `render --size` take).
pub const MAX_EDGE: u32 = 16384;

/// A command of a script and where it was written.
#[derive(Debug, Clone)]
pub struct Step {
    pub cmd: Cmd,
    /// Its line in the file (from 1).
    pub line: usize,
    /// `FILE: line N: "text"`, for errors the command meets when it runs.
    pub at: String,
}

/// Parse a script; errors name the file and line, and so does each step
/// for the errors it meets when it runs.
pub fn parse(path: &Path, text: &str) -> Result<Vec<Step>> {
    let mut out = vec![];
    for (n, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let w: Vec<&str> = line.split_whitespace().collect();
        let at = format!("{}: line {}: {line:?}", path.display(), n + 1);
        let cmd = parse_line(&w).with_context(|| at.clone())?;
        out.push(Step {
            cmd,
            line: n + 1,
            at,
        });
    }
    Ok(out)
}

fn parse_line(w: &[&str]) -> Result<Cmd> {
    let arity = |k: usize| -> Result<()> {
        if w.len() != k + 1 {
            bail!("{} takes {k} argument(s), found {}", w[0], w.len() - 1);
        }
        Ok(())
    };
    Ok(match w[0] {
        "size" => {
            arity(3)?;
            let (v, wd, ht): (usize, u32, u32) = (view(w[1])?, num(w[2])?, num(w[3])?);
            if !(1..=MAX_EDGE).contains(&wd) || !(1..=MAX_EDGE).contains(&ht) {
                bail!(
                    "size: expected W H between 1 and {MAX_EDGE}, found {} {}",
                    w[2],
                    w[3]
                );
            }
            Cmd::Size(v, wd, ht)
        }
        "mode" => {
            arity(1)?;
            if !["dvr", "mip", "slice"].contains(&w[1]) {
                bail!("mode: expected dvr, mip or slice, found {:?}", w[1]);
            }
            Cmd::Mode(w[1].into())
        }
        "drag" => {
            arity(4)?;
            if !["left", "right", "middle"].contains(&w[2]) {
                bail!("drag: expected left, right or middle, found {:?}", w[2]);
            }
            Cmd::Drag(view(w[1])?, w[2].into(), num(w[3])?, num(w[4])?)
        }
        "scroll" => {
            arity(2)?;
            Cmd::Scroll(view(w[1])?, num(w[2])?)
        }
        "click" => {
            arity(3)?;
            let (x, y) = pixel("click", w[2], w[3])?;
            Cmd::Click(view(w[1])?, x as f32, y as f32)
        }
        "hover" => match w.len() {
            2 if w[1] == "off" => Cmd::Hover(None),
            4 => {
                let (x, y) = pixel("hover", w[2], w[3])?;
                Cmd::Hover(Some((view(w[1])?, x, y)))
            }
            _ => bail!("hover takes a view and X Y, or off"),
        },
        "pick" => {
            arity(3)?;
            let (x, y) = pixel("pick", w[2], w[3])?;
            Cmd::Pick(view(w[1])?, x, y)
        }
        "largest-labels" => {
            arity(1)?;
            Cmd::LargestLabels(num(w[1])?, crate::view::probe::TableOrder::LARGEST)
        }
        "labels-table" => {
            use crate::view::probe::{SortBy, TableOrder};
            if !(4..=5).contains(&w.len()) {
                bail!("labels-table takes N, voxels|mean|label, asc|desc and a least voxel count");
            }
            let by = SortBy::parse(w[2]).with_context(|| {
                format!(
                    "labels-table: expected voxels, mean or label, found {:?}",
                    w[2]
                )
            })?;
            let descending = match w[3] {
                "asc" => false,
                "desc" => true,
                o => bail!("labels-table: expected asc or desc, found {o:?}"),
            };
            let min_voxels = match w.get(4) {
                Some(m) => num(m)?,
                None => 0,
            };
            Cmd::LargestLabels(
                num(w[1])?,
                TableOrder {
                    by,
                    descending,
                    min_voxels,
                },
            )
        }
        "goto-label" => {
            arity(1)?;
            Cmd::GotoLabel(num(w[1])?)
        }
        "label-select" => {
            arity(1)?;
            Cmd::LabelSelect(w[1].into())
        }
        "label-mode" => {
            arity(1)?;
            Cmd::LabelMode(match w[1] {
                "all" => 0,
                "only" => 1,
                "hide" => 2,
                x => bail!("label-mode: expected all, only or hide, found {x:?}"),
            })
        }
        "wait-probe" => match w.len() {
            1 => Cmd::WaitProbe(60.0),
            2 => Cmd::WaitProbe(duration("wait-probe", w[1])?),
            _ => bail!("wait-probe takes at most 1 argument"),
        },
        "key" => {
            arity(1)?;
            if !["left", "right", "up", "down", "plus", "minus", "r"].contains(&w[1]) {
                bail!("key: unknown key {:?}", w[1]);
            }
            Cmd::Key(w[1].into())
        }
        "tf" => {
            arity(1)?;
            Cmd::Tf(w[1].into())
        }
        "colormap" => {
            arity(1)?;
            Cmd::Colormap(w[1].into())
        }
        "window" => {
            arity(2)?;
            Cmd::Window(num(w[1])?, num(w[2])?)
        }
        "point" => {
            arity(2)?;
            Cmd::Point(num(w[1])?, num(w[2])?)
        }
        "cursor" => {
            arity(3)?;
            Cmd::Cursor([num(w[1])?, num(w[2])?, num(w[3])?])
        }
        "channel" => {
            arity(2)?;
            let on = match w[2] {
                "on" => true,
                "off" => false,
                x => bail!("channel: expected on or off, found {x:?}"),
            };
            Cmd::Channel(num(w[1])?, on)
        }
        "channel-color" => {
            arity(2)?;
            let h = w[2].trim_start_matches('#');
            let v = (h.len() == 6)
                .then(|| u32::from_str_radix(h, 16).ok())
                .flatten()
                .with_context(|| format!("channel-color: expected RRGGBB, found {:?}", w[2]))?;
            Cmd::ChannelColor(num(w[1])?, [16, 8, 0].map(|s| ((v >> s) & 0xff) as u8))
        }
        "channel-window" => {
            arity(3)?;
            Cmd::ChannelWindow(num(w[1])?, num(w[2])?, num(w[3])?)
        }
        "labels" => {
            arity(1)?;
            Cmd::Labels(match w[1] {
                "on" => true,
                "off" => false,
                x => bail!("labels: expected on or off, found {x:?}"),
            })
        }
        "label-opacity" => {
            arity(1)?;
            let a: f32 = num(w[1])?;
            if !(a > 0.0 && a <= 1.0) {
                bail!("label-opacity: expected an opacity above 0 and at most 1, found {a}");
            }
            Cmd::LabelOpacity(a)
        }
        "channel-levels" => match w.len() {
            3 if w[2] == "all" => Cmd::ChannelLevels(num(w[1])?, None),
            4 => Cmd::ChannelLevels(num(w[1])?, Some([num(w[2])?, num(w[3])?])),
            _ => bail!("channel-levels takes a channel and LO HI, or a channel and `all`"),
        },
        "apply" => {
            arity(1)?;
            Cmd::Apply(w[1].into())
        }
        "wait-job" => match w.len() {
            1 => Cmd::WaitJob(600.0),
            2 => Cmd::WaitJob(duration("wait-job", w[1])?),
            _ => bail!("wait-job takes at most 1 argument"),
        },
        "derive" => {
            // The pipeline may hold spaces: the rest of the line.
            if w.len() < 2 {
                bail!("derive takes a pipeline or off");
            }
            let rest = w[1..].join(" ");
            if rest == "off" {
                Cmd::Derive(None)
            } else {
                Cmd::Derive(Some(rest))
            }
        }
        "dvr-channel" => {
            arity(1)?;
            Cmd::DvrChannel(num(w[1])?)
        }
        "dvr-channels" => {
            arity(1)?;
            Cmd::DvrChannels(match w[1] {
                "on" => true,
                "off" => false,
                x => bail!("dvr-channels: expected on or off, found {x:?}"),
            })
        }
        "stereo" => {
            arity(1)?;
            match w[1] {
                "off" => Cmd::Stereo("off".into(), 1),
                "sbs" | "anaglyph" => Cmd::Stereo(w[1].into(), 2),
                x => bail!("stereo: expected off, sbs or anaglyph, found {x:?}"),
            }
        }
        "views" => {
            arity(1)?;
            let n: u32 = num(w[1])?;
            if !(2..=brickyard_core::views::MAX_VIEWS).contains(&n) {
                bail!(
                    "views: expected 2 to {} views, found {n}",
                    brickyard_core::views::MAX_VIEWS
                );
            }
            Cmd::Stereo("tiles".into(), n)
        }
        "oblique" => {
            arity(2)?;
            Cmd::Oblique(num(w[1])?, num(w[2])?)
        }
        "lod-bias" => {
            arity(1)?;
            Cmd::LodBias(num(w[1])?)
        }
        "level" => {
            arity(1)?;
            Cmd::Level(if w[1] == "auto" {
                None
            } else {
                Some(num(w[1])?)
            })
        }
        "quality" => {
            arity(1)?;
            Cmd::Quality(num(w[1])?)
        }
        "wait-complete" => match w.len() {
            1 => Cmd::WaitComplete(120.0),
            2 => Cmd::WaitComplete(duration("wait-complete", w[1])?),
            _ => bail!("wait-complete takes at most one argument"),
        },
        "screenshot" => {
            arity(2)?;
            Cmd::Screenshot(view(w[1])?, w[2].into())
        }
        "save-view" => {
            arity(2)?;
            Cmd::SaveView(view(w[1])?, w[2].into())
        }
        "window-shot" => {
            arity(1)?;
            Cmd::WindowShot(w[1].into())
        }
        "expect-streaming" => {
            arity(2)?;
            Cmd::ExpectStreaming(view(w[1])?, num(w[2])?)
        }
        "touch" => {
            arity(1)?;
            Cmd::Touch(w[1].into())
        }
        "wait-file" => match w.len() {
            2 => Cmd::WaitFile(w[1].into(), 120.0),
            3 => Cmd::WaitFile(w[1].into(), duration("wait-file", w[2])?),
            _ => bail!("wait-file takes a file and at most a number of seconds"),
        },
        "sleep" => {
            if w.len() != 2 {
                bail!("sleep takes a number of milliseconds");
            }
            Cmd::Sleep(duration("sleep", w[1])?)
        }
        "quit" => {
            arity(0)?;
            Cmd::Quit
        }
        c => bail!("unknown command {c:?}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scripts_parse_and_errors_name_the_line() {
        let p = Path::new("s.txt");
        let c = parse(
            p,
            "size 3d 64 48 # main\n\nmode mip\ndrag xy left 3 -4\ntouch a.txt\nwait-file c\nwait-file d 5\nquit\n",
        )
        .unwrap();
        // Each step keeps its file line (the blank one counted).
        assert_eq!(
            c.iter().map(|s| s.line).collect::<Vec<_>>(),
            [1, 3, 4, 5, 6, 7, 8]
        );
        assert!(
            c[1].at.starts_with("s.txt: line 3: \"mode mip\""),
            "{}",
            c[1].at
        );
        assert_eq!(
            c.into_iter().map(|s| s.cmd).collect::<Vec<_>>(),
            vec![
                Cmd::Size(0, 64, 48),
                Cmd::Mode("mip".into()),
                Cmd::Drag(1, "left".into(), 3.0, -4.0),
                Cmd::Touch("a.txt".into()),
                Cmd::WaitFile("c".into(), 120.0),
                Cmd::WaitFile("d".into(), 5.0),
                Cmd::Quit
            ]
        );
        let e = format!(
            "{:#}",
            parse(p, "mode dvr\ndrag side left 1 1\n").unwrap_err()
        );
        assert!(
            e.contains("s.txt: line 2") && e.contains("expected a view"),
            "{e}"
        );
        let e = format!("{:#}", parse(p, "window 1\n").unwrap_err());
        assert!(e.contains("line 1") && e.contains("takes 2"), "{e}");
    }

    /// Sizes of no pixels or beyond what a view can take, numbers that are
    /// not finite, times and pixels below 0: refused when the script is
    /// read, naming the line (they panicked the render thread, hung the
    /// window or were taken silently).
    #[test]
    fn scripts_refuse_zero_sizes_non_finite_and_negative_numbers() {
        let p = Path::new("s.txt");
        for (line, want) in [
            ("size 3d 0 0", "between 1 and 16384"),
            ("size xy 64 0", "between 1 and 16384"),
            ("size 3d 20000 64", "between 1 and 16384"),
            ("cursor 2 -1 nan", "finite"),
            ("point nan 0.5", "finite"),
            ("scroll xy nan", "finite"),
            ("scroll 3d inf", "finite"),
            ("drag 3d left nan nan", "finite"),
            ("sleep nan", "finite"),
            ("sleep inf", "finite"),
            ("sleep -5", "0 or more"),
            ("lod-bias nan", "finite"),
            ("oblique nan 0", "finite"),
            ("wait-complete nan", "finite"),
            ("wait-complete -1", "0 or more"),
            ("wait-probe nan", "finite"),
            ("wait-probe -2", "0 or more"),
            ("wait-job -inf", "finite"),
            ("wait-file f -1", "0 or more"),
            ("window nan 1", "finite"),
            ("channel-window 0 0 inf", "finite"),
            ("quality NaN", "finite"),
            ("label-opacity nan", "finite"),
            ("hover xy -5 -5", "pixel of the view"),
            ("click 3d -1 4", "pixel of the view"),
            ("pick xy 3 nan", "finite"),
            ("point 1e39 0.5", "finite"),
        ] {
            let e = format!(
                "{:#}",
                parse(p, &format!("mode dvr\n{line}\nquit\n")).unwrap_err()
            );
            assert!(
                e.contains(&format!("s.txt: line 2: {line:?}")) && e.contains(want),
                "{line}: {e}"
            );
        }
        // What stays allowed.
        let c = parse(
            p,
            "size 3d 1 16384\nsleep 0\nwait-complete 0.5\nhover xy 0 0\nscroll 3d -3\nlod-bias -1.5\n",
        )
        .unwrap();
        assert_eq!(c[0].cmd, Cmd::Size(0, 1, 16384));
        assert_eq!(c[1].cmd, Cmd::Sleep(0.0));
        assert_eq!(c[3].cmd, Cmd::Hover(Some((1, 0.0, 0.0))));
    }
}
