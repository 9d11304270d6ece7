//! The convolution kernel of narrow layers (at most [`crate::NARROW_OC`] output channels), on
//! the rows of [`super::conv`].

use super::act;
use super::conv::{for_rows, Pass, Row, RowKernel};
use super::vector::{load_n, Simd};
use crate::{Activation, ConvShape, OC_ALIGN};

/// Accumulators of the narrow layers' microkernel (a multiple of 1 to `NARROW_OC`).
const SMALL_ACC: usize = 12;

/// Narrow layers (the generator's last, 3 channels): vectors over output channels would be
/// mostly padding, so each output channel of each pixel gets its own accumulator vector over
/// input channels, summed across lanes at the end. Their weights are packed `[oc][ky][kx][ic]`,
/// so input channels are contiguous in the weights as in the input.
#[inline(always)]
pub(super) unsafe fn small<V: Simd, const OCN: usize>(
    shape: &ConvShape,
    input: &[f32],
    weights: &[f32],
    bias: &[f32],
    act: Activation,
    output: *mut f32,
) {
    unsafe {
        // One row of weights per output channel, a value per (tap, input channel).
        let rows = shape.kernel * shape.kernel * shape.input.channels;
        let mut b = [0.0; OCN];
        b.copy_from_slice(bias);
        let f = Small::<V, OCN> {
            weights: weights.as_ptr(),
            rows,
            bias: b,
            lanes: core::marker::PhantomData,
        };
        for_rows(shape, input, output, Pass::all(rows), &f);
        // The activation, vectorized: done per value in the tiles it would cost as much as the sums.
        let op = shape.output;
        for y in 0..op.height {
            let row = core::slice::from_raw_parts_mut(output.add(op.index(y, 0)), op.width * op.channels);
            act::apply_slice::<V>(act, row);
        }
    }
}

struct Small<V, const OCN: usize> {
    /// `[oc][row]` with `rows` rows, a row being one (tap, input channel).
    weights: *const f32,
    rows: usize,
    bias: [f32; OCN],
    lanes: core::marker::PhantomData<V>,
}

impl<V: Simd, const OCN: usize> RowKernel for Small<V, OCN> {
    #[inline(always)]
    unsafe fn run(&self, row: &Row<'_>) {
        unsafe {
            // As many pixels as keep `SMALL_ACC` accumulators busy; single pixels for the rest.
            let max = SMALL_ACC / OCN;
            let whole = row.count / max * max;
            let mut p = 0;
            while p < whole {
                macro_rules! tile_of {
                ($($n:literal)+) => {
                    match max {
                        $($n => self.tile::<$n>(row, p),)+
                        _ => unreachable!(),
                    }
                };
            }
                tile_of!(3 4 6 12);
                p += max;
            }
            for p in whole..row.count {
                self.tile::<1>(row, p);
            }
        }
    }
}

impl<V: Simd, const OCN: usize> Small<V, OCN> {
    /// Adds the products of `n <= LANES` input channels at `x` (pixel `t` at `x + t * in_step`)
    /// and the weights at `w` (output channel `o` at `w + o * rows`).
    #[inline(always)]
    unsafe fn step<const T: usize>(
        &self,
        acc: &mut [[V; OCN]; T],
        w: *const f32,
        x: *const f32,
        in_step: usize,
        n: usize,
    ) {
        unsafe {
            let mut wv = [V::splat(0.0); OCN];
            for (o, wv) in wv.iter_mut().enumerate() {
                *wv = load_n(w.add(o * self.rows), n);
            }
            for (t, acc) in acc.iter_mut().enumerate() {
                let xv: V = load_n(x.add(t * in_step), n);
                for (a, &wv) in acc.iter_mut().zip(&wv) {
                    *a = xv.mul_add(wv, *a);
                }
            }
        }
    }

    #[inline(always)]
    unsafe fn tile<const T: usize>(&self, row: &Row<'_>, first: usize) {
        unsafe {
            let mut acc = [[V::splat(0.0); OCN]; T];
            let input = row.input.add(first * row.in_step);
            for seg in row.segs {
                let x = input.offset(seg.input);
                // `Seg::weight` counts panel rows of `OC_ALIGN`; here a row is one value.
                let w = self.weights.add(seg.weight / OC_ALIGN);
                let whole = seg.len / V::LANES * V::LANES;
                for i in (0..whole).step_by(V::LANES) {
                    self.step(&mut acc, w.add(i), x.add(i), row.in_step, V::LANES);
                }
                if whole < seg.len {
                    self.step(&mut acc, w.add(whole), x.add(whole), row.in_step, seg.len - whole);
                }
            }
            for (t, acc) in acc.iter().enumerate() {
                let out = row.output.add((first + t) * row.out_step);
                for (o, a) in acc.iter().enumerate() {
                    *out.add(o) = a.reduce_add() + self.bias[o];
                }
            }
        }
    }
}
