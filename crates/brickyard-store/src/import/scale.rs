//! Linear rescaling of stored numbers into the values a file means:
//! `value = slope · stored + inter` (NIfTI's `scl_slope`/`scl_inter`).
//!
//! The choice of the type that holds the values, [`choose_dtype`]:
//!
//! * float input keeps its type (float32 stays float32, float64 float64);
//! * integer input with an integer slope and intercept stays integer when the
//!   rescaled values fit an integer type: the stored type if they fit it,
//!   else the narrowest wider type that holds them (`uint8` with intercept
//!   −1024 becomes `int16`). Whether they fit is judged over the range of the
//!   stored type or, better, over the range of the numbers actually stored
//!   when the caller has scanned it ([`Choice::NeedsRange`] asks for that
//!   only when the answer can depend on it);
//! * anything else becomes float: float32 for 8- and 16-bit input, float64
//!   for 32-bit input (float32 would round stored integers above 2²⁴).
//!
//! The arithmetic follows nibabel's `get_fdata()`: for float output the
//! product and sum are taken in float64 (the multiplication is skipped for a
//! slope of 1, the addition for an intercept of 0) and rounded once to the
//! output type; integer output is computed exactly in 64-bit integers.

use brickyard_core::DType;
use serde::Serialize;

/// A rescale a file asks for and what the importer did with it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ValueScaling {
    /// Names of the header fields holding slope and intercept.
    pub fields: [&'static str; 2],
    pub slope: f64,
    pub inter: f64,
    /// Type of the numbers in the file.
    pub stored: DType,
    /// Type of the values the importer returns (`stored` when not applied).
    pub dtype: DType,
    /// Whether the rescale is applied (`false`: raw values were asked for).
    pub applied: bool,
    /// `[min, max]` of the stored numbers when they were scanned to choose
    /// `dtype`.
    pub scanned: Option<[f64; 2]>,
}

impl ValueScaling {
    /// One line for reports, e.g. `values scaled by scl_slope=1,
    /// scl_inter=-1024 (int16 kept)`.
    pub fn describe(&self) -> String {
        let fields = format!(
            "{}={}, {}={}",
            self.fields[0],
            num(self.slope),
            self.fields[1],
            num(self.inter)
        );
        if !self.applied {
            return format!(
                "values kept as stored ({}): {fields} not applied (raw values asked for)",
                self.stored.zarr_name()
            );
        }
        let what = if self.dtype == self.stored {
            format!("{} kept", self.stored.zarr_name())
        } else if self.dtype.is_float() {
            format!("{} → {}", self.stored.zarr_name(), self.dtype.zarr_name())
        } else {
            format!(
                "{} → {}, exact",
                self.stored.zarr_name(),
                self.dtype.zarr_name()
            )
        };
        let scan = match self.scanned {
            Some([lo, hi]) => format!("; stored numbers span {}..{}", num(lo), num(hi)),
            None => String::new(),
        };
        format!("values scaled by {fields} ({what}{scan})")
    }

    /// Rescale `src`, native-endian numbers of type `stored`, into `out`,
    /// native-endian values of type `dtype`. Does nothing to the numbers
    /// when the rescale is not applied (then the types are equal).
    pub fn apply(&self, src: &[u8], out: &mut [u8]) {
        assert_eq!(
            src.len() / self.stored.size(),
            out.len() / self.dtype.size()
        );
        if !self.applied {
            out.copy_from_slice(src);
            return;
        }
        let op = self.op();
        brickyard_core::dispatch_dtype!(self.stored, S => {
            brickyard_core::dispatch_dtype!(self.dtype, O => {
                for (s, o) in src
                    .chunks_exact(S::N)
                    .zip(out.chunks_exact_mut(O::N))
                {
                    op.map::<S, O>(S::get(s)).put(o);
                }
            })
        })
    }

