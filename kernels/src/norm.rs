//! BatchNorm in training mode and its backward pass (whose per-channel sums, [`moments`], are
//! also a bias's gradient), over a batch
//! of planes (items of [`Plane::len`] floats one after another; only interiors are read or
//! written, borders stay zero).
//!
//! The per-channel sums are in f64: they make the statistics of a hundred thousand values exact
//! to f32 rounding. Every pass over the pixels ([`moments`], [`normalize`],
//! [`gradient_moments`], [`normalize_gradient`]) runs on the caller's instruction set (the sums
//! and the gradient in f64 vectors) with the same results as the scalar references
//! ([`crate::scalar::moments`] and the others) bit for bit, a block of at most 64 channels (the
//! crate's private `BLOCK`) at a time; the per-channel steps between them are plain loops.

use crate::pack::BN_EPS;
use crate::{simd, Activation, Isa, Plane};
use core::iter::StepBy;
use core::ops::Range;

/// PyTorch's default BatchNorm momentum: the weight of a batch in the running statistics.
pub const MOMENTUM: f64 = 0.1;

/// Channels summed together in one pass over the pixels: up to this many f64 sums live on
/// the stack, and one pass reads a pixel's block of channels as one contiguous run.
pub(crate) const BLOCK: usize = 64;

/// The blocks of channels of a plane.
pub(crate) fn blocks(channels: usize) -> impl Iterator<Item = Range<usize>> {
    (0..channels).step_by(BLOCK).map(move |c| c..(c + BLOCK).min(channels))
}

/// Items in a batch of planes (checked to be whole).
fn items(plane: Plane, batch: &[f32]) -> usize {
    assert!(batch.len().is_multiple_of(plane.len()), "batch is not whole planes");
    batch.len() / plane.len()
}

/// The interior pixels of a plane, row by row: each row the offsets of channel 0 of its pixels.
/// (Nested loops, `for row in rows(plane) { for p in row { .. } }`: a flattened iterator over
/// the pixels did not inline into the SIMD bodies, whose accumulators then lived in memory.)
pub(crate) fn rows(plane: Plane) -> impl Iterator<Item = StepBy<Range<usize>>> {
    (0..plane.height).map(move |y| {
        let start = plane.index(y, 0);
        (start..start + plane.width * plane.channels).step_by(plane.channels.max(1))
    })
}

/// `1 / sqrt(var + eps)` as PyTorch computes it for a biased batch variance.
fn inv_std(var: f32) -> f64 {
    1.0 / crate::math::sqrt(var as f64 + BN_EPS)
}

/// f64 sums a batch's statistics take: two per channel.
pub const fn sums_len(channels: usize) -> usize {
    2 * channels
}

/// Step 1 of BatchNorm in training mode, for one plane `x` of a batch: adds its per-channel sums
/// of values and of squares to `sums` (`[Σ x | Σ x²]`, [`sums_len`] f64). Threads may take the
/// planes of a batch, each into sums of its own, added up after in the planes' order.
pub fn moments(isa: Isa, plane: Plane, x: &[f32], sums: &mut [f64]) {
    assert_eq!(x.len(), plane.len());
    assert_eq!(sums.len(), sums_len(plane.channels));
    // SAFETY: `isa` proves the CPU has the kernel's features; the lengths are checked above.
    unsafe { (simd::entries(isa).moments)(plane, x, sums) }
}

/// Step 2: a batch's mean and biased variance from its sums over `count` values per channel
/// (the variance `E[x²] - E[x]²` in f64: f32 accuracy unless the mean is a million times the
/// spread).
pub fn statistics(sums: &[f64], count: usize, mean: &mut [f32], var: &mut [f32]) {
    let c = mean.len();
    assert!(sums.len() == sums_len(c) && var.len() == c);
    let n = count as f64;
    for ch in 0..c {
        let m = sums[ch] / n;
        mean[ch] = m as f32;
        var[ch] = (sums[c + ch] / n - m * m).max(0.0) as f32;
    }
}

/// Step 3, for one plane: `y = act(gamma · (x - mean) / sqrt(var + eps) + beta)` into the
/// interior of `y`, computed as PyTorch's CPU kernel folds it, `x · scale + shift`.
#[allow(clippy::too_many_arguments)] // a plane in and out, the statistics and the parameters
pub fn normalize(
    isa: Isa,
    plane: Plane,
    x: &[f32],
    mean: &[f32],
    var: &[f32],
    gamma: &[f32],
    beta: &[f32],
    act: Activation,
    y: &mut [f32],
) {
    let c = plane.channels;
    assert!(x.len() == plane.len() && y.len() == plane.len());
    assert!(mean.len() == c && var.len() == c && gamma.len() == c && beta.len() == c);
    let kernel = simd::entries(isa).normalize_block;
    for block in blocks(c) {
        let (mut scale, mut shift) = ([0.0f32; BLOCK], [0.0f32; BLOCK]);
        for (j, ch) in block.clone().enumerate() {
            scale[j] = (gamma[ch] as f64 * inv_std(var[ch])) as f32;
            shift[j] = beta[ch] - mean[ch] * scale[j];
        }
        // SAFETY: `isa` proves the CPU has the kernel's features; the lengths are checked
        // above and the block is inside the plane's channels.
        unsafe { kernel(plane, x, y, block, (&scale, &shift), act) }
    }
}

