//! A convolution's weight gradient over a batch, shared by the threads in a partition that the
//! layer's shape and the batch fix alone: the same sums, bit for bit, whatever the thread count.
//!
//! The gradient is a sum over the batch's output pixels. Cutting it by output channels only
//! (panels of 16 rows) leaves 2 parts to a 32-channel layer, however many threads there are; so
//! the pixels are cut too, into blocks of whole chunks, each block summed into a partial
//! gradient of its own (planned memory), and the partials are then added in block order. The
//! blocks are set by the layer's shape and the batch alone, so the sums do not change with the
//! thread count; the rows are cut by the threads.

use crate::pool::{spans, Exec, Parts};
use core::ops::Range;
use drivesim_kernels::{
    conv_grad_pixels, conv_patch_len, conv_weight_grad_add_rows, conv_weight_grad_block_rows,
    conv_weight_grad_scratch_len, ConvShape, Matrix, OutputParts, GRAD_PIXELS, OC_ALIGN,
};

/// Parts a layer's weight gradient aims at (panels of rows times blocks of pixels): enough for
/// 32 threads.
const UNITS: usize = 32;
/// Output pixels in a block at least: each block adds a partial gradient (the weights' size)
/// to read back, which stays a small fraction of its products (pixels x weights) beside them.
const BLOCK_PIXELS: usize = 2 * GRAD_PIXELS;
/// A gathered patch float's cost in multiply-adds, roughly: a copy against vectors of FMAs.
const GATHER_COST: usize = 4;

/// How the weight gradient of the strided shape `down` over `items` planes is cut: `groups`
/// ranges of whole panels of its rows (as [`OutputParts`] cuts them), times `blocks` ranges of
/// whole chunks of its output pixels ([`GradSplit::pixels`]). The blocks, which decide the
/// sums, come from the shape and the batch alone; the groups, which do not, from the threads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct GradSplit {
    pub(crate) groups: usize,
    pub(crate) blocks: usize,
    chunks: usize,
    pixels: usize,
}

impl GradSplit {
    /// The blocks for the shape and batch; the groups that make the slowest of `threads`
    /// threads finish first, counting a unit's products and its gathering of patches (each
    /// group gathers its block's patches again).
    pub(crate) fn new(down: &ConvShape, items: usize, threads: usize) -> GradSplit {
        let (rows, pixels) = (down.output.channels, conv_grad_pixels(down, items));
        let panels = rows.div_ceil(OC_ALIGN).max(1);
        let chunks = pixels.div_ceil(GRAD_PIXELS).max(1);
        // No more blocks than the panels need to make the parts: each is read back.
        let blocks = (pixels / BLOCK_PIXELS).clamp(1, UNITS.div_ceil(panels));
        let threads = threads.max(1);
        let slowest = |groups: usize| {
            let units_each = (groups * blocks).div_ceil(threads);
            units_each * (panels.div_ceil(groups) * OC_ALIGN + GATHER_COST)
        };
        let groups = (1..=panels).min_by_key(|&g| slowest(g)).unwrap_or(1);
        GradSplit {
            groups,
            blocks,
            chunks,
            pixels,
        }
    }

    /// Output pixels of block `b`: whole chunks of [`GRAD_PIXELS`] shared as evenly as can be.
    pub(crate) fn pixels(&self, b: usize) -> Range<usize> {
        let at = |b: usize| (self.chunks * b / self.blocks * GRAD_PIXELS).min(self.pixels);
        at(b)..at(b + 1)
    }

    /// Floats of the partial gradients (none for one block: it adds into the gradient itself).
    pub(crate) fn partials_len(&self, down: &ConvShape) -> usize {
        match self.blocks {
            1 => 0,
            blocks => blocks * Matrix::packed_len(down.output.channels, conv_patch_len(down)),
        }
    }

    /// The rows of each group ([`OutputParts`]' ranges of whole panels).
    pub(crate) fn group_rows(&self, rows: usize, g: usize) -> usize {
        let panels = rows.div_ceil(OC_ALIGN);
        let panel = |g: usize| panels * g / self.groups * OC_ALIGN;
        panel(g + 1).min(rows) - panel(g).min(rows)
    }
}

