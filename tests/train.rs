//! The transition trainer (`--features train`): every step against PyTorch's
//! (`weights/drivesim_reference/fixtures.py` wrote `NAME.train.safetensors` with `weights/drivesim_reference/train.py`'s step), the
//! action gradient against finite differences, bit-identical results across thread counts,
//! and typed errors for bad input.
#![cfg(feature = "train")]

mod common;

use common::{fixture_path, relative_error, Io, Rng, FIXTURES};
use drivesim::train::{
    cosine_lr, fit_noise_factor, sharpen_noise_factor, with_noise_factor, TrainedOn, TransitionPlan,
    TransitionSettings, TransitionTrainer,
};
use drivesim::{Config, Error, Isa, Model, WeightDtype};

/// Max |found - expected| / max |expected| allowed against PyTorch (the 1e-4).
const TOLERANCE: f32 = 1e-4;

struct Fixture {
    model: Model,
    io: Io,
    codes: Vec<f32>,
    actions: Vec<f32>,
    batch: usize,
    window: usize,
    settings: TransitionSettings,
    lr: f32,
}

fn fixture(name: &str) -> Fixture {
    let model = Model::load(fixture_path(&format!("{name}.safetensors"))).unwrap();
    let io = Io::open(&format!("{name}.train.safetensors"));
    let (shape, codes) = io.get("codes");
    let actions = io.values("actions");
    let settings = TransitionSettings {
        teacher: io.metadata("teacher").parse().unwrap(),
        clip: io.metadata("clip").parse().unwrap(),
        ..TransitionSettings::default()
    };
    let lr = io.metadata("lr").parse().unwrap();
    Fixture {
        model,
        io,
        codes,
        actions,
        batch: shape[0],
        window: shape[1],
        settings,
        lr,
    }
}

impl Fixture {
    fn trainer(&self, isa: Isa, full_bptt: bool) -> TransitionTrainer<'static> {
        let mut plan = TransitionPlan::new(self.model.config(), self.batch, self.window).unwrap();
        if self.model.samples() {
            plan = plan.with_spread().unwrap();
        }
        let settings = TransitionSettings {
            full_bptt,
            ..self.settings
        };
        TransitionTrainer::new(&self.model, &plan, settings)
            .unwrap()
            .with_isa(isa)
    }
}

fn check(what: &str, found: &[f32], expected: &[f32]) {
    let err = relative_error(found, expected);
    eprintln!("{what}: {err:.1e}");
    assert!(err <= TOLERANCE, "{what}: relative error {err}");
}

#[test]
fn one_step_matches_pytorch() {
    for name in FIXTURES {
        let f = fixture(name);
        for isa in common::levels() {
            for (full, prefix) in [(false, ""), (true, "full.")] {
                let mut trainer = f.trainer(isa, full);
                let loss = trainer.compute_gradients(&f.codes, &f.actions).unwrap();
                let at = format!("{name} {:?} {prefix}", isa.level());
                check(&format!("{at}loss"), &[loss], &f.io.values(&format!("{prefix}loss")));
                for (tensor, shape, grad) in trainer.gradients() {
                    let (want_shape, want) = f.io.get(&format!("{prefix}grad.{tensor}"));
                    assert_eq!(shape, want_shape, "{at}grad.{tensor}");
                    check(&format!("{at}grad.{tensor}"), &grad, &want);
                }
                if !full {
                    trainer.apply_gradients(f.lr).unwrap();
                    for (tensor, _, values) in trainer.tensors() {
                        check(&format!("{at}{tensor} after one step"), &values, &f.io.values(&tensor));
                    }
                }
            }
        }
    }
}

