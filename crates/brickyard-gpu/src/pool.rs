//! The brick pool on the device: one 3D texture of padded bricks (apron
//! included), a slot per brick, and the host→device write of bricks.
//!
//! Texture formats, per data type (the shader reads `texel × scale`, the
//! voxel's value, in every case):
//!
//! | data type | format | scale | exact |
//! |---|---|---|---|
//! | u8 | `R8Unorm` | 255 | yes |
//! | u16 | `R16Unorm` where the adapter has `TEXTURE_FORMAT_16BIT_NORM` | 65535 | yes |
//! | u16 elsewhere (browsers), i16 | `R32Float` | 1 | yes |
//! | i8 | `R16Float` | 1 | yes (integers up to 2048 are exact in f16) |
//! | f32 | `R32Float` | 1 | yes |
//! | u32, i32, f64 | `R32Float` | 1 | no: rounded to f32 (as the CPU renderer samples) |
//!
//! `R8Unorm`, `R16Unorm` and `R16Float` are filterable everywhere;
//! `R32Float` is filterable only with `FLOAT32_FILTERABLE`, so kernels
//! interpolate by hand where [`PoolFormat::filterable`] is false.

use crate::context::{Gpu, GpuError};
use brickyard_core::{dispatch_dtype, DType, Sample};
use std::borrow::Cow;

/// How a data type is stored in the device pool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoolFormat {
    pub format: wgpu::TextureFormat,
    /// Texel value × `scale` = voxel value.
    pub scale: f32,
    /// Every value of the data type is stored without rounding.
    pub exact: bool,
    /// The texture can be sampled with hardware filtering.
    pub filterable: bool,
    /// Bytes per texel.
    pub texel_bytes: u32,
}

/// The pool format for `dtype` on an adapter with (`r16_unorm`) or without
/// `TEXTURE_FORMAT_16BIT_NORM`.
pub fn pool_format(dtype: DType, r16_unorm: bool) -> PoolFormat {
    use wgpu::TextureFormat as F;
    let f = |format, scale, exact, filterable, texel_bytes| PoolFormat {
        format,
        scale,
        exact,
        filterable,
        texel_bytes,
    };
    match dtype {
        DType::U8 => f(F::R8Unorm, 255.0, true, true, 1),
        DType::U16 if r16_unorm => f(F::R16Unorm, 65535.0, true, true, 2),
        DType::U16 | DType::I16 | DType::F32 => f(F::R32Float, 1.0, true, false, 4),
        DType::I8 => f(F::R16Float, 1.0, true, true, 2),
        DType::U32 | DType::I32 | DType::F64 => f(F::R32Float, 1.0, false, false, 4),
    }
}

/// A brick for [`DevicePool::write_many`]: its slot, its padded voxels
/// and its cell ranges (empty where the pool keeps none).
pub type BrickWrite<'a> = (u32, &'a [u8], &'a [[f32; 2]]);

/// The brick pool texture: `slots` padded bricks in a grid of slots
/// (`[z, y, x]`, x fastest: slot `s` is at `(s mod gx, s / gx mod gy,
/// s / (gx·gy))`).
pub struct DevicePool {
    pub texture: wgpu::Texture,
    pub format: PoolFormat,
    dtype: DType,
    /// Padded brick, voxels `[z, y, x]`.
    padded: [u32; 3],
    /// Slots per axis `[z, y, x]`.
    grid: [u32; 3],
    slots: u32,
    /// Host→device bytes written since the last [`take_uploaded`](Self::take_uploaded).
    uploaded: u64,
    /// The value range `(lo, hi)` of each cell of each slot's brick
    /// (`brickyard_cache::cells`), `Rg32Float`, cells of slot `s` at its
    /// slot coordinates × cells per axis; and cells per axis `[z, y, x]`.
    cells: Option<(wgpu::Texture, [u32; 3])>,
}

impl DevicePool {
    /// A pool of `slots` padded bricks of `padded` voxels (`[z, y, x]`) of
    /// `dtype`. Fails if the texture would exceed the device's limits.
    pub fn new(
        gpu: &Gpu,
        dtype: DType,
        padded: [u32; 3],
        slots: u32,
    ) -> Result<DevicePool, GpuError> {
        Self::with_slots_per_axis(gpu, dtype, padded, slots, u32::MAX)
    }

