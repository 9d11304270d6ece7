//! Convolution kernels: one generic body over [`Simd`], instantiated per instruction set by the
//! architecture module inside a `#[target_feature]` function.
//!
//! Both kinds of layer reduce to the same microkernel. The output is cut into *rows*: runs of
//! output pixels in one image row whose inputs are evenly spaced and which use the same taps.
//! - `Down` (stride 2): a row is a whole output row; consecutive outputs read input pixels two
//!   apart, and for one `ky` the taps `kx` and the input channels form one contiguous run in both
//!   the input (`kx * C + ic`) and the packed weights (`(kx * C + ic) * OC_ALIGN` in a panel).
//! - `Up` (transposed, computed by gathering): a row is one stride phase (even or odd `ox`) of an
//!   output row; consecutive outputs read consecutive input pixels, and only the taps of that
//!   phase apply (the inserted zeros are never multiplied).
//!
//! The packed weights of one block of output channels are one contiguous panel, so they stream
//! from L2 while every output pixel of the layer uses them. Panels too large to stay in L2 next
//! to the input (the deep layers: 400-800 KiB) would stream from L3 once per tile; their sum is
//! taken in passes of a few kernel rows instead (see [`Pass`]), each reading its share of the
//! weights from L3 once, with partial sums kept in the output between passes.
//!
//! Each row is a list of *segments* (an input offset, a weight offset and a length in channels)
//! and the microkernel computes a tile of `T` pixels of a row times `NV` vectors of output
//! channels: per segment step it loads `NV` weight vectors, broadcasts one input value per pixel
//! and does `T * NV` fused multiply-adds into register accumulators. Taps that fall outside the
//! image horizontally read the zero border; rows of taps outside the image are skipped.

use super::act;
use super::conv_narrow::small;
use super::vector::{load_n, store_n, Simd};
use crate::{scalar, Activation, ConvKind, ConvParams, ConvShape, OC_ALIGN};
use core::ops::Range;

/// The most segments one row can have (`k` for `Down`, `ceil(k / 2)^2` for `Up`); kernels with
/// `k * k` above it, which no model uses, fall back to the scalar kernel.
const MAX_SEGS: usize = 128;
/// The most output pixels of a tile.
const MAX_TILE: usize = 12;

/// A run of `len` consecutive input floats times `len` weight rows `OC_ALIGN` apart.
#[derive(Clone, Copy, Default)]
pub(super) struct Seg {
    /// Floats from the row's input base (pixel 0, channel 0) to the first input value.
    pub input: isize,
    /// Floats from the start of a panel of packed weights to the first weight row.
    pub weight: usize,
    pub len: usize,
}

/// Output pixels `0..count` of a row: pixel `p` reads `input + p * in_step + seg.input + i` and
/// writes `output + p * out_step`.
pub(super) struct Row<'a> {
    pub segs: &'a [Seg],
    pub input: *const f32,
    pub in_step: usize,
    pub output: *mut f32,
    pub out_step: usize,
    pub count: usize,
    /// Start from the partial sums in the output instead of the bias.
    pub accumulate: bool,
    /// Apply the activation on store (else store the sums).
    pub activate: bool,
}

/// The rows of a panel of packed weights (a row: `OC_ALIGN` values, one per output channel, for
/// one tap and input channel) that one pass over the output sums. When a panel is too large for
/// L2 next to the input, every tile streams it from L3; in passes of a few kernel rows each,
/// a window of weights is read from L3 once and reused from L2 by every tile.
#[derive(Clone, Copy)]
pub(super) struct Pass {
    window: (usize, usize),
    first: bool,
    last: bool,
}

impl Pass {
    /// The one pass over all `rows`.
    pub(super) fn all(rows: usize) -> Pass {
        Pass {
            window: (0, rows),
            first: true,
            last: true,
        }
    }
}

/// One block of output channels: `NV` vectors from channel `first`, of which `valid` are real.
#[derive(Clone, Copy)]
pub(super) struct Block<V, const NV: usize> {
    /// For each vector, its channels' lane in their panel of the packed weights.
    pub weights: [*const f32; NV],
    pub bias: [V; NV],
    /// Channel offset within an output pixel.
    pub first: usize,
    pub valid: usize,
}

