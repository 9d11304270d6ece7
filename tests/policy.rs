//! The policy (the cloned driver, `policy.*` tensors): the trainer's steps against a scalar
//! f64 reference of the same network, loss and Adam; the written file read back and run by
//! `Simulator::act` as trained; bit-identical across batches and threads; typed errors.
#![cfg(feature = "train")]

mod common;

use common::{relative_error, values, Tensor, SMALL};
use drivesim::train::{random_weight_file, HeadSettings, HeadTrainer, NamedTensor};
use drivesim::{Error, Model, Simulator};
use safetensors::{Dtype, SafeTensors};

const WIDTH: usize = 20; // not a whole panel of rows
const COLS: usize = SMALL.z_dim + SMALL.hidden_dim;

/// The small config's random model as a weight file (f32, no action metadata).
fn small_file() -> Vec<u8> {
    random_weight_file(&SMALL, 5).unwrap()
}

fn trainer(model: &Model, batch: usize) -> HeadTrainer {
    let settings = HeadSettings {
        width: WIDTH,
        batch,
        restart: Some(3),
        ..HeadSettings::default()
    };
    HeadTrainer::new(model, drivesim::HeadKind::Policy, settings).unwrap()
}

fn tensor<'a>(tensors: &'a [NamedTensor], name: &str) -> &'a [f32] {
    &tensors.iter().find(|(n, ..)| n == name).unwrap().2
}

/// The policy in f64: `[W1, b1, W2, b2]` row-major.
struct Reference {
    params: [Vec<f64>; 4],
    m: [Vec<f64>; 4],
    v: [Vec<f64>; 4],
    step: i32,
}

impl Reference {
    fn new(tensors: &[NamedTensor]) -> Reference {
        let get = |name| tensor(tensors, name).iter().map(|&v| v as f64).collect::<Vec<f64>>();
        let params = [
            get("policy.hidden.weight"),
            get("policy.hidden.bias"),
            get("policy.output.weight"),
            get("policy.output.bias"),
        ];
        let zeros = || params.clone().map(|p| vec![0.0; p.len()]);
        Reference {
            m: zeros(),
            v: zeros(),
            params,
            step: 0,
        }
    }

    /// Hidden activations and outputs of one input row.
    fn forward(&self, x: &[f32]) -> (Vec<f64>, Vec<f64>) {
        let [w1, b1, w2, b2] = &self.params;
        let hidden: Vec<f64> = (0..WIDTH)
            .map(|r| (b1[r] + (0..COLS).map(|c| w1[r * COLS + c] * x[c] as f64).sum::<f64>()).tanh())
            .collect();
        let out = (0..2)
            .map(|r| b2[r] + (0..WIDTH).map(|c| w2[r * WIDTH + c] * hidden[c]).sum::<f64>())
            .collect();
        (hidden, out)
    }

    /// Loss (mean squared error; no action statistics: the scaled units are the actions') and
    /// one Adam step (PyTorch's defaults).
    fn step(&mut self, inputs: &[f32], actions: &[f32], lr: f64) -> f64 {
        let n = inputs.len() / COLS;
        let mut grads = self.params.clone().map(|p| vec![0.0; p.len()]);
        let mut loss = 0.0;
        for (x, y) in inputs.chunks_exact(COLS).zip(actions.chunks_exact(2)) {
            let (hidden, out) = self.forward(x);
            for r in 0..2 {
                let error = out[r] - y[r] as f64;
                loss += error * error / (2 * n) as f64;
                let g = 2.0 * error / (2 * n) as f64;
                grads[3][r] += g;
                for c in 0..WIDTH {
                    grads[2][r * WIDTH + c] += g * hidden[c];
                    let dpre = g * self.params[2][r * WIDTH + c] * (1.0 - hidden[c] * hidden[c]);
                    grads[1][c] += dpre;
                    for k in 0..COLS {
                        grads[0][c * COLS + k] += dpre * x[k] as f64;
                    }
                }
            }
        }
        self.step += 1;
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8);
        let moments = self.m.iter_mut().zip(self.v.iter_mut());
        for ((params, grads), (m, v)) in self.params.iter_mut().zip(&grads).zip(moments) {
            for (((p, g), m), v) in params.iter_mut().zip(grads).zip(m.iter_mut()).zip(v.iter_mut()) {
                *m = b1 * *m + (1.0 - b1) * g;
                *v = b2 * *v + (1.0 - b2) * g * g;
                let m_hat = *m / (1.0 - b1.powi(self.step));
                let v_hat = *v / (1.0 - b2.powi(self.step));
                *p -= lr * m_hat / (v_hat.sqrt() + eps);
            }
        }
        loss
    }
}