#[test]
fn noise_factor_matches_pytorch() {
    let f = fixture("spread_f32");
    let (z, a) = (f.model.config().z_dim, f.model.config().action_dim);
    let drives: Vec<(&[f32], &[f32])> = f
        .codes
        .chunks_exact(f.window * z)
        .zip(f.actions.chunks_exact((f.window - 1) * a))
        .collect();
    let factor = fit_noise_factor(&f.model, &drives).unwrap();
    check("noise factor", &factor, &f.io.values("noise_factor"));
    // Sharpened (the correlation squared, back to unit diagonal) as PyTorch sharpens it; power
    // 1 gives the factor back.
    let sharp = sharpen_noise_factor(&factor, 2).unwrap();
    check("noise factor, power 2", &sharp, &f.io.values("noise_factor_power2"));
    assert_eq!(sharpen_noise_factor(&factor, 1).unwrap(), factor);
    assert!(sharp.iter().zip(&factor).any(|(a, b)| (a - b).abs() > 1e-2));
    assert!(matches!(sharpen_noise_factor(&factor, 0), Err(Error::Config { .. })));
    assert!(matches!(
        sharpen_noise_factor(&factor[1..], 2),
        Err(Error::BufferLength { .. })
    ));
    let mut bad = factor.clone();
    bad[3] = f32::NAN;
    assert!(matches!(sharpen_noise_factor(&bad, 2), Err(Error::NonFinite { .. })));
    // The same drives with the unused last action of each: the same factor.
    let longer: Vec<Vec<f32>> = drives.iter().map(|(_, c)| [c, &c[..a]].concat()).collect();
    let drives_t: Vec<(&[f32], &[f32])> = drives.iter().zip(&longer).map(|((z, _), c)| (*z, &c[..])).collect();
    assert_eq!(fit_noise_factor(&f.model, &drives_t).unwrap(), factor);
    // Written into the file, it loads and samples correlated.
    let file = std::fs::read(common::fixture_path("spread_f32.safetensors")).unwrap();
    let model = Model::from_bytes(&with_noise_factor(&file, &factor).unwrap()).unwrap();
    assert!(model.samples_correlated() && !f.model.samples_correlated());
    // Too few steps for the code's dimensions, a model without the spread head, a bad drive.
    assert!(matches!(
        fit_noise_factor(&f.model, &drives[..0]),
        Err(Error::Episodes { .. })
    ));
    let plain = Model::random(f.model.config(), 1, WeightDtype::F32).unwrap();
    assert!(matches!(fit_noise_factor(&plain, &drives), Err(Error::NoSampling)));
    let short = [(drives[0].0, &drives[0].1[1..])];
    assert!(matches!(
        fit_noise_factor(&f.model, &short),
        Err(Error::BufferLength { .. })
    ));
    let mut nan = drives[0].1.to_vec();
    nan[3] = f32::NAN;
    assert!(matches!(
        fit_noise_factor(&f.model, &[(drives[0].0, &nan[..])]),
        Err(Error::NonFinite { .. })
    ));
}

#[test]
fn ten_steps_match_pytorch() {
    for name in FIXTURES {
        let f = fixture(name);
        let steps: usize = f.io.metadata("steps").parse().unwrap();
        let mut trainer = f.trainer(Isa::best(), false);
        for _ in 0..steps {
            trainer.step(&f.codes, &f.actions, f.lr).unwrap();
        }
        for (tensor, _, values) in trainer.tensors() {
            check(
                &format!("{name}: {tensor} after {steps} steps"),
                &values,
                &f.io.values(&format!("after10.{tensor}")),
            );
        }
    }
}

/// Windows of random codes and actions for a small config.
fn batch(config: &Config, batch: usize, window: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = Rng::new(seed);
    (
        rng.fill(batch * window * config.z_dim, 1.0),
        rng.fill(batch * (window - 1) * config.action_dim, 2.0),
    )
}

const SMALL: Config = Config {
    z_dim: 7,
    hidden_dim: 19,
    action_dim: 3,
    ..Config::COMMA
};

/// With full back-propagation the action gradient is the loss's derivative: central
/// differences on each action agree (the loss is smooth; f64 would not add anything the step
/// size does not already bound).
#[test]
fn action_gradient_matches_finite_differences() {
    let model = Model::random(&SMALL, 5, WeightDtype::F32).unwrap();
    let (b, t) = (2, 6);
    let (codes, actions) = batch(&SMALL, b, t, 9);
    let plan = TransitionPlan::new(&SMALL, b, t).unwrap();
    let settings = TransitionSettings {
        teacher: 2,
        full_bptt: true,
        ..TransitionSettings::default()
    };
    let mut trainer = TransitionTrainer::new(&model, &plan, settings).unwrap();
    let mut grad = vec![0.0; actions.len()];
    trainer.action_gradients(&codes, &actions, &mut grad).unwrap();
    let mut scratch = vec![0.0; b * (t - 1) * SMALL.z_dim];
    let eps = 1e-2;
    let mut worst = 0.0f32;
    for i in 0..actions.len() {
        let mut loss_at = |delta: f32| {
            let mut moved = actions.clone();
            moved[i] += delta;
            trainer.predict(&codes, &moved, &mut scratch).unwrap()
        };
        let numeric = (loss_at(eps) - loss_at(-eps)) / (2.0 * eps);
        worst = worst.max((numeric - grad[i]).abs());
    }
    let scale = grad.iter().fold(0.0f32, |m, g| m.max(g.abs()));
    assert!(scale > 1e-4, "the actions must matter");
    assert!(
        worst <= 2e-3 * scale,
        "worst difference {worst} against gradients up to {scale}"
    );
}

