//! [`TransitionTrainer`]'s public API: starting from a model, the steps (gradients, clipping,
//! Adam), predictions, action gradients, and the trained tensors in PyTorch layout.

use super::plan::{Dims, TransitionPlan};
use super::settings::{check_settings, Backward, TransitionSettings};
use super::threads::squares;
use crate::error::{expect_finite, expect_finite_output, expect_len};
use crate::pool::{Exec, Pool};
use crate::train::arena::{cut, cut_ref, Memory};
use crate::train::shared::check_lr;
#[cfg(feature = "std")]
use crate::train::shared::start_pool;
use crate::train::NamedTensor;
use crate::{Error, Model, Result};
use alloc::vec;
use alloc::vec::Vec;
use drivesim_kernels::{math, Isa, Matrix};

/// The tensors a transition has, in PyTorch layout: name, shape (the spread head's last).
fn tensor_shapes(d: &Dims) -> [(&'static str, [usize; 2]); 8] {
    let (h, z, a) = (d.hidden, d.z, d.actions);
    [
        ("transition.W", [h, h]),
        ("transition.V", [h, z]),
        ("transition.U", [h, a]),
        ("transition.b", [h, 1]),
        ("transition.A", [z, h]),
        ("transition.a", [z, 1]),
        ("transition.S", [z, h]),
        ("transition.s", [z, 1]),
    ]
}

/// Trains a model's transition in the memory of a [`TransitionPlan`], allocated once (or the
/// caller's): a step allocates nothing.
///
/// ```
/// use drivesim::train::{TransitionPlan, TransitionSettings, TransitionTrainer};
/// use drivesim::{Config, Model, WeightDtype};
///
/// let config = Config { z_dim: 8, hidden_dim: 16, ..Config::COMMA };
/// let model = Model::random(&config, 1, WeightDtype::F32)?;
/// let (batch, window) = (4, 15);
/// let plan = TransitionPlan::new(&config, batch, window)?;
/// let mut trainer = TransitionTrainer::new(&model, &plan, TransitionSettings::default())?;
///
/// // Windows of codes [batch, window, z] and the actions between them [batch, window - 1, 2].
/// let codes: Vec<f32> = (0..batch * window * 8).map(|i| (i as f32 * 0.37).sin()).collect();
/// let actions = vec![0.1; batch * (window - 1) * 2];
/// let first = trainer.step(&codes, &actions, 1e-2)?;
/// for _ in 0..50 {
///     trainer.step(&codes, &actions, 1e-2)?;
/// }
/// assert!(trainer.step(&codes, &actions, 1e-2)? < first);
/// # Ok::<(), drivesim::Error>(())
/// ```
pub struct TransitionTrainer<'a> {
    pub(super) plan: TransitionPlan,
    pub(super) settings: TransitionSettings,
    pub(super) memory: Memory<'a>,
    pub(super) isa: Isa,
    pub(super) pool: Option<Pool>,
    /// Adam steps taken so far.
    steps: u32,
    /// The global gradient norm of the gradients computed last, if they were not applied yet.
    pending: Option<f32>,
    /// Whether the transposed packings hold the current weights.
    pub(super) transposed: bool,
}

impl TransitionTrainer<'static> {
    /// A trainer starting from `model`'s transition, its arena allocated once here (an
    /// allocation the allocator refuses is [`Error::OutOfMemory`] naming the plan's bytes).
    pub fn new(model: &Model, plan: &TransitionPlan, settings: TransitionSettings) -> Result<Self> {
        let memory = Memory::allocate(plan.floats(), plan.bytes())?;
        TransitionTrainer::start(model, plan, settings, memory)
    }
}

impl<'a> TransitionTrainer<'a> {
    /// [`TransitionTrainer::new`] in the caller's `arena` (at least [`TransitionPlan::bytes`];
    /// a smaller one is [`Error::ArenaTooSmall`]), e.g. static memory without an allocator.
    pub fn with_arena(
        model: &Model,
        plan: &TransitionPlan,
        settings: TransitionSettings,
        arena: &'a mut [f32],
    ) -> Result<Self> {
        let memory = Memory::borrow(arena, plan.floats())?;
        TransitionTrainer::start(model, plan, settings, memory)
    }