    /// [`apply`](Self::apply) in place, for types of the same size.
    pub fn apply_in_place(&self, buf: &mut [u8]) {
        assert_eq!(self.stored.size(), self.dtype.size());
        if !self.applied {
            return;
        }
        let op = self.op();
        brickyard_core::dispatch_dtype!(self.stored, S => {
            brickyard_core::dispatch_dtype!(self.dtype, O => {
                for b in buf.chunks_exact_mut(S::N) {
                    op.map::<S, O>(S::get(b)).put(b);
                }
            })
        })
    }

    fn op(&self) -> Op {
        if self.dtype.is_float() {
            Op::Float {
                slope: self.slope,
                inter: self.inter,
            }
        } else {
            Op::Int {
                slope: self.slope as i64,
                inter: self.inter as i64,
            }
        }
    }
}

/// Whether `slope`/`inter` ask for a rescale at all: `None` when the slope is
/// 0 or not finite (no scaling) or the pair is the identity `(1, 0)`, as
/// nibabel reads them.
pub fn effective(slope: f64, inter: f64) -> Option<(f64, f64)> {
    if slope == 0.0 || !slope.is_finite() || (slope == 1.0 && inter == 0.0) {
        None
    } else {
        Some((slope, inter))
    }
}

/// The range of every value of an integer type (`None` for floats).
pub fn int_range(t: DType) -> Option<(i64, i64)> {
    Some(match t {
        DType::U8 => (0, u8::MAX as i64),
        DType::I8 => (i8::MIN as i64, i8::MAX as i64),
        DType::U16 => (0, u16::MAX as i64),
        DType::I16 => (i16::MIN as i64, i16::MAX as i64),
        DType::U32 => (0, u32::MAX as i64),
        DType::I32 => (i32::MIN as i64, i32::MAX as i64),
        DType::F32 | DType::F64 => return None,
    })
}

/// Whether the rescale maps integers to integers exactly (integer slope and
/// intercept small enough for exact 64-bit arithmetic).
pub fn is_integer_map(slope: f64, inter: f64) -> bool {
    let ok = |v: f64| v.is_finite() && v.fract() == 0.0 && v.abs() <= (1u64 << 24) as f64;
    ok(slope) && ok(inter)
}

/// Result of [`choose_dtype`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Choice {
    /// This type holds every rescaled value.
    Type(DType),
    /// The rescaled range of the stored type does not fit the stored type,
    /// but the numbers actually stored might: scan them and ask again.
    NeedsRange,
}

/// The type of the rescaled values of `stored` numbers (see the [module
/// docs](self)); `range` is `[min, max]` of the numbers actually stored,
/// when known.
pub fn choose_dtype(stored: DType, slope: f64, inter: f64, range: Option<[f64; 2]>) -> Choice {
    let Some((tlo, thi)) = int_range(stored) else {
        return Choice::Type(stored);
    };
    let float = if stored.size() >= 4 {
        DType::F64
    } else {
        DType::F32
    };
    if !is_integer_map(slope, inter) {
        return Choice::Type(float);
    }
    let (s, i) = (slope as i64, inter as i64);
    let (lo, hi) = match range {
        Some([lo, hi]) => (lo as i64, hi as i64),
        None => (tlo, thi),
    };
    let (a, b) = (s * lo + i, s * hi + i);
    let (lo, hi) = (a.min(b), a.max(b));
    let fits = |t: DType| int_range(t).is_some_and(|(l, h)| l <= lo && hi <= h);
    if fits(stored) {
        return Choice::Type(stored);
    }
    // The narrowest type that holds them (at least as wide as the stored
    // one), the stored signedness first.
    let signed = matches!(stored, DType::I8 | DType::I16 | DType::I32);
    let order: &[DType] = if signed {
        &[
            DType::I8,
            DType::U8,
            DType::I16,
            DType::U16,
            DType::I32,
            DType::U32,
        ]
    } else {
        &[
            DType::U8,
            DType::I8,
            DType::U16,
            DType::I16,
            DType::U32,
            DType::I32,
        ]
    };
    let pick = order
        .iter()
        .copied()
        .filter(|t| t.size() >= stored.size())
        .find(|&t| fits(t));
    if range.is_none() {
        // Over the type's range the values overflow the stored type. The
        // numbers actually stored may do better, unless no stored number
        // maps into the stored type at all and the type's range already
        // fits the next size up (uint8 with intercept −1024: int16).
        let never_fits = hi < tlo || lo > thi;
        match pick {
            Some(t) if never_fits && t.size() == 2 * stored.size() => {}
            _ => return Choice::NeedsRange,
        }
    }
    pick.map_or(Choice::Type(float), Choice::Type)
}

