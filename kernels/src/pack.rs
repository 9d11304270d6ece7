//! Weight preparation done once at load: PyTorch layouts in, kernel layouts out.

use crate::winograd::Winograd;
use crate::{math, ConvKind, ConvShape, Matrix, OC_ALIGN};
use alloc::vec::Vec;

/// PyTorch's BatchNorm epsilon.
pub const BN_EPS: f64 = 1e-5;

/// Eval-mode BatchNorm parameters of one layer (per channel).
#[derive(Clone, Copy, Debug)]
pub struct BatchNorm<'a> {
    /// Scale (gamma).
    pub weight: &'a [f32],
    /// Shift (beta).
    pub bias: &'a [f32],
    /// The mean used in eval mode.
    pub running_mean: &'a [f32],
    /// The variance used in eval mode (eps 1e-5 is added).
    pub running_var: &'a [f32],
}

impl BatchNorm<'_> {
    /// `bn(x) = scale * x + shift` per channel, computed in f64.
    pub fn affine(&self) -> Vec<(f64, f64)> {
        (0..self.weight.len())
            .map(|c| {
                let scale = self.weight[c] as f64 / math::sqrt(self.running_var[c] as f64 + BN_EPS);
                (scale, self.bias[c] as f64 - scale * self.running_mean[c] as f64)
            })
            .collect()
    }
}

/// Packs PyTorch convolution weights into panels of output channels (see [`ConvShape`]),
/// folding an optional BatchNorm that follows the layer into weights and bias.
///
/// `torch_weight` is `[out, in, k, k]` for [`ConvKind::Down`] (`Conv2d`) and `[in, out, k, k]`
/// for [`ConvKind::Up`] (`ConvTranspose2d`). Returns `(packed weights, bias)`.
pub fn conv_weights(
    shape: &ConvShape,
    torch_weight: &[f32],
    bias: &[f32],
    bn: Option<BatchNorm<'_>>,
) -> (Vec<f32>, Vec<f32>) {
    let oc = shape.output.channels;
    assert_eq!(bias.len(), oc);
    let affine = bn.map(|bn| bn.affine()).unwrap_or_else(|| alloc::vec![(1.0, 0.0); oc]);
    assert_eq!(affine.len(), oc);
    let mut packed = alloc::vec![0.0f32; shape.packed_len()];
    for_each_conv_weight(shape, torch_weight.len(), |src, _, at, o| {
        packed[at] = (torch_weight[src] as f64 * affine[o].0) as f32
    });
    let bias = bias
        .iter()
        .zip(&affine)
        .map(|(&b, &(s, t))| (b as f64 * s + t) as f32)
        .collect();
    (packed, bias)
}

/// [`conv_weights`] without BatchNorm and without allocating: packs `torch_weight` into
/// `packed` ([`ConvShape::packed_len`] floats, its padding left as it was). Packs a layer's data
/// gradient, the forward pass of [`ConvShape::transposed`], from the layer's own PyTorch
/// weights.
pub fn conv_weights_into(shape: &ConvShape, torch_weight: &[f32], packed: &mut [f32]) {
    assert_eq!(packed.len(), shape.packed_len());
    for_each_conv_weight(shape, torch_weight.len(), |src, _, at, _| {
        packed[at] = torch_weight[src]
    });
}

/// A convolution's weights in the layout of its gradient ([`crate::conv_weight_grad`]): the
/// packed `out x (k·k·in)` [`Matrix`] of its strided form ([`ConvShape::strided`]). A trainer keeps its weights so, for the gradients to add
/// to them as they come; this packs them for `shape` (either form) after every update, its
/// padding left as it was.
pub fn conv_weights_from_matrix(shape: &ConvShape, matrix: &[f32], packed: &mut [f32]) {
    assert_eq!(packed.len(), shape.packed_len());
    assert_eq!(matrix.len(), conv_matrix_len(shape));
    let (k, ic, oc) = (shape.kernel, shape.input.channels, shape.output.channels);
    match (shape.kind, shape.is_narrow()) {
        // A strided layer with panels of outputs is packed as its matrix is.
        (ConvKind::Down, false) => packed.copy_from_slice(matrix),
        // A transposed layer with panels: for each tap, 16 x 16 blocks (its input channels,
        // the matrix's rows, by its output channels) are transposed, each 1 KiB block to 1 KiB.
        (ConvKind::Up, false) => {
            let row_panel = OC_ALIGN * k * k * oc;
            for tap in 0..k * k {
                for i0 in (0..ic).step_by(OC_ALIGN) {
                    for o0 in (0..oc).step_by(OC_ALIGN) {
                        let (rows, cols) = (OC_ALIGN.min(ic - i0), OC_ALIGN.min(oc - o0));
                        let from = &matrix[i0 / OC_ALIGN * row_panel + (tap * oc + o0) * OC_ALIGN..][..cols * OC_ALIGN];
                        let to = &mut packed[o0 / OC_ALIGN * shape.panel_len() + (tap * ic + i0) * OC_ALIGN..];
                        transpose_block(from, to, rows, cols);
                    }
                }
            }
        }
        _ => for_each_conv_weight(shape, oc * ic * k * k, |_, m, at, _| packed[at] = matrix[m]),
    }
}

