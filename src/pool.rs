//! A fixed set of worker threads, started when a simulator is planned, that run one borrowed
//! closure at a time. Dispatching allocates nothing: the closure stays on the caller's stack and
//! the workers only ever see a pointer to it while the caller waits for them.

use core::marker::PhantomData;
use core::ops::Range;
use core::sync::atomic::{AtomicUsize, Ordering};
use drivesim_kernels::Isa;

/// The most threads one simulator or trainer shares its work among, the caller's included.
/// More is a [`crate::Error::Config`] from planning, before any buffer is allocated or any
/// thread started: a count that large is a mistake (no machine has the cores to use it), and
/// the pool's bookkeeping for it alone could exhaust memory.
pub const MAX_THREADS: usize = 1024;

/// `threads` (0 counts as 1) when at most [`MAX_THREADS`], else [`crate::Error::Config`].
pub(crate) fn check_threads(threads: usize) -> crate::Result<usize> {
    match threads {
        0..=MAX_THREADS => Ok(threads.max(1)),
        found => Err(crate::Error::Config {
            field: "threads",
            expected: "at most 1024 (drivesim::MAX_THREADS), the caller's included",
            found,
        }),
    }
}

/// How a network runs: the kernels' instruction set and, optionally, threads to share it.
#[derive(Clone, Copy)]
pub(crate) struct Exec<'a> {
    pub isa: Isa,
    pub pool: Option<&'a Pool>,
}

impl Exec<'_> {
    pub fn threads(&self) -> usize {
        self.pool.map_or(1, Pool::threads)
    }

    /// Runs `task` on every thread at once, or alone on the caller's without a pool. The
    /// threads share the work by taking [`Parts`] of it.
    pub fn run(&self, task: &(dyn Fn() + Sync)) {
        match self.pool {
            Some(pool) => pool.run(task),
            None => task(),
        }
    }
}

#[cfg(feature = "std")]
pub(crate) use workers::Pool;

/// Without std there are no threads: no pool can be made.
#[cfg(not(feature = "std"))]
pub(crate) enum Pool {}

#[cfg(not(feature = "std"))]
impl Pool {
    pub fn threads(&self) -> usize {
        match *self {}
    }
    pub fn run(&self, _task: &(dyn Fn() + Sync)) {
        match *self {}
    }
}

#[cfg(feature = "std")]
mod workers;

/// Spans a pass over a buffer is cut into (zeroing, checking, Adam, sums in f64, partial
/// gradients added), threads taking them in turn: the same spans, so the same bits, whatever
/// the thread count; enough for 64 threads. (The trainers' passes.)
#[cfg(feature = "train")]
pub(crate) const SPANS: usize = 64;

/// The [`SPANS`] ranges of `len` values (the last ones shorter or empty).
#[cfg(feature = "train")]
pub(crate) fn spans(len: usize) -> [Range<usize>; SPANS] {
    spans_of_at_least(len, 1)
}

/// [`spans`] of at least `least` values each (fewer, then): a pass that reads every row of a
/// batch for its span of columns reads whole cache lines and vectors.
#[cfg(feature = "train")]
pub(crate) fn spans_of_at_least(len: usize, least: usize) -> [Range<usize>; SPANS] {
    let step = len.div_ceil(SPANS).max(least).max(1);
    core::array::from_fn(|i| (i * step).min(len)..((i + 1) * step).min(len))
}

/// A slice cut into parts that the threads of one task take, each part once: whole items of a
/// batch, sets of planes, scratch per thread, spans of a buffer. Taking is safe: the parts are
/// disjoint by construction and handed out by an atomic counter.
pub(crate) struct Parts<'a, T> {
    ptr: *mut T,
    cut: Cut<'a>,
    count: usize,
    next: AtomicUsize,
    _borrow: PhantomData<&'a mut [T]>,
}

/// How [`Parts`] cuts its slice.
enum Cut<'a> {
    /// Consecutive chunks of this length.
    Chunks(usize),
    /// These ranges, increasing and disjoint (checked).
    Spans(&'a [Range<usize>]),
}

