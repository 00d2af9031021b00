//! What an image of several views side by side (`RenderParams::views`)
//! becomes for a display: the views tiled, a stereo pair side by side or
//! top and bottom, a red–cyan anaglyph, or the N views multiplexed for a
//! lenticular or parallax-barrier display through per-view sub-pixel
//! filters (`V_c(x, y) = Σ_i V_c^i(x, y)·F_c^i(x, y)`, each filter 0 or 1
//! and exactly one view feeding each sub-pixel).
//!
//! Anaglyphs and multiplexed images mix sub-pixels of different views, so
//! each view is first composited over the background (its alpha taken as
//! 1: a transparent background counts as black) and the result is opaque.
//! The other layouts only move pixels and keep transparency.

use crate::image::Image;
use brickyard_core::ConfigError;
use serde_json::Value;
use std::path::Path;

/// How the views are laid out.
#[derive(Debug, Clone, PartialEq)]
pub enum Layout {
    /// The views in a grid of `ceil(√N)` columns, row by row.
    Tiles,
    /// Left view, then right (the render's own layout).
    SideBySide,
    /// Left view above the right.
    TopBottom,
    /// Red–cyan anaglyph (two views): Dubois's least-squares matrices.
    Anaglyph,
    /// Sub-pixels multiplexed for a multi-view display.
    Multiplex(Multiplex),
}

/// Which view feeds each sub-pixel of a multi-view display.
#[derive(Debug, Clone, PartialEq)]
pub struct Multiplex {
    pub views: u32,
    pub pattern: Pattern,
}

/// The sub-pixel pattern.
#[derive(Debug, Clone, PartialEq)]
pub enum Pattern {
    /// A tile of sub-pixel view numbers repeated over the image: rows of
    /// `3·columns` entries (R, G, B of each pixel).
    Table(Vec<Vec<u32>>),
    /// A slanted lenticular sheet: sub-pixel `k = 3x + c` of row `y` shows
    /// view `⌊((k + offset − 3·y·slant) mod lens) · views / lens⌋`, `lens`
    /// the sheet's pitch in sub-pixels and `slant` the lenses' tangent
    /// (pixels across per pixel down).
    Lens { lens: f64, slant: f64, offset: f64 },
}

impl Multiplex {
    /// Parse `{"views": N, "pattern": [[…], …]}` or `{"views": N, "lens":
    /// L, "slant": S, "offset": O}` (`offset` optional); `what` names the
    /// source in errors.
    pub fn from_json(text: &str, what: &str) -> Result<Multiplex, ConfigError> {
        let v: Value =
            serde_json::from_str(text).map_err(|e| ConfigError::syntax("multiplex", &e))?;
        let err = |f: &str, m: String| ConfigError::new(what, f, m);
        let obj = v
            .as_object()
            .ok_or_else(|| err("(top)", "expected a JSON object".into()))?;
        for k in obj.keys() {
            if !["views", "pattern", "lens", "slant", "offset"].contains(&k.as_str()) {
                return Err(err(
                    k,
                    "unknown field; expected views, pattern, or lens, slant and offset".into(),
                ));
            }
        }
        let views = obj
            .get("views")
            .and_then(Value::as_u64)
            .filter(|n| (2..=brickyard_core::views::MAX_VIEWS as u64).contains(n))
            .ok_or_else(|| {
                err(
                    "views",
                    format!(
                        "expected a whole number of views from 2 to {}",
                        brickyard_core::views::MAX_VIEWS
                    ),
                )
            })? as u32;
        let number = |k: &str| -> Result<Option<f64>, ConfigError> {
            match obj.get(k) {
                None => Ok(None),
                Some(x) => x
                    .as_f64()
                    .filter(|x| x.is_finite())
                    .map(Some)
                    .ok_or_else(|| err(k, format!("expected a finite number, got {x}"))),
            }
        };
        let pattern = match (obj.get("pattern"), number("lens")?) {
            (Some(_), Some(_)) => {
                return Err(err(
                    "pattern",
                    "give either pattern or lens, not both".into(),
                ))
            }
            (None, None) => return Err(err("pattern", "missing: give pattern or lens".into())),
            (Some(p), None) => {
                let rows = p
                    .as_array()
                    .filter(|r| !r.is_empty())
                    .ok_or_else(|| err("pattern", "expected a non-empty array of rows".into()))?;
                let mut table: Vec<Vec<u32>> = vec![];
                for (y, row) in rows.iter().enumerate() {
                    let f = format!("pattern[{y}]");
                    let row = row
                        .as_array()
                        .ok_or_else(|| err(&f, "expected an array".into()))?;
                    if row.is_empty() || row.len() % 3 != 0 {
                        return Err(err(
                            &f,
                            format!(
                                "expected 3 sub-pixels (R, G, B) per pixel, got {} entries",
                                row.len()
                            ),
                        ));
                    }
                    let row: Vec<u32> = row
                        .iter()
                        .map(|x| x.as_u64().filter(|&x| x < views as u64).map(|x| x as u32))
                        .collect::<Option<_>>()
                        .ok_or_else(|| {
                            err(&f, format!("expected view numbers 0 to {}", views - 1))
                        })?;
                    if !table.is_empty() && row.len() != table[0].len() {
                        return Err(err(&f, "rows of different lengths".into()));
                    }
                    table.push(row);
                }
                Pattern::Table(table)
            }
            (None, Some(lens)) => {
                if lens <= 0.0 {
                    return Err(err("lens", format!("must be positive, got {lens}")));
                }
                Pattern::Lens {
                    lens,
                    slant: number("slant")?.unwrap_or(0.0),
                    offset: number("offset")?.unwrap_or(0.0),
                }
            }
        };
        Ok(Multiplex { views, pattern })
    }

