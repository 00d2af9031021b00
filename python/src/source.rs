//! Arrays as [`VolumeSource`]s, for `brickyard.from_numpy`: an in-memory
//! array, or a lazy one read region by region.

use anyhow::{anyhow, bail, Result};
use brickyard_core::DType;
use brickyard_store::{SourceMeta, StoreError, VolumeSource};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use std::ops::Range;
use std::sync::Mutex;

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

/// A lazy array (dask, zarr, h5py, anything with `__getitem__`, `shape` and
/// `dtype`) as a [`VolumeSource`], for `brickyard.from_numpy`: each region
/// the builder asks for is fetched by calling the Python function
/// `read(c, z0, z1, y0, y1, x0, x1) -> bytes` (C order, native-endian), so
/// the array is never materialised whole. The first Python exception is
/// kept, to be raised in place of the builder's error.
pub struct LazySource {
    meta: SourceMeta,
    read: Py<PyAny>,
    chunk: [u64; 3],
    pub error: Mutex<Option<PyErr>>,
}

impl LazySource {
    pub fn new(
        read: Py<PyAny>,
        name: &str,
        shape: [u64; 4],
        dtype: &str,
        chunk: Option<[u64; 3]>,
    ) -> Result<Self> {
        let d = DType::parse(dtype).ok_or_else(|| {
            anyhow!(
                "dtype: expected one of uint8, int8, uint16, int16, uint32, int32, float32, float64, found {dtype:?}"
            )
        })?;
        if shape.contains(&0) {
            bail!("array: every axis must be non-empty, shape (c, z, y, x) is {shape:?}");
        }
        let dims = [shape[1], shape[2], shape[3]];
        let chunk = match chunk {
            Some(c) if !c.contains(&0) => [0, 1, 2].map(|a| c[a].min(dims[a])),
            _ => [1, dims[1], dims[2]],
        };
        Ok(LazySource {
            meta: SourceMeta::new(name, dims, shape[0] as usize, d),
            read,
            chunk,
            error: Mutex::new(None),
        })
    }
}

impl VolumeSource for LazySource {
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
        let what = format!(
            "channel {c}, [{}:{}, {}:{}, {}:{}]",
            z.start, z.end, y.start, y.end, x.start, x.end
        );
        let fail = |msg: String| StoreError::Invalid {
            path: self.meta.path.clone(),
            field: "array".into(),
            msg,
        };
        Python::attach(|py| {
            let r = self
                .read
                .call1(py, (c, z.start, z.end, y.start, y.end, x.start, x.end))
                .and_then(|b| {
                    let b = b.into_bound(py);
                    let bytes = b.cast::<PyBytes>().map_err(PyErr::from)?;
                    let data = bytes.as_bytes();
                    if data.len() != out.len() {
                        return Err(PyValueError::new_err(format!(
                            "{}: reading {what} gave {} bytes, {} expected",
                            self.meta.path.display(),
                            data.len(),
                            out.len()
                        )));
                    }
                    out.copy_from_slice(data);
                    Ok(())
                });
            r.map_err(|e| {
                let msg = format!("reading {what}: {e}");
                let mut kept = self.error.lock().unwrap();
                if kept.is_none() {
                    *kept = Some(e);
                }
                fail(msg)
            })
        })
    }

    fn preferred_read(&self) -> [u64; 3] {
        self.chunk
    }
}