#[test]
fn threads_give_the_same_bits() {
    // Threads share each product by panels of rows and blocks of items (as many blocks as
    // divide the batch: 5 and 12 windows cut differently), the weight gradients by rows and, for
    // 40 windows (560 steps), by two blocks of steps summed apart.
    let model = Model::random(&SMALL, 6, WeightDtype::F32).unwrap();
    for b in [5, 12, 40] {
        let t = 15;
        let (codes, actions) = batch(&SMALL, b, t, 10);
        let plan = TransitionPlan::new(&SMALL, b, t).unwrap();
        let run = |threads| {
            let mut trainer = TransitionTrainer::new(&model, &plan, TransitionSettings::default())
                .unwrap()
                .with_threads(threads)
                .unwrap();
            for _ in 0..3 {
                trainer.step(&codes, &actions, 1e-2).unwrap();
            }
            trainer.compute_gradients(&codes, &actions).unwrap();
            (trainer.gradients(), trainer.tensors())
        };
        let one = run(1);
        for threads in [2, 3, 8, 16] {
            assert!(run(threads) == one, "{b} windows, {threads} threads");
        }
    }
}

#[test]
fn action_normalisation_is_folded_back_exactly_enough() {
    // Normalising the actions changes how the weights are stored, not what the model computes.
    let model = Model::random(&SMALL, 7, WeightDtype::F32).unwrap();
    let (b, t) = (3, 8);
    let (codes, actions) = batch(&SMALL, b, t, 11);
    let plan = TransitionPlan::new(&SMALL, b, t).unwrap();
    let mut plain = TransitionTrainer::new(&model, &plan, TransitionSettings::default()).unwrap();
    let mut normalised = TransitionTrainer::new(&model, &plan, TransitionSettings::default()).unwrap();
    normalised
        .set_action_normalisation(&[20.0, -0.5, 1.0], &[5.0, 0.3, 2.0])
        .unwrap();
    let mut p = vec![0.0; b * (t - 1) * SMALL.z_dim];
    let mut q = p.clone();
    plain.predict(&codes, &actions, &mut p).unwrap();
    normalised.predict(&codes, &actions, &mut q).unwrap();
    assert!(relative_error(&q, &p) < 1e-5);
    for ((name, _, a), (_, _, b)) in plain.tensors().iter().zip(normalised.tensors()) {
        assert!(relative_error(&b, a) < 1e-5, "{name}");
    }
}

#[test]
fn cosine_schedule_is_pytorchs() {
    // CosineAnnealingLR(T_max = 100): lr_t = base (1 + cos(π t / 100)) / 2.
    for (step, want) in [
        (0, 1e-3),
        (50, 5e-4),
        (100, 0.0),
        (25, 1e-3 * (1.0 + 0.5f64.sqrt()) / 2.0),
    ] {
        assert!((cosine_lr(1e-3, step, 100) as f64 - want).abs() < 1e-9, "step {step}");
    }
}

