//! `--backend auto|gpu|cpu`: who renders the frames of a session, and
//! `--gpu-update device|host`: who decides the device's cache updates.
//! With `device` (the default) the device keeps its own LRU orders and
//! page tables: per frame only the request list and the slots to write
//! come back, and only bricks with their keys go over. With `host` the
//! host's virtual memory decides and the device mirrors its changes (the
//! used slots come back so the host's LRU keeps them). Both report what
//! crossed the bus.

use anyhow::{bail, Context, Result};
use brickyard_cache::session::{FrameStats as SessionStats, Session};
use brickyard_cache::vm::{FrameReport, InsertReport};
use brickyard_gpu::update::DeviceCache;
use brickyard_gpu::vm::DeviceVm;
use brickyard_gpu::{AdapterChoice, Gpu};
use brickyard_render::cpu::{render_tiles, FrameStats, Lod, Scene, Tiles};
use brickyard_render::gpu::update_on_device;
use brickyard_render::gpu::GpuRenderer;
use brickyard_render::reference::RenderParams;
use brickyard_render::savr::device::DeviceAccumulation;
use brickyard_render::savr::Accumulation;
use brickyard_render::Image;
use brickyard_store::info::human_bytes;

/// One frame, whoever drew it.
pub struct Frame {
    pub image: Image,
    pub stats: FrameStats,
    pub session: SessionStats,
    /// Host→device bytes after the frame (bricks and page entries; the
    /// CPU back end: bytes written into its pool).
    pub up: u64,
    /// Device→host bytes of cache management (request list, used slots,
    /// counters); 0 on the CPU.
    pub down: u64,
    /// Milliseconds spent drawing (the GPU: submission to completion,
    /// read-backs included).
    pub render_ms: f64,
    /// Milliseconds of cache management after drawing: requests to the
    /// loader, bricks into the host's pool and, on the GPU, to the device.
    pub cache_ms: f64,
    /// Of that, milliseconds carrying changes to the device (0 on the CPU).
    pub upload_ms: f64,
    /// Pool slots used at their own level this frame, pinned slots left
    /// out (on the device: counted by the pool's LRU compaction).
    pub exact_slots: Option<usize>,
    /// The CPU: which tiles are not settled yet (see [`Tiles`]), for
    /// [`Backend::frame_again`].
    pub tiles: Option<Tiles>,
}

pub struct GpuBackend {
    gpu: Gpu,
    dvm: DeviceVm,
    renderer: GpuRenderer,
    /// The update step on the device (`None`: the host decides).
    cache: Option<DeviceCache>,
}

/// Who decides the device's cache updates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GpuUpdate {
    Device,
    Host,
}

impl std::str::FromStr for GpuUpdate {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "device" => Ok(GpuUpdate::Device),
            "host" => Ok(GpuUpdate::Host),
            _ => Err(format!("expected device or host, found {s:?}")),
        }
    }
}

/// Run `f` with the process's standard error silenced. Probing the
/// graphics stack on a machine without a display makes window-system
/// libraries print errors (`XDG_RUNTIME_DIR is invalid or not set`) that
/// explain nothing about a render; a real failure comes back as `f`'s
/// error and is reported with context.
pub fn quietly<T>(f: impl FnOnce() -> T) -> T {
    if std::env::var_os("BRICKYARD_GPU_STDERR").is_some() {
        return f();
    }
    // SAFETY: plain descriptor calls; the saved descriptor is restored and
    // closed before returning, whatever `f` returned.
    unsafe {
        let saved = libc::dup(2);
        let null = libc::open(c"/dev/null".as_ptr(), libc::O_WRONLY);
        if saved < 0 || null < 0 {
            if saved >= 0 {
                libc::close(saved);
            }
            if null >= 0 {
                libc::close(null);
            }
            return f();
        }
        libc::dup2(null, 2);
        libc::close(null);
        let out = f();
        libc::dup2(saved, 2);
        libc::close(saved);
        out
    }
}

