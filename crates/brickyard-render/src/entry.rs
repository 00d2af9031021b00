//! Entry depths for the CPU DVR: per pixel, the ray parameter before which
//! its ray meets nothing that could show, found for the whole frame at
//! once before any ray is walked.
//!
//! A DVR ray spends most of its walk getting to where the volume shows:
//! landing past transparent bricks and jumping clear cells, one brick and
//! one cell at a time, before the handful of samples that end it. Here the
//! parts of the level rays start at that may show something — each cell of
//! a resident brick that the transfer function does not hide, each brick
//! that is not resident (the walk falls back to stand-ins and requests it
//! there), never a brick its value range hides — become boxes in world
//! space. Each box is projected to the screen and binned by tile; per pixel
//! the nearest hit over the boxes of its tile is its *entry*. The walk then
//! starts a step or so before the entry (see `Walker::dvr`): every step
//! before it has its voxel base in a clear cell or a hidden brick, which
//! the walk would have crossed without sampling anyway, so the image is
//! the same bits. A ray that meets no box over its whole span at that
//! level is done at once.
//!
//! Boxes are the sampler's: the samples whose voxel base lies in a cell's
//! voxels `[lo, hi)` are the world points with `q = w·scale − ½` in that
//! range, widened by a thousandth of a voxel for rounding and to the
//! volume's faces where the sampler clamps. Rays are the renderer's own
//! (`ViewRays::pixel_ray`), so entries are on the same parameter.
//!
//! The walk marks the bricks it passes through as used this frame (the
//! pool's replacement keeps them). Bricks that rays now pass before their
//! entry — resident ones crossed through clear cells, and bricks of one
//! hidden value — are marked here instead ([`Entries::mark_passed`]), as
//! the walk would, so that a pool smaller than the view still converges.

use crate::cpu::{Tiles, TILE_H, TILE_W};
use crate::optics::label_clear;
use crate::walk::Frame;
use brickyard_cache::brick::BrickKey;
use brickyard_cache::vm::BrickRef;
use brickyard_core::camera::{intersect_box_inv, length, sub, Ray, RayGen, Vec3};
use brickyard_core::views::ViewRays;
use brickyard_core::Dims3;
use rayon::prelude::*;

/// Most bricks of the level rays start at that a frame looks at; beyond,
/// rays walk from the volume's face as before.
const MAX_BRICKS: u64 = 1 << 15;
/// Most boxes (cells and bricks) a frame bins; beyond, the same.
const MAX_BOXES: usize = 1 << 18;
/// Widening of each box, in voxels, for the rounding of the sampler's
/// coordinates (far below it: 1e-7 voxel for runs of 1000 steps).
const MARGIN: f64 = 1e-3;

/// A box in world coordinates `[x, y, z]` and the pixels it may cover.
struct Box3 {
    lo: Vec3,
    hi: Vec3,
    /// No ray parameter in the box is smaller.
    near: f64,
    /// Pixel rectangle `[x0, y0, x1, y1)`, clipped to the image.
    rect: [u32; 4],
}

/// A brick that rays may pass through before their entry and that the
/// walk would have marked as used: its box and pixels.
struct Passable {
    channel: usize,
    brick: Dims3,
    bx: Box3,
}

/// Entry depths of a frame's pixels at one level.
pub(crate) struct Entries {
    /// The level the boxes are of; rays starting at another level walk from
    /// their start.
    pub(crate) level: usize,
    /// Every ray stays at `level` through the whole volume (the level
    /// never changes before the volume's farthest point).
    whole: bool,
    width: usize,
    /// Per pixel, row-major: the entry rounded down to f32 (`+∞`: nothing
    /// on the ray; `−∞`: not computed, the tile is not drawn).
    depth: Vec<f32>,
    passable: Vec<Passable>,
}

impl Entries {
    /// The entry of pixel `(i, j)`: no sample before it may show.
    #[inline]
    pub(crate) fn at(&self, i: usize, j: usize) -> f64 {
        self.depth[j * self.width + i] as f64
    }

    /// Whether pixel `(i, j)` shows nothing: its ray meets no box and
    /// stays at the boxes' level, so the walk would return a clear pixel
    /// without a sample (the ray need not be made).
    #[inline]
    pub(crate) fn shows_nothing(&self, i: usize, j: usize) -> bool {
        self.whole && self.depth[j * self.width + i] == f32::INFINITY
    }