/// See [`crate::conv_channels`]: the weights in passes of whole kernel rows that stay in cache,
/// each summed by [`body`] on top of the last.
///
/// # Safety
/// As for [`crate::scalar::conv_channels`]; the CPU must have `V`'s features.
#[inline(always)]
pub(super) unsafe fn conv<V: Simd>(layer: ConvParams<'_>, input: &[f32], output: *mut f32, channels: Range<usize>) {
    unsafe {
        let shape = &layer.shape;
        if shape.kernel * shape.kernel > MAX_SEGS {
            return scalar::conv_channels(layer, input, output, channels);
        }
        // Panel rows of one kernel row (`ky`): every tap `kx` and input channel.
        let ky_rows = shape.kernel * shape.input.channels;
        let rows = shape.kernel * ky_rows;
        let row_bytes = 2 * V::LANES * core::mem::size_of::<f32>();
        let window = if shape.is_narrow() || rows * row_bytes <= SINGLE_PASS_BYTES {
            rows
        } else {
            (PASS_BYTES / (ky_rows * row_bytes)).max(1) * ky_rows
        };
        for start in (0..rows).step_by(window) {
            let pass = Pass {
                window: (start, (start + window).min(rows)),
                first: start == 0,
                last: start + window >= rows,
            };
            body::<V>(layer, input, output, channels.clone(), pass);
        }
    }
}

/// Panels of a block of output channels up to this size are summed in one pass: they stay in
/// L2 next to the input.
const SINGLE_PASS_BYTES: usize = 256 << 10;
/// Bytes of weights per pass when there are several (whole kernel rows, at least one).
const PASS_BYTES: usize = 128 << 10;

/// Walks the blocks of output channels.
#[inline(always)]
pub(super) unsafe fn body<V: Simd>(
    layer: ConvParams<'_>,
    input: &[f32],
    output: *mut f32,
    channels: Range<usize>,
    pass: Pass,
) {
    unsafe {
        let ConvParams {
            shape,
            weights,
            bias,
            act,
        } = layer;
        let shape = &shape;
        if channels.is_empty() {
            return;
        }
        // Narrow layers are never split between threads: they are one panel.
        if shape.is_narrow() {
            return match shape.output.channels {
                1 => small::<V, 1>(shape, input, weights, bias, act, output),
                2 => small::<V, 2>(shape, input, weights, bias, act, output),
                3 => small::<V, 3>(shape, input, weights, bias, act, output),
                _ => small::<V, 4>(shape, input, weights, bias, act, output),
            };
        }
        let mut first = channels.start;
        while first < channels.end {
            let left = channels.end - first;
            // Two vectors while more than one is needed: the packed weights are padded to whole
            // panels, so the second vector's weights exist whenever `left > LANES`.
            if left > V::LANES {
                let block = block::<V, 2>(shape, weights, pass.first.then_some(bias), first, left);
                for_rows(shape, input, output, pass, &Blocked { block: &block, act });
                first += 2 * V::LANES;
            } else {
                let block = block::<V, 1>(shape, weights, pass.first.then_some(bias), first, left);
                for_rows(shape, input, output, pass, &Blocked { block: &block, act });
                first += V::LANES;
            }
        }
        // With several passes, rows without taps in the last window were stored without the
        // activation: apply it to the whole range here.
        if pass.last && !pass.first {
            let op = shape.output;
            for y in 0..op.height {
                for x in 0..op.width {
                    let at = output.add(op.index(y, x) + channels.start);
                    act::apply_slice::<V>(act, core::slice::from_raw_parts_mut(at, channels.len()));
                }
            }
        }
    }
}

