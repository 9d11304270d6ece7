//! `train policy`: behavioural cloning of the recorded driver. Encodes the episodes (and their
//! mirror images), steps the transition along each drive for the hidden state the policy reads,
//! trains the policy to give the driver's steering and the speed it reached `--lead` frames
//! later (or, where the episodes carry them, a teacher's `labels`: DAgger's), reports the held-out error before and after, and writes the weights with the policy.

use crate::args::{data_help, Data};
use crate::checkpoint::Checkpointing;
use crate::common::{bar, Encoded};
use crate::drives::split;
use crate::files::read;
use clap::Parser;
use drivesim::train::{cosine_lr, PolicySettings, PolicyTrainer};
use drivesim::{Model, Simulator};
use std::time::Instant;

#[derive(Parser)]
#[command(mut_args = data_help(&[
    ("weights", "Weight file to start from (its encoder and transition give the policy's input)"),
    ("episodes", "Episodes of the driver to clone (weights/tool record writes them)"),
    ("heldout", "Episodes to evaluate on; without it, the last --holdout episodes of --episodes"),
    ("holdout", "Episodes of --episodes held out when there is no --heldout file"),
    ("out", "Where to write the weights with the trained policy"),
]))]
pub struct PolicyArgs {
    #[command(flatten)]
    pub data: Data,
    #[arg(long, default_value_t = 4000)]
    pub steps: usize,
    /// Examples (frames) per step
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub batch: u32,
    /// Peak learning rate (cosine decay to zero)
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f32,
    /// Units of the policy's hidden layer (a new policy; one the file has keeps its own)
    #[arg(long, default_value_t = 64)]
    pub width: usize,
    /// The speed to learn is the one the driver reached this many frames later
    #[arg(long, default_value_t = 1)]
    pub lead: usize,
    /// Start a new policy even where the file has one
    #[arg(long)]
    pub restart: bool,
    /// Threads that encode the frames
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub threads: u32,
    /// Seed of the new policy's weights and of the order of the examples
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub checkpointing: Checkpointing,
}

impl PolicyArgs {
    /// The arguments that decide the run (and so its checkpoints): all but the threads, which
    /// change no bit, and the checkpointing itself.
    fn run_arguments(&self) -> String {
        let d = &self.data;
        format!(
            "weights {:?} episodes {:?} heldout {:?} holdout {} steps {} batch {} lr {} width {} lead {} no_mirror {} restart {} seed {}",
            d.weights, d.episodes, d.heldout, d.holdout, self.steps, self.batch, self.lr, self.width, self.lead,
            d.no_mirror, self.restart, self.seed
        )
    }
}

/// The policy's examples: inputs `[z | h]` and actions (speed `lead` frames later, steering),
/// or the episodes' labels where they have them.
struct Examples {
    inputs: Vec<f32>,
    actions: Vec<f32>,
}

/// The examples of encoded drives: the transition stepped along each from zeros, as the
/// policy's user steps it (`Simulator::act`'s documentation).
fn examples(model: &Model, drives: &[Encoded], lead: usize) -> Result<Examples, String> {
    let c = model.config();
    let (z, hd) = (c.z_dim, c.hidden_dim);
    let mut sim = Simulator::new(model).map_err(|e| e.to_string())?;
    let (mut inputs, mut actions) = (Vec::new(), Vec::new());
    let (mut h, mut next) = (vec![0.0; hd], vec![0.0; z]);
    for drive in drives {
        h.fill(0.0);
        let frames = drive.codes.len() / z;
        for t in 0..frames {
            let code = &drive.codes[t * z..][..z];
            // A teacher's label where the episodes have one (DAgger), else what the driver did.
            if let Some(labels) = &drive.labels {
                inputs.extend_from_slice(code);
                inputs.extend_from_slice(&h);
                actions.extend_from_slice(&labels[t * 2..][..2]);
            } else if t + lead < frames {
                inputs.extend_from_slice(code);
                inputs.extend_from_slice(&h);
                actions.extend_from_slice(&[drive.actions[(t + lead) * 2], drive.actions[t * 2 + 1]]);
            }
            let action = &drive.actions[t * 2..][..2];
            sim.transition(code, &mut h, action, &mut next)
                .map_err(|e| e.to_string())?;
        }
    }
    Ok(Examples { inputs, actions })
}

