//! The filters on the device: WGSL compute kernels (`shaders/filter.wgsl`)
//! through `wgpu`, on the device [`brickyard_gpu`] opens.
//!
//! Five kernels, each the twin of the CPU function of the same name in
//! [`crate::kernels`] instantiated in f32: `correlate_valid` (one 1D pass of
//! a separable filter along one axis, valid part), `sum_squares` and
//! `square_root` (the gradient magnitude's combine), `threshold` and
//! `window`. [`DeviceFilter`] runs a whole [`Filter`] on a padded block with
//! them — the same passes in the same order as [`Filter::apply`] — reusing
//! its device buffers from block to block; its CPU twin is
//! `Filter::apply::<f32>`. [`crate::FilterSource::with_device`] makes a
//! stage compute its reads this way.
//!
//! **Arithmetic and tolerance.** The device computes in f32, the CPU filters
//! in f64 (both store f32). Against the f32 twins the only differences are
//! what Vulkan allows a driver: `acc + w·x` may be fused into one rounding,
//! and `sqrt` is accurate to a few ulp, not correctly rounded. Against the
//! f64 filters, each output of a separable pass is a sum of `n` products
//! rounded in f32, whose error is at most `n·u·Σ|w_k·x_k|` (`u = 2⁻²⁴`; the
//! a-priori bound of recursive summation); over the passes of a stage, with
//! the rounding of the input to f32, of the weights and of the stored
//! result, [`Filter::device_tolerance`] bounds the difference by
//! `2 · m · u · G · M`: `m` the roundings on the way (`Σ_axes (taps + 1)`,
//! plus 2, plus 4 for a magnitude), `G` the filter's gain (`Π_axes Σ|w|`,
//! combined over the components in quadrature for a magnitude), `M` the
//! largest `|input|`, and the factor 2 for fused products and the square
//! root's ulps. For `gauss(2)` that is about `6.7·10⁻⁶ · M`, for `sobel`
//! `1.2·10⁻⁴ · M`; measured differences are far smaller. Masks are exact:
//! the bounds of `threshold` and `window` are rounded outward to f32 on the
//! host (see [`threshold_bounds`]), so that for every f32 value the device's
//! f32 comparison gives the f64 comparison of the CPU; a mask after a float
//! stage can only differ where that stage's value lies within its tolerance
//! of a bound.

use crate::filter::Filter;
use crate::kernels::is_identity;
use brickyard_gpu::kernel::{Binding, Kernel};
use brickyard_gpu::{Gpu, GpuError};
use std::sync::Arc;

/// Invocations per workgroup of every entry point.
const WG: u64 = 256;

/// Largest padded block computed at once on the device, in voxels: 32 MiB
/// of f32 per buffer. Larger regions are cut into pieces of at most this
/// many voxels with their halos.
pub const DEVICE_BLOCK_VOXELS: u64 = 1 << 23;

const ENTRIES: [&str; 5] = [
    "correlate_valid",
    "sum_squares",
    "square_root",
    "threshold",
    "window",
];

/// `Params` of `filter.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    nx: u32,
    ny: u32,
    nz: u32,
    count: u32,
    sy: u32,
    sz: u32,
    step: u32,
    taps: u32,
    w0: u32,
    first: u32,
    pad0: u32,
    pad1: u32,
    lo: f32,
    hi: f32,
    pad2: f32,
    pad3: f32,
}

impl Params {
    /// An element-wise kernel over `count` voxels (one row of `count`).
    fn flat(count: usize) -> Params {
        Params {
            nx: count as u32,
            ny: 1,
            nz: 1,
            count: count as u32,
            ..Default::default()
        }
    }

    /// One `correlate_valid` pass over input `dims` along `axis` with `taps`
    /// weights starting at `w0`; also returns the output dimensions.
    fn pass(dims: [usize; 3], axis: usize, taps: usize, w0: u32) -> (Params, [usize; 3]) {
        let mut od = dims;
        od[axis] -= taps - 1;
        let (sy, sz) = (dims[2], dims[1] * dims[2]);
        let p = Params {
            nx: od[2] as u32,
            ny: od[1] as u32,
            nz: od[0] as u32,
            count: (od[0] * od[1] * od[2]) as u32,
            sy: sy as u32,
            sz: sz as u32,
            step: [sz, sy, 1][axis] as u32,
            taps: taps as u32,
            w0,
            ..Default::default()
        };
        (p, od)
    }
}

