//! The SIMD kernels, one file per operation: each a generic body over the vector traits of
//! [`vector`]. The architecture's module implements the trait for its vectors and compiles
//! each body once per instruction set inside a `#[target_feature]` entry point
//! (`x86_64`: AVX2 + FMA + F16C and AVX-512F; `aarch64`: NEON); the operations look their entry
//! up by [`crate::IsaLevel`] and fall back to the scalar kernels where there is none.

// Without a vector unit the kernels know, nothing instantiates the generic bodies.
#![cfg_attr(
    not(any(
        all(target_arch = "aarch64", target_feature = "neon"),
        all(target_arch = "x86_64", target_feature = "sse2")
    )),
    allow(dead_code, unused_macros)
)]

pub(crate) mod act;
mod conv;
mod dense;
pub(crate) mod vector;
pub(crate) mod winograd;

/// One instruction set's entry points: each generic body compiled inside a
/// `#[target_feature]` function. Made by `entries!` below; each architecture's `entries(level)`
/// returns the set for a level of its own.
pub(super) struct Entries {
    conv: conv::Entry,
    dense_f32: dense::Entry<f32>,
    dense_f16: dense::Entry<crate::f16>,
    winograd_input: winograd::InputEntry,
    winograd_channels: winograd::ChannelsEntry,
}

/// `static $name: Entries` for the vector type `$vector` under the target features
/// `$features`, with the dense batch tile `$items` x `$vectors`.
macro_rules! entries {
    ($name:ident, $features:literal, $vector:ty, dense tile $items:literal x $vectors:literal) => {
        static $name: $crate::simd::Entries = {
            /// # Safety
            /// The CPU must have the features; as for `conv::body`.
            #[target_feature(enable = $features)]
            unsafe fn conv(
                layer: $crate::ConvParams<'_>,
                input: &[f32],
                output: *mut f32,
                channels: core::ops::Range<usize>,
                pass: $crate::simd::conv::Pass,
            ) {
                $crate::simd::conv::body::<$vector>(layer, input, output, channels, pass)
            }

            /// # Safety
            /// The CPU must have the features; as for `dense::body`.
            #[target_feature(enable = $features)]
            unsafe fn dense<T: $crate::simd::dense::Weight>(w: &[T], args: $crate::simd::dense::Args<'_>) {
                $crate::simd::dense::body::<$vector, T, $items, $vectors>(w, args)
            }

            /// # Safety
            /// The CPU must have the features; as for `winograd::input_body`.
            #[target_feature(enable = $features)]
            unsafe fn input(w: &$crate::winograd::Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
                $crate::simd::winograd::input_body::<$vector>(w, phase, input, v)
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
                $crate::simd::winograd::channels_body::<$vector>(w, layer, v, scratch, output, channels)
            }

            $crate::simd::Entries {
                conv,
                dense_f32: dense::<f32>,
                dense_f16: dense::<$crate::f16>,
                winograd_input: input,
                winograd_channels: channels,
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

pub(crate) use conv::conv;
pub(crate) use dense::dense;
