//! # drivesim
//!
//! comma.ai's learned driving simulator ("Learning a Driving Simulator", Santana & Hotz, 2016)
//! on the CPU: an **encoder** (frame to latent code), an action-conditioned tanh-RNN
//! **transition** model in latent space, and a **generator** (code to frame). Seeding the
//! transition with encoded frames and feeding its predictions back hallucinates video that a
//! controller can drive.
//!
//! - [`Model`] loads weights exported from PyTorch as safetensors and packs them for the
//!   kernels once. Every file format is stated in one place, the repository's `weights/`:
//!   the weight contract in `weights/README.md`, the episodes, checkpoint, fixture and
//!   step files in `weights/TRAINING_FILES.md`.
//! - [`Simulator`] allocates every buffer up front, as its [`Plan`] computed (an unaffordable
//!   plan is an error, never an abort); encoding, stepping and generating allocate nothing,
//!   and give the same bits whatever the thread count, batch or call history.
//! - The arithmetic lives in the `drivesim-kernels` crate: scalar reference kernels and
//!   AVX2/AVX-512 (x86-64) or NEON (aarch64) versions, chosen at run time (cap with
//!   `DRIVESIM_ISA=scalar|neon|avx2|avx512`).
//!
//! BatchNorm uses PyTorch eval semantics (running statistics). The paper's Keras code used
//! batch statistics even at test time (`BN(mode=2)`), which makes outputs depend on the batch;
//! here a frame's code never depends on what else is in the batch.
//!
//! ```
//! use drivesim::{Config, Model, Simulator, WeightDtype};
//!
//! # fn main() -> Result<(), drivesim::Error> {
//! // A small config with seeded random weights; real use: `Model::load("weights/default.safetensors")`.
//! let config = Config { height: 32, width: 64, base_channels: 4, z_dim: 16, hidden_dim: 16, ..Config::COMMA };
//! let model = Model::random(&config, 7, WeightDtype::F32)?;
//! let mut sim = Simulator::new(&model)?;
//!
//! let frame = vec![0.0f32; config.frame_len()]; // HWC, values in [-1, 1]
//! let mut z = vec![0.0; config.z_dim];
//! sim.encode(&frame, &mut z)?;
//!
//! let mut h = vec![0.0; config.hidden_dim];
//! let mut z_next = vec![0.0; config.z_dim];
//! sim.transition(&z, &mut h, &[10.0, -0.1], &mut z_next)?; // (speed, steering)
//!
//! let mut predicted = vec![0.0; config.frame_len()];
//! sim.generate(&z_next, &mut predicted)?;
//! assert!(predicted.iter().all(|v| (-1.0..=1.0).contains(v)));
//! # Ok(())
//! # }
//! ```
#![cfg_attr(not(feature = "std"), no_std)]
#![deny(missing_docs)]
// An `unsafe fn`'s body is not an unsafe block: each unsafe operation in one is marked, and its
// obligations are the function's documented `# Safety` contract.
#![deny(unsafe_op_in_unsafe_fn)]

extern crate alloc;

mod actions;
mod config;
mod driver;
mod encoder;
mod environment;
mod episodes;
mod error;
mod frames;
mod generator;
mod heads;
mod layers;
mod metadata;
mod model;
mod plan;
mod pool;
mod sampling;
mod simulator;
mod texture;
#[cfg(feature = "train")]
pub mod train;
mod transition;
mod weights;

pub use actions::ActionSpec;
pub use config::Config;
#[cfg(feature = "std")]
pub use driver::driver_file;
#[cfg(feature = "std")]
pub use driver::sampler_file;
pub use driver::world_fingerprint;
pub use drivesim_kernels::{Isa, IsaLevel};
pub use environment::Environment;
pub use episodes::{Episode, Episodes};
pub use error::{Error, Result};
pub use frames::{frames_from_rgb, frames_to_rgb, PixelLayout};
pub use heads::HeadKind;
pub use model::Model;
pub use plan::Plan;
pub use pool::MAX_THREADS;
pub use simulator::Simulator;
pub use weights::WeightDtype;

/// The README's Rust snippet, compiled and run as a doctest so that it stays true.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;

/// The API guide's Rust snippets (`docs/guide.md`), compiled and run as doctests too.
#[cfg(doctest)]
#[doc = include_str!("../docs/guide.md")]
pub struct GuideDoctests;