/// The largest f32 not above `t` (`t` itself when it is one).
fn round_down(t: f64) -> f32 {
    let f = t as f32;
    if f as f64 > t {
        f.next_down()
    } else {
        f
    }
}

/// The smallest f32 not below `t`.
fn round_up(t: f64) -> f32 {
    let f = t as f32;
    if (f as f64) < t {
        f.next_up()
    } else {
        f
    }
}

/// The f32 bounds the device compares with, for the f64 bounds of a mask
/// stage: `threshold(t)` → `(down(t), _)`, `window(lo, hi)` →
/// `(up(lo), down(hi))`. For every f32 `v`: `v > t ⇔ v > down(t)`,
/// `lo ≤ v ⇔ up(lo) ≤ v` and `v ≤ hi ⇔ v ≤ down(hi)`, so the masks equal
/// the CPU's (which compares in f64) exactly, for the same f32 values.
pub fn threshold_bounds(f: &Filter) -> Option<(f32, f32)> {
    match f {
        Filter::Threshold(t) => Some((round_down(*t), 0.0)),
        Filter::Window(lo, hi) => Some((round_up(*lo), round_down(*hi))),
        _ => None,
    }
}

/// The compiled filter kernels on one device, shared by every stage that
/// computes there.
pub struct FilterKernels {
    pub gpu: Arc<Gpu>,
    kernel: Kernel,
    /// See [`FilterKernels::max_voxels`].
    max_voxels: u64,
}

/// A device buffer that grows to the largest size asked of it.
struct Grown {
    buf: wgpu::Buffer,
    bytes: u64,
    usage: wgpu::BufferUsages,
    label: &'static str,
}

impl Grown {
    fn new(gpu: &Gpu, label: &'static str, usage: wgpu::BufferUsages) -> Grown {
        Grown {
            buf: make_buffer(gpu, label, 4, usage),
            bytes: 4,
            usage,
            label,
        }
    }

    fn ensure(&mut self, gpu: &Gpu, bytes: u64) {
        if bytes > self.bytes {
            self.buf = make_buffer(gpu, self.label, bytes, self.usage);
            self.bytes = bytes;
        }
    }
}

fn make_buffer(gpu: &Gpu, label: &str, bytes: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
    gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(4).next_multiple_of(4),
        usage,
        mapped_at_creation: false,
    })
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_SRC)
    .union(wgpu::BufferUsages::COPY_DST);

impl FilterKernels {
    /// Compile the kernels on `gpu`; blocks of up to
    /// [`DEVICE_BLOCK_VOXELS`].
    pub fn new(gpu: Arc<Gpu>) -> Arc<FilterKernels> {
        Self::with_block_voxels(gpu, DEVICE_BLOCK_VOXELS)
    }

    /// [`FilterKernels::new`] with blocks of up to `voxels` padded voxels
    /// (less where the device's limits say so).
    pub fn with_block_voxels(gpu: Arc<Gpu>, voxels: u64) -> Arc<FilterKernels> {
        use Binding::*;
        let kernel = Kernel::new(
            &gpu,
            "filter",
            include_str!("shaders/filter.wgsl"),
            &ENTRIES,
            &[Uniform, Read, Read, ReadWrite],
        );
        let limit = (gpu.max_storage_binding() / 4).min(u32::MAX as u64);
        let max_voxels = voxels.clamp(1, limit);
        Arc::new(FilterKernels {
            gpu,
            kernel,
            max_voxels,
        })
    }

    /// The most voxels of one padded block computed at once (f32 in each
    /// of the device's buffers): regions are cut into pieces that fit.
    pub fn max_voxels(&self) -> u64 {
        self.max_voxels
    }

    /// Workgroups `[x, y, 1]` covering `count` invocations.
    fn groups(&self, count: u32) -> Result<[u32; 3], GpuError> {
        let max = self.gpu.limits.max_compute_workgroups_per_dimension as u64;
        let groups = (count as u64).div_ceil(WG).max(1);
        let gx = groups.min(max);
        let gy = groups.div_ceil(gx);
        if gy > max {
            return Err(GpuError::Limit {
                what: "filter block voxels / 256".into(),
                got: groups,
                limit: max * max,
            });
        }
        Ok([gx as u32, gy as u32, 1])
    }

