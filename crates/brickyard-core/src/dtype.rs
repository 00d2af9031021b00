//! Voxel data types. Values are kept as they are: no silent quantization.

use serde::{Deserialize, Serialize};
use std::fmt;

/// A voxel data type.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl DType {
    pub const ALL: [DType; 8] = [
        DType::U8,
        DType::I8,
        DType::U16,
        DType::I16,
        DType::U32,
        DType::I32,
        DType::F32,
        DType::F64,
    ];

    /// Bytes per voxel.
    pub fn size(self) -> usize {
        match self {
            DType::U8 | DType::I8 => 1,
            DType::U16 | DType::I16 => 2,
            DType::U32 | DType::I32 | DType::F32 => 4,
            DType::F64 => 8,
        }
    }

    /// The Zarr v3 data type name.
    pub fn zarr_name(self) -> &'static str {
        match self {
            DType::U8 => "uint8",
            DType::I8 => "int8",
            DType::U16 => "uint16",
            DType::I16 => "int16",
            DType::U32 => "uint32",
            DType::I32 => "int32",
            DType::F32 => "float32",
            DType::F64 => "float64",
        }
    }

    /// Short name used on the command line (`u8`, `i16`, `f32`, ...).
    pub fn short_name(self) -> &'static str {
        match self {
            DType::U8 => "u8",
            DType::I8 => "i8",
            DType::U16 => "u16",
            DType::I16 => "i16",
            DType::U32 => "u32",
            DType::I32 => "i32",
            DType::F32 => "f32",
            DType::F64 => "f64",
        }
    }

    /// Parse a data type from the many spellings found in the wild:
    /// `u8`, `uint8`, `uchar`, `unsigned short`, `<u2`, `float32`, `float`, ...
    /// Returns `None` for anything unknown.
    pub fn parse(s: &str) -> Option<DType> {
        let t = s.trim().to_ascii_lowercase();
        let t = t.trim_start_matches(['<', '>', '|', '=']);
        Some(match t {
            "u8" | "uint8" | "uint8_t" | "uchar" | "unsigned char" | "b1" | "u1" => DType::U8,
            "i8" | "int8" | "int8_t" | "signed char" | "char" | "i1" => DType::I8,
            "u16" | "uint16" | "uint16_t" | "ushort" | "unsigned short" | "unsigned short int"
            | "u2" => DType::U16,
            "i16" | "int16" | "int16_t" | "short" | "short int" | "signed short"
            | "signed short int" | "i2" => DType::I16,
            "u32" | "uint32" | "uint32_t" | "uint" | "unsigned int" | "u4" => DType::U32,
            "i32" | "int32" | "int32_t" | "int" | "signed int" | "i4" => DType::I32,
            "f32" | "float32" | "float" | "f4" => DType::F32,
            "f64" | "float64" | "double" | "f8" => DType::F64,
            _ => return None,
        })
    }

    #[inline]
    pub const fn is_float(self) -> bool {
        matches!(self, DType::F32 | DType::F64)
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.short_name())
    }
}

/// A voxel value type. Implemented for every [`DType`].
pub trait Sample:
    Copy + PartialOrd + PartialEq + Send + Sync + Default + fmt::Debug + 'static
{
    const DTYPE: DType;
    fn to_f64(self) -> f64;
    /// `self.to_f64() as f32`, in one conversion (the same value: both
    /// round once).
    #[inline]
    fn to_f32(self) -> f32 {
        self.to_f64() as f32
    }
    /// Box mean of `count` voxels whose sum is `sum`, rounded as documented in
    /// `docs/FORMAT.md`: integers round half up (`floor(sum/count + 1/2)`,
    /// exact in integer arithmetic), floats are the f64 mean cast to the type.
    fn mean(sum: Self::Acc, count: u32) -> Self;
    /// Accumulator for sums of up to 2^16 values.
    type Acc: Copy + Default + std::ops::AddAssign + Send + Sync;
    fn acc(self) -> Self::Acc;
    /// Read from little-endian bytes.
    fn from_le(b: &[u8]) -> Self;
    /// Raw bits for exact comparison and mode computation (bit-pattern equality).
    fn bits(self) -> u64;
    /// Smallest and largest value of a non-empty slice (NaN ignored; a
    /// slice of only NaN gives NaN). Written to vectorize.
    fn min_max(s: &[Self]) -> (Self, Self);
}