/// Steps 1 to 3 on a whole batch `x` on one thread (`sums`: [`sums_len`] f64 of scratch):
/// normalises each channel by its mean and biased variance over every item and pixel (written
/// to `mean` and `var`), then `y = act(gamma · x̂ + beta)` into the interior of `y`.
#[allow(clippy::too_many_arguments)] // a layer's input, parameters, output, statistics, scratch
pub fn batch_norm_train(
    isa: Isa,
    plane: Plane,
    x: &[f32],
    gamma: &[f32],
    beta: &[f32],
    act: Activation,
    y: &mut [f32],
    mean: &mut [f32],
    var: &mut [f32],
    sums: &mut [f64],
) {
    assert_eq!(x.len(), y.len());
    let n = items(plane, x);
    sums.fill(0.0);
    for x in x.chunks_exact(plane.len()) {
        moments(isa, plane, x, sums);
    }
    statistics(sums, n * plane.height * plane.width, mean, var);
    for (x, y) in x.chunks_exact(plane.len()).zip(y.chunks_exact_mut(plane.len())) {
        normalize(isa, plane, x, mean, var, gamma, beta, act, y);
    }
}

/// Backward step 1, for one plane: adds `Σ g` and `Σ (x - mean) · g` per channel to `sums`
/// ([`sums_len`] f64), `g` the gradient before the activation (see
/// [`crate::activation_backward`]), `x` the layer's input.
pub fn gradient_moments(isa: Isa, plane: Plane, x: &[f32], g: &[f32], mean: &[f32], sums: &mut [f64]) {
    assert!(x.len() == plane.len() && g.len() == plane.len() && mean.len() == plane.channels);
    assert_eq!(sums.len(), sums_len(plane.channels));
    // SAFETY: as in `moments`.
    unsafe { (simd::entries(isa).gradient_moments)(plane, x, g, mean, sums) }
}

/// Backward step 2: the gradients of `gamma` and `beta` from a batch's sums.
pub fn parameter_gradients(sums: &[f64], var: &[f32], dgamma: &mut [f32], dbeta: &mut [f32]) {
    let c = var.len();
    assert!(sums.len() == sums_len(c) && dgamma.len() == c && dbeta.len() == c);
    for ch in 0..c {
        dgamma[ch] = (sums[c + ch] * inv_std(var[ch])) as f32;
        dbeta[ch] = sums[ch] as f32;
    }
}

/// Backward step 3, for one plane, in place: `g` (the gradient before the activation) becomes
/// the gradient of `x`, `dx = gamma / σ · (g - mean(g) - x̂ · mean(g · x̂))`, from the batch's
/// sums over `count` values per channel. Only the interior is read and written.
#[allow(clippy::too_many_arguments)] // a plane in and out, the batch's statistics and sums
pub fn normalize_gradient(
    isa: Isa,
    plane: Plane,
    x: &[f32],
    g: &mut [f32],
    mean: &[f32],
    var: &[f32],
    gamma: &[f32],
    sums: &[f64],
    count: usize,
) {
    let c = plane.channels;
    assert!(x.len() == plane.len() && g.len() == plane.len());
    assert!(mean.len() == c && var.len() == c && gamma.len() == c && sums.len() == sums_len(c));
    let n = count as f64;
    let kernel = simd::entries(isa).normalize_gradient_block;
    for block in blocks(c) {
        let mut coef = GradientCoefficients {
            mean_g: [0.0; BLOCK],
            proj: [0.0; BLOCK],
            scale: [0.0; BLOCK],
            mean: [0.0; BLOCK],
        };
        for (j, ch) in block.clone().enumerate() {
            let s = inv_std(var[ch]);
            coef.mean_g[j] = sums[ch] / n;
            coef.proj[j] = sums[c + ch] * s * s / n;
            coef.scale[j] = s * gamma[ch] as f64;
            coef.mean[j] = mean[ch] as f64;
        }
        // SAFETY: as in `moments`; the block is inside the plane's channels.
        unsafe { kernel(plane, x, g, block, &coef) }
    }
}

/// The per-channel constants of [`normalize_gradient`] for a block of at most [`BLOCK`]
/// channels (zero past its end): `dx = (g - mean_g - (x - mean) · proj) · scale`, where
/// `mean_g = Σ g / n`, `proj = Σ (x - mean) g · s² / n`, `scale = s · gamma`, `s = 1 / σ`.
pub(crate) struct GradientCoefficients {
    pub mean_g: [f64; BLOCK],
    pub proj: [f64; BLOCK],
    pub scale: [f64; BLOCK],
    pub mean: [f64; BLOCK],
}

/// The backward pass of [`batch_norm_train`] on one thread (its `x`, `y`, `mean`, `var`,
/// `gamma`; `sums`: [`sums_len`] f64 of scratch): turns `dy`, the gradient of `y`, into the
/// gradient before the activation in place, then writes the gradient of `x` to the interior of
/// `dx` and those of `gamma` and `beta`: `dx = gamma / σ · (g - mean(g) - x̂ · mean(g · x̂))`,
/// `dgamma = Σ g · x̂`, `dbeta = Σ g`.
#[allow(clippy::too_many_arguments)] // one layer's saved forward values, its gradients, scratch
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
    sums: &mut [f64],
) {
    assert!(x.len() == y.len() && x.len() == dy.len() && x.len() == dx.len());
    let n = items(plane, x);
    // The activation's gradient by its vector kernel (the borders are zero and stay so).
    crate::activation_backward(isa, act, y, dy);
    sums.fill(0.0);
    for (x, g) in x.chunks_exact(plane.len()).zip(dy.chunks_exact(plane.len())) {
        gradient_moments(isa, plane, x, g, mean, sums);
    }
    parameter_gradients(sums, var, dgamma, dbeta);
    let count = n * plane.height * plane.width;
    dx.copy_from_slice(dy);
    for (x, dx) in x.chunks_exact(plane.len()).zip(dx.chunks_exact_mut(plane.len())) {
        normalize_gradient(isa, plane, x, dx, mean, var, gamma, sums, count);
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
