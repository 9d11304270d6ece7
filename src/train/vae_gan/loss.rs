//! The losses' building blocks: softplus, sigmoid and PyTorch's binary cross-entropy with logits.

use drivesim_kernels::math;

/// `ln(1 + e^x)` in f64, without overflow.
fn softplus(x: f64) -> f64 {
    x.max(0.0) + math::ln64(1.0 + math::exp64(-x.abs()))
}

/// `1 / (1 + e^-x)` in f64.
fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + math::exp64(-x))
}

/// PyTorch's `binary_cross_entropy_with_logits` against a constant target (mean over the
/// logits), and its gradient times `scale` into `grad`.
pub(super) fn bce(logits: &[f32], target: bool, scale: f64, grad: &mut [f32]) -> f64 {
    let n = logits.len() as f64;
    let t = if target { 1.0 } else { 0.0 };
    let mut loss = 0.0;
    for (g, &l) in grad.iter_mut().zip(logits) {
        let l = l as f64;
        loss += softplus(if target { -l } else { l });
        *g = (scale * (sigmoid(l) - t) / n) as f32;
    }
    loss / n
}
