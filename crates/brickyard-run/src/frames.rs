//! The frame loop of one view, for renders nobody watches (`render`,
//! turntables, `demo`) and the budget rules every view follows.
//!
//! - **Batch** (the default of `render`): the session waits for each
//!   frame's requests to load before inserting them, requests and uploads
//!   are sized to the pool, and a first pass at a fraction of the pixels
//!   ([`pass_divisor`]) and a quarter of the samples along each ray (with the level of detail
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

/// Requests per frame: as many bricks as both the pool and the host cache
/// hold (slots of `slot_bytes`), at least 256 and at most `most`: batch
/// renders up to [`BATCH_REQUESTS`], streamed views (`render --stream`,
/// the viewer, remote sessions) up to [`STREAM_REQUESTS`]. The floor is
/// lower where the host cache holds fewer than 256 bricks (not under 16):
/// the bricks a frame asks for are in memory at once, loaded and waiting
/// for the pool, and 256 bricks of 4-byte voxels (154 KiB each) went
/// 40 MiB past a 64 MiB budget.
pub fn requests_per_frame(pool: u64, host: u64, slot_bytes: u64, most: usize) -> usize {
    let slot = slot_bytes.max(1);
    let floor = (host / slot).clamp(16, 256);
    (pool.min(host) / slot).clamp(floor, (most as u64).max(floor)) as usize
}

/// The most requests a frame of a batch render makes.
pub const BATCH_REQUESTS: usize = 4096;

/// The most requests a frame of a streamed view makes. Its frames take
/// longer than the loader takes for a few hundred bricks: with 256 a frame,
/// a 512³ view at 1024² took 11 frames to complete, with 1024 five or six
/// (BENCHMARKS.md).
pub const STREAM_REQUESTS: usize = 1024;

/// How a view is driven.
#[derive(Debug, Clone, Copy)]
pub struct DriveOptions {
    pub batch: bool,
    pub max_frames: usize,
    /// What the user asked for (its bias is the budget's base).
    pub lod: Lod,
    /// Draw only the tile rows `[start, end)` (CPU; see
    /// [`Tiles::band`]): one rank's share of an image-parallel render; the
    /// request pass draws the rows of its smaller image that cover the
    /// band. The other pixels stay transparent.
    pub band: Option<(u32, u32)>,
}

/// One frame as the loop saw it (for progress lines).
pub struct FrameInfo<'a> {
    pub frame: usize,
    /// The request pass (a fraction of the pixels, [`pass_divisor`])
    /// rather than the image.
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
    /// Samples of the last full frame that found no data at any level
    /// (where even the coarsest level's bricks could not be read): holes.
    pub unserved: u64,
    pub seconds: f64,
}

/// The request pass's width and height are the image's divided by this:
/// the largest of 2, 4 and 8 that leaves the pass at least 256 pixels on
/// its shorter side (2 for smaller images).
pub fn pass_divisor(width: u32, height: u32) -> u32 {
    let short = width.min(height);
    [8, 4].into_iter().find(|d| short / d >= 256).unwrap_or(2)
}

/// The request pass of `params`: the image's width and height divided by
/// [`pass_divisor`] and a quarter of the samples along each ray, at the
/// levels of detail the full image draws (its pixel footprint picks them:
/// [`RenderParams::lod_height`]). The viewer's previews are drawn so too.
pub fn request_pass(params: &RenderParams) -> RenderParams {
    let div = pass_divisor(params.width, params.height);
    let mut p = params.clone();
    p.width = params.width / div;
    p.height = params.height / div;
    p.lod_height = Some(params.lod_height());
    p.samples_per_voxel = params.samples_per_voxel * 0.25;
    p
}

/// A view changed draws previews for at most this long, in the viewer and
/// in remote rendering (then full frames, whose level-of-detail budget
/// copes with a pool the view does not fit).
pub const PREVIEW_FOR: std::time::Duration = std::time::Duration::from_secs(2);

/// A view's preview, as `render`'s request pass is drawn: the width and
/// height divided by [`pass_divisor`], a quarter of the
/// samples along each ray, at the level of detail of the full image.
/// `None` where a frame is cheap anyway or laid out otherwise (slices,
/// several views, images under 128 pixels a side) and on a device, whose
/// frames are fast.
///
/// A full frame drawn while none of the finer bricks are resident samples
/// the coarse stand-ins at the full image's positions, and rays go deeper
/// through the smoother data: on two cores a 1200×800 DVR of Colin27
/// took 1.7 s so, four times a complete frame (BENCHMARKS.md).
pub fn preview(backend: &Backend, p: &RenderParams, lod: Lod) -> Option<(RenderParams, Lod)> {
    use brickyard_render::reference::RenderMode;
    let cheap = matches!(p.mode, RenderMode::Slice { .. });
    if cheap
        || !matches!(backend, Backend::Cpu)
        || p.views.is_some()
        || p.width < 128
        || p.height < 128
    {
        return None;
    }
    Some((request_pass(p), lod))
}

