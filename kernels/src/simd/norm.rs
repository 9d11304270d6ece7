//! BatchNorm's passes over the pixels (see [`crate::norm`]): the per-channel sums, the
//! forward normalisation and the gradient's, whole vectors of channels at a time, the sums and
//! the gradient in f64 vectors; every operation the scalar reference's in the same order (none
//! fused), so that the results are the same bit for bit.

use super::act;
use super::vector::{load_n, store_n, Double, Simd};
use crate::norm::{rows, GradientCoefficients, BLOCK};
use crate::{Activation, Plane};
use core::ops::Range;

/// f32 vectors of channels summed in one pass over the pixels: each has two f64 halves per
/// sum, so the AVX-512 body keeps 8 accumulators in registers.
const VECTORS: usize = 2;

/// The most f64 a block's sums of one kind take (two vectors of 16 lanes).
const MAX_BLOCK: usize = VECTORS * 16;

/// Adds the accumulators of the block of `n` channels from `c0` to `sums` (`[Σ u | Σ v]` over
/// `channels`), lane after lane.
#[inline(always)]
unsafe fn add_block<V: Double>(
    sums: &mut [f64],
    channels: usize,
    c0: usize,
    n: usize,
    acc: &[[V::F64; 2 * VECTORS]; 2],
) {
    unsafe {
        let half = V::LANES / 2;
        for (kind, acc) in acc.iter().enumerate() {
            let mut lanes = [0.0f64; MAX_BLOCK];
            for (k, &v) in acc.iter().enumerate() {
                V::store_f64(v, lanes.as_mut_ptr().add(k * half));
            }
            for (sum, &lane) in sums[kind * channels + c0..][..n].iter_mut().zip(&lanes) {
                *sum += lane;
            }
        }
    }
}

/// See [`crate::scalar::moments`].
#[inline(always)]
pub(super) unsafe fn moments<V: Double>(plane: Plane, x: &[f32], sums: &mut [f64]) {
    unsafe {
        let c = plane.channels;
        for c0 in (0..c).step_by(VECTORS * V::LANES) {
            let n = (c - c0).min(VECTORS * V::LANES);
            let mut acc = [[V::zero_f64(); 2 * VECTORS]; 2];
            for row in rows(plane) {
                for p in row {
                    for v in 0..n.div_ceil(V::LANES) {
                        let at = c0 + v * V::LANES;
                        let halves = load_n::<V>(x.as_ptr().add(p + at), c - at).widen();
                        for (h, value) in halves.into_iter().enumerate() {
                            let k = 2 * v + h;
                            acc[0][k] = V::add_f64(acc[0][k], value);
                            acc[1][k] = V::add_f64(acc[1][k], V::mul_f64(value, value));
                        }
                    }
                }
            }
            add_block::<V>(sums, c, c0, n, &acc);
        }
    }
}

/// See [`crate::scalar::gradient_moments`].
#[inline(always)]
pub(super) unsafe fn gradient_moments<V: Double>(plane: Plane, x: &[f32], g: &[f32], mean: &[f32], sums: &mut [f64]) {
    unsafe {
        let c = plane.channels;
        for c0 in (0..c).step_by(VECTORS * V::LANES) {
            let n = (c - c0).min(VECTORS * V::LANES);
            let mut means = [V::zero_f64(); 2 * VECTORS];
            for v in 0..n.div_ceil(V::LANES) {
                let at = c0 + v * V::LANES;
                let [lo, hi] = load_n::<V>(mean.as_ptr().add(at), c - at).widen();
                (means[2 * v], means[2 * v + 1]) = (lo, hi);
            }
            let mut acc = [[V::zero_f64(); 2 * VECTORS]; 2];
            for row in rows(plane) {
                for p in row {
                    for v in 0..n.div_ceil(V::LANES) {
                        let at = c0 + v * V::LANES;
                        let gs = load_n::<V>(g.as_ptr().add(p + at), c - at).widen();
                        let xs = load_n::<V>(x.as_ptr().add(p + at), c - at).widen();
                        for h in 0..2 {
                            let k = 2 * v + h;
                            acc[0][k] = V::add_f64(acc[0][k], gs[h]);
                            let centred = V::sub_f64(xs[h], means[k]);
                            acc[1][k] = V::add_f64(acc[1][k], V::mul_f64(centred, gs[h]));
                        }
                    }
                }
            }
            add_block::<V>(sums, c, c0, n, &acc);
        }
    }
}

/// The f64 of `values` from `j` as the halves of a vector (a function, not a closure: closures
/// do not inherit the caller's target features).
#[inline(always)]
unsafe fn load_pair<V: Double>(values: &[f64], j: usize) -> [V::F64; 2] {
    assert!(j + V::LANES <= values.len());
    unsafe {
        [
            V::load_f64(values.as_ptr().add(j)),
            V::load_f64(values.as_ptr().add(j + V::LANES / 2)),
        ]
    }
}

/// See [`crate::scalar::normalize_gradient_block`].
#[inline(always)]
pub(super) unsafe fn normalize_gradient_block<V: Double>(
    plane: Plane,
    x: &[f32],
    g: &mut [f32],
    block: Range<usize>,
    coef: &GradientCoefficients,
) {
    unsafe {
        for row in rows(plane) {
            for p in row {
                for j in (0..block.len()).step_by(V::LANES) {
                    let (at, n) = (p + block.start + j, block.len() - j);
                    let gs = load_n::<V>(g.as_ptr().add(at), n).widen();
                    let xs = load_n::<V>(x.as_ptr().add(at), n).widen();
                    let (mean_g, proj) = (load_pair::<V>(&coef.mean_g, j), load_pair::<V>(&coef.proj, j));
                    let (scale, mean) = (load_pair::<V>(&coef.scale, j), load_pair::<V>(&coef.mean, j));
                    let mut out = [V::zero_f64(); 2];
                    for h in 0..2 {
                        let centred = V::mul_f64(V::sub_f64(xs[h], mean[h]), proj[h]);
                        out[h] = V::mul_f64(V::sub_f64(V::sub_f64(gs[h], mean_g[h]), centred), scale[h]);
                    }
                    store_n(V::narrow(out), g.as_mut_ptr().add(at), n);
                }
            }
        }
    }
}

/// See [`crate::scalar::normalize_block`].
#[inline(always)]
pub(super) unsafe fn normalize_block<V: Simd>(
    plane: Plane,
    x: &[f32],
    y: &mut [f32],
    block: Range<usize>,
    (scale, shift): (&[f32; BLOCK], &[f32; BLOCK]),
    act: Activation,
) {
    unsafe {
        for row in rows(plane) {
            for p in row {
                for j in (0..block.len()).step_by(V::LANES) {
                    let (at, n) = (p + block.start + j, block.len() - j);
                    let v = load_n::<V>(x.as_ptr().add(at), n);
                    // Multiplied, then added: rounded as the scalar reference rounds.
                    let v = v
                        .mul(V::load(scale.as_ptr().add(j)))
                        .add(V::load(shift.as_ptr().add(j)));
                    store_n(act::apply(act, v), y.as_mut_ptr().add(at), n);
                }
            }
        }
    }
}
