//! Training the transition model, `h' = tanh(W h + V z + U c + b)`, `z' = A h' + a`, as
//! `weights/train.py` does: windows of codes, the first inputs teacher-forced and the later ones
//! the model's own previous prediction, mean squared error over every prediction,
//! back-propagation through time, gradient-norm clipping and Adam.
//!
//! Everything lives in one arena ([`TransitionPlan`]): the master weights in the kernels'
//! packed layout (so that the forward pass runs on them directly and the optimiser updates them
//! in place), their gradients and Adam moments in the same layout, the transposed packings the
//! backward pass multiplies by, and the activations saved for it.

use super::adam::Adam;
use super::arena::{bytes_of, cut, cut_ref, total, Memory};
use super::NamedTensor;
use crate::error::{expect_finite, expect_finite_output, expect_len};
use crate::layers::dense;
use crate::pool::{Exec, Pool};
use crate::{Config, Error, Model, Result};
use alloc::vec;
use alloc::vec::Vec;
use drivesim_kernels::math;
use drivesim_kernels::pack::dense_from_fn;
use drivesim_kernels::{Activation, Isa, Matrix, MatrixData, OutputParts};

/// The arena's buffers, in order.
const BUFFERS: [&str; 15] = [
    "weights",
    "gradients",
    "Adam first moments",
    "Adam second moments",
    "[Aᵀ | Wᵀ] (hidden-state gradient)",
    "[Vᵀ ; Uᵀ] (input gradient)",
    "saved inputs [h | z | c]",
    "saved hidden states",
    "saved predictions",
    "pre-activation gradients",
    "prediction gradients",
    "input gradients",
    "gathered [dz' | dpre]",
    "zero bias",
    "action normalisation",
];

/// The memory of a [`TransitionTrainer`], computed from the config, the batch and the window
/// length before anything is allocated. Threads need none of their own: they share each
/// product by rows.
///
/// ```
/// use drivesim::train::TransitionPlan;
/// use drivesim::Config;
///
/// let plan = TransitionPlan::new(&Config::COMMA, 16, 15)?;
/// for (buffer, bytes) in plan.buffers() {
///     println!("{buffer:>36}: {bytes} bytes");
/// }
/// assert!(plan.bytes() < 24 << 20);
/// assert!(TransitionPlan::new(&Config::COMMA, usize::MAX, 15).is_err());
/// # Ok::<(), drivesim::Error>(())
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TransitionPlan {
    dims: Dims,
    lens: [usize; BUFFERS.len()],
    bytes: usize,
}

/// The sizes every buffer follows from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Dims {
    hidden: usize,
    z: usize,
    actions: usize,
    /// Most windows per step.
    batch: usize,
    /// Codes per window (`T`): `T - 1` predictions.
    window: usize,
}

impl Dims {
    /// Columns of `[W | V | U]`.
    fn cols(&self) -> usize {
        self.hidden + self.z + self.actions
    }

    /// Predictions per window.
    fn steps(&self) -> usize {
        self.window - 1
    }

    /// Floats of `[W | V | U]` packed, `b`, `A` packed and `a`, in that order.
    fn params(&self) -> [usize; 4] {
        let (h, z) = (self.hidden, self.z);
        [Matrix::packed_len(h, self.cols()), h, Matrix::packed_len(z, h), z]
    }
}

const WHAT: &str = "the transition trainer's arena";

fn mul(a: usize, b: usize) -> Result<usize> {
    a.checked_mul(b).ok_or(Error::OutOfMemory {
        what: WHAT,
        bytes: None,
    })
}