/// Whether previews of a view that changed at `since` give way to full
/// frames after preview `f`: it is complete (the view was warm), nothing
/// more is coming, the pool thrashes, or [`PREVIEW_FOR`] has passed.
pub fn preview_over(s: &Session, f: &Frame, since: Instant) -> bool {
    let sig = signals(s, f);
    let pending = f.session.pending + f.session.in_flight + f.session.waiting_upload;
    f.stats.completeness() >= 1.0
        || (sig.requests == 0 && pending == 0)
        || sig.evicted_in_use > 0
        || since.elapsed() >= PREVIEW_FOR
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
    // The request pass: the image's width and height divided by
    // `pass_divisor` (2, 4 or 8), at the levels the full image asks for
    // (its pixel footprint picks them), and a quarter of the samples
    // along each ray: rays cross
    // the same bricks and, with the opacity corrected for the longer step,
    // end about where they would. A brick of the level the image draws
    // spans tens of its pixels, so pass rays a few pixels apart still
    // cross every brick that shows; the few they pass between, the full
    // image asks for (at 512³ and 1920×1080: 35 bricks more than the
    // pass's 1915 at a quarter of the width, 16 at half of it, while the
    // first pass took a third of the time; BENCHMARKS.md).
    let div = pass_divisor(params.width, params.height);
    let small = request_pass(params);
    let small = (opt.batch && params.width >= 128 && params.height >= 128).then_some(small);
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
    let mut unserved = 0;
    // The last complete image (its unserved samples, its bias) while a
    // finer bias is tried.
    let mut complete: Option<(Image, u64, f64)> = None;
    loop {
        if frames >= opt.max_frames && full_drawn {
            break;
        }
        if frames + 1 >= opt.max_frames {
            pass = false;
        }
        let l = budget.apply(lod, levels);
        let p = match (&small, pass) {
            (Some(sp), true) => sp,
            _ => params,
        };
        let ft = Instant::now();
        let mut f = match keep.take() {
            Some((kp, kl, img, tiles)) if kp == pass && kl == l => {
                backend.frame_again(s, scene, p, l, img, tiles)?
            }
            _ => match opt.band {
                Some((a, b)) => {
                    // The pass's tile row r covers the image's rows
                    // div·r to div·r + div − 1 (tiles of the same size).
                    let rows = if pass { a / div..b.div_ceil(div) } else { a..b };
                    backend.frame_band(s, scene, p, l, rows)?
                }
                None => backend.frame(s, scene, p, l)?,
            },
        };
        frames += 1;
        crate::memory::relieve();
        // Stopped (Ctrl-C) during the frame: it is not whole.
        if scene.stopped() {
            return Err(crate::process::Interrupted.into());
        }
        let sig = signals(s, &f);
        on_frame(&FrameInfo {
            frame: frames,
            pass,
            ms: ft.elapsed().as_secs_f64() * 1e3,
            bias: budget.bias,
            bytes_read: s.loader().bytes_read(),
            f: &f,
        });
        // A request pass complete while a finer bias is tried says nothing
        // of the image (it samples a fraction of its pixels, and the image
        // may need bricks the pass passed between): the image's frame
        // decides whether the try holds. Taken as the try's end, the image
        // then coarsened again and a finer bias was tried again, frame
        // after frame (a 600 KiB pool on the device ran until its frames
        // ran out).
        let d = if pass && sig.complete && budget.trying_finer() {
            Decision::Stop(Stop::Complete)
        } else {
            budget.update(&sig)
        };
        if let Decision::Revert { .. } = d {
            // The finer bias did not fit: the complete image stands.
            break;
        }
        let tiles = f.tiles.take();
        if pass {
            keep = tiles.map(|t| (true, l, f.image, t));
            // Complete, only failed bricks left, stalled, or nothing more
            // to ask for: the full image takes over.
            pass = match d {
                Decision::Changed { .. } => true,
                Decision::Stop(_) => false,
                Decision::Continue => sig.requests > 0,
                Decision::Revert { .. } => unreachable!("handled above"),
            };
            continue;
        }
        full_drawn = true;
        completeness = f.stats.completeness();
        unserved = f.stats.unserved;
        match tiles {
            Some(t) => keep = Some((false, l, f.image, t)),
            None => shown = Some(f.image),
        }
        if let Decision::Stop(why) = d {
            // Complete at a bias the budget raised: try finer, keeping
            // this image in case the finer one does not fit.
            let finer = (why == Stop::Complete && frames < opt.max_frames)
                .then(|| match lod {
                    Lod::Fixed(_) => budget.try_finer_level(),
                    Lod::Auto { .. } => budget.try_finer(),
                })
                .flatten();
            if let Some((from, _)) = finer {
                let img = match keep.take() {
                    Some((_, _, img, _)) => img,
                    None => shown.take().expect("a full frame was drawn"),
                };
                complete = Some((img, unserved, from));
                pass = small.is_some();
                continue;
            }
            stop = Some(why);
            break;
        }
        if !opt.batch && !sig.progress && !sig.complete {
            // Nothing arrived yet: do not spin.
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }
    // Ended while trying a finer bias (out of frames, or it did not
    // fit): the image complete at the coarser bias is the result.
    budget.abandon_try();
    let kept = complete.filter(|_| stop.is_none());
    if let Some((_, _, bias)) = kept {
        budget.bias = bias;
    }
    // A fixed level moves by whole levels: the bias says by how many
    // (+0.5 and +1.0 draw the same level; the back ends then report
    // alike).
    if let Lod::Fixed(_) = lod {
        budget.bias = budget.base + (budget.bias - budget.base).max(0.0).ceil();
    }
    if let Some((img, u, _)) = kept {
        return Ok(Outcome {
            image: img,
            frames,
            stop: Some(Stop::Complete),
            budget: budget.clone(),
            completeness: 1.0,
            unserved: u,
            seconds: t0.elapsed().as_secs_f64(),
        });
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
        unserved,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::{pass_divisor, requests_per_frame, BATCH_REQUESTS, STREAM_REQUESTS};

    /// Requests per frame: what the smaller of pool and host cache holds,
    /// between 256 and the mode's most.
    #[test]
    fn requests_per_frame_follow_the_pool_and_host_cache() {
        let slot = 40 << 10;
        // A small pool: the floor.
        assert_eq!(
            requests_per_frame(4 << 20, 1 << 30, slot, BATCH_REQUESTS),
            256
        );
        // 20 MiB: 512 slots, under either cap.
        assert_eq!(
            requests_per_frame(20 << 20, 2 << 30, slot, BATCH_REQUESTS),
            512
        );
        assert_eq!(
            requests_per_frame(2 << 30, 20 << 20, slot, STREAM_REQUESTS),
            512
        );
        // Large budgets: the mode's cap.
        assert_eq!(
            requests_per_frame(1 << 30, 1 << 30, slot, BATCH_REQUESTS),
            4096
        );
        assert_eq!(
            requests_per_frame(1 << 30, 1 << 30, slot, STREAM_REQUESTS),
            1024
        );
        // Degenerate inputs stay in range.
        assert_eq!(
            requests_per_frame(1 << 30, 1 << 30, 0, STREAM_REQUESTS),
            1024
        );
        assert_eq!(requests_per_frame(0, 0, slot, 100), 16);
        // A host cache of fewer than 256 bricks lowers the floor to what
        // it holds.
        assert_eq!(
            requests_per_frame(5 << 20, 4 << 20, 154 << 10, BATCH_REQUESTS),
            26
        );
    }

    /// The pass keeps at least 256 pixels on its shorter side, and takes
    /// the largest divisor that does (up to 8).
    #[test]
    fn pass_divisor_keeps_256_pixels_on_the_shorter_side() {
        assert_eq!(pass_divisor(512, 512), 2);
        assert_eq!(pass_divisor(800, 600), 2);
        assert_eq!(pass_divisor(1024, 1024), 4);
        assert_eq!(pass_divisor(1920, 1080), 4);
        assert_eq!(pass_divisor(3840, 2160), 8);
        assert_eq!(pass_divisor(8192, 8192), 8);
        assert_eq!(pass_divisor(200, 4000), 2);
        for w in (128..5000).step_by(37) {
            for h in (128..5000).step_by(41) {
                let d = pass_divisor(w, h);
                assert!([2, 4, 8].contains(&d));
                assert!(d == 2 || w.min(h) / d >= 256, "{w}x{h}: {d}");
                assert!(d == 8 || w.min(h) / (2 * d) < 256, "{w}x{h}: {d}");
            }
        }
    }
}
