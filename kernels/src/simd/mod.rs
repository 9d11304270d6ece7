//! The SIMD kernels, one file per operation: each a generic body over the vector traits of
//! [`vector`]. The architecture's module implements the trait for its vectors and compiles
//! each body once per instruction set inside a `#[target_feature]` entry point
//! (`x86_64`: AVX2 + FMA + F16C and AVX-512F; `aarch64`: NEON). [`entries`] gives the kernels of
//! an [`Isa`]: those, or the scalar kernels where there are none.

// Without a vector unit the kernels know, nothing instantiates the generic bodies.
#![cfg_attr(
    not(any(
        all(target_arch = "aarch64", target_feature = "neon"),
        all(target_arch = "x86_64", target_feature = "sse2")
    )),
    allow(dead_code, unused_macros)
)]

use crate::norm::{GradientCoefficients, BLOCK};
use crate::winograd::Winograd;
use crate::{scalar, Activation, AdamStep, ConvParams, Isa, Matrix, Plane};
use core::ops::Range;

pub(crate) mod act;
mod adam;
mod conv;
mod conv_narrow;
mod dense;
mod dense_grad;
mod norm;
pub(crate) mod vector;
pub(crate) mod winograd;

/// One instruction set's kernels, one per operation, behind the checks of [`crate::ops`]:
/// each architecture's `entries!` instances (each generic body compiled inside a
/// `#[target_feature]` function), or [`SCALAR`], the reference kernels. [`entries`] picks the
/// set of an [`Isa`], so that the scalar fallback of every operation is written once.
pub(crate) struct Entries {
    /// See [`crate::scalar::conv_channels`].
    pub conv: unsafe fn(ConvParams<'_>, &[f32], *mut f32, Range<usize>),
    /// See [`crate::scalar::dense_rows`].
    pub dense: Dense,
    /// See [`crate::scalar::dense_weight_grad_rows`].
    pub dense_weight_grad: DenseWeightGrad,
    /// See [`crate::scalar::dense_data_grad_cols`].
    pub dense_data_grad: DenseDataGrad,
    /// See [`crate::scalar::activation_backward`].
    pub activation_backward: unsafe fn(Activation, &[f32], &mut [f32]),
    /// See [`crate::scalar::winograd_input`].
    pub winograd_input: unsafe fn(&Winograd, usize, &[f32], &mut [f32]),
    /// See [`crate::scalar::winograd_channels`].
    pub winograd_channels: WinogradChannels,
    /// See [`crate::scalar::winograd_weights`].
    pub winograd_weights: unsafe fn(&Winograd, &[f32], &mut [f32]),
    /// See [`crate::scalar::moments`].
    pub moments: unsafe fn(Plane, &[f32], &mut [f64]),
    /// See [`crate::scalar::gradient_moments`].
    pub gradient_moments: GradientMoments,
    /// See [`crate::scalar::normalize_gradient_block`].
    pub normalize_gradient_block: unsafe fn(Plane, &[f32], &mut [f32], Range<usize>, &GradientCoefficients),
    /// See [`crate::scalar::normalize_block`].
    pub normalize_block: NormalizeBlock,
    /// See [`crate::scalar::adam`].
    pub adam: Adam,
}

/// `(w, bias, act, x, y, ldy)`: without a bias, the sums add to what `y` holds.
type Dense = unsafe fn(Matrix<'_>, Option<&[f32]>, Activation, &[f32], *mut f32, usize);

/// `(dy, x, cols, grad, rows, total_rows, accumulate)`.
type DenseWeightGrad = unsafe fn(&[f32], &[f32], usize, *mut f32, Range<usize>, usize, bool);

/// `(w, rows, cols, dy, dx, columns)`.
type DenseDataGrad = unsafe fn(&[f32], usize, usize, &[f32], *mut f32, Range<usize>);

/// `(plane, x, y, channels, (scale, shift), act)`.
type NormalizeBlock = unsafe fn(Plane, &[f32], &mut [f32], Range<usize>, (&[f32; BLOCK], &[f32; BLOCK]), Activation);

/// `(step, params, grads, m, v)`.
type Adam = unsafe fn(AdamStep, &mut [f32], &[f32], &mut [f32], &mut [f32]);

/// `(plane, x, g, mean, sums)`.
type GradientMoments = unsafe fn(Plane, &[f32], &[f32], &[f32], &mut [f64]);

/// `(w, layer, v, scratch, output, channels)`.
type WinogradChannels = unsafe fn(&Winograd, ConvParams<'_>, &[f32], &mut [f32], *mut f32, Range<usize>);

/// A register tile run on a block of `N` consecutive units (items, columns) from `start`: what
/// [`balanced_blocks`] calls.
pub(super) trait Block<S> {
    /// # Safety
    /// As for the tile it runs.
    unsafe fn run<const N: usize>(&self, start: usize);
}

/// Runs `tile` on `count` units in balanced blocks of at most `MAX <= 8`. Const generics need
/// one arm per block size (the guards keep the arms above `MAX` from being compiled).
///
/// # Safety
/// As for the tile.
#[inline(always)]
pub(super) unsafe fn balanced_blocks<S, const MAX: usize>(count: usize, tile: &impl Block<S>) {
    unsafe {
        let blocks = count.div_ceil(MAX);
        for block in 0..blocks {
            let start = block * count / blocks;
            match (block + 1) * count / blocks - start {
                1 => tile.run::<1>(start),
                2 if MAX >= 2 => tile.run::<2>(start),
                3 if MAX >= 3 => tile.run::<3>(start),
                4 if MAX >= 4 => tile.run::<4>(start),
                5 if MAX >= 5 => tile.run::<5>(start),
                6 if MAX >= 6 => tile.run::<6>(start),
                7 if MAX >= 7 => tile.run::<7>(start),
                8 if MAX >= 8 => tile.run::<8>(start),
                _ => unreachable!("blocks hold at most MAX units"),
            }
        }
    }
}

/// A register tile of `NV` vectors of rows from `row`: what [`row_tiles`] calls.
pub(super) trait RowTile<S> {
    /// # Safety
    /// As for the tile it runs.
    unsafe fn run<const NV: usize>(&self, row: usize);
}

/// Covers `vectors` vectors of `lanes` rows each, from `row`, with tiles of at most `MAX <= 4`
/// vectors. A single-vector tile does a third of the multiply-adds per load of a three-vector
/// one, so a remainder of one vector takes the last full tile with it and splits the two
/// (3 + 1 as 2 + 2, 4 + 1 as 3 + 2).
///
/// # Safety
/// As for the tile.
#[inline(always)]
pub(super) unsafe fn row_tiles<S, const MAX: usize>(
    mut row: usize,
    vectors: usize,
    lanes: usize,
    tile: &impl RowTile<S>,
) {
    unsafe {
        let (mut full, rest) = (vectors / MAX, vectors % MAX);
        let mut tail = [rest, 0];
        if rest == 1 && full > 0 && MAX > 2 {
            full -= 1;
            tail = [(MAX + 1).div_ceil(2), MAX.div_ceil(2)];
        }
        for _ in 0..full {
            tile.run::<MAX>(row);
            row += MAX * lanes;
        }
        for nv in tail {
            match nv {
                0 => {}
                1 => tile.run::<1>(row),
                2 if MAX >= 2 => tile.run::<2>(row),
                3 if MAX >= 3 => tile.run::<3>(row),
                4 if MAX >= 4 => tile.run::<4>(row),
                _ => unreachable!("tiles hold at most MAX vectors"),
            }
            row += nv * lanes;
        }
    }
}

/// The reference kernels, for [`crate::IsaLevel::Scalar`] and every CPU without a vector unit
/// the kernels know.
static SCALAR: Entries = Entries {
    conv: scalar::conv_channels,
    dense: scalar::dense_rows,
    dense_weight_grad: scalar::dense_weight_grad_rows,
    dense_data_grad: scalar::dense_data_grad_cols,
    activation_backward: scalar::activation_backward,
    winograd_input: scalar::winograd_input,
    winograd_channels: scalar::winograd_channels,
    winograd_weights: scalar::winograd_weights,
    moments: scalar::moments,
    gradient_moments: scalar::gradient_moments,
    normalize_gradient_block: scalar::normalize_gradient_block,
    normalize_block: scalar::normalize_block,
    adam: scalar::adam,
};

/// The kernels of `isa`. Calling them is sound on this CPU: an [`Isa`] proves its features.
pub(crate) fn entries(isa: Isa) -> &'static Entries {
    arch::entries(isa.level()).unwrap_or(&SCALAR)
}

/// `static $name: Entries` for the vector type `$vector` under the target features
/// `$features`, with the dense batch tile `$items` x `$vectors` (and the same tile of columns
/// by vectors of rows for the dense weight gradient).
macro_rules! entries {
    ($name:ident, $features:literal, $vector:ty, dense tile $items:literal x $vectors:literal) => {
        static $name: $crate::simd::Entries = {
            /// # Safety
            /// The CPU must have the features; as for `conv::conv`.
            #[target_feature(enable = $features)]
            unsafe fn conv(
                layer: $crate::ConvParams<'_>,
                input: &[f32],
                output: *mut f32,
                channels: core::ops::Range<usize>,
            ) {
                unsafe { $crate::simd::conv::conv::<$vector>(layer, input, output, channels) }
            }

            /// # Safety
            /// The CPU must have the features; as for `dense::dense`.
            #[target_feature(enable = $features)]
            unsafe fn dense(
                w: $crate::Matrix<'_>,
                bias: Option<&[f32]>,
                act: $crate::Activation,
                x: &[f32],
                y: *mut f32,
                ldy: usize,
            ) {
                unsafe { $crate::simd::dense::dense::<$vector, $items, $vectors>(w, bias, act, x, y, ldy) }
            }

            /// # Safety
            /// The CPU must have the features; as for `dense_grad::weight_grad`.
            #[target_feature(enable = $features)]
            unsafe fn dense_weight_grad(
                dy: &[f32],
                x: &[f32],
                cols: usize,
                grad: *mut f32,
                rows: core::ops::Range<usize>,
                total_rows: usize,
                accumulate: bool,
            ) {
                unsafe {
                    $crate::simd::dense_grad::weight_grad::<$vector, $items, $vectors>(
                        dy, x, cols, grad, rows, total_rows, accumulate,
                    )
                }
            }

            /// # Safety
            /// The CPU must have the features; as for `dense_grad::data_grad`.
            #[target_feature(enable = $features)]
            unsafe fn dense_data_grad(
                w: &[f32],
                rows: usize,
                cols: usize,
                dy: &[f32],
                dx: *mut f32,
                columns: core::ops::Range<usize>,
            ) {
                unsafe { $crate::simd::dense_grad::data_grad::<$vector, 4, 4>(w, rows, cols, dy, dx, columns) }
            }

            /// # Safety
            /// The CPU must have the features.
            #[target_feature(enable = $features)]
            unsafe fn activation_backward(act: $crate::Activation, y: &[f32], grad: &mut [f32]) {
                unsafe { $crate::simd::act::backward::<$vector>(act, y, grad) }
            }

            /// # Safety
            /// The CPU must have the features; as for `winograd::input_body`.
            #[target_feature(enable = $features)]
            unsafe fn input(w: &$crate::winograd::Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
                unsafe { $crate::simd::winograd::input_body::<$vector>(w, phase, input, v) }
            }

            /// # Safety
            /// The CPU must have the features; as for `winograd::channels_body`.
            #[target_feature(enable = $features)]
            unsafe fn channels(
                w: &$crate::winograd::Winograd,
                layer: $crate::ConvParams<'_>,
                v: &[f32],
                scratch: &mut [f32],
                output: *mut f32,
                channels: core::ops::Range<usize>,
            ) {
                unsafe { $crate::simd::winograd::channels_body::<$vector>(w, layer, v, scratch, output, channels) }
            }

            /// # Safety
            /// The CPU must have the features; as for `winograd::weights_body`.
            #[target_feature(enable = $features)]
            unsafe fn weights(w: &$crate::winograd::Winograd, direct: &[f32], packed: &mut [f32]) {
                unsafe { $crate::simd::winograd::weights_body::<$vector>(w, direct, packed) }
            }

            /// # Safety
            /// The CPU must have the features; as for `norm::moments`.
            #[target_feature(enable = $features)]
            unsafe fn moments(plane: $crate::Plane, x: &[f32], sums: &mut [f64]) {
                unsafe { $crate::simd::norm::moments::<$vector>(plane, x, sums) }
            }

            /// # Safety
            /// The CPU must have the features; as for `norm::gradient_moments`.
            #[target_feature(enable = $features)]
            unsafe fn gradient_moments(plane: $crate::Plane, x: &[f32], g: &[f32], mean: &[f32], sums: &mut [f64]) {
                unsafe { $crate::simd::norm::gradient_moments::<$vector>(plane, x, g, mean, sums) }
            }

            /// # Safety
            /// The CPU must have the features; as for `norm::normalize_gradient_block`.
            #[target_feature(enable = $features)]
            unsafe fn normalize_gradient_block(
                plane: $crate::Plane,
                x: &[f32],
                g: &mut [f32],
                block: core::ops::Range<usize>,
                coef: &$crate::norm::GradientCoefficients,
            ) {
                unsafe { $crate::simd::norm::normalize_gradient_block::<$vector>(plane, x, g, block, coef) }
            }

            /// # Safety
            /// The CPU must have the features; as for `norm::normalize_block`.
            #[target_feature(enable = $features)]
            unsafe fn normalize_block(
                plane: $crate::Plane,
                x: &[f32],
                y: &mut [f32],
                block: core::ops::Range<usize>,
                coef: (&[f32; $crate::norm::BLOCK], &[f32; $crate::norm::BLOCK]),
                act: $crate::Activation,
            ) {
                unsafe { $crate::simd::norm::normalize_block::<$vector>(plane, x, y, block, coef, act) }
            }

            /// # Safety
            /// The CPU must have the features; as for `adam::adam`.
            #[target_feature(enable = $features)]
            unsafe fn adam(step: $crate::AdamStep, params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
                unsafe { $crate::simd::adam::adam::<$vector>(step, params, grads, m, v) }
            }

            $crate::simd::Entries {
                conv,
                dense,
                dense_weight_grad,
                dense_data_grad,
                activation_backward,
                winograd_input: input,
                winograd_channels: channels,
                winograd_weights: weights,
                moments,
                gradient_moments,
                normalize_gradient_block,
                normalize_block,
                adam,
            }
        };
    };
}

#[cfg(all(target_arch = "aarch64", target_feature = "neon"))]
mod aarch64;
#[cfg(all(target_arch = "aarch64", target_feature = "neon"))]
use aarch64 as arch;
#[cfg(all(target_arch = "x86_64", target_feature = "sse2"))]
mod x86_64;
#[cfg(all(target_arch = "x86_64", target_feature = "sse2"))]
use x86_64 as arch;
// Soft-float targets (x86_64-unknown-none) and other architectures: no entries, so every
// operation takes the scalar kernels.
#[cfg(not(any(
    all(target_arch = "aarch64", target_feature = "neon"),
    all(target_arch = "x86_64", target_feature = "sse2")
)))]
mod arch {
    pub(super) fn entries(_: crate::IsaLevel) -> Option<&'static super::Entries> {
        None
    }
}
