//! Training the encoder and generator as a VAE-GAN (Larsen et al.), exactly as
//! `weights/train.py`'s `vae_gan_step`: a discriminator (the encoder's mirror, a logit on top)
//! learns to tell real frames from reconstructions and prior samples; the encoder minimises a
//! KL prior plus the reconstruction error measured on the discriminator's third-convolution
//! features (relative to their spread) and in pixels; the generator minimises the same
//! reconstruction error and fools the discriminator. The GAN term never reaches the encoder, and
//! prior samples go through the generator's BatchNorm with batch statistics without moving its
//! running statistics. Adam with lr 2e-4 and betas 0.5 / 0.999 for each network.
//!
//! Every buffer is sized before anything is allocated: [`VaeGanPlan`] builds the trainer once
//! in a measuring mode (as ggml's allocator measures a graph), adding up what each buffer would
//! take; [`VaeGanTrainer::new`] then allocates exactly that. Convolutions keep their parameters,
//! gradients and Adam moments in PyTorch's layout and dense layers in the kernels' packed one
//! (the forward pass multiplies by them as they are); each network's packings (convolutions'
//! forward ones, and every layer's data gradient: the forward kernel of the transposed
//! convolution or dense layer) are rebuilt in place after each update. A step allocates
//! nothing.

// Passes are lists of item ranges, each a batch of its own for BatchNorm: often just one.
#![allow(clippy::single_range_in_vec_init)]

use super::adam::Adam;
use super::NamedTensor;
use crate::encoder::LEAKY_SLOPE;
use crate::error::{all_finite, expect_finite, expect_finite_output, expect_frames, expect_len};
use crate::layers::dense;
use crate::pool::{Exec, Parts, Pool};
use crate::weights::{Init, RandomSource, SafetensorsSource, TensorSource, WeightDtype, DISCRIMINATOR_PREFIX};
use crate::{Config, Error, Result};
use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;
use core::ops::Range;
use drivesim_kernels::norm::{
    gradient_moments, moments, normalize, normalize_gradient, parameter_gradients, statistics, sums_len,
    update_running_stats,
};
use drivesim_kernels::pack::{conv_matrix_from_torch, conv_matrix_len, conv_matrix_to_torch, conv_weights_from_matrix};
use drivesim_kernels::{
    activation_backward, conv, conv_weight_grad_add_rows, conv_weight_grad_scratch_len, dense_data_grad_cols,
    dense_weight_grad_add_rows, math, winograd_conv, winograd_weights, Activation, ConvKind, ConvParams, ConvShape,
    Isa, Matrix, MatrixData, OutputParts, Plane, Winograd,
};

/// The border of every plane of the training networks: strided convolutions read 2 pixels
/// beyond the image, transposed ones 1, and so do their gradients; one border for all keeps each
/// gradient plane in the layout of the activation it belongs to.
const HALO: usize = 2;

/// The learning rate of `weights/train.py fit`'s VAE-GAN.
pub const VAE_GAN_LR: f32 = 2e-4;

/// The loss weights and optimiser of the VAE-GAN (`weights/train.py fit`'s defaults).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VaeGanSettings {
    /// Weight of the KL prior in the encoder's loss.
    pub kl: f32,
    /// Weight of the discriminator-feature error (encoder and generator).
    pub feature: f32,
    /// Weight of the pixel L1 error (encoder and generator).
    pub pixel: f32,
    /// Weight of the non-saturating GAN term in the generator's loss.
    pub gan: f32,
    /// Adam's constants, shared by the three networks.
    pub adam: Adam,
}

impl Default for VaeGanSettings {
    fn default() -> Self {
        VaeGanSettings {
            kl: 1e-3,
            feature: 0.1,
            pixel: 1.0,
            gan: 0.01,
            adam: Adam {
                beta1: 0.5,
                beta2: 0.999,
                eps: 1e-8,
            },
        }
    }
}

impl VaeGanSettings {
    /// Every loss weight finite and at least zero, and Adam's constants valid.
    fn check(&self) -> Result<()> {
        let weights = [
            ("kl", self.kl),
            ("feature", self.feature),
            ("pixel", self.pixel),
            ("gan", self.gan),
        ];
        if let Some(&(name, value)) = weights.iter().find(|(_, w)| !(w.is_finite() && *w >= 0.0)) {
            return Err(Error::Setting {
                name,
                expected: "a finite number >= 0",
                value,
            });
        }
        self.adam.check()
    }
}

/// The losses of one step (each network's, and the terms they are made of).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct VaeGanLosses {
    /// The discriminator's: BCE on real frames plus BCE on reconstructions and prior samples.
    pub discriminator: f32,
    /// `kl · KL + feature · feature error + pixel · pixel L1`.
    pub encoder: f32,
    /// `feature · feature error + pixel · pixel L1 + gan · GAN`.
    pub generator: f32,
    /// The generator's non-saturating GAN term (BCE of fakes against "real").
    pub gan: f32,
    /// The squared error of the reconstructions' third-convolution features, over the variance
    /// of the real frames' features.
    pub feature: f32,
    /// The mean absolute error of the reconstructions, in [-1, 1] units.
    pub pixel_l1: f32,
    /// `KL(N(mu, sigma) || N(0, 1))`, mean over items and code dimensions.
    pub kl: f32,
}

/// Where the buffers' floats come from: counted only (planning) or allocated (the trainer).
struct Budget {
    allocate: bool,
    /// Floats per kind of buffer, in the order first met.
    floats: Vec<(&'static str, usize)>,
}

impl Budget {
    /// A buffer of `len` f64 zeros, counted as two floats each under `what`.
    fn take_f64(&mut self, what: &'static str, len: usize) -> Result<Vec<f64>> {
        self.count(what, mul(len, 2)?)?;
        zeros(self.allocate, len)
    }

    /// A buffer of `len` zeros, counted under `what` (empty when only measuring).
    fn take(&mut self, what: &'static str, len: usize) -> Result<Vec<f32>> {
        self.count(what, len)?;
        zeros(self.allocate, len)
    }

    /// Adds `len` floats to `what`'s count.
    fn count(&mut self, what: &'static str, len: usize) -> Result<()> {
        match self.floats.iter_mut().find(|(w, _)| *w == what) {
            Some((_, n)) => *n = n.checked_add(len).ok_or(OVERFLOW)?,
            None => self.floats.push((what, len)),
        }
        Ok(())
    }
}

/// `len` zeros if `allocate`, else nothing; an allocation refused is [`Error::OutOfMemory`].
fn zeros<T: Copy + Default>(allocate: bool, len: usize) -> Result<Vec<T>> {
    let mut v = Vec::new();
    if allocate {
        v.try_reserve_exact(len).map_err(|_| Error::OutOfMemory {
            what: WHAT,
            bytes: len.checked_mul(core::mem::size_of::<T>()),
        })?;
        v.resize(len, T::default());
    }
    Ok(v)
}

const WHAT: &str = "the VAE-GAN trainer's buffers";
const OVERFLOW: Error = Error::OutOfMemory {
    what: WHAT,
    bytes: None,
};

fn mul(a: usize, b: usize) -> Result<usize> {
    a.checked_mul(b).ok_or(OVERFLOW)
}

/// One tensor of the three networks: its name, PyTorch shape, place (in the parameters, or in
/// the running statistics) and initialisation where the file has none.
struct Entry {
    name: String,
    shape: Vec<usize>,
    at: Range<usize>,
    param: bool,
    init: Init,
    layout: Layout,
}

/// How a tensor is kept in the parameters.
#[derive(Clone, Copy)]
enum Layout {
    /// As PyTorch's.
    Torch,
    /// A dense layer's weights, packed: the layer (see [`Networks::dense`]) and the tensor's
    /// first row in it; `at` is then the whole layer's packed matrix.
    Dense(usize, usize),
    /// A convolution's weights, in the layout of their gradient for this shape (see
    /// [`conv_weights_from_matrix`]).
    Conv(ConvShape),
}

/// The tensors, laid out as they are declared.
#[derive(Default)]
struct Table {
    entries: Vec<Entry>,
    params: usize,
    stats: usize,
}

impl Table {
    fn add(&mut self, name: String, shape: &[usize], param: bool, init: Init) -> Range<usize> {
        let len: usize = shape.iter().product();
        let next = if param { &mut self.params } else { &mut self.stats };
        let at = *next..*next + len;
        *next += len;
        self.entries.push(Entry {
            name,
            shape: shape.to_vec(),
            at: at.clone(),
            param,
            init,
            layout: Layout::Torch,
        });
        at
    }

    /// A convolution's weights `[out, in, k, k]` (`[in, out, k, k]` if transposed), in the
    /// layout of their gradient: Adam updates them where the gradients add up.
    fn conv(&mut self, name: String, shape: ConvShape, init: Init) -> Range<usize> {
        let at = self.params..self.params + conv_matrix_len(&shape);
        self.params = at.end;
        let (k, ic, oc) = (shape.kernel, shape.input.channels, shape.output.channels);
        let torch = match shape.kind {
            ConvKind::Down => [oc, ic, k, k],
            ConvKind::Up => [ic, oc, k, k],
        };
        self.entries.push(Entry {
            name,
            shape: torch.to_vec(),
            at: at.clone(),
            param: true,
            init,
            layout: Layout::Conv(shape),
        });
        at
    }

