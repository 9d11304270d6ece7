//! Adam, with the arithmetic of PyTorch's `torch.optim.Adam` (single-tensor path, the CPU's):
//! `m += (1 - β1)(g - m)`, `v = β2 v + (1 - β2) g²`,
//! `θ -= (lr / (1 - β1ᵗ)) m / (√v / √(1 - β2ᵗ) + eps)`.

use crate::pool::{Exec, ItemParts, SPANS};
use crate::{Error, Result};
use drivesim_kernels::{math, AdamStep, Isa};

/// Adam's constants; PyTorch's defaults.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Adam {
    /// Decay of the first moment (0.9).
    pub beta1: f32,
    /// Decay of the second moment (0.999).
    pub beta2: f32,
    /// Added to the denominator (1e-8).
    pub eps: f32,
}

impl Default for Adam {
    fn default() -> Self {
        Adam {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        }
    }
}

impl Adam {
    pub(crate) fn check(&self) -> Result<()> {
        for (name, value) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&value) {
                return Err(Error::Setting {
                    name,
                    expected: "in [0, 1)",
                    value,
                });
            }
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return Err(Error::Setting {
                name: "eps",
                expected: "a finite number > 0",
                value: self.eps,
            });
        }
        Ok(())
    }

    /// Adam step `step` (from 1) on `params`, with the gradients multiplied by `scale` first
    /// (gradient clipping, as PyTorch scales them in place; 1.0: none); `m` and `v` are the
    /// moments, zeros before the first step. Also for a caller's own parameters, e.g. actions
    /// recovered through [`super::TransitionTrainer::action_gradients`]. Runs on the best
    /// instruction set ([`drivesim_kernels::adam`]): the same bits on every one.
    #[allow(clippy::too_many_arguments)]
    pub fn update(&self, step: u32, lr: f32, scale: f32, params: &mut [f32], grads: &[f32], [m, v]: [&mut [f32]; 2]) {
        // PyTorch computes the corrections in Python floats (f64).
        let correction1 = 1.0 - math::powi(self.beta1 as f64, step);
        let adam = AdamStep {
            beta1: self.beta1,
            beta2: self.beta2,
            eps: self.eps,
            scale,
            step_size: (lr as f64 / correction1) as f32,
            correction2_sqrt: math::sqrt(1.0 - math::powi(self.beta2 as f64, step)) as f32,
        };
        drivesim_kernels::adam(Isa::best(), adam, params, grads, m, v);
    }

    /// [`Adam::update`] (step, learning rate, gradient scale) with threads taking spans: it is
    /// elementwise, so the same values whatever their number.
    pub(crate) fn update_shared(
        &self,
        exec: Exec<'_>,
        (step, lr, scale): (u32, f32, f32),
        params: &mut [f32],
        grads: &[f32],
        [m, v]: [&mut [f32]; 2],
    ) {
        if params.is_empty() {
            return;
        }
        let parts = ItemParts::new([params, m, v], grads.len(), SPANS);
        exec.run(&|| {
            while let Some((span, [p, m, v])) = parts.take() {
                self.update(step, lr, scale, p, &grads[span], [m, v]);
            }
        });
    }
}
