//! The device frame driver: ray-guided DVR, MIP and slices on the device
//! (`gpu.wgsl` and the WGSL twins beside the CPU modules), through the device's
//! copy of the virtual memory ([`brickyard_gpu::vm::DeviceVm`]): the twin
//! of [`crate::cpu`]. One invocation per pixel; each frame stamps the pool
//! slots and page-table blocks it used and reports the capped request list
//! and its sample counts. With the update step on the device
//! ([`update_on_device`]) nothing else comes back; with the host deciding,
//! the newly used slots do too (so that the host's LRU keeps them).
//!
//! Modes: DVR of one channel; MIP and slices of one channel or of several
//! added up. Empty space: DVR rays cross
//! bricks in one jump where the transfer function maps the brick to zero
//! opacity, known from the store's value ranges or from an EMPTY/CONSTANT
//! page entry; inside resident bricks, DVR rays cross cells whose value
//! range the transfer function hides and MIP rays cells whose maximum
//! cannot raise theirs.

use crate::cpu::{channel_frames, channel_parts, scene_octree, FrameStats, Lod, Scene};
use crate::image::Image;
use crate::octree::device::DeviceOctree;
use crate::octree::dvr::{OctFrame, TableKey};
use crate::octree::Octree;
use crate::params::{ChannelStyle, RenderMode, RenderParams, Traversal, MAX_DVR_CHANNELS};
use crate::walk::Frame;
use brickyard_cache::bookkeeping::BrickIds;
use brickyard_cache::brick::BrickKey;
use brickyard_cache::ranges::BrickRanges;
use brickyard_cache::vm::{Requests, VirtualMemory};
use brickyard_core::camera::{length, sub, Projection};
use brickyard_core::TransferFunction;
use brickyard_gpu::context::{Gpu, GpuError};
use brickyard_gpu::kernel::{Binding, Kernel};
use brickyard_gpu::requests::{RequestTableGpu, REQUEST_INSERT_WGSL};
use brickyard_gpu::update::DeviceCache;
use brickyard_gpu::vm::{with_vm_common, DeviceVm, MAX_LEVELS};

#[cfg(feature = "loader")]
mod update;
#[cfg(feature = "loader")]
pub use update::{update_on_device, DeviceUpdate};

/// The render shader: the frame driver (`gpu.wgsl`: uniform, bindings,
/// the entry point) and the twins of the CPU modules beside their Rust
/// files, joined at build time (WGSL declarations may come in any order).
const RENDER_WGSL: &str = concat!(
    include_str!("gpu.wgsl"),
    "\n",
    include_str!("optics.wgsl"),
    "\n",
    include_str!("walk.wgsl"),
    "\n",
    include_str!("slice.wgsl"),
    "\n",
    include_str!("superslice.wgsl"),
    "\n",
    include_str!("mip.wgsl"),
    "\n",
    include_str!("dvr.wgsl"),
    "\n",
    include_str!("shading.wgsl"),
    "\n",
    include_str!("savr.wgsl"),
    "\n",
    include_str!("multi.wgsl"),
    "\n",
    include_str!("octree/dvr.wgsl"),
    "\n",
    include_str!("labels.wgsl"),
);

/// The render uniform (see `gpu.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Uniform {
    width: u32,
    height: u32,
    mode: u32,
    levels: u32,
    eye: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    forward: [f32; 4],
    extent: [f32; 4],
    half_h: f32,
    aspect: f32,
    perspective: u32,
    lod_fixed: u32,
    lod_bias: f32,
    fp_slope: f32,
    fp_const: f32,
    voxel0: f32,
    window0: f32,
    inv_width: f32,
    n_opacity: u32,
    n_color: u32,
    frame: u32,
    buckets: u32,
    channel: u32,
    used_cap: u32,
    skip: u32,
    clear_off: u32,
    /// DVR: cross cells of resident bricks that the transfer function
    /// hides.
    skip_cells: u32,
    /// DVR: gradient shading (1) with `shading`'s parameters.
    shade: u32,
    /// Cells per brick and axis, and voxels per cell edge (`[z, y, x, _]`).
    cell_count: [u32; 4],
    cell_edge: [u32; 4],
    /// Channels added up (0: one through the transfer function), and where
    /// their styles start in the aux buffer.
    n_channels: u32,
    styles_off: u32,
    /// Views side by side (1: one) and the width of each.
    n_views: u32,
    view_width: u32,
    plane_origin: [f32; 4],
    plane_normal: [f32; 4],
    /// Ambient, diffuse, specular, shininess.
    shading: [f32; 4],
    /// Sample accumulation (`savr.wgsl`): frames, samples a pixel keeps, 0,
    /// normals kept; store offsets; the reference step.
    acc: [u32; 4],
    acc_off: [u32; 4],
    acc_ref: [f32; 4],
    /// Views: eye separation, distance to the target plane, super-slice
    /// parallax and slice spacing.
    views: [f32; 4],
    /// The first view of the image (a view drawn alone), 0, 0, 0.
    view_sel: [u32; 4],
    /// DVR through the residency octree: where its node table, masks and
    /// deepest depths start in the aux buffer; the volume's channels (the
    /// masks' stride) when traversed, 0 when not.
    oct: [u32; 4],
    scale: [[f32; 4]; MAX_LEVELS],
    qmax: [[f32; 4]; MAX_LEVELS],
    step: [[f32; 4]; MAX_LEVELS],
    bricks: [[u32; 4]; MAX_LEVELS],
    /// A sort-last region ([`RenderParams::clip`]): its world box; on (1),
    /// no early termination (1), MIP raw maxima (1), a slice of a label
    /// image (1, [`RenderParams::labels`]).
    clip_lo: [f32; 4],
    clip_hi: [f32; 4],
    region: [u32; 4],
    /// Only pixel rows `[y, z)` drawn (`x` = 1; [`GpuRenderer::rows`]).
    rows: [u32; 4],
    /// A label image's selection ([`RenderParams::label_select`]): every
    /// label (0), only the labels listed (1) or all but them (2); where
    /// the list starts in the aux buffer (increasing, `i32` bits); its
    /// length; 0.
    label_sel: [u32; 4],
    /// Sample accumulation: the band of image rows a dispatch draws (its
    /// store is the image binding): first row, rows, 0, 0.
    acc_band: [u32; 4],
}

