//! The vector abstractions every kernel body is written over.
//!
//! - [`Simd`]: a vector of f32 lanes, implemented by each architecture's module: `__m256`
//!   (AVX2 + FMA) and `__m512` (AVX-512F) on x86-64, `float32x4_t` (NEON) on aarch64; [`Widen`]
//!   adds loading halves widened (the dense kernel's f16 weights), [`Double`] f64 vectors
//!   (BatchNorm's sums); [`load_n`] / [`store_n`] touch only the first `n` lanes (masked tails).
//! - [`Lane`]: what Winograd's transforms run on: one f32 on the scalar path, a [`Simd`] vector
//!   on the others, so that both paths share one transform.
//!
//! The methods are `#[inline(always)]` and call target-feature intrinsics: they are only meant to
//! be used inside a `#[target_feature]` function that enables the features of the type
//! (`avx2,fma` for `__m256`, `avx512f` for `__m512`, `neon` for `float32x4_t`), where they
//! inline into plain instructions.

use super::act;
use crate::{f16, Activation, OC_ALIGN};

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
    /// The correctly rounded square root.
    unsafe fn sqrt(self) -> Self;
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
    /// Hints that the cache line at `p` will be read soon; `p` need not be valid.
    unsafe fn prefetch(p: *const u8);
}

/// What the dense kernel needs on top of [`Simd`]: loading halves widened.
/// Methods are `inline(always)`, to compile inside the caller's `#[target_feature]` function.
pub(super) trait Widen: Simd {
    /// Loads `LANES` halves and widens them.
    unsafe fn load_f16(p: *const f16) -> Self;
}

/// What BatchNorm's kernels need on top of [`Simd`]: f64 vectors of half the lanes, for sums
/// that stay exact to f32 rounding (and equal the scalar reference's bit for bit: the same
/// operations in the same order, none fused).
/// Methods are `inline(always)`, to compile inside the caller's `#[target_feature]` function.
pub(super) trait Double: Simd {
    type F64: Copy;
    unsafe fn zero_f64() -> Self::F64;
    /// Loads `LANES / 2` f64 from `p` (no alignment needed).
    unsafe fn load_f64(p: *const f64) -> Self::F64;
    unsafe fn store_f64(v: Self::F64, p: *mut f64);
    unsafe fn add_f64(a: Self::F64, b: Self::F64) -> Self::F64;
    unsafe fn sub_f64(a: Self::F64, b: Self::F64) -> Self::F64;
    unsafe fn mul_f64(a: Self::F64, b: Self::F64) -> Self::F64;
    /// The lanes as f64 (exactly): the low half, then the high half.
    unsafe fn widen(self) -> [Self::F64; 2];
    /// Halves back to f32, rounded to nearest (as `as f32`).
    unsafe fn narrow(halves: [Self::F64; 2]) -> Self;
}

#[inline(always)]
pub(super) unsafe fn load_n<V: Simd>(p: *const f32, n: usize) -> V {
    unsafe {
        if n >= V::LANES {
            V::load(p)
        } else if n > 0 {
            V::load_partial(p, n)
        } else {
            V::splat(0.0)
        }
    }
}

#[inline(always)]
pub(super) unsafe fn store_n<V: Simd>(v: V, p: *mut f32, n: usize) {
    unsafe {
        if n >= V::LANES {
            v.store(p)
        } else if n > 0 {
            v.store_partial(p, n)
        }
    }
}

/// A run of `LANES` floats the transforms work on: one float on the scalar path, a vector on
/// the SIMD paths. Methods are unsafe for the SIMD types (see `simd::act::Simd`).
pub(crate) trait Lane: Copy {
    const LANES: usize;
    /// Output channels per block of the matrix products.
    const BLOCK: usize;
    unsafe fn zero() -> Self;
    /// The first `min(n, LANES)` floats at `p`, zero in the other lanes.
    unsafe fn load_n(p: *const f32, n: usize) -> Self;
    /// Stores the first `min(n, LANES)` lanes to `p`.
    unsafe fn store_n(self, p: *mut f32, n: usize);
    unsafe fn add(self, b: Self) -> Self;
    unsafe fn sub(self, b: Self) -> Self;
    /// `self * c + acc`.
    unsafe fn mul_add(self, c: f32, acc: Self) -> Self;
    unsafe fn activate(self, act: Activation) -> Self;
}

impl Lane for f32 {
    const LANES: usize = 1;
    const BLOCK: usize = OC_ALIGN;
    unsafe fn zero() -> f32 {
        0.0
    }
    unsafe fn load_n(p: *const f32, n: usize) -> f32 {
        unsafe {
            if n > 0 {
                *p
            } else {
                0.0
            }
        }
    }
    unsafe fn store_n(self, p: *mut f32, n: usize) {
        unsafe {
            if n > 0 {
                *p = self
            }
        }
    }
    unsafe fn add(self, b: f32) -> f32 {
        self + b
    }
    unsafe fn sub(self, b: f32) -> f32 {
        self - b
    }
    unsafe fn mul_add(self, c: f32, acc: f32) -> f32 {
        self * c + acc
    }
    unsafe fn activate(self, act: Activation) -> f32 {
        act.apply(self)
    }
}

impl<V: Simd> Lane for V {
    const LANES: usize = V::LANES;
    const BLOCK: usize = 2 * V::LANES;
    #[inline(always)]
    unsafe fn zero() -> V {
        unsafe { V::splat(0.0) }
    }
    #[inline(always)]
    unsafe fn load_n(p: *const f32, n: usize) -> V {
        unsafe { load_n(p, n) }
    }
    #[inline(always)]
    unsafe fn store_n(self, p: *mut f32, n: usize) {
        unsafe { store_n(self, p, n) }
    }
    #[inline(always)]
    unsafe fn add(self, b: V) -> V {
        unsafe { Simd::add(self, b) }
    }
    #[inline(always)]
    unsafe fn sub(self, b: V) -> V {
        unsafe { Simd::sub(self, b) }
    }
    #[inline(always)]
    unsafe fn mul_add(self, c: f32, acc: V) -> V {
        unsafe { Simd::mul_add(self, V::splat(c), acc) }
    }
    #[inline(always)]
    unsafe fn activate(self, act: Activation) -> V {
        unsafe { act::apply(act, self) }
    }
}
