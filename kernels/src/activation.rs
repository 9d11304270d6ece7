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
}
