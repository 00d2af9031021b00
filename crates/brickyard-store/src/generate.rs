//! Procedural volumes of any size and type, computed on the fly region by
//! region (so a multi-GB volume never has to be held in memory):
//!
//! - `mandelbulb`: the power-8 Mandelbulb over `[-1.2, 1.2]³`; the value is
//!   the escape iteration count `n` (bail-out radius 2, 16 iterations) as
//!   `max(n - 2, 0) / 14` scaled to the type's range; points that never
//!   escape get the maximum. Large empty (zero) and constant (interior)
//!   regions, fine detail on the surface.
//! - `marschner-lobb`: the Marschner–Lobb test signal over `[-1, 1]³`
//!   (f_M = 6, α = 0.25), values in `[0, 1]` scaled to the type's range.
//!
//! Integer types get `round(v · max)` with `max` the largest value of the
//! type (for signed types, the positive range); float types get `v`.

use crate::error::{IoContext, Result, StoreError};
use crate::import::raw::RawOptions;
use crate::source::{check_region, SourceMeta, VolumeSource};
use brickyard_core::{dispatch_dtype, DType, Dims3, Sample};
use rayon::prelude::*;
use std::io::Write;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// Which procedural volume.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Mandelbulb,
    MarschnerLobb,
}

impl Kind {
    pub fn parse(s: &str) -> Option<Kind> {
        match s {
            "mandelbulb" => Some(Kind::Mandelbulb),
            "marschner-lobb" | "ml" => Some(Kind::MarschnerLobb),
            _ => None,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Kind::Mandelbulb => "mandelbulb",
            Kind::MarschnerLobb => "marschner-lobb",
        }
    }
}

/// A procedural volume.
pub struct Procedural {
    meta: SourceMeta,
    kind: Kind,
}

impl Procedural {
    /// `dims` is `[z, y, x]`.
    pub fn new(kind: Kind, dims: Dims3, dtype: DType) -> Procedural {
        let meta = SourceMeta::new(PathBuf::from(format!("<{}>", kind.name())), dims, 1, dtype);
        Procedural { meta, kind }
    }

    /// The same volume with its voxel spacing `[z, y, x]` stated (the
    /// `generate` command's: a procedural volume's grid is one unit per
    /// voxel by definition, not a spacing that went missing).
    pub fn with_spacing(mut self, spacing: [f64; 3]) -> Procedural {
        self.meta.spacing = Some(spacing);
        self
    }

    /// Value in `[0, 1]` at voxel `(z, y, x)`.
    pub fn value(&self, z: u64, y: u64, x: u64) -> f64 {
        let [dz, dy, dx] = self.meta.dims;
        let u = |i: u64, n: u64| (i as f64 + 0.5) / n as f64 * 2.0 - 1.0; // [-1, 1]
        match self.kind {
            Kind::Mandelbulb => mandelbulb(1.2 * u(x, dx), 1.2 * u(y, dy), 1.2 * u(z, dz)),
            Kind::MarschnerLobb => marschner_lobb(u(x, dx), u(y, dy), u(z, dz)),
        }
    }
}

const MB_ITER: u32 = 16;
const MB_EMPTY: u32 = 2;

