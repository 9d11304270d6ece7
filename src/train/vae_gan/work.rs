//! The count of one VAE-GAN step's work per thread ([`VaeGanPlan::work`]), from the networks a
//! plan builds and the passes `step.rs` runs over them.

use super::budget::Budget;
use super::layers::{Conv, Dense};
use super::networks::build;
use super::plan::VaeGanPlan;
use super::weight_grad::GradSplit;
use crate::layers::dense_parts;
use crate::pool::spans;
use crate::train::work::{panel_units, StepWork};
use crate::Result;
use alloc::vec::Vec;
use drivesim_kernels::{conv_grad_pixels, conv_patch_len, Matrix};

/// Multiply-adds of a layer's convolution for one item (direct, every tap).
fn conv_macs(l: &Conv) -> u64 {
    let down = l.grad_shape();
    (conv_grad_pixels(&down, 1) * down.output.channels * conv_patch_len(&down)) as u64
}

/// The passes of [`super::step`] over the networks, as they share their work.
struct Count<'a> {
    work: StepWork,
    threads: usize,
    _plan: &'a VaeGanPlan,
}

impl Count<'_> {
    /// A stack's forward pass over `items`: convolutions and BatchNorm take items.
    fn forward(&mut self, layers: &[Conv], items: usize) {
        for l in layers {
            self.work.equal("convolutions", items, conv_macs(l));
            // BatchNorm's moments and normalisation: two passes over each output.
            self.work
                .equal("passes over activations", items, 2 * l.shape.output.len() as u64);
            self.alone_sums(l, items);
        }
    }

    /// BatchNorm's (or a bias's) per-item sums added up in item order, on one thread.
    fn alone_sums(&mut self, l: &Conv, items: usize) {
        let sums = 2 * l.shape.output.channels as u64;
        self.work.alone("on one thread", items as u64 * sums);
    }

    /// A stack's backward pass over `items` from its top, the data gradients of `data` layers
    /// (from the top), the weight gradients if `weights`.
    fn backward(&mut self, layers: &[Conv], items: usize, data: usize, weights: bool) {
        for (i, l) in layers.iter().enumerate().rev() {
            // The activation's and BatchNorm's gradients: three passes over each output.
            self.work
                .equal("passes over activations", items, 3 * l.shape.output.len() as u64);
            self.alone_sums(l, items);
            if weights {
                self.weight_grad(l, items);
            }
            if i + data >= layers.len() {
                self.work.equal("data gradients", items, conv_macs(l));
            }
        }
    }

    /// A layer's weight gradient as [`GradSplit`] cuts it, and the partials' sum.
    fn weight_grad(&mut self, l: &Conv, items: usize) {
        let down = l.grad_shape();
        let split = GradSplit::new(&down, items, self.threads);
        let (rows, cols) = (down.output.channels, conv_patch_len(&down));
        let units = (0..split.blocks).flat_map(|b| {
            let pixels = split.pixels(b).len();
            (0..split.groups).map(move |g| (split.group_rows(rows, g) * cols * pixels) as u64)
        });
        self.work.part("weight gradients", units.collect::<Vec<_>>());
        if split.blocks > 1 {
            let spans = spans(Matrix::packed_len(rows, cols));
            let adds = spans.map(|s| (s.len() * split.blocks) as u64);
            self.work.part("partial gradients added", adds);
        }
    }

    /// A dense layer's product over `items`, its rows shared as [`crate::layers::dense`] does.
    fn dense(&mut self, d: &Dense, items: usize) {
        let parts = dense_parts(self.threads, d.rows, d.cols);
        self.work
            .part("dense layers", panel_units(d.rows, parts, (d.cols * items) as u64));
    }

    /// A dense layer's gradients over `items`: weights (rows shared, the bias on one thread)
    /// if `weights`, and data (columns shared).
    fn dense_grads(&mut self, d: &Dense, items: usize, weights: bool) {
        let (rows, cols, t) = (d.rows, d.cols, self.threads);
        if weights {
            self.work
                .part("dense layers", panel_units(rows, t, (cols * items) as u64));
            self.work.alone("on one thread", (rows * items) as u64);
        }
        self.work
            .part("dense layers", panel_units(cols, t, (rows * items) as u64));
    }
}

impl VaeGanPlan {
    /// The work each of `threads` threads gets in one step of a trainer of this plan's config
    /// and batch, part by part (see [`crate::train::StepWork`]): a count, measured on no
    /// machine.
    ///
    /// ```
    /// use drivesim::{train::VaeGanPlan, Config};
    /// let plan = VaeGanPlan::new(&Config::COMMA, 16, 1)?;
    /// let work = plan.work(16)?;
    /// assert!(work.imbalance() >= 1.0 && work.largest() <= work.total());
    /// # Ok::<(), drivesim::Error>(())
    /// ```
    pub fn work(&self, threads: usize) -> Result<StepWork> {
        let threads = crate::pool::check_threads(threads)?;
        let mut budget = Budget {
            allocate: false,
            floats: Vec::new(),
        };
        let nets = build(&self.config, self.batch, threads, &mut budget)?;
        let (n, pair) = (self.batch, 2 * self.batch);
        let mut c = Count {
            work: StepWork::new(threads),
            threads,
            _plan: self,
        };
        let (enc, gen, dis) = (&nets.enc[..], &nets.gen[..], &nets.dis[..]);
        // Forward: the encoder, its heads, the generator on reconstructions and prior samples,
        // then the discriminator on real frames and on both, before and after its update.
        c.forward(enc, n);
        c.dense(&nets.heads, n);
        c.dense(&nets.fc, pair);
        c.forward(gen, pair);
        for items in [n, pair, n, pair] {
            c.forward(dis, items);
            c.dense(&nets.logit, items);
        }
        // The discriminator's gradients on real frames and on both fakes.
        for items in [n, pair] {
            c.dense_grads(&nets.logit, items, true);
            c.backward(dis, items, dis.len() - 1, true);
        }
        // The encoder's and generator's: the feature loss down the discriminator's first three
        // layers, the pixel loss through the generator, the heads, the encoder, the GAN loss
        // down the whole discriminator, and the generator with its weights.
        c.backward(&dis[..3], pair, 3, false);
        c.backward(gen, n, gen.len(), false);
        c.dense_grads(&nets.fc, n, false);
        c.dense_grads(&nets.heads, n, true);
        c.backward(enc, n, enc.len() - 1, true);
        c.dense_grads(&nets.logit, pair, false);
        c.backward(dis, pair, dis.len(), false);
        c.backward(gen, pair, gen.len(), true);
        c.dense_grads(&nets.fc, pair, true);
        // Each network's update: its gradients zeroed, checked and applied by Adam, a piece of
        // each at a time, then its layers repacked one at a time.
        for net in &nets.nets {
            let pieces = spans(net.len()).map(|p| 8 * p.len() as u64);
            c.work.part("zeroing, checking and Adam", pieces);
        }
        for (convs, dense) in [(enc, &nets.heads), (gen, &nets.fc), (dis, &nets.logit)] {
            let mut jobs: Vec<u64> = convs.iter().flat_map(|l| [2 * l.weight.len() as u64; 2]).collect();
            jobs.push((dense.rows * dense.cols) as u64);
            jobs.sort_unstable_by(|a, b| b.cmp(a));
            c.work.part("repacking", jobs);
        }
        Ok(c.work)
    }
}
