//! The nonlinearities the kernels fuse into their stores.

use crate::math;

/// The nonlinearity applied to a kernel's output before it is stored.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Activation {
    /// `x`.
    Identity,
    /// `max(x, 0)`.
    Relu,
    /// `max(x, slope * x)` for `0 < slope < 1`.
    LeakyRelu(f32),
    /// `tanh(x)`, by [`crate::math::tanh`].
    Tanh,
}

impl Activation {
    /// The activation of one value: the scalar reference of the fused stores.
    #[inline]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Activation::Identity => x,
            Activation::Relu => x.max(0.0),
            Activation::LeakyRelu(slope) => x.max(slope * x),
            Activation::Tanh => math::tanh(x),
        }
    }

    /// The gradient through the activation, given its output `y` and the gradient `grad` of
    /// `y`: the scalar reference of [`crate::activation_backward`]. ReLU and LeakyReLU read the
    /// sign of the input from `y` (the same sign) and, as PyTorch does, take the left slope at 0;
    /// tanh multiplies by `1 - y²`, in this order, unfused.
    #[inline]
    pub fn backward(self, y: f32, grad: f32) -> f32 {
        match self {
            Activation::Identity => grad,
            Activation::Relu => {
                if y > 0.0 {
                    grad
                } else {
                    0.0
                }
            }
            Activation::LeakyRelu(slope) => {
                if y > 0.0 {
                    grad
                } else {
                    grad * slope
                }
            }
            Activation::Tanh => grad * (1.0 - y * y),
        }
    }
}