    /// Entries of the pixels of `tiles` still to draw, for a one-channel
    /// DVR through the page tables of frame `f` with rays `rg`; `None`
    /// when the level rays start at has too many bricks or boxes for a
    /// pre-pass to pay.
    pub(crate) fn new(f: &Frame, rg: &ViewRays, tiles: &Tiles) -> Option<Entries> {
        let level = f.level_at(near_distance(f));
        let (boxes, passable) = Self::boxes(f, level)?;
        Self::from_boxes(f, level, (boxes, passable), rg, tiles)
    }

    /// The boxes of frame `f`'s level `level` that may show something
    /// (cells of resident bricks, bricks not resident, bricks of one value
    /// that shows) and the bricks rays may pass without sampling; `None`
    /// when the level has too many bricks or boxes.
    fn boxes(f: &Frame, level: usize) -> Option<(Vec<Box3>, Vec<Passable>)> {
        let nb = f.bricks[level];
        if nb.iter().product::<u64>() > MAX_BRICKS {
            return None;
        }
        let proj = Projector::new(f);
        let hidden = f.transparent[level].as_deref();
        let scale = f.scale[level];
        let dims = f.dims[level];
        let extent = f.scene.extent;
        // The sampler's world box of the voxel bases `[lo, hi)`.
        let world = |lo: Dims3, hi: Dims3| -> (Vec3, Vec3) {
            let mut a = [0.0; 3];
            let mut b = [0.0; 3];
            for ax in 0..3 {
                let z = 2 - ax;
                let s = scale[z];
                a[ax] = if lo[z] == 0 {
                    -MARGIN / s
                } else {
                    (lo[z] as f64 + 0.5 - MARGIN) / s
                };
                b[ax] = if hi[z] >= dims[z] {
                    extent[ax] + MARGIN / s
                } else {
                    (hi[z] as f64 + 0.5 + MARGIN) / s
                };
            }
            (a, b)
        };
        // The box of voxel bases `[lo, hi)` placed on the screen.
        let place = |lo: Dims3, hi: Dims3| {
            let (a, c) = world(lo, hi);
            proj.place(a, c)
        };
        // Per slab of bricks along z, in parallel.
        let slab = |bz: u64| {
            let mut boxes: Vec<Box3> = Vec::new();
            let mut passable = Vec::new();
            for by in 0..nb[1] {
                for bx in 0..nb[2] {
                    let b = [bz, by, bx];
                    let i = ((bz * nb[1] + by) * nb[2] + bx) as usize;
                    if hidden.is_some_and(|t| t[i]) {
                        continue;
                    }
                    let lo = [0, 1, 2].map(|a| b[a] * f.brick[a]);
                    let hi = [0, 1, 2].map(|a| (lo[a] + f.brick[a]).min(dims[a]));
                    let key = BrickKey::new(
                        level as u8,
                        f.scene.channel as u16,
                        [bz as u32, by as u32, bx as u32],
                    );
                    // Whether rays may pass through the brick without
                    // sampling it (clear cells, or one hidden value).
                    let pass = match f.vm.peek(key) {
                        BrickRef::Data { slot, .. } if f.scene.skip_cells => {
                            let cells = f.vm.cell_ranges(slot);
                            let shows = |&[vlo, vhi]: &[f32; 2]| match f.params.labels {
                                true => !label_clear(vlo, vhi, f.params.label_select.as_ref()),
                                false => f.tf_eval.range_visible(vlo, vhi),
                            };
                            if cells.iter().all(shows) {
                                // One box for the brick, not one per cell.
                                boxes.extend(place(lo, hi));
                                false
                            } else {
                                let mut show = 0u64;
                                for (c, r) in cells.iter().enumerate() {
                                    show |= (shows(r) as u64) << c;
                                }
                                let (n, e) = (f.cells.count, f.cells.edge);
                                for (c0, c1) in merge_cells(n, show) {
                                    let clo = [0, 1, 2].map(|a| lo[a] + c0[a] * e[a]);
                                    let chi = [0, 1, 2].map(|a| (lo[a] + c1[a] * e[a]).min(hi[a]));
                                    // (Cells past a brick cut by the
                                    // volume's faces hold no voxels.)
                                    if (0..3).all(|a| clo[a] < chi[a]) {
                                        boxes.extend(place(clo, chi));
                                    }
                                }
                                true
                            }
                        }
                        r @ (BrickRef::Empty | BrickRef::Constant(_)) => {
                            let v = match r {
                                BrickRef::Constant(v) => v,
                                _ => 0.0,
                            };
                            let hides = match f.params.labels {
                                true => label_clear(v, v, f.params.label_select.as_ref()),
                                false => f.tf.lookup_visible(v).is_none(),
                            };
                            if !hides {
                                boxes.extend(place(lo, hi));
                            }
                            hides
                        }
                        _ => {
                            boxes.extend(place(lo, hi));
                            false
                        }
                    };
                    if pass {
                        if let Some(bx) = place(lo, hi) {
                            passable.push(Passable {
                                channel: f.scene.channel,
                                brick: b,
                                bx,
                            });
                        }
                    }
                }
            }
            (boxes, passable)
        };
        let slabs: Vec<(Vec<Box3>, Vec<Passable>)> = (0..nb[0]).into_par_iter().map(slab).collect();
        if slabs.iter().map(|s| s.0.len()).sum::<usize>() > MAX_BOXES {
            return None;
        }
        let (mut boxes, mut passable) = (Vec::new(), Vec::new());
        for (b, p) in slabs {
            boxes.extend(b);
            passable.extend(p);
        }
        Some((boxes, passable))
    }

