//! Dense (matrix times batch of vectors) kernels for AVX2 and AVX-512.
//!
//! One generic body ([`dense_body`]) is instantiated per vector width (`__m256`, `__m512`)
//! through the activations' [`Simd`] trait and its small extension [`Dot`]; only the
//! `#[target_feature]` entry points differ. The Tanh/ReLU epilogue is [`act::apply`].
//!
//! Layout of the work: `y[n][r] = act(W[r] . x[n] + b[r])`. A batch is taken `RT` rows by `BT`
//! inputs at a time (a register tile of `RT x BT` vector accumulators, each a partial dot
//! product summed horizontally at the end: 3 x 4 for AVX2, 4 x 4 for AVX-512), so each weight
//! vector loaded feeds `BT` multiply-adds and each input vector `RT`. A single input streams
//! every weight once, 4 rows at a time with two accumulators per row and a software prefetch
//! (single-core DRAM streaming is latency-bound without it); the 4 rows are a quarter of the
//! matrix apart, so even short rows form 4 long sequential streams.
//! With several tiles of the batch, the columns are cut into panels so that the 4 rows of a
//! panel stay in L1 while every batch tile reads them: the weights still come from memory once.
//! Columns that do not fill a vector are read with masked loads (inputs) or through a
//! zero-padded copy on the stack (weights, which may be f16).

use super::act::{self, Simd};
use crate::{f16, Activation, IsaLevel, Matrix, MatrixData};
use core::arch::x86_64::*;

pub(crate) fn dense(level: IsaLevel, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    let args = Args {
        rows: w.rows,
        cols: w.cols,
        bias,
        act,
        x,
        y,
    };
    // SAFETY: an `IsaLevel` other than `Scalar` reaches here only from an `Isa`, which proves
    // that the CPU has the features each entry point enables; `crate::dense` checked the lengths.
    unsafe {
        match (level, w.data) {
            (IsaLevel::Avx512, MatrixData::F32(d)) => dense_avx512(d, args),
            (IsaLevel::Avx512, MatrixData::F16(d)) => dense_avx512(d, args),
            (IsaLevel::Avx2, MatrixData::F32(d)) => dense_avx2(d, args),
            (IsaLevel::Avx2, MatrixData::F16(d)) => dense_avx2(d, args),
            (IsaLevel::Scalar, _) => crate::scalar::dense(w, args.bias, args.act, args.x, args.y),
        }
    }
}

/// The arguments of one call besides the weights.
struct Args<'a> {
    rows: usize,
    cols: usize,
    bias: &'a [f32],
    act: Activation,
    x: &'a [f32],
    y: &'a mut [f32],
}

#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn dense_avx2<T: Weight>(w: &[T], args: Args<'_>) {
    // 16 registers: 3 x 4 accumulators, 3 weight vectors, 1 input vector.
    dense_body::<__m256, T, 3, 4>(w, args)
}

#[target_feature(enable = "avx512f,avx2,fma,f16c")]
unsafe fn dense_avx512<T: Weight>(w: &[T], args: Args<'_>) {
    // 32 registers: 4 x 4 accumulators, 4 weight vectors, 1 input vector.
    dense_body::<__m512, T, 4, 4>(w, args)
}

/// Rows of the register tile for a single input.
const ROWS: usize = 4;
/// Columns per panel when the batch takes several tiles: 4 rows of f32 fill 16 KiB of L1.
const PANEL: usize = 1024;
/// Bytes ahead of the current weights to prefetch.
const PREFETCH: usize = 1024;
/// Widest vector, in lanes (for the stack buffers of partial vectors).
const MAX_LANES: usize = 16;

/// What the dense kernel needs on top of [`Simd`]: widening halves and a horizontal sum.
/// Methods are `inline(always)`, to compile inside the caller's `#[target_feature]` function.
trait Dot: Simd {
    /// Loads `LANES` halves and widens them.
    unsafe fn load_f16(p: *const f16) -> Self;
    /// Sum of the lanes.
    unsafe fn sum(self) -> f32;
}

impl Dot for __m256 {
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m256 {
        _mm256_cvtph_ps(_mm_loadu_si128(p.cast()))
    }
    #[inline(always)]
    unsafe fn sum(self) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(self), _mm256_extractf128_ps::<1>(self));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        _mm_cvtss_f32(_mm_add_ss(s, _mm_movehdup_ps(s)))
    }
}

