//! The transforms of one tile: the input's (step 1), the products' back to output pixels
//! (step 3), and the weights' (at packing).

use super::filters::{with_phase, Filter, PhaseFn};
use super::Winograd;
use crate::simd::vector::Lane;
use crate::{Activation, ConvKind, OC_ALIGN};
use core::marker::PhantomData;

/// The tile's columns, each a `PY`-array.
#[inline(always)]
unsafe fn columns<L: Lane, const PY: usize, const PX: usize>(x: &[[L; PX]; PY]) -> [[L; PY]; PX] {
    unsafe {
        let mut columns = [[L::zero(); PY]; PX];
        for (r, row) in x.iter().enumerate() {
            for (column, &v) in columns.iter_mut().zip(row) {
                column[r] = v;
            }
        }
        columns
    }
}

/// One axis of a tile transform, `P` values to `Q`: a filter's `B^T` ([`In`]) or `A^T` ([`Out`]).
trait Pass<const P: usize, const Q: usize> {
    unsafe fn apply<L: Lane>(x: [L; P]) -> [L; Q];
}

/// [`Filter::input`] of `F`, an F(`M`, `K`).
struct In<F, const M: usize, const K: usize>(PhantomData<F>);

impl<F: Filter<M, P, K>, const M: usize, const P: usize, const K: usize> Pass<P, P> for In<F, M, K> {
    #[inline(always)]
    unsafe fn apply<L: Lane>(d: [L; P]) -> [L; P] {
        unsafe { F::input(d) }
    }
}

/// [`Filter::output`] of `F`, an F(`M`, `K`).
struct Out<F, const K: usize>(PhantomData<F>);

impl<F: Filter<M, P, K>, const M: usize, const P: usize, const K: usize> Pass<P, M> for Out<F, K> {
    #[inline(always)]
    unsafe fn apply<L: Lane>(m: [L; P]) -> [L; M] {
        unsafe { F::output(m) }
    }
}

/// A `PY x PX` tile transformed by `TY` along its columns, then by `TX` along its rows:
/// `B_y^T d B_x` of an input tile `d` with [`In`], `A_y^T m A_x` of a tile of products `m` (a
/// tile of `M x M` outputs) with [`Out`].
#[inline(always)]
unsafe fn tile_transform<L: Lane, const PY: usize, const PX: usize, const QY: usize, const QX: usize, TY, TX>(
    x: &[[L; PX]; PY],
) -> [[L; QX]; QY]
where
    TY: Pass<PY, QY>,
    TX: Pass<PX, QX>,
{
    unsafe {
        let mut down = [[L::zero(); QY]; PX];
        for (t, column) in down.iter_mut().zip(columns(x)) {
            *t = TY::apply(column);
        }
        // Loops, not closures: a closure would not inherit the caller's target features, and
        // every vector operation in it would become a call.
        let mut y = [[L::zero(); QX]; QY];
        for (y, row) in y.iter_mut().zip(columns(&down)) {
            *y = TX::apply(row);
        }
        y
    }
}

/// Step 1 for one phase: fills `V`'s span of `phase` (`v` is that span, see
/// [`Winograd::phase_span`]) from the input plane, `L::LANES` channels at a time.
pub(crate) struct InputTransform<'a, L> {
    w: &'a Winograd,
    input: &'a [f32],
    v: &'a mut [f32],
    lanes: PhantomData<L>,
}

impl<'a, L> InputTransform<'a, L> {
    pub fn new(w: &'a Winograd, input: &'a [f32], v: &'a mut [f32]) -> Self {
        InputTransform {
            w,
            input,
            v,
            lanes: PhantomData,
        }
    }
}

impl<L: Lane> PhaseFn for InputTransform<'_, L> {
    #[inline(always)]
    unsafe fn call<const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
        &mut self,
        phase: usize,
    ) where
        FY: Filter<M, PY, KY>,
        FX: Filter<M, PX, KX>,
    {
        unsafe {
            let w = self.w;
            let (ip, (gh, gw)) = (w.shape.input, w.grid());
            let (py, px) = (phase / 2, phase % 2);
            let (c, tiles, wide) = (ip.channels, w.tiles(), w.tiles_wide());
            let input = self.input.as_ptr();
            let v = self.v.as_mut_ptr();
            for tile in 0..tiles {
                let (gy, gx) = (
                    (M * (tile / wide)) as isize + w.lo(py),
                    (M * (tile % wide)) as isize + w.lo(px),
                );
                // Each tap's pixel, or none where the grid has no source.
                let mut pixels = [[None; PX]; PY];
                for (r, row) in pixels.iter_mut().enumerate() {
                    if let Some(y) = w.source(py, gy + r as isize, gh) {
                        for (s, pixel) in row.iter_mut().enumerate() {
                            *pixel = w.source(px, gx + s as isize, gw).map(|x| ip.index(y, x));
                        }
                    }
                }
                for c0 in (0..c).step_by(L::LANES) {
                    let n = c - c0;
                    let mut d = [[L::zero(); PX]; PY];
                    for (d, pixels) in d.iter_mut().zip(&pixels) {
                        for (d, pixel) in d.iter_mut().zip(pixels) {
                            if let Some(p) = pixel {
                                *d = L::load_n(input.add(p + c0), n);
                            }
                        }
                    }
                    let t = tile_transform::<L, PY, PX, PY, PX, In<FY, M, KY>, In<FX, M, KX>>(&d);
                    for (r, row) in t.iter().enumerate() {
                        for (s, value) in row.iter().enumerate() {
                            value.store_n(v.add(((r * PX + s) * tiles + tile) * c + c0), n);
                        }
                    }
                }
            }
        }
    }
}

