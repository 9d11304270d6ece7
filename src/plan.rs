//! The simulator's memory, planned before anything is allocated: every buffer's size from the
//! config, the batch and the thread count, in checked arithmetic, so that an impossible or
//! unaffordable plan is an [`Error`] naming its size instead of an overflow or an abort.

use crate::{Config, Error, Result};
use alloc::vec::Vec;
use drivesim_kernels::{ConvShape, Winograd};

/// The sizes of every buffer a [`crate::Simulator`] allocates, computed without allocating
/// them. [`Plan::bytes`] is what the simulator will hold besides the model's weights.
///
/// ```
/// use drivesim::{Config, Plan};
///
/// let plan = Plan::new(&Config::COMMA, 16, 2)?;
/// assert!(plan.bytes() < 64 << 20);
/// // Sizes that overflow or that no machine could allocate are errors, not aborts.
/// assert!(Plan::new(&Config::COMMA, usize::MAX, 1).is_err());
/// // So are more threads than any machine has cores, before anything is allocated or started.
/// assert!(Plan::new(&Config::COMMA, 1, drivesim::MAX_THREADS + 1).is_err());
/// # Ok::<(), drivesim::Error>(())
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Plan {
    pub(crate) max_batch: usize,
    pub(crate) threads: usize,
    pub(crate) encoder: StackPlan,
    pub(crate) generator: StackPlan,
    /// Floats of the encoder's last convolution output (its dense heads' input) for a batch.
    pub(crate) encoder_flat: usize,
    /// Floats of the generator's first (dense) layer output for a batch.
    pub(crate) generator_flat: usize,
    /// Floats of the transition's gathered input `[h | z | c]` for a batch.
    pub(crate) transition_concat: usize,
    /// Floats of the code an f16 model's fed-back step recomputes from `h` for a batch.
    pub(crate) transition_code: usize,
    /// Floats of a sampled step's noise for a batch, drawn and correlated (`crate::sampling`).
    pub(crate) sampling_noise: usize,
    /// Floats of a rollout's hidden states (a batch of candidates) and codes (a batch, and one).
    pub(crate) rollout: usize,
    /// Floats of a head's hidden layer for a batch (a head is at most `hidden_dim` wide).
    pub(crate) heads: usize,
    bytes: usize,
}

/// The buffers of a stack of convolutions: sets of planes, each one image's worth.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct StackPlan {
    /// The padded input plane of each layer.
    pub inputs: Vec<usize>,
    /// The transformed input of the largest Winograd layer (0 without one).
    pub transformed: usize,
    /// Winograd product scratch of the first set, one per thread; the other sets, one thread
    /// each, hold one ([`Winograd::scratch_len`] of the largest; 0 without a Winograd layer).
    pub products_first: usize,
    pub products_other: usize,
    /// One set, or one per thread when threads take whole items of a batch.
    pub sets: usize,
}

impl StackPlan {
    fn new(shapes: impl Iterator<Item = ConvShape>, sets: usize, threads: usize) -> Result<StackPlan> {
        // Each Winograd layer reports its transformed input and product scratch: plan the largest.
        let (mut inputs, mut transformed, mut scratch) = (Vec::new(), 0, 0);
        for shape in shapes {
            inputs.push(shape.input.len());
            if let Some(w) = Winograd::new(shape) {
                transformed = transformed.max(w.input_len());
                scratch = scratch.max(w.scratch_len());
            }
        }
        Ok(StackPlan {
            inputs,
            transformed,
            products_first: mul(scratch, threads)?,
            products_other: scratch,
            sets,
        })
    }

    /// Floats of set `set`'s Winograd product scratch.
    fn products(&self, set: usize) -> usize {
        if set == 0 {
            self.products_first
        } else {
            self.products_other
        }
    }

    /// Floats held by set `set`.
    fn set_floats(&self, set: usize) -> Result<usize> {
        let fixed = add(self.transformed, self.products(set))?;
        self.inputs.iter().try_fold(fixed, |sum, &n| add(sum, n))
    }

    fn floats(&self) -> Result<usize> {
        let others = mul(self.set_floats(1)?, self.sets - 1)?;
        add(self.set_floats(0)?, others)
    }
}

