//! The data layouts the kernels read and write: feature maps ([`Plane`]), convolution layers
//! ([`ConvShape`], [`ConvParams`]) and packed dense matrices ([`Matrix`]).

use crate::Activation;
use alloc::vec::Vec;
use half::f16;

/// Packed convolution and dense weights come in panels of this many output channels or rows
/// (the last panel zero-padded), so that every SIMD width up to 16 lanes loads whole vectors of
/// weights and one block of outputs streams through contiguous memory.
pub const OC_ALIGN: usize = 16;

/// Layers with at most this many output channels pack their weights input-channel-major
/// (`[out_channel][ky][kx][in_channel]`, see [`ConvShape::packed_index`]): vectors over output
/// channels would be mostly padding, so their kernels vectorise over input channels instead.
pub const NARROW_OC: usize = 4;

/// A feature map stored in HWC order (channels innermost) inside a border of `halo` zero pixels
/// on every side. The border lets convolution kernels read taps that fall outside the image
/// without bounds checks; it is zeroed once when the buffer is made and never written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Plane {
    /// Rows of the image, border excluded.
    pub height: usize,
    /// Columns of the image, border excluded.
    pub width: usize,
    /// Values per pixel.
    pub channels: usize,
    /// Zero pixels around the image on every side.
    pub halo: usize,
}

impl Plane {
    /// A plane of `height x width` pixels of `channels` inside a border of `halo`.
    pub const fn new(height: usize, width: usize, channels: usize, halo: usize) -> Self {
        Plane {
            height,
            width,
            channels,
            halo,
        }
    }

    /// Floats in the buffer, border included.
    #[allow(clippy::len_without_is_empty)] // a plane is never empty
    pub const fn len(&self) -> usize {
        (self.height + 2 * self.halo) * self.row_stride()
    }

    /// Floats from one stored row to the next.
    pub const fn row_stride(&self) -> usize {
        (self.width + 2 * self.halo) * self.channels
    }

    /// Index of channel 0 of interior pixel (`y`, `x`).
    pub const fn index(&self, y: usize, x: usize) -> usize {
        (y + self.halo) * self.row_stride() + (x + self.halo) * self.channels
    }

    /// Floats in the interior (the image without its border).
    pub const fn interior_len(&self) -> usize {
        self.height * self.width * self.channels
    }

    /// Copies an unpadded HWC image into the interior of `buf`.
    pub fn write_interior(&self, buf: &mut [f32], image: &[f32]) {
        assert_eq!(image.len(), self.interior_len());
        assert_eq!(buf.len(), self.len());
        let row = self.width * self.channels;
        for (y, src) in image.chunks_exact(row.max(1)).enumerate() {
            let start = self.index(y, 0);
            buf[start..start + row].copy_from_slice(src);
        }
    }
}

/// Which of the model's two convolutions: both have stride 2 and padding `kernel / 2`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvKind {
    /// `Conv2d(stride 2)`: output is half the input size.
    Down,
    /// `ConvTranspose2d(stride 2, output_padding 1)`: output is twice the input size.
    /// Computed by gathering the taps that reach each output pixel, so the zeros a naive
    /// implementation inserts between input pixels are never multiplied.
    Up,
}

impl ConvKind {
    /// The input coordinate that kernel tap `tap` of output coordinate `out` reads, or `None`
    /// when it falls outside an input of length `len` (padding, or the wrong stride phase).
    #[inline]
    pub fn source(self, out: usize, tap: usize, pad: usize, len: usize) -> Option<usize> {
        let i = match self {
            ConvKind::Down => (2 * out + tap).checked_sub(pad)?,
            // out = 2 * i - pad + tap
            ConvKind::Up => {
                let twice = (out + pad).checked_sub(tap)?;
                if twice % 2 != 0 {
                    return None;
                }
                twice / 2
            }
        };
        (i < len).then_some(i)
    }

    /// The border an input plane needs so that every tap a kernel reads lies in the buffer.
    pub const fn input_halo(self, kernel: usize) -> usize {
        match self {
            ConvKind::Down => kernel / 2,
            ConvKind::Up => (kernel / 2).div_ceil(2),
        }
    }
}

/// One convolution layer: square odd `kernel`, stride 2, padding `kernel / 2`.
///
/// Weights are packed by [`pack::conv_weights`] in panels of [`OC_ALIGN`] output channels:
/// `[out_channel / 16][ky][kx][in_channel][out_channel % 16]`, the last panel zero-padded, or
/// for at most [`NARROW_OC`] output channels as `[out_channel][ky][kx][in_channel]` (see
/// [`ConvShape::packed_index`]); `bias` has `output.channels` values.
///
/// [`pack::conv_weights`]: crate::pack::conv_weights
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvShape {
    /// Strided or transposed.
    pub kind: ConvKind,
    /// Taps per side of the square kernel (odd).
    pub kernel: usize,
    /// The plane read.
    pub input: Plane,
    /// The plane written.
    pub output: Plane,
}

