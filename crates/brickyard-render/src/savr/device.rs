//! Sample accumulation on the device (`savr.wgsl`), twin of
//! [`Accumulation`](super::Accumulation): the same sample positions, room
//! rule, stand-in retakes, run extension and blend, drawn through the
//! device's copy of the virtual memory by [`GpuRenderer`].
//!
//! # Memory
//!
//! The device cannot grow a pixel's store as the CPU does, so each pixel
//! owns a fixed region, the sample buffer of the paper: `B` samples (4
//! bytes of value and 2 bits of flags each, 4 more bytes of normal cosine
//! when shading), `N` words of run lengths and 8 of header, after the
//! image itself. Run `k` of a pixel whose ray has `S` steps occupies
//! samples `k·S …`, so a pixel begins run `k` only when `(k + 1)·S ≤ B` (the
//! CPU's rule): a pixel whose buffer is full stays at the rate it reached,
//! blended correctly for it.
//!
//! The image's rows are split into bands, each with a buffer of its own
//! (its pixels' image, then their store) no larger than one storage
//! binding of the device, drawn by one dispatch each within the same
//! frame: the store of the whole image is not bound by that limit (on
//! lavapipe 128 MiB, which kept a 480 × 360 view at 85 samples a pixel and
//! made `render --progressive` draw it coarser than a plain frame).
//! [`DeviceAccumulation::max_budget`] gives the largest `B` one row of the
//! image can keep. The first frame lowers `B` to what the view's rays can
//! use (`N` runs of the longest ray at the finest level asked for), so a
//! generous budget costs no memory.

use super::MAX_FRAMES;
use crate::cpu::{FrameStats, Lod, Scene};
use crate::gpu::{AccBand, AccPass, GpuFrame, GpuRenderer};
use crate::image::Image;
use crate::params::{RenderMode, RenderParams};
use brickyard_cache::vm::VirtualMemory;
use brickyard_gpu::context::{Gpu, GpuError};
use brickyard_gpu::update::DeviceCache;
use brickyard_gpu::vm::DeviceVm;

/// Header words a pixel.
const HEADER: u64 = 8;

/// What a device accumulation frame did (the device's counters).
#[derive(Debug, Clone, Default)]
pub struct DeviceAccumStats {
    /// Lookups made (new samples, extensions and retakes, gradient
    /// neighbours not counted).
    pub frame: FrameStats,
    /// Stand-in samples retaken at the level they asked for.
    pub retaken: u64,
    /// Samples added to open runs for the blend.
    pub extended: u64,
    /// Stand-ins kept after the frame.
    pub stand_ins: u64,
    /// Pixels not complete after the frame.
    pub incomplete: u64,
}

/// The accumulation of one view on the device. A camera move or a change
/// of image size, level of detail, sampling rate or channel starts a new
/// one (or [`restart`](Self::restart)s this one).
pub struct DeviceAccumulation {
    width: u32,
    height: u32,
    target: u32,
    budget: u32,
    /// Samples a pixel keeps as asked for (before the first frame lowers
    /// `budget` to what the view can use).
    asked: u32,
    /// Fixed by the first frame: whether its transfer function shades.
    normals: Option<bool>,
    /// Bands of image rows (first row, rows) and the buffer of each (the
    /// band's image, then its store), made by the first frame.
    bands: Vec<(u32, u32, wgpu::Buffer)>,
    drawn: u32,
    last: DeviceAccumStats,
    image: Image,
    /// Blend a pixel only in the frame that takes its last run (see
    /// [`blend_last_only`](Self::blend_last_only)).
    last_only: bool,
}

impl DeviceAccumulation {
    /// Words of store a pixel needs (image included).
    fn words(target: u32, budget: u32, normals: bool) -> u64 {
        let b = budget as u64;
        4 + HEADER + target as u64 + b + b.div_ceil(16) + if normals { b } else { 0 }
    }

    /// The largest per-pixel budget the device holds for images `width`
    /// pixels wide and `target` frames (with normals: shading): what one
    /// storage binding holds for one row of the image (the store is split
    /// into bands of rows, so the height does not lower it). The memory the
    /// whole store takes is the caller's to bound
    /// ([`budget_within`](Self::budget_within)).
    pub fn max_budget(gpu: &Gpu, width: u32, target: u32, normals: bool) -> u32 {
        Self::budget_within(gpu.max_storage_binding(), width, 1, target, normals)
    }

