//! Several processes drawing one render (`mpirun -n N brickyard render`):
//! what the render run asks of them. The MPI side is `brickyard-dist`;
//! here only the questions, so that the run stays free of MPI.
//!
//! - **Image-parallel**: the image's rows of CPU tiles go out in bands, on
//!   demand ([`Share::next_band`]); each rank draws its bands through its
//!   own virtual-memory session over the shared store, the other pixels
//!   stay transparent, and the ranks' images are added up
//!   ([`Share::sum`]: every pixel was drawn by exactly one rank).
//! - **Data-parallel (sort-last)**: each rank draws the whole image but
//!   only the samples inside its region of the volume ([`Share::region`],
//!   a box of whole bricks), and the partial images are composited in
//!   visibility order ([`Share::composite`]).

use anyhow::Result;
use brickyard_render::Image;

/// How the ranks share a render.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    Image,
    Data,
}

/// The ranks of a shared render. Every method is collective unless it
/// says otherwise: every rank calls it, in the same order.
pub trait Share {
    fn rank(&self) -> usize;
    fn size(&self) -> usize;
    fn split(&self) -> Split;
    /// How many ranks run on this rank's node, this one included (they
    /// share its memory: a default memory budget taken from the node's
    /// RAM is divided among them). Not collective.
    fn ranks_on_node(&self) -> usize {
        1
    }
    /// Image-parallel: the next band of tile rows this rank draws of the
    /// `rows` of view `view`; `None` when none is left. Not collective.
    fn next_band(&mut self, view: u32, rows: u32) -> Result<Option<(u32, u32)>>;
    /// Image-parallel: rank 0 answers whoever asks for a band (called
    /// between frames; nothing elsewhere). Not collective.
    fn serve(&mut self);
    /// Image-parallel, after a failure: this rank takes no more bands of
    /// view `view`. Not collective.
    fn stop_asking(&mut self, view: u32);
    /// Every rank's outcome; all get the first failure (naming its rank).
    fn agree(&mut self, mine: Result<()>) -> Result<()>;
    /// Every rank's `mine` (a time, say), in rank order, on rank 0; empty
    /// on the others.
    fn gather_times(&mut self, mine: f64) -> Vec<f64>;
    /// Every rank's `mine` (how its part of a view went, say), in rank
    /// order, on rank 0; empty on the others.
    fn gather_text(&mut self, mine: String) -> Vec<String>;
    /// Image-parallel: the sum of the ranks' images, on rank 0.
    fn sum(&mut self, img: Image) -> Result<Option<Image>>;
    /// Data-parallel: the k-d split of the grid of `bricks` level-0
    /// bricks (`[z, y, x]`) among the ranks, balancing `weight` (per
    /// brick, see [`brick_weight`]): every rank's box of bricks, in rank
    /// order (an empty box where there are more ranks than bricks). The
    /// same on every rank for the same weights; kept for
    /// [`composite`](Self::composite), whose visibility order follows the
    /// cuts in the world of `spacing` (`[z, y, x]`) and bricks of `brick`
    /// voxels.
    fn regions(
        &mut self,
        bricks: [u64; 3],
        brick: u64,
        spacing: [f64; 3],
        weight: &dyn Fn([u64; 3]) -> f64,
    ) -> Vec<BrickBox>;
    /// Data-parallel: the partial images composited front to back as seen
    /// from `eye` (world), or by maximum (`mip`), on rank 0; the time spent
    /// compositing is reported with it.
    fn composite(&mut self, img: Image, mip: bool, eye: [f64; 3]) -> Result<(Option<Image>, f64)>;
}

/// A box of level-0 bricks `[lo, hi)` per axis, `[z, y, x]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BrickBox {
    pub lo: [u64; 3],
    pub hi: [u64; 3],
}

impl BrickBox {
    pub fn is_empty(&self) -> bool {
        (0..3).any(|a| self.hi[a] <= self.lo[a])
    }

