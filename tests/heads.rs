//! The reward, value and pace heads (`reward.*`, `value.*`, `pace.*`): read back as the trainer
//! wrote them, run by `Simulator::reward` / `value` / `pace` as a scalar f64 reference of the
//! network computes them,
//! read in candidate rollouts with the bits of a step-by-step rollout whatever the batch or
//! threads; their trainer and its λ-returns; typed errors.
#![cfg(feature = "train")]

mod common;

use common::{relative_error, values, with_f32_tensors, SMALL};
use drivesim::train::{lambda_returns, random_weight_file, HeadSettings, HeadTrainer, NamedTensor, TrainedOn};
use drivesim::{Error, HeadKind, Model, Simulator};

const COLS: usize = SMALL.z_dim + SMALL.hidden_dim;

fn settings(width: usize, seed: u64) -> HeadSettings {
    HeadSettings {
        width,
        batch: 8,
        restart: Some(seed),
        ..HeadSettings::default()
    }
}

/// The small random model with a reward head (width 20), a value head (width 11, discount
/// 0.97) and a pace head (width 9, around -0.5 so that the clamp at 0 is met), each trained a
/// few steps so that its output layer is not the draw's.
fn file_with_heads() -> Vec<u8> {
    let mut bytes = random_weight_file(&SMALL, 5).unwrap();
    let heads = [
        (HeadKind::Reward, 20, None, 1.0),
        (HeadKind::Value, 11, Some(0.97), 1.0),
        (HeadKind::Pace, 9, None, -0.5),
    ];
    for (kind, width, discount, mean) in heads {
        let model = Model::from_bytes(&bytes).unwrap();
        let units = vec![(mean, 2.0); kind.outputs(&SMALL)];
        let mut trainer = HeadTrainer::with_units(&model, kind, &units, settings(width, 3)).unwrap();
        for step in 0..3 {
            let targets = values(40 + step, 8 * units.len(), 3.0);
            trainer.step(&values(30 + step, 8 * COLS, 1.0), &targets, 0.05).unwrap();
        }
        let trained_on = TrainedOn {
            discount,
            ..TrainedOn::default()
        };
        bytes = trainer.weight_file(&bytes, trained_on).unwrap();
    }
    bytes
}

fn tensor<'a>(tensors: &'a [NamedTensor], name: &str) -> &'a [f32] {
    &tensors.iter().find(|(n, ..)| n == name).unwrap().2
}

/// The head `prefix` of the file in f64 on one input row.
fn reference(file: &[u8], prefix: &str, x: &[f32]) -> Vec<f64> {
    let st = safetensors::SafeTensors::deserialize(file).unwrap();
    let get = |name: &str| -> (Vec<usize>, Vec<f64>) {
        let view = st.tensor(&format!("{prefix}{name}")).unwrap();
        let values = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()) as f64);
        (view.shape().to_vec(), values.collect())
    };
    let ((w1_shape, w1), (_, b1), (w2_shape, w2), (_, b2)) = (
        get("hidden.weight"),
        get("hidden.bias"),
        get("output.weight"),
        get("output.bias"),
    );
    let (width, outputs) = (w1_shape[0], w2_shape[0]);
    let hidden: Vec<f64> = (0..width)
        .map(|r| (b1[r] + (0..COLS).map(|c| w1[r * COLS + c] * x[c] as f64).sum::<f64>()).tanh())
        .collect();
    (0..outputs)
        .map(|r| b2[r] + (0..width).map(|c| w2[r * width + c] * hidden[c]).sum::<f64>())
        .collect()
}

