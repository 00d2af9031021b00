//! LRU order by order-preserving compaction on the device: the twin of
//! [`brickyard_cache::bookkeeping::compact_lru`].

use crate::context::{Gpu, GpuError};
use crate::kernel::{Binding, Kernel};

/// Entries per workgroup (256 invocations × 4).
const BLOCK: u32 = 1024;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    n: u32,
    frame: u32,
    blocks: u32,
    base: u32,
    stride: u32,
    word: u32,
    pad: [u32; 2],
}

/// The compaction kernel (three passes: block scans, scan of the block
/// sums, scatter).
pub struct LruCompaction {
    kernel: Kernel,
}

/// Device buffers of one LRU list: the order (most recently used first)
/// and, per slot, the last frame it was used in.
pub struct LruBuffers {
    pub n: u32,
    pub order: wgpu::Buffer,
    pub usage: wgpu::Buffer,
    /// Scratch: per-entry prefix, per-block sums, the compacted order.
    prefix: wgpu::Buffer,
    block_sums: wgpu::Buffer,
    out: wgpu::Buffer,
}

impl LruBuffers {
    /// Buffers for `order` (a permutation of `0..n`) and `usage` (`n`
    /// frame stamps).
    pub fn new(gpu: &Gpu, order: &[u32], usage: &[u32]) -> Result<LruBuffers, GpuError> {
        assert_eq!(order.len(), usage.len(), "one usage stamp per slot");
        Self::build(gpu, order, Some(usage))
    }

    fn build(gpu: &Gpu, order: &[u32], usage: Option<&[u32]>) -> Result<LruBuffers, GpuError> {
        let n = order.len() as u32;
        let blocks = n.div_ceil(BLOCK);
        let max = gpu.limits.max_compute_workgroups_per_dimension;
        if blocks > max {
            return Err(GpuError::Limit {
                what: "LRU slots / 1024".into(),
                got: blocks as u64,
                limit: max as u64,
            });
        }
        Ok(LruBuffers {
            n,
            order: gpu.storage_buffer("lru order", order),
            usage: match usage {
                Some(u) => gpu.storage_buffer("lru usage", u),
                None => gpu.storage_buffer_zeroed("lru usage (unused)", 16),
            },
            prefix: gpu.storage_buffer_zeroed("lru prefix", n as u64 * 4),
            block_sums: gpu.storage_buffer_zeroed("lru block sums", (blocks as u64 + 1) * 4),
            out: gpu.storage_buffer_zeroed("lru out", n as u64 * 4),
        })
    }

    /// Buffers for `order` whose stamps live elsewhere (see
    /// [`LruCompaction::record_with`]).
    pub fn order_only(gpu: &Gpu, order: &[u32]) -> Result<LruBuffers, GpuError> {
        Self::build(gpu, order, None)
    }

    /// Record a copy of the number of slots the last recorded compaction
    /// found used (its total after the last block) to `dst` at byte
    /// `offset`.
    pub fn copy_used_count(&self, enc: &mut wgpu::CommandEncoder, dst: &wgpu::Buffer, offset: u64) {
        if self.n == 0 {
            return;
        }
        let blocks = self.n.div_ceil(BLOCK) as u64;
        enc.copy_buffer_to_buffer(&self.block_sums, blocks * 4, dst, offset, 4);
    }

    /// The order, read back (for tests and reports).
    pub fn read_order(&self, gpu: &Gpu) -> Result<Vec<u32>, GpuError> {
        gpu.read_u32("LRU order", &self.order, self.n as usize)
    }
}

impl LruCompaction {
    pub fn new(gpu: &Gpu) -> LruCompaction {
        use Binding::*;
        LruCompaction {
            kernel: Kernel::new(
                gpu,
                "lru",
                include_str!("shaders/lru.wgsl"),
                &["scan_blocks", "scan_sums", "scatter"],
                &[Uniform, Read, Read, ReadWrite, ReadWrite, ReadWrite],
            ),
        }
    }

    /// Record the compaction of `b` for `frame` into `enc`: afterwards
    /// `b.order` holds the slots used in `frame` first, then the others,
    /// each group in its previous order.
    pub fn record(&self, gpu: &Gpu, enc: &mut wgpu::CommandEncoder, b: &LruBuffers, frame: u32) {
        self.record_with(gpu, enc, b, &b.usage, [0, 1, 0], frame)
    }

    /// [`record`](Self::record) with the stamps in another buffer: slot
    /// `i`'s stamp is word `stride · (base + i) + word` of `usage`, where
    /// `at = [base, stride, word]`.
    pub fn record_with(
        &self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        b: &LruBuffers,
        usage: &wgpu::Buffer,
        at: [u32; 3],
        frame: u32,
    ) {
        let [base, stride, word] = at;
        if b.n == 0 {
            return;
        }
        let blocks = b.n.div_ceil(BLOCK);
        let params = gpu.uniform_buffer(
            "lru params",
            &Params {
                n: b.n,
                frame,
                blocks,
                base,
                stride,
                word,
                pad: [0; 2],
            },
        );
        let bind = self.kernel.bind(
            gpu,
            &[&params, &b.order, usage, &b.prefix, &b.block_sums, &b.out],
        );
        self.kernel
            .dispatch(enc, "scan_blocks", &bind, [blocks, 1, 1]);
        self.kernel.dispatch(enc, "scan_sums", &bind, [1, 1, 1]);
        self.kernel.dispatch(enc, "scatter", &bind, [blocks, 1, 1]);
        enc.copy_buffer_to_buffer(&b.out, 0, &b.order, 0, b.n as u64 * 4);
    }

    /// [`record`](Self::record) and submit.
    pub fn run(&self, gpu: &Gpu, b: &LruBuffers, frame: u32) {
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        self.record(gpu, &mut enc, b, frame);
        gpu.queue.submit([enc.finish()]);
    }
}
