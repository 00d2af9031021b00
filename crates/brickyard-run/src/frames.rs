//! The frame loop of one view, for renders nobody watches (`render`,
//! turntables, `demo`) and the budget rules every view follows.
//!
//! - **Batch** (the default of `render`): the session waits for each
//!   frame's requests to load before inserting them, requests and uploads
//!   are sized to the pool, and a first pass at a quarter of the pixels
//!   and a quarter of the samples along each ray (with the level of detail
//!   of the full image) finds most of the working set cheaply. The full
//!   image is drawn once that pass asks for nothing; what the pass missed
//!   the full image's next frames ask for, and they draw again only the
//!   tiles it touches.
//! - **Streaming** (`--stream`, the viewer, remote sessions): one frame
//!   per batch of arrivals. `render --stream` never waits; the viewer and
//!   remote sessions let a frame that asks for bricks wait up to
//!   [`STREAM_LOAD_WAIT`] for them before inserting, so that the next
//!   frame shows them rather than the same stand-ins again.
//!
//! Either way the LOD budget ([`LodBudget`]) coarsens a view whose working
//! set does not fit the pool, and the loop ends: complete (at the detail
//! that fits), complete but for bricks that failed to load, or because
//! nothing has moved for several frames.

use crate::backend::{Backend, Frame};
use anyhow::Result;
use brickyard_cache::session::Session;
use brickyard_render::budget::{Decision, FrameSignals, LodBudget, Stop};
use brickyard_render::cpu::{Lod, Scene, Tiles};
use brickyard_render::reference::RenderParams;
use brickyard_render::Image;
use std::time::Instant;

/// The longest a frame of a watched view (viewer, remote session) waits
/// for the bricks it asked for (`Session::set_batch`): frames come at
/// least this often while loading.
pub const STREAM_LOAD_WAIT: std::time::Duration = std::time::Duration::from_millis(100);

/// How a view is driven.
#[derive(Debug, Clone, Copy)]
pub struct DriveOptions {
    pub batch: bool,
    pub max_frames: usize,
    /// What the user asked for (its bias is the budget's base).
    pub lod: Lod,
    /// Draw only the tile rows `[start, end)` (CPU; see
    /// [`Tiles::band`]): one rank's share of an image-parallel render; the
    /// request pass draws the rows of its half-size image that cover the
    /// band. The other pixels stay transparent.
    pub band: Option<(u32, u32)>,
}

/// One frame as the loop saw it (for progress lines).
pub struct FrameInfo<'a> {
    pub frame: usize,
    /// The request pass (a quarter of the pixels) rather than the image.
    pub pass: bool,
    pub ms: f64,
    pub bias: f64,
    /// Bytes the loader has read so far.
    pub bytes_read: u64,
    pub f: &'a Frame,
}

/// How a view ended.
pub struct Outcome {
    pub image: Image,
    pub frames: usize,
    pub stop: Option<Stop>,
    /// The LOD budget as it ended (bias in force, working set estimate).
    pub budget: LodBudget,
    pub completeness: f64,
    pub seconds: f64,
}

/// The signals of a frame for the LOD budget.
pub fn signals(s: &Session, f: &Frame) -> FrameSignals {
    FrameSignals::of_frame(s, &f.session, f.stats.completeness() >= 1.0, f.exact_slots)
}

/// Draw one view until it ends; `on_frame` sees every frame.
pub fn drive(
    backend: &mut Backend,
    s: &mut Session,
    scene: &Scene,
    params: &RenderParams,
    opt: DriveOptions,
    budget: &mut LodBudget,
    mut on_frame: impl FnMut(&FrameInfo),
) -> Result<Outcome> {
    let t0 = Instant::now();
    let lod = opt.lod;
    let levels = scene.levels.len();
    let mut frames = 0;
    // The request pass: half the width and height, one level finer than
    // the automatic rule would pick for that size, which is the level the
    // full image asks for (the pixel footprint doubles), and a quarter of
    // the samples along each ray: rays cross the same bricks and, with the
    // opacity corrected for the longer step, end about where they would
    // (at 512³ and 1024² the full frames then asked for 25 bricks more
    // than the pass's 1915, against 22 more than 1917 at the full rate;
    // the pass drew 4.2 M samples instead of 16.9 M).
    let small = (opt.batch && params.width >= 128 && params.height >= 128).then(|| {
        let mut p = params.clone();
        p.width = params.width / 2;
        p.height = params.height / 2;
        p.samples_per_voxel = params.samples_per_voxel * 0.25;
        p
    });
    // First the request pass (while it finds bricks to ask for), then full
    // frames until the budget says stop; at least one full frame. Passes
    // count among `max_frames`: the last frame it allows is always a full
    // one, so that a run draws at most `max_frames` frames (one when
    // `max_frames` is 0 or 1). On the CPU a frame like the last (same
    // pass, same level of detail) draws again only the tiles that were not
    // settled.
    let mut pass = small.is_some();
    let mut full_drawn = false;
    let mut keep: Option<(bool, Lod, Image, Tiles)> = None;
    let mut shown: Option<Image> = None;
    let mut stop = None;
    let mut completeness = 0.0;
    loop {
        if frames >= opt.max_frames && full_drawn {
            break;
        }
        if frames + 1 >= opt.max_frames {
            pass = false;
        }
        let (p, l) = match (&small, pass) {
            (Some(sp), true) => (
                sp,
                match budget.apply(lod, levels) {
                    Lod::Auto { bias } => Lod::Auto { bias: bias - 1.0 },
                    fixed => fixed,
                },
            ),
            _ => (params, budget.apply(lod, levels)),
        };
        let ft = Instant::now();
        let mut f = match keep.take() {
            Some((kp, kl, img, tiles)) if kp == pass && kl == l => {
                backend.frame_again(s, scene, p, l, img, tiles)?
            }
            _ => match opt.band {
                Some((a, b)) => {
                    // The pass's tile row r covers the image's rows 2r and
                    // 2r + 1 (half the pixels, tiles of the same size).
                    let rows = if pass { a / 2..b.div_ceil(2) } else { a..b };
                    backend.frame_band(s, scene, p, l, rows)?
                }
                None => backend.frame(s, scene, p, l)?,
            },
        };
        frames += 1;
        let sig = signals(s, &f);
        on_frame(&FrameInfo {
            frame: frames,
            pass,
            ms: ft.elapsed().as_secs_f64() * 1e3,
            bias: budget.bias,
            bytes_read: s.loader().bytes_read(),
            f: &f,
        });
        let d = budget.update(&sig);
        let tiles = f.tiles.take();
        if pass {
            keep = tiles.map(|t| (true, l, f.image, t));
            // Complete, only failed bricks left, stalled, or nothing more
            // to ask for: the full image takes over.
            pass = match d {
                Decision::Changed { .. } => true,
                Decision::Stop(_) => false,
                Decision::Continue => sig.requests > 0,
            };
            continue;
        }
        full_drawn = true;
        completeness = f.stats.completeness();
        match tiles {
            Some(t) => keep = Some((false, l, f.image, t)),
            None => shown = Some(f.image),
        }
        if let Decision::Stop(why) = d {
            stop = Some(why);
            break;
        }
        if !opt.batch && !sig.progress && !sig.complete {
            // Nothing arrived yet: do not spin.
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }
    let image = match keep {
        Some((false, _, img, _)) => img,
        _ => shown.unwrap_or_else(|| Image::new(params.width, params.height)),
    };
    Ok(Outcome {
        image,
        frames,
        stop,
        budget: budget.clone(),
        completeness,
        seconds: t0.elapsed().as_secs_f64(),
    })
}