/// Step 3 for one tile and `L::LANES` channels: reads the products of each phase, transforms
/// them back and stores the output pixels (after summing the phases for `Down`).
pub(super) struct OutputTransform<'a, L> {
    pub(super) w: &'a Winograd,
    /// The products of the group, `[point][tile in group][L::BLOCK]`.
    pub(super) m: *const f32,
    /// Bias and output from the block's first channel.
    pub(super) bias: *const f32,
    pub(super) act: Activation,
    pub(super) output: *mut f32,
    /// The phases summed so far (`Down`), in the first `tile x tile`.
    pub(super) sum: [[L; 4]; 4],
    pub(super) tile: usize,
    /// These channels' offset from the block's first, and how many of them are real.
    pub(super) channel: usize,
    pub(super) n: usize,
    /// Offset of these channels in a point's products.
    pub(super) m_at: usize,
}

impl<L: Lane> OutputTransform<'_, L> {
    /// Runs every phase for the current tile and channels; `start` is the group's first tile.
    #[inline(always)]
    pub(super) unsafe fn finish_tile(&mut self, start: usize) {
        unsafe {
            self.m_at = (self.tile - start) * L::BLOCK + self.channel;
            self.sum = [[L::zero(); 4]; 4];
            for phase in 0..4 {
                with_phase(self.w, phase, self);
            }
            if self.w.shape.kind == ConvKind::Down {
                let s = self.sum;
                match self.w.tile {
                    2 => self.store(0, [[s[0][0], s[0][1]], [s[1][0], s[1][1]]]),
                    _ => self.store(0, s),
                }
            }
        }
    }

    /// Adds the bias, applies the activation and stores the pixels of `y` (the tile of `phase`
    /// for `Up`; of all phases for `Down`) that lie in the output.
    #[inline(always)]
    unsafe fn store<const M: usize>(&self, phase: usize, y: [[L; M]; M]) {
        unsafe {
            let (w, op, (gh, gw)) = (self.w, self.w.shape.output, self.w.grid());
            let (ty, tx) = (self.tile / w.tiles_wide(), self.tile % w.tiles_wide());
            let bias = L::load_n(self.bias.add(self.channel), self.n);
            for (dy, row) in y.iter().enumerate() {
                let gy = M * ty + dy;
                if gy >= gh {
                    continue;
                }
                for (dx, value) in row.iter().enumerate() {
                    let gx = M * tx + dx;
                    if gx >= gw {
                        continue;
                    }
                    let at = op.index(w.target(phase / 2, gy), w.target(phase % 2, gx)) + self.channel;
                    value.add(bias).activate(self.act).store_n(self.output.add(at), self.n);
                }
            }
        }
    }
}

impl<L: Lane> PhaseFn for OutputTransform<'_, L> {
    #[inline(always)]
    unsafe fn call<const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
        &mut self,
        phase: usize,
    ) where
        FY: Filter<M, PY, KY>,
        FX: Filter<M, PX, KX>,
    {
        unsafe {
            let (first, group_tiles) = (self.w.phase_points(phase).0, self.w.group_tiles());
            let mut m = [[L::zero(); PX]; PY];
            for (r, row) in m.iter_mut().enumerate() {
                for (s, m) in row.iter_mut().enumerate() {
                    let point = first + r * PX + s;
                    *m = L::load_n(self.m.add(point * group_tiles * L::BLOCK + self.m_at), self.n);
                }
            }
            let y = tile_transform::<L, PY, PX, M, M, Out<FY, KY>, Out<FX, KX>>(&m);
            match self.w.shape.kind {
                ConvKind::Down => {
                    for (sum, y) in self.sum.iter_mut().zip(&y) {
                        for (s, &y) in sum.iter_mut().zip(y) {
                            *s = s.add(y);
                        }
                    }
                }
                ConvKind::Up => self.store(phase, y),
            }
        }
    }
}