impl Plan {
    /// The buffers of a simulator for `config` taking up to `max_batch` (at least 1) frames or
    /// codes per call with `threads` threads (the caller's included; 0 counts as 1, more than
    /// [`crate::MAX_THREADS`] is [`Error::Config`]).
    pub fn new(config: &Config, max_batch: usize, threads: usize) -> Result<Plan> {
        config.validate()?;
        let (max_batch, threads) = (max_batch.max(1), crate::pool::check_threads(threads)?);
        // Threads take whole items of a batch on planes of their own.
        let sets = if max_batch > 1 { threads } else { 1 };
        let c = config;
        let mut plan = Plan {
            max_batch,
            threads,
            encoder: StackPlan::new(c.encoder_convs(), sets, threads)?,
            generator: StackPlan::new(c.generator_convs(), sets, threads)?,
            encoder_flat: mul(max_batch, c.flat_len())?,
            generator_flat: mul(max_batch, c.flat_len())?,
            transition_concat: mul(max_batch, c.hidden_dim + c.z_dim + c.action_dim)?,
            transition_code: mul(max_batch, c.z_dim.max(c.hidden_dim))?,
            sampling_noise: mul(max_batch, mul(2, c.z_dim)?)?,
            rollout: add(mul(max_batch, c.hidden_dim + c.z_dim)?, c.z_dim)?,
            heads: mul(max_batch, c.hidden_dim)?,
            bytes: 0,
        };
        let floats = [
            plan.encoder.floats()?,
            plan.generator.floats()?,
            plan.encoder_flat,
            plan.generator_flat,
            plan.transition_concat,
            plan.transition_code,
            plan.sampling_noise,
            plan.rollout,
            plan.heads,
        ]
        .into_iter()
        .try_fold(0, add)?;
        plan.bytes = mul(floats, core::mem::size_of::<f32>())?;
        // A Vec holds at most isize::MAX bytes.
        if plan.bytes > isize::MAX as usize {
            return Err(Error::OutOfMemory {
                what: "the simulator's buffers",
                bytes: Some(plan.bytes),
            });
        }
        Ok(plan)
    }

    /// Bytes of every buffer of the plan together.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// The largest batch one call takes.
    pub fn max_batch(&self) -> usize {
        self.max_batch
    }

    /// Threads that share each call, the caller's included.
    pub fn threads(&self) -> usize {
        self.threads
    }
}

fn overflow() -> Error {
    Error::OutOfMemory {
        what: "the simulator's buffers",
        bytes: None,
    }
}

fn mul(a: usize, b: usize) -> Result<usize> {
    a.checked_mul(b).ok_or_else(overflow)
}

fn add(a: usize, b: usize) -> Result<usize> {
    a.checked_add(b).ok_or_else(overflow)
}

/// `len` zeros, or [`Error::OutOfMemory`] naming the plan's `bytes` if the allocator refuses.
pub(crate) fn zeros(len: usize, plan_bytes: usize) -> Result<Vec<f32>> {
    let mut v = Vec::new();
    v.try_reserve_exact(len).map_err(|_| Error::OutOfMemory {
        what: "the simulator's buffers",
        bytes: Some(plan_bytes),
    })?;
    v.resize(len, 0.0);
    Ok(v)
}

/// The buffers of a chain of convolutions running one image at a time.
pub(crate) struct Planes {
    /// The padded input plane of each layer.
    pub inputs: Vec<Vec<f32>>,
    /// The transformed input of the largest Winograd layer.
    pub transformed: Vec<f32>,
    /// Winograd product scratch, one per thread that may share a layer on these planes.
    pub products: Vec<f32>,
}

impl Planes {
    /// The zeroed buffers of set `set` of `stack`.
    fn new(stack: &StackPlan, set: usize, plan_bytes: usize) -> Result<Self> {
        let mut inputs = Vec::with_capacity(stack.inputs.len());
        for &len in &stack.inputs {
            inputs.push(zeros(len, plan_bytes)?);
        }
        Ok(Planes {
            inputs,
            transformed: zeros(stack.transformed, plan_bytes)?,
            products: zeros(stack.products(set), plan_bytes)?,
        })
    }

    /// The first layer's input plane.
    pub fn input(&mut self) -> &mut [f32] {
        &mut self.inputs[0]
    }
}

/// Per-simulator buffers of a convolution stack (the encoder's or the generator's), as planned.
pub(crate) struct StackBuffers {
    /// The padded input plane of every convolution: one set, or one per thread when threads
    /// take whole items of a batch.
    pub planes: Vec<Planes>,
    /// The flat features between the convolutions and the dense layer, for a whole batch.
    pub flat: Vec<f32>,
}

impl StackBuffers {
    pub fn new(stack: &StackPlan, flat: usize, plan_bytes: usize) -> Result<Self> {
        let mut planes = Vec::with_capacity(stack.sets);
        for set in 0..stack.sets {
            planes.push(Planes::new(stack, set, plan_bytes)?);
        }
        Ok(StackBuffers {
            planes,
            flat: zeros(flat, plan_bytes)?,
        })
    }
}
