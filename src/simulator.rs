//! Running the networks in buffers planned once.

use crate::error::{expect_finite, expect_finite_output, expect_frames, expect_len};
use crate::plan::{zeros, Plan, StackBuffers};
use crate::pool::{Exec, Pool};
use crate::transition::TransitionBuffers;
use crate::{Config, Error, Model, Result};
use alloc::vec::Vec;
use core::borrow::Borrow;
use drivesim_kernels::Isa;

/// Runs a [`Model`]: encodes frames, steps the transition model, generates frames, and rolls
/// the three together into a hallucinated drive.
///
/// Every buffer is sized by a [`Plan`] and allocated by [`Simulator::new`] /
/// [`Simulator::with_batch`] (an unaffordable plan is an [`Error::OutOfMemory`], never an
/// abort); after that no method allocates. Frames are `&[f32]` of `height * width * channels`
/// values in HWC order (pixel-interleaved RGB) in [-1, 1]; codes are `z_dim` values; actions
/// are `action_dim` values, (speed, steering) for the comma config. Methods that take several
/// frames, codes or actions take them back to back in one slice, up to the planned batch.
///
/// Results are bit-identical for the same inputs whatever the thread count, the batch an item
/// is computed in and what the simulator did before, on one machine and instruction set. Every
/// `Ok` result is finite: inputs must be finite (frames within [-1, 1]), and an output that
/// overflowed is an [`Error::NonFiniteOutput`].
///
/// The model is borrowed (`Simulator<&Model>`) or owned (`Simulator<Model>`,
/// `Simulator<Arc<Model>>` to share one model's weights among several simulators), so that a
/// controller's environment can hold its simulator, model included:
///
/// ```
/// use drivesim::{Config, Model, Simulator, WeightDtype};
/// use std::sync::Arc;
///
/// struct Environment {
///     sim: Simulator<Arc<Model>>,
///     hidden: Vec<f32>,
///     code: Vec<f32>,
/// }
///
/// # fn main() -> Result<(), drivesim::Error> {
/// let config = Config { height: 32, width: 64, base_channels: 4, z_dim: 16, hidden_dim: 16, ..Config::COMMA };
/// let model = Arc::new(Model::random(&config, 7, WeightDtype::F32)?);
/// let mut env = Environment {
///     sim: Simulator::new(Arc::clone(&model))?,
///     hidden: vec![0.0; config.hidden_dim],
///     code: vec![0.0; config.z_dim],
/// };
/// env.sim.transition_fed_back(&mut env.hidden, &[20.0, 0.1], &mut env.code)?;
/// let second = Simulator::with_batch(model, 16)?; // the same weights, other buffers
/// assert_eq!(second.config(), env.sim.config());
/// # Ok(())
/// # }
/// ```
pub struct Simulator<M: Borrow<Model>> {
    /// The model, borrowed (`&Model`) or owned (`Model`, `Arc<Model>`, `Box<Model>`: a struct
    /// can then hold the simulator and its model together).
    model: M,
    isa: Isa,
    /// Threads that share each convolution and large dense layer (none: the caller's alone).
    pool: Option<Pool>,
    plan: Plan,
    encoder: StackBuffers,
    generator: StackBuffers,
    transition: TransitionBuffers,
    /// Hidden states and codes of a rollout: one of each, or one per candidate
    /// ([`Simulator::rollout_candidates`]) in the first two.
    rollout_h: Vec<f32>,
    rollout_z: [Vec<f32>; 2],
}

impl<M: Borrow<Model>> Simulator<M> {
    /// A simulator for one frame or code per call.
    pub fn new(model: M) -> Result<Self> {
        Simulator::with_batch(model, 1)
    }

    /// A simulator for up to `max_batch` frames or codes per call (at least 1). Batches
    /// share each pass over the dense layers' weights, which dominate at batch 1.
    /// [`Plan::new`] tells the memory this needs without allocating it.
    pub fn with_batch(model: M, max_batch: usize) -> Result<Self> {
        let plan = Plan::new(model.borrow().config(), max_batch, 1)?;
        Simulator::from_plan(model, plan, None)
    }

    /// Allocates the buffers of `plan`, for `pool`'s threads.
    fn from_plan(model: M, plan: Plan, pool: Option<Pool>) -> Result<Self> {
        let c = *model.borrow().config();
        let bytes = plan.bytes();
        Ok(Simulator {
            model,
            isa: Isa::best(),
            pool,
            encoder: StackBuffers::new(&plan.encoder, plan.encoder_flat, bytes)?,
            generator: StackBuffers::new(&plan.generator, plan.generator_flat, bytes)?,
            transition: TransitionBuffers::new(&plan)?,
            rollout_h: zeros(plan.max_batch() * c.hidden_dim, bytes)?,
            rollout_z: [zeros(plan.max_batch() * c.z_dim, bytes)?, zeros(c.z_dim, bytes)?],
            plan,
        })
    }

