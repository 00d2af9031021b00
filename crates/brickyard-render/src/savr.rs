//! Progressive DVR by sample accumulation on the CPU. Each accumulation
//! frame takes one more run of samples along every ray, at positions
//! shifted within the step by a low-discrepancy offset, keeps the values,
//! and blends every sample kept so far in depth order. After `2^m` frames a
//! ray has been sampled at `2^m` times the rate of a single frame, at the
//! positions of a single pass with step `Δ/2^m`; a transfer-function edit
//! re-blends the kept values without touching the volume.
//!
//! # Sample positions
//!
//! Frame `k` samples a ray entering the volume at `t0` at
//! `t0 + (j + o_k)·Δ`, `j = 0, 1, …`, with `o_k = ½ + r₂(k) (mod 1)` and
//! `r₂` the base-2 radical inverse (Halton/van der Corput: 0, ½, ¼, ¾, …).
//! Frame 0 is the plain renderer's grid (`o = ½`); the first `2^m` offsets
//! are the multiples of `2^-m`, so the union of their runs is the grid of
//! step `Δ/2^m`. `Δ` is the step of the level where the ray enters (with
//! automatic level of detail the level of each sample still follows its
//! distance; only the step is the entry level's for the whole ray).
//!
//! # The store and its order
//!
//! A pixel keeps its samples frame-major: run `k` holds frame `k`'s values
//! in order of `j`. Depth is implicit (`j` and `k` give it), so a sample
//! costs 5 bytes: the value (`f32`) and a flag byte (taken from a coarser
//! stand-in; nothing resident at all). The depth order is a traversal, not
//! a sort: for `j = 0, 1, …`, the runs in the order of their offsets. A
//! pixel also keeps its step and a first step, length and end flag per run
//! (12 bytes a frame) and about 120 bytes of header.
//!
//! # Regions and bands
//!
//! A sort-last rank keeps only the samples of the whole ray's positions
//! that fall in its region (`RenderParams::clip`, `[c0, c1)` along the ray)
//! and blends without early termination when the parameters say so; a run
//! then starts at the first step in the region. [`Accumulation::rows`]
//! keeps a band of an image's rows (image-parallel ranks).
//!
//! # Opacity correction and early termination
//!
//! A pixel holding `n` runs blends with step `Δ/n`: opacity is corrected
//! by `(Δ/n)/Δ_ref` (the spacing reached; exactly the spacing of the
//! samples whenever `n` is a power of two). Blending stops at an
//! accumulated opacity of 0.99 like the plain renderer. A run is taken up
//! to its own early termination (as a single frame would stop) and
//! recorded as *open*; when the blend reaches the end of an open run
//! before stopping, that run is extended from the volume and the blend
//! starts again. The blend is thus always what it would be with every run
//! taken to the ray's end.
//!
//! # When the store is full
//!
//! The budget is a number of samples per pixel. A run never holds more
//! than the ray's steps `S = ⌈(t1 − t0)/Δ⌉ + 1`, and a pixel begins run `k`
//! only when `(k + 1)·S` fits the budget (run 0 always): a pixel whose
//! budget is spent stays at the rate it reached, blended correctly for it,
//! and later frames leave it alone. Memory never exceeds
//! `max(budget, S)·5` bytes a pixel.
//!
//! Run 0 must fit too: where the longest ray of the view would take more
//! samples than the budget at the level of detail asked for, the
//! accumulation samples coarser levels ([`lod_within`]), whose larger step
//! takes fewer samples. A small budget thus costs detail, never the ray's
//! end (the device's store, fixed per pixel, cannot hold more).
//!
//! # Out of core
//!
//! Samples are looked up through the virtual memory like the plain
//! renderer's, at the level each sample asks for; a miss is requested and
//! answered by the finest resident coarser level, and the sample is marked
//! as a stand-in. Every frame first retakes a pixel's stand-ins, so they
//! are replaced as the finer bricks arrive: a complete image
//! ([`Accumulation::complete`]) holds none. Accumulation keeps every value a
//! ray crosses (a later transfer function may show them), so it does not
//! skip bricks the current transfer function hides.

pub mod device;

use crate::cpu::{FrameStats, Lod, Scene};
use crate::image::Image;
use crate::optics::composite_visible;
use crate::params::{RenderMode, RenderParams};
use crate::shading::{cosine, lit};
use crate::walk::{Frame, Walker};
use brickyard_cache::vm::{Requests, VirtualMemory};
use brickyard_core::camera::{intersect_box_inv, Ray};
use brickyard_core::transfer::TfEval;
use brickyard_core::views::ViewRays;
use brickyard_core::{dispatch_dtype, Sample, Shading, TransferFunction};
use rayon::prelude::*;

/// The most frames a pixel accumulates.
pub const MAX_FRAMES: u32 = 256;

/// Flag: the sample came from a coarser level than it asked for.
const STAND_IN: u8 = 1;
/// Flag: nothing resident served the sample (its value is meaningless).
const UNSERVED: u8 = 2;

/// Samples an open run is extended by when the blend needs more of it.
const EXTEND: usize = 8;

/// Rows of pixels per piece of parallel work.
const BAND: usize = 8;