#[test]
fn steps_match_the_scalar_reference() {
    let model = Model::from_bytes(&small_file()).unwrap();
    let batch = 7;
    let mut trainer = trainer(&model, batch);
    let mut reference = Reference::new(&trainer.tensors());
    for step in 0..4u64 {
        let inputs = values(10 + step, batch * COLS, 1.0);
        let actions = values(20 + step, batch * 2, 2.0);
        let loss = trainer.step(&inputs, &actions, 0.01).unwrap();
        let expected = reference.step(&inputs, &actions, 0.01);
        assert!(
            ((loss as f64 - expected) / expected).abs() < 1e-5,
            "step {step}: loss {loss} against {expected}"
        );
    }
    let found = trainer.tensors();
    for (i, name) in [
        "policy.hidden.weight",
        "policy.hidden.bias",
        "policy.output.weight",
        "policy.output.bias",
    ]
    .into_iter()
    .enumerate()
    {
        let expected: Vec<f32> = reference.params[i].iter().map(|&v| v as f32).collect();
        let error = relative_error(tensor(&found, name), &expected);
        assert!(error < 1e-5, "{name}: relative error {error}");
    }
    assert_eq!(trainer.steps(), 4);
}

#[test]
fn written_file_acts_as_trained_whatever_the_batch_or_threads() {
    let original = small_file();
    let model = Model::from_bytes(&original).unwrap();
    assert_eq!(model.policy_width(), None);
    let mut trainer = trainer(&model, 16);
    for step in 0..3 {
        trainer
            .step(&values(step, 16 * COLS, 1.0), &values(50 + step, 32, 1.0), 0.01)
            .unwrap();
    }
    let trained = Model::from_bytes(&trainer.weight_file(&original, Default::default()).unwrap()).unwrap();
    assert_eq!(trained.policy_width(), Some(WIDTH));
    let reference = Reference::new(&trainer.tensors());
    let inputs = values(99, 5 * COLS, 1.0);
    let (z, h): (Vec<f32>, Vec<f32>) = (
        inputs
            .chunks_exact(COLS)
            .flat_map(|r| r[..SMALL.z_dim].to_vec())
            .collect(),
        inputs
            .chunks_exact(COLS)
            .flat_map(|r| r[SMALL.z_dim..].to_vec())
            .collect(),
    );
    let mut batched = vec![0.0; 10];
    Simulator::with_batch(&trained, 5)
        .unwrap()
        .act(&z, &h, &mut batched)
        .unwrap();
    for (i, x) in inputs.chunks_exact(COLS).enumerate() {
        let expected: Vec<f32> = reference.forward(x).1.iter().map(|&v| v as f32).collect();
        assert!(relative_error(&batched[i * 2..][..2], &expected) < 1e-5, "item {i}");
        let mut one = [0.0; 2];
        let mut sim = Simulator::new(&trained).unwrap().with_threads(2).unwrap();
        sim.act(
            &z[i * SMALL.z_dim..][..SMALL.z_dim],
            &h[i * SMALL.hidden_dim..][..SMALL.hidden_dim],
            &mut one,
        )
        .unwrap();
        assert_eq!(
            one.map(f32::to_bits),
            [batched[2 * i].to_bits(), batched[2 * i + 1].to_bits()]
        );
    }
}

