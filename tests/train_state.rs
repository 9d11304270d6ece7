//! A transition trainer's state (checkpoints): a run saved, restored in a new trainer and gone
//! on gives the bits of the run never stopped; bad states are typed errors that change nothing.
#![cfg(feature = "train")]

mod common;

use common::values;
use drivesim::train::{NamedTensor, TransitionPlan, TransitionSettings, TransitionTrainer};
use drivesim::{Config, Error, Model, WeightDtype};
use std::ops::Range;

const CONFIG: Config = Config {
    z_dim: 12,
    hidden_dim: 20,
    ..Config::COMMA
};
const WINDOW: usize = 6;

fn trainer(model: &Model, batch: usize, threads: usize) -> TransitionTrainer<'static> {
    let plan = TransitionPlan::new(&CONFIG, batch, WINDOW).unwrap();
    let settings = TransitionSettings {
        teacher: 2,
        ..TransitionSettings::default()
    };
    let mut t = TransitionTrainer::new(model, &plan, settings)
        .unwrap()
        .with_threads(threads)
        .unwrap();
    t.set_action_normalisation(&[20.0, 0.1], &[5.0, 0.5]).unwrap();
    t
}

/// Step `step`'s batch of 4 windows.
fn batch(step: u64) -> (Vec<f32>, Vec<f32>) {
    let codes = values(100 + step, 4 * WINDOW * CONFIG.z_dim, 1.0);
    let actions = values(200 + step, 4 * (WINDOW - 1) * 2, 3.0);
    (codes, actions)
}

fn run(t: &mut TransitionTrainer<'_>, steps: Range<u64>) {
    for step in steps {
        let (codes, actions) = batch(step);
        t.step(&codes, &actions, 1e-2 * (1.0 - step as f32 / 10.0)).unwrap();
    }
}

/// What the tests ask of both trainers: their state, steps and tensors.
trait Resumable {
    fn state(&self) -> Vec<u8>;
    fn load(&mut self, state: &[u8]) -> Result<(), Error>;
    fn taken(&self) -> u32;
    fn trained(&self) -> Vec<NamedTensor>;

    fn bits(&self) -> Vec<u32> {
        self.trained()
            .iter()
            .flat_map(|(_, _, v)| v.iter().map(|x| x.to_bits()))
            .collect()
    }
}