    /// Dense layer `layer`'s weights: the packed matrix (see [`Matrix`]) of the PyTorch tensors
    /// `(name, rows)` stacked in order, each `rows x cols`. The optimiser updates them in place,
    /// so that the forward pass multiplies by them as they are.
    fn packed(&mut self, layer: usize, tensors: &[(&str, usize)], cols: usize, init: Init) -> Range<usize> {
        let rows = tensors.iter().map(|t| t.1).sum();
        let at = self.params..self.params + Matrix::packed_len(rows, cols);
        self.params = at.end;
        let mut first = 0;
        for &(name, n) in tensors {
            self.entries.push(Entry {
                name: name.into(),
                shape: alloc::vec![n, cols],
                at: at.clone(),
                param: true,
                init,
                layout: Layout::Dense(layer, first),
            });
            first += n;
        }
        at
    }

    fn param(&mut self, name: String, shape: &[usize], init: Init) -> Range<usize> {
        self.add(name, shape, true, init)
    }

    /// A BatchNorm layer's four tensors.
    fn norm(&mut self, name: &str, channels: usize) -> Norm {
        Norm {
            gamma: self.param(format!("{name}.weight"), &[channels], Init::Ones),
            beta: self.param(format!("{name}.bias"), &[channels], Init::Zeros),
            mean: self.add(format!("{name}.running_mean"), &[channels], false, Init::Zeros),
            var: self.add(format!("{name}.running_var"), &[channels], false, Init::Ones),
        }
    }
}

/// A BatchNorm layer's tensors: scale and shift in the parameters, running statistics in the
/// statistics.
#[derive(Clone)]
struct Norm {
    gamma: Range<usize>,
    beta: Range<usize>,
    mean: Range<usize>,
    var: Range<usize>,
}

/// Convolution weights packed for one shape: direct, and for Winograd where it takes the shape.
struct Packed {
    shape: ConvShape,
    winograd: Option<Winograd>,
    direct: Vec<f32>,
    transformed: Vec<f32>,
}

/// Winograd's transformed input and product scratch, shared by every layer.
struct Scratch {
    v: Vec<f32>,
    products: Vec<f32>,
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
    fn pack(&mut self, isa: Isa, matrix: &[f32]) {
        conv_weights_from_matrix(&self.shape, matrix, &mut self.direct);
        if let Some(w) = &self.winograd {
            winograd_weights(isa, w, &self.direct, &mut self.transformed);
        }
    }

