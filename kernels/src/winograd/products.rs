//! Steps 2 and 3 of a Winograd convolution: the matrix products of each transform point, in
//! groups of tiles and blocks of output channels, then the output transform.

use super::transform::OutputTransform;
use super::Winograd;
use crate::simd::vector::Lane;
use crate::ConvParams;
use core::ops::Range;

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
    /// [`crate::OC_ALIGN`] where the caller's channels start; `first + valid` is at most the output
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
        unsafe {
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
}

/// Steps 2 and 3 for output channels `channels` (`channels.start` a multiple of [`crate::OC_ALIGN`]).
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
    unsafe {
        let tiles = w.tiles();
        // The tiles go in groups of nearly equal size; all the products of a group and a block of
        // output channels (points x group tiles x 16 floats with AVX2, at most 189 KiB) are kept
        // until the output transform. Of the two operands, the larger streams from L3 and the
        // smaller is reused from L2: with more weights than transformed input, each block's weights
        // (points x input channels x 16) serve every group in turn; otherwise each group's
        // transformed input serves every block.
        let groups = tiles.div_ceil(w.group_tiles());
        let blocks = channels.len().div_ceil(L::BLOCK);
        let weights_outer = w.packed_len() > w.input_len();
        let c = w.shape.input.channels;
        let m = scratch.as_mut_ptr();
        // Each pair of a group and a block, in the order above: its products (step 2) into
        // `scratch`, then their output transform (step 3).
        for i in 0..groups * blocks {
            let (g, b) = if weights_outer {
                (i % groups, i / groups)
            } else {
                (i / blocks, i % blocks)
            };
            let group = tiles * g / groups..tiles * (g + 1) / groups;
            let first = channels.start + b * L::BLOCK;
            let valid = (channels.end - first).min(L::BLOCK);
            for point in 0..w.points() {
                let v = v.as_ptr().add((point * tiles + group.start) * c);
                let m = m.add(point * w.group_tiles() * L::BLOCK);
                let products = Products {
                    w,
                    u: layer.weights,
                    point,
                    v,
                    count: group.len(),
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
            for tile in group.clone() {
                for channel in (0..valid).step_by(L::LANES) {
                    out.tile = tile;
                    out.channel = channel;
                    out.n = valid - channel;
                    out.finish_tile(group.start);
                }
            }
        }
    }
}
