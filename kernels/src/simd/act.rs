//! The activations on vectors ([`Simd`]).
//!
//! Tanh evaluates exactly the formula of [`crate::math::tanh`] lane by lane, with the same
//! constants and the same (unfused) operation order, so SIMD and scalar agree bit for bit on the
//! same input (up to the sign of a zero).

use super::vector::{load_n, store_n, Simd};
use crate::math::{EXP_POLY, LN2_HI, LN2_LO, TANH_CLAMP, TANH_SERIES, TANH_SERIES_LIMIT};
use crate::Activation;

/// [`crate::math::exp`] lane by lane (valid for `0 <= x <= 2 * TANH_CLAMP`).
#[inline(always)]
pub(crate) unsafe fn exp<V: Simd>(x: V) -> V {
    unsafe {
        let n = x.mul(V::splat(core::f32::consts::LOG2_E)).add(V::splat(0.5)).trunc();
        let r = x.sub(n.mul(V::splat(LN2_HI))).sub(n.mul(V::splat(LN2_LO)));
        let mut p = V::splat(EXP_POLY[4]);
        for &c in EXP_POLY[..4].iter().rev() {
            p = V::splat(c).add(r.mul(p));
        }
        let p = V::splat(1.0).add(r.mul(V::splat(1.0).add(r.mul(p))));
        p.mul(n.pow2())
    }
}

/// [`crate::math::tanh`] lane by lane.
#[inline(always)]
pub(crate) unsafe fn tanh<V: Simd>(x: V) -> V {
    unsafe {
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
}

/// [`Activation::apply`] lane by lane, for any [`Simd`] type.
#[inline(always)]
pub(crate) unsafe fn apply<V: Simd>(act: Activation, v: V) -> V {
    unsafe {
        match act {
            Activation::Identity => v,
            Activation::Relu => v.max(V::splat(0.0)),
            Activation::LeakyRelu(slope) => v.max(V::splat(slope).mul(v)),
            Activation::Tanh => tanh(v),
        }
    }
}

/// [`apply`] to every value of `data` in place.
#[inline(always)]
pub(crate) unsafe fn apply_slice<V: Simd>(act: Activation, data: &mut [f32]) {
    unsafe {
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
}

/// [`Activation::backward`] lane by lane, in the same operation order: bit-identical to
/// [`crate::scalar::activation_backward`].
#[inline(always)]
pub(crate) unsafe fn backward<V: Simd>(act: Activation, y: &[f32], grad: &mut [f32]) {
    unsafe {
        if act == Activation::Identity {
            return;
        }
        let n = grad.len().min(y.len());
        let (zero, one) = (V::splat(0.0), V::splat(1.0));
        for i in (0..n).step_by(V::LANES) {
            let lanes = V::LANES.min(n - i);
            let (y, p) = (load_n::<V>(y.as_ptr().add(i), lanes), grad.as_mut_ptr().add(i));
            let g = load_n::<V>(p, lanes);
            // `zero.select_lt(y, a, b)` is `if 0 < y { a } else { b }`, as the scalar test.
            let d = match act {
                Activation::Identity => g,
                Activation::Relu => zero.select_lt(y, g, zero),
                Activation::LeakyRelu(slope) => zero.select_lt(y, g, g.mul(V::splat(slope))),
                Activation::Tanh => g.mul(one.sub(y.mul(y))),
            };
            store_n(d, p, lanes);
        }
    }
}

#[cfg(all(test, feature = "std"))]
pub(super) mod tests {
    use super::*;

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

    /// Checks `apply_v`, an instruction set's [`apply`] on 16 values, against
    /// [`Activation::apply`].
    pub(in crate::simd) fn check(apply_v: impl Fn(Activation, &[f32; 16]) -> [f32; 16]) {
        let xs: alloc::vec::Vec<f32> = inputs().collect();
        for act in ACTS {
            for chunk in xs.chunks(16) {
                let mut lanes = [0.0f32; 16];
                lanes[..chunk.len()].copy_from_slice(chunk);
                let got = apply_v(act, &lanes);
                for (i, &x) in lanes.iter().enumerate() {
                    let want = act.apply(x);
                    // Same formula, same operation order: equal up to the sign of zero.
                    assert!(got[i] == want, "{act:?}({x}): simd {} scalar {want}", got[i]);
                }
            }
        }
    }
}
