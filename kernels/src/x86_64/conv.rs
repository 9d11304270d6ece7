//! Convolution kernels for AVX2 and AVX-512. Not written yet: the scalar kernel runs.

use crate::{scalar, Activation, ConvShape, IsaLevel};

pub(crate) fn conv(
    _level: IsaLevel,
    shape: &ConvShape,
    input: &[f32],
    weights: &[f32],
    bias: &[f32],
    act: Activation,
    output: &mut [f32],
) {
    scalar::conv(shape, input, weights, bias, act, output)
}
