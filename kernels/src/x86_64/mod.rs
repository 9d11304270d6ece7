//! x86-64 SIMD kernels. Until the AVX2 and AVX-512 bodies land, every level runs the scalar one.

use crate::{scalar, Activation, ConvShape, IsaLevel, Matrix};

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

pub(crate) fn dense(_level: IsaLevel, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    scalar::dense(w, bias, act, x, y)
}
