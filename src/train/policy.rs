//! Behavioural cloning of a driver: the model's policy (`policy.*`, see [`crate::Simulator::act`])
//! trained to give the action the driver took, by mean squared error on the actions scaled by
//! the model's action statistics (`drivesim.actions`: each action's mean and standard deviation),
//! with Adam.
//!
//! The examples are the caller's: for each recorded frame, the policy's input `[z | h]` (the
//! frame's code and the transition's hidden state stepped along the drive up to the frame
//! before, as [`crate::Simulator::act`] reads them) and the action to learn (e.g. the steering
//! the driver applied and the speed it reached a moment later). `train policy` builds them from
//! episodes, mirrored too. Parameters, gradients, moments and one batch's activations are one
//! block allocated once; a step allocates nothing.

use super::arena::{cut, cut_ref, Memory};
use super::shared::column_sums;
use super::{Adam, NamedTensor};
use crate::layers::dense;
use crate::policy::Policy;
use crate::pool::Exec;
use crate::weights::{RandomSource, WeightDtype};
use crate::{Config, Error, Model, Result};
use alloc::string::ToString;
use alloc::vec;
use alloc::vec::Vec;
use drivesim_kernels::{Activation, Isa, Matrix, MatrixData};

/// The first 8 bytes of a policy trainer's state (`weights/README.md`, "Checkpoints").
const STATE_MAGIC: &[u8; 8] = b"DSPOLI01";

/// How a [`PolicyTrainer`] starts and steps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PolicySettings {
    /// Units of the hidden layer of a new policy (1 to `hidden_dim`); a policy the model has
    /// keeps its own.
    pub width: usize,
    /// Examples per step (at least 1).
    pub batch: usize,
    /// Start a new policy from this seed's draw (PyTorch's default initialisation) even where
    /// the model has one (`None`: fine-tune the model's policy where it has one, else draw
    /// from seed 0).
    pub restart: Option<u64>,
    /// Adam's constants.
    pub adam: Adam,
}

impl Default for PolicySettings {
    fn default() -> Self {
        PolicySettings {
            width: 64,
            batch: 256,
            restart: None,
            adam: Adam::default(),
        }
    }
}

/// Trains a model's policy by behavioural cloning (see the module's documentation).
pub struct PolicyTrainer {
    config: Config,
    width: usize,
    batch: usize,
    adam: Adam,
    isa: Isa,
    /// The floats of each buffer of `memory`, in order: parameters, gradients and Adam's two
    /// moments (each `[W1 | b1 | W2 | b2]`, weights packed), a batch's hidden activations and
    /// their gradient, its outputs and their gradient.
    lens: [usize; 8],
    memory: Memory<'static>,
    /// Each action's mean and standard deviation: the outputs are trained in these units.
    mean: Vec<f32>,
    std: Vec<f32>,
    steps: u32,
}

impl PolicyTrainer {
    /// A trainer for `model`'s policy (or a new one), in the model's action statistics; a model
    /// without `drivesim.actions` metadata trains in the actions' own units.
    pub fn new(model: &Model, settings: PolicySettings) -> Result<PolicyTrainer> {
        settings.adam.check()?;
        let config = *model.config();
        let drawn;
        let policy = match (&model.policy, settings.restart) {
            (Some(policy), None) => policy,
            (_, seed) => {
                let width = settings.width;
                if !(1..=config.hidden_dim).contains(&width) {
                    return Err(Error::Config {
                        field: "policy width",
                        expected: "1 to hidden_dim",
                        found: width,
                    });
                }
                let mut src = RandomSource::new(seed.unwrap_or(0), WeightDtype::F32);
                drawn = Policy::read(&config, &mut src, width)?;
                &drawn
            }
        };
        if settings.batch == 0 {
            return Err(Error::Config {
                field: "policy batch",
                expected: "at least 1",
                found: 0,
            });
        }
        let (width, cols, a) = (policy.width(), config.z_dim + config.hidden_dim, config.action_dim);
        let (mean, std): (Vec<f32>, Vec<f32>) = match model.actions() {
            Some(specs) => specs.iter().map(|s| (s.mean, s.std)).unzip(),
            None => (vec![0.0; a], vec![1.0; a]),
        };
        let per_batch = |n: usize| {
            n.checked_mul(settings.batch).ok_or(Error::OutOfMemory {
                what: "the policy trainer's memory",
                bytes: None,
            })
        };
        let params = Matrix::packed_len(width, cols) + width + Matrix::packed_len(a, width) + a;
        let (hidden, out) = (per_batch(width)?, per_batch(a)?);
        let lens = [params, params, params, params, hidden, hidden, out, out];
        let floats = super::arena::total(&lens, "the policy trainer's memory")?;
        let bytes = super::arena::bytes_of(floats, "the policy trainer's memory")?;
        let mut trainer = PolicyTrainer {
            config,
            width,
            batch: settings.batch,
            adam: settings.adam,
            isa: Isa::best(),
            lens,
            memory: Memory::allocate(floats, bytes)?,
            mean,
            std,
            steps: 0,
        };
        trainer.start_from(policy);
        Ok(trainer)
    }

