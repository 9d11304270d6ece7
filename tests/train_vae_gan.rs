//! The VAE-GAN trainer (`--features train`) against PyTorch: `weights/fixtures.py` wrote
//! `NAME.gan.safetensors` (weights with a discriminator) and `NAME.gan.io.safetensors` (a batch,
//! `weights/train.py`'s `vae_gan_step` losses, gradients and updated tensors, and the tensors
//! after five steps on the batch).
#![cfg(feature = "train")]

mod common;

use common::{fixture_path, relative_error, Io};
use drivesim::train::{VaeGanPlan, VaeGanSettings, VaeGanTrainer};
use drivesim::{Isa, Model};

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
        let model = Model::from_bytes(&self.weights).unwrap();
        let plan = VaeGanPlan::new(model.config(), self.batch).unwrap();
        VaeGanTrainer::new(&self.weights, &plan, VaeGanSettings::default())
            .unwrap()
            .with_isa(isa)
    }
}

fn check(what: &str, found: &[f32], expected: &[f32]) {
    let err = relative_error(found, expected);
    if std::env::var("SHOW").is_ok() { eprintln!("{what}: {err:.3e}"); return; }
    assert!(err <= TOLERANCE, "{what}: relative error {err:.3e}");
}

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
                check(&format!("{at} loss.{loss}"), &[value], &f.io.values(&format!("loss.{loss}")));
            }
            for (tensor, shape, grad) in trainer.gradients() {
                let (want_shape, want) = f.io.get(&format!("grad.{tensor}"));
                assert_eq!(shape, want_shape, "{at} grad.{tensor}");
                check(&format!("{at} grad.{tensor}"), &grad, &want);
            }
            for (tensor, _, values) in trainer.tensors() {
                check(&format!("{at} {tensor} after one step"), &values, &f.io.values(&tensor));
            }
        }
    }
}

#[test]
fn five_steps_match_pytorch() {
    for name in GAN_FIXTURES {
        let f = fixture(name);
        let steps: usize = f.io.metadata("steps").parse().unwrap();
        let mut trainer = f.trainer(Isa::best());
        for _ in 0..steps {
            trainer.step(&f.frames, &f.eps, &f.prior, f.lr).unwrap();
        }
        for (tensor, _, values) in trainer.tensors() {
            let want = f.io.values(&format!("after{steps}.{tensor}"));
            check(&format!("{name}: {tensor} after {steps} steps"), &values, &want);
        }
    }
}
