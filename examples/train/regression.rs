//! Fitting a head on examples (`train policy`, `train heads`): batches drawn in a seeded order,
//! Adam at a cosine learning rate, checkpoints a killed run resumes from bit for bit.

use crate::args::Data;
use crate::checkpoint::Checkpointing;
use crate::common::bar;
use drivesim::train::{cosine_lr, HeadSettings, HeadTrainer, TrainedOn};
use drivesim::{HeadKind, Model, Simulator};
use std::path::Path;
use std::time::Instant;

/// A head's examples: its input `[z | h]` per example and `outputs` targets per example.
pub struct Examples {
    pub inputs: Vec<f32>,
    pub targets: Vec<f32>,
    pub outputs: usize,
}

impl Examples {
    pub fn new(outputs: usize) -> Examples {
        Examples {
            inputs: Vec::new(),
            targets: Vec::new(),
            outputs,
        }
    }

    pub fn len(&self) -> usize {
        self.targets.len() / self.outputs
    }

    /// Each target's mean and standard deviation (1 where the targets do not vary): the units
    /// a head trains in.
    pub fn units(&self) -> Vec<(f32, f32)> {
        let n = self.len().max(1) as f64;
        (0..self.outputs)
            .map(|k| {
                let column = || self.targets.iter().skip(k).step_by(self.outputs).map(|&v| v as f64);
                let mean = column().sum::<f64>() / n;
                let var = column().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
                let std = if var > 1e-12 { var.sqrt() } else { 1.0 };
                (mean as f32, std as f32)
            })
            .collect()
    }
}

/// The model's head of `kind` on every example's input: `kind.outputs` values per example.
pub fn predict(model: &Model, kind: HeadKind, examples: &Examples) -> Result<Vec<f32>, String> {
    let c = model.config();
    let (cols, outputs) = (c.z_dim + c.hidden_dim, kind.outputs(c));
    const BATCH: usize = 256;
    let mut sim = Simulator::with_batch(model, BATCH).map_err(|e| e.to_string())?;
    let (mut z, mut h, mut out) = (Vec::new(), Vec::new(), Vec::with_capacity(examples.len() * outputs));
    for rows in examples.inputs.chunks(BATCH * cols) {
        z.clear();
        h.clear();
        for row in rows.chunks_exact(cols) {
            z.extend_from_slice(&row[..c.z_dim]);
            h.extend_from_slice(&row[c.z_dim..]);
        }
        let at = out.len();
        out.resize(at + rows.len() / cols * outputs, 0.0);
        let o = &mut out[at..];
        match kind {
            HeadKind::Policy => sim.act(&z, &h, o),
            HeadKind::Reward => sim.reward(&z, &h, o),
            HeadKind::Value => sim.value(&z, &h, o),
            HeadKind::Pace => sim.pace(&z, &h, o),
        }
        .map_err(|e| e.to_string())?;
    }
    Ok(out)
}

/// Root mean squared error of each output of the model's head of `kind` on `examples`.
pub fn rms_errors(model: &Model, kind: HeadKind, examples: &Examples) -> Result<Vec<f64>, String> {
    let k = examples.outputs;
    let mut sums = vec![0.0f64; k];
    for (i, (o, w)) in predict(model, kind, examples)?
        .iter()
        .zip(&examples.targets)
        .enumerate()
    {
        sums[i % k] += ((o - w) as f64).powi(2);
    }
    let n = examples.len().max(1) as f64;
    Ok(sums.iter().map(|s| (s / n).sqrt()).collect())
}

/// The flags of a head's fit, shared by `train policy` and `train heads`.
#[derive(clap::Args)]
pub struct FitFlags {
    #[arg(long, default_value_t = 4000)]
    pub steps: usize,
    /// Examples (frames) per step
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub batch: u32,
    /// Peak learning rate (cosine decay to zero)
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f32,
    /// Units of the head's hidden layer (a new head; one the file has keeps its own)
    #[arg(long, default_value_t = 64)]
    pub width: usize,
    /// Start a new head even where the file has one
    #[arg(long)]
    pub restart: bool,
    /// Threads that encode the frames
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub threads: u32,
    /// Seed of the new head's weights and of the order of the examples
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub checkpointing: Checkpointing,
}

impl FitFlags {
    /// The trainer's settings: a new head (seeded) with `--restart` or where `has_head` is false.
    pub fn settings(&self, has_head: bool) -> HeadSettings {
        HeadSettings {
            width: self.width,
            batch: self.batch as usize,
            restart: (self.restart || !has_head).then_some(self.seed),
            ..HeadSettings::default()
        }
    }

    /// The arguments that decide a run (and so its checkpoints): the data, these flags and
    /// the command's own (`head`, before the flags, and `own`, after them); not the threads,
    /// which change no bit, nor the checkpointing itself. The words are those checkpoints
    /// already written hold: changing them would refuse every old checkpoint.
    pub fn run_arguments(&self, data: &Data, head: Option<&str>, own: &str) -> String {
        let (d, head) = (data, head.map(|h| format!(" head {h}")).unwrap_or_default());
        format!(
            "weights {:?} episodes {:?} heldout {:?} holdout {}{head} steps {} batch {} lr {} width {}{own} no_mirror {} restart {} seed {}",
            d.weights, d.episodes, d.heldout, d.holdout, self.steps, self.batch, self.lr, self.width,
            d.no_mirror, self.restart, self.seed
        )
    }

