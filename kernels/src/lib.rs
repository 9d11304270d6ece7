//! The numeric kernels of drivesim.
//!
//! This crate is the contract between the networks and the arithmetic. It defines
//! - the data layouts the kernels read and write ([`Plane`], [`ConvShape`], [`Matrix`]),
//! - one entry point per operation ([`conv`], [`dense`], [`rnn_step`]) that dispatches on an
//!   [`Isa`] chosen once at run time, plus [`conv_channels`] and [`dense_rows`], which compute
//!   part of the output so that threads can share one call,
//! - a second algorithm for the convolutions, Winograd's minimal filtering ([`winograd`]:
//!   [`winograd_conv`], or [`winograd_input`] and [`winograd_channels`] for threads), with its
//!   own weight layout and caller-provided scratch; its scalar path is tested against the
//!   direct scalar convolution,
//! - the scalar reference of every operation ([`scalar`]), which is the test oracle for the
//!   SIMD versions (AVX2 and AVX-512 on x86-64, NEON on aarch64: one generic body per
//!   operation, instantiated per instruction set) and the fallback on every other target,
//! - weight packing done once at load ([`pack`]).
//!
//! Nothing here allocates except the packing functions; the kernels write into caller buffers.
//! Shapes are the caller's responsibility: a kernel panics on inconsistent lengths, since the
//! model validates every shape before it ever calls one.
#![cfg_attr(not(feature = "std"), no_std)]

extern crate alloc;

mod isa;
pub mod math;
pub mod pack;
pub mod scalar;
mod simd;
pub mod winograd;

pub use half::f16;
pub use isa::{Isa, IsaLevel};
pub use winograd::Winograd;

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
    pub height: usize,
    pub width: usize,
    pub channels: usize,
    pub halo: usize,
}

impl Plane {
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
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvShape {
    pub kind: ConvKind,
    pub kernel: usize,
    pub input: Plane,
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
    fn check_channels(&self, channels: &core::ops::Range<usize>) {
        assert!(
            channels.start.is_multiple_of(OC_ALIGN)
                && channels.start <= channels.end
                && channels.end <= self.output.channels
        );
    }

    fn check(&self, input: &[f32], weights: &[f32], bias: &[f32]) {
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

/// The nonlinearity applied to a kernel's output before it is stored.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Activation {
    Identity,
    Relu,
    /// `max(x, slope * x)` for `0 < slope < 1`.
    LeakyRelu(f32),
    Tanh,
}

impl Activation {
    #[inline]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Activation::Identity => x,
            Activation::Relu => x.max(0.0),
            Activation::LeakyRelu(slope) => x.max(slope * x),
            Activation::Tanh => math::tanh(x),
        }
    }
}

/// The stored values of a packed weight matrix (see [`Matrix`]).
#[derive(Clone, Copy, Debug)]
pub enum MatrixData<'a> {
    F32(&'a [f32]),
    /// Kept in half precision and widened inside the kernel: half the memory traffic.
    F16(&'a [f16]),
}

/// A `rows x cols` matrix for `y = W x`, packed by [`pack::dense_weights`] in panels of
/// [`OC_ALIGN`] rows stored column by column: `[row / 16][col][row % 16]`, the last panel
/// zero-padded (see [`Matrix::packed_index`]). One column of a panel is then one or two whole
/// vectors of weights, one per output row, and each panel streams through contiguous memory.
#[derive(Clone, Copy, Debug)]
pub struct Matrix<'a> {
    pub data: MatrixData<'a>,
    pub rows: usize,
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

    fn check_packed(&self) {
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

    fn check(&self, bias: &[f32], x: &[f32], y: &[f32]) -> usize {
        self.check_packed();
        assert_eq!(bias.len(), self.rows);
        assert!(
            self.cols > 0 && x.len().is_multiple_of(self.cols),
            "input is not whole rows"
        );
        let batch = x.len() / self.cols;
        assert_eq!(y.len(), batch * self.rows);
        batch
    }
}

/// A convolution layer as the kernels take it: its shape, packed weights (see [`ConvShape`]),
/// bias and the activation fused into the store.
#[derive(Clone, Copy, Debug)]
pub struct ConvParams<'a> {
    pub shape: ConvShape,
    pub weights: &'a [f32],
    pub bias: &'a [f32],
    pub act: Activation,
}

/// `output = act(conv(input) + bias)` for one image: see [`ConvShape`] for the layouts.
/// Only the interior of `output` is written; its border stays as it was (zero).
pub fn conv(isa: Isa, layer: ConvParams<'_>, input: &[f32], output: &mut [f32]) {
    assert_eq!(output.len(), layer.shape.output.len());
    let all = 0..layer.shape.output.channels;
    // SAFETY: `output` holds the whole output plane and is borrowed mutably for the call.
    unsafe { conv_channels(isa, layer, input, output.as_mut_ptr(), all) }
}