    /// Read and parse a filter description file.
    pub fn from_file(path: &Path) -> Result<Multiplex, ConfigError> {
        let what = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|e| ConfigError::new(&what, "(file)", format!("cannot read it: {e}")))?;
        Multiplex::from_json(&text, &what)
    }

    /// The view that feeds sub-pixel `c` (0 R, 1 G, 2 B) of pixel `(x, y)`.
    pub fn view_of(&self, x: u32, y: u32, c: u32) -> u32 {
        match &self.pattern {
            Pattern::Table(t) => {
                let row = &t[y as usize % t.len()];
                row[(3 * x as usize + c as usize) % row.len()]
            }
            Pattern::Lens {
                lens,
                slant,
                offset,
            } => {
                let k = (3 * x + c) as f64;
                let q = (k + offset - 3.0 * y as f64 * slant).rem_euclid(*lens);
                ((q * self.views as f64 / lens) as u32).min(self.views - 1)
            }
        }
    }
}

/// Dubois's red–cyan matrices (rows: output R, G, B; columns: input R, G,
/// B) for the left and the right view.
const DUBOIS_LEFT: [[f32; 3]; 3] = [
    [0.456, 0.500, 0.176],
    [-0.040, -0.038, -0.016],
    [-0.015, -0.021, -0.005],
];
const DUBOIS_RIGHT: [[f32; 3]; 3] = [
    [-0.043, -0.088, -0.002],
    [0.378, 0.734, -0.018],
    [-0.072, -0.113, 1.226],
];

/// View `v` of an image of `count` views side by side.
pub fn view(img: &Image, count: u32, v: u32) -> Image {
    let w = img.width / count;
    let mut out = Image::new(w, img.height);
    for y in 0..img.height {
        let row = (y * img.width + v * w) as usize;
        out.rgba[(y * w) as usize..((y + 1) * w) as usize]
            .copy_from_slice(&img.rgba[row..row + w as usize]);
    }
    out
}

/// A premultiplied pixel over the opaque `bg` (straight RGB), opaque.
#[inline]
fn over(p: [f32; 4], bg: [f32; 3]) -> [f32; 3] {
    let k = 1.0 - p[3];
    [p[0] + k * bg[0], p[1] + k * bg[1], p[2] + k * bg[2]]
}

