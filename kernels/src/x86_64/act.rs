//! Vectorised activations shared by the x86-64 kernels, written once over a small vector trait
//! ([`Simd`]) that `__m256` (AVX2 + FMA) and `__m512` (AVX-512F) implement.
//!
//! Tanh evaluates exactly the formula of [`crate::math::tanh`] lane by lane, with the same
//! constants and the same (unfused) operation order, so SIMD and scalar agree bit for bit on the
//! same input (up to the sign of a zero).
//!
//! The trait's methods are `#[inline(always)]` and call target-feature intrinsics: they are only
//! meant to be used inside a `#[target_feature]` function that enables the features of the type
//! (`avx2,fma` for `__m256`, `avx512f` for `__m512`), where they inline into plain instructions.

use crate::math::{EXP_POLY, LN2_HI, LN2_LO, TANH_CLAMP, TANH_SERIES, TANH_SERIES_LIMIT};
use crate::Activation;
use core::arch::x86_64::*;

/// A vector of `LANES` f32. Every method is unsafe: the caller must run on a CPU with the
/// type's features (see the module comment) and pass pointers valid for the lanes touched.
#[allow(clippy::missing_safety_doc)]
pub(crate) trait Simd: Copy {
    const LANES: usize;
    unsafe fn splat(x: f32) -> Self;
    /// Loads `LANES` floats from `p` (no alignment needed).
    unsafe fn load(p: *const f32) -> Self;
    /// Loads the first `n < LANES` floats from `p`, the other lanes are zero; reads only `n`.
    unsafe fn load_partial(p: *const f32, n: usize) -> Self;
    unsafe fn store(self, p: *mut f32);
    /// Stores the first `n < LANES` lanes to `p`; writes only `n` floats.
    unsafe fn store_partial(self, p: *mut f32, n: usize);
    unsafe fn add(self, b: Self) -> Self;
    unsafe fn sub(self, b: Self) -> Self;
    unsafe fn mul(self, b: Self) -> Self;
    unsafe fn div(self, b: Self) -> Self;
    unsafe fn max(self, b: Self) -> Self;
    unsafe fn min(self, b: Self) -> Self;
    /// `self * b + c` with one rounding.
    unsafe fn mul_add(self, b: Self, c: Self) -> Self;
    unsafe fn abs(self) -> Self;
    /// `self` (assumed >= 0) negated in the lanes where `sign_of < 0`.
    unsafe fn neg_where_negative(self, sign_of: Self) -> Self;
    /// Per lane: `if self < limit { then } else { other }`.
    unsafe fn select_lt(self, limit: Self, then: Self, other: Self) -> Self;
    /// Per lane `x as i32 as f32` (truncation toward zero).
    unsafe fn trunc(self) -> Self;
    /// Per lane `2^n` for integral `n` in the normal exponent range.
    unsafe fn pow2(self) -> Self;
    /// The sum of the lanes.
    unsafe fn reduce_add(self) -> f32;
}

/// Mask of the first `n` of 8 lanes (all bits set in those lanes).
#[inline(always)]
unsafe fn mask8(n: usize) -> __m256i {
    _mm256_cmpgt_epi32(_mm256_set1_epi32(n as i32), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7))
}

