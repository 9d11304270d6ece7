//! The transition model: `h' = tanh(W h + V z + U c + b)`, `z' = A h' + a`.

use crate::layers::{DenseLayer, DenseWeights};
use crate::pool::Exec;
use crate::weights::{Init, Tensor, TensorSource};
use crate::{Config, Result};
use alloc::vec::Vec;
use drivesim_kernels::{Activation, Rnn};

pub(crate) struct Transition {
    /// `[W | V | U]` and `b`.
    input: DenseLayer,
    /// `A` and `a`.
    output: DenseLayer,
}

impl Transition {
    pub fn load(config: &Config, src: &mut dyn TensorSource) -> Result<Self> {
        let (hd, z, a) = (config.hidden_dim, config.z_dim, config.action_dim);
        let fan_in = Init::FanIn(hd + z + a);
        let w = src.tensor("transition.W", &[hd, hd], fan_in)?;
        let v = src.tensor("transition.V", &[hd, z], fan_in)?;
        let u = src.tensor("transition.U", &[hd, a], fan_in)?;
        let b = src.f32("transition.b", &[hd], fan_in)?;
        let big_a = src.tensor("transition.A", &[z, hd], Init::FanIn(hd))?;
        let small_a = src.f32("transition.a", &[z], Init::FanIn(hd))?;
        let input = match (w, v, u) {
            // All three in f16: keep f16, the kernel widens it.
            (Tensor::F16(w), Tensor::F16(v), Tensor::F16(u)) => {
                DenseWeights::F16(concat_cols(&[(&w, hd), (&v, z), (&u, a)]))
            }
            (w, v, u) => DenseWeights::F32(concat_cols(&[
                (&w.into_f32(), hd),
                (&v.into_f32(), z),
                (&u.into_f32(), a),
            ])),
        };
        Ok(Transition {
            input: DenseLayer::new(input, b, hd, hd + z + a, Activation::Tanh),
            output: DenseLayer::new(big_a.into(), small_a, z, hd, Activation::Identity),
        })
    }

    /// Floats of scratch one step needs per batch element.
    pub fn concat_len(&self) -> usize {
        self.input.cols
    }

    /// One step for a batch (see [`drivesim_kernels::rnn_step`]). With threads, each product
    /// is split between them by rows ([`DenseLayer::run`]), so the two products are two tasks,
    /// the second waiting for all of `h'`.
    pub fn step(
        &self,
        exec: Exec<'_>,
        concat: &mut [f32],
        h: &mut [f32],
        z: &[f32],
        action: &[f32],
        z_next: &mut [f32],
    ) {
        let rnn = Rnn {
            input: self.input.matrix(),
            input_bias: &self.input.bias,
            output: self.output.matrix(),
            output_bias: &self.output.bias,
        };
        let concat = &mut concat[..h.len() / self.input.rows * self.input.cols];
        if exec.threads() == 1 {
            return drivesim_kernels::rnn_step(exec.isa, &rnn, concat, h, z, action, z_next);
        }
        rnn.gather(concat, h, z, action);
        self.input.run(exec, concat, h);
        self.output.run(exec, h, z_next);
    }
}

/// Places row-major matrices with the same row count side by side: `(values, cols)` each.
fn concat_cols<T: Copy>(parts: &[(&Vec<T>, usize)]) -> Vec<T> {
    let rows = parts.first().map_or(0, |(v, cols)| v.len() / cols.max(&1));
    let mut out = Vec::with_capacity(parts.iter().map(|(v, _)| v.len()).sum());
    for r in 0..rows {
        for (v, cols) in parts {
            out.extend_from_slice(&v[r * cols..][..*cols]);
        }
    }
    out
}
