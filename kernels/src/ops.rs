//! The operations' entry points: each checks its arguments against the layouts, then runs the
//! kernel of the caller's instruction set (see `simd::entries`: the scalar kernels are the
//! fallback of every operation, in one place).
//!
//! The parts of an operation that threads share take an [`OutputPart`] of the output buffer
//! (from [`OutputParts::take`](crate::OutputParts::take), which hands each part out once), so
//! every entry point here is safe.

use crate::winograd::Winograd;
use crate::{simd, Activation, ConvKind, ConvParams, ConvShape, Isa, Matrix, OutputPart};
use core::ops::Range;

/// `output = act(conv(input) + bias)` for one image: see [`crate::ConvShape`] for the layouts.
/// Only the interior of `output` is written; its border stays as it was (zero).
pub fn conv(isa: Isa, layer: ConvParams<'_>, input: &[f32], output: &mut [f32]) {
    let channels = layer.shape.output.channels;
    conv_channels(isa, layer, input, OutputPart::whole(output, channels));
}

/// [`conv`] for the output channels of `part` only (its units), so that threads can fill
/// disjoint channel ranges of one output plane at once; each reads only its own panels of
/// weights.
pub fn conv_channels(isa: Isa, layer: ConvParams<'_>, input: &[f32], part: OutputPart<'_>) {
    layer.shape.check(input, layer.weights, layer.bias);
    assert_eq!(part.buffer_len(), layer.shape.output.len());
    let channels = part.units();
    layer.shape.check_channels(&channels);
    // SAFETY: `isa` proves the CPU has the kernel's features; the part's buffer is the whole
    // output plane (checked), and its channels are this call's alone.
    unsafe { (simd::entries(isa).conv)(layer, input, part.ptr(), channels) }
}

/// Step 1 of a Winograd convolution (see [`crate::winograd`]): writes the transformed input
/// of stride phase `phase` (0 to 3) to `v`, the span [`Winograd::phase_span`] of the whole
/// transformed input. Threads may fill different phases at once.
pub fn winograd_input(isa: Isa, w: &Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
    assert!(phase < 4);
    assert_eq!(input.len(), w.shape.input.len());
    assert_eq!(v.len(), w.phase_span(phase).len());
    // SAFETY: `isa` proves the CPU has the kernel's features; the lengths are checked above.
    unsafe { (simd::entries(isa).winograd_input)(w, phase, input, v) }
}

/// Transforms weights packed for the direct convolution of `w.shape` (by
/// [`crate::pack::conv_weights`] or [`crate::pack::conv_weights_into`]) into `packed`,
/// [`Winograd::packed_len`] floats, for [`winograd_channels`], without allocating: `G g G^T` of
/// each phase's taps. The scalar level computes it in f64 and rounds once (a loaded model is
/// packed so, on every CPU); the vector levels in f32 with fused multiply-adds, within a few
/// ulp of it and four times as fast: a trainer runs it after every update.
pub fn winograd_weights(isa: Isa, w: &Winograd, direct: &[f32], packed: &mut [f32]) {
    assert_eq!(direct.len(), w.shape.packed_len());
    assert_eq!(packed.len(), w.packed_len());
    // SAFETY: `isa` proves the CPU has the kernel's features; the lengths are checked above
    // (whole panels in both layouts).
    unsafe { (simd::entries(isa).winograd_weights)(w, direct, packed) }
}

/// Steps 2 and 3 of a Winograd convolution (see [`crate::winograd`]) for the output channels
/// of `part`: `output = act(conv(input) + bias)` from the transformed input `v` (all four
/// phases) and weights packed by [`crate::pack::winograd_weights`] for the same `w`, using
/// `scratch` ([`Winograd::scratch_len`] floats, one per thread). Only those channels of the
/// output's interior are written.
pub fn winograd_channels(
    isa: Isa,
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    part: OutputPart<'_>,
) {
    assert_eq!(w.shape, layer.shape);
    assert_eq!(layer.weights.len(), w.packed_len());
    assert_eq!(layer.bias.len(), layer.shape.output.channels);
    assert_eq!(v.len(), w.input_len());
    assert!(scratch.len() >= w.scratch_len());
    assert_eq!(part.buffer_len(), layer.shape.output.len());
    let channels = part.units();
    layer.shape.check_channels(&channels);
    // SAFETY: as in `conv_channels`.
    unsafe { (simd::entries(isa).winograd_channels)(w, layer, v, scratch, part.ptr(), channels) }
}

