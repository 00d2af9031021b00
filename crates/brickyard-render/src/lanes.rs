//! Four f32 lanes for the per-sample work of one ray on the CPU (the
//! transfer function's four pieces, compositing, the trilinear kernel's
//! lerps). SSE2 on x86-64 (part of the baseline, so no feature detection),
//! plain arrays elsewhere. Every operation is the IEEE operation of the
//! scalar code lane by lane, so results are the same bits as the scalar
//! path's (tested in `optics` and `walk`).

#[cfg(target_arch = "x86_64")]
mod imp {
    use std::arch::x86_64::*;

    #[derive(Clone, Copy, Debug)]
    pub(crate) struct F4(__m128);

    // SAFETY (every `unsafe` below): SSE2 is part of the x86-64 baseline;
    // loads and stores go through references to `[f32; 4]`.
    impl F4 {
        #[inline(always)]
        pub(crate) fn new(a: [f32; 4]) -> F4 {
            F4(unsafe { _mm_loadu_ps(a.as_ptr()) })
        }
        #[inline(always)]
        pub(crate) fn splat(x: f32) -> F4 {
            F4(unsafe { _mm_set1_ps(x) })
        }
        #[inline(always)]
        pub(crate) fn to_array(self) -> [f32; 4] {
            let mut a = [0.0f32; 4];
            unsafe { _mm_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }
        /// Lane 0.
        #[inline(always)]
        pub(crate) fn first(self) -> f32 {
            unsafe { _mm_cvtss_f32(self.0) }
        }
        #[inline(always)]
        pub(crate) fn add(self, b: F4) -> F4 {
            F4(unsafe { _mm_add_ps(self.0, b.0) })
        }
        #[inline(always)]
        pub(crate) fn sub(self, b: F4) -> F4 {
            F4(unsafe { _mm_sub_ps(self.0, b.0) })
        }
        #[inline(always)]
        pub(crate) fn mul(self, b: F4) -> F4 {
            F4(unsafe { _mm_mul_ps(self.0, b.0) })
        }
        /// Per lane `if v < lo { lo } else if v > hi { hi } else { v }`
        /// for `lo ≤ hi` (NaN stays NaN, as in the scalar code):
        /// `maxps`/`minps` return their second operand when either is NaN.
        #[inline(always)]
        pub(crate) fn clamp(self, lo: F4, hi: F4) -> F4 {
            F4(unsafe { _mm_min_ps(hi.0, _mm_max_ps(lo.0, self.0)) })
        }
        /// Lane 0 of `b`, lanes 1–3 of `self`.
        #[inline(always)]
        pub(crate) fn with_first(self, b: F4) -> F4 {
            F4(unsafe { _mm_move_ss(self.0, b.0) })
        }
        /// `[self₀, self₂, b₀, b₂]` and `[self₁, self₃, b₁, b₃]`: the even
        /// and the odd elements of the eight.
        #[inline(always)]
        pub(crate) fn deinterleave(self, b: F4) -> (F4, F4) {
            unsafe {
                (
                    F4(_mm_shuffle_ps::<0b10_00_10_00>(self.0, b.0)),
                    F4(_mm_shuffle_ps::<0b11_01_11_01>(self.0, b.0)),
                )
            }
        }
        /// Lane 1 as lane 0 (the others unspecified).
        #[inline(always)]
        pub(crate) fn second(self) -> f32 {
            unsafe { _mm_cvtss_f32(_mm_shuffle_ps::<0b01_01_01_01>(self.0, self.0)) }
        }
        /// The eight corners `c[4·dz + 2·dy + dx]` of a trilinear sample
        /// of bytes at `p` (strides `sz`, `sy`; x: 1) as f32: `c[0..4]`
        /// and `c[4..8]`.
        ///
        /// # Safety
        /// `p .. p + sz + sy + 2` must be readable.
        #[inline(always)]
        pub(crate) unsafe fn corners_u8(p: *const u8, sz: usize, sy: usize) -> (F4, F4) {
            unsafe {
                let r = |o: usize| p.add(o).cast::<u16>().read_unaligned() as u64;
                let w = r(0) | r(sy) << 16 | r(sz) << 32 | r(sz + sy) << 48;
                let z = _mm_setzero_si128();
                let b16 = _mm_unpacklo_epi8(_mm_cvtsi64_si128(w as i64), z);
                (
                    F4(_mm_cvtepi32_ps(_mm_unpacklo_epi16(b16, z))),
                    F4(_mm_cvtepi32_ps(_mm_unpackhi_epi16(b16, z))),
                )
            }
        }

        /// [`corners_u8`](Self::corners_u8) of 16-bit values.
        ///
        /// # Safety
        /// `p .. p + sz + sy + 2` (in elements) must be readable.
        #[inline(always)]
        pub(crate) unsafe fn corners_u16(p: *const u16, sz: usize, sy: usize) -> (F4, F4) {
            unsafe {
                let r = |o: usize| p.add(o).cast::<u32>().read_unaligned() as u64;
                let lo = r(0) | r(sy) << 32;
                let hi = r(sz) | r(sz + sy) << 32;
                let v = _mm_set_epi64x(hi as i64, lo as i64);
                let z = _mm_setzero_si128();
                (
                    F4(_mm_cvtepi32_ps(_mm_unpacklo_epi16(v, z))),
                    F4(_mm_cvtepi32_ps(_mm_unpackhi_epi16(v, z))),
                )
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod imp {
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct F4([f32; 4]);

    impl F4 {
        #[inline(always)]
        pub(crate) fn new(a: [f32; 4]) -> F4 {
            F4(a)
        }
        #[inline(always)]
        pub(crate) fn splat(x: f32) -> F4 {
            F4([x; 4])
        }
        #[inline(always)]
        pub(crate) fn to_array(self) -> [f32; 4] {
            self.0
        }
        #[inline(always)]
        pub(crate) fn first(self) -> f32 {
            self.0[0]
        }
        #[inline(always)]
        pub(crate) fn add(self, b: F4) -> F4 {
            F4(std::array::from_fn(|i| self.0[i] + b.0[i]))
        }
        #[inline(always)]
        pub(crate) fn sub(self, b: F4) -> F4 {
            F4(std::array::from_fn(|i| self.0[i] - b.0[i]))
        }
        #[inline(always)]
        pub(crate) fn mul(self, b: F4) -> F4 {
            F4(std::array::from_fn(|i| self.0[i] * b.0[i]))
        }
        #[inline(always)]
        pub(crate) fn clamp(self, lo: F4, hi: F4) -> F4 {
            F4(std::array::from_fn(|i| {
                let v = self.0[i];
                if v < lo.0[i] {
                    lo.0[i]
                } else if v > hi.0[i] {
                    hi.0[i]
                } else {
                    v
                }
            }))
        }
        #[inline(always)]
        pub(crate) fn with_first(self, b: F4) -> F4 {
            let mut a = self.0;
            a[0] = b.0[0];
            F4(a)
        }
        #[inline(always)]
        pub(crate) fn deinterleave(self, b: F4) -> (F4, F4) {
            let (a, b) = (self.0, b.0);
            (F4([a[0], a[2], b[0], b[2]]), F4([a[1], a[3], b[1], b[3]]))
        }
        #[inline(always)]
        pub(crate) fn second(self) -> f32 {
            self.0[1]
        }

        /// # Safety
        /// `p .. p + sz + sy + 2` must be readable.
        #[inline(always)]
        pub(crate) unsafe fn corners_u8(p: *const u8, sz: usize, sy: usize) -> (F4, F4) {
            let c = |o: usize| unsafe { *p.add(o) } as f32;
            (
                F4([c(0), c(1), c(sy), c(sy + 1)]),
                F4([c(sz), c(sz + 1), c(sz + sy), c(sz + sy + 1)]),
            )
        }

        /// # Safety
        /// `p .. p + sz + sy + 2` must be readable.
        #[inline(always)]
        pub(crate) unsafe fn corners_u16(p: *const u16, sz: usize, sy: usize) -> (F4, F4) {
            let c = |o: usize| unsafe { *p.add(o) } as f32;
            (
                F4([c(0), c(1), c(sy), c(sy + 1)]),
                F4([c(sz), c(sz + 1), c(sz + sy), c(sz + sy + 1)]),
            )
        }
    }
}

pub(crate) use imp::F4;

impl F4 {
    /// `a + (b − a)·t` per lane: the scalar lerp of the trilinear formula
    /// (without its skip of a zero fraction).
    #[inline(always)]
    pub(crate) fn lerp(self, b: F4, t: F4) -> F4 {
        self.add(b.sub(self).mul(t))
    }

    /// [`brickyard_core::trilinear`] without its skip of zero fractions
    /// (integer volumes) of the corners `c[0..4]`, `c[4..8]` at fractions
    /// `[fz, fy, fx]`: the four lerps along x in one, the two along y in
    /// one, then z; each lane the scalar operations, so the same bits.
    #[inline(always)]
    pub(crate) fn trilinear(lo: F4, hi: F4, f: [f32; 3]) -> f32 {
        // [c0, c2, c4, c6] and [c1, c3, c5, c7] → [x00, x01, x10, x11].
        let (even, odd) = lo.deinterleave(hi);
        let x = even.lerp(odd, F4::splat(f[2]));
        // [x00, x10, ·, ·] and [x01, x11, ·, ·] → [y0, y1, ·, ·].
        let (e, o) = x.deinterleave(x);
        let y = e.lerp(o, F4::splat(f[1]));
        let (y0, y1) = (y.first(), y.second());
        y0 + (y1 - y0) * f[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lanes_do_the_scalar_operations() {
        let a = F4::new([1.5, -2.0, 3.25, 0.1]);
        let b = F4::new([0.5, 4.0, -1.0, 0.7]);
        assert_eq!(a.add(b).to_array(), [2.0, 2.0, 2.25, 0.1f32 + 0.7]);
        assert_eq!(a.sub(b).to_array(), [1.0, -6.0, 4.25, 0.1f32 - 0.7]);
        assert_eq!(a.mul(b).to_array(), [0.75, -8.0, -3.25, 0.1f32 * 0.7]);
        assert_eq!(a.first(), 1.5);
        assert_eq!(a.second(), -2.0);
        assert_eq!(a.with_first(b).to_array(), [0.5, -2.0, 3.25, 0.1]);
        let (e, o) = a.deinterleave(b);
        assert_eq!(e.to_array(), [1.5, 3.25, 0.5, -1.0]);
        assert_eq!(o.to_array(), [-2.0, 0.1, 4.0, 0.7]);
        let lo = F4::new([0.0, 0.0, 0.0, 0.0]);
        let hi = F4::new([1.0, 1.0, 1.0, 1.0]);
        let c = F4::new([-1.0, 0.5, 2.0, f32::NAN]).clamp(lo, hi).to_array();
        assert_eq!(c[..3], [0.0, 0.5, 1.0]);
        assert!(c[3].is_nan(), "NaN stays NaN as in the scalar clamp");
        let t = F4::splat(0.25);
        assert_eq!(a.lerp(b, t).to_array()[0], 1.5 + (0.5 - 1.5) * 0.25);
    }
}