    /// [`new`](Self::new) with at most `limit` slots along each axis (tests
    /// use it to spread a few slots over several rows and layers).
    pub fn with_slots_per_axis(
        gpu: &Gpu,
        dtype: DType,
        padded: [u32; 3],
        slots: u32,
        limit: u32,
    ) -> Result<DevicePool, GpuError> {
        let format = pool_format(dtype, gpu.r16_unorm);
        let max = gpu.limits.max_texture_dimension_3d;
        let per_axis = [0, 1, 2].map(|a| (max / padded[a]).clamp(1, limit.max(1)));
        let slots = slots.max(1);
        let gx = slots.min(per_axis[2]);
        let gy = slots.div_ceil(gx).min(per_axis[1]);
        let gz = slots.div_ceil(gx * gy);
        if gz > per_axis[0] {
            return Err(GpuError::Limit {
                what: format!("brick pool of {slots} slots of {padded:?} voxels (slots per axis)"),
                got: gz as u64,
                limit: per_axis[0] as u64,
            });
        }
        // A pool larger than the device's memory is an error to report,
        // not a panic of the device's error handler.
        let scope = gpu.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("brick pool"),
            size: wgpu::Extent3d {
                width: gx * padded[2],
                height: gy * padded[1],
                depth_or_array_layers: gz * padded[0],
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D3,
            format: format.format,
            usage: wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_DST
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        // In the browser an error scope resolves on the page's event loop,
        // which cannot be waited for here: a pool the device cannot hold
        // shows up there as a validation error of the first frame.
        #[cfg(not(target_arch = "wasm32"))]
        let refused = pollster::block_on(scope.pop());
        #[cfg(target_arch = "wasm32")]
        let refused: Option<wgpu::Error> = {
            drop(scope);
            None
        };
        if let Some(e) = refused {
            let voxels =
                (gx * padded[2]) as u64 * (gy * padded[1]) as u64 * (gz * padded[0]) as u64;
            return Err(GpuError::OutOfMemory {
                what: format!("a brick pool of {slots} bricks"),
                bytes: voxels * dtype.size() as u64,
                reason: e.to_string(),
            });
        }
        Ok(DevicePool {
            texture,
            format,
            dtype,
            padded,
            grid: [gz, gy, gx],
            slots,
            uploaded: 0,
            cells: None,
        })
    }

    /// Keep the value ranges of `count` cells per axis (`[z, y, x]`) per
    /// slot, for skipping cells the transfer function hides; every range
    /// starts unknown (`NaN`: never skipped).
    pub fn enable_cells(&mut self, gpu: &Gpu, count: [u32; 3]) {
        let [gz, gy, gx] = self.grid;
        let size = wgpu::Extent3d {
            width: gx * count[2],
            height: gy * count[1],
            depth_or_array_layers: gz * count[0],
        };
        let t = gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("cell ranges"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D3,
            format: wgpu::TextureFormat::Rg32Float,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let n = (size.width * size.height * size.depth_or_array_layers) as usize;
        let nan: Vec<f32> = vec![f32::NAN; 2 * n];
        gpu.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &t,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(&nan),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(size.width * 8),
                rows_per_image: Some(size.height),
            },
            size,
        );
        self.cells = Some((t, count));
    }

    /// Cells per axis `[z, y, x]` and a view of the cell ranges (`None`
    /// until [`enable_cells`](Self::enable_cells)).
    pub fn cells(&self) -> Option<([u32; 3], wgpu::TextureView)> {
        self.cells
            .as_ref()
            .map(|(t, c)| (*c, t.create_view(&Default::default())))
    }

