//! Dense (matrix times batch of vectors) kernels for AVX2 and AVX-512.
//!
//! One generic body ([`dense_body`]) is instantiated per vector width (`__m256`, `__m512`)
//! through the activations' [`Simd`] trait and its small extension [`Dot`]; only the
//! `#[target_feature]` entry points differ. The Tanh/ReLU epilogue is [`act::apply`].
//!
//! Layout of the work: `y[n][r] = act(W[r] . x[n] + b[r])`.
//! - A single input streams every weight once, 4 rows at a time with two accumulators per row
//!   (partial dot products, summed across lanes at the end) and a software prefetch
//!   (single-core DRAM streaming is latency-bound without it); the 4 rows are a quarter of the
//!   matrix apart, so even short rows form 4 long sequential streams.
//! - A batch puts its items across the vector lanes instead: the inputs are transposed,
//!   [`BATCH_COLS`] columns at a time, into a buffer on the stack, and a register tile of
//!   `BR` rows by `NV` vectors of items (6 x 2 for AVX2, 12 x 1 for AVX-512) broadcasts each
//!   weight once to multiply it with `NV * LANES` items: the same shape as the convolution's
//!   microkernel, with no sums across lanes.
//!
//! Columns that do not fill a vector are read with masked loads (inputs) or through a
//! zero-padded copy on the stack (weights, which may be f16).

use super::act::{self, Simd};
use crate::{f16, Activation, IsaLevel, Matrix, MatrixData};
use core::arch::x86_64::*;
use core::mem::size_of;

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
    // A batch tile in 16 registers: 6 x 2 accumulators, 2 input vectors, 1 weight broadcast.
    dense_body::<__m256, T, 6, 2>(w, args)
}

#[target_feature(enable = "avx512f,avx2,fma,f16c")]
unsafe fn dense_avx512<T: Weight>(w: &[T], args: Args<'_>) {
    // A batch tile of 16 items (one vector): 12 accumulators of 32 registers.
    dense_body::<__m512, T, 12, 1>(w, args)
}

/// Rows of the register tile for a single input.
const ROWS: usize = 4;
/// Columns of a batch's inputs transposed at a time, into 32 KiB on the stack (with the
/// widened f16 rows, a batch call uses up to 56 KiB of stack).
const BATCH_COLS: usize = 512;
/// Columns per prefetch in the batch microkernel.
const UNROLL: usize = 4;
/// Items of a batch tile: `NV * LANES` for both instruction sets.
const BATCH_ITEMS: usize = 16;
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
    /// The `n` values at `p` as f32: `p` itself, or their widened copy in `buf`.
    unsafe fn as_f32<S: Dot>(p: *const Self, n: usize, buf: *mut f32) -> *const f32;
}

impl Weight for f32 {
    #[inline(always)]
    unsafe fn load<S: Dot>(p: *const f32) -> S {
        S::load(p)
    }
    #[inline(always)]
    unsafe fn as_f32<S: Dot>(p: *const f32, _n: usize, _buf: *mut f32) -> *const f32 {
        p
    }
}

impl Weight for f16 {
    #[inline(always)]
    unsafe fn load<S: Dot>(p: *const f16) -> S {
        S::load_f16(p)
    }
    #[inline(always)]
    unsafe fn as_f32<S: Dot>(p: *const f16, n: usize, buf: *mut f32) -> *const f32 {
        let whole = n / S::LANES * S::LANES;
        for i in (0..whole).step_by(S::LANES) {
            S::load_f16(p.add(i)).store(buf.add(i));
        }
        if whole < n {
            load_partial::<S, f16>(p.add(whole), n - whole).store_partial(buf.add(whole), n - whole);
        }
        buf
    }
}

/// Loads the `n < LANES` values at `p`, the other lanes zero.
#[inline(always)]
unsafe fn load_partial<S: Dot, T: Weight>(p: *const T, n: usize) -> S {
    let mut buf = [T::default(); MAX_LANES];
    core::ptr::copy_nonoverlapping(p, buf.as_mut_ptr(), n);
    T::load::<S>(buf.as_ptr())
}

/// One vector of columns: `wl(r)` loads the weights of row `r`, `xv` is the input, and their
/// products go to accumulator `u` of each row.
#[inline(always)]
unsafe fn step<S: Dot, const R: usize, const U: usize>(
    acc: &mut [[S; U]; R],
    u: usize,
    wl: impl Fn(usize) -> S,
    xv: S,
) {
    for (r, acc) in acc.iter_mut().enumerate() {
        acc[u] = wl(r).mul_add(xv, acc[u]);
    }
}

