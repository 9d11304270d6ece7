//! A step's activations, their gradients and the scratch its layers share, as the networks'
//! build sizes them.

use super::layers::Work;
use super::stack::{Stack, StackGrads};
use alloc::vec::Vec;

/// The activations, their gradients and the scratch of a step, for up to `batch` frames.
pub(super) struct Buffers {
    pub(super) batch: usize,
    /// Real frames (planes of the first convolution's input).
    pub(super) real: Vec<f32>,
    pub(super) enc: Stack,
    pub(super) enc_flat: Vec<f32>,
    /// `[mu | logsigma]` per item (logsigma after its tanh).
    pub(super) heads: Vec<f32>,
    /// The generator's inputs: `mu + eps · sigma` for the batch, then the prior samples.
    pub(super) codes: Vec<f32>,
    pub(super) eps: Vec<f32>,
    pub(super) fc_out: Vec<f32>,
    /// The generator's first feature map before and after BatchNorm0 + ReLU, and its stats.
    pub(super) top_z: Vec<f32>,
    pub(super) top_y: Vec<f32>,
    pub(super) top_mean: Vec<f32>,
    pub(super) top_var: Vec<f32>,
    pub(super) gen: Stack,
    pub(super) dis_real: Stack,
    pub(super) dis_fake: Stack,
    pub(super) flat_real: Vec<f32>,
    pub(super) flat_fake: Vec<f32>,
    pub(super) logits_real: Vec<f32>,
    pub(super) logits_fake: Vec<f32>,
    pub(super) enc_grads: StackGrads,
    pub(super) gen_grads: StackGrads,
    pub(super) dis_grads: StackGrads,
    /// The gradient of the generator's first feature map, then of the dense layer's output.
    pub(super) top_g: Vec<f32>,
    /// Gradients of the discriminator's input, the feature error, dense outputs and inputs.
    pub(super) dx: Vec<f32>,
    pub(super) dfeature: Vec<f32>,
    pub(super) dlogits: Vec<f32>,
    pub(super) dflat: Vec<f32>,
    pub(super) dheads: Vec<f32>,
    pub(super) dcodes: Vec<f32>,
    pub(super) work: Work,
}
