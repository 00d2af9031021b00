//! Zarr and OME-Zarr input: Zarr v2 and v3 arrays (any chunking, sharded or
//! not, any codec `zarrs` decodes) and OME-Zarr 0.4 / 0.5 multiscale images.

use crate::error::{Result, StoreError};
use crate::omezarr::{read_json, read_multiscale, Multiscale};
use crate::source::{check_region, SourceMeta, VolumeSource};
use brickyard_core::{as_bytes, dispatch_dtype, DType, Dims3};
use serde_json::Value;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::{Array, ArraySubset};
use zarrs::filesystem::FilesystemStore;

/// A 3D (optionally multi-channel) view of one Zarr array.
pub struct ZarrSource {
    meta: SourceMeta,
    array: Array<FilesystemStore>,
    /// Array axis index of z, y, x (`None` for an absent axis of size 1).
    zyx: [Option<usize>; 3],
    /// Array axis index of the channel axis.
    caxis: Option<usize>,
    chunk: Vec<u64>,
    /// The multiscale metadata, when the path was an OME-Zarr image.
    pub multiscale: Option<Multiscale>,
}

fn is_array_dir(p: &Path) -> bool {
    if p.join(".zarray").exists() {
        return true;
    }
    match read_json(&p.join("zarr.json")) {
        Ok(j) => j.get("node_type").and_then(Value::as_str) == Some("array"),
        Err(_) => false,
    }
}

/// Whether `p` looks like a Zarr node (group or array).
pub fn is_zarr(p: &Path) -> bool {
    p.is_dir()
        && (p.join("zarr.json").exists()
            || p.join(".zarray").exists()
            || p.join(".zgroup").exists())
}

/// Open level `level` of an OME-Zarr image, or a bare Zarr array.
pub fn open(path: &Path, level: usize) -> Result<ZarrSource> {
    if !path.exists() {
        return Err(StoreError::io(
            path,
            std::io::Error::from(std::io::ErrorKind::NotFound),
        ));
    }
    if is_array_dir(path) {
        return open_array(path, None, None);
    }
    let ms = read_multiscale(path)?.ok_or_else(|| {
        StoreError::invalid(
            path,
            "multiscales",
            "this Zarr group holds no OME multiscale image (and is not an array)",
        )
    })?;
    let ds = ms.datasets.get(level).ok_or_else(|| {
        StoreError::invalid(
            path,
            "multiscales.datasets",
            format!(
                "level {level} asked for but the image has {} levels",
                ms.datasets.len()
            ),
        )
    })?;
    let apath = path.join(&ds.path);
    if !is_array_dir(&apath) {
        return Err(StoreError::invalid(
            &apath,
            "datasets.path",
            "no Zarr array at this path",
        ));
    }
    let ds0 = ms.datasets[0].clone();
    open_array(&apath, Some((ms, level)), Some(ds0.path))
}

