//! The reward and value heads' calls allocate nothing: `Simulator::reward`, `value` and
//! `rollout_candidates_scored` (sampled too), after planning. (A binary of its own: the
//! allocation counter is global, so a test beside it would count its calls.)
#![cfg(feature = "train")]

mod common;
#[path = "common/counting.rs"]
mod counting;

use common::{values as seeded, with_f32_tensors, TINY};
use counting::{counted, Counting};
use drivesim::train::{random_weight_file, HeadSettings, HeadTrainer, TrainedOn};
use drivesim::{HeadKind, Model, Simulator};

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn the_heads_allocate_nothing() {
    let config = TINY;
    let (zd, hd) = (config.z_dim, config.hidden_dim);
    // The spread head, so that the sampled path is counted too.
    let spread = [
        ("transition.S", vec![zd, hd], seeded(1, zd * hd, 0.05)),
        ("transition.s", vec![zd], seeded(2, zd, 0.1)),
    ];
    let mut bytes = with_f32_tensors(&random_weight_file(&config, 1).unwrap(), &spread);
    for kind in [HeadKind::Reward, HeadKind::Value] {
        let settings = HeadSettings {
            width: 9,
            restart: Some(2),
            ..HeadSettings::default()
        };
        let trainer = HeadTrainer::new(&Model::from_bytes(&bytes).unwrap(), kind, settings).unwrap();
        bytes = trainer.weight_file(&bytes, TrainedOn::default()).unwrap();
    }
    let model = Model::from_bytes(&bytes).unwrap();
    let (n, steps) = (6, 5);
    let mut sim = Simulator::with_batch(&model, n).unwrap().with_threads(2).unwrap();
    let (z, h) = (vec![0.1; n * config.z_dim], vec![-0.2; n * config.hidden_dim]);
    let actions: Vec<f32> = (0..steps * n * 2).map(|i| (i as f32 * 0.3).sin() + 1.0).collect();
    let mut codes = vec![0.0; steps * n * config.z_dim];
    let (mut rewards, mut values) = (vec![0.0; steps * n * 2], vec![0.0; steps * n]);
    assert!(model.samples());
    let ((), count, _) = counted(|| {
        sim.reward(&z, &h, &mut rewards[..2 * n]).unwrap();
        sim.value(&z, &h, &mut values[..n]).unwrap();
        for temperature in [0.0, 1.0] {
            sim.set_sampling(temperature, 7).unwrap();
            sim.rollout_candidates_scored(
                &h[..config.hidden_dim],
                Some(&z),
                n,
                &actions,
                &mut codes,
                &mut rewards,
                &mut values,
            )
            .unwrap();
        }
        assert!(sim.value(&z, &h[1..], &mut values[..n]).is_err());
    });
    assert_eq!(count, 0, "{count} allocations in the heads' calls");
}
