//! Dense (matrix times batch of vectors) kernels.
//!
//! One generic body ([`body`]) is instantiated per instruction set through the activations'
//! [`Simd`] trait and its small extension [`Widen`]; the architecture module holds the
//! `#[target_feature]` entry points and picks each one's tile. The Tanh/ReLU epilogue is
//! [`act::apply`].
//!
//! The weights are in the panels of [`Matrix`]: one column of a panel is the weight of that
//! column for [`OC_ALIGN`] consecutive rows, one vector (AVX-512), two (AVX2) or four (NEON).
//! So outputs go
//! across the vector lanes: a register tile of `NI` items by `NV` vectors of rows loads `NV`
//! weight vectors per column, broadcasts each item's input value, and multiplies every pair,
//! `NI * NV` multiply-adds for `NV + NI` loads, with no sums across lanes.
//! - Long rows are cut into chunks of at most [`CHUNK`] columns; later chunks add to what
//!   earlier ones stored. The chunks depend on the column count alone, so every output is
//!   summed in the same order whatever the batch or the rows asked for (bit-identical results
//!   across thread counts and batches).
//! - A single input uses `NI = 1` and eight vectors, their panels a part of the matrix apart:
//!   the weights stream as two to eight long runs (one per panel of the tile), with a
//!   software prefetch (single-core DRAM streaming is latency-bound without it).
//! - A batch is split into balanced blocks of up to `NI` items (8 x 3 vectors for AVX-512,
//!   6 x 2 for AVX2, 4 x 4 for NEON), so that a chunk of a tile's weights stays in L2 while
//!   every block of items reuses it. AVX2's 16 registers hold 12 sums, two weight vectors and
//!   a broadcast: 12 independent FMAs cover the two FMA ports' 4 cycles of latency with room
//!   to spare (4 x 2, eight, just covers it: 92-93% of the peak against 94-95% at batch 16 to
//!   256 on Zen 3, the best of four runs of `dense_speed`).

use super::act;
use super::vector::{load_n, store_n, Simd, Widen};
use super::{balanced_blocks, row_tiles, Block, RowTile};
use crate::{f16, Activation, Matrix, MatrixData, OC_ALIGN};

/// `y[n * ldy + r] = act(W[r] . x[n] + bias[r])` for every row of `w` (see
/// [`crate::dense_rows`]), with a batch tile of `NI` items by `NV` vectors.
///
/// # Safety
/// As for [`crate::scalar::dense_rows`]; the CPU must have `S`'s features.
#[inline(always)]
pub(super) unsafe fn dense<S: Widen, const NI: usize, const NV: usize>(
    w: Matrix<'_>,
    bias: Option<&[f32]>,
    act: Activation,
    x: &[f32],
    y: *mut f32,
    ldy: usize,
) {
    unsafe {
        // Balanced groups of items whose inputs stay in L2 while every tile of rows passes over
        // them: the weights then stream from memory once per group.
        let items = x.len() / w.cols;
        let groups = (items * w.cols).div_ceil(GROUP_FLOATS.max(NI * w.cols));
        for group in 0..groups {
            let (first, end) = (group * items / groups, (group + 1) * items / groups);
            let args = Args {
                rows: w.rows,
                cols: w.cols,
                bias,
                act,
                x: &x[first * w.cols..end * w.cols],
                y: y.add(first * ldy),
                ldy,
            };
            match w.data {
                MatrixData::F32(d) => body::<S, f32, NI, NV>(d, args),
                MatrixData::F16(d) => body::<S, f16, NI, NV>(d, args),
            }
        }
    }
}

/// Most input floats per group of items (see [`dense`]): 256 KiB, half an L2 of 512 KiB (Zen 3;
/// 1 to 2 MiB on Zen 4 and recent Xeons), the rest for the tile's weights and the outputs.
/// Each item gets the same bits whatever its group (as whatever its batch).
const GROUP_FLOATS: usize = 64 * 1024;

