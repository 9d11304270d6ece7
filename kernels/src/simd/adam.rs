//! Adam's update (see [`crate::scalar::adam`]): the same operations as the scalar reference, each
//! rounded as written (IEEE add, multiply, divide and square root, none fused), so every level
//! gives the same bits; the tail that fills no vector is the reference's.

use super::vector::Simd;
use crate::AdamStep;

/// See [`crate::scalar::adam`].
#[inline(always)]
pub(super) unsafe fn adam<V: Simd>(s: AdamStep, params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
    unsafe {
        let n = params.len();
        let whole = n - n % V::LANES;
        let (scale, b1, b2) = (V::splat(s.scale), V::splat(1.0 - s.beta1), V::splat(s.beta2));
        let (one_minus_b2, step_size) = (V::splat(1.0 - s.beta2), V::splat(s.step_size));
        let (correction2_sqrt, eps) = (V::splat(s.correction2_sqrt), V::splat(s.eps));
        for i in (0..whole).step_by(V::LANES) {
            let (pp, mp, vp) = (params.as_mut_ptr().add(i), m.as_mut_ptr().add(i), v.as_mut_ptr().add(i));
            let g = V::load(grads.as_ptr().add(i)).mul(scale);
            let mi = V::load(mp);
            let mi = mi.add(g.sub(mi).mul(b1));
            let vi = V::load(vp).mul(b2).add(one_minus_b2.mul(g).mul(g));
            let step = step_size.mul(mi).div(vi.sqrt().div(correction2_sqrt).add(eps));
            V::load(pp).sub(step).store(pp);
            mi.store(mp);
            vi.store(vp);
        }
        crate::scalar::adam(
            s,
            &mut params[whole..],
            &grads[whole..],
            &mut m[whole..],
            &mut v[whole..],
        );
    }
}