impl Dot for __m512 {
    #[inline(always)]
    unsafe fn load_f16(p: *const f16) -> __m512 {
        _mm512_cvtph_ps(_mm256_loadu_si256(p.cast()))
    }
    #[inline(always)]
    unsafe fn sum(self) -> f32 {
        _mm512_reduce_add_ps(self)
    }
}

/// A stored weight type: loads `LANES` of them as f32 lanes.
trait Weight: Copy + Default {
    unsafe fn load<S: Dot>(p: *const Self) -> S;
}

impl Weight for f32 {
    #[inline(always)]
    unsafe fn load<S: Dot>(p: *const f32) -> S {
        S::load(p)
    }
}

impl Weight for f16 {
    #[inline(always)]
    unsafe fn load<S: Dot>(p: *const f16) -> S {
        S::load_f16(p)
    }
}

/// Loads the `n < LANES` values at `p`, the other lanes zero.
#[inline(always)]
unsafe fn load_partial<S: Dot, T: Weight>(p: *const T, n: usize) -> S {
    let mut buf = [T::default(); MAX_LANES];
    core::ptr::copy_nonoverlapping(p, buf.as_mut_ptr(), n);
    T::load::<S>(buf.as_ptr())
}

/// One vector of columns: `wl(r)` loads the weights of row `r`, `xl(b)` the input of item `b`,
/// and their products go to accumulator `u`.
#[inline(always)]
unsafe fn step<S: Dot, const R: usize, const B: usize, const U: usize>(
    acc: &mut [[[S; U]; B]; R],
    u: usize,
    wl: impl Fn(usize) -> S,
    xl: impl Fn(usize) -> S,
) {
    let mut wv = [S::splat(0.0); R];
    for (r, v) in wv.iter_mut().enumerate() {
        *v = wl(r);
    }
    for b in 0..B {
        let xv = xl(b);
        for (acc, &wv) in acc.iter_mut().zip(&wv) {
            acc[b][u] = wv.mul_add(xv, acc[b][u]);
        }
    }
}

/// The dot products of `R` weight rows (`w`, `w + ldw`, ...) with `B` inputs (`x`, `x + ldx`,
/// ...) over `len` columns, each accumulated in `U` vectors. `stream`: this tile is the first
/// to read these weights, from memory, so it prefetches ahead of them.
#[inline(always)]
unsafe fn tile<S: Dot, T: Weight, const R: usize, const B: usize, const U: usize>(
    w: *const T,
    ldw: usize,
    x: *const f32,
    ldx: usize,
    len: usize,
    stream: bool,
) -> [[f32; B]; R] {
    let mut acc = [[[S::splat(0.0); U]; B]; R];
    // Long rows prefetch further along the same row; short rows (a tall, narrow matrix such as
    // the generator's fc) would run off its end, so they prefetch the next block of rows.
    let row_bytes = ldw * core::mem::size_of::<T>();
    let ahead = if row_bytes >= 4 * PREFETCH {
        PREFETCH
    } else {
        R * row_bytes
    };
    let mut k = 0;
    while k + U * S::LANES <= len {
        // Later tiles of a batch reuse the weights from L1.
        if stream {
            for r in 0..R {
                _mm_prefetch::<_MM_HINT_T0>(w.add(r * ldw + k).cast::<i8>().wrapping_add(ahead));
            }
        }
        for u in 0..U {
            let at = k + u * S::LANES;
            step::<S, R, B, U>(
                &mut acc,
                u,
                |r| T::load::<S>(w.add(r * ldw + at)),
                |b| S::load(x.add(b * ldx + at)),
            );
        }
        k += U * S::LANES;
    }
    while k + S::LANES <= len {
        step::<S, R, B, U>(
            &mut acc,
            0,
            |r| T::load::<S>(w.add(r * ldw + k)),
            |b| S::load(x.add(b * ldx + k)),
        );
        k += S::LANES;
    }
    if k < len {
        let n = len - k;
        step::<S, R, B, U>(
            &mut acc,
            0,
            |r| load_partial::<S, T>(w.add(r * ldw + k), n),
            |b| S::load_partial(x.add(b * ldx + k), n),
        );
    }
    let mut sums = [[0.0; B]; R];
    for (sums, acc) in sums.iter_mut().zip(&acc) {
        for (sum, acc) in sums.iter_mut().zip(acc) {
            let mut v = acc[0];
            for &a in &acc[1..] {
                v = v.add(a);
            }
            *sum = v.sum();
        }
    }
    sums
}