    /// [`Packed::run`] for each item of a batch of planes; threads take whole items, each with
    /// a scratch of its own.
    fn run_items(
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
struct Conv {
    shape: ConvShape,
    weight: Range<usize>,
    bias: Range<usize>,
    norm: Option<Norm>,
    act: Activation,
    forward: Packed,
    /// Packed for [`ConvShape::transposed`]: the data gradient.
    backward: Packed,
}

impl Conv {
    fn new(
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

/// How a dense layer's PyTorch rows or columns map to the kernels' order: a flattened feature
/// map is CHW in PyTorch and HWC in a plane.
#[derive(Clone, Copy)]
enum Order {
    /// The columns are a flattened `(channels, height, width)` map.
    Columns(usize, usize, usize),
    /// The rows are.
    Rows(usize, usize, usize),
}

impl Order {
    /// Calls `f(r, c, t)` for every weight of a `rows x cols` layer: its row and column in the
    /// kernels' order and its index in PyTorch's row-major tensor, counted up without division
    /// (this runs over every weight after every update).
    fn for_each(self, rows: usize, cols: usize, mut f: impl FnMut(usize, usize, usize)) {
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
struct Dense {
    rows: usize,
    cols: usize,
    /// The packed matrix in the parameters (see [`Table::packed`]).
    weight: Range<usize>,
    bias: Range<usize>,
    order: Order,
    /// The bias in the kernels' row order.
    bias_rows: Vec<f32>,
}

impl Dense {
    /// A layer over the tensors `weight` and `bias` already in the table.
    fn new(
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
    fn pack(&mut self, params: &[f32]) {
        let bias = &params[self.bias.clone()];
        for (r, b) in self.bias_rows.iter_mut().enumerate() {
            *b = bias[self.order.torch_row(r)];
        }
    }

    /// `y = W x + b` for a batch.
    fn run(&self, exec: Exec<'_>, params: &[f32], x: &[f32], y: &mut [f32]) {
        let w = Matrix {
            data: MatrixData::F32(&params[self.weight.clone()]),
            rows: self.rows,
            cols: self.cols,
        };
        dense(exec, w, &self.bias_rows, Activation::Identity, x, y);
    }

    /// `dx = Wᵀ dy` for a batch.
    fn data_grad(&self, exec: Exec<'_>, params: &[f32], dy: &[f32], dx: &mut [f32]) {
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
    fn weight_grad(&self, exec: Exec<'_>, dy: &[f32], x: &[f32], grads: &mut [f32]) {
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

/// The largest scratch any layer needs.
#[derive(Default)]
struct Sizes {
    winograd_v: usize,
    winograd_products: usize,
    /// Per thread.
    weight_scratch: usize,
    channels: usize,
}

/// The activations of a stack of convolutions for a batch, saved for the backward pass, and
/// the BatchNorm statistics of each of its passes (batches normalised on their own).
struct Stack {
    /// Each layer's convolution output before BatchNorm (empty for layers without one).
    z: Vec<Vec<f32>>,
    /// Each layer's output.
    y: Vec<Vec<f32>>,
    /// Per layer, each pass's batch means and variances, `[pass][channel]`.
    mean: Vec<Vec<f32>>,
    var: Vec<Vec<f32>>,
}

/// The gradients of a stack's activations, one buffer per layer: of the layer's output, then in
/// place of its convolution's output (before BatchNorm and the activation).
struct StackGrads {
    g: Vec<Vec<f32>>,
}

const PASSES: usize = 2;

fn stack(budget: &mut Budget, layers: &[Conv], items: usize, what: &'static str) -> Result<Stack> {
    let (mut z, mut y, mut mean, mut var) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for l in layers {
        let len = mul(items, l.shape.output.len())?;
        let c = l.shape.output.channels;
        z.push(budget.take(what, if l.norm.is_some() { len } else { 0 })?);
        y.push(budget.take(what, len)?);
        mean.push(budget.take(what, PASSES * c)?);
        var.push(budget.take(what, PASSES * c)?);
    }
    Ok(Stack { z, y, mean, var })
}

fn stack_grads(budget: &mut Budget, layers: &[Conv], items: usize) -> Result<StackGrads> {
    let mut g = Vec::new();
    for l in layers {
        let len = mul(items, l.shape.output.len())?;
        g.push(budget.take("activation gradients", len)?);
    }
    Ok(StackGrads { g })
}

/// The planes of a strided stack from `input` through `channels`, each in a border of [`HALO`].
fn down_shapes(input: Plane, channels: [usize; 4], k: usize) -> [ConvShape; 4] {
    let mut plane = input;
    channels.map(|oc| {
        let shape = ConvShape::new(ConvKind::Down, k, plane, oc, HALO);
        plane = shape.output;
        shape
    })
}

/// The encoder's or the discriminator's convolutions on `shapes`: layer `i` named
/// `{conv}{i}`, BatchNorm `{norm}{i}` after all but the first, LeakyReLU after each.
fn strided(
    t: &mut Table,
    budget: &mut Budget,
    sizes: &mut Sizes,
    shapes: &[ConvShape],
    (conv, norm): (&str, &str),
) -> Result<Vec<Conv>> {
    let leaky = Activation::LeakyRelu(LEAKY_SLOPE);
    let layers = shapes.iter().enumerate().map(|(i, &shape)| {
        let norm = (i > 0).then(|| format!("{norm}{i}"));
        Conv::new(t, budget, sizes, &format!("{conv}{i}"), norm.as_deref(), shape, leaky)
    });
    layers.collect()
}

/// The three networks, their tensors and every buffer of a step.
struct Networks {
    table: Table,
    params: Vec<f32>,
    grads: Vec<f32>,
    moments: [Vec<f32>; 2],
    stats: Vec<f32>,
    /// The running statistics as the last update left them: a step whose gradients are not
    /// finite puts them back, so that its forward passes leave no trace.
    saved_stats: Vec<f32>,
    /// Where the discriminator's running statistics start (the encoder's and generator's come
    /// first).
    dis_stats: usize,
    /// Each network's span of the parameters (encoder, generator, discriminator).
    nets: [Range<usize>; 3],
    enc: [Conv; 4],
    heads: Dense,
    fc: Dense,
    top_norm: Norm,
    top: Plane,
    gen: [Conv; 4],
    dis: [Conv; 4],
    logit: Dense,
    buffers: Buffers,
}

/// The activations, their gradients and the scratch of a step, for up to `batch` frames.
struct Buffers {
    batch: usize,
    /// Real frames (planes of the first convolution's input).
    real: Vec<f32>,
    enc: Stack,
    enc_flat: Vec<f32>,
    /// `[mu | logsigma]` per item (logsigma after its tanh).
    heads: Vec<f32>,
    /// The generator's inputs: `mu + eps · sigma` for the batch, then the prior samples.
    codes: Vec<f32>,
    eps: Vec<f32>,
    fc_out: Vec<f32>,
    /// The generator's first feature map before and after BatchNorm0 + ReLU, and its stats.
    top_z: Vec<f32>,
    top_y: Vec<f32>,
    top_mean: Vec<f32>,
    top_var: Vec<f32>,
    gen: Stack,
    dis_real: Stack,
    dis_fake: Stack,
    flat_real: Vec<f32>,
    flat_fake: Vec<f32>,
    logits_real: Vec<f32>,
    logits_fake: Vec<f32>,
    enc_grads: StackGrads,
    gen_grads: StackGrads,
    dis_grads: StackGrads,
    /// The gradient of the generator's first feature map, then of the dense layer's output.
    top_g: Vec<f32>,
    /// Gradients of the discriminator's input, the feature error, dense outputs and inputs.
    dx: Vec<f32>,
    dfeature: Vec<f32>,
    dlogits: Vec<f32>,
    dflat: Vec<f32>,
    dheads: Vec<f32>,
    dcodes: Vec<f32>,
    work: Work,
}

/// The scratch every layer's passes share.
struct Work {
    /// One per thread.
    scratch: Vec<Scratch>,
    weight_scratch: Vec<f32>,
    /// The gradients of a BatchNorm pass's scale and shift.
    channel_tmp: Vec<f32>,
    /// Zeros: the bias of the data-gradient convolutions.
    zero: Vec<f32>,
    /// BatchNorm's per-channel sums of each item of a pass, and of the pass.
    item_sums: Vec<f64>,
    sums: Vec<f64>,
}

fn build(config: &Config, batch: usize, threads: usize, budget: &mut Budget) -> Result<Networks> {
    config.validate()?;
    if batch == 0 {
        return Err(Error::Config {
            field: "batch",
            expected: "at least 1 frame",
            found: 0,
        });
    }
    let c = config;
    let (k, b, z) = (c.kernel, c.base_channels, c.z_dim);
    let (flat, top_c, (top_h, top_w)) = (c.flat_len(), c.top_channels(), c.top_size());
    let mut t = Table::default();
    let mut sizes = Sizes::default();
    let image = Plane::new(c.height, c.width, c.channels, HALO);
    let down = down_shapes(image, [b, 2 * b, 4 * b, 8 * b], k);

    // Encoder: its dense heads are one layer of 2z rows, mean then logsigma (their tensors
    // side by side in the table).
    let enc = strided(&mut t, budget, &mut sizes, &down, ("encoder.conv", "encoder.bn"))?;
    let fan = Init::FanIn(flat);
    let heads_weight = t.packed(
        0,
        &[("encoder.mean.weight", z), ("encoder.logsigma.weight", z)],
        flat,
        fan,
    );
    let (mb, lb) = (
        t.param("encoder.mean.bias".into(), &[z], fan),
        t.param("encoder.logsigma.bias".into(), &[z], fan),
    );
    let heads = Dense::new(
        budget,
        (heads_weight, mb.start..lb.end),
        2 * z,
        flat,
        Order::Columns(top_c, top_h, top_w),
    )?;
    let enc_end = t.params;

    // Generator.
    let fc_tensors = (
        t.packed(1, &[("generator.fc.weight", flat)], z, Init::FanIn(z)),
        t.param("generator.fc.bias".into(), &[flat], Init::FanIn(z)),
    );
    let fc = Dense::new(budget, fc_tensors, flat, z, Order::Rows(top_c, top_h, top_w))?;
    let top_norm = t.norm("generator.bn0", top_c);
    let top = Plane::new(top_h, top_w, top_c, HALO);
    let mut gen = Vec::new();
    let mut plane = top;
    for i in 1..=4 {
        let last = i == 4;
        let oc = if last { c.channels } else { plane.channels / 2 };
        let shape = ConvShape::new(ConvKind::Up, k, plane, oc, HALO);
        let norm = (!last).then(|| format!("generator.bn{i}"));
        let act = if last { Activation::Tanh } else { Activation::Relu };
        let name = format!("generator.deconv{i}");
        gen.push(Conv::new(
            &mut t,
            budget,
            &mut sizes,
            &name,
            norm.as_deref(),
            shape,
            act,
        )?);
        plane = shape.output;
    }
    let gen_end = t.params;
    let dis_stats = t.stats;

    // Discriminator.
    let names = ("discriminator.convs.", "discriminator.bns.");
    let dis = strided(&mut t, budget, &mut sizes, &down, names)?;
    let logit_tensors = (
        t.packed(2, &[("discriminator.out.weight", 1)], flat, Init::FanIn(flat)),
        t.param("discriminator.out.bias".into(), &[1], Init::FanIn(flat)),
    );
    let logit = Dense::new(budget, logit_tensors, 1, flat, Order::Columns(top_c, top_h, top_w))?;
    let params = t.params;
    let [enc, gen, dis]: [[Conv; 4]; 3] = [enc, gen, dis].map(|v| v.try_into().ok().expect("four layers"));

    let pair = mul(2, batch)?;
    let act = "activations";
    let buffers = Buffers {
        batch,
        real: budget.take(act, mul(batch, image.len())?)?,
        enc: stack(budget, &enc, batch, act)?,
        enc_flat: budget.take(act, mul(batch, flat)?)?,
        heads: budget.take(act, mul(batch, 2 * z)?)?,
        codes: budget.take(act, mul(pair, z)?)?,
        eps: budget.take(act, mul(batch, z)?)?,
        fc_out: budget.take(act, mul(pair, flat)?)?,
        top_z: budget.take(act, mul(pair, top.len())?)?,
        top_y: budget.take(act, mul(pair, top.len())?)?,
        top_mean: budget.take(act, PASSES * top_c)?,
        top_var: budget.take(act, PASSES * top_c)?,
        gen: stack(budget, &gen, pair, act)?,
        dis_real: stack(budget, &dis, batch, act)?,
        dis_fake: stack(budget, &dis, pair, act)?,
        flat_real: budget.take(act, mul(batch, flat)?)?,
        flat_fake: budget.take(act, mul(pair, flat)?)?,
        logits_real: budget.take(act, batch)?,
        logits_fake: budget.take(act, pair)?,
        enc_grads: stack_grads(budget, &enc, batch)?,
        gen_grads: stack_grads(budget, &gen, pair)?,
        dis_grads: stack_grads(budget, &dis, pair)?,
        top_g: budget.take("activation gradients", mul(pair, top.len())?)?,
        dx: budget.take("activation gradients", mul(pair, image.len())?)?,
        dfeature: budget.take("activation gradients", mul(pair, down[2].output.len())?)?,
        dlogits: budget.take("activation gradients", pair)?,
        dflat: budget.take("activation gradients", mul(pair, flat)?)?,
        dheads: budget.take("activation gradients", mul(batch, 2 * z)?)?,
        dcodes: budget.take("activation gradients", mul(batch, z)?)?,
        work: Work {
            scratch: (0..threads)
                .map(|_| {
                    Ok(Scratch {
                        v: budget.take("scratch", sizes.winograd_v)?,
                        products: budget.take("scratch", sizes.winograd_products)?,
                    })
                })
                .collect::<Result<_>>()?,
            weight_scratch: budget.take("scratch", mul(threads, sizes.weight_scratch)?)?,
            channel_tmp: budget.take("scratch", 2 * sizes.channels.max(top_c))?,
            zero: budget.take("scratch", sizes.channels)?,
            item_sums: budget.take_f64("scratch", mul(pair, sums_len(sizes.channels.max(top_c)))?)?,
            sums: budget.take_f64("scratch", sums_len(sizes.channels.max(top_c)))?,
        },
    };
    Ok(Networks {
        params: budget.take("parameters", params)?,
        grads: budget.take("gradients", params)?,
        moments: [
            budget.take("Adam moments", params)?,
            budget.take("Adam moments", params)?,
        ],
        stats: budget.take("running statistics", t.stats)?,
        saved_stats: budget.take("running statistics", t.stats)?,
        dis_stats,
        nets: [0..enc_end, enc_end..gen_end, gen_end..params],
        table: t,
        enc,
        heads,
        fc,
        top_norm,
        top,
        gen,
        dis,
        logit,
        buffers,
    })
}

/// The memory of a [`VaeGanTrainer`] for a config and a batch of frames, measured by building
/// the trainer without allocating (every buffer counted, none made).
///
/// ```
/// use drivesim::train::VaeGanPlan;
/// use drivesim::Config;
///
/// let config = Config { base_channels: 32, z_dim: 128, hidden_dim: 256, ..Config::COMMA };
/// let plan = VaeGanPlan::new(&config, 8, 2)?;
/// for (buffer, bytes) in plan.buffers() {
///     println!("{buffer:>22}: {bytes} bytes");
/// }
/// assert!(plan.bytes() < 1 << 30);
/// assert!(VaeGanPlan::new(&config, usize::MAX, 1).is_err());
/// # Ok::<(), drivesim::Error>(())
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VaeGanPlan {
    config: Config,
    batch: usize,
    threads: usize,
    floats: Vec<(&'static str, usize)>,
    bytes: usize,
}

impl VaeGanPlan {
    /// The plan for `config` taking up to `batch` frames per step with `threads` threads (the
    /// caller's included; 0 counts as 1), each with scratch of its own.
    pub fn new(config: &Config, batch: usize, threads: usize) -> Result<VaeGanPlan> {
        let threads = threads.max(1);
        let mut budget = Budget {
            allocate: false,
            floats: Vec::new(),
        };
        build(config, batch, threads, &mut budget)?;
        let total = budget.floats.iter().try_fold(0usize, |s, &(_, n)| s.checked_add(n));
        let bytes = total
            .and_then(|n| n.checked_mul(4))
            .filter(|&b| b <= isize::MAX as usize)
            .ok_or(OVERFLOW)?;
        Ok(VaeGanPlan {
            config: *config,
            batch,
            threads,
            floats: budget.floats,
            bytes,
        })
    }

    /// Bytes the trainer allocates (besides a few tensor names).
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Bytes per kind of buffer.
    pub fn buffers(&self) -> impl Iterator<Item = (&'static str, usize)> + '_ {
        self.floats.iter().map(|&(what, n)| (what, n * 4))
    }

    /// Most frames per step.
    pub fn batch(&self) -> usize {
        self.batch
    }
}

/// Trains a model's encoder and generator as a VAE-GAN, with a discriminator, in the memory of
/// a [`VaeGanPlan`], allocated once: a step allocates nothing.
///
/// ```
/// use drivesim::train::{VaeGanPlan, VaeGanSettings, VaeGanTrainer, VAE_GAN_LR};
/// use drivesim::{Config, Model};
///
/// let config = Config { height: 32, width: 64, base_channels: 4, z_dim: 8, hidden_dim: 8, ..Config::COMMA };
/// let file = drivesim::train::random_weight_file(&config, 7)?;
/// let plan = VaeGanPlan::new(&config, 2, 1)?;
/// let mut trainer = VaeGanTrainer::new(&file, &plan, VaeGanSettings::default())?;
/// let frames: Vec<f32> = (0..2 * 32 * 64 * 3).map(|i| ((i % 7) as f32 / 3.0 - 1.0)).collect();
/// let eps = vec![0.5; 2 * 8];
/// let prior = vec![-0.5; 2 * 8];
/// let first = trainer.step(&frames, &eps, &prior, VAE_GAN_LR)?;
/// for _ in 0..20 {
///     trainer.step(&frames, &eps, &prior, VAE_GAN_LR)?;
/// }
/// assert!(trainer.step(&frames, &eps, &prior, VAE_GAN_LR)?.pixel_l1 < first.pixel_l1);
/// // The trained networks as a weight file the simulator loads (discriminator included).
/// let model = Model::from_bytes(&trainer.weight_file(&file, None, Default::default())?)?;
/// assert_eq!(model.config(), &config);
/// # Ok::<(), drivesim::Error>(())
/// ```
pub struct VaeGanTrainer {
    config: Config,
    settings: VaeGanSettings,
    isa: Isa,
    pool: Option<Pool>,
    steps: u32,
    parts: Networks,
}

impl VaeGanTrainer {
    /// A trainer starting from a drivesim weight file's encoder and generator (and its
    /// discriminator, `discriminator.*`, if it has one; otherwise a seeded random one with
    /// PyTorch's default initialisation ranges), its buffers allocated once here.
    pub fn new(weights: &[u8], plan: &VaeGanPlan, settings: VaeGanSettings) -> Result<VaeGanTrainer> {
        let (config, _, mut src) = SafetensorsSource::parse(weights)?;
        if config != plan.config {
            return Err(Error::Config {
                field: "config",
                expected: "the plan's config",
                found: 0,
            });
        }
        settings.check()?;
        let mut budget = Budget {
            allocate: true,
            floats: Vec::new(),
        };
        let mut parts = build(&config, plan.batch, plan.threads, &mut budget)?;
        debug_assert_eq!(budget.floats, plan.floats, "the plan measures what is allocated");
        let has_discriminator = src.contains(DISCRIMINATOR_PREFIX);
        let mut random = RandomSource::new(0x5eed_d15c, WeightDtype::F32);
        for e in &parts.table.entries {
            let from_file = has_discriminator || !e.name.starts_with(DISCRIMINATOR_PREFIX);
            let values = if from_file {
                src.f32(&e.name, &e.shape, e.init)?
            } else {
                random.f32(&e.name, &e.shape, e.init)?
            };
            match e.layout {
                Layout::Dense(layer, first) => {
                    let dense = parts.dense(layer);
                    let (order, all, cols, rows) = (dense.order, dense.rows, dense.cols, first..first + e.shape[0]);
                    let w = &mut parts.params[e.at.clone()];
                    order.for_each(all, cols, |r, c, t| {
                        if rows.contains(&(t / cols)) {
                            w[Matrix::packed_index(r, c, cols)] = values[t - rows.start * cols];
                        }
                    });
                }
                Layout::Conv(shape) => conv_matrix_from_torch(&shape, &values, &mut parts.params[e.at.clone()]),
                Layout::Torch => {
                    let dst = if e.param { &mut parts.params } else { &mut parts.stats };
                    dst[e.at.clone()].copy_from_slice(&values);
                }
            }
        }
        let mut trainer = VaeGanTrainer {
            config,
            settings,
            isa: Isa::best(),
            pool: start_pool(plan.threads)?,
            steps: 0,
            parts,
        };
        let exec = Exec {
            isa: trainer.isa,
            pool: trainer.pool.as_ref(),
        };
        for net in 0..3 {
            trainer.parts.pack(net, exec);
        }
        Ok(trainer)
    }

    /// Uses the kernels of `isa` instead of the best this CPU has.
    pub fn with_isa(mut self, isa: Isa) -> Self {
        self.isa = isa;
        self
    }

    /// One step on `frames` (`[B, H, W, C]` in [-1, 1], `B` at most the plan's batch), with
    /// the reparametrisation draws `eps` and the prior samples `prior` (`[B, z]` each, standard
    /// normal for training): the discriminator's update, then the encoder's and generator's,
    /// at learning rate `lr`. Returns the losses, computed before the updates. Gradients that
    /// are not finite are [`Error::NonFiniteOutput`] before the update they would feed (the
    /// discriminator's, or the encoder's and generator's), which then does not happen, nor do
    /// the moves of that network's running statistics by the step's forward passes.
    pub fn step(&mut self, frames: &[f32], eps: &[f32], prior: &[f32], lr: f32) -> Result<VaeGanLosses> {
        let c = self.config;
        if frames.is_empty()
            || !frames.len().is_multiple_of(c.frame_len())
            || frames.len() / c.frame_len() > self.parts.buffers.batch
        {
            return Err(Error::BufferLength {
                buffer: "frames",
                expected: self.parts.buffers.batch * c.frame_len(),
                found: frames.len(),
            });
        }
        let n = frames.len() / c.frame_len();
        expect_frames("frames", frames)?;
        expect_len("eps", eps, n * c.z_dim)?;
        expect_len("prior", prior, n * c.z_dim)?;
        expect_finite("eps", eps)?;
        expect_finite("prior", prior)?;
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(Error::Setting {
                name: "lr",
                expected: "a finite number >= 0",
                value: lr,
            });
        }
        let exec = Exec {
            isa: self.isa,
            pool: self.pool.as_ref(),
        };
        let losses = self
            .parts
            .step(exec, &self.settings, frames, eps, prior, n, lr, self.steps + 1)?;
        self.steps += 1;
        Ok(losses)
    }

    /// Adam steps taken.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// The encoder's, generator's and discriminator's tensors in PyTorch layout (running
    /// statistics included), named as in the weight file.
    pub fn tensors(&self) -> Vec<NamedTensor> {
        let p = &self.parts;
        let entries = p.table.entries.iter();
        entries
            .map(|e| p.torch(e, if e.param { &p.params } else { &p.stats }))
            .collect()
    }

    /// The gradients of the last step (encoder and generator: of their own losses; the
    /// discriminator: of its loss), named as the tensors they belong to.
    pub fn gradients(&self) -> Vec<NamedTensor> {
        let p = &self.parts;
        let params = p.table.entries.iter().filter(|e| e.param);
        params.map(|e| p.torch(e, &p.grads)).collect()
    }

    /// A weight file with the trained networks: `original` (a drivesim weight file of the same
    /// config, e.g. the one training started from) with the encoder's, generator's and
    /// discriminator's tensors replaced (or, for a discriminator it lacked, added), every tensor
    /// in `dtype` (`None`: the file's own), and what it was trained on in its metadata
    /// ([`super::TrainedOn`]; the original's where not given). [`crate::Model::from_bytes`]
    /// reads it.
    #[cfg(feature = "std")]
    pub fn weight_file(
        &self,
        original: &[u8],
        dtype: Option<WeightDtype>,
        trained_on: super::TrainedOn<'_>,
    ) -> Result<Vec<u8>> {
        let tensors = self.tensors();
        let replace: Vec<(&str, &[usize], &[f32])> = tensors
            .iter()
            .map(|(name, shape, values)| (name.as_str(), &shape[..], &values[..]))
            .collect();
        crate::weights::rewrite(original, &replace, dtype, trained_on)
    }
}

/// A drivesim weight file (f32) with seeded random weights for `config` (PyTorch's default
/// initialisation ranges, BatchNorm at identity), discriminator included: where training from
/// scratch starts.
#[cfg(feature = "std")]
pub fn random_weight_file(config: &Config, seed: u64) -> Result<Vec<u8>> {
    let mut budget = Budget {
        allocate: false,
        floats: Vec::new(),
    };
    let parts = build(config, 1, 1, &mut budget)?;
    let (h, z, a) = (config.hidden_dim, config.z_dim, config.action_dim);
    let transition = [
        ("transition.W", alloc::vec![h, h], Init::FanIn(h)),
        ("transition.V", alloc::vec![h, z], Init::FanIn(z)),
        ("transition.U", alloc::vec![h, a], Init::FanIn(a)),
        ("transition.b", alloc::vec![h], Init::Zeros),
        ("transition.A", alloc::vec![z, h], Init::FanIn(h)),
        ("transition.a", alloc::vec![z], Init::Zeros),
    ];
    let specs = parts
        .table
        .entries
        .iter()
        .map(|e| (e.name.as_str(), e.shape.clone(), e.init));
    let specs: Vec<_> = specs
        .chain(transition.iter().map(|(n, s, i)| (*n, s.clone(), *i)))
        .collect();
    let mut random = RandomSource::new(seed, WeightDtype::F32);
    let mut data = Vec::new();
    for (name, shape, init) in &specs {
        let values = random.f32(name, shape, *init)?;
        data.push(bytemuck::cast_slice::<f32, u8>(&values).to_vec());
    }
    let views = specs
        .iter()
        .zip(&data)
        .map(|((name, shape, _), bytes)| {
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), bytes)
                .map(|view| (String::from(*name), view))
        })
        .collect::<core::result::Result<Vec<_>, _>>();
    let malformed = |e| Error::Malformed {
        what: "weight file",
        reason: format!("{e:?}"),
    };
    let mut metadata = std::collections::HashMap::new();
    metadata.insert(String::from(Config::METADATA_KEY), config.to_json());
    safetensors::serialize(views.map_err(malformed)?, Some(metadata)).map_err(malformed)
}

/// Copies the interiors of `items` planes into consecutive HWC vectors (a dense layer's input).
fn gather(plane: Plane, planes: &[f32], items: usize, flat: &mut [f32]) {
    let row = plane.width * plane.channels;
    let per_item = plane.height * row;
    for n in 0..items {
        for y in 0..plane.height {
            let src = &planes[n * plane.len() + plane.index(y, 0)..][..row];
            flat[n * per_item + y * row..][..row].copy_from_slice(src);
        }
    }
}

/// The inverse of [`gather`]: HWC vectors into the interiors of planes.
fn scatter(plane: Plane, flat: &[f32], items: usize, planes: &mut [f32]) {
    let row = plane.width * plane.channels;
    let per_item = plane.height * row;
    for n in 0..items {
        for y in 0..plane.height {
            let dst = &mut planes[n * plane.len() + plane.index(y, 0)..][..row];
            dst.copy_from_slice(&flat[n * per_item + y * row..][..row]);
        }
    }
}

/// `ln(1 + e^x)` in f64, without overflow.
fn softplus(x: f64) -> f64 {
    x.max(0.0) + math::ln64(1.0 + math::exp64(-x.abs()))
}

/// `1 / (1 + e^-x)` in f64.
fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + math::exp64(-x))
}

/// PyTorch's `binary_cross_entropy_with_logits` against a constant target (mean over the
/// logits), and its gradient times `scale` into `grad`.
fn bce(logits: &[f32], target: bool, scale: f64, grad: &mut [f32]) -> f64 {
    let n = logits.len() as f64;
    let t = if target { 1.0 } else { 0.0 };
    let mut loss = 0.0;
    for (g, &l) in grad.iter_mut().zip(logits) {
        let l = l as f64;
        loss += softplus(if target { -l } else { l });
        *g = (scale * (sigmoid(l) - t) / n) as f32;
    }
    loss / n
}

/// `dst += src`.
fn add(dst: &mut [f32], src: &[f32]) {
    dst.iter_mut().zip(src).for_each(|(d, s)| *d += s);
}

/// BatchNorm + activation in training mode over one pass of `plane`s, moving the running
/// statistics if `update`.
#[allow(clippy::too_many_arguments)] // a layer's tensors, its input and output, its statistics
fn norm_forward(
    exec: Exec<'_>,
    plane: Plane,
    norm: &Norm,
    params: &[f32],
    stats: &mut [f32],
    act: Activation,
    z: &[f32],
    y: &mut [f32],
    (mean, var): (&mut [f32], &mut [f32]),
    update: bool,
    work: &mut Work,
) {
    let (items, pl) = (z.len() / plane.len(), plane.len());
    let count = items * plane.height * plane.width;
    let slots = (&mut work.item_sums[..], &mut work.sums[..]);
    let sums = batch_sums(exec, plane, items, slots, &|n, slot| {
        moments(exec.isa, plane, &z[n * pl..][..pl], slot)
    });
    statistics(sums, count, mean, var);
    let (mean, var) = (&*mean, &*var);
    let (gamma, beta) = (&params[norm.gamma.clone()], &params[norm.beta.clone()]);
    let outputs = Parts::chunks(&mut y[..items * pl], pl);
    exec.run(&|| {
        while let Some((n, y)) = outputs.take() {
            normalize(exec.isa, plane, &z[n * pl..][..pl], mean, var, gamma, beta, act, y);
        }
    });
    if update {
        // The running mean and variance were declared one after the other.
        let (rm, rv) = stats[norm.mean.start..norm.var.end].split_at_mut(norm.mean.len());
        update_running_stats(mean, var, count, rm, rv);
    }
}

/// A batch's per-channel sums for BatchNorm: `add(item, sums)` adds each item's into sums of
/// its own in `slots` (threads taking items), then these are added up in the items' order, so
/// that the result is the same for any thread count. Returns them, in the first floats of
/// `sums`.
fn batch_sums<'w>(
    exec: Exec<'_>,
    plane: Plane,
    items: usize,
    (slots, sums): (&mut [f64], &'w mut [f64]),
    add: &(dyn Fn(usize, &mut [f64]) + Sync),
) -> &'w [f64] {
    let len = sums_len(plane.channels);
    let slots = &mut slots[..items * len];
    slots.fill(0.0);
    let parts = Parts::chunks(&mut *slots, len);
    exec.run(&|| {
        while let Some((n, slot)) = parts.take() {
            add(n, slot);
        }
    });
    let sums = &mut sums[..len];
    sums.fill(0.0);
    for slot in slots.chunks_exact(len) {
        sums.iter_mut().zip(slot).for_each(|(s, v)| *s += v);
    }
    sums
}

/// The backward pass of BatchNorm + `act` over one pass's planes (`z` its input, `y` its
/// output, `mean` and `var` its statistics), in place: `g`, the gradient of `y`, becomes that
/// of `z`; those of `gamma` and `beta` are added to `grads` if given. Threads take items.
#[allow(clippy::too_many_arguments)]
fn norm_backward(
    exec: Exec<'_>,
    plane: Plane,
    norm: &Norm,
    params: &[f32],
    grads: Option<&mut [f32]>,
    act: Activation,
    (z, y): (&[f32], &[f32]),
    (mean, var): (&[f32], &[f32]),
    g: &mut [f32],
    work: &mut Work,
) {
    let (items, pl, c) = (z.len() / plane.len(), plane.len(), plane.channels);
    let count = items * plane.height * plane.width;
    let g = &mut g[..items * pl];
    let gradients = Parts::chunks(&mut *g, pl);
    exec.run(&|| {
        while let Some((n, g)) = gradients.take() {
            activation_backward(exec.isa, act, &y[n * pl..][..pl], g);
        }
    });
    let gradient = &*g;
    let slots = (&mut work.item_sums[..], &mut work.sums[..]);
    let sums = batch_sums(exec, plane, items, slots, &|n, slot| {
        gradient_moments(
            exec.isa,
            plane,
            &z[n * pl..][..pl],
            &gradient[n * pl..][..pl],
            mean,
            slot,
        )
    });
    if let Some(grads) = grads {
        let (dgamma, dbeta) = work.channel_tmp[..2 * c].split_at_mut(c);
        parameter_gradients(sums, var, dgamma, dbeta);
        add(&mut grads[norm.gamma.clone()], dgamma);
        add(&mut grads[norm.beta.clone()], dbeta);
    }
    let gamma = &params[norm.gamma.clone()];
    let outputs = Parts::chunks(g, pl);
    exec.run(&|| {
        while let Some((n, g)) = outputs.take() {
            normalize_gradient(exec.isa, plane, &z[n * pl..][..pl], g, mean, var, gamma, sums, count);
        }
    });
}

/// The forward pass of a stack of convolutions over the items of `passes` (each pass a batch
/// for BatchNorm, moving the running statistics if its flag says so).
#[allow(clippy::too_many_arguments)]
fn stack_forward(
    exec: Exec<'_>,
    layers: &[Conv],
    params: &[f32],
    stats: &mut [f32],
    input: &[f32],
    acts: &mut Stack,
    passes: &[(Range<usize>, bool)],
    work: &mut Work,
) {
    let items = passes.last().map_or(0, |p| p.0.end);
    for (i, l) in layers.iter().enumerate() {
        let (il, ol, oc) = (l.shape.input.len(), l.shape.output.len(), l.shape.output.channels);
        let (done, rest) = acts.y.split_at_mut(i);
        let x = if i == 0 { input } else { &done[i - 1][..] };
        let y = &mut rest[0];
        let bias = &params[l.bias.clone()];
        let Some(norm) = &l.norm else {
            l.forward.run_items(
                exec,
                bias,
                l.act,
                &x[..items * il],
                &mut y[..items * ol],
                &mut work.scratch,
            );
            continue;
        };
        let z = &mut acts.z[i];
        l.forward.run_items(
            exec,
            bias,
            Activation::Identity,
            &x[..items * il],
            &mut z[..items * ol],
            &mut work.scratch,
        );
        let (mean, var) = (&mut acts.mean[i], &mut acts.var[i]);
        for (p, (range, update)) in passes.iter().enumerate() {
            let span = range.start * ol..range.end * ol;
            let statistics = (&mut mean[p * oc..][..oc], &mut var[p * oc..][..oc]);
            let (z, y) = (&z[span.clone()], &mut y[span]);
            norm_forward(
                exec,
                l.shape.output,
                norm,
                params,
                stats,
                l.act,
                z,
                y,
                statistics,
                *update,
                work,
            );
        }
    }
}

/// The weight gradient of the strided layer `down` over a batch, added to what `grad` holds
/// (in the layout of [`Table::conv`]): in one run, each thread takes a share of the gradient's
/// panels and gathers every patch into its own `scratch`
/// ([`drivesim_kernels::conv_weight_grad_add_rows`]). Gathering twice costs less than sharing:
/// a shared gathering needs a barrier per block of patches, and half of what each thread reads
/// would be the other's writes.
fn conv_weight_grad(exec: Exec<'_>, down: ConvShape, input: &[f32], dy: &[f32], scratch: &mut [f32], grad: &mut [f32]) {
    let each = conv_weight_grad_scratch_len(&down);
    let scratch = Parts::chunks(&mut scratch[..exec.threads() * each], each);
    let parts = OutputParts::new(grad, down.output.channels, exec.threads());
    exec.run(&|| {
        let (_, scratch) = scratch.take().expect("a scratch for every thread");
        while let Some(part) = parts.take() {
            conv_weight_grad_add_rows(exec.isa, down, input, dy, scratch, part);
        }
    });
}

/// Where a backward pass through a stack starts: from the gradient of layer `i`'s output (in
/// `g[i]`), or of its convolution's output before BatchNorm and the activation (in `g[i]` too).
#[derive(Clone, Copy)]
enum Start {
    Output(usize),
    BeforeNorm(usize),
}

/// The backward pass of a stack over the items of `passes` (with their BatchNorm statistics)
/// from `start` down: parameter gradients added to `grads` if given, `inject` (a layer and a
/// gradient) added to that layer's gradient before BatchNorm, and the input's gradient written
/// to `dx` if given.
#[allow(clippy::too_many_arguments)]
fn stack_backward(
    exec: Exec<'_>,
    layers: &[Conv],
    params: &[f32],
    mut grads: Option<&mut [f32]>,
    input: &[f32],
    acts: &Stack,
    g: &mut StackGrads,
    passes: &[Range<usize>],
    start: Start,
    inject: Option<(usize, &[f32])>,
    mut dx: Option<&mut [f32]>,
    work: &mut Work,
) {
    let items = passes.last().map_or(0, |p| p.end);
    let (top, norm_done) = match start {
        Start::Output(i) => (i, false),
        Start::BeforeNorm(i) => (i, true),
    };
    for i in (0..=top).rev() {
        let l = &layers[i];
        let (plane, il, ol) = (l.shape.output, l.shape.input.len(), l.shape.output.len());
        let oc = plane.channels;
        let (below, rest) = g.g.split_at_mut(i);
        // The output's gradient, turned in place into the convolution output's.
        let gz = &mut rest[0][..items * ol];
        if !(norm_done && i == top) {
            match &l.norm {
                Some(norm) => {
                    for (p, r) in passes.iter().enumerate() {
                        let s = r.start * ol..r.end * ol;
                        let statistics = (&acts.mean[i][p * oc..][..oc], &acts.var[i][p * oc..][..oc]);
                        let saved = (&acts.z[i][s.clone()], &acts.y[i][s.clone()]);
                        let grads = grads.as_deref_mut();
                        norm_backward(
                            exec, plane, norm, params, grads, l.act, saved, statistics, &mut gz[s], work,
                        );
                    }
                }
                None => {
                    let y = &acts.y[i];
                    let outputs = Parts::chunks(&mut *gz, ol);
                    exec.run(&|| {
                        while let Some((n, gz)) = outputs.take() {
                            activation_backward(exec.isa, l.act, &y[n * ol..][..ol], gz);
                        }
                    });
                }
            }
        }
        if let Some((_, d)) = inject.filter(|(at, _)| *at == i) {
            add(gz, &d[..items * ol]);
        }
        let x = if i == 0 { input } else { &acts.y[i - 1][..] };
        let x = &x[..items * il];
        if let Some(grads) = grads.as_deref_mut() {
            // The bias's gradient: the channel sums of gz, item by item (the first half of
            // their moments).
            let g = &*gz;
            let slots = (&mut work.item_sums[..], &mut work.sums[..]);
            let sums = batch_sums(exec, plane, items, slots, &|n, slot| {
                moments(exec.isa, plane, &g[n * ol..][..ol], slot)
            });
            for (g, &s) in grads[l.bias.clone()].iter_mut().zip(&sums[..oc]) {
                *g += s as f32;
            }
            // A transposed layer's weight gradient is its transposed shape's, with the input
            // and the output gradient swapped.
            let (down, a, b) = match l.shape.kind {
                ConvKind::Down => (l.shape, x, &*gz),
                ConvKind::Up => (l.shape.transposed(), &*gz, x),
            };
            conv_weight_grad(exec, down, a, b, &mut work.weight_scratch, &mut grads[l.weight.clone()]);
        }
        let target = if i > 0 {
            Some(&mut below[i - 1][..items * il])
        } else {
            dx.as_deref_mut().map(|d| &mut d[..items * il])
        };
        if let Some(target) = target {
            let zero = &work.zero[..l.shape.input.channels];
            l.backward
                .run_items(exec, zero, Activation::Identity, gz, target, &mut work.scratch);
        }
    }
}

/// One packing of [`Networks::pack`].
enum Job<'a> {
    Dense(&'a mut Dense),
    Conv(&'a mut Packed, Range<usize>),
}

/// Pieces that the passes over every parameter (Adam, zeroing and checking the gradients) are
/// cut into, threads taking them in turn: the same pieces whatever the thread count.
const PIECES: usize = 16;

/// Values in each of the [`PIECES`] pieces of `len` values (the last may hold fewer).
fn piece_len(len: usize) -> usize {
    len.div_ceil(PIECES).max(1)
}

/// The [`PIECES`] ranges of `len` values.
fn pieces(len: usize) -> [Range<usize>; PIECES] {
    let step = piece_len(len);
    core::array::from_fn(|i| (i * step).min(len)..((i + 1) * step).min(len))
}

/// Sets `data` to zero, threads taking pieces.
fn zero(exec: Exec<'_>, data: &mut [f32]) {
    let spans = pieces(data.len());
    let parts = Parts::spans(data, &spans);
    exec.run(&|| {
        while let Some((_, piece)) = parts.take() {
            piece.fill(0.0);
        }
    });
}

/// [`expect_finite_output`] on gradients, threads checking pieces (the index of the first bad
/// value is then searched alone).
fn expect_finite_gradients(exec: Exec<'_>, buffer: &'static str, data: &[f32]) -> Result<()> {
    let spans = pieces(data.len());
    let mut finite = [true; PIECES];
    let flags = Parts::chunks(&mut finite[..], 1);
    exec.run(&|| {
        while let Some((i, flag)) = flags.take() {
            flag[0] = all_finite(&data[spans[i].clone()]);
        }
    });
    match finite.iter().all(|&f| f) {
        true => Ok(()),
        false => expect_finite_output(buffer, data),
    }
}

/// The worker threads of a plan for `threads` (none for one).
fn start_pool(threads: usize) -> Result<Option<Pool>> {
    match threads {
        1 => Ok(None),
        #[cfg(feature = "std")]
        n => Pool::new(n)
            .map(Some)
            .map_err(|source| Error::Threads { requested: n, source }),
        #[cfg(not(feature = "std"))]
        n => Err(Error::Config {
            field: "threads",
            expected: "1 without the std feature",
            found: n,
        }),
    }
}

impl Networks {
    /// Dense layer `layer`: the encoder's heads, the generator's first layer, the logit.
    fn dense(&self, layer: usize) -> &Dense {
        [&self.heads, &self.fc, &self.logit][layer]
    }

    /// Tensor `e` of `values` (the parameters, their gradients or the statistics) in
    /// PyTorch's layout.
    fn torch(&self, e: &Entry, values: &[f32]) -> NamedTensor {
        let tensor = match e.layout {
            Layout::Torch => values[e.at.clone()].to_vec(),
            Layout::Conv(shape) => {
                let mut out = alloc::vec![0.0; e.shape.iter().product()];
                conv_matrix_to_torch(&shape, &values[e.at.clone()], &mut out);
                out
            }
            Layout::Dense(layer, first) => {
                let dense = self.dense(layer);
                let (cols, rows) = (dense.cols, first..first + e.shape[0]);
                let (w, mut out) = (&values[e.at.clone()], alloc::vec![0.0; rows.len() * cols]);
                dense.order.for_each(dense.rows, cols, |r, c, t| {
                    if rows.contains(&(t / cols)) {
                        out[t - rows.start * cols] = w[Matrix::packed_index(r, c, cols)];
                    }
                });
                out
            }
        };
        (e.name.clone(), e.shape.clone(), tensor)
    }

    /// Repacks network `net`'s layers (0 encoder, 1 generator, 2 discriminator), threads
    /// taking the packings one at a time, the largest first.
    fn pack(&mut self, net: usize, exec: Exec<'_>) {
        let p = &self.params;
        let (convs, dense) = match net {
            0 => (&mut self.enc, &mut self.heads),
            1 => (&mut self.gen, &mut self.fc),
            _ => (&mut self.dis, &mut self.logit),
        };
        let [a, b, c, d] = convs;
        let mut jobs = [
            Job::Dense(dense),
            Job::Conv(&mut d.backward, d.weight.clone()),
            Job::Conv(&mut d.forward, d.weight.clone()),
            Job::Conv(&mut c.backward, c.weight.clone()),
            Job::Conv(&mut c.forward, c.weight.clone()),
            Job::Conv(&mut b.backward, b.weight.clone()),
            Job::Conv(&mut b.forward, b.weight.clone()),
            Job::Conv(&mut a.backward, a.weight.clone()),
            Job::Conv(&mut a.forward, a.weight.clone()),
        ];
        let jobs = Parts::chunks(&mut jobs, 1);
        exec.run(&|| {
            while let Some((_, job)) = jobs.take() {
                match &mut job[0] {
                    Job::Dense(layer) => layer.pack(p),
                    Job::Conv(packed, weight) => packed.pack(exec.isa, &p[weight.clone()]),
                }
            }
        });
    }

    /// Adam on network `net`'s parameters, then its packings.
    fn update(&mut self, net: usize, exec: Exec<'_>, adam: &Adam, t: u32, lr: f32) {
        let r = self.nets[net].clone();
        let [m, v] = &mut self.moments;
        // Adam is elementwise: threads take pieces (the same values whatever their number).
        let len = piece_len(r.len());
        let (params, grads) = (&mut self.params[r.clone()], &self.grads[r.clone()]);
        let mut split = params
            .chunks_mut(len)
            .zip(grads.chunks(len))
            .zip(m[r.clone()].chunks_mut(len).zip(v[r].chunks_mut(len)));
        let mut jobs: [_; PIECES] = core::array::from_fn(|_| split.next().unwrap_or_default());
        let jobs = Parts::chunks(&mut jobs, 1);
        exec.run(&|| {
            while let Some((_, job)) = jobs.take() {
                let ((p, g), (m, v)) = &mut job[0];
                adam.update(t, lr, 1.0, p, g, [m, v]);
            }
        });
        self.pack(net, exec);
    }

    /// The discriminator on `items` planes of `input` (real frames, or the fakes in the
    /// generator's output): its activations in `set`, the logits in `logits`.
    fn discriminate(&mut self, exec: Exec<'_>, fake: bool, items: usize) {
        let b = &mut self.buffers;
        let (input, acts, flat, logits) = if fake {
            (&b.gen.y[3], &mut b.dis_fake, &mut b.flat_fake, &mut b.logits_fake)
        } else {
            (&b.real, &mut b.dis_real, &mut b.flat_real, &mut b.logits_real)
        };
        let passes = [(0..items, true)];
        stack_forward(
            exec,
            &self.dis,
            &self.params,
            &mut self.stats,
            input,
            acts,
            &passes,
            &mut b.work,
        );
        gather(self.dis[3].shape.output, &acts.y[3], items, flat);
        self.logit.run(
            exec,
            &self.params,
            &flat[..items * self.logit.cols],
            &mut logits[..items],
        );
    }

    /// The gradient `dlogits` (of `items` logits) back through the discriminator's `fake` or
    /// real set: to its parameters if `weights`, to its input (into `buffers.dx`) if `input`,
    /// with `inject` added to the third convolution's output gradient.
    fn discriminator_backward(
        &mut self,
        exec: Exec<'_>,
        fake: bool,
        items: usize,
        weights: bool,
        input: bool,
        inject: bool,
    ) {
        let b = &mut self.buffers;
        let (x, acts, flat) = if fake {
            (&b.gen.y[3], &b.dis_fake, &b.flat_fake)
        } else {
            (&b.real, &b.dis_real, &b.flat_real)
        };
        let flat_len = self.logit.cols;
        let dlogits = &b.dlogits[..items];
        if weights {
            self.logit
                .weight_grad(exec, dlogits, &flat[..items * flat_len], &mut self.grads);
        }
        self.logit
            .data_grad(exec, &self.params, dlogits, &mut b.dflat[..items * flat_len]);
        scatter(self.dis[3].shape.output, &b.dflat, items, &mut b.dis_grads.g[3]);
        let grads = weights.then_some(&mut self.grads[..]);
        let inject = inject.then_some((2, &b.dfeature[..]));
        let dx = input.then_some(&mut b.dx[..]);
        let passes = [0..items];
        stack_backward(
            exec,
            &self.dis,
            &self.params,
            grads,
            x,
            acts,
            &mut b.dis_grads,
            &passes,
            Start::Output(3),
            inject,
            dx,
            &mut b.work,
        );
    }

    /// The generator's gradient `buffers.dx` (of its `items` outputs) back through its first
    /// `items` (with their passes' statistics): parameter gradients if `weights`, the codes'
    /// gradient into `buffers.dcodes` otherwise.
    fn generator_backward(&mut self, exec: Exec<'_>, passes: &[Range<usize>], weights: bool) {
        let b = &mut self.buffers;
        let items = passes.last().map_or(0, |p| p.end);
        let image = self.gen[3].shape.output.len();
        b.gen_grads.g[3][..items * image].copy_from_slice(&b.dx[..items * image]);
        let grads = weights.then_some(&mut self.grads[..]);
        let (top_y, gen) = (&b.top_y, &b.gen);
        stack_backward(
            exec,
            &self.gen,
            &self.params,
            grads,
            top_y,
            gen,
            &mut b.gen_grads,
            passes,
            Start::Output(3),
            None,
            Some(&mut b.top_g),
            &mut b.work,
        );
        // BatchNorm0 + ReLU on the fully connected layer's output, per pass.
        let (top, tl, c) = (self.top, self.top.len(), self.top.channels);
        let norm = &self.top_norm;
        for (p, r) in passes.iter().enumerate() {
            let s = r.start * tl..r.end * tl;
            let statistics = (&b.top_mean[p * c..][..c], &b.top_var[p * c..][..c]);
            let saved = (&b.top_z[s.clone()], &b.top_y[s.clone()]);
            let grads = weights.then_some(&mut self.grads[..]);
            let (relu, g) = (Activation::Relu, &mut b.top_g[s]);
            norm_backward(
                exec,
                top,
                norm,
                &self.params,
                grads,
                relu,
                saved,
                statistics,
                g,
                &mut b.work,
            );
        }
        let flat = self.fc.rows;
        gather(top, &b.top_g, items, &mut b.dflat);
        let (dflat, z) = (&b.dflat[..items * flat], self.fc.cols);
        if weights {
            self.fc.weight_grad(exec, dflat, &b.codes[..items * z], &mut self.grads);
        } else {
            self.fc.data_grad(exec, &self.params, dflat, &mut b.dcodes[..items * z]);
        }
    }

    /// Checks the gradients `range` before their update; if they are not finite, the running
    /// statistics go back to [`Networks::saved_stats`].
    fn check_gradients(&mut self, exec: Exec<'_>, buffer: &'static str, range: Range<usize>) -> Result<()> {
        let checked = expect_finite_gradients(exec, buffer, &self.grads[range]);
        if checked.is_err() {
            self.stats.copy_from_slice(&self.saved_stats);
        }
        checked
    }

    /// One VAE-GAN step on `n` frames; see [`VaeGanTrainer::step`]. `t` is the Adam step.
    #[allow(clippy::too_many_arguments)]
    fn step(
        &mut self,
        exec: Exec<'_>,
        s: &VaeGanSettings,
        frames: &[f32],
        eps: &[f32],
        prior: &[f32],
        n: usize,
        lr: f32,
        t: u32,
    ) -> Result<VaeGanLosses> {
        zero(exec, &mut self.grads);
        self.saved_stats.copy_from_slice(&self.stats);
        let z = self.fc.cols;
        let image = self.enc[0].shape.input;
        {
            let b = &mut self.buffers;
            for (plane, frame) in b
                .real
                .chunks_exact_mut(image.len())
                .zip(frames.chunks_exact(image.interior_len()))
            {
                image.write_interior(plane, frame);
            }
            // Encoder.
            let passes = [(0..n, true)];
            stack_forward(
                exec,
                &self.enc,
                &self.params,
                &mut self.stats,
                &b.real,
                &mut b.enc,
                &passes,
                &mut b.work,
            );
            gather(self.enc[3].shape.output, &b.enc.y[3], n, &mut b.enc_flat);
            let flat = self.heads.cols;
            self.heads
                .run(exec, &self.params, &b.enc_flat[..n * flat], &mut b.heads[..n * 2 * z]);
            // The generator's inputs: mu + eps · exp(logsigma), then the prior samples.
            b.eps[..n * z].copy_from_slice(eps);
            for i in 0..n {
                let (mu, ls) = b.heads[i * 2 * z..][..2 * z].split_at_mut(z);
                for j in 0..z {
                    ls[j] = math::tanh(ls[j]);
                    b.codes[i * z + j] = mu[j] + eps[i * z + j] * math::exp64(ls[j] as f64) as f32;
                }
            }
            b.codes[n * z..2 * n * z].copy_from_slice(prior);
            // Generator: reconstructions update the running statistics, prior samples do not.
            self.fc.run(
                exec,
                &self.params,
                &b.codes[..2 * n * z],
                &mut b.fc_out[..2 * n * self.fc.rows],
            );
            scatter(self.top, &b.fc_out, 2 * n, &mut b.top_z);
            let (tl, tc) = (self.top.len(), self.top.channels);
            for (p, update) in [(0, true), (1, false)] {
                let span = p * n * tl..(p + 1) * n * tl;
                let statistics = (&mut b.top_mean[p * tc..][..tc], &mut b.top_var[p * tc..][..tc]);
                let (z, y) = (&b.top_z[span.clone()], &mut b.top_y[span]);
                let (norm, relu) = (&self.top_norm, Activation::Relu);
                norm_forward(
                    exec,
                    self.top,
                    norm,
                    &self.params,
                    &mut self.stats,
                    relu,
                    z,
                    y,
                    statistics,
                    update,
                    &mut b.work,
                );
            }
            let passes = [(0..n, true), (n..2 * n, false)];
            stack_forward(
                exec,
                &self.gen,
                &self.params,
                &mut self.stats,
                &b.top_y,
                &mut b.gen,
                &passes,
                &mut b.work,
            );
        }

        // The discriminator: real frames against reconstructions and prior samples.
        self.discriminate(exec, false, n);
        self.discriminate(exec, true, 2 * n);
        let b = &mut self.buffers;
        let real = bce(&b.logits_real[..n], true, 1.0, &mut b.dlogits[..n]);
        self.discriminator_backward(exec, false, n, true, false, false);
        let b = &mut self.buffers;
        let fake = bce(&b.logits_fake[..2 * n], false, 1.0, &mut b.dlogits[..2 * n]);
        self.discriminator_backward(exec, true, 2 * n, true, false, false);
        self.check_gradients(exec, "discriminator gradients", self.nets[2].clone())?;
        self.update(2, exec, &s.adam, t, lr);
        let d = self.dis_stats;
        self.saved_stats[d..].copy_from_slice(&self.stats[d..]);

        // The encoder's and generator's losses through the updated discriminator.
        self.discriminate(exec, false, n);
        self.discriminate(exec, true, 2 * n);
        let b = &mut self.buffers;
        let features = self.dis[2].shape.output;
        let (fl, f_len) = (features.len(), n * features.interior_len());
        let (f_real, f_fake) = (&b.dis_real.z[2][..n * fl], &b.dis_fake.z[2][..n * fl]);
        // Interior values only: the borders are zero in both.
        let (mut sum, mut sq, mut err) = (0.0f64, 0.0f64, 0.0f64);
        for (&r, &f) in f_real.iter().zip(f_fake) {
            sum += r as f64;
            err += ((f - r) as f64) * ((f - r) as f64);
        }
        let mean = sum / f_len as f64;
        for item in f_real.chunks_exact(fl) {
            for y in 0..features.height {
                for &r in &item[features.index(y, 0)..][..features.width * features.channels] {
                    sq += (r as f64 - mean) * (r as f64 - mean);
                }
            }
        }
        let spread = (sq / (f_len as f64 - 1.0)).max(1e-6);
        let feature = err / f_len as f64 / spread;
        let dfeature_scale = s.feature as f64 * 2.0 / (f_len as f64 * spread);
        b.dfeature.fill(0.0);
        for ((d, &r), &f) in b.dfeature.iter_mut().zip(f_real).zip(f_fake) {
            *d = (dfeature_scale * (f - r) as f64) as f32;
        }
        // Pixel L1 and its gradient (sign(0) = 0, as PyTorch's).
        let (il, pixels) = (image.len(), n * image.interior_len());
        let (xr, x) = (&b.gen.y[3][..n * il], &b.real[..n * il]);
        let pixel = xr.iter().zip(x).map(|(&r, &x)| (r - x).abs() as f64).sum::<f64>() / pixels as f64;
        let pixel_grad = |r: f32, x: f32| -> f32 {
            let d = r - x;
            let sign = if d > 0.0 {
                1.0
            } else if d < 0.0 {
                -1.0
            } else {
                0.0
            };
            (s.pixel as f64 * sign / pixels as f64) as f32
        };
        // KL prior.
        let codes = (n * z) as f64;
        let mut kl = 0.0;
        for item in b.heads[..n * 2 * z].chunks_exact(2 * z) {
            let (mu, ls) = item.split_at(z);
            for (&m, &l) in mu.iter().zip(ls) {
                let (m, l) = (m as f64, l as f64);
                kl += m * m + math::exp64(2.0 * l) - 1.0 - 2.0 * l;
            }
        }
        let kl = 0.5 * kl / codes;
        let gan = bce(&b.logits_fake[..2 * n], true, s.gan as f64, &mut b.dlogits[..2 * n]);

        // The encoder's loss: the feature error back through the discriminator (from its third
        // convolution down), plus the pixel error, back through the reconstructions' pass of
        // the generator to the codes, the reparametrisation and the KL prior.
        let fake_len = 2 * n * fl;
        b.dis_grads.g[2][..fake_len].copy_from_slice(&b.dfeature[..fake_len]);
        let passes = [0..2 * n];
        stack_backward(
            exec,
            &self.dis,
            &self.params,
            None,
            &b.gen.y[3],
            &b.dis_fake,
            &mut b.dis_grads,
            &passes,
            Start::BeforeNorm(2),
            None,
            Some(&mut b.dx),
            &mut b.work,
        );
        for ((d, &r), &x) in b.dx[..n * il].iter_mut().zip(xr).zip(x) {
            *d += pixel_grad(r, x);
        }
        self.generator_backward(exec, &[0..n], false);
        let b = &mut self.buffers;
        for i in 0..n {
            let (mu, ls) = b.heads[i * 2 * z..][..2 * z].split_at(z);
            let (dmu, dls) = b.dheads[i * 2 * z..][..2 * z].split_at_mut(z);
            for j in 0..z {
                let (m, l, dc, e) = (
                    mu[j] as f64,
                    ls[j] as f64,
                    b.dcodes[i * z + j] as f64,
                    b.eps[i * z + j] as f64,
                );
                let sigma = math::exp64(l);
                dmu[j] = (dc + s.kl as f64 * m / codes) as f32;
                let dl = dc * e * sigma + s.kl as f64 * (math::exp64(2.0 * l) - 1.0) / codes;
                dls[j] = (dl * (1.0 - l * l)) as f32;
            }
        }
        let flat = self.heads.cols;
        let dheads = &b.dheads[..n * 2 * z];
        self.heads
            .weight_grad(exec, dheads, &b.enc_flat[..n * flat], &mut self.grads);
        self.heads
            .data_grad(exec, &self.params, dheads, &mut b.dflat[..n * flat]);
        scatter(self.enc[3].shape.output, &b.dflat, n, &mut b.enc_grads.g[3]);
        let passes = [0..n];
        stack_backward(
            exec,
            &self.enc,
            &self.params,
            Some(&mut self.grads),
            &b.real,
            &b.enc,
            &mut b.enc_grads,
            &passes,
            Start::Output(3),
            None,
            None,
            &mut b.work,
        );

        // The generator's loss: the GAN term and the feature error back through the
        // discriminator to both fakes, plus the pixel error, back through both passes.
        self.discriminator_backward(exec, true, 2 * n, false, true, true);
        let b = &mut self.buffers;
        let (xr, x) = (&b.gen.y[3][..n * il], &b.real[..n * il]);
        for ((d, &r), &x) in b.dx[..n * il].iter_mut().zip(xr).zip(x) {
            *d += pixel_grad(r, x);
        }
        self.generator_backward(exec, &[0..n, n..2 * n], true);

        self.check_gradients(exec, "encoder and generator gradients", 0..self.nets[1].end)?;
        self.update(0, exec, &s.adam, t, lr);
        self.update(1, exec, &s.adam, t, lr);
        let recon = s.feature as f64 * feature + s.pixel as f64 * pixel;
        Ok(VaeGanLosses {
            discriminator: (real + fake) as f32,
            encoder: (s.kl as f64 * kl + recon) as f32,
            generator: (recon + s.gan as f64 * gan) as f32,
            gan: gan as f32,
            feature: feature as f32,
            pixel_l1: pixel as f32,
            kl: kl as f32,
        })
    }
}