    /// The box in world coordinates `[x, y, z]` `(lo, hi)` for level 0 of
    /// `dims` voxels (`[z, y, x]`) of `spacing`, bricks of `brick` voxels
    /// (clipped to the volume); `None` when empty.
    pub fn world(&self, dims: [u64; 3], spacing: [f64; 3], brick: u64) -> Option<[[f64; 3]; 2]> {
        if self.is_empty() {
            return None;
        }
        let world = |b: [u64; 3]| {
            let v = [0, 1, 2].map(|a| (b[a] * brick).min(dims[a]) as f64 * spacing[a]);
            [v[2], v[1], v[0]]
        };
        Some([world(self.lo), world(self.hi)])
    }

    /// The sum of `weight` over the box's bricks.
    pub fn load(&self, weight: &dyn Fn([u64; 3]) -> f64) -> f64 {
        let mut s = 0.0;
        for z in self.lo[0]..self.hi[0] {
            for y in self.lo[1]..self.hi[1] {
                for x in self.lo[2]..self.hi[2] {
                    s += weight([z, y, x]);
                }
            }
        }
        s
    }
}

/// What a brick costs a rank that draws nothing of it, against one it
/// draws (1): rays cross it in one jump and nothing of it is read.
pub const SKIPPED_WEIGHT: f64 = 1.0 / 16.0;

/// The weight of level-0 brick `b` of channel `channel` for the k-d split,
/// from the bricks' value ranges (the store's per-brick statistics, apron
/// included): 1 for a brick the rays draw (`drawn(lo, hi)`: for DVR, the
/// transfer function gives its range some opacity; for MIP, it holds data,
/// `lo < hi`) or whose range is unknown, [`SKIPPED_WEIGHT`] for the others
/// (empty or constant bricks that draw nothing, hidden ones). Without
/// ranges (no statistics) every brick weighs 1. The same on every rank.
pub fn brick_weight<'a>(
    ranges: Option<&'a brickyard_cache::ranges::LevelRanges>,
    channel: usize,
    drawn: &'a dyn Fn(f32, f32) -> bool,
) -> impl Fn([u64; 3]) -> f64 + 'a {
    move |b| match ranges {
        Some(r) if channel < r.channels && (0..3).all(|a| b[a] < r.bricks[a]) => {
            let [lo, hi] = r.get(channel, b);
            if lo.is_nan() || hi.is_nan() || drawn(lo, hi) {
                1.0
            } else {
                SKIPPED_WEIGHT
            }
        }
        _ => 1.0,
    }
}

/// How far the rays of a view run through each level-0 brick: the rays of
/// a `grid × grid·h/w` lattice over a `width × height` image of `camera`,
/// stepped at a quarter of a brick, their length summed per brick
/// (`[z, y, x]`, index `(z·ny + y)·nx + x`, of `bricks` bricks of `brick`
/// voxels over `dims` voxels of `spacing`). A brick's samples in the view
/// are in proportion (every ray steps evenly), so this weighs the work a
/// brick gives a rank that draws it, which its statistics alone do not:
/// a brick at the rim of the view is crossed by few rays, one in its
/// middle by many, and the regions behind each other along the rays share
/// their samples unevenly. The same on every rank.
pub fn ray_lengths(
    camera: &brickyard_core::Camera,
    (width, height): (u32, u32),
    grid: u32,
    (dims, spacing, brick): ([u64; 3], [f64; 3], u64),
    bricks: [u64; 3],
) -> Vec<f64> {
    use brickyard_core::camera::intersect_box_inv;
    let rays = brickyard_core::views::ViewRays::new(camera, None, width, height);
    let extent = brickyard_core::camera::world_extent(dims, spacing);
    let gx = grid.clamp(1, width.max(1));
    let gy = ((grid as u64 * height as u64 / width.max(1) as u64) as u32).clamp(1, height.max(1));
    let n = (bricks[0] * bricks[1] * bricks[2]) as usize;
    let mut len = vec![0.0f64; n];
    // World x, y, z: spacing and bricks are [z, y, x].
    let sp = [spacing[2], spacing[1], spacing[0]];
    let nb = [bricks[2], bricks[1], bricks[0]];
    let dt = 0.25 * brick as f64 * sp.iter().cloned().fold(f64::INFINITY, f64::min);
    for j in 0..gy {
        for i in 0..gx {
            let px = ((i as u64 * 2 + 1) * width as u64 / (2 * gx as u64)) as u32;
            let py = ((j as u64 * 2 + 1) * height as u64 / (2 * gy as u64)) as u32;
            let ray = rays.pixel_ray(px, py);
            let inv = ray.dir.map(|d| 1.0 / d);
            let Some((t0, t1)) = intersect_box_inv(&ray, inv, [0.0; 3], extent) else {
                continue;
            };
            let mut t = t0 + 0.5 * dt;
            while t < t1 {
                let w = ray.at(t);
                let b = [0, 1, 2].map(|a| {
                    ((w[a] / sp[a] / brick as f64).floor().max(0.0) as u64).min(nb[a] - 1)
                });
                len[((b[2] * nb[1] + b[1]) * nb[0] + b[0]) as usize] += dt;
                t += dt;
            }
        }
    }
    len
}

