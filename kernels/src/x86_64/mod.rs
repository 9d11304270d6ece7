//! x86-64 SIMD kernels, one file per operation; each has an AVX2+FMA and an AVX-512 body.

pub(crate) mod act;
mod conv;
mod dense;

pub(crate) use conv::conv;
pub(crate) use dense::dense;
pub(crate) mod winograd;