/// `to[r][c] = from[c][r]` for the first `rows x cols` of two row-major blocks of 16 columns
/// (`from` holds `cols` rows; a whole 16 x 16 block is unrolled, so that it vectorises; the
/// rest of `to` is left as it was).
fn transpose_block(from: &[f32], to: &mut [f32], rows: usize, cols: usize) {
    if rows == OC_ALIGN && cols == OC_ALIGN {
        let from: &[f32; OC_ALIGN * OC_ALIGN] = from.try_into().expect("a whole block");
        let to: &mut [f32; OC_ALIGN * OC_ALIGN] = (&mut to[..OC_ALIGN * OC_ALIGN]).try_into().expect("a whole block");
        for r in 0..OC_ALIGN {
            for c in 0..OC_ALIGN {
                to[r * OC_ALIGN + c] = from[c * OC_ALIGN + r];
            }
        }
    } else {
        for r in 0..rows {
            for c in 0..cols {
                to[r * OC_ALIGN + c] = from[c * OC_ALIGN + r];
            }
        }
    }
}

/// Floats in [`conv_weights_from_matrix`]'s layout for `shape`.
pub fn conv_matrix_len(shape: &ConvShape) -> usize {
    let down = shape.strided();
    Matrix::packed_len(down.output.channels, down.kernel * down.kernel * down.input.channels)
}

/// Fills [`conv_weights_from_matrix`]'s layout for `shape` from PyTorch weights (`[out, in,
/// k, k]`, or `[in, out, k, k]` for a transposed layer), its padding left as it was.
pub fn conv_matrix_from_torch(shape: &ConvShape, torch_weight: &[f32], matrix: &mut [f32]) {
    assert_eq!(matrix.len(), conv_matrix_len(shape));
    for_each_conv_weight(shape, torch_weight.len(), |src, m, _, _| matrix[m] = torch_weight[src]);
}

/// Calls `f(source, matrix, packed, out_channel)` for every weight of a PyTorch convolution
/// tensor of `torch_len` values (checked to be `shape`'s size): its index there, in
/// [`conv_weights_from_matrix`]'s layout and in the packed layout.
fn for_each_conv_weight(shape: &ConvShape, torch_len: usize, mut f: impl FnMut(usize, usize, usize, usize)) {
    let (k, ic, oc) = (shape.kernel, shape.input.channels, shape.output.channels);
    assert_eq!(torch_len, oc * ic * k * k);
    // In the packed layout's own order, so that it is written in one stream: a trainer repacks
    // after every update, and rows of taps a power-of-two apart (other orders) would fall into
    // a few L1 sets and evict each other (the 128 x 256 layers ran 4x slower).
    let (tap_stride, ic_stride) = (shape.packed_index(0, 1, 0, 0), shape.packed_index(0, 0, 1, 0));
    let lanes = if shape.is_narrow() { 1 } else { OC_ALIGN };
    // The matrix's rows are the strided form's output channels, its columns (tap, input).
    let down_in = shape.strided().input.channels;
    let row_panel = OC_ALIGN * k * k * down_in;
    for first in (0..oc).step_by(lanes) {
        for tap in 0..k * k {
            for i in 0..ic {
                for o in first..oc.min(first + lanes) {
                    let (src, (row, col)) = match shape.kind {
                        ConvKind::Down => ((o * ic + i) * k * k, (o, i)),
                        ConvKind::Up => ((i * oc + o) * k * k, (i, o)),
                    };
                    let m = (row / OC_ALIGN) * row_panel + (tap * down_in + col) * OC_ALIGN + row % OC_ALIGN;
                    let dst = shape.packed_index(0, 0, 0, o) + i * ic_stride + tap * tap_stride;
                    f(src + tap, m, dst, o);
                }
            }
        }
    }
}

/// Packs PyTorch convolution weights for [`crate::winograd_channels`] (see [`Winograd`]),
/// folding an optional BatchNorm as [`conv_weights`] does, with the scalar
/// [`crate::winograd_weights`] (exact to f32 rounding, and the same on every CPU). Returns
/// `(packed weights, bias)`.
pub fn winograd_weights(
    w: &Winograd,
    torch_weight: &[f32],
    bias: &[f32],
    bn: Option<BatchNorm<'_>>,
) -> (Vec<f32>, Vec<f32>) {
    let (direct, bias) = conv_weights(&w.shape, torch_weight, bias, bn);
    let mut packed = alloc::vec![0.0f32; w.packed_len()];
    crate::winograd_weights(crate::Isa::SCALAR, w, &direct, &mut packed);
    (packed, bias)
}

