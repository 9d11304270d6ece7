//! `train vae-gan`: fine-tune or train the encoder and generator on episodes' frames, as a
//! VAE-GAN, measuring the held-out reconstruction PSNR as it goes.

use crate::args::{data_help, dtype, Data, DtypeArg};
use crate::checkpoint::Checkpointing;
use crate::common::{bar, mirror, write_png, Gaussian};
use crate::files::read;
use clap::Parser;
use drivesim::train::{
    random_weight_file, TrainedOn, VaeGanLosses, VaeGanPlan, VaeGanSettings, VaeGanTrainer, VAE_GAN_LR,
};
use drivesim::{frames_to_rgb, Config, Episodes, Model, PixelLayout, Simulator};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Parser)]
#[command(mut_args = data_help(&[
    ("weights", concat!(
        "Weight file to start from: its encoder, generator and discriminator (`discriminator.*`, ",
        "seeded random ones if it has none); resume an interrupted run from its --out",
    )),
    ("episodes", "Episodes to train on (python -m drivesim record writes them)"),
    ("heldout", "Episodes to measure reconstruction on; without it, the last --holdout episodes of --episodes"),
    ("out", "Where to write the trained weights (every --every steps, and at the end)"),
]))]
pub struct VaeGanArgs {
    #[command(flatten)]
    pub data: Data,
    #[arg(long, default_value_t = 1000)]
    pub steps: usize,
    /// Frames per step
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub batch: u32,
    #[arg(long, default_value_t = VAE_GAN_LR)]
    pub lr: f32,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub threads: u32,
    /// Seed of the batches, the reparametrisation draws and the prior samples
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Stop after this many minutes (what was trained is written)
    #[arg(long)]
    pub minutes: Option<f64>,
    /// Measure held-out PSNR and write --out every this many steps
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u64).range(1..))]
    pub every: u64,
    /// Write a contact sheet of held-out frames (top) and their reconstructions (bottom)
    #[arg(long)]
    pub sheet: Option<PathBuf>,
    /// Start from seeded random weights of --weights' config (training from scratch)
    #[arg(long)]
    pub from_scratch: bool,
    /// Dtype of the written tensors (default: --weights' own)
    #[arg(long, value_enum)]
    pub dtype: Option<DtypeArg>,
    /// Weight of the pixel L1 term (as train.py fit's --w-pixel)
    #[arg(long, default_value_t = VaeGanSettings::default().pixel)]
    pub w_pixel: f32,
    /// Weight of the discriminator-feature term
    #[arg(long, default_value_t = VaeGanSettings::default().feature)]
    pub w_feature: f32,
    /// Weight of the KL prior
    #[arg(long, default_value_t = VaeGanSettings::default().kl)]
    pub w_kl: f32,
    /// Weight of the generator's GAN term
    #[arg(long, default_value_t = VaeGanSettings::default().gan)]
    pub w_gan: f32,
    #[command(flatten)]
    pub checkpointing: Checkpointing,
}

impl VaeGanArgs {
    /// The arguments that decide the run (and so its checkpoints): all but the threads, which
    /// change no bit, the time limit, the reports (`--every`, `--sheet`) and the checkpointing.
    fn run_arguments(&self) -> String {
        let d = &self.data;
        format!(
            "weights {:?} episodes {:?} heldout {:?} holdout {} no_mirror {} steps {} batch {} lr {} seed {} from_scratch {} \
             w_pixel {} w_feature {} w_kl {} w_gan {}",
            d.weights,
            d.episodes,
            d.heldout,
            d.holdout,
            d.no_mirror,
            self.steps,
            self.batch,
            self.lr,
            self.seed,
            self.from_scratch,
            self.w_pixel,
            self.w_feature,
            self.w_kl,
            self.w_gan
        )
    }
}

/// Frames of the held-out episodes spread evenly over them, at most this many.
const HELDOUT_FRAMES: usize = 64;
/// Held-out frames on the contact sheet.
const SHEET_FRAMES: usize = 8;

/// Every frame of `episodes` as f32 in [-1, 1], `[frames, H, W, 3]`, checked against `c`.
fn frames(episodes: &Episodes, c: &Config, what: &str) -> Result<Vec<f32>, String> {
    if episodes.frame_size() != (c.height, c.width) || c.channels != 3 {
        let (h, w) = episodes.frame_size();
        return Err(format!(
            "{what}: {h}x{w} RGB frames, the model takes {}x{} with {} channels",
            c.height, c.width, c.channels
        ));
    }
    let mut out = Vec::new();
    for i in 0..episodes.len() {
        let episode = episodes.episode(i).map_err(|e| e.to_string())?;
        let start = out.len();
        out.resize(start + episode.len() * c.frame_len(), 0.0);
        for (j, frame) in out[start..].chunks_exact_mut(c.frame_len()).enumerate() {
            episode.frame_f32(j, frame).map_err(|e| e.to_string())?;
        }
    }
    Ok(out)
}

