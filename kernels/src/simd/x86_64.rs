//! x86-64: the vector types of AVX2 + FMA + F16C (`__m256`) and AVX-512F (`__m512`), and the
//! kernels' `#[target_feature]` entry points for each.

use super::vector::{Double, Simd, Widen};
use super::Entries;
use crate::{f16, IsaLevel};
use core::arch::x86_64::*;

/// Mask of the first `n` of 8 lanes (all bits set in those lanes).
#[inline(always)]
unsafe fn mask8(n: usize) -> __m256i {
    unsafe { _mm256_cmpgt_epi32(_mm256_set1_epi32(n as i32), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7)) }
}

impl Simd for __m256 {
    const LANES: usize = 8;
    #[inline(always)]
    unsafe fn splat(x: f32) -> Self {
        unsafe { _mm256_set1_ps(x) }
    }
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        unsafe { _mm256_loadu_ps(p) }
    }
    #[inline(always)]
    unsafe fn load_partial(p: *const f32, n: usize) -> Self {
        unsafe { _mm256_maskload_ps(p, mask8(n)) }
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        unsafe { _mm256_storeu_ps(p, self) }
    }
    #[inline(always)]
    unsafe fn store_partial(self, p: *mut f32, n: usize) {
        unsafe { _mm256_maskstore_ps(p, mask8(n), self) }
    }
    #[inline(always)]
    unsafe fn add(self, b: Self) -> Self {
        unsafe { _mm256_add_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn sub(self, b: Self) -> Self {
        unsafe { _mm256_sub_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn mul(self, b: Self) -> Self {
        unsafe { _mm256_mul_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn div(self, b: Self) -> Self {
        unsafe { _mm256_div_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn sqrt(self) -> Self {
        unsafe { _mm256_sqrt_ps(self) }
    }
    #[inline(always)]
    unsafe fn max(self, b: Self) -> Self {
        unsafe { _mm256_max_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn min(self, b: Self) -> Self {
        unsafe { _mm256_min_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn mul_add(self, b: Self, c: Self) -> Self {
        unsafe { _mm256_fmadd_ps(self, b, c) }
    }
    #[inline(always)]
    unsafe fn abs(self) -> Self {
        unsafe { _mm256_andnot_ps(_mm256_set1_ps(-0.0), self) }
    }
    #[inline(always)]
    unsafe fn neg_where_negative(self, sign_of: Self) -> Self {
        unsafe {
            let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(sign_of, _mm256_setzero_ps());
            _mm256_xor_ps(self, _mm256_and_ps(negative, _mm256_set1_ps(-0.0)))
        }
    }
    #[inline(always)]
    unsafe fn select_lt(self, limit: Self, then: Self, other: Self) -> Self {
        unsafe { _mm256_blendv_ps(other, then, _mm256_cmp_ps::<_CMP_LT_OQ>(self, limit)) }
    }
    #[inline(always)]
    unsafe fn trunc(self) -> Self {
        unsafe { _mm256_cvtepi32_ps(_mm256_cvttps_epi32(self)) }
    }
    #[inline(always)]
    unsafe fn pow2(self) -> Self {
        unsafe {
            let n = _mm256_add_epi32(_mm256_cvttps_epi32(self), _mm256_set1_epi32(127));
            _mm256_castsi256_ps(_mm256_slli_epi32::<23>(n))
        }
    }
    #[inline(always)]
    unsafe fn reduce_add(self) -> f32 {
        unsafe {
            let x = _mm_add_ps(_mm256_castps256_ps128(self), _mm256_extractf128_ps::<1>(self));
            let x = _mm_add_ps(x, _mm_movehl_ps(x, x));
            _mm_cvtss_f32(_mm_add_ss(x, _mm_movehdup_ps(x)))
        }
    }
    #[inline(always)]
    unsafe fn prefetch(p: *const u8) {
        unsafe { _mm_prefetch::<_MM_HINT_T0>(p.cast()) }
    }
}

/// Mask of the first `n` of 16 lanes.
#[inline(always)]
fn mask16(n: usize) -> __mmask16 {
    ((1u32 << n) - 1) as __mmask16
}

impl Simd for __m512 {
    const LANES: usize = 16;
    #[inline(always)]
    unsafe fn splat(x: f32) -> Self {
        unsafe { _mm512_set1_ps(x) }
    }
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        unsafe { _mm512_loadu_ps(p) }
    }
    #[inline(always)]
    unsafe fn load_partial(p: *const f32, n: usize) -> Self {
        unsafe { _mm512_maskz_loadu_ps(mask16(n), p) }
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        unsafe { _mm512_storeu_ps(p, self) }
    }
    #[inline(always)]
    unsafe fn store_partial(self, p: *mut f32, n: usize) {
        unsafe { _mm512_mask_storeu_ps(p, mask16(n), self) }
    }
    #[inline(always)]
    unsafe fn add(self, b: Self) -> Self {
        unsafe { _mm512_add_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn sub(self, b: Self) -> Self {
        unsafe { _mm512_sub_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn mul(self, b: Self) -> Self {
        unsafe { _mm512_mul_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn div(self, b: Self) -> Self {
        unsafe { _mm512_div_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn sqrt(self) -> Self {
        unsafe { _mm512_sqrt_ps(self) }
    }
    #[inline(always)]
    unsafe fn max(self, b: Self) -> Self {
        unsafe { _mm512_max_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn min(self, b: Self) -> Self {
        unsafe { _mm512_min_ps(self, b) }
    }
    #[inline(always)]
    unsafe fn mul_add(self, b: Self, c: Self) -> Self {
        unsafe { _mm512_fmadd_ps(self, b, c) }
    }
    #[inline(always)]
    unsafe fn abs(self) -> Self {
        unsafe { _mm512_castsi512_ps(_mm512_and_si512(_mm512_castps_si512(self), _mm512_set1_epi32(i32::MAX))) }
    }
    #[inline(always)]
    unsafe fn neg_where_negative(self, sign_of: Self) -> Self {
        unsafe {
            let negative = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(sign_of, _mm512_setzero_ps());
            let bits = _mm512_castps_si512(self);
            _mm512_castsi512_ps(_mm512_mask_xor_epi32(bits, negative, bits, _mm512_set1_epi32(i32::MIN)))
        }
    }
    #[inline(always)]
    unsafe fn select_lt(self, limit: Self, then: Self, other: Self) -> Self {
        unsafe { _mm512_mask_blend_ps(_mm512_cmp_ps_mask::<_CMP_LT_OQ>(self, limit), other, then) }
    }
    #[inline(always)]
    unsafe fn trunc(self) -> Self {
        unsafe { _mm512_cvtepi32_ps(_mm512_cvttps_epi32(self)) }
    }
    #[inline(always)]
    unsafe fn pow2(self) -> Self {
        unsafe {
            let n = _mm512_add_epi32(_mm512_cvttps_epi32(self), _mm512_set1_epi32(127));
            _mm512_castsi512_ps(_mm512_slli_epi32::<23>(n))
        }
    }
    #[inline(always)]
    unsafe fn reduce_add(self) -> f32 {
        unsafe { _mm512_reduce_add_ps(self) }
    }
    #[inline(always)]
    unsafe fn prefetch(p: *const u8) {
        unsafe { _mm_prefetch::<_MM_HINT_T0>(p.cast()) }
    }
}

impl Widen for __m256 {
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m256 {
        unsafe { _mm256_cvtph_ps(_mm_loadu_si128(p.cast())) }
    }
}

impl Widen for __m512 {
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m512 {
        unsafe { _mm512_cvtph_ps(_mm256_loadu_si256(p.cast())) }
    }
}

impl Double for __m256 {
    type F64 = __m256d;
    #[inline(always)]
    unsafe fn zero_f64() -> __m256d {
        unsafe { _mm256_setzero_pd() }
    }
    #[inline(always)]
    unsafe fn load_f64(p: *const f64) -> __m256d {
        unsafe { _mm256_loadu_pd(p) }
    }
    #[inline(always)]
    unsafe fn store_f64(v: __m256d, p: *mut f64) {
        unsafe { _mm256_storeu_pd(p, v) }
    }
    #[inline(always)]
    unsafe fn add_f64(a: __m256d, b: __m256d) -> __m256d {
        unsafe { _mm256_add_pd(a, b) }
    }
    #[inline(always)]
    unsafe fn sub_f64(a: __m256d, b: __m256d) -> __m256d {
        unsafe { _mm256_sub_pd(a, b) }
    }
    #[inline(always)]
    unsafe fn mul_f64(a: __m256d, b: __m256d) -> __m256d {
        unsafe { _mm256_mul_pd(a, b) }
    }
    #[inline(always)]
    unsafe fn widen(self) -> [__m256d; 2] {
        unsafe {
            [
                _mm256_cvtps_pd(_mm256_castps256_ps128(self)),
                _mm256_cvtps_pd(_mm256_extractf128_ps(self, 1)),
            ]
        }
    }
    #[inline(always)]
    unsafe fn narrow([lo, hi]: [__m256d; 2]) -> __m256 {
        unsafe { _mm256_set_m128(_mm256_cvtpd_ps(hi), _mm256_cvtpd_ps(lo)) }
    }
}

impl Double for __m512 {
    type F64 = __m512d;
    #[inline(always)]
    unsafe fn zero_f64() -> __m512d {
        unsafe { _mm512_setzero_pd() }
    }
    #[inline(always)]
    unsafe fn load_f64(p: *const f64) -> __m512d {
        unsafe { _mm512_loadu_pd(p) }
    }
    #[inline(always)]
    unsafe fn store_f64(v: __m512d, p: *mut f64) {
        unsafe { _mm512_storeu_pd(p, v) }
    }
    #[inline(always)]
    unsafe fn add_f64(a: __m512d, b: __m512d) -> __m512d {
        unsafe { _mm512_add_pd(a, b) }
    }
    #[inline(always)]
    unsafe fn sub_f64(a: __m512d, b: __m512d) -> __m512d {
        unsafe { _mm512_sub_pd(a, b) }
    }
    #[inline(always)]
    unsafe fn mul_f64(a: __m512d, b: __m512d) -> __m512d {
        unsafe { _mm512_mul_pd(a, b) }
    }
    #[inline(always)]
    unsafe fn widen(self) -> [__m512d; 2] {
        unsafe {
            // The upper eight floats through the f64 view (extracting f32 x 8 needs AVX-512DQ).
            let hi = _mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(self), 1));
            [_mm512_cvtps_pd(_mm512_castps512_ps256(self)), _mm512_cvtps_pd(hi)]
        }
    }
    #[inline(always)]
    unsafe fn narrow([lo, hi]: [__m512d; 2]) -> __m512 {
        unsafe {
            let lo = _mm512_castpd256_pd512(_mm256_castps_pd(_mm512_cvtpd_ps(lo)));
            _mm512_castpd_ps(_mm512_insertf64x4(lo, _mm256_castps_pd(_mm512_cvtpd_ps(hi)), 1))
        }
    }
}

// The dense batch tile on AVX2 takes 14 of the 16 registers: 4 x 2 accumulators, 2 weight
// vectors and the 4 broadcasts, which the compiler loads all at once (with more items, an
// accumulator spills to the stack and the loop waits on it).
entries!(AVX2, "avx2,fma,f16c", __m256, dense tile 6 x 2);
// On AVX-512, 8 x 3 accumulators and 3 weight vectors; the broadcasts fold into the
// multiply-adds' memory operands. On a Xeon this measured level with or ahead of 8 x 2 and
// 12 x 2.
entries!(AVX512, "avx512f,avx2,fma,f16c", __m512, dense tile 8 x 3);

/// The entry points of `level`, if it is one of this architecture's.
pub(super) fn entries(level: IsaLevel) -> Option<&'static Entries> {
    match level {
        IsaLevel::Avx2 => Some(&AVX2),
        IsaLevel::Avx512 => Some(&AVX512),
        _ => None,
    }
}

#[cfg(all(test, feature = "std"))]
mod tests {
    use super::*;
    use crate::simd::act::{apply, tests::check};
    use crate::{Activation, Isa};

    /// [`Activation::apply`] on 8 lanes.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn apply_avx2(act: Activation, v: __m256) -> __m256 {
        // SAFETY: this function's features are `__m256`'s.
        unsafe { apply(act, v) }
    }

    /// [`Activation::apply`] on 16 lanes.
    ///
    /// # Safety
    /// The CPU must support AVX-512F.
    #[inline]
    #[target_feature(enable = "avx512f,avx2,fma")]
    unsafe fn apply_avx512(act: Activation, v: __m512) -> __m512 {
        // SAFETY: this function's features are `__m512`'s.
        unsafe { apply(act, v) }
    }

    #[test]
    fn avx2_matches_scalar() {
        if Isa::new(IsaLevel::Avx2).is_none() {
            std::eprintln!("skipping avx2: CPU lacks it");
            return;
        }
        check(|act, lanes| {
            let mut out = [0.0f32; 16];
            // SAFETY: the Isa check above proves the CPU has AVX2 and FMA.
            unsafe {
                for h in 0..2 {
                    let v = apply_avx2(act, _mm256_loadu_ps(lanes[8 * h..].as_ptr()));
                    _mm256_storeu_ps(out[8 * h..].as_mut_ptr(), v);
                }
            }
            out
        });
    }

    #[test]
    fn avx512_matches_scalar() {
        if Isa::new(IsaLevel::Avx512).is_none() {
            std::eprintln!("skipping avx512: CPU lacks it");
            return;
        }
        check(|act, lanes| {
            let mut out = [0.0f32; 16];
            // SAFETY: the Isa check above proves the CPU has AVX-512F.
            unsafe { _mm512_storeu_ps(out.as_mut_ptr(), apply_avx512(act, _mm512_loadu_ps(lanes.as_ptr()))) };
            out
        });
    }
}