    /// The largest per-pixel budget whose store takes at most `bytes`.
    pub fn budget_within(bytes: u64, width: u32, height: u32, target: u32, normals: bool) -> u32 {
        let limit = bytes;
        let pixels = (width as u64 * height as u64).max(1);
        let words = limit / 4 / pixels;
        let fixed = 4 + HEADER + target as u64;
        let per = if normals {
            2.0 + 1.0 / 16.0
        } else {
            1.0 + 1.0 / 16.0
        };
        let b = (words.saturating_sub(fixed + 1) as f64 / per) as u64;
        b.min(u32::MAX as u64 / 2) as u32
    }

    /// An empty accumulation of `target` frames (at most
    /// [`MAX_FRAMES`]) for images of `width × height`, keeping at most
    /// `budget` samples per pixel (lowered to [`max_budget`] with normals,
    /// so a shading function fits too).
    ///
    /// [`max_budget`]: Self::max_budget
    pub fn new(gpu: &Gpu, width: u32, height: u32, target: u32, budget: usize) -> Self {
        let target = target.clamp(1, MAX_FRAMES);
        let max = Self::max_budget(gpu, width, target, true);
        let budget = (budget.min(u32::MAX as usize) as u32).min(max).max(1);
        DeviceAccumulation {
            width,
            height,
            target,
            budget,
            asked: budget,
            normals: None,
            bands: vec![],
            drawn: 0,
            last: DeviceAccumStats::default(),
            image: Image::new(width, height),
            last_only: false,
        }
    }

    /// Blend each pixel only in the frame that takes its last run (and in
    /// frames after it that replace stand-ins or extend its runs), as the
    /// CPU twin's [`Accumulation::blend_last_only`]: for a render that
    /// shows only the complete image. The complete image is the same; the
    /// frames before show nothing new for pixels with runs still to come.
    ///
    /// [`Accumulation::blend_last_only`]: crate::savr::Accumulation::blend_last_only
    pub fn blend_last_only(&mut self) {
        self.last_only = true;
    }

    /// Samples a pixel keeps.
    pub fn budget(&self) -> usize {
        self.budget as usize
    }

    /// Frames asked for.
    pub fn target(&self) -> u32 {
        self.target
    }

    /// Frames drawn since the start.
    pub fn drawn(&self) -> u32 {
        self.drawn
    }

    /// Bytes of the store on the device (image included).
    pub fn memory(&self) -> u64 {
        self.bands.iter().map(|(_, _, b)| b.size()).sum()
    }

    /// Bands of image rows the store is split into (first row, rows);
    /// empty before the first frame.
    pub fn bands(&self) -> Vec<(u32, u32)> {
        self.bands.iter().map(|&(a, n, _)| (a, n)).collect()
    }

    /// The image of the last pass (when the renderer reads images back).
    pub fn image(&self) -> &Image {
        &self.image
    }

    /// The figures of the last pass.
    pub fn last(&self) -> &DeviceAccumStats {
        &self.last
    }

    /// Every pixel holds the frames asked for (or all its budget allows),
    /// no stand-in and no run short of its blend.
    pub fn complete(&self) -> bool {
        self.drawn > 0 && self.last.incomplete == 0
    }

    /// Forget every kept sample (a new view): the store is let go, and
    /// the next frame makes one for its view (the budget as asked for).
    pub fn restart(&mut self) {
        self.bands.clear();
        self.budget = self.asked;
        self.normals = None;
        self.drawn = 0;
        self.last = DeviceAccumStats::default();
    }

    fn pass<'b>(&'b self, entry: &'static str, reference: f64) -> AccPass<'b> {
        assert!(!self.bands.is_empty(), "made by the first frame");
        let (n, b) = (self.target as u64, self.budget as u64);
        let normals = self.normals == Some(true);
        let bands = self
            .bands
            .iter()
            .map(|(first, rows, store)| {
                let p = self.width as u64 * *rows as u64;
                let runs = HEADER * p;
                let vals = runs + n * p;
                let flags = vals + b * p;
                let cos = flags + b.div_ceil(16) * p;
                AccBand {
                    first: *first,
                    rows: *rows,
                    store,
                    acc_off: [runs as u32, vals as u32, flags as u32, cos as u32],
                }
            })
            .collect();
        AccPass {
            entry,
            bands,
            acc: [
                self.target,
                self.budget,
                self.last_only as u32,
                normals as u32,
            ],
            reference: reference as f32,
        }
    }