impl Simd for __m256 {
    const LANES: usize = 8;
    #[inline(always)]
    unsafe fn splat(x: f32) -> Self {
        _mm256_set1_ps(x)
    }
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        _mm256_loadu_ps(p)
    }
    #[inline(always)]
    unsafe fn load_partial(p: *const f32, n: usize) -> Self {
        _mm256_maskload_ps(p, mask8(n))
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        _mm256_storeu_ps(p, self)
    }
    #[inline(always)]
    unsafe fn store_partial(self, p: *mut f32, n: usize) {
        _mm256_maskstore_ps(p, mask8(n), self)
    }
    #[inline(always)]
    unsafe fn add(self, b: Self) -> Self {
        _mm256_add_ps(self, b)
    }
    #[inline(always)]
    unsafe fn sub(self, b: Self) -> Self {
        _mm256_sub_ps(self, b)
    }
    #[inline(always)]
    unsafe fn mul(self, b: Self) -> Self {
        _mm256_mul_ps(self, b)
    }
    #[inline(always)]
    unsafe fn div(self, b: Self) -> Self {
        _mm256_div_ps(self, b)
    }
    #[inline(always)]
    unsafe fn max(self, b: Self) -> Self {
        _mm256_max_ps(self, b)
    }
    #[inline(always)]
    unsafe fn min(self, b: Self) -> Self {
        _mm256_min_ps(self, b)
    }
    #[inline(always)]
    unsafe fn mul_add(self, b: Self, c: Self) -> Self {
        _mm256_fmadd_ps(self, b, c)
    }
    #[inline(always)]
    unsafe fn abs(self) -> Self {
        _mm256_andnot_ps(_mm256_set1_ps(-0.0), self)
    }
    #[inline(always)]
    unsafe fn neg_where_negative(self, sign_of: Self) -> Self {
        let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(sign_of, _mm256_setzero_ps());
        _mm256_xor_ps(self, _mm256_and_ps(negative, _mm256_set1_ps(-0.0)))
    }
    #[inline(always)]
    unsafe fn select_lt(self, limit: Self, then: Self, other: Self) -> Self {
        _mm256_blendv_ps(other, then, _mm256_cmp_ps::<_CMP_LT_OQ>(self, limit))
    }
    #[inline(always)]
    unsafe fn trunc(self) -> Self {
        _mm256_cvtepi32_ps(_mm256_cvttps_epi32(self))
    }
    #[inline(always)]
    unsafe fn pow2(self) -> Self {
        let n = _mm256_add_epi32(_mm256_cvttps_epi32(self), _mm256_set1_epi32(127));
        _mm256_castsi256_ps(_mm256_slli_epi32::<23>(n))
    }
    #[inline(always)]
    unsafe fn reduce_add(self) -> f32 {
        let x = _mm_add_ps(_mm256_castps256_ps128(self), _mm256_extractf128_ps::<1>(self));
        let x = _mm_add_ps(x, _mm_movehl_ps(x, x));
        _mm_cvtss_f32(_mm_add_ss(x, _mm_movehdup_ps(x)))
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
        _mm512_set1_ps(x)
    }
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        _mm512_loadu_ps(p)
    }
    #[inline(always)]
    unsafe fn load_partial(p: *const f32, n: usize) -> Self {
        _mm512_maskz_loadu_ps(mask16(n), p)
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        _mm512_storeu_ps(p, self)
    }
    #[inline(always)]
    unsafe fn store_partial(self, p: *mut f32, n: usize) {
        _mm512_mask_storeu_ps(p, mask16(n), self)
    }
    #[inline(always)]
    unsafe fn add(self, b: Self) -> Self {
        _mm512_add_ps(self, b)
    }
    #[inline(always)]
    unsafe fn sub(self, b: Self) -> Self {
        _mm512_sub_ps(self, b)
    }
    #[inline(always)]
    unsafe fn mul(self, b: Self) -> Self {
        _mm512_mul_ps(self, b)
    }
    #[inline(always)]
    unsafe fn div(self, b: Self) -> Self {
        _mm512_div_ps(self, b)
    }
    #[inline(always)]
    unsafe fn max(self, b: Self) -> Self {
        _mm512_max_ps(self, b)
    }
    #[inline(always)]
    unsafe fn min(self, b: Self) -> Self {
        _mm512_min_ps(self, b)
    }
    #[inline(always)]
    unsafe fn mul_add(self, b: Self, c: Self) -> Self {
        _mm512_fmadd_ps(self, b, c)
    }
    #[inline(always)]
    unsafe fn abs(self) -> Self {
        _mm512_castsi512_ps(_mm512_and_si512(_mm512_castps_si512(self), _mm512_set1_epi32(i32::MAX)))
    }
    #[inline(always)]
    unsafe fn neg_where_negative(self, sign_of: Self) -> Self {
        let negative = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(sign_of, _mm512_setzero_ps());
        let bits = _mm512_castps_si512(self);
        _mm512_castsi512_ps(_mm512_mask_xor_epi32(bits, negative, bits, _mm512_set1_epi32(i32::MIN)))
    }
    #[inline(always)]
    unsafe fn select_lt(self, limit: Self, then: Self, other: Self) -> Self {
        _mm512_mask_blend_ps(_mm512_cmp_ps_mask::<_CMP_LT_OQ>(self, limit), other, then)
    }
    #[inline(always)]
    unsafe fn trunc(self) -> Self {
        _mm512_cvtepi32_ps(_mm512_cvttps_epi32(self))
    }
    #[inline(always)]
    unsafe fn pow2(self) -> Self {
        let n = _mm512_add_epi32(_mm512_cvttps_epi32(self), _mm512_set1_epi32(127));
        _mm512_castsi512_ps(_mm512_slli_epi32::<23>(n))
    }
    #[inline(always)]
    unsafe fn reduce_add(self) -> f32 {
        _mm512_reduce_add_ps(self)
    }
}

/// [`crate::math::exp`] lane by lane (valid for `0 <= x <= 2 * TANH_CLAMP`).
#[inline(always)]
pub(crate) unsafe fn exp<V: Simd>(x: V) -> V {
    let n = x.mul(V::splat(core::f32::consts::LOG2_E)).add(V::splat(0.5)).trunc();
    let r = x.sub(n.mul(V::splat(LN2_HI))).sub(n.mul(V::splat(LN2_LO)));
    let mut p = V::splat(EXP_POLY[4]);
    for &c in EXP_POLY[..4].iter().rev() {
        p = V::splat(c).add(r.mul(p));
    }
    let p = V::splat(1.0).add(r.mul(V::splat(1.0).add(r.mul(p))));
    p.mul(n.pow2())
}

