//! The voxel under the pointer: where it is, its stored value in every
//! channel and, with `--labels NAME`, the label there with its row of the
//! label image's statistics (`_brickyard/labels.csv`, written by
//! `process`).
//!
//! A thread of its own reads the full-resolution brick that holds the
//! voxel (through a small cache of decoded chunks and the last few bricks),
//! so the window never waits for it. Labels are read at the level the view
//! draws at that point (by its footprint and level of detail), so what is
//! read out and picked is what is seen, also in a zoomed-out view that
//! draws a coarser level. The window asks again only when the
//! pointer enters another voxel, and the thread answers only the latest
//! question. Reads that fail are answered with their error; the viewer goes
//! on.

use anyhow::{Context, Result};
use brickyard_cache::brick::{BrickContent, BrickKey, LoadedBrick};
use brickyard_cache::host_cache::HostCache;
use brickyard_cache::loader::Loader;
use brickyard_core::camera::{world_to_level_voxel, world_to_voxel, Ray};
use brickyard_core::{cast_slice, dispatch_dtype, DType, Dims3, Sample};
use brickyard_render::params::LabelBoxes;
use brickyard_render::params::LabelSelect;
use brickyard_render::readout::{self, label_id};
pub use brickyard_render::readout::{Drawn, Look};
pub use brickyard_run::label_stats::{LabelRow, SortBy, TableOrder};
use brickyard_run::label_stats::{Stats, WINDOW};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, Sender};
use std::sync::Arc;
use std::time::{Duration, Instant};

type Vec3 = [f64; 3];

/// Edge of the bricks the probe reads (voxels; no apron).
const BRICK: u64 = 32;
/// Decoded chunks each of the probe's readers keeps.
const CHUNK_BYTES: u64 = 4 << 20;
/// Bricks each reader keeps, newest last.
const KEPT: usize = 8;

/// Memory the probe may hold for an image of `levels` levels (and a label
/// image of `label_levels`): each reader's decoded chunks (plus the half
/// MiB per level the loader adds), its kept bricks (at most 8-byte voxels)
/// and a search window.
pub fn bytes(levels: usize, channels: usize, label_levels: Option<usize>) -> u64 {
    let reader = |levels: usize, channels: usize| {
        CHUNK_BYTES + levels as u64 * (1 << 19) + (KEPT * channels.max(1)) as u64 * BRICK.pow(3) * 8
    };
    reader(levels, channels) + label_levels.map_or(0, |l| reader(l, 1) + WINDOW as u64)
}

/// A question: the voxel at world point `world` (with the label drawn
/// there read at `label_level`), or a label's row of the statistics.
pub enum Ask {
    Voxel {
        id: u64,
        world: Vec3,
        label_level: usize,
    },
    /// The point a 3D view shows along `ray` (its pixel's), then read out
    /// as a voxel.
    Seen {
        id: u64,
        ray: Ray,
        drawn: Drawn,
        look: Look,
    },
    Row(u64),
    /// The first labels of the statistics in an order, this many.
    Largest(usize, TableOrder),
    /// Where these labels lie (their bounding boxes).
    Boxes(Vec<i32>),
    /// The first label drawn along a ray (a pick in 3D) by a view that
    /// chose its levels so.
    Ray(Ray, Option<LabelSelect>, Drawn),
}

/// The first labels of the statistics in a [`TableOrder`]
/// ([`Probe::largest`]).
pub type Largest = std::result::Result<Vec<(u64, LabelRow)>, String>;

/// Where some labels lie ([`Probe::boxes`]; `Ok(None)`: no statistics).
pub type Boxes = std::result::Result<Option<LabelBoxes>, String>;

/// A label's row of the statistics, looked up ([`Probe::find`]).
pub type Found = (u64, std::result::Result<Option<LabelRow>, String>);

enum Reply {
    Voxel(Answer),
    Row(Found),
    Largest(Largest),
    Hit(std::result::Result<u64, String>),
    Boxes(Vec<i32>, Boxes),
}

/// What the label image has at the voxel.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelAt {
    /// The level read: the one the view draws there (0: full resolution).
    pub level: usize,
    /// The label image's voxel `[z, y, x]` of that level.
    pub voxel: [u64; 3],
    /// 0: background.
    pub label: u64,
    /// Its statistics: `Ok(None)` when the image has none or no row for
    /// this label.
    pub row: std::result::Result<Option<LabelRow>, String>,
}

