//! The VAE-GAN trainer's public face: its settings, the losses a step returns, and
//! [`VaeGanTrainer`] (loading the weights, checking a step's inputs, the trained tensors).

use super::budget::Budget;
use super::networks::{build, Networks};
use super::plan::VaeGanPlan;
use super::table::Layout;
use crate::error::{expect_finite, expect_frames, expect_len};
use crate::pool::{Exec, Pool};
use crate::train::adam::Adam;
use crate::train::shared::{check_lr, start_pool};
use crate::train::NamedTensor;
use crate::weights::{RandomSource, SafetensorsSource, TensorSource, WeightDtype, DISCRIMINATOR_PREFIX};
use crate::{Config, Error, Result};
use alloc::vec::Vec;
use drivesim_kernels::pack::conv_matrix_from_torch;
use drivesim_kernels::{Isa, Matrix};

/// The learning rate of `weights/drivesim_reference/train.py fit`'s VAE-GAN.
pub const VAE_GAN_LR: f32 = 2e-4;

/// The loss weights and optimiser of the VAE-GAN (`weights/drivesim_reference/train.py fit`'s defaults).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VaeGanSettings {
    /// Weight of the KL prior in the encoder's loss.
    pub kl: f32,
    /// Weight of the discriminator-feature error (encoder and generator).
    pub feature: f32,
    /// Weight of the pixel L1 error (encoder and generator).
    pub pixel: f32,
    /// Weight of the non-saturating GAN term in the generator's loss.
    pub gan: f32,
    /// Adam's constants, shared by the three networks.
    pub adam: Adam,
}

impl Default for VaeGanSettings {
    fn default() -> Self {
        VaeGanSettings {
            kl: 1e-3,
            feature: 0.1,
            pixel: 1.0,
            gan: 0.01,
            adam: Adam {
                beta1: 0.5,
                beta2: 0.999,
                eps: 1e-8,
            },
        }
    }
}

impl VaeGanSettings {
    /// Every loss weight finite and at least zero, and Adam's constants valid.
    fn check(&self) -> Result<()> {
        let weights = [
            ("kl", self.kl),
            ("feature", self.feature),
            ("pixel", self.pixel),
            ("gan", self.gan),
        ];
        if let Some(&(name, value)) = weights.iter().find(|(_, w)| !(w.is_finite() && *w >= 0.0)) {
            return Err(Error::Setting {
                name,
                expected: "a finite number >= 0",
                value,
            });
        }
        self.adam.check()
    }
}

/// The losses of one step (each network's, and the terms they are made of).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct VaeGanLosses {
    /// The discriminator's: BCE on real frames plus BCE on reconstructions and prior samples.
    pub discriminator: f32,
    /// `kl · KL + feature · feature error + pixel · pixel L1`.
    pub encoder: f32,
    /// `feature · feature error + pixel · pixel L1 + gan · GAN`.
    pub generator: f32,
    /// The generator's non-saturating GAN term (BCE of fakes against "real").
    pub gan: f32,
    /// The squared error of the reconstructions' third-convolution features, over the variance
    /// of the real frames' features.
    pub feature: f32,
    /// The mean absolute error of the reconstructions, in [-1, 1] units.
    pub pixel_l1: f32,
    /// `KL(N(mu, sigma) || N(0, 1))`, mean over items and code dimensions.
    pub kl: f32,
}

/// Trains a model's encoder and generator as a VAE-GAN, with a discriminator, in the memory of
/// a [`VaeGanPlan`], allocated once: a step allocates nothing.
///
/// ```
/// use drivesim::train::{VaeGanPlan, VaeGanSettings, VaeGanTrainer, VAE_GAN_LR};
/// use drivesim::{Config, Model};
///
/// let config = Config { height: 32, width: 64, base_channels: 4, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
/// let file = drivesim::train::random_weight_file(&config, 7)?;
/// let plan = VaeGanPlan::new(&config, 2, 1)?;
/// let mut trainer = VaeGanTrainer::new(&file, &plan, VaeGanSettings::default())?;
/// let frames: Vec<f32> = (0..2 * 32 * 64 * 3).map(|i| ((i % 7) as f32 / 3.0 - 1.0)).collect();
/// let eps = vec![0.5; 2 * 8];
/// let prior = vec![-0.5; 2 * 8];
/// let first = trainer.step(&frames, &eps, &prior, VAE_GAN_LR)?;
/// for _ in 0..20 {
///     trainer.step(&frames, &eps, &prior, VAE_GAN_LR)?;
/// }
/// assert!(trainer.step(&frames, &eps, &prior, VAE_GAN_LR)?.pixel_l1 < first.pixel_l1);
/// // The trained networks as a weight file the simulator loads (discriminator included).
/// let model = Model::from_bytes(&trainer.weight_file(&file, None, Default::default())?)?;
/// assert_eq!(model.config(), &config);
/// # Ok::<(), drivesim::Error>(())
/// ```
pub struct VaeGanTrainer {
    pub(super) config: Config,
    settings: VaeGanSettings,
    pub(super) isa: Isa,
    pub(super) pool: Option<Pool>,
    pub(super) steps: u32,
    pub(super) parts: Networks,
}