/// Bytes a kept sample costs.
pub const BYTES_PER_SAMPLE: usize = 5;

/// Bytes a kept sample costs, with its normal's cosine where the samples
/// keep normals (a shading transfer function).
pub fn sample_bytes(normals: bool) -> u64 {
    BYTES_PER_SAMPLE as u64 + if normals { 4 } else { 0 }
}

/// The offset within a step of frame `k`'s samples: `½ + r₂(k) (mod 1)`.
pub fn offset(k: u32) -> f64 {
    let r = k.reverse_bits() as f64 / 4_294_967_296.0;
    (0.5 + r).fract()
}

#[derive(Debug, Clone, Copy)]
struct RunInfo {
    /// The step index `j` of the run's first sample (0 but in a region,
    /// whose runs start at its entry).
    first: u32,
    len: u32,
    /// Taken to the ray's end (else open: more may be taken).
    ended: bool,
}

/// One pixel's kept samples.
#[derive(Debug, Clone, Default)]
struct Pixel {
    /// Step of the runs (0: the ray misses the volume).
    dt: f64,
    t0: f64,
    t1: f64,
    /// The part of the ray whose samples are kept, `[lo, hi)`: the whole
    /// ray, or its part in the region (sort-last).
    lo: f64,
    hi: f64,
    values: Vec<f32>,
    flags: Vec<u8>,
    /// With shading: per sample the cosine `|ĝ·d̂|` between its gradient
    /// and the ray (negative: a zero gradient, unshaded); else empty.
    cos: Vec<f32>,
    runs: Vec<RunInfo>,
    /// Kept samples flagged as stand-ins.
    stand_ins: u32,
    /// The last blend ran out of kept samples (after a re-blend).
    short: bool,
}

impl Pixel {
    fn frames(&self) -> u32 {
        self.runs.len() as u32
    }

    /// Upper bound on the samples of one run.
    fn max_run(&self) -> usize {
        ((self.t1 - self.t0) / self.dt).ceil() as usize + 1
    }

    fn start(&self, k: usize) -> usize {
        self.runs[..k].iter().map(|r| r.len as usize).sum()
    }

    /// Bytes this pixel holds allocated.
    fn memory(&self) -> usize {
        self.values.capacity() * 4
            + self.flags.capacity()
            + self.cos.capacity() * 4
            + self.runs.capacity() * std::mem::size_of::<RunInfo>()
            + std::mem::size_of::<Pixel>()
    }
}

/// What an accumulation frame did.
#[derive(Debug, Clone, Default)]
pub struct AccumStats {
    /// Lookups made (new samples, extensions and retakes).
    pub frame: FrameStats,
    /// Stand-in samples retaken at the level they asked for.
    pub retaken: u64,
    /// Stand-ins kept after the frame.
    pub stand_ins: u64,
    /// Samples added to open runs for the blend.
    pub extended: u64,
    /// Pixels whose budget stopped them short of the frames asked for.
    pub full: u64,
    /// Samples kept after the frame, all pixels.
    pub kept: u64,
}

/// The accumulation of one view: per pixel the samples kept so far, and
/// the image they blend to. A camera move or a change of image size,
/// level of detail, sampling rate or channel starts a new one.
pub struct Accumulation {
    width: u32,
    height: u32,
    /// The image rows kept: `row0 .. row0 + rows` of the `height` rows.
    row0: u32,
    rows: u32,
    target: u32,
    budget: usize,
    pixels: Vec<Pixel>,
    /// `orders[n − 1]`: frames `0..n` by increasing offset.
    orders: Vec<Vec<u8>>,
    reference: f64,
    image: Image,
    /// Frames drawn.
    drawn: u32,
    /// Whether samples keep their normal's cosine (fixed by the first
    /// frame: whether its transfer function shades).
    shaded: Option<bool>,
    /// Blends stop at an opacity of 0.99 (`RenderParams::early_termination`
    /// of the last frame; regions of a sort-last render blend everything).
    early: bool,
    /// Blend a pixel only once its last run is taken (a render that shows
    /// only the last image): frame `k` then costs one run, not a blend of
    /// `k` runs, and `N` frames cost `N` runs instead of `N²/2`.
    last_only: bool,
}

/// The result of a blend from kept samples.
enum Blend {
    Done([f32; 4]),
    /// Run `k` ran out before the ray stopped (colour so far).
    Short(usize, [f32; 4]),
}

impl Accumulation {
    /// An empty accumulation of `target` frames (at most [`MAX_FRAMES`])
    /// for images of `width × height`, keeping at most `budget` samples per
    /// pixel (see the module notes).
    pub fn new(width: u32, height: u32, target: u32, budget: usize) -> Accumulation {
        Accumulation::rows(width, height, 0..height, target, budget)
    }