/// Adds the dot products of rows `r0 .. r0 + R` with every input over the columns
/// `k0 .. k0 + len` into `y` (or writes them plus the bias when `first`). The tile's rows are
/// `r0, r0 + step, r0 + 2 * step, ...`.
#[inline(always)]
unsafe fn row_block<S: Dot, T: Weight, const R: usize, const BT: usize>(
    w: &[T],
    cols: usize,
    (r0, step, k0, len): (usize, usize, usize, usize),
    bias: &[f32],
    x: &[f32],
    y: &mut [f32],
    first: bool,
) {
    let rows = bias.len();
    let batch = x.len() / cols;
    let wp = w.as_ptr().add(r0 * cols + k0);
    let ldw = step * cols;
    let mut emit = |n0: usize, sums: &[f32], nb: usize| {
        for r in 0..R {
            let row = r0 + r * step;
            for b in 0..nb {
                let out = &mut y[(n0 + b) * rows + row];
                let s = sums[r * nb + b];
                *out = if first { s + bias[row] } else { *out + s };
            }
        }
    };
    let xp = |n0: usize| x.as_ptr().add(n0 * cols + k0);
    let mut n0 = 0;
    if batch == 1 {
        let s = tile::<S, T, R, 1, 2>(wp, ldw, xp(0), cols, len, true);
        emit(0, s.as_flattened(), 1);
        return;
    }
    while n0 + BT <= batch {
        let s = tile::<S, T, R, BT, 1>(wp, ldw, xp(n0), cols, len, n0 == 0);
        emit(n0, s.as_flattened(), BT);
        n0 += BT;
    }
    let stream = n0 == 0;
    match batch - n0 {
        0 => {}
        1 => emit(
            n0,
            tile::<S, T, R, 1, 1>(wp, ldw, xp(n0), cols, len, stream).as_flattened(),
            1,
        ),
        2 => emit(
            n0,
            tile::<S, T, R, 2, 1>(wp, ldw, xp(n0), cols, len, stream).as_flattened(),
            2,
        ),
        _ => emit(
            n0,
            tile::<S, T, R, 3, 1>(wp, ldw, xp(n0), cols, len, stream).as_flattened(),
            3,
        ),
    }
}

/// Every row block over the columns `k0 .. k0 + len`: `R` rows at a time, then one at a time.
///
/// With `spread`, a block's rows are `rows / R` apart instead of adjacent, so that the weights
/// stream from memory as `R` long sequential runs even when rows are short (the generator's
/// 25600 x 512 fc): adjacent short rows would restart the prefetchers every few cache lines.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
unsafe fn row_blocks<S: Dot, T: Weight, const R: usize, const BT: usize>(
    w: &[T],
    rows: usize,
    cols: usize,
    (k0, len): (usize, usize),
    bias: &[f32],
    x: &[f32],
    y: &mut [f32],
    spread: bool,
) {
    let first = k0 == 0;
    let blocks = rows / R;
    let (count, step) = if spread { (blocks, blocks) } else { (blocks, R) };
    for i in 0..count {
        let (r0, row_step) = if spread { (i, step) } else { (i * step, 1) };
        row_block::<S, T, R, BT>(w, cols, (r0, row_step, k0, len), bias, x, y, first);
    }
    for r0 in blocks * R..rows {
        row_block::<S, T, 1, BT>(w, cols, (r0, 1, k0, len), bias, x, y, first);
    }
}

/// See [`crate::dense`]. Batches use a register tile of `RT` rows by `BT` inputs (`BT` at most
/// 4); a single input uses [`ROWS`] rows with two accumulators each.
#[inline(always)]
unsafe fn dense_body<S: Dot, T: Weight, const RT: usize, const BT: usize>(w: &[T], args: Args<'_>) {
    let Args {
        rows,
        cols,
        bias,
        act,
        x,
        y,
    } = args;
    debug_assert!(BT <= 4 && S::LANES <= MAX_LANES);
    let batch = x.len() / cols;
    // Panels only pay when several batch tiles reuse them.
    let panels = if batch <= BT { 1 } else { cols.div_ceil(PANEL) };
    let panel = cols.div_ceil(panels).next_multiple_of(S::LANES);
    let mut k0 = 0;
    while k0 < cols {
        let len = panel.min(cols - k0);
        if batch == 1 {
            row_blocks::<S, T, ROWS, BT>(w, rows, cols, (k0, len), bias, x, y, true);
        } else {
            row_blocks::<S, T, RT, BT>(w, rows, cols, (k0, len), bias, x, y, false);
        }
        k0 += len;
    }
    act::apply_slice::<S>(act, y);
}
