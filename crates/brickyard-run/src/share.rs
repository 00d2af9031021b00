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
    /// Image-parallel: the sum of the ranks' images, on rank 0.
    fn sum(&mut self, img: Image) -> Result<Option<Image>>;
    /// Data-parallel: this rank's region, a world box `[x, y, z]` `(lo,
    /// hi)` (`None`: an empty region), for level 0 of `dims` voxels
    /// (`[z, y, x]`) of `spacing`, cut at bricks of `brick` voxels.
    fn region(
        &mut self,
        dims: [u64; 3],
        spacing: [f64; 3],
        brick: u64,
    ) -> Option<([f64; 3], [f64; 3])>;
    /// Data-parallel: the partial images composited front to back as seen
    /// from `eye` (world), or by maximum (`mip`), on rank 0; the time spent
    /// compositing is reported with it.
    fn composite(&mut self, img: Image, mip: bool, eye: [f64; 3]) -> Result<(Option<Image>, f64)>;
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