/// What an answer about a 3D view's pixel says of it.
#[derive(Clone, Copy, Debug)]
pub struct Seen {
    /// How the point was found ([`Look::name`]).
    pub how: &'static str,
    /// Whether anything is drawn along the ray.
    pub hit: bool,
    /// The pixel's ray.
    pub ray: Ray,
}

/// The answer to an [`Ask`].
#[derive(Clone, Debug)]
pub struct Answer {
    pub id: u64,
    /// A 3D view's pixel: how its point was found, and whether anything is
    /// drawn along its ray (if not, the rest says nothing).
    pub seen: Option<Seen>,
    pub world: Vec3,
    /// The image's level-0 voxel `[z, y, x]`.
    pub voxel: [u64; 3],
    /// The stored value of every channel, or why it could not be read.
    pub values: std::result::Result<Vec<f64>, String>,
    pub label: Option<std::result::Result<LabelAt, String>>,
    pub ms: f64,
}

impl Answer {
    /// One line for the status bar.
    pub fn describe(&self, dtype: DType, label_name: &str) -> String {
        let [z, y, x] = self.voxel;
        let fmt = |v: f64| match dtype {
            DType::F32 | DType::F64 => format!("{v:.6}"),
            _ => format!("{v}"),
        };
        let mut s = String::new();
        match (self.seen.map(|s| (s.how, s.hit)), &self.values) {
            (Some((how, false)), _) => return format!("nothing drawn along the ray ({how})"),
            (Some((how, true)), Err(e)) if self.label.is_none() => {
                return format!("{how}: unreadable ({e})")
            }
            (Some((how, true)), _) => s += &format!("{how}, "),
            (None, _) => {}
        }
        s += &format!("voxel x {x} y {y} z {z}: ");
        match &self.values {
            Ok(v) if v.len() == 1 => s += &fmt(v[0]),
            Ok(v) => {
                let each: Vec<String> = v
                    .iter()
                    .enumerate()
                    .map(|(c, v)| format!("ch{c} {}", fmt(*v)))
                    .collect();
                s += &each.join(", ");
            }
            Err(e) => s += &format!("unreadable ({e})"),
        }
        // (A label image shown itself: its label, with its statistics.)
        let name = match label_name {
            "" => "label".to_string(),
            n => format!("labels/{n}"),
        };
        let level = |l: &LabelAt| match l.level {
            0 => String::new(),
            n => format!(" at level {n}"),
        };
        match &self.label {
            None => {}
            Some(Err(e)) => s += &format!(" · {name}: unreadable ({e})"),
            Some(Ok(l)) if l.label == 0 => s += &format!(" · {name}{}: background", level(l)),
            Some(Ok(l)) => {
                s += &format!(" · {name}{}: {}", level(l), l.label);
                match &l.row {
                    Ok(Some(r)) => {
                        let [cz, cy, cx] = r.centroid;
                        s += &format!(
                            " ({} voxels, centroid x {cx:.1} y {cy:.1} z {cz:.1}",
                            r.voxels
                        );
                        if let Some(m) = r.mean {
                            s += &format!(", mean {m:.4}");
                        }
                        s += ")";
                    }
                    Ok(None) => {}
                    Err(e) => s += &format!(" (statistics unreadable: {e})"),
                }
            }
        }
        s
    }

    /// The answer as JSON (the viewer's `--log`).
    pub fn to_json(&self) -> serde_json::Value {
        let label = match &self.label {
            None => serde_json::Value::Null,
            Some(Err(e)) => serde_json::json!({ "error": e }),
            Some(Ok(l)) => {
                let row = match &l.row {
                    Ok(Some(r)) => serde_json::json!({
                        "voxels": r.voxels, "min_zyx": r.min, "max_zyx": r.max,
                        "centroid_zyx": r.centroid, "mean": r.mean,
                    }),
                    Ok(None) => serde_json::Value::Null,
                    Err(e) => serde_json::json!({ "error": e }),
                };
                serde_json::json!({
                    "level": l.level, "voxel_zyx": l.voxel, "label": l.label, "stats": row,
                })
            }
        };
        let values = match &self.values {
            Ok(v) => serde_json::json!(v),
            Err(e) => serde_json::json!({ "error": e }),
        };
        let seen = match self.seen {
            Some(s) => serde_json::json!({
                "how": s.how, "hit": s.hit, "ray": [s.ray.origin, s.ray.dir],
            }),
            None => serde_json::Value::Null,
        };
        serde_json::json!({
            "world": self.world, "voxel_zyx": self.voxel, "values": values,
            "label": label, "seen": seen, "ms": self.ms,
        })
    }
}