    /// Entries at `level` from the boxes that may show (`boxes`, of one
    /// channel or of several) for the pixels of `tiles`; `f`: a frame of
    /// the view (its geometry and size).
    fn from_boxes(
        f: &Frame,
        level: usize,
        (mut boxes, passable): (Vec<Box3>, Vec<Passable>),
        rg: &ViewRays,
        tiles: &Tiles,
    ) -> Option<Entries> {
        let (w, h) = (f.params.width as usize, f.params.height as usize);
        // Nearest first: a pixel whose entry is already nearer than a
        // box's nearest point skips its test.
        boxes.sort_unstable_by(|a, b| a.near.total_cmp(&b.near));
        // Boxes by tile (tiles to draw only).
        let tiles_x = w.div_ceil(TILE_W);
        let tiles_y = h.div_ceil(TILE_H);
        let mut bins: Vec<Vec<u32>> = vec![Vec::new(); tiles_x * tiles_y];
        for (n, b) in boxes.iter().enumerate() {
            let [x0, y0, x1, y1] = b.rect;
            for ty in y0 as usize / TILE_H..=(y1 as usize - 1) / TILE_H {
                for tx in x0 as usize / TILE_W..=(x1 as usize - 1) / TILE_W {
                    let t = ty * tiles_x + tx;
                    if tiles.redo[t] {
                        bins[t].push(n as u32);
                    }
                }
            }
        }
        let mut depth = vec![f32::NEG_INFINITY; w * h];
        depth
            .par_chunks_mut(w * TILE_H)
            .enumerate()
            .for_each(|(ty, rows)| {
                let nrows = rows.len() / w;
                let mut rays: Vec<(Ray, Vec3, f64)> = Vec::with_capacity(TILE_W * TILE_H);
                for tx in 0..tiles_x {
                    let t = ty * tiles_x + tx;
                    if !tiles.redo[t] {
                        continue;
                    }
                    let x0 = tx * TILE_W;
                    let tw = TILE_W.min(w - x0);
                    let y0 = ty * TILE_H;
                    for r in 0..nrows {
                        rows[r * w + x0..r * w + x0 + tw].fill(f32::INFINITY);
                    }
                    // The pixels of the tile that some box may cover: rays
                    // for these only (the others meet no box).
                    let (mut rx0, mut ry0, mut rx1, mut ry1) = (x0 + tw, y0 + nrows, x0, y0);
                    for &n in &bins[t] {
                        let [bx0, by0, bx1, by1] = boxes[n as usize].rect.map(|v| v as usize);
                        rx0 = rx0.min(bx0.max(x0));
                        ry0 = ry0.min(by0.max(y0));
                        rx1 = rx1.max(bx1.min(x0 + tw));
                        ry1 = ry1.max(by1.min(y0 + nrows));
                    }
                    if rx0 >= rx1 || ry0 >= ry1 {
                        continue;
                    }
                    let rw = rx1 - rx0;
                    rays.clear();
                    for y in ry0..ry1 {
                        for x in rx0..rx1 {
                            let ray = rg.pixel_ray(x as u32, y as u32);
                            let d = ray.dir;
                            rays.push((ray, [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]], f64::INFINITY));
                        }
                    }
                    for (m, &n) in bins[t].iter().enumerate() {
                        let b = &boxes[n as usize];
                        // Every pixel's entry nearer than this box (and so
                        // than every box after it): the tile is done.
                        if m % 8 == 7 && rays.iter().all(|r| r.2 <= b.near) {
                            break;
                        }
                        let [bx0, by0, bx1, by1] = b.rect;
                        let (px0, px1) = ((bx0 as usize).max(rx0), (bx1 as usize).min(rx1));
                        let (y_lo, y_hi) = ((by0 as usize).max(ry0), (by1 as usize).min(ry1));
                        for y in y_lo..y_hi {
                            let row = (y - ry0) * rw;
                            for x in px0..px1 {
                                let (ray, inv, best) = &mut rays[row + x - rx0];
                                if *best <= b.near {
                                    continue;
                                }
                                if let Some((tn, _)) = intersect_box_inv(ray, *inv, b.lo, b.hi) {
                                    if tn < *best {
                                        *best = tn;
                                    }
                                }
                            }
                        }
                    }
                    for y in ry0..ry1 {
                        for x in rx0..rx1 {
                            rows[(y - y0) * w + x] = down(rays[(y - ry0) * rw + x - rx0].2);
                        }
                    }
                }
            });
        // Every sample of every ray lies before the level changes: a ray
        // with no entry has nothing to show at all.
        let whole = f.next_level_t(level) > far_distance(f) * (1.0 + 1e-6);
        Some(Entries {
            level,
            whole,
            width: w,
            depth,
            passable,
        })
    }

    /// DVR of several channels (`frames`, one per channel shown, none with
    /// a level range of its own): per pixel the nearest of the channels'
    /// entries (before it every channel hides every sample), each
    /// channel's passed bricks marked as its walk would. `None` when a
    /// channel has none (see [`new`](Self::new)) or their levels differ.
    pub(crate) fn of_channels(frames: &[Frame], rg: &ViewRays, tiles: &Tiles) -> Option<Entries> {
        let f = frames.first()?;
        if frames.iter().any(|f| f.channel_levels.is_some()) {
            return None;
        }
        // The channels' boxes together, one pass over the pixels.
        let level = f.level_at(near_distance(f));
        let (mut boxes, mut passable) = (Vec::new(), Vec::new());
        for fc in frames {
            let (b, p) = Self::boxes(fc, level)?;
            boxes.extend(b);
            passable.extend(p);
            if boxes.len() > MAX_BOXES {
                return None;
            }
        }
        Self::from_boxes(f, level, (boxes, passable), rg, tiles)
    }

    /// Mark as used, as the walk would have, every brick that some drawn
    /// pixel's ray passes through before its entry. Bricks of one value
    /// and resident bricks crossed through their clear cells are the ones
    /// the walk looked up there and rays now skip (of each channel, for
    /// [`of_channels`](Self::of_channels)).
    ///
    /// Only up to where the level changes: rays walk on from there at a
    /// coarser level (`start_at_entry`), and this level's bricks beyond
    /// are not theirs. (Marked, they held the pool: after a coarser bias
    /// the pool's finer bricks, crossed far past their level's end, took
    /// the room of the bricks the view needs, and a render that fits
    /// found no room.)
    pub(crate) fn mark_passed(&self, f: &Frame, rg: &ViewRays) {
        let end = f.next_level_t(self.level);
        self.passable.par_iter().for_each(|p| {
            let near = p.bx.near;
            let [x0, y0, x1, y1] = p.bx.rect;
            'px: for j in y0..y1 {
                for i in x0..x1 {
                    let e = self.at(i as usize, j as usize).min(end);
                    if e <= near {
                        continue;
                    }
                    let ray = rg.pixel_ray(i, j);
                    let d = ray.dir;
                    let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
                    if let Some((tn, _)) = intersect_box_inv(&ray, inv, p.bx.lo, p.bx.hi) {
                        if tn < e {
                            f.vm.brick(self.level, p.channel, p.brick, true);
                            break 'px;
                        }
                    }
                }
            }
        });
    }
}