/// [`conv`] for the output channels `channels` only, written through a pointer so that
/// threads can fill disjoint channel ranges of one output plane at once. `channels.start` must
/// be a multiple of [`OC_ALIGN`]: each thread then reads only its own panels of weights.
///
/// # Safety
/// `output` must point to `shape.output.len()` floats, valid for writes, and no other thread
/// may read or write channels `channels` of its interior during the call.
pub unsafe fn conv_channels(
    isa: Isa,
    layer: ConvParams<'_>,
    input: &[f32],
    output: *mut f32,
    channels: core::ops::Range<usize>,
) {
    layer.shape.check(input, layer.weights, layer.bias);
    layer.shape.check_channels(&channels);
    match isa.level() {
        IsaLevel::Scalar => scalar::conv_channels(layer, input, output, channels),
        level => simd::conv(level, layer, input, output, channels),
    }
}

/// Step 1 of a Winograd convolution (see [`winograd`]): writes the transformed input of stride
/// phase `phase` (0 to 3) to `v`, the span [`Winograd::phase_span`] of the whole transformed
/// input. Threads may fill different phases at once.
pub fn winograd_input(isa: Isa, w: &Winograd, phase: usize, input: &[f32], v: &mut [f32]) {
    assert!(phase < 4);
    assert_eq!(input.len(), w.shape.input.len());
    assert_eq!(v.len(), w.phase_span(phase).len());
    match isa.level() {
        IsaLevel::Scalar => scalar::winograd_input(w, phase, input, v),
        // SAFETY: `level` comes from an `Isa`; the lengths are checked above.
        level => unsafe { simd::winograd::input(level, w, phase, input, v) },
    }
}

/// Steps 2 and 3 of a Winograd convolution (see [`winograd`]) for the output channels
/// `channels`: `output = act(conv(input) + bias)` from the transformed input `v` (all four
/// phases) and weights packed by [`pack::winograd_weights`] for the same `w`, using `scratch`
/// ([`winograd::SCRATCH_LEN`] floats, one per thread). `channels.start` must be a multiple of
/// [`OC_ALIGN`]. Only those channels of the output's interior are written.
///
/// # Safety
/// As for [`conv_channels`].
pub unsafe fn winograd_channels(
    isa: Isa,
    w: &Winograd,
    layer: ConvParams<'_>,
    v: &[f32],
    scratch: &mut [f32],
    output: *mut f32,
    channels: core::ops::Range<usize>,
) {
    assert_eq!(w.shape, layer.shape);
    assert_eq!(layer.weights.len(), w.packed_len());
    assert_eq!(layer.bias.len(), layer.shape.output.channels);
    assert_eq!(v.len(), w.input_len());
    assert!(scratch.len() >= winograd::SCRATCH_LEN);
    layer.shape.check_channels(&channels);
    match isa.level() {
        IsaLevel::Scalar => scalar::winograd_channels(w, layer, v, scratch, output, channels),
        level => simd::winograd::channels(level, w, layer, v, scratch, output, channels),
    }
}

/// A whole Winograd convolution on one thread: [`winograd_input`] for every phase into `v`
/// ([`Winograd::input_len`] floats), then [`winograd_channels`] for every channel.
pub fn winograd_conv(
    isa: Isa,
    w: &Winograd,
    layer: ConvParams<'_>,
    input: &[f32],
    v: &mut [f32],
    scratch: &mut [f32],
    output: &mut [f32],
) {
    assert_eq!(output.len(), layer.shape.output.len());
    assert_eq!(v.len(), w.input_len());
    for phase in 0..4 {
        winograd_input(isa, w, phase, input, &mut v[w.phase_span(phase)]);
    }
    let all = 0..layer.shape.output.channels;
    // SAFETY: `output` holds the whole output plane and is borrowed mutably for the call.
    unsafe { winograd_channels(isa, w, layer, v, scratch, output.as_mut_ptr(), all) }
}

/// `y[n] = act(W x[n] + bias)` for a batch of `x.len() / W.cols` inputs stored one after another.
pub fn dense(isa: Isa, w: Matrix<'_>, bias: &[f32], act: Activation, x: &[f32], y: &mut [f32]) {
    w.check(bias, x, y);
    // SAFETY: `y` holds every row of every item and is borrowed mutably for the call.
    unsafe { dense_rows(isa, w, bias, act, x, y.as_mut_ptr(), 0..w.rows) }
}

