//! `train heads`: the reward head or the value head, on episodes that carry the env's rewards
//! (`python -m drivesim record` and `dagger` write them). Encodes the episodes (and their mirror
//! images), steps the transition along each drive for the states the heads read, trains the
//! head, reports its held-out error before and after, and writes the weights with it.
//!
//! - `--head reward`: from the state a decision led to (the next frame's code and the hidden
//!   state after the step), the decision's reward and whether the car is off the road there.
//! - `--head value`: TD(λ): from each frame's state, its λ-return, recomputed with the head as
//!   trained so far every `--refresh` steps, the discount written as `drivesim.discount`; with
//!   `--dream-steps`, on dreamed drives too (`dreams.rs`).

use crate::args::{data_help, Data};
use crate::common::Encoded;
use crate::dreams::{dream, Dreams};
use crate::drives::split;
use crate::files::read;
use crate::regression::{fit, predict, rms_errors, write_trained, Examples, FitFlags, Refresh};
use clap::{Parser, ValueEnum};
use drivesim::train::{lambda_returns, HeadTrainer, TrainedOn};
use drivesim::{HeadKind, Model, Simulator};
use std::time::Instant;

#[derive(Clone, Copy, PartialEq, ValueEnum)]
pub enum HeadArg {
    Reward,
    Value,
}

#[derive(Parser)]
#[command(mut_args = data_help(&[
    ("weights", "Weight file to start from (its encoder and transition give the head's input)"),
    ("episodes", "Episodes with rewards (`reward`, `on_road`) to learn from"),
    ("heldout", "Episodes to evaluate on; without it, the last --holdout episodes of --episodes"),
    ("holdout", "Episodes of --episodes held out when there is no --heldout file"),
    ("out", "Where to write the weights with the trained head"),
]))]
pub struct HeadsArgs {
    #[command(flatten)]
    pub data: Data,
    /// Which head to train
    #[arg(long, value_enum)]
    pub head: HeadArg,
    #[command(flatten)]
    pub fit: FitFlags,
    /// The value's discount per decision (0.98: a return looks about 50 decisions, 4 s, ahead)
    #[arg(long, default_value_t = 0.98)]
    pub discount: f32,
    /// TD(λ)'s λ
    #[arg(long, default_value_t = 0.95)]
    pub lambda: f32,
    /// Steps between recomputing the value's targets with the head as trained so far
    #[arg(long, default_value_t = 500, value_parser = clap::value_parser!(u32).range(1..))]
    pub refresh: u32,
    /// The value head also learns from dreamed drives of this many decisions (0: real drives
    /// only): the policy driving on from real states over sampled futures, the reward head
    /// scoring them (the file needs both)
    #[arg(long, default_value_t = 0)]
    pub dream_steps: usize,
    /// A dreamed drive from every this many real states
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..))]
    pub dream_every: u32,
}

impl HeadsArgs {
    /// The arguments that decide the run (and so its checkpoints).
    fn run_arguments(&self) -> String {
        let own = format!(
            " discount {} lambda {} refresh {} dream_steps {} dream_every {}",
            self.discount, self.lambda, self.refresh, self.dream_steps, self.dream_every
        );
        self.fit.run_arguments(&self.data, Some(self.kind().name()), &own)
    }

    fn kind(&self) -> HeadKind {
        match self.head {
            HeadArg::Reward => HeadKind::Reward,
            HeadArg::Value => HeadKind::Value,
        }
    }
}

/// The heads' examples of encoded drives. `reward`: each decision's next state, its reward and
/// whether the car is off the road there. `value`: each decision's state, with what its
/// λ-return needs: the decision's reward, the next state, and where each drive ends.
struct HeadExamples {
    reward: Examples,
    value: Examples,
    rewards: Vec<f32>,
    next_states: Examples,
    drive_ends: Vec<usize>,
    /// Every frame's state and the speedometer there: where dreamed drives start.
    states: Vec<f32>,
    speeds: Vec<f32>,
}

/// Every frame's state `[z | h]` along each drive (the transition stepped from zeros, as the
/// heads' user steps it) and the examples the heads learn from.
fn examples(model: &Model, drives: &[Encoded], what: &str) -> Result<HeadExamples, String> {
    let c = model.config();
    let (z, hd) = (c.z_dim, c.hidden_dim);
    let mut sim = Simulator::new(model).map_err(|e| e.to_string())?;
    let mut out = HeadExamples {
        reward: Examples::new(2),
        value: Examples::new(1),
        rewards: Vec::new(),
        next_states: Examples::new(1),
        drive_ends: Vec::new(),
        states: Vec::new(),
        speeds: Vec::new(),
    };
    let (mut states, mut h, mut next) = (Vec::new(), vec![0.0; hd], vec![0.0; z]);
    for drive in drives {
        let (rewards, on_road) = drive
            .outcomes
            .as_ref()
            .ok_or_else(|| format!("{what}: an episode without rewards (`reward`, `on_road`): record it again"))?;
        let frames = drive.codes.len() / z;
        states.clear();
        h.fill(0.0);
        for t in 0..frames {
            let code = &drive.codes[t * z..][..z];
            states.extend_from_slice(code);
            states.extend_from_slice(&h);
            sim.transition(code, &mut h, &drive.actions[t * 2..][..2], &mut next)
                .map_err(|e| e.to_string())?;
        }
        let state = |t: usize| &states[t * (z + hd)..][..z + hd];
        for t in 0..frames.saturating_sub(1) {
            out.reward.inputs.extend_from_slice(state(t + 1));
            out.reward
                .targets
                .extend_from_slice(&[rewards[t], 1.0 - on_road[t + 1] as f32]);
            out.value.inputs.extend_from_slice(state(t));
            out.next_states.inputs.extend_from_slice(state(t + 1));
            out.rewards.push(rewards[t]);
        }
        out.value.targets.resize(out.rewards.len(), 0.0);
        out.next_states.targets.resize(out.rewards.len(), 0.0);
        out.drive_ends.push(out.rewards.len());
        out.states.extend_from_slice(&states);
        out.speeds.extend(drive.actions.iter().step_by(2));
    }
    Ok(out)
}