/// Escape-time of the power-8 Mandelbulb (trigonometry-free form of the
/// White–Nylander iteration, `y` as the polar axis), normalized to `[0, 1]`.
pub fn mandelbulb(cx: f64, cy: f64, cz: f64) -> f64 {
    let (mut x, mut y, mut z) = (cx, cy, cz);
    for i in 0..MB_ITER {
        let r2 = x * x + y * y + z * z;
        if r2 > 4.0 {
            // Points that leave within the first iterations are empty space.
            return i.saturating_sub(MB_EMPTY) as f64 / (MB_ITER - MB_EMPTY) as f64;
        }
        let (x2, y2, z2) = (x * x, y * y, z * z);
        let (x4, y4, z4) = (x2 * x2, y2 * y2, z2 * z2);
        let k3 = x2 + z2;
        let k2 = 1.0 / (k3 * k3 * k3 * k3 * k3 * k3 * k3).sqrt().max(1e-300);
        let k1 = x4 + y4 + z4 - 6.0 * y2 * z2 - 6.0 * x2 * y2 + 2.0 * z2 * x2;
        let k4 = x2 - y2 + z2;
        let nx = cx + 64.0 * x * y * z * (x2 - z2) * k4 * (x4 - 6.0 * x2 * z2 + z4) * k1 * k2;
        let ny = cy + -16.0 * y2 * k3 * k4 * k4 + k1 * k1;
        let nz = cz
            + -8.0
                * y
                * k4
                * (x4 * x4 - 28.0 * x4 * x2 * z2 + 70.0 * x4 * z4 - 28.0 * x2 * z2 * z4 + z4 * z4)
                * k1
                * k2;
        x = nx;
        y = ny;
        z = nz;
    }
    1.0
}

/// The Marschner–Lobb signal at `(x, y, z) ∈ [-1, 1]³`, in `[0, 1]`.
pub fn marschner_lobb(x: f64, y: f64, z: f64) -> f64 {
    use std::f64::consts::PI;
    let (fm, alpha) = (6.0, 0.25);
    let r = (x * x + y * y).sqrt();
    let rho_r = (2.0 * PI * fm * (PI * r / 2.0).cos()).cos();
    ((1.0 - (PI * z / 2.0).sin() + alpha * (1.0 + rho_r)) / (2.0 * (1.0 + alpha))).clamp(0.0, 1.0)
}

/// Map `v ∈ [0, 1]` to a sample of type `T`.
pub fn to_sample<T: Sample + FromF64>(v: f64) -> T {
    T::from_unit(v)
}

/// Conversion from a unit value.
pub trait FromF64 {
    fn from_unit(v: f64) -> Self;
}
macro_rules! from_unit_int {
    ($($t:ty),*) => {$(
        impl FromF64 for $t {
            fn from_unit(v: f64) -> Self { (v * <$t>::MAX as f64).round() as $t }
        }
    )*};
}
from_unit_int!(u8, i8, u16, i16, u32, i32);
impl FromF64 for f32 {
    fn from_unit(v: f64) -> Self {
        v as f32
    }
}
impl FromF64 for f64 {
    fn from_unit(v: f64) -> Self {
        v
    }
}

impl VolumeSource for Procedural {
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
        let nx = (x.end - x.start) as usize;
        let ny = (y.end - y.start) as usize;
        let es = self.meta.dtype.size();
        dispatch_dtype!(self.meta.dtype, T => {
            out.par_chunks_mut(nx * es).enumerate().for_each(|(row, o)| {
                let zz = z.start + (row / ny) as u64;
                let yy = y.start + (row % ny) as u64;
                for (i, e) in o.chunks_exact_mut(es).enumerate() {
                    let v: T = to_sample(self.value(zz, yy, x.start + i as u64));
                    e.copy_from_slice(brickyard_core::as_bytes(std::slice::from_ref(&v)));
                }
            });
        });
        Ok(())
    }
}

/// Write a procedural volume as a raw file plus its JSON sidecar, in slabs.
/// `progress` gets the bytes written. The file is written to a temporary
/// name and renamed when complete.
pub fn write_raw(src: &Procedural, path: &Path, progress: &dyn crate::Progress) -> Result<()> {
    write_raw_within(src, path, progress, 64 << 20, &AtomicBool::new(false))
}

