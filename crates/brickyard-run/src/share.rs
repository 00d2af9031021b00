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