    /// Record one dispatch of `entry` with `params` (in `pbuf`).
    fn record(
        &self,
        enc: &mut wgpu::CommandEncoder,
        entry: &str,
        params: &Params,
        pbuf: &wgpu::Buffer,
        bufs: [&wgpu::Buffer; 3],
    ) -> Result<(), GpuError> {
        self.gpu
            .queue
            .write_buffer(pbuf, 0, bytemuck::bytes_of(params));
        let bind = self
            .kernel
            .bind(&self.gpu, &[pbuf, bufs[0], bufs[1], bufs[2]]);
        self.kernel
            .dispatch(enc, entry, &bind, self.groups(params.count)?);
        Ok(())
    }

    /// Check that a block of `voxels` f32 values fits this device.
    fn check_size(&self, voxels: usize) -> Result<(), GpuError> {
        let limit = (self.gpu.max_storage_binding() / 4).min(u32::MAX as u64);
        if voxels as u64 > limit {
            return Err(GpuError::Limit {
                what: "filter block (f32 voxels)".into(),
                got: voxels as u64,
                limit,
            });
        }
        Ok(())
    }

    /// Run one element-wise or correlation kernel on fresh buffers and read
    /// its `out_len` results back (the one-off form the twin tests and the
    /// benchmark use; [`DeviceFilter`] keeps its buffers).
    fn run_once(
        &self,
        entry: &str,
        params: Params,
        weights: &[f32],
        src: &[f32],
        dst: Option<&[f32]>,
        out_len: usize,
    ) -> Result<Vec<f32>, GpuError> {
        let g = &self.gpu;
        self.check_size(src.len().max(out_len))?;
        let pbuf = g.uniform_buffer("filter params", &params);
        let w = g.storage_buffer("filter weights", weights);
        let s = g.storage_buffer("filter src", src);
        let d = match dst {
            Some(v) => g.storage_buffer("filter dst", v),
            None => g.storage_buffer_zeroed("filter dst", out_len as u64 * 4),
        };
        let mut enc = g.device.create_command_encoder(&Default::default());
        self.record(&mut enc, entry, &params, &pbuf, [&w, &s, &d])?;
        g.queue.submit([enc.finish()]);
        let b = g.read_back(entry, &d, out_len as u64 * 4)?;
        Ok(bytemuck::pod_collect_to_vec(&b))
    }

    /// The device's `correlate_valid` (twin of
    /// [`kernels::correlate_valid`](crate::kernels::correlate_valid) in f32).
    pub fn correlate_valid(
        &self,
        data: &[f32],
        dims: [usize; 3],
        axis: usize,
        w: &[f32],
    ) -> Result<(Vec<f32>, [usize; 3]), GpuError> {
        assert_eq!(data.len(), dims.iter().product::<usize>());
        assert!(w.len() % 2 == 1 && dims[axis] + 1 >= w.len());
        let (p, od) = Params::pass(dims, axis, w.len(), 0);
        let n = od.iter().product();
        if n == 0 {
            return Ok((vec![], od));
        }
        Ok((self.run_once("correlate_valid", p, w, data, None, n)?, od))
    }

    /// The device's `sum_squares`: `acc + v²` (`v²` for the first
    /// component, `acc = None`).
    pub fn sum_squares(&self, acc: Option<&[f32]>, v: &[f32]) -> Result<Vec<f32>, GpuError> {
        let mut p = Params::flat(v.len());
        p.first = acc.is_none() as u32;
        if let Some(a) = acc {
            assert_eq!(a.len(), v.len());
        }
        self.run_once("sum_squares", p, &[], v, acc, v.len())
    }

    /// The device's `square_root`.
    pub fn square_root(&self, v: &[f32]) -> Result<Vec<f32>, GpuError> {
        self.run_once(
            "square_root",
            Params::flat(v.len()),
            &[],
            &[],
            Some(v),
            v.len(),
        )
    }

    /// The device's `threshold`: 1 where `v > t`.
    pub fn threshold(&self, v: &[f32], t: f64) -> Result<Vec<f32>, GpuError> {
        let mut p = Params::flat(v.len());
        (p.lo, _) = threshold_bounds(&Filter::Threshold(t)).unwrap();
        self.run_once("threshold", p, &[], v, None, v.len())
    }

    /// The device's `window`: 1 where `lo <= v <= hi`.
    pub fn window(&self, v: &[f32], lo: f64, hi: f64) -> Result<Vec<f32>, GpuError> {
        let mut p = Params::flat(v.len());
        (p.lo, p.hi) = threshold_bounds(&Filter::Window(lo, hi)).unwrap();
        self.run_once("window", p, &[], v, None, v.len())
    }
}