fn open_array(
    apath: &Path,
    ms: Option<(Multiscale, usize)>,
    _p0: Option<String>,
) -> Result<ZarrSource> {
    let store = Arc::new(FilesystemStore::new(apath).map_err(|e| StoreError::zarr(apath, e))?);
    let array = Array::open(store, "/").map_err(|e| StoreError::zarr(apath, e))?;
    let mj = serde_json::to_value(array.metadata()).map_err(|e| StoreError::zarr(apath, e))?;
    let dt_name = mj
        .get("data_type")
        .or_else(|| mj.get("dtype"))
        .and_then(Value::as_str)
        .unwrap_or("?")
        .to_string();
    let dtype = DType::parse(&dt_name).ok_or_else(|| {
        StoreError::unsupported(
            apath,
            "data_type",
            format!("{dt_name:?}; expected one of uint8, int8, uint16, int16, uint32, int32, float32, float64"),
        )
    })?;
    let shape = array.shape().to_vec();
    let n = shape.len();
    if !(2..=5).contains(&n) {
        return Err(StoreError::unsupported(
            apath,
            "shape",
            format!("{n} dimensions; expected 2 to 5"),
        ));
    }
    // Axis names: from the multiscale, else from dimension_names, else positional.
    let mut names: Vec<Option<String>> = vec![None; n];
    let mut kinds: Vec<Option<String>> = vec![None; n];
    let mut units: Vec<Option<String>> = vec![None; n];
    if let Some((m, _)) = &ms {
        if m.axes.len() == n {
            for (i, a) in m.axes.iter().enumerate() {
                names[i] = Some(a.name.to_ascii_lowercase());
                kinds[i] = a.kind.clone();
                units[i] = a.unit.clone();
            }
        } else if !m.axes.is_empty() {
            return Err(StoreError::invalid(
                apath,
                "multiscales.axes",
                format!("{} axes for an array of {n} dimensions", m.axes.len()),
            ));
        }
    }
    if names.iter().all(Option::is_none) {
        if let Some(dn) = mj.get("dimension_names").and_then(Value::as_array) {
            for (i, v) in dn.iter().enumerate().take(n) {
                names[i] = v.as_str().map(|s| s.to_ascii_lowercase());
            }
        }
    }
    let find = |nm: &str| names.iter().position(|x| x.as_deref() == Some(nm));
    let mut zyx = [find("z"), find("y"), find("x")];
    if zyx[1].is_none() || zyx[2].is_none() {
        // Positional: the last axes are (z,) y, x.
        zyx = if n == 2 {
            [None, Some(0), Some(1)]
        } else {
            [Some(n - 3), Some(n - 2), Some(n - 1)]
        };
    }
    let used: Vec<usize> = zyx.iter().flatten().copied().collect();
    let mut caxis = None;
    for i in 0..n {
        if used.contains(&i) {
            continue;
        }
        let is_c = names[i].as_deref() == Some("c") || kinds[i].as_deref() == Some("channel");
        let is_t = names[i].as_deref() == Some("t") || kinds[i].as_deref() == Some("time");
        if shape[i] == 1 && !is_c {
            continue;
        }
        if is_t {
            return Err(StoreError::unsupported(
                apath,
                "axes",
                format!(
                    "time axis with {} points; brickyard converts one 3D (multi-channel) volume",
                    shape[i]
                ),
            ));
        }
        if caxis.is_some() {
            return Err(StoreError::unsupported(
                apath,
                "axes",
                "more than one non-spatial axis longer than 1",
            ));
        }
        caxis = Some(i);
    }
    let dim = |a: Option<usize>| a.map(|i| shape[i]).unwrap_or(1);
    let dims: Dims3 = [dim(zyx[0]), dim(zyx[1]), dim(zyx[2])];
    let channels = caxis.map(|i| shape[i] as usize).unwrap_or(1);
    let mut meta = SourceMeta::new(apath, dims, channels, dtype);
    if let Some((m, level)) = &ms {
        let ds = &m.datasets[*level];
        let pick = |v: &Option<Vec<f64>>| -> Option<[f64; 3]> {
            let v = v.as_ref()?;
            if v.len() != n {
                return None;
            }
            Some([
                zyx[0].map(|i| v[i]).unwrap_or(1.0),
                zyx[1].map(|i| v[i])?,
                zyx[2].map(|i| v[i])?,
            ])
        };
        meta.spacing = pick(&ds.scale);
        meta.origin = pick(&ds.translation);
        meta.unit = zyx.iter().flatten().find_map(|&i| units[i].clone());
        meta.path = apath
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_else(|| PathBuf::from(apath));
        if let Some(b) = &m.brickyard {
            meta.labels = b.get("labels").and_then(Value::as_bool).unwrap_or(false);
        }
    }
    let chunk = array
        .chunk_shape(&vec![0; n])
        .map_err(|e| StoreError::zarr(apath, e))?
        .iter()
        .map(|c| c.get())
        .collect();
    Ok(ZarrSource {
        meta,
        array,
        zyx,
        caxis,
        chunk,
        multiscale: ms.map(|(m, _)| m),
    })
}

impl ZarrSource {
    /// Open one Zarr array directory directly (no multiscale metadata).
    pub fn open_level_array(path: &Path) -> Result<ZarrSource> {
        open_array(path, None, None)
    }

    /// The underlying array's shape.
    pub fn array_shape(&self) -> &[u64] {
        self.array.shape()
    }
}

impl VolumeSource for ZarrSource {
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
    ) -> Result<()> {
        check_region(&self.meta, c, &z, &y, &x, out);
        let n = self.array.shape().len();
        let mut ranges: Vec<Range<u64>> = vec![0..1; n];
        let rs = [z, y, x];
        for (a, r) in rs.iter().enumerate() {
            if let Some(i) = self.zyx[a] {
                ranges[i] = r.clone();
            }
        }
        if let Some(i) = self.caxis {
            ranges[i] = c as u64..c as u64 + 1;
        }
        let subset = ArraySubset::new_with_ranges(&ranges);
        // Strides of the retrieved subset (C order over array axes).
        let sizes: Vec<u64> = ranges.iter().map(|r| r.end - r.start).collect();
        let mut strides = vec![1u64; n];
        for i in (0..n.saturating_sub(1)).rev() {
            strides[i] = strides[i + 1] * sizes[i + 1];
        }
        let order: Vec<usize> = self.zyx.iter().flatten().copied().collect();
        let natural = order.windows(2).all(|w| w[0] < w[1]);
        let path = &self.meta.path;
        dispatch_dtype!(self.meta.dtype, T => {
            let v: Vec<T> = self
                .array
                .retrieve_array_subset::<Vec<T>>(&subset)
                .map_err(|e| StoreError::zarr(path, e))?;
            if natural {
                out.copy_from_slice(as_bytes(&v));
            } else {
                // Transpose into z, y, x order.
                let es = std::mem::size_of::<T>();
                let st = |a: usize| self.zyx[a].map(|i| strides[i]).unwrap_or(0);
                let (sz, sy, sx) = (st(0), st(1), st(2));
                let (nz, ny, nx) = (rs[0].end - rs[0].start, rs[1].end - rs[1].start, rs[2].end - rs[2].start);
                let src = as_bytes(&v);
                let mut o = 0;
                for k in 0..nz {
                    for j in 0..ny {
                        for i in 0..nx {
                            let s = ((k * sz + j * sy + i * sx) as usize) * es;
                            out[o..o + es].copy_from_slice(&src[s..s + es]);
                            o += es;
                        }
                    }
                }
            }
        });
        Ok(())
    }

    fn preferred_read(&self) -> Dims3 {
        let cz = self.zyx[0].map(|i| self.chunk[i]).unwrap_or(1);
        [cz, self.meta.dims[1], self.meta.dims[2]]
    }
}
