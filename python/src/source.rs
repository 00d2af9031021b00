//! An in-memory array as a [`VolumeSource`], for `brickyard.from_numpy`.

use anyhow::{anyhow, bail, Result};
use brickyard_core::DType;
use brickyard_store::{SourceMeta, VolumeSource};
use std::ops::Range;

/// `[c, z, y, x]` voxels in C order, native-endian, borrowed from Python.
pub struct MemorySource<'a> {
    meta: SourceMeta,
    data: &'a [u8],
    shape: [u64; 4],
}

impl<'a> MemorySource<'a> {
    pub fn new(data: &'a [u8], shape: [u64; 4], dtype: &str) -> Result<Self> {
        let d = DType::parse(dtype).ok_or_else(|| {
            anyhow!(
                "dtype: expected one of uint8, int8, uint16, int16, uint32, int32, float32, float64, found {dtype:?}"
            )
        })?;
        if shape.contains(&0) {
            bail!("array: every axis must be non-empty, shape (c, z, y, x) is {shape:?}");
        }
        let want = shape.iter().product::<u64>() * d.size() as u64;
        if want != data.len() as u64 {
            bail!(
                "array: shape {shape:?} of {dtype} needs {want} bytes, {} given",
                data.len()
            );
        }
        let meta = SourceMeta::new(
            "<numpy array>",
            [shape[1], shape[2], shape[3]],
            shape[0] as usize,
            d,
        );
        Ok(MemorySource { meta, data, shape })
    }
}

impl VolumeSource for MemorySource<'_> {
    fn meta(&self) -> &SourceMeta {
        &self.meta
    }

    fn read_region(
        &self,
        c: usize,
        z: Range<u64>,
        y: Range<u64>,
        x: Range<u64>,
        out: &mut [u8],
    ) -> brickyard_store::Result<()> {
        let es = self.meta.dtype.size();
        let [_, dz, dy, dx] = self.shape;
        let run = (x.end - x.start) as usize * es;
        let mut at = 0;
        for zz in z.clone() {
            for yy in y.clone() {
                let src = ((((c as u64 * dz + zz) * dy + yy) * dx) + x.start) as usize * es;
                out[at..at + run].copy_from_slice(&self.data[src..src + run]);
                at += run;
            }
        }
        Ok(())
    }

    fn preferred_read(&self) -> [u64; 3] {
        let d = self.meta.dims;
        [1, d[1], d[2]]
    }
}