/// Mean PSNR in dB of reconstructions (encoder mean, then generator) of `frames` by the
/// weights `bytes`, on the 0-255 scale as `weights/drivesim_reference/train.py` measures it; and the
/// reconstructions.
fn psnr(bytes: &[u8], frames: &[f32], threads: usize) -> Result<(f64, Vec<f32>), String> {
    let model = Model::from_bytes(bytes).map_err(|e| e.to_string())?;
    let c = *model.config();
    let n = frames.len() / c.frame_len();
    let mut sim = Simulator::with_batch(&model, n)
        .and_then(|s| s.with_threads(threads))
        .map_err(|e| e.to_string())?;
    let mut codes = vec![0.0; n * c.z_dim];
    let mut out = vec![0.0; frames.len()];
    sim.encode(frames, &mut codes).map_err(|e| e.to_string())?;
    sim.generate(&codes, &mut out).map_err(|e| e.to_string())?;
    let mut sum = 0.0;
    for (x, y) in frames.chunks_exact(c.frame_len()).zip(out.chunks_exact(c.frame_len())) {
        let mse = x
            .iter()
            .zip(y)
            .map(|(&x, &y)| ((y.clamp(-1.0, 1.0) - x) as f64 * 127.5).powi(2))
            .sum::<f64>()
            / x.len() as f64;
        sum += 10.0 * (255.0f64.powi(2) / mse.max(1e-10)).log10();
    }
    Ok((sum / n as f64, out))
}

/// Held-out frames (top row) over their reconstructions (bottom row), as a PNG.
fn sheet(path: &Path, c: &Config, frames: &[f32], recon: &[f32]) -> Result<(), String> {
    let n = (frames.len() / c.frame_len()).min(SHEET_FRAMES);
    let (w, h) = (c.width, c.height);
    let mut rgb = vec![0u8; 2 * h * n * w * 3];
    let mut one = vec![0u8; c.frame_len()];
    for (row, source) in [frames, recon].into_iter().enumerate() {
        for i in 0..n {
            frames_to_rgb(
                &source[i * c.frame_len()..][..c.frame_len()],
                PixelLayout::Hwc,
                c,
                &mut one,
            )
            .map_err(|e| e.to_string())?;
            for y in 0..h {
                let dst = ((row * h + y) * n * w + i * w) * 3;
                rgb[dst..dst + w * 3].copy_from_slice(&one[y * w * 3..][..w * 3]);
            }
        }
    }
    write_png(path, n * w, 2 * h, &rgb)
}

