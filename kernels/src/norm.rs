//! BatchNorm in training mode, and the per-channel sums of the backward passes, over a batch
//! of planes (items of [`Plane::len`] floats one after another; only interiors are read or
//! written, borders stay zero).
//!
//! These read each value twice per call and do a few operations on it: memory-bound, so
//! written once as plain loops over blocks of [`BLOCK`] channels, with per-channel sums in f64
//! on the stack. The f64 sums make the statistics of a hundred thousand values exact to f32
//! rounding.

use crate::pack::BN_EPS;
use crate::{Activation, Isa, Plane};
use core::ops::Range;

/// PyTorch's default BatchNorm momentum: the weight of a batch in the running statistics.
pub const MOMENTUM: f64 = 0.1;

/// Channels summed together in one pass over the pixels: up to this many f64 sums live on
/// the stack, and one pass reads a pixel's block of channels as one contiguous run.
const BLOCK: usize = 64;

/// The blocks of channels of a plane.
fn blocks(channels: usize) -> impl Iterator<Item = Range<usize>> {
    (0..channels).step_by(BLOCK).map(move |c| c..(c + BLOCK).min(channels))
}

/// Items in a batch of planes (checked to be whole).
fn items(plane: Plane, batch: &[f32]) -> usize {
    assert!(batch.len().is_multiple_of(plane.len()), "batch is not whole planes");
    batch.len() / plane.len()
}

/// The offset of channel 0 of every interior pixel of every item of a batch of `items`
/// planes, row by row.
fn pixels(plane: Plane, items: usize) -> impl Iterator<Item = usize> {
    let row = plane.width * plane.channels;
    (0..items).flat_map(move |n| {
        (0..plane.height).flat_map(move |y| {
            let start = n * plane.len() + plane.index(y, 0);
            (start..start + row).step_by(plane.channels.max(1))
        })
    })
}

/// `sums[c] = Σ batch[c]` over every interior pixel of every item: a bias's gradient.
pub fn channel_sums(plane: Plane, batch: &[f32], sums_out: &mut [f32]) {
    assert_eq!(sums_out.len(), plane.channels);
    let n = items(plane, batch);
    for block in blocks(plane.channels) {
        let mut sum = [0.0f64; BLOCK];
        for p in pixels(plane, n) {
            let values = &batch[p + block.start..p + block.end];
            sum.iter_mut().zip(values).for_each(|(s, &v)| *s += v as f64);
        }
        sums_out[block.clone()]
            .iter_mut()
            .zip(sum)
            .for_each(|(o, s)| *o = s as f32);
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
        // Sums of values and squares in f64, in one pass: the variance E[x²] - E[x]² keeps
        // f32 accuracy unless the mean is a million times the spread.
        let (mut sum, mut squares) = ([0.0f64; BLOCK], [0.0f64; BLOCK]);
        for p in pixels(plane, n) {
            let values = &x[p + block.start..p + block.end];
            for ((s, q), &v) in sum.iter_mut().zip(squares.iter_mut()).zip(values) {
                *s += v as f64;
                *q += v as f64 * v as f64;
            }
        }
        // y = x · scale + shift, as PyTorch's CPU kernel folds it.
        let (mut scale, mut shift) = ([0.0f32; BLOCK], [0.0f32; BLOCK]);
        for (j, ch) in block.clone().enumerate() {
            let m = sum[j] / count;
            mean[ch] = m as f32;
            var[ch] = (squares[j] / count - m * m).max(0.0) as f32;
            scale[j] = (gamma[ch] as f64 * inv_std(var[ch])) as f32;
            shift[j] = beta[ch] - mean[ch] * scale[j];
        }
        for p in pixels(plane, n) {
            let (values, out) = (
                &x[p + block.start..p + block.end],
                &mut y[p + block.start..p + block.end],
            );
            for (j, (o, &v)) in out.iter_mut().zip(values).enumerate() {
                *o = act.apply(v * scale[j] + shift[j]);
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
    isa: Isa,
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
    // The activation's gradient by its vector kernel (the borders are zero and stay so).
    crate::activation_backward(isa, act, y, dy);
    for block in blocks(c) {
        let m = &mean[block.clone()];
        // The sums of g and (x - mean) · g, in one pass.
        let (mut sum, mut dot) = ([0.0f64; BLOCK], [0.0f64; BLOCK]);
        for p in pixels(plane, n) {
            let span = p + block.start..p + block.end;
            let (xs, gs) = (&x[span.clone()], &dy[span]);
            for (j, (&g, &xv)) in gs.iter().zip(xs).enumerate() {
                sum[j] += g as f64;
                dot[j] += (xv as f64 - m[j] as f64) * g as f64;
            }
        }
        // dx = (g - sum / count - (x - mean) · dot · s² / count) · s · gamma
        let mut coef = [(0.0f64, 0.0f64, 0.0f64); BLOCK];
        for (j, ch) in block.clone().enumerate() {
            let s = inv_std(var[ch]);
            dgamma[ch] = (dot[j] * s) as f32;
            dbeta[ch] = sum[j] as f32;
            coef[j] = (sum[j] / count, dot[j] * s * s / count, s * gamma[ch] as f64);
        }
        for p in pixels(plane, n) {
            let span = p + block.start..p + block.end;
            let (xs, gs, out) = (&x[span.clone()], &dy[span.clone()], &mut dx[span]);
            for (j, ((o, &xv), &g)) in out.iter_mut().zip(xs).zip(gs).enumerate() {
                let (mean_g, proj, scale) = coef[j];
                *o = ((g as f64 - mean_g - (xv as f64 - m[j] as f64) * proj) * scale) as f32;
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
