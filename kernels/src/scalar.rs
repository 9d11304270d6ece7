//! Reference kernels: written straight from the definitions, with explicit bounds instead of
//! relying on the zero border, so they check the SIMD kernels' use of it too.

use crate::{Activation, ConvShape, Matrix, MatrixData};

/// See [`crate::conv`].
pub fn conv(shape: &ConvShape, input: &[f32], weights: &[f32], bias: &[f32], act: Activation, output: &mut [f32]) {
    let ConvShape {
        kind,
        kernel: k,
        input: ip,
        output: op,
    } = *shape;
    let pad = k / 2;
    let oc_stride = shape.oc_stride();
    for oy in 0..op.height {
        for ox in 0..op.width {
            let out = &mut output[op.index(oy, ox)..][..op.channels];
            out.copy_from_slice(bias);
            for ky in 0..k {
                let Some(iy) = kind.source(oy, ky, pad, ip.height) else {
                    continue;
                };
                for kx in 0..k {
                    let Some(ix) = kind.source(ox, kx, pad, ip.width) else {
                        continue;
                    };
                    let pixel = &input[ip.index(iy, ix)..][..ip.channels];
                    let taps = &weights[(ky * k + kx) * ip.channels * oc_stride..];
                    for (&v, w) in pixel.iter().zip(taps.chunks_exact(oc_stride)) {
                        for (o, &w) in out.iter_mut().zip(w) {
                            *o += v * w;
                        }
                    }
                }
            }
            for o in out.iter_mut() {
                *o = act.apply(*o);
            }
        }
    }
}

/// See [`crate::dense`].
pub fn dense(w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    for (x, y) in x.chunks_exact(w.cols).zip(y.chunks_exact_mut(w.rows)) {
        for (r, (y, &b)) in y.iter_mut().zip(bias).enumerate() {
            let dot: f32 = match w.data {
                MatrixData::F32(d) => d[r * w.cols..][..w.cols].iter().zip(x).map(|(w, x)| w * x).sum(),
                MatrixData::F16(d) => d[r * w.cols..][..w.cols]
                    .iter()
                    .zip(x)
                    .map(|(w, x)| w.to_f32() * x)
                    .sum(),
            };
            *y = act.apply(dot + b);
        }
    }
}
