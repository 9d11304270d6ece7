//! The count of one transition training step's work per thread ([`TransitionPlan::work`]):
//! the products of `bptt.rs` over the window's steps, and what runs on one thread.

use super::bptt::product_grid;
use super::plan::TransitionPlan;
use crate::train::work::{panel_units, StepWork};
use crate::Result;
use alloc::vec::Vec;

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
        // A product `y = W x` over `items`, cut as `bptt::product` cuts it.
        let product = |w: &mut StepWork, name, rows: usize, cols: usize, items: usize| {
            let (row_parts, blocks) = product_grid(threads, rows, items);
            let per_block = (cols * (items / blocks)) as u64;
            let units: Vec<u64> = (0..blocks)
                .flat_map(|_| panel_units(rows, row_parts, per_block))
                .collect();
            w.part(name, units);
        };
        for _ in 0..d.steps() {
            // Forward: the inputs gathered, `h = tanh([W | V | U] x + b)`, `z' = A h + a`, the
            // loss; backward: the gradients gathered, `[Aᵀ | Wᵀ]`, the tanh's gradient.
            w.alone("on one thread", (batch * (cols + 3 * z + (z + h) + h)) as u64);
            product(&mut w, "products over a step", h, cols, batch);
            product(&mut w, "products over a step", z, h, batch);
            product(&mut w, "products over a step", h, z + h, batch);
        }
        // The weight gradients over every step at once (rows shared by the threads), the biases'
        // on one thread.
        let items = d.steps() * batch;
        w.part("weight gradients", panel_units(h, threads, (cols * items) as u64));
        w.part("weight gradients", panel_units(z, threads, (h * items) as u64));
        w.alone("on one thread", (items * (h + z)) as u64);
        // The norm for clipping, Adam, and the transposed packings made again.
        let params = h * cols + z * h + h + z;
        w.alone("on one thread", (10 * params + h * (z + h) + (z + a) * h) as u64);
        Ok(w)
    }
}