/// The dot products of `R` weight rows (`w`, `w + ldw`, ...) with the input `x` over `len`
/// columns, each accumulated in `U` vectors, prefetching ahead of the weights.
#[inline(always)]
unsafe fn tile<S: Dot, T: Weight, const R: usize, const U: usize>(
    w: *const T,
    ldw: usize,
    x: *const f32,
    len: usize,
) -> [f32; R] {
    let mut acc = [[S::splat(0.0); U]; R];
    // Long rows prefetch further along the same row; short rows (a tall, narrow matrix such as
    // the generator's fc) would run off its end, so they prefetch the next block of rows.
    let row_bytes = ldw * size_of::<T>();
    let ahead = if row_bytes >= 4 * PREFETCH {
        PREFETCH
    } else {
        R * row_bytes
    };
    let mut k = 0;
    while k + U * S::LANES <= len {
        for r in 0..R {
            _mm_prefetch::<_MM_HINT_T0>(w.add(r * ldw + k).cast::<i8>().wrapping_add(ahead));
        }
        for u in 0..U {
            let at = k + u * S::LANES;
            step(&mut acc, u, |r| T::load::<S>(w.add(r * ldw + at)), S::load(x.add(at)));
        }
        k += U * S::LANES;
    }
    while k + S::LANES <= len {
        step(&mut acc, 0, |r| T::load::<S>(w.add(r * ldw + k)), S::load(x.add(k)));
        k += S::LANES;
    }
    if k < len {
        let n = len - k;
        let xv = S::load_partial(x.add(k), n);
        step(&mut acc, 0, |r| load_partial::<S, T>(w.add(r * ldw + k), n), xv);
    }
    let mut sums = [0.0; R];
    for (sum, acc) in sums.iter_mut().zip(&acc) {
        let mut v = acc[0];
        for &a in &acc[1..] {
            v = v.add(a);
        }
        *sum = v.sum();
    }
    sums
}

/// A single input: every row block, `R` rows at a time (then one at a time) whose rows are
/// `rows / R` apart rather than adjacent, so that the weights stream from memory as `R` long
/// sequential runs even when rows are short (the generator's 25600 x 512 fc): adjacent short
/// rows would restart the prefetchers every few cache lines.
#[inline(always)]
unsafe fn single<S: Dot, T: Weight, const R: usize>(w: &[T], cols: usize, bias: &[f32], x: &[f32], y: *mut f32) {
    let rows = bias.len();
    let blocks = rows / R;
    let emit = |r0: usize, step: usize, sums: &[f32]| {
        for (r, s) in sums.iter().enumerate() {
            let row = r0 + r * step;
            *y.add(row) = s + bias[row];
        }
    };
    for r0 in 0..blocks {
        let sums = tile::<S, T, R, 2>(w.as_ptr().add(r0 * cols), blocks * cols, x.as_ptr(), cols);
        emit(r0, blocks, &sums);
    }
    for r0 in blocks * R..rows {
        emit(
            r0,
            1,
            &tile::<S, T, 1, 2>(w.as_ptr().add(r0 * cols), cols, x.as_ptr(), cols),
        );
    }
}

/// A batch, [`BATCH_ITEMS`] items at a time (see the module comment).
#[inline(always)]
unsafe fn batch<S: Dot, T: Weight, const BR: usize, const NV: usize>(
    w: &[T],
    cols: usize,
    bias: &[f32],
    x: &[f32],
    (y, ldy): (*mut f32, usize),
) {
    let (rows, batch) = (bias.len(), x.len() / cols);
    debug_assert_eq!(NV * S::LANES, BATCH_ITEMS);
    // `xt[k * BATCH_ITEMS + j]` is column `k0 + k` of item `n0 + j`. Lanes past the last item
    // hold stale values: lanes never mix, and their sums are not stored.
    let mut xt = [0.0f32; BATCH_COLS * BATCH_ITEMS];
    for n0 in (0..batch).step_by(BATCH_ITEMS) {
        let items = BATCH_ITEMS.min(batch - n0);
        for k0 in (0..cols).step_by(BATCH_COLS) {
            let len = BATCH_COLS.min(cols - k0);
            for (j, item) in x[n0 * cols..].chunks_exact(cols).take(items).enumerate() {
                for (k, &v) in item[k0..k0 + len].iter().enumerate() {
                    xt[k * BATCH_ITEMS + j] = v;
                }
            }
            let out = Out {
                y,
                ldy,
                n0,
                items,
                bias: (k0 == 0).then_some(bias),
            };
            let wk = w.as_ptr().add(k0);
            let mut r0 = 0;
            while r0 + BR <= rows {
                batch_tile::<S, T, BR, NV>(wk.add(r0 * cols), cols, &xt, len, r0, &out);
                r0 += BR;
            }
            for r0 in r0..rows {
                batch_tile::<S, T, 1, NV>(wk.add(r0 * cols), cols, &xt, len, r0, &out);
            }
        }
    }
}

