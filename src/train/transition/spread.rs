//! The spread head's loss and gradient (`transition.S`, `transition.s`; `crate::sampling`):
//! `log σ = S h' + s` of each saved hidden state, and the Gaussian negative log-likelihood
//! (without its constant) of each target dimension around the prediction,
//! `0.5 r² exp(-2 log σ) + log σ`, mean over the windows, the dimensions and the predictions
//! made from true codes (the teacher-forced ones: their error is one step's innovation, which a
//! sampled rollout adds at every step; a fed-back prediction's error is the drift of the mean,
//! which sampling would add again and again). The mean and the hidden states enter as constants
//! (`weights/drivesim_reference/sequences.py`'s `spread_loss` detaches them): the head learns the error the mean
//! makes, and the mean trains as without a head.

use super::plan::Dims;
use crate::layers::dense;
use crate::pool::Exec;
use crate::sampling::sigma;
use drivesim_kernels::{Activation, Matrix, MatrixData};

/// The saved activations the head reads: hidden states and predictions, time-major (item
/// `t * batch + n`), and the windows' codes.
pub(super) struct Saved<'s> {
    pub hs: &'s [f32],
    pub outs: &'s [f32],
    pub codes: &'s [f32],
    pub batch: usize,
}

/// The head's mean loss over the first `teacher` steps' predictions; `log_sigma` (`items x z`
/// for those items, time-major) receives `S h' + s`, or with `gradient` the loss's gradient
/// with respect to it.
pub(super) fn spread_loss(
    exec: Exec<'_>,
    d: Dims,
    teacher: usize,
    head: (&[f32], &[f32]),
    saved: Saved<'_>,
    log_sigma: &mut [f32],
    gradient: bool,
) -> f64 {
    let (z, items) = (d.z, teacher.min(d.steps()) * saved.batch);
    let s = Matrix {
        data: MatrixData::F32(head.0),
        rows: z,
        cols: d.hidden,
    };
    let log_sigma = &mut log_sigma[..items * z];
    dense(
        exec,
        s,
        head.1,
        Activation::Identity,
        &saved.hs[..items * d.hidden],
        log_sigma,
    );
    let count = (items * z) as f64;
    let mut sum = 0.0f64;
    for (i, (ls, out)) in log_sigma
        .chunks_exact_mut(z)
        .zip(saved.outs.chunks_exact(z))
        .enumerate()
    {
        let (t, n) = (i / saved.batch, i % saved.batch);
        let target = &saved.codes[(n * d.window + t + 1) * z..][..z];
        for ((l, o), y) in ls.iter_mut().zip(out).zip(target) {
            let (r, spread) = (y - o, sigma(*l));
            let scaled = r * r / (spread * spread);
            sum += 0.5 * scaled as f64 + *l as f64;
            if gradient {
                *l = ((1.0 - scaled as f64) / count) as f32;
            }
        }
    }
    sum / count
}