/// A number as people write it: a value that came from a float32 header
/// field prints as that float32 (`0.1`, not `0.10000000149011612`).
pub(crate) fn num(v: f64) -> String {
    let f = v as f32;
    if f as f64 == v {
        format!("{f}")
    } else {
        format!("{v}")
    }
}

#[derive(Clone, Copy)]
enum Op {
    Int { slope: i64, inter: i64 },
    Float { slope: f64, inter: f64 },
}

impl Op {
    #[inline(always)]
    fn map<S: Num, O: Num>(self, v: S) -> O {
        match self {
            Op::Int { slope, inter } => O::from_i64(v.to_i64() * slope + inter),
            Op::Float { slope, inter } => {
                let mut x = v.to_f64();
                if slope != 1.0 {
                    x *= slope;
                }
                if inter != 0.0 {
                    x += inter;
                }
                O::from_f64(x)
            }
        }
    }
}

/// Native-endian access and conversions of the voxel types.
trait Num: Copy {
    const N: usize;
    fn get(b: &[u8]) -> Self;
    fn put(self, b: &mut [u8]);
    fn to_i64(self) -> i64;
    fn to_f64(self) -> f64;
    fn from_i64(v: i64) -> Self;
    fn from_f64(v: f64) -> Self;
}

macro_rules! num {
    ($($t:ty),*) => {$(
        impl Num for $t {
            const N: usize = std::mem::size_of::<$t>();
            #[inline(always)]
            fn get(b: &[u8]) -> Self {
                <$t>::from_ne_bytes(b.try_into().expect("element size"))
            }
            #[inline(always)]
            fn put(self, b: &mut [u8]) {
                b.copy_from_slice(&self.to_ne_bytes());
            }
            #[inline(always)]
            fn to_i64(self) -> i64 {
                self as i64
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                self as f64
            }
            #[inline(always)]
            fn from_i64(v: i64) -> Self {
                v as $t
            }
            #[inline(always)]
            fn from_f64(v: f64) -> Self {
                v as $t
            }
        }
    )*};
}
num!(u8, i8, u16, i16, u32, i32, f32, f64);

#[cfg(test)]
mod tests {
    use super::*;

    fn scaling(stored: DType, dtype: DType, slope: f64, inter: f64) -> ValueScaling {
        ValueScaling {
            fields: ["scl_slope", "scl_inter"],
            slope,
            inter,
            stored,
            dtype,
            applied: true,
            scanned: None,
        }
    }

    #[test]
    fn effective_follows_nibabel() {
        assert_eq!(effective(0.0, -1024.0), None, "slope 0: no scaling");
        assert_eq!(effective(f64::NAN, 5.0), None);
        assert_eq!(effective(f64::INFINITY, 5.0), None);
        assert_eq!(effective(1.0, 0.0), None, "identity");
        assert_eq!(effective(1.0, -1024.0), Some((1.0, -1024.0)));
        assert_eq!(effective(0.5, 0.0), Some((0.5, 0.0)));
        assert_eq!(effective(-1.0, 0.0), Some((-1.0, 0.0)));
    }