impl VaeGanTrainer {
    /// A trainer starting from a drivesim weight file's encoder and generator (and its
    /// discriminator, `discriminator.*`, if it has one; otherwise a seeded random one with
    /// PyTorch's default initialisation ranges), its buffers allocated once here.
    pub fn new(weights: &[u8], plan: &VaeGanPlan, settings: VaeGanSettings) -> Result<VaeGanTrainer> {
        let (config, _, mut src) = SafetensorsSource::parse(weights)?;
        if config != plan.config {
            return Err(Error::Config {
                field: "config",
                expected: "the plan's config",
                found: 0,
            });
        }
        settings.check()?;
        let mut budget = Budget {
            allocate: true,
            floats: Vec::new(),
        };
        let mut parts = build(&config, plan.batch, plan.threads, &mut budget)?;
        debug_assert_eq!(budget.floats, plan.floats, "the plan measures what is allocated");
        let has_discriminator = src.contains(DISCRIMINATOR_PREFIX);
        let mut random = RandomSource::new(0x5eed_d15c, WeightDtype::F32);
        for e in &parts.table.entries {
            let from_file = has_discriminator || !e.name.starts_with(DISCRIMINATOR_PREFIX);
            let values = if from_file {
                src.f32(&e.name, &e.shape, e.init)?
            } else {
                random.f32(&e.name, &e.shape, e.init)?
            };
            match e.layout {
                Layout::Dense(layer, first) => {
                    let dense = parts.dense(layer);
                    let (order, all, cols, rows) = (dense.order, dense.rows, dense.cols, first..first + e.shape[0]);
                    let w = &mut parts.params[e.at.clone()];
                    order.for_each(all, cols, |r, c, t| {
                        if rows.contains(&(t / cols)) {
                            w[Matrix::packed_index(r, c, cols)] = values[t - rows.start * cols];
                        }
                    });
                }
                Layout::Conv(shape) => conv_matrix_from_torch(&shape, &values, &mut parts.params[e.at.clone()]),
                Layout::Torch => {
                    let dst = if e.param { &mut parts.params } else { &mut parts.stats };
                    dst[e.at.clone()].copy_from_slice(&values);
                }
            }
        }
        let mut trainer = VaeGanTrainer {
            config,
            settings,
            isa: Isa::best(),
            pool: start_pool(plan.threads)?,
            steps: 0,
            parts,
        };
        let exec = Exec {
            isa: trainer.isa,
            pool: trainer.pool.as_ref(),
        };
        for net in 0..3 {
            trainer.parts.pack(net, exec);
        }
        Ok(trainer)
    }

    /// Uses the kernels of `isa` instead of the best this CPU has.
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    /// One step on `frames` (`[B, H, W, C]` in [-1, 1], `B` at most the plan's batch), with
    /// the reparametrisation draws `eps` and the prior samples `prior` (`[B, z]` each, standard
    /// normal for training): the discriminator's update, then the encoder's and generator's,
    /// at learning rate `lr`. Returns the losses, computed before the updates. Gradients that
    /// are not finite are [`Error::NonFiniteOutput`] before the update they would feed (the
    /// discriminator's, or the encoder's and generator's), which then does not happen, nor do
    /// the moves of that network's running statistics by the step's forward passes.
    pub fn step(&mut self, frames: &[f32], eps: &[f32], prior: &[f32], lr: f32) -> Result<VaeGanLosses> {
        let c = self.config;
        if frames.is_empty()
            || !frames.len().is_multiple_of(c.frame_len())
            || frames.len() / c.frame_len() > self.parts.buffers.batch
        {
            return Err(Error::BufferLength {
                buffer: "frames",
                expected: self.parts.buffers.batch * c.frame_len(),
                found: frames.len(),
            });
        }
        let n = frames.len() / c.frame_len();
        expect_frames("frames", frames)?;
        expect_len("eps", eps, n * c.z_dim)?;
        expect_len("prior", prior, n * c.z_dim)?;
        expect_finite("eps", eps)?;
        expect_finite("prior", prior)?;
        check_lr("lr", lr)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let losses = self
            .parts
            .step(exec, &self.settings, frames, eps, prior, n, lr, self.steps + 1)?;
        self.steps += 1;
        Ok(losses)
    }

    /// Adam steps taken.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// The encoder's, generator's and discriminator's tensors in PyTorch layout (running
    /// statistics included), named as in the weight file.
    pub fn tensors(&self) -> Vec<NamedTensor> {
        let p = &self.parts;
        let entries = p.table.entries.iter();
        entries
            .map(|e| p.torch(e, if e.param { &p.params } else { &p.stats }))
            .collect()
    }

    /// The gradients of the last step (encoder and generator: of their own losses; the
    /// discriminator: of its loss), named as the tensors they belong to.
    pub fn gradients(&self) -> Vec<NamedTensor> {
        let p = &self.parts;
        let params = p.table.entries.iter().filter(|e| e.param);
        params.map(|e| p.torch(e, &p.grads)).collect()
    }

    /// A weight file with the trained networks: `original` (a drivesim weight file of the same
    /// config, e.g. the one training started from) with the encoder's, generator's and
    /// discriminator's tensors replaced (or, for a discriminator it lacked, added), every tensor
    /// in `dtype` (`None`: the file's own), and what it was trained on in its metadata
    /// ([`TrainedOn`](crate::train::TrainedOn); the original's where not given).
    /// [`crate::Model::from_bytes`] reads it.
    #[cfg(feature = "std")]
    pub fn weight_file(
        &self,
        original: &[u8],
        dtype: Option<WeightDtype>,
        trained_on: crate::train::TrainedOn<'_>,
    ) -> Result<Vec<u8>> {
        crate::train::shared::weight_file(original, &self.tensors(), None, dtype, trained_on)
    }
}