/// [`crate::math::tanh`] lane by lane.
#[inline(always)]
pub(crate) unsafe fn tanh<V: Simd>(x: V) -> V {
    let a = x.abs().min(V::splat(TANH_CLAMP));
    let a2 = a.mul(a);
    let series = V::splat(TANH_SERIES[1]).add(a2.mul(V::splat(TANH_SERIES[2])));
    let series = V::splat(TANH_SERIES[0]).add(a2.mul(series));
    let series = a.mul(V::splat(1.0).add(a2.mul(series)));
    let one = V::splat(1.0);
    let large = one.sub(V::splat(2.0).div(exp(V::splat(2.0).mul(a)).add(one)));
    a.select_lt(V::splat(TANH_SERIES_LIMIT), series, large)
        .neg_where_negative(x)
}

/// [`Activation::apply`] lane by lane, for any [`Simd`] type.
#[inline(always)]
pub(crate) unsafe fn apply<V: Simd>(act: Activation, v: V) -> V {
    match act {
        Activation::Identity => v,
        Activation::Relu => v.max(V::splat(0.0)),
        Activation::LeakyRelu(slope) => v.max(V::splat(slope).mul(v)),
        Activation::Tanh => tanh(v),
    }
}

/// [`apply`] to every value of `data` in place.
#[inline(always)]
pub(crate) unsafe fn apply_slice<V: Simd>(act: Activation, data: &mut [f32]) {
    if act == Activation::Identity {
        return;
    }
    let mut chunks = data.chunks_exact_mut(V::LANES);
    for c in &mut chunks {
        apply(act, V::load(c.as_ptr())).store(c.as_mut_ptr());
    }
    let rest = chunks.into_remainder();
    if !rest.is_empty() {
        apply(act, V::load_partial(rest.as_ptr(), rest.len())).store_partial(rest.as_mut_ptr(), rest.len());
    }
}

#[cfg(all(test, feature = "std"))]
mod tests {
    use super::*;
    use crate::{Isa, IsaLevel};

    /// [`Activation::apply`] on 8 lanes.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn apply_avx2(act: Activation, v: __m256) -> __m256 {
        apply(act, v)
    }

    /// [`Activation::apply`] on 16 lanes.
    ///
    /// # Safety
    /// The CPU must support AVX-512F.
    #[inline]
    #[target_feature(enable = "avx512f,avx2,fma")]
    unsafe fn apply_avx512(act: Activation, v: __m512) -> __m512 {
        apply(act, v)
    }

    const ACTS: [Activation; 4] = [
        Activation::Identity,
        Activation::Relu,
        Activation::LeakyRelu(0.2),
        Activation::Tanh,
    ];

    /// Inputs from -20 to 20 in small steps, plus the special points of the tanh formula.
    fn inputs() -> impl Iterator<Item = f32> {
        let specials = [
            0.0,
            -0.0,
            TANH_SERIES_LIMIT,
            -TANH_SERIES_LIMIT,
            TANH_CLAMP,
            1e-30,
            -1e30,
        ];
        (-20 * 512..=20 * 512)
            .map(|i| i as f32 / 512.0 + 1.0 / 4096.0)
            .chain(specials)
    }

    fn check<V: Simd>(apply_v: impl Fn(Activation, &[f32; 16]) -> [f32; 16]) {
        let xs: alloc::vec::Vec<f32> = inputs().collect();
        for act in ACTS {
            for chunk in xs.chunks(16) {
                let mut lanes = [0.0f32; 16];
                lanes[..chunk.len()].copy_from_slice(chunk);
                let got = apply_v(act, &lanes);
                for (i, &x) in lanes.iter().enumerate().take(V::LANES) {
                    let want = act.apply(x);
                    // Same formula, same operation order: equal up to the sign of zero.
                    assert!(got[i] == want, "{act:?}({x}): simd {} scalar {want}", got[i]);
                }
            }
        }
    }

    #[test]
    fn avx2_matches_scalar() {
        if Isa::new(IsaLevel::Avx2).is_none() {
            std::eprintln!("skipping avx2: CPU lacks it");
            return;
        }
        check::<__m256>(|act, lanes| {
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
        check::<__m512>(|act, lanes| {
            let mut out = [0.0f32; 16];
            // SAFETY: the Isa check above proves the CPU has AVX-512F.
            unsafe { _mm512_storeu_ps(out.as_mut_ptr(), apply_avx512(act, _mm512_loadu_ps(lanes.as_ptr()))) };
            out
        });
    }
}
