//! `train policy`: behavioural cloning of the recorded driver. Encodes the episodes (and their
//! mirror images), steps the transition along each drive for the hidden state the policy reads,
//! trains the policy to give the driver's steering and the speed it reached `--lead` frames
//! later (or, where the episodes carry them, a teacher's `labels`: DAgger's), reports the held-out error before and after, and writes the weights with the policy.
//! With `--pace`, trains the pace head (`pace.*`) on the same examples' speeds alone, in their
//! own statistics, and leaves the policy as it is: the speed a faster teacher's labels ask for.

use crate::args::{data_help, Data};
use crate::common::Encoded;
use crate::drives::split;
use crate::files::read;
use crate::regression::{fit, rms_errors, write_trained, Examples, FitFlags};
use clap::Parser;
use drivesim::train::{HeadTrainer, TrainedOn};
use drivesim::HeadKind;
use drivesim::{Model, Simulator};
use std::time::Instant;

#[derive(Parser)]
#[command(mut_args = data_help(&[
    ("weights", "Weight file to start from (its encoder and transition give the policy's input)"),
    ("episodes", "Episodes of the driver to clone (python -m drivesim record writes them)"),
    ("heldout", "Episodes to evaluate on; without it, the last --holdout episodes of --episodes"),
    ("holdout", "Episodes of --episodes held out when there is no --heldout file"),
    ("out", "Where to write the weights with the trained policy"),
]))]
pub struct PolicyArgs {
    #[command(flatten)]
    pub data: Data,
    #[command(flatten)]
    pub fit: FitFlags,
    /// The speed to learn is the one the driver reached this many frames later
    #[arg(long, default_value_t = 1)]
    pub lead: usize,
    /// Train the pace head (`pace.*`) on the speeds alone instead of the policy (from DAgger's
    /// labels at the expert's pace: the speed the cloned driver drives at where its own is at
    /// the top of its range)
    #[arg(long)]
    pub pace: bool,
}

impl PolicyArgs {
    /// The arguments that decide the run (and so its checkpoints): all but the threads, which
    /// change no bit, and the checkpointing itself.
    fn run_arguments(&self) -> String {
        let head = self.pace.then_some("pace");
        self.fit
            .run_arguments(&self.data, head, &format!(" lead {}", self.lead))
    }

    fn kind(&self) -> HeadKind {
        if self.pace {
            HeadKind::Pace
        } else {
            HeadKind::Policy
        }
    }
}

/// The examples with the speed (the first target) alone: the pace head's.
fn speeds(examples: Examples) -> Examples {
    let mut out = Examples::new(1);
    out.inputs = examples.inputs;
    out.targets = examples.targets.iter().step_by(2).copied().collect();
    out
}

/// The examples of encoded drives: the transition stepped along each from zeros, as the
/// policy's user steps it (`Simulator::act`'s documentation).
fn examples(model: &Model, drives: &[Encoded], lead: usize) -> Result<Examples, String> {
    let c = model.config();
    let (z, hd) = (c.z_dim, c.hidden_dim);
    let mut sim = Simulator::new(model).map_err(|e| e.to_string())?;
    let mut examples = Examples::new(2);
    let (inputs, actions) = (&mut examples.inputs, &mut examples.targets);
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
    Ok(examples)
}

pub fn policy(args: &PolicyArgs) -> Result<(), String> {
    let bytes = read(&args.data.weights)?;
    let model = Model::from_bytes(&bytes).map_err(|e| format!("{}: {e}", args.data.weights.display()))?;
    let drives = split(&model, &args.data, args.fit.threads as usize)?;
    let (train, heldout) = (drives.train, drives.heldout);
    let (mut train, mut heldout) = (
        examples(&model, &train, args.lead)?,
        examples(&model, &heldout, args.lead)?,
    );
    let kind = args.kind();
    if args.pace {
        (train, heldout) = (speeds(train), speeds(heldout));
    }
    let settings = args.fit.settings(model.head_width(kind).is_some());
    let mut trainer = match kind {
        HeadKind::Pace => HeadTrainer::with_units(&model, kind, &train.units(), settings),
        _ => HeadTrainer::new(&model, kind, settings),
    }
    .map_err(|e| e.to_string())?;
    let count = train.len();
    if count == 0 {
        return Err(format!(
            "no examples: every episode is at most --lead {} frames long",
            args.lead
        ));
    }
    println!(
        "{count} examples ({} held out), {} width {}, {} steps of {}",
        heldout.len(),
        kind.name(),
        trainer.width(),
        args.fit.steps,
        args.fit.batch
    );
    let report = |model: &Model, when: &str| -> Result<(), String> {
        if model.head_width(kind).is_some() && heldout.len() > 0 {
            let rms = rms_errors(model, kind, &heldout)?;
            match rms[..] {
                [speed, steering] => println!("held out, {when}: RMS error speed {speed:.2}, steering {steering:.3}"),
                _ => println!("held out, {when}: RMS error of the pace {:.2}", rms[0]),
            }
        }
        Ok(())
    };
    report(&model, "before")?;
    let run = args.fit.run(kind.name(), args.run_arguments());
    let start = Instant::now();
    fit(&mut trainer, &mut train, &run, None)?;
    write_trained(&trainer, &bytes, TrainedOn::default(), start, report, &args.data.out)
}