/// [`dense`] for the rows `rows` only (`y[n * W.rows + r]` for `r` in `rows`), written through
/// a pointer so that threads can fill disjoint row ranges of one batch's output at once (each
/// reading only its rows of the weights). `rows.start` must be a multiple of [`OC_ALIGN`].
///
/// # Safety
/// `y` must point to `batch * W.rows` floats valid for writes, and no other thread may read or
/// write rows `rows` of any item during the call.
pub unsafe fn dense_rows(
    isa: Isa,
    w: Matrix<'_>,
    bias: &[f32],
    act: Activation,
    x: &[f32],
    y: *mut f32,
    rows: core::ops::Range<usize>,
) {
    assert!(rows.start <= rows.end && rows.end <= w.rows && bias.len() == w.rows);
    w.check_packed();
    let (ldy, part) = (w.rows, w.row_range(rows.clone()));
    let (bias, y) = (&bias[rows.clone()], y.add(rows.start));
    let batch = x.len() / w.cols;
    assert!(w.cols > 0 && batch * w.cols == x.len(), "input is not whole rows");
    match isa.level() {
        IsaLevel::Scalar => scalar::dense_rows(part, bias, act, x, y, ldy),
        level => simd::dense(level, part, bias, act, x, y, ldy),
    }
}

/// The weights of the action-conditioned tanh RNN:
/// `h' = tanh(W h + V z + U c + b)`, `z' = A h' + a`.
///
/// `W`, `V` and `U` are stored side by side as one `hidden x (hidden + z + action)` matrix so that
/// one pass over memory computes all three products.
///
/// A step whose code is the one `h` itself predicted (`z = A h + a`: every step of a rollout
/// after its seeds) needs no `V`: `h' = tanh((W + V A) h + U c + (b + V a))`. For such steps
/// `input` is `[W + V A | U]`, `hidden x (hidden + action)`, with bias `b + V a`, and the step
/// is given no `z`: a third fewer weights to read per step.
#[derive(Clone, Copy, Debug)]
pub struct Rnn<'a> {
    /// `[W | V | U]`, `hidden x (hidden + z + action)`, or `[W + V A | U]`,
    /// `hidden x (hidden + action)`.
    pub input: Matrix<'a>,
    /// `b`, or `b + V a`; `hidden`.
    pub input_bias: &'a [f32],
    /// `A`, `z x hidden`.
    pub output: Matrix<'a>,
    /// `a`, `z`.
    pub output_bias: &'a [f32],
}

impl Rnn<'_> {
    pub fn hidden(&self) -> usize {
        self.input.rows
    }
    pub fn z_dim(&self) -> usize {
        self.output.rows
    }

    /// Writes each batch element's `[h | z | action]` (or `[h | action]` without `z`) to
    /// `concat`, the input of `input`: the first half of [`rnn_step`], for callers that run its
    /// two products themselves (split between threads).
    pub fn gather(&self, concat: &mut [f32], h: &[f32], z: Option<&[f32]>, action: &[f32]) {
        let hd = self.hidden();
        let zd = z.map_or(0, |_| self.z_dim());
        assert!(hd > 0 && h.len().is_multiple_of(hd) && self.input.cols >= hd + zd);
        let batch = h.len() / hd;
        let ad = self.input.cols - hd - zd;
        assert_eq!(z.map_or(0, <[f32]>::len), batch * zd);
        assert_eq!(action.len(), batch * ad);
        assert_eq!(concat.len(), batch * self.input.cols);
        for (n, row) in concat.chunks_exact_mut(self.input.cols).enumerate() {
            row[..hd].copy_from_slice(&h[n * hd..][..hd]);
            if let Some(z) = z {
                row[hd..hd + zd].copy_from_slice(&z[n * zd..][..zd]);
            }
            row[hd + zd..].copy_from_slice(&action[n * ad..][..ad]);
        }
    }
}

/// One RNN step for a batch: updates `h` in place and writes `z_next`. `z` is the input code,
/// or `None` for the fed-back form of [`Rnn`]. `concat` is scratch of `batch * input.cols`
/// floats.
pub fn rnn_step(
    isa: Isa,
    rnn: &Rnn<'_>,
    concat: &mut [f32],
    h: &mut [f32],
    z: Option<&[f32]>,
    action: &[f32],
    z_next: &mut [f32],
) {
    rnn.gather(concat, h, z, action);
    dense(isa, rnn.input, rnn.input_bias, Activation::Tanh, concat, h);
    dense(isa, rnn.output, rnn.output_bias, Activation::Identity, h, z_next);
}
