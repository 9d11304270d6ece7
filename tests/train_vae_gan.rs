//! The VAE-GAN trainer (`--features train`) against PyTorch: `weights/drivesim_reference/fixtures.py` wrote
//! `NAME.gan.safetensors` (weights with a discriminator) and `NAME.gan.io.safetensors` (a batch,
//! `weights/drivesim_reference/vae_gan.py`'s `vae_gan_step` losses, gradients and updated tensors, and the tensors
//! after five steps on the batch).
#![cfg(feature = "train")]

mod common;

use common::{fixture_path, relative_error, Io};
use drivesim::train::{VaeGanLosses, VaeGanPlan, VaeGanSettings, VaeGanTrainer};
use drivesim::{Config, Error, Isa, Model};

/// Max |found - expected| / max |expected| allowed against PyTorch (the 1e-4).
const TOLERANCE: f32 = 1e-4;
const GAN_FIXTURES: [&str; 3] = ["small_f32", "wide_f32", "tiny_bf16"];

struct Fixture {
    weights: Vec<u8>,
    io: Io,
    frames: Vec<f32>,
    eps: Vec<f32>,
    prior: Vec<f32>,
    batch: usize,
    lr: f32,
}

fn fixture(name: &str) -> Fixture {
    let weights = std::fs::read(fixture_path(&format!("{name}.gan.safetensors"))).unwrap();
    let io = Io::open(&format!("{name}.gan.io.safetensors"));
    let (shape, frames) = io.get("frames");
    Fixture {
        weights,
        frames,
        eps: io.values("eps"),
        prior: io.values("prior"),
        batch: shape[0],
        lr: io.metadata("lr").parse().unwrap(),
        io,
    }
}

impl Fixture {
    fn trainer(&self, isa: Isa) -> VaeGanTrainer {
        self.trainer_with_threads(isa, 1)
    }

    fn trainer_with_threads(&self, isa: Isa, threads: usize) -> VaeGanTrainer {
        let model = Model::from_bytes(&self.weights).unwrap();
        let plan = VaeGanPlan::new(model.config(), self.batch, threads).unwrap();
        VaeGanTrainer::new(&self.weights, &plan, VaeGanSettings::default())
            .unwrap()
            .with_isa(isa)
    }
}

fn check(what: &str, found: &[f32], expected: &[f32]) {
    let err = relative_error(found, expected);
    assert!(err <= TOLERANCE, "{what}: relative error {err:.3e}");
}

/// Whether a gradient is that of a convolution's bias before BatchNorm: zero in exact
/// arithmetic (the normalisation removes any constant per channel), so both sides hold rounding
/// noise.
fn before_norm(tensor: &str) -> bool {
    let layer = tensor.trim_end_matches(".bias");
    tensor.ends_with(".bias")
        && [
            "conv1", "conv2", "conv3", "convs.1", "convs.2", "convs.3", "deconv1", "deconv2", "deconv3",
        ]
        .iter()
        .any(|l| layer.ends_with(l))
}

/// Checks weights after one Adam step against the exact step. Adam's first step moves every
/// weight by about `lr` against its gradient's sign, whatever the gradient's size: where the
/// exact gradient is within rounding of zero (below 1e-3 of the tensor's largest, or everywhere
/// in a bias before BatchNorm, see [`before_norm`]) the sign is rounding's, and the weight may
/// land up to `2 lr` away; everywhere else within 1e-4 of the tensor's scale.
fn check_update(what: &str, found: &[f32], exact: &[f32], exact_grad: &[f32], lr: f32, zero_grad: bool) {
    let scale = exact.iter().fold(0f32, |m, v| m.max(v.abs()));
    let grad_scale = exact_grad.iter().fold(0f32, |m, v| m.max(v.abs()));
    for (i, ((&w, &e), &g)) in found.iter().zip(exact).zip(exact_grad).enumerate() {
        let undetermined = zero_grad || g.abs() < 1e-3 * grad_scale;
        let allowed = TOLERANCE * scale + if undetermined { 2.0 * lr } else { 0.0 };
        assert!(
            (w - e).abs() <= allowed,
            "{what}[{i}]: {w} vs {e} (gradient {g} of {grad_scale})"
        );
    }
}

/// Checks tensors after training against PyTorch's float64 run: no further from it than
/// `RATIO` times PyTorch's own float32 run (or `TOLERANCE`). Adam's first steps move each weight
/// by about ±lr whatever its gradient's size, so rounding moves float32 weights by 1e-4 to 1e-3
/// of their scale within a few steps; drivesim must be as close to the exact step as PyTorch.
fn check_trained(what: &str, found: &[f32], pytorch: &[f32], exact: &[f32]) -> (f32, f32) {
    let (ours, theirs) = (relative_error(found, exact), relative_error(pytorch, exact));
    if std::env::var("SHOW").is_ok() {
        eprintln!("{what}: {ours:.2e} vs PyTorch f32 {theirs:.2e}");
    }
    assert!(
        ours <= TOLERANCE.max(RATIO * theirs),
        "{what}: {ours:.3e} from the float64 result, PyTorch float32 {theirs:.3e}"
    );
    (ours, theirs)
}
const RATIO: f32 = 3.0;

