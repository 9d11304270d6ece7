//! Convolution kernels for AVX2 and AVX-512: one generic body over [`Simd`], instantiated per
//! instruction set inside a `#[target_feature]` function.
//!
//! Both kinds of layer reduce to the same microkernel. The output is cut into *rows*: runs of
//! output pixels in one image row whose inputs are evenly spaced and which use the same taps.
//! - `Down` (stride 2): a row is a whole output row; consecutive outputs read input pixels two
//!   apart, and for one `ky` the taps `kx` and the input channels form one contiguous run in both
//!   the input (`kx * C + ic`) and the packed weights (`(kx * C + ic) * oc_stride`).
//! - `Up` (transposed, computed by gathering): a row is one stride phase (even or odd `ox`) of an
//!   output row; consecutive outputs read consecutive input pixels, and only the taps of that
//!   phase apply (the inserted zeros are never multiplied).
//!
//! Each row is a list of *segments* (an input offset, a weight offset and a length in channels)
//! and the microkernel computes a tile of `T` pixels of a row times `NV` vectors of output
//! channels: per segment step it loads `NV` weight vectors, broadcasts one input value per pixel
//! and does `T * NV` fused multiply-adds into register accumulators. Taps that fall outside the
//! image horizontally read the zero border; rows of taps outside the image are skipped.

use super::act::{self, Simd};
use crate::{scalar, Activation, ConvKind, ConvShape, IsaLevel};
use core::arch::x86_64::{__m256, __m512};

/// The most segments one row can have: `k` for `Down`, `ceil(k / 2)^2` for `Up`.
const MAX_SEGS: usize = 64;
/// The most output pixels of a tile.
const MAX_TILE: usize = 12;

/// A run of `len` consecutive input floats times `len` weight rows `oc_stride` apart.
#[derive(Clone, Copy, Default)]
struct Seg {
    /// Floats from the row's input base (pixel 0, channel 0) to the first input value.
    input: isize,
    /// Floats from the start of the packed weights to the first weight row.
    weight: usize,
    len: usize,
}

/// Output pixels `0..count` of a row: pixel `p` reads `input + p * in_step + seg.input + i` and
/// writes `output + p * out_step`.
struct Row<'a> {
    segs: &'a [Seg],
    input: *const f32,
    in_step: usize,
    output: *mut f32,
    out_step: usize,
    count: usize,
}

/// One block of output channels: `NV` vectors from channel `first`, of which `valid` are real.
#[derive(Clone, Copy)]
struct Block<V, const NV: usize> {
    /// The packed weights advanced to channel `first`.
    weights: *const f32,
    bias: [V; NV],
    /// Channel offset within an output pixel.
    first: usize,
    valid: usize,
}

pub(crate) fn conv(
    level: IsaLevel,
    shape: &ConvShape,
    input: &[f32],
    weights: &[f32],
    bias: &[f32],
    act: Activation,
    output: &mut [f32],
) {
    if shape.kernel.div_ceil(2).pow(2) > MAX_SEGS {
        return scalar::conv(shape, input, weights, bias, act, output);
    }
    match level {
        // SAFETY: `level` comes from an `Isa`, which proves the CPU has AVX-512F, AVX2 and FMA;
        // `crate::conv` checked the buffer lengths against `shape`.
        IsaLevel::Avx512 => unsafe { conv_avx512(shape, input, weights, bias, act, output) },
        // SAFETY: `level` comes from an `Isa`, which proves the CPU has AVX2 and FMA; `crate::conv`
        // checked the buffer lengths against `shape`.
        IsaLevel::Avx2 => unsafe { conv_avx2(shape, input, weights, bias, act, output) },
        IsaLevel::Scalar => scalar::conv(shape, input, weights, bias, act, output),
    }
}

/// # Safety
/// The CPU must have AVX2 and FMA, and the buffers must match `shape` (see `crate::conv`).
#[target_feature(enable = "avx2,fma")]
unsafe fn conv_avx2(
    shape: &ConvShape,
    input: &[f32],
    weights: &[f32],
    bias: &[f32],
    act: Activation,
    output: &mut [f32],
) {
    body::<__m256>(shape, input, weights, bias, act, output)
}

/// # Safety
/// The CPU must have AVX-512F, AVX2 and FMA, and the buffers must match `shape`.
#[target_feature(enable = "avx512f,avx2,fma")]
#[allow(clippy::incompatible_msrv)] // AVX-512 target features are stable since Rust 1.89
unsafe fn conv_avx512(
    shape: &ConvShape,
    input: &[f32],
    weights: &[f32],
    bias: &[f32],
    act: Activation,
    output: &mut [f32],
) {
    body::<__m512>(shape, input, weights, bias, act, output)
}

/// Walks the output channel blocks, and within each the rows, so that the weights of one block
/// (`k * k * C * NV * LANES` floats) stay in cache while every pixel uses them.
#[inline(always)]
unsafe fn body<V: Simd>(
    shape: &ConvShape,
    input: &[f32],
    weights: &[f32],
    bias: &[f32],
    act: Activation,
    output: &mut [f32],
) {
    let oc = shape.output.channels;
    let mut first = 0;
    while first < oc {
        let left = oc - first;
        // Two vectors while more than one is needed: the packed weights are padded to 16
        // channels, so the second vector's weights exist whenever `left > LANES`.
        if left > V::LANES {
            let block = block::<V, 2>(weights, bias, first, left);
            for_rows(shape, input, output, &block, act);
            first += 2 * V::LANES;
        } else {
            let block = block::<V, 1>(weights, bias, first, left);
            for_rows(shape, input, output, &block, act);
            first += V::LANES;
        }
    }
}