/// The cells whose bit is set in `show` (cells of a brick, `count` per
/// axis `[z, y, x]`, in [`CellGrid`] order) as fewer boxes, each the union
/// of the cells in it: from each cell not yet taken, a run along x, grown
/// along y while whole rows of cells not yet taken follow, then along z
/// while whole such rectangles follow. Returns cell ranges `[c0, c1)`.
///
/// [`CellGrid`]: brickyard_cache::cells::CellGrid
fn merge_cells(count: Dims3, show: u64) -> Vec<(Dims3, Dims3)> {
    let [nz, ny, nx] = count;
    let bit = |z: u64, y: u64, x: u64| (z * ny + y) * nx + x;
    let mut left = show;
    let has = |left: u64, z: u64, y: u64, x: u64| left >> bit(z, y, x) & 1 != 0;
    let mut out = Vec::new();
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                if !has(left, z, y, x) {
                    continue;
                }
                let mut x1 = x + 1;
                while x1 < nx && has(left, z, y, x1) {
                    x1 += 1;
                }
                let row = |left: u64, z: u64, y: u64| (x..x1).all(|i| has(left, z, y, i));
                let mut y1 = y + 1;
                while y1 < ny && row(left, z, y1) {
                    y1 += 1;
                }
                let mut z1 = z + 1;
                while z1 < nz && (y..y1).all(|j| row(left, z1, j)) {
                    z1 += 1;
                }
                for k in z..z1 {
                    for j in y..y1 {
                        for i in x..x1 {
                            left &= !(1 << bit(k, j, i));
                        }
                    }
                }
                out.push(([z, y, x], [z1, y1, x1]));
            }
        }
    }
    out
}

