//! How the transition trainer's threads share a step: its products by panels of rows and blocks
//! of items, its weight gradients by panels of rows and blocks of items summed apart (the blocks
//! fixed by the items alone, so the bits do not change with the threads), and its passes over
//! items and over columns.

use crate::pool::{spans, spans_of_at_least, Exec, Parts, SPANS};
use drivesim_kernels::{dense_rows, dense_weight_grad_rows, Activation, Matrix, OutputParts, OC_ALIGN};

/// `y = act(W x + b)` over a batch, shared by the threads in a grid: ranges of whole panels of
/// the rows (each thread reading its share of the weights) times equal blocks of items, where
/// the panels alone are too few for the threads ([`product_grid`]). Each output is the same dot
/// product however the batch is cut, so the bits do not change with the threads.
pub(super) fn product(exec: Exec<'_>, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    let items = x.len() / w.cols;
    let (row_parts, blocks) = product_grid(exec.threads(), w.rows, items);
    let per_block = items / blocks;
    let parts = OutputParts::grid(y, blocks, w.rows, row_parts);
    exec.run(&|| {
        while let Some((b, part)) = parts.take_in_buffer() {
            let x = &x[b * per_block * w.cols..][..per_block * w.cols];
            dense_rows(exec.isa, w, bias, act, x, part);
        }
    });
}

/// The grid of [`product`] for `threads` threads, `rows` rows and `items` items: row parts and
/// item blocks (a divisor of `items`), the pair whose slowest thread gets the least work (in
/// panels times items), the fewest blocks among equals (each block reads every weight again).
pub(super) fn product_grid(threads: usize, rows: usize, items: usize) -> (usize, usize) {
    let threads = threads.max(1);
    let mut best = (usize::MAX, 1, 1);
    for blocks in (1..=threads.min(items.max(1))).filter(|b| items.is_multiple_of(*b)) {
        let (row_parts, slowest) = row_parts(threads, rows, blocks, items / blocks);
        if slowest < best.0 {
            best = (slowest, row_parts, blocks);
        }
    }
    (best.1, best.2)
}

/// The row parts for `blocks` blocks of `per_block` items each that leave the slowest of
/// `threads` threads the least work, and that work (in panels times items).
pub(super) fn row_parts(threads: usize, rows: usize, blocks: usize, per_block: usize) -> (usize, usize) {
    let panels = rows.div_ceil(OC_ALIGN).max(1);
    let slowest = |parts: usize| (parts * blocks).div_ceil(threads) * panels.div_ceil(parts) * per_block;
    let best = (1..=panels.min(threads.max(1)))
        .min_by_key(|&p| slowest(p))
        .unwrap_or(1);
    (best, slowest(best))
}

/// Items of a weight gradient's block at least (each block adds a partial gradient to read
/// back: a small fraction of its products at this size).
const GRAD_BLOCK_ITEMS: usize = 256;
/// Parts a weight gradient aims at: enough for 32 threads.
const GRAD_UNITS: usize = 32;

/// The blocks a `rows`-row weight gradient over `items` items is summed in: fixed by the shape
/// and the items alone. None beyond one where the panels of rows are enough parts already (the
/// partials cost their reading back, a few per cent of a step on one thread); else a power of
/// two, to pair with the usual thread counts.
pub(super) fn grad_blocks(rows: usize, items: usize) -> usize {
    let wanted = GRAD_UNITS.div_ceil(rows.div_ceil(OC_ALIGN).max(1));
    let most = (items / GRAD_BLOCK_ITEMS).clamp(1, wanted);
    1 << most.ilog2()
}

/// Floats of the partial gradients of a `rows x cols` weight over at most `items` items.
pub(super) fn partials_len(rows: usize, cols: usize, items: usize) -> usize {
    match grad_blocks(rows, items) {
        1 => 0,
        blocks => blocks * Matrix::packed_len(rows, cols),
    }
}

/// `grad = dyᵀ x` packed, over the items of `dy` and `x` cut into [`grad_blocks`] blocks, each
/// summed (threads taking panels of its rows) into its own partial in `partials`, the partials
/// then added in block order by threads taking spans of the gradient.
pub(super) fn weight_grad(
    exec: Exec<'_>,
    (dy, x): (&[f32], &[f32]),
    rows: usize,
    cols: usize,
    partials: &mut [f32],
    grad: &mut [f32],
) {
    let items = x.len() / cols;
    let blocks = grad_blocks(rows, items);
    let per_block = items.div_ceil(blocks);
    let (parts, _) = row_parts(exec.threads(), rows, blocks, per_block);
    let block = |b: usize| (b * per_block).min(items)..((b + 1) * per_block).min(items);
    if blocks == 1 {
        let parts = OutputParts::new(grad, rows, parts);
        exec.run(&|| {
            while let Some(part) = parts.take() {
                dense_weight_grad_rows(exec.isa, dy, x, rows, cols, part);
            }
        });
        return;
    }
    let len = grad.len();
    let partials = &mut partials[..blocks * len];
    let grid = OutputParts::grid(partials, blocks, rows, parts);
    exec.run(&|| {
        while let Some((b, part)) = grid.take_in_buffer() {
            let items = block(b);
            let (dy, x) = (
                &dy[items.start * rows..items.end * rows],
                &x[items.start * cols..items.end * cols],
            );
            dense_weight_grad_rows(exec.isa, dy, x, rows, cols, part);
        }
    });
    let partials = &*partials;
    let spans = spans(len);
    let sums = Parts::spans(grad, &spans);
    exec.run(&|| {
        while let Some((i, grad)) = sums.take() {
            let start = spans[i].start;
            grad.copy_from_slice(&partials[start..][..grad.len()]);
            for partial in partials.chunks_exact(len).skip(1) {
                let partial = &partial[start..][..grad.len()];
                grad.iter_mut().zip(partial).for_each(|(g, p)| *g += p);
            }
        }
    });
}