    /// An accumulation of the image rows `rows` only of a `width × height`
    /// view (a band of an image shared by several processes): its
    /// [`image`](Self::image) holds those rows.
    pub fn rows(
        width: u32,
        height: u32,
        rows: std::ops::Range<u32>,
        target: u32,
        budget: usize,
    ) -> Accumulation {
        let row0 = rows.start.min(height);
        let n_rows = rows.end.min(height).saturating_sub(row0);
        let target = target.clamp(1, MAX_FRAMES);
        let orders = (1..=target)
            .map(|n| {
                let mut o: Vec<u8> = (0..n).map(|k| k as u8).collect();
                o.sort_by(|a, b| offset(*a as u32).total_cmp(&offset(*b as u32)));
                o
            })
            .collect();
        Accumulation {
            width,
            height,
            row0,
            rows: n_rows,
            target,
            budget,
            pixels: vec![Pixel::default(); width as usize * n_rows as usize],
            orders,
            reference: 0.0,
            image: Image::new(width, n_rows),
            drawn: 0,
            shaded: None,
            early: true,
            last_only: false,
        }
    }

    /// The image of the samples kept so far (of the rows kept, see
    /// [`rows`](Self::rows)).
    pub fn image(&self) -> &Image {
        &self.image
    }

    /// Frames drawn (a frame drawn in parts counts when its last part is).
    pub fn drawn(&self) -> u32 {
        self.drawn
    }

    /// Frames asked for.
    pub fn target(&self) -> u32 {
        self.target
    }

    /// Samples a pixel may keep.
    pub fn budget(&self) -> usize {
        self.budget
    }

    /// The fewest frames any pixel whose ray meets the volume holds.
    pub fn frames(&self) -> u32 {
        self.pixels
            .iter()
            .filter(|p| p.dt > 0.0)
            .map(|p| p.frames())
            .min()
            .unwrap_or(self.drawn.min(self.target))
    }

    /// Bytes of kept samples and run headers, all pixels: what their
    /// buffers hold allocated, room not yet used included.
    pub fn memory(&self) -> usize {
        self.pixels.iter().map(Pixel::memory).sum()
    }

    /// The bytes this accumulation is expected to hold once it has drawn
    /// `target` frames, from what its frames so far kept: each pixel's
    /// runs at their mean length so far (an eighth more, and two samples
    /// a run, for runs a little longer and for extensions), or what its
    /// buffers hold now where more. Before the first frame: what the
    /// pixels alone take.
    pub fn expected_memory(&self, target: u32) -> u64 {
        let per = sample_bytes(self.shaded == Some(true));
        let t = target.max(1) as u64;
        self.pixels
            .iter()
            .map(|p| {
                let d = p.runs.len() as u64;
                let now = p.memory() as u64;
                if d == 0 {
                    return now;
                }
                let runs = (t * std::mem::size_of::<RunInfo>() as u64)
                    .max((p.runs.capacity() * std::mem::size_of::<RunInfo>()) as u64);
                let samples = (p.values.len() as u64 * t * 9).div_ceil(d * 8) + 2 * t;
                let expected = std::mem::size_of::<Pixel>() as u64 + runs + samples * per;
                // (After one run the buffers hold only it: the second
                // reserves for the frames asked for then.)
                match d {
                    1 => expected,
                    _ => now.max(expected),
                }
            })
            .sum()
    }