    /// Make the store for the first frame: the budget lowered to what the
    /// view's rays can use at `lod` (`target` runs of the longest ray at
    /// its finest level: no pixel keeps more), then bands of rows each
    /// within one storage binding.
    fn make_store(
        &mut self,
        gpu: &Gpu,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
        normals: bool,
    ) -> Result<(), GpuError> {
        let finest = match lod {
            Lod::Fixed(l) => l.min(scene.levels.len() - 1),
            Lod::Auto { .. } => 0,
        };
        let usable = self.target as u64 * super::longest_run(scene, params, finest);
        self.budget = self.budget.min(usable.min(u32::MAX as u64) as u32).max(1);
        let row = self.width as u64 * Self::words(self.target, self.budget, normals) * 4;
        let limit = gpu.max_storage_binding();
        if row > limit {
            return Err(GpuError::Limit {
                what: format!(
                    "bytes of one image row of the sample store ({} samples a pixel; a narrower image, or fewer frames)",
                    self.budget
                ),
                got: row,
                limit,
            });
        }
        let per = ((limit / row) as u32).clamp(1, self.height.max(1));
        let mut first = 0;
        while first < self.height {
            let rows = per.min(self.height - first);
            let buf = gpu.storage_buffer_zeroed("sample store", rows as u64 * row);
            self.bands.push((first, rows, buf));
            first += rows;
        }
        Ok(())
    }

    fn take_counts(&mut self, f: &GpuFrame) {
        let c = f.counters;
        self.last = DeviceAccumStats {
            frame: FrameStats {
                samples: c[0] as u64,
                exact: c[1] as u64,
                unserved: c[2] as u64,
                ..Default::default()
            },
            retaken: c[3] as u64,
            extended: c[5] as u64,
            incomplete: c[6] as u64,
            stand_ins: c[7] as u64,
        };
        if !f.image.rgba.is_empty() {
            self.image = f.image.clone();
        }
    }

    /// One accumulation frame of a DVR view (one channel; the same camera
    /// and size on every frame) from what `dvm` holds: retake stand-ins,
    /// take one more run per pixel that has room, blend. The frame's
    /// requests and used slots are in the result, as for a plain frame;
    /// with `cache`, the device decides updates (see
    /// [`GpuRenderer::render_with`]).
    #[allow(clippy::too_many_arguments)]
    pub fn frame(
        &mut self,
        gpu: &Gpu,
        renderer: &mut GpuRenderer,
        dvm: &DeviceVm,
        vm: &VirtualMemory,
        cache: Option<&DeviceCache>,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
    ) -> Result<GpuFrame, GpuError> {
        assert!(
            matches!(params.mode, RenderMode::Dvr) && params.channels.is_empty(),
            "accumulation draws DVR of one channel"
        );
        assert_eq!(
            (params.width, params.height),
            (self.width, self.height),
            "accumulation and parameters of one size"
        );
        let on = params.tf.shading.is_some();
        let normals = *self.normals.get_or_insert(on);
        assert!(
            normals || !on,
            "the samples of this accumulation keep no normals: restart it to shade"
        );
        if self.bands.is_empty() {
            self.make_store(gpu, scene, params, lod, normals)?;
        }
        // Every pixel's first run fits its region of the store: coarser
        // levels where the view's rays are too long for it.
        let coarsest = scene.levels.len() - 1;
        let lod = super::lod_within(scene, params, lod, self.budget as u64).ok_or_else(|| {
            GpuError::Limit {
                what: format!(
                    "samples of a ray at the coarsest level against the {} a pixel's store keeps (a smaller image, or fewer frames)",
                    self.budget
                ),
                got: super::longest_run(scene, params, coarsest),
                limit: self.budget as u64,
            }
        })?;
        let reference = params.reference_step.unwrap_or(scene.voxel(0));
        let pass = self.pass("accumulate", reference);
        let f = renderer.draw(gpu, dvm, vm, cache, scene, params, lod, Some(pass))?;
        self.drawn += 1;
        self.take_counts(&f);
        Ok(f)
    }

    /// Blend the kept samples again under `params.tf`, without volume
    /// access. Returns the pixels whose kept runs end before their ray
    /// stops (the next [`frame`](Self::frame) extends them); `None`
    /// (nothing done) when the function shades and the samples keep no
    /// normals, or before the first frame.
    #[allow(clippy::too_many_arguments)]
    pub fn reblend(
        &mut self,
        gpu: &Gpu,
        renderer: &mut GpuRenderer,
        dvm: &DeviceVm,
        vm: &VirtualMemory,
        scene: &Scene,
        params: &RenderParams,
    ) -> Result<Option<u64>, GpuError> {
        if self.drawn == 0 || (params.tf.shading.is_some() && self.normals != Some(true)) {
            return Ok(None);
        }
        let reference = params.reference_step.unwrap_or(scene.voxel(0));
        let pass = self.pass("reblend", reference);
        let f = renderer.draw(gpu, dvm, vm, None, scene, params, Lod::Fixed(0), Some(pass))?;
        self.take_counts(&f);
        Ok(Some(self.last.incomplete))
    }
}