/// The arguments of one call besides the weights: output item `n` starts at `y + n * ldy`;
/// the sums start from the bias, or from what `y` holds where there is none.
pub(super) struct Args<'a> {
    rows: usize,
    cols: usize,
    bias: Option<&'a [f32]>,
    act: Activation,
    x: &'a [f32],
    y: *mut f32,
    ldy: usize,
}

/// Vectors of rows in the single-input tile.
const SINGLE_NV: usize = 8;
/// Most columns per pass over a tile's weights (see the module comment): 80 KiB of f32 weights
/// per panel, so that the comma transition's 1026 columns (`[W | V | U]`) take one pass.
const CHUNK: usize = 1280;
/// Bytes ahead of the current weights to prefetch, in each panel.
const PREFETCH: usize = 1024;

/// A stored weight type: loads `LANES` of them as f32 lanes.
pub(super) trait Weight: Copy {
    unsafe fn load<S: Widen>(p: *const Self) -> S;
}

impl Weight for f32 {
    #[inline(always)]
    unsafe fn load<S: Widen>(p: *const f32) -> S {
        unsafe { S::load(p) }
    }
}

impl Weight for f16 {
    #[inline(always)]
    unsafe fn load<S: Widen>(p: *const f16) -> S {
        unsafe { S::load_f16(p) }
    }
}

/// One register tile's place in the call: its rows, items and columns.
struct Tile {
    /// First row: a multiple of [`OC_ALIGN`] or, in a tile of single vectors, of the lanes.
    row: usize,
    /// Panels from one of the tile's panels to the next: 1, or more to spread a single input's
    /// tile over distant parts of the matrix.
    stride: usize,
    /// First item.
    item: usize,
    /// Columns `col .. col + len`.
    col: usize,
    len: usize,
}

impl Tile {
    /// The first row of the tile's vector `v`.
    fn row_of<S: Simd>(&self, v: usize) -> usize {
        let (panel, lane) = (v * S::LANES / OC_ALIGN, v * S::LANES % OC_ALIGN);
        self.row + panel * self.stride * OC_ALIGN + lane
    }
}

/// The sums of the tile's rows (`NV` vectors of them) times items `tile.item ..` (`NI`) over
/// the tile's columns, then stored: plus the bias for the first chunk of columns, else (and
/// without a bias) added to what is stored. Rows past the last are computed (the panel's zero padding)
/// but not stored.
#[inline(always)]
unsafe fn tile<S: Widen, T: Weight, const NI: usize, const NV: usize>(w: &[T], args: &Args<'_>, tile: Tile) {
    unsafe {
        let Args {
            rows,
            cols,
            bias,
            x,
            y,
            ldy,
            ..
        } = *args;
        // Vector `v` of the tile at column 0: its panel, and its lanes within the panel.
        let starts: [*const T; NV] =
            core::array::from_fn(|v| w.as_ptr().add(Matrix::packed_index(tile.row_of::<S>(v), 0, cols)));
        let inputs: [*const f32; NI] = core::array::from_fn(|i| x.as_ptr().add((tile.item + i) * cols));
        let mut acc = [[S::splat(0.0); NV]; NI];
        for k in tile.col..tile.col + tile.len {
            let at = |v: usize| starts[v].add(k * OC_ALIGN);
            // A column of a panel is 64 bytes of f32 (one cache line) or 32 of f16: one prefetch
            // per panel and column.
            for v in (0..NV).step_by(OC_ALIGN / S::LANES) {
                S::prefetch(at(v).cast::<u8>().wrapping_add(PREFETCH));
            }
            let wv: [S; NV] = core::array::from_fn(|v| T::load::<S>(at(v)));
            for (acc, input) in acc.iter_mut().zip(&inputs) {
                let xb = S::splat(*input.add(k));
                for (a, &wv) in acc.iter_mut().zip(&wv) {
                    *a = wv.mul_add(xb, *a);
                }
            }
        }
        for (i, acc) in acc.iter().enumerate() {
            let out = y.add((tile.item + i) * ldy);
            for (v, &sum) in acc.iter().enumerate() {
                let row = tile.row_of::<S>(v);
                if row >= rows {
                    break;
                }
                let n = S::LANES.min(rows - row);
                let dst = out.add(row);
                let earlier = match bias {
                    Some(b) if tile.col == 0 => b.as_ptr().add(row),
                    _ => dst,
                };
                store_n(load_n::<S>(earlier, n).add(sum), dst, n);
            }
        }
    }
}

