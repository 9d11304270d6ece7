//! Training the encoder and generator as a VAE-GAN (Larsen et al.), exactly as
//! `weights/drivesim_reference/vae_gan.py`'s `vae_gan_step`: a discriminator (the encoder's mirror, a logit on top)
//! learns to tell real frames from reconstructions and prior samples; the encoder minimises a
//! KL prior plus the reconstruction error measured on the discriminator's third-convolution
//! features (relative to their spread) and in pixels; the generator minimises the same
//! reconstruction error and fools the discriminator. The GAN term never reaches the encoder, and
//! prior samples go through the generator's BatchNorm with batch statistics without moving its
//! running statistics. Adam with lr 2e-4 and betas 0.5 / 0.999 for each network.
//!
//! Every buffer is sized before anything is allocated: [`VaeGanPlan`] builds the trainer once
//! in a measuring mode (as ggml's allocator measures a graph), adding up what each buffer would
//! take; [`VaeGanTrainer::new`] then allocates exactly that. Convolutions keep their parameters,
//! gradients and Adam moments in PyTorch's layout and dense layers in the kernels' packed one
//! (the forward pass multiplies by them as they are); each network's packings (convolutions'
//! forward ones, and every layer's data gradient: the forward kernel of the transposed
//! convolution or dense layer) are rebuilt in place after each update. A step allocates
//! nothing.
//!
//! The files: `trainer` (the public API: settings, losses, [`VaeGanTrainer`]), `plan` (the
//! [`VaeGanPlan`] and a step's buffers), `networks` (the tensors' table, the networks built),
//! `layers` (packed convolutions and dense layers), `stack` (a convolution stack's forward and
//! backward passes), `norm` (BatchNorm's training passes), `weight_grad` (a convolution's weight gradient shared
//! by threads), `loss` (the losses' building blocks),
//! `step` (one step, top to bottom), `update` (the gradients checked, Adam, the repacking) and
//! `state` (the trainer's state as bytes, for checkpoints).

// Passes are lists of item ranges, each a batch of its own for BatchNorm: often just one.
#![allow(clippy::single_range_in_vec_init)]

mod budget;
mod buffers;
mod layers;
mod loss;
mod networks;
mod norm;
mod plan;
mod stack;
mod state;
mod step;
mod table;
mod trainer;
mod update;
mod weight_grad;
mod work;

#[cfg(feature = "std")]
pub use networks::random_weight_file;
pub use plan::VaeGanPlan;
pub use trainer::{VaeGanLosses, VaeGanSettings, VaeGanTrainer, VAE_GAN_LR};

/// The border of every plane of the training networks: strided convolutions read 2 pixels
/// beyond the image, transposed ones 1, and so do their gradients; one border for all keeps each
/// gradient plane in the layout of the activation it belongs to.
const HALO: usize = 2;