pub enum Backend {
    Cpu,
    Gpu(Box<GpuBackend>),
}

/// What a device back end takes of the memory budget, decided before the
/// budget is split (the driver lives in this process too).
#[derive(Debug, Clone, PartialEq)]
pub struct DevicePlan {
    /// The back end to open: `--backend`, or `cpu` where `auto` finds no
    /// hardware device or the budget leaves no room for one.
    pub choice: String,
    /// Bytes set aside for it: [`crate::memory::DEVICE_BYTES`] for a
    /// hardware device, [`crate::memory::SOFTWARE_DEVICE_BYTES`] for a
    /// software one, each with twice [`crate::memory::STAGING_BYTES`] for
    /// the upload staging buffer; for `auto` that found only a software
    /// one, what loading its driver took.
    pub bytes: u64,
    /// A software adapter: its device memory is host memory, so the
    /// device's copy of the pool counts too.
    pub mirror_pool: bool,
    /// What to tell the user of a choice made for them.
    pub note: Option<String>,
}

impl DevicePlan {
    /// Bricks written into the pool per frame at most: a device's staging
    /// buffer is set aside for [`crate::memory::STAGING_BYTES`] of them;
    /// the CPU back end has none (`None`).
    pub fn upload_cap(&self) -> Option<u64> {
        (self.choice != "cpu" && self.bytes > 0).then_some(crate::memory::STAGING_BYTES)
    }

    /// Record the device's share in `split` (made with [`Self::bytes`] as
    /// its extra): a software device's copy of the pool comes out of the
    /// pool's share when the budget chose it (half each), or out of the
    /// host cache's when `--pool` gave it (`pool_given`), or is refused.
    pub fn take_from(
        &self,
        split: &mut crate::memory::Split,
        pool_given: Option<u64>,
    ) -> Result<()> {
        split.device = self.bytes;
        if !self.mirror_pool {
            return Ok(());
        }
        let copy = match pool_given {
            None => {
                let half = split.pool / 2;
                split.pool -= half;
                half
            }
            Some(p) => {
                if split.host >= p + (1 << 20) {
                    split.host -= p;
                } else if split.explicit {
                    bail!(
                        "memory: the device is a software one, whose memory is host memory: \
                         its copy of the {} pool does not fit beside the host cache of {} in {}; \
                         raise --memory, lower --pool or use --backend cpu",
                        human_bytes(p),
                        human_bytes(split.host),
                        human_bytes(split.total)
                    );
                } else {
                    split.total += p;
                }
                p
            }
        };
        split.device += copy;
        split.fixed += copy;
        Ok(())
    }
}

/// The [`DevicePlan`] for `--backend choice` on adapter `adapter` under
/// `--memory` `memory` (`None`: the default budget).
pub fn plan_device(choice: &str, adapter: usize, memory: Option<u64>) -> DevicePlan {
    use crate::memory::{rss, DEVICE_BYTES, FIXED_BYTES, SOFTWARE_DEVICE_BYTES, STAGING_BYTES};
    let plan = |choice: &str, bytes, mirror_pool| DevicePlan {
        choice: choice.into(),
        bytes,
        mirror_pool,
        note: None,
    };
    let probe = || quietly(|| Gpu::adapter_info(AdapterChoice::Best, adapter));
    // The driver's share and the upload staging buffer's.
    let (hardware, software) = (
        DEVICE_BYTES + 2 * STAGING_BYTES,
        SOFTWARE_DEVICE_BYTES + 2 * STAGING_BYTES,
    );
    match choice {
        "auto" => {
            // Under an address-space limit a graphics driver looked at
            // maps more than it holds (lavapipe: an allocation failed
            // within `ulimit -v 400000` at a budget that fits without it).
            if crate::memory::address_space_limit().is_some() {
                return DevicePlan {
                    note: Some(
                        "note: an address-space limit is set (ulimit -v): --backend auto takes \
                         the CPU without looking for a device (--backend gpu to use one)"
                            .into(),
                    ),
                    ..plan("cpu", 0, false)
                };
            }
            // Room for a driver and at least 64 MiB of data besides.
            if let Some(m) = memory.filter(|&m| m < FIXED_BYTES + hardware + (64 << 20)) {
                return DevicePlan {
                    note: Some(format!(
                        "note: --memory {} leaves no room for a device driver (about {}): \
                         --backend auto takes the CPU",
                        human_bytes(m),
                        human_bytes(hardware)
                    )),
                    ..plan("cpu", 0, false)
                };
            }
            let before = rss();
            match probe() {
                Ok(i) if i.device_type != wgpu::DeviceType::Cpu => plan("auto", hardware, false),
                // The driver looked at stays loaded: its share is what
                // it took.
                _ => {
                    let took = before.zip(rss()).map_or(0, |(a, b)| b.saturating_sub(a));
                    plan("cpu", took, false)
                }
            }
        }
        "gpu" => match probe() {
            Ok(i) if i.device_type == wgpu::DeviceType::Cpu => plan("gpu", software, true),
            Ok(_) => plan("gpu", hardware, false),
            // Opening it says why it cannot be.
            Err(_) => plan("gpu", 0, false),
        },
        c => plan(c, 0, false),
    }
}

