//! The layers: a convolution's weights packed for the forward kernels ([`Packed`]), a
//! convolution with its BatchNorm and activation ([`Conv`]), and a dense layer in the kernels'
//! packed layout ([`Dense`]) with its forward product and gradients.

use super::budget::{Budget, Sizes};
use super::table::{Norm, Table};
use crate::layers::dense;
use crate::pool::{Exec, Parts};
use crate::weights::Init;
use crate::Result;
use alloc::format;
use alloc::vec::Vec;
use core::ops::Range;
use drivesim_kernels::pack::conv_weights_from_matrix;
use drivesim_kernels::{
    conv, conv_weight_grad_scratch_len, dense_data_grad_cols, dense_weight_grad_add_rows, winograd_conv,
    winograd_weights, Activation, ConvKind, ConvParams, ConvShape, Isa, Matrix, MatrixData, OutputParts, Winograd,
};

/// Convolution weights packed for one shape: direct, and for Winograd where it takes the shape.
pub(super) struct Packed {
    shape: ConvShape,
    winograd: Option<Winograd>,
    direct: Vec<f32>,
    transformed: Vec<f32>,
}

/// Winograd's transformed input and product scratch, shared by every layer.
pub(super) struct Scratch {
    pub(super) v: Vec<f32>,
    pub(super) products: Vec<f32>,
}

impl Packed {
    fn new(budget: &mut Budget, shape: ConvShape, sizes: &mut Sizes) -> Result<Packed> {
        let winograd = Winograd::new(shape);
        if let Some(w) = &winograd {
            sizes.winograd_v = sizes.winograd_v.max(w.input_len());
            sizes.winograd_products = sizes.winograd_products.max(w.scratch_len());
        }
        Ok(Packed {
            shape,
            winograd,
            direct: budget.take("packed weights", shape.packed_len())?,
            transformed: budget.take("packed weights", winograd.map_or(0, |w| w.packed_len()))?,
        })
    }

    /// Packs the layer's weights, kept as [`Table::conv`] keeps them (for its transposed shape
    /// too).
    pub(super) fn pack(&mut self, isa: Isa, matrix: &[f32]) {
        conv_weights_from_matrix(&self.shape, matrix, &mut self.direct);
        if let Some(w) = &self.winograd {
            winograd_weights(isa, w, &self.direct, &mut self.transformed);
        }
    }

    /// [`Packed::run`] for each item of a batch of planes; threads take whole items, each with
    /// a scratch of its own.
    pub(super) fn run_items(
        &self,
        exec: Exec<'_>,
        bias: &[f32],
        act: Activation,
        input: &[f32],
        output: &mut [f32],
        scratch: &mut [Scratch],
    ) {
        let (il, ol) = (self.shape.input.len(), self.shape.output.len());
        let items = Parts::chunks(output, ol);
        let scratch = Parts::chunks(scratch, 1);
        exec.run(&|| {
            let (_, s) = scratch.take().expect("a scratch for every thread");
            while let Some((n, out)) = items.take() {
                self.run(exec.isa, bias, act, &input[n * il..][..il], out, &mut s[0]);
            }
        });
    }

    /// `output = act(conv(input) + bias)` for one plane.
    fn run(&self, isa: Isa, bias: &[f32], act: Activation, input: &[f32], output: &mut [f32], s: &mut Scratch) {
        let layer = ConvParams {
            shape: self.shape,
            weights: &self.direct,
            bias,
            act,
        };
        match &self.winograd {
            None => conv(isa, layer, input, output),
            Some(w) => {
                let layer = ConvParams {
                    weights: &self.transformed,
                    ..layer
                };
                let (v, products) = (&mut s.v[..w.input_len()], &mut s.products[..w.scratch_len()]);
                winograd_conv(isa, w, layer, input, v, products, output)
            }
        }
    }
}

/// A convolution, optionally followed by BatchNorm, then an activation.
pub(super) struct Conv {
    pub(super) shape: ConvShape,
    pub(super) weight: Range<usize>,
    pub(super) bias: Range<usize>,
    pub(super) norm: Option<Norm>,
    pub(super) act: Activation,
    pub(super) forward: Packed,
    /// Packed for [`ConvShape::transposed`]: the data gradient.
    pub(super) backward: Packed,
}

impl Conv {
    pub(super) fn new(
        t: &mut Table,
        budget: &mut Budget,
        sizes: &mut Sizes,
        name: &str,
        norm: Option<&str>,
        shape: ConvShape,
        act: Activation,
    ) -> Result<Conv> {
        let (k, ic, oc) = (shape.kernel, shape.input.channels, shape.output.channels);
        let fan_in = match shape.kind {
            ConvKind::Down => ic * k * k,
            ConvKind::Up => oc * k * k,
        };
        sizes.weight_scratch = sizes.weight_scratch.max(conv_weight_grad_scratch_len(&shape.strided()));
        sizes.channels = sizes.channels.max(oc).max(ic);
        Ok(Conv {
            shape,
            weight: t.conv(format!("{name}.weight"), shape, Init::FanIn(fan_in)),
            bias: t.param(format!("{name}.bias"), &[oc], Init::FanIn(fan_in)),
            norm: norm.map(|n| t.norm(n, oc)),
            act,
            forward: Packed::new(budget, shape, sizes)?,
            backward: Packed::new(budget, shape.transposed(), sizes)?,
        })
    }
}