/// Reads single voxels of one image, at any of its levels.
struct Reader {
    loader: Loader,
    /// Level 0's size.
    dims: Dims3,
    channels: usize,
    dtype: DType,
    kept: Vec<(BrickKey, Arc<LoadedBrick>)>,
}

impl Reader {
    fn open(store: &Path, read_delay: Duration) -> Result<Reader> {
        let loader = Loader::open_with_chunk_cache(
            store,
            [BRICK; 3],
            0,
            1,
            Arc::new(HostCache::new(0)),
            CHUNK_BYTES,
        )
        .with_context(|| format!("{}: cannot open", store.display()))?;
        loader.set_read_delay(read_delay);
        let g = loader.geometry();
        let (dims, channels, dtype) = (g.levels[0], g.channels, g.dtype);
        Ok(Reader {
            loader,
            dims,
            channels,
            dtype,
            kept: vec![],
        })
    }

    /// Level `level`'s size.
    fn dims_at(&self, level: usize) -> Dims3 {
        self.loader.geometry().levels[level]
    }

    fn levels(&self) -> usize {
        self.loader.geometry().levels.len()
    }

    /// Channel `c` of voxel `v` (`[z, y, x]`) of level `level`.
    fn value(&mut self, level: usize, v: [u64; 3], c: usize) -> Result<f64> {
        let key = BrickKey::new(level as u8, c as u16, v.map(|i| (i / BRICK) as u32));
        let brick = match self.kept.iter().position(|(k, _)| *k == key) {
            Some(i) => {
                let b = self.kept.remove(i);
                self.kept.push(b.clone());
                b.1
            }
            None => {
                let b = Arc::new(self.loader.load_now(&key).map_err(anyhow::Error::from)?);
                if self.kept.len() == KEPT * self.channels.max(1) {
                    self.kept.remove(0);
                }
                self.kept.push((key, b.clone()));
                b
            }
        };
        Ok(match &brick.content {
            BrickContent::Data(d) => {
                let [pz, py, px] = self.loader.geometry().padded();
                let [z, y, x] = v.map(|i| i % BRICK);
                let i = ((z * py + y) * px + x) as usize;
                debug_assert!(z < pz);
                dispatch_dtype!(self.dtype, T => { cast_slice::<T>(d)[i].to_f64() })
            }
            uniform => uniform.uniform_value().unwrap_or(0.0),
        })
    }
}

/// The probe's thread: the image, and the label image over it if any.
pub struct Setup {
    pub store: PathBuf,
    pub labels: Option<PathBuf>,
    /// Where the label statistics are (`_brickyard/labels.csv` below it):
    /// the label image laid over, or the store when it is a label image.
    pub stats: Option<PathBuf>,
    pub extent: Vec3,
    pub read_delay: Duration,
    /// The image is a label image (its labels are read out, picked and
    /// looked up in `stats`).
    pub image_labels: bool,
}

/// The window's side: asks, and keeps the latest answer.
pub struct Probe {
    tx: Sender<Ask>,
    rx: Receiver<Reply>,
    /// The image's level-0 size, to tell voxels apart.
    dims: Dims3,
    extent: Vec3,
    next: u64,
    /// The last question: its id, voxel and level of the labels.
    asked: Option<(u64, [u64; 3], usize)>,
    /// The last question about a 3D view's pixel: its ray, how the view
    /// chose its levels and what it draws.
    asked_seen: Option<(Ray, Drawn, Look)>,
    pub answer: Option<Answer>,
    /// The last label looked up, and its row once found.
    pub finding: Option<u64>,
    pub found: Option<Found>,
    /// The level-0 size of the image the statistics describe (the label
    /// image's, or the store's when it is a label image).
    pub stats_dims: Option<Dims3>,
    /// The labels of most voxels, once asked for and read.
    pub largest: Option<Largest>,
    /// The first label drawn along the last ray asked about (0: none).
    pub hit: Option<std::result::Result<u64, String>>,
    /// The labels whose boxes were asked for last, and the boxes
    /// (`Ok(None)`: no statistics).
    pub boxes: Option<(Vec<i32>, Boxes)>,
}

