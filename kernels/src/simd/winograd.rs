//! The SIMD side of [`crate::winograd`]: its transforms over vectors of channels, and its
//! matrix products on the direct convolution's microkernel (a product is a row of "pixels"
//! (tiles) with one segment of input channels).

use super::arch;
use super::conv::{run_row, Block, Row, Seg};
use super::vector::Simd;
use crate::winograd::{self, InputTransform, Product, Products, Winograd};
use crate::{scalar, Activation, ConvParams, IsaLevel, OC_ALIGN};
use core::ops::Range;

/// Steps of input channels ahead to prefetch the weights: they stream from L3 or memory (twice
/// the direct weights) and each step is only a few cycles.
const PREFETCH_STEPS: usize = 32;

/// The products on the microkernel: tiles are its pixels, `in_channels` apart in `V`.
struct Microkernel<V>(core::marker::PhantomData<V>);

impl<V: Simd> Product for Microkernel<V> {
    #[inline(always)]
    unsafe fn run(&self, p: &Products<'_>) {
        let Products {
            w,
            u,
            point,
            v,
            count,
            m,
            first,
            valid,
        } = *p;
        let c = w.shape.input.channels;
        let segs = [Seg {
            input: 0,
            weight: point * c * OC_ALIGN,
            len: c,
        }];
        let row = Row {
            segs: &segs,
            input: v,
            in_step: c,
            output: m,
            out_step: 2 * V::LANES,
            count,
            accumulate: false,
            activate: false,
        };
        // The lane of channel `first + i` in its panel (panels are whole, so the second vector's
        // weights exist whenever `valid > LANES`).
        let lane = |i: usize| u.as_ptr().add(w.packed_index(0, 0, first + i));
        if valid > V::LANES {
            let block = Block::<V, 2> {
                weights: [lane(0), lane(V::LANES)],
                bias: [V::splat(0.0); 2],
                first: 0,
                valid,
            };
            run_row::<V, 2, PREFETCH_STEPS>(&row, &block, Activation::Identity)
        } else {
            let block = Block::<V, 1> {
                weights: [lane(0)],
                bias: [V::splat(0.0)],
                first: 0,
                valid,
            };
            run_row::<V, 1, PREFETCH_STEPS>(&row, &block, Activation::Identity)
        }
    }
}

/// An instruction set's instance of [`input_body`] (see [`super::Entries`]).
pub(super) type InputEntry = unsafe fn(&Winograd, usize, &[f32], &mut [f32]);
/// An instruction set's instance of [`channels_body`] (see [`super::Entries`]).
pub(super) type ChannelsEntry = unsafe fn(&Winograd, ConvParams<'_>, &[f32], &mut [f32], *mut f32, Range<usize>);

/// See [`crate::winograd_input`].
///
/// # Safety
/// `level` must come from an `Isa`; the buffers are checked by the caller.
pub(crate) unsafe fn input(level: IsaLevel, w: &Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
    match arch::entries(level) {
        // SAFETY: `level` comes from an `Isa`, which proves the CPU has the entry's features.
        Some(entries) => (entries.winograd_input)(w, phase, input, v),
        None => scalar::winograd_input(w, phase, input, v),
    }
}

/// See [`crate::winograd_channels`].
///
/// # Safety
/// As for [`crate::winograd_channels`]; `level` must come from an `Isa`.
pub(crate) unsafe fn channels(
    level: IsaLevel,
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    output: *mut f32,
    channels: Range<usize>,
) {
    match arch::entries(level) {
        // SAFETY: `level` comes from an `Isa`, which proves the CPU has the entry's features.
        Some(entries) => (entries.winograd_channels)(w, layer, v, scratch, output, channels),
        None => scalar::winograd_channels(w, layer, v, scratch, output, channels),
    }
}

/// The input transform of one phase, for one instruction set.
#[inline(always)]
pub(super) unsafe fn input_body<V: Simd>(w: &Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
    winograd::with_phase(w, phase, &mut InputTransform::<V>::new(w, input, v))
}

/// The products and output transform of some channels, for one instruction set.
#[inline(always)]
pub(super) unsafe fn channels_body<V: Simd>(
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    output: *mut f32,
    channels: Range<usize>,
) {
    let product = Microkernel::<V>(core::marker::PhantomData);
    winograd::channels::<V, _>(&product, w, layer, v, scratch, output, channels)
}