    /// Copies the policy's packed layers into the parameters, in the trainer's scaled units.
    fn start_from(&mut self, policy: &Policy) {
        let (hidden, output) = policy.layers();
        let (mean, std) = (self.mean.clone(), self.std.clone());
        let (lens, width, params) = (self.param_lens(), self.width, self.lens[0]);
        let [w1, b1, w2, b2] = cut(&mut self.memory.floats()[..params], &lens);
        copy_packed(hidden.matrix().data, w1);
        b1.copy_from_slice(&hidden.bias);
        copy_packed(output.matrix().data, w2);
        // Scaled units: output r is (action r - mean r) / std r.
        for (r, (s, m)) in std.iter().zip(&mean).enumerate() {
            for c in 0..width {
                w2[Matrix::packed_index(r, c, width)] /= s;
            }
            b2[r] = (output.bias[r] - m) / s;
        }
    }

    fn param_lens(&self) -> [usize; 4] {
        let (cols, a) = (self.config.z_dim + self.config.hidden_dim, self.config.action_dim);
        [
            Matrix::packed_len(self.width, cols),
            self.width,
            Matrix::packed_len(a, self.width),
            a,
        ]
    }

    /// Units of the policy's hidden layer.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Adam steps taken.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// One Adam step at learning rate `lr` on a batch of examples: `inputs` `[z | h]` per
    /// example, `actions` `action_dim` values per example, at most the planned batch. Returns
    /// the batch's loss before the step (mean squared error in the scaled units).
    pub fn step(&mut self, inputs: &[f32], actions: &[f32], lr: f32) -> Result<f32> {
        super::shared::check_lr("lr", lr)?;
        let loss = self.forward_backward(inputs, actions, true)?;
        self.steps += 1;
        let lens = self.lens;
        let [params, grads, m, v, ..] = cut(self.memory.floats(), &lens);
        self.adam.update(self.steps, lr, 1.0, params, grads, [m, v]);
        Ok(loss)
    }

    /// The loss on a batch of examples, as [`PolicyTrainer::step`] measures it, without a step.
    pub fn loss(&mut self, inputs: &[f32], actions: &[f32]) -> Result<f32> {
        self.forward_backward(inputs, actions, false)
    }

    /// The forward pass and its loss, then (with `gradients`) every parameter's gradient.
    fn forward_backward(&mut self, inputs: &[f32], actions: &[f32], gradients: bool) -> Result<f32> {
        let (cols, a, width) = (
            self.config.z_dim + self.config.hidden_dim,
            self.config.action_dim,
            self.width,
        );
        let n = crate::error::whole_items("inputs", inputs, cols)?;
        if n > self.batch {
            return Err(Error::BatchTooLarge {
                max: self.batch,
                found: n,
            });
        }
        crate::error::expect_len("actions", actions, n * a)?;
        crate::error::expect_finite("inputs", inputs)?;
        crate::error::expect_finite("actions", actions)?;
        let exec = Exec {
            isa: self.isa,
            pool: None,
        };
        let (mean, std) = (&self.mean, &self.std);
        let (lens, param_lens) = (self.lens, self.param_lens());
        let [params, grads, _, _, hidden, dhidden, out, dout] = cut(self.memory.floats(), &lens);
        let [w1, b1, w2, b2] = cut_ref(params, &param_lens);
        let matrix = |w, rows, cols| Matrix {
            data: MatrixData::F32(w),
            rows,
            cols,
        };
        let (hidden, out) = (&mut hidden[..n * width], &mut out[..n * a]);
        dense(exec, matrix(w1, width, cols), b1, Activation::Tanh, inputs, hidden);
        dense(exec, matrix(w2, a, width), b2, Activation::Identity, hidden, out);
        let (dhidden, dout) = (&mut dhidden[..n * width], &mut dout[..n * a]);
        let (mut sum, scale) = (0.0f64, 2.0 / (n * a) as f32);
        for (i, ((o, g), y)) in out.iter().zip(dout.iter_mut()).zip(actions).enumerate() {
            let error = o - (y - mean[i % a]) / std[i % a];
            sum += (error as f64) * (error as f64);
            *g = scale * error;
        }
        let loss = (sum / (n * a) as f64) as f32;
        if !loss.is_finite() {
            return Err(Error::NonFiniteOutput {
                buffer: "loss",
                index: 0,
            });
        }
        if gradients {
            let [gw1, gb1, gw2, gb2] = cut(grads, &param_lens);
            drivesim_kernels::dense_weight_grad(self.isa, dout, hidden, a, width, gw2);
            column_sums(dout, gb2);
            drivesim_kernels::dense_data_grad(self.isa, w2, a, width, dout, dhidden);
            drivesim_kernels::activation_backward(self.isa, Activation::Tanh, hidden, dhidden);
            drivesim_kernels::dense_weight_grad(self.isa, dhidden, inputs, width, cols, gw1);
            column_sums(dhidden, gb1);
        }
        Ok(loss)
    }