#[test]
fn heads_read_back_and_match_the_scalar_reference() {
    let file = file_with_heads();
    let model = Model::from_bytes(&file).unwrap();
    assert_eq!(model.head_width(HeadKind::Reward), Some(20));
    assert_eq!(model.head_width(HeadKind::Value), Some(11));
    assert_eq!(model.head_width(HeadKind::Pace), Some(9));
    assert_eq!((model.policy_width(), model.discount()), (None, Some(0.97)));
    let n = 5;
    let (z, h) = (values(1, n * SMALL.z_dim, 1.0), values(2, n * SMALL.hidden_dim, 1.0));
    let mut sim = Simulator::with_batch(&model, n).unwrap();
    let (mut rewards, mut value, mut pace) = (vec![0.0; 2 * n], vec![0.0; n], vec![0.0; n]);
    sim.reward(&z, &h, &mut rewards).unwrap();
    sim.value(&z, &h, &mut value).unwrap();
    sim.pace(&z, &h, &mut pace).unwrap();
    let (mut expected_rewards, mut expected_values, mut raw_pace) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..n {
        let x: Vec<f32> = [
            &z[i * SMALL.z_dim..][..SMALL.z_dim],
            &h[i * SMALL.hidden_dim..][..SMALL.hidden_dim],
        ]
        .concat();
        let r = reference(&file, "reward.", &x);
        expected_rewards.extend([r[0] as f32, r[1].clamp(0.0, 1.0) as f32]);
        expected_values.push(reference(&file, "value.", &x)[0] as f32);
        raw_pace.push(reference(&file, "pace.", &x)[0] as f32);
    }
    let expected_pace: Vec<f32> = raw_pace.iter().map(|v| v.max(0.0)).collect();
    assert!(
        relative_error(&pace, &expected_pace) < 1e-5,
        "{pace:?} against {expected_pace:?}"
    );
    // Speeds on both sides of 0: the clamp is tested, and only where it applies.
    assert!(
        raw_pace.iter().any(|&v| v < 0.0) && raw_pace.iter().any(|&v| v > 0.0),
        "{raw_pace:?}"
    );
    assert!(
        relative_error(&rewards, &expected_rewards) < 1e-5,
        "{rewards:?} against {expected_rewards:?}"
    );
    assert!(
        relative_error(&value, &expected_values) < 1e-5,
        "{value:?} against {expected_values:?}"
    );
    // The targets reach outside [0, 1]: some chance was clamped, so the clamp is tested.
    assert!(rewards.iter().skip(1).step_by(2).all(|p| (0.0..=1.0).contains(p)));
}

/// Each candidate's scores as a rollout of its own gives them: a transition step from the code,
/// then fed back, each state read by `reward` and `value`.
fn scores_step_by_step(
    model: &Model,
    h: &[f32],
    z: &[f32],
    actions: &[f32],
    n: usize,
    steps: usize,
) -> (Vec<f32>, Vec<f32>) {
    let mut sim = Simulator::new(model).unwrap();
    let (mut rewards, mut values) = (vec![0.0; steps * n * 2], vec![0.0; steps * n]);
    for k in 0..n {
        let (mut state, mut code) = (h.to_vec(), vec![0.0; SMALL.z_dim]);
        for t in 0..steps {
            let action = &actions[(t * n + k) * 2..][..2];
            match t {
                0 => sim.transition(z, &mut state, action, &mut code).unwrap(),
                _ => sim.transition_fed_back(&mut state, action, &mut code).unwrap(),
            }
            sim.reward(&code, &state, &mut rewards[(t * n + k) * 2..][..2]).unwrap();
            sim.value(&code, &state, &mut values[t * n + k..][..1]).unwrap();
        }
    }
    (rewards, values)
}

#[test]
fn scored_candidates_get_the_bits_of_their_own_rollout_whatever_the_batch_or_threads() {
    let model = Model::from_bytes(&file_with_heads()).unwrap();
    let (n, steps) = (7, 4);
    let (h, z) = (values(3, SMALL.hidden_dim, 0.5), values(4, SMALL.z_dim, 1.0));
    let actions: Vec<f32> = values(5, steps * n * 2, 1.0).iter().map(|v| v + 1.0).collect();
    let expected = scores_step_by_step(&model, &h, &z, &actions, n, steps);
    for (batch, threads) in [(7, 1), (16, 1), (7, 3), (9, 2)] {
        let mut sim = Simulator::with_batch(&model, batch)
            .unwrap()
            .with_threads(threads)
            .unwrap();
        let mut codes = vec![0.0; steps * n * SMALL.z_dim];
        let (mut rewards, mut values) = (vec![0.0; steps * n * 2], vec![0.0; steps * n]);
        sim.rollout_candidates_scored(&h, Some(&z), n, &actions, &mut codes, &mut rewards, &mut values)
            .unwrap();
        assert_eq!(
            (&rewards, &values),
            (&expected.0, &expected.1),
            "batch {batch}, threads {threads}"
        );
        // The codes are rollout_candidates' own.
        let mut plain = vec![0.0; codes.len()];
        sim.rollout_candidates(&h, Some(&z), n, &actions, &mut plain, None)
            .unwrap();
        assert_eq!(codes, plain);
    }
}