    fn start(model: &Model, plan: &TransitionPlan, settings: TransitionSettings, memory: Memory<'a>) -> Result<Self> {
        let c = model.config();
        let d = plan.dims;
        for (field, model_has, planned) in [
            ("hidden_dim", c.hidden_dim, d.hidden),
            ("z_dim", c.z_dim, d.z),
            ("action_dim", c.action_dim, d.actions),
        ] {
            if model_has != planned {
                return Err(Error::Config {
                    field,
                    expected: "the plan's value",
                    found: model_has,
                });
            }
        }
        check_settings(&settings)?;
        let spread = model.transition.spread_layer();
        if spread.is_some() && !d.spread {
            return Err(Error::Config {
                field: "spread head",
                expected: "a plan with room for it (TransitionPlan::with_spread), as the model has one",
                found: 0,
            });
        }
        let mut trainer = TransitionTrainer {
            plan: plan.clone(),
            settings,
            memory,
            isa: Isa::best(),
            pool: None,
            steps: 0,
            pending: None,
            transposed: false,
        };
        let [params, .., norm, _] = cut(trainer.memory.floats(), &trainer.plan.lens);
        let [wx, bx, wa, ba, ws, bs] = cut(params, &d.params());
        model.transition.trainer_weights((wx, bx), (wa, ba));
        match spread {
            Some(layer) => {
                layer.copy_packed(ws);
                bs.copy_from_slice(&layer.bias);
            }
            // A new spread head: zeros, a unit spread to start from.
            None => {
                ws.fill(0.0);
                bs.fill(0.0);
            }
        }
        // Identity normalisation: mean 0, standard deviation 1.
        norm[d.actions..].fill(1.0);
        Ok(trainer)
    }

    /// Uses the kernels of `isa` instead of the best this CPU has.
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    /// Shares each product among `threads` threads (the caller's included), started here once.
    /// Results are bit-identical whatever the thread count.
    #[cfg(feature = "std")]
    pub fn with_threads(mut self, threads: usize) -> Result<Self> {
        self.pool = None;
        self.pool = start_pool(threads)?;
        Ok(self)
    }

    /// The settings in use.
    pub fn settings(&self) -> &TransitionSettings {
        &self.settings
    }

    /// Trains on actions normalised as `(c - mean) / std` (as `weights/drivesim_reference/train.py` does, so that
    /// speed in metres per second and steering in [-1, 1] weigh alike), while every method
    /// keeps taking and returning raw actions: the model's `U` and `b` are rewritten for
    /// normalised actions here and folded back in [`TransitionTrainer::tensors`]. Resets Adam.
    pub fn set_action_normalisation(&mut self, mean: &[f32], std: &[f32]) -> Result<()> {
        let (d, a) = (self.plan.dims, self.plan.dims.actions);
        expect_len("mean", mean, a)?;
        expect_len("std", std, a)?;
        expect_finite("mean", mean)?;
        expect_finite("std", std)?;
        if let Some(&s) = std.iter().find(|&&s| s.is_nan() || s <= 0.0) {
            return Err(Error::Setting {
                name: "std",
                expected: "positive",
                value: s,
            });
        }
        let [params, grads, m, v, .., norm, _] = cut(self.memory.floats(), &self.plan.lens);
        let [wx, bx, ..] = cut(params, &d.params());
        let (old_mean, old_std) = norm.split_at_mut(a);
        let cols = d.cols();
        for r in 0..d.hidden {
            for j in 0..a {
                let u = &mut wx[Matrix::packed_index(r, d.hidden + d.z + j, cols)];
                // Raw-action weight, then the same map for the new normalisation.
                let raw = *u / old_std[j];
                bx[r] += raw * (mean[j] - old_mean[j]);
                *u = raw * std[j];
            }
        }
        old_mean.copy_from_slice(mean);
        old_std.copy_from_slice(std);
        for buffer in [grads, m, v] {
            buffer.fill(0.0);
        }
        self.steps = 0;
        self.pending = None;
        self.transposed = false;
        Ok(())
    }

    /// One training step: [`TransitionTrainer::compute_gradients`], then
    /// [`TransitionTrainer::apply_gradients`] with learning rate `lr`. Returns the loss before
    /// the step.
    pub fn step(&mut self, codes: &[f32], actions: &[f32], lr: f32) -> Result<f32> {
        let loss = self.compute_gradients(codes, actions)?;
        self.apply_gradients(lr)?;
        Ok(loss)
    }

    /// The loss of a batch of windows and its gradient with respect to every weight (see
    /// [`TransitionTrainer::gradients`]), without changing the weights.
    ///
    /// `codes` holds `[batch, window, z]` values (each window's codes in order), `actions`
    /// `[batch, window - 1, action_dim]` (the action taken after each code but the last), raw.
    /// The loss is the mean squared error of the `window - 1` predictions (plus, with the spread
    /// head, its negative log-likelihood: `weights/TRAINING_FILES.md`).
    pub fn compute_gradients(&mut self, codes: &[f32], actions: &[f32]) -> Result<f32> {
        let batch = self.check_batch(codes, actions)?;
        let loss = self.forward(codes, actions, batch)?;
        self.backward(codes, batch, Backward::Weights)?;
        let [_, grads, ..] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        // The norm that clipping scales by is the mean's alone: the spread head's loss is one of
        // its own, and Adam bounds its steps (`weights/drivesim_reference/sequences.py`'s `transition_step`).
        let grads = &grads[..self.plan.dims.clipped()];
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let norm = math::sqrt(squares(exec, grads)) as f32;
        if !norm.is_finite() {
            return Err(Error::NonFiniteOutput {
                buffer: "gradients",
                index: grads.iter().position(|g| !g.is_finite()).unwrap_or(0),
            });
        }
        self.pending = Some(norm);
        Ok(loss)
    }

