//! Winograd convolution for the model's 5x5 stride-2 layers, both kinds.
//!
//! A stride-2 layer is four stride-1 correlations, one per pair of stride phases `(py, px)`:
//! - `Down`: output `o` reads input `2o + k - 2`. Split the input into its even and odd pixels
//!   per axis ("phase grids" of half the size): taps `k = 0, 2, 4` read the even grid at
//!   `o - 1, o, o + 1`, taps `k = 1, 3` the odd grid at `o - 1, o`. The output sums the four.
//! - `Up`: output `2j + p` reads input `j + (p + 2 - k) / 2` for the taps of parity `p`: the
//!   even outputs see taps `4, 2, 0` at `j - 1, j, j + 1`, the odd ones taps `3, 1` at `j, j + 1`.
//!   Each output phase is its own correlation of the input.
//!
//! Each correlation uses Winograd's minimal filtering per axis on tiles of `m` outputs, with
//! `m` = 2 or 4 per layer ([`Winograd::tile`]): F(m,3) for three taps and F(m,2) for two. A
//! 2x2 tile of every phase takes 16 + 12 + 12 + 9 = 49 products per pair of channels where the
//! direct sum takes 100; a 4x4 tile takes 36 + 30 + 30 + 25 = 121 where the direct sum takes
//! 400, but its transformed weights are 121 / 49 times larger. The products of one transform
//! point over all input channels are a matrix product (tiles x in_channels times in_channels x
//! out_channels), which the SIMD path computes with the direct convolution's microkernel.
//!
//! Three steps, each over a caller's buffer (nothing is allocated):
//! 1. [`crate::winograd_input`] transforms the input into `V`, `[point][tile][in_channel]`, one
//!    phase at a time (tiles row-major over the phase grid, see [`Winograd::tiles`]);
//! 2. and 3. [`crate::winograd_channels`] multiplies a group of tiles by the packed weights
//!    `U` (`[out_channel / 16][point][in_channel][out_channel % 16]`, see
//!    [`Winograd::packed_index`]) into a scratch of [`SCRATCH_LEN`] floats, then transforms the
//!    products back, adds the bias, applies the activation and stores the output pixels.
//!
//! The input and output transforms are written out (their coefficients are small integers), so
//! the scalar and SIMD paths share them; the weight transform runs once, in f64.
//!
//! The scalar path runs the same three steps one float at a time; it is tested against the
//! direct scalar convolution, the oracle of both.

use crate::{Activation, ConvKind, ConvParams, ConvShape, OC_ALIGN};
use core::ops::Range;

/// Floats of the product scratch [`crate::winograd_channels`] needs: the products of one group
/// of tiles ([`Winograd::group_tiles`]) at every transform point, for a block of up to 32 output
/// channels (two AVX-512 vectors). 4x4 tiles (121 points, groups of 25) need more than 2x2
/// tiles (49 points, groups of 20).
pub const SCRATCH_LEN: usize = 121 * GROUP_4X4 * 2 * OC_ALIGN;
/// Tiles per group (see [`Winograd::group_tiles`]).
const GROUP_2X2: usize = 20;
const GROUP_4X4: usize = 25;
/// Layers with fewer input channels stay direct: each product would be too short to pay for
/// the transforms (the first encoder layer has 3).
pub const MIN_IN_CHANNELS: usize = 8;

/// The Winograd geometry of a convolution layer; made only for layers it computes exactly:
/// kernel 5, more than [`crate::NARROW_OC`] output channels, at least [`MIN_IN_CHANNELS`] input
/// channels, and for `Down` an even input size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Winograd {
    pub shape: ConvShape,
    /// Outputs per tile along each axis of a phase grid: 2 or 4.
    tile: usize,
}

