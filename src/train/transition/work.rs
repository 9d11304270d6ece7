//! The count of one transition training step's work per thread ([`TransitionPlan::work`]):
//! the products and passes of `bptt.rs` over the window's steps, as `threads.rs` shares them.

use super::plan::TransitionPlan;
use super::threads::{grad_blocks, product_grid, row_parts, row_run, SUM_COLUMNS};
use crate::pool::{spans, spans_of_at_least};
use crate::train::work::{panel_units, StepWork};
use crate::Result;
use alloc::vec::Vec;
use drivesim_kernels::Matrix;

impl TransitionPlan {
    /// The work each of `threads` threads gets in one step ([`super::TransitionTrainer::step`]
    /// with the default settings, then the Adam step) on a full batch, part by part (see
    /// [`crate::train::StepWork`]): a count, measured on no machine.
    ///
    /// ```
    /// use drivesim::{train::TransitionPlan, Config};
    /// let work = TransitionPlan::new(&Config::COMMA, 256, 15)?.work(16)?;
    /// assert!(work.imbalance() >= 1.0);
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn work(&self, threads: usize) -> Result<StepWork> {
        let threads = crate::pool::check_threads(threads)?;
        let d = self.dims;
        let (h, z, a, cols, batch) = (d.hidden, d.z, d.actions, d.cols(), d.batch);
        let mut w = StepWork::new(threads);
        // A pass over `count` rows of `each` work, runs of rows as `threads::each_row` takes them
        // (the last rows after them on one thread).
        let runs = |w: &mut StepWork, count: usize, each: u64| {
            let run = row_run(count, threads);
            w.equal("passes over items", count / run, run as u64 * each);
            w.alone("on one thread", (count % run) as u64 * each);
        };
        // A product `y = W x` over `items`, cut as `threads::product` cuts it.
        let product = |w: &mut StepWork, rows: usize, cols: usize, items: usize| {
            let (row_parts, blocks) = product_grid(threads, rows, items);
            let per_block = (cols * (items / blocks)) as u64;
            let units: Vec<u64> = (0..blocks)
                .flat_map(|_| panel_units(rows, row_parts, per_block))
                .collect();
            w.part("products over a step", units);
        };
        for _ in 0..d.steps() {
            // Forward: the inputs gathered (threads take windows), `h = tanh([W | V | U] x + b)`,
            // `z' = A h + a`; backward: the gradients gathered, `[Aᵀ | Wᵀ]`, the tanh's gradient.
            runs(&mut w, batch, (cols + (z + h) + h) as u64);
            product(&mut w, h, cols, batch);
            product(&mut w, z, h, batch);
            product(&mut w, h, z + h, batch);
        }
        let items = d.steps() * batch;
        // The loss, a span of each step's windows at a time, and its gradient, runs of items.
        for _ in 0..d.steps() {
            w.part("passes over items", spans(batch).map(|s| (s.len() * z) as u64));
        }
        runs(&mut w, items, z as u64);
        // The weight gradients, blocks of items summed apart and added, and the biases'.
        for (rows, cols) in [(h, cols), (z, h)] {
            let blocks = grad_blocks(rows, items);
            let per_block = items.div_ceil(blocks);
            let (parts, _) = row_parts(threads, rows, blocks, per_block);
            let block = |b: usize| (((b + 1) * per_block).min(items) - (b * per_block).min(items)) as u64;
            let units: Vec<u64> = (0..blocks)
                .flat_map(|b| panel_units(rows, parts, block(b) * cols as u64))
                .collect();
            w.part("weight gradients", units);
            if blocks > 1 {
                let adds = spans(Matrix::packed_len(rows, cols)).map(|s| (s.len() * blocks) as u64);
                w.part("partial gradients added", adds);
            }
            w.part(
                "passes over items",
                spans_of_at_least(rows, SUM_COLUMNS).map(|s| (s.len() * items) as u64),
            );
        }
        // The norm for clipping and Adam, a span at a time; the transposed packings made again
        // on one thread.
        let params = h * cols + z * h + h + z;
        w.part("norm and Adam", spans(params).map(|s| 10 * s.len() as u64));
        w.alone("on one thread", (h * (z + h) + (z + a) * h) as u64);
        Ok(w)
    }
}
