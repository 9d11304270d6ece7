//! The gradients of a dense layer: its weights', `G = dYᵀ X` summed over a batch of `K` items,
//! written straight into the packed layout of [`Matrix`] so that an optimiser updates packed
//! weights in place; and its input's, `dX = dY W`, read from the forward pass's packing (see
//! [`data_grad`]).
//!
//! The same register tile as the forward kernel ([`super::dense`]) with the roles swapped:
//! a column of a panel is `NV` vectors of consecutive rows, so the vectors are loaded from an
//! item's output gradient `dy[k]` (rows are contiguous there), and each of `NC` columns
//! broadcasts the item's input `x[k][c]`: `NC * NV` multiply-adds for `NC + NV` loads per item.
//! - The items are summed in chunks of at most [`ITEMS`], the later ones added to what the
//!   earlier ones stored. The chunks depend on `K` alone, so every gradient is summed in the
//!   same order however threads split the rows (bit-identical results across thread counts).
//! - A chunk's output gradients for one tile of rows (`ITEMS x NV` vectors) are copied to a
//!   contiguous block on the stack first, then stay in L1 while every block of columns passes
//!   over them. In place, `dy[k]` rows a power of two apart (256 or 512 floats) would fall
//!   into a few of L1's sets and evict each other: the copy ran the default transition's
//!   gradients 1.3x faster.
//! - For the same reason the chunk's inputs are copied too, a panel of at most [`PANEL_COLS`]
//!   columns at a time (48 KiB, in L2 while every tile of rows passes over it), before the
//!   tiles of rows: the comma transition's `[W | V | U]` gradient on AVX2 (Zen 3) went from
//!   54.0 to 48.5 ms over 3,584 items, 70 % to 78 % of the FMA peak (`dense_speed`, the best of
//!   five interleaved runs). Each gradient's sum keeps its order.

use super::vector::{load_n, Simd};
use super::{balanced_blocks, row_tiles, Block, RowTile};
use crate::{Matrix, OC_ALIGN};
use core::mem::MaybeUninit;
use core::ops::Range;

/// Most items per pass over a tile (see the module comment): 128 items of three AVX-512 row
/// vectors are 24 KiB, within L1.
const ITEMS: usize = 128;

/// The arguments of one call: `dy` is `K x rows`, item-major (the inputs `x` go through
/// [`Panel`]s); `grad` the packed `rows x cols` gradient.
struct Args<'a> {
    dy: &'a [f32],
    rows: usize,
    cols: usize,
    grad: *mut f32,
}

/// `grad = dyᵀ x` (or `grad += dyᵀ x` if `accumulate`) for the rows `rows` (see [`crate::dense_weight_grad_rows`]), with tiles of
/// `NC` columns by `NV` vectors of rows.
///
/// # Safety
/// As for [`crate::scalar::dense_weight_grad_rows`]; the CPU must have `S`'s features.
#[inline(always)]
pub(super) unsafe fn weight_grad<S: Simd, const NC: usize, const NV: usize>(
    dy: &[f32],
    x: &[f32],
    cols: usize,
    grad: *mut f32,
    rows: Range<usize>,
    total_rows: usize,
    accumulate: bool,
) {
    unsafe {
        let args = Args {
            dy,
            rows: total_rows,
            cols,
            grad,
        };
        let items = dy.len() / total_rows;
        // Whole panels: the padding rows of the last one are written too (as zeros).
        let end = rows.end.next_multiple_of(OC_ALIGN);
        let chunks = items.div_ceil(ITEMS).max(1);
        let panels = cols.div_ceil(PANEL_COLS);
        let mut packed = [0.0f32; ITEMS * PANEL_COLS];
        for chunk in 0..chunks {
            let ks = chunk * items / chunks..(chunk + 1) * items / chunks;
            for panel in 0..panels {
                // The chunk's inputs for a panel of columns, copied together: in place, rows a
                // power of two apart (or close to one) fall into a few of L1's sets.
                let columns = panel * cols / panels..(panel + 1) * cols / panels;
                let width = columns.len();
                for (n, k) in ks.clone().enumerate() {
                    // The rows a few items ahead, one cache line at a time: rows `cols` floats
                    // apart, read once each (from L3 or memory), would otherwise wait in turn.
                    let ahead = x.as_ptr().wrapping_add((k + PREFETCH_ITEMS) * cols + columns.start);
                    for line in (0..width).step_by(LINE_FLOATS) {
                        S::prefetch(ahead.wrapping_add(line).cast());
                    }
                    packed[n * width..][..width].copy_from_slice(&x[k * cols + columns.start..][..width]);
                }
                let tiles = RowsForColumns::<NC> {
                    args: &args,
                    ks: ks.clone(),
                    panel: Panel {
                        x: &packed[..ks.len() * width],
                        columns,
                    },
                    first: chunk == 0 && !accumulate,
                };
                row_tiles::<S, NV>(rows.start, (end - rows.start) / S::LANES, S::LANES, &tiles);
            }
        }
    }
}