    /// The policy's tensors in PyTorch layout and the model's action units (the scaling folded
    /// into the output layer): `policy.hidden.weight`, `.bias`, `policy.output.weight`, `.bias`.
    pub fn tensors(&self) -> Vec<NamedTensor> {
        let (cols, a, width) = (
            self.config.z_dim + self.config.hidden_dim,
            self.config.action_dim,
            self.width,
        );
        let [w1, b1, w2, b2] = cut_ref(&self.memory.floats_ref()[..self.lens[0]], &self.param_lens());
        let unpack = |w: &[f32], rows, cols, scale: &dyn Fn(usize) -> f32| -> Vec<f32> {
            (0..rows * cols)
                .map(|i| scale(i / cols) * w[Matrix::packed_index(i / cols, i % cols, cols)])
                .collect()
        };
        let output_bias = b2.iter().enumerate().map(|(r, b)| b * self.std[r] + self.mean[r]);
        vec![
            (
                "policy.hidden.weight".to_string(),
                vec![width, cols],
                unpack(w1, width, cols, &|_| 1.0),
            ),
            ("policy.hidden.bias".to_string(), vec![width], b1.to_vec()),
            (
                "policy.output.weight".to_string(),
                vec![a, width],
                unpack(w2, a, width, &|r| self.std[r]),
            ),
            ("policy.output.bias".to_string(), vec![a], output_bias.collect()),
        ]
    }

    /// Bytes of [`PolicyTrainer::save_state`]'s state.
    pub fn state_len(&self) -> usize {
        let a = self.config.action_dim;
        super::state::state_len(5, 3 * self.lens[0] + 2 * a)
    }

    fn sizes(&self) -> [u32; 4] {
        let c = &self.config;
        [self.width, c.z_dim, c.hidden_dim, c.action_dim].map(|n| n as u32)
    }

    /// Writes the trainer's state into `out` ([`PolicyTrainer::state_len`] bytes): the
    /// parameters, Adam's moments and step count, and the action units it trains in. A trainer
    /// that [`PolicyTrainer::load_state`] reads it back goes on bit for bit as this one would.
    pub fn save_state(&self, out: &mut [u8]) -> Result<()> {
        let [params, _, m, v, ..] = cut_ref(self.memory.floats_ref(), &self.lens);
        let [width, z, hd, a] = self.sizes();
        let buffers = [params, m, v, &self.mean, &self.std];
        super::state::write_state(out, STATE_MAGIC, &[width, z, hd, a, self.steps], &buffers)
    }

    /// Restores a state [`PolicyTrainer::save_state`] wrote, for a policy of the same width and
    /// model sizes (any batch). A state of other sizes, of another kind or truncated is
    /// [`Error::Malformed`], one holding a non-finite value [`Error::BadWeight`]; then the
    /// trainer is unchanged.
    pub fn load_state(&mut self, state: &[u8]) -> Result<()> {
        let (sizes, lens) = (self.sizes(), self.lens);
        let [params, _, m, v, ..] = cut(self.memory.floats(), &lens);
        let buffers = &mut [params, m, v, &mut self.mean[..], &mut self.std[..]];
        self.steps = super::state::read_state(state, STATE_MAGIC, "policy trainer state", &sizes, buffers)?;
        Ok(())
    }

    /// `original` (the model's weight file) with this policy's tensors added (or in place of
    /// its own policy, of any width), in the file's dtype: a file [`Model::load`] reads, whose
    /// [`crate::Simulator::act`] is this policy.
    #[cfg(feature = "std")]
    pub fn weight_file(&self, original: &[u8]) -> Result<Vec<u8>> {
        let (config, ..) = crate::weights::SafetensorsSource::parse(original)?;
        if config != self.config {
            return Err(Error::Metadata {
                reason: alloc::format!("the file's config is {config:?}, the trainer's {:?}", self.config),
            });
        }
        // The file's own policy goes, whatever its width.
        let group = Some(crate::policy::POLICY_PREFIX);
        super::shared::weight_file(original, &self.tensors(), group, None, super::TrainedOn::default())
    }
}

/// A packed layer's weights into `out` as f32 (f16 ones widened exactly).
fn copy_packed(data: MatrixData<'_>, out: &mut [f32]) {
    match data {
        MatrixData::F32(w) => out.copy_from_slice(w),
        MatrixData::F16(w) => out.iter_mut().zip(w).for_each(|(o, w)| *o = w.to_f32()),
    }
}
