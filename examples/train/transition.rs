//! `train transition`: encode episodes with the model's encoder, train (or fine-tune) the
//! transition on windows of their codes, and report the held-out latent error before and after.

use crate::args::{data_help, dtype, Data, DtypeArg};
use crate::checkpoint::Checkpointing;
use crate::common::{bar, Encoded};
use crate::drives::{split, Drives};
use crate::files::read;
use clap::Parser;
use drivesim::train::{cosine_lr, TrainedOn, TransitionPlan, TransitionSettings, TransitionTrainer};
use drivesim::{ActionSpec, Episodes, Model, WeightDtype};
use std::time::Instant;

#[derive(Parser)]
#[command(mut_args = data_help(&[
    ("weights", "Weight file to start from (its encoder encodes the episodes)"),
    ("episodes", "Episodes to train on (python -m drivesim record writes them)"),
    ("heldout", "Episodes to evaluate on; without it, the last --holdout episodes of --episodes"),
    ("holdout", "Episodes of --episodes held out when there is no --heldout file"),
    ("out", "Where to write the trained weights"),
]))]
pub struct TransitionArgs {
    #[command(flatten)]
    pub data: Data,
    #[arg(long, default_value_t = 2000)]
    pub steps: usize,
    /// Windows per step
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub batch: u32,
    /// Codes per window
    #[arg(long, default_value_t = 15, value_parser = clap::value_parser!(u32).range(2..=4096))]
    pub window: u32,
    /// Inputs of each window taken from the data before the model's own predictions
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    pub teacher: u32,
    /// Peak learning rate (cosine decay to zero)
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f32,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub threads: u32,
    /// Back-propagate through fed-back predictions (the paper detaches them)
    #[arg(long)]
    pub full_bptt: bool,
    /// Start the transition from seeded random weights (`Model::random`'s draw) instead of the
    /// file's: training from scratch, the encoder still the file's
    #[arg(long)]
    pub restart: bool,
    /// Also train a spread head (the spread of each predicted code, which sampled futures draw
    /// from: `Simulator::set_sampling`); a file that has one trains its own
    #[arg(long)]
    pub spread: bool,
    /// Leave the spread head's noise independent across the code's dimensions: without it, the
    /// correlation of the one-step errors on the training drives is fitted (`transition.L`)
    #[arg(long)]
    pub independent_noise: bool,
    #[command(flatten)]
    pub noise_power: crate::noise::NoisePower,
    /// Dtype of the written file (default: the input file's)
    #[arg(long)]
    pub dtype: Option<DtypeArg>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub checkpointing: Checkpointing,
}

impl TransitionArgs {
    /// The arguments that decide the run (and so its checkpoints): all but the threads, which
    /// change no bit, and the checkpointing itself.
    fn run_arguments(&self) -> String {
        let d = &self.data;
        format!(
            "weights {:?} episodes {:?} heldout {:?} holdout {} no_mirror {} steps {} batch {} window {} teacher {} lr {} full_bptt {} restart {} spread {} seed {}",
            d.weights, d.episodes, d.heldout, d.holdout, d.no_mirror, self.steps, self.batch, self.window, self.teacher,
            self.lr, self.full_bptt, self.restart, self.spread, self.seed
        )
    }
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

pub fn transition(args: &TransitionArgs) -> Result<(), String> {
    let original = read(&args.data.weights)?;
    let model = Model::from_bytes(&original).map_err(|e| format!("{}: {e}", args.data.weights.display()))?;
    let c = *model.config();
    let (z, a, window, teacher) = (c.z_dim, c.action_dim, args.window as usize, args.teacher as usize);
    let batch = args.batch as usize;
    let threads = args.threads as usize;
    if teacher >= window {
        return Err(format!(
            "--teacher {teacher}: it must be below --window {window}, so that predictions are fed back"
        ));
    }
    let Drives {
        train,
        heldout,
        frame_hz,
    } = split(&model, &args.data, threads)?;
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

    let mut plan = TransitionPlan::new(&c, batch, window).map_err(|e| e.to_string())?;
    if args.spread || (model.samples() && !args.restart) {
        plan = plan.with_spread().map_err(|e| e.to_string())?;
    }
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
    let (checkpoints, arguments) = (&args.checkpointing, args.run_arguments());
    let mut first_step = 0;
    if let Some((step, state)) = checkpoints.restore("transition", &arguments, |s| trainer.load_state(s))? {
        (first_step, draw) = (step, Draw(state));
        progress.set_position(step as u64);
    }
    let mut state = checkpoints.buffer(trainer.state_len());
    let (mut codes, mut actions) = (Vec::new(), Vec::new());
    let mut picked = vec![(0, 0); batch];
    let start = Instant::now();
    let (mut first, mut recent) = (0.0, 0.0);
    for step in first_step..args.steps {
        picked
            .iter_mut()
            .for_each(|p| *p = train_starts[draw.below(train_starts.len())]);
        gather(&train, &picked, (z, a, window), &mut codes, &mut actions);
        let loss = trainer
            .step(&codes, &actions, cosine_lr(args.lr, step, args.steps))
            .map_err(|e| format!("step {step}: {e}"))?;
        if step == first_step {
            (first, recent) = (loss, loss);
        }
        recent = 0.98 * recent + 0.02 * loss;
        progress.set_message(format!("loss {recent:.4}"));
        progress.inc(1);
        if checkpoints.due(step + 1, args.steps) {
            trainer.save_state(&mut state).map_err(|e| e.to_string())?;
            checkpoints.save("transition", &arguments, step + 1, draw.0, &state)?;
        }
    }
    progress.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();
    println!(
        "{} steps of {batch} windows in {seconds:.1} s ({:.1} steps/s), training loss {first:.4} at the first step, {recent:.4} at the end",
        args.steps - first_step,
        (args.steps - first_step) as f64 / seconds
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
                discount: None,
            },
        )
        .map_err(|e| e.to_string())?;
    let written = Model::from_bytes(&bytes).map_err(|e| format!("the written file does not load: {e}"))?;
    let bytes = match written.samples() && !args.independent_noise {
        // Too few steps for the correlation must not cost the training: the file goes without.
        true => crate::noise::with_fitted_noise(&bytes, &written, &train, &args.noise_power).unwrap_or_else(|e| {
            eprintln!("warning: written without transition.L (independent sampled noise): {e}");
            bytes
        }),
        false => bytes,
    };
    crate::files::write_atomically(&args.data.out, &bytes)?;
    println!("wrote {}", args.data.out.display());
    Ok(())
}
