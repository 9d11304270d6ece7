//! The SIMD side of [`crate::winograd`]: its transforms over vectors of channels, and its
//! matrix products on the direct convolution's microkernel (a product is a row of "pixels"
//! (tiles) with one segment of input channels).

use super::conv::{run_row, Block, Row, Seg};
use super::vector::Simd;
use crate::winograd::{self, InputTransform, Product, Products, WeightTransform, Winograd};
use crate::{Activation, ConvParams, OC_ALIGN};
use core::ops::Range;

/// Steps of input channels ahead to prefetch the weights: they stream from L3 or memory (twice
/// the direct weights) and each step is only a few cycles.
const PREFETCH_STEPS: usize = 32;

/// The products on the microkernel: tiles are its pixels, `in_channels` apart in `V`.
struct Microkernel<V>(core::marker::PhantomData<V>);

impl<V: Simd> Product for Microkernel<V> {
    #[inline(always)]
    unsafe fn run(&self, p: &Products<'_>) {
        unsafe {
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
}

/// The input transform of one phase, for one instruction set.
#[inline(always)]
pub(super) unsafe fn input_body<V: Simd>(w: &Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
    unsafe { winograd::with_phase(w, phase, &mut InputTransform::<V>::new(w, input, v)) }
}

/// The weight transform, for one instruction set.
#[inline(always)]
pub(super) unsafe fn weights_body<V: Simd>(w: &Winograd, direct: &[f32], packed: &mut [f32]) {
    for phase in 0..4 {
        unsafe { winograd::with_phase(w, phase, &mut WeightTransform::<V>::new(w, direct, packed)) }
    }
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
    unsafe {
        let product = Microkernel::<V>(core::marker::PhantomData);
        winograd::channels::<V, _>(&product, w, layer, v, scratch, output, channels)
    }
}