impl HeadExamples {
    /// Dreamed drives added to the value's examples, after the real ones.
    fn add(&mut self, dreams: Dreams) {
        let base = self.rewards.len();
        self.value.inputs.extend_from_slice(&dreams.inputs);
        self.next_states.inputs.extend_from_slice(&dreams.next_states);
        self.rewards.extend_from_slice(&dreams.rewards);
        self.value.targets.resize(self.rewards.len(), 0.0);
        self.next_states.targets.resize(self.rewards.len(), 0.0);
        self.drive_ends.extend(dreams.ends.iter().map(|e| base + e));
    }

    /// The value's targets into `targets`: each drive's λ-returns with `next_values` (the value
    /// of each next state; a drive cut off by the recording is bootstrapped from its last
    /// state's value).
    fn returns(&self, next_values: &[f32], discount: f32, lambda: f32, targets: &mut [f32]) -> Result<(), String> {
        let mut start = 0;
        for &end in &self.drive_ends {
            let out = &mut targets[start..end];
            lambda_returns(
                &self.rewards[start..end],
                &next_values[start..end],
                discount,
                lambda,
                out,
            )
            .map_err(|e| e.to_string())?;
            start = end;
        }
        Ok(())
    }
}

pub fn heads(args: &HeadsArgs) -> Result<(), String> {
    let kind = args.kind();
    let bytes = read(&args.data.weights)?;
    let model = Model::from_bytes(&bytes).map_err(|e| format!("{}: {e}", args.data.weights.display()))?;
    let drives = split(&model, &args.data, args.fit.threads as usize)?;
    let mut train = examples(&model, &drives.train, "episodes")?;
    let mut heldout = examples(&model, &drives.heldout, "held-out episodes")?;
    let (discount, lambda) = (args.discount, args.lambda);
    if kind == HeadKind::Value && args.dream_steps > 0 {
        let every = args.dream_every as usize;
        let dreams = dream(
            &model,
            &train.states,
            &train.speeds,
            args.dream_steps,
            every,
            args.fit.seed,
        )?;
        println!(
            "{} dreamed drives of {} decisions from real states",
            dreams.ends.len(),
            args.dream_steps
        );
        train.add(dreams);
    }
    if kind == HeadKind::Value {
        // The first targets, for the units: the returns with every next value 0.
        let zeros = vec![0.0; train.rewards.len()];
        let mut targets = zeros.clone();
        train.returns(&zeros, discount, lambda, &mut targets)?;
        train.value.targets = targets;
    }
    let target = |e: &mut HeadExamples| -> Examples {
        let pick = if kind == HeadKind::Reward {
            &mut e.reward
        } else {
            &mut e.value
        };
        std::mem::replace(pick, Examples::new(kind.outputs(model.config())))
    };
    let mut examples = target(&mut train);
    let units = examples.units();
    let settings = args.fit.settings(model.head_width(kind).is_some());
    let mut trainer = HeadTrainer::with_units(&model, kind, &units, settings).map_err(|e| e.to_string())?;
    println!(
        "{} examples ({} held out), {} head width {}, targets' mean and deviation {units:?}, {} steps of {}",
        examples.len(),
        heldout.rewards.len(),
        kind.name(),
        trainer.width(),
        args.fit.steps,
        args.fit.batch
    );
    let trained_on = TrainedOn {
        discount: (kind == HeadKind::Value).then_some(discount),
        ..TrainedOn::default()
    };
    let as_model = |t: &HeadTrainer| -> Result<Model, String> {
        let file = t.weight_file(&bytes, trained_on).map_err(|e| e.to_string())?;
        Model::from_bytes(&file).map_err(|e| e.to_string())
    };
    let mut report = |model: &Model, when: &str| -> Result<(), String> {
        if model.head_width(kind).is_none() || heldout.rewards.is_empty() {
            return Ok(());
        }
        if kind == HeadKind::Reward {
            let rms = rms_errors(model, kind, &heldout.reward)?;
            let spread = heldout.reward.units();
            println!(
                "held out, {when}: RMS error reward {:.3} (targets' deviation {:.3}), off the road {:.3} ({:.3})",
                rms[0], spread[0].1, rms[1], spread[1].1
            );
        } else {
            let next = predict(model, kind, &heldout.next_states)?;
            let mut targets = next.clone();
            heldout.returns(&next, discount, lambda, &mut targets)?;
            heldout.value.targets = targets;
            let rms = rms_errors(model, kind, &heldout.value)?;
            let spread = heldout.value.units()[0].1;
            println!(
                "held out, {when}: RMS error against the λ-returns {:.2} (their deviation {spread:.2})",
                rms[0]
            );
        }
        Ok(())
    };
    report(&model, "before")?;
    let run = args.fit.run("heads", args.run_arguments());
    let start = Instant::now();
    let mut refresh_targets = |t: &HeadTrainer, e: &mut Examples| -> Result<(), String> {
        let next = predict(&as_model(t)?, HeadKind::Value, &train.next_states)?;
        train.returns(&next, discount, lambda, &mut e.targets)
    };
    let refresh = (kind == HeadKind::Value).then_some(Refresh {
        every: args.refresh as usize,
        targets: &mut refresh_targets,
    });
    fit(&mut trainer, &mut examples, &run, refresh)?;
    write_trained(&trainer, &bytes, trained_on, start, report, &args.data.out)
}