/// Corner `c` (bits x, y, z: 0 low, 1 high) of the box `[lo, hi]`.
fn corner(lo: Vec3, hi: Vec3, c: usize) -> Vec3 {
    [
        if c & 1 == 0 { lo[0] } else { hi[0] },
        if c & 2 == 0 { lo[1] } else { hi[1] },
        if c & 4 == 0 { lo[2] } else { hi[2] },
    ]
}

/// Distance from `p` to the box `[lo, hi]` (0 inside).
fn distance(p: Vec3, lo: Vec3, hi: Vec3) -> f64 {
    let mut d2 = 0.0;
    for a in 0..3 {
        let c = p[a].clamp(lo[a], hi[a]);
        d2 += (p[a] - c) * (p[a] - c);
    }
    d2.sqrt()
}

/// `t` rounded down to an f32 (an entry may come early, never late).
fn down(t: f64) -> f32 {
    let e = t as f32;
    if e as f64 > t {
        e.next_down()
    } else {
        e
    }
}

/// Distance from the eye to the volume's box (0 inside): the smallest ray
/// parameter of any sample, where the level rays start at is decided.
fn near_distance(f: &Frame) -> f64 {
    distance(f.params.camera.eye, [0.0; 3], f.scene.extent)
}

/// Distance from the eye to the volume's farthest corner: no ray
/// parameter of a sample is larger (perspective; orthographic views do not
/// change level along a ray).
fn far_distance(f: &Frame) -> f64 {
    let (eye, hi) = (f.params.camera.eye, f.scene.extent);
    (0..8)
        .map(|c| length(sub(corner([0.0; 3], hi, c), eye)))
        .fold(0.0, f64::max)
}

/// The camera's projection to pixel positions, with the frame computed
/// once ([`RayGen::eye_coords`], [`RayGen::image_of`]).
struct Projector(RayGen);

impl Projector {
    fn new(f: &Frame) -> Projector {
        Projector(f.params.camera.ray_gen(f.params.width, f.params.height))
    }