/// The weight gradient of the strided shape `down` over a batch (`input` its planes, `dy` its
/// output's gradient), added to what `grad` holds (in the layout of
/// [`Table::conv`](super::table::Table::conv)), cut as [`GradSplit::new`] says: each thread
/// takes parts, gathering the patches of its block into its own share of `scratch`
/// ([`conv_weight_grad_scratch_len`] each); then the threads add the partials (in `partials`)
/// into `grad` span by span, block after block.
pub(super) fn conv_weight_grad(
    exec: Exec<'_>,
    down: ConvShape,
    (input, dy): (&[f32], &[f32]),
    scratch: &mut [f32],
    partials: &mut [f32],
    grad: &mut [f32],
) {
    let (isa, rows) = (exec.isa, down.output.channels);
    let split = GradSplit::new(&down, input.len() / down.input.len(), exec.threads());
    let each = conv_weight_grad_scratch_len(&down);
    let scratch = Parts::chunks(&mut scratch[..exec.threads() * each], each);
    if split.blocks == 1 {
        let parts = OutputParts::new(grad, rows, split.groups);
        exec.run(&|| {
            let (_, scratch) = scratch.take().expect("a scratch for every thread");
            while let Some(part) = parts.take() {
                conv_weight_grad_add_rows(isa, down, input, dy, scratch, part);
            }
        });
        return;
    }
    let len = grad.len();
    let partials = &mut partials[..split.blocks * len];
    let parts = OutputParts::grid(partials, split.blocks, rows, split.groups);
    exec.run(&|| {
        let (_, scratch) = scratch.take().expect("a scratch for every thread");
        while let Some((b, part)) = parts.take_in_buffer() {
            conv_weight_grad_block_rows(isa, down, input, dy, split.pixels(b), scratch, part);
        }
    });
    let partials = &*partials;
    let spans = spans(len);
    let sums = Parts::spans(grad, &spans);
    exec.run(&|| {
        while let Some((i, grad)) = sums.take() {
            add_partials(grad, partials, len, spans[i].start);
        }
    });
}

/// Floats summed at once: a tile of the blocks' sum stays in registers and L1.
const TILE: usize = 256;

/// `grad += Σ_b partials[b][start..]` over `grad`'s length, the blocks added in order.
fn add_partials(grad: &mut [f32], partials: &[f32], len: usize, start: usize) {
    let mut sum = [0.0f32; TILE];
    for (t, grad) in grad.chunks_mut(TILE).enumerate() {
        let (at, n) = (start + t * TILE, grad.len());
        let sum = &mut sum[..n];
        let mut blocks = partials.chunks_exact(len).map(|p| &p[at..][..n]);
        sum.copy_from_slice(blocks.next().expect("two blocks or more"));
        for block in blocks {
            sum.iter_mut().zip(block).for_each(|(s, p)| *s += p);
        }
        grad.iter_mut().zip(sum.iter()).for_each(|(g, s)| *g += s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Config;

    /// The blocks (which decide the sums) are the same for every thread count, cover the
    /// batch's pixels in order on chunk boundaries, and one thread takes the rows whole.
    #[test]
    fn blocks_depend_on_the_layer_and_batch_alone() {
        let mut default = Config::COMMA;
        default.base_channels = 32;
        for config in [Config::COMMA, default] {
            let shapes = config
                .encoder_convs()
                .chain(config.generator_convs().map(|s| s.transposed()));
            for down in shapes {
                for items in [1, 3, 64, 128] {
                    let one = GradSplit::new(&down, items, 1);
                    assert_eq!(one.groups, 1);
                    let mut end = 0;
                    for b in 0..one.blocks {
                        let pixels = one.pixels(b);
                        assert!(pixels.start == end && pixels.start.is_multiple_of(GRAD_PIXELS));
                        end = pixels.end;
                    }
                    assert_eq!(end, conv_grad_pixels(&down, items));
                    for threads in 2..=32 {
                        let split = GradSplit::new(&down, items, threads);
                        assert_eq!(split.blocks, one.blocks, "{down:?} {items} items {threads} threads");
                        assert!(split.groups <= down.output.channels.div_ceil(OC_ALIGN));
                    }
                }
            }
        }
    }
}