impl TransitionPlan {
    /// The arena of a trainer for `config`'s transition taking up to `batch` windows of
    /// `window` codes (at least 2: one input, one target) per step.
    pub fn new(config: &Config, batch: usize, window: usize) -> Result<TransitionPlan> {
        config.validate()?;
        if window < 2 {
            return Err(Error::Config {
                field: "window",
                expected: "at least 2 codes",
                found: window,
            });
        }
        if batch == 0 {
            return Err(Error::Config {
                field: "batch",
                expected: "at least 1 window",
                found: 0,
            });
        }
        let dims = Dims {
            hidden: config.hidden_dim,
            z: config.z_dim,
            actions: config.action_dim,
            batch,
            window,
        };
        let (h, z, a) = (dims.hidden, dims.z, dims.actions);
        let params = total(&dims.params(), WHAT)?;
        let items = mul(dims.steps(), batch)?;
        let lens = [
            params,
            params,
            params,
            params,
            Matrix::packed_len(h, z + h),
            Matrix::packed_len(z + a, h),
            mul(items, dims.cols())?,
            mul(items, h)?,
            mul(items, z)?,
            mul(items, h)?,
            mul(items, z)?,
            mul(items, z + a)?,
            mul(batch, z + h)?,
            h.max(z + a),
            2 * a,
        ];
        let bytes = bytes_of(total(&lens, WHAT)?, WHAT)?;
        Ok(TransitionPlan { dims, lens, bytes })
    }

    /// Bytes of the whole arena.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Each buffer of the arena with its bytes, in the arena's order.
    pub fn buffers(&self) -> impl Iterator<Item = (&'static str, usize)> + '_ {
        BUFFERS.iter().zip(self.lens).map(|(&name, len)| (name, len * 4))
    }

    /// The most windows one step takes.
    pub fn batch(&self) -> usize {
        self.dims.batch
    }

    /// Codes per window.
    pub fn window(&self) -> usize {
        self.dims.window
    }

    fn floats(&self) -> usize {
        self.bytes / 4
    }
}

/// How a [`TransitionTrainer`] trains: `weights/train.py`'s choices by default.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransitionSettings {
    /// Inputs taken from the data at the start of each window (at least 1); later inputs are
    /// the model's own previous prediction. The paper and `weights/train.py`: 5 of 15.
    pub teacher: usize,
    /// Back-propagate through the fed-back predictions too. The paper stops the gradient
    /// there (PyTorch's `.detach()`, `false`); the hidden state carries it through time either
    /// way.
    pub full_bptt: bool,
    /// The largest global L2 norm of the gradients; larger ones are scaled down to it as
    /// `torch.nn.utils.clip_grad_norm_` does. `f32::INFINITY`: no clipping.
    pub clip: f32,
    /// Adam's `beta1`, `beta2` and `eps`, with PyTorch's semantics (bias correction).
    pub adam: Adam,
}

impl Default for TransitionSettings {
    fn default() -> Self {
        TransitionSettings {
            teacher: 5,
            full_bptt: false,
            clip: 1.0,
            adam: Adam::default(),
        }
    }
}