/// [`write_raw`], holding at most about `slab_bytes` of voxels at a time
/// (slabs of slices, of rows of one slice, or of one row, as the volume's
/// shape allows), and stopping when `cancel` is set: the temporary file is
/// removed and the error is [`StoreError::Interrupted`].
pub fn write_raw_within(
    src: &Procedural,
    path: &Path,
    progress: &dyn crate::Progress,
    slab_bytes: u64,
    cancel: &AtomicBool,
) -> Result<()> {
    write_raw_described(
        src,
        path,
        progress,
        slab_bytes,
        cancel,
        Some([1.0; 3]),
        None,
        None,
    )
}

/// [`write_raw_within`], the sidecar giving `spacing` and `origin`
/// (`[x, y, z]`) and `unit` (an OME-Zarr space unit, or one of its short
/// names): the geometry the caller asked for.
#[allow(clippy::too_many_arguments)]
pub fn write_raw_described(
    src: &Procedural,
    path: &Path,
    progress: &dyn crate::Progress,
    slab_bytes: u64,
    cancel: &AtomicBool,
    spacing: Option<[f64; 3]>,
    origin: Option<[f64; 3]>,
    unit: Option<String>,
) -> Result<()> {
    let m = src.meta();
    let [dz, dy, dx] = m.dims;
    let es = m.dtype.size() as u64;
    let opts = RawOptions {
        dims: [dx, dy, dz],
        dtype: m.dtype,
        endian: "little".into(),
        spacing,
        origin,
        unit,
        channels: 1,
        header_bytes: 0,
    };
    // Geometry convert would refuse is refused before anything is written.
    opts.check_geometry(path)?;
    crate::builder::check_parent(path)?;
    crate::builder::check_not_link(path)?;
    let tmp = crate::builder::partial_path(path);
    let _lock = crate::lock::PidLock::take(
        &crate::builder::lock_path(path),
        &format!("writing {}", path.display()),
    )?;
    let written = (|| -> Result<()> {
        let mut f = std::io::BufWriter::new(std::fs::File::create(&tmp).at(&tmp)?);
        progress.start(dz * dy * dx * es);
        // Pieces in file order: whole slices, rows of a slice, or runs of
        // one row, each within the slab.
        let slab = slab_bytes.max(es);
        let (row, slice) = (dx * es, dy * dx * es);
        let mut buf = vec![];
        let mut piece = |z: std::ops::Range<u64>,
                         y: std::ops::Range<u64>,
                         x: std::ops::Range<u64>|
         -> Result<()> {
            if cancel.load(Ordering::Relaxed) {
                return Err(StoreError::Interrupted);
            }
            let n = (z.end - z.start) * (y.end - y.start) * (x.end - x.start) * es;
            buf.resize(n as usize, 0u8);
            src.read_region(0, z, y, x, &mut buf)?;
            f.write_all(&buf).at(&tmp)?;
            progress.inc(n);
            Ok(())
        };
        if slice <= slab {
            let per = (slab / slice).clamp(1, dz);
            for z0 in (0..dz).step_by(per as usize) {
                piece(z0..(z0 + per).min(dz), 0..dy, 0..dx)?;
            }
        } else if row <= slab {
            let per = (slab / row).clamp(1, dy);
            for z in 0..dz {
                for y0 in (0..dy).step_by(per as usize) {
                    piece(z..z + 1, y0..(y0 + per).min(dy), 0..dx)?;
                }
            }
        } else {
            let per = (slab / es).clamp(1, dx);
            for z in 0..dz {
                for y in 0..dy {
                    for x0 in (0..dx).step_by(per as usize) {
                        piece(z..z + 1, y..y + 1, x0..(x0 + per).min(dx))?;
                    }
                }
            }
        }
        f.flush().at(&tmp)
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }

    opts.write_sidecar(&RawOptions::sidecar_path(path))?;
    std::fs::rename(&tmp, path).at(path)?;
    Ok(())
}

/// Parse a size: `256` (a cube) or `XxYxZ`. Returns `[z, y, x]`.
pub fn parse_size(s: &str) -> std::result::Result<Dims3, String> {
    let parts: Vec<&str> = s.split(['x', 'X', ',']).collect();
    let nums: std::result::Result<Vec<u64>, _> =
        parts.iter().map(|p| p.trim().parse::<u64>()).collect();
    match nums {
        Ok(v) if v.len() == 1 && v[0] > 0 => Ok([v[0]; 3]),
        Ok(v) if v.len() == 3 && v.iter().all(|&n| n > 0) => Ok([v[2], v[1], v[0]]),
        _ => Err(format!(
            "expected N or XxYxZ with positive integers, found {s:?}"
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Records the pieces a writer reports.
    struct Pieces(std::sync::Mutex<Vec<u64>>);
    impl crate::Progress for Pieces {
        fn start(&self, _: u64) {}
        fn inc(&self, n: u64) {
            self.0.lock().unwrap().push(n);
        }
    }

    #[test]
    fn raw_files_are_written_in_pieces_within_the_slab() {
        let d = tempfile::tempdir().unwrap();
        let dims = [3, 20, 30];
        let src = Procedural::new(Kind::MarschnerLobb, dims, DType::U16);
        let whole = d.path().join("whole.raw");
        write_raw(&src, &whole, &crate::NoProgress).unwrap();
        let want = std::fs::read(&whole).unwrap();
        assert_eq!(want.len(), 3 * 20 * 30 * 2);
        // Slabs of several slices, of rows, of runs of a row: the same
        // bytes, no piece larger than the slab.
        for slab in [2400u64, 1200, 600, 100, 7] {
            let p = d.path().join(format!("s{slab}.raw"));
            let pieces = Pieces(Default::default());
            write_raw_within(&src, &p, &pieces, slab, &AtomicBool::new(false)).unwrap();
            assert_eq!(std::fs::read(&p).unwrap(), want, "slab {slab}");
            let pieces = pieces.0.into_inner().unwrap();
            assert!(
                pieces.iter().all(|&n| n <= slab.max(2)),
                "slab {slab}: {pieces:?}"
            );
            assert_eq!(pieces.iter().sum::<u64>(), want.len() as u64);
        }
        // Cancelled: an error, and neither the file nor its temporary
        // one left.
        let p = d.path().join("c.raw");
        let e = write_raw_within(&src, &p, &crate::NoProgress, 600, &AtomicBool::new(true));
        assert!(matches!(e, Err(StoreError::Interrupted)), "{e:?}");
        let left: Vec<_> = std::fs::read_dir(d.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .filter(|n| n.starts_with("c.raw"))
            .collect();
        assert!(left.is_empty(), "{left:?}");
    }

    #[test]
    fn mandelbulb_has_inside_and_outside() {
        assert_eq!(mandelbulb(0.0, 0.0, 0.0), 1.0);
        assert!(mandelbulb(1.19, 1.19, 1.19) < 0.2);
    }

    #[test]
    fn marschner_lobb_in_range() {
        for i in 0..50 {
            let t = i as f64 / 49.0 * 2.0 - 1.0;
            let v = marschner_lobb(t, -t * 0.3, t * 0.7);
            assert!((0.0..=1.0).contains(&v));
        }
    }

    #[test]
    fn region_equals_pointwise() {
        let p = Procedural::new(Kind::Mandelbulb, [7, 9, 11], DType::U16);
        let mut out = vec![0u8; 3 * 4 * 5 * 2];
        p.read_region(0, 2..5, 3..7, 4..9, &mut out).unwrap();
        let v: &[u16] = brickyard_core::cast_slice(&out);
        let mut i = 0;
        for z in 2..5 {
            for y in 3..7 {
                for x in 4..9 {
                    assert_eq!(v[i], to_sample::<u16>(p.value(z, y, x)));
                    i += 1;
                }
            }
        }
        assert_eq!(parse_size("5x6x7").unwrap(), [7, 6, 5]);
        assert!(parse_size("5x6").is_err());
    }
}
