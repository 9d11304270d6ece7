//! BatchNorm in training mode, and the per-channel sums of the backward passes, over a batch
//! of planes (items of [`Plane::len`] floats one after another; only interiors are read or
//! written, borders stay zero).
//!
//! These read each value once or twice per call and do a few operations on it: memory-bound,
//! so written once as plain loops over blocks of [`BLOCK`] channels (one cache line of a
//! pixel), with per-channel sums in f64 on the stack. The f64 sums make the statistics of a
//! hundred thousand values exact to f32 rounding, and independent of how a batch is split.

use crate::pack::BN_EPS;
use crate::{Activation, Plane};
use core::ops::Range;

/// PyTorch's default BatchNorm momentum: the weight of a batch in the running statistics.
pub const MOMENTUM: f64 = 0.1;

/// Channels summed together in one pass over the pixels.
const BLOCK: usize = 16;

/// The blocks of channels of a plane.
fn blocks(channels: usize) -> impl Iterator<Item = Range<usize>> {
    (0..channels).step_by(BLOCK).map(move |c| c..(c + BLOCK).min(channels))
}

/// The offset of channel 0 of every interior pixel of every item of a batch of `items` planes.
fn pixels(plane: Plane, items: usize) -> impl Iterator<Item = usize> {
    (0..items).flat_map(move |n| {
        (0..plane.height).flat_map(move |y| (0..plane.width).map(move |x| n * plane.len() + plane.index(y, x)))
    })
}

/// Items in a batch of planes (checked to be whole).
fn items(plane: Plane, batch: &[f32]) -> usize {
    assert!(batch.len().is_multiple_of(plane.len()), "batch is not whole planes");
    batch.len() / plane.len()
}

/// `Σ f(offset of the pixel's channel c, c)` over every interior pixel, per channel of `block`.
fn sums(plane: Plane, items: usize, block: Range<usize>, f: impl Fn(usize, usize) -> f64) -> [f64; BLOCK] {
    let mut sum = [0.0f64; BLOCK];
    for p in pixels(plane, items) {
        for (s, c) in sum.iter_mut().zip(block.clone()) {
            *s += f(p + c, c);
        }
    }
    sum
}

/// `sums[c] = Σ batch[c]` over every interior pixel of every item: a bias's gradient.
pub fn channel_sums(plane: Plane, batch: &[f32], sums_out: &mut [f32]) {
    assert_eq!(sums_out.len(), plane.channels);
    let n = items(plane, batch);
    for block in blocks(plane.channels) {
        let s = sums(plane, n, block.clone(), |i, _| batch[i] as f64);
        for (o, s) in sums_out[block].iter_mut().zip(s) {
            *o = s as f32;
        }
    }
}

/// `1 / sqrt(var + eps)` as PyTorch computes it for a biased batch variance.
fn inv_std(var: f32) -> f64 {
    1.0 / crate::math::sqrt(var as f64 + BN_EPS)
}

/// BatchNorm in training mode followed by `act`: normalises each channel of the batch `x` by
/// its mean and biased variance over every item and pixel (written to `mean` and `var`), then
/// `y = act(gamma · x̂ + beta)` into the interior of `y`.
#[allow(clippy::too_many_arguments)] // a layer's input, parameters, output and two statistics
pub fn batch_norm_train(
    plane: Plane,
    x: &[f32],
    gamma: &[f32],
    beta: &[f32],
    act: Activation,
    y: &mut [f32],
    mean: &mut [f32],
    var: &mut [f32],
) {
    let c = plane.channels;
    assert!(gamma.len() == c && beta.len() == c && mean.len() == c && var.len() == c);
    assert_eq!(x.len(), y.len());
    let n = items(plane, x);
    let count = (n * plane.height * plane.width) as f64;
    for block in blocks(c) {
        let sum = sums(plane, n, block.clone(), |i, _| x[i] as f64);
        let m: [f64; BLOCK] = core::array::from_fn(|j| sum[j] / count);
        let b0 = block.start;
        let squares = sums(plane, n, block.clone(), |i, c| {
            let d = x[i] as f64 - m[c - b0];
            d * d
        });
        for (j, c) in block.clone().enumerate() {
            mean[c] = m[j] as f32;
            var[c] = (squares[j] / count) as f32;
        }
        // y = x · scale + shift, as PyTorch's CPU kernel folds it.
        let scale: [f32; BLOCK] = core::array::from_fn(|j| {
            block
                .clone()
                .nth(j)
                .map_or(0.0, |c| (gamma[c] as f64 * inv_std(var[c])) as f32)
        });
        let shift: [f32; BLOCK] =
            core::array::from_fn(|j| block.clone().nth(j).map_or(0.0, |c| beta[c] - mean[c] * scale[j]));
        for p in pixels(plane, n) {
            for (j, c) in block.clone().enumerate() {
                y[p + c] = act.apply(x[p + c] * scale[j] + shift[j]);
            }
        }
    }
}