impl Conv {
    /// The strided shape whose weight gradient is this layer's: its own, or a transposed
    /// layer's [`ConvShape::transposed`] (its rows the layer's input channels).
    pub(super) fn grad_shape(&self) -> ConvShape {
        match self.shape.kind {
            ConvKind::Down => self.shape,
            ConvKind::Up => self.shape.transposed(),
        }
    }
}

/// How a dense layer's PyTorch rows or columns map to the kernels' order: a flattened feature
/// map is CHW in PyTorch and HWC in a plane.
#[derive(Clone, Copy)]
pub(super) enum Order {
    /// The columns are a flattened `(channels, height, width)` map.
    Columns(usize, usize, usize),
    /// The rows are.
    Rows(usize, usize, usize),
}

impl Order {
    /// Calls `f(r, c, t)` for every weight of a `rows x cols` layer: its row and column in the
    /// kernels' order and its index in PyTorch's row-major tensor, counted up without division
    /// (this runs over every weight after every update).
    pub(super) fn for_each(self, rows: usize, cols: usize, mut f: impl FnMut(usize, usize, usize)) {
        match self {
            Order::Columns(ch, h, w) => {
                for r in 0..rows {
                    for c in 0..ch {
                        for p in 0..h * w {
                            f(r, p * ch + c, r * cols + c * h * w + p);
                        }
                    }
                }
            }
            Order::Rows(ch, h, w) => {
                for c in 0..ch {
                    for p in 0..h * w {
                        let (r, tr) = (p * ch + c, c * h * w + p);
                        for col in 0..cols {
                            f(r, col, tr * cols + col);
                        }
                    }
                }
            }
        }
    }

    /// PyTorch's row of the kernels' row `r` (for the bias).
    fn torch_row(self, r: usize) -> usize {
        match self {
            Order::Columns(..) => r,
            Order::Rows(ch, h, w) => (r % ch) * h * w + r / ch,
        }
    }
}

/// `y = W x + b` with PyTorch weights `rows x cols`.
pub(super) struct Dense {
    pub(super) rows: usize,
    pub(super) cols: usize,
    /// The packed matrix in the parameters (see [`Table::packed`]).
    weight: Range<usize>,
    bias: Range<usize>,
    pub(super) order: Order,
    /// The bias in the kernels' row order.
    bias_rows: Vec<f32>,
}

impl Dense {
    /// A layer over the tensors `weight` and `bias` already in the table.
    pub(super) fn new(
        budget: &mut Budget,
        (weight, bias): (Range<usize>, Range<usize>),
        rows: usize,
        cols: usize,
        order: Order,
    ) -> Result<Dense> {
        Ok(Dense {
            rows,
            cols,
            weight,
            bias,
            order,
            bias_rows: budget.take("packed weights", rows)?,
        })
    }

    /// Puts the bias in the kernels' order (the weights are used as they are kept).
    pub(super) fn pack(&mut self, params: &[f32]) {
        let bias = &params[self.bias.clone()];
        for (r, b) in self.bias_rows.iter_mut().enumerate() {
            *b = bias[self.order.torch_row(r)];
        }
    }

    /// `y = W x + b` for a batch.
    pub(super) fn run(&self, exec: Exec<'_>, params: &[f32], x: &[f32], y: &mut [f32]) {
        let w = Matrix {
            data: MatrixData::F32(&params[self.weight.clone()]),
            rows: self.rows,
            cols: self.cols,
        };
        dense(exec, w, &self.bias_rows, Activation::Identity, x, y);
    }

    /// `dx = Wᵀ dy` for a batch.
    pub(super) fn data_grad(&self, exec: Exec<'_>, params: &[f32], dy: &[f32], dx: &mut [f32]) {
        let (w, rows, cols) = (&params[self.weight.clone()], self.rows, self.cols);
        let parts = OutputParts::new(dx, cols, exec.threads());
        exec.run(&|| {
            while let Some(part) = parts.take() {
                dense_data_grad_cols(exec.isa, w, rows, cols, dy, part);
            }
        });
    }

    /// Adds the weight and bias gradients of a batch (`dy` of the outputs, `x` the inputs) to
    /// `grads` (the weight's in the packed layout of the parameters, which the kernel adds to
    /// in place).
    pub(super) fn weight_grad(&self, exec: Exec<'_>, dy: &[f32], x: &[f32], grads: &mut [f32]) {
        let (rows, cols) = (self.rows, self.cols);
        let parts = OutputParts::new(&mut grads[self.weight.clone()], rows, exec.threads());
        exec.run(&|| {
            while let Some(part) = parts.take() {
                dense_weight_grad_add_rows(exec.isa, dy, x, rows, cols, part);
            }
        });
        let gb = &mut grads[self.bias.clone()];
        for dy in dy.chunks_exact(rows) {
            for (r, &d) in dy.iter().enumerate() {
                gb[self.order.torch_row(r)] += d;
            }
        }
    }
}

/// The scratch every layer's passes share.
pub(super) struct Work {
    /// One per thread.
    pub(super) scratch: Vec<Scratch>,
    pub(super) weight_scratch: Vec<f32>,
    /// The partial weight gradients of a layer's blocks of pixels
    /// ([`super::weight_grad::GradSplit`]).
    pub(super) partials: Vec<f32>,
    /// The gradients of a BatchNorm pass's scale and shift.
    pub(super) channel_tmp: Vec<f32>,
    /// Zeros: the bias of the data-gradient convolutions.
    pub(super) zero: Vec<f32>,
    /// BatchNorm's per-channel sums of each item of a pass, and of the pass.
    pub(super) item_sums: Vec<f64>,
    pub(super) sums: Vec<f64>,
}