/// Columns of a span of [`column_sums`] at least.
pub(super) const SUM_COLUMNS: usize = 64;

/// `sums[c] = Σ_k dy[k][c]` (a bias's gradient), the items added in order for each column,
/// threads taking spans of at least [`SUM_COLUMNS`] columns.
pub(super) fn column_sums(exec: Exec<'_>, dy: &[f32], sums: &mut [f32]) {
    let cols = sums.len();
    let spans = spans_of_at_least(cols, SUM_COLUMNS);
    let parts = Parts::spans(sums, &spans);
    exec.run(&|| {
        while let Some((i, sums)) = parts.take() {
            let span = spans[i].clone();
            sums.fill(0.0);
            for row in dy.chunks_exact(cols) {
                sums.iter_mut().zip(&row[span.clone()]).for_each(|(s, v)| *s += v);
            }
        }
    });
}

/// Rows per run of [`each_row`] over `count` rows.
pub(super) fn row_run(count: usize, threads: usize) -> usize {
    count.div_ceil(4 * threads.max(1)).max(1)
}

/// `f(n, row)` for each row of `rows` (rows of `len` floats), threads taking runs of rows (a
/// few per thread: each take is a cache line the threads pass between them).
pub(super) fn each_row(exec: Exec<'_>, rows: &mut [f32], len: usize, f: &(dyn Fn(usize, &mut [f32]) + Sync)) {
    let count = rows.len() / len;
    let run = row_run(count, exec.threads());
    let parts = Parts::chunks(rows, run * len);
    let tail = count / run * run;
    exec.run(&|| {
        while let Some((i, rows)) = parts.take() {
            for (k, row) in rows.chunks_exact_mut(len).enumerate() {
                f(i * run + k, row);
            }
        }
    });
    // The rows after the last whole run.
    for (k, row) in rows[tail * len..].chunks_exact_mut(len).enumerate() {
        f(tail + k, row);
    }
}

/// `Σ v²` in f64, threads summing fixed spans, the spans added in order: the clipping norm's
/// square, the same whatever the thread count.
pub(super) fn squares(exec: Exec<'_>, values: &[f32]) -> f64 {
    let spans = spans(values.len());
    let mut sums = [0.0f64; SPANS];
    let slots = Parts::chunks(&mut sums[..], 1);
    exec.run(&|| {
        while let Some((i, slot)) = slots.take() {
            slot[0] = values[spans[i].clone()].iter().map(|&v| v as f64 * v as f64).sum();
        }
    });
    sums.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use drivesim_kernels::{dense_weight_grad, Isa};

    /// Blocks of items summed apart come to the whole batch's gradient (to rounding), and
    /// their bits do not change with the threads (here: none).
    #[test]
    fn blocked_weight_gradient_is_the_whole_batchs() {
        let (rows, cols, items) = (40, 24, 1100);
        assert_eq!(grad_blocks(rows, items), 4);
        let value = |i: usize| ((i * 7919 % 1000) as f32 / 500.0) - 1.0;
        let dy: Vec<f32> = (0..items * rows).map(value).collect();
        let x: Vec<f32> = (0..items * cols).map(|i| value(i + 3)).collect();
        let len = Matrix::packed_len(rows, cols);
        let mut whole = vec![0.0; len];
        dense_weight_grad(Isa::best(), &dy, &x, rows, cols, &mut whole);
        let mut partials = vec![f32::NAN; partials_len(rows, cols, items)];
        let mut blocked = vec![f32::NAN; len];
        let exec = Exec {
            isa: Isa::best(),
            pool: None,
        };
        weight_grad(exec, (&dy, &x), rows, cols, &mut partials, &mut blocked);
        let scale = whole.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for (b, w) in blocked.iter().zip(&whole) {
            assert!((b - w).abs() <= 1e-5 * scale, "blocked {b}, whole {w}");
        }
        assert!(blocked != whole, "the blocks' sums differ in their last bits somewhere");
    }
}
