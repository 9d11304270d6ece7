//! A model's heads trained by regression ([`crate::HeadKind`]): each output fitted by mean
//! squared error in units of its own (a mean and a standard deviation each), with Adam.
//!
//! - The **policy** by behavioural cloning: the action the driver took, in the model's action
//!   statistics (`drivesim.actions`).
//! - The **reward** head: the env's reward for a decision and whether the car is off the road
//!   after it (0 or 1: the squared error of a probability, the Brier score).
//! - The **value** head: the λ-returns of drives ([`lambda_returns`]), recomputed with the head
//!   itself between rounds of steps: TD(λ).
//!
//! The examples are the caller's: for each, the head's input `[z | h]` and its targets. For the
//! policy, a recorded frame's code and the transition's hidden state stepped along the drive up
//! to the frame before (as [`crate::Simulator::act`] reads them); for the reward head the state
//! a decision led to (the next frame's code and the hidden state after the step). `train
//! policy` and `train heads` build them from episodes, mirrored too. Parameters, gradients,
//! moments and one batch's activations are one block allocated once; a step allocates nothing.

use super::arena::{cut, cut_ref, Memory};
use super::shared::column_sums;
use super::{Adam, NamedTensor};
use crate::heads::{Head, HeadKind};
use crate::layers::dense;
use crate::pool::Exec;
use crate::weights::{RandomSource, WeightDtype};
use crate::{Config, Error, Model, Result};
use alloc::vec;
use alloc::vec::Vec;
use drivesim_kernels::{Activation, Isa, Matrix, MatrixData};

/// The first 8 bytes of a head trainer's state (`weights/TRAINING_FILES.md`, "Checkpoints"), one
/// kind per head so that one head's state is never read into another's trainer.
fn state_magic(kind: HeadKind) -> &'static [u8; 8] {
    match kind {
        HeadKind::Policy => b"DSPOLI01",
        HeadKind::Reward => b"DSREWA01",
        HeadKind::Value => b"DSVALU01",
        HeadKind::Pace => b"DSPACE01",
    }
}

/// How a [`HeadTrainer`] starts and steps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeadSettings {
    /// Units of the hidden layer of a new head (1 to `hidden_dim`); a head the model has
    /// keeps its own.
    pub width: usize,
    /// Examples per step (at least 1).
    pub batch: usize,
    /// Start a new head from this seed's draw (PyTorch's default initialisation) even where
    /// the model has one (`None`: fine-tune the model's head where it has one, else draw
    /// from seed 0).
    pub restart: Option<u64>,
    /// Adam's constants.
    pub adam: Adam,
}

impl Default for HeadSettings {
    fn default() -> Self {
        HeadSettings {
            width: 64,
            batch: 256,
            restart: None,
            adam: Adam::default(),
        }
    }
}

/// Trains one of a model's heads (see the module's documentation).
pub struct HeadTrainer {
    kind: HeadKind,
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
    /// Each output's mean and standard deviation: the outputs are trained in these units.
    mean: Vec<f32>,
    std: Vec<f32>,
    steps: u32,
}

impl HeadTrainer {
    /// A trainer for `model`'s head of `kind` (or a new one). The policy trains in the model's
    /// action statistics and the pace in its speed's (a model without `drivesim.actions`
    /// metadata in the outputs' own units), the other heads in their outputs' own units: give them better ones with
    /// [`HeadTrainer::with_units`].
    pub fn new(model: &Model, kind: HeadKind, settings: HeadSettings) -> Result<HeadTrainer> {
        let outputs = kind.outputs(model.config());
        let units: Vec<(f32, f32)> = match (kind, model.actions()) {
            (HeadKind::Policy, Some(specs)) => specs.iter().map(|s| (s.mean, s.std)).collect(),
            // The pace is a speed: trained in the speed's statistics.
            (HeadKind::Pace, Some(specs)) => vec![(specs[0].mean, specs[0].std)],
            _ => vec![(0.0, 1.0); outputs],
        };
        HeadTrainer::with_units(model, kind, &units, settings)
    }

