//! `train fit`: both stages, as `weights/tool train fit` runs them: the VAE-GAN, then the
//! transition on its codes.

use crate::args::{data_help, Data, DtypeArg};
use crate::checkpoint::Checkpointing;
use crate::transition::{transition, TransitionArgs};
use crate::vae_gan::{vae_gan, VaeGanArgs};
use clap::Parser;
use drivesim::train::VaeGanSettings;

#[derive(Parser)]
#[command(mut_args = data_help(&[
    ("weights", "Weight file to start from (or, with --from-scratch, whose config to train)"),
    ("out", "Where to write the weights (the autoencoder stage's go beside it, OUT.autoencoder.safetensors)"),
]))]
pub struct FitArgs {
    #[command(flatten)]
    pub data: Data,
    /// Start both stages from seeded random weights
    #[arg(long)]
    from_scratch: bool,
    #[arg(long, default_value_t = 1000)]
    vae_steps: usize,
    /// Frames per VAE-GAN step
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=4096))]
    batch: u32,
    #[arg(long, default_value_t = drivesim::train::VAE_GAN_LR)]
    lr: f32,
    /// Stop the VAE-GAN stage after this many minutes
    #[arg(long)]
    minutes: Option<f64>,
    #[arg(long, default_value_t = 2000)]
    transition_steps: usize,
    /// Windows per transition step
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=65536))]
    transition_batch: u32,
    #[arg(long, default_value_t = 1e-3)]
    transition_lr: f32,
    /// Also train the transition's spread head (sampled futures; see `transition --spread`)
    #[arg(long)]
    spread: bool,
    #[command(flatten)]
    noise_power: crate::noise::NoisePower,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    threads: u32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Dtype of the written file (default: the input file's)
    #[arg(long)]
    dtype: Option<DtypeArg>,
    #[command(flatten)]
    checkpointing: Checkpointing,
}

/// Each stage's checkpoints: `CKPT.vae-gan` and `CKPT.transition`. A resumed `fit` runs the
/// VAE-GAN stage again from its last checkpoint (at most `--checkpoint-every` steps again, to
/// the same autoencoder), then goes on with the transition's.
fn stage(c: &Checkpointing, name: &str) -> Checkpointing {
    Checkpointing {
        checkpoint: c.checkpoint.as_ref().map(|p| p.with_extension(name)),
        ..c.clone()
    }
}

/// `fit`: the VAE-GAN stage into OUT.autoencoder.safetensors (f32), then the transition from it.
pub fn fit(args: &FitArgs) -> Result<(), String> {
    let autoencoder = args.data.out.with_extension("autoencoder.safetensors");
    let defaults = VaeGanSettings::default();
    vae_gan(&VaeGanArgs {
        data: Data {
            out: autoencoder.clone(),
            ..args.data.clone()
        },
        steps: args.vae_steps,
        batch: args.batch,
        lr: args.lr,
        threads: args.threads,
        seed: args.seed,
        minutes: args.minutes,
        every: 200,
        sheet: None,
        from_scratch: args.from_scratch,
        dtype: Some(DtypeArg::F32),
        w_pixel: defaults.pixel,
        w_feature: defaults.feature,
        w_kl: defaults.kl,
        w_gan: defaults.gan,
        checkpointing: stage(&args.checkpointing, "vae-gan"),
    })?;
    transition(&TransitionArgs {
        data: Data {
            weights: autoencoder,
            ..args.data.clone()
        },
        steps: args.transition_steps,
        batch: args.transition_batch,
        window: 15,
        teacher: 5,
        lr: args.transition_lr,
        threads: args.threads,
        full_bptt: false,
        restart: args.from_scratch,
        spread: args.spread,
        independent_noise: false,
        noise_power: args.noise_power,
        dtype: args.dtype,
        seed: args.seed,
        checkpointing: stage(&args.checkpointing, "transition"),
    })
}