#[test]
fn one_step_matches_pytorch() {
    for name in GAN_FIXTURES {
        let f = fixture(name);
        for isa in Isa::supported() {
            let mut trainer = f.trainer(isa);
            let losses = trainer.step(&f.frames, &f.eps, &f.prior, f.lr).unwrap();
            let at = format!("{name} {:?}", isa.level());
            for (loss, value) in [
                ("d", losses.discriminator),
                ("e", losses.encoder),
                ("g", losses.generator),
                ("gan", losses.gan),
                ("feature", losses.feature),
                ("pixel_l1", losses.pixel_l1),
                ("kl", losses.kl),
            ] {
                check(
                    &format!("{at} loss.{loss}"),
                    &[value],
                    &f.io.values(&format!("loss.{loss}")),
                );
            }
            let gradients = trainer.gradients();
            for (tensor, shape, grad) in &gradients {
                let (want_shape, exact) = f.io.get(&format!("f64.grad.{tensor}"));
                assert_eq!(*shape, want_shape, "{at} grad.{tensor}");
                if before_norm(tensor) {
                    // Rounding-level zero, against the scale of the layer's weight gradient.
                    let weight = tensor.replace(".bias", ".weight");
                    let scale =
                        f.io.values(&format!("f64.grad.{weight}"))
                            .iter()
                            .fold(0f32, |m, v| m.max(v.abs()));
                    let worst = grad.iter().chain(&exact).fold(0f32, |m, v| m.max(v.abs()));
                    assert!(worst <= 1e-5 * scale, "{at} grad.{tensor}: {worst:e} of {scale:e}");
                } else {
                    check(&format!("{at} grad.{tensor}"), grad, &exact);
                }
            }
            for (tensor, _, values) in trainer.tensors() {
                let exact = f.io.values(&format!("f64.{tensor}"));
                let what = format!("{at} {tensor} after one step");
                match gradients.iter().find(|(name, ..)| *name == tensor) {
                    Some(_) => {
                        let grad = f.io.values(&format!("f64.grad.{tensor}"));
                        check_update(&what, &values, &exact, &grad, f.lr, before_norm(&tensor));
                    }
                    // Running statistics: the discriminator's last two moves come after its update.
                    None => {
                        check_trained(&what, &values, &f.io.values(&tensor), &exact);
                    }
                }
            }
        }
    }
}

/// The losses in the fixtures' order.
fn values(l: &VaeGanLosses) -> [f32; 7] {
    [
        l.discriminator,
        l.encoder,
        l.generator,
        l.gan,
        l.feature,
        l.pixel_l1,
        l.kl,
    ]
}

#[test]
fn five_steps_match_pytorch() {
    for name in GAN_FIXTURES {
        let f = fixture(name);
        let steps: usize = f.io.metadata("steps").parse().unwrap();
        // A tenth of the training rate: see `GAN_STEPS_LR` in weights/drivesim_reference/fixtures.py.
        let lr: f32 = f.io.metadata("steps_lr").parse().unwrap();
        let mut trainer = f.trainer(Isa::best());
        let (pytorch, exact) = (f.io.values("losses"), f.io.values("f64.losses"));
        for step in 0..steps {
            let losses = values(&trainer.step(&f.frames, &f.eps, &f.prior, lr).unwrap());
            // The losses of every step, as close to the exact ones as PyTorch's float32 run.
            for (i, &loss) in losses.iter().enumerate() {
                let at = step * losses.len() + i;
                let what = format!("{name}: loss {i} of step {}", step + 1);
                check_trained(&what, &[loss], &[pytorch[at]], &[exact[at]]);
            }
        }
        for (tensor, _, values) in trainer.tensors() {
            let pytorch = f.io.values(&format!("after{steps}.{tensor}"));
            let exact = f.io.values(&format!("f64.after{steps}.{tensor}"));
            check_trained(
                &format!("{name}: {tensor} after {steps} steps"),
                &values,
                &pytorch,
                &exact,
            );
        }
    }
}

#[test]
fn threads_give_the_same_bits() {
    // Threads take whole items of each convolution, and parts of each weight gradient cut by
    // the layer and the batch alone (panels of rows, blocks of pixels added in block order): the
    // same sums in the same order whatever their number, more threads than parts included.
    let f = fixture("wide_f32");
    let run = |threads| {
        let mut trainer = f.trainer_with_threads(Isa::best(), threads);
        let losses: Vec<[f32; 7]> = (0..2)
            .map(|_| values(&trainer.step(&f.frames, &f.eps, &f.prior, f.lr).unwrap()))
            .collect();
        (losses, trainer.gradients(), trainer.tensors())
    };
    let one = run(1);
    for threads in [2, 3, 16] {
        assert!(run(threads) == one, "{threads} threads differ from one");
    }
}