    #[test]
    fn integer_types_kept_widened_or_scanned() {
        use Choice::*;
        // int16 CT: the whole int16 range shifted by -1024 does not fit
        // int16, the stored numbers (0..4095) do.
        assert_eq!(choose_dtype(DType::I16, 1.0, -1024.0, None), NeedsRange);
        assert_eq!(
            choose_dtype(DType::I16, 1.0, -1024.0, Some([0.0, 4095.0])),
            Type(DType::I16)
        );
        assert_eq!(
            choose_dtype(DType::I16, 1.0, -1024.0, Some([-32768.0, 100.0])),
            Type(DType::I32)
        );
        // uint8 minus 1024: int16 whatever the stored numbers, so no scan.
        assert_eq!(
            choose_dtype(DType::U8, 1.0, -1024.0, None),
            Type(DType::I16)
        );
        assert_eq!(
            choose_dtype(DType::U8, 2.0, -1024.0, None),
            Type(DType::I16)
        );
        assert_eq!(
            choose_dtype(DType::U8, 1.0, -1024.0, Some([0.0, 255.0])),
            Type(DType::I16)
        );
        // int8 plus 128 over its whole range: uint8 (same size).
        assert_eq!(choose_dtype(DType::I8, 1.0, 128.0, None), NeedsRange);
        assert_eq!(
            choose_dtype(DType::I8, 1.0, 128.0, Some([-128.0, 127.0])),
            Type(DType::U8)
        );
        // int16 times 4 never fits int16 over its range, but int32 is two
        // sizes up: the stored numbers decide.
        assert_eq!(choose_dtype(DType::I16, 4.0, 0.0, None), NeedsRange);
        // Disjoint from the stored type but beyond the next size: scan.
        assert_eq!(choose_dtype(DType::U8, 1.0, 70000.0, None), NeedsRange);
        assert_eq!(
            choose_dtype(DType::U8, 1.0, 70000.0, Some([0.0, 3.0])),
            Type(DType::U32)
        );
        // uint8 plus 10: uint8 kept when the stored numbers leave room.
        assert_eq!(
            choose_dtype(DType::U8, 1.0, 10.0, Some([0.0, 200.0])),
            Type(DType::U8)
        );
        assert_eq!(
            choose_dtype(DType::U8, 1.0, 10.0, Some([0.0, 250.0])),
            Type(DType::U16)
        );
        // Fits the stored type over its whole range: no scan needed.
        assert_eq!(choose_dtype(DType::I8, 1.0, 0.5, None), Type(DType::F32));
        assert_eq!(choose_dtype(DType::U8, 2.0, 0.0, None), NeedsRange);
        assert_eq!(choose_dtype(DType::I32, 1.0, 0.0, None), Type(DType::I32));
        assert_eq!(choose_dtype(DType::U16, -1.0, 0.0, None), NeedsRange);
        assert_eq!(
            choose_dtype(DType::U16, -1.0, 0.0, Some([0.0, 65535.0])),
            Type(DType::I32)
        );
        // Negative slope on int16 over a small range: kept.
        assert_eq!(
            choose_dtype(DType::I16, -1.0, 0.0, Some([-100.0, 100.0])),
            Type(DType::I16)
        );
        // Beyond 32 bits: float64.
        assert_eq!(
            choose_dtype(DType::U32, 4.0, 0.0, Some([0.0, 4e9])),
            Type(DType::F64)
        );
    }

    #[test]
    fn fractions_make_floats() {
        use Choice::*;
        assert_eq!(choose_dtype(DType::I16, 0.5, 3.25, None), Type(DType::F32));
        assert_eq!(choose_dtype(DType::U8, 1.0, 0.5, None), Type(DType::F32));
        assert_eq!(choose_dtype(DType::U16, 0.1, 0.0, None), Type(DType::F32));
        assert_eq!(choose_dtype(DType::I32, 0.5, 0.0, None), Type(DType::F64));
        assert_eq!(choose_dtype(DType::U32, 0.5, 0.0, None), Type(DType::F64));
        assert_eq!(choose_dtype(DType::F32, 2.0, 1.0, None), Type(DType::F32));
        assert_eq!(choose_dtype(DType::F64, 0.5, 1.0, None), Type(DType::F64));
        assert_eq!(
            choose_dtype(DType::I16, 1e12, 0.0, None),
            Type(DType::F32),
            "slope too large for exact integer arithmetic"
        );
    }

    fn ne<T: Copy, const N: usize>(v: &[T], f: impl Fn(T) -> [u8; N]) -> Vec<u8> {
        v.iter().flat_map(|x| f(*x)).collect()
    }