    /// Adam steps taken so far.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// After a restored state: `steps` Adam steps taken, no gradients pending, the transposed
    /// packings to be made again.
    pub(super) fn restore_steps(&mut self, steps: u32) {
        self.steps = steps;
        self.pending = None;
        self.transposed = false;
    }

    /// The global L2 norm of the gradients computed last (before clipping), if they were not
    /// applied yet.
    pub fn gradient_norm(&self) -> Option<f32> {
        self.pending
    }

    /// One Adam step with learning rate `lr` on the gradients computed last, clipped to the
    /// settings' norm first. An error if there are none, or if `lr` is negative or not finite.
    pub fn apply_gradients(&mut self, lr: f32) -> Result<()> {
        check_lr("learning rate", lr)?;
        let norm = self.pending.take().ok_or(Error::NoGradients)?;
        // torch.nn.utils.clip_grad_norm_: scale by max_norm / (norm + 1e-6), at most 1.
        let scale = (self.settings.clip / (norm + 1e-6)).min(1.0);
        self.steps += 1;
        let [params, grads, m, v, ..] = cut(self.memory.floats(), &self.plan.lens);
        let at = self.plan.dims.clipped();
        let (params, spread_params) = params.split_at_mut(at);
        let ((grads, spread_grads), (m, spread_m), (v, spread_v)) =
            (grads.split_at(at), m.split_at_mut(at), v.split_at_mut(at));
        let (adam, t) = (self.settings.adam, self.steps);
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        adam.update_shared(exec, (t, lr, scale), params, grads, [m, v]);
        adam.update_shared(exec, (t, lr, 1.0), spread_params, spread_grads, [spread_m, spread_v]);
        self.transposed = false;
        Ok(())
    }

    /// The predictions of a batch of windows (`[batch, window - 1, z]`: the code after each
    /// input, teacher-forced as in training) and their loss against the codes.
    pub fn predict(&mut self, codes: &[f32], actions: &[f32], predictions: &mut [f32]) -> Result<f32> {
        let batch = self.check_batch(codes, actions)?;
        let d = self.plan.dims;
        expect_len("predictions", predictions, batch * d.steps() * d.z)?;
        let loss = self.forward(codes, actions, batch)?;
        let [.., outs, _, _, _, _, _, _, _] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        for (n, window) in predictions.chunks_exact_mut(d.steps() * d.z).enumerate() {
            for (t, out) in window.chunks_exact_mut(d.z).enumerate() {
                out.copy_from_slice(&outs[(t * batch + n) * d.z..][..d.z]);
            }
        }
        Ok(loss)
    }

    /// The loss of a batch of windows and its gradient with respect to the actions
    /// (`[batch, window - 1, action_dim]`, raw units), the weights fixed: what recovering the
    /// actions of a video optimises. With detached feedback (the default), only the actions a
    /// prediction's hidden state saw reach it.
    pub fn action_gradients(&mut self, codes: &[f32], actions: &[f32], gradient: &mut [f32]) -> Result<f32> {
        let batch = self.check_batch(codes, actions)?;
        let d = self.plan.dims;
        expect_len("gradient", gradient, actions.len())?;
        let loss = self.forward(codes, actions, batch)?;
        self.backward(codes, batch, Backward::Inputs)?;
        let [.., dzc, _, _, norm, _] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        let (a, std) = (d.actions, &norm[d.actions..]);
        for (n, window) in gradient.chunks_exact_mut(d.steps() * a).enumerate() {
            for (t, g) in window.chunks_exact_mut(a).enumerate() {
                let dc = &dzc[(t * batch + n) * (d.z + a) + d.z..][..a];
                // The model sees (c - mean) / std.
                for ((g, dc), s) in g.iter_mut().zip(dc).zip(std) {
                    *g = dc / s;
                }
            }
        }
        expect_finite_output("gradient", gradient)?;
        Ok(loss)
    }

