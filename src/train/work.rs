//! How a training step's work falls to its threads: a count from the plan, the same on every
//! machine, of the multiply-adds (and the element operations of the passes over buffers) that
//! each of `threads` threads gets in each of the step's parallel parts, and of the work done on
//! one thread alone. Every part ends when its slowest thread does, so the sum of the parts'
//! largest shares against the mean share bounds the step's speed-up: the
//! [`StepWork::imbalance`].
//!
//! The units of each part are those the trainers' partitions hand out (items of a batch, panels
//! of rows, blocks of pixels, pieces of buffers), each taken in turn by the thread with the least
//! work so far, as threads taking them from a counter do when they run at one speed.

use alloc::vec::Vec;

/// One parallel part of a step (or work on one thread: a single unit).
#[derive(Clone, Debug, PartialEq)]
pub struct PartWork {
    /// What the part computes.
    pub name: &'static str,
    /// Multiply-adds (or element operations) of all its units.
    pub total: u64,
    /// The largest thread's share.
    pub largest: u64,
}

/// The parts of one training step at a thread count ([`crate::train::VaeGanPlan::work`],
/// [`crate::train::TransitionPlan::work`]).
#[derive(Clone, Debug, PartialEq)]
pub struct StepWork {
    /// The threads sharing the step.
    pub threads: usize,
    /// Its parts, each name once (in the order first met).
    pub parts: Vec<PartWork>,
}

impl StepWork {
    pub(crate) fn new(threads: usize) -> StepWork {
        StepWork {
            threads: threads.max(1),
            parts: Vec::new(),
        }
    }

    /// Adds a part of these units (their work, in the order threads take them); equal parts
    /// with the same name are merged.
    pub(crate) fn part(&mut self, name: &'static str, units: impl IntoIterator<Item = u64>) {
        let mut loads = alloc::vec![0u64; self.threads];
        let mut total = 0u64;
        for unit in units {
            let least = loads.iter_mut().min().expect("one thread at least");
            *least += unit;
            total += unit;
        }
        let largest = loads.into_iter().max().unwrap_or(0);
        match self.parts.iter_mut().find(|p| p.name == name) {
            Some(p) => {
                p.total += total;
                p.largest += largest;
            }
            None => self.parts.push(PartWork { name, total, largest }),
        }
    }

    /// `count` units of `each`.
    pub(crate) fn equal(&mut self, name: &'static str, count: usize, each: u64) {
        self.part(name, (0..count).map(|_| each));
    }

    /// Work all on one thread.
    pub(crate) fn alone(&mut self, name: &'static str, work: u64) {
        self.part(name, [work]);
    }

    /// All the parts' work.
    pub fn total(&self) -> u64 {
        self.parts.iter().map(|p| p.total).sum()
    }

    /// The parts' largest shares, added: the step's critical path.
    pub fn largest(&self) -> u64 {
        self.parts.iter().map(|p| p.largest).sum()
    }

    /// [`StepWork::largest`] against the mean share (`total / threads`): 1 where every thread
    /// gets the same in every part; the speed-up over one thread is at most `threads /
    /// imbalance`.
    pub fn imbalance(&self) -> f64 {
        match self.total() {
            0 => 1.0,
            total => self.largest() as f64 * self.threads as f64 / total as f64,
        }
    }
}

/// The units of a product whose `rows` are cut into `parts` ranges of whole panels (as
/// [`drivesim_kernels::OutputParts`] cuts them), each unit `per_row` work for each of its rows.
pub(crate) fn panel_units(rows: usize, parts: usize, per_row: u64) -> impl Iterator<Item = u64> {
    let panels = rows.div_ceil(drivesim_kernels::OC_ALIGN);
    let parts = parts.max(1);
    let at = move |i: usize| (panels * i / parts * drivesim_kernels::OC_ALIGN).min(rows);
    (0..parts).map(move |i| (at(i + 1) - at(i)) as u64 * per_row)
}