// SAFETY: threads reach the data only through `take`, which hands each disjoint part out once;
// the values move between threads, so they must be `Send`.
unsafe impl<T: Send> Sync for Parts<'_, T> {}

impl<'a, T> Parts<'a, T> {
    /// `data` in whole chunks of `len` (a shorter tail is left out).
    pub fn chunks(data: &'a mut [T], len: usize) -> Self {
        let count = data.len().checked_div(len).unwrap_or(0);
        Parts::new(data, Cut::Chunks(len), count)
    }

    /// The `spans` of `data`: they must increase, not overlap, and lie inside it.
    pub fn spans(data: &'a mut [T], spans: &'a [Range<usize>]) -> Self {
        let mut end = 0;
        for span in spans {
            assert!(end <= span.start && span.start <= span.end, "spans overlap");
            end = span.end;
        }
        assert!(end <= data.len(), "span past the end");
        Parts::new(data, Cut::Spans(spans), spans.len())
    }

    fn new(data: &'a mut [T], cut: Cut<'a>, count: usize) -> Self {
        Parts {
            ptr: data.as_mut_ptr(),
            cut,
            count,
            next: AtomicUsize::new(0),
            _borrow: PhantomData,
        }
    }

    /// The next part no thread has taken, with its index, or `None` when all were.
    #[allow(clippy::mut_from_ref)] // the point of the type: each part is handed out once
    pub fn take(&self) -> Option<(usize, &mut [T])> {
        let i = self.next.fetch_add(1, Ordering::Relaxed);
        if i >= self.count {
            return None;
        }
        let range = match self.cut {
            Cut::Chunks(len) => i * len..(i + 1) * len,
            Cut::Spans(spans) => spans[i].clone(),
        };
        // SAFETY: the range lies in the borrowed slice (checked at construction), is disjoint
        // from every other part's, and `next` gives index `i` to one caller only.
        Some((i, unsafe {
            core::slice::from_raw_parts_mut(self.ptr.add(range.start), range.len())
        }))
    }
}

/// Several buffers of one batch cut into the same ranges of whole items and taken together:
/// what a thread needs to run its share of the items alone, every layer of them, with no
/// barrier between the layers. `parts` balanced ranges; taking is safe as for [`Parts`].
pub(crate) struct ItemParts<'a, const B: usize> {
    /// Each buffer's start and floats per item.
    buffers: [(*mut f32, usize); B],
    items: usize,
    parts: usize,
    next: AtomicUsize,
    _borrow: PhantomData<&'a mut [f32]>,
}

// SAFETY: the buffers are only reached through `take`, which hands each range of items out
// once, and the ranges are disjoint.
unsafe impl<const B: usize> Sync for ItemParts<'_, B> {}

impl<'a, const B: usize> ItemParts<'a, B> {
    /// `buffers`, each holding `items` items of equal length, in `parts` ranges of items.
    pub fn new(buffers: [&'a mut [f32]; B], items: usize, parts: usize) -> Self {
        assert!(
            items > 0 && buffers.iter().all(|b| b.len().is_multiple_of(items)),
            "not whole items"
        );
        ItemParts {
            buffers: buffers.map(|b| (b.as_mut_ptr(), b.len() / items)),
            items,
            parts: parts.clamp(1, items),
            next: AtomicUsize::new(0),
            _borrow: PhantomData,
        }
    }

    /// The next range of items no thread has taken, with each buffer's part of it.
    #[allow(clippy::mut_from_ref)] // each range is handed out once
    pub fn take(&self) -> Option<(Range<usize>, [&mut [f32]; B])> {
        let i = self.next.fetch_add(1, Ordering::Relaxed);
        if i >= self.parts {
            return None;
        }
        let items = i * self.items / self.parts..(i + 1) * self.items / self.parts;
        // SAFETY: the range lies in every buffer (whole items, checked at construction) and is
        // disjoint from every other part's; `next` gives index `i` to one caller only.
        let parts = self.buffers.map(|(ptr, len)| unsafe {
            core::slice::from_raw_parts_mut(ptr.add(items.start * len), items.len() * len)
        });
        Some((items, parts))
    }
}