    /// The transition's tensors in PyTorch layout (`transition.W`, `.V`, `.U`, `.b`, `.A`,
    /// `.a`), for raw actions (the normalisation folded into `U` and `b`).
    pub fn tensors(&self) -> Vec<NamedTensor> {
        let [params, .., norm, _] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        let mut tensors = self.unpack(params);
        let d = self.plan.dims;
        let (mean, std) = norm.split_at(d.actions);
        // U c_norm + b = (U / std) c + (b - (U / std) mean).
        let (u, b) = split_pair(&mut tensors, 2, 3);
        for (row, b) in u.chunks_exact_mut(d.actions).zip(b.iter_mut()) {
            for ((u, m), s) in row.iter_mut().zip(mean).zip(std) {
                *u /= s;
                *b -= *u * m;
            }
        }
        tensors
    }

    /// A weight file with this transition: `original` (the bytes of a drivesim weight file of
    /// the same config, e.g. the one the model was loaded from) with the transition's tensors
    /// replaced by [`TransitionTrainer::tensors`], every tensor stored in `dtype` (`None`: the
    /// file's own dtype; f16 files are trained on f32 master weights and rounded here), and
    /// what it was trained on in its metadata ([`TrainedOn`](crate::train::TrainedOn): what the
    /// actions mean and their range, the frame rate; the original's where not given).
    /// [`Model::from_bytes`] reads it. The original's noise factor (`transition.L`) is not
    /// kept: it was fitted for the transition it came with ([`crate::train::fit_noise_factor`]
    /// and [`crate::train::with_noise_factor`] fit and add one for this one).
    #[cfg(feature = "std")]
    pub fn weight_file(
        &self,
        original: &[u8],
        dtype: Option<crate::WeightDtype>,
        trained_on: crate::train::TrainedOn<'_>,
    ) -> Result<Vec<u8>> {
        // The whole group: a spread head the trainer has not (after a restart) leaves the file too.
        crate::train::shared::weight_file(original, &self.tensors(), Some("transition."), dtype, trained_on)
    }

    /// The gradients computed last, named and laid out as the tensors they belong to
    /// (`transition.W`, ...; for normalised actions if [`set_action_normalisation`] was
    /// called), before clipping.
    ///
    /// [`set_action_normalisation`]: TransitionTrainer::set_action_normalisation
    pub fn gradients(&self) -> Vec<NamedTensor> {
        let [_, grads, ..] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        self.unpack(grads)
    }

    /// Packed parameters (or gradients) as PyTorch-layout tensors.
    fn unpack(&self, packed: &[f32]) -> Vec<NamedTensor> {
        let d = self.plan.dims;
        let [wx, bx, wa, ba, ws, bs] = cut_ref(packed, &d.params());
        let (h, z, cols) = (d.hidden, d.z, d.cols());
        let from_wx = |rows: usize, first: usize, n: usize| -> Vec<f32> {
            (0..rows * n)
                .map(|i| wx[Matrix::packed_index(i / n, first + i % n, cols)])
                .collect()
        };
        let values = [
            from_wx(h, 0, h),
            from_wx(h, h, z),
            from_wx(h, h + z, d.actions),
            bx.to_vec(),
            (0..z * h).map(|i| wa[Matrix::packed_index(i / h, i % h, h)]).collect(),
            ba.to_vec(),
            match d.spread {
                true => (0..z * h).map(|i| ws[Matrix::packed_index(i / h, i % h, h)]).collect(),
                false => Vec::new(),
            },
            bs.to_vec(),
        ];
        let tensors = if d.spread { 8 } else { 6 };
        tensor_shapes(&d)
            .into_iter()
            .zip(values)
            .take(tensors)
            .map(|((name, shape), values)| {
                let shape = if shape[1] == 1 { vec![shape[0]] } else { shape.to_vec() };
                (name.into(), shape, values)
            })
            .collect()
    }

    /// The batch of `codes` and `actions`, checked against the plan.
    fn check_batch(&self, codes: &[f32], actions: &[f32]) -> Result<usize> {
        let d = self.plan.dims;
        let per_window = d.window * d.z;
        if codes.is_empty() || !codes.len().is_multiple_of(per_window) {
            return Err(Error::NotWholeItems {
                buffer: "codes",
                item_len: per_window,
                found: codes.len(),
            });
        }
        let batch = codes.len() / per_window;
        if batch > d.batch {
            return Err(Error::BatchTooLarge {
                max: d.batch,
                found: batch,
            });
        }
        expect_len("actions", actions, batch * d.steps() * d.actions)?;
        expect_finite("codes", codes)?;
        expect_finite("actions", actions)?;
        Ok(batch)
    }
}

/// Mutable access to two different tensors' values.
fn split_pair(tensors: &mut [NamedTensor], i: usize, j: usize) -> (&mut [f32], &mut [f32]) {
    debug_assert!(i < j);
    let (left, right) = tensors.split_at_mut(j);
    (&mut left[i].2, &mut right[0].2)
}
