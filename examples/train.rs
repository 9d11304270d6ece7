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
//! cargo run --release --features train --example train -- step --stage transition|vae-gan \
//!     --weights W.safetensors --batch B.safetensors --out O.safetensors [--lr ...] [--teacher 5] [--clip 1.0]
//! ```
//! `vae-gan` trains the encoder and generator with a discriminator as `weights/train.py fit`'s
//! first stage does, measures held-out reconstruction PSNR every `--every` steps, and writes
//! the weights (discriminator included, so a run resumes from its `--out`; Adam's moments
//! start again). `fit` runs both stages, as `weights/tool train fit` does.
//! `transition` encodes the episodes with the crate's encoder, trains (or fine-tunes) the
//! transition on windows of 15 codes as `weights/train.py` does, reports the held-out latent
//! error before and after, and writes a weight file `Model::load` reads. `step` is the
//! verification mode: one step on a given batch, writing the loss, every gradient and the
//! updated tensors (the file formats are in `weights/README.md`), as `weights/tool train step`
//! does in PyTorch.

#[path = "common.rs"]
mod common;
#[path = "train_vae_gan.rs"]
mod vae_gan;

use clap::{Parser, Subcommand, ValueEnum};
use common::{bar, encode, Encoded};
use drivesim::train::{cosine_lr, TrainedOn, TransitionPlan, TransitionSettings, TransitionTrainer, VaeGanSettings};
use drivesim::{ActionSpec, Episodes, Model, WeightDtype};
use safetensors::{Dtype, SafeTensors};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Parser)]
#[command(about = "Train drivesim's transition model on the CPU, or run one verifiable step")]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train or fine-tune the transition on episodes, report held-out errors, write weights
    Transition(TransitionArgs),
    /// Train or fine-tune the encoder and generator as a VAE-GAN on episodes' frames
    VaeGan(vae_gan::VaeGanArgs),
    /// Both stages, as `weights/tool train fit`: the VAE-GAN, then the transition on its codes
    Fit(FitArgs),
    /// One step on a batch file; write the loss, gradients and updated tensors
    Step(StepArgs),
}

#[derive(Parser)]
struct TransitionArgs {
    /// Weight file to start from (its encoder encodes the episodes)
    #[arg(long)]
    weights: PathBuf,
    /// Episodes to train on (weights/tool record writes them)
    #[arg(long)]
    episodes: PathBuf,
    /// Episodes to evaluate on; without it, the last --holdout episodes of --episodes
    #[arg(long)]
    heldout: Option<PathBuf>,
    /// Episodes of --episodes held out when there is no --heldout file
    #[arg(long, default_value_t = 1)]
    holdout: usize,
    /// Where to write the trained weights
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 2000)]
    steps: usize,
    /// Windows per step
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=65536))]
    batch: u32,
    /// Codes per window
    #[arg(long, default_value_t = 15, value_parser = clap::value_parser!(u32).range(2..=4096))]
    window: u32,
    /// Inputs of each window taken from the data before the model's own predictions
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    teacher: u32,
    /// Peak learning rate (cosine decay to zero)
    #[arg(long, default_value_t = 1e-3)]
    lr: f32,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    threads: u32,
    /// Back-propagate through fed-back predictions (the paper detaches them)
    #[arg(long)]
    full_bptt: bool,
    /// Start the transition from seeded random weights (`Model::random`'s draw) instead of the
    /// file's: training from scratch, the encoder still the file's
    #[arg(long)]
    restart: bool,
    /// Dtype of the written file (default: the input file's)
    #[arg(long)]
    dtype: Option<DtypeArg>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

