//! `train noise`: fit the correlation of sampled futures' noise (`transition.L`) for a weight
//! file whose transition has the spread head, from its one-step errors on episodes, training
//! nothing: the factor of a file trained before it existed, or on other data. `train transition
//! --spread` fits it itself after training (the same `with_fitted_noise`).

use crate::args::{data_help, Data};
use crate::common::Encoded;
use crate::drives::{split, Drives};
use crate::files::read;
use clap::Parser;
use drivesim::train::{fit_noise_factor, sharpen_noise_factor, with_noise_factor};
use drivesim::Model;

#[derive(Parser)]
#[command(mut_args = data_help(&[
    ("weights", "Weight file whose transition has the spread head (its encoder encodes the episodes)"),
    ("episodes", "Episodes whose one-step errors the correlation is fitted on (the transition's training data)"),
    ("heldout", "Unused (the flags are the training commands')"),
    ("holdout", "Episodes of --episodes left out of the fit"),
    ("out", "Where to write the weights with transition.L"),
]))]
pub struct NoiseArgs {
    #[command(flatten)]
    pub data: Data,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub threads: u32,
    #[command(flatten)]
    pub power: NoisePower,
}

/// How the fitted correlation is sharpened (`train noise`, `train transition --spread`, `train fit`).
#[derive(clap::Args, Clone, Copy)]
pub struct NoisePower {
    /// Raise the noise's correlation to this power, back to unit diagonal
    /// (`sharpen_noise_factor`): 2 brings the best of a few sampled futures nearer what
    /// happened and makes the sampled codes smaller (docs/history/next_second.md); 1 keeps it as fitted
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub noise_power: u32,
}

/// `file` (whose model is `model`) with the noise factor fitted on the drives `train`,
/// sharpened to `power`.
pub fn with_fitted_noise(file: &[u8], model: &Model, train: &[Encoded], power: &NoisePower) -> Result<Vec<u8>, String> {
    let drives: Vec<(&[f32], &[f32])> = train.iter().map(|e| (&e.codes[..], &e.actions[..])).collect();
    let fitted = fit_noise_factor(model, &drives).map_err(|e| format!("the noise's correlation: {e}"))?;
    let factor =
        sharpen_noise_factor(&fitted, power.noise_power).map_err(|e| format!("the noise's correlation: {e}"))?;
    println!(
        "fitted the noise's correlation (transition.L, power {}) on {} drives",
        power.noise_power,
        drives.len()
    );
    with_noise_factor(file, &factor).map_err(|e| e.to_string())
}

pub fn noise(args: &NoiseArgs) -> Result<(), String> {
    let original = read(&args.data.weights)?;
    let model = Model::from_bytes(&original).map_err(|e| format!("{}: {e}", args.data.weights.display()))?;
    if !model.samples() {
        return Err(format!(
            "{}: the transition has no spread head (train transition --spread adds one)",
            args.data.weights.display()
        ));
    }
    let Drives { train, .. } = split(&model, &args.data, args.threads as usize)?;
    let bytes = with_fitted_noise(&original, &model, &train, &args.power)?;
    crate::files::write_atomically(&args.data.out, &bytes)?;
    println!("wrote {}", args.data.out.display());
    Ok(())
}
