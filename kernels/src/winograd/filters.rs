//! Winograd's minimal filtering F(m,k) for the layers' tiles, and the dispatch on the filters
//! of a stride phase.

use super::Winograd;
use crate::simd::vector::Lane;

/// Winograd's minimal filtering F(`M`, `K`) on `P = M + K - 1` points: for inputs `d` (P
/// values) and taps `g` (K values), the `M` outputs `y[i] = sum_k d[i + k] g[k]` are
/// `output(G g . input(d))`. The transforms are written out, so that their constant small
/// integer coefficients cost little.
pub(crate) trait Filter<const M: usize, const P: usize, const K: usize> {
    /// The weight transform, applied once at packing.
    const G: [[f64; K]; P];
    /// `B^T d`.
    unsafe fn input<L: Lane>(d: [L; P]) -> [L; P];
    /// `A^T m`.
    unsafe fn output<L: Lane>(m: [L; P]) -> [L; M];
}

/// F(2,3), points 0, 1, -1 and infinity.
pub(crate) struct F23;

impl Filter<2, 4, 3> for F23 {
    const G: [[f64; 3]; 4] = [[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 1.0]];
    #[inline(always)]
    unsafe fn input<L: Lane>([d0, d1, d2, d3]: [L; 4]) -> [L; 4] {
        unsafe { [d0.sub(d2), d1.add(d2), d2.sub(d1), d1.sub(d3)] }
    }
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2, m3]: [L; 4]) -> [L; 2] {
        unsafe { [m0.add(m1).add(m2), m1.sub(m2).sub(m3)] }
    }
}

/// F(2,2), points 0, 1 and infinity.
pub(crate) struct F22;

impl Filter<2, 3, 2> for F22 {
    const G: [[f64; 2]; 3] = [[1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    #[inline(always)]
    unsafe fn input<L: Lane>([d0, d1, d2]: [L; 3]) -> [L; 3] {
        unsafe { [d0.sub(d1), d1, d2.sub(d1)] }
    }
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2]: [L; 3]) -> [L; 2] {
        unsafe { [m0.add(m1), m1.add(m2)] }
    }
}

/// F(4,3), points 0, 1, -1, 2, -2 and infinity.
pub(crate) struct F43;

impl Filter<4, 6, 3> for F43 {
    const G: [[f64; 3]; 6] = [
        [1.0 / 4.0, 0.0, 0.0],
        [-1.0 / 6.0, -1.0 / 6.0, -1.0 / 6.0],
        [-1.0 / 6.0, 1.0 / 6.0, -1.0 / 6.0],
        [1.0 / 24.0, 1.0 / 12.0, 1.0 / 6.0],
        [1.0 / 24.0, -1.0 / 12.0, 1.0 / 6.0],
        [0.0, 0.0, 1.0],
    ];
    #[inline(always)]
    unsafe fn input<L: Lane>([d0, d1, d2, d3, d4, d5]: [L; 6]) -> [L; 6] {
        unsafe {
            let (a, b) = (d2.mul_add(-4.0, d4), d1.mul_add(-4.0, d3));
            let (c, e) = (d4.sub(d2), d3.sub(d1));
            let e = e.add(e);
            [
                d2.mul_add(-5.0, d0.mul_add(4.0, d4)),
                a.add(b),
                a.sub(b),
                c.add(e),
                c.sub(e),
                d3.mul_add(-5.0, d1.mul_add(4.0, d5)),
            ]
        }
    }
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2, m3, m4, m5]: [L; 6]) -> [L; 4] {
        unsafe {
            let (p, q, r, s) = (m1.add(m2), m1.sub(m2), m3.add(m4), m3.sub(m4));
            [
                m0.add(p).add(r),
                s.mul_add(2.0, q),
                r.mul_add(4.0, p),
                s.mul_add(8.0, q).add(m5),
            ]
        }
    }
}

/// F(4,2), points 0, 1, -1, 2 and infinity.
pub(crate) struct F42;

impl Filter<4, 5, 2> for F42 {
    const G: [[f64; 2]; 5] = [
        [1.0 / 2.0, 0.0],
        [-1.0 / 2.0, -1.0 / 2.0],
        [-1.0 / 6.0, 1.0 / 6.0],
        [1.0 / 6.0, 1.0 / 3.0],
        [0.0, 1.0],
    ];
    #[inline(always)]
    unsafe fn input<L: Lane>([d0, d1, d2, d3, d4]: [L; 5]) -> [L; 5] {
        unsafe {
            [
                d0.sub(d2).mul_add(2.0, d3.sub(d1)),
                d1.mul_add(-2.0, d3.sub(d2)),
                d1.mul_add(2.0, d2.mul_add(-3.0, d3)),
                d3.sub(d1),
                d1.sub(d3).mul_add(2.0, d4.sub(d2)),
            ]
        }
    }
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2, m3, m4]: [L; 5]) -> [L; 4] {
        unsafe {
            let (p, q) = (m1.add(m2), m1.sub(m2));
            [
                m0.add(p).add(m3),
                m3.mul_add(2.0, q),
                m3.mul_add(4.0, p),
                m3.mul_add(8.0, q).add(m4),
            ]
        }
    }
}

/// Something generic over the transforms of one phase: tiles of `M x M` outputs, `PY x PX`
/// points, `KY x KX` taps.
pub(crate) trait PhaseFn {
    /// # Safety
    /// As the implementation requires (SIMD features, valid pointers).
    unsafe fn call<const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
        &mut self,
        phase: usize,
    ) where
        FY: Filter<M, PY, KY>,
        FX: Filter<M, PX, KX>;
}

/// Calls `f` with the transforms of `phase` (`2 * py + px`; phase 0 of an axis has 3 taps) for
/// the tiles of `w`.
///
/// # Safety
/// As `f` requires.
#[inline(always)]
pub(crate) unsafe fn with_phase(w: &Winograd, phase: usize, f: &mut impl PhaseFn) {
    unsafe {
        match (w.tile, phase) {
            (2, 0) => f.call::<2, 4, 3, 4, 3, F23, F23>(0),
            (2, 1) => f.call::<2, 4, 3, 3, 2, F23, F22>(1),
            (2, 2) => f.call::<2, 3, 2, 4, 3, F22, F23>(2),
            (2, _) => f.call::<2, 3, 2, 3, 2, F22, F22>(3),
            (_, 0) => f.call::<4, 6, 3, 6, 3, F43, F43>(0),
            (_, 1) => f.call::<4, 6, 3, 5, 2, F43, F42>(1),
            (_, 2) => f.call::<4, 5, 2, 6, 3, F42, F43>(2),
            (_, _) => f.call::<4, 5, 2, 5, 2, F42, F42>(3),
        }
    }
}
