//! Sampled rollouts allocate nothing: `set_sampling`, `sample`, the rollouts and an
//! environment's steps with sampling on, through the spread head and through the texture net. (A binary of its own: the allocation counter is global.)
#![cfg(feature = "train")]

mod common;
#[path = "common/counting.rs"]
mod counting;

use common::{values, with_f32_tensors, SMALL};
use counting::{counted, Counting};
use drivesim::{Environment, Model, Simulator};

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn sampling_allocates_nothing() {
    let (z, hd) = (SMALL.z_dim, SMALL.hidden_dim);
    let file = drivesim::train::random_weight_file(&SMALL, 4).unwrap();
    let spread = [
        ("transition.S", vec![z, hd], values(1, z * hd, 0.05)),
        ("transition.s", vec![z], values(2, z, 0.1)),
        // A noise factor: the correlated path's product allocates nothing either.
        (
            "transition.L",
            vec![z, z],
            (0..z * z).map(|i| (i % (z + 1) == 0) as u8 as f32).collect(),
        ),
    ];
    let model = Model::from_bytes(&with_f32_tensors(&file, &spread)).unwrap();
    assert!(model.samples_correlated());
    let mut sim = Simulator::with_batch(&model, 6).unwrap().with_threads(2).unwrap();
    let mut env = Environment::new(&model, 2, 6).unwrap();
    let (h, code) = (values(3, hd, 0.5), values(4, z, 1.0));
    let actions: Vec<f32> = (0..4 * 6).flat_map(|i| [20.0, (i % 6) as f32 * 0.1 - 0.3]).collect();
    let (mut codes, mut one) = (vec![0.0; 4 * 6 * z], vec![0.0; 4 * z]);
    let seeds = values(5, 2 * z, 1.0);
    let ((), n, _) = counted(|| {
        sim.set_sampling(0.8, 3).unwrap();
        sim.rollout_candidates(&h, Some(&code), 6, &actions, &mut codes, None)
            .unwrap();
        sim.rollout_from_codes(&code, &actions[..8], &mut one, None).unwrap();
        sim.sample(&h, 2, &mut one[..z]).unwrap();
        env.set_sampling(1.0, 5).unwrap();
        env.reset_from_codes(&seeds, &[]).unwrap();
        env.step(&actions[..4]).unwrap();
        env.rollout_candidates(1, 6, &actions, &mut codes, None).unwrap();
        assert!(sim.set_sampling(-1.0, 3).is_err());
    });
    assert_eq!(n, 0, "{n} allocations with sampling on");

    // The texture net's sampled path (transition.texture.*, width up to hidden_dim).
    let cols = z + hd;
    let net = [
        (
            "transition.texture.hidden.weight",
            vec![hd, cols],
            values(6, hd * cols, 0.2),
        ),
        ("transition.texture.hidden.bias", vec![hd], values(7, hd, 0.1)),
        ("transition.texture.output.weight", vec![z, hd], values(8, z * hd, 0.2)),
        ("transition.texture.output.bias", vec![z], values(9, z, 0.1)),
    ];
    let model = Model::from_bytes(&with_f32_tensors(&file, &net)).unwrap();
    let mut sim = Simulator::with_batch(&model, 6).unwrap().with_threads(2).unwrap();
    let ((), n, _) = counted(|| {
        sim.set_sampling(0.8, 3).unwrap();
        sim.rollout_candidates(&h, Some(&code), 6, &actions, &mut codes, None)
            .unwrap();
        sim.sample(&h, 2, &mut one[..z]).unwrap();
    });
    assert_eq!(n, 0, "{n} allocations sampling through the texture net");
}
