//! `Environment`: drives reset from seeds and stepped together give each drive the bits of its
//! own `Simulator::rollout`, borrowed or owning the model; misuse is a typed error.

mod common;

use common::values;
use drivesim::{Config, Environment, Error, Model, Simulator, WeightDtype};
use std::sync::Arc;

const CONFIG: Config = common::SMALL;
const DRIVES: usize = 3;
const SEEDS: usize = 3;
const STEPS: usize = 6;

/// Drive `d`'s seed frames and its actions (seeds, then steps), each drive its own.
fn drive_inputs(d: usize) -> (Vec<f32>, Vec<f32>) {
    (
        values((10 + d) as u64, SEEDS * CONFIG.frame_len(), 1.0),
        values((20 + d) as u64, (SEEDS - 1 + STEPS) * CONFIG.action_dim, 1.0),
    )
}

/// The drives' inputs step-major: `[seed][drive][frame]`, and the actions `[step][drive][a]`.
fn step_major() -> (Vec<f32>, Vec<f32>) {
    let (c, inputs): (_, Vec<_>) = (CONFIG, (0..DRIVES).map(drive_inputs).collect());
    let mut frames = Vec::new();
    for s in 0..SEEDS {
        for (f, _) in &inputs {
            frames.extend_from_slice(&f[s * c.frame_len()..][..c.frame_len()]);
        }
    }
    let mut actions = Vec::new();
    for t in 0..SEEDS - 1 + STEPS {
        for (_, a) in &inputs {
            actions.extend_from_slice(&a[t * c.action_dim..][..c.action_dim]);
        }
    }
    (frames, actions)
}

fn check_against_rollouts<M: std::borrow::Borrow<Model>>(model: &Model, env: &mut Environment<M>) {
    let c = CONFIG;
    let (frames, actions) = step_major();
    let per_step = DRIVES * c.action_dim;
    env.reset_from_frames(&frames, &actions[..(SEEDS - 1) * per_step])
        .unwrap();
    let mut got = Vec::new();
    for t in 0..STEPS {
        env.step(&actions[(SEEDS - 1 + t) * per_step..][..per_step]).unwrap();
        got.push(env.codes().to_vec());
    }
    let mut sim = Simulator::new(model).unwrap();
    for d in 0..DRIVES {
        let (seed_frames, drive_actions) = drive_inputs(d);
        let mut codes = vec![0.0; STEPS * c.z_dim];
        sim.rollout(&seed_frames, &drive_actions, &mut codes, None).unwrap();
        for (t, step) in got.iter().enumerate() {
            assert_eq!(
                step[d * c.z_dim..][..c.z_dim],
                codes[t * c.z_dim..][..c.z_dim],
                "drive {d} step {t}"
            );
        }
    }
}

#[test]
fn drives_get_the_bits_of_their_own_rollouts() {
    for dtype in [WeightDtype::F32, WeightDtype::F16] {
        let model = Model::random(&CONFIG, 3, dtype).unwrap();
        check_against_rollouts(&model, &mut Environment::new(&model, DRIVES, 8).unwrap());
        let shared = Arc::new(Model::random(&CONFIG, 3, dtype).unwrap());
        let mut owned = Environment::new(Arc::clone(&shared), DRIVES, 8)
            .unwrap()
            .with_threads(2)
            .unwrap();
        check_against_rollouts(&shared, &mut owned);
    }
}

#[test]
fn candidates_start_from_a_drives_state() {
    let c = CONFIG;
    let model = Model::random(&CONFIG, 5, WeightDtype::F32).unwrap();
    let mut env = Environment::new(&model, DRIVES, 4).unwrap();
    let (frames, actions) = step_major();
    let per_step = DRIVES * c.action_dim;
    env.reset_from_frames(&frames, &actions[..(SEEDS - 1) * per_step])
        .unwrap();
    // Every candidate repeats drive 1's next two actions: each equals stepping the drive.
    let next: Vec<f32> = (0..2)
        .flat_map(|t| actions[(SEEDS - 1 + t) * per_step..][..per_step].to_vec())
        .collect();
    let mut plan = Vec::new();
    for t in 0..2 {
        for _ in 0..4 {
            plan.extend_from_slice(&next[t * per_step + c.action_dim..][..c.action_dim]);
        }
    }
    let mut codes = vec![0.0; 2 * 4 * c.z_dim];
    env.rollout_candidates(1, 4, &plan, &mut codes, None).unwrap();
    for t in 0..2 {
        env.step(&next[t * per_step..][..per_step]).unwrap();
        for n in 0..4 {
            assert_eq!(
                codes[(t * 4 + n) * c.z_dim..][..c.z_dim],
                env.codes()[c.z_dim..][..c.z_dim],
                "step {t}"
            );
        }
        if t == 0 {
            // From a predicted state too.
            env.rollout_candidates(1, 4, &plan[4 * c.action_dim..], &mut codes[4 * c.z_dim..], None)
                .unwrap();
        }
    }
}

#[test]
fn misuse_is_a_typed_error() {
    let c = CONFIG;
    let model = Model::random(&CONFIG, 6, WeightDtype::F32).unwrap();
    assert!(matches!(Environment::new(&model, 0, 4), Err(Error::Config { .. })));
    let mut env = Environment::new(&model, DRIVES, 4).unwrap();
    let actions = vec![0.0; DRIVES * c.action_dim];
    assert!(matches!(env.step(&actions), Err(Error::NotSeeded)));
    let mut frames = vec![0.0; DRIVES * c.frame_len()];
    assert!(matches!(env.frames(&mut frames), Err(Error::NotSeeded)));
    let codes = vec![0.0; 2 * DRIVES * c.z_dim];
    assert!(matches!(
        env.reset_from_codes(&codes[1..], &actions),
        Err(Error::NotWholeItems { .. })
    ));
    assert!(matches!(
        env.reset_from_codes(&codes, &actions[1..]),
        Err(Error::BufferLength { .. })
    ));
    env.reset_from_codes(&codes, &actions).unwrap();
    env.step(&actions).unwrap();
    assert!(matches!(
        env.step(&actions[1..]),
        Err(Error::BufferLength { .. }) | Err(Error::NotWholeItems { .. })
    ));
    let mut out = vec![0.0; c.z_dim];
    assert!(matches!(
        env.rollout_candidates(DRIVES, 1, &actions[..c.action_dim], &mut out, None),
        Err(Error::OutOfRange { what: "drive", .. })
    ));
}
