//! The SIMD kernels, one file per operation: each a generic body over the vector trait
//! [`act::Simd`]. The architecture's module implements the trait for its vectors and compiles
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
pub(crate) mod winograd;

/// Every kernel's generic body compiled for one instruction set: the architecture modules'
/// entry points (`$features` for `#[target_feature]`, `$vector` the [`act::Simd`] type, the
/// dense batch tile `$items` x `$vectors`).
macro_rules! entries {
    ($features:literal, $vector:ty, dense tile $items:literal x $vectors:literal,
     $conv:ident, $dense:ident, $input:ident, $channels:ident) => {
        /// # Safety
        #[doc = concat!("The CPU must have ", $features, "; as for `conv::body`.")]
        #[target_feature(enable = $features)]
        unsafe fn $conv(
            layer: $crate::ConvParams<'_>,
            input: &[f32],
            output: *mut f32,
            channels: core::ops::Range<usize>,
            pass: $crate::simd::conv::Pass,
        ) {
            $crate::simd::conv::body::<$vector>(layer, input, output, channels, pass)
        }

        /// # Safety
        #[doc = concat!("The CPU must have ", $features, "; as for `dense::body`.")]
        #[target_feature(enable = $features)]
        unsafe fn $dense<T: $crate::simd::dense::Weight>(w: &[T], args: $crate::simd::dense::Args<'_>) {
            $crate::simd::dense::body::<$vector, T, $items, $vectors>(w, args)
        }

        /// # Safety
        #[doc = concat!("The CPU must have ", $features, "; as for `winograd::input_body`.")]
        #[target_feature(enable = $features)]
        unsafe fn $input(w: &$crate::winograd::Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
            $crate::simd::winograd::input_body::<$vector>(w, phase, input, v)
        }

        /// # Safety
        #[doc = concat!("The CPU must have ", $features, "; as for `winograd::channels_body`.")]
        #[target_feature(enable = $features)]
        unsafe fn $channels(
            w: &$crate::winograd::Winograd,
            layer: $crate::ConvParams<'_>,
            v: &[f32],
            scratch: &mut [f32],
            output: *mut f32,
            channels: core::ops::Range<usize>,
        ) {
            $crate::simd::winograd::channels_body::<$vector>(w, layer, v, scratch, output, channels)
        }
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
    use super::{conv, dense, winograd};
    use crate::IsaLevel;

    pub(super) fn conv_entry(_: IsaLevel) -> Option<conv::Entry> {
        None
    }
    pub(super) fn dense_entry<T>(_: IsaLevel) -> Option<dense::Entry<T>> {
        None
    }
    pub(super) fn winograd_input_entry(_: IsaLevel) -> Option<winograd::InputEntry> {
        None
    }
    pub(super) fn winograd_channels_entry(_: IsaLevel) -> Option<winograd::ChannelsEntry> {
        None
    }
}

pub(crate) use conv::conv;
pub(crate) use dense::dense;