/// The backward pass of [`batch_norm_train`] (its `x`, `y`, `mean`, `var`, `gamma`): turns
/// `dy`, the gradient of `y`, into the gradient before the activation in place, then writes the
/// gradient of `x` to the interior of `dx` and those of `gamma` and `beta`:
/// `dx = gamma / σ · (g - mean(g) - x̂ · mean(g · x̂))`, `dgamma = Σ g · x̂`, `dbeta = Σ g`.
#[allow(clippy::too_many_arguments)] // one layer's saved forward values and its three gradients
pub fn batch_norm_backward(
    plane: Plane,
    x: &[f32],
    y: &[f32],
    act: Activation,
    gamma: &[f32],
    mean: &[f32],
    var: &[f32],
    dy: &mut [f32],
    dx: &mut [f32],
    dgamma: &mut [f32],
    dbeta: &mut [f32],
) {
    let c = plane.channels;
    assert!(gamma.len() == c && mean.len() == c && var.len() == c && dgamma.len() == c && dbeta.len() == c);
    assert!(x.len() == y.len() && x.len() == dy.len() && x.len() == dx.len());
    let n = items(plane, x);
    let count = (n * plane.height * plane.width) as f64;
    for block in blocks(c) {
        for p in pixels(plane, n) {
            for c in block.clone() {
                dy[p + c] = act.backward(y[p + c], dy[p + c]);
            }
        }
        let dy = &*dy;
        let sum = sums(plane, n, block.clone(), |i, _| dy[i] as f64);
        let dot = sums(plane, n, block.clone(), |i, c| {
            (x[i] as f64 - mean[c] as f64) * dy[i] as f64
        });
        let mut coef = [(0.0f64, 0.0f64, 0.0f64, 0.0f64); BLOCK];
        for (j, c) in block.clone().enumerate() {
            let s = inv_std(var[c]);
            dgamma[c] = (dot[j] * s) as f32;
            dbeta[c] = sum[j] as f32;
            // dx = (g - sum / count - (x - mean) · dot · s² / count) · s · gamma
            coef[j] = (
                sum[j] / count,
                dot[j] * s * s / count,
                s * gamma[c] as f64,
                mean[c] as f64,
            );
        }
        for p in pixels(plane, n) {
            for (j, c) in block.clone().enumerate() {
                let (mean_g, proj, scale, m) = coef[j];
                let g = dy[p + c] as f64 - mean_g - (x[p + c] as f64 - m) * proj;
                dx[p + c] = (g * scale) as f32;
            }
        }
    }
}

/// Moves running statistics towards a batch's as PyTorch does: with momentum 0.1, the variance
/// unbiased (`var · count / (count - 1)`, `count` the values per channel in the batch).
pub fn update_running_stats(
    mean: &[f32],
    var: &[f32],
    count: usize,
    running_mean: &mut [f32],
    running_var: &mut [f32],
) {
    assert!(mean.len() == var.len() && mean.len() == running_mean.len() && mean.len() == running_var.len());
    let unbias = count as f64 / (count.max(2) - 1) as f64;
    for c in 0..mean.len() {
        running_mean[c] = ((1.0 - MOMENTUM) * running_mean[c] as f64 + MOMENTUM * mean[c] as f64) as f32;
        running_var[c] = ((1.0 - MOMENTUM) * running_var[c] as f64 + MOMENTUM * var[c] as f64 * unbias) as f32;
    }
}
