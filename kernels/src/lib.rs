//! The numeric kernels of drivesim.
//!
//! This crate is the contract between the networks and the arithmetic:
//! - [`layout`]: the data layouts the kernels read and write ([`Plane`], [`ConvShape`],
//!   [`Matrix`]); [`activation`]: the nonlinearities fused into the stores;
//! - [`ops`]: one entry point per operation ([`conv`], [`dense`], [`winograd_conv`], and the
//!   parts of them that threads share: [`conv_channels`], [`dense_rows`], [`winograd_input`],
//!   [`winograd_channels`]), each checking its arguments and then running the kernel of an
//!   [`Isa`] chosen once at run time; all safe: threads write their parts of one output
//!   through [`OutputParts`], which hands each part out once;
//! - the backward operations of training, on the same layouts: [`dense_weight_grad`] (the
//!   data gradient of a dense layer is the forward [`dense`] on the transposed packing,
//!   [`pack::dense_from_fn`]) and [`activation_backward`]; a convolution's data gradient is
//!   the forward [`conv`] (or Winograd) of its [`ConvShape::transposed`] shape, its weight
//!   gradient [`conv_weight_grad`] (the dense weight gradient over patches); [`norm`] holds
//!   BatchNorm in training mode and the per-channel sums of bias gradients;
//! - [`winograd`]: a second algorithm for the convolutions, Winograd's minimal filtering, with
//!   its own weight layout and caller-provided scratch; its scalar path is tested against the
//!   direct scalar convolution;
//! - [`scalar`]: the scalar reference of every operation, the test oracle of the SIMD kernels
//!   (`simd/`: AVX2 and AVX-512 on x86-64, NEON on aarch64; one generic body per operation,
//!   instantiated per instruction set) and the fallback on every other target;
//! - [`pack`]: weight packing, done once at load.
//!
//! Nothing here allocates except the packing functions; the kernels write into caller buffers.
//! Shapes are the caller's responsibility: a kernel panics on inconsistent lengths, since the
//! model validates every shape before it ever calls one.
#![cfg_attr(not(feature = "std"), no_std)]
#![deny(missing_docs)]
// An `unsafe fn`'s body is not an unsafe block: each unsafe operation in one is marked, and its
// obligations are the function's documented `# Safety` contract.
#![deny(unsafe_op_in_unsafe_fn)]

extern crate alloc;

pub mod activation;
mod isa;
pub mod layout;
pub mod math;
pub mod norm;
pub mod ops;
mod output;
pub mod pack;
pub mod scalar;
mod simd;
pub mod winograd;

pub use activation::Activation;
pub use half::f16;
pub use isa::{Isa, IsaLevel};
pub use layout::{ConvKind, ConvParams, ConvShape, Matrix, MatrixData, Plane, Tensor, Weights, NARROW_OC, OC_ALIGN};
pub use ops::{
    activation_backward, adam, conv, conv_channels, conv_grad_pixels, conv_patch_len, conv_patches, conv_weight_grad,
    conv_weight_grad_add_rows, conv_weight_grad_block_rows, conv_weight_grad_rows, conv_weight_grad_scratch_len, dense,
    dense_add, dense_add_rows, dense_data_grad, dense_data_grad_cols, dense_rows, dense_weight_grad,
    dense_weight_grad_add_rows, dense_weight_grad_rows, winograd_channels, winograd_conv, winograd_input,
    winograd_weights, AdamStep, GRAD_PIXELS,
};
pub use output::{OutputPart, OutputParts};
pub use winograd::Winograd;
