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

    /// Name the channels (one name each, checked by the caller).
    pub fn name_channels(&mut self, names: &[String]) {
        self.meta.channel_names = names.to_vec();
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

/// Where a NumPy array's voxels lie, from its `__array_interface__`: a
/// C-contiguous, native-endian `[c, z, y, x]` array of one of the stored
/// types (anything else is refused; `brickyard.from_numpy` reads such
/// arrays region by region instead).
pub struct ArrayView {
    ptr: usize,
    len: usize,
    pub shape: [u64; 4],
}

impl ArrayView {
    pub fn of(array: &Bound<'_, PyAny>, dtype: &str) -> PyResult<ArrayView> {
        let bad = |msg: String| PyValueError::new_err(format!("array: {msg}"));
        let d = DType::parse(dtype)
            .ok_or_else(|| bad(format!("dtype {dtype:?} is not stored by brickyard")))?;
        let iface = array.getattr("__array_interface__")?;
        let shape: Vec<u64> = iface.get_item("shape")?.extract()?;
        let shape: [u64; 4] = shape.try_into().map_err(|s: Vec<u64>| {
            bad(format!(
                "expected 4 dimensions (c, z, y, x), got {} of shape {s:?}",
                s.len()
            ))
        })?;
        // `typestr` is byte order, kind and size: "<u2", "|u1", ">f4".
        let typestr: String = iface.get_item("typestr")?.extract()?;
        let native = if cfg!(target_endian = "little") {
            '<'
        } else {
            '>'
        };
        let kind = match d {
            DType::U8 | DType::U16 | DType::U32 => 'u',
            DType::I8 | DType::I16 | DType::I32 => 'i',
            DType::F32 | DType::F64 => 'f',
        };
        let mut t = typestr.chars();
        let (order, k, size) = (t.next(), t.next(), t.as_str());
        let order_ok = order == Some(native) || (order == Some('|') && d.size() == 1);
        if !order_ok || k != Some(kind) || size != d.size().to_string() {
            return Err(bad(format!(
                "expected native-endian {dtype} voxels, found type {typestr:?}"
            )));
        }
        // `strides` is None for a C-contiguous array, or the C-order
        // strides themselves.
        let strides = iface.get_item("strides")?;
        if !strides.is_none() {
            let strides: Vec<i64> = strides.extract()?;
            let mut want = [0i64; 4];
            let mut step = d.size() as i64;
            for a in (0..4).rev() {
                want[a] = step;
                step = step.saturating_mul(shape[a] as i64);
            }
            let same = strides
                .iter()
                .zip(want)
                .zip(shape)
                .all(|((&s, w), n)| n <= 1 || s == w);
            if strides.len() != 4 || !same {
                return Err(bad(format!(
                    "expected a C-contiguous array, found strides {strides:?}"
                )));
            }
        }
        let (ptr, _readonly): (usize, bool) = iface.get_item("data")?.extract()?;
        let len = shape
            .iter()
            .try_fold(d.size() as u64, |n, &s| n.checked_mul(s))
            .and_then(|n| usize::try_from(n).ok())
            .ok_or_else(|| bad(format!("shape {shape:?} is too large")))?;
        if ptr == 0 && len > 0 {
            return Err(bad("the array has no data".into()));
        }
        Ok(ArrayView { ptr, len, shape })
    }

    /// The voxels, in place.
    ///
    /// # Safety
    ///
    /// The array this view was taken of must stay alive, unresized and
    /// unwritten while the bytes are used.
    pub unsafe fn bytes<'a>(&self) -> &'a [u8] {
        if self.len == 0 {
            return &[];
        }
        std::slice::from_raw_parts(self.ptr as *const u8, self.len)
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

    /// Name the channels (one name each, checked by the caller).
    pub fn name_channels(&mut self, names: &[String]) {
        self.meta.channel_names = names.to_vec();
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
