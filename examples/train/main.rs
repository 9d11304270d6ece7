//! Trains the networks on the CPU with `drivesim::train`, or runs one verifiable step.
//!
//! ```text
//! cargo run --release --features train --example train -- transition \
//!     --weights weights/default.safetensors --episodes DATA.safetensors.gz --out tuned.safetensors \
//!     [--heldout HELDOUT.safetensors.gz] [--steps 2000] [--batch 64] [--lr 1e-3] [--threads 2] [--full-bptt]
//! cargo run --release --features train --example train -- vae-gan \
//!     --weights weights/default.safetensors --episodes DATA.safetensors.gz --out tuned.safetensors \
//!     [--heldout HELDOUT.safetensors.gz] [--steps 1000] [--batch 32] [--threads 2] [--minutes 20] \
//!     [--every 200] [--sheet sheet.png] [--from-scratch] [--w-pixel 1 --w-feature 0.1 --w-kl 0.001 --w-gan 0.01]
//! cargo run --release --features train --example train -- fit --weights W --episodes DATA \
//!     --out model.safetensors [--from-scratch] [--vae-steps 1000] [--transition-steps 2000] [--threads 2]
//! cargo run --release --features train --example train -- policy --weights W --episodes DATA \
//!     --out model.safetensors [--steps 4000] [--batch 256] [--lr 1e-3] [--width 64] [--lead 1]
//!     (transition, vae-gan, fit, policy: [--no-mirror] [--checkpoint CKPT [--checkpoint-every 500] [--resume]])
//! cargo run --release --features train --example train -- noise --weights W --episodes DATA \
//!     --out model.safetensors [--holdout 1] [--threads 2]
//! cargo run --release --features train --example train -- step --stage transition|vae-gan \
//!     --weights W.safetensors --batch B.safetensors --out O.safetensors [--lr ...] [--teacher 5] [--clip 1.0]
//! ```
//! `vae-gan` trains the encoder and generator with a discriminator as `weights/drivesim_reference/train.py fit`'s
//! first stage does, measures held-out reconstruction PSNR every `--every` steps, and writes
//! the weights (discriminator included, so a run resumes from its `--out`; Adam's moments
//! start again). `fit` runs both stages, as `weights/tool train fit` does.
//! `transition` encodes the episodes with the crate's encoder, trains (or fine-tunes) the
//! transition on windows of 15 codes as `weights/drivesim_reference/train.py` does, reports the held-out latent
//! error before and after, and writes a weight file `Model::load` reads. `step` is the
//! verification mode: one step on a given batch, writing the loss, every gradient and the
//! updated tensors (the file formats are in `weights/TRAINING_FILES.md`), as
//! `weights/tool train step` does in PyTorch.
//!
//! `noise` fits the correlation of sampled futures' noise (`transition.L`) for a file with the
//! spread head, training nothing (`transition --spread` fits it after training).
//!
//! `policy` clones the recorded driver (see `policy.rs`): the policy that `Simulator::act` runs.
//!
//! Every training command learns from the episodes and their mirror images (each frame flipped
//! left to right, the steering negated: CarRacing's laps turn mostly one way, the mirror gives
//! the other) unless `--no-mirror`.
//!
//! This file parses the command line and dispatches; each command is a module of its own
//! (`transition.rs`, `vae_gan.rs`, `fit.rs`, `noise.rs`, `policy.rs`, `step.rs`), the flags they share are in `args.rs`,
//! the drives they encode in `drives.rs` and the file helpers in `files.rs`.

mod args;
mod checkpoint;
#[path = "../common.rs"]
mod common;
mod dreams;
mod drives;
mod files;
mod fit;
mod heads;
mod noise;
mod policy;
mod regression;
mod step;
mod transition;
mod vae_gan;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(about = "Train drivesim's transition model on the CPU, or run one verifiable step")]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train or fine-tune the transition on episodes, report held-out errors, write weights
    Transition(transition::TransitionArgs),
    /// Train or fine-tune the encoder and generator as a VAE-GAN on episodes' frames
    VaeGan(vae_gan::VaeGanArgs),
    /// Both stages, as `weights/tool train fit`: the VAE-GAN, then the transition on its codes
    Fit(fit::FitArgs),
    /// Fit the correlation of sampled futures' noise (transition.L) on episodes, training nothing
    Noise(noise::NoiseArgs),
    /// Behavioural cloning: train the policy (the cloned driver) on a driver's episodes
    Policy(policy::PolicyArgs),
    /// The reward head or the value head (TD(λ)) on episodes with the env's rewards
    Heads(heads::HeadsArgs),
    /// One step on a batch file; write the loss, gradients and updated tensors
    Step(step::StepArgs),
}

fn main() -> ExitCode {
    common::exit(match Args::parse().command {
        Command::Transition(args) => transition::transition(&args),
        Command::VaeGan(args) => vae_gan::vae_gan(&args),
        Command::Fit(args) => fit::fit(&args),
        Command::Noise(args) => noise::noise(&args),
        Command::Policy(args) => policy::policy(&args),
        Command::Heads(args) => heads::heads(&args),
        Command::Step(args) => step::step(&args),
    })
}