#[inline(always)]
unsafe fn block<V: Simd, const NV: usize>(weights: &[f32], bias: &[f32], first: usize, left: usize) -> Block<V, NV> {
    let mut b = [V::splat(0.0); NV];
    for (v, b) in b.iter_mut().enumerate() {
        let n = left.saturating_sub(v * V::LANES);
        let p = bias.as_ptr().add(first + v * V::LANES);
        *b = if n >= V::LANES {
            V::load(p)
        } else if n > 0 {
            V::load_partial(p, n)
        } else {
            V::splat(0.0)
        };
    }
    Block {
        weights: weights.as_ptr().add(first),
        bias: b,
        first,
        valid: left.min(NV * V::LANES),
    }
}

/// Runs `block` over every row of the output (see the module comment). No closures here: they
/// would not inherit the caller's target features.
#[inline(always)]
unsafe fn for_rows<V: Simd, const NV: usize>(
    shape: &ConvShape,
    input: &[f32],
    output: &mut [f32],
    block: &Block<V, NV>,
    act: Activation,
) {
    let (k, ip, op) = (shape.kernel, shape.input, shape.output);
    let pad = k / 2;
    let (c, ocs) = (ip.channels, shape.oc_stride());
    let in0 = input.as_ptr().add(ip.index(0, 0));
    let irs = ip.row_stride() as isize;
    let mut segs = [Seg::default(); MAX_SEGS];
    for oy in 0..op.height {
        let rows = (0..k).filter_map(|ky| Some((ky, shape.kind.source(oy, ky, pad, ip.height)? as isize)));
        match shape.kind {
            ConvKind::Down => {
                let mut n = 0;
                for (ky, iy) in rows {
                    segs[n] = Seg {
                        input: iy * irs - (pad * c) as isize,
                        weight: ky * k * c * ocs,
                        len: k * c,
                    };
                    n += 1;
                }
                run_row(
                    &Row {
                        segs: &segs[..n],
                        input: in0,
                        in_step: 2 * c,
                        output: output.as_mut_ptr().add(op.index(oy, 0)),
                        out_step: op.channels,
                        count: op.width,
                    },
                    block,
                    ocs,
                    act,
                );
            }
            ConvKind::Up => {
                for px in 0..2 {
                    let mut n = 0;
                    for (ky, iy) in rows.clone() {
                        // Output 2j + px reads input j + (px + pad - kx) / 2 for even differences.
                        for kx in (0..k).filter(|kx| kx % 2 == (px + pad) % 2) {
                            let dx = (px + pad) as isize - kx as isize;
                            segs[n] = Seg {
                                input: iy * irs + dx / 2 * c as isize,
                                weight: (ky * k + kx) * c * ocs,
                                len: c,
                            };
                            n += 1;
                        }
                    }
                    run_row(
                        &Row {
                            segs: &segs[..n],
                            input: in0,
                            in_step: c,
                            output: output.as_mut_ptr().add(op.index(oy, px)),
                            out_step: 2 * op.channels,
                            count: ip.width,
                        },
                        block,
                        ocs,
                        act,
                    );
                }
            }
        }
    }
}

/// Cuts a row into tiles of nearly equal size, at most `MAX_TILE / NV` pixels each.
#[inline(always)]
unsafe fn run_row<V: Simd, const NV: usize>(row: &Row<'_>, block: &Block<V, NV>, ocs: usize, act: Activation) {
    let max = MAX_TILE / NV;
    let tiles = row.count.div_ceil(max);
    let mut start = 0;
    for i in 0..tiles {
        let end = row.count * (i + 1) / tiles;
        macro_rules! tile_of {
            ($($t:literal)+) => {
                match end - start {
                    $($t => tile::<V, $t, NV>(row, start, block, ocs, act),)+
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

/// Output pixels `first..first + T` of `row`, channels of `block`: the microkernel.
#[inline(always)]
unsafe fn tile<V: Simd, const T: usize, const NV: usize>(
    row: &Row<'_>,
    first: usize,
    block: &Block<V, NV>,
    ocs: usize,
    act: Activation,
) {
    let mut acc = [block.bias; T];
    let input = row.input.add(first * row.in_step);
    let step = row.in_step;
    for seg in row.segs {
        let mut x = input.offset(seg.input);
        let mut w = block.weights.add(seg.weight);
        for _ in 0..seg.len {
            let mut wv = [V::splat(0.0); NV];
            for (v, wv) in wv.iter_mut().enumerate() {
                *wv = V::load(w.add(v * V::LANES));
            }
            for (t, acc) in acc.iter_mut().enumerate() {
                let b = V::splat(*x.add(t * step));
                for (a, &wv) in acc.iter_mut().zip(&wv) {
                    *a = b.mul_add(wv, *a);
                }
            }
            x = x.add(1);
            w = w.add(ocs);
        }
    }
    let out = row.output.add(first * row.out_step + block.first);
    for (t, acc) in acc.iter().enumerate() {
        for (v, &a) in acc.iter().enumerate() {
            let p = out.add(t * row.out_step + v * V::LANES);
            let y = act::apply(act, a);
            let n = block.valid.saturating_sub(v * V::LANES);
            if n >= V::LANES {
                y.store(p);
            } else if n > 0 {
                y.store_partial(p, n);
            }
        }
    }
}