/// Most columns in a panel whose inputs are copied together (see [`weight_grad`]): 48 KiB for
/// [`ITEMS`] items, which stay in L2 while every tile of rows passes over them.
const PANEL_COLS: usize = 96;

/// Items ahead of the one copied into a [`Panel`] whose inputs are prefetched.
const PREFETCH_ITEMS: usize = 4;

/// Floats in a 64-byte cache line: the step between the prefetched addresses of a row.
const LINE_FLOATS: usize = 64 / core::mem::size_of::<f32>();

/// The inputs of a chunk's items for the `columns`, item after item.
#[derive(Clone)]
struct Panel<'a> {
    x: &'a [f32],
    columns: Range<usize>,
}

/// The tiles of rows over the items `ks`, each for every block of the panel's columns: stored
/// if `first`, else added to what earlier chunks of items stored.
struct RowsForColumns<'a, 'b, const NC: usize> {
    args: &'a Args<'b>,
    ks: Range<usize>,
    panel: Panel<'a>,
    first: bool,
}

/// Most vectors of rows in a tile (`NV`): the size of the copied block.
const MAX_NV: usize = 4;

impl<S: Simd, const NC: usize> RowTile<S> for RowsForColumns<'_, '_, NC> {
    #[inline(always)]
    unsafe fn run<const NV: usize>(&self, row: usize) {
        unsafe {
            debug_assert!(NV <= MAX_NV && self.ks.len() <= ITEMS);
            let Args { dy, rows, .. } = *self.args;
            // Rows past the last are read as zeros (their gradient is the panel's padding).
            let lanes: [usize; NV] = core::array::from_fn(|v| rows.saturating_sub(row + v * S::LANES));
            // Uninitialised: zeroing the whole block for every tile of every panel took more
            // stores than the copy itself (the weight gradients ran about 5 % slower).
            let mut block = [const { MaybeUninit::<S>::uninit() }; ITEMS * MAX_NV];
            for (n, k) in self.ks.clone().enumerate() {
                // Wrapping: the padding vectors' addresses may lie past `dy` (they load nothing).
                let d = dy.as_ptr().wrapping_add(k * rows + row);
                for (v, &lanes) in lanes.iter().enumerate() {
                    block[n * NV + v].write(load_n::<S>(d.wrapping_add(v * S::LANES), lanes));
                }
            }
            // The first `ks.len() * NV` vectors, every one written above.
            let copied = core::slice::from_raw_parts(block.as_ptr().cast::<S>(), self.ks.len() * NV);
            let tile = ColumnTile::<S, NV> {
                args: self.args,
                dy: copied,
                row,
                panel: self.panel.clone(),
                first: self.first,
            };
            balanced_blocks::<S, NC>(self.panel.columns.len(), &tile)
        }
    }
}

/// `NV` vectors of rows from `row`, over the items `ks` (their `dy`, `NV` vectors each, copied
/// to `dy`): stored if `first`, else added.
struct ColumnTile<'a, 'b, S, const NV: usize> {
    args: &'a Args<'b>,
    dy: &'a [S],
    row: usize,
    panel: Panel<'a>,
    first: bool,
}

impl<S: Simd, const NV: usize> Block<S> for ColumnTile<'_, '_, S, NV> {
    /// The tile's rows for the `N` columns from the panel's column `at`.
    #[inline(always)]
    unsafe fn run<const N: usize>(&self, at: usize) {
        unsafe {
            let Args { cols, grad, .. } = *self.args;
            let (width, col) = (self.panel.columns.len(), self.panel.columns.start + at);
            let mut acc = [[S::splat(0.0); NV]; N];
            for (n, dv) in self.dy.chunks_exact(NV).enumerate() {
                let xk = self.panel.x.as_ptr().add(n * width + at);
                for (i, acc) in acc.iter_mut().enumerate() {
                    let xb = S::splat(*xk.add(i));
                    for (a, &d) in acc.iter_mut().zip(dv) {
                        *a = d.mul_add(xb, *a);
                    }
                }
            }
            for (i, acc) in acc.iter().enumerate() {
                for (v, &sum) in acc.iter().enumerate() {
                    // `LANES` divides a panel, so a vector of rows stays inside one.
                    let p = grad.add(Matrix::packed_index(self.row + v * S::LANES, col + i, cols));
                    let sum = if self.first { sum } else { S::load(p).add(sum) };
                    sum.store(p);
                }
            }
        }
    }
}