    /// Uses the kernels of `isa` instead of the best this CPU has (e.g. to compare paths).
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    /// Shares the work of each call among `threads` threads (the caller's included), started
    /// here once and kept until the simulator is dropped. Calls still allocate nothing.
    ///
    /// A single frame or code is shared layer by layer: each convolution by blocks of output
    /// channels, each large dense layer (the transition's included) by rows. A batch of at
    /// least `threads` items is shared item by item instead, so this plans again, with a set
    /// of activation planes per thread when the planned batch is above 1 (see
    /// [`Simulator::buffer_bytes`]). If the threads cannot be started, those that were are
    /// stopped and joined before the error returns.
    #[cfg(feature = "std")]
    pub fn with_threads(self, threads: usize) -> Result<Self> {
        let plan = Plan::new(self.config(), self.plan.max_batch(), threads)?;
        let pool = match plan.threads() {
            1 => None,
            n => Some(Pool::new(n).map_err(|source| Error::Threads { requested: n, source })?),
        };
        // The old buffers go before the new ones are allocated.
        let Simulator {
            model,
            isa,
            pool: old_pool,
            encoder,
            generator,
            transition,
            rollout_h,
            rollout_z,
            plan: _,
        } = self;
        drop((old_pool, encoder, generator, transition, rollout_h, rollout_z));
        Ok(Simulator::from_plan(model, plan, pool)?.with_isa(isa))
    }

    /// Threads that share each frame's work, the caller's included.
    pub fn threads(&self) -> usize {
        self.pool.as_ref().map_or(1, Pool::threads)
    }

    /// The instruction set the kernels run with.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// The model this simulator runs.
    pub fn model(&self) -> &Model {
        self.model.borrow()
    }

    /// The model's config.
    pub fn config(&self) -> &Config {
        self.model.borrow().config()
    }

    /// Bytes of the buffers this simulator allocated when it was planned ([`Plan::bytes`]):
    /// all the memory its calls use besides the model's weights (and a few hundred bytes of
    /// bookkeeping).
    pub fn buffer_bytes(&self) -> usize {
        self.plan.bytes()
    }

    /// The largest batch one call takes.
    pub fn max_batch(&self) -> usize {
        self.plan.max_batch()
    }

    /// How many items of `item_len` values `data` holds: a whole, non-zero number, at most the batch.
    fn batch_of(&self, buffer: &'static str, data: &[f32], item_len: usize) -> Result<usize> {
        if data.is_empty() || !data.len().is_multiple_of(item_len) {
            return Err(Error::NotWholeItems {
                buffer,
                item_len,
                found: data.len(),
            });
        }
        let n = data.len() / item_len;
        if n > self.max_batch() {
            return Err(Error::BatchTooLarge {
                max: self.max_batch(),
                found: n,
            });
        }
        Ok(n)
    }

    /// Encodes frames to the VAE mean (the code used for simulation): one `z_dim` code per frame.
    pub fn encode(&mut self, frames: &[f32], z: &mut [f32]) -> Result<()> {
        self.encode_inner(frames, z, None)
    }

    /// Like [`Simulator::encode`], and also writes log-sigma (`tanh`-bounded) for each frame,
    /// for sampling `z = mean + exp(logsigma) * noise`.
    pub fn encode_with_logsigma(&mut self, frames: &[f32], mean: &mut [f32], logsigma: &mut [f32]) -> Result<()> {
        self.encode_inner(frames, mean, Some(logsigma))
    }

    fn encode_inner(&mut self, frames: &[f32], z: &mut [f32], logsigma: Option<&mut [f32]>) -> Result<()> {
        let n = self.batch_of("frames", frames, self.config().frame_len())?;
        let codes_len = n * self.config().z_dim;
        expect_len("z", z, codes_len)?;
        if let Some(logsigma) = logsigma.as_deref() {
            expect_len("logsigma", logsigma, codes_len)?;
        }
        expect_frames("frames", frames)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model
            .borrow()
            .encoder
            .forward(exec, &mut self.encoder, frames, z, logsigma);
        expect_finite_output("z", z)
    }