    /// Write the cell ranges of slot `s` (`[z][y][x]` order, as
    /// `brickyard_cache::cells::cell_ranges` gives them).
    pub fn write_cells(&mut self, gpu: &Gpu, s: u32, ranges: &[[f32; 2]]) {
        let Some((t, c)) = &self.cells else { return };
        assert_eq!(
            ranges.len(),
            c.iter().product::<u32>() as usize,
            "one range per cell"
        );
        gpu.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: t,
                mip_level: 0,
                origin: self.cell_origin(s, *c),
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(ranges),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(c[2] * 8),
                rows_per_image: Some(c[1]),
            },
            wgpu::Extent3d {
                width: c[2],
                height: c[1],
                depth_or_array_layers: c[0],
            },
        );
        self.uploaded += ranges.len() as u64 * 8;
    }

    /// Where slot `s`'s cell ranges begin in the cell texture of `c`
    /// cells per axis.
    fn cell_origin(&self, s: u32, c: [u32; 3]) -> wgpu::Origin3d {
        let g = self.grid;
        wgpu::Origin3d {
            x: s % g[2] * c[2],
            y: s / g[2] % g[1] * c[1],
            z: s / (g[2] * g[1]) * c[0],
        }
    }

    pub fn slots(&self) -> u32 {
        self.slots
    }

    /// Slots per axis `[z, y, x]`.
    pub fn grid(&self) -> [u32; 3] {
        self.grid
    }

    /// Bytes of the pool texture.
    pub fn bytes(&self) -> u64 {
        let e = self.texture.size();
        e.width as u64
            * e.height as u64
            * e.depth_or_array_layers as u64
            * self.format.texel_bytes as u64
    }

    /// First texel `(x, y, z)` of slot `s`.
    pub fn origin(&self, s: u32) -> wgpu::Origin3d {
        let [_, gy, gx] = self.grid;
        wgpu::Origin3d {
            x: (s % gx) * self.padded[2],
            y: (s / gx % gy) * self.padded[1],
            z: (s / (gx * gy)) * self.padded[0],
        }
    }

    fn extent(&self) -> wgpu::Extent3d {
        wgpu::Extent3d {
            width: self.padded[2],
            height: self.padded[1],
            depth_or_array_layers: self.padded[0],
        }
    }

    /// Texel bytes of the padded brick for slot `s`, given as
    /// native-endian voxels of the pool's data type (the voxels
    /// themselves where the format stores them as they are, else
    /// converted).
    fn texels<'v>(&self, s: u32, voxels: &'v [u8]) -> Cow<'v, [u8]> {
        use wgpu::TextureFormat as F;
        assert!(s < self.slots, "slot {s} of {}", self.slots);
        let n: u32 = self.padded.iter().product();
        assert_eq!(
            voxels.len(),
            n as usize * self.dtype.size(),
            "a padded brick of {:?} voxels",
            self.padded
        );
        match (self.dtype, self.format.format) {
            (DType::U8, F::R8Unorm) | (DType::U16, F::R16Unorm) | (DType::F32, F::R32Float) => {
                Cow::Borrowed(voxels)
            }
            (DType::I8, F::R16Float) => voxels
                .iter()
                .flat_map(|&b| f32_to_f16(b as i8 as f32).to_le_bytes())
                .collect(),
            (d, F::R32Float) => dispatch_dtype!(d, T => {
                voxels
                    .chunks_exact(std::mem::size_of::<T>())
                    .flat_map(|c| (<T as Sample>::from_le(c).to_f64() as f32).to_le_bytes())
                    .collect()
            }),
            (d, f) => unreachable!("no conversion from {d:?} to {f:?}"),
        }
    }

    /// Write the padded brick `voxels` (native-endian voxels of the pool's
    /// data type, `[z, y, x]`) into slot `s`. Counts the bytes moved.
    pub fn write(&mut self, gpu: &Gpu, s: u32, voxels: &[u8]) {
        let texels = self.texels(s, voxels);
        gpu.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.texture,
                mip_level: 0,
                origin: self.origin(s),
                aspect: wgpu::TextureAspect::All,
            },
            &texels,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(self.padded[2] * self.format.texel_bytes),
                rows_per_image: Some(self.padded[1]),
            },
            self.extent(),
        );
        self.uploaded += texels.len() as u64;
    }

    /// Write many padded bricks at once, each with its cell ranges when
    /// the pool keeps them (`cells` empty otherwise): `(slot, voxels,
    /// cells)` as [`write`](Self::write) and
    /// [`write_cells`](Self::write_cells) take them, in one staging buffer
    /// and one submission. [`write`](Self::write) goes through
    /// `Queue::write_texture`, which makes a staging buffer per call: two
    /// per brick, and a frame writes thousands of bricks. Counts the bytes
    /// moved (the bricks', not the staging buffer's padding).
    pub fn write_many(&mut self, gpu: &Gpu, bricks: &[BrickWrite]) {
        if bricks.is_empty() {
            return;
        }
        let texels: Vec<Cow<[u8]>> = bricks
            .iter()
            .map(|&(s, voxels, _)| self.texels(s, voxels))
            .collect();
        // Per texture: how its boxes lie in the staging buffer, and each
        // box's texture, origin and bytes.
        let items: Vec<(&wgpu::Texture, wgpu::Origin3d, &[u8])> = bricks
            .iter()
            .zip(&texels)
            .map(|((s, _, _), t)| (&self.texture, self.origin(*s), &t[..]))
            .collect();
        let mut copies = vec![(Staged::new(self.padded, self.format.texel_bytes), items)];
        if let Some((t, c)) = &self.cells {
            let mut items = vec![];
            for &(s, _, ranges) in bricks.iter().filter(|b| !b.2.is_empty()) {
                assert_eq!(
                    ranges.len(),
                    c.iter().product::<u32>() as usize,
                    "one range per cell"
                );
                items.push((
                    t,
                    self.cell_origin(s, *c),
                    bytemuck::cast_slice::<_, u8>(ranges),
                ));
            }
            copies.push((Staged::new(*c, 8), items));
        }
        let total: u64 = copies.iter().map(|(st, it)| st.bytes(it.len())).sum();
        let buf = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("brick uploads"),
            size: total,
            usage: wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::MAP_WRITE,
            mapped_at_creation: true,
        });
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        let mut uploaded = 0;
        {
            let mut map = buf
                .slice(..)
                .get_mapped_range_mut()
                .expect("a buffer mapped at creation");
            let mut base = 0u64;
            for (st, items) in &copies {
                for (i, (texture, origin, bytes)) in items.iter().enumerate() {
                    let at = base + st.offset(i);
                    st.put(&mut map, at as usize, bytes);
                    enc.copy_buffer_to_texture(
                        wgpu::TexelCopyBufferInfo {
                            buffer: &buf,
                            layout: wgpu::TexelCopyBufferLayout {
                                offset: at,
                                bytes_per_row: Some(st.line),
                                rows_per_image: Some(st.dims[1]),
                            },
                        },
                        wgpu::TexelCopyTextureInfo {
                            texture,
                            mip_level: 0,
                            origin: *origin,
                            aspect: wgpu::TextureAspect::All,
                        },
                        st.extent(),
                    );
                    uploaded += bytes.len() as u64;
                }
                base += st.bytes(items.len());
            }
        }
        buf.unmap();
        gpu.queue.submit([enc.finish()]);
        self.uploaded += uploaded;
    }

    /// Bytes written since the last call.
    pub fn take_uploaded(&mut self) -> u64 {
        std::mem::take(&mut self.uploaded)
    }

    /// The voxel values of slot `s` (`[z, y, x]`), read back from the
    /// device (tests, debugging).
    pub fn read_slot(&self, gpu: &Gpu, s: u32) -> Result<Vec<f32>, GpuError> {
        let tb = self.format.texel_bytes;
        let row = (self.padded[2] * tb).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
        let rows = self.padded[1] * self.padded[0];
        let buf = gpu.storage_buffer_zeroed("pool read-back", row as u64 * rows as u64);
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        enc.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &self.texture,
                mip_level: 0,
                origin: self.origin(s),
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &buf,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(row),
                    rows_per_image: Some(self.padded[1]),
                },
            },
            self.extent(),
        );
        gpu.queue.submit([enc.finish()]);
        let bytes = gpu.read_back("pool slot", &buf, row as u64 * rows as u64)?;
        let mut out = Vec::with_capacity((self.padded[2] * rows) as usize);
        for r in 0..rows as usize {
            let line = &bytes[r * row as usize..][..(self.padded[2] * tb) as usize];
            for t in line.chunks_exact(tb as usize) {
                use wgpu::TextureFormat as F;
                let texel = match self.format.format {
                    F::R8Unorm => t[0] as f32 / 255.0,
                    F::R16Unorm => u16::from_le_bytes([t[0], t[1]]) as f32 / 65535.0,
                    F::R16Float => f16_to_f32(u16::from_le_bytes([t[0], t[1]])),
                    _ => f32::from_le_bytes([t[0], t[1], t[2], t[3]]),
                };
                out.push(texel * self.format.scale);
            }
        }
        Ok(out)
    }
}

