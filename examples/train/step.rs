//! `train step`: one verifiable step of the transition or of the VAE-GAN on a batch file,
//! writing the loss, every gradient and the updated tensors.

use crate::files::{f32_tensor, read, write_f32};
use clap::{Parser, ValueEnum};
use drivesim::train::{
    TransitionPlan, TransitionSettings, TransitionTrainer, VaeGanPlan, VaeGanSettings, VaeGanTrainer, VAE_GAN_LR,
};
use drivesim::Model;
use safetensors::{Dtype, SafeTensors};
use std::path::PathBuf;

#[derive(Clone, Copy, ValueEnum)]
enum Stage {
    Transition,
    VaeGan,
}

#[derive(Parser)]
pub struct StepArgs {
    #[arg(long, value_enum)]
    stage: Stage,
    #[arg(long)]
    weights: PathBuf,
    /// transition: `codes` f32 [B, T, z] and `actions` f32 [B, T-1, action_dim]; vae-gan:
    /// `frames` [B, H, W, C] (u8, or f32 in [-1, 1]), `eps` and `prior` f32 [B, z]
    #[arg(long)]
    batch: PathBuf,
    #[arg(long)]
    out: PathBuf,
    /// Adam's learning rate (default 1e-3 transition, 2e-4 vae-gan)
    #[arg(long)]
    lr: Option<f32>,
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    teacher: u32,
    #[arg(long, default_value_t = 1.0)]
    clip: f32,
    #[arg(long)]
    full_bptt: bool,
}

pub fn step(args: &StepArgs) -> Result<(), String> {
    match args.stage {
        Stage::Transition => step_transition(args),
        Stage::VaeGan => step_vae_gan(args),
    }
}

fn step_transition(args: &StepArgs) -> Result<(), String> {
    let model = Model::load(&args.weights).map_err(|e| format!("{}: {e}", args.weights.display()))?;
    let c = *model.config();
    let bytes = read(&args.batch)?;
    let file = SafeTensors::deserialize(&bytes).map_err(|e| format!("{}: {e:?}", args.batch.display()))?;
    let (shape, codes) = f32_tensor(&file, "codes", &args.batch)?;
    let (action_shape, actions) = f32_tensor(&file, "actions", &args.batch)?;
    let [b, t, z] = shape[..] else {
        return Err(format!("`codes` has shape {shape:?}: expected [B, T, {}]", c.z_dim));
    };
    if z != c.z_dim || t < 2 || b == 0 {
        return Err(format!(
            "`codes` has shape {shape:?}: expected [B >= 1, T >= 2, {}]",
            c.z_dim
        ));
    }
    if action_shape != [b, t - 1, c.action_dim] {
        return Err(format!(
            "`actions` has shape {action_shape:?}: expected {:?}",
            [b, t - 1, c.action_dim]
        ));
    }
    let plan = TransitionPlan::for_model(&model, b, t).map_err(|e| e.to_string())?;
    let settings = TransitionSettings {
        teacher: args.teacher as usize,
        clip: args.clip,
        full_bptt: args.full_bptt,
        ..TransitionSettings::default()
    };
    let mut trainer = TransitionTrainer::new(&model, &plan, settings).map_err(|e| e.to_string())?;
    let loss = trainer.compute_gradients(&codes, &actions).map_err(|e| e.to_string())?;
    let norm = trainer.gradient_norm().unwrap_or(f32::NAN);
    let gradients = trainer.gradients();
    trainer
        .apply_gradients(args.lr.unwrap_or(1e-3))
        .map_err(|e| e.to_string())?;
    let mut out: Vec<(String, Vec<usize>, Vec<f32>)> = vec![("loss".into(), vec![1], vec![loss])];
    out.extend(
        gradients
            .into_iter()
            .map(|(name, shape, v)| (format!("grad.{name}"), shape, v)),
    );
    out.extend(
        trainer
            .tensors()
            .into_iter()
            .map(|(name, shape, v)| (name.to_string(), shape, v)),
    );
    write_f32(&args.out, &out)?;
    println!(
        "loss {loss:.6e}, gradient norm {norm:.6e}: wrote {}",
        args.out.display()
    );
    Ok(())
}

/// `train step --stage vae-gan`: one step on `frames` (uint8, or f32 in [-1, 1]), `eps` and
/// `prior` from the batch file; writes the losses, every gradient and the updated tensors.
fn step_vae_gan(args: &StepArgs) -> Result<(), String> {
    let weights = read(&args.weights)?;
    let model = Model::from_bytes(&weights).map_err(|e| format!("{}: {e}", args.weights.display()))?;
    let c = *model.config();
    let bytes = read(&args.batch)?;
    let file = SafeTensors::deserialize(&bytes).map_err(|e| format!("{}: {e:?}", args.batch.display()))?;
    let view = file
        .tensor("frames")
        .map_err(|_| format!("{}: no tensor `frames`", args.batch.display()))?;
    let want = [c.height, c.width, c.channels];
    if view.shape().len() != 4 || view.shape()[1..] != want || view.shape()[0] == 0 {
        return Err(format!(
            "`frames` has shape {:?}: expected [B >= 1, {}, {}, {}]",
            view.shape(),
            want[0],
            want[1],
            want[2]
        ));
    }
    let b = view.shape()[0];
    let frames: Vec<f32> = match view.dtype() {
        Dtype::U8 => view.data().iter().map(|&v| v as f32 / 127.5 - 1.0).collect(),
        Dtype::F32 => f32_tensor(&file, "frames", &args.batch)?.1,
        other => return Err(format!("`frames` is {other:?}: expected U8, or F32 in [-1, 1]")),
    };
    let mut draws = Vec::new();
    for name in ["eps", "prior"] {
        let (shape, values) = f32_tensor(&file, name, &args.batch)?;
        if shape != [b, c.z_dim] {
            return Err(format!("`{name}` has shape {shape:?}: expected [{b}, {}]", c.z_dim));
        }
        draws.push(values);
    }
    let plan = VaeGanPlan::new(&c, b, 1).map_err(|e| e.to_string())?;
    let mut trainer = VaeGanTrainer::new(&weights, &plan, VaeGanSettings::default()).map_err(|e| e.to_string())?;
    let lr = args.lr.unwrap_or(VAE_GAN_LR);
    let l = trainer
        .step(&frames, &draws[0], &draws[1], lr)
        .map_err(|e| e.to_string())?;
    let losses = [
        ("d", l.discriminator),
        ("e", l.encoder),
        ("g", l.generator),
        ("gan", l.gan),
        ("feature", l.feature),
        ("pixel_l1", l.pixel_l1),
        ("kl", l.kl),
    ];
    let mut out: Vec<(String, Vec<usize>, Vec<f32>)> = losses
        .iter()
        .map(|(name, v)| (format!("loss.{name}"), vec![1], vec![*v]))
        .collect();
    out.extend(
        trainer
            .gradients()
            .into_iter()
            .map(|(name, shape, v)| (format!("grad.{name}"), shape, v)),
    );
    out.extend(trainer.tensors());
    write_f32(&args.out, &out)?;
    let listed: Vec<String> = losses.iter().map(|(name, v)| format!("{name} {v:.6e}")).collect();
    println!("{}: wrote {}", listed.join(", "), args.out.display());
    Ok(())
}