#[test]
fn models_without_heads_and_bad_buffers_are_typed_errors() {
    let plain = Model::from_bytes(&random_weight_file(&SMALL, 5).unwrap()).unwrap();
    assert_eq!((plain.head_width(HeadKind::Reward), plain.discount()), (None, None));
    let mut sim = Simulator::with_batch(&plain, 4).unwrap();
    let (z, h) = (vec![0.0; SMALL.z_dim], vec![0.0; SMALL.hidden_dim]);
    let mut out = [0.0; 2];
    assert!(matches!(
        sim.reward(&z, &h, &mut out),
        Err(Error::NoHead { head: "reward" })
    ));
    assert!(matches!(
        sim.value(&z, &h, &mut out[..1]),
        Err(Error::NoHead { head: "value" })
    ));
    assert!(matches!(
        sim.pace(&z, &h, &mut out[..1]),
        Err(Error::NoHead { head: "pace" })
    ));
    let (actions, mut codes) = (vec![10.0; 2 * 4 * 2], vec![0.0; 2 * 4 * SMALL.z_dim]);
    let (mut rewards, mut values) = (vec![0.0; 16], vec![0.0; 8]);
    let scored = sim.rollout_candidates_scored(&h, None, 4, &actions, &mut codes, &mut rewards, &mut values);
    assert!(matches!(scored, Err(Error::NoHead { head: "reward" })), "{scored:?}");

    let model = Model::from_bytes(&file_with_heads()).unwrap();
    let mut sim = Simulator::with_batch(&model, 4).unwrap();
    let scored = sim.rollout_candidates_scored(&h, None, 4, &actions, &mut codes, &mut rewards[..15], &mut values);
    assert!(matches!(scored, Err(Error::BufferLength { .. })), "{scored:?}");
    let scored = sim.rollout_candidates_scored(&h, None, 4, &actions, &mut codes, &mut rewards, &mut values[..7]);
    assert!(matches!(scored, Err(Error::BufferLength { .. })), "{scored:?}");
    assert!(matches!(
        sim.reward(&z, &h, &mut out[..1]),
        Err(Error::BufferLength { .. })
    ));
    let nan = [f32::NAN; SMALL.z_dim];
    assert!(matches!(
        sim.value(&nan, &h, &mut out[..1]),
        Err(Error::NonFinite { .. })
    ));
}

#[test]
fn bad_head_tensors_and_discounts_are_refused_at_load() {
    let file = file_with_heads();
    let wide = SMALL.hidden_dim + 1;
    let cases = [
        ("reward.output.weight", vec![3, 20]),
        ("value.output.bias", vec![2]),
        ("reward.hidden.bias", vec![wide]),
    ];
    for (name, shape) in cases {
        let values = vec![0.1; shape.iter().product()];
        let edited = with_f32_tensors(&file, &[(name, shape.clone(), values)]);
        let result = Model::from_bytes(&edited);
        assert!(
            matches!(result, Err(Error::Shape { .. } | Error::Config { .. })),
            "{name} {shape:?}: {result:?}"
        );
    }
    for bad in ["1.0", "0", "-0.5", "nan", "soon"] {
        let (_, metadata) = safetensors::SafeTensors::read_metadata(&file).unwrap();
        let mut metadata = metadata.metadata().clone().unwrap();
        metadata.insert("drivesim.discount".into(), bad.into());
        let st = safetensors::SafeTensors::deserialize(&file).unwrap();
        let edited = safetensors::serialize(st.tensors(), Some(metadata)).unwrap();
        assert!(
            matches!(Model::from_bytes(&edited), Err(Error::Metadata { .. })),
            "discount {bad}"
        );
    }
    // A head with only some of its tensors.
    let st = safetensors::SafeTensors::deserialize(&file).unwrap();
    let partial = st.tensors().into_iter().filter(|(n, _)| n != "value.output.bias");
    let partial = safetensors::serialize(partial, None).unwrap();
    assert!(Model::from_bytes(&partial).is_err());
}

