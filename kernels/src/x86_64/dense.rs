//! Dense (matrix times batch of vectors) kernels for AVX2 and AVX-512. Not written yet: the
//! scalar kernel runs.

use crate::{scalar, Activation, IsaLevel, Matrix};

pub(crate) fn dense(_level: IsaLevel, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    scalar::dense(w, bias, act, x, y)
}
