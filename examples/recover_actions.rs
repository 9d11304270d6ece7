//! Recovers the actions of recorded video: the (speed, steering) that make the transition model
//! reproduce the encoded frames, found by gradient descent on the actions through the RNN
//! (DriveGAN's differentiable re-simulation; `TransitionTrainer::action_gradients`), then
//! compared with the actions actually recorded.
//!
//! ```text
//! cargo run --release --features train --example recover_actions -- \
//!     --episodes HELDOUT.safetensors.gz [--weights weights/default.safetensors] [--out recovered]
//!     [--window 30] [--iterations 300] [--lr 0.05] [--smooth 0.03] [--threads 2]
//! ```
//! Each episode is cut into windows of `--window` frames that share their end frames, so each
//! action belongs to one window; every input is the encoded frame (teacher-forced), and the
//! actions start at the training data's mean. The loss adds a weak smoothness prior (`--smooth`
//! times the mean squared change between consecutive actions, in standard deviations): an
//! action late in a window reaches few predictions, and without the prior it is free to spike.
//! Prints the correlation and mean error per action and writes `actions_EPISODE.png`: recorded
//! (white) and recovered (orange) over time.

#[path = "common.rs"]
mod common;

use clap::Parser;
use common::{encode, report, write_png, Encoded};
use drivesim::train::{Adam, TransitionPlan, TransitionSettings, TransitionTrainer};
use drivesim::{Episodes, Model};
use std::path::PathBuf;
use std::process::ExitCode;

/// The default model's training actions (`docs/history/default.md`): speed in Box2D units/s and
/// steering in [-1, 1], their means and standard deviations, for weight files without
/// `drivesim.actions` metadata. The search starts at the means.
const DEFAULT_MEAN: [f32; 2] = [24.8, -0.04];
const DEFAULT_STD: [f32; 2] = [11.2, 0.23];

#[derive(Parser)]
#[command(about = "Recover the actions of recorded episodes through the transition model")]
struct Args {
    #[arg(long, default_value = "weights/default.safetensors")]
    weights: PathBuf,
    /// Episodes the model never saw (python -m drivesim record writes them)
    #[arg(long)]
    episodes: PathBuf,
    /// Where the plots go
    #[arg(long, default_value = "recovered")]
    out: PathBuf,
    /// Frames per window (its actions: one fewer)
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(2..=1000))]
    window: u32,
    /// Gradient steps on the actions
    #[arg(long, default_value_t = 300)]
    iterations: u32,
    /// Adam's learning rate, in standard deviations of each action
    #[arg(long, default_value_t = 0.05)]
    lr: f32,
    /// Weight of the smoothness prior: the mean squared change between consecutive actions
    /// (in standard deviations), added to the loss
    #[arg(long, default_value_t = 0.03)]
    smooth: f32,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    threads: u32,
}

fn main() -> ExitCode {
    common::exit(run(&Args::parse()))
}

/// Pearson correlation and mean absolute error of `found` against `want`.
fn agreement(found: &[f64], want: &[f64]) -> (f64, f64) {
    let n = found.len().max(1) as f64;
    let (mf, mw) = (found.iter().sum::<f64>() / n, want.iter().sum::<f64>() / n);
    let (mut cov, mut vf, mut vw, mut abs) = (0.0, 0.0, 0.0, 0.0);
    for (f, w) in found.iter().zip(want) {
        cov += (f - mf) * (w - mw);
        vf += (f - mf).powi(2);
        vw += (w - mw).powi(2);
        abs += (f - w).abs();
    }
    (cov / (vf * vw).sqrt().max(1e-30), abs / n)
}