/// The inverse of [`conv_matrix_from_torch`], also for a gradient (the layout is that of
/// [`crate::conv_weight_grad`]'s `out x (k·k·in)` [`crate::Matrix`] for the strided form):
/// fills `torch`, the layer's PyTorch tensor (`[out, in, k, k]`, or `[in, out, k, k]` for a
/// transposed layer), from `packed`. `shape` is the layer, in either form.
pub fn conv_matrix_to_torch(shape: &ConvShape, packed: &[f32], torch: &mut [f32]) {
    let down = shape.strided();
    let (k, ic, oc) = (down.kernel, down.input.channels, down.output.channels);
    let cols = k * k * ic;
    assert_eq!(packed.len(), Matrix::packed_len(oc, cols));
    assert_eq!(torch.len(), oc * cols);
    // In the packed layout's order, so that it is read in one stream (a trainer converts every
    // gradient after every step): panel, column (tap, then input), lane (output channel).
    for (panel, values) in packed.chunks_exact(OC_ALIGN * cols).enumerate() {
        let first = panel * OC_ALIGN;
        let lanes = OC_ALIGN.min(oc - first);
        for (col, column) in values.chunks_exact(OC_ALIGN).enumerate() {
            let (tap, i) = (col / ic, col % ic);
            for (lane, &v) in column[..lanes].iter().enumerate() {
                torch[(first + lane) * cols + i * k * k + tap] = v;
            }
        }
    }
}

/// Maps an index of a flattened `[channels, height, width]` (PyTorch NCHW flatten) tensor to
/// the index of the same value in `[height, width, channels]` order (the kernels' layout).
pub fn chw_to_hwc(index: usize, channels: usize, height: usize, width: usize) -> usize {
    let (c, rest) = (index / (height * width), index % (height * width));
    rest * channels + c
}

/// Reorders the columns of a row-major `rows x (c*h*w)` matrix from CHW to HWC order, so a
/// dense layer reads an HWC feature map as PyTorch reads the NCHW flatten.
pub fn permute_cols_chw_to_hwc<T: Copy + Default>(w: &[T], rows: usize, c: usize, h: usize, wd: usize) -> Vec<T> {
    let cols = c * h * wd;
    assert_eq!(w.len(), rows * cols);
    let mut out = alloc::vec![T::default(); w.len()];
    for (src_row, dst_row) in w.chunks_exact(cols).zip(out.chunks_exact_mut(cols)) {
        for (i, &v) in src_row.iter().enumerate() {
            dst_row[chw_to_hwc(i, c, h, wd)] = v;
        }
    }
    out
}

/// Reorders the rows of a `(c*h*w) x cols` matrix and its bias from CHW to HWC order, folding
/// a per-channel BatchNorm that follows the reshape. Returns `(weights, bias)`.
pub fn permute_rows_chw_to_hwc(
    w: &[f32],
    bias: &[f32],
    cols: usize,
    c: usize,
    h: usize,
    wd: usize,
    bn: Option<BatchNorm<'_>>,
) -> (Vec<f32>, Vec<f32>) {
    let rows = c * h * wd;
    assert_eq!(w.len(), rows * cols);
    assert_eq!(bias.len(), rows);
    let affine = bn.map(|bn| bn.affine()).unwrap_or_else(|| alloc::vec![(1.0, 0.0); c]);
    let mut out_w = alloc::vec![0.0f32; w.len()];
    let mut out_b = alloc::vec![0.0f32; rows];
    for (r, src) in w.chunks_exact(cols).enumerate() {
        let (scale, shift) = affine[r / (h * wd)];
        let dst = chw_to_hwc(r, c, h, wd);
        for (d, &s) in out_w[dst * cols..][..cols].iter_mut().zip(src) {
            *d = (s as f64 * scale) as f32;
        }
        out_b[dst] = (bias[r] as f64 * scale + shift) as f32;
    }
    (out_w, out_b)
}

/// Packs a row-major `rows x cols` matrix (PyTorch's `Linear.weight`) into the panels of
/// [`Matrix`], f32 or f16 alike.
pub fn dense_weights<T: Copy + Default>(row_major: &[T], rows: usize, cols: usize) -> Vec<T> {
    assert_eq!(row_major.len(), rows * cols);
    let mut packed = alloc::vec![T::default(); Matrix::packed_len(rows, cols)];
    dense_from_fn(rows, cols, &mut packed, |r, c| row_major[r * cols + c]);
    packed
}

/// Packs the `rows x cols` matrix whose weight `(r, c)` is `value(r, c)` into `packed` (the
/// panels of [`Matrix`], padding rows set to the default, zero), writing it in order. Training
/// packs transposes with it in place: the data gradient of a dense layer is the forward
/// [`crate::dense`] on `Wᵀ`.
pub fn dense_from_fn<T: Copy + Default>(rows: usize, cols: usize, packed: &mut [T], value: impl Fn(usize, usize) -> T) {
    assert_eq!(packed.len(), Matrix::packed_len(rows, cols));
    for (panel, panel_values) in packed.chunks_exact_mut(OC_ALIGN * cols.max(1)).enumerate() {
        for (col, column) in panel_values.chunks_exact_mut(OC_ALIGN).enumerate() {
            for (lane, p) in column.iter_mut().enumerate() {
                let row = panel * OC_ALIGN + lane;
                *p = if row < rows { value(row, col) } else { T::default() };
            }
        }
    }
}
