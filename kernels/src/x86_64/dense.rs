//! Dense (matrix times batch of vectors) kernels for AVX2 and AVX-512.
//!
//! One generic body ([`dense_body`]) is instantiated per vector width (`__m256`, `__m512`)
//! through the activations' [`Simd`] trait and its small extension [`Widen`]; only the
//! `#[target_feature]` entry points differ. The Tanh/ReLU epilogue is [`act::apply`].
//!
//! The weights are in the panels of [`Matrix`]: one column of a panel is the weight of that
//! column for [`OC_ALIGN`] consecutive rows, one vector (AVX-512) or two (AVX2). So outputs go
//! across the vector lanes: a register tile of `NI` items by `NV` vectors of rows loads `NV`
//! weight vectors per column, broadcasts each item's input value, and multiplies every pair,
//! `NI * NV` multiply-adds for `NV + NI` loads, with no sums across lanes.
//! - A single input uses `NI = 1` and eight vectors, their panels a part of the matrix apart:
//!   the weights stream once, as four or eight long runs, with a software prefetch (single-core
//!   DRAM streaming is latency-bound without it).
//! - A batch is split into balanced blocks of up to `NI` items (8 x 3 vectors for AVX-512,
//!   4 x 2 for AVX2). Long rows are cut into chunks of at most [`CHUNK`] columns, so that a
//!   tile's weights stay in L2 while every block of items reuses them; later chunks add to
//!   what earlier ones stored.

use super::act::{self, Simd};
use super::conv::{load_n, store_n};
use crate::{f16, Activation, IsaLevel, Matrix, MatrixData, OC_ALIGN};
use core::arch::x86_64::*;

/// `y[n * ldy + r] = act(W[r] . x[n] + bias[r])` for every row of `w` (see
/// [`crate::dense_rows`]).
///
/// # Safety
/// `y` must be valid for those writes; `level` must come from an `Isa`.
pub(crate) unsafe fn dense(
    level: IsaLevel,
    w: Matrix<'_>,
    bias: &[f32],
    act: Activation,
    x: &[f32],
    y: *mut f32,
    ldy: usize,
) {
    let args = Args {
        cols: w.cols,
        bias,
        act,
        x,
        y,
        ldy,
    };
    // SAFETY: an `IsaLevel` other than `Scalar` reaches here only from an `Isa`, which proves
    // that the CPU has the features each entry point enables; the caller vouches for `y`.
    match (level, w.data) {
        (IsaLevel::Avx512, MatrixData::F32(d)) => dense_avx512(d, args),
        (IsaLevel::Avx512, MatrixData::F16(d)) => dense_avx512(d, args),
        (IsaLevel::Avx2, MatrixData::F32(d)) => dense_avx2(d, args),
        (IsaLevel::Avx2, MatrixData::F16(d)) => dense_avx2(d, args),
        (IsaLevel::Scalar, _) => crate::scalar::dense_rows(w, bias, act, x, y, ldy),
    }
}

/// The arguments of one call besides the weights: output item `n` starts at `y + n * ldy`.
struct Args<'a> {
    cols: usize,
    bias: &'a [f32],
    act: Activation,
    x: &'a [f32],
    y: *mut f32,
    ldy: usize,
}

#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn dense_avx2<T: Weight>(w: &[T], args: Args<'_>) {
    // A batch tile in 14 of 16 registers: 4 x 2 accumulators, 2 weight vectors and the 4
    // broadcasts, which the compiler loads all at once (with more items, an accumulator spills
    // to the stack and the loop waits on it).
    dense_body::<__m256, T, 4, 2>(w, args)
}

#[target_feature(enable = "avx512f,avx2,fma,f16c")]
unsafe fn dense_avx512<T: Weight>(w: &[T], args: Args<'_>) {
    // 8 x 3 accumulators and 3 weight vectors; the broadcasts fold into the multiply-adds'
    // memory operands. On a Xeon this measured level with or ahead of 8 x 2 and 12 x 2.
    dense_body::<__m512, T, 8, 3>(w, args)
}

/// Vectors of rows in the single-input tile.
const SINGLE_NV: usize = 8;
/// Most columns per pass over a tile's weights (see the module comment): 64 KiB of f32 weights
/// per panel.
const CHUNK: usize = 1024;
/// Bytes ahead of the current weights to prefetch, in each panel.
const PREFETCH: usize = 1024;

/// What the dense kernel needs on top of [`Simd`]: loading halves widened.
/// Methods are `inline(always)`, to compile inside the caller's `#[target_feature]` function.
trait Widen: Simd {
    /// Loads `LANES` halves and widens them.
    unsafe fn load_f16(p: *const f16) -> Self;
}

impl Widen for __m256 {
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m256 {
        _mm256_cvtph_ps(_mm_loadu_si128(p.cast()))
    }
}

impl Widen for __m512 {
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m512 {
        _mm512_cvtph_ps(_mm256_loadu_si256(p.cast()))
    }
}

/// A stored weight type: loads `LANES` of them as f32 lanes.
trait Weight: Copy {
    unsafe fn load<S: Widen>(p: *const Self) -> S;
}