    /// How `command`'s fit runs, `arguments` deciding its checkpoints.
    pub fn run<'a>(&'a self, command: &'a str, arguments: String) -> Run<'a> {
        Run {
            steps: self.steps,
            batch: self.batch as usize,
            lr: self.lr,
            seed: self.seed,
            checkpoints: &self.checkpointing,
            command,
            arguments,
        }
    }
}

/// How a fit runs.
pub struct Run<'a> {
    pub steps: usize,
    pub batch: usize,
    pub lr: f32,
    pub seed: u64,
    pub checkpoints: &'a Checkpointing,
    /// The command and the arguments that decide the run, as its checkpoints record them.
    pub command: &'a str,
    pub arguments: String,
}

/// Recomputes the targets from the head as trained so far (TD(λ)'s returns), every `every`
/// steps from the first; checkpoints are then written only where targets are recomputed, so
/// that a resumed run recomputes what the run never stopped did.
pub struct Refresh<'a> {
    pub every: usize,
    pub targets: &'a mut dyn FnMut(&HeadTrainer, &mut Examples) -> Result<(), String>,
}

/// The fit's end: the trained head into the weight file `bytes` (its `trained_on` recorded),
/// `report` on the trained model ("after"), the file written atomically to `out`.
pub fn write_trained(
    trainer: &HeadTrainer,
    bytes: &[u8],
    trained_on: TrainedOn,
    started: Instant,
    mut report: impl FnMut(&Model, &str) -> Result<(), String>,
    out: &Path,
) -> Result<(), String> {
    let written = trainer.weight_file(bytes, trained_on).map_err(|e| e.to_string())?;
    let trained = Model::from_bytes(&written).map_err(|e| e.to_string())?;
    println!("trained in {:.1} s", started.elapsed().as_secs_f64());
    report(&trained, "after")?;
    crate::files::write_atomically(out, &written)?;
    println!("wrote {}", out.display());
    Ok(())
}

/// Trains `trainer` on `examples` for `run.steps` Adam steps (from a checkpoint, with
/// `--resume`). Prints the loss every 500 steps in the progress bar.
pub fn fit(
    trainer: &mut HeadTrainer,
    examples: &mut Examples,
    run: &Run,
    mut refresh: Option<Refresh>,
) -> Result<(), String> {
    let count = examples.len();
    if count == 0 {
        return Err("no examples to train on".into());
    }
    let (cols, outputs) = (examples.inputs.len() / count, examples.outputs);
    let batch = run.batch.min(count);
    let mut first_step = 0;
    if let Some((step, draw)) = run
        .checkpoints
        .restore(run.command, &run.arguments, |s| trainer.load_state(s))?
    {
        first_step = step;
        if Order::after(count, run.seed, step * batch).state != draw {
            return Err("the checkpoint's order of the examples is not this data's: other episodes?".into());
        }
    }
    let mut order = Order::after(count, run.seed, first_step * batch);
    let mut state = run.checkpoints.buffer(trainer.state_len());
    let (mut inputs, mut targets, mut loss_sum) = (Vec::new(), Vec::new(), 0.0);
    let progress = bar(
        run.steps as u64,
        "training: {pos}/{len} steps ({per_sec}, {eta} left) {msg}",
    );
    progress.set_position(first_step as u64);
    for step in first_step..run.steps {
        if let Some(refresh) = refresh.as_mut().filter(|r| step % r.every == 0) {
            (refresh.targets)(trainer, examples)?;
        }
        inputs.clear();
        targets.clear();
        for _ in 0..batch {
            let i = order.draw();
            inputs.extend_from_slice(&examples.inputs[i * cols..][..cols]);
            targets.extend_from_slice(&examples.targets[i * outputs..][..outputs]);
        }
        let lr = cosine_lr(run.lr, step, run.steps);
        loss_sum += trainer.step(&inputs, &targets, lr).map_err(|e| e.to_string())?;
        if (step + 1) % 500 == 0 {
            progress.set_message(format!("loss {:.4}", loss_sum / 500.0));
            loss_sum = 0.0;
        }
        progress.inc(1);
        let at_refresh = refresh.as_ref().is_none_or(|r| (step + 1) % r.every == 0);
        if at_refresh && run.checkpoints.due(step + 1, run.steps) {
            trainer.save_state(&mut state).map_err(|e| e.to_string())?;
            run.checkpoints
                .save(run.command, &run.arguments, step + 1, order.state, &state)?;
        }
    }
    progress.finish_and_clear();
    Ok(())
}

/// The order the examples are drawn in: each pass over them a new shuffle, from a seeded
/// generator (SplitMix64).
struct Order {
    order: Vec<usize>,
    next: usize,
    state: u64,
}

impl Order {
    /// The order after `drawn` examples of `count` were drawn, from `seed`: the shuffles of the
    /// passes begun replayed, so that a resumed run draws what the run never stopped would.
    fn after(count: usize, seed: u64, drawn: usize) -> Order {
        let mut order = Order {
            order: (0..count).collect(),
            next: count,
            state: seed,
        };
        let passes = drawn.div_ceil(count);
        for _ in 0..passes {
            order.shuffle();
        }
        if passes > 0 {
            order.next = drawn - (passes - 1) * count;
        }
        order
    }

    fn shuffle(&mut self) {
        for i in (1..self.order.len()).rev() {
            self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut x = self.state;
            x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            self.order.swap(i, ((x ^ (x >> 31)) % (i as u64 + 1)) as usize);
        }
    }

    fn draw(&mut self) -> usize {
        if self.next == self.order.len() {
            self.shuffle();
            self.next = 0;
        }
        self.next += 1;
        self.order[self.next - 1]
    }
}
