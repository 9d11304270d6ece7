//! Training inside planned memory (the `train` feature): every network of the paper.
//!
//! - [`TransitionTrainer`] trains the transition RNN. As llm.c does for GPT-2, every parameter,
//!   gradient, optimiser moment and saved activation lives in one block allocated once, sized
//!   by a plan before anything is allocated ([`TransitionPlan`]); the caller may hand that block
//!   in ([`TransitionTrainer::with_arena`]), so that training needs no allocator.
//! - [`VaeGanTrainer`] trains the encoder and generator with a discriminator; its
//!   [`VaeGanPlan`] is measured by building the trainer without allocating (as ggml's
//!   allocator measures a graph), then exactly that is allocated.
//! - [`fit_noise_factor`] fits the correlation of sampled futures' noise (`transition.L`) once
//!   a transition with the spread head is trained; [`sharpen_noise_factor`] gathers it in the
//!   directions the errors share most.
//! - [`HeadTrainer`] trains a head ([`crate::HeadKind`]) by regression on the caller's
//!   examples: the policy, the cloned driver of [`crate::Simulator::act`], by behavioural
//!   cloning; the reward head on the env's rewards; the value head on [`lambda_returns`].
//!
//! Steps allocate nothing. The backward passes run on the forward kernels where the maths
//! allows (the data gradient of a dense layer is the forward product by the transposed
//! packing in the transition trainer, that of a convolution the forward kernel of its
//! transposed shape, [`drivesim_kernels::ConvShape::transposed`]) and on the kernels crate's
//! backward operations otherwise ([`drivesim_kernels::dense_weight_grad`],
//! [`drivesim_kernels::dense_data_grad`] for the VAE-GAN's large dense layers,
//! [`drivesim_kernels::conv_weight_grad`],
//! [`drivesim_kernels::activation_backward`], [`drivesim_kernels::norm`]). Each step agrees with
//! PyTorch's (`weights/drivesim_reference/train.py`, checked by the fixtures of `tests/train.rs` and
//! `tests/train_vae_gan.rs`), and threads change no bit of it.

mod adam;
mod arena;
mod heads;
mod noise;
mod returns;
mod shared;
mod state;
mod transition;
mod vae_gan;
mod work;

pub use adam::Adam;
pub use heads::{HeadSettings, HeadTrainer};
#[cfg(feature = "std")]
pub use noise::with_noise_factor;
pub use noise::{fit_noise_factor, sharpen_noise_factor};
pub use returns::lambda_returns;
// Defined beside the metadata it fills, so that the core never imports `train`.
pub use crate::metadata::TrainedOn;
pub use transition::{TransitionPlan, TransitionSettings, TransitionTrainer};
#[cfg(feature = "std")]
pub use vae_gan::random_weight_file;
pub use vae_gan::{VaeGanLosses, VaeGanPlan, VaeGanSettings, VaeGanTrainer, VAE_GAN_LR};
pub use work::{PartWork, StepWork};

/// A named tensor in PyTorch layout: name, shape, row-major values.
pub type NamedTensor = (alloc::string::String, alloc::vec::Vec<usize>, alloc::vec::Vec<f32>);

/// `torch.optim.lr_scheduler.CosineAnnealingLR` (to zero): the learning rate of step `step`
/// (from 0) of `steps`, `base (1 + cos(π step / steps)) / 2`.
pub fn cosine_lr(base: f32, step: usize, steps: usize) -> f32 {
    let progress = step.min(steps) as f64 / steps.max(1) as f64;
    (base as f64 * (1.0 + drivesim_kernels::math::cos(core::f64::consts::PI * progress)) / 2.0) as f32
}
