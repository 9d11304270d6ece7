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
//!    [`Winograd::packed_index`]) into a scratch of [`Winograd::scratch_len`] floats, then transforms the
//!    products back, adds the bias, applies the activation and stores the output pixels.
//!
//! The input and output transforms are written out (their coefficients are small integers), so
//! the scalar and SIMD paths share them. The weight transform is the two products `G g G^T`
//! with constant coefficients: in f64, rounded once, on the scalar path, which packs a loaded
//! model's weights (the same on every CPU); in f32 on the vector paths, which a trainer runs
//! after every update.
//!
//! The scalar path runs the same three steps one float at a time; it is tested against the
//! direct scalar convolution, the oracle of both.
//!
//! This module holds the geometry ([`Winograd`]); `filters.rs` the F(m,k) transforms and the
//! dispatch on a phase's filters; `transform.rs` the input, output and weight transforms of a
//! tile; `products.rs` the matrix products and the driver of steps 2 and 3.

mod filters;
mod products;
mod transform;

pub(crate) use filters::with_phase;
pub(crate) use products::{channels, Product, Products, ScalarProduct};
pub(crate) use transform::{ExactWeightTransform, InputTransform, WeightTransform};

use crate::{ConvKind, ConvShape, OC_ALIGN};
use core::ops::Range;

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
    /// The layer computed.
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
    pub(crate) fn phase_points(&self, phase: usize) -> (usize, usize) {
        let per_axis = |p: usize| self.tile + 2 - p;
        let count = |phase: usize| per_axis(phase / 2) * per_axis(phase % 2);
        ((0..phase).map(count).sum(), count(phase))
    }

    /// The most tiles whose products are kept at once (see [`crate::winograd_channels`]): 20
    /// of 2x2 (tried from 12 to 64: as good as any), 25 of 4x4 (the encoder's conv1 on Zen 3:
    /// 1.74 ms in groups of 12, 1.49-1.58 of 17, 1.43-1.48 of 25, 1.37 in one group of 50,
    /// whose scratch would be as large as L2).
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

    /// Floats of the product scratch [`crate::winograd_channels`] needs (one per thread): the
    /// products of one group of tiles ([`Winograd::group_tiles`]) at every transform point, for
    /// a block of up to 32 output channels (two AVX-512 vectors).
    pub fn scratch_len(&self) -> usize {
        self.points() * self.group_tiles() * 2 * OC_ALIGN
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
    pub(crate) fn lo(&self, phase: usize) -> isize {
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
    pub(crate) fn source(&self, phase: usize, g: isize, len: usize) -> Option<usize> {
        let g = usize::try_from(g).ok().filter(|&g| g < len)?;
        Some(match self.shape.kind {
            ConvKind::Down => 2 * g + phase,
            ConvKind::Up => g,
        })
    }

    /// The output coordinate of grid position `g` of `phase` along an axis.
    pub(crate) fn target(&self, phase: usize, g: usize) -> usize {
        match self.shape.kind {
            ConvKind::Down => g,
            ConvKind::Up => 2 * g + phase,
        }
    }
}