impl Winograd {
    /// The layer with the tile size that suits it: 4 where 2x2 tiles would make the transformed
    /// input larger than the weights (large images, few channels), which then streams through
    /// the products; there 4x4 tiles shrink both it and the products by 1.6 and the weights,
    /// read once per group of tiles, grow by 2.5. Elsewhere the weights are the larger operand
    /// and 2x2 tiles keep them small.
    pub fn new(shape: ConvShape) -> Option<Winograd> {
        let small = Self::with_tile(shape, 2)?;
        if small.input_len() > small.packed_len() {
            Self::with_tile(shape, 4)
        } else {
            Some(small)
        }
    }

    /// The layer with tiles of `tile` (2 or 4) outputs per axis.
    pub fn with_tile(shape: ConvShape, tile: usize) -> Option<Winograd> {
        let even =
            shape.kind == ConvKind::Up || (shape.input.height.is_multiple_of(2) && shape.input.width.is_multiple_of(2));
        let fits = shape.kernel == 5 && !shape.is_narrow() && shape.input.channels >= MIN_IN_CHANNELS && even;
        (fits && (tile == 2 || tile == 4)).then_some(Winograd { shape, tile })
    }

    /// Outputs per tile along each axis of a phase grid.
    pub fn tile(&self) -> usize {
        self.tile
    }

    /// Transform points of the four phases together: `(m + 2)^2 + 2 (m + 2)(m + 1) + (m + 1)^2`.
    pub fn points(&self) -> usize {
        (2 * self.tile + 3) * (2 * self.tile + 3)
    }

    /// First point and number of points of phase `2 * py + px` (phase 0 of an axis has three
    /// taps, phase 1 two).
    fn phase_points(&self, phase: usize) -> (usize, usize) {
        let per_axis = |p: usize| self.tile + 2 - p;
        let count = |phase: usize| per_axis(phase / 2) * per_axis(phase % 2);
        ((0..phase).map(count).sum(), count(phase))
    }

    /// The most tiles whose products are kept at once (see [`crate::winograd_channels`]): 20
    /// of 2x2 (tried from 12 to 64: as good as any), 25 of 4x4 (the encoder's conv1 on Zen 3:
    /// 1.74 ms in groups of 12, 1.49-1.58 of 17, 1.43-1.48 of 25, 1.37 in one group of 50,
    /// whose scratch would be as large as L2). Their products fit [`SCRATCH_LEN`].
    pub fn group_tiles(&self) -> usize {
        if self.tile == 2 {
            GROUP_2X2
        } else {
            GROUP_4X4
        }
    }

    /// Height and width of a phase grid: the output for `Down`, the input for `Up`.
    pub fn grid(&self) -> (usize, usize) {
        let p = match self.shape.kind {
            ConvKind::Down => self.shape.output,
            ConvKind::Up => self.shape.input,
        };
        (p.height, p.width)
    }

    /// Tiles per row of the phase grid.
    pub fn tiles_wide(&self) -> usize {
        self.grid().1.div_ceil(self.tile)
    }

    /// Tiles of `tile x tile` grid positions covering the phase grid (the last row and column of
    /// tiles may hang over it).
    pub fn tiles(&self) -> usize {
        self.grid().0.div_ceil(self.tile) * self.tiles_wide()
    }

    /// Floats of one panel of 16 output channels of the packed weights.
    pub fn panel_len(&self) -> usize {
        self.points() * self.shape.input.channels * OC_ALIGN
    }

    /// Floats of the packed weights.
    pub fn packed_len(&self) -> usize {
        self.shape.output.channels.div_ceil(OC_ALIGN) * self.panel_len()
    }

    /// Where the transformed weight of `point` from input channel `ic` to output channel `oc`
    /// is packed.
    pub fn packed_index(&self, point: usize, ic: usize, oc: usize) -> usize {
        (oc / OC_ALIGN) * self.panel_len() + (point * self.shape.input.channels + ic) * OC_ALIGN + oc % OC_ALIGN
    }

    /// Floats of the transformed input `V`.
    pub fn input_len(&self) -> usize {
        self.points() * self.tiles() * self.shape.input.channels
    }