/// The tensors a transition has, in PyTorch layout: name, shape.
fn tensor_shapes(d: &Dims) -> [(&'static str, [usize; 2]); 6] {
    let (h, z, a) = (d.hidden, d.z, d.actions);
    [
        ("transition.W", [h, h]),
        ("transition.V", [h, z]),
        ("transition.U", [h, a]),
        ("transition.b", [h, 1]),
        ("transition.A", [z, h]),
        ("transition.a", [z, 1]),
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
    plan: TransitionPlan,
    settings: TransitionSettings,
    memory: Memory<'a>,
    isa: Isa,
    pool: Option<Pool>,
    /// Adam steps taken so far.
    steps: u32,
    /// The global gradient norm of the gradients computed last, if they were not applied yet.
    pending: Option<f32>,
    /// Whether the transposed packings hold the current weights.
    transposed: bool,
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
        let [params, .., norm] = cut(trainer.memory.floats(), &trainer.plan.lens);
        let [wx, bx, wa, ba] = cut(params, &d.params());
        let (input, output) = model.transition.layers();
        for (dst, layer) in [(wx, input), (wa, output)] {
            match layer.matrix().data {
                MatrixData::F32(w) => dst.copy_from_slice(w),
                MatrixData::F16(w) => dst.iter_mut().zip(w).for_each(|(d, w)| *d = w.to_f32()),
            }
        }
        bx.copy_from_slice(&input.bias);
        ba.copy_from_slice(&output.bias);
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
        if threads > 1 {
            let pool = Pool::new(threads).map_err(|source| Error::Threads {
                requested: threads,
                source,
            })?;
            self.pool = Some(pool);
        }
        Ok(self)
    }

    /// The settings in use.
    pub fn settings(&self) -> &TransitionSettings {
        &self.settings
    }

    /// Trains on actions normalised as `(c - mean) / std` (as `weights/train.py` does, so that
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
        let [params, grads, m, v, .., norm] = cut(self.memory.floats(), &self.plan.lens);
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
    /// The loss is the mean squared error of the `window - 1` predictions.
    pub fn compute_gradients(&mut self, codes: &[f32], actions: &[f32]) -> Result<f32> {
        let batch = self.check_batch(codes, actions)?;
        let loss = self.forward(codes, actions, batch)?;
        self.backward(codes, batch, Backward::Weights)?;
        let [_, grads, ..] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
        let norm = grads.iter().map(|&g| g as f64 * g as f64).sum::<f64>();
        let norm = math::sqrt(norm) as f32;
        if !norm.is_finite() {
            return Err(Error::NonFiniteOutput {
                buffer: "gradients",
                index: grads.iter().position(|g| !g.is_finite()).unwrap_or(0),
            });
        }
        self.pending = Some(norm);
        Ok(loss)
    }

    /// The global L2 norm of the gradients computed last (before clipping), if they were not
    /// applied yet.
    pub fn gradient_norm(&self) -> Option<f32> {
        self.pending
    }

    /// One Adam step with learning rate `lr` on the gradients computed last, clipped to the
    /// settings' norm first. An error if there are none, or if `lr` is negative or not finite.
    pub fn apply_gradients(&mut self, lr: f32) -> Result<()> {
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(Error::Setting {
                name: "learning rate",
                expected: "a finite number >= 0",
                value: lr,
            });
        }
        let norm = self.pending.take().ok_or(Error::NoGradients)?;
        // torch.nn.utils.clip_grad_norm_: scale by max_norm / (norm + 1e-6), at most 1.
        let scale = (self.settings.clip / (norm + 1e-6)).min(1.0);
        self.steps += 1;
        let [params, grads, m, v, ..] = cut(self.memory.floats(), &self.plan.lens);
        self.settings.adam.update(self.steps, lr, scale, params, grads, [m, v]);
        self.transposed = false;
        Ok(())
    }

    /// The predictions of a batch of windows (`[batch, window - 1, z]`: the code after each
    /// input, teacher-forced as in training) and their mean squared error against the codes.
    pub fn predict(&mut self, codes: &[f32], actions: &[f32], predictions: &mut [f32]) -> Result<f32> {
        let batch = self.check_batch(codes, actions)?;
        let d = self.plan.dims;
        expect_len("predictions", predictions, batch * d.steps() * d.z)?;
        let loss = self.forward(codes, actions, batch)?;
        let [.., outs, _, _, _, _, _, _] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
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
        let [.., dzc, _, _, norm] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
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
        let [params, .., norm] = cut_ref(self.memory.floats_ref(), &self.plan.lens);
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
    /// what it was trained on in its metadata ([`super::TrainedOn`]: what the actions mean and
    /// their range, the frame rate; the original's where not given). [`Model::from_bytes`]
    /// reads it.
    #[cfg(feature = "std")]
    pub fn weight_file(
        &self,
        original: &[u8],
        dtype: Option<crate::WeightDtype>,
        trained_on: super::TrainedOn<'_>,
    ) -> Result<Vec<u8>> {
        let tensors = self.tensors();
        let replace: Vec<(&str, &[usize], &[f32])> = tensors
            .iter()
            .map(|(name, shape, values)| (name.as_str(), &shape[..], &values[..]))
            .collect();
        crate::weights::rewrite(original, &replace, dtype, trained_on)
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
        let [wx, bx, wa, ba] = cut_ref(packed, &d.params());
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
        ];
        tensor_shapes(&d)
            .into_iter()
            .zip(values)
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

    /// Runs the windows forward, saving every input, hidden state and prediction (time-major:
    /// item `t * batch + n`), and returns the loss.
    fn forward(&mut self, codes: &[f32], actions: &[f32], batch: usize) -> Result<f32> {
        let (d, teacher) = (self.plan.dims, self.settings.teacher);
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let [params, _, _, _, _, _, xs, hs, outs, .., norm] = cut(self.memory.floats(), &self.plan.lens);
        let [wx, bx, wa, ba] = cut_ref(params, &d.params());
        let (h, z, a, cols) = (d.hidden, d.z, d.actions, d.cols());
        let (mean, std) = norm.split_at(a);
        let input = Matrix {
            data: MatrixData::F32(wx),
            rows: h,
            cols,
        };
        let output = Matrix {
            data: MatrixData::F32(wa),
            rows: z,
            cols: h,
        };
        let mut sum = 0.0f64;
        for t in 0..d.steps() {
            let (x, hs_t) = (&mut xs[t * batch * cols..][..batch * cols], t * batch * h);
            for (n, row) in x.chunks_exact_mut(cols).enumerate() {
                let (h_prev, rest) = row.split_at_mut(h);
                let (z_in, c) = rest.split_at_mut(z);
                match t {
                    0 => h_prev.fill(0.0),
                    _ => h_prev.copy_from_slice(&hs[hs_t - batch * h + n * h..][..h]),
                }
                match t < teacher {
                    true => z_in.copy_from_slice(&codes[(n * d.window + t) * z..][..z]),
                    false => z_in.copy_from_slice(&outs[((t - 1) * batch + n) * z..][..z]),
                }
                let raw = &actions[(n * d.steps() + t) * a..][..a];
                for (((c, raw), m), s) in c.iter_mut().zip(raw).zip(mean).zip(std.iter()) {
                    *c = (raw - m) / s;
                }
            }
            let h_t = &mut hs[hs_t..][..batch * h];
            dense(exec, input, bx, Activation::Tanh, x, h_t);
            let out = &mut outs[t * batch * z..][..batch * z];
            dense(exec, output, ba, Activation::Identity, h_t, out);
            for (n, out) in out.chunks_exact(z).enumerate() {
                let target = &codes[(n * d.window + t + 1) * z..][..z];
                sum += out
                    .iter()
                    .zip(target)
                    .map(|(o, y)| ((o - y) as f64) * ((o - y) as f64))
                    .sum::<f64>();
            }
        }
        let loss = (sum / (batch * d.steps() * z) as f64) as f32;
        if !loss.is_finite() {
            return Err(Error::NonFiniteOutput {
                buffer: "loss",
                index: 0,
            });
        }
        Ok(loss)
    }

    /// Back-propagation through time from the loss of the last [`forward`], newest step first:
    /// the gradients of every weight, or (`Backward::Inputs`) of every input instead.
    ///
    /// [`forward`]: TransitionTrainer::forward
    fn backward(&mut self, codes: &[f32], batch: usize, what: Backward) -> Result<()> {
        let (d, teacher, full) = (self.plan.dims, self.settings.teacher, self.settings.full_bptt);
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let [params, grads, _, _, bt, vut, xs, hs, outs, dpre, dout, dzc, gathered, zero, _] =
            cut(self.memory.floats(), &self.plan.lens);
        let (h, z, a, cols, steps) = (d.hidden, d.z, d.actions, d.cols(), d.steps());
        if !self.transposed {
            let [wx, _, wa, _] = cut_ref(params, &d.params());
            let wx_at = |r: usize, c: usize| wx[Matrix::packed_index(r, c, cols)];
            // [Aᵀ | Wᵀ]: the hidden state's gradient from the prediction's and the next step's.
            dense_from_fn(h, z + h, bt, |r, c| match c < z {
                true => wa[Matrix::packed_index(c, r, h)],
                false => wx_at(c - z, r),
            });
            // [Vᵀ ; Uᵀ]: the gradient of the code and action inputs.
            dense_from_fn(z + a, h, vut, |r, c| wx_at(c, h + r));
            self.transposed = true;
        }
        let matrix = |w, rows, cols| Matrix {
            data: MatrixData::F32(w),
            rows,
            cols,
        };
        let (bt, vut) = (matrix(bt, h, z + h), matrix(vut, z + a, h));
        // d loss / d prediction: 2 (prediction - code) / (values in the loss).
        let scale = 2.0 / (batch * steps * z) as f32;
        for t in 0..steps {
            let (out, g) = (
                &outs[t * batch * z..][..batch * z],
                &mut dout[t * batch * z..][..batch * z],
            );
            for (n, (out, g)) in out.chunks_exact(z).zip(g.chunks_exact_mut(z)).enumerate() {
                let target = &codes[(n * d.window + t + 1) * z..][..z];
                for ((g, o), y) in g.iter_mut().zip(out).zip(target) {
                    *g = scale * (o - y);
                }
            }
        }
        let inputs = what == Backward::Inputs || full;
        for t in (0..steps).rev() {
            let later = t + 1 < steps;
            let dout_t = &mut dout[t * batch * z..][..batch * z];
            if full && later && t + 1 >= teacher {
                // The next step's input was this prediction: its gradient joins the loss's.
                let dz_next = &dzc[(t + 1) * batch * (z + a)..][..batch * (z + a)];
                for (g, dz) in dout_t.chunks_exact_mut(z).zip(dz_next.chunks_exact(z + a)) {
                    g.iter_mut().zip(dz).for_each(|(g, dz)| *g += dz);
                }
            }
            let g = &mut gathered[..batch * (z + h)];
            for (n, row) in g.chunks_exact_mut(z + h).enumerate() {
                row[..z].copy_from_slice(&dout_t[n * z..][..z]);
                match later {
                    true => row[z..].copy_from_slice(&dpre[((t + 1) * batch + n) * h..][..h]),
                    false => row[z..].fill(0.0),
                }
            }
            step_backward(
                exec,
                bt,
                &zero[..h],
                g,
                &hs[t * batch * h..][..batch * h],
                &mut dpre[t * batch * h..][..batch * h],
            );
            if inputs {
                let dpre_t = &dpre[t * batch * h..][..batch * h];
                dense(
                    exec,
                    vut,
                    &zero[..z + a],
                    Activation::Identity,
                    dpre_t,
                    &mut dzc[t * batch * (z + a)..][..batch * (z + a)],
                );
            }
        }
        if what == Backward::Weights {
            let [gwx, gbx, gwa, gba] = cut(grads, &d.params());
            let items = steps * batch;
            weight_grad(exec, &dpre[..items * h], &xs[..items * cols], h, cols, gwx);
            column_sums(&dpre[..items * h], gbx);
            weight_grad(exec, &dout[..items * z], &hs[..items * h], z, h, gwa);
            column_sums(&dout[..items * z], gba);
        }
        Ok(())
    }
}

/// What [`TransitionTrainer::backward`] computes.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Backward {
    Weights,
    Inputs,
}