    /// [`HeadTrainer::new`] training in `units`: each output's `(mean, standard deviation)`
    /// (e.g. of its targets), one per output, finite, the deviations above zero
    /// ([`Error::Setting`] otherwise). The units change how the steps condition the outputs,
    /// not what the trained head computes.
    pub fn with_units(
        model: &Model,
        kind: HeadKind,
        units: &[(f32, f32)],
        settings: HeadSettings,
    ) -> Result<HeadTrainer> {
        settings.adam.check()?;
        let config = *model.config();
        let a = kind.outputs(&config);
        if units.len() != a {
            return Err(Error::Config {
                field: "units (a mean and a deviation per output)",
                expected: "one per output of the head",
                found: units.len(),
            });
        }
        for &(mean, std) in units {
            if !mean.is_finite() {
                let expected = "finite";
                return Err(Error::Setting {
                    name: "units' mean",
                    expected,
                    value: mean,
                });
            }
            if !(std.is_finite() && std > 0.0) {
                let expected = "finite and above 0";
                return Err(Error::Setting {
                    name: "units' deviation",
                    expected,
                    value: std,
                });
            }
        }
        let drawn;
        let head = match (model.head(kind), settings.restart) {
            (Some(head), None) => head,
            (_, seed) => {
                let width = settings.width;
                if !(1..=config.hidden_dim).contains(&width) {
                    return Err(Error::Config {
                        field: "head width",
                        expected: "1 to hidden_dim",
                        found: width,
                    });
                }
                let mut src = RandomSource::new(seed.unwrap_or(0), WeightDtype::F32);
                drawn = Head::read(&config, &mut src, kind, width)?;
                &drawn
            }
        };
        if settings.batch == 0 {
            return Err(Error::Config {
                field: "head batch",
                expected: "at least 1",
                found: 0,
            });
        }
        let (width, cols) = (head.width(), config.z_dim + config.hidden_dim);
        let (mean, std): (Vec<f32>, Vec<f32>) = units.iter().copied().unzip();
        let per_batch = |n: usize| {
            n.checked_mul(settings.batch).ok_or(Error::OutOfMemory {
                what: "the head trainer's memory",
                bytes: None,
            })
        };
        let params = Matrix::packed_len(width, cols) + width + Matrix::packed_len(a, width) + a;
        let (hidden, out) = (per_batch(width)?, per_batch(a)?);
        let lens = [params, params, params, params, hidden, hidden, out, out];
        let floats = super::arena::total(&lens, "the head trainer's memory")?;
        let bytes = super::arena::bytes_of(floats, "the head trainer's memory")?;
        let mut trainer = HeadTrainer {
            kind,
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
        trainer.start_from(head);
        Ok(trainer)
    }

    /// Copies the head's packed layers into the parameters, in the trainer's scaled units.
    fn start_from(&mut self, head: &Head) {
        let (hidden, output) = head.layers();
        let (mean, std) = (self.mean.clone(), self.std.clone());
        let (lens, width, params) = (self.param_lens(), self.width, self.lens[0]);
        let [w1, b1, w2, b2] = cut(&mut self.memory.floats()[..params], &lens);
        copy_packed(hidden.matrix().data, w1);
        b1.copy_from_slice(&hidden.bias);
        copy_packed(output.matrix().data, w2);
        // Scaled units: output r is (value r - mean r) / std r.
        for (r, (s, m)) in std.iter().zip(&mean).enumerate() {
            for c in 0..width {
                w2[Matrix::packed_index(r, c, width)] /= s;
            }
            b2[r] = (output.bias[r] - m) / s;
        }
    }

    fn param_lens(&self) -> [usize; 4] {
        let (cols, a) = (self.config.z_dim + self.config.hidden_dim, self.outputs());
        [
            Matrix::packed_len(self.width, cols),
            self.width,
            Matrix::packed_len(a, self.width),
            a,
        ]
    }

    /// Units of the head's hidden layer.
    pub fn width(&self) -> usize {
        self.width
    }

    /// The head this trains.
    pub fn kind(&self) -> HeadKind {
        self.kind
    }

    /// Outputs per example.
    fn outputs(&self) -> usize {
        self.kind.outputs(&self.config)
    }

    /// Adam steps taken.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// One Adam step at learning rate `lr` on a batch of examples: `inputs` `[z | h]` per
    /// example, `targets` the head's outputs per example ([`HeadKind::outputs`]), at most the
    /// planned batch. Returns the batch's loss before the step (mean squared error in the
    /// scaled units).
    pub fn step(&mut self, inputs: &[f32], targets: &[f32], lr: f32) -> Result<f32> {
        super::shared::check_lr("lr", lr)?;
        let loss = self.forward_backward(inputs, targets, true)?;
        self.steps += 1;
        let lens = self.lens;
        let [params, grads, m, v, ..] = cut(self.memory.floats(), &lens);
        self.adam.update(self.steps, lr, 1.0, params, grads, [m, v]);
        Ok(loss)
    }

    /// The loss on a batch of examples, as [`HeadTrainer::step`] measures it, without a step.
    pub fn loss(&mut self, inputs: &[f32], targets: &[f32]) -> Result<f32> {
        self.forward_backward(inputs, targets, false)
    }

    /// The forward pass and its loss, then (with `gradients`) every parameter's gradient.
    fn forward_backward(&mut self, inputs: &[f32], targets: &[f32], gradients: bool) -> Result<f32> {
        let (cols, a, width) = (self.config.z_dim + self.config.hidden_dim, self.outputs(), self.width);
        let n = crate::error::whole_items("inputs", inputs, cols)?;
        if n > self.batch {
            return Err(Error::BatchTooLarge {
                max: self.batch,
                found: n,
            });
        }
        crate::error::expect_len("targets", targets, n * a)?;
        crate::error::expect_finite("inputs", inputs)?;
        crate::error::expect_finite("targets", targets)?;
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
        for (i, ((o, g), y)) in out.iter().zip(dout.iter_mut()).zip(targets).enumerate() {
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

    /// The head's tensors in PyTorch layout and the outputs' own units (the scaling folded
    /// into the output layer): e.g. `policy.hidden.weight`, `.bias`, `policy.output.weight`,
    /// `.bias`.
    pub fn tensors(&self) -> Vec<NamedTensor> {
        let (cols, a, width) = (self.config.z_dim + self.config.hidden_dim, self.outputs(), self.width);
        let name = |part: &str| alloc::format!("{}{part}", self.kind.prefix());
        let [w1, b1, w2, b2] = cut_ref(&self.memory.floats_ref()[..self.lens[0]], &self.param_lens());
        let unpack = |w: &[f32], rows, cols, scale: &dyn Fn(usize) -> f32| -> Vec<f32> {
            (0..rows * cols)
                .map(|i| scale(i / cols) * w[Matrix::packed_index(i / cols, i % cols, cols)])
                .collect()
        };
        let output_bias = b2.iter().enumerate().map(|(r, b)| b * self.std[r] + self.mean[r]);
        vec![
            (
                name("hidden.weight"),
                vec![width, cols],
                unpack(w1, width, cols, &|_| 1.0),
            ),
            (name("hidden.bias"), vec![width], b1.to_vec()),
            (
                name("output.weight"),
                vec![a, width],
                unpack(w2, a, width, &|r| self.std[r]),
            ),
            (name("output.bias"), vec![a], output_bias.collect()),
        ]
    }

    /// Bytes of [`HeadTrainer::save_state`]'s state.
    pub fn state_len(&self) -> usize {
        let a = self.outputs();
        super::state::state_len(5, 3 * self.lens[0] + 2 * a)
    }

    fn sizes(&self) -> [u32; 4] {
        let c = &self.config;
        [self.width, c.z_dim, c.hidden_dim, self.outputs()].map(|n| n as u32)
    }

    /// Writes the trainer's state into `out` ([`HeadTrainer::state_len`] bytes): the
    /// parameters, Adam's moments and step count, and the output units it trains in. A trainer
    /// that [`HeadTrainer::load_state`] reads it back goes on bit for bit as this one would.
    pub fn save_state(&self, out: &mut [u8]) -> Result<()> {
        let [params, _, m, v, ..] = cut_ref(self.memory.floats_ref(), &self.lens);
        let [width, z, hd, a] = self.sizes();
        let buffers = [params, m, v, &self.mean, &self.std];
        super::state::write_state(out, state_magic(self.kind), &[width, z, hd, a, self.steps], &buffers)
    }

    /// Restores a state [`HeadTrainer::save_state`] wrote, for the same head of the same width
    /// and model sizes (any batch). A state of other sizes, of another head or truncated is
    /// [`Error::Malformed`], one holding a non-finite value [`Error::BadWeight`]; then the
    /// trainer is unchanged.
    pub fn load_state(&mut self, state: &[u8]) -> Result<()> {
        let (sizes, lens) = (self.sizes(), self.lens);
        let [params, _, m, v, ..] = cut(self.memory.floats(), &lens);
        let buffers = &mut [params, m, v, &mut self.mean[..], &mut self.std[..]];
        self.steps = super::state::read_state(state, state_magic(self.kind), "head trainer state", &sizes, buffers)?;
        Ok(())
    }

    /// `original` (the model's weight file) with this head's tensors added (or in place of its
    /// own head of this kind, of any width), in the file's dtype, with the metadata of
    /// `trained_on` (a value head's `discount`): a file [`Model::load`] reads, whose
    /// [`crate::Simulator::act`] (or reward or value) is this head.
    #[cfg(feature = "std")]
    pub fn weight_file(&self, original: &[u8], trained_on: super::TrainedOn<'_>) -> Result<Vec<u8>> {
        let (config, ..) = crate::weights::SafetensorsSource::parse(original)?;
        if config != self.config {
            return Err(Error::Metadata {
                reason: alloc::format!("the file's config is {config:?}, the trainer's {:?}", self.config),
            });
        }
        // The file's own head of this kind goes, whatever its width.
        let group = Some(self.kind.prefix());
        super::shared::weight_file(original, &self.tensors(), group, None, trained_on)
    }
}

/// A packed layer's weights into `out` as f32 (f16 ones widened exactly).
fn copy_packed(data: MatrixData<'_>, out: &mut [f32]) {
    match data {
        MatrixData::F32(w) => out.copy_from_slice(w),
        MatrixData::F16(w) => out.iter_mut().zip(w).for_each(|(o, w)| *o = w.to_f32()),
    }
}