/// The weight transform `G g G^T` of each phase's taps on the vector levels (see
/// [`crate::winograd_weights`]; the scalar reference is [`ExactWeightTransform`]), in f32,
/// `L::LANES` output channels at a time: both layouts keep a panel's 16 channels adjacent, so
/// the lanes load and store whole (padding lanes get the transform of the direct weights'
/// padding).
pub(crate) struct WeightTransform<'a, L> {
    w: &'a Winograd,
    direct: &'a [f32],
    packed: &'a mut [f32],
    lanes: PhantomData<L>,
}

impl<'a, L> WeightTransform<'a, L> {
    pub fn new(w: &'a Winograd, direct: &'a [f32], packed: &'a mut [f32]) -> Self {
        WeightTransform {
            w,
            direct,
            packed,
            lanes: PhantomData,
        }
    }
}

impl<L: Lane> PhaseFn for WeightTransform<'_, L> {
    #[inline(always)]
    unsafe fn call<const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
        &mut self,
        phase: usize,
    ) where
        FY: Filter<M, PY, KY>,
        FX: Filter<M, PX, KX>,
    {
        unsafe {
            let (w, shape) = (self.w, &self.w.shape);
            let (py, px, first) = (phase / 2, phase % 2, w.phase_points(phase).0);
            // Where each of the phase's taps sits in a direct panel (input channel 0).
            let mut taps = [[0; KX]; KY];
            for (my, row) in taps.iter_mut().enumerate() {
                for (mx, at) in row.iter_mut().enumerate() {
                    *at = shape.packed_index(w.tap(py, my), w.tap(px, mx), 0, 0);
                }
            }
            let point_stride = w.packed_index(1, 0, 0);
            let (direct, packed) = (self.direct.as_ptr(), self.packed.as_mut_ptr());
            for oc in (0..shape.output.channels).step_by(OC_ALIGN) {
                for ic in 0..shape.input.channels {
                    let (from, to) = (shape.packed_index(0, 0, ic, oc), w.packed_index(first, ic, oc));
                    for lane in (0..OC_ALIGN).step_by(L::LANES) {
                        let mut g = [[L::zero(); KX]; KY];
                        for (g, taps) in g.iter_mut().zip(&taps) {
                            for (g, &at) in g.iter_mut().zip(taps) {
                                *g = L::load_n(direct.add(from + at + lane), L::LANES);
                            }
                        }
                        // The coefficients are constants: the zeros among them are skipped at
                        // compile time (their products could only change the sign of a zero).
                        let mut gg = [[L::zero(); KX]; PY];
                        for (row, gy) in gg.iter_mut().zip(FY::G.iter()) {
                            for (c, value) in row.iter_mut().enumerate() {
                                for (g, &cy) in g.iter().zip(gy) {
                                    if cy != 0.0 {
                                        *value = g[c].mul_add(cy as f32, *value);
                                    }
                                }
                            }
                        }
                        for (r, row) in gg.iter().enumerate() {
                            for (s, gx) in FX::G.iter().enumerate() {
                                let mut sum = L::zero();
                                for (&v, &cx) in row.iter().zip(gx) {
                                    if cx != 0.0 {
                                        sum = v.mul_add(cx as f32, sum);
                                    }
                                }
                                sum.store_n(packed.add(to + (r * PX + s) * point_stride + lane), L::LANES);
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The scalar reference of [`WeightTransform`]: `G g G^T` one pair of channels at a time, in
/// f64 (`G g`, then by `G^T`), rounded once. A loaded model's weights are packed so: the
/// transformed weights are as exact as f32 holds them.
pub(crate) struct ExactWeightTransform<'a> {
    pub w: &'a Winograd,
    pub direct: &'a [f32],
    pub packed: &'a mut [f32],
}

impl PhaseFn for ExactWeightTransform<'_> {
    unsafe fn call<const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
        &mut self,
        phase: usize,
    ) where
        FY: Filter<M, PY, KY>,
        FX: Filter<M, PX, KX>,
    {
        let (w, shape) = (self.w, &self.w.shape);
        let (py, px, first) = (phase / 2, phase % 2, w.phase_points(phase).0);
        for oc in 0..shape.output.channels {
            for ic in 0..shape.input.channels {
                let g = |my: usize, mx: usize| self.direct[shape.packed_index(w.tap(py, my), w.tap(px, mx), ic, oc)];
                let mut gg = [[0.0f64; KX]; PY];
                for (row, gy) in gg.iter_mut().zip(FY::G.iter()) {
                    for (mx, value) in row.iter_mut().enumerate() {
                        *value = (0..KY).map(|my| gy[my] * g(my, mx) as f64).sum();
                    }
                }
                for (r, row) in gg.iter().enumerate() {
                    for (s, gx) in FX::G.iter().enumerate() {
                        let sum: f64 = row.iter().zip(gx).map(|(v, c)| v * c).sum();
                        self.packed[w.packed_index(first + r * PX + s, ic, oc)] = sum as f32;
                    }
                }
            }
        }
    }
}