impl ConvShape {
    /// A layer from `input` to an output plane with `out_channels` and border `out_halo`.
    pub const fn new(kind: ConvKind, kernel: usize, input: Plane, out_channels: usize, out_halo: usize) -> Self {
        let (height, width) = match kind {
            ConvKind::Down => (input.height / 2, input.width / 2),
            ConvKind::Up => (input.height * 2, input.width * 2),
        };
        ConvShape {
            kind,
            kernel,
            input,
            output: Plane::new(height, width, out_channels, out_halo),
        }
    }

    /// The layer whose forward pass is this one's gradient with respect to its input: the
    /// other kind, from a plane shaped as this one's output (with at least the border the other
    /// kind reads) to a plane shaped as this one's input. The gradient of a strided convolution
    /// is the transposed convolution with the same PyTorch weights, and the converse: packing
    /// this layer's PyTorch weight tensor for the transposed shape
    /// ([`crate::pack::conv_weights_into`]) reads `[out, in, k, k]` as `[in, out, k, k]`,
    /// which is exactly the swap of roles. Its bias is zero and its activation the identity.
    pub const fn transposed(&self) -> ConvShape {
        let kind = match self.kind {
            ConvKind::Down => ConvKind::Up,
            ConvKind::Up => ConvKind::Down,
        };
        let o = self.output;
        let needed = kind.input_halo(self.kernel);
        let halo = if o.halo > needed { o.halo } else { needed };
        ConvShape {
            kind,
            kernel: self.kernel,
            input: Plane::new(o.height, o.width, o.channels, halo),
            output: self.input,
        }
    }

    /// The strided form of this layer: itself, or a transposed layer's [`Self::transposed`],
    /// whose weight gradient (`out x (k·k·in)`) is the layer's.
    pub const fn strided(&self) -> ConvShape {
        match self.kind {
            ConvKind::Down => *self,
            ConvKind::Up => self.transposed(),
        }
    }

    /// Stride between the weight vectors of consecutive input channels.
    pub const fn oc_stride(&self) -> usize {
        self.output.channels.div_ceil(OC_ALIGN) * OC_ALIGN
    }

    /// Whether the weights use the narrow layout (at most [`NARROW_OC`] output channels).
    pub const fn is_narrow(&self) -> bool {
        self.output.channels <= NARROW_OC
    }

    /// Floats in the packed weights.
    pub const fn packed_len(&self) -> usize {
        let per_output = self.kernel * self.kernel * self.input.channels;
        per_output
            * if self.is_narrow() {
                self.output.channels
            } else {
                self.oc_stride()
            }
    }

    /// Floats in one panel of [`OC_ALIGN`] output channels of the packed weights.
    pub const fn panel_len(&self) -> usize {
        self.kernel * self.kernel * self.input.channels * OC_ALIGN
    }

    /// Where the weight of tap `(ky, kx)` from input channel `ic` to output channel `oc` is
    /// packed. In panels, consecutive input channels of one tap are `OC_ALIGN` floats apart; in
    /// the narrow layout they are adjacent.
    pub const fn packed_index(&self, ky: usize, kx: usize, ic: usize, oc: usize) -> usize {
        let row = (ky * self.kernel + kx) * self.input.channels + ic;
        if self.is_narrow() {
            oc * self.kernel * self.kernel * self.input.channels + row
        } else {
            (oc / OC_ALIGN) * self.panel_len() + row * OC_ALIGN + oc % OC_ALIGN
        }
    }

    /// Multiply-adds per image, counting only taps that land inside the input.
    pub fn macs(&self) -> u64 {
        let k = self.kernel;
        let taps = |out_len: usize, in_len: usize| -> u64 {
            (0..out_len)
                .map(|o| {
                    (0..k)
                        .filter(|&t| self.kind.source(o, t, k / 2, in_len).is_some())
                        .count() as u64
                })
                .sum()
        };
        taps(self.output.height, self.input.height)
            * taps(self.output.width, self.input.width)
            * (self.input.channels * self.output.channels) as u64
    }

    /// A range of output channels a call may compute: starting on a panel, inside the layer.
    pub(crate) fn check_channels(&self, channels: &core::ops::Range<usize>) {
        assert!(
            channels.start.is_multiple_of(OC_ALIGN)
                && channels.start <= channels.end
                && channels.end <= self.output.channels
        );
    }