/// A whole Winograd convolution on one thread: [`winograd_input`] for every phase into `v`
/// ([`Winograd::input_len`] floats), then [`winograd_channels`] for every channel.
pub fn winograd_conv(
    isa: Isa,
    w: &Winograd,
    layer: ConvParams<'_>,
    input: &[f32],
    v: &mut [f32],
    scratch: &mut [f32],
    output: &mut [f32],
) {
    assert_eq!(v.len(), w.input_len());
    for phase in 0..4 {
        winograd_input(isa, w, phase, input, &mut v[w.phase_span(phase)]);
    }
    let channels = layer.shape.output.channels;
    winograd_channels(isa, w, layer, v, scratch, OutputPart::whole(output, channels));
}

/// `y[n] = act(W x[n] + bias)` for a batch of `x.len() / W.cols` inputs stored one after another.
pub fn dense(isa: Isa, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    dense_rows(isa, w, bias, act, x, OutputPart::whole(y, w.rows));
}

/// [`dense`] for the rows of `part` only (`y[n * W.rows + r]` for `r` in its units), so that
/// threads can fill disjoint row ranges of one batch's output at once, each reading only its
/// rows of the weights.
pub fn dense_rows(isa: Isa, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], part: OutputPart<'_>) {
    assert_eq!(bias.len(), w.rows);
    dense_part(isa, w, Some(bias), act, x, part);
}

/// `y[n] = act(y[n] + W x[n])`: [`dense`] adding to what `y` holds instead of a bias, with the
/// same bits as [`dense`] given that as the bias. What a product's second part does after its
/// first (a transition's action after its shared state).
pub fn dense_add(isa: Isa, w: Matrix<'_>, act: Activation, x: &[f32], y: &mut [f32]) {
    dense_add_rows(isa, w, act, x, OutputPart::whole(y, w.rows));
}

/// [`dense_add`] for the rows of `part` only, as [`dense_rows`].
pub fn dense_add_rows(isa: Isa, w: Matrix<'_>, act: Activation, x: &[f32], part: OutputPart<'_>) {
    dense_part(isa, w, None, act, x, part);
}

/// [`dense_rows`] and [`dense_add_rows`].
fn dense_part(isa: Isa, w: Matrix<'_>, bias: Option<&[f32]>, act: Activation, x: &[f32], part: OutputPart<'_>) {
    let rows = part.units();
    assert!(rows.start.is_multiple_of(crate::OC_ALIGN) && rows.end <= w.rows);
    w.check_packed();
    assert!(w.cols > 0 && x.len().is_multiple_of(w.cols), "input is not whole rows");
    assert_eq!(part.buffer_len(), x.len() / w.cols * w.rows);
    let (ldy, sub) = (w.rows, w.row_range(rows.clone()));
    // SAFETY: `isa` proves the CPU has the kernel's features; the part's buffer holds every row
    // of every item (checked), and its rows are this call's alone.
    unsafe {
        let y = part.ptr().add(rows.start);
        (simd::entries(isa).dense)(sub, bias.map(|b| &b[rows]), act, x, y, ldy)
    }
}

/// The data gradient of [`dense`] over a batch: `dx = dy W`, that is
/// `dx[k][c] = Σ_r W[r][c] dy[k][r]` for `K` items, `dy` `K x rows` and `dx` `K x cols`
/// item-major, read from the packed f32 weights of the forward pass (no transposed copy).
pub fn dense_data_grad(isa: Isa, w: &[f32], rows: usize, cols: usize, dy: &[f32], dx: &mut [f32]) {
    dense_data_grad_cols(isa, w, rows, cols, dy, OutputPart::whole(dx, cols));
}

/// [`dense_data_grad`] for the columns of `part` only (`dx[k * cols + c]` for `c` in its
/// units), so that threads can fill disjoint columns of one batch's gradient at once; each
/// value is summed in the same order whatever the split or the batch.
pub fn dense_data_grad_cols(isa: Isa, w: &[f32], rows: usize, cols: usize, dy: &[f32], part: OutputPart<'_>) {
    assert_eq!(w.len(), Matrix::packed_len(rows, cols));
    assert!(
        rows > 0 && dy.len().is_multiple_of(rows),
        "output gradient is not whole rows"
    );
    assert_eq!(part.buffer_len(), dy.len() / rows * cols);
    let columns = part.units();
    assert!(columns.end <= cols);
    // SAFETY: `isa` proves the CPU has the kernel's features; the part's buffer holds every
    // column of every item (checked), and its columns are this call's alone.
    unsafe { (simd::entries(isa).dense_data_grad)(w, rows, cols, dy, part.ptr(), columns) }
}

