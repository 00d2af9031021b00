//! The virtual memory's page tables and brick pool on the device, and the
//! device's page-table walk and sampler (twins of
//! [`VirtualMemory::entry_of`] and [`VirtualMemory::sample_at`]).
//!
//! Who decides updates: either the device ([`crate::update::DeviceCache`]
//! chooses slots and references bricks in these tables), or the host's
//! [`VirtualMemory`], whose changes [`DeviceVm::sync`] carries over: the
//! bricks written and the entries set (16 bytes each), applied on the
//! device by a scatter kernel.

use crate::context::{Gpu, GpuError};
use crate::kernel::{Binding, Kernel};
use crate::pool::DevicePool;
use brickyard_cache::vm::VirtualMemory;
use brickyard_core::DType;

/// Levels and page-table depths the device layout has room for.
pub const MAX_LEVELS: usize = 16;
pub const MAX_NMAX: usize = 7;

/// The layout uniform (see `vm.wgsl`); vectors are `[z, y, x, _]`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct Layout {
    pub(crate) levels: u32,
    pub(crate) nmax: u32,
    pub(crate) channels: u32,
    pub(crate) dir_len: u32,
    pub(crate) apron: u32,
    pub(crate) scale: f32,
    pub(crate) count: u32,
    pub(crate) value_kind: u32,
    pub(crate) dir_dims: [u32; 4],
    pub(crate) brick_grid: [u32; 4],
    pub(crate) dev_grid: [u32; 4],
    pub(crate) padded: [u32; 4],
    pub(crate) dims: [[u32; 4]; MAX_LEVELS],
    pub(crate) dir_base: [[u32; 4]; MAX_LEVELS],
    pub(crate) span: [[u32; 4]; 8],
    pub(crate) block: [[u32; 4]; 8],
    pub(crate) pt_grid: [[u32; 4]; 8],
    pub(crate) table_off: [[u32; 4]; 8],
    /// Per slot set (0: the brick pool, n: the cache of intermediate level
    /// n): `.x` its first slot in the per-slot arrays of all sets (stamps,
    /// owners), `.y` its slots.
    pub(crate) set_base: [[u32; 4]; 8],
}

/// One query of the walk or the sampler: level, channel, voxel (base)
/// `[z, y, x]` and trilinear fractions `[z, y, x]`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Query {
    pub level: u32,
    pub channel: u32,
    pub pad: [u32; 2],
    pub voxel: [u32; 4],
    pub frac: [f32; 4],
}

impl Query {
    pub fn new(level: usize, channel: usize, voxel: [u64; 3], frac: [f32; 3]) -> Query {
        Query {
            level: level as u32,
            channel: channel as u32,
            pad: [0; 2],
            voxel: [voxel[0] as u32, voxel[1] as u32, voxel[2] as u32, 0],
            frac: [frac[0], frac[1], frac[2], 0.0],
        }
    }
}

/// What the walk found for a query: the entry `(word, value)` and, for a
/// resident brick, its pool slot.
pub type Walked = ([u32; 2], Option<u32>);

/// `source` after `vm_common.wgsl` (the layout, bindings 0–2, the walk and
/// the sampler), for kernels that read the virtual memory.
pub fn with_vm_common(source: &str) -> String {
    format!("{}\n{}", include_str!("shaders/vm_common.wgsl"), source)
}

/// Bindings 0–2 of a kernel built with [`with_vm_common`].
pub struct VmResources<'a> {
    pub layout: wgpu::Buffer,
    pub entries: &'a wgpu::Buffer,
    pub pool: wgpu::TextureView,
}

/// What one [`DeviceVm::sync`] carried to the device.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SyncReport {
    pub entries: usize,
    pub bricks: usize,
    /// Host→device bytes: bricks (as texels) and entry updates.
    pub bytes: u64,
}

/// The device side of one [`VirtualMemory`].
pub struct DeviceVm {
    kernel: Kernel,
    layout: Layout,
    pub pool: DevicePool,
    entries: wgpu::Buffer,
    n_entries: u32,
    /// Bound where a pass reads nothing (updates, queries, results): two,
    /// as one buffer cannot be bound read-only and writable at once.
    unused: [wgpu::Buffer; 2],
}

fn v4(d: [u64; 3]) -> [u32; 4] {
    [d[0] as u32, d[1] as u32, d[2] as u32, 0]
}