    /// The box `[lo, hi]` on the screen: the pixels whose centres may
    /// see it, the rectangle of its projected corners a pixel wider on
    /// each side, clipped to the image (the whole image when a corner lies
    /// on or behind the eye's plane), and the smallest ray parameter in it
    /// (perspective: its distance from the eye; orthographic: from the
    /// eye's plane); `None` when no pixel may see it.
    fn place(&self, lo: Vec3, hi: Vec3) -> Option<Box3> {
        let mut near = f64::INFINITY;
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        let corners = (0..8).map(|c| self.0.eye_coords(corner(lo, hi, c)));
        // A box wholly behind the eye's plane: no ray meets it (it had been
        // taken as covering the whole image, and a camera turned away from
        // the volume tested every pixel against every box: 0.9 s a frame
        // for an empty image).
        let behind = |v: &Vec3| v[2] <= 0.0;
        if self.0.is_perspective() && corners.clone().all(|v| behind(&v)) {
            return None;
        }
        for v in corners {
            near = near.min(v[2]);
            if self.0.is_perspective() && v[2] <= 1e-9 {
                (x0, y0, x1, y1) = (f64::MIN, f64::MIN, f64::MAX, f64::MAX);
                break;
            }
            let [px, py] = self.0.image_of(v);
            x0 = x0.min(px);
            x1 = x1.max(px);
            y0 = y0.min(py);
            y1 = y1.max(py);
        }
        // Pixel i's centre is i + ½: i from ⌈x0 − ½⌉ to ⌊x1 − ½⌋, a pixel
        // more each way.
        let clip = |v: f64, n: f64| v.clamp(0.0, n) as u32;
        let [w, h] = self.0.size();
        let r = [
            clip((x0 - 0.5).ceil() - 1.0, w),
            clip((y0 - 0.5).ceil() - 1.0, h),
            clip((x1 - 0.5).floor() + 2.0, w),
            clip((y1 - 0.5).floor() + 2.0, h),
        ];
        if self.0.is_perspective() {
            near = distance(self.0.eye(), lo, hi);
        }
        (r[0] < r[2] && r[1] < r[3]).then_some(Box3 {
            lo,
            hi,
            near,
            rect: r,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A box wholly behind a perspective eye covers no pixel; one the eye's
    /// plane cuts covers the whole image; one in front its projection.
    #[test]
    fn boxes_behind_the_eye_cover_nothing() {
        use brickyard_core::camera::{Camera, Projection};
        let cam = Camera::look_at(
            [0.0, 0.0, 0.0],
            [0.0, 0.0, -1.0],
            [0.0, 1.0, 0.0],
            Projection::Perspective { fov_y_deg: 40.0 },
        );
        let p = Projector(cam.ray_gen(64, 48));
        assert!(p.place([-1.0, -1.0, 5.0], [1.0, 1.0, 7.0]).is_none());
        let cut = p.place([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]).unwrap();
        assert_eq!(cut.rect, [0, 0, 64, 48]);
        let ahead = p.place([-0.1, -0.1, -6.0], [0.1, 0.1, -5.0]).unwrap();
        assert!(ahead.rect[0] > 20 && ahead.rect[2] < 44, "{:?}", ahead.rect);
    }

    /// Merged boxes cover exactly the cells set, each once, for random
    /// masks on grids of 1–4 cells per axis.
    #[test]
    fn merged_cells_cover_the_cells_set_once() {
        let mut r = 0x9e37_79b9_7f4a_7c15u64;
        let mut merged_some = 0;
        for n in 0..4000 {
            r ^= r << 13;
            r ^= r >> 7;
            r ^= r << 17;
            let count = [1 + r % 4, 1 + (r >> 8) % 4, 1 + (r >> 16) % 4];
            let cells = count.iter().product::<u64>();
            let dense = n % 3;
            let mut show = 0u64;
            for c in 0..cells {
                r ^= r << 13;
                r ^= r >> 7;
                r ^= r << 17;
                if r % 4 < 1 + dense {
                    show |= 1 << c;
                }
            }
            let boxes = merge_cells(count, show);
            let mut covered = 0u64;
            for (c0, c1) in &boxes {
                for z in c0[0]..c1[0] {
                    for y in c0[1]..c1[1] {
                        for x in c0[2]..c1[2] {
                            let b = 1u64 << ((z * count[1] + y) * count[2] + x);
                            assert_eq!(covered & b, 0, "{count:?} {show:#x}: cell twice");
                            covered |= b;
                        }
                    }
                }
            }
            assert_eq!(covered, show, "{count:?}");
            merged_some += (boxes.len() < show.count_ones() as usize) as u32;
        }
        assert!(merged_some > 1000, "{merged_some}");
    }
}