const EXACT_BIT: u32 = 0x8000_0000;

/// One frame on the device.
pub struct GpuFrame {
    /// The frame (0 × 0 when [`GpuRenderer::read_image`] is off).
    pub image: Image,
    /// Samples, exact samples, unserved samples and bricks crossed in one
    /// jump (the other counts of [`FrameStats`] stay 0).
    pub stats: FrameStats,
    /// The device's request list as a collector, for
    /// `Session::finish_frame`: up to twice the cap, so that the cap can
    /// go to bricks not here yet once those that arrived are left out.
    pub requests: Requests,
    /// The same list, most wanted first (for `Session::exchange`).
    pub list: Vec<BrickKey>,
    /// Misses dropped because the device's request table was full.
    pub dropped: u64,
    /// Pool slots used this frame.
    pub used_slots: usize,
    /// Device→host bytes of cache management this frame (request list,
    /// counters, used slots; the image read-back is not counted).
    pub bytes_down: u64,
    /// The frame's eight counters as the entry point left them (`gpu.wgsl`
    /// for a plain frame, `savr.wgsl` for accumulation).
    pub counters: [u32; 8],
}

/// A pass of a sample accumulation (`savr.wgsl`): its entry point
/// (`accumulate` or `reblend`), the bands of image rows its store is
/// split into (one dispatch each, within one storage binding), and the
/// accumulation's uniform fields.
pub(crate) struct AccPass<'b> {
    pub entry: &'static str,
    pub bands: Vec<AccBand<'b>>,
    pub acc: [u32; 4],
    pub reference: f32,
}

/// A band of image rows of an accumulation: its first row, its rows, the
/// buffer holding the band's image and its store after it, and where the
/// store's parts start (words after the band's image).
pub(crate) struct AccBand<'b> {
    pub first: u32,
    pub rows: u32,
    pub store: &'b wgpu::Buffer,
    pub acc_off: [u32; 4],
}

/// The device renderer: pipelines and the per-slot buffers that persist
/// between frames.
pub struct GpuRenderer {
    /// Read the image back to the host after each frame (on by default;
    /// off for benchmarks and for views that present it on the device).
    pub read_image: bool,
    /// Draw only the pixel rows `[a, b)`, the others transparent (an
    /// image-parallel band of a render shared by several processes);
    /// `None` (the default): every row.
    pub rows: Option<(u32, u32)>,
    kernel: Kernel,
    /// Per slot of every set: frame stamps, with the slot count they were
    /// made for (with the update on the device, its stamps are used).
    stamps: Option<(u32, wgpu::Buffer)>,
    /// The counters and used-slot list (sized by the slot count), and the
    /// image (sized by width × height): kept between frames.
    counters: Option<(u32, wgpu::Buffer)>,
    /// Image buffers by size, most recently used last (a viewer draws
    /// several views of different sizes in turn).
    images: Vec<((u32, u32), wgpu::Buffer)>,
    /// The request table and the first brick id of each level it was made
    /// for.
    table: Option<(Vec<u32>, RequestTableGpu)>,
    /// The transfer function and transparent-brick bits (`gpu.wgsl`'s
    /// `aux`) and where the bits start; rebuilt only when what they were
    /// made for changes.
    /// Several, most recently used last (views with different transfer
    /// functions in turn).
    aux: Vec<(AuxKey, wgpu::Buffer, u32, u32, u32, Option<TableKey>)>,
    /// The device's twin of the scene's residency octree (its update
    /// passes keep the masks the octree traversal reads), with the octree
    /// it follows (`Octree::id`).
    octree: Option<(u64, DeviceOctree)>,
}