macro_rules! int_sample {
    ($t:ty, $d:expr, $acc:ty) => {
        impl Sample for $t {
            const DTYPE: DType = $d;
            type Acc = $acc;
            #[inline]
            fn to_f64(self) -> f64 {
                self as f64
            }
            #[inline]
            fn to_f32(self) -> f32 {
                self as f32
            }
            #[inline]
            fn acc(self) -> $acc {
                self as $acc
            }
            #[inline]
            fn mean(sum: $acc, count: u32) -> Self {
                let c = count as $acc;
                // floor((2*sum + c) / (2*c)) with floor division (exact, half up).
                (2 * sum + c).div_euclid(2 * c) as $t
            }
            #[inline]
            fn from_le(b: &[u8]) -> Self {
                <$t>::from_le_bytes(b[..std::mem::size_of::<$t>()].try_into().unwrap())
            }
            #[inline]
            fn bits(self) -> u64 {
                self as u64
            }
            #[inline]
            fn min_max(s: &[Self]) -> (Self, Self) {
                let mut mn = <$t>::MAX;
                let mut mx = <$t>::MIN;
                for c in s.chunks(64) {
                    for &v in c {
                        mn = mn.min(v);
                        mx = mx.max(v);
                    }
                }
                (mn, mx)
            }
        }
    };
}
int_sample!(u8, DType::U8, u32);
int_sample!(i8, DType::I8, i32);
int_sample!(u16, DType::U16, u64);
int_sample!(i16, DType::I16, i64);
int_sample!(u32, DType::U32, u64);
int_sample!(i32, DType::I32, i64);

impl Sample for f32 {
    const DTYPE: DType = DType::F32;
    type Acc = f64;
    #[inline]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline]
    fn to_f32(self) -> f32 {
        self
    }
    #[inline]
    fn acc(self) -> f64 {
        self as f64
    }
    #[inline]
    fn mean(sum: f64, count: u32) -> Self {
        (sum / count as f64) as f32
    }
    #[inline]
    fn from_le(b: &[u8]) -> Self {
        f32::from_le_bytes(b[..4].try_into().unwrap())
    }
    #[inline]
    fn bits(self) -> u64 {
        self.to_bits() as u64
    }
    #[inline]
    fn min_max(s: &[Self]) -> (Self, Self) {
        let mut mn = f32::NAN;
        let mut mx = f32::NAN;
        for &v in s {
            // f::min/max return the other operand when one is NaN.
            mn = mn.min(v);
            mx = mx.max(v);
        }
        (mn, mx)
    }
}

impl Sample for f64 {
    const DTYPE: DType = DType::F64;
    type Acc = f64;
    #[inline]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline]
    fn acc(self) -> f64 {
        self
    }
    #[inline]
    fn mean(sum: f64, count: u32) -> Self {
        sum / count as f64
    }
    #[inline]
    fn from_le(b: &[u8]) -> Self {
        f64::from_le_bytes(b[..8].try_into().unwrap())
    }
    #[inline]
    fn bits(self) -> u64 {
        self.to_bits()
    }
    #[inline]
    fn min_max(s: &[Self]) -> (Self, Self) {
        let mut mn = f64::NAN;
        let mut mx = f64::NAN;
        for &v in s {
            // f::min/max return the other operand when one is NaN.
            mn = mn.min(v);
            mx = mx.max(v);
        }
        (mn, mx)
    }
}

/// Call a generic function with the Rust type of a [`DType`]:
/// `dispatch_dtype!(dt, T => { body using T })`.
#[macro_export]
macro_rules! dispatch_dtype {
    ($dt:expr, $T:ident => $body:block) => {
        match $dt {
            $crate::DType::U8 => {
                type $T = u8;
                $body
            }
            $crate::DType::I8 => {
                type $T = i8;
                $body
            }
            $crate::DType::U16 => {
                type $T = u16;
                $body
            }
            $crate::DType::I16 => {
                type $T = i16;
                $body
            }
            $crate::DType::U32 => {
                type $T = u32;
                $body
            }
            $crate::DType::I32 => {
                type $T = i32;
                $body
            }
            $crate::DType::F32 => {
                type $T = f32;
                $body
            }
            $crate::DType::F64 => {
                type $T = f64;
                $body
            }
        }
    };
}

/// Trilinear interpolation of the 8 corner values `c` (`[z][y][x]` order:
/// `c[4·dz + 2·dy + dx]`) at fractions `f = [fz, fy, fx]` in `[0, 1)`: the
/// one formula every sampler uses (the reference, the virtual memory's
/// point lookup and the renderers), so that they agree bit for bit. Lerps
/// along x, then y, then z (`a + (b − a)·t`); with `skip_zero` a fraction
/// of exactly 0 takes the first value as it is, so a NaN on the far side of
/// a voxel centre does not leak into samples that give it no weight (float
/// volumes; integer ones can pass `false`).
#[inline(always)]
pub fn trilinear(c: [f32; 8], f: [f32; 3], skip_zero: bool) -> f32 {
    #[inline(always)]
    fn lerp(a: f32, b: f32, t: f32, skip_zero: bool) -> f32 {
        if skip_zero && t == 0.0 {
            a
        } else {
            a + (b - a) * t
        }
    }
    let x00 = lerp(c[0], c[1], f[2], skip_zero);
    let x01 = lerp(c[2], c[3], f[2], skip_zero);
    let x10 = lerp(c[4], c[5], f[2], skip_zero);
    let x11 = lerp(c[6], c[7], f[2], skip_zero);
    let y0 = lerp(x00, x01, f[1], skip_zero);
    let y1 = lerp(x10, x11, f[1], skip_zero);
    lerp(y0, y1, f[0], skip_zero)
}