/// A failure every rank agreed on at a meeting point (the message names
/// the rank that failed and why).
#[derive(Debug, Clone)]
pub struct Agreed(pub String);

impl std::fmt::Display for Agreed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Agreed {}

#[cfg(test)]
mod tests {
    use super::*;
    use brickyard_core::camera::{intersect_box_inv, world_extent, Camera, Projection};

    /// The lengths add up to the rays' lengths inside the volume (within a
    /// step per ray), and the bricks in the middle of the view are crossed
    /// by more ray length than its corners.
    #[test]
    fn ray_lengths_follow_the_rays() {
        let (dims, spacing, brick) = ([64u64, 48, 80], [1.0, 1.5, 0.8], 16u64);
        let nb = dims.map(|d| d.div_ceil(brick));
        let extent = world_extent(dims, spacing);
        let cam = Camera::fit(
            extent,
            30.0,
            20.0,
            Projection::Perspective { fov_y_deg: 35.0 },
        );
        let (w, h, grid) = (320u32, 240u32, 64u32);
        let l = ray_lengths(&cam, (w, h), grid, (dims, spacing, brick), nb);
        assert_eq!(l.len() as u64, nb.iter().product::<u64>());
        assert!(l.iter().all(|x| *x >= 0.0));
        let rays = brickyard_core::views::ViewRays::new(&cam, None, w, h);
        let (gy, mut want, mut n) = (grid * h / w, 0.0, 0u32);
        for j in 0..gy {
            for i in 0..grid {
                let r = rays.pixel_ray((2 * i + 1) * w / (2 * grid), (2 * j + 1) * h / (2 * gy));
                if let Some((t0, t1)) =
                    intersect_box_inv(&r, r.dir.map(|d| 1.0 / d), [0.0; 3], extent)
                {
                    want += t1 - t0;
                    n += 1;
                }
            }
        }
        let dt = 0.25 * brick as f64 * 0.8;
        let got: f64 = l.iter().sum();
        assert!(
            n > 100 && (got - want).abs() <= n as f64 * dt,
            "{got} vs {want}"
        );
        // Per brick against the exact lengths of the same rays in its box
        // (within one step per ray that meets it, at each end).
        let mut worst = 0.0f64;
        for z in 0..nb[0] {
            for y in 0..nb[1] {
                for x in 0..nb[2] {
                    let v = |b: [u64; 3]| {
                        [2, 1, 0].map(|a| (b[a] * brick).min(dims[a]) as f64 * spacing[a])
                    };
                    let (lo, hi) = (v([z, y, x]), v([z + 1, y + 1, x + 1]));
                    let (mut exact, mut met) = (0.0, 0u32);
                    for j in 0..gy {
                        for i in 0..grid {
                            let r = rays.pixel_ray(
                                (2 * i + 1) * w / (2 * grid),
                                (2 * j + 1) * h / (2 * gy),
                            );
                            if let Some((t0, t1)) =
                                intersect_box_inv(&r, r.dir.map(|d| 1.0 / d), lo, hi)
                            {
                                exact += t1 - t0;
                                met += 1;
                            }
                        }
                    }
                    let got = l[((z * nb[1] + y) * nb[2] + x) as usize];
                    assert!(
                        (got - exact).abs() <= 2.0 * dt * met as f64,
                        "brick {:?}: {got} vs {exact}",
                        [z, y, x]
                    );
                    worst = worst.max(exact);
                }
            }
        }
        assert!(worst > 100.0 * dt, "the view meets the bricks");
    }
}