    /// Lower the frames asked for to the most whose
    /// [`expected_memory`](Self::expected_memory) is within `bytes` (never
    /// below the frames drawn, nor below 1); pixels then stop at the rate
    /// reached, as with a per-pixel budget. Returns, when it was lowered,
    /// the new number of frames and the bytes the frames asked for were
    /// expected to take. Call it after the first frame: the second
    /// reserves each pixel's room for the frames then asked for.
    pub fn fit_memory(&mut self, bytes: u64) -> Option<(u32, u64)> {
        let least = self.drawn.clamp(1, self.target);
        let asked = self.expected_memory(self.target);
        if asked <= bytes {
            return None;
        }
        // The most frames that fit (the expected bytes grow with them).
        let (mut lo, mut hi) = (least, self.target);
        while lo < hi {
            let mid = lo + (hi - lo).div_ceil(2);
            if self.expected_memory(mid) <= bytes {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        self.target = lo;
        Some((lo, asked))
    }

    /// Every pixel holds the frames asked for (or all its budget allows),
    /// no stand-in and no run short of its blend: further frames change
    /// nothing.
    pub fn complete(&self) -> bool {
        self.drawn > 0
            && self.pixels.iter().all(|p| {
                p.dt == 0.0
                    || (p.stand_ins == 0
                        && !p.short
                        && (p.frames() == self.target || !self.room(p, p.frames())))
            })
    }

    /// Stand-in samples kept, all pixels.
    pub fn stand_ins(&self) -> u64 {
        self.pixels.iter().map(|p| p.stand_ins as u64).sum()
    }

    /// Whether pixel `p` may begin run `k`.
    fn room(&self, p: &Pixel, k: u32) -> bool {
        room(self.target, self.budget, p, k)
    }

    /// One accumulation frame of a DVR view (`params.mode` DVR, one
    /// channel; the same camera and size on every frame): retake stand-ins,
    /// take one more run per pixel that has room, blend with
    /// `params.tf`. Returns the figures and the request collectors (hand
    /// them to `Session::finish_frame`).
    pub fn frame(
        &mut self,
        vm: &VirtualMemory,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
    ) -> (AccumStats, Vec<Requests>) {
        self.frame_rows(vm, scene, params, lod, 0..self.height)
    }

    /// Blend each pixel only in the frame that takes its last run (and
    /// in frames after it that replace stand-ins): for a render that
    /// shows only the complete image. The image is the same; the frames
    /// before show nothing new.
    pub fn blend_last_only(&mut self) {
        self.last_only = true;
    }

    /// The image rows this accumulation keeps.
    pub fn kept_rows(&self) -> std::ops::Range<u32> {
        self.row0..self.row0 + self.rows
    }

    /// [`frame`](Self::frame) for the image rows `rows` only (pixels are
    /// independent: a view can spread a frame over several calls and
    /// answer input between them). A frame counts as drawn when its part
    /// reaches the last row.
    pub fn frame_rows(
        &mut self,
        vm: &VirtualMemory,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
        rows: std::ops::Range<u32>,
    ) -> (AccumStats, Vec<Requests>) {
        assert!(
            matches!(params.mode, RenderMode::Dvr) && params.channels.is_empty(),
            "accumulation draws DVR of one channel"
        );
        assert_eq!(
            (params.width, params.height),
            (self.width, self.height),
            "accumulation and parameters of one size"
        );
        self.reference = params.reference_step.unwrap_or(scene.voxel(0));
        let on = params.tf.shading.is_some();
        let shaded = *self.shaded.get_or_insert(on);
        assert!(
            shaded || !on,
            "the samples of this accumulation keep no normals: start a new one to shade"
        );
        self.early = params.early_termination;
        // The first run always fits the store (the CPU could grow it, but
        // keeps the device's rule: its twin).
        let lod = lod_within(scene, params, lod, self.budget as u64)
            .unwrap_or(Lod::Fixed(scene.levels.len() - 1));
        let end = self.row0 + self.rows;
        let rows = rows.start.clamp(self.row0, end)..rows.end.clamp(self.row0, end);
        dispatch_dtype!(vm.dtype(), T => { self.frame_typed::<T>(vm, scene, params, lod, rows) })
    }

    fn frame_typed<T: Sample>(
        &mut self,
        vm: &VirtualMemory,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
        rows: std::ops::Range<u32>,
    ) -> (AccumStats, Vec<Requests>) {
        let frame = Frame::new(vm, scene, params, lod);
        let w = self.width as usize;
        let rg = ViewRays::new(
            &params.camera,
            params.views.as_ref(),
            self.width,
            self.height,
        );
        let tf = params.tf.evaluator();
        let shading = params.tf.shading;
        let normals = self.shaded == Some(true);
        let (orders, reference) = (&self.orders.clone(), self.reference);
        let (target, budget) = (self.target, self.budget);
        let room = move |p: &Pixel, k: u32| room(target, budget, p, k);
        let mut pixels = std::mem::take(&mut self.pixels);
        let mut image = std::mem::replace(&mut self.image, Image::new(1, 1));
        let span = (rows.start - self.row0) as usize * w..(rows.end - self.row0) as usize * w;
        let first = rows.start as usize;
        let (clip, early, last_only) =
            (params.clip.as_deref().copied(), self.early, self.last_only);
        let parts: Vec<(AccumStats, Requests)> = pixels[span.clone()]
            .par_chunks_mut(w * BAND)
            .zip(image.rgba[span].par_chunks_mut(w * BAND))
            .enumerate()
            .fold(
                || {
                    (
                        Walker::<T>::new(&frame, scene.channel),
                        vm.requests(),
                        AccumStats::default(),
                    )
                },
                |(mut wk, mut req, mut st), (band, (px, out))| {
                    for (n, (p, o)) in px.iter_mut().zip(out.iter_mut()).enumerate() {
                        let (i, j) = ((n % w) as u32, (first + band * BAND + n / w) as u32);
                        let ray = rg.pixel_ray(i, j);
                        let mut s = Sampler {
                            wk: &mut wk,
                            f: &frame,
                            ray: &ray,
                            req: &mut req,
                            st: &mut st,
                            normals,
                            clip,
                            early,
                            last_only,
                            target,
                            budget,
                        };
                        *o = s.pixel(p, (&tf, shading.as_ref()), orders, reference, &room, *o);
                    }
                    (wk, req, st)
                },
            )
            .map(|(mut wk, mut req, st)| {
                wk.flush(&mut req);
                (st, req)
            })
            .collect();
        drop(frame);
        let mut stats = AccumStats::default();
        let mut reqs = Vec::with_capacity(parts.len());
        for (s, r) in parts {
            stats.frame.add(&s.frame);
            stats.retaken += s.retaken;
            stats.extended += s.extended;
            reqs.push(r);
        }
        for p in &pixels {
            stats.stand_ins += p.stand_ins as u64;
            stats.kept += p.values.len() as u64;
            stats.full +=
                (p.dt > 0.0 && p.frames() < self.target && !self.room(p, p.frames())) as u64;
        }
        self.pixels = pixels;
        self.image = image;
        if rows.end == self.row0 + self.rows {
            self.drawn += 1;
        }
        (stats, reqs)
    }

    /// Blend the kept samples again under `tf`, without volume access.
    /// Returns the pixels whose kept runs end before their ray stops under
    /// `tf` (a more transparent function sees further than the runs were
    /// taken): they show the blend so far, and the next
    /// [`frame`](Self::frame) extends them. `None` (nothing done) when `tf`
    /// shades and the kept samples have no normals (the accumulation began
    /// unshaded): that takes a new accumulation.
    pub fn reblend(&mut self, tf: &TransferFunction) -> Option<usize> {
        if tf.shading.is_some() && self.shaded != Some(true) {
            return None;
        }
        let eval = tf.evaluator();
        let shading = tf.shading.as_ref();
        let (orders, reference, early) = (&self.orders, self.reference, self.early);
        self.pixels
            .par_iter_mut()
            .zip(self.image.rgba.par_iter_mut())
            .map(|(p, o)| {
                if p.dt == 0.0 {
                    *o = [0.0; 4];
                    return 0;
                }
                let n = p.runs.len();
                let e = exponent(p, reference);
                let (c, short) = match blend(p, &orders[n - 1], (&eval, shading), e, early) {
                    Blend::Done(c) => (c, false),
                    Blend::Short(_, c) => (c, true),
                };
                *o = c;
                p.short = short;
                short as usize
            })
            .sum::<usize>()
            .into()
    }
}

/// Samples of the longest run a ray can take at `level`'s step: a ray's
/// span in the volume is at most the box's diagonal.
pub fn longest_run(scene: &Scene, params: &RenderParams, level: usize) -> u64 {
    let e = scene.extent;
    let diagonal = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt();
    (diagonal / (scene.voxel(level) / params.samples_per_voxel)).ceil() as u64 + 2
}

/// The most bytes the first frame of an accumulation of `params`' view
/// (its image rows `rows`) holds, with every ray's first run sampled at
/// `level`'s step: each pixel's header, its first run's entry, and room
/// for its whole ray's samples (what the first frame reserves; rays end
/// earlier where they turn opaque). The frames asked for do not enter: the
/// room for them is reserved at the second. An automatic level of detail
/// asks for `level` or coarser.
pub fn first_frame_memory(
    scene: &Scene,
    params: &RenderParams,
    rows: std::ops::Range<u32>,
    level: usize,
) -> u64 {
    let per = sample_bytes(params.tf.shading.is_some());
    let dt = scene.voxel(level) / params.samples_per_voxel;
    let rg = ViewRays::new(
        &params.camera,
        params.views.as_ref(),
        params.width,
        params.height,
    );
    let head = std::mem::size_of::<Pixel>() as u64;
    // (A vector's first allocation for one 12-byte entry holds 4.)
    let runs = (4 * std::mem::size_of::<RunInfo>()) as u64;
    rows.into_par_iter()
        .map(|j| {
            (0..params.width)
                .map(|i| {
                    let ray = rg.pixel_ray(i, j);
                    let d = ray.dir;
                    let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
                    head + match intersect_box_inv(&ray, inv, [0.0; 3], scene.extent) {
                        Some((t0, t1)) if t1 > t0 => {
                            runs + (((t1 - t0) / dt).ceil() as u64 + 1) * per
                        }
                        _ => 0,
                    }
                })
                .sum::<u64>()
        })
        .sum()
}

/// The level of detail at which every ray's first run of samples fits
/// `budget` samples: `lod` itself where it does, else `lod` moved to the
/// finest level `F` whose longest run fits (a fixed level no finer than
/// `F`; an automatic one with its bias raised so that the nearest point of
/// the volume asks for `F` or coarser, or fixed at `F` when the eye is
/// inside the volume). `None` when not even the coarsest level's run fits.
pub fn lod_within(scene: &Scene, params: &RenderParams, lod: Lod, budget: u64) -> Option<Lod> {
    let n = scene.levels.len();
    let finest = (0..n).find(|&l| longest_run(scene, params, l) <= budget)?;
    Some(lod_at_least(scene, params, lod, finest))
}

/// `lod` moved so that no ray asks for a level finer than `finest` (a
/// fixed level no finer; an automatic one with its bias raised so that the
/// nearest point of the volume asks for `finest` or coarser, or fixed at
/// `finest` when the eye is inside the volume).
pub fn lod_at_least(scene: &Scene, params: &RenderParams, lod: Lod, finest: usize) -> Lod {
    if finest == 0 {
        return lod;
    }
    match lod {
        Lod::Fixed(l) => Lod::Fixed(l.max(finest)),
        Lod::Auto { bias } => {
            // The footprint grows with the distance (perspective) or is
            // the same everywhere (orthographic): the nearest point of the
            // box asks for the finest level.
            let eye = params.camera.eye;
            let near = (0..3)
                .map(|a| {
                    let d = (0.0 - eye[a]).max(eye[a] - scene.extent[a]).max(0.0);
                    d * d
                })
                .sum::<f64>()
                .sqrt();
            let fp = params.camera.pixel_footprint(near, params.lod_height());
            // (The rule's level is never finer than level 0.)
            let x = (fp / scene.voxel(0)).log2().max(0.0);
            // A hundredth of a level above the threshold: the device
            // computes in f32.
            let want = finest as f64 + 0.01;
            match x.is_finite() {
                true if x + bias >= want => lod,
                true => Lod::Auto { bias: want - x },
                false => Lod::Fixed(finest),
            }
        }
    }
}

/// Whether pixel `p` may begin run `k` of `target` with `budget` samples.
fn room(target: u32, budget: usize, p: &Pixel, k: u32) -> bool {
    k == 0 || (k < target && (k as usize + 1) * p.max_run() <= budget)
}

/// The first step `j` of a run with offset `o` whose position
/// `t0 + (j + o)·Δ` lies at or past `p.lo` (0 for the whole ray).
fn first_step(p: &Pixel, o: f64) -> u32 {
    if p.lo <= p.t0 {
        return 0;
    }
    let at = |j: u64| p.t0 + (j as f64 + o) * p.dt;
    let mut j = ((p.lo - p.t0) / p.dt - o).floor().max(0.0) as u64;
    // The estimate is within a step; settle it with the positions taken.
    while j > 0 && at(j - 1) >= p.lo {
        j -= 1;
    }
    while at(j) < p.lo {
        j += 1;
    }
    j as u32
}

/// The opacity-correction exponent of pixel `p`'s blend: `(Δ/n)/Δ_ref`.
fn exponent(p: &Pixel, reference: f64) -> f32 {
    ((p.dt / p.runs.len() as f64) / reference) as f32
}

/// Blend pixel `p`'s kept samples in depth order (`order`: its runs by
/// offset), stopping at an opacity of 0.99 when `early`.
fn blend(
    p: &Pixel,
    order: &[u8],
    (tf, shading): (&TfEval, Option<&Shading>),
    exponent: f32,
    early: bool,
) -> Blend {
    let shading = shading.filter(|_| !p.cos.is_empty());
    let mut starts = [0usize; MAX_FRAMES as usize];
    let mut s = 0;
    for (k, r) in p.runs.iter().enumerate() {
        starts[k] = s;
        s += r.len as usize;
    }
    let mut acc = [0.0f32; 4];
    // Step by step along the ray (runs of a region start at its entry,
    // within one step of each other).
    let mut j = p.runs.iter().map(|r| r.first as usize).min().unwrap_or(0);
    loop {
        let mut any = false;
        for &k in order {
            let k = k as usize;
            let r = p.runs[k];
            let Some(jr) = j.checked_sub(r.first as usize) else {
                any = true;
                continue;
            };
            if jr >= r.len as usize {
                if !r.ended {
                    return Blend::Short(k, acc);
                }
                continue;
            }
            any = true;
            let i = starts[k] + jr;
            if p.flags[i] & UNSERVED != 0 {
                continue;
            }
            if let Some(mut c) = tf.lookup_visible(p.values[i]) {
                if let Some(sh) = shading {
                    let x = p.cos[i];
                    if x >= 0.0 {
                        c = lit(sh, c, x as f64);
                    }
                }
                if composite_visible(&mut acc, c, exponent) && early {
                    return Blend::Done(acc);
                }
            }
        }
        if !any {
            return Blend::Done(acc);
        }
        j += 1;
    }
}

/// One thread's access to the volume for one pixel.
struct Sampler<'w, 'f, 'a, T> {
    wk: &'w mut Walker<'f, 'a, T>,
    f: &'f Frame<'a>,
    ray: &'w Ray,
    req: &'w mut Requests,
    st: &'w mut AccumStats,
    /// Keep each sample's normal cosine.
    normals: bool,
    /// The region whose samples are kept (sort-last), or the whole ray.
    clip: Option<[[f64; 3]; 2]>,
    /// Runs stop where they alone would stop a ray.
    early: bool,
    /// [`Accumulation::blend_last_only`].
    last_only: bool,
    /// Frames asked for and samples a pixel may keep (the room each
    /// pixel's buffers reserve).
    target: u32,
    budget: usize,
}

impl<T: Sample> Sampler<'_, '_, '_, T> {
    /// The value at ray parameter `t`, its flags and (keeping normals)
    /// the cosine of its normal with the ray (negative for a zero
    /// gradient). A sample whose value or any gradient neighbour was not
    /// served at its level is a stand-in.
    fn sample(&mut self, t: f64) -> (f32, u8, f32) {
        let f = self.f;
        let level = f.level_at(t);
        let w = self.ray.at(t);
        let (vb, frac) = f.coords(level, w);
        self.wk.enter(level, vb, self.req, true);
        let st = &mut self.st.frame;
        let (samples, exact) = (st.samples, st.exact);
        let Some(v) = self.wk.value(level, w, vb, frac, self.req, st) else {
            return (0.0, STAND_IN | UNSERVED, -1.0);
        };
        let mut cos = -1.0;
        if self.normals {
            match self.wk.gradient(level, w, self.req, st) {
                Some(g) => cos = cosine(g, self.ray.dir).map_or(-1.0, |x| x as f32),
                None => return (v, STAND_IN, -1.0),
            }
        }
        let fl = if st.exact - exact == st.samples - samples {
            0
        } else {
            STAND_IN
        };
        (v, fl, cos)
    }