impl Weight for f32 {
    #[inline(always)]
    unsafe fn load<S: Widen>(p: *const f32) -> S {
        S::load(p)
    }
}

impl Weight for f16 {
    #[inline(always)]
    unsafe fn load<S: Widen>(p: *const f16) -> S {
        S::load_f16(p)
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
/// the tile's columns, then stored: plus the bias for the first chunk of columns, else added
/// to what earlier chunks stored. Rows past the last are computed (the panel's zero padding)
/// but not stored.
#[inline(always)]
unsafe fn tile<S: Widen, T: Weight, const NI: usize, const NV: usize>(w: &[T], args: &Args<'_>, tile: Tile) {
    let Args {
        cols, bias, x, y, ldy, ..
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
            _mm_prefetch::<_MM_HINT_T0>(at(v).cast::<i8>().wrapping_add(PREFETCH));
        }
        let wv: [S; NV] = core::array::from_fn(|v| T::load::<S>(at(v)));
        for (acc, input) in acc.iter_mut().zip(&inputs) {
            let xb = S::splat(*input.add(k));
            for (a, &wv) in acc.iter_mut().zip(&wv) {
                *a = wv.mul_add(xb, *a);
            }
        }
    }
    let rows = bias.len();
    for (i, acc) in acc.iter().enumerate() {
        let out = y.add((tile.item + i) * ldy);
        for (v, &sum) in acc.iter().enumerate() {
            let row = tile.row_of::<S>(v);
            if row >= rows {
                break;
            }
            let n = S::LANES.min(rows - row);
            let (dst, b) = (out.add(row), bias.as_ptr().add(row));
            let earlier = if tile.col == 0 { b } else { dst };
            store_n(load_n::<S>(earlier, n).add(sum), dst, n);
        }
    }
}

/// See [`crate::dense`].
#[inline(always)]
unsafe fn dense_body<S: Widen, T: Weight, const NI: usize, const NV: usize>(w: &[T], args: Args<'_>) {
    let (cols, rows) = (args.cols, args.bias.len());
    debug_assert!(OC_ALIGN.is_multiple_of(S::LANES) && (NV * S::LANES).is_multiple_of(OC_ALIGN));
    let padded = rows.next_multiple_of(OC_ALIGN);
    let items = args.x.len() / cols;
    let mut first_row = 0;
    if items == 1 {
        // Each tile's panels a part of the matrix apart, so that the weights stream from memory
        // as several long runs.
        let groups = SINGLE_NV * S::LANES / OC_ALIGN;
        let spread = padded / OC_ALIGN / groups;
        for panel in 0..spread {
            let at = Tile {
                row: panel * OC_ALIGN,
                stride: spread,
                item: 0,
                col: 0,
                len: cols,
            };
            tile::<S, T, 1, SINGLE_NV>(w, &args, at);
        }
        first_row = spread * groups * OC_ALIGN;
    }
    // The rows left (all of them for a batch) in chunks of at most CHUNK columns: in each chunk,
    // every tile of NV vectors of rows (then of one vector) meets every block of items while its
    // weights are in cache.
    let chunks = cols.div_ceil(CHUNK);
    for chunk in 0..chunks {
        let col = chunk * cols / chunks;
        let len = (chunk + 1) * cols / chunks - col;
        let mut row = first_row;
        while row + NV * S::LANES <= padded {
            item_blocks::<S, T, NI, NV>(w, &args, items, (row, col, len));
            row += NV * S::LANES;
        }
        while row < rows {
            item_blocks::<S, T, NI, 1>(w, &args, items, (row, col, len));
            row += S::LANES;
        }
    }
    for n in 0..items {
        act::apply_slice::<S>(
            args.act,
            core::slice::from_raw_parts_mut(args.y.add(n * args.ldy), rows),
        );
    }
}

/// One tile of rows (from `row`, `NV` vectors) over columns `col .. col + len` for every item,
/// in balanced blocks of at most `NI <= 8` items. Const generics need one arm per block size
/// (the guards keep the arms above `NI` from being compiled).
#[inline(always)]
unsafe fn item_blocks<S: Widen, T: Weight, const NI: usize, const NV: usize>(
    w: &[T],
    args: &Args<'_>,
    items: usize,
    (row, col, len): (usize, usize, usize),
) {
    let blocks = items.div_ceil(NI);
    for block in 0..blocks {
        let item = block * items / blocks;
        let at = Tile {
            row,
            stride: 1,
            item,
            col,
            len,
        };
        match (block + 1) * items / blocks - item {
            1 => tile::<S, T, 1, NV>(w, args, at),
            2 if NI >= 2 => tile::<S, T, 2, NV>(w, args, at),
            3 if NI >= 3 => tile::<S, T, 3, NV>(w, args, at),
            4 if NI >= 4 => tile::<S, T, 4, NV>(w, args, at),
            5 if NI >= 5 => tile::<S, T, 5, NV>(w, args, at),
            6 if NI >= 6 => tile::<S, T, 6, NV>(w, args, at),
            7 if NI >= 7 => tile::<S, T, 7, NV>(w, args, at),
            8 if NI >= 8 => tile::<S, T, 8, NV>(w, args, at),
            _ => unreachable!("item blocks hold at most NI items"),
        }
    }
}