#[test]
fn the_loss_falls_on_a_learnable_target() {
    let model = Model::from_bytes(&small_file()).unwrap();
    let mut trainer = trainer(&model, 64);
    let inputs = values(7, 64 * COLS, 1.0);
    // Each action a smooth function of the input.
    let actions: Vec<f32> = inputs
        .chunks_exact(COLS)
        .flat_map(|x| [x[0] + 0.5 * x[3], (x[1] - x[2]).tanh()])
        .collect();
    let first = trainer.loss(&inputs, &actions).unwrap();
    for _ in 0..300 {
        trainer.step(&inputs, &actions, 3e-3).unwrap();
    }
    let last = trainer.loss(&inputs, &actions).unwrap();
    assert!(last < 0.05 * first, "loss {first} -> {last}");
}

#[test]
fn actions_stay_in_the_trained_ranges() {
    let bytes = std::fs::read("weights/default.safetensors").unwrap();
    let model = Model::from_bytes(&bytes).unwrap();
    let c = *model.config();
    let mut trainer = HeadTrainer::new(
        &model,
        drivesim::HeadKind::Policy,
        HeadSettings {
            width: 8,
            batch: 4,
            restart: Some(1),
            ..HeadSettings::default()
        },
    )
    .unwrap();
    // Far-off targets drive the outputs past the ranges.
    let (inputs, actions) = (values(3, 4 * (c.z_dim + c.hidden_dim), 1.0), [500.0, 9.0].repeat(4));
    for _ in 0..50 {
        trainer.step(&inputs, &actions, 0.05).unwrap();
    }
    // The default model's own policy (64 wide) is replaced, not mixed with this one.
    let trained = Model::from_bytes(&trainer.weight_file(&bytes, Default::default()).unwrap()).unwrap();
    assert_eq!((model.policy_width(), trained.policy_width()), (Some(64), Some(8)));
    let mut sim = Simulator::new(&trained).unwrap();
    let mut action = [0.0; 2];
    sim.act(
        &inputs[..c.z_dim],
        &inputs[c.z_dim..c.z_dim + c.hidden_dim],
        &mut action,
    )
    .unwrap();
    let specs = trained.actions().unwrap();
    assert_eq!(action, [specs[0].max, specs[1].max]);
    trained.check_actions(&action).unwrap();
}

/// `bytes` with tensor `name` replaced by `shape` (f32 values), or removed (`None`).
fn edited(bytes: &[u8], name: &str, shape: Option<Vec<usize>>) -> Vec<u8> {
    let file = SafeTensors::deserialize(bytes).unwrap();
    let (_, metadata) = SafeTensors::read_metadata(bytes).unwrap();
    let mut tensors = Vec::new();
    for (n, view) in file.tensors() {
        let tensor = match (n == name, &shape) {
            (true, None) => continue,
            (true, Some(shape)) => Tensor::new(Dtype::F32, shape.clone(), vec![0; 4 * shape.iter().product::<usize>()]),
            (false, _) => Tensor::new(view.dtype(), view.shape().to_vec(), view.data().to_vec()),
        };
        tensors.push((n, tensor));
    }
    let views = tensors.iter().map(|(n, t)| (n.clone(), t));
    safetensors::serialize(views, metadata.metadata().clone()).unwrap()
}