/// The weight gradient of [`dense`] over a batch: `grad = dyᵀ x`, that is
/// `grad[r][c] = Σ_k dy[k][r] x[k][c]` for `K` items, with `dy` `K x rows` and `x` `K x cols`
/// item-major (the gradients of the outputs and the inputs of the forward pass). `grad` is
/// overwritten in the packed layout of a `rows x cols` [`Matrix`] (its padding rows zero), so
/// that it lines up with the packed weights it updates.
pub fn dense_weight_grad(isa: Isa, dy: &[f32], x: &[f32], rows: usize, cols: usize, grad: &mut [f32]) {
    dense_weight_grad_rows(isa, dy, x, rows, cols, OutputPart::whole(grad, rows));
}

/// [`dense_weight_grad`] for the rows of `part` only, so that threads can fill disjoint panels
/// of one gradient at once; each item is summed in the same order whatever the split.
pub fn dense_weight_grad_rows(isa: Isa, dy: &[f32], x: &[f32], rows: usize, cols: usize, part: OutputPart<'_>) {
    weight_grad_rows(isa, dy, x, rows, cols, part, false)
}

/// [`dense_weight_grad_rows`] adding `dyᵀ x` to what the gradient holds: a sum over several
/// batches (the chunks of a convolution's patches, see [`conv_patches`]).
pub fn dense_weight_grad_add_rows(isa: Isa, dy: &[f32], x: &[f32], rows: usize, cols: usize, part: OutputPart<'_>) {
    weight_grad_rows(isa, dy, x, rows, cols, part, true)
}

fn weight_grad_rows(isa: Isa, dy: &[f32], x: &[f32], rows: usize, cols: usize, part: OutputPart<'_>, accumulate: bool) {
    let units = part.units();
    assert!(units.start.is_multiple_of(crate::OC_ALIGN) && units.end <= rows);
    assert!(
        rows > 0 && cols > 0 && dy.len().is_multiple_of(rows),
        "dy is not whole rows"
    );
    assert_eq!(x.len(), dy.len() / rows * cols, "dy and x hold different batches");
    assert_eq!(part.buffer_len(), Matrix::packed_len(rows, cols));
    // SAFETY: `isa` proves the CPU has the kernel's features; the part's buffer is the whole
    // packed matrix (checked), and the panels of its rows are this call's alone.
    unsafe { (simd::entries(isa).dense_weight_grad)(dy, x, cols, part.ptr(), units, rows, accumulate) }
}

/// The gradient through `y = act(x)`, given `y`, in place (see [`Activation::backward`]):
/// bit-identical on every instruction set.
pub fn activation_backward(isa: Isa, act: Activation, y: &[f32], grad: &mut [f32]) {
    assert_eq!(y.len(), grad.len());
    // SAFETY: `isa` proves the CPU has the kernel's features.
    unsafe { (simd::entries(isa).activation_backward)(act, y, grad) }
}

/// Output pixels per chunk of a convolution's weight gradient: one chunk of the dense weight
/// gradient's items. The chunks are numbered over the whole batch, so the sums run in the same
/// order whatever the thread count.
pub const GRAD_PIXELS: usize = 128;

/// Floats in the patch an output pixel of `shape` reads: `k · k · in_channels`, the columns of
/// its weight gradient.
pub const fn conv_patch_len(shape: &ConvShape) -> usize {
    shape.kernel * shape.kernel * shape.input.channels
}

/// Floats of scratch that [`conv_weight_grad_rows`] needs for `shape`, one per thread: a chunk
/// of patches and of output gradients.
pub const fn conv_weight_grad_scratch_len(shape: &ConvShape) -> usize {
    GRAD_PIXELS * (conv_patch_len(shape) + shape.output.channels)
}