    /// Generates one frame per code, with values in [-1, 1].
    pub fn generate(&mut self, z: &[f32], frames: &mut [f32]) -> Result<()> {
        let n = self.batch_of("z", z, self.config().z_dim)?;
        expect_len("frames", frames, n * self.config().frame_len())?;
        expect_finite("z", z)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model
            .borrow()
            .generator
            .forward(exec, &mut self.generator, z, frames);
        expect_finite_output("frames", frames)
    }

    /// One transition step per code: updates the hidden states `h` in place and writes the
    /// predicted next codes to `z_next`. Start a sequence with `h` all zeros.
    pub fn transition(&mut self, z: &[f32], h: &mut [f32], action: &[f32], z_next: &mut [f32]) -> Result<()> {
        let c = *self.config();
        let n = self.batch_of("z", z, c.z_dim)?;
        expect_len("h", h, n * c.hidden_dim)?;
        expect_finite("z", z)?;
        self.step(n, h, Some(z), action, z_next)
    }

    /// One transition step per code fed its own prediction: the input code is the one `h`
    /// predicts, `A h + a` (what the step that left `h` wrote to its `z_next`), so `z` is
    /// not read but written: the predicted next codes. This is the step of a rollout after its
    /// seeds and of a controller's closed loop.
    ///
    /// `V z = V (A h + a)`, so with f32 weights the model folds `V A` into `W` at load and
    /// such a step reads a third fewer weights; with f16 weights it computes `A h + a` first.
    /// The result differs from [`Simulator::transition`] given that code only by rounding.
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// # let model = Model::random(&config, 1, WeightDtype::F32)?;
    /// let mut sim = Simulator::new(&model)?;
    /// let (seed, mut z, mut h) = (vec![0.1; 8], vec![0.0; 8], vec![0.0; 8]);
    /// sim.transition(&seed, &mut h, &[10.0, 0.0], &mut z)?; // from an encoded frame
    /// for steering in [0.1, 0.2, 0.3] {
    ///     sim.transition_fed_back(&mut h, &[10.0, steering], &mut z)?; // from its own prediction
    /// }
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn transition_fed_back(&mut self, h: &mut [f32], action: &[f32], z: &mut [f32]) -> Result<()> {
        let c = *self.config();
        let n = self.batch_of("h", h, c.hidden_dim)?;
        self.step(n, h, None, action, z)
    }

    /// The checks and the step shared by [`Simulator::transition`] and
    /// [`Simulator::transition_fed_back`], for `n` items.
    fn step(&mut self, n: usize, h: &mut [f32], z: Option<&[f32]>, action: &[f32], z_next: &mut [f32]) -> Result<()> {
        let c = *self.config();
        expect_len("action", action, n * c.action_dim)?;
        expect_len("z_next", z_next, n * c.z_dim)?;
        expect_finite("h", h)?;
        expect_finite("action", action)?;
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        self.model
            .borrow()
            .transition
            .step(exec, &mut self.transition, h, z, action, z_next);
        expect_finite_output("h", h)?;
        expect_finite_output("z_next", z_next)
    }

    /// Hallucinates a drive: seeds the transition model with real frames, then feeds its own
    /// predictions back.
    ///
    /// There is one action per transition: step `i` maps frame `i` to frame `i + 1` with
    /// `actions[i]`. With `S` seed frames and `S - 1 + T` actions, the first `S - 1` steps are
    /// teacher-forced (their input is the encoded seed frame), step `S - 1` starts from the
    /// last seed frame's code, and every later step from the previous prediction. The `T`
    /// predicted codes (frames `S .. S + T`) go to `codes`; if `frames` is given, the generated
    /// frames go there too. The hidden state starts at zero. Steps from a prediction are
    /// [`Simulator::transition_fed_back`]'s.
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// # let model = Model::random(&config, 1, WeightDtype::F32)?;
    /// let mut sim = Simulator::new(&model)?;
    /// let seeds = vec![0.0; 3 * config.frame_len()]; // three frames
    /// let steps = 10;
    /// // 2 teacher-forced steps through the seeds, then 10 predictions: 12 (speed, steering).
    /// let actions: Vec<f32> = (0..2 + steps).flat_map(|t| [25.0, (t as f32 / 4.0).sin()]).collect();
    /// let mut codes = vec![0.0; steps * config.z_dim];
    /// let mut frames = vec![0.0; steps * config.frame_len()];
    /// sim.rollout(&seeds, &actions, &mut codes, Some(&mut frames))?;
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn rollout(
        &mut self,
        seed_frames: &[f32],
        actions: &[f32],
        codes: &mut [f32],
        frames: Option<&mut [f32]>,
    ) -> Result<()> {
        self.run_rollout(Seeds::Frames(seed_frames), actions, codes, frames)
    }