impl DeviceVm {
    /// Mirror `vm` on the device (its current page tables and resident
    /// bricks) and turn on its change tracking for [`sync`](Self::sync).
    pub fn new(gpu: &Gpu, vm: &mut VirtualMemory) -> Result<(DeviceVm, SyncReport), GpuError> {
        let lay = vm.layout();
        let nmax = lay.nmax();
        let too_deep = |what: &str, got: usize, limit: usize| GpuError::Limit {
            what: what.into(),
            got: got as u64,
            limit: limit as u64,
        };
        if lay.num_levels() > MAX_LEVELS {
            return Err(too_deep("resolution levels", lay.num_levels(), MAX_LEVELS));
        }
        if nmax > MAX_NMAX {
            return Err(too_deep("page-table levels", nmax, MAX_NMAX));
        }
        let padded = vm.padded().map(|p| p as u32);
        let mut pool = DevicePool::new(gpu, vm.dtype(), padded, vm.pool_slots() as u32)?;
        pool.enable_cells(gpu, vm.cell_grid().count.map(|c| c as u32));
        let offsets = vm.table_offsets();
        let mut l = Layout {
            levels: lay.num_levels() as u32,
            nmax: nmax as u32,
            channels: vm.channels() as u32,
            dir_len: vm.dir_len() as u32,
            apron: vm.config().apron as u32,
            scale: pool.format.scale,
            count: 0,
            value_kind: match vm.dtype() {
                DType::U8 | DType::U16 | DType::U32 => 0,
                DType::I8 | DType::I16 | DType::I32 => 1,
                DType::F32 | DType::F64 => 2,
            },
            dir_dims: v4(lay.dir_dims),
            brick_grid: {
                let g = vm.slot_grid(None);
                [g[0], g[1], g[2], 0]
            },
            dev_grid: {
                let g = pool.grid();
                [g[0], g[1], g[2], 0]
            },
            padded: [padded[0], padded[1], padded[2], 0],
            ..bytemuck::Zeroable::zeroed()
        };
        for (i, d) in lay.levels.iter().enumerate() {
            l.dims[i] = v4(*d);
            l.dir_base[i] = v4(lay.dir_base[i]);
        }
        for n in 0..=nmax {
            l.span[n] = v4(lay.entry_span(n));
            if n >= 1 {
                l.block[n] = v4(lay.block(n));
            }
            if n >= 1 && n < nmax {
                let g = vm.slot_grid(Some(n));
                l.pt_grid[n] = [g[0], g[1], g[2], vm.pt_block_len(n) as u32];
            }
        }
        for (n, &o) in offsets.iter().take(nmax).enumerate() {
            l.table_off[n][0] = o;
        }
        l.set_base[0] = [0, vm.pool_slots() as u32, 0, 0];
        for n in 1..nmax {
            let blocks = (offsets[n + 1] - offsets[n]) / vm.pt_block_len(n) as u32;
            let prev = l.set_base[n - 1];
            l.set_base[n] = [prev[0] + prev[1], blocks, 0, 0];
        }
        let words: Vec<[u32; 2]> = vm
            .tables()
            .iter()
            .flat_map(|t| t.iter().map(|e| [e.word, e.value]))
            .collect();
        let limit = gpu.max_storage_binding();
        if words.len() as u64 * 8 > limit {
            return Err(GpuError::Limit {
                what: "page tables (bytes; fewer page-table cache blocks)".into(),
                got: words.len() as u64 * 8,
                limit,
            });
        }
        let entries = gpu.storage_buffer("page tables", &words);
        let mut bytes = words.len() as u64 * 8;
        let resident = vm.resident_slots();
        let bricks: Vec<_> = resident
            .iter()
            .map(|&s| (s, vm.slot_voxels(s), vm.cell_ranges(s)))
            .collect();
        pool.write_many(gpu, &bricks);
        bytes += pool.take_uploaded();
        vm.track_changes();
        use Binding::*;
        let kernel = Kernel::new(
            gpu,
            "vm",
            &with_vm_common(include_str!("shaders/vm.wgsl")),
            &["apply", "lookup", "sample"],
            &[Uniform, ReadWrite, Texture3d, Read, Read, ReadWrite],
        );
        let dvm = DeviceVm {
            kernel,
            layout: l,
            pool,
            entries,
            n_entries: words.len() as u32,
            unused: [0, 1].map(|_| gpu.storage_buffer_zeroed("unused", 64)),
        };
        let report = SyncReport {
            entries: words.len(),
            bricks: resident.len(),
            bytes,
        };
        Ok((dvm, report))
    }

    /// Entries in all page tables.
    pub fn entries(&self) -> u32 {
        self.n_entries
    }

    /// The page tables on the device (`(word, value)` pairs, the tables of
    /// [`VirtualMemory::tables`] one after the other).
    pub fn entries_buffer(&self) -> &wgpu::Buffer {
        &self.entries
    }

    pub(crate) fn layout(&self) -> &Layout {
        &self.layout
    }