/// Root mean squared error of each action of the policy on `examples`, in the actions' units.
fn errors(model: &Model, examples: &Examples) -> Result<[f64; 2], String> {
    let c = model.config();
    let cols = c.z_dim + c.hidden_dim;
    const BATCH: usize = 256;
    let mut sim = Simulator::with_batch(model, BATCH).map_err(|e| e.to_string())?;
    let (mut sums, mut out) = ([0.0f64; 2], vec![0.0; BATCH * 2]);
    for (inputs, wanted) in examples
        .inputs
        .chunks(BATCH * cols)
        .zip(examples.actions.chunks(BATCH * 2))
    {
        let n = inputs.len() / cols;
        let (z, h): (Vec<f32>, Vec<f32>) = (
            inputs.chunks_exact(cols).flat_map(|r| r[..c.z_dim].to_vec()).collect(),
            inputs.chunks_exact(cols).flat_map(|r| r[c.z_dim..].to_vec()).collect(),
        );
        sim.act(&z, &h, &mut out[..n * 2]).map_err(|e| e.to_string())?;
        for (i, (o, w)) in out[..n * 2].iter().zip(wanted).enumerate() {
            sums[i % 2] += ((o - w) as f64).powi(2);
        }
    }
    let n = (examples.actions.len() / 2).max(1) as f64;
    Ok([(sums[0] / n).sqrt(), (sums[1] / n).sqrt()])
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

pub fn policy(args: &PolicyArgs) -> Result<(), String> {
    let bytes = read(&args.data.weights)?;
    let model = Model::from_bytes(&bytes).map_err(|e| format!("{}: {e}", args.data.weights.display()))?;
    let drives = split(&model, &args.data, args.threads as usize)?;
    let (train, heldout) = (drives.train, drives.heldout);
    let (train, heldout) = (
        examples(&model, &train, args.lead)?,
        examples(&model, &heldout, args.lead)?,
    );
    let settings = PolicySettings {
        width: args.width,
        batch: args.batch as usize,
        restart: (args.restart || model.policy_width().is_none()).then_some(args.seed),
        ..PolicySettings::default()
    };
    let mut trainer = PolicyTrainer::new(&model, settings).map_err(|e| e.to_string())?;
    let c = model.config();
    let cols = c.z_dim + c.hidden_dim;
    let count = train.actions.len() / 2;
    if count == 0 {
        return Err(format!(
            "no examples: every episode is at most --lead {} frames long",
            args.lead
        ));
    }
    println!(
        "{count} examples ({} held out), policy width {}, {} steps of {}",
        heldout.actions.len() / 2,
        trainer.width(),
        args.steps,
        args.batch
    );
    let report = |model: &Model, when: &str| -> Result<(), String> {
        if model.policy_width().is_some() && !heldout.actions.is_empty() {
            let [speed, steering] = errors(model, &heldout)?;
            println!("held out, {when}: RMS error speed {speed:.2}, steering {steering:.3}");
        }
        Ok(())
    };
    report(&model, "before")?;
    let batch = (args.batch as usize).min(count);
    let (checkpoints, arguments) = (&args.checkpointing, args.run_arguments());
    let mut first_step = 0;
    if let Some((step, draw)) = checkpoints.restore("policy", &arguments, |s| trainer.load_state(s))? {
        first_step = step;
        if Order::after(count, args.seed, step * batch).state != draw {
            return Err("the checkpoint's order of the examples is not this data's: other episodes?".into());
        }
    }
    let mut order = Order::after(count, args.seed, first_step * batch);
    let mut state = checkpoints.buffer(trainer.state_len());
    let (mut inputs, mut actions) = (Vec::new(), Vec::new());
    let (mut loss_sum, start) = (0.0, Instant::now());
    let progress = bar(
        args.steps as u64,
        "training: {pos}/{len} steps ({per_sec}, {eta} left) {msg}",
    );
    progress.set_position(first_step as u64);
    for step in first_step..args.steps {
        inputs.clear();
        actions.clear();
        for _ in 0..batch {
            let i = order.draw();
            inputs.extend_from_slice(&train.inputs[i * cols..][..cols]);
            actions.extend_from_slice(&train.actions[i * 2..][..2]);
        }
        let lr = cosine_lr(args.lr, step, args.steps);
        loss_sum += trainer.step(&inputs, &actions, lr).map_err(|e| e.to_string())?;
        if (step + 1) % 500 == 0 {
            progress.set_message(format!("loss {:.4}", loss_sum / 500.0));
            loss_sum = 0.0;
        }
        progress.inc(1);
        if checkpoints.due(step + 1, args.steps) {
            trainer.save_state(&mut state).map_err(|e| e.to_string())?;
            checkpoints.save("policy", &arguments, step + 1, order.state, &state)?;
        }
    }
    progress.finish_and_clear();
    let written = trainer.weight_file(&bytes).map_err(|e| e.to_string())?;
    let trained = Model::from_bytes(&written).map_err(|e| e.to_string())?;
    println!("trained in {:.1} s", start.elapsed().as_secs_f64());
    report(&trained, "after")?;
    crate::files::write_atomically(&args.data.out, &written)?;
    println!("wrote {}", args.data.out.display());
    Ok(())
}