fn run(args: &Args) -> Result<(), String> {
    let model = Model::load(&args.weights).map_err(|e| format!("weights: {}", report(&e)))?;
    let c = *model.config();
    let episodes = Episodes::load(&args.episodes).map_err(|e| format!("episodes: {}", report(&e)))?;
    let data = encode(&model, &episodes, args.threads as usize, "episodes")?;
    let (mean, std) = match model.actions() {
        Some(specs) => ([specs[0].mean, specs[1].mean], [specs[0].std, specs[1].std]),
        None => (DEFAULT_MEAN, DEFAULT_STD),
    };
    std::fs::create_dir_all(&args.out).map_err(|e| format!("cannot create {}: {e}", args.out.display()))?;
    let (z, window) = (c.z_dim, args.window as usize);
    let (mut all_found, mut all_want) = ([Vec::new(), Vec::new()], [Vec::new(), Vec::new()]);
    println!("episode  frames   speed: corr  mean error   steering: corr  mean error");
    for (e, Encoded { codes, actions, .. }) in data.iter().enumerate() {
        let frames = codes.len() / z;
        let windows = frames.saturating_sub(1) / (window - 1);
        if windows == 0 {
            continue;
        }
        // Window w holds frames w (T - 1) ..= (w + 1)(T - 1): consecutive windows share a frame.
        let mut batch_codes = Vec::with_capacity(windows * window * z);
        for w in 0..windows {
            batch_codes.extend_from_slice(&codes[w * (window - 1) * z..][..window * z]);
        }
        let steps = windows * (window - 1);
        let plan = TransitionPlan::for_model(&model, windows, window).map_err(|e| e.to_string())?;
        let settings = TransitionSettings {
            teacher: window,
            ..TransitionSettings::default()
        };
        let mut trainer = TransitionTrainer::new(&model, &plan, settings)
            .and_then(|t| t.with_threads(args.threads as usize))
            .map_err(|e| e.to_string())?;
        // The search runs on actions in standard deviations from the mean, as the model was
        // trained on them: a step of `lr` moves speed and steering alike.
        let mut units = vec![0.0f32; steps * 2];
        let (mut raw, mut grad) = (vec![0.0f32; steps * 2], vec![0.0f32; steps * 2]);
        let (mut m, mut v) = (vec![0.0; steps * 2], vec![0.0; steps * 2]);
        let adam = Adam::default();
        let mut loss = 0.0;
        for iteration in 1..=args.iterations {
            for (i, (r, u)) in raw.iter_mut().zip(&units).enumerate() {
                *r = mean[i % 2] + std[i % 2] * u;
            }
            loss = trainer
                .action_gradients(&batch_codes, &raw, &mut grad)
                .map_err(|e| e.to_string())?;
            for (i, g) in grad.iter_mut().enumerate() {
                *g *= std[i % 2];
            }
            smoothness(&units, args.smooth, &mut grad);
            adam.update(iteration, args.lr, 1.0, &mut units, &grad, [&mut m, &mut v]);
        }
        let mut row = format!("{e:>7}  {frames:>6}");
        let mut series = Vec::new();
        for j in 0..2 {
            let found: Vec<f64> = units
                .iter()
                .skip(j)
                .step_by(2)
                .map(|&u| (mean[j] + std[j] * u) as f64)
                .collect();
            let want: Vec<f64> = actions
                .iter()
                .skip(j)
                .step_by(2)
                .take(steps)
                .map(|&a| a as f64)
                .collect();
            let (corr, err) = agreement(&found, &want);
            row += &format!("   {:>11.3}  {err:>10.3}", corr);
            all_found[j].extend_from_slice(&found);
            all_want[j].extend_from_slice(&want);
            series.push((want, found));
        }
        println!("{row}   (final loss {loss:.4})");
        let path = args.out.join(format!("actions_{e}.png"));
        let (w, h, rgb) = plot(&series);
        write_png(&path, w, h, &rgb)?;
    }
    let mut row = String::from("    all        ");
    for j in 0..2 {
        let (corr, err) = agreement(&all_found[j], &all_want[j]);
        row += &format!("   {corr:>11.3}  {err:>10.3}");
    }
    println!("{row}");
    println!(
        "plots: {}/actions_*.png (recorded white, recovered orange; speed above, steering below)",
        args.out.display()
    );
    Ok(())
}

/// Adds the gradient of `weight` times the mean squared change between consecutive actions
/// (pairs of values, each action its own sequence) to `grad`.
fn smoothness(units: &[f32], weight: f32, grad: &mut [f32]) {
    let scale = 2.0 * weight / (units.len() / 2).max(1) as f32;
    for i in 2..units.len() {
        let change = units[i] - units[i - 2];
        grad[i] += scale * change;
        grad[i - 2] -= scale * change;
    }
}

/// One panel per action, stacked: the recorded and the recovered series over time, each panel
/// scaled to the range of both.
fn plot(series: &[(Vec<f64>, Vec<f64>)]) -> (usize, usize, Vec<u8>) {
    const PANEL_H: usize = 160;
    let len = series.first().map_or(0, |s| s.0.len());
    let (w, h) = ((2 * len).max(200), PANEL_H * series.len());
    let mut rgb = vec![24u8; w * h * 3];
    for (p, (want, found)) in series.iter().enumerate() {
        let (lo, hi) = want
            .iter()
            .chain(found)
            .fold((f64::MAX, f64::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        let span = (hi - lo).max(1e-9);
        let y_of = |v: f64| p * PANEL_H + 4 + ((hi - v) / span * (PANEL_H - 8) as f64) as usize;
        for x in 0..w {
            let at = ((p * PANEL_H) * w + x) * 3;
            rgb[at..at + 3].copy_from_slice(&[90, 90, 90]); // panel border
        }
        for (values, colour) in [(want, [235u8, 235, 235]), (found, [255u8, 150, 40])] {
            for (i, pair) in values.windows(2).enumerate() {
                let (y0, y1) = (y_of(pair[0]), y_of(pair[1]));
                for y in y0.min(y1)..=y0.max(y1) {
                    for x in [2 * i, 2 * i + 1] {
                        let at = (y.min(h - 1) * w + x.min(w - 1)) * 3;
                        rgb[at..at + 3].copy_from_slice(&colour);
                    }
                }
            }
        }
    }
    (w, h, rgb)
}