#[test]
fn the_trainer_checks_its_units_and_states_and_learns() {
    let model = Model::from_bytes(&random_weight_file(&SMALL, 5).unwrap()).unwrap();
    let with = |units: &[(f32, f32)]| HeadTrainer::with_units(&model, HeadKind::Reward, units, settings(8, 1));
    assert!(matches!(with(&[(0.0, 1.0)]), Err(Error::Config { .. })));
    assert!(matches!(with(&[(0.0, 1.0), (0.0, 0.0)]), Err(Error::Setting { .. })));
    assert!(matches!(
        with(&[(f32::NAN, 1.0), (0.0, 1.0)]),
        Err(Error::Setting { .. })
    ));
    let mut reward = with(&[(2.0, 3.0), (0.5, 0.5)]).unwrap();
    let policy = HeadTrainer::new(&model, HeadKind::Policy, settings(8, 1)).unwrap();
    let mut state = vec![0; policy.state_len()];
    policy.save_state(&mut state).unwrap();
    assert!(matches!(reward.load_state(&state), Err(Error::Malformed { .. })));
    // A learnable target: the reward is the first input's double, off the road where it is < 0.
    let inputs = values(7, 8 * COLS, 1.0);
    let targets: Vec<f32> = inputs
        .chunks_exact(COLS)
        .flat_map(|x| [2.0 * x[0] + 2.0, (x[0] < 0.0) as u8 as f32])
        .collect();
    let first = reward.loss(&inputs, &targets).unwrap();
    for _ in 0..200 {
        reward.step(&inputs, &targets, 0.01).unwrap();
    }
    let last = reward.loss(&inputs, &targets).unwrap();
    assert!(last < 0.05 * first, "loss {first} -> {last}");
    assert!(matches!(
        reward.step(&inputs, &targets[1..], 0.01),
        Err(Error::BufferLength { .. })
    ));
    let tensors = reward.tensors();
    assert_eq!(tensor(&tensors, "reward.output.weight").len(), 2 * 8);
}

#[test]
fn lambda_returns_are_td_targets_at_zero_and_monte_carlo_at_one() {
    let (rewards, next) = ([1.0, 2.0, 3.0, 4.0], [10.0, 20.0, 30.0, 40.0]);
    let mut g = [0.0; 4];
    lambda_returns(&rewards, &next, 0.5, 0.0, &mut g).unwrap();
    assert_eq!(g, [6.0, 12.0, 18.0, 24.0]); // r + γ v'
    lambda_returns(&rewards, &next, 0.5, 1.0, &mut g).unwrap();
    // 4 + 0.5·40 = 24; 3 + 12 = 15; 2 + 7.5 = 9.5; 1 + 4.75 = 5.75.
    assert_eq!(g, [5.75, 9.5, 15.0, 24.0]);
    lambda_returns(&rewards, &next, 0.5, 0.5, &mut g).unwrap();
    // G3 = 24; G2 = 3 + 0.5 (0.5·30 + 0.5·24) = 16.5; G1 = 2 + 0.5 (10 + 8.25) = 11.125;
    // G0 = 1 + 0.5 (5 + 5.5625) = 6.28125.
    assert_eq!(g, [6.28125, 11.125, 16.5, 24.0]);
    assert!(matches!(
        lambda_returns(&rewards, &next, 1.5, 0.5, &mut g),
        Err(Error::Setting { .. })
    ));
    assert!(matches!(
        lambda_returns(&rewards, &next, 0.5, f32::NAN, &mut g),
        Err(Error::Setting { .. })
    ));
    assert!(matches!(
        lambda_returns(&rewards, &next[..3], 0.5, 0.5, &mut g),
        Err(Error::BufferLength { .. })
    ));
    assert!(matches!(
        lambda_returns(&[f32::INFINITY; 4], &next, 0.5, 0.5, &mut g),
        Err(Error::NonFinite { .. })
    ));
    lambda_returns(&[], &[], 0.5, 0.5, &mut []).unwrap();
}