    /// The part of `V` that phase `phase` (0 to 3) fills.
    pub fn phase_span(&self, phase: usize) -> Range<usize> {
        let (first, count) = self.phase_points(phase);
        let per_point = self.tiles() * self.shape.input.channels;
        first * per_point..(first + count) * per_point
    }

    /// Offset from `tile` times a tile's index to its first source position, along an axis.
    fn lo(&self, phase: usize) -> isize {
        match self.shape.kind {
            ConvKind::Down => -1,
            ConvKind::Up => phase as isize - 1,
        }
    }

    /// The kernel tap that sub-tap `m` of `phase` is, along an axis.
    pub(crate) fn tap(&self, phase: usize, m: usize) -> usize {
        match self.shape.kind {
            ConvKind::Down => 2 * m + phase,
            ConvKind::Up => 4 - phase - 2 * m,
        }
    }

    /// The input coordinate of grid position `g` of `phase` along an axis of `len` grid
    /// positions, or `None` outside the grid (where the source is zero).
    fn source(&self, phase: usize, g: isize, len: usize) -> Option<usize> {
        let g = usize::try_from(g).ok().filter(|&g| g < len)?;
        Some(match self.shape.kind {
            ConvKind::Down => 2 * g + phase,
            ConvKind::Up => g,
        })
    }

    /// The output coordinate of grid position `g` of `phase` along an axis.
    fn target(&self, phase: usize, g: usize) -> usize {
        match self.shape.kind {
            ConvKind::Down => g,
            ConvKind::Up => 2 * g + phase,
        }
    }
}

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
        [d0.sub(d2), d1.add(d2), d2.sub(d1), d1.sub(d3)]
    }
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2, m3]: [L; 4]) -> [L; 2] {
        [m0.add(m1).add(m2), m1.sub(m2).sub(m3)]
    }
}

/// F(2,2), points 0, 1 and infinity.
pub(crate) struct F22;

