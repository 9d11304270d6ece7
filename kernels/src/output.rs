//! Output buffers that threads fill at once, each writing its own range of output channels (of
//! a convolution's plane) or rows (of a dense layer's batch of outputs).
//!
//! These ranges are strided through the buffer, so they cannot be `&mut` slices. Instead an
//! [`OutputParts`] borrows the whole buffer and hands each of its parts out once
//! ([`OutputParts::take`]); a kernel given an [`OutputPart`] writes only the units of that part.
//! So the threaded callers use safe functions, and the `unsafe` stays here and in the kernels.

use crate::OC_ALIGN;
use core::marker::PhantomData;
use core::ops::Range;
use core::sync::atomic::{AtomicUsize, Ordering};

/// An output buffer cut into `parts` ranges of its `units` (output channels or rows), each
/// starting on a multiple of [`OC_ALIGN`] (a panel of weights), of nearly equal size; or
/// ([`OutputParts::grid`]) several such buffers one after the other, each cut the same way.
pub struct OutputParts<'a> {
    ptr: *mut f32,
    /// Floats of each buffer.
    len: usize,
    buffers: usize,
    units: usize,
    parts: usize,
    /// The next part to hand out.
    next: AtomicUsize,
    _borrow: PhantomData<&'a mut [f32]>,
}

// SAFETY: the buffer is only reached through the parts `take` hands out, each once, and their
// unit ranges (or buffers) are disjoint.
unsafe impl Sync for OutputParts<'_> {}

impl<'a> OutputParts<'a> {
    /// `output` (all of the operation's output) as `parts` ranges of `units` (at least one).
    pub fn new(output: &'a mut [f32], units: usize, parts: usize) -> Self {
        OutputParts::grid(output, 1, units, parts)
    }

    /// `output` as `buffers` outputs of equal length one after the other (at least one; a
    /// shorter tail is left out), each as `parts` ranges of its `units`: buffer `b`'s part `p` is
    /// part `b * parts + p`. For sums that threads share by blocks of their terms, each block
    /// into a buffer of its own.
    pub fn grid(output: &'a mut [f32], buffers: usize, units: usize, parts: usize) -> Self {
        let buffers = buffers.max(1);
        OutputParts {
            ptr: output.as_mut_ptr(),
            len: output.len() / buffers,
            buffers,
            units,
            parts: parts.max(1),
            next: AtomicUsize::new(0),
            _borrow: PhantomData,
        }
    }

    /// The units of part `i` of a buffer: whole panels shared as evenly as can be.
    fn range(&self, i: usize) -> Range<usize> {
        let panels = self.units.div_ceil(OC_ALIGN);
        let panel = |i: usize| panels * i / self.parts;
        (panel(i) * OC_ALIGN).min(self.units)..(panel(i + 1) * OC_ALIGN).min(self.units)
    }

    /// The next part no one has taken, or `None` when all were; empty parts are skipped.
    pub fn take(&self) -> Option<OutputPart<'_>> {
        self.take_in_buffer().map(|(_, part)| part)
    }

    /// [`OutputParts::take`] with the index of the part's buffer.
    pub fn take_in_buffer(&self) -> Option<(usize, OutputPart<'_>)> {
        loop {
            let i = self.next.fetch_add(1, Ordering::Relaxed);
            if i >= self.parts * self.buffers {
                return None;
            }
            let (buffer, units) = (i / self.parts, self.range(i % self.parts));
            if !units.is_empty() {
                return Some((
                    buffer,
                    OutputPart {
                        // SAFETY: `buffer < buffers`, so its start lies in the borrowed output.
                        ptr: unsafe { self.ptr.add(buffer * self.len) },
                        len: self.len,
                        units,
                        _borrow: PhantomData,
                    },
                ));
            }
        }
    }
}

/// The units `units()` of an output buffer, for one kernel call to write.
pub struct OutputPart<'a> {
    ptr: *mut f32,
    len: usize,
    units: Range<usize>,
    _borrow: PhantomData<&'a mut [f32]>,
}

// SAFETY: a part is the only handle to its units; moving it to another thread moves that right.
unsafe impl Send for OutputPart<'_> {}

impl<'a> OutputPart<'a> {
    /// All `units` of `output`.
    pub fn whole(output: &'a mut [f32], units: usize) -> Self {
        OutputPart {
            ptr: output.as_mut_ptr(),
            len: output.len(),
            units: 0..units,
            _borrow: PhantomData,
        }
    }

    /// The same units for a shorter while: one part for several kernel calls in turn (a sum
    /// over chunks, [`crate::dense_weight_grad_add_rows`]).
    pub fn reborrow(&mut self) -> OutputPart<'_> {
        OutputPart {
            ptr: self.ptr,
            len: self.len,
            units: self.units.clone(),
            _borrow: PhantomData,
        }
    }

    /// The output channels or rows this part may write.
    pub fn units(&self) -> Range<usize> {
        self.units.clone()
    }

    /// Floats of the whole output buffer.
    pub fn buffer_len(&self) -> usize {
        self.len
    }

    /// The start of the whole buffer: a kernel writes only its units' floats through it.
    pub(crate) fn ptr(&self) -> *mut f32 {
        self.ptr
    }
}