#[derive(Parser)]
struct FitArgs {
    /// Weight file to start from (or, with --from-scratch, whose config to train)
    #[arg(long)]
    weights: PathBuf,
    #[arg(long)]
    episodes: PathBuf,
    #[arg(long)]
    heldout: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    holdout: usize,
    /// Where to write the weights (the autoencoder stage's go beside it, OUT.autoencoder.safetensors)
    #[arg(long)]
    out: PathBuf,
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
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    threads: u32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Dtype of the written file (default: the input file's)
    #[arg(long)]
    dtype: Option<DtypeArg>,
}

/// `fit`: the VAE-GAN stage into OUT.autoencoder.safetensors (f32), then the transition from it.
fn fit(args: &FitArgs) -> Result<(), String> {
    let autoencoder = args.out.with_extension("autoencoder.safetensors");
    let defaults = VaeGanSettings::default();
    vae_gan::vae_gan(&vae_gan::VaeGanArgs {
        weights: args.weights.clone(),
        episodes: args.episodes.clone(),
        heldout: args.heldout.clone(),
        holdout: args.holdout,
        out: autoencoder.clone(),
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
    })?;
    transition(&TransitionArgs {
        weights: autoencoder,
        episodes: args.episodes.clone(),
        heldout: args.heldout.clone(),
        holdout: args.holdout,
        out: args.out.clone(),
        steps: args.transition_steps,
        batch: args.transition_batch,
        window: 15,
        teacher: 5,
        lr: args.transition_lr,
        threads: args.threads,
        full_bptt: false,
        restart: args.from_scratch,
        dtype: args.dtype,
        seed: args.seed,
    })
}

#[derive(Clone, Copy, ValueEnum)]
enum DtypeArg {
    F32,
    F16,
}

#[derive(Clone, Copy, ValueEnum)]
enum Stage {
    Transition,
    VaeGan,
}

/// The weight dtype asked for, if any.
fn dtype(arg: Option<DtypeArg>) -> Option<WeightDtype> {
    arg.map(|d| match d {
        DtypeArg::F32 => WeightDtype::F32,
        DtypeArg::F16 => WeightDtype::F16,
    })
}

#[derive(Parser)]
struct StepArgs {
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

fn main() -> ExitCode {
    common::exit(match Args::parse().command {
        Command::Transition(args) => transition(&args),
        Command::VaeGan(args) => vae_gan::vae_gan(&args),
        Command::Fit(args) => fit(&args),
        Command::Step(args) => step(&args),
    })
}

fn read(path: &Path) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

/// A float32 tensor of a safetensors file: shape and values.
fn f32_tensor(file: &SafeTensors<'_>, name: &str, path: &Path) -> Result<(Vec<usize>, Vec<f32>), String> {
    let view = file
        .tensor(name)
        .map_err(|_| format!("{}: no tensor `{name}`", path.display()))?;
    if view.dtype() != Dtype::F32 {
        return Err(format!(
            "{}: `{name}` is {:?}, expected F32",
            path.display(),
            view.dtype()
        ));
    }
    Ok((view.shape().to_vec(), bytemuck::pod_collect_to_vec(view.data())))
}

fn step(args: &StepArgs) -> Result<(), String> {
    match args.stage {
        Stage::Transition => step_transition(args),
        Stage::VaeGan => vae_gan::step(args),
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
    let plan = TransitionPlan::new(&c, b, t).map_err(|e| e.to_string())?;
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

/// Writes named float32 tensors as a safetensors file.
fn write_f32(path: &Path, tensors: &[(String, Vec<usize>, Vec<f32>)]) -> Result<(), String> {
    let views = tensors
        .iter()
        .map(|(name, shape, values)| {
            safetensors::tensor::TensorView::new(Dtype::F32, shape.clone(), bytemuck::cast_slice(values))
                .map(|view| (name.clone(), view))
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("{e:?}"))?;
    safetensors::serialize_to_file(views, None, path).map_err(|e| format!("cannot write {}: {e:?}", path.display()))
}

/// Every window of `window` consecutive frames inside one episode: (episode, first frame).
fn windows(data: &[Encoded], z: usize, window: usize) -> Vec<(usize, usize)> {
    let mut starts = Vec::new();
    for (e, episode) in data.iter().enumerate() {
        let frames = episode.codes.len() / z;
        starts.extend((0..(frames + 1).saturating_sub(window)).map(|s| (e, s)));
    }
    starts
}

/// Copies the windows `which` into batch buffers: codes [B, T, z], actions [B, T-1, a].
fn gather(
    data: &[Encoded],
    which: &[(usize, usize)],
    (z, a, window): (usize, usize, usize),
    codes: &mut Vec<f32>,
    actions: &mut Vec<f32>,
) {
    codes.clear();
    actions.clear();
    for &(e, s) in which {
        codes.extend_from_slice(&data[e].codes[s * z..(s + window) * z]);
        actions.extend_from_slice(&data[e].actions[s * a..(s + window - 1) * a]);
    }
}

/// Held-out latent errors, each the mean over windows and code values.
struct Report {
    one_step: f64,
    ten_step: f64,
    copy_one: f64,
    copy_ten: f64,
    mean_one: f64,
    mean_ten: f64,
}

/// Predicts every held-out window (teacher-forced for `teacher` inputs, then fed back) and
/// measures the first fed-back prediction and the one `window - 1 - teacher` steps later
/// against copying the last true code and against the training data's mean code.
fn evaluate(
    trainer: &mut TransitionTrainer<'_>,
    data: &[Encoded],
    starts: &[(usize, usize)],
    mean_code: &[f32],
    (z, a, window, teacher, batch): (usize, usize, usize, usize, usize),
) -> Result<Report, String> {
    let (first, last) = (teacher - 1, window - 2); // prediction index: code first + 1, last + 1
    let mut sums = [0.0f64; 6];
    let (mut codes, mut actions) = (Vec::new(), Vec::new());
    let mut predictions = vec![0.0; batch * (window - 1) * z];
    for chunk in starts.chunks(batch) {
        gather(data, chunk, (z, a, window), &mut codes, &mut actions);
        let p = &mut predictions[..chunk.len() * (window - 1) * z];
        trainer.predict(&codes, &actions, p).map_err(|e| e.to_string())?;
        for n in 0..chunk.len() {
            let code = |t: usize| &codes[(n * window + t) * z..][..z];
            let predicted = |t: usize| &p[(n * (window - 1) + t) * z..][..z];
            let se = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>();
            let (one, ten) = (code(first + 1), code(last + 1));
            for (sum, value) in sums.iter_mut().zip([
                se(predicted(first), one),
                se(predicted(last), ten),
                se(code(first), one),
                se(code(first), ten),
                se(mean_code, one),
                se(mean_code, ten),
            ]) {
                *sum += value;
            }
        }
    }
    let values = (starts.len() * z) as f64;
    let [one_step, ten_step, copy_one, copy_ten, mean_one, mean_ten] = sums.map(|s| s / values);
    Ok(Report {
        one_step,
        ten_step,
        copy_one,
        copy_ten,
        mean_one,
        mean_ten,
    })
}

/// Each action's mean, standard deviation (unbiased, as torch.std) and range over the data,
/// named and with units as `known` (the starting model's metadata) or as episodes files hold
/// them: (speed, steering), in the recording's units.
fn action_specs(data: &[Encoded], known: Option<&[ActionSpec]>) -> Vec<ActionSpec> {
    let a = Episodes::ACTION_DIM;
    let (mut sum, mut sq) = (vec![0.0f64; a], vec![0.0f64; a]);
    let (mut min, mut max) = (vec![f32::INFINITY; a], vec![f32::NEG_INFINITY; a]);
    let mut n = 0usize;
    for action in data.iter().flat_map(|e| e.actions.chunks_exact(a)) {
        for (j, &v) in action.iter().enumerate() {
            sum[j] += v as f64;
            sq[j] += (v as f64).powi(2);
            min[j] = min[j].min(v);
            max[j] = max[j].max(v);
        }
        n += 1;
    }
    let n = n.max(2) as f64;
    (0..a)
        .map(|j| {
            let mean = sum[j] / n;
            let std = ((sq[j] - n * mean * mean) / (n - 1.0)).max(0.0).sqrt().max(1e-6);
            let (name, unit) = match known {
                Some(specs) => (specs[j].name.clone(), specs[j].unit.clone()),
                None => (["speed", "steering"][j].to_string(), "as recorded".to_string()),
            };
            ActionSpec {
                name,
                unit,
                mean: mean as f32,
                std: std as f32,
                min: min[j],
                max: max[j],
            }
        })
        .collect()
}

/// A small xorshift generator: window draws reproducible from `--seed`.
struct Draw(u64);

impl Draw {
    fn below(&mut self, n: usize) -> usize {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 % n as u64) as usize
    }
}

fn transition(args: &TransitionArgs) -> Result<(), String> {
    let original = read(&args.weights)?;
    let model = Model::from_bytes(&original).map_err(|e| format!("{}: {e}", args.weights.display()))?;
    let c = *model.config();
    let (z, a, window, teacher) = (c.z_dim, c.action_dim, args.window as usize, args.teacher as usize);
    let batch = args.batch as usize;
    let threads = args.threads as usize;
    if teacher >= window {
        return Err(format!(
            "--teacher {teacher}: it must be below --window {window}, so that predictions are fed back"
        ));
    }
    let load = |path: &PathBuf| Episodes::load(path).map_err(|e| format!("{}: {e}", path.display()));
    let all = load(&args.episodes)?;
    let frame_hz = all.frame_hz();
    let mut train = encode(&model, &all, threads, "episodes")?;
    let heldout = match &args.heldout {
        Some(path) => encode(&model, &load(path)?, threads, "held-out episodes")?,
        None if args.holdout < train.len() => train.split_off(train.len() - args.holdout),
        None => return Err(format!("--holdout {} leaves no training episode", args.holdout)),
    };
    let (train_starts, heldout_starts) = (windows(&train, z, window), windows(&heldout, z, window));
    if train_starts.is_empty() || heldout_starts.is_empty() {
        return Err(format!(
            "no window of {window} frames in the training or held-out episodes"
        ));
    }
    let mut mean_code = vec![0.0f32; z];
    let frames: usize = train.iter().map(|e| e.codes.len() / z).sum();
    for code in train.iter().flat_map(|e| e.codes.chunks_exact(z)) {
        mean_code
            .iter_mut()
            .zip(code)
            .for_each(|(m, c)| *m += c / frames as f32);
    }

    let plan = TransitionPlan::new(&c, batch, window).map_err(|e| e.to_string())?;
    println!(
        "{} training windows in {} episodes, {} held out; arena {:.2} MiB",
        train_starts.len(),
        train.len(),
        heldout_starts.len(),
        plan.bytes() as f64 / (1 << 20) as f64
    );
    let settings = TransitionSettings {
        teacher,
        full_bptt: args.full_bptt,
        ..TransitionSettings::default()
    };
    let model_actions = model.actions().map(<[ActionSpec]>::to_vec);
    let start = match args.restart {
        true => Model::random(&c, args.seed, WeightDtype::F32).map_err(|e| e.to_string())?,
        false => model,
    };
    let mut trainer = TransitionTrainer::new(&start, &plan, settings)
        .and_then(|t| t.with_threads(threads))
        .map_err(|e| e.to_string())?;
    drop(start);
    let specs = action_specs(&train, model_actions.as_deref());
    let (mean, std): (Vec<f32>, Vec<f32>) = specs.iter().map(|s| (s.mean, s.std)).unzip();
    trainer
        .set_action_normalisation(&mean, &std)
        .map_err(|e| e.to_string())?;
    let dims = (z, a, window, teacher, batch);
    let before = evaluate(&mut trainer, &heldout, &heldout_starts, &mean_code, dims)?;

    let progress = bar(
        args.steps as u64,
        "{bar:40} {pos}/{len} steps, {msg} ({per_sec}, {eta} left)",
    );
    let mut draw = Draw(args.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let (mut codes, mut actions) = (Vec::new(), Vec::new());
    let mut picked = vec![(0, 0); batch];
    let start = Instant::now();
    let (mut first, mut recent) = (0.0, 0.0);
    for step in 0..args.steps {
        picked
            .iter_mut()
            .for_each(|p| *p = train_starts[draw.below(train_starts.len())]);
        gather(&train, &picked, (z, a, window), &mut codes, &mut actions);
        let loss = trainer
            .step(&codes, &actions, cosine_lr(args.lr, step, args.steps))
            .map_err(|e| format!("step {step}: {e}"))?;
        if step == 0 {
            first = loss;
        }
        recent = if step == 0 { loss } else { 0.98 * recent + 0.02 * loss };
        progress.set_message(format!("loss {recent:.4}"));
        progress.inc(1);
    }
    progress.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();
    println!(
        "{} steps of {batch} windows in {seconds:.1} s ({:.1} steps/s), training loss {first:.4} at the first step, {recent:.4} at the end",
        args.steps,
        args.steps as f64 / seconds
    );
    let after = evaluate(&mut trainer, &heldout, &heldout_starts, &mean_code, dims)?;
    // Predictions from the last true code: the first, and the last of the window (10 steps
    // ahead for 15-code windows with 5 teacher-forced, as `train.py eval`'s "10-step").
    let ahead = window - teacher;
    println!(
        "held-out latent MSE ({} windows)    before      after   copy last   mean code",
        heldout_starts.len()
    );
    println!(
        "  1 step ahead                   {:>9.4}  {:>9.4}   {:>9.4}   {:>9.4}",
        before.one_step, after.one_step, after.copy_one, after.mean_one
    );
    println!(
        "  {ahead:>2} steps ahead                  {:>9.4}  {:>9.4}   {:>9.4}   {:>9.4}",
        before.ten_step, after.ten_step, after.copy_ten, after.mean_ten
    );

    let dtype = dtype(args.dtype);
    let bytes = trainer
        .weight_file(
            &original,
            dtype,
            TrainedOn {
                actions: Some(&specs),
                frame_hz,
            },
        )
        .map_err(|e| e.to_string())?;
    Model::from_bytes(&bytes).map_err(|e| format!("the written file does not load: {e}"))?;
    std::fs::write(&args.out, &bytes).map_err(|e| format!("cannot write {}: {e}", args.out.display()))?;
    println!("wrote {}", args.out.display());
    Ok(())
}