    /// Slots of every set together: the brick pool, then the cache of
    /// each intermediate level (the length of per-slot arrays such as the
    /// renderer's usage stamps).
    pub fn all_slots(&self) -> u32 {
        let n = self.layout.nmax as usize;
        let last = self.layout.set_base[n - 1];
        last[0] + last[1]
    }

    /// The page tables, read back (for tests).
    pub fn read_entries(&self, gpu: &Gpu) -> Result<Vec<[u32; 2]>, GpuError> {
        let w = gpu.read_u32("page tables", &self.entries, self.n_entries as usize * 2)?;
        Ok(w.chunks_exact(2).map(|c| [c[0], c[1]]).collect())
    }

    fn bind(
        &self,
        gpu: &Gpu,
        count: usize,
        updates: &wgpu::Buffer,
        queries: &wgpu::Buffer,
        results: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        let res = self.resources(gpu, count as u32);
        self.kernel.bind_resources(
            gpu,
            vec![
                res.layout.as_entire_binding(),
                self.entries.as_entire_binding(),
                wgpu::BindingResource::TextureView(&res.pool),
                updates.as_entire_binding(),
                queries.as_entire_binding(),
                results.as_entire_binding(),
            ],
        )
    }

    /// What a kernel built on `vm_common.wgsl` binds at 0–2: the layout
    /// uniform (with `count`), the page tables and the pool.
    pub fn resources(&self, gpu: &Gpu, count: u32) -> VmResources<'_> {
        let mut l = self.layout;
        l.count = count;
        VmResources {
            layout: gpu.uniform_buffer("vm layout", &l),
            entries: &self.entries,
            pool: self.pool.texture.create_view(&Default::default()),
        }
    }

    /// Carry `vm`'s changes since the last sync to the device: the bricks
    /// written into the pool and the page-table entries set.
    pub fn sync(&mut self, gpu: &Gpu, vm: &mut VirtualMemory) -> SyncReport {
        let ch = vm.take_changes();
        let bricks: Vec<_> = ch
            .slots
            .iter()
            .map(|&s| (s, vm.slot_voxels(s), vm.cell_ranges(s)))
            .collect();
        self.pool.write_many(gpu, &bricks);
        let mut bytes = self.pool.take_uploaded();
        if !ch.entries.is_empty() {
            let ups: Vec<[u32; 4]> = ch
                .entries
                .iter()
                .map(|(i, e)| [*i, e.word, e.value, 0])
                .collect();
            bytes += ups.len() as u64 * 16;
            let buf = gpu.storage_buffer("entry updates", &ups);
            let [queries, results] = &self.unused;
            let bind = self.bind(gpu, ups.len(), &buf, queries, results);
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            let groups = (ups.len() as u32).div_ceil(64);
            self.kernel
                .dispatch(&mut enc, "apply", &bind, [groups, 1, 1]);
            gpu.queue.submit([enc.finish()]);
        }
        SyncReport {
            entries: ch.entries.len(),
            bricks: ch.slots.len(),
            bytes,
        }
    }

    fn run(&self, gpu: &Gpu, entry: &str, queries: &[Query]) -> Result<Vec<[u32; 4]>, GpuError> {
        if queries.is_empty() {
            return Ok(vec![]);
        }
        let q = gpu.storage_buffer("queries", queries);
        let r = gpu.storage_buffer_zeroed("results", queries.len() as u64 * 16);
        let bind = self.bind(gpu, queries.len(), &self.unused[0], &q, &r);
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        let groups = (queries.len() as u32).div_ceil(64);
        self.kernel.dispatch(&mut enc, entry, &bind, [groups, 1, 1]);
        gpu.queue.submit([enc.finish()]);
        let words = gpu.read_u32(entry, &r, queries.len() * 4)?;
        Ok(words
            .chunks_exact(4)
            .map(|w| [w[0], w[1], w[2], w[3]])
            .collect())
    }

    /// The page-table walk: per query, the entry `(word, value)` found and,
    /// for a resident brick, its pool slot.
    pub fn lookup(&self, gpu: &Gpu, queries: &[Query]) -> Result<Vec<Walked>, GpuError> {
        Ok(self
            .run(gpu, "lookup", queries)?
            .into_iter()
            .map(|r| ([r[0], r[1]], (r[2] != u32::MAX).then_some(r[2])))
            .collect())
    }

    /// The sampler: per query, the trilinear value if its brick is mapped.
    pub fn sample(&self, gpu: &Gpu, queries: &[Query]) -> Result<Vec<Option<f32>>, GpuError> {
        Ok(self
            .run(gpu, "sample", queries)?
            .into_iter()
            .map(|r| (r[1] == 1).then_some(f32::from_bits(r[0])))
            .collect())
    }
}
