//! The trainer's memory, measured before it is allocated: the [`Budget`] that counts (or
//! allocates) every buffer, the scratch sizes, a step's [`Buffers`] and [`Work`], and
//! [`VaeGanPlan`].

use super::layers::Scratch;
use super::networks::build;
use super::stack::{Stack, StackGrads};
use crate::{Config, Error, Result};
use alloc::vec::Vec;

/// Where the buffers' floats come from: counted only (planning) or allocated (the trainer).
pub(super) struct Budget {
    pub(super) allocate: bool,
    /// Floats per kind of buffer, in the order first met.
    pub(super) floats: Vec<(&'static str, usize)>,
}

impl Budget {
    /// A buffer of `len` f64 zeros, counted as two floats each under `what`.
    pub(super) fn take_f64(&mut self, what: &'static str, len: usize) -> Result<Vec<f64>> {
        self.count(what, mul(len, 2)?)?;
        zeros(self.allocate, len)
    }

    /// A buffer of `len` zeros, counted under `what` (empty when only measuring).
    pub(super) fn take(&mut self, what: &'static str, len: usize) -> Result<Vec<f32>> {
        self.count(what, len)?;
        zeros(self.allocate, len)
    }

    /// Adds `len` floats to `what`'s count.
    fn count(&mut self, what: &'static str, len: usize) -> Result<()> {
        match self.floats.iter_mut().find(|(w, _)| *w == what) {
            Some((_, n)) => *n = n.checked_add(len).ok_or(OVERFLOW)?,
            None => self.floats.push((what, len)),
        }
        Ok(())
    }
}

/// `len` zeros if `allocate`, else nothing; an allocation refused is [`Error::OutOfMemory`].
fn zeros<T: Copy + Default>(allocate: bool, len: usize) -> Result<Vec<T>> {
    let mut v = Vec::new();
    if allocate {
        v.try_reserve_exact(len).map_err(|_| Error::OutOfMemory {
            what: WHAT,
            bytes: len.checked_mul(core::mem::size_of::<T>()),
        })?;
        v.resize(len, T::default());
    }
    Ok(v)
}

const WHAT: &str = "the VAE-GAN trainer's buffers";
const OVERFLOW: Error = Error::OutOfMemory {
    what: WHAT,
    bytes: None,
};

pub(super) fn mul(a: usize, b: usize) -> Result<usize> {
    a.checked_mul(b).ok_or(OVERFLOW)
}

/// The largest scratch any layer needs.
#[derive(Default)]
pub(super) struct Sizes {
    pub(super) winograd_v: usize,
    pub(super) winograd_products: usize,
    /// Per thread.
    pub(super) weight_scratch: usize,
    pub(super) channels: usize,
}

/// The activations, their gradients and the scratch of a step, for up to `batch` frames.
pub(super) struct Buffers {
    pub(super) batch: usize,
    /// Real frames (planes of the first convolution's input).
    pub(super) real: Vec<f32>,
    pub(super) enc: Stack,
    pub(super) enc_flat: Vec<f32>,
    /// `[mu | logsigma]` per item (logsigma after its tanh).
    pub(super) heads: Vec<f32>,
    /// The generator's inputs: `mu + eps · sigma` for the batch, then the prior samples.
    pub(super) codes: Vec<f32>,
    pub(super) eps: Vec<f32>,
    pub(super) fc_out: Vec<f32>,
    /// The generator's first feature map before and after BatchNorm0 + ReLU, and its stats.
    pub(super) top_z: Vec<f32>,
    pub(super) top_y: Vec<f32>,
    pub(super) top_mean: Vec<f32>,
    pub(super) top_var: Vec<f32>,
    pub(super) gen: Stack,
    pub(super) dis_real: Stack,
    pub(super) dis_fake: Stack,
    pub(super) flat_real: Vec<f32>,
    pub(super) flat_fake: Vec<f32>,
    pub(super) logits_real: Vec<f32>,
    pub(super) logits_fake: Vec<f32>,
    pub(super) enc_grads: StackGrads,
    pub(super) gen_grads: StackGrads,
    pub(super) dis_grads: StackGrads,
    /// The gradient of the generator's first feature map, then of the dense layer's output.
    pub(super) top_g: Vec<f32>,
    /// Gradients of the discriminator's input, the feature error, dense outputs and inputs.
    pub(super) dx: Vec<f32>,
    pub(super) dfeature: Vec<f32>,
    pub(super) dlogits: Vec<f32>,
    pub(super) dflat: Vec<f32>,
    pub(super) dheads: Vec<f32>,
    pub(super) dcodes: Vec<f32>,
    pub(super) work: Work,
}

/// The scratch every layer's passes share.
pub(super) struct Work {
    /// One per thread.
    pub(super) scratch: Vec<Scratch>,
    pub(super) weight_scratch: Vec<f32>,
    /// The gradients of a BatchNorm pass's scale and shift.
    pub(super) channel_tmp: Vec<f32>,
    /// Zeros: the bias of the data-gradient convolutions.
    pub(super) zero: Vec<f32>,
    /// BatchNorm's per-channel sums of each item of a pass, and of the pass.
    pub(super) item_sums: Vec<f64>,
    pub(super) sums: Vec<f64>,
}

/// The memory of a [`VaeGanTrainer`](super::VaeGanTrainer) for a config and a batch of frames,
/// measured by building the trainer without allocating (every buffer counted, none made).
///
/// ```
/// use drivesim::train::VaeGanPlan;
/// use drivesim::Config;
///
/// let config = Config { base_channels: 32, z_dim: 128, hidden_dim: 256, ..Config::COMMA };
/// let plan = VaeGanPlan::new(&config, 8, 2)?;
/// for (buffer, bytes) in plan.buffers() {
///     println!("{buffer:>22}: {bytes} bytes");
/// }
/// assert!(plan.bytes() < 1 << 30);
/// assert!(VaeGanPlan::new(&config, usize::MAX, 1).is_err());
/// # Ok::<(), drivesim::Error>(())
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VaeGanPlan {
    pub(super) config: Config,
    pub(super) batch: usize,
    pub(super) threads: usize,
    pub(super) floats: Vec<(&'static str, usize)>,
    bytes: usize,
}

impl VaeGanPlan {
    /// The plan for `config` taking up to `batch` frames per step with `threads` threads (the
    /// caller's included; 0 counts as 1), each with scratch of its own.
    pub fn new(config: &Config, batch: usize, threads: usize) -> Result<VaeGanPlan> {
        let threads = threads.max(1);
        let mut budget = Budget {
            allocate: false,
            floats: Vec::new(),
        };
        build(config, batch, threads, &mut budget)?;
        let total = budget.floats.iter().try_fold(0usize, |s, &(_, n)| s.checked_add(n));
        let bytes = total
            .and_then(|n| n.checked_mul(4))
            .filter(|&b| b <= isize::MAX as usize)
            .ok_or(OVERFLOW)?;
        Ok(VaeGanPlan {
            config: *config,
            batch,
            threads,
            floats: budget.floats,
            bytes,
        })
    }

    /// Bytes the trainer allocates (besides a few tensor names).
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Bytes per kind of buffer.
    pub fn buffers(&self) -> impl Iterator<Item = (&'static str, usize)> + '_ {
        self.floats.iter().map(|&(what, n)| (what, n * 4))
    }

    /// Most frames per step.
    pub fn batch(&self) -> usize {
        self.batch
    }
}