    /// Take samples `j = from, from + 1, …` of run `k` of `p` (offset
    /// `o`), at most `limit` of them, or (`own` set) until the run alone
    /// would stop a ray blended at the frame's step with `tf`; appended to
    /// the run. Marks the run ended when it reaches the ray's end.
    fn take(&mut self, p: &mut Pixel, k: usize, limit: usize, own: Option<(&TfEval, f32)>) {
        let o = offset(k as u32);
        let start = p.start(k) + p.runs[k].len as usize;
        // The newest run ends the store: its samples are appended in place.
        let last = k + 1 == p.runs.len();
        let (mut vals, mut flags, mut coss) = match last {
            true => (
                std::mem::take(&mut p.values),
                std::mem::take(&mut p.flags),
                std::mem::take(&mut p.cos),
            ),
            false => (Vec::new(), Vec::new(), Vec::new()),
        };
        let base = if last { vals.len() } else { 0 };
        let mut j = (p.runs[k].first + p.runs[k].len) as usize;
        let mut acc = [0.0f32; 4];
        let mut ended = false;
        while vals.len() - base < limit {
            let t = p.t0 + (j as f64 + o) * p.dt;
            if t >= p.hi {
                ended = true;
                break;
            }
            let (v, fl, cos) = self.sample(t);
            if vals.len() == vals.capacity() {
                // Beyond the room reserved: an eighth more, not double.
                let more = EXTEND.max(vals.len() / 8);
                vals.reserve_exact(more);
                flags.reserve_exact(more);
                if self.normals {
                    coss.reserve_exact(more);
                }
            }
            vals.push(v);
            flags.push(fl);
            if self.normals {
                coss.push(cos);
            }
            j += 1;
            if fl & UNSERVED == 0 {
                if let Some((tf, e)) = own {
                    if let Some(c) = tf.lookup_visible(v) {
                        if composite_visible(&mut acc, c, e) {
                            break;
                        }
                    }
                }
            }
        }
        p.stand_ins += flags[base..].iter().filter(|f| **f & STAND_IN != 0).count() as u32;
        p.runs[k].len += (vals.len() - base) as u32;
        p.runs[k].ended = ended;
        if last {
            (p.values, p.flags, p.cos) = (vals, flags, coss);
        } else {
            // (Room for exactly these: an extension, not a doubling.)
            p.values.reserve_exact(vals.len());
            p.flags.reserve_exact(flags.len());
            p.values.splice(start..start, vals);
            p.flags.splice(start..start, flags);
            if self.normals {
                p.cos.reserve_exact(coss.len());
                p.cos.splice(start..start, coss);
            }
        }
    }