impl Filter<2, 3, 2> for F22 {
    const G: [[f64; 2]; 3] = [[1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    #[inline(always)]
    unsafe fn input<L: Lane>([d0, d1, d2]: [L; 3]) -> [L; 3] {
        [d0.sub(d1), d1, d2.sub(d1)]
    }
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2]: [L; 3]) -> [L; 2] {
        [m0.add(m1), m1.add(m2)]
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
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2, m3, m4, m5]: [L; 6]) -> [L; 4] {
        let (p, q, r, s) = (m1.add(m2), m1.sub(m2), m3.add(m4), m3.sub(m4));
        [
            m0.add(p).add(r),
            s.mul_add(2.0, q),
            r.mul_add(4.0, p),
            s.mul_add(8.0, q).add(m5),
        ]
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
        [
            d0.sub(d2).mul_add(2.0, d3.sub(d1)),
            d1.mul_add(-2.0, d3.sub(d2)),
            d1.mul_add(2.0, d2.mul_add(-3.0, d3)),
            d3.sub(d1),
            d1.sub(d3).mul_add(2.0, d4.sub(d2)),
        ]
    }
    #[inline(always)]
    unsafe fn output<L: Lane>([m0, m1, m2, m3, m4]: [L; 5]) -> [L; 4] {
        let (p, q) = (m1.add(m2), m1.sub(m2));
        [
            m0.add(p).add(m3),
            m3.mul_add(2.0, q),
            m3.mul_add(4.0, p),
            m3.mul_add(8.0, q).add(m4),
        ]
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

/// A run of `LANES` floats the transforms work on: one float on the scalar path, a vector on
/// the SIMD paths. Methods are unsafe for the SIMD types (see `simd::act::Simd`).
pub(crate) trait Lane: Copy {
    const LANES: usize;
    /// Output channels per block of the matrix products.
    const BLOCK: usize;
    unsafe fn zero() -> Self;
    /// The first `min(n, LANES)` floats at `p`, zero in the other lanes.
    unsafe fn load_n(p: *const f32, n: usize) -> Self;
    /// Stores the first `min(n, LANES)` lanes to `p`.
    unsafe fn store_n(self, p: *mut f32, n: usize);
    unsafe fn add(self, b: Self) -> Self;
    unsafe fn sub(self, b: Self) -> Self;
    /// `self * c + acc`.
    unsafe fn mul_add(self, c: f32, acc: Self) -> Self;
    unsafe fn activate(self, act: Activation) -> Self;
}

impl Lane for f32 {
    const LANES: usize = 1;
    const BLOCK: usize = OC_ALIGN;
    unsafe fn zero() -> f32 {
        0.0
    }
    unsafe fn load_n(p: *const f32, n: usize) -> f32 {
        if n > 0 {
            *p
        } else {
            0.0
        }
    }
    unsafe fn store_n(self, p: *mut f32, n: usize) {
        if n > 0 {
            *p = self
        }
    }
    unsafe fn add(self, b: f32) -> f32 {
        self + b
    }
    unsafe fn sub(self, b: f32) -> f32 {
        self - b
    }
    unsafe fn mul_add(self, c: f32, acc: f32) -> f32 {
        self * c + acc
    }
    unsafe fn activate(self, act: Activation) -> f32 {
        act.apply(self)
    }
}

/// The tile's columns, each a `PY`-array.
#[inline(always)]
unsafe fn columns<L: Lane, const PY: usize, const PX: usize>(x: &[[L; PX]; PY]) -> [[L; PY]; PX] {
    let mut columns = [[L::zero(); PY]; PX];
    for (r, row) in x.iter().enumerate() {
        for (column, &v) in columns.iter_mut().zip(row) {
            column[r] = v;
        }
    }
    columns
}

/// `B_y^T d B_x` for a `PY x PX` input tile `d`.
#[inline(always)]
unsafe fn input_tile<L, const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
    d: &[[L; PX]; PY],
) -> [[L; PX]; PY]
where
    L: Lane,
    FY: Filter<M, PY, KY>,
    FX: Filter<M, PX, KX>,
{
    let mut out = *d;
    for c in 0..PX {
        let mut column = [L::zero(); PY];
        for (value, row) in column.iter_mut().zip(&out) {
            *value = row[c];
        }
        for (row, value) in out.iter_mut().zip(FY::input(column)) {
            row[c] = value;
        }
    }
    for row in out.iter_mut() {
        *row = FX::input(*row);
    }
    out
}

/// `A_y^T m A_x` for a `PY x PX` tile of products `m`: a tile of `M x M` outputs.
#[inline(always)]
unsafe fn output_tile<L, const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
    m: &[[L; PX]; PY],
) -> [[L; M]; M]
where
    L: Lane,
    FY: Filter<M, PY, KY>,
    FX: Filter<M, PX, KX>,
{
    let mut down = [[L::zero(); M]; PX];
    for (t, column) in down.iter_mut().zip(columns(m)) {
        *t = FY::output(column);
    }
    // Loops, not closures: a closure would not inherit the caller's target features, and
    // every vector operation in it would become a call.
    let mut y = [[L::zero(); M]; M];
    for (y, row) in y.iter_mut().zip(columns(&down)) {
        *y = FX::output(row);
    }
    y
}

/// Step 1 for one phase: fills `V`'s span of `phase` (`v` is that span, see
/// [`Winograd::phase_span`]) from the input plane, `L::LANES` channels at a time.
pub(crate) struct InputTransform<'a, L> {
    w: &'a Winograd,
    input: &'a [f32],
    v: &'a mut [f32],
    lanes: core::marker::PhantomData<L>,
}

impl<'a, L> InputTransform<'a, L> {
    pub fn new(w: &'a Winograd, input: &'a [f32], v: &'a mut [f32]) -> Self {
        InputTransform {
            w,
            input,
            v,
            lanes: core::marker::PhantomData,
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
                let t = input_tile::<L, M, PY, KY, PX, KX, FY, FX>(&d);
                for (r, row) in t.iter().enumerate() {
                    for (s, value) in row.iter().enumerate() {
                        value.store_n(v.add(((r * PX + s) * tiles + tile) * c + c0), n);
                    }
                }
            }
        }
    }
}