/// Both trainers have the same methods, not a trait of the crate's.
macro_rules! resumable {
    ($trainer:ty) => {
        impl Resumable for $trainer {
            fn state(&self) -> Vec<u8> {
                let mut out = vec![0u8; self.state_len()];
                self.save_state(&mut out).unwrap();
                out
            }
            fn load(&mut self, state: &[u8]) -> Result<(), Error> {
                self.load_state(state)
            }
            fn taken(&self) -> u32 {
                self.steps()
            }
            fn trained(&self) -> Vec<NamedTensor> {
                self.tensors()
            }
        }
    };
}
resumable!(TransitionTrainer<'_>);
resumable!(drivesim::train::VaeGanTrainer);
resumable!(drivesim::train::HeadTrainer);

fn bits(t: &impl Resumable) -> Vec<u32> {
    t.bits()
}

/// `2 n` steps in one go against `n` steps, the state saved, restored in a trainer of another
/// plan (a larger batch) and two threads, then `n` more: the same bits, the same step count.
/// Returns the state saved.
fn resumes_bit_for_bit<T: Resumable>(make: impl Fn(bool) -> T, run: impl Fn(&mut T, Range<u64>), n: u64) -> Vec<u8> {
    let mut whole = make(false);
    run(&mut whole, 0..2 * n);
    let mut first = make(false);
    run(&mut first, 0..n);
    let state = first.state();
    drop(first);
    let mut second = make(true);
    second.load(&state).unwrap();
    assert_eq!(second.taken(), n as u32);
    run(&mut second, n..2 * n);
    assert_eq!(second.bits(), whole.bits());
    assert_eq!(second.taken(), whole.taken());
    state
}

#[test]
fn a_restored_run_goes_on_bit_for_bit() {
    let model = Model::random(&CONFIG, 4, WeightDtype::F32).unwrap();
    let other = |other: bool| {
        if other {
            trainer(&model, 8, 2)
        } else {
            trainer(&model, 4, 1)
        }
    };
    resumes_bit_for_bit(other, run, 3);
}

#[test]
fn bad_states_are_typed_errors_that_change_nothing() {
    let model = Model::random(&CONFIG, 4, WeightDtype::F32).unwrap();
    let mut t = trainer(&model, 4, 1);
    run(&mut t, 0..2);
    let mut state = vec![0u8; t.state_len()];
    t.save_state(&mut state).unwrap();
    assert!(matches!(t.save_state(&mut state[1..]), Err(Error::BufferLength { .. })));

    let mut fresh = trainer(&model, 4, 1);
    let before = bits(&fresh);
    let truncated = fresh.load_state(&state[..state.len() - 4]);
    assert!(matches!(truncated, Err(Error::Malformed { .. })), "{truncated:?}");
    let mut other_kind = state.clone();
    other_kind[0] = b'X';
    assert!(matches!(fresh.load_state(&other_kind), Err(Error::Malformed { .. })));
    let mut nan = state.clone();
    let at = nan.len() - 8;
    nan[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    assert!(matches!(fresh.load_state(&nan), Err(Error::BadWeight { .. })));
    assert_eq!(
        (bits(&fresh), fresh.steps()),
        (before, 0),
        "a refused state changes nothing"
    );

    let wider = Config {
        hidden_dim: 24,
        ..CONFIG
    };
    let model = Model::random(&wider, 4, WeightDtype::F32).unwrap();
    let plan = TransitionPlan::new(&wider, 4, WINDOW).unwrap();
    let mut other = TransitionTrainer::new(&model, &plan, TransitionSettings::default()).unwrap();
    // Same length by chance or not, another size is refused by name.
    let refused = other.load_state(&state);
    assert!(matches!(refused, Err(Error::Malformed { .. })), "{refused:?}");
}

#[test]
fn a_spread_head_resumes_and_a_state_without_one_is_refused() {
    let model = Model::random(&CONFIG, 4, WeightDtype::F32).unwrap();
    let spread = |batch: usize, threads: usize| {
        let plan = TransitionPlan::new(&CONFIG, batch, WINDOW)
            .unwrap()
            .with_spread()
            .unwrap();
        let settings = TransitionSettings {
            teacher: 2,
            ..TransitionSettings::default()
        };
        TransitionTrainer::new(&model, &plan, settings)
            .unwrap()
            .with_threads(threads)
            .unwrap()
    };
    let state = resumes_bit_for_bit(|other| if other { spread(8, 2) } else { spread(4, 1) }, run, 3);
    let names: Vec<String> = spread(4, 1).tensors().into_iter().map(|(n, ..)| n).collect();
    assert_eq!(names[6..], ["transition.S", "transition.s"]);
    // A state with the head and a trainer without, or the other way: refused by name.
    let refused = trainer(&model, 4, 1).load_state(&state);
    assert!(matches!(refused, Err(Error::Malformed { .. })), "{refused:?}");
    let mut without = vec![0u8; trainer(&model, 4, 1).state_len()];
    trainer(&model, 4, 1).save_state(&mut without).unwrap();
    assert!(matches!(
        spread(4, 1).load_state(&without),
        Err(Error::Malformed { .. })
    ));
}

#[test]
fn the_written_file_is_the_same_bytes_every_time() {
    // The metadata's entries used to come out in a `HashMap`'s order, different from call to
    // call: a resumed run could not write the bytes of the run never stopped.
    let original = std::fs::read("weights/default.safetensors").unwrap();
    let model = Model::from_bytes(&original).unwrap();
    let plan = TransitionPlan::for_model(&model, 2, WINDOW).unwrap();
    let t = TransitionTrainer::new(&model, &plan, TransitionSettings::default()).unwrap();
    let specs = model.actions().unwrap();
    let trained_on = drivesim::train::TrainedOn {
        actions: Some(specs),
        frame_hz: Some(12.5),
        discount: None,
    };
    let first = t.weight_file(&original, None, trained_on).unwrap();
    for _ in 0..8 {
        assert!(t.weight_file(&original, None, trained_on).unwrap() == first);
    }
    Model::from_bytes(&first).unwrap();
}

mod vae_gan {
    use super::{bits, resumes_bit_for_bit, values};
    use drivesim::train::{random_weight_file, VaeGanPlan, VaeGanSettings, VaeGanTrainer};
    use drivesim::{Config, Error};

    const SMALL: Config = Config {
        height: 16,
        width: 32,
        base_channels: 2,
        z_dim: 6,
        hidden_dim: 8,
        ..Config::COMMA
    };

    fn trainer(file: &[u8], batch: usize, threads: usize) -> VaeGanTrainer {
        let plan = VaeGanPlan::new(&SMALL, batch, threads).unwrap();
        VaeGanTrainer::new(file, &plan, VaeGanSettings::default()).unwrap()
    }

    fn run(t: &mut VaeGanTrainer, steps: std::ops::Range<u64>) {
        for step in steps {
            let frames = values(300 + step, 2 * SMALL.frame_len(), 1.0);
            let (eps, prior) = (
                values(400 + step, 2 * SMALL.z_dim, 1.0),
                values(500 + step, 2 * SMALL.z_dim, 1.0),
            );
            t.step(&frames, &eps, &prior, 1e-3).unwrap();
        }
    }

    #[test]
    fn a_restored_run_goes_on_bit_for_bit() {
        let file = random_weight_file(&SMALL, 9).unwrap();
        let other = |other: bool| {
            if other {
                trainer(&file, 3, 2)
            } else {
                trainer(&file, 2, 1)
            }
        };
        let state = resumes_bit_for_bit(other, run, 2);

        let mut nan = state.clone();
        let at = nan.len() - 4;
        nan[at..].copy_from_slice(&f32::NAN.to_le_bytes());
        let mut fresh = trainer(&file, 2, 1);
        let before = bits(&fresh);
        assert!(matches!(fresh.load_state(&nan), Err(Error::BadWeight { .. })));
        assert!(matches!(fresh.load_state(&state[1..]), Err(Error::Malformed { .. })));
        assert_eq!((bits(&fresh), fresh.steps()), (before, 0));
        let wider = Config { z_dim: 7, ..SMALL };
        let plan = VaeGanPlan::new(&wider, 2, 1).unwrap();
        let mut other = VaeGanTrainer::new(
            &random_weight_file(&wider, 1).unwrap(),
            &plan,
            VaeGanSettings::default(),
        )
        .unwrap();
        assert!(matches!(other.load_state(&state), Err(Error::Malformed { .. })));
    }
}

mod policy {
    use super::{bits, resumes_bit_for_bit, values, CONFIG};
    use drivesim::train::{HeadSettings, HeadTrainer};
    use drivesim::{Config, Error, Model, WeightDtype};

    fn trainer(model: &Model, width: usize, batch: usize) -> HeadTrainer {
        let settings = HeadSettings {
            width,
            batch,
            restart: Some(2),
            ..HeadSettings::default()
        };
        HeadTrainer::new(model, drivesim::HeadKind::Policy, settings).unwrap()
    }

    fn run(t: &mut HeadTrainer, steps: std::ops::Range<u64>) {
        let cols = CONFIG.z_dim + CONFIG.hidden_dim;
        for step in steps {
            let (inputs, actions) = (values(600 + step, 3 * cols, 1.0), values(700 + step, 6, 2.0));
            t.step(&inputs, &actions, 1e-2).unwrap();
        }
    }

    #[test]
    fn a_restored_run_goes_on_bit_for_bit() {
        let model = Model::random(&CONFIG, 6, WeightDtype::F32).unwrap();
        let state = resumes_bit_for_bit(|other| trainer(&model, 5, if other { 7 } else { 3 }), run, 3);

        let mut fresh = trainer(&model, 5, 3);
        let before = bits(&fresh);
        let mut nan = state.clone();
        let at = nan.len() - 4;
        nan[at..].copy_from_slice(&f32::INFINITY.to_le_bytes());
        assert!(matches!(fresh.load_state(&nan), Err(Error::BadWeight { .. })));
        assert!(matches!(
            fresh.load_state(&state[..state.len() - 1]),
            Err(Error::Malformed { .. })
        ));
        let mut renamed = state.clone();
        renamed[0] = b'X';
        assert!(matches!(fresh.load_state(&renamed), Err(Error::Malformed { .. })));
        assert_eq!((bits(&fresh), fresh.steps()), (before, 0));
        // Another width, or another model's sizes: refused.
        assert!(matches!(
            trainer(&model, 4, 3).load_state(&state),
            Err(Error::Malformed { .. })
        ));
        let wider = Model::random(
            &Config {
                z_dim: CONFIG.z_dim + 1,
                ..CONFIG
            },
            6,
            WeightDtype::F32,
        )
        .unwrap();
        assert!(matches!(
            trainer(&wider, 5, 3).load_state(&state),
            Err(Error::Malformed { .. })
        ));
    }
}