/// Most vectors in one column of a panel ([`OC_ALIGN`] floats): four for NEON.
const PANEL_VECTORS: usize = 4;
/// Bytes ahead of the current columns of each panel to prefetch: four tiles of four columns.
const PREFETCH: usize = 1024;

/// `dx[n * cols + c] = Σ_r W[r][c] dy[n * rows + r]` for the columns `columns` of the packed
/// f32 `rows x cols` matrix `w`, every item `n`: the data gradient of a dense layer without a
/// transposed copy of its weights (a trainer would rewrite that copy after every update).
///
/// A column of a panel is one cache line of `W`'s rows, multiplied lane by lane with those
/// rows of each item's `dy`; a tile of `NC` columns by a block of `NI` items shares every load
/// of `W` and of `dy` between them. The products are summed per lane over the panels, then
/// across the lanes, so every output is summed in the same order whatever the batch or the
/// columns asked for. With fewer rows than a vector has lanes, most lanes would be padding:
/// then the scalar reference sums them.
///
/// # Safety
/// As for [`crate::scalar::dense_data_grad_cols`]; the CPU must have `S`'s features.
#[inline(always)]
pub(super) unsafe fn data_grad<S: Simd, const NC: usize, const NI: usize>(
    w: &[f32],
    rows: usize,
    cols: usize,
    dy: &[f32],
    dx: *mut f32,
    columns: Range<usize>,
) {
    unsafe {
        if rows < S::LANES {
            return crate::scalar::dense_data_grad_cols(w, rows, cols, dy, dx, columns);
        }
        let items = dy.len() / rows;
        // Whole tiles, then single columns and single items: register tiles of fixed size.
        let whole = (columns.len() / NC) * NC;
        let (blocks, rest) = (items / NI, items % NI);
        let args = (w, rows, cols, dy, dx);
        for col in (columns.start..columns.start + whole).step_by(NC) {
            for block in 0..blocks {
                data_grad_tile::<S, NC, NI>(args, col, block * NI);
            }
            for item in items - rest..items {
                data_grad_tile::<S, NC, 1>(args, col, item);
            }
        }
        for col in columns.start + whole..columns.end {
            for block in 0..blocks {
                data_grad_tile::<S, 1, NI>(args, col, block * NI);
            }
            for item in items - rest..items {
                data_grad_tile::<S, 1, 1>(args, col, item);
            }
        }
    }
}

/// Columns `col..col + NC` of [`data_grad`] for the items `item..item + NI`.
#[inline(always)]
unsafe fn data_grad_tile<S: Simd, const NC: usize, const NI: usize>(
    (w, rows, cols, dy, dx): (&[f32], usize, usize, &[f32], *mut f32),
    col: usize,
    item: usize,
) {
    unsafe {
        let vectors = OC_ALIGN / S::LANES;
        debug_assert!(vectors <= PANEL_VECTORS);
        let mut acc = [[[S::splat(0.0); PANEL_VECTORS]; NC]; NI];
        for panel in 0..rows.div_ceil(OC_ALIGN) {
            let first = panel * OC_ALIGN;
            let line = w.as_ptr().add(Matrix::packed_index(first, col, cols));
            // Each panel is a stream of its own, too many for the hardware prefetchers to
            // follow from DRAM: ask for the lines a few tiles ahead.
            for j in 0..NC {
                S::prefetch(line.add(j * OC_ALIGN).cast::<u8>().wrapping_add(PREFETCH));
            }
            for v in 0..vectors {
                let wv: [S; NC] = core::array::from_fn(|j| S::load(line.add(j * OC_ALIGN + v * S::LANES)));
                // Rows past the last: the weights' padding lanes, zero; read none of dy's
                // (wrapping: their addresses may lie past `dy`, and load nothing).
                let lanes = rows.saturating_sub(first + v * S::LANES);
                for (i, acc) in acc.iter_mut().enumerate() {
                    let at = dy.as_ptr().wrapping_add((item + i) * rows + first + v * S::LANES);
                    let d = load_n::<S>(at, lanes);
                    for (a, &w) in acc.iter_mut().zip(&wv) {
                        a[v] = w.mul_add(d, a[v]);
                    }
                }
            }
        }
        for (i, acc) in acc.iter().enumerate() {
            for (j, a) in acc.iter().enumerate() {
                let sum = a[1..vectors].iter().fold(a[0], |s, &x| s.add(x));
                *dx.add((item + i) * cols + col + j) = sum.reduce_add();
            }
        }
    }
}