impl Backend {
    /// The largest storage buffer a device frame may bind (`None`: the
    /// CPU).
    pub fn max_storage_binding(&self) -> Option<u64> {
        match self {
            Backend::Gpu(g) => Some(g.gpu.max_storage_binding()),
            Backend::Cpu => None,
        }
    }

    /// A device whose memory is this process's (a software adapter): what
    /// it allocates counts against --memory.
    pub fn device_in_host_memory(&self) -> bool {
        matches!(self, Backend::Gpu(g) if g.gpu.is_software())
    }

    /// The back end `choice` names for rendering `channels` channels (added
    /// up when several) from session `s`. `auto` takes a hardware adapter when
    /// there is one, the CPU otherwise (a software adapter is slower than the
    /// CPU renderer).
    pub fn choose(
        choice: &str,
        update: GpuUpdate,
        s: &mut Session,
        channels: usize,
    ) -> Result<Backend> {
        Backend::choose_on(choice, update, s, channels, 0)
    }

    /// [`Backend::choose`] on adapter `adapter` (modulo the adapters of the
    /// preferred kind: [`Gpu::new_nth`]): one MPI rank per device.
    pub fn choose_on(
        choice: &str,
        update: GpuUpdate,
        s: &mut Session,
        channels: usize,
        adapter: usize,
    ) -> Result<Backend> {
        let most = brickyard_render::params::MAX_DVR_CHANNELS;
        if channels > most {
            bail!("at most {most} channels at once (16 added up in mip and slice), {channels} asked for");
        }
        let gpu = match choice {
            "cpu" => return Ok(Backend::Cpu),
            "gpu" => {
                quietly(|| Gpu::new_nth(AdapterChoice::Best, adapter)).context("--backend gpu")?
            }
            "auto" => match quietly(|| Gpu::new_nth(AdapterChoice::Best, adapter)) {
                Ok(g) if g.info.device_type != wgpu::DeviceType::Cpu => g,
                _ => return Ok(Backend::Cpu),
            },
            c => bail!("--backend: expected auto, gpu or cpu, found {c:?}"),
        };
        let (dvm, _) = DeviceVm::new(&gpu, s.vm_mut())?;
        let renderer = GpuRenderer::new(&gpu);
        let cache = match update {
            GpuUpdate::Device => Some(DeviceCache::new(&gpu, &dvm, s.vm())?),
            GpuUpdate::Host => None,
        };
        Ok(Backend::Gpu(Box::new(GpuBackend {
            gpu,
            dvm,
            renderer,
            cache,
        })))
    }

    /// Whether frames come back to the host as images (on by default; a
    /// benchmark of the device turns it off: a viewer presents the image
    /// where it was drawn).
    pub fn set_read_image(&mut self, on: bool) {
        if let Backend::Gpu(g) = self {
            g.renderer.read_image = on;
        }
    }

