//! The policy's calls allocate nothing: `Simulator::act`, and the trainer's steps. (A binary
//! of its own: the allocation counter is global, so a test beside it would count its calls.)
#![cfg(feature = "train")]

mod common;

use common::TINY;
use drivesim::{Model, Simulator};
#[path = "common/counting.rs"]
mod counting;

use counting::{counted, Counting};

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A model with a policy needs the trainer to write one.
#[test]
fn the_policy_allocates_nothing() {
    use drivesim::train::{random_weight_file, HeadSettings, HeadTrainer};
    let config = TINY;
    let original = random_weight_file(&config, 1).unwrap();
    let settings = HeadSettings {
        width: 18,
        batch: 5,
        restart: Some(2),
        ..HeadSettings::default()
    };
    let mut trainer = HeadTrainer::new(
        &Model::from_bytes(&original).unwrap(),
        drivesim::HeadKind::Policy,
        settings,
    )
    .unwrap();
    let cols = config.z_dim + config.hidden_dim;
    let inputs: Vec<f32> = (0..5 * cols).map(|i| (i as f32 * 0.37).sin()).collect();
    let actions: Vec<f32> = (0..10).map(|i| (i as f32 * 0.7).cos()).collect();
    let ((), n, _) = counted(|| {
        for _ in 0..3 {
            trainer.step(&inputs, &actions, 0.01).unwrap();
        }
        trainer.loss(&inputs[..2 * cols], &actions[..4]).unwrap();
    });
    assert_eq!(n, 0, "{n} allocations in the trainer's steps");
    let model = Model::from_bytes(&trainer.weight_file(&original, Default::default()).unwrap()).unwrap();
    let mut sim = Simulator::with_batch(&model, 5).unwrap().with_threads(2).unwrap();
    let (z, h): (Vec<f32>, Vec<f32>) = (
        inputs[..5 * config.z_dim].to_vec(),
        inputs[..5 * config.hidden_dim].to_vec(),
    );
    let mut out = vec![0.0; 10];
    let ((), n, _) = counted(|| {
        sim.act(&z, &h, &mut out).unwrap();
        sim.act(&z[..config.z_dim], &h[..config.hidden_dim], &mut out[..2])
            .unwrap();
        assert!(sim.act(&z, &h[1..], &mut out).is_err());
    });
    assert_eq!(n, 0, "{n} allocations in act");
}