/// The weight gradient of a strided convolution ([`ConvKind::Down`]) summed over a batch:
/// `grad[o][(ky, kx, i)] = Σ dy[o](oy, ox) · x[i](2oy + ky - k/2, 2ox + kx - k/2)` over items and
/// output pixels, overwriting `grad`, the packed `out_channels x (k·k·in_channels)` [`Matrix`]
/// (for layers wider than [`crate::NARROW_OC`], the packed layout of the weights themselves).
/// `input` holds planes of `shape.input`, `dy` the same number of planes of `shape.output`.
///
/// It is [`dense_weight_grad`] with one item per output pixel whose input is the patch the
/// pixel reads ([`conv_patches`]), gathered a chunk of [`GRAD_PIXELS`] at a time into
/// `scratch` ([`conv_weight_grad_scratch_len`]). The gradient of a transposed convolution
/// `x -> y` is this one for its [`ConvShape::transposed`] shape with the roles swapped: `input`
/// the gradient of `y`, `dy` the layer's input `x`; its rows are then the layer's input
/// channels, as in PyTorch's `[in, out, k, k]` tensor (see [`crate::pack::conv_matrix_to_torch`]).
pub fn conv_weight_grad(isa: Isa, shape: ConvShape, input: &[f32], dy: &[f32], scratch: &mut [f32], grad: &mut [f32]) {
    let rows = shape.output.channels;
    conv_weight_grad_rows(isa, shape, input, dy, scratch, OutputPart::whole(grad, rows));
}

/// [`conv_weight_grad`] for the output channels of `part` only, so that threads can fill
/// disjoint panels of one gradient at once, each with its own `scratch`: each then gathers
/// every patch itself, and no thread reads what another wrote (on a VM whose two vCPUs sit on
/// different dies, reading another core's writes costs hundreds of nanoseconds a line).
pub fn conv_weight_grad_rows(
    isa: Isa,
    shape: ConvShape,
    input: &[f32],
    dy: &[f32],
    scratch: &mut [f32],
    part: OutputPart<'_>,
) {
    conv_grad_rows(isa, shape, input, dy, scratch, part, false)
}

/// [`conv_weight_grad_rows`] adding the gradient to what `part` holds (a trainer's gradient
/// summed over several passes).
pub fn conv_weight_grad_add_rows(
    isa: Isa,
    shape: ConvShape,
    input: &[f32],
    dy: &[f32],
    scratch: &mut [f32],
    part: OutputPart<'_>,
) {
    conv_grad_rows(isa, shape, input, dy, scratch, part, true)
}

/// Output pixels of `shape` in a batch of `items` planes: the items of its weight gradient, which
/// [`conv_weight_grad_block_rows`] takes in ranges.
pub const fn conv_grad_pixels(shape: &ConvShape, items: usize) -> usize {
    items * shape.output.height * shape.output.width
}

/// [`conv_weight_grad_rows`] over the output pixels `pixels` of the batch only (numbered item by
/// item, row by row, as [`conv_patches`]), overwriting the rows of `part`: one block of a sum
/// that threads share by pixels as well as by rows, each block into a gradient of its own, the
/// blocks then added in a fixed order. A block starting on a multiple of [`GRAD_PIXELS`] sums its
/// chunks as the whole-batch functions do.
pub fn conv_weight_grad_block_rows(
    isa: Isa,
    shape: ConvShape,
    input: &[f32],
    dy: &[f32],
    pixels: Range<usize>,
    scratch: &mut [f32],
    part: OutputPart<'_>,
) {
    let total = conv_pixels(&shape, input, dy);
    assert!(
        pixels.start <= pixels.end && pixels.end <= total,
        "pixels past the batch"
    );
    pixel_grad_rows(isa, shape, input, dy, pixels, scratch, part, false)
}

fn conv_grad_rows(
    isa: Isa,
    shape: ConvShape,
    input: &[f32],
    dy: &[f32],
    scratch: &mut [f32],
    part: OutputPart<'_>,
    add: bool,
) {
    let total = conv_pixels(&shape, input, dy);
    pixel_grad_rows(isa, shape, input, dy, 0..total, scratch, part, add)
}

/// The weight gradient over `pixels` (checked to lie in the batch), a chunk of [`GRAD_PIXELS`]
/// at a time from its start, added to `part` if `add`.
#[allow(clippy::too_many_arguments)]
fn pixel_grad_rows(
    isa: Isa,
    shape: ConvShape,
    input: &[f32],
    dy: &[f32],
    pixels: Range<usize>,
    scratch: &mut [f32],
    mut part: OutputPart<'_>,
    add: bool,
) {
    let (rows, cols) = (shape.output.channels, conv_patch_len(&shape));
    assert!(scratch.len() >= conv_weight_grad_scratch_len(&shape));
    let (first, end) = (pixels.start, pixels.end);
    let (patches, dys) = scratch.split_at_mut(GRAD_PIXELS * cols);
    // At least one chunk, which checks `part`: no pixels make a zero gradient.
    for start in (first..end.max(first + 1)).step_by(GRAD_PIXELS) {
        let n = GRAD_PIXELS.min(end - start.min(end));
        conv_patches(
            shape,
            input,
            dy,
            start..start + n,
            &mut patches[..n * cols],
            &mut dys[..n * rows],
        );
        let (d, x) = (&dys[..n * rows], &patches[..n * cols]);
        weight_grad_rows(isa, d, x, rows, cols, part.reborrow(), add || start > first);
    }
}