impl Probe {
    /// Open the readers (errors name the store) and start the thread;
    /// `wake` tells the window an answer came.
    pub fn start(setup: Setup, wake: impl Fn() + Send + 'static) -> Result<Probe> {
        let image = Reader::open(&setup.store, setup.read_delay)?;
        let labels = match &setup.labels {
            Some(dir) => Some(Reader::open(dir, setup.read_delay)?),
            None => None,
        };
        let stats = setup.stats.as_deref().map(Stats::open);
        let dims = image.dims;
        let stats_dims = setup
            .stats
            .as_ref()
            .map(|_| labels.as_ref().map_or(dims, |l| l.dims));
        let (tx, ask_rx) = std::sync::mpsc::channel();
        let (answer_tx, rx) = std::sync::mpsc::channel();
        let (extent, image_labels) = (setup.extent, setup.image_labels);
        std::thread::Builder::new()
            .name("probe".into())
            .spawn(move || {
                run(
                    image,
                    labels,
                    image_labels,
                    stats,
                    extent,
                    ask_rx,
                    answer_tx,
                    wake,
                )
            })
            .context("probe thread")?;
        Ok(Probe {
            tx,
            rx,
            dims,
            extent,
            next: 0,
            asked: None,
            asked_seen: None,
            answer: None,
            finding: None,
            found: None,
            stats_dims,
            largest: None,
            hit: None,
            boxes: None,
        })
    }

    /// Find the first label along `ray` that `select` draws, at the
    /// levels a view `drawn` so reads along it (the answer comes into
    /// `hit`).
    pub fn ray(&mut self, ray: Ray, select: Option<LabelSelect>, drawn: Drawn) {
        self.hit = None;
        let _ = self.tx.send(Ask::Ray(ray, select, drawn));
    }

    /// Find where labels `ids` lie, from the statistics (the answer comes
    /// into `boxes`).
    pub fn boxes(&mut self, ids: Vec<i32>) {
        let _ = self.tx.send(Ask::Boxes(ids));
    }

    /// Read the first `n` labels of the statistics in `order` (the answer
    /// comes into `largest`).
    pub fn largest(&mut self, n: usize, order: TableOrder) {
        self.largest = None;
        let _ = self.tx.send(Ask::Largest(n, order));
    }

    /// Look up `label`'s row of the statistics (the answer comes into
    /// `found`).
    pub fn find(&mut self, label: u64) {
        self.finding = Some(label);
        self.found = None;
        let _ = self.tx.send(Ask::Row(label));
    }

    /// Ask for the voxel at `world`, with the label there read at
    /// `label_level` (the level the view draws there), unless that is what
    /// was asked last.
    pub fn ask(&mut self, world: Vec3, label_level: usize) {
        let v = world_to_voxel(world, self.extent, self.dims);
        if self
            .asked
            .is_some_and(|(_, a, l)| a == v && l == label_level)
        {
            return;
        }
        self.next += 1;
        self.asked = Some((self.next, v, label_level));
        self.asked_seen = None;
        let _ = self.tx.send(Ask::Voxel {
            id: self.next,
            world,
            label_level,
        });
    }

    /// Ask for the point a 3D view (`drawn`, drawing `look`) shows along
    /// a pixel's `ray`, unless that is what was asked last. Returns the
    /// question's id.
    pub fn ask_seen(&mut self, ray: Ray, drawn: Drawn, look: Look) -> u64 {
        let same = self.asked_seen.as_ref().is_some_and(|(r, d, l)| {
            *r == ray
                && d.camera == drawn.camera
                && d.height == drawn.height
                && d.lod == drawn.lod
                && *l == look
        });
        if !same {
            self.next += 1;
            self.asked = Some((self.next, [u64::MAX; 3], usize::MAX));
            self.asked_seen = Some((ray, drawn, look.clone()));
            let _ = self.tx.send(Ask::Seen {
                id: self.next,
                ray,
                drawn,
                look,
            });
        }
        self.next
    }