/// See [`crate::dense`].
#[inline(always)]
pub(super) unsafe fn body<S: Widen, T: Weight, const NI: usize, const NV: usize>(w: &[T], args: Args<'_>) {
    unsafe {
        let (cols, rows) = (args.cols, args.rows);
        debug_assert!(OC_ALIGN.is_multiple_of(S::LANES) && (NV * S::LANES).is_multiple_of(OC_ALIGN));
        let padded = rows.next_multiple_of(OC_ALIGN);
        let items = args.x.len() / cols;
        // Every row sums its columns in the same chunks, in the same order, whatever the batch or
        // the range of rows asked for: results are bit-identical however threads split the work.
        let chunks = cols.div_ceil(CHUNK);
        for chunk in 0..chunks {
            let col = chunk * cols / chunks;
            let len = (chunk + 1) * cols / chunks - col;
            let mut row = 0;
            if items == 1 {
                // Each tile's panels a part of the matrix apart, so that the weights stream from
                // memory as several long runs.
                let groups = SINGLE_NV * S::LANES / OC_ALIGN;
                let spread = padded / OC_ALIGN / groups;
                for panel in 0..spread {
                    let at = Tile {
                        row: panel * OC_ALIGN,
                        stride: spread,
                        item: 0,
                        col,
                        len,
                    };
                    tile::<S, T, 1, SINGLE_NV>(w, &args, at);
                }
                row = spread * groups * OC_ALIGN;
            }
            // The rows left (all of them for a batch): every tile of up to NV vectors of rows
            // meets every block of items while its weights are in cache.
            let vectors = rows.saturating_sub(row).div_ceil(S::LANES);
            let tiles = RowsForItems::<T, NI> {
                w,
                args: &args,
                items,
                col,
                len,
            };
            row_tiles::<S, NV>(row, vectors, S::LANES, &tiles);
        }
        for n in 0..items {
            act::apply_slice::<S>(
                args.act,
                core::slice::from_raw_parts_mut(args.y.add(n * args.ldy), rows),
            );
        }
    }
}

/// The tiles of rows of one chunk of columns, each over every item (see [`item_blocks`]).
struct RowsForItems<'a, 'b, T, const NI: usize> {
    w: &'a [T],
    args: &'a Args<'b>,
    items: usize,
    col: usize,
    len: usize,
}

impl<S: Widen, T: Weight, const NI: usize> RowTile<S> for RowsForItems<'_, '_, T, NI> {
    #[inline(always)]
    unsafe fn run<const NV: usize>(&self, row: usize) {
        unsafe { item_blocks::<S, T, NI, NV>(self.w, self.args, self.items, (row, self.col, self.len)) }
    }
}

/// One tile of rows (from `row`, `NV` vectors) over columns `col .. col + len` for every item,
/// in balanced blocks of at most `NI <= 8` items.
#[inline(always)]
unsafe fn item_blocks<S: Widen, T: Weight, const NI: usize, const NV: usize>(
    w: &[T],
    args: &Args<'_>,
    items: usize,
    (row, col, len): (usize, usize, usize),
) {
    struct Items<'a, 'b, T, const NV: usize> {
        w: &'a [T],
        args: &'a Args<'b>,
        row: usize,
        col: usize,
        len: usize,
    }
    impl<S: Widen, T: Weight, const NV: usize> Block<S> for Items<'_, '_, T, NV> {
        #[inline(always)]
        unsafe fn run<const N: usize>(&self, item: usize) {
            let at = Tile {
                row: self.row,
                stride: 1,
                item,
                col: self.col,
                len: self.len,
            };
            unsafe { tile::<S, T, N, NV>(self.w, self.args, at) }
        }
    }
    unsafe { balanced_blocks::<S, NI>(items, &Items::<T, NV> { w, args, row, col, len }) }
}