/// One matrix product of step 2: `m[t * L::BLOCK + j] = sum_i v[t * in_channels + i] *
/// U[point][i][first + j]` for tiles `t < count` and `j < valid`.
pub(crate) struct Products<'a> {
    pub w: &'a Winograd,
    /// The packed weights `U`.
    pub u: &'a [f32],
    pub point: usize,
    /// `count` tiles of input channels.
    pub v: *const f32,
    pub count: usize,
    /// `count` rows of `L::BLOCK` floats.
    pub m: *mut f32,
    /// The block's first output channel: a multiple of `L::BLOCK` past the multiple of
    /// [`OC_ALIGN`] where the caller's channels start; `first + valid` is at most the output
    /// channels.
    pub first: usize,
    pub valid: usize,
}

/// What computes [`Products`].
pub(crate) trait Product {
    /// # Safety
    /// The pointers of `p` must be valid as [`Products`] describes.
    unsafe fn run(&self, p: &Products<'_>);
}

/// The scalar products, straight from the definition.
pub(crate) struct ScalarProduct;

impl Product for ScalarProduct {
    unsafe fn run(&self, p: &Products<'_>) {
        let (w, u, point, v, m) = (p.w, p.u, p.point, p.v, p.m);
        let (count, first, valid) = (p.count, p.first, p.valid);
        let c = w.shape.input.channels;
        for t in 0..count {
            let v = core::slice::from_raw_parts(v.add(t * c), c);
            for j in 0..valid {
                let sum = v
                    .iter()
                    .enumerate()
                    .map(|(i, x)| x * u[w.packed_index(point, i, first + j)])
                    .sum();
                *m.add(t * <f32 as Lane>::BLOCK + j) = sum;
            }
        }
    }
}

/// Steps 2 and 3 for output channels `channels` (`channels.start` a multiple of [`OC_ALIGN`]).
///
/// # Safety
/// As for [`crate::winograd_channels`], and the CPU must support `L` and `P`.
#[inline(always)]
pub(crate) unsafe fn channels<L: Lane, P: Product>(
    product: &P,
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    output: *mut f32,
    channels: Range<usize>,
) {
    let tiles = w.tiles();
    // The tiles go in groups of nearly equal size; all the products of a group and a block of
    // output channels (points x group tiles x 16 floats with AVX2, at most 189 KiB) are kept
    // until the output transform. Of the two operands, the larger streams from L3 and the
    // smaller is reused from L2: with more weights than transformed input, each block's weights
    // (points x input channels x 16) serve every group in turn; otherwise each group's
    // transformed input serves every block.
    let groups = tiles.div_ceil(w.group_tiles());
    let group = |g: usize| tiles * g / groups..tiles * (g + 1) / groups;
    let blocks = channels.clone().step_by(L::BLOCK);
    if w.packed_len() > w.input_len() {
        for first in blocks {
            for g in 0..groups {
                group_block::<L, P>(product, w, layer, v, scratch, output, group(g), first..channels.end);
            }
        }
    } else {
        for g in 0..groups {
            for first in blocks.clone() {
                group_block::<L, P>(product, w, layer, v, scratch, output, group(g), first..channels.end);
            }
        }
    }
}

/// Steps 2 and 3 for the tiles `tiles` and the block of output channels from `channels.start`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn group_block<L: Lane, P: Product>(
    product: &P,
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    output: *mut f32,
    tiles: Range<usize>,
    channels: Range<usize>,
) {
    let (first, valid) = (channels.start, channels.len().min(L::BLOCK));
    let c = w.shape.input.channels;
    let m = scratch.as_mut_ptr();
    for point in 0..w.points() {
        let v = v.as_ptr().add((point * w.tiles() + tiles.start) * c);
        let m = m.add(point * w.group_tiles() * L::BLOCK);
        let products = Products {
            w,
            u: layer.weights,
            point,
            v,
            count: tiles.len(),
            m,
            first,
            valid,
        };
        product.run(&products);
    }
    let mut out = OutputTransform::<L> {
        w,
        m,
        bias: layer.bias.as_ptr().add(first),
        act: layer.act,
        output: output.add(first),
        sum: [[L::zero(); 4]; 4],
        tile: 0,
        channel: 0,
        n: 0,
        m_at: 0,
    };
    for tile in tiles.clone() {
        for channel in (0..valid).step_by(L::LANES) {
            out.tile = tile;
            out.channel = channel;
            out.n = valid - channel;
            out.finish_tile(tiles.start);
        }
    }
}

