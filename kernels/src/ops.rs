//! The operations' entry points: each checks its arguments against the layouts, then runs the
//! kernel of the caller's instruction set.

use crate::winograd::{self, Winograd};
use crate::{scalar, simd, Activation, ConvParams, Isa, IsaLevel, Matrix};

/// `output = act(conv(input) + bias)` for one image: see [`ConvShape`] for the layouts.
/// Only the interior of `output` is written; its border stays as it was (zero).
pub fn conv(isa: Isa, layer: ConvParams<'_>, input: &[f32], output: &mut [f32]) {
    assert_eq!(output.len(), layer.shape.output.len());
    let all = 0..layer.shape.output.channels;
    // SAFETY: `output` holds the whole output plane and is borrowed mutably for the call.
    unsafe { conv_channels(isa, layer, input, output.as_mut_ptr(), all) }
}

/// [`conv`] for the output channels `channels` only, written through a pointer so that
/// threads can fill disjoint channel ranges of one output plane at once. `channels.start` must
/// be a multiple of [`OC_ALIGN`]: each thread then reads only its own panels of weights.
///
/// # Safety
/// `output` must point to `shape.output.len()` floats, valid for writes, and no other thread
/// may read or write channels `channels` of its interior during the call.
pub unsafe fn conv_channels(
    isa: Isa,
    layer: ConvParams<'_>,
    input: &[f32],
    output: *mut f32,
    channels: core::ops::Range<usize>,
) {
    layer.shape.check(input, layer.weights, layer.bias);
    layer.shape.check_channels(&channels);
    match isa.level() {
        IsaLevel::Scalar => scalar::conv_channels(layer, input, output, channels),
        level => simd::conv(level, layer, input, output, channels),
    }
}

/// Step 1 of a Winograd convolution (see [`winograd`]): writes the transformed input of stride
/// phase `phase` (0 to 3) to `v`, the span [`Winograd::phase_span`] of the whole transformed
/// input. Threads may fill different phases at once.
pub fn winograd_input(isa: Isa, w: &Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
    assert!(phase < 4);
    assert_eq!(input.len(), w.shape.input.len());
    assert_eq!(v.len(), w.phase_span(phase).len());
    match isa.level() {
        IsaLevel::Scalar => scalar::winograd_input(w, phase, input, v),
        // SAFETY: `level` comes from an `Isa`; the lengths are checked above.
        level => unsafe { simd::winograd::input(level, w, phase, input, v) },
    }
}

/// Steps 2 and 3 of a Winograd convolution (see [`winograd`]) for the output channels
/// `channels`: `output = act(conv(input) + bias)` from the transformed input `v` (all four
/// phases) and weights packed by [`pack::winograd_weights`] for the same `w`, using `scratch`
/// ([`winograd::SCRATCH_LEN`] floats, one per thread). `channels.start` must be a multiple of
/// [`OC_ALIGN`]. Only those channels of the output's interior are written.
///
/// # Safety
/// As for [`conv_channels`].
pub unsafe fn winograd_channels(
    isa: Isa,
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    output: *mut f32,
    channels: core::ops::Range<usize>,
) {
    assert_eq!(w.shape, layer.shape);
    assert_eq!(layer.weights.len(), w.packed_len());
    assert_eq!(layer.bias.len(), layer.shape.output.channels);
    assert_eq!(v.len(), w.input_len());
    assert!(scratch.len() >= winograd::SCRATCH_LEN);
    layer.shape.check_channels(&channels);
    match isa.level() {
        IsaLevel::Scalar => scalar::winograd_channels(w, layer, v, scratch, output, channels),
        level => simd::winograd::channels(level, w, layer, v, scratch, output, channels),
    }
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
    assert_eq!(output.len(), layer.shape.output.len());
    assert_eq!(v.len(), w.input_len());
    for phase in 0..4 {
        winograd_input(isa, w, phase, input, &mut v[w.phase_span(phase)]);
    }
    let all = 0..layer.shape.output.channels;
    // SAFETY: `output` holds the whole output plane and is borrowed mutably for the call.
    unsafe { winograd_channels(isa, w, layer, v, scratch, output.as_mut_ptr(), all) }
}

/// `y[n] = act(W x[n] + bias)` for a batch of `x.len() / W.cols` inputs stored one after another.
pub fn dense(isa: Isa, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    w.check(bias, x, y);
    // SAFETY: `y` holds every row of every item and is borrowed mutably for the call.
    unsafe { dense_rows(isa, w, bias, act, x, y.as_mut_ptr(), 0..w.rows) }
}

/// [`dense`] for the rows `rows` only (`y[n * W.rows + r]` for `r` in `rows`), written through
/// a pointer so that threads can fill disjoint row ranges of one batch's output at once (each
/// reading only its rows of the weights). `rows.start` must be a multiple of [`OC_ALIGN`].
///
/// # Safety
/// `y` must point to `batch * W.rows` floats valid for writes, and no other thread may read or
/// write rows `rows` of any item during the call.
pub unsafe fn dense_rows(
    isa: Isa,
    w: Matrix<'_>,
    bias: &[f32],
    act: Activation,
    x: &[f32],
    y: *mut f32,
    rows: core::ops::Range<usize>,
) {
    assert!(rows.start <= rows.end && rows.end <= w.rows && bias.len() == w.rows);
    w.check_packed();
    let (ldy, part) = (w.rows, w.row_range(rows.clone()));
    let (bias, y) = (&bias[rows.clone()], y.add(rows.start));
    let batch = x.len() / w.cols;
    assert!(w.cols > 0 && batch * w.cols == x.len(), "input is not whole rows");
    match isa.level() {
        IsaLevel::Scalar => scalar::dense_rows(part, bias, act, x, y, ldy),
        level => simd::dense(level, part, bias, act, x, y, ldy),
    }
}