pub fn vae_gan(args: &VaeGanArgs) -> Result<(), String> {
    let original = read(&args.data.weights)?;
    let model = Model::from_bytes(&original).map_err(|e| format!("{}: {e}", args.data.weights.display()))?;
    let c = *model.config();
    drop(model);
    let start_file = match args.from_scratch {
        true => random_weight_file(&c, args.seed).map_err(|e| e.to_string())?,
        false => original.clone(),
    };
    let load = |path: &PathBuf| Episodes::load(path).map_err(|e| format!("{}: {e}", path.display()));
    let all = load(&args.data.episodes)?;
    let trained_on = TrainedOn {
        actions: None,
        frame_hz: all.frame_hz(),
        discount: None,
    };
    let (train, heldout) = match &args.data.heldout {
        Some(path) => (
            frames(&all, &c, "episodes")?,
            frames(&load(path)?, &c, "held-out episodes")?,
        ),
        None if args.data.holdout < all.len() => {
            let split: usize = (0..all.len() - args.data.holdout)
                .map(|i| all.episode(i).map_or(0, |e| e.len()))
                .sum();
            let mut train = frames(&all, &c, "episodes")?;
            let heldout = train.split_off(split * c.frame_len());
            (train, heldout)
        }
        None => return Err(format!("--holdout {} leaves no training episode", args.data.holdout)),
    };
    let (count, held) = (train.len() / c.frame_len(), heldout.len() / c.frame_len());
    let views = if args.data.no_mirror { 1 } else { 2 };
    if count == 0 || held == 0 {
        return Err("no training or no held-out frames".into());
    }
    // Held-out frames spread evenly over the held-out episodes.
    let picked: Vec<f32> = (0..held.min(HELDOUT_FRAMES))
        .flat_map(|i| heldout[i * held / held.min(HELDOUT_FRAMES) * c.frame_len()..][..c.frame_len()].to_vec())
        .collect();
    let (batch, threads) = (args.batch as usize, args.threads as usize);
    let plan = VaeGanPlan::new(&c, batch, threads).map_err(|e| e.to_string())?;
    println!(
        "{count} training frames, {} held-out frames measured; {} MiB planned for batch {batch}, {threads} thread(s)",
        picked.len() / c.frame_len(),
        plan.bytes() >> 20
    );
    let settings = VaeGanSettings {
        pixel: args.w_pixel,
        feature: args.w_feature,
        kl: args.w_kl,
        gan: args.w_gan,
        ..VaeGanSettings::default()
    };
    let mut trainer = VaeGanTrainer::new(&start_file, &plan, settings).map_err(|e| e.to_string())?;
    let dtype = dtype(args.dtype);
    let save = |trainer: &VaeGanTrainer| -> Result<Vec<u8>, String> {
        let bytes = trainer
            .weight_file(&original, dtype, trained_on)
            .map_err(|e| e.to_string())?;
        crate::files::write_atomically(&args.data.out, &bytes)?;
        Ok(bytes)
    };
    let (before, _) = psnr(
        &trainer
            .weight_file(&original, None, trained_on)
            .map_err(|e| e.to_string())?,
        &picked,
        threads,
    )?;
    println!("held-out reconstruction PSNR {before:.2} dB before training");

    let progress = bar(
        args.steps as u64,
        "{bar:30} {pos}/{len} steps, {msg} ({per_sec}, {eta} left)",
    );
    let mut draws = Gaussian(args.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x5eed);
    let (checkpoints, arguments) = (&args.checkpointing, args.run_arguments());
    let mut first_step = 0;
    if let Some((step, state)) = checkpoints.restore("vae-gan", &arguments, |s| trainer.load_state(s))? {
        (first_step, draws) = (step, Gaussian(state));
        progress.set_position(step as u64);
    }
    let mut state = checkpoints.buffer(trainer.state_len());
    let mut batch_frames = vec![0.0; batch * c.frame_len()];
    let (mut eps, mut prior) = (vec![0.0; batch * c.z_dim], vec![0.0; batch * c.z_dim]);
    let started = Instant::now();
    let mut recent = VaeGanLosses::default();
    let mut done = first_step;
    let mut last_psnr = before;
    for step in first_step..args.steps {
        if args.minutes.is_some_and(|m| started.elapsed().as_secs_f64() > 60.0 * m) {
            progress.println(format!("--minutes reached after {step} steps"));
            break;
        }
        for frame in batch_frames.chunks_exact_mut(c.frame_len()) {
            // Unless --no-mirror, the frames' mirror images are as likely as the frames.
            let i = ((draws.uniform() * (views * count) as f64) as usize).min(views * count - 1);
            frame.copy_from_slice(&train[i % count * c.frame_len()..][..c.frame_len()]);
            if i >= count {
                mirror(frame, c.width, c.channels);
            }
        }
        eps.iter_mut().chain(prior.iter_mut()).for_each(|v| *v = draws.next());
        let losses = trainer
            .step(&batch_frames, &eps, &prior, args.lr)
            .map_err(|e| format!("step {step}: {e}"))?;
        recent = if step == first_step {
            losses
        } else {
            smooth(recent, losses)
        };
        done = step + 1;
        progress.set_message(format!(
            "D {:.3} GAN {:.3} feature {:.3} L1 {:.4} KL {:.3}, held-out {last_psnr:.2} dB",
            recent.discriminator, recent.gan, recent.feature, recent.pixel_l1, recent.kl
        ));
        progress.inc(1);
        if ((step + 1) as u64).is_multiple_of(args.every) {
            last_psnr = psnr(&save(&trainer)?, &picked, threads)?.0;
        }
        if checkpoints.due(step + 1, args.steps) {
            trainer.save_state(&mut state).map_err(|e| e.to_string())?;
            checkpoints.save("vae-gan", &arguments, step + 1, draws.0, &state)?;
        }
    }
    progress.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    let bytes = save(&trainer)?;
    let (after, recon) = psnr(&bytes, &picked, threads)?;
    println!(
        "{done} steps of {batch} frames in {seconds:.0} s ({:.2} steps/s); losses at the end: D {:.3}, GAN {:.3}, \
         feature {:.3}, pixel L1 {:.4}, KL {:.3}",
        (done - first_step) as f64 / seconds,
        recent.discriminator,
        recent.gan,
        recent.feature,
        recent.pixel_l1,
        recent.kl
    );
    println!("held-out reconstruction PSNR {before:.2} dB before, {after:.2} dB after");
    if let Some(path) = &args.sheet {
        sheet(path, &c, &picked, &recon)?;
        println!("wrote {}", path.display());
    }
    println!("wrote {}", args.data.out.display());
    Ok(())
}

/// An exponential moving average of the losses, for the progress line.
fn smooth(a: VaeGanLosses, b: VaeGanLosses) -> VaeGanLosses {
    let s = |a: f32, b: f32| 0.95 * a + 0.05 * b;
    VaeGanLosses {
        discriminator: s(a.discriminator, b.discriminator),
        encoder: s(a.encoder, b.encoder),
        generator: s(a.generator, b.generator),
        gan: s(a.gan, b.gan),
        feature: s(a.feature, b.feature),
        pixel_l1: s(a.pixel_l1, b.pixel_l1),
        kl: s(a.kl, b.kl),
    }
}