/// Transfer function, value ranges (by address), channel, brick grid, DVR
/// (the clear bits are for DVR only: 1, and 2 for a label image's, whose
/// clear bricks hold only label 0), channels, the words of the octree's
/// tables (0: no octree).
type AuxKey = (
    TransferFunction,
    usize,
    usize,
    Vec<[u64; 3]>,
    u8,
    Vec<ChannelStyle>,
    usize,
    Option<crate::params::LabelSelect>,
);

/// Image and transfer-function buffers kept for reuse.
const KEPT: usize = 6;

/// One bit per brick id: set when the transfer function maps the brick's
/// value range (from `ranges`, for `channel`) to zero opacity.
fn clear_bits(
    ids: &BrickIds,
    ranges: &BrickRanges,
    tf: &TransferFunction,
    channel: usize,
) -> Vec<u32> {
    clear_bits_by(ids, ranges, channel, |lo, hi, _, _| {
        tf.max_opacity(lo, hi) <= 0.0
    })
}

/// One bit per brick id: set where `clear(lo, hi, level, i)` holds for
/// the brick's value range (from `ranges`, for `channel`; `i`: the brick's
/// index in its level, raster order).
fn clear_bits_by(
    ids: &BrickIds,
    ranges: &BrickRanges,
    channel: usize,
    clear: impl Fn(f32, f32, usize, usize) -> bool,
) -> Vec<u32> {
    let mut bits = vec![0u32; (ids.len() as usize).div_ceil(32).max(1)];
    let starts = ids.level_starts();
    for (l, &first) in starts.iter().enumerate().take(starts.len() - 1) {
        let Some(r) = ranges.level(l).filter(|r| channel < r.channels) else {
            continue;
        };
        let n = r.bricks.iter().product::<u64>() as usize;
        let off = channel * n;
        for (i, &[lo, hi]) in r.range[off..off + n].iter().enumerate() {
            if clear(lo, hi, l, i) {
                let id = first as usize + off + i;
                bits[id / 32] |= 1 << (id % 32);
            }
        }
    }
    bits
}

/// The render kernel's WGSL module as it is compiled.
pub fn render_source() -> String {
    format!("{}\n{}", with_vm_common(RENDER_WGSL), REQUEST_INSERT_WGSL)
}

impl GpuRenderer {
    pub fn new(gpu: &Gpu) -> GpuRenderer {
        use Binding::*;
        let source = render_source();
        let kernel = Kernel::new(
            gpu,
            "render",
            &source,
            &["render", "accumulate", "reblend"],
            &[
                Uniform, ReadWrite, Texture3d, Uniform, Read, ReadWrite, ReadWrite, ReadWrite,
                ReadWrite, ReadWrite, ReadWrite, Texture3d,
            ],
        );
        GpuRenderer {
            read_image: true,
            rows: None,
            kernel,
            stamps: None,
            counters: None,
            images: vec![],
            table: None,
            aux: vec![],
            octree: None,
        }
    }

    /// The device's twin of the scene's octree (for tests: its masks
    /// equal the host's as of the last frame drawn).
    pub fn device_octree(&self) -> Option<&DeviceOctree> {
        self.octree.as_ref().map(|(_, d)| d)
    }

    /// Render one frame of `scene` (DVR or MIP of one channel) from what
    /// `dvm` holds; marks the slots used in `vm` (the host's virtual
    /// memory, between `begin_frame` and `end_frame`).
    pub fn render(
        &mut self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        vm: &VirtualMemory,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
    ) -> Result<GpuFrame, GpuError> {
        self.render_with(gpu, dvm, vm, None, scene, params, lod)
    }

    /// [`render`](Self::render); with `cache`, the device decides updates
    /// ([`DeviceCache`]): the frame stamps its slots and page-table blocks
    /// there and nothing about them comes back to the host (`vm` then
    /// only gives the frame number and configuration).
    #[allow(clippy::too_many_arguments)]
    pub fn render_with(
        &mut self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        vm: &VirtualMemory,
        cache: Option<&DeviceCache>,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
    ) -> Result<GpuFrame, GpuError> {
        self.draw(gpu, dvm, vm, cache, scene, params, lod, None)
    }

    /// [`render`](Self::render) without blocking on the device's answers:
    /// the browser's frame (its read-backs complete on the page's event
    /// loop). The same frame as `render`.
    pub async fn render_async(
        &mut self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        vm: &VirtualMemory,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
    ) -> Result<GpuFrame, GpuError> {
        self.draw_async(gpu, dvm, vm, None, scene, params, lod, None)
            .await
    }

