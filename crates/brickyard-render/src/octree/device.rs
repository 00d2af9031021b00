//! The residency octree on the device: its buffers (leaf counters, masks,
//! node ranges) and the passes of `octree.wgsl` that keep them, twins of
//! the CPU model's (`Octree::pass` for map/evict events, `Octree::new`'s
//! ranges from the store's per-brick statistics). The host filters the
//! events ([`Octree::effective`]) and sends 16 bytes per event.

use super::{node_count, Event, Octree};
use brickyard_cache::ranges::BrickRanges;
use brickyard_gpu::context::{Gpu, GpuError};
use brickyard_gpu::kernel::{Binding, Kernel};

const NONE: u32 = u32::MAX;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    depth: u32,
    channels: u32,
    levels: u32,
    count: u32,
    d: u32,
    pad: [u32; 3],
    brick: [u32; 4],
    dims: [[u32; 4]; 32],
    /// Per level: its ratio to level 0 (`Octree::span`'s denominator).
    ratio: [[u32; 4]; 32],
}

/// The octree's buffers on the device and its update passes.
pub struct DeviceOctree {
    kernel: Kernel,
    params: Params,
    uniform: wgpu::Buffer,
    events: wgpu::Buffer,
    event_capacity: usize,
    counts: wgpu::Buffer,
    /// `[node][channel]` masks (as on the host).
    pub masks: wgpu::Buffer,
    brick_ranges: wgpu::Buffer,
    /// `[node][channel][level]` ranges (as on the host).
    pub ranges: wgpu::Buffer,
    bind: wgpu::BindGroup,
    nodes: usize,
    leaves: usize,
}

fn groups(n: usize) -> [u32; 3] {
    let g = n.div_ceil(64).max(1) as u32;
    [g.min(65535), g.div_ceil(65535), 1]
}

impl DeviceOctree {
    /// The device twin of `tree` (its counters and masks as they are
    /// now); node ranges computed on the device from `ranges`, the store's
    /// per-brick statistics (see [`DeviceOctree::read`] to compare). An
    /// error when a buffer would pass the device's binding limit.
    pub fn new(
        gpu: &Gpu,
        tree: &Octree,
        ranges: Option<&BrickRanges>,
    ) -> Result<DeviceOctree, GpuError> {
        let nl = tree.levels();
        let limit = gpu.max_storage_binding();
        let nodes = node_count(tree.depth) as u64;
        let leaves = 1u64 << (3 * tree.depth);
        let (ch, l) = (tree.channels as u64, nl as u64);
        for (what, bytes) in [
            ("node ranges", nodes * ch * l * 8),
            ("leaf counters", leaves * ch * l * 4),
            ("masks", nodes * ch * 4),
        ] {
            if bytes > limit {
                return Err(GpuError::Limit {
                    what: format!(
                        "the residency octree's {what} on the device, bytes (depth {} with {} channels: choose a smaller --octree-depth)",
                        tree.depth, tree.channels
                    ),
                    got: bytes,
                    limit,
                });
            }
        }
        let mut params = Params {
            depth: tree.depth,
            channels: tree.channels as u32,
            levels: nl as u32,
            count: 0,
            d: 0,
            pad: [0; 3],
            brick: [
                tree.brick[0] as u32,
                tree.brick[1] as u32,
                tree.brick[2] as u32,
                0,
            ],
            dims: [[0; 4]; 32],
            ratio: [[0; 4]; 32],
        };
        let mut flat: Vec<[f32; 2]> = vec![];
        for l in 0..nl {
            let d = tree.dims[l];
            let off = match ranges.and_then(|r| r.level(l)) {
                Some(r) if r.channels >= tree.channels => {
                    let o = flat.len() as u32;
                    let per = r.bricks.iter().product::<u64>() as usize;
                    flat.extend_from_slice(&r.range[..per * tree.channels]);
                    o
                }
                _ => NONE,
            };
            params.dims[l] = [d[0] as u32, d[1] as u32, d[2] as u32, off];
            let r = tree.span(l).1;
            params.ratio[l] = [r[0] as u32, r[1] as u32, r[2] as u32, 0];
        }
        let kernel = Kernel::new(
            gpu,
            "octree",
            include_str!("../octree.wgsl"),
            &[
                "apply_events",
                "leaf_masks",
                "or_up",
                "leaf_ranges",
                "union_up",
            ],
            &[
                Binding::Uniform,
                Binding::Read,
                Binding::ReadWrite,
                Binding::ReadWrite,
                Binding::Read,
                Binding::ReadWrite,
            ],
        );
        let uniform = gpu.uniform_buffer("octree params", &params);
        let event_capacity = 256;
        let events = gpu.storage_buffer_zeroed("octree events", event_capacity as u64 * 16);
        let counts = gpu.storage_buffer("octree counts", &tree.count);
        let masks = gpu.storage_buffer("octree masks", &tree.mask);
        let brick_ranges = gpu.storage_buffer("brick ranges", &flat);
        let ranges = gpu.storage_buffer_zeroed(
            "octree ranges",
            (node_count(tree.depth) * tree.channels * nl * 8) as u64,
        );
        let bind = kernel.bind(
            gpu,
            &[&uniform, &events, &counts, &masks, &brick_ranges, &ranges],
        );
        let mut o = DeviceOctree {
            kernel,
            params,
            uniform,
            events,
            event_capacity,
            counts,
            masks,
            brick_ranges,
            ranges,
            bind,
            nodes: node_count(tree.depth),
            leaves: 1 << (3 * tree.depth),
        };
        // Ranges: leaves, then every depth up to the root.
        let per = tree.channels * nl;
        o.run(gpu, "leaf_ranges", 0, 0, o.leaves * per);
        for d in (0..tree.depth).rev() {
            let n = 1usize << (3 * d);
            o.run(gpu, "union_up", n as u32, d, n * per);
        }
        Ok(o)
    }

