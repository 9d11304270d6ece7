//! What the trainers share: their worker threads, the check of a step's learning rate, a bias's
//! gradient, and the weight file they write their tensors into.

use crate::pool::Pool;
use crate::{Error, Result};

/// The worker threads for `threads` threads, the caller's included (none for one or zero).
pub(super) fn start_pool(threads: usize) -> Result<Option<Pool>> {
    match threads {
        0 | 1 => Ok(None),
        #[cfg(feature = "std")]
        n => Pool::new(n).map(Some),
        #[cfg(not(feature = "std"))]
        n => Err(Error::Config {
            field: "threads",
            expected: "1 without the std feature",
            found: n,
        }),
    }
}

/// A learning rate `lr` finite and at least zero, or [`Error::Setting`] naming it `name`.
pub(super) fn check_lr(name: &'static str, lr: f32) -> Result<()> {
    if !(lr.is_finite() && lr >= 0.0) {
        return Err(Error::Setting {
            name,
            expected: "a finite number >= 0",
            value: lr,
        });
    }
    Ok(())
}

/// `original` (a drivesim weight file) with `tensors` in place of its own of the same names
/// (or added), every tensor in `dtype` (`None`: the file's own), and `trained_on` in its
/// metadata: [`crate::weights::rewrite`] of a trainer's tensors. With `group`, the file's tensors
/// under that prefix go, and `tensors` are the whole group.
#[cfg(feature = "std")]
pub(super) fn weight_file(
    original: &[u8],
    tensors: &[super::NamedTensor],
    group: Option<&str>,
    dtype: Option<crate::WeightDtype>,
    trained_on: super::TrainedOn<'_>,
) -> Result<alloc::vec::Vec<u8>> {
    let replace: alloc::vec::Vec<(&str, &[usize], &[f32])> = tensors
        .iter()
        .map(|(name, shape, values)| (name.as_str(), &shape[..], &values[..]))
        .collect();
    crate::weights::rewrite(original, &replace, group, dtype, trained_on)
}

/// `sums[r] = Σ_k dy[k][r]`: the gradient of a bias.
pub(super) fn column_sums(dy: &[f32], sums: &mut [f32]) {
    sums.fill(0.0);
    for row in dy.chunks_exact(sums.len()) {
        sums.iter_mut().zip(row).for_each(|(s, v)| *s += v);
    }
}
