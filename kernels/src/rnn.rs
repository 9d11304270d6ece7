//! The model's RNN step on the dense kernel.

use crate::{dense, Activation, Isa, Matrix};

/// The weights of the action-conditioned tanh RNN:
/// `h' = tanh(W h + V z + U c + b)`, `z' = A h' + a`.
///
/// `W`, `V` and `U` are stored side by side as one `hidden x (hidden + z + action)` matrix so that
/// one pass over memory computes all three products.
///
/// A step whose code is the one `h` itself predicted (`z = A h + a`: every step of a rollout
/// after its seeds) needs no `V`: `h' = tanh((W + V A) h + U c + (b + V a))`. For such steps
/// `input` is `[W + V A | U]`, `hidden x (hidden + action)`, with bias `b + V a`, and the step
/// is given no `z`: a third fewer weights to read per step.
#[derive(Clone, Copy, Debug)]
pub struct Rnn<'a> {
    /// `[W | V | U]`, `hidden x (hidden + z + action)`, or `[W + V A | U]`,
    /// `hidden x (hidden + action)`.
    pub input: Matrix<'a>,
    /// `b`, or `b + V a`; `hidden`.
    pub input_bias: &'a [f32],
    /// `A`, `z x hidden`.
    pub output: Matrix<'a>,
    /// `a`, `z`.
    pub output_bias: &'a [f32],
}

impl Rnn<'_> {
    pub fn hidden(&self) -> usize {
        self.input.rows
    }
    pub fn z_dim(&self) -> usize {
        self.output.rows
    }

    /// Writes each batch element's `[h | z | action]` (or `[h | action]` without `z`) to
    /// `concat`, the input of `input`: the first half of [`rnn_step`], for callers that run its
    /// two products themselves (split between threads).
    pub fn gather(&self, concat: &mut [f32], h: &[f32], z: Option<&[f32]>, action: &[f32]) {
        let hd = self.hidden();
        let zd = z.map_or(0, |_| self.z_dim());
        assert!(hd > 0 && h.len().is_multiple_of(hd) && self.input.cols >= hd + zd);
        let batch = h.len() / hd;
        let ad = self.input.cols - hd - zd;
        assert_eq!(z.map_or(0, <[f32]>::len), batch * zd);
        assert_eq!(action.len(), batch * ad);
        assert_eq!(concat.len(), batch * self.input.cols);
        for (n, row) in concat.chunks_exact_mut(self.input.cols).enumerate() {
            row[..hd].copy_from_slice(&h[n * hd..][..hd]);
            if let Some(z) = z {
                row[hd..hd + zd].copy_from_slice(&z[n * zd..][..zd]);
            }
            row[hd + zd..].copy_from_slice(&action[n * ad..][..ad]);
        }
    }
}

/// One RNN step for a batch: updates `h` in place and writes `z_next`. `z` is the input code,
/// or `None` for the fed-back form of [`Rnn`]. `concat` is scratch of `batch * input.cols`
/// floats.
pub fn rnn_step(
    isa: Isa,
    rnn: &Rnn<'_>,
    concat: &mut [f32],
    h: &mut [f32],
    z: Option<&[f32]>,
    action: &[f32],
    z_next: &mut [f32],
) {
    rnn.gather(concat, h, z, action);
    dense(isa, rnn.input, rnn.input_bias, Activation::Tanh, concat, h);
    dense(isa, rnn.output, rnn.output_bias, Activation::Identity, h, z_next);
}