    /// [`Simulator::rollout`] seeded with codes instead of frames, e.g. codes sampled from the
    /// encoder's `mean + exp(logsigma) * noise`.
    pub fn rollout_from_codes(
        &mut self,
        seed_codes: &[f32],
        actions: &[f32],
        codes: &mut [f32],
        frames: Option<&mut [f32]>,
    ) -> Result<()> {
        self.run_rollout(Seeds::Codes(seed_codes), actions, codes, frames)
    }

    /// Rolls out `candidates` action sequences at once from one state (or one state each):
    /// the planner's building block. Every candidate steps in one batch, so each step reads
    /// the transition's weights once for all of them.
    ///
    /// `h` is the hidden state of one step (`hidden_dim` values, shared by every candidate) or
    /// of one per candidate. The first step starts from `z` (the current code, `z_dim` values
    /// or one per candidate) where given, else from the code `h` predicts (as after a
    /// rollout's or [`Simulator::transition_fed_back`]'s last step); every later step from the
    /// candidate's previous prediction. Everything is **step-major**: `actions` holds `T`
    /// steps of `candidates` actions (`[T][candidates][action_dim]`), `codes` receives
    /// `[T][candidates][z_dim]` and `frames`, if given, `[T][candidates][frame]`. Each
    /// candidate gets the bits a rollout of its own would ([`Simulator::transition`] and
    /// [`Simulator::transition_fed_back`] step by step). `candidates` is at most the planned
    /// batch ([`Simulator::with_batch`]); `h` is not changed.
    ///
    /// ```
    /// # use drivesim::{Config, Model, Simulator, WeightDtype};
    /// # let config = Config { height: 16, width: 32, base_channels: 2, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
    /// # let model = Model::random(&config, 1, WeightDtype::F32)?;
    /// let (candidates, steps) = (64, 10);
    /// let mut sim = Simulator::with_batch(&model, candidates)?;
    /// // The state after seeding: a rollout's hidden state and the real last code.
    /// let (h, z) = (vec![0.1; config.hidden_dim], vec![0.0; config.z_dim]);
    /// // Candidate n steers (n - 32) / 32 at every step, at speed 25.
    /// let actions: Vec<f32> = (0..steps * candidates)
    ///     .flat_map(|i| [25.0, ((i % candidates) as f32 - 32.0) / 32.0])
    ///     .collect();
    /// let mut codes = vec![0.0; steps * candidates * config.z_dim];
    /// sim.rollout_candidates(&h, Some(&z), candidates, &actions, &mut codes, None)?;
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn rollout_candidates(
        &mut self,
        h: &[f32],
        z: Option<&[f32]>,
        candidates: usize,
        actions: &[f32],
        codes: &mut [f32],
        mut frames: Option<&mut [f32]>,
    ) -> Result<()> {
        let c = *self.config();
        let n = candidates;
        if n == 0 || n > self.max_batch() {
            return Err(Error::BatchTooLarge {
                max: self.max_batch(),
                found: n,
            });
        }
        // One value set for all candidates, or one each.
        let each = |buffer, data: &[f32], len: usize| match data.len() {
            l if l == len || l == n * len => Ok(()),
            found => Err(Error::BufferLength {
                buffer,
                expected: n * len,
                found,
            }),
        };
        each("h", h, c.hidden_dim)?;
        if let Some(z) = z {
            each("z", z, c.z_dim)?;
            expect_finite("z", z)?;
        }
        let step_len = n * c.action_dim;
        if actions.is_empty() || !actions.len().is_multiple_of(step_len) {
            return Err(Error::NotWholeItems {
                buffer: "actions",
                item_len: step_len,
                found: actions.len(),
            });
        }
        let steps = actions.len() / step_len;
        expect_len("codes", codes, steps * n * c.z_dim)?;
        if let Some(frames) = frames.as_deref() {
            expect_len("frames", frames, steps * n * c.frame_len())?;
        }
        expect_finite("h", h)?;
        expect_finite("actions", actions)?;

        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let model = self.model.borrow();
        let hs = &mut self.rollout_h[..n * c.hidden_dim];
        for state in hs.chunks_exact_mut(h.len()) {
            state.copy_from_slice(h);
        }
        let first = &mut self.rollout_z[0][..n * c.z_dim];
        if let Some(z) = z {
            for code in first.chunks_exact_mut(z.len()) {
                code.copy_from_slice(z);
            }
        }
        let (len, folds) = (n * c.z_dim, model.transition.folds());
        for t in 0..steps {
            let (done, rest) = codes.split_at_mut(t * len);
            let out = &mut rest[..len];
            let input = match t {
                0 => z.map(|_| &first[..]),
                // An unfolded model would recompute the previous prediction: give it that.
                _ if !folds => Some(&done[(t - 1) * len..]),
                _ => None,
            };
            let action = &actions[t * step_len..][..step_len];
            model
                .transition
                .step(exec, &mut self.transition, hs, input, action, out);
            expect_finite_output("codes", out)?;
            if let Some(frames) = frames.as_deref_mut() {
                let frames = &mut frames[t * n * c.frame_len()..][..n * c.frame_len()];
                model.generator.forward(exec, &mut self.generator, out, frames);
                expect_finite_output("frames", frames)?;
            }
        }
        Ok(())
    }

