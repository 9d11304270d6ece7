//! The same inputs give the same bits whatever the thread count, the batch an item is computed
//! in, and what the simulator did before, on every instruction set this CPU has, for f32 and
//! f16 models.

mod common;

use common::levels;
use drivesim::{Config, Model, Simulator, WeightDtype};
use std::borrow::Borrow;
use std::sync::Arc;

/// Large enough that the encoder's heads cut their 1280 columns in two chunks and split their
/// rows between threads, and that the transition's product is split too.
const CONFIG: Config = Config {
    height: 32,
    width: 64,
    base_channels: 20,
    z_dim: 96,
    hidden_dim: 256,
    ..Config::COMMA
};
const BATCH: usize = 3;
const SEEDS: usize = 2;
const STEPS: usize = 40;

fn inputs() -> (Vec<f32>, Vec<f32>) {
    let c = CONFIG;
    let frames = (0..BATCH * c.frame_len())
        .map(|i| ((i * 7919) % 2001) as f32 / 1000.0 - 1.0)
        .collect();
    let actions = (0..(SEEDS - 1 + STEPS) * c.action_dim)
        .map(|i| (i as f32 / 9.0).sin())
        .collect();
    (frames, actions)
}

/// Everything a simulator computes from [`inputs`]: codes of the frames as a batch, frames of
/// those codes, 30 transition steps (the first from the codes, then fed back) as a batch, and a
/// 40-step rollout with frames (long enough for every step to feed back its own codes; longer
/// only costs time, under emulation most of all).
#[derive(PartialEq)]
struct Outputs {
    codes: Vec<f32>,
    frames: Vec<f32>,
    steps: Vec<f32>,
    rollout_codes: Vec<f32>,
    rollout_frames: Vec<f32>,
}

/// [`Outputs`] with a batch of `BATCH` per call, or (`one_at_a_time`) one item per call.
fn run<M: Borrow<Model>>(sim: &mut Simulator<M>, one_at_a_time: bool) -> Outputs {
    let c = CONFIG;
    let (frames, actions) = inputs();
    let per_call = if one_at_a_time { 1 } else { BATCH };
    let mut codes = vec![0.0; BATCH * c.z_dim];
    let mut generated = vec![0.0; BATCH * c.frame_len()];
    for (f, z) in frames
        .chunks(per_call * c.frame_len())
        .zip(codes.chunks_mut(per_call * c.z_dim))
    {
        sim.encode(f, z).unwrap();
    }
    for (z, f) in codes
        .chunks(per_call * c.z_dim)
        .zip(generated.chunks_mut(per_call * c.frame_len()))
    {
        sim.generate(z, f).unwrap();
    }
    let (mut hs, mut zs) = (Vec::new(), Vec::new());
    for (z0, n) in codes.chunks(per_call * c.z_dim).zip(0..) {
        let items = z0.len() / c.z_dim;
        let mut h = vec![0.0; items * c.hidden_dim];
        let mut z = vec![0.0; items * c.z_dim];
        for step in 0..30 {
            // Item k of the whole batch gets the same actions however the batch is cut.
            let first = n * per_call * c.action_dim;
            let action: Vec<f32> = (first..first + items * c.action_dim)
                .map(|i| ((step * 5 + i) as f32 / 7.0).cos())
                .collect();
            if step == 0 {
                sim.transition(z0, &mut h, &action, &mut z).unwrap();
            } else {
                sim.transition_fed_back(&mut h, &action, &mut z).unwrap();
            }
        }
        hs.extend_from_slice(&h);
        zs.extend_from_slice(&z);
    }
    let mut rollout_codes = vec![0.0; STEPS * c.z_dim];
    let mut rollout_frames = vec![0.0; STEPS * c.frame_len()];
    let seeds = &frames[..SEEDS * c.frame_len()];
    sim.rollout(seeds, &actions, &mut rollout_codes, Some(&mut rollout_frames))
        .unwrap();
    Outputs {
        codes,
        frames: generated,
        steps: [hs, zs].concat(),
        rollout_codes,
        rollout_frames,
    }
}

#[test]
fn same_bits_whatever_threads_batch_or_history() {
    for dtype in [WeightDtype::F32, WeightDtype::F16] {
        let model = Model::random(&CONFIG, 11, dtype).unwrap();
        for isa in levels() {
            let what = format!("{dtype:?} on {isa:?}");
            let fresh = |threads| {
                Simulator::with_batch(&model, BATCH)
                    .and_then(|s| s.with_threads(threads))
                    .unwrap()
                    .with_isa(isa)
            };
            let mut sim = fresh(1);
            let reference = run(&mut sim, true);
            assert!(reference.rollout_frames.iter().any(|&v| v != 0.0));
            // Used: the same simulator again, after all that.
            assert!(run(&mut sim, true) == reference, "{what}: a used simulator differs");
            assert!(run(&mut sim, false) == reference, "{what}: a batch of {BATCH} differs");
            assert!(run(&mut fresh(2), false) == reference, "{what}: 2 threads, batched");
            assert!(
                run(&mut fresh(3), true) == reference,
                "{what}: 3 threads, one at a time"
            );
        }
    }
}

/// A simulator that owns its model (by value, boxed or shared) computes what one borrowing it
/// does.
#[test]
fn owned_models_give_the_bits_of_borrowed_ones() {
    let model = Model::random(&CONFIG, 11, WeightDtype::F32).unwrap();
    let want = run(&mut Simulator::with_batch(&model, BATCH).unwrap(), false);
    let shared = Arc::new(Model::random(&CONFIG, 11, WeightDtype::F32).unwrap());
    let boxed = Box::new(Model::random(&CONFIG, 11, WeightDtype::F32).unwrap());
    assert!(run(&mut Simulator::with_batch(Arc::clone(&shared), BATCH).unwrap(), false) == want);
    assert!(run(&mut Simulator::with_batch(boxed, BATCH).unwrap(), false) == want);
    let owned = Simulator::with_batch(model, BATCH).unwrap().with_threads(2).unwrap();
    assert!(run(&mut { owned }, false) == want);
}