#[test]
fn bad_input_is_a_typed_error() {
    let model = Model::random(&SMALL, 8, WeightDtype::F32).unwrap();
    let (b, t) = (2, 5);
    let (codes, actions) = batch(&SMALL, b, t, 12);
    let plan = TransitionPlan::new(&SMALL, b, t).unwrap();
    let settings = TransitionSettings::default();
    let mut trainer = TransitionTrainer::new(&model, &plan, settings).unwrap();
    assert!(matches!(
        trainer.step(&codes[1..], &actions, 1e-3),
        Err(Error::NotWholeItems { .. })
    ));
    assert!(matches!(
        trainer.step(&codes, &actions[1..], 1e-3),
        Err(Error::BufferLength { .. })
    ));
    let mut nan = codes.clone();
    nan[3] = f32::NAN;
    assert!(matches!(
        trainer.step(&nan, &actions, 1e-3),
        Err(Error::NonFinite { index: 3, .. })
    ));
    let three = batch(&SMALL, 3, t, 1);
    assert!(matches!(
        trainer.step(&three.0, &three.1, 1e-3),
        Err(Error::BatchTooLarge { max: 2, found: 3 })
    ));
    assert!(matches!(trainer.apply_gradients(1e-3), Err(Error::NoGradients)));
    trainer.compute_gradients(&codes, &actions).unwrap();
    assert!(matches!(trainer.apply_gradients(-1.0), Err(Error::Setting { .. })));
    assert!(matches!(
        trainer.set_action_normalisation(&[0.0; 3], &[1.0, 0.0, 1.0]),
        Err(Error::Setting { .. })
    ));
    for (batch, window) in [(0, 5), (2, 1), (usize::MAX, 15)] {
        assert!(
            TransitionPlan::new(&SMALL, batch, window).is_err(),
            "batch {batch} window {window}"
        );
    }
    let bad = [
        TransitionSettings { teacher: 0, ..settings },
        TransitionSettings { clip: 0.0, ..settings },
        TransitionSettings {
            clip: f32::NAN,
            ..settings
        },
    ];
    for settings in bad {
        assert!(TransitionTrainer::new(&model, &plan, settings).is_err(), "{settings:?}");
    }
    let other = TransitionPlan::new(&Config { z_dim: 8, ..SMALL }, b, t).unwrap();
    assert!(matches!(
        TransitionTrainer::new(&model, &other, settings),
        Err(Error::Config { field: "z_dim", .. })
    ));
}

/// The trained weights written as a weight file (f32 or rounded to f16, with action metadata)
/// load back with the trained tensors.
#[test]
fn weight_file_holds_the_trained_tensors() {
    let original = std::fs::read(fixture_path("small_f32.safetensors")).unwrap();
    let model = Model::from_bytes(&original).unwrap();
    let c = *model.config();
    let (codes, actions) = batch(&c, 3, 9, 13);
    let plan = TransitionPlan::new(&c, 3, 9).unwrap();
    let settings = TransitionSettings::default();
    let mut trainer = TransitionTrainer::new(&model, &plan, settings).unwrap();
    trainer.set_action_normalisation(&[20.0, 0.0], &[5.0, 0.5]).unwrap();
    for _ in 0..3 {
        trainer.step(&codes, &actions, 1e-2).unwrap();
    }
    let spec = |name: &str, mean| drivesim::ActionSpec {
        name: name.into(),
        unit: "test".into(),
        mean,
        std: 1.0,
        min: -1.0,
        max: 40.0,
    };
    let specs = [spec("speed", 20.0), spec("steering", 0.0)];
    for (dtype, tolerance) in [(None, 1e-6), (Some(WeightDtype::F16), 1e-3)] {
        let trained_on = TrainedOn {
            actions: Some(&specs),
            frame_hz: Some(12.5),
            discount: None,
        };
        let file = trainer.weight_file(&original, dtype, trained_on).unwrap();
        let loaded = Model::from_bytes(&file).unwrap();
        assert_eq!(loaded.actions(), Some(&specs[..]));
        assert_eq!(loaded.frame_hz(), Some(12.5));
        let again = TransitionTrainer::new(&loaded, &plan, settings).unwrap();
        for ((name, _, want), (_, _, got)) in trainer.tensors().iter().zip(again.tensors()) {
            let err = relative_error(&got, want);
            assert!(err <= tolerance, "{dtype:?} {name}: {err}");
        }
    }
    let bad_rate = TrainedOn {
        frame_hz: Some(f32::NAN),
        ..TrainedOn::default()
    };
    assert!(matches!(
        trainer.weight_file(&original, None, bad_rate),
        Err(Error::Metadata { .. })
    ));
    assert!(trainer
        .weight_file(&original[..100], None, TrainedOn::default())
        .is_err());
}