    pub fn describe(&self) -> String {
        match self {
            Backend::Cpu => format!("CPU ({} threads)", rayon::current_num_threads()),
            Backend::Gpu(g) => format!(
                "GPU: {} (updates decided on the {})",
                g.gpu.describe(),
                if g.cache.is_some() { "device" } else { "host" }
            ),
        }
    }

    /// Draw one frame and end it (requests out, bricks in).
    pub fn frame(
        &mut self,
        s: &mut Session,
        scene: &Scene,
        p: &RenderParams,
        lod: Lod,
    ) -> Result<Frame> {
        let g = match self {
            Backend::Cpu => {
                let (w, h) = (p.width, p.height);
                return cpu_frame(s, scene, p, lod, Image::new(w, h), Tiles::all(w, h));
            }
            Backend::Gpu(g) => g,
        };
        s.begin_frame();
        let t = std::time::Instant::now();
        match g.cache {
            Some(_) => g.device_frame(s, scene, p, lod, t),
            None => {
                let f = g.renderer.render(&g.gpu, &g.dvm, s.vm(), scene, p, lod)?;
                let render_ms = t.elapsed().as_secs_f64() * 1e3;
                let c = std::time::Instant::now();
                let session = finish_host_frame(s, scene, [&f.requests]);
                let u = std::time::Instant::now();
                let sync = g.dvm.sync(&g.gpu, s.vm_mut());
                // The copies are queued: wait for them, to time them.
                let _ = g.gpu.device.poll(wgpu::PollType::wait_indefinitely());
                Ok(Frame {
                    exact_slots: Some(session.frame.exact_slots),
                    tiles: None,
                    image: f.image,
                    stats: f.stats,
                    session,
                    up: sync.bytes,
                    down: f.bytes_down,
                    render_ms,
                    cache_ms: c.elapsed().as_secs_f64() * 1e3,
                    upload_ms: u.elapsed().as_secs_f64() * 1e3,
                })
            }
        }
    }
}

impl Backend {
    /// The next frame of a view whose last frame (`image`, `tiles`, from
    /// the CPU) had the same parameters and level of detail: only the
    /// tiles not settled then are drawn again (the others would come out
    /// the same). Other back ends draw a whole frame.
    pub fn frame_again(
        &mut self,
        s: &mut Session,
        scene: &Scene,
        p: &RenderParams,
        lod: Lod,
        image: Image,
        tiles: Tiles,
    ) -> Result<Frame> {
        if !matches!(self, Backend::Cpu) {
            return self.frame(s, scene, p, lod);
        }
        cpu_frame(s, scene, p, lod, image, tiles)
    }

    /// A frame of the tile rows `rows` only (an image-parallel band), the
    /// other pixels transparent: the CPU draws their tiles, the device
    /// their pixel rows.
    pub fn frame_band(
        &mut self,
        s: &mut Session,
        scene: &Scene,
        p: &RenderParams,
        lod: Lod,
        rows: std::ops::Range<u32>,
    ) -> Result<Frame> {
        let (w, h) = (p.width, p.height);
        match self {
            Backend::Cpu => cpu_frame(s, scene, p, lod, Image::new(w, h), Tiles::band(w, h, rows)),
            Backend::Gpu(g) => {
                let px = Tiles::pixel_rows(h, rows);
                g.renderer.rows = Some((px.start, px.end));
                let f = self.frame(s, scene, p, lod);
                if let Backend::Gpu(g) = self {
                    g.renderer.rows = None;
                }
                f
            }
        }
    }
}

/// End a frame whose updates the host decides (drawn on the CPU, or on the
/// device mirroring the host): requests out, arrivals in; the scene's
/// residency octree, if any, follows what the frame mapped and evicted.
fn finish_host_frame<'a>(
    s: &mut Session,
    scene: &Scene,
    reqs: impl IntoIterator<Item = &'a brickyard_cache::vm::Requests>,
) -> SessionStats {
    let session = s.finish_frame(reqs);
    if let Some(o) = &scene.octree {
        o.write().expect("octree lock").sync(s.vm_mut());
    }
    session
}

