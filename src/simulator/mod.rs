//! Running the networks in buffers planned once: the [`Simulator`], its constructors and
//! accessors. Its calls are in the submodules: `networks` (encode, generate, one transition
//! step), `heads` (the policy, reward and value heads), `rollout` (rollouts and candidate
//! rollouts) and `checks` (their input checks).

mod checks;
mod heads;
mod networks;
mod rollout;
mod sampled;

use crate::plan::{zeros, Plan, StackBuffers};
use crate::pool::Pool;
use crate::sampling::Sampling;
use crate::transition::TransitionBuffers;
#[cfg(doc)]
use crate::Error;
use crate::{Config, Model, Result};
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
    /// A head's hidden layer for a batch.
    head_hidden: Vec<f32>,
    /// Whether rollouts sample their futures ([`Simulator::set_sampling`]).
    sampling: Sampling,
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
            head_hidden: zeros(plan.heads, bytes)?,
            sampling: Sampling::OFF,
            plan,
        })
    }

    /// Uses the kernels of `isa` instead of the best this CPU has (e.g. to compare paths).
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    /// What planning again keeps: the model, the kernels and the sampling. The rest (the old
    /// buffers and threads) is dropped on return.
    #[cfg(feature = "std")]
    fn into_kept(self) -> (M, Isa, Sampling) {
        let Simulator {
            model, isa, sampling, ..
        } = self;
        (model, isa, sampling)
    }

    /// Shares the work of each call among `threads` threads (the caller's included), started
    /// here once and kept until the simulator is dropped. Calls still allocate nothing.
    ///
    /// A single frame or code is shared layer by layer: each convolution by blocks of output
    /// channels, each large dense layer (the transition's included) by rows. A batch of at
    /// least `threads` items (of transition steps, 8 per thread) is shared item by item
    /// instead, each thread running every layer of its items, so this plans again, with a set
    /// of activation planes per thread when the planned batch is above 1 (see
    /// [`Simulator::buffer_bytes`]). More than [`crate::MAX_THREADS`] is an [`Error::Config`]
    /// from planning, before anything is allocated or started; if the threads cannot be
    /// started, those that were are stopped and joined before the error returns.
    #[cfg(feature = "std")]
    pub fn with_threads(self, threads: usize) -> Result<Self> {
        let plan = Plan::new(self.config(), self.plan.max_batch(), threads)?;
        let pool = match plan.threads() {
            1 => None,
            n => Some(Pool::new(n)?),
        };
        // The old buffers go (at the end of `into_kept`) before the new ones are allocated.
        let (model, isa, sampling) = self.into_kept();
        let mut sim = Simulator::from_plan(model, plan, pool)?.with_isa(isa);
        sim.sampling = sampling;
        Ok(sim)
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