    fn run(&mut self, gpu: &Gpu, entry: &str, count: u32, d: u32, invocations: usize) {
        self.params.count = count;
        self.params.d = d;
        gpu.queue
            .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&self.params));
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        self.kernel
            .dispatch(&mut enc, entry, &self.bind, groups(invocations));
        gpu.queue.submit([enc.finish()]);
    }

    /// The update pass for `events` (already [`Octree::effective`]):
    /// counters, leaf masks, then the inner masks depth by depth.
    pub fn update(&mut self, gpu: &Gpu, events: &[Event]) {
        if events.len() > self.event_capacity {
            self.event_capacity = events.len().next_power_of_two();
            self.events =
                gpu.storage_buffer_zeroed("octree events", self.event_capacity as u64 * 16);
            self.bind = self.kernel.bind(
                gpu,
                &[
                    &self.uniform,
                    &self.events,
                    &self.counts,
                    &self.masks,
                    &self.brick_ranges,
                    &self.ranges,
                ],
            );
        }
        if events.is_empty() {
            return;
        }
        let words: Vec<[u32; 4]> = events
            .iter()
            .map(|e| {
                [
                    e.key.level as u32 | (e.key.channel as u32) << 8 | (e.mapped as u32) << 31,
                    e.key.brick[0],
                    e.key.brick[1],
                    e.key.brick[2],
                ]
            })
            .collect();
        gpu.queue
            .write_buffer(&self.events, 0, bytemuck::cast_slice(&words));
        let ch = self.params.channels as usize;
        self.run(gpu, "apply_events", events.len() as u32, 0, events.len());
        self.run(gpu, "leaf_masks", 0, 0, self.leaves * ch);
        for d in (0..self.params.depth).rev() {
            let n = 1usize << (3 * d);
            self.run(gpu, "or_up", n as u32, d, n * ch);
        }
    }

    /// Masks, leaf counters and node ranges, read back (for tests).
    #[allow(clippy::type_complexity)]
    pub fn read(&self, gpu: &Gpu) -> Result<(Vec<u32>, Vec<u32>, Vec<[f32; 2]>), GpuError> {
        let ch = self.params.channels as usize;
        let nl = self.params.levels as usize;
        let masks = gpu.read_u32("octree masks", &self.masks, self.nodes * ch)?;
        let counts = gpu.read_u32("octree counts", &self.counts, self.leaves * ch * nl)?;
        let r = gpu.read_u32("octree ranges", &self.ranges, self.nodes * ch * nl * 2)?;
        let ranges = r
            .chunks(2)
            .map(|p| [f32::from_bits(p[0]), f32::from_bits(p[1])])
            .collect();
        Ok((masks, counts, ranges))
    }
}
