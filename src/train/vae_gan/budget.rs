//! How the VAE-GAN trainer's buffers are counted before anything is allocated (planning) or
//! allocated (the trainer): the [`Budget`], and the scratch sizes every layer reports.

use crate::Error;
use crate::Result;
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
pub(super) const OVERFLOW: Error = Error::OutOfMemory {
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
