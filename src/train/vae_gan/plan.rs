//! The trainer's memory, measured before it is allocated: [`VaeGanPlan`], from the networks
//! built with a [`Budget`] that counts every buffer and allocates none.

use super::budget::{Budget, OVERFLOW};
use super::networks::build;
use crate::{Config, Result};
use alloc::vec::Vec;

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