/// Lay out an image of `count` views side by side for a display;
/// `background` (straight RGBA) is what anaglyphs and multiplexed images
/// composite the views over. Errors when the layout does not fit the count.
pub fn compose(
    img: &Image,
    count: u32,
    layout: &Layout,
    background: [f32; 4],
) -> Result<Image, String> {
    let bg = [0, 1, 2].map(|c| background[c] * background[3]);
    let w = img.width / count;
    let h = img.height;
    // Pixel (x, y) of view v, read in place (copies of the views would
    // take as much memory again as the image).
    let at = |v: u32, x: u32, y: u32| img.rgba[(y * img.width + v * w + x) as usize];
    // The views in a grid of `cols × rows` tiles, row by row, copied a
    // pixel row at a time (tiles past the last view clear).
    let tiled = |cols: u32, rows: u32| {
        let mut out = Image::new(cols * w, rows * h);
        for v in 0..count {
            let (ox, oy) = ((v % cols) * w, (v / cols) * h);
            for y in 0..h {
                let from = (y * img.width + v * w) as usize;
                let to = ((oy + y) * out.width + ox) as usize;
                out.rgba[to..to + w as usize].copy_from_slice(&img.rgba[from..from + w as usize]);
            }
        }
        out
    };
    let pair = || {
        if count == 2 {
            Ok(())
        } else {
            Err(format!("{layout:?} needs 2 views, the image has {count}"))
        }
    };
    Ok(match layout {
        Layout::SideBySide => {
            pair()?;
            img.clone()
        }
        Layout::Tiles => {
            let cols = (count as f64).sqrt().ceil() as u32;
            let rows = count.div_ceil(cols);
            tiled(cols, rows)
        }
        Layout::TopBottom => {
            pair()?;
            tiled(1, 2)
        }
        Layout::Anaglyph => {
            pair()?;
            let mut out = Image::new(w, h);
            for (i, px) in out.rgba.iter_mut().enumerate() {
                let (x, y) = (i as u32 % w, i as u32 / w);
                let l = over(at(0, x, y), bg);
                let r = over(at(1, x, y), bg);
                let mut c = [0f32; 4];
                for (o, cc) in c.iter_mut().take(3).enumerate() {
                    let mut s = 0.0;
                    for k in 0..3 {
                        s += DUBOIS_LEFT[o][k] * l[k] + DUBOIS_RIGHT[o][k] * r[k];
                    }
                    *cc = s.clamp(0.0, 1.0);
                }
                c[3] = 1.0;
                *px = c;
            }
            out
        }
        Layout::Multiplex(m) => {
            if m.views != count {
                return Err(format!(
                    "the multiplexing filters are for {} views, the image has {count}",
                    m.views
                ));
            }
            let mut out = Image::new(w, h);
            for y in 0..h {
                for x in 0..w {
                    let mut c = [0f32, 0.0, 0.0, 1.0];
                    for (s, cc) in c.iter_mut().take(3).enumerate() {
                        let v = m.view_of(x, y, s as u32) as usize;
                        *cc = over(at(v as u32, x, y), bg)[s];
                    }
                    out.set(x, y, c);
                }
            }
            out
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An image of `n` views of `w × h` with distinct random opaque-ish
    /// pixels.
    fn views_image(n: u32, w: u32, h: u32) -> Image {
        let mut img = Image::new(n * w, h);
        let mut x = 0x9e3779b97f4a7c15u64;
        for p in img.rgba.iter_mut() {
            let mut r = || {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 40) as f32 / (1u64 << 24) as f32
            };
            let a = 0.5 + 0.5 * r();
            *p = [r() * a, r() * a, r() * a, a];
        }
        img
    }

    /// The multiplexed image is exactly `Σ_i V_c^i·F_c^i` with the binary
    /// filters built here from the pattern's own rule (a table and a
    /// slanted lens), every filter sub-pixel owned by exactly one view.
    #[test]
    fn multiplexing_is_the_sum_of_views_through_their_filters() {
        let (n, w, h) = (4u32, 23u32, 11u32);
        let img = views_image(n, w, h);
        let bg = [0.1f32, 0.2, 0.3, 1.0];
        for text in [
            r#"{"views": 4, "pattern": [[0,1,2,3,0,1], [2,3,0,1,2,3]]}"#,
            r#"{"views": 4, "lens": 4.5, "slant": 0.3333, "offset": 1}"#,
        ] {
            let m = Multiplex::from_json(text, "test").unwrap();
            let out = compose(&img, n, &Layout::Multiplex(m.clone()), bg).unwrap();
            let mut seen = vec![0u32; n as usize];
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3usize {
                        let k = 3 * x as usize + c;
                        let owner = |i: u32| -> f32 {
                            let on = match &m.pattern {
                                Pattern::Table(t) => {
                                    let row = &t[y as usize % t.len()];
                                    row[k % row.len()] == i
                                }
                                Pattern::Lens { .. } => {
                                    // 4.5 sub-pixels per lens, 4 views: view
                                    // i owns [i·1.125, (i+1)·1.125).
                                    let q =
                                        (k as f64 + 1.0 - 3.0 * y as f64 * 0.3333).rem_euclid(4.5);
                                    q >= i as f64 * 1.125 && q < (i + 1) as f64 * 1.125
                                }
                            };
                            on as u32 as f32
                        };
                        let filters: Vec<f32> = (0..n).map(owner).collect();
                        assert_eq!(filters.iter().sum::<f32>(), 1.0, "one view per sub-pixel");
                        let mut want = 0f32;
                        for i in 0..n {
                            let p = img.get(i * w + x, y);
                            let composited = p[c] + (1.0 - p[3]) * bg[c];
                            want += composited * filters[i as usize];
                            seen[i as usize] += filters[i as usize] as u32;
                        }
                        assert_eq!(out.get(x, y)[c], want, "({x}, {y}) sub-pixel {c}");
                    }
                    assert_eq!(out.get(x, y)[3], 1.0);
                }
            }
            assert!(seen.iter().all(|&s| s > 0), "a view never shown: {seen:?}");
        }
    }

    #[test]
    fn stereo_layouts_move_the_views_and_anaglyphs_split_the_colours() {
        let img = views_image(2, 8, 5);
        let tb = compose(&img, 2, &Layout::TopBottom, [0.0; 4]).unwrap();
        assert_eq!((tb.width, tb.height), (8, 10));
        assert_eq!(tb.get(3, 2), img.get(3, 2));
        assert_eq!(tb.get(3, 7), img.get(8 + 3, 2));
        let five = views_image(5, 4, 3);
        let tiles = compose(&five, 5, &Layout::Tiles, [0.0; 4]).unwrap();
        assert_eq!((tiles.width, tiles.height), (12, 6));
        // Views 0–2 on the first row of tiles, 3–4 on the second, the
        // sixth tile clear; each pixel as the view itself has it.
        for v in 0..6u32 {
            let (ox, oy) = ((v % 3) * 4, (v / 3) * 3);
            for (x, y) in (0..4).flat_map(|x| (0..3).map(move |y| (x, y))) {
                let want = if v < 5 {
                    view(&five, 5, v).get(x, y)
                } else {
                    [0.0; 4]
                };
                assert_eq!(tiles.get(ox + x, oy + y), want, "view {v} ({x}, {y})");
            }
        }
        assert!(compose(&views_image(3, 4, 3), 3, &Layout::Anaglyph, [0.0; 4]).is_err());
        // White on the left only: red lit, cyan dark; on the right only:
        // red dark, green and blue lit.
        let mut lr = Image::new(2, 1);
        lr.set(0, 0, [1.0, 1.0, 1.0, 1.0]);
        let a = compose(&lr, 2, &Layout::Anaglyph, [0.0, 0.0, 0.0, 1.0]).unwrap();
        let p = a.get(0, 0);
        assert!(p[0] > 0.9 && p[1] == 0.0 && p[2] == 0.0, "{p:?}");
        let mut lr = Image::new(2, 1);
        lr.set(1, 0, [1.0, 1.0, 1.0, 1.0]);
        let p = compose(&lr, 2, &Layout::Anaglyph, [0.0, 0.0, 0.0, 1.0])
            .unwrap()
            .get(0, 0);
        assert!(p[0] == 0.0 && p[1] > 0.9 && p[2] > 0.9, "{p:?}");
    }

    #[test]
    fn bad_filter_files_name_the_field() {
        let e = |t: &str| Multiplex::from_json(t, "f.json").unwrap_err().to_string();
        assert!(e(r#"{"pattern": [[0,1,0]]}"#).contains("views"));
        assert!(e(r#"{"views": 2, "pattern": [[0,1]]}"#).contains("pattern[0]"));
        assert!(e(r#"{"views": 2, "pattern": [[0,1,2]]}"#).contains("0 to 1"));
        assert!(e(r#"{"views": 2, "lens": -1}"#).contains("lens"));
        assert!(e(r#"{"views": 2}"#).contains("pattern"));
        assert!(e(r#"{"views": 2, "lens": 3, "tilt": 1}"#).contains("tilt"));
        assert!(e("{").contains("multiplex"));
    }
}