    fn run_rollout(
        &mut self,
        seeds: Seeds<'_>,
        actions: &[f32],
        codes: &mut [f32],
        mut frames: Option<&mut [f32]>,
    ) -> Result<()> {
        let c = *self.config();
        let (buffer, data, item_len) = match seeds {
            Seeds::Frames(f) => ("seed_frames", f, c.frame_len()),
            Seeds::Codes(z) => ("seed_codes", z, c.z_dim),
        };
        if data.is_empty() || data.len() % item_len != 0 {
            return Err(Error::NotWholeItems {
                buffer,
                item_len,
                found: data.len(),
            });
        }
        if !actions.len().is_multiple_of(c.action_dim) {
            return Err(Error::NotWholeItems {
                buffer: "actions",
                item_len: c.action_dim,
                found: actions.len(),
            });
        }
        let seed_count = data.len() / item_len;
        let steps = actions.len() / c.action_dim;
        let predicted = steps
            .checked_sub(seed_count - 1)
            .filter(|&t| t > 0)
            .ok_or(Error::BufferLength {
                buffer: "actions",
                expected: seed_count * c.action_dim,
                found: actions.len(),
            })?;
        expect_len("codes", codes, predicted * c.z_dim)?;
        if let Some(frames) = frames.as_deref() {
            expect_len("frames", frames, predicted * c.frame_len())?;
        }
        match seeds {
            Seeds::Frames(f) => expect_frames(buffer, f)?,
            Seeds::Codes(z) => expect_finite(buffer, z)?,
        }
        expect_finite("actions", actions)?;

        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        // An unfolded model's fed-back step would recompute `A h + a`: the last prediction,
        // bit for bit (the kernels sum in one order whatever the split), so give it that.
        let folds = self.model.borrow().transition.folds();
        let h = &mut self.rollout_h[..c.hidden_dim];
        h.fill(0.0);
        let [z, z_next] = &mut self.rollout_z;
        let z = &mut z[..c.z_dim];
        for (step, action) in actions.chunks_exact(c.action_dim).enumerate() {
            let fed_back = step >= seed_count;
            match seeds {
                _ if fed_back => z.copy_from_slice(z_next),
                Seeds::Frames(f) => self.model.borrow().encoder.forward(
                    exec,
                    &mut self.encoder,
                    &f[step * item_len..][..item_len],
                    z,
                    None,
                ),
                Seeds::Codes(codes) => z.copy_from_slice(&codes[step * item_len..][..item_len]),
            }
            let input = if fed_back && folds { None } else { Some(&z[..]) };
            self.model
                .borrow()
                .transition
                .step(exec, &mut self.transition, h, input, action, z_next);
            if let Some(t) = (step + 1).checked_sub(seed_count) {
                codes[t * c.z_dim..][..c.z_dim].copy_from_slice(z_next);
                if let Some(frames) = frames.as_deref_mut() {
                    let frame = &mut frames[t * c.frame_len()..][..c.frame_len()];
                    self.model
                        .borrow()
                        .generator
                        .forward(exec, &mut self.generator, z_next, frame);
                    expect_finite_output("frames", frame)?;
                }
            }
            expect_finite_output("codes", z_next)?;
        }
        Ok(())
    }
}

impl<M: Borrow<Model>> core::fmt::Debug for Simulator<M> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Simulator")
            .field("config", self.config())
            .field("isa", &self.isa)
            .field("threads", &self.threads())
            .field("max_batch", &self.max_batch())
            .field("buffer_bytes", &self.buffer_bytes())
            .finish_non_exhaustive()
    }
}

/// What a rollout is seeded with.
#[derive(Clone, Copy)]
enum Seeds<'a> {
    Frames(&'a [f32]),
    Codes(&'a [f32]),
}