    pub(crate) fn check(&self, input: &[f32], weights: &[f32], bias: &[f32]) {
        assert!(self.kernel % 2 == 1, "odd kernels only");
        assert!(
            self.input.halo >= self.kind.input_halo(self.kernel),
            "input border too small"
        );
        let expected = ConvShape::new(
            self.kind,
            self.kernel,
            self.input,
            self.output.channels,
            self.output.halo,
        );
        assert_eq!(*self, expected, "output plane does not match the input plane");
        assert_eq!(input.len(), self.input.len());
        assert_eq!(weights.len(), self.packed_len());
        assert_eq!(bias.len(), self.output.channels);
    }
}

/// Weights stored in f32 or f16: the one weight-dtype type, borrowed ([`MatrixData`]: the
/// values of a packed matrix) or owned ([`Tensor`]: as loaded). BF16 files load as f32.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Weights<F32, F16> {
    /// Single precision.
    F32(F32),
    /// Kept in half precision and widened inside the kernel: half the memory traffic.
    F16(F16),
}

/// The stored values of a packed weight matrix (see [`Matrix`]).
pub type MatrixData<'a> = Weights<&'a [f32], &'a [f16]>;

/// Weights as loaded or packed, owned.
pub type Tensor = Weights<Vec<f32>, Vec<f16>>;

impl Tensor {
    /// The values as f32 (f16 ones widened exactly).
    pub fn into_f32(self) -> Vec<f32> {
        match self {
            Weights::F32(v) => v,
            Weights::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        }
    }

    /// The same function of both dtypes' values, keeping the dtype (packing, permuting).
    pub fn map(&self, f32s: impl FnOnce(&[f32]) -> Vec<f32>, f16s: impl FnOnce(&[f16]) -> Vec<f16>) -> Tensor {
        match self {
            Weights::F32(v) => Weights::F32(f32s(v)),
            Weights::F16(v) => Weights::F16(f16s(v)),
        }
    }

    /// Borrowed.
    pub fn as_data(&self) -> MatrixData<'_> {
        match self {
            Weights::F32(v) => Weights::F32(v),
            Weights::F16(v) => Weights::F16(v),
        }
    }
}

/// A `rows x cols` matrix for `y = W x`, packed by [`pack::dense_weights`] in panels of
/// [`OC_ALIGN`] rows stored column by column: `[row / 16][col][row % 16]`, the last panel
/// zero-padded (see [`Matrix::packed_index`]). One column of a panel is then one or two whole
/// vectors of weights, one per output row, and each panel streams through contiguous memory.
///
/// [`pack::dense_weights`]: crate::pack::dense_weights
#[derive(Clone, Copy, Debug)]
pub struct Matrix<'a> {
    /// The packed values.
    pub data: MatrixData<'a>,
    /// Outputs.
    pub rows: usize,
    /// Inputs.
    pub cols: usize,
}

impl<'a> Matrix<'a> {
    /// Values stored for a `rows x cols` matrix: whole panels.
    pub const fn packed_len(rows: usize, cols: usize) -> usize {
        rows.div_ceil(OC_ALIGN) * OC_ALIGN * cols
    }

    /// Where weight `(row, col)` of a matrix with `cols` columns is stored.
    pub const fn packed_index(row: usize, col: usize, cols: usize) -> usize {
        (row / OC_ALIGN * cols + col) * OC_ALIGN + row % OC_ALIGN
    }

    /// Rows `rows` of this matrix; `rows.start` must be a multiple of [`OC_ALIGN`] (a panel).
    pub fn row_range(&self, rows: core::ops::Range<usize>) -> Matrix<'a> {
        assert!(rows.start.is_multiple_of(OC_ALIGN), "row range does not start a panel");
        let start = rows.start * self.cols;
        let span = start..start + Self::packed_len(rows.len(), self.cols);
        let data = match self.data {
            MatrixData::F32(d) => MatrixData::F32(&d[span]),
            MatrixData::F16(d) => MatrixData::F16(&d[span]),
        };
        Matrix {
            data,
            rows: rows.len(),
            cols: self.cols,
        }
    }

    pub(crate) fn check_packed(&self) {
        let stored = match self.data {
            MatrixData::F32(d) => d.len(),
            MatrixData::F16(d) => d.len(),
        };
        assert_eq!(
            stored,
            Self::packed_len(self.rows, self.cols),
            "matrix is not packed whole"
        );
    }
}

/// A convolution layer as the kernels take it: its shape, packed weights (see [`ConvShape`]),
/// bias and the activation fused into the store.
#[derive(Clone, Copy, Debug)]
pub struct ConvParams<'a> {
    /// The layer's planes and kernel.
    pub shape: ConvShape,
    /// Packed by [`crate::pack::conv_weights`] (or [`crate::pack::winograd_weights`]).
    pub weights: &'a [f32],
    /// One per output channel.
    pub bias: &'a [f32],
    /// Applied before the store.
    pub act: Activation,
}
