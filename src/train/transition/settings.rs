//! How a transition trainer trains ([`TransitionSettings`]) and the check of those settings.

use crate::train::adam::Adam;
use crate::{Error, Result};

/// How a [`TransitionTrainer`](super::TransitionTrainer) trains: `weights/drivesim_reference/train.py`'s choices by
/// default.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransitionSettings {
    /// Inputs taken from the data at the start of each window (at least 1); later inputs are
    /// the model's own previous prediction. The paper and `weights/drivesim_reference/train.py`: 5 of 15.
    pub teacher: usize,
    /// Back-propagate through the fed-back predictions too. The paper stops the gradient
    /// there (PyTorch's `.detach()`, `false`); the hidden state carries it through time either
    /// way.
    pub full_bptt: bool,
    /// The largest global L2 norm of the gradients; larger ones are scaled down to it as
    /// `torch.nn.utils.clip_grad_norm_` does. `f32::INFINITY`: no clipping.
    pub clip: f32,
    /// Adam's `beta1`, `beta2` and `eps`, with PyTorch's semantics (bias correction).
    pub adam: Adam,
}

impl Default for TransitionSettings {
    fn default() -> Self {
        TransitionSettings {
            teacher: 5,
            full_bptt: false,
            clip: 1.0,
            adam: Adam::default(),
        }
    }
}

pub(super) fn check_settings(s: &TransitionSettings) -> Result<()> {
    if s.teacher == 0 {
        return Err(Error::Config {
            field: "teacher",
            expected: "at least 1 teacher-forced input",
            found: 0,
        });
    }
    if s.clip.is_nan() || s.clip <= 0.0 {
        return Err(Error::Setting {
            name: "clip",
            expected: "a norm > 0 (infinity: no clipping)",
            value: s.clip,
        });
    }
    s.adam.check()
}

/// What `TransitionTrainer::backward` (in `bptt.rs`) computes.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Backward {
    Weights,
    Inputs,
}