/// A block of output channels; without `bias` (passes after the first) the sums start at zero.
#[inline(always)]
unsafe fn block<V: Simd, const NV: usize>(
    shape: &ConvShape,
    weights: &[f32],
    bias: Option<&[f32]>,
    first: usize,
    left: usize,
) -> Block<V, NV> {
    unsafe {
        let mut b = [V::splat(0.0); NV];
        let mut w = [weights.as_ptr(); NV];
        for (v, (b, w)) in b.iter_mut().zip(&mut w).enumerate() {
            let channel = first + v * V::LANES;
            if let Some(bias) = bias {
                *b = load_n(bias.as_ptr().add(channel), left.saturating_sub(v * V::LANES));
            }
            *w = w.add(shape.packed_index(0, 0, 0, channel));
        }
        Block {
            weights: w,
            bias: b,
            first,
            valid: left.min(NV * V::LANES),
        }
    }
}

/// Runs `f` over every row of the output (see the module comment), with the taps of `pass`'s
/// window only; after the first pass, rows with none are skipped.
#[inline(always)]
pub(super) unsafe fn for_rows(shape: &ConvShape, input: &[f32], output: *mut f32, pass: Pass, f: &impl RowKernel) {
    unsafe {
        let (k, ip, op) = (shape.kernel, shape.input, shape.output);
        let pad = k / 2;
        let c = ip.channels;
        let in0 = input.as_ptr().add(ip.index(0, 0));
        let irs = ip.row_stride() as isize;
        let mut segs = [Seg::default(); MAX_SEGS];
        // Tap (`ky`, `kx`) of input row `iy` for pixel steps `dx` from the row's input base.
        let seg = |ky: usize, iy: isize, kx: usize, dx: isize, len: usize| Seg {
            input: iy * irs + dx * c as isize,
            weight: (ky * k + kx) * c * OC_ALIGN,
            len,
        };
        for oy in 0..op.height {
            let rows = (0..k).filter_map(|ky| Some((ky, shape.kind.source(oy, ky, pad, ip.height)? as isize)));
            // Stride-2 outputs of `Down`, or the two stride phases of `Up`.
            let (phases, in_step, out_step, count) = match shape.kind {
                ConvKind::Down => (1, 2 * c, op.channels, op.width),
                ConvKind::Up => (2, c, 2 * op.channels, ip.width),
            };
            for px in 0..phases {
                let mut n = 0;
                for (ky, iy) in rows.clone() {
                    match shape.kind {
                        // The taps of one `ky` and all their channels are one contiguous run.
                        ConvKind::Down => {
                            segs[n] = seg(ky, iy, 0, -(pad as isize), k * c);
                            n += 1;
                        }
                        // Output 2j + px reads input j + (px + pad - kx) / 2 for even differences.
                        ConvKind::Up => {
                            for kx in (0..k).filter(|kx| kx % 2 == (px + pad) % 2) {
                                segs[n] = seg(ky, iy, kx, ((px + pad) as isize - kx as isize) / 2, c);
                                n += 1;
                            }
                        }
                    }
                }
                // Keep the segments inside the window (whole kernel rows: a segment is in or out).
                let (lo, hi) = pass.window;
                let mut kept = 0;
                for i in 0..n {
                    let row = segs[i].weight / OC_ALIGN;
                    if (lo..hi).contains(&row) {
                        segs[kept] = segs[i];
                        kept += 1;
                    }
                }
                if kept == 0 && !pass.first {
                    continue;
                }
                f.run(&Row {
                    segs: &segs[..kept],
                    input: in0,
                    in_step,
                    output: output.add(op.index(oy, px)),
                    out_step,
                    count,
                    accumulate: !pass.first,
                    activate: pass.first && pass.last,
                });
            }
        }
    }
}

/// What computes the output of a row (a trait, not a closure: closures would not inherit the
/// caller's target features).
pub(super) trait RowKernel {
    unsafe fn run(&self, row: &Row<'_>);
}

/// One pass of a block of output channels (the path of every layer but the narrowest).
struct Blocked<'a, V, const NV: usize> {
    block: &'a Block<V, NV>,
    act: Activation,
}

impl<V: Simd, const NV: usize> RowKernel for Blocked<'_, V, NV> {
    #[inline(always)]
    unsafe fn run(&self, row: &Row<'_>) {
        unsafe { run_row::<V, NV, 0>(row, self.block, self.act) }
    }
}