    #[test]
    fn apply_int16_to_int16_and_widened() {
        let stored: Vec<i16> = vec![0, 1, 1024, 4095, -5];
        let src = ne(&stored, i16::to_ne_bytes);
        let s = scaling(DType::I16, DType::I16, 1.0, -1024.0);
        let mut out = src.clone();
        s.apply_in_place(&mut out);
        assert_eq!(
            out,
            ne(&[-1024i16, -1023, 0, 3071, -1029], i16::to_ne_bytes)
        );
        let mut out2 = vec![0u8; src.len()];
        s.apply(&src, &mut out2);
        assert_eq!(out2, out);

        let u: Vec<u8> = vec![0, 7, 255];
        let s = scaling(DType::U8, DType::I16, 2.0, -1024.0);
        let mut out = vec![0u8; 6];
        s.apply(&u, &mut out);
        assert_eq!(out, ne(&[-1024i16, -1010, -514], i16::to_ne_bytes));
    }

    #[test]
    fn apply_to_floats() {
        let stored: Vec<i16> = vec![-3, 0, 1, 1000];
        let s = scaling(DType::I16, DType::F32, 0.5, 3.25);
        let mut out = vec![0u8; 16];
        s.apply(&ne(&stored, i16::to_ne_bytes), &mut out);
        assert_eq!(out, ne(&[1.75f32, 3.25, 3.75, 503.25], f32::to_ne_bytes));

        // float32 in place, computed in float64 and rounded once.
        let v = [0.1f32, -2.0, f32::NAN];
        let s = scaling(DType::F32, DType::F32, 3.0, 0.1);
        let mut buf = ne(&v, f32::to_ne_bytes);
        s.apply_in_place(&mut buf);
        let got: Vec<f32> = buf
            .chunks_exact(4)
            .map(|b| f32::from_ne_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(got[0], (0.1f32 as f64 * 3.0 + 0.1) as f32);
        assert_eq!(got[1], (-6.0f64 + 0.1) as f32);
        assert!(got[2].is_nan());

        // A slope of 1 leaves -0.0 alone (no multiplication); intercept 0 too.
        let s = scaling(DType::F64, DType::F64, 2.0, 0.0);
        let mut buf = (-0.0f64).to_ne_bytes().to_vec();
        s.apply_in_place(&mut buf);
        assert_eq!(
            f64::from_ne_bytes(buf.try_into().unwrap()).to_bits(),
            (-0.0f64).to_bits()
        );

        // int32 → float64 keeps large integers exact.
        let s = scaling(DType::I32, DType::F64, 0.5, 0.0);
        let mut out = vec![0u8; 8];
        s.apply(&(16_777_217i32).to_ne_bytes(), &mut out);
        assert_eq!(f64::from_ne_bytes(out.try_into().unwrap()), 8_388_608.5);
    }

    #[test]
    fn not_applied_copies() {
        let mut s = scaling(DType::I16, DType::I16, 1.0, -1024.0);
        s.applied = false;
        let src = ne(&[5i16, 6], i16::to_ne_bytes);
        let mut out = vec![0u8; 4];
        s.apply(&src, &mut out);
        assert_eq!(out, src);
        assert!(s.describe().contains("not applied"), "{}", s.describe());
    }

    #[test]
    fn descriptions() {
        let s = scaling(DType::I16, DType::I16, 1.0, -1024.0);
        assert_eq!(
            s.describe(),
            "values scaled by scl_slope=1, scl_inter=-1024 (int16 kept)"
        );
        let s = scaling(DType::I16, DType::F32, 0.1f32 as f64, 3.25);
        assert_eq!(
            s.describe(),
            "values scaled by scl_slope=0.1, scl_inter=3.25 (int16 → float32)"
        );
        let mut s = scaling(DType::U8, DType::I16, 1.0, -1024.0);
        s.scanned = Some([0.0, 130.0]);
        assert_eq!(
            s.describe(),
            "values scaled by scl_slope=1, scl_inter=-1024 (uint8 → int16, exact; stored \
             numbers span 0..130)"
        );
    }
}