/// `x` (an integer of magnitude at most 2048, or any value that f16
/// represents exactly) as IEEE half-precision bits.
fn f32_to_f16(x: f32) -> u16 {
    let b = x.to_bits();
    let sign = ((b >> 16) & 0x8000) as u16;
    if x == 0.0 {
        return sign;
    }
    let exp = ((b >> 23) & 0xff) as i32 - 127 + 15;
    debug_assert!((1..31).contains(&exp), "{x} is not a normal f16");
    let mant = ((b >> 13) & 0x3ff) as u16;
    sign | ((exp as u16) << 10) | mant
}

/// IEEE half-precision bits as `f32` (normal numbers and zero).
fn f16_to_f32(h: u16) -> f32 {
    let sign = ((h & 0x8000) as u32) << 16;
    let exp = ((h >> 10) & 0x1f) as u32;
    let mant = (h & 0x3ff) as u32;
    if exp == 0 && mant == 0 {
        return f32::from_bits(sign);
    }
    f32::from_bits(sign | ((exp + 127 - 15) << 23) | (mant << 13))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_floats_hold_every_i8() {
        for v in -128..=127i32 {
            let h = f32_to_f16(v as f32);
            assert_eq!(f16_to_f32(h), v as f32, "{v}");
        }
        // Hand-checked bit patterns: 1.0 = 0x3c00, −2.0 = 0xc000, 100 = 0x5640.
        assert_eq!(f32_to_f16(1.0), 0x3c00);
        assert_eq!(f32_to_f16(-2.0), 0xc000);
        assert_eq!(f32_to_f16(100.0), 0x5640);
    }
}