/// Cuts a row into tiles of nearly equal size, at most `MAX_TILE / NV` pixels each. With
/// `PREFETCH > 0` the tiles prefetch the weights that many segment steps ahead: for weights that
/// stream from L3 or memory at each use, faster than the hardware prefetcher ramps up.
#[inline(always)]
pub(super) unsafe fn run_row<V: Simd, const NV: usize, const PREFETCH: usize>(
    row: &Row<'_>,
    block: &Block<V, NV>,
    act: Activation,
) {
    unsafe {
        let max = MAX_TILE / NV;
        let tiles = row.count.div_ceil(max);
        let mut start = 0;
        for i in 0..tiles {
            let end = row.count * (i + 1) / tiles;
            macro_rules! tile_of {
            ($($t:literal)+) => {
                match end - start {
                    $($t => tile::<V, $t, NV, PREFETCH>(row, start, block, act),)+
                    _ => unreachable!(),
                }
            };
        }
            if NV == 1 {
                tile_of!(1 2 3 4 5 6 7 8 9 10 11 12)
            } else {
                tile_of!(1 2 3 4 5 6)
            }
            start = end;
        }
    }
}

/// Output pixels `first..first + T` of `row`, channels of `block`: the microkernel.
#[inline(always)]
unsafe fn tile<V: Simd, const T: usize, const NV: usize, const PREFETCH: usize>(
    row: &Row<'_>,
    first: usize,
    block: &Block<V, NV>,
    act: Activation,
) {
    unsafe {
        let out = row.output.add(first * row.out_step + block.first);
        let mut acc = [block.bias; T];
        let input = row.input.add(first * row.in_step);
        for seg in row.segs {
            // One pointer per pixel and one index shared by all: the loads address `pixel + index`
            // with no arithmetic per pixel, and `UNROLL` steps share each loop's bookkeeping.
            let x: [*const f32; T] = core::array::from_fn(|t| input.offset(seg.input).add(t * row.in_step));
            let w: [*const f32; NV] = core::array::from_fn(|v| block.weights[v].add(seg.weight));
            let mut i = 0;
            while i + UNROLL <= seg.len {
                for u in i..i + UNROLL {
                    if PREFETCH > 0 {
                        for w in w {
                            let ahead = w.wrapping_add((u + PREFETCH) * OC_ALIGN);
                            V::prefetch(ahead.cast());
                        }
                    }
                    conv_step(&mut acc, &x, &w, u);
                }
                i += UNROLL;
            }
            for u in i..seg.len {
                conv_step(&mut acc, &x, &w, u);
            }
        }
        for (t, acc) in acc.iter().enumerate() {
            for (v, &a) in acc.iter().enumerate() {
                let n = block.valid.saturating_sub(v * V::LANES);
                let at = out.add(t * row.out_step + v * V::LANES);
                let a = if row.accumulate { a.add(load_n(at, n)) } else { a };
                let a = if row.activate { act::apply(act, a) } else { a };
                store_n(a, at, n);
            }
        }
    }
}

/// Steps of a segment per loop iteration in [`tile`].
const UNROLL: usize = 8;

/// Step `i` of a segment: weights `w[v] + i * OC_ALIGN`, inputs `x[t] + i`.
#[inline(always)]
unsafe fn conv_step<V: Simd, const T: usize, const NV: usize>(
    acc: &mut [[V; NV]; T],
    x: &[*const f32; T],
    w: &[*const f32; NV],
    i: usize,
) {
    unsafe {
        let mut wv = [V::splat(0.0); NV];
        for (wv, w) in wv.iter_mut().zip(w) {
            *wv = V::load(w.add(i * OC_ALIGN));
        }
        for (acc, x) in acc.iter_mut().zip(x) {
            let b = V::splat(*x.add(i));
            for (a, &wv) in acc.iter_mut().zip(&wv) {
                *a = b.mul_add(wv, *a);
            }
        }
    }
}