    /// Retake `p`'s stand-in samples; those now served at their level
    /// lose the mark.
    fn retake(&mut self, p: &mut Pixel) {
        let mut i = 0;
        for k in 0..p.runs.len() {
            let o = offset(k as u32);
            let first = p.runs[k].first as usize;
            for j in first..first + p.runs[k].len as usize {
                if p.flags[i] & STAND_IN != 0 {
                    let t = p.t0 + (j as f64 + o) * p.dt;
                    let (v, fl, cos) = self.sample(t);
                    if self.normals && fl & UNSERVED == 0 {
                        p.cos[i] = cos;
                    }
                    if fl == 0 {
                        p.values[i] = v;
                        p.flags[i] = 0;
                        p.stand_ins -= 1;
                        self.st.retaken += 1;
                    } else if fl & UNSERVED == 0 {
                        // A finer stand-in than before may have arrived.
                        p.values[i] = v;
                        p.flags[i] = fl;
                    }
                }
                i += 1;
            }
        }
    }

    /// One frame of pixel `p`: its colour (`shown`: its colour after the
    /// frame before).
    fn pixel(
        &mut self,
        p: &mut Pixel,
        look: (&TfEval, Option<&Shading>),
        orders: &[Vec<u8>],
        reference: f64,
        room: &impl Fn(&Pixel, u32) -> bool,
        shown: [f32; 4],
    ) -> [f32; 4] {
        if p.runs.is_empty() {
            let d = self.ray.dir;
            let inv = [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]];
            let Some((t0, t1)) = intersect_box_inv(self.ray, inv, [0.0; 3], self.f.scene.extent)
            else {
                return [0.0; 4];
            };
            // A region (sort-last): the samples of the whole ray's grid in
            // `[c0, c1)`, split between neighbouring regions exactly (the
            // same face gives the same `t` on both sides).
            let (lo, hi) = match self.clip {
                None => (t0, t1),
                Some([lo, hi]) => match intersect_box_inv(self.ray, inv, lo, hi) {
                    Some((c0, c1)) if c0.max(t0) < c1.min(t1) => (c0.max(t0), c1.min(t1)),
                    _ => return [0.0; 4],
                },
            };
            p.t0 = t0;
            p.t1 = t1;
            p.lo = lo;
            p.hi = hi;
            p.dt = self.f.step[self.f.level_at(t0)].0;
        }
        if p.dt == 0.0 {
            return [0.0; 4];
        }
        let retaken = p.stand_ins > 0;
        if retaken {
            self.retake(p);
        }
        let k = p.frames();
        if !retaken && !p.short && !room(p, k) {
            // Nothing new to blend (no run to add, no stand-in replaced,
            // the last blend reached its end): `shown`, the last blend of
            // the same samples, stays. (Re-blending every kept sample of
            // such pixels each frame took most of a frame once the
            // budget was full.)
            return shown;
        }
        if room(p, k) {
            // The buffers' room, reserved instead of doubling as they
            // fill: the first run's bound while it is taken (then only
            // what it took), then from its length the frames asked for.
            // What they hold allocated stays close to what they keep
            // (see `expected_memory`, `first_frame_memory`).
            let more = match k {
                0 => p.max_run(),
                // (Never past what the pixel may keep.)
                1 => ((p.values.len() + 2) * (self.target as usize).saturating_sub(1))
                    .min(self.budget.saturating_sub(p.values.len())),
                _ => 0,
            };
            if more > 0 {
                p.values.reserve_exact(more);
                p.flags.reserve_exact(more);
                if self.normals {
                    p.cos.reserve_exact(more);
                }
            }
            if k == 1 {
                p.runs.reserve_exact(self.target as usize - 1);
            }
            p.runs.push(RunInfo {
                first: first_step(p, offset(k)),
                len: 0,
                ended: false,
            });
            let e = (p.dt / reference) as f32;
            let own = self.early.then_some((look.0, e));
            self.take(p, k as usize, usize::MAX, own);
            if k == 0 {
                p.values.shrink_to_fit();
                p.flags.shrink_to_fit();
                p.cos.shrink_to_fit();
            }
            if self.last_only && room(p, k + 1) {
                // More runs to come: the blend waits for them (marked
                // short, so that it is not taken for done).
                p.short = true;
                return shown;
            }
        }
        let order = &orders[p.runs.len() - 1];
        let e = exponent(p, reference);
        loop {
            match blend(p, order, look, e, self.early) {
                Blend::Done(c) => {
                    p.short = false;
                    return c;
                }
                Blend::Short(k, _) => {
                    let before = p.runs[k].len;
                    self.take(p, k, EXTEND, None);
                    self.st.extended += (p.runs[k].len - before) as u64;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first 2^m offsets are the multiples of 2^-m, frame 0's is the
    /// plain grid's ½, and each next frame halves the largest gap.
    #[test]
    fn offsets_fill_the_step_evenly() {
        assert_eq!(
            (0..4).map(offset).collect::<Vec<_>>(),
            [0.5, 0.0, 0.75, 0.25]
        );
        for m in 0..8u32 {
            let n = 1u32 << m;
            let mut o: Vec<f64> = (0..n).map(offset).collect();
            o.sort_by(f64::total_cmp);
            let want: Vec<f64> = (0..n).map(|i| i as f64 / n as f64).collect();
            let mut o2 = o.clone();
            if n == 1 {
                o2 = vec![0.0];
                assert_eq!(o, [0.5]);
            }
            assert_eq!(o2, want, "{n} frames");
        }
    }

    /// Runs are blended in depth order: with `j` outer and runs by offset
    /// inner. Two runs of a two-sample ray: frame 0 at ½, 1½; frame 1 at
    /// 0, 1. Values 1, 2 (frame 0) and 3, 4 (frame 1) in depth order are
    /// 3, 1, 4, 2: the opacity blended is that order's, which differs from
    /// the frame-major one's.
    #[test]
    fn blend_follows_depth() {
        let p = Pixel {
            dt: 1.0,
            t0: 0.0,
            t1: 2.0,
            lo: 0.0,
            hi: 2.0,
            values: vec![1.0, 2.0, 3.0, 4.0],
            flags: vec![0; 4],
            cos: vec![],
            runs: vec![
                RunInfo {
                    first: 0,
                    len: 2,
                    ended: true,
                },
                RunInfo {
                    first: 0,
                    len: 2,
                    ended: true,
                },
            ],
            stand_ins: 0,
            short: false,
        };
        let a = Accumulation::new(1, 1, 2, 100);
        assert_eq!(a.orders[1], [1, 0]);
        let lin = TransferFunction::preset("linear", [0.0, 16.0]).unwrap();
        let eval_blend =
            |p: &Pixel| match blend(p, &a.orders[1], (&lin.evaluator(), None), 1.0, true) {
                Blend::Done(c) => c,
                Blend::Short(..) => panic!("short"),
            };
        // Under a linear ramp the first sample in depth order (value 3)
        // has the largest weight: A after it is its own opacity.
        let c = eval_blend(&p);
        let op = |v: f32| lin.lookup(v)[3];
        let mut t = 1.0f32;
        let mut a_want = 0.0;
        for v in [3.0, 1.0, 4.0, 2.0] {
            a_want += t * op(v);
            t *= 1.0 - op(v);
        }
        assert!((c[3] - a_want).abs() < 1e-6, "{c:?} vs {a_want}");
        // An open run that ran out stops the blend there.
        let mut q = p.clone();
        q.runs[0].ended = false;
        q.runs[0].len = 1;
        q.values.remove(1);
        q.flags.remove(1);
        assert!(matches!(
            blend(&q, &a.orders[1], (&lin.evaluator(), None), 1.0, true),
            Blend::Short(0, _)
        ));
    }
}