    /// A frame of `render_with`, or a pass of a sample accumulation.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn draw(
        &mut self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        vm: &VirtualMemory,
        cache: Option<&DeviceCache>,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
        pass: Option<AccPass>,
    ) -> Result<GpuFrame, GpuError> {
        // Natively every read-back inside is ready when polled.
        pollster::block_on(self.draw_async(gpu, dvm, vm, cache, scene, params, lod, pass))
    }

    #[allow(clippy::too_many_arguments)]
    async fn draw_async(
        &mut self,
        gpu: &Gpu,
        dvm: &DeviceVm,
        vm: &VirtualMemory,
        cache: Option<&DeviceCache>,
        scene: &Scene,
        params: &RenderParams,
        lod: Lod,
        pass: Option<AccPass<'_>>,
    ) -> Result<GpuFrame, GpuError> {
        let (mode, plane) = match params.mode {
            RenderMode::Dvr => (0, ([0.0; 3], [0.0; 3])),
            RenderMode::Mip => (1, ([0.0; 3], [0.0; 3])),
            RenderMode::Slice { origin, normal } => {
                (2, (origin, brickyard_core::camera::normalize(normal)))
            }
        };
        let dvr_multi = mode == 0 && !params.channels.is_empty();
        // DVR through the residency octree: always by channel styles (one
        // for a one-channel DVR), its tables after them in `aux`.
        let by_octree = mode == 0 && params.traversal == Traversal::Octree;
        assert!(
            !(by_octree && cache.is_some()),
            "the octree follows the host's virtual memory: its updates must be decided on the host"
        );
        assert!(
            params.channels.len() <= if dvr_multi { MAX_DVR_CHANNELS } else { 16 },
            "at most 16 channels added up, 64 composited"
        );
        let nl = scene.levels.len();
        assert!(
            nl <= MAX_LEVELS && nl == vm.levels(),
            "levels of the scene and the virtual memory"
        );
        let grid: Vec<[u64; 3]> = scene
            .levels
            .iter()
            .map(|d| [0, 1, 2].map(|a| d[a].div_ceil(vm.config().brick[a])))
            .collect();
        let ids = BrickIds::new(&grid, vm.channels()).ok_or_else(|| GpuError::Limit {
            what: "bricks of the volume".into(),
            got: u32::MAX as u64,
            limit: u32::MAX as u64 - 1,
        })?;
        let buckets = vm.config().request_cap * 8;
        let starts = ids.level_starts();
        if self
            .table
            .as_ref()
            .is_none_or(|(s, t)| *s != starts || t.buckets() < buckets)
        {
            self.table = Some((starts.clone(), RequestTableGpu::new(gpu, &ids, buckets)));
        }
        let table = &mut self.table.as_mut().expect("made above").1;
        table.clear(gpu);
        let slots = dvm.pool.slots();
        let all = dvm.all_slots();
        if self.stamps.as_ref().is_none_or(|(n, _)| *n != all) {
            let b = gpu.storage_buffer_zeroed("slot stamps", all as u64 * 8);
            self.stamps = Some((all, b));
            let c = gpu.storage_buffer_zeroed("counters", (8 + 2 * slots as u64) * 4);
            self.counters = Some((all, c));
        }
        // With the update on the device, no used list comes back.
        let used_cap = if cache.is_some() { 0 } else { 2 * slots };
        let stamps = match cache {
            Some(c) => &c.stamps,
            None => &self.stamps.as_ref().expect("made above").1,
        };
        let counters = &self.counters.as_ref().expect("made with the stamps").1;
        // The counters start at 0; the used list is written up to its count.
        gpu.queue.write_buffer(counters, 0, &[0; 32]);
        let (w, h) = (params.width, params.height);
        match self.images.iter().position(|(d, _)| *d == (w, h)) {
            _ if pass.is_some() => {}
            Some(i) => {
                let x = self.images.remove(i);
                self.images.push(x);
            }
            None => {
                let bytes = w as u64 * h as u64 * 16;
                let limit = gpu.max_storage_binding();
                if bytes > limit {
                    return Err(GpuError::Limit {
                        what: format!(
                            "the image of {w}x{h} pixels (bytes, four floats a pixel; a smaller image or fewer views)"
                        ),
                        got: bytes,
                        limit,
                    });
                }
                // Every invocation writes its pixel: no clearing between
                // frames.
                let b = gpu.storage_buffer_zeroed("image", bytes);
                if self.images.len() >= KEPT {
                    self.images.remove(0);
                }
                self.images.push(((w, h), b));
            }
        }
        // The buffers drawn into, one dispatch each: the image, or the
        // bands of an accumulation (first row, rows, store offsets).
        let targets: Vec<(&wgpu::Buffer, u32, u32, [u32; 4])> = match &pass {
            Some(p) => p
                .bands
                .iter()
                .map(|b| (b.store, b.first, b.rows, b.acc_off))
                .collect(),
            None => vec![(&self.images.last().expect("made above").1, 0, h, [0; 4])],
        };

        let cam = &params.camera;
        let basis = cam.basis();
        let n_views = params.views.map_or(1, |v| v.count);
        let view_width = w / params.views.map_or(1, |v| v.columns());
        let f4 = |v: [f64; 3]| [v[0] as f32, v[1] as f32, v[2] as f32, 0.0];
        let (half_h, perspective) = match cam.projection {
            Projection::Perspective { fov_y_deg } => ((fov_y_deg * 0.5).to_radians().tan(), 1),
            Projection::Orthographic { height } => (height * 0.5, 0),
        };
        let tf = &params.tf;
        let reference = params.reference_step.unwrap_or(scene.voxel(0));
        let mut u = Uniform {
            width: w,
            height: h,
            mode,
            levels: nl as u32,
            eye: f4(cam.eye),
            right: f4(basis.right),
            up: f4(basis.up),
            forward: f4(basis.forward),
            extent: f4(scene.extent),
            half_h: half_h as f32,
            aspect: (view_width as f64 / h as f64) as f32,
            n_views,
            view_width,
            view_sel: [params.views.and_then(|v| v.alone).unwrap_or(0), 0, 0, 0],
            views: params.views.map_or([0.0; 4], |v| {
                [
                    v.separation as f32,
                    length(sub(cam.target, cam.eye)) as f32,
                    v.parallax as f32,
                    v.spacing as f32,
                ]
            }),
            perspective,
            lod_fixed: match lod {
                Lod::Fixed(l) => l as u32,
                Lod::Auto { .. } => u32::MAX,
            },
            lod_bias: match lod {
                Lod::Auto { bias } => bias as f32,
                Lod::Fixed(_) => 0.0,
            },
            fp_slope: cam.pixel_footprint(1.0, params.lod_height()) as f32,
            fp_const: cam.pixel_footprint(0.0, params.lod_height()) as f32,
            voxel0: scene.voxel(0) as f32,
            window0: tf.window[0],
            inv_width: 1.0 / (tf.window[1] - tf.window[0]),
            n_opacity: tf.opacity.len() as u32,
            n_color: tf.colormap.points().len() as u32,
            frame: vm.frame(),
            buckets: table.buckets() as u32,
            channel: scene.channel as u32,
            used_cap,
            ..bytemuck::Zeroable::zeroed()
        };
        for (l, d) in scene.levels.iter().enumerate() {
            let ext = [scene.extent[2], scene.extent[1], scene.extent[0]];
            let span = scene.span(l);
            u.scale[l] = [0, 1, 2, 3].map(|a| {
                if a < 3 {
                    (span[a] / ext[a]) as f32
                } else {
                    0.0
                }
            });
            u.qmax[l] = [0, 1, 2, 3].map(|a| if a < 3 { (d[a] - 1) as f32 } else { 0.0 });
            let dt = scene.voxel(l) / params.samples_per_voxel;
            u.step[l] = [dt as f32, (dt / reference) as f32, 0.0, 0.0];
            u.bricks[l] = [
                grid[l][0] as u32,
                grid[l][1] as u32,
                grid[l][2] as u32,
                starts[l],
            ];
        }
        // The octree's tables for this frame, from the host's octree (kept
        // in step with the host's virtual memory by `Octree::sync`): their
        // layout, and what they were made of (`None`: an octree made for
        // this frame alone); its residency masks from the device's twin,
        // brought up to date with the events since the last frame.
        let nl_oct = scene.levels.len();
        let (oct_layout, table_key) = match (by_octree, &scene.octree) {
            (false, _) => (None, None),
            (true, None) => (
                Some(OctFrame::device_layout(
                    crate::octree::DEFAULT_DEPTH,
                    nl_oct,
                    vm.channels(),
                )),
                None,
            ),
            (true, Some(o)) => {
                let t = o.read().expect("octree lock");
                (
                    Some(OctFrame::device_layout(t.depth, nl_oct, t.channels)),
                    Some(TableKey::new(&t, scene, params, lod)),
                )
            }
        };
        let oct_masks = match (&oct_layout, &scene.octree) {
            (Some(_), Some(arc)) => Some(device_octree_for(&mut self.octree, gpu, arc, scene)?),
            _ => None,
        };
        let key: AuxKey = (
            tf.clone(),
            scene
                .ranges
                .as_ref()
                .map_or(0, |r| std::sync::Arc::as_ptr(r) as usize),
            scene.channel,
            grid.clone(),
            match (mode, params.labels) {
                (0, true) => 2,
                (0, false) => 1,
                _ => 0,
            },
            params.channels.clone(),
            oct_layout.map_or(0, |o| o[2]),
            params.label_select.clone().filter(|_| params.labels),
        );
        if let Some(i) = self.aux.iter().position(|(k, ..)| *k == key) {
            let x = self.aux.remove(i);
            self.aux.push(x);
        } else {
            // The transfer function's points (then, for a DVR of several
            // channels, each channel's), then the clear bits.
            let points = |t: &TransferFunction| -> Vec<u32> {
                t.opacity
                    .iter()
                    .flat_map(|p| [p[0], p[1], 0.0, 0.0])
                    .chain(t.colormap.points().iter().flatten().copied())
                    .map(f32::to_bits)
                    .collect()
            };
            let mut words: Vec<u32> = points(tf);
            // DVR channels by style: (channel, transfer function, level
            // range).
            let ch_tfs: Vec<(usize, TransferFunction, Option<[usize; 2]>)> = if dvr_multi {
                params
                    .channels
                    .iter()
                    .map(|c| (c.channel, c.dvr_tf(), c.levels))
                    .collect()
            } else if by_octree {
                vec![(scene.channel, tf.clone(), None)]
            } else {
                vec![]
            };
            let mut first = vec![];
            for (_, t, _) in &ch_tfs {
                first.push(words.len() as u32 / 4);
                words.extend(points(t));
            }
            let off = words.len() as u32;
            let bits = match (&scene.ranges, mode) {
                // A channel's bricks have ids of their own: its bits are
                // set by its own transfer function.
                (Some(r), 0) if !ch_tfs.is_empty() => {
                    let mut bits = vec![];
                    for (c, t, _) in &ch_tfs {
                        let b = clear_bits(&ids, r, t, *c);
                        bits.resize(b.len(), 0);
                        for (x, y) in bits.iter_mut().zip(b) {
                            *x |= y;
                        }
                    }
                    bits
                }
                // A label image: bricks of background alone (its
                // surfaces take no transfer function).
                (Some(r), 0) if params.labels => {
                    // (Also bricks no label of a selection reaches.)
                    let sel = key.7.as_ref();
                    let cfg = vm.config();
                    let spans: Vec<_> = (0..scene.levels.len()).map(|l| scene.span(l)).collect();
                    clear_bits_by(&ids, r, scene.channel, |lo, hi, l, i| {
                        crate::optics::label_clear(lo, hi, sel)
                            || sel.is_some_and(|s| {
                                !s.may_reach_brick(
                                    i,
                                    scene.levels[l],
                                    spans[l],
                                    cfg.brick,
                                    cfg.apron,
                                )
                            })
                    })
                }
                (Some(r), 0) => clear_bits(&ids, r, tf, scene.channel),
                // No statistics, a label image drawing only some labels:
                // the bricks their boxes miss.
                (None, 0)
                    if params.labels
                        && key.7.as_ref().is_some_and(|s| !s.hide && s.boxes.is_some()) =>
                {
                    let sel = key.7.as_ref().expect("tested above");
                    let cfg = vm.config();
                    let mut bits = vec![0u32; (ids.len() as usize).div_ceil(32).max(1)];
                    let starts = ids.level_starts();
                    for (l, &first) in starts.iter().enumerate().take(starts.len() - 1) {
                        let (d, span) = (scene.levels[l], scene.span(l));
                        let n =
                            (0..3).map(|a| d[a].div_ceil(cfg.brick[a])).product::<u64>() as usize;
                        let off = scene.channel * n;
                        for i in (0..n)
                            .filter(|&i| !sel.may_reach_brick(i, d, span, cfg.brick, cfg.apron))
                        {
                            let id = first as usize + off + i;
                            bits[id / 32] |= 1 << (id % 32);
                        }
                    }
                    bits
                }
                // No statistics: no brick is known clear. A bit for every
                // brick all the same, as DVR tests them all (one word
                // here let the shader read the words after it as bits,
                // and skip bricks that showed).
                (None, 0) => vec![0; (ids.len() as usize).div_ceil(32).max(1)],
                _ => vec![0],
            };
            words.extend(bits);
            let styles_off = words.len() as u32;
            {
                // Per channel: channel, window start, 1 / width, first
                // point, opacity points, colour points, finest and
                // coarsest level (multi.wgsl).
                for ((c, t, lv), &p) in ch_tfs.iter().zip(&first) {
                    let [lo, hi] = lv.map_or([0, u32::MAX], |[a, b]| [a as u32, b as u32]);
                    words.extend([
                        *c as u32,
                        t.window[0].to_bits(),
                        (1.0 / (t.window[1] - t.window[0])).to_bits(),
                        p,
                        t.opacity.len() as u32,
                        t.colormap.points().len() as u32,
                        lo,
                        hi,
                    ]);
                }
            }
            // The channels added up: channel, lo, hi, 0, r, g, b, 0.
            for c in params.channels.iter().filter(|_| !dvr_multi) {
                words.extend([
                    c.channel as u32,
                    c.window[0].to_bits(),
                    c.window[1].to_bits(),
                    0,
                    c.color[0].to_bits(),
                    c.color[1].to_bits(),
                    c.color[2].to_bits(),
                    0,
                ]);
            }
            // A label image's selection: its labels, right before the
            // octree's tables.
            if let Some(sel) = &key.7 {
                words.extend(sel.ids.iter().map(|&id| id as u32));
            }
            // The octree's tables follow, rewritten when what they are made
            // of changes.
            let oct_off = words.len() as u32;
            if let Some(o) = &oct_layout {
                words.extend(std::iter::repeat_n(0, o[2]));
            }
            let bytes = words.len() as u64 * 4;
            let limit = gpu.max_storage_binding();
            if bytes > limit {
                return Err(GpuError::Limit {
                    what: "the transfer functions and the octree's tables (bytes; a smaller --octree-depth or fewer channels)".into(),
                    got: bytes,
                    limit,
                });
            }
            let buf = gpu.storage_buffer("transfer function", &words);
            if self.aux.len() >= KEPT {
                self.aux.remove(0);
            }
            self.aux.push((key, buf, off, styles_off, oct_off, None));
        }
        let (key, aux, off, styles_off, oct_off, written) =
            self.aux.last_mut().expect("made above");
        if let Some(sel) = &key.7 {
            let n = sel.ids.len() as u32;
            u.label_sel = [1 + sel.hide as u32, *oct_off - n, n, 0];
        }
        u.n_channels = if by_octree {
            params.channels.len().max(1) as u32
        } else {
            params.channels.len() as u32
        };
        let mut copy_masks = None;
        if let Some([m, d, _]) = oct_layout {
            let at = |rel: usize| (*oct_off as usize + rel) as u64 * 4;
            // The tables, unless this buffer holds them as they are.
            if table_key.is_none() || *written != table_key {
                let (words, masks, depths) = octree_tables(vm, scene, params, lod)?;
                debug_assert_eq!([masks as usize, depths as usize], [m, d]);
                gpu.queue
                    .write_buffer(aux, at(0), bytemuck::cast_slice(&words[..m]));
                gpu.queue
                    .write_buffer(aux, at(d), bytemuck::cast_slice(&words[d..]));
                if oct_masks.is_none() {
                    gpu.queue
                        .write_buffer(aux, at(m), bytemuck::cast_slice(&words[m..d]));
                }
                *written = table_key;
            }
            // The device's masks, copied on the device before drawing.
            if oct_masks.is_some() {
                copy_masks = Some((at(m), (d - m) as u64 * 4));
            }
            let channels = oct_masks.unwrap_or(vm.channels());
            u.oct = [
                *oct_off,
                *oct_off + m as u32,
                *oct_off + d as u32,
                channels as u32,
            ];
        }
        u.styles_off = *styles_off;
        u.skip = (mode == 0) as u32;
        let (count, cells) = dvm.pool.cells().expect("DeviceVm keeps cell ranges");
        let edge = brickyard_cache::cells::CellGrid::new(vm.config().brick).edge;
        u.skip_cells = (mode <= 1 && scene.skip_cells) as u32;
        u.cell_count = [count[0], count[1], count[2], 0];
        u.cell_edge = [edge[0] as u32, edge[1] as u32, edge[2] as u32, 0];
        u.plane_origin = f4(plane.0);
        u.plane_normal = f4(plane.1);
        if let Some(p) = &pass {
            u.acc = p.acc;
            u.acc_ref = [p.reference, 0.0, 0.0, 0.0];
        }
        if let (0, Some(sh)) = (mode, &tf.shading) {
            u.shade = 1;
            u.shading = [sh.ambient, sh.diffuse, sh.specular, sh.shininess];
        }
        u.clear_off = *off;
        if let Some(&[lo, hi]) = params.clip.as_deref() {
            u.clip_lo = f4(lo);
            u.clip_hi = f4(hi);
            u.region[0] = 1;
        }
        // MIP: raw maxima (a region's, to meet the others' before the
        // transfer function) or, outside regions, no ray ended early.
        u.region[2] = params.mip_values as u32;
        u.region[1] = !params.early_termination as u32;
        u.region[3] = params.labels as u32;
        if let Some((a, b)) = self.rows {
            u.rows = [1, a, b, 0];
        }
        let res = dvm.resources(gpu, 0);
        let [keys, counts, dropped] = table.buffers();
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        if let (Some((at, bytes)), Some((_, dev))) = (copy_masks, &self.octree) {
            enc.copy_buffer_to_buffer(&dev.masks, 0, aux, at, bytes);
        }
        let entry = pass.as_ref().map_or("render", |p| p.entry);
        // One dispatch per target (an accumulation's bands share the
        // frame's counters, stamps and request table).
        for &(image, first, rows, acc_off) in &targets {
            if pass.is_some() {
                u.acc_off = acc_off;
                u.acc_band = [first, rows, 0, 0];
            }
            let uniform = gpu.uniform_buffer("render", &u);
            let bind = self.kernel.bind_resources(
                gpu,
                vec![
                    res.layout.as_entire_binding(),
                    res.entries.as_entire_binding(),
                    wgpu::BindingResource::TextureView(&res.pool),
                    uniform.as_entire_binding(),
                    aux.as_entire_binding(),
                    image.as_entire_binding(),
                    stamps.as_entire_binding(),
                    counters.as_entire_binding(),
                    keys.as_entire_binding(),
                    counts.as_entire_binding(),
                    dropped.as_entire_binding(),
                    wgpu::BindingResource::TextureView(&cells),
                ],
            );
            self.kernel
                .dispatch(&mut enc, entry, &bind, [w.div_ceil(8), rows.div_ceil(8), 1]);
        }
        gpu.queue.submit([enc.finish()]);

        let head = gpu.read_u32_async("frame counters", counters, 8).await?;
        let used_n = head[4].min(used_cap) as usize;
        let used: Vec<u32> = if used_n > 0 {
            let used = gpu
                .read_back_async("used slots", counters, (8 + used_n as u64) * 4)
                .await?;
            bytemuck::pod_collect_to_vec(&used[32..])
        } else {
            vec![]
        };
        for &s in &used {
            vm.mark_used(s & !EXACT_BIT, s & EXACT_BIT != 0);
        }
        // Twice the cap: the host leaves out bricks that arrived while the
        // frame was drawn, and the cap goes to the next most wanted.
        let (list, dropped) = table.list_async(gpu, 2 * vm.config().request_cap).await?;
        let mut requests = vm.requests();
        for &(id, n) in &list {
            requests.add(ids.key(id), n);
        }
        let list = list.into_iter().map(|(id, _)| ids.key(id)).collect();
        let img = if self.read_image {
            let mut img = Image::new(w, h);
            img.rgba.clear();
            for &(image, _, rows, _) in &targets {
                let pixels = gpu
                    .read_back_async("image", image, w as u64 * rows as u64 * 16)
                    .await?;
                img.rgba
                    .extend(bytemuck::pod_collect_to_vec::<u8, [f32; 4]>(&pixels));
            }
            img
        } else {
            Image::new(0, 0)
        };
        Ok(GpuFrame {
            image: img,
            stats: FrameStats {
                samples: head[0] as u64,
                exact: head[1] as u64,
                unserved: head[2] as u64,
                skipped_bricks: head[3] as u64,
                skipped_cells: head[5] as u64,
                octree_nodes: if by_octree { head[6] as u64 } else { 0 },
                skipped_nodes: if by_octree { head[7] as u64 } else { 0 },
                ..Default::default()
            },
            requests,
            list,
            dropped,
            used_slots: used.len(),
            bytes_down: 32 + used.len() as u64 * 4 + table.downloaded,
            counters: head[..8].try_into().expect("eight counters"),
        })
    }
}