/// What a [`DeviceFilter`] records per block.
enum Plan {
    /// Per component, per axis `[z, y, x]`: the offset and length of the
    /// pass's weights in the weight buffer (`None`: an identity pass,
    /// skipped as on the CPU); `magnitude`: the components' squares are
    /// summed and rooted.
    Separable {
        comps: Vec<[Option<(u32, usize)>; 3]>,
        magnitude: bool,
    },
    Mask {
        entry: &'static str,
        lo: f32,
        hi: f32,
    },
}

/// One [`Filter`] on the device, with the buffers it reuses from block to
/// block (grown to the largest block seen).
pub struct DeviceFilter {
    k: Arc<FilterKernels>,
    filter: Filter,
    plan: Plan,
    weights: wgpu::Buffer,
    /// The padded input, two buffers for the passes, the magnitude's sum.
    input: Grown,
    ping: Grown,
    pong: Grown,
    acc: Grown,
    staging: Grown,
    /// One uniform buffer per dispatch of a block.
    params: Vec<wgpu::Buffer>,
}

impl DeviceFilter {
    pub fn new(k: Arc<FilterKernels>, filter: Filter) -> DeviceFilter {
        let g = &k.gpu;
        let mut w: Vec<f32> = vec![];
        let plan = match filter.components() {
            Some((cs, magnitude)) => {
                let comps = cs
                    .iter()
                    .map(|c| {
                        c.each_ref().map(|wa| {
                            if is_identity(wa) {
                                None
                            } else {
                                let at = w.len() as u32;
                                w.extend(wa.iter().map(|&v| v as f32));
                                Some((at, wa.len()))
                            }
                        })
                    })
                    .collect();
                Plan::Separable { comps, magnitude }
            }
            None => {
                let (lo, hi) = threshold_bounds(&filter).expect("a mask filter");
                let entry = match filter {
                    Filter::Threshold(_) => "threshold",
                    _ => "window",
                };
                Plan::Mask { entry, lo, hi }
            }
        };
        DeviceFilter {
            weights: g.storage_buffer("filter weights", &w),
            input: Grown::new(g, "filter input", STORAGE),
            ping: Grown::new(g, "filter ping", STORAGE),
            pong: Grown::new(g, "filter pong", STORAGE),
            acc: Grown::new(g, "filter sum", STORAGE),
            staging: Grown::new(
                g,
                "filter read-back",
                wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            ),
            params: vec![],
            k,
            filter,
            plan,
        }
    }

    pub fn filter(&self) -> &Filter {
        &self.filter
    }

    /// Compute the filter on a block padded by [`Filter::halo`] (`dims`:
    /// the padded dimensions): the device twin of `Filter::apply::<f32>`.
    /// Returns the values and their dimensions (`dims` less twice the
    /// halo).
    pub fn apply(
        &mut self,
        data: &[f32],
        dims: [usize; 3],
    ) -> Result<(Vec<f32>, [usize; 3]), GpuError> {
        let n_in: usize = dims.iter().product();
        assert_eq!(data.len(), n_in, "one value per voxel of the padded block");
        let h = self.filter.halo();
        assert!(
            (0..3).all(|a| dims[a] >= 2 * h[a]),
            "block thinner than the halo"
        );
        let od: [usize; 3] = [0, 1, 2].map(|a| dims[a] - 2 * h[a]);
        let n_out: usize = od.iter().product();
        if n_out == 0 {
            return Ok((vec![], od));
        }
        self.k.check_size(n_in)?;
        let k = self.k.clone();
        let g = &k.gpu;
        let bytes_in = n_in as u64 * 4;
        let bytes_out = n_out as u64 * 4;
        self.input.ensure(g, bytes_in);
        g.queue
            .write_buffer(&self.input.buf, 0, bytemuck::cast_slice(data));
        // The dispatches of the block: (entry, params, src, dst), buffers
        // named 0 = input, 1 = ping, 2 = pong, 3 = sum.
        let mut steps: Vec<(&str, Params, usize, usize)> = vec![];
        let result = match &self.plan {
            Plan::Separable { comps, magnitude } => {
                let mut result = 0;
                for (ci, comp) in comps.iter().enumerate() {
                    let (mut cur, mut d) = (0usize, dims);
                    for (axis, pass) in comp.iter().enumerate() {
                        let Some((w0, taps)) = *pass else { continue };
                        let dst = if cur == 1 { 2 } else { 1 };
                        let (p, nd) = Params::pass(d, axis, taps, w0);
                        steps.push(("correlate_valid", p, cur, dst));
                        (cur, d) = (dst, nd);
                    }
                    debug_assert_eq!(d, od);
                    if *magnitude {
                        let mut p = Params::flat(n_out);
                        p.first = (ci == 0) as u32;
                        steps.push(("sum_squares", p, cur, 3));
                        result = 3;
                    } else {
                        result = cur;
                    }
                }
                if *magnitude {
                    steps.push(("square_root", Params::flat(n_out), 0, 3));
                }
                result
            }
            Plan::Mask { entry, lo, hi } => {
                let mut p = Params::flat(n_out);
                (p.lo, p.hi) = (*lo, *hi);
                steps.push((entry, p, 0, 1));
                1
            }
        };
        if steps.iter().any(|s| s.3 == 1 || s.2 == 1) {
            self.ping.ensure(g, bytes_in);
        }
        if steps.iter().any(|s| s.3 == 2 || s.2 == 2) {
            self.pong.ensure(g, bytes_in);
        }
        if result == 3 {
            self.acc.ensure(g, bytes_out);
        }
        self.staging.ensure(g, bytes_out);
        while self.params.len() < steps.len() {
            self.params
                .push(g.uniform_buffer("filter params", &Params::default()));
        }
        let bufs = [
            &self.input.buf,
            &self.ping.buf,
            &self.pong.buf,
            &self.acc.buf,
        ];
        let mut enc = g.device.create_command_encoder(&Default::default());
        for (i, (entry, p, src, dst)) in steps.iter().enumerate() {
            k.record(
                &mut enc,
                entry,
                p,
                &self.params[i],
                [&self.weights, bufs[*src], bufs[*dst]],
            )?;
        }
        enc.copy_buffer_to_buffer(bufs[result], 0, &self.staging.buf, 0, bytes_out);
        g.queue.submit([enc.finish()]);
        let out = read_mapped(g, &self.staging.buf, bytes_out)?;
        Ok((out, od))
    }
}