/// A residency octree of depth `depth` over `s`'s virtual memory as it is
/// now, kept in `scene` (every CPU frame's end syncs it).
pub fn attach_octree(scene: &mut Scene, s: &mut Session, depth: u32) -> Result<()> {
    let o = brickyard_render::octree::Octree::attach(
        depth,
        &scene.levels,
        s.vm_mut(),
        scene.ranges.as_deref(),
    )
    .map_err(|e| anyhow::anyhow!("octree-depth: {e}"))?;
    scene.octree = Some(std::sync::Arc::new(std::sync::RwLock::new(o)));
    Ok(())
}

/// A CPU frame: draw the marked tiles of `image`, then end the frame.
fn cpu_frame(
    s: &mut Session,
    scene: &Scene,
    p: &RenderParams,
    lod: Lod,
    mut image: Image,
    mut tiles: Tiles,
) -> Result<Frame> {
    s.begin_frame();
    let t = std::time::Instant::now();
    let (stats, reqs) = render_tiles(s.vm(), scene, p, lod, &mut image, &mut tiles);
    let render_ms = t.elapsed().as_secs_f64() * 1e3;
    let c = std::time::Instant::now();
    let session = finish_host_frame(s, scene, reqs.iter());
    Ok(Frame {
        exact_slots: Some(session.frame.exact_slots),
        tiles: Some(tiles),
        image,
        stats,
        up: session.insert.bytes_uploaded,
        down: 0,
        session,
        render_ms,
        cache_ms: c.elapsed().as_secs_f64() * 1e3,
        upload_ms: 0.0,
    })
}

impl GpuBackend {
    /// A frame with the update step on the device: draw (stamping what was
    /// used), then [`update_on_device`].
    fn device_frame(
        &mut self,
        s: &mut Session,
        scene: &Scene,
        p: &RenderParams,
        lod: Lod,
        t: std::time::Instant,
    ) -> Result<Frame> {
        let cache = self.cache.as_mut().expect("device updates");
        let frame = s.vm().frame();
        let f =
            self.renderer
                .render_with(&self.gpu, &self.dvm, s.vm(), Some(cache), scene, p, lod)?;
        let render_ms = t.elapsed().as_secs_f64() * 1e3;
        let c = std::time::Instant::now();
        let before = cache.counts();
        cache.set_in_use_frames(s.vm().in_use_frames());
        let x = update_on_device(&self.gpu, &mut self.dvm, cache, s, frame, &f.list)?;
        let _ = self.gpu.device.poll(wgpu::PollType::wait_indefinitely());
        // Deciding and carrying over are one step here.
        let upload_ms = c.elapsed().as_secs_f64() * 1e3;
        let now = x.counts;
        let failed_requested = x.requested.iter().filter(|k| s.vm().is_failed(**k)).count();
        // Slots used at their own level, as the CPU counts them: the
        // pinned ones are stamped so at every frame's end, whether used or
        // not, and are left out.
        let exact_slots = (now.exact_pool_slots as usize).saturating_sub(s.vm().pinned_bricks());
        let session = SessionStats {
            failed: 0,
            frame: FrameReport {
                exact_slots,
                failed_requested,
                frame,
                requested: x.requested.len(),
                requests: x.requested,
                dropped: f.dropped,
                resident_bricks: now.resident_bricks() as usize,
                resident_pt_blocks: vec![
                    now.blocks_mapped.saturating_sub(now.blocks_unmapped) as usize
                ],
            },
            insert: InsertReport {
                inserted: x.inserted,
                flagged: x.flagged,
                bytes_uploaded: x.up,
                evicted_bricks: (now.bricks_unmapped - before.bricks_unmapped) as usize,
                evicted_pt_blocks: (now.blocks_unmapped - before.blocks_unmapped) as usize,
                deferred: x.deferred,
                processed: x.inserted + x.flagged,
                evicted_in_use: now.evicted_in_use as usize,
                ..Default::default()
            },
            delivered: x.delivered,
            cancelled: x.cancelled,
            pending: s.loader().pending(),
            in_flight: s.loader().in_flight(),
            waiting_upload: s.waiting().len(),
        };
        Ok(Frame {
            exact_slots: Some(exact_slots),
            tiles: None,
            image: f.image,
            stats: f.stats,
            session,
            up: x.up,
            down: f.bytes_down + x.down,
            render_ms,
            cache_ms: c.elapsed().as_secs_f64() * 1e3,
            upload_ms,
        })
    }
}

