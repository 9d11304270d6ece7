//! A trainer's memory: one block of f32, sized by its plan before anything is allocated, either
//! allocated once by the crate or handed in by the caller, then cut into named buffers in a
//! fixed order at every call (cutting allocates nothing).

use crate::plan::zeros;
use crate::{Error, Result};
use alloc::vec::Vec;

/// Bytes of `floats` f32 values, or the overflow as [`Error::OutOfMemory`].
pub(crate) fn bytes_of(floats: usize, what: &'static str) -> Result<usize> {
    floats
        .checked_mul(core::mem::size_of::<f32>())
        .filter(|&b| b <= isize::MAX as usize)
        .ok_or(Error::OutOfMemory { what, bytes: None })
}

/// The sum of `lens`, or the overflow as [`Error::OutOfMemory`].
pub(crate) fn total(lens: &[usize], what: &'static str) -> Result<usize> {
    lens.iter()
        .try_fold(0usize, |sum, &n| sum.checked_add(n))
        .ok_or(Error::OutOfMemory { what, bytes: None })
}

/// The arena's block of floats.
pub(crate) enum Memory<'a> {
    /// Allocated once by [`Memory::allocate`].
    Owned(Vec<f32>),
    /// The caller's buffer (its first `floats` values).
    Borrowed(&'a mut [f32]),
}

impl Memory<'_> {
    /// `floats` zeros in one allocation, or [`Error::OutOfMemory`] naming `bytes`.
    pub fn allocate(floats: usize, bytes: usize) -> Result<Memory<'static>> {
        Ok(Memory::Owned(zeros(floats, bytes)?))
    }

    /// The first `floats` values of `buffer`, zeroed, or [`Error::ArenaTooSmall`].
    pub fn borrow(buffer: &mut [f32], floats: usize) -> Result<Memory<'_>> {
        let given = buffer.len().saturating_mul(core::mem::size_of::<f32>());
        let needed = floats.saturating_mul(core::mem::size_of::<f32>());
        let block = buffer.get_mut(..floats).ok_or(Error::ArenaTooSmall { needed, given })?;
        block.fill(0.0);
        Ok(Memory::Borrowed(block))
    }

    pub fn floats(&mut self) -> &mut [f32] {
        match self {
            Memory::Owned(v) => v,
            Memory::Borrowed(b) => b,
        }
    }

    pub fn floats_ref(&self) -> &[f32] {
        match self {
            Memory::Owned(v) => v,
            Memory::Borrowed(b) => b,
        }
    }
}

/// `block` cut into consecutive buffers of `lens` (which the plan made sum to its length).
pub(crate) fn cut<'b, const N: usize>(mut block: &'b mut [f32], lens: &[usize; N]) -> [&'b mut [f32]; N] {
    core::array::from_fn(|i| {
        let (head, rest) = core::mem::take(&mut block).split_at_mut(lens[i]);
        block = rest;
        head
    })
}

/// [`cut`] for shared access.
pub(crate) fn cut_ref<'b, const N: usize>(mut block: &'b [f32], lens: &[usize; N]) -> [&'b [f32]; N] {
    core::array::from_fn(|i| {
        let (head, rest) = block.split_at(lens[i]);
        block = rest;
        head
    })
}
