//! aarch64: the NEON vector type (`float32x4_t`), and the kernels' entry points for it. NEON is
//! part of every aarch64 target this module is compiled for (`target_feature = "neon"`), so the
//! entries need no run-time check.

use super::vector::{Double, Simd, Widen};
use super::Entries;
use crate::{f16, IsaLevel};
use core::arch::aarch64::*;
use core::arch::asm;

impl Simd for float32x4_t {
    const LANES: usize = 4;
    #[inline(always)]
    unsafe fn splat(x: f32) -> Self {
        unsafe { vdupq_n_f32(x) }
    }
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        unsafe { vld1q_f32(p) }
    }
    #[inline(always)]
    unsafe fn load_partial(p: *const f32, n: usize) -> Self {
        unsafe {
            // NEON has no masked loads: gather the `n` floats in a zeroed buffer.
            let mut lanes = [0.0f32; 4];
            core::ptr::copy_nonoverlapping(p, lanes.as_mut_ptr(), n);
            vld1q_f32(lanes.as_ptr())
        }
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        unsafe { vst1q_f32(p, self) }
    }
    #[inline(always)]
    unsafe fn store_partial(self, p: *mut f32, n: usize) {
        unsafe {
            let mut lanes = [0.0f32; 4];
            vst1q_f32(lanes.as_mut_ptr(), self);
            core::ptr::copy_nonoverlapping(lanes.as_ptr(), p, n);
        }
    }
    #[inline(always)]
    unsafe fn add(self, b: Self) -> Self {
        unsafe { vaddq_f32(self, b) }
    }
    #[inline(always)]
    unsafe fn sub(self, b: Self) -> Self {
        unsafe { vsubq_f32(self, b) }
    }
    #[inline(always)]
    unsafe fn mul(self, b: Self) -> Self {
        unsafe { vmulq_f32(self, b) }
    }
    #[inline(always)]
    unsafe fn div(self, b: Self) -> Self {
        unsafe { vdivq_f32(self, b) }
    }
    #[inline(always)]
    unsafe fn sqrt(self) -> Self {
        unsafe { vsqrtq_f32(self) }
    }
    #[inline(always)]
    unsafe fn max(self, b: Self) -> Self {
        unsafe { vmaxq_f32(self, b) }
    }
    #[inline(always)]
    unsafe fn min(self, b: Self) -> Self {
        unsafe { vminq_f32(self, b) }
    }
    #[inline(always)]
    unsafe fn mul_add(self, b: Self, c: Self) -> Self {
        unsafe { vfmaq_f32(c, self, b) }
    }
    #[inline(always)]
    unsafe fn abs(self) -> Self {
        unsafe { vabsq_f32(self) }
    }
    #[inline(always)]
    unsafe fn neg_where_negative(self, sign_of: Self) -> Self {
        unsafe {
            let negative = vcltq_f32(sign_of, vdupq_n_f32(0.0));
            let sign = vandq_u32(negative, vdupq_n_u32(0x8000_0000));
            vreinterpretq_f32_u32(veorq_u32(vreinterpretq_u32_f32(self), sign))
        }
    }
    #[inline(always)]
    unsafe fn select_lt(self, limit: Self, then: Self, other: Self) -> Self {
        unsafe { vbslq_f32(vcltq_f32(self, limit), then, other) }
    }
    #[inline(always)]
    unsafe fn trunc(self) -> Self {
        unsafe { vcvtq_f32_s32(vcvtq_s32_f32(self)) }
    }
    #[inline(always)]
    unsafe fn pow2(self) -> Self {
        unsafe {
            let n = vaddq_s32(vcvtq_s32_f32(self), vdupq_n_s32(127));
            vreinterpretq_f32_s32(vshlq_n_s32::<23>(n))
        }
    }
    #[inline(always)]
    unsafe fn reduce_add(self) -> f32 {
        unsafe { vaddvq_f32(self) }
    }
    #[inline(always)]
    unsafe fn prefetch(p: *const u8) {
        unsafe {
            // A prefetch never faults, whatever the address.
            asm!("prfm pldl1keep, [{0}]", in(reg) p, options(nostack, preserves_flags, readonly));
        }
    }
}

impl Widen for float32x4_t {
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> float32x4_t {
        unsafe {
            // FCVTL widens exactly, as F16C does; its intrinsic needs the unstable `float16x4_t`.
            let halves = vld1_u16(p.cast());
            let widened: float32x4_t;
            asm!("fcvtl {0:v}.4s, {1:v}.4h", lateout(vreg) widened, in(vreg) halves, options(pure, nomem, nostack, preserves_flags));
            widened
        }
    }
}

impl Double for float32x4_t {
    type F64 = float64x2_t;
    #[inline(always)]
    unsafe fn zero_f64() -> float64x2_t {
        unsafe { vdupq_n_f64(0.0) }
    }
    #[inline(always)]
    unsafe fn load_f64(p: *const f64) -> float64x2_t {
        unsafe { vld1q_f64(p) }
    }
    #[inline(always)]
    unsafe fn store_f64(v: float64x2_t, p: *mut f64) {
        unsafe { vst1q_f64(p, v) }
    }
    #[inline(always)]
    unsafe fn add_f64(a: float64x2_t, b: float64x2_t) -> float64x2_t {
        unsafe { vaddq_f64(a, b) }
    }
    #[inline(always)]
    unsafe fn sub_f64(a: float64x2_t, b: float64x2_t) -> float64x2_t {
        unsafe { vsubq_f64(a, b) }
    }
    #[inline(always)]
    unsafe fn mul_f64(a: float64x2_t, b: float64x2_t) -> float64x2_t {
        unsafe { vmulq_f64(a, b) }
    }
    #[inline(always)]
    unsafe fn widen(self) -> [float64x2_t; 2] {
        unsafe { [vcvt_f64_f32(vget_low_f32(self)), vcvt_high_f64_f32(self)] }
    }
    #[inline(always)]
    unsafe fn narrow([lo, hi]: [float64x2_t; 2]) -> float32x4_t {
        unsafe { vcvt_high_f32_f64(vcvt_f32_f64(lo), hi) }
    }
}

// The dense batch tile: 4 items x 4 vectors (one panel of rows), 16 of the 32 registers as
// accumulators, 4 for the weights and 4 for the broadcasts. Not tuned on hardware.
entries!(NEON, "neon", float32x4_t, dense tile 4 x 4);

/// The entry points of `level`, if it is NEON.
pub(super) fn entries(level: IsaLevel) -> Option<&'static Entries> {
    (level == IsaLevel::Neon).then_some(&NEON)
}

#[cfg(all(test, feature = "std"))]
mod tests {
    use super::*;
    use crate::simd::act::{apply, tests::check};

    #[test]
    fn neon_matches_scalar() {
        check(|act, lanes| {
            let mut out = [0.0f32; 16];
            // SAFETY: NEON is part of the target; the pointers cover 16 floats.
            unsafe {
                for q in 0..4 {
                    let v = apply(act, vld1q_f32(lanes[4 * q..].as_ptr()));
                    vst1q_f32(out[4 * q..].as_mut_ptr(), v);
                }
            }
            out
        });
    }
}