/// Whether `e` is the device running out of memory (for a pool too large
/// for it).
pub fn device_out_of_memory(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        matches!(
            c.downcast_ref::<brickyard_gpu::context::GpuError>(),
            Some(brickyard_gpu::context::GpuError::OutOfMemory { .. })
        )
    })
}

/// A sample accumulation on the back end that draws the view: the CPU's
/// [`Accumulation`] or the device's [`DeviceAccumulation`].
pub enum Accumulating {
    Cpu(Accumulation),
    Gpu(DeviceAccumulation),
}

/// What an accumulation frame reports.
#[derive(Debug, Clone, Copy, Default)]
pub struct AccumFrame {
    /// Lookups made, those served at their level, stand-ins kept after
    /// the frame.
    pub samples: u64,
    pub exact: u64,
    pub stand_ins: u64,
    /// Pixels not complete after the frame (the device counts them; the
    /// CPU's are those with stand-ins, `None`).
    pub incomplete: Option<u64>,
}

impl Accumulating {
    /// Blend only what the last frame shows (see
    /// [`Accumulation::blend_last_only`]).
    pub fn blend_last_only(&mut self) {
        match self {
            Accumulating::Cpu(a) => a.blend_last_only(),
            Accumulating::Gpu(a) => a.blend_last_only(),
        }
    }

    /// An empty accumulation of `n` frames for `p`'s image on `backend`,
    /// keeping at most `budget` samples a pixel (the device lowers it to
    /// what one of its buffers holds).
    pub fn new(backend: &Backend, p: &RenderParams, n: u32, budget: usize) -> Accumulating {
        match backend {
            Backend::Cpu => Accumulating::Cpu(Accumulation::new(p.width, p.height, n, budget)),
            Backend::Gpu(g) => Accumulating::Gpu(DeviceAccumulation::new(
                &g.gpu, p.width, p.height, n, budget,
            )),
        }
    }

    /// Whether frames can be drawn in parts ([`frame_rows`](Self::frame_rows)).
    pub fn in_parts(&self) -> bool {
        matches!(self, Accumulating::Cpu(_))
    }

    pub fn complete(&self) -> bool {
        match self {
            Accumulating::Cpu(a) => a.complete(),
            Accumulating::Gpu(a) => a.complete(),
        }
    }

    pub fn image(&self) -> &Image {
        match self {
            Accumulating::Cpu(a) => a.image(),
            Accumulating::Gpu(a) => a.image(),
        }
    }

    /// Frames blended so far (the fewest of any pixel on the CPU; frames
    /// drawn, at most the target, on the device).
    pub fn frames(&self) -> u32 {
        match self {
            Accumulating::Cpu(a) => a.frames(),
            Accumulating::Gpu(a) => a.drawn().min(a.target()),
        }
    }

    /// Frames drawn, at most the target: where the memory for kept
    /// samples stopped some pixels short, more than [`frames`](Self::frames).
    pub fn drawn(&self) -> u32 {
        match self {
            Accumulating::Cpu(a) => a.drawn().min(a.target()),
            Accumulating::Gpu(a) => a.drawn().min(a.target()),
        }
    }

    /// Frames asked for (lowered by [`fit_memory`](Self::fit_memory)).
    pub fn target(&self) -> u32 {
        match self {
            Accumulating::Cpu(a) => a.target(),
            Accumulating::Gpu(a) => a.target(),
        }
    }

