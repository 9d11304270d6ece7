//! The head trainer's steps and the value head's λ-returns against PyTorch's
//! (`weights/drivesim_reference/heads.py`; `weights/drivesim_reference/fixtures.py` wrote `heads_f32.train.safetensors`): a reward
//! head fine-tuned from the fixture's tensors for three Adam steps, each loss and the final
//! tensors within 1e-5 of PyTorch's, and one drive's returns within 1e-6.
#![cfg(feature = "train")]

mod common;

use common::{relative_error, with_f32_tensors, Io};
use drivesim::train::{lambda_returns, random_weight_file, HeadSettings, HeadTrainer};
use drivesim::{Config, HeadKind, Model};

/// Relative error allowed against PyTorch's float32 steps (they are within 1e-6 of float64's).
const TOLERANCE: f32 = 1e-5;
/// The reward head's tensors, in the order `HeadTrainer::tensors` gives them.
const TENSORS: [&str; 4] = [
    "reward.hidden.weight",
    "reward.hidden.bias",
    "reward.output.weight",
    "reward.output.bias",
];

fn fixture() -> Io {
    Io::open("heads_f32.train.safetensors")
}

fn meta<T: std::str::FromStr>(io: &Io, key: &str) -> T
where
    T::Err: std::fmt::Debug,
{
    io.metadata(key).parse().unwrap()
}

fn check(what: &str, found: &[f32], expected: &[f32], tolerance: f32) {
    let err = relative_error(found, expected);
    eprintln!("{what}: {err:.1e}");
    assert!(
        err <= tolerance,
        "{what}: relative error {err} (found {found:?}, expected {expected:?})"
    );
}

/// A random model of the fixture's config with the fixture's initial reward head.
fn model(io: &Io) -> Model {
    let config = Config::from_json(&io.metadata("drivesim.config")).unwrap();
    let file = random_weight_file(&config, 7).unwrap();
    let head: Vec<(&str, Vec<usize>, Vec<f32>)> = TENSORS
        .iter()
        .map(|&name| {
            let (shape, values) = io.get(&format!("initial.{name}"));
            (name, shape, values)
        })
        .collect();
    Model::from_bytes(&with_f32_tensors(&file, &head)).unwrap()
}

#[test]
fn reward_head_steps_match_pytorch() {
    let io = fixture();
    assert_eq!(io.metadata("kind"), "reward");
    let model = model(&io);
    let units: Vec<(f32, f32)> = io.values("units").chunks_exact(2).map(|u| (u[0], u[1])).collect();
    let (width, batch): (usize, usize) = (meta(&io, "width"), meta(&io, "batch"));
    let settings = HeadSettings {
        width,
        batch,
        restart: None, // fine-tune the file's head: the fixture's initial tensors
        ..Default::default()
    };
    let mut trainer = HeadTrainer::with_units(&model, HeadKind::Reward, &units, settings).unwrap();
    assert_eq!((trainer.kind(), trainer.width()), (HeadKind::Reward, width));
    // The scaling into the trainer's units and back again changes the start by rounding only.
    for (name, shape, values) in trainer.tensors() {
        let (expected_shape, expected) = io.get(&format!("initial.{name}"));
        assert_eq!(shape, expected_shape, "{name}");
        check(&format!("initial {name}"), &values, &expected, 1e-6);
    }
    let (steps, lr): (usize, f32) = (meta(&io, "steps"), meta(&io, "lr"));
    let losses = io.values("losses");
    assert_eq!(losses.len(), steps);
    for (i, &expected) in losses.iter().enumerate() {
        let inputs = io.values(&format!("step{i}.inputs"));
        let targets = io.values(&format!("step{i}.targets"));
        let before = trainer.loss(&inputs, &targets).unwrap();
        let loss = trainer.step(&inputs, &targets, lr).unwrap();
        assert_eq!(
            before.to_bits(),
            loss.to_bits(),
            "step {i}: loss() and step() measure alike"
        );
        check(&format!("step {i} loss"), &[loss], &[expected], TOLERANCE);
    }
    assert_eq!(trainer.steps(), steps as u32);
    let tensors = trainer.tensors();
    assert_eq!(tensors.len(), TENSORS.len());
    for ((name, shape, values), expected_name) in tensors.iter().zip(TENSORS) {
        assert_eq!(name, expected_name);
        let (expected_shape, expected) = io.get(&format!("final.{name}"));
        assert_eq!(shape, &expected_shape, "{name}");
        check(&format!("final {name}"), values, &expected, TOLERANCE);
    }
}

#[test]
fn lambda_returns_match_pytorch() {
    let io = fixture();
    let (discount, lambda): (f32, f32) = (meta(&io, "discount"), meta(&io, "lambda"));
    let rewards = io.values("returns.rewards");
    let next_values = io.values("returns.next_values");
    let expected = io.values("returns.expected");
    let mut returns = vec![f32::NAN; rewards.len()];
    lambda_returns(&rewards, &next_values, discount, lambda, &mut returns).unwrap();
    check("returns", &returns, &expected, 1e-6);
}