#[test]
fn bad_input_is_a_typed_error() {
    let f = fixture("tiny_bf16");
    let mut trainer = f.trainer(Isa::best());
    let z = f.eps.len() / f.batch;
    let before = trainer.tensors();
    let mut frames = f.frames.clone();
    frames[5] = 1.5;
    assert!(matches!(
        trainer.step(&frames, &f.eps, &f.prior, f.lr),
        Err(Error::FrameValue { index: 5, .. })
    ));
    frames[5] = f32::NAN;
    assert!(matches!(
        trainer.step(&frames, &f.eps, &f.prior, f.lr),
        Err(Error::NonFinite { .. })
    ));
    let too_many = [f.frames.clone(), f.frames.clone()].concat();
    assert!(matches!(
        trainer.step(&too_many, &f.eps, &f.prior, f.lr),
        Err(Error::BufferLength { buffer: "frames", .. })
    ));
    assert!(matches!(
        trainer.step(&f.frames[..7], &f.eps, &f.prior, f.lr),
        Err(Error::BufferLength { buffer: "frames", .. })
    ));
    assert!(matches!(
        trainer.step(&f.frames, &f.eps[..z], &f.prior, f.lr),
        Err(Error::BufferLength { buffer: "eps", .. })
    ));
    let mut prior = f.prior.clone();
    prior[0] = f32::INFINITY;
    assert!(matches!(
        trainer.step(&f.frames, &f.eps, &prior, f.lr),
        Err(Error::NonFinite { buffer: "prior", .. })
    ));
    assert!(matches!(
        trainer.step(&f.frames, &f.eps, &f.prior, -1.0),
        Err(Error::Setting { name: "lr", .. })
    ));
    // Nothing was trained by the rejected calls.
    assert!(trainer.tensors() == before);
    assert_eq!(trainer.steps(), 0);

    // A plan for another config, a batch of nothing, a file that is not a weight file.
    let other = Config {
        z_dim: 3,
        ..*Model::from_bytes(&f.weights).unwrap().config()
    };
    let plan = VaeGanPlan::new(&other, 2, 1).unwrap();
    assert!(matches!(
        VaeGanTrainer::new(&f.weights, &plan, VaeGanSettings::default()),
        Err(Error::Config { .. })
    ));
    assert!(matches!(
        VaeGanPlan::new(&other, 0, 1),
        Err(Error::Config { field: "batch", .. })
    ));
    assert!(VaeGanTrainer::new(b"not a weight file", &plan, VaeGanSettings::default()).is_err());

    // Loss weights must be finite and not negative.
    let plan = VaeGanPlan::new(Model::from_bytes(&f.weights).unwrap().config(), 2, 1).unwrap();
    for (settings, name) in [
        (
            VaeGanSettings {
                gan: -0.01,
                ..Default::default()
            },
            "gan",
        ),
        (
            VaeGanSettings {
                kl: f32::NAN,
                ..Default::default()
            },
            "kl",
        ),
        (
            VaeGanSettings {
                pixel: f32::INFINITY,
                ..Default::default()
            },
            "pixel",
        ),
    ] {
        match VaeGanTrainer::new(&f.weights, &plan, settings) {
            Err(Error::Setting { name: got, .. }) => assert_eq!(got, name),
            other => panic!("{name}: expected a setting error, got {:?}", other.map(|t| t.steps())),
        }
    }
}

/// Gradients that are not finite stop the step before the update they would feed, running
/// statistics included (the step's forward passes had moved them), with every thread count
/// (threads check pieces of the gradients).
#[test]
fn non_finite_gradients_stop_the_step() {
    let f = fixture("small_f32");
    let networks = |tensors: Vec<(String, Vec<usize>, Vec<f32>)>| {
        let discriminator = |t: &(String, _, _)| t.0.starts_with("discriminator.");
        tensors.into_iter().partition::<Vec<_>, _>(discriminator)
    };
    for threads in [1, 2, 3] {
        let mut trainer = f.trainer_with_threads(Isa::best(), threads);
        // A learning rate of 1e37 moves the discriminator's weights by about that much: the
        // encoder's and generator's losses through it overflow, and their gradients are not
        // finite, so they are not updated.
        let (_, before) = networks(trainer.tensors());
        let err = trainer.step(&f.frames, &f.eps, &f.prior, 1e37).unwrap_err();
        assert!(
            matches!(
                err,
                Error::NonFiniteOutput {
                    buffer: "encoder and generator gradients",
                    ..
                }
            ),
            "{threads} threads: {err}"
        );
        assert!(
            networks(trainer.tensors()).1 == before,
            "{threads} threads: updated anyway"
        );
        // The next step's discriminator gradients are not finite either: nothing changes.
        let before = trainer.tensors();
        let err = trainer.step(&f.frames, &f.eps, &f.prior, f.lr).unwrap_err();
        assert!(
            matches!(
                err,
                Error::NonFiniteOutput {
                    buffer: "discriminator gradients",
                    ..
                }
            ),
            "{threads} threads: {err}"
        );
        assert!(trainer.tensors() == before, "{threads} threads: updated anyway");
        assert_eq!(trainer.steps(), 0);
    }
}