/// [`trilinear`] of the corners `corner(dz, dy, dx)` (each 0 or 1).
#[inline(always)]
pub fn trilinear_of(
    corner: impl Fn(usize, usize, usize) -> f32,
    f: [f32; 3],
    skip_zero: bool,
) -> f32 {
    let c = [
        corner(0, 0, 0),
        corner(0, 0, 1),
        corner(0, 1, 0),
        corner(0, 1, 1),
        corner(1, 0, 0),
        corner(1, 0, 1),
        corner(1, 1, 0),
        corner(1, 1, 1),
    ];
    trilinear(c, f, skip_zero)
}

/// View a byte buffer as a slice of samples (native endianness; brickyard
/// only runs on little-endian targets).
pub fn cast_slice<T: Sample>(b: &[u8]) -> &[T] {
    assert_eq!(b.len() % std::mem::size_of::<T>(), 0);
    assert_eq!(
        b.as_ptr() as usize % std::mem::align_of::<T>(),
        0,
        "misaligned buffer"
    );
    // SAFETY: all Sample types are plain old data valid for any bit pattern;
    // length and alignment are checked above.
    unsafe {
        std::slice::from_raw_parts(b.as_ptr() as *const T, b.len() / std::mem::size_of::<T>())
    }
}

/// Mutable version of [`cast_slice`].
pub fn cast_slice_mut<T: Sample>(b: &mut [u8]) -> &mut [T] {
    assert_eq!(b.len() % std::mem::size_of::<T>(), 0);
    assert_eq!(
        b.as_ptr() as usize % std::mem::align_of::<T>(),
        0,
        "misaligned buffer"
    );
    // SAFETY: as in cast_slice.
    unsafe {
        std::slice::from_raw_parts_mut(b.as_mut_ptr() as *mut T, b.len() / std::mem::size_of::<T>())
    }
}

/// View samples as mutable bytes.
pub fn as_bytes_mut<T: Sample>(s: &mut [T]) -> &mut [u8] {
    // SAFETY: plain old data, valid for any bit pattern.
    unsafe { std::slice::from_raw_parts_mut(s.as_mut_ptr() as *mut u8, std::mem::size_of_val(s)) }
}

/// View samples as bytes.
pub fn as_bytes<T: Sample>(s: &[T]) -> &[u8] {
    // SAFETY: plain old data.
    unsafe { std::slice::from_raw_parts(s.as_ptr() as *const u8, std::mem::size_of_val(s)) }
}

#[cfg(not(target_endian = "little"))]
compile_error!("brickyard supports little-endian targets only");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn to_f32_is_to_f64_then_f32() {
        for v in [0u32, 1, 16_777_217, 16_777_219, u32::MAX, 2_147_483_649] {
            assert_eq!(v.to_f32(), v.to_f64() as f32, "{v}");
            let i = v as i32;
            assert_eq!(i.to_f32(), i.to_f64() as f32, "{i}");
        }
        assert_eq!(f64::MAX.to_f32(), f64::MAX.to_f64() as f32);
    }

    #[test]
    fn integer_mean_rounds_half_up() {
        assert_eq!(u8::mean(3, 2), 2); // 1.5 -> 2
        assert_eq!(u8::mean(5, 4), 1); // 1.25 -> 1
        assert_eq!(u8::mean(7, 4), 2); // 1.75 -> 2
        assert_eq!(i16::mean(-3, 2), -1); // -1.5 -> -1 (half up)
        assert_eq!(i16::mean(-5, 4), -1); // -1.25 -> -1
        assert_eq!(i16::mean(-7, 4), -2); // -1.75 -> -2
        assert_eq!(u8::mean(255 * 8, 8), 255);
        assert_eq!(u32::mean(u32::MAX as u64 * 8, 8), u32::MAX);
        assert_eq!(i32::mean(i32::MIN as i64 * 8, 8), i32::MIN);
    }

    #[test]
    fn min_max_ignores_nan() {
        assert_eq!(u16::min_max(&[5, 3, 9, 4]), (3, 9));
        assert_eq!(i8::min_max(&[-5, 3, -9, 4]), (-9, 4));
        assert_eq!(f32::min_max(&[f32::NAN, 2.0, -1.0]), (-1.0, 2.0));
        assert!(f64::min_max(&[f64::NAN]).0.is_nan());
    }

    #[test]
    fn parse_names() {
        assert_eq!(DType::parse("unsigned short"), Some(DType::U16));
        assert_eq!(DType::parse("<u2"), Some(DType::U16));
        assert_eq!(DType::parse("float32"), Some(DType::F32));
        assert_eq!(DType::parse("complex64"), None);
        for d in DType::ALL {
            assert_eq!(DType::parse(d.short_name()), Some(d));
            assert_eq!(DType::parse(d.zarr_name()), Some(d));
        }
    }
}