    /// Samples a pixel keeps.
    pub fn budget(&self) -> usize {
        match self {
            Accumulating::Cpu(a) => a.budget(),
            Accumulating::Gpu(a) => a.budget(),
        }
    }

    /// Lower the frames asked for to the most whose expected samples fit
    /// `bytes` (see [`Accumulation::fit_memory`]): where lowered, the new
    /// number and the bytes the frames asked for were expected to take.
    /// The device's store is allocated whole at the first frame (sized
    /// within its share before): `None`.
    pub fn fit_memory(&mut self, bytes: u64) -> Option<(u32, u64)> {
        match self {
            Accumulating::Cpu(a) => a.fit_memory(bytes),
            Accumulating::Gpu(_) => None,
        }
    }

    /// Bytes of kept samples (on the device: the whole store, allocated at
    /// the first frame).
    pub fn memory(&self) -> u64 {
        match self {
            Accumulating::Cpu(a) => a.memory() as u64,
            Accumulating::Gpu(a) => a.memory(),
        }
    }

    /// One accumulation frame, ended (requests out, bricks in).
    pub fn frame(
        &mut self,
        backend: &mut Backend,
        s: &mut Session,
        scene: &Scene,
        p: &RenderParams,
        lod: Lod,
    ) -> Result<AccumFrame> {
        self.frame_rows(backend, s, scene, p, lod, 0..p.height)
    }

    /// [`frame`](Self::frame) for image rows `rows` only on the CPU (a
    /// view answers input between the parts of a frame); the device draws
    /// whole frames.
    pub fn frame_rows(
        &mut self,
        backend: &mut Backend,
        s: &mut Session,
        scene: &Scene,
        p: &RenderParams,
        lod: Lod,
        rows: std::ops::Range<u32>,
    ) -> Result<AccumFrame> {
        s.begin_frame();
        match (self, backend) {
            (Accumulating::Cpu(a), Backend::Cpu) => {
                let (st, reqs) = a.frame_rows(s.vm(), scene, p, lod, rows);
                finish_host_frame(s, scene, reqs.iter());
                Ok(AccumFrame {
                    samples: st.frame.samples,
                    exact: st.frame.exact,
                    stand_ins: st.stand_ins,
                    incomplete: None,
                })
            }
            (Accumulating::Gpu(a), Backend::Gpu(g)) => {
                let frame = s.vm().frame();
                let f = a.frame(
                    &g.gpu,
                    &mut g.renderer,
                    &g.dvm,
                    s.vm(),
                    g.cache.as_ref(),
                    scene,
                    p,
                    lod,
                )?;
                match g.cache.as_mut() {
                    Some(cache) => {
                        update_on_device(&g.gpu, &mut g.dvm, cache, s, frame, &f.list)?;
                    }
                    None => {
                        s.finish_frame([&f.requests]);
                        g.dvm.sync(&g.gpu, s.vm_mut());
                    }
                }
                Ok(AccumFrame {
                    samples: a.last().frame.samples,
                    exact: a.last().frame.exact,
                    stand_ins: a.last().stand_ins,
                    incomplete: Some(a.last().incomplete),
                })
            }
            _ => bail!("the accumulation was begun on another back end"),
        }
    }

    /// Blend the kept samples again under `p.tf` (no volume access): the
    /// pixels left short (the next frame extends them); `None` when the
    /// function shades and the samples keep no normals.
    pub fn reblend(
        &mut self,
        backend: &mut Backend,
        s: &Session,
        scene: &Scene,
        p: &RenderParams,
    ) -> Result<Option<u64>> {
        match (self, backend) {
            (Accumulating::Cpu(a), _) => Ok(a.reblend(&p.tf).map(|n| n as u64)),
            (Accumulating::Gpu(a), Backend::Gpu(g)) => {
                Ok(a.reblend(&g.gpu, &mut g.renderer, &g.dvm, s.vm(), scene, p)?)
            }
            _ => bail!("the accumulation was begun on another back end"),
        }
    }
}