    /// Answers that came (the latest is kept in `answer`; a row looked up
    /// goes into `found`).
    pub fn take(&mut self) -> Vec<Answer> {
        let mut got = vec![];
        for r in self.rx.try_iter() {
            match r {
                Reply::Voxel(a) => got.push(a),
                Reply::Row(f) if Some(f.0) == self.finding => self.found = Some(f),
                Reply::Row(_) => {}
                Reply::Largest(l) => self.largest = Some(l),
                Reply::Hit(h) => self.hit = Some(h),
                Reply::Boxes(ids, b) => self.boxes = Some((ids, b)),
            }
        }
        if let Some(a) = got.last() {
            self.answer = Some(a.clone());
        }
        got
    }

    /// Whether the latest answer is for the latest question.
    pub fn answered(&self) -> bool {
        matches!((&self.answer, self.asked), (Some(a), Some((id, ..))) if a.id == id)
    }
}

#[allow(clippy::too_many_arguments)]
fn run(
    mut image: Reader,
    mut labels: Option<Reader>,
    image_labels: bool,
    mut stats: Option<Result<Option<Stats>>>,
    extent: Vec3,
    rx: Receiver<Ask>,
    tx: Sender<Reply>,
    wake: impl Fn(),
) {
    // The level-0 size of the image the statistics describe.
    let stats_dims = labels.as_ref().map_or(image.dims, |l| l.dims);
    // A label's row of the statistics.
    let row = |stats: &mut Option<Result<Option<Stats>>>, label: u64| match stats {
        _ if label == 0 => Ok(None),
        Some(Ok(Some(s))) => s
            .row(label)
            .map_err(|e| format!("{}: {e:#}", s.path.display())),
        Some(Err(e)) => Err(format!("{e:#}")),
        _ => Ok(None),
    };
    while let Ok(first) = rx.recv() {
        // Only the latest question about a voxel matters; every label
        // looked up is answered.
        let mut voxel = None;
        let mut rows = vec![];
        let mut largest = None;
        let mut ray = None;
        let mut boxes = None;
        for a in std::iter::once(first).chain(rx.try_iter()) {
            match a {
                Ask::Voxel {
                    id,
                    world,
                    label_level,
                } => voxel = Some((id, Some(world), label_level, None)),
                Ask::Seen {
                    id,
                    ray,
                    drawn,
                    look,
                } => voxel = Some((id, None, 0, Some((ray, drawn, look)))),
                Ask::Row(l) => rows.push(l),
                Ask::Largest(n, order) => largest = Some((n, order)),
                Ask::Boxes(ids) => boxes = Some(ids),
                Ask::Ray(r, sel, d) => ray = Some((r, sel, d)),
            }
        }
        if let Some((r, sel, drawn)) = ray {
            let hit = first_label(&mut image, extent, &r, sel.as_ref(), &drawn)
                .map_err(|e| format!("{e:#}"));
            if tx.send(Reply::Hit(hit)).is_err() {
                return;
            }
            wake();
        }
        if let Some(ids) = boxes {
            let r = match &mut stats {
                Some(Ok(Some(s))) => s
                    .boxes(&ids, stats_dims)
                    .map(Some)
                    .map_err(|e| format!("{}: {e:#}", s.path.display())),
                Some(Err(e)) => Err(format!("{e:#}")),
                _ => Ok(None),
            };
            if tx.send(Reply::Boxes(ids, r)).is_err() {
                return;
            }
            wake();
        }
        if let Some((n, order)) = largest {
            let r = match &mut stats {
                Some(Ok(Some(s))) => s
                    .top(n, order, 1 << 20)
                    .map_err(|e| format!("{}: {e:#}", s.path.display())),
                Some(Err(e)) => Err(format!("{e:#}")),
                _ => Err("the label image has no statistics (_brickyard/labels.csv)".into()),
            };
            if tx.send(Reply::Largest(r)).is_err() {
                return;
            }
            wake();
        }
        for l in rows {
            let r = row(&mut stats, l);
            if tx.send(Reply::Row((l, r))).is_err() {
                return;
            }
            wake();
        }
        let Some((id, world, label_level, seen)) = voxel else {
            continue;
        };
        let t0 = Instant::now();
        // A 3D view's pixel: the point it shows, and the level drawn there.
        let (world, label_level, seen) = match (world, seen) {
            (Some(w), _) => (w, label_level, None),
            (None, Some((ray, drawn, look))) => {
                match seen_point(&mut image, extent, &ray, &drawn, &look) {
                    Ok(Some((w, level, _))) => (
                        w,
                        level,
                        Some(Seen {
                            how: look.name(),
                            hit: true,
                            ray,
                        }),
                    ),
                    r => {
                        // Nothing drawn along the ray, or a read failed.
                        let values = r.map(|_| vec![]).map_err(|e| format!("{e:#}"));
                        let answer = Answer {
                            id,
                            seen: Some(Seen {
                                how: look.name(),
                                hit: values.is_err(),
                                ray,
                            }),
                            world: ray.origin,
                            voxel: [0; 3],
                            values,
                            label: None,
                            ms: t0.elapsed().as_secs_f64() * 1e3,
                        };
                        if tx.send(Reply::Voxel(answer)).is_err() {
                            return;
                        }
                        wake();
                        continue;
                    }
                }
            }
            (None, None) => unreachable!("a voxel or a pixel is asked about"),
        };
        let voxel = world_to_voxel(world, extent, image.dims);
        let values = (0..image.channels)
            .map(|c| image.value(0, voxel, c))
            .collect::<Result<Vec<f64>>>()
            .map_err(|e| format!("{e:#}"));
        // The label drawn there: of the label image laid over, or of the
        // image itself when it is one.
        let reader = match &mut labels {
            Some(r) => Some(r),
            None if image_labels => Some(&mut image),
            None => None,
        };
        let label = reader.map(|r| {
            let level = label_level.min(r.levels() - 1);
            let sizes: Vec<Dims3> = (0..r.levels()).map(|l| r.dims_at(l)).collect();
            let lv = world_to_level_voxel(world, extent, &sizes, level);
            let v = r.value(level, lv, 0).map_err(|e| format!("{e:#}"))?;
            let label = label_id(v);
            Ok(LabelAt {
                level,
                voxel: lv,
                label,
                row: row(&mut stats, label),
            })
        });
        let answer = Answer {
            id,
            seen,
            world,
            voxel,
            values,
            label,
            ms: t0.elapsed().as_secs_f64() * 1e3,
        };
        if tx.send(Reply::Voxel(answer)).is_err() {
            return;
        }
        wake();
    }
}