#[test]
fn bad_policies_and_inputs_are_typed_errors() {
    let original = small_file();
    let model = Model::from_bytes(&original).unwrap();
    let (z, h, mut out) = (vec![0.1; SMALL.z_dim], vec![0.1; SMALL.hidden_dim], [0.0; 2]);
    let no_policy = Simulator::new(&model).unwrap().act(&z, &h, &mut out);
    assert!(matches!(no_policy, Err(Error::NoPolicy)), "{no_policy:?}");

    let file = trainer(&model, 4).weight_file(&original, Default::default()).unwrap();
    let trained = Model::from_bytes(&file).unwrap();
    let mut sim = Simulator::new(&trained).unwrap();
    assert!(matches!(
        sim.act(&z, &h[1..], &mut out),
        Err(Error::BufferLength { buffer: "h", .. })
    ));
    assert!(matches!(
        sim.act(&z, &h, &mut [0.0; 3]),
        Err(Error::BufferLength { buffer: "actions", .. })
    ));
    let mut nan = h.clone();
    nan[3] = f32::NAN;
    assert!(matches!(
        sim.act(&z, &nan, &mut out),
        Err(Error::NonFinite {
            buffer: "h",
            index: 3,
            ..
        })
    ));
    assert!(matches!(
        sim.act(
            &[z.clone(), z.clone()].concat(),
            &[h.clone(), h.clone()].concat(),
            &mut [0.0; 4]
        ),
        Err(Error::BatchTooLarge { max: 1, found: 2 })
    ));

    let missing = Model::from_bytes(&edited(&file, "policy.output.bias", None));
    assert!(
        matches!(missing, Err(Error::MissingTensor { ref name }) if name == "policy.output.bias"),
        "{missing:?}"
    );
    let alone = Model::from_bytes(&edited(&file, "policy.hidden.bias", None));
    assert!(
        matches!(alone, Err(Error::MissingTensor { ref name }) if name == "policy.hidden.bias"),
        "{alone:?}"
    );
    let flat = Model::from_bytes(&edited(&file, "policy.hidden.bias", Some(vec![4, 5])));
    assert!(matches!(flat, Err(Error::Shape { .. })), "{flat:?}");
    let wide = Model::from_bytes(&edited(&file, "policy.hidden.bias", Some(vec![SMALL.hidden_dim + 1])));
    assert!(
        matches!(wide, Err(Error::Config { found, .. }) if found == SMALL.hidden_dim + 1),
        "{wide:?}"
    );
    let mismatched = Model::from_bytes(&edited(&file, "policy.output.weight", Some(vec![2, WIDTH + 1])));
    assert!(matches!(mismatched, Err(Error::Shape { .. })), "{mismatched:?}");

    let mut t = trainer(&model, 4);
    let (inputs, actions) = (values(1, 4 * COLS, 1.0), values(2, 8, 1.0));
    assert!(matches!(
        t.step(&inputs, &actions, f32::NAN),
        Err(Error::Setting { name: "lr", .. })
    ));
    assert!(matches!(
        t.step(&inputs[1..], &actions, 0.1),
        Err(Error::NotWholeItems { .. })
    ));
    assert!(matches!(
        t.step(&inputs, &actions[1..], 0.1),
        Err(Error::BufferLength { buffer: "targets", .. })
    ));
    let more = [inputs.clone(), inputs.clone()].concat();
    assert!(matches!(
        t.step(&more, &[actions.clone(), actions.clone()].concat(), 0.1),
        Err(Error::BatchTooLarge { .. })
    ));
    let mut bad = actions.clone();
    bad[5] = f32::INFINITY;
    assert!(matches!(
        t.step(&inputs, &bad, 0.1),
        Err(Error::NonFinite {
            buffer: "targets",
            index: 5,
            ..
        })
    ));
    assert_eq!(t.steps(), 0, "a refused step changes nothing");
    for width in [0, SMALL.hidden_dim + 1] {
        let settings = HeadSettings {
            width,
            restart: Some(0),
            ..HeadSettings::default()
        };
        assert!(matches!(
            HeadTrainer::new(&model, drivesim::HeadKind::Policy, settings),
            Err(Error::Config { .. })
        ));
    }
    let settings = HeadSettings {
        batch: 0,
        restart: Some(0),
        ..HeadSettings::default()
    };
    assert!(matches!(
        HeadTrainer::new(&model, drivesim::HeadKind::Policy, settings),
        Err(Error::Config { .. })
    ));
    let other = random_weight_file(&drivesim::Config { z_dim: 16, ..SMALL }, 1).unwrap();
    assert!(matches!(
        t.weight_file(&other, Default::default()),
        Err(Error::Metadata { .. })
    ));
}