/// The residency octree's tables for a frame drawn on the device
/// ([`OctFrame::device_words`]): from the scene's octree, or one made from
/// `vm` as the CPU frame does when the scene has none.
fn octree_tables(
    vm: &VirtualMemory,
    scene: &Scene,
    params: &RenderParams,
    lod: Lod,
) -> Result<(Vec<u32>, u32, u32), GpuError> {
    let tree = scene_octree(scene, vm);
    let tree = &*tree;
    let nl = scene.levels.len();
    // One frame per channel shown (one for a one-channel DVR).
    let parts = (!params.channels.is_empty()).then(|| channel_parts(scene, params));
    let frames: Vec<Frame> = match &parts {
        Some((scenes, ps)) => channel_frames(vm, scenes, ps, params, lod),
        None => vec![Frame::new(vm, scene, params, lod)],
    };
    let refs: Vec<&Frame> = frames.iter().collect();
    let key = TableKey::new(tree, scene, params, lod);
    let of = OctFrame::cached(tree, &refs, &key.used.clone(), key);
    let words = of.device_words(&refs);
    debug_assert_eq!(
        words.0.len(),
        OctFrame::device_layout(tree.depth, nl, tree.channels)[2]
    );
    Ok(words)
}

/// Bring the device's twin (`slot`) of the octree `arc` up to date: made
/// when the octree is new to the renderer, then updated by its passes with
/// the events the octree logged since the last frame. Returns the
/// octree's channels, or the device's limit the twin would pass.
fn device_octree_for(
    slot: &mut Option<(u64, DeviceOctree)>,
    gpu: &Gpu,
    arc: &std::sync::Arc<std::sync::RwLock<Octree>>,
    scene: &Scene,
) -> Result<usize, GpuError> {
    let mut tree = arc.write().expect("octree lock");
    match slot {
        Some((id, dev)) if *id == tree.id() => {
            let events = tree.take_device_events();
            dev.update(gpu, &events);
        }
        _ => {
            let dev = DeviceOctree::new(gpu, &tree, scene.ranges.as_deref())?;
            tree.log_for_device();
            *slot = Some((tree.id(), dev));
        }
    }
    Ok(tree.channels)
}