/// The first label along `ray` through a label image (`r`, spanning
/// `extent`) that `select` draws, at the levels a view `drawn` so reads
/// (0: none met).
fn first_label(
    r: &mut Reader,
    extent: Vec3,
    ray: &Ray,
    select: Option<&LabelSelect>,
    drawn: &Drawn,
) -> Result<u64> {
    let look = Look::Labels(select.cloned());
    Ok(seen_point(r, extent, ray, drawn, &look)?.map_or(0, |(_, _, v)| label_id(v)))
}

/// [`seen_point`] through reader `r` (nearest voxels of each level).
fn seen_point(
    r: &mut Reader,
    extent: Vec3,
    ray: &Ray,
    drawn: &Drawn,
    look: &Look,
) -> Result<Option<(Vec3, usize, f64)>> {
    let dims: Vec<Dims3> = (0..r.levels()).map(|l| r.dims_at(l)).collect();
    readout::seen_point(ray, extent, &dims, drawn, look, |l, w, c| {
        r.value(l, world_to_level_voxel(w, extent, &dims, l), c)
            .map(Some)
    })
}

/// The world point of a statistics row's centroid (voxels `[z, y, x]` of
/// an image of level-0 size `dims` spanning `extent`).
pub fn centroid_world(r: &LabelRow, dims: Dims3, extent: Vec3) -> Vec3 {
    let [cz, cy, cx] = r.centroid;
    let f = |c: f64, n: u64, e: f64| ((c + 0.5) / n as f64 * e).clamp(0.0, e);
    [
        f(cx, dims[2], extent[0]),
        f(cy, dims[1], extent[1]),
        f(cz, dims[0], extent[2]),
    ]
}