/// How boxes of `dims` texels (`[z, y, x]`) of `texel` bytes lie in a
/// staging buffer for `copy_buffer_to_texture`, whose rows must start 256
/// bytes apart: the rows of several boxes side by side in each 256-byte
/// line (lanes 4-byte aligned), `lanes` boxes to a slab of `y·z` lines.
#[derive(Debug, Clone, Copy)]
struct Staged {
    dims: [u32; 3],
    /// Bytes of one row of a box.
    row: u32,
    /// Bytes between boxes in a line.
    lane: u32,
    lanes: u32,
    /// Bytes between lines.
    line: u32,
}

impl Staged {
    fn new(dims: [u32; 3], texel: u32) -> Staged {
        let align = wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let row = dims[2] * texel;
        let lane = row.next_multiple_of(4);
        let line = lane.next_multiple_of(align);
        Staged {
            dims,
            row,
            lane,
            lanes: (line / lane).max(1),
            line,
        }
    }

    fn slab(&self) -> u64 {
        self.line as u64 * self.dims[1] as u64 * self.dims[0] as u64
    }

    /// Bytes for `n` boxes.
    fn bytes(&self, n: usize) -> u64 {
        (n as u64).div_ceil(self.lanes as u64) * self.slab()
    }

    /// Where box `i` begins.
    fn offset(&self, i: usize) -> u64 {
        let i = i as u64;
        i / self.lanes as u64 * self.slab() + i % self.lanes as u64 * self.lane as u64
    }

    /// Box `bytes` (rows of `row` bytes, x fastest) into the mapped
    /// staging buffer `out` at `at`, where the box begins.
    fn put(&self, out: &mut wgpu::BufferViewMut, at: usize, bytes: &[u8]) {
        let (row, line) = (self.row as usize, self.line as usize);
        debug_assert_eq!(
            bytes.len(),
            row * self.dims[1] as usize * self.dims[0] as usize
        );
        for (r, src) in bytes.chunks_exact(row).enumerate() {
            let o = at + r * line;
            out.slice(o..o + row).copy_from_slice(src);
        }
    }

    fn extent(&self) -> wgpu::Extent3d {
        wgpu::Extent3d {
            width: self.dims[2],
            height: self.dims[1],
            depth_or_array_layers: self.dims[0],
        }
    }
}