/// Step 3 for one tile and `L::LANES` channels: reads the products of each phase, transforms
/// them back and stores the output pixels (after summing the phases for `Down`).
struct OutputTransform<'a, L> {
    w: &'a Winograd,
    /// The products of the group, `[point][tile in group][L::BLOCK]`.
    m: *const f32,
    /// Bias and output from the block's first channel.
    bias: *const f32,
    act: Activation,
    output: *mut f32,
    /// The phases summed so far (`Down`), in the first `tile x tile`.
    sum: [[L; 4]; 4],
    tile: usize,
    /// These channels' offset from the block's first, and how many of them are real.
    channel: usize,
    n: usize,
    /// Offset of these channels in a point's products.
    m_at: usize,
}

impl<L: Lane> OutputTransform<'_, L> {
    /// Runs every phase for the current tile and channels; `start` is the group's first tile.
    #[inline(always)]
    unsafe fn finish_tile(&mut self, start: usize) {
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

    /// Adds the bias, applies the activation and stores the pixels of `y` (the tile of `phase`
    /// for `Up`; of all phases for `Down`) that lie in the output.
    #[inline(always)]
    unsafe fn store<const M: usize>(&self, phase: usize, y: [[L; M]; M]) {
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

impl<L: Lane> PhaseFn for OutputTransform<'_, L> {
    #[inline(always)]
    unsafe fn call<const M: usize, const PY: usize, const KY: usize, const PX: usize, const KX: usize, FY, FX>(
        &mut self,
        phase: usize,
    ) where
        FY: Filter<M, PY, KY>,
        FX: Filter<M, PX, KX>,
    {
        let (first, group_tiles) = (self.w.phase_points(phase).0, self.w.group_tiles());
        let mut m = [[L::zero(); PX]; PY];
        for (r, row) in m.iter_mut().enumerate() {
            for (s, m) in row.iter_mut().enumerate() {
                let point = first + r * PX + s;
                *m = L::load_n(self.m.add(point * group_tiles * L::BLOCK + self.m_at), self.n);
            }
        }
        let y = output_tile::<L, M, PY, KY, PX, KX, FY, FX>(&m);
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

/// Packs weights already in the direct layout (see [`crate::pack::winograd_weights`]).
pub(crate) struct WeightTransform<'a> {
    pub w: &'a Winograd,
    pub direct: &'a [f32],
    pub packed: &'a mut [f32],
}

impl PhaseFn for WeightTransform<'_> {
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
                let g: [[f64; KX]; KY] = core::array::from_fn(|my| {
                    core::array::from_fn(|mx| {
                        self.direct[shape.packed_index(w.tap(py, my), w.tap(px, mx), ic, oc)] as f64
                    })
                });
                // G g G^T in f64, rounded once.
                for (r, gy) in FY::G.iter().enumerate() {
                    for (s, gx) in FX::G.iter().enumerate() {
                        let mut sum = 0.0;
                        for (grow, &cy) in g.iter().zip(gy) {
                            for (&value, &cx) in grow.iter().zip(gx) {
                                sum += cy * value * cx;
                            }
                        }
                        self.packed[w.packed_index(first + r * PX + s, ic, oc)] = sum as f32;
                    }
                }
            }
        }
    }
}
