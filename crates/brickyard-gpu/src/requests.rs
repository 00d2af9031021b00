//! Request collection and the capped request list on the device: twins of
//! [`brickyard_cache::bookkeeping::RequestTable`] and
//! [`brickyard_cache::bookkeeping::prioritize`]. Only the request list
//! (`cap` entries of 8 bytes) is read back.

use crate::context::{Gpu, GpuError};
use crate::kernel::{Binding, Kernel};
use brickyard_cache::bookkeeping::{BrickIds, NO_BRICK};

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    buckets: u32,
    count: u32,
    levels: u32,
    pad: u32,
}

/// The request table of one frame on the device.
pub struct RequestTableGpu {
    kernel: Kernel,
    buckets: u32,
    levels: u32,
    keys: wgpu::Buffer,
    counts: wgpu::Buffer,
    dropped: wgpu::Buffer,
    level_starts: wgpu::Buffer,
    sorted: wgpu::Buffer,
    /// Bound as the misses of the sort pass, which reads none.
    no_misses: wgpu::Buffer,
    /// The host→device bytes of the last [`insert`](Self::insert) and the
    /// device→host bytes of the last [`list`](Self::list).
    pub uploaded: u64,
    pub downloaded: u64,
}

/// WGSL adding misses to a request table (`request_add(id, samples,
/// buckets)`); the including shader declares `keys`, `counts` and
/// `dropped` as in `requests.wgsl`.
pub const REQUEST_INSERT_WGSL: &str = include_str!("shaders/request_insert.wgsl");

/// Largest table one workgroup sorts in reasonable time.
pub const MAX_BUCKETS: usize = 1 << 16;

impl RequestTableGpu {
    /// A table of `buckets` buckets (rounded up to a power of two, at most
    /// [`MAX_BUCKETS`]) for the bricks of `ids`.
    pub fn new(gpu: &Gpu, ids: &BrickIds, buckets: usize) -> RequestTableGpu {
        use Binding::*;
        let n = buckets.clamp(1, MAX_BUCKETS).next_power_of_two() as u32;
        let starts = ids.level_starts();
        let kernel = Kernel::new(
            gpu,
            "requests",
            &format!(
                "{}\n{}",
                include_str!("shaders/requests.wgsl"),
                REQUEST_INSERT_WGSL
            ),
            &["insert", "sort"],
            &[
                Uniform, Read, ReadWrite, ReadWrite, ReadWrite, Read, ReadWrite,
            ],
        );
        RequestTableGpu {
            kernel,
            buckets: n,
            levels: (starts.len() - 1) as u32,
            keys: gpu.storage_buffer("request keys", &vec![NO_BRICK; n as usize]),
            counts: gpu.storage_buffer_zeroed("request counts", n as u64 * 4),
            dropped: gpu.storage_buffer_zeroed("requests dropped, occupied", 8),
            level_starts: gpu.storage_buffer("level starts", &starts),
            sorted: gpu.storage_buffer_zeroed("requests sorted", n as u64 * 8),
            no_misses: gpu.storage_buffer_zeroed("no misses", 8),
            uploaded: 0,
            downloaded: 0,
        }
    }

    pub fn buckets(&self) -> usize {
        self.buckets as usize
    }

    /// The table's keys, counts and drop counter, for kernels that add
    /// misses themselves.
    pub fn buffers(&self) -> [&wgpu::Buffer; 3] {
        [&self.keys, &self.counts, &self.dropped]
    }

    /// Empty the table (start of a frame).
    pub fn clear(&mut self, gpu: &Gpu) {
        let n = self.buckets as usize;
        gpu.queue
            .write_buffer(&self.keys, 0, bytemuck::cast_slice(&vec![NO_BRICK; n]));
        gpu.queue
            .write_buffer(&self.counts, 0, bytemuck::cast_slice(&vec![0u32; n]));
        gpu.queue.write_buffer(&self.dropped, 0, &[0; 8]);
    }

    fn bind(&self, gpu: &Gpu, params: &wgpu::Buffer, misses: &wgpu::Buffer) -> wgpu::BindGroup {
        self.kernel.bind(
            gpu,
            &[
                params,
                misses,
                &self.keys,
                &self.counts,
                &self.dropped,
                &self.level_starts,
                &self.sorted,
            ],
        )
    }

    /// Add misses `(brick id, samples)` from the host (consumers on the
    /// device add theirs in their own kernels, the same way).
    pub fn insert(&mut self, gpu: &Gpu, misses: &[[u32; 2]]) {
        if misses.is_empty() {
            return;
        }
        let count = misses.len() as u32;
        let params = self.params(gpu, count);
        let buf = gpu.storage_buffer("misses", misses);
        self.uploaded = std::mem::size_of_val(misses) as u64;
        let bind = self.bind(gpu, &params, &buf);
        let groups = count.div_ceil(256);
        let max = gpu.limits.max_compute_workgroups_per_dimension;
        let (gx, gy) = (groups.min(max), groups.div_ceil(max));
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        self.kernel.dispatch(&mut enc, "insert", &bind, [gx, gy, 1]);
        gpu.queue.submit([enc.finish()]);
    }

    fn params(&self, gpu: &Gpu, count: u32) -> wgpu::Buffer {
        gpu.uniform_buffer(
            "request params",
            &Params {
                buckets: self.buckets,
                count,
                levels: self.levels,
                pad: 0,
            },
        )
    }

    /// The request list: at most `cap` (brick id, samples), most wanted
    /// first (see [`brickyard_cache::bookkeeping::prioritize`]), and the
    /// number of misses dropped because the table was full.
    pub fn list(&mut self, gpu: &Gpu, cap: usize) -> Result<(Vec<(u32, u32)>, u64), GpuError> {
        pollster::block_on(self.list_async(gpu, cap))
    }

    /// [`list`](Self::list) without blocking (the browser's read-backs).
    pub async fn list_async(
        &mut self,
        gpu: &Gpu,
        cap: usize,
    ) -> Result<(Vec<(u32, u32)>, u64), GpuError> {
        let params = self.params(gpu, 0);
        let bind = self.bind(gpu, &params, &self.no_misses);
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        self.kernel.dispatch(&mut enc, "sort", &bind, [1, 1, 1]);
        gpu.queue.submit([enc.finish()]);
        let head = gpu
            .read_u32_async("dropped requests", &self.dropped, 2)
            .await?;
        let (dropped, occupied) = (head[0] as u64, head[1] as usize);
        let n = cap.min(occupied);
        let words = gpu
            .read_u32_async("request list", &self.sorted, n * 2)
            .await?;
        self.downloaded = (n * 8 + 8) as u64;
        let list = words.chunks_exact(2).map(|w| (w[0], w[1])).collect();
        Ok((list, dropped))
    }
}
