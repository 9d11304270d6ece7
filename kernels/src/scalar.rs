//! Reference kernels: written straight from the definitions, with explicit bounds instead of
//! relying on the zero border, so they check the SIMD kernels' use of it too. The public ones
//! are the test oracle; the others are the scalar entries of every operation's dispatch.

use crate::winograd::{self, Winograd};
use crate::{norm, Activation, ConvParams, ConvShape, Matrix, MatrixData, Plane};
use core::ops::Range;

/// See [`crate::conv`].
pub fn conv(layer: ConvParams<'_>, input: &[f32], output: &mut [f32]) {
    assert_eq!(output.len(), layer.shape.output.len());
    // SAFETY: `output` holds the whole output plane and is borrowed mutably for the call.
    unsafe { conv_channels(layer, input, output.as_mut_ptr(), 0..layer.shape.output.channels) }
}

/// See [`crate::conv_channels`].
///
/// # Safety
/// `output` must point to the whole output plane (`shape.output.len()` floats), valid for
/// writes, and no other thread may read or write channels `channels` of it during the call.
pub(crate) unsafe fn conv_channels(layer: ConvParams<'_>, input: &[f32], output: *mut f32, channels: Range<usize>) {
    unsafe {
        let ConvParams {
            shape,
            weights,
            bias,
            act,
        } = layer;
        let ConvShape {
            kind,
            kernel: k,
            input: ip,
            output: op,
        } = shape;
        let pad = k / 2;
        for oy in 0..op.height {
            for ox in 0..op.width {
                // SAFETY: the caller gives us these channels of every output pixel.
                let out =
                    core::slice::from_raw_parts_mut(output.add(op.index(oy, ox) + channels.start), channels.len());
                out.copy_from_slice(&bias[channels.clone()]);
                for ky in 0..k {
                    let Some(iy) = kind.source(oy, ky, pad, ip.height) else {
                        continue;
                    };
                    for kx in 0..k {
                        let Some(ix) = kind.source(ox, kx, pad, ip.width) else {
                            continue;
                        };
                        let pixel = &input[ip.index(iy, ix)..][..ip.channels];
                        for (ic, &v) in pixel.iter().enumerate() {
                            for (o, out) in channels.clone().zip(out.iter_mut()) {
                                *out += v * weights[shape.packed_index(ky, kx, ic, o)];
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
}

/// See [`crate::winograd_input`]: the transforms one float at a time.
pub fn winograd_input(w: &Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
    // SAFETY: plain scalar code; `crate::winograd_input` checked the buffer lengths.
    unsafe { winograd::with_phase(w, phase, &mut winograd::InputTransform::<f32>::new(w, input, v)) }
}

/// See [`crate::winograd_weights`]: the transform one weight at a time, in f64, rounded once.
pub fn winograd_weights(w: &Winograd, direct: &[f32], packed: &mut [f32]) {
    let mut transform = winograd::ExactWeightTransform { w, direct, packed };
    for phase in 0..4 {
        // SAFETY: plain scalar code (bounds-checked).
        unsafe { winograd::with_phase(w, phase, &mut transform) }
    }
}

/// See [`crate::winograd_channels`]: the products straight from their definition, the output
/// transform one float at a time.
///
/// # Safety
/// As for [`conv_channels`].
pub(crate) unsafe fn winograd_channels(
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    output: *mut f32,
    channels: Range<usize>,
) {
    unsafe { winograd::channels::<f32, _>(&winograd::ScalarProduct, w, layer, v, scratch, output, channels) }
}

/// See [`crate::dense`].
pub fn dense(w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    assert_eq!(y.len(), x.len() / w.cols * w.rows);
    // SAFETY: `y` holds every row of every item.
    unsafe { dense_rows(w, Some(bias), act, x, y.as_mut_ptr(), w.rows) }
}

/// `y[n * ldy + r] = act(W[r] . x[n] + bias[r])` for every row `r` of `w` and item `n`; without
/// a bias, `act(W[r] . x[n] + y[n * ldy + r])`.
///
/// # Safety
/// `y` must be valid for those reads and writes, and no other thread may read or write them.
pub(crate) unsafe fn dense_rows(
    w: Matrix<'_>,
    bias: Option<&[f32]>,
    act: Activation,
    x: &[f32],
    y: *mut f32,
    ldy: usize,
) {
    unsafe {
        let weight = |r: usize, c: usize| {
            let at = Matrix::packed_index(r, c, w.cols);
            match w.data {
                MatrixData::F32(d) => d[at],
                MatrixData::F16(d) => d[at].to_f32(),
            }
        };
        for (n, x) in x.chunks_exact(w.cols).enumerate() {
            for r in 0..w.rows {
                let dot: f32 = x.iter().enumerate().map(|(c, &x)| weight(r, c) * x).sum();
                let out = y.add(n * ldy + r);
                *out = act.apply(dot + bias.map_or(*out, |b| b[r]));
            }
        }
    }
}

/// See [`crate::dense_weight_grad`].
pub fn dense_weight_grad(dy: &[f32], x: &[f32], rows: usize, cols: usize, grad: &mut [f32]) {
    assert_eq!(grad.len(), Matrix::packed_len(rows, cols));
    // SAFETY: `grad` holds the whole packed matrix and is borrowed mutably for the call.
    unsafe { dense_weight_grad_rows(dy, x, cols, grad.as_mut_ptr(), 0..rows, rows, false) }
}

/// `grad[r][c] = Σ_k dy[k * total_rows + r] * x[k * cols + c]` for the rows `rows`, summed in
/// item order, into the packed layout of a `total_rows x cols` [`Matrix`] (added to what it
/// holds if `accumulate`); when `rows` ends the matrix, the padding rows of its last panel are
/// set to zero.
///
/// # Safety
/// `grad` must point to the whole packed matrix, valid for writes, and no other thread may
/// read or write the panels of `rows` during the call.
pub(crate) unsafe fn dense_weight_grad_rows(
    dy: &[f32],
    x: &[f32],
    cols: usize,
    grad: *mut f32,
    rows: Range<usize>,
    total_rows: usize,
    accumulate: bool,
) {
    unsafe {
        let end = rows.end.next_multiple_of(crate::OC_ALIGN);
        for r in rows.start..end {
            for c in 0..cols {
                let sum = if r < total_rows {
                    let (dy, x) = (dy.chunks_exact(total_rows), x.chunks_exact(cols));
                    dy.zip(x).map(|(dy, x)| dy[r] * x[c]).sum()
                } else {
                    0.0
                };
                let g = grad.add(Matrix::packed_index(r, c, cols));
                *g = if accumulate { *g + sum } else { sum };
            }
        }
    }
}

/// `dx[n * cols + c] = Σ_r W[r][c] dy[n * rows + r]` for the columns `columns` of the packed
/// f32 `rows x cols` matrix `w` and every item `n` (see [`crate::dense_data_grad`]), summed in
/// row order.
///
/// # Safety
/// `dx` must be valid for those writes, and no other thread may read or write them.
pub(crate) unsafe fn dense_data_grad_cols(
    w: &[f32],
    rows: usize,
    cols: usize,
    dy: &[f32],
    dx: *mut f32,
    columns: Range<usize>,
) {
    unsafe {
        // Columns outside, items inside: a column's weights (one cache line per panel) are read
        // once for every item.
        for c in columns {
            for (n, dy) in dy.chunks_exact(rows).enumerate() {
                let sum: f32 = dy
                    .iter()
                    .enumerate()
                    .map(|(r, &d)| w[Matrix::packed_index(r, c, cols)] * d)
                    .sum();
                *dx.add(n * cols + c) = sum;
            }
        }
    }
}

/// See [`crate::activation_backward`]: [`Activation::backward`] value by value.
pub fn activation_backward(act: Activation, y: &[f32], grad: &mut [f32]) {
    for (g, &y) in grad.iter_mut().zip(y) {
        *g = act.backward(y, *g);
    }
}

/// Adds `Σ f(i, c).0` and `Σ f(i, c).1` over one plane's interior values (`i` a value's index,
/// `c` its channel) to `sums[c]` and `sums[channels + c]`: per channel, a sum from zero in
/// pixel order, then added to `sums`.
fn add_sums(plane: Plane, sums: &mut [f64], f: impl Fn(usize, usize) -> (f64, f64)) {
    let c = plane.channels;
    for block in norm::blocks(c) {
        let (mut a, mut b) = ([0.0f64; norm::BLOCK], [0.0f64; norm::BLOCK]);
        for row in norm::rows(plane) {
            for p in row {
                for (j, ch) in block.clone().enumerate() {
                    let (u, v) = f(p + ch, ch);
                    a[j] += u;
                    b[j] += v;
                }
            }
        }
        for (j, ch) in block.enumerate() {
            sums[ch] += a[j];
            sums[c + ch] += b[j];
        }
    }
}

/// See [`crate::norm::moments`]: per channel, `Σ x` and `Σ x²` in f64.
pub fn moments(plane: Plane, x: &[f32], sums: &mut [f64]) {
    add_sums(plane, sums, |i, _| (x[i] as f64, x[i] as f64 * x[i] as f64));
}

/// See [`crate::norm::gradient_moments`]: per channel, `Σ g` and `Σ (x - mean) · g` in f64.
pub fn gradient_moments(plane: Plane, x: &[f32], g: &[f32], mean: &[f32], sums: &mut [f64]) {
    add_sums(plane, sums, |i, c| {
        (g[i] as f64, (x[i] as f64 - mean[c] as f64) * g[i] as f64)
    });
}

/// See [`crate::norm::normalize_gradient`]: `g = (g - mean_g - (x - mean) · proj) · scale` in
/// f64 for the channels of `block`.
pub(crate) fn normalize_gradient_block(
    plane: Plane,
    x: &[f32],
    g: &mut [f32],
    block: Range<usize>,
    coef: &norm::GradientCoefficients,
) {
    for row in norm::rows(plane) {
        for p in row {
            let span = p + block.start..p + block.end;
            for (j, (gv, &xv)) in g[span.clone()].iter_mut().zip(&x[span]).enumerate() {
                let centred = (xv as f64 - coef.mean[j]) * coef.proj[j];
                *gv = ((*gv as f64 - coef.mean_g[j] - centred) * coef.scale[j]) as f32;
            }
        }
    }
}

/// See [`crate::adam`]: element by element, each operation rounded as written.
pub fn adam(s: crate::AdamStep, params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
    for (((p, &g), m), v) in params.iter_mut().zip(grads).zip(m.iter_mut()).zip(v.iter_mut()) {
        let g = g * s.scale;
        *m += (g - *m) * (1.0 - s.beta1);
        *v = *v * s.beta2 + (1.0 - s.beta2) * g * g;
        *p -= s.step_size * *m / (sqrt(*v) / s.correction2_sqrt + s.eps);
    }
}

/// The correctly rounded square root: the CPU's instruction with std, else from f64 (Newton's
/// method, correct to the last bit but for values within an f64 ulp of a halfway point).
#[inline]
fn sqrt(x: f32) -> f32 {
    #[cfg(feature = "std")]
    return x.sqrt();
    #[cfg(not(feature = "std"))]
    return crate::math::sqrt(x as f64) as f32;
}

/// See [`crate::norm::normalize`]: `y = act(x · scale + shift)` for the channels of `block`
/// (`scale` and `shift` indexed from the block's first channel).
pub(crate) fn normalize_block(
    plane: Plane,
    x: &[f32],
    y: &mut [f32],
    block: Range<usize>,
    (scale, shift): (&[f32; norm::BLOCK], &[f32; norm::BLOCK]),
    act: Activation,
) {
    let (scale, shift) = (&scale[..block.len()], &shift[..block.len()]);
    // One loop per activation, each with its activation known (a match per value stops the
    // loop vectorising).
    match act {
        Activation::Identity => affine(plane, x, y, &block, scale, shift, |v| v),
        Activation::Relu => affine(plane, x, y, &block, scale, shift, |v| Activation::Relu.apply(v)),
        Activation::LeakyRelu(s) => affine(plane, x, y, &block, scale, shift, |v| Activation::LeakyRelu(s).apply(v)),
        Activation::Tanh => affine(plane, x, y, &block, scale, shift, |v| Activation::Tanh.apply(v)),
    }
}

/// `y = f(x · scale + shift)` for the channels of `block` of one plane's interior.
#[inline(always)]
fn affine(
    plane: Plane,
    x: &[f32],
    y: &mut [f32],
    block: &Range<usize>,
    scale: &[f32],
    shift: &[f32],
    f: impl Fn(f32) -> f32,
) {
    for row in norm::rows(plane) {
        for p in row {
            let span = p + block.start..p + block.end;
            for (((o, &v), &a), &b) in y[span.clone()].iter_mut().zip(&x[span]).zip(scale).zip(shift) {
                *o = f(v * a + b);
            }
        }
    }
}