/// Where a batch tile's sums go: `y[(n0 + j) * ldy + r]` for its `items` items, plus the bias
/// on the first pass over the columns, else added to what earlier passes stored.
struct Out<'a> {
    y: *mut f32,
    ldy: usize,
    n0: usize,
    items: usize,
    bias: Option<&'a [f32]>,
}

/// Rows `r0 .. r0 + R` (weights at `w`, `w + ldw`, ...) times the transposed inputs `xt` over
/// `len` columns: the batch microkernel.
#[inline(always)]
unsafe fn batch_tile<S: Dot, T: Weight, const R: usize, const NV: usize>(
    w: *const T,
    ldw: usize,
    xt: &[f32; BATCH_COLS * BATCH_ITEMS],
    len: usize,
    r0: usize,
    out: &Out<'_>,
) {
    let mut acc = [[S::splat(0.0); NV]; R];
    // f16 rows are widened once here rather than per broadcast.
    let mut wide = core::mem::MaybeUninit::<[[f32; BATCH_COLS]; R]>::uninit();
    let wide = wide.as_mut_ptr().cast::<f32>();
    let rows: [*const f32; R] = core::array::from_fn(|r| T::as_f32::<S>(w.add(r * ldw), len, wide.add(r * BATCH_COLS)));
    // The next block of rows streams from memory while this one computes: a cache line of each
    // of its rows every `UNROLL` columns (enough: a line holds at least 16 weights).
    let next: [*const i8; R] = core::array::from_fn(|r| w.cast::<i8>().wrapping_add((R + r) * ldw * size_of::<T>()));
    let lines = (len * size_of::<T>()).div_ceil(64);
    let step = |acc: &mut [[S; NV]; R], k: usize| {
        let xv: [S; NV] = core::array::from_fn(|v| S::load(xt.as_ptr().add(k * BATCH_ITEMS + v * S::LANES)));
        for (acc, row) in acc.iter_mut().zip(&rows) {
            let b = S::splat(*row.add(k));
            for (a, &xv) in acc.iter_mut().zip(&xv) {
                *a = b.mul_add(xv, *a);
            }
        }
    };
    let mut k = 0;
    while k + UNROLL <= len {
        for u in 0..UNROLL {
            step(&mut acc, k + u);
        }
        let line = k / UNROLL;
        if line < lines {
            for row in next {
                _mm_prefetch::<_MM_HINT_T0>(row.wrapping_add(line * 64));
            }
        }
        k += UNROLL;
    }
    for k in k..len {
        step(&mut acc, k);
    }
    let mut sums = [0.0f32; BATCH_ITEMS];
    for (r, acc) in acc.iter().enumerate() {
        for (v, a) in acc.iter().enumerate() {
            a.store(sums.as_mut_ptr().add(v * S::LANES));
        }
        let row = r0 + r;
        for (j, &s) in sums[..out.items].iter().enumerate() {
            let at = out.y.add((out.n0 + j) * out.ldy + row);
            *at = match out.bias {
                Some(bias) => s + bias[row],
                None => *at + s,
            };
        }
    }
}

/// See [`crate::dense`].
#[inline(always)]
unsafe fn dense_body<S: Dot, T: Weight, const BR: usize, const NV: usize>(w: &[T], args: Args<'_>) {
    let Args {
        cols,
        bias,
        act,
        x,
        y,
        ldy,
    } = args;
    debug_assert!(S::LANES <= MAX_LANES);
    let items = x.len() / cols;
    if items == 1 {
        single::<S, T, ROWS>(w, cols, bias, x, y);
    } else {
        batch::<S, T, BR, NV>(w, cols, bias, x, (y, ldy));
    }
    for n in 0..items {
        act::apply_slice::<S>(act, core::slice::from_raw_parts_mut(y.add(n * ldy), bias.len()));
    }
}