/// One step of the RNN backward: `dh = [Aᵀ | Wᵀ] [dz' | dpre_next]` (the hidden state feeds
/// the prediction and the next step), then through the tanh: `dpre = dh (1 - h²)`.
fn step_backward(exec: Exec<'_>, bt: Matrix<'_>, zero: &[f32], gathered: &[f32], h: &[f32], dpre: &mut [f32]) {
    dense(exec, bt, zero, Activation::Identity, gathered, dpre);
    drivesim_kernels::activation_backward(exec.isa, Activation::Tanh, h, dpre);
}

/// `grad = dyᵀ x` packed, shared among the threads by panels of rows.
fn weight_grad(exec: Exec<'_>, dy: &[f32], x: &[f32], rows: usize, cols: usize, grad: &mut [f32]) {
    let parts = OutputParts::new(grad, rows, exec.threads());
    exec.run(&|| {
        while let Some(part) = parts.take() {
            drivesim_kernels::dense_weight_grad_rows(exec.isa, dy, x, rows, cols, part);
        }
    });
}

/// `sums[r] = Σ_k dy[k][r]`: the gradient of a bias.
fn column_sums(dy: &[f32], sums: &mut [f32]) {
    sums.fill(0.0);
    for row in dy.chunks_exact(sums.len()) {
        sums.iter_mut().zip(row).for_each(|(s, v)| *s += v);
    }
}

/// Mutable access to two different tensors' values.
fn split_pair(tensors: &mut [NamedTensor], i: usize, j: usize) -> (&mut [f32], &mut [f32]) {
    debug_assert!(i < j);
    let (left, right) = tensors.split_at_mut(j);
    (&mut left[i].2, &mut right[0].2)
}

fn check_settings(s: &TransitionSettings) -> Result<()> {
    if s.teacher == 0 {
        return Err(Error::Config {
            field: "teacher",
            expected: "at least 1 teacher-forced input",
            found: 0,
        });
    }
    if s.clip.is_nan() || s.clip <= 0.0 {
        return Err(Error::Setting {
            name: "clip",
            expected: "a norm > 0 (infinity: no clipping)",
            value: s.clip,
        });
    }
    s.adam.check()
}