/// Output pixels in a batch of `input` and `dy` for `shape` (checked: a strided layer, whole
/// planes, the same number of each).
fn conv_pixels(shape: &ConvShape, input: &[f32], dy: &[f32]) -> usize {
    let (ip, op, k) = (shape.input, shape.output, shape.kernel);
    assert_eq!(
        shape.kind,
        ConvKind::Down,
        "a transposed layer's weight gradient is its transposed shape's"
    );
    assert!(k % 2 == 1 && ip.halo >= k / 2, "odd kernels in a border of k / 2");
    assert_eq!(*shape, ConvShape::new(shape.kind, k, ip, op.channels, op.halo));
    assert!(input.len().is_multiple_of(ip.len()), "input is not whole planes");
    let items = input.len() / ip.len();
    assert_eq!(dy.len(), items * op.len(), "input and dy hold different batches");
    items * op.height * op.width
}

/// The items of a strided convolution's weight gradient as a dense one's, for the output
/// pixels `pixels` of a batch (numbered item by item, row by row): each pixel's patch (the
/// `k · k · in_channels` inputs its taps read, [`conv_patch_len`]) into `patches`, and its
/// output gradient (`out_channels`) into `dys`, pixel after pixel.
pub fn conv_patches(
    shape: ConvShape,
    input: &[f32],
    dy: &[f32],
    pixels: Range<usize>,
    patches: &mut [f32],
    dys: &mut [f32],
) {
    let total = conv_pixels(&shape, input, dy);
    let (ip, op, k) = (shape.input, shape.output, shape.kernel);
    let (rows, cols) = (op.channels, conv_patch_len(&shape));
    assert!(pixels.start <= pixels.end && pixels.end <= total);
    assert_eq!(patches.len(), pixels.len() * cols);
    assert_eq!(dys.len(), pixels.len() * rows);
    let per_item = op.height * op.width;
    // Tap (ky, kx) reads input pixel (2oy + ky - k/2, 2ox + kx - k/2): the k taps of one row of
    // the kernel are k adjacent pixels, inside the border.
    let row = k * ip.channels;
    for ((p, patch), d) in pixels
        .zip(patches.chunks_exact_mut(cols))
        .zip(dys.chunks_exact_mut(rows))
    {
        let (item, pixel) = (p / per_item, p % per_item);
        let (oy, ox) = (pixel / op.width, pixel % op.width);
        d.copy_from_slice(&dy[item * op.len() + op.index(oy, ox)..][..rows]);
        let x = &input[item * ip.len()..][..ip.len()];
        for (ky, patch_row) in patch.chunks_exact_mut(row).enumerate() {
            let at = (2 * oy + ky + ip.halo - k / 2) * ip.row_stride() + (2 * ox + ip.halo - k / 2) * ip.channels;
            patch_row.copy_from_slice(&x[at..][..row]);
        }
    }
}

/// The constants of one Adam step for [`adam`] (the optimiser of `drivesim::train`, with
/// PyTorch's arithmetic).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamStep {
    /// Decay of the first moment.
    pub beta1: f32,
    /// Decay of the second moment.
    pub beta2: f32,
    /// Added to the denominator.
    pub eps: f32,
    /// Multiplies every gradient first (gradient clipping; 1: none).
    pub scale: f32,
    /// `lr / (1 - β1ᵗ)` at step `t`.
    pub step_size: f32,
    /// `√(1 - β2ᵗ)` at step `t`.
    pub correction2_sqrt: f32,
}

/// One Adam step on `params` from `grads`, with the moments `m` and `v` (all the same length),
/// element by element: `g = scale · grad`, `m += (g - m)(1 - β1)`, `v = β2 v + (1 - β2) g g`,
/// `p -= step_size · m / (√v / correction2_sqrt + eps)`. Each operation is rounded as written
/// (IEEE, none fused), so every instruction set gives the same bits.
pub fn adam(isa: Isa, step: AdamStep, params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
    let n = params.len();
    assert!(grads.len() == n && m.len() == n && v.len() == n);
    // SAFETY: `isa` proves the CPU has the kernel's features; the lengths are checked above.
    unsafe { (simd::entries(isa).adam)(step, params, grads, m, v) }
}