/// Map the first `bytes` of `staging` (a MAP_READ buffer whose copy was
/// submitted), wait, and return them as f32.
fn read_mapped(g: &Gpu, staging: &wgpu::Buffer, bytes: u64) -> Result<Vec<f32>, GpuError> {
    let fail = |reason: String| GpuError::ReadBack {
        what: "filter block".into(),
        reason,
    };
    let (tx, rx) = std::sync::mpsc::channel();
    staging.map_async(wgpu::MapMode::Read, ..bytes, move |r| {
        let _ = tx.send(r);
    });
    g.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| fail(e.to_string()))?;
    rx.recv()
        .map_err(|e| fail(e.to_string()))?
        .map_err(|e| fail(e.to_string()))?;
    let view = staging
        .get_mapped_range(..bytes)
        .map_err(|e| fail(format!("{e:?}")))?;
    let out: Vec<f32> = bytemuck::pod_collect_to_vec(&view);
    drop(view);
    staging.unmap();
    Ok(out)
}

impl Filter {
    /// [`Filter::apply`] on the device, once (a [`DeviceFilter`] reuses its
    /// buffers across blocks).
    pub fn apply_device(
        &self,
        k: &Arc<FilterKernels>,
        data: &[f32],
        dims: [usize; 3],
    ) -> Result<Vec<f32>, GpuError> {
        Ok(DeviceFilter::new(k.clone(), self.clone())
            .apply(data, dims)?
            .0)
    }

    /// The largest `|output|` per unit of `max |input|`: `Π_axes Σ|w|` of
    /// the one component, or the components' gains combined in quadrature
    /// for a magnitude; 1 for masks.
    pub fn gain(&self) -> f64 {
        match self.components() {
            None => 1.0,
            Some((cs, _)) => cs
                .iter()
                .map(|c| {
                    c.iter()
                        .map(|w| w.iter().map(|v| v.abs()).sum::<f64>())
                        .product::<f64>()
                        .powi(2)
                })
                .sum::<f64>()
                .sqrt(),
        }
    }

    /// The largest difference between this stage's value on the device and
    /// on the CPU, for inputs of at most `max_abs_input` in magnitude (see
    /// the module's documentation): `2·m·2⁻²⁴·gain·max_abs_input`. Masks: 0
    /// (equal for equal inputs).
    pub fn device_tolerance(&self, max_abs_input: f64) -> f64 {
        let Some((cs, magnitude)) = self.components() else {
            return 0.0;
        };
        let taps: usize = cs[0].iter().map(|w| w.len() + 1).sum();
        let m = taps + 2 + if magnitude { 4 } else { 0 };
        2.0 * m as f64 * 2f64.powi(-24) * self.gain() * max_abs_input
    }
}
